"""Multi-turn agent rollouts, token in and token out.

A trajectory is one token sequence: the prompt, then the model's turns with the environment's
observations (tool outputs) between them. The engine generates a turn until one of the
environment's stop strings (the end of a tool call), the environment acts on the turn's text in a
thread (a tool may take a while), and its observation is tokenised once and appended; the model
continues from the exact ids it sampled, which are never decoded and re-tokenised, so the trainer
scores the tokens the rollout sampled. ``GenerationResult.response_mask`` marks the model's ids
(trained) against the observation ids (never trained: no loss, KL or entropy on them).

The token that completes a stop string may carry more text (SmolLM2 writes ``</calculator><`` as
``... ator ><``): the loop drops from the observation's start what the turn already wrote past the
stop string, so the ids read as the observation's text once (``<result>`` after ``><``: one ``<``).
An observation over ``max_observation_tokens`` is cut in the tool's own text; the wrapper around it
(``AgentStep.parts``: a result's closing tag, a chat template's end of turn) is kept whole.

A trajectory ends when a turn ends without calling the environment (EOS, one of the task's own
stop strings, or a turn the environment answers with ``done``), or when a budget runs out: turns,
response tokens (model and observation ids together), the tokens of one turn, the engine's context
(``InferenceEngine.context_length``: each turn's room is bounded by what is left of it) or an
environment step's time (``step_timeout_s``). An environment with ``step_answer_turns`` is handed
those answer turns too while the budget allows another turn (a coding environment runs the code of
an answer as well, so ending a turn with EOS is no way around the feedback); it ends the trajectory
with ``done`` or answers with feedback, and an answer whose feedback has no room left still ends as
an answer.

Scheduling (``AgentBudget.schedule``):

* ``async``: while the environment works on some trajectories, the engine generates the next turn
  of every other trajectory that is ready; nothing waits for the slowest tool of a turn (steps that
  finish within ``batch_window_s`` of each other share a generate call). Which
  trajectories share a generate call depends on the tools' timing, so sampled runs are not
  bit-reproducible (greedy ones are).
* ``lockstep``: every active trajectory generates its turn in one call, then every environment
  step runs (concurrently), then the next turn: reproducible with a seed, slower with slow tools.
"""

from __future__ import annotations

import concurrent.futures as futures
import queue
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any, Literal

from infinirl.config import ConfigError, bounded
from infinirl.engines.base import GenerationResult, InferenceEngine, SamplingParams
from infinirl.engines.seeds import turn_seed
from infinirl.registry import Registry

__all__ = ["AGENT_ENVS", "AgentBudget", "AgentConfig", "AgentEnv", "AgentRollout", "AgentStep", "agent_metrics",
           "drop_start", "overlap", "request_context", "template_parts"]

Schedule = Literal["async", "lockstep"]


@dataclass(kw_only=True, frozen=True)
class AgentStep:
    """What the environment answers to one model turn."""

    observation: str = ""
    """Text appended (as environment tokens) before the model's next turn; ignored when ``done``.
    Over ``AgentBudget.max_observation_tokens`` its end is cut, unless ``parts`` says what may be."""
    parts: tuple[tuple[str, bool], ...] = ()
    """The observation as ``(text, cuttable)`` pieces in order (``observation`` is their join; given
    alone, it is filled in). Over the budget only the cuttable pieces (a tool's output) are cut,
    each ending with the marker; the others (a result's tags, a chat template's turn markers) are
    kept whole, so the model's next turn still starts where the template says."""
    done: bool = False
    """The trajectory ends with this turn (e.g. the turn held no tool call: it is the answer)."""
    error: bool = False
    """The turn's action failed (a malformed call, a tool that raised or timed out); the
    observation says so to the model, the trajectory goes on, and the failure is counted."""
    info: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not self.parts:
            return
        parts = tuple((str(text), bool(cuttable)) for text, cuttable in self.parts)
        joined = "".join(text for text, _ in parts)
        if self.observation and self.observation != joined:
            raise ValueError("AgentStep: parts must join to observation (or give parts alone)")
        object.__setattr__(self, "parts", parts)
        object.__setattr__(self, "observation", joined)


def template_parts(template: str, placeholder: str,
                   inner: Sequence[tuple[str, bool]]) -> tuple[tuple[str, bool], ...]:
    """``template`` with ``inner`` at each ``placeholder``, as :attr:`AgentStep.parts`: the
    template's own text is never cut."""
    pieces = template.split(placeholder)
    parts: list[tuple[str, bool]] = [(pieces[0], False)]
    for piece in pieces[1:]:
        parts += [*inner, (piece, False)]
    return tuple((text, cuttable) for text, cuttable in parts if text)


def drop_start(parts: Sequence[tuple[str, bool]], count: int) -> tuple[tuple[str, bool], ...]:
    """``parts`` without the first ``count`` characters of their join."""
    kept = []
    for text, cuttable in parts:
        cut = min(count, len(text))
        count -= cut
        if text[cut:]:
            kept.append((text[cut:], cuttable))
    return tuple(kept)


def overlap(text: str, following: str) -> int:
    """Length of the longest end of ``text`` that ``following`` starts with (what not to repeat)."""
    for length in range(min(len(text), len(following)), 0, -1):
        if text.endswith(following[:length]):
            return length
    return 0


class AgentEnv(ABC):
    """One trajectory's environment. ``step`` runs in a worker thread and may block (a tool call);
    it must not raise for bad model output: it answers with an observation saying what was wrong
    (``AgentStep(error=True)``). An exception is caught, shown to the model and counted as well."""

    stop_strings: tuple[str, ...] = ()
    """Strings that end a model turn and hand it to the environment (e.g. a closing tool tag). The
    token completing one may carry more text; the loop drops from the observation's start what the
    turn wrote past the stop string (:func:`overlap`), so the observation need not care."""
    step_answer_turns: bool = False
    """Also hand the environment turns that end without one of ``stop_strings`` (EOS, a task's stop
    string) while the budget allows another turn; otherwise such a turn is the answer. The text
    then ends with what ended the turn (e.g. ``<|im_end|>``): an observation should not repeat it."""

    def reset(self, problem: Any) -> None:  # noqa: B027 (optional hook)
        """Called once before the first turn with the trajectory's problem."""

    @abstractmethod
    def step(self, turn: str) -> AgentStep:
        """React to the text of the model's last turn (it ends with one of ``stop_strings``)."""

    def close(self) -> None:  # noqa: B027 (optional hook)
        """Release what the trajectory held (a sandbox, a connection). May be called while a step
        the loop abandoned (``step_timeout_s``) still runs in its thread."""

    def prompt_problem(self, instructions: str) -> str | None:
        """What the task's instructions (system prompt and worked examples, joined) fail to tell the
        model that this environment needs (e.g. a tool it was never shown), or None. Checked with
        the run's config, before any worker starts."""
        return None


AGENT_ENVS: Registry[Callable[..., AgentEnv]] = Registry("agent environment", entry_point_group="infinirl.agent_envs")


@dataclass(kw_only=True, frozen=True)
class AgentBudget:
    """Limits of one trajectory, and how trajectories share the engine."""

    max_turns: int = 4
    """Model turns; after the last one the trajectory ends even if it called a tool."""
    max_response_tokens: int = 512
    """Response ids of the whole trajectory, model and observation ids together."""
    max_observation_tokens: int = 256
    """An observation longer than this is cut (its end replaced by ``truncated_marker``), only in its
    cuttable parts (``AgentStep.parts``): the wrapper pieces are kept whole, even past this."""
    truncated_marker: str = " ...[truncated]"
    concurrency: int = 8
    """Environment steps running at once (threads)."""
    step_timeout_s: float | None = None
    """An environment step still running after this long is abandoned (its thread runs on, unheard)
    and ends its trajectory with finish reason ``length``; None: wait however long a step takes."""
    schedule: Schedule = "async"
    batch_window_s: float = 0.02
    """``async``: once a step finishes, keep waiting while others finish less than this apart, so
    steps that finish together (tools of similar latency) share one generate call."""

    def __post_init__(self) -> None:
        for name in ("max_turns", "max_response_tokens", "max_observation_tokens", "concurrency"):
            if getattr(self, name) < 1:
                raise ValueError(f"AgentBudget.{name}={getattr(self, name)}: must be >= 1")
        if self.batch_window_s < 0:
            raise ValueError(f"AgentBudget.batch_window_s={self.batch_window_s}: must be >= 0")
        if self.step_timeout_s is not None and self.step_timeout_s <= 0:
            raise ValueError(f"AgentBudget.step_timeout_s={self.step_timeout_s}: must be > 0, or None for no limit")
        if self.schedule not in ("async", "lockstep"):
            raise ValueError(f"AgentBudget.schedule={self.schedule!r}: use 'async' or 'lockstep'")


@dataclass
class _Trajectory:
    """A trajectory being rolled out."""

    prompt_index: int
    sample_index: int
    prompt_ids: list[int]
    env: AgentEnv
    ids: list[int] = field(default_factory=list)
    logprobs: list[float] = field(default_factory=list)
    mask: list[int] = field(default_factory=list)
    versions: list[int] = field(default_factory=list)
    turns: int = 0
    env_steps: int = 0
    env_errors: int = 0
    env_seconds: float = 0.0
    env_totals: dict[str, float] = field(default_factory=dict)  # sums of the numbers in the steps' info
    finish_reason: str = "stop"
    done: bool = False
    after_stop: str | None = None  # what the last turn wrote past its stop string; None: it ended without one

    def context(self) -> list[int]:
        return self.prompt_ids + self.ids

    def add_turn(self, turn: GenerationResult) -> None:
        self.ids += turn.response_ids
        self.logprobs += turn.response_logprobs
        self.mask += [1] * len(turn.response_ids)
        self.versions += turn.response_versions or [turn.weight_version] * len(turn.response_ids)
        self.turns += 1

    def add_observation(self, ids: list[int]) -> None:
        self.ids += ids
        self.logprobs += [0.0] * len(ids)
        self.mask += [0] * len(ids)
        self.versions += [self.versions[-1] if self.versions else 0] * len(ids)

    def result(self) -> GenerationResult:
        versions = self.versions or [0]
        return GenerationResult(
            prompt_ids=self.prompt_ids, response_ids=self.ids, response_logprobs=self.logprobs,
            finish_reason="length" if self.finish_reason == "length" else "stop", weight_version=versions[0],
            prompt_index=self.prompt_index, sample_index=self.sample_index,
            extra={"agent": {"turns": self.turns, "env_steps": self.env_steps, "env_errors": self.env_errors,
                             "env_s": self.env_seconds, "end": self.finish_reason,
                             "observation_tokens": len(self.mask) - sum(self.mask), "totals": self.env_totals}},
            response_versions=None if len(set(versions)) == 1 else list(self.versions),
            response_mask=list(self.mask))


class AgentRollout:
    """Rolls out multi-turn trajectories on an engine (see the module docstring).

    ``tokenizer`` decodes the model's turns for the environment and encodes its observations;
    ``make_env()`` builds one environment per trajectory."""

    def __init__(self, engine: InferenceEngine, tokenizer, make_env: Callable[[], AgentEnv], budget: AgentBudget):
        self.engine, self.tokenizer, self.make_env, self.budget = engine, tokenizer, make_env, budget
        # duck-typed engines (without the base class) set no limit
        self.context_length: int | None = getattr(engine, "context_length", None)

    def generate(self, prompt_ids: Sequence[list[int]], sampling: SamplingParams,
                 problems: Sequence[Any] | None = None) -> list[GenerationResult]:
        """``len(prompt_ids) * sampling.n`` trajectories, prompt-major like ``engine.generate``;
        ``problems[i]`` (if given) is passed to the environments of prompt i."""
        trajectories = [self._start(p, s, prompt_ids[p], None if problems is None else problems[p])
                        for p in range(len(prompt_ids)) for s in range(sampling.n)]
        env_stops = tuple(dict.fromkeys(s for t in trajectories[:1] for s in t.env.stop_strings))
        turn_sampling = replace(sampling, n=1, stop_strings=tuple(dict.fromkeys(sampling.stop_strings + env_stops)))
        steps = _StepThreads(self.budget.concurrency)
        try:
            run = self._run_async if self.budget.schedule == "async" else self._run_lockstep
            run(trajectories, turn_sampling, env_stops, steps)
        finally:
            steps.close()
            for trajectory in trajectories:
                trajectory.env.close()
        return [t.result() for t in trajectories]

    # ------------------------------------------------------------------ schedules
    def _run_lockstep(self, trajectories, sampling, env_stops, steps: _StepThreads) -> None:
        active = [t for t in trajectories if not t.done]
        call = 0
        while active:
            calling, calls = self._generate_turn(active, sampling, env_stops, call)
            call += calls
            pending = {steps.submit(self._env_step, t): t for t in calling}
            settled: dict[int, Any] = {}
            while pending:
                self._wait(list(pending), steps)
                for future in self._settled(pending, steps):
                    settled[id(pending.pop(future))] = future
            for trajectory in calling:  # in turn order, whatever order the steps finished in
                self._settle(trajectory, settled[id(trajectory)], steps)
            active = [t for t in active if not t.done]

    def _run_async(self, trajectories, sampling, env_stops, steps: _StepThreads) -> None:
        ready = [t for t in trajectories if not t.done]
        pending: dict[futures.Future, _Trajectory] = {}
        call = 0
        while ready or pending:
            if ready:
                calling, calls = self._generate_turn(ready, sampling, env_stops, call)
                for trajectory in calling:
                    pending[steps.submit(self._env_step, trajectory)] = trajectory
                call += calls
                ready = []
            if pending:
                self._wait_for_burst(list(pending), steps)
            for future in self._settled(pending, steps):
                trajectory = pending.pop(future)
                self._settle(trajectory, future, steps)
                if not trajectory.done:
                    ready.append(trajectory)
            ready.sort(key=lambda t: (t.prompt_index, t.sample_index))

    def _wait_for_burst(self, pending: list[futures.Future], steps: _StepThreads) -> None:
        """Until a step finishes, then while others keep finishing less than ``batch_window_s``
        apart: steps that end together share the next generate call. A step past its time limit
        ends the wait too."""
        done, waiting = self._wait(pending, steps)
        if not done:
            return
        while waiting:
            done, waiting = futures.wait(waiting, timeout=self.budget.batch_window_s,
                                         return_when=futures.FIRST_COMPLETED)
            if not done:
                return

    def _wait(self, pending: list[futures.Future], steps: _StepThreads):
        """Until a step finishes or the first running one reaches its time limit."""
        return futures.wait(pending, timeout=steps.time_to_limit(pending, self.budget.step_timeout_s),
                            return_when=futures.FIRST_COMPLETED)

    def _settled(self, pending: dict[futures.Future, _Trajectory], steps: _StepThreads) -> list[futures.Future]:
        """The steps that finished or ran past their time limit."""
        return [f for f in pending if f.done() or steps.overdue(f, self.budget.step_timeout_s)]

    def _settle(self, trajectory: _Trajectory, future: futures.Future, steps: _StepThreads) -> None:
        if future.done() or not steps.abandon(future):
            step, seconds = future.result()
            trajectory.env_seconds += seconds
            self._observe(trajectory, step)
            return
        # The step runs on in its thread, unheard; the environment may be mid-step, so the
        # trajectory cannot go on. A time budget ran out: finish reason "length".
        trajectory.env_errors += 1
        trajectory.env_seconds += self.budget.step_timeout_s
        trajectory.env_totals["step_timeouts"] = trajectory.env_totals.get("step_timeouts", 0.0) + 1.0
        self._finish(trajectory, "length")

    # ------------------------------------------------------------------ one turn
    def _start(self, prompt_index: int, sample_index: int, prompt_ids: list[int], problem) -> _Trajectory:
        env = self.make_env()
        trajectory = _Trajectory(prompt_index=prompt_index, sample_index=sample_index, prompt_ids=list(prompt_ids),
                                 env=env)
        env.reset(problem)
        return trajectory

    def _context_room(self, trajectory: _Trajectory) -> int | None:
        """Tokens left in the engine's context after the trajectory so far (None: no limit)."""
        return None if self.context_length is None else self.context_length - len(trajectory.prompt_ids) - len(
            trajectory.ids)

    def _generate_turn(self, trajectories: list[_Trajectory], sampling: SamplingParams, env_stops: tuple[str, ...],
                       call: int) -> tuple[list[_Trajectory], int]:
        """One model turn for each of ``trajectories``; returns those whose turn calls the env, and
        how many generate calls it made.

        One call serves them all, unless some have less of the engine's context left than the call's
        ``max_new_tokens`` (the engine refuses a prompt that could outgrow it): those are generated
        in calls of their own, as long as their room, and the trajectories with none left end.
        ``sampling.seed`` is the chunk's (or the generation's) seed: the seed of call number ``call``
        (then ``call + 1``, ...) mixes it with that number (:func:`~infinirl.engines.seeds.turn_seed`), so no
        call of this chunk or another shares it."""
        rooms = [self.budget.max_response_tokens - len(t.ids) for t in trajectories]
        widest = max(1, min(sampling.max_new_tokens, max(rooms)))
        by_size: dict[int, list[int]] = {}
        for index, trajectory in enumerate(trajectories):
            context_room = self._context_room(trajectory)
            if context_room is not None and context_room < 1:
                self._finish(trajectory, "length")
                continue
            size = widest if context_room is None else min(widest, context_room)
            by_size.setdefault(size, []).append(index)
        turns: dict[int, GenerationResult] = {}
        for number, size in enumerate(sorted(by_size, reverse=True)):
            indices = by_size[size]
            turn_sampling = replace(sampling, max_new_tokens=size,
                                    seed=None if sampling.seed is None else turn_seed(sampling.seed, call + number))
            results = self.engine.generate([trajectories[i].context() for i in indices], turn_sampling)
            turns.update(zip(indices, results))
        calling = []
        for index in sorted(turns):
            trajectory, turn, room = trajectories[index], turns[index], rooms[index]
            if len(turn.response_ids) > room:  # the batch's call allowed more than this trajectory has left
                turn = _cut(turn, room)
            trajectory.add_turn(turn)
            text = self.tokenizer.decode(turn.response_ids, skip_special_tokens=False)
            ends = [text.rfind(stop) + len(stop) for stop in env_stops if stop in text]
            trajectory.after_stop = text[max(ends):] if ends else None
            context_room = self._context_room(trajectory)
            out_of_budget = (trajectory.turns >= self.budget.max_turns
                             or len(trajectory.ids) >= self.budget.max_response_tokens
                             or (context_room is not None and context_room < 1))
            if turn.finish_reason == "length":
                self._finish(trajectory, "length")
            elif not ends:
                if trajectory.env.step_answer_turns and not out_of_budget:
                    trajectory.env_steps += 1
                    calling.append(trajectory)
                else:
                    self._finish(trajectory, "answer")
            elif out_of_budget:
                self._finish(trajectory, "length")
            else:
                trajectory.env_steps += 1
                calling.append(trajectory)
        return calling, len(by_size)

    def _env_step(self, trajectory: _Trajectory) -> tuple[AgentStep, float]:
        """The environment's answer to the trajectory's last turn and the seconds it took (runs in
        a step thread)."""
        turn_ids = trajectory.ids[len(trajectory.ids) - _last_run(trajectory.mask):]
        text = self.tokenizer.decode(turn_ids, skip_special_tokens=False)
        start = time.perf_counter()
        try:
            step = trajectory.env.step(text)
        except Exception as exc:  # a broken tool must not end the run: the model sees the error
            step = AgentStep(observation=f"error: {type(exc).__name__}: {exc}", error=True)
        return step, time.perf_counter() - start

    def _observe(self, trajectory: _Trajectory, step: AgentStep) -> None:
        trajectory.env_errors += step.error
        for key, value in step.info.items():
            if isinstance(value, (int, float)) and not isinstance(value, bool):
                trajectory.env_totals[key] = trajectory.env_totals.get(key, 0.0) + float(value)
        if step.done:
            self._finish(trajectory, "answer")
            return
        parts = step.parts or ((step.observation, True),)
        if trajectory.after_stop:  # the token ending the call wrote the observation's first characters
            parts = drop_start(parts, overlap(trajectory.after_stop, step.observation))
        ids = self._observation_ids(parts)
        room = self.budget.max_response_tokens - len(trajectory.ids)
        context_room = self._context_room(trajectory)
        if context_room is not None:
            room = min(room, context_room)
        if len(ids) >= room:  # no room left for the model to read it and answer
            # An answer turn (run_answers-like environments) stays an answer: it ended by itself,
            # only its feedback did not fit.
            self._finish(trajectory, "length" if trajectory.after_stop is not None else "answer")
            return
        trajectory.add_observation(ids)

    def _observation_ids(self, parts: Sequence[tuple[str, bool]]) -> list[int]:
        """The observation's ids, at most ``max_observation_tokens`` of the cuttable pieces' (the
        wrapper pieces are kept whole, even past it)."""
        def encode(text: str) -> list[int]:
            return self.tokenizer.encode(text, add_special_tokens=False)

        limit = self.budget.max_observation_tokens
        ids = encode("".join(text for text, _ in parts))
        if len(ids) <= limit:
            return ids
        # Tokenised piece by piece to know where each ends (only here: a fitting observation is
        # tokenised whole, as the same text in a prompt would be).
        pieces = [(encode(text), cuttable) for text, cuttable in parts]
        marker = encode(self.budget.truncated_marker)
        shares = iter(_shares([len(p) for p, cuttable in pieces if cuttable],
                              limit - sum(len(p) for p, cuttable in pieces if not cuttable)))
        ids = []
        for piece, cuttable in pieces:
            keep = next(shares) if cuttable else len(piece)
            if keep >= len(piece):
                ids += piece
            elif keep > len(marker):
                ids += piece[:keep - len(marker)] + marker
            else:
                ids += piece[:keep]
        return ids

    @staticmethod
    def _finish(trajectory: _Trajectory, reason: str) -> None:
        trajectory.done, trajectory.finish_reason = True, reason


def _shares(lengths: list[int], room: int) -> list[int]:
    """Tokens each cuttable piece keeps of ``room``: an even split, a piece shorter than its share
    keeping all of itself and leaving the rest to the longer ones."""
    shares, room, left = [0] * len(lengths), max(room, 0), len(lengths)
    for index in sorted(range(len(lengths)), key=lengths.__getitem__):
        shares[index] = min(lengths[index], room // left)
        room, left = room - shares[index], left - 1
    return shares


class _StepThreads:
    """Daemon threads running environment steps, ``size`` at a time.

    A thread cannot be stopped: a step past ``step_timeout_s`` is abandoned, its thread runs on
    until the step returns and then ends, and a fresh thread takes its place, so a hanging step
    neither shrinks the pool nor (the threads being daemons) keeps the process from exiting."""

    def __init__(self, size: int):
        self._tasks: queue.SimpleQueue = queue.SimpleQueue()
        self._lock = threading.Lock()
        self._started: dict[futures.Future, float] = {}  # running steps -> when they started
        self._abandoned: set[futures.Future] = set()
        self._threads = 0
        for _ in range(size):
            self._add_thread()

    def _add_thread(self) -> None:
        with self._lock:
            self._threads += 1
        threading.Thread(target=self._work, name="agent-env", daemon=True).start()

    def _work(self) -> None:
        while True:
            task = self._tasks.get()
            if task is None:
                return
            future, fn, argument = task
            if not future.set_running_or_notify_cancel():
                continue
            with self._lock:
                self._started[future] = time.monotonic()
            try:
                result = fn(argument)
            except BaseException as exc:  # noqa: BLE001 - handed to whoever reads the future
                future.set_exception(exc)
            else:
                future.set_result(result)
            with self._lock:
                self._started.pop(future, None)
                if future in self._abandoned:  # its replacement already works on
                    self._abandoned.discard(future)
                    self._threads -= 1
                    return

    def submit(self, fn: Callable[[Any], Any], argument: Any) -> futures.Future:
        future: futures.Future = futures.Future()
        self._tasks.put((future, fn, argument))
        return future

    def overdue(self, future: futures.Future, limit: float | None) -> bool:
        with self._lock:
            started = self._started.get(future)
        return limit is not None and started is not None and time.monotonic() - started >= limit

    def time_to_limit(self, pending: Sequence[futures.Future], limit: float | None) -> float | None:
        """Seconds until the first of ``pending`` reaches ``limit`` (one that has not started yet
        may start now)."""
        if limit is None:
            return None
        now = time.monotonic()
        with self._lock:
            started = [self._started.get(future, now) for future in pending]
        return max(0.0, min(start + limit - now for start in started))

    def abandon(self, future: futures.Future) -> bool:
        """Give up on a running step; False if it finished after all (read its result)."""
        with self._lock:
            if future.done():
                return False
            self._abandoned.add(future)
        self._add_thread()
        return True

    def close(self) -> None:
        with self._lock:
            threads = self._threads
        for _ in range(threads):
            self._tasks.put(None)


def _cut(turn: GenerationResult, length: int) -> GenerationResult:
    """``turn`` cut to its first ``length`` ids, as if it had hit its token budget."""
    versions = None if turn.response_versions is None else turn.response_versions[:length]
    return replace(turn, response_ids=turn.response_ids[:length], response_logprobs=turn.response_logprobs[:length],
                   response_versions=versions, finish_reason="length")


def _last_run(mask: list[int]) -> int:
    """Length of the trailing run of 1s (the model's last turn)."""
    count = 0
    for value in reversed(mask):
        if not value:
            break
        count += 1
    return count


def agent_metrics(results: Sequence[GenerationResult]) -> dict[str, float]:
    """Per-step means over a batch of agent trajectories (empty when the batch has none)."""
    stats = [r.extra["agent"] for r in results if "agent" in r.extra]
    if not stats:
        return {}
    n = len(stats)
    totals = {f"agent/{key}_mean": sum(s["totals"].get(key, 0.0) for s in stats) / n
              for key in sorted({key for s in stats for key in s["totals"]})}
    return {**totals,
        "agent/turns_mean": sum(s["turns"] for s in stats) / n,
        "agent/env_steps_mean": sum(s["env_steps"] for s in stats) / n,
        "agent/env_error_rate": sum(s["env_errors"] for s in stats) / max(sum(s["env_steps"] for s in stats), 1),
        "agent/tool_use_fraction": sum(s["env_steps"] > 0 for s in stats) / n,
        "agent/env_s_total": sum(s["env_s"] for s in stats),
        "agent/observation_tokens_mean": sum(s["observation_tokens"] for s in stats) / n,
        "agent/length_ended_fraction": sum(s["end"] == "length" for s in stats) / n,
    }


@dataclass(kw_only=True)
class AgentConfig:
    """``rollout.agent`` of a reasoning run: roll out multi-turn trajectories with an environment
    (tools) between the model's turns. ``rollout.max_new_tokens`` then bounds each turn."""

    env: str = "tools"
    """Environment by registered name (``AGENT_ENVS``; plugins through the ``infinirl.agent_envs``
    entry point), or ``package.module:Class`` of one of your own."""
    env_options: dict[str, Any] = field(default_factory=dict)
    """Keyword options of the environment's constructor (e.g. ``tools``, ``call_format``)."""
    max_turns: int = bounded(4, ge=1)
    """Model turns; after the last one the trajectory ends even if it called a tool."""
    max_response_tokens: int = bounded(512, ge=1)
    """Response ids of a whole trajectory, model and tool-output ids together."""
    max_observation_tokens: int = bounded(256, ge=1)
    """A tool output longer than this is cut, in the tool's own text: the wrapper around it (result
    tags, a chat template's turn markers) is kept whole."""
    concurrency: int = bounded(8, ge=1)
    """Environment steps (tool calls) running at once on each rollout rank."""
    step_timeout_s: float | None = bounded(None, gt=0)
    """An environment step (all of a turn's tool calls) still running after this many seconds is
    abandoned and its trajectory ends (finish reason length); null: no limit besides the tools' own."""
    schedule: Schedule = "async"
    """async: generate other trajectories' turns while tools run; lockstep: every turn waits for the
    slowest tool (reproducible with a seed)."""
    batch_window_s: float = bounded(0.02, ge=0)
    """async: tool calls finishing within this window of each other share one generate call."""

    def budget(self) -> AgentBudget:
        return AgentBudget(max_turns=self.max_turns, max_response_tokens=self.max_response_tokens,
                           max_observation_tokens=self.max_observation_tokens, concurrency=self.concurrency,
                           step_timeout_s=self.step_timeout_s, schedule=self.schedule,
                           batch_window_s=self.batch_window_s)

    def check(self, key: str, instructions: str | None = None) -> None:
        """Raise ``ConfigError`` naming ``key`` if the environment cannot be built as configured, or
        (given the task's ``instructions``: its system prompt and worked examples, joined) if they
        fail to tell the model what the environment needs (:meth:`AgentEnv.prompt_problem`)."""
        from infinirl.agents.registered import AGENT_ENVS, resolve_agent_env

        try:
            factory = resolve_agent_env(self.env)
        except KeyError:
            raise ConfigError(f"{key}.env={self.env!r} is not registered; registered: "
                              f"{', '.join(AGENT_ENVS.names())}, or give package.module:Class") from None
        except (ImportError, AttributeError, TypeError) as exc:
            raise ConfigError(f"{key}.env: {exc}") from None
        try:
            env = factory(**self.env_options)
        except (TypeError, ValueError, KeyError) as exc:
            raise ConfigError(f"{key}.env_options for env {self.env!r}: {exc}") from None
        try:
            check_prompt = getattr(env, "prompt_problem", None)  # a plain factory's object may lack the hook
            problem = None if instructions is None or check_prompt is None else check_prompt(instructions)
        finally:
            env.close()
        if problem:
            raise ConfigError(f"task.system_prompt (with task.few_shot) for {key}.env={self.env!r}: {problem}")

    def make_env_factory(self) -> Callable[[], AgentEnv]:
        from infinirl.agents.registered import resolve_agent_env

        factory = resolve_agent_env(self.env)
        options = dict(self.env_options)
        return lambda: factory(**options)


def request_context(prompt: tuple[str, int], max_new_tokens: tuple[str, int], agent: AgentConfig | AgentBudget | None,
                    agent_key: str = "rollout.agent") -> tuple[int, str]:
    """The most tokens one generate call can ask an engine to hold (prompt plus requested
    response), and how that sum is made, from ``(key, value)`` pairs for messages.

    One turn: the longest prompt plus ``max_new_tokens``. An agent: a trajectory still running has
    at most ``max_response_tokens - 1`` ids after its prompt, and a call asks each trajectory in it
    for the most room any of them has left, up to ``max_new_tokens``
    (:meth:`AgentRollout._generate_turn`), so a nearly full trajectory may be asked for a whole turn.
    """
    (prompt_key, prompt_tokens), (new_key, new_tokens) = prompt, max_new_tokens
    if agent is None:
        return prompt_tokens + new_tokens, f"{prompt_key}={prompt_tokens} + {new_key}={new_tokens}"
    cap = agent.max_response_tokens
    turn = min(new_tokens, cap)
    return (prompt_tokens + cap - 1 + turn,
            f"{prompt_key}={prompt_tokens} + {agent_key}.max_response_tokens={cap} - 1 (a trajectory so far) + "
            f"min({new_key}={new_tokens}, {cap}) (its next turn)")
