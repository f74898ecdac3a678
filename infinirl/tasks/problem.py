"""`Problem`: the one record every task source produces and every verifier consumes."""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Any, Protocol


@dataclass(frozen=True)
class Problem:
    """One prompt with its ground truth.

    Attributes:
        uid: stable identifier (e.g. ``"gsm8k/test/17"``, ``"chain_sum/train/1234"``); logs and
            per-problem statistics (GRPO groups, pass@k) key on it.
        prompt: the user message text, instruction template already applied. Token ids are made
            from it once, by `prompts.encode_prompt`, and travel as ids from then on.
        answer: ground-truth answer as a string (a number, or LaTeX for MATH).
        verifier: registry name of the verifier (``"math"``, ``"gsm8k"``, ``"reasoning_gym"``) or
            a dotted path ``"package.module:function"`` to a user reward function.
        metadata: whatever the verifier needs beyond ``answer``; for reasoning-gym it holds the
            generator's full entry (its ``score_answer`` wants that dict) and the generator config.
    """

    uid: str
    prompt: str
    answer: str
    verifier: str
    metadata: dict[str, Any] = field(default_factory=dict)


class ProblemSource(Protocol):
    """What a runner draws training prompts from: a dataset iterator or a generator stream.

    Both kinds are infinite and resumable, so the runner's checkpoint stores ``state_dict()`` and
    a resumed run continues with exactly the problems it would have seen.
    """

    def next_batch(self, batch_size: int) -> list[Problem]: ...

    def state_dict(self) -> dict[str, Any]: ...

    def load_state_dict(self, state: dict[str, Any]) -> None: ...


_WHITESPACE = re.compile(r"\s+")


def normalize_question(text: str) -> str:
    """Canonical form used to decide whether two questions are "the same problem".

    Case and runs of whitespace are the only differences a generator or a template introduces
    between equal problems, so that is all we remove; anything more aggressive (dropping
    punctuation, digits' formatting) would merge problems that differ.
    """
    return _WHITESPACE.sub(" ", text).strip().lower()
