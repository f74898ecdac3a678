"""What a coding problem carries in ``Problem.metadata`` (one place for the keys)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

__all__ = ["CodeSpec"]


@dataclass(kw_only=True, frozen=True)
class CodeSpec:
    """A function-writing problem: write ``entry_point`` so that ``tests`` pass.

    ``tests`` and ``visible_tests`` are Python source defining ``check(candidate)`` (HumanEval's
    form): its top-level statements with an ``assert`` are the tests. ``visible_tests`` are the
    examples the prompt shows (what an agent may run while it works); ``tests`` decide the reward.
    """

    entry_point: str
    tests: str
    stub: str = ""
    """Signature and docstring the prompt shows (and anything before them: imports, helpers)."""
    visible_tests: str = ""

    KEYS = ("entry_point", "tests", "stub", "visible_tests")

    def __post_init__(self) -> None:
        if not self.entry_point.isidentifier():
            raise ValueError(f"CodeSpec.entry_point={self.entry_point!r} is not a Python name")
        if "def check(" not in self.tests:
            raise ValueError(f"CodeSpec.tests of {self.entry_point!r} define no check(candidate) function")

    def to_metadata(self) -> dict[str, str]:
        return {key: getattr(self, key) for key in self.KEYS}

    @classmethod
    def from_metadata(cls, metadata: dict[str, Any], uid: str = "?") -> CodeSpec:
        missing = [key for key in ("entry_point", "tests") if key not in metadata]
        if missing:
            raise ValueError(f"problem {uid} is not a coding problem: its metadata lacks {missing}; build it with "
                             "infinirl.tasks.code_tasks (code_problem) or give entry_point and tests")
        return cls(**{key: str(metadata[key]) for key in cls.KEYS if key in metadata})

    @classmethod
    def of(cls, problem: Any) -> CodeSpec | None:
        """The spec of a Problem that has one, else None (an env without a problem, or another task)."""
        metadata = getattr(problem, "metadata", None)
        if not isinstance(metadata, dict) or "entry_point" not in metadata or "tests" not in metadata:
            return None
        return cls.from_metadata(metadata, getattr(problem, "uid", "?"))
