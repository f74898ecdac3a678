"""Procedurally generated reasoning tasks (reasoning-gym) as held-out eval sets and train streams.

Held-out means disjoint: the eval set is built first, from its own seed, and the train stream
skips every generated problem whose normalised question is in it. Seeds alone do not guarantee
this: reasoning-gym derives item ``i`` from ``Random(seed + i)``, so two seeds' streams are
shifted copies of each other, and small problem spaces repeat questions under any seed.

The train stream is infinite and resumable: its whole state is one integer, the generator index
of the next item, because every item is a pure function of ``(name, config, seed, index)``.

Choosing a chain_sum config (distinct questions = sum over term counts t and digit counts d of
``operands(d)**t * 2**(t-1)``, operands(1) = 10, operands(d) = 9*10**(d-1); generation draws t and
d uniformly first, so the smallest (t, d) cell supplies a disproportionate share of draws). The
embedded model's greedy accuracy per config: docs/results.md, "Base accuracy on chain_sum".
"""

from __future__ import annotations

import json
import threading
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any

from infinirl.tasks.problem import Problem, normalize_question
from infinirl.tasks.prompts import RAW_TEMPLATE, render_prompt

# Generator configs are instantiated in chunks of this many items; any index is reachable by
# picking chunk ``index // CHUNK`` (seed shifted by ``chunk * CHUNK``) and item ``index % CHUNK``,
# which matches reasoning-gym's ``seed + index`` derivation and also works for generators that
# precompute or bounds-check a fixed ``size``.
CHUNK = 10_000

# Far from typical train seeds (0, 1, 42, ...) so eval and train generator indices do not
# overlap in practice; disjointness itself is still enforced by question-text exclusion.
DEFAULT_EVAL_SEED = 1_000_000_007


@dataclass(frozen=True)
class ReasoningGymTask:
    """A reasoning-gym generator and the prompt around its questions.

    Attributes:
        name: reasoning-gym dataset name, e.g. ``"chain_sum"``.
        config: generator options except ``seed``/``size`` (e.g. ``{"min_terms": 2, ...}``).
        prompt_template: instruction around each question. Default: the question as generated,
            since reasoning-gym questions carry their own instruction ("State the final answer
            to ..."), and the ``reasoning_gym`` verifier's ``auto`` extractor reads the answer
            whatever format the model picks; for tiny models extra answer-format instructions
            cost prompt tokens and accuracy (docs/results.md, "Prompt format of chain_sum").
        verifier: what its problems name as their verifier (``task.verifier``: the generator's
            own ``score_answer`` by default, or a user reward function).
    """

    name: str
    config: Mapping[str, Any] = field(default_factory=dict)
    prompt_template: str = RAW_TEMPLATE
    verifier: str = "reasoning_gym"

    def __post_init__(self) -> None:
        for reserved in ("seed", "size"):
            if reserved in self.config:
                raise ValueError(
                    f"reasoning-gym task {self.name!r}: do not put {reserved!r} in config; "
                    "seeds and sizes are arguments of build_eval_set / ReasoningGymStream."
                )
        object.__setattr__(self, "config", _plain(self.config))


def _plain(value: Any) -> Any:
    """Config values as plain dicts/lists, so OmegaConf containers survive the JSON cache key."""
    if isinstance(value, Mapping):
        return {str(key): _plain(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)) or type(value).__name__ == "ListConfig":
        return [_plain(item) for item in value]
    return value


def _config_key(config: Mapping[str, Any]) -> str:
    return json.dumps(_plain(config), sort_keys=True)


def make_generator(name: str, config: Mapping[str, Any], seed: int, size: int) -> Any:
    """A reasoning-gym dataset, with errors that name the bad task or option and the fix."""
    import reasoning_gym
    from reasoning_gym.factory import DATASETS

    if name not in DATASETS:
        raise KeyError(
            f"unknown reasoning-gym task {name!r}; some available: {sorted(DATASETS)[:40]}... "
            f"({len(DATASETS)} in all; see reasoning_gym.factory.DATASETS)"
        )
    try:
        return reasoning_gym.create_dataset(name, **dict(config), seed=seed, size=size)
    except TypeError as error:
        raise TypeError(
            f"bad config for reasoning-gym task {name!r}: {dict(config)} ({error})"
        ) from None
    except AssertionError as error:
        raise ValueError(
            f"invalid config for reasoning-gym task {name!r}: {dict(config)} ({error})"
        ) from None


@lru_cache(maxsize=64)
def _cached_generator(name: str, config_key: str, seed: int) -> Any:
    return make_generator(name, json.loads(config_key), seed=seed, size=CHUNK)


def generate_entry(task: ReasoningGymTask, seed: int, index: int) -> dict[str, Any]:
    """Item ``index`` of the endless sequence defined by ``(task, seed)``."""
    chunk, within = divmod(index, CHUNK)
    return _cached_generator(task.name, _config_key(task.config), seed + chunk * CHUNK)[within]


def entry_to_problem(task: ReasoningGymTask, entry: dict[str, Any], uid: str) -> Problem:
    return Problem(
        uid=uid,
        prompt=render_prompt(entry["question"], task.prompt_template),
        answer=str(entry["answer"]),
        verifier=task.verifier,
        metadata={"task": task.name, "config": dict(task.config), "entry": entry},
    )


def build_eval_set(
    task: ReasoningGymTask, size: int, seed: int = DEFAULT_EVAL_SEED, max_draws_per_item: int = 50
) -> list[Problem]:
    """``size`` problems with pairwise-distinct questions, drawn from the eval seed's sequence.

    Duplicates are skipped so a small problem space does not silently weight some questions
    twice; if the space is too small to supply ``size`` distinct questions, this says so.
    """
    problems: list[Problem] = []
    seen: set[str] = set()
    for index in range(size * max_draws_per_item):
        if len(problems) == size:
            break
        entry = generate_entry(task, seed, index)
        key = normalize_question(entry["question"])
        if key not in seen:
            seen.add(key)
            problems.append(entry_to_problem(task, entry, f"{task.name}/eval/{index}"))
    if len(problems) < size:
        raise ValueError(
            f"task {task.name!r} with config {task.config} yielded only {len(problems)} distinct "
            f"questions in {size * max_draws_per_item} draws, fewer than eval size {size}; "
            "widen the config or shrink the eval set."
        )
    return problems


class ReasoningGymStream:
    """Endless, seeded, resumable train problems that never repeat a held-out question.

    Implements `ProblemSource`. ``exclude`` takes the eval problems (or their question texts);
    matching is on `normalize_question` of the raw generator question, so the prompt template
    cannot hide an overlap.
    """

    def __init__(
        self,
        task: ReasoningGymTask,
        seed: int = 0,
        exclude: Iterable[Problem | str] = (),
        max_consecutive_skips: int = 10_000,
    ):
        self.task = task
        self.seed = seed
        self.excluded = frozenset(_question_key(item) for item in exclude)
        self.max_consecutive_skips = max_consecutive_skips
        self.position = 0
        self.skipped = 0  # how many generated problems were dropped for being held out
        self._lock = threading.Lock()

    def __iter__(self) -> ReasoningGymStream:
        return self

    def __next__(self) -> Problem:
        with self._lock:
            for _ in range(self.max_consecutive_skips):
                index = self.position
                entry = generate_entry(self.task, self.seed, index)
                self.position += 1
                if normalize_question(entry["question"]) in self.excluded:
                    self.skipped += 1
                    continue
                return entry_to_problem(self.task, entry, f"{self.task.name}/train/{index}")
        raise RuntimeError(
            f"task {self.task.name!r}: {self.max_consecutive_skips} consecutive generated problems "
            "were all in the held-out set; the problem space is nearly exhausted by the eval set. "
            "Widen the task config or shrink the eval set."
        )

    def next_batch(self, batch_size: int) -> list[Problem]:
        return [next(self) for _ in range(batch_size)]

    def state_dict(self) -> dict[str, Any]:
        return {
            "task": self.task.name,
            "config": _config_key(self.task.config),
            "seed": self.seed,
            "position": self.position,
            "skipped": self.skipped,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        mine = self.state_dict()
        for key in ("task", "config", "seed"):
            if state[key] != mine[key]:
                raise ValueError(
                    f"cannot resume reasoning-gym stream: checkpoint {key}={state[key]!r} but this "
                    f"stream has {key}={mine[key]!r}; resume with the same task, config and seed."
                )
        self.position = int(state["position"])
        self.skipped = int(state["skipped"])


def _question_key(item: Problem | str) -> str:
    if isinstance(item, Problem):
        entry = item.metadata.get("entry")
        question = entry["question"] if entry else item.metadata.get("question", item.prompt)
        return normalize_question(question)
    return normalize_question(item)


def count_distinct_questions(task: ReasoningGymTask, draws: int, seed: int = 0) -> int:
    """Distinct questions among the first ``draws`` generated: a quick probe of the problem space.

    When the count stays well below ``draws``, the space is small enough that a held-out set
    covers a real fraction of it and the train stream repeats questions often.
    """
    questions = (generate_entry(task, seed, index)["question"] for index in range(draws))
    return len({normalize_question(question) for question in questions})


@lru_cache(maxsize=64)
def _scoring_generator(name: str, config_key: str) -> Any:
    return make_generator(name, json.loads(config_key), seed=0, size=1)


def score_entry(
    answer: str | None, entry: dict[str, Any], task: str, config: Mapping[str, Any]
) -> float:
    """The task's own ``score_answer(answer, entry)``, from a cached generator of that config."""
    return float(_scoring_generator(task, _config_key(config)).score_answer(answer, entry))
