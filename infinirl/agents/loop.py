"""Multi-turn agent rollouts, token in and token out.

A trajectory is one token sequence: the prompt, then the model's turns with the environment's
observations (tool outputs) between them. The engine generates a turn until one of the
environment's stop strings (the end of a tool call), the environment acts on the turn's text in a
thread (a tool may take a while), and its observation is tokenised once and appended; the model
continues from the exact ids it sampled, which are never decoded and re-tokenised, so the trainer
scores the tokens the rollout sampled. ``GenerationResult.response_mask`` marks the model's ids
(trained) against the observation ids (never trained: no loss, KL or entropy on them).

A trajectory ends when a turn ends without calling the environment (EOS, one of the task's own
stop strings, or a turn the environment answers with ``done``), or when a budget runs out: turns,
response tokens (model and observation ids together) or the tokens of one turn. An environment
with ``step_answer_turns`` is handed those answer turns too while the budget allows another turn
(a coding environment runs the code of an answer as well, so ending a turn with EOS is no way
around the feedback); it ends the trajectory with ``done`` or answers with feedback.

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
           "request_context"]

Schedule = Literal["async", "lockstep"]


@dataclass(kw_only=True, frozen=True)
class AgentStep:
    """What the environment answers to one model turn."""

    observation: str = ""
    """Text appended (as environment tokens) before the model's next turn; ignored when ``done``."""
    done: bool = False
    """The trajectory ends with this turn (e.g. the turn held no tool call: it is the answer)."""
    error: bool = False
    """The turn's action failed (a malformed call, a tool that raised or timed out); the
    observation says so to the model, the trajectory goes on, and the failure is counted."""
    info: dict[str, Any] = field(default_factory=dict)


class AgentEnv(ABC):
    """One trajectory's environment. ``step`` runs in a worker thread and may block (a tool call);
    it must not raise for bad model output: it answers with an observation saying what was wrong
    (``AgentStep(error=True)``). An exception is caught, shown to the model and counted as well."""

    stop_strings: tuple[str, ...] = ()
    """Strings that end a model turn and hand it to the environment (e.g. a closing tool tag)."""
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
        """Release what the trajectory held (a sandbox, a connection)."""


AGENT_ENVS: Registry[Callable[..., AgentEnv]] = Registry("agent environment", entry_point_group="infinirl.agent_envs")


@dataclass(kw_only=True, frozen=True)
class AgentBudget:
    """Limits of one trajectory, and how trajectories share the engine."""

    max_turns: int = 4
    """Model turns; after the last one the trajectory ends even if it called a tool."""
    max_response_tokens: int = 512
    """Response ids of the whole trajectory, model and observation ids together."""
    max_observation_tokens: int = 256
    """An observation longer than this is cut (its end replaced by ``truncated_marker``)."""
    truncated_marker: str = " ...[truncated]"
    concurrency: int = 8
    """Environment steps running at once (threads)."""
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

    def generate(self, prompt_ids: Sequence[list[int]], sampling: SamplingParams,
                 problems: Sequence[Any] | None = None) -> list[GenerationResult]:
        """``len(prompt_ids) * sampling.n`` trajectories, prompt-major like ``engine.generate``;
        ``problems[i]`` (if given) is passed to the environments of prompt i."""
        trajectories = [self._start(p, s, prompt_ids[p], None if problems is None else problems[p])
                        for p in range(len(prompt_ids)) for s in range(sampling.n)]
        env_stops = tuple(dict.fromkeys(s for t in trajectories[:1] for s in t.env.stop_strings))
        turn_sampling = replace(sampling, n=1, stop_strings=tuple(dict.fromkeys(sampling.stop_strings + env_stops)))
        try:
            with futures.ThreadPoolExecutor(max_workers=self.budget.concurrency,
                                            thread_name_prefix="agent-env") as pool:
                run = self._run_async if self.budget.schedule == "async" else self._run_lockstep
                run(trajectories, turn_sampling, env_stops, pool)
        finally:
            for trajectory in trajectories:
                trajectory.env.close()
        return [t.result() for t in trajectories]

    # ------------------------------------------------------------------ schedules
    def _run_lockstep(self, trajectories, sampling, env_stops, pool) -> None:
        active = [t for t in trajectories if not t.done]
        turn = 0
        while active:
            calling = self._generate_turn(active, sampling, env_stops, turn)
            for trajectory, step in zip(calling, pool.map(self._env_step, calling)):
                self._observe(trajectory, step)
            active = [t for t in active if not t.done]
            turn += 1

    def _run_async(self, trajectories, sampling, env_stops, pool) -> None:
        ready = [t for t in trajectories if not t.done]
        pending: dict[futures.Future, _Trajectory] = {}
        call = 0
        while ready or pending:
            if ready:
                for trajectory in self._generate_turn(ready, sampling, env_stops, call):
                    pending[pool.submit(self._env_step, trajectory)] = trajectory
                call += 1
                ready = []
            if pending:
                self._wait_for_burst(list(pending))
            for future in [f for f in pending if f.done()]:
                trajectory = pending.pop(future)
                self._observe(trajectory, future.result())
                if not trajectory.done:
                    ready.append(trajectory)
            ready.sort(key=lambda t: (t.prompt_index, t.sample_index))

    def _wait_for_burst(self, pending: list[futures.Future]) -> None:
        """Until a step finishes, then while others keep finishing less than ``batch_window_s``
        apart: steps that end together share the next generate call."""
        done, waiting = futures.wait(pending, return_when=futures.FIRST_COMPLETED)
        while waiting:
            done, waiting = futures.wait(waiting, timeout=self.budget.batch_window_s,
                                         return_when=futures.FIRST_COMPLETED)
            if not done:
                return

    # ------------------------------------------------------------------ one turn
    def _start(self, prompt_index: int, sample_index: int, prompt_ids: list[int], problem) -> _Trajectory:
        env = self.make_env()
        trajectory = _Trajectory(prompt_index=prompt_index, sample_index=sample_index, prompt_ids=list(prompt_ids),
                                 env=env)
        env.reset(problem)
        return trajectory

    def _generate_turn(self, trajectories: list[_Trajectory], sampling: SamplingParams, env_stops: tuple[str, ...],
                       call: int) -> list[_Trajectory]:
        """One model turn for each of ``trajectories``; returns those whose turn calls the env.

        ``sampling.seed`` is the chunk's (or the generation's) seed: the call's own seed mixes it with
        ``call`` (:func:`~infinirl.engines.seeds.turn_seed`), so no call of this chunk or another shares it."""
        rooms = [self.budget.max_response_tokens - len(t.ids) for t in trajectories]
        turn_sampling = replace(sampling, max_new_tokens=max(1, min(sampling.max_new_tokens, max(rooms))),
                                seed=None if sampling.seed is None else turn_seed(sampling.seed, call))
        results = self.engine.generate([t.context() for t in trajectories], turn_sampling)
        calling = []
        for trajectory, turn, room in zip(trajectories, results, rooms):
            if len(turn.response_ids) > room:  # the batch's call allowed more than this trajectory has left
                turn = _cut(turn, room)
            trajectory.add_turn(turn)
            text = self.tokenizer.decode(turn.response_ids, skip_special_tokens=False)
            out_of_budget = (trajectory.turns >= self.budget.max_turns
                             or len(trajectory.ids) >= self.budget.max_response_tokens)
            if turn.finish_reason == "length":
                self._finish(trajectory, "length")
            elif not any(stop in text for stop in env_stops):  # the token completing a stop may carry more
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
        return calling

    def _env_step(self, trajectory: _Trajectory) -> AgentStep:
        turn_ids = trajectory.ids[len(trajectory.ids) - _last_run(trajectory.mask):]
        text = self.tokenizer.decode(turn_ids, skip_special_tokens=False)
        start = time.perf_counter()
        try:
            step = trajectory.env.step(text)
        except Exception as exc:  # a broken tool must not end the run: the model sees the error
            step = AgentStep(observation=f"error: {type(exc).__name__}: {exc}", error=True)
        trajectory.env_seconds += time.perf_counter() - start
        return step

    def _observe(self, trajectory: _Trajectory, step: AgentStep) -> None:
        trajectory.env_errors += step.error
        for key, value in step.info.items():
            if isinstance(value, (int, float)) and not isinstance(value, bool):
                trajectory.env_totals[key] = trajectory.env_totals.get(key, 0.0) + float(value)
        if step.done:
            self._finish(trajectory, "answer")
            return
        ids = self.tokenizer.encode(step.observation, add_special_tokens=False)
        if len(ids) > self.budget.max_observation_tokens:
            marker = self.tokenizer.encode(self.budget.truncated_marker, add_special_tokens=False)
            keep = self.budget.max_observation_tokens - len(marker)
            ids = ids[:keep] + marker if keep > 0 else ids[:self.budget.max_observation_tokens]
        if len(trajectory.ids) + len(ids) >= self.budget.max_response_tokens:
            self._finish(trajectory, "length")  # no room left for the model to read it and answer
            return
        trajectory.add_observation(ids)

    @staticmethod
    def _finish(trajectory: _Trajectory, reason: str) -> None:
        trajectory.done, trajectory.finish_reason = True, reason


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
    """A tool output longer than this is cut."""
    concurrency: int = bounded(8, ge=1)
    """Environment steps (tool calls) running at once on each rollout rank."""
    schedule: Schedule = "async"
    """async: generate other trajectories' turns while tools run; lockstep: every turn waits for the
    slowest tool (reproducible with a seed)."""
    batch_window_s: float = bounded(0.02, ge=0)
    """async: tool calls finishing within this window of each other share one generate call."""

    def budget(self) -> AgentBudget:
        return AgentBudget(max_turns=self.max_turns, max_response_tokens=self.max_response_tokens,
                           max_observation_tokens=self.max_observation_tokens, concurrency=self.concurrency,
                           schedule=self.schedule, batch_window_s=self.batch_window_s)

    def check(self, key: str) -> None:
        """Raise ``ConfigError`` naming ``key`` if the environment cannot be built as configured."""
        from infinirl.agents.registered import AGENT_ENVS, resolve_agent_env

        try:
            factory = resolve_agent_env(self.env)
        except KeyError:
            raise ConfigError(f"{key}.env={self.env!r} is not registered; registered: "
                              f"{', '.join(AGENT_ENVS.names())}, or give package.module:Class") from None
        except (ImportError, AttributeError, TypeError) as exc:
            raise ConfigError(f"{key}.env: {exc}") from None
        try:
            factory(**self.env_options).close()
        except (TypeError, ValueError, KeyError) as exc:
            raise ConfigError(f"{key}.env_options for env {self.env!r}: {exc}") from None

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
