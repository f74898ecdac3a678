"""What the scheduler knows about each runner: its phases, units of work, depth knob and probes.

One :class:`RunnerModel` per runner, registered by name (``RUNNER_MODELS``), so supporting a new
runner is one entry here and no edit in the profiler, the cost model or the search:

* ``phases(cfg)`` and ``units(cfg)``: the shape of one iteration (see :mod:`.cost`);
* ``depths(cfg, candidate_ranks)``: the pipeline depths the config can run, and ``apply(cfg, candidate)``
  writes a candidate into a config (placement and the runner's depth key);
* ``check(cfg, candidate)``: the runner's own rules a placement must meet (paired ranks, divisibility);
* ``probes``: the placements the profiler runs, and ``measure(window, probe)``: one iteration's
  own seconds per ``"<phase>/<component>"``, read from the tracer's spans (a streamed phase's
  span holds both sides, so the split uses the timings the components report with their result),
  and, where the runner counts them, the bytes each component sent downstream (``"bytes/<component>"``,
  all its ranks together) and the driver's own seconds (``"overhead"``, when the probe ran less
  work than the config and the step time therefore cannot give it);
* ``shorten(cfg, iterations)``: a profiling or measuring run of the same work, without evaluation
  or checkpoints worth keeping; ``scale_batch(cfg, factor)``: the same run with ``factor`` times the
  work per iteration (what a larger cluster is given);
* ``fixed(cfg)``: components the search leaves where the config puts them (robots), ``paced(cfg)``:
  the wall-clock seconds per unit real time sets (a robot's control period), ``refuses(cfg)``: why
  a config of the runner cannot be planned, if it cannot.

Runners the scheduler does not plan are listed in ``UNPLANNED_RUNNERS`` with the reason and what
to write instead, which ``infinirl plan`` and ``placement=auto`` print.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from infinirl.registry import Registry
from infinirl.scheduler.cost import Allocation, Candidate, Phase

__all__ = ["RUNNER_MODELS", "UNPLANNED_RUNNERS", "Probe", "RunnerModel", "StepWindow", "probe_candidates"]


@dataclass(frozen=True, kw_only=True)
class StepWindow:
    """One iteration as the profiler saw it: per (component, method), each rank's summed span
    seconds; per (component, method), the latest span end; the runner's metrics row."""

    busy: dict[tuple[str, str], list[float]]
    last_end: dict[tuple[str, str], float]
    metrics: dict[str, Any]

    def per_rank(self, component: str, method: str) -> float:
        """Mean over ranks of a method's seconds in this iteration (ranks work side by side)."""
        values = self.busy.get((component, method), [])
        return sum(values) / len(values) if values else 0.0


@dataclass(frozen=True, kw_only=True)
class Probe:
    """A profiling placement: per component, (first device, device count), and the depth."""

    name: str
    devices: dict[str, tuple[int, int]]
    depth: int = 1

    def candidate(self, components: tuple[str, ...] | None = None) -> Candidate:
        """The probe as a candidate, over ``components`` (default: every component it names)."""
        names = components if components is not None else tuple(self.devices)
        return Candidate(allocations={c: Allocation(first=self.devices[c][0], count=self.devices[c][1],
                                                    ranks=self.devices[c][1]) for c in names},
                         depth=self.depth)


@dataclass(frozen=True, kw_only=True)
class RunnerModel:
    runner: str
    step_metric: str
    """The metrics key of one iteration's wall time."""
    window_method: tuple[str, str]
    """(component, method) whose calls on rank 0 start each iteration: the spans' step boundaries."""
    phases: Callable[[Any], tuple[Phase, ...]]
    units: Callable[[Any], dict[str, float]]
    model_key: Callable[[Any], str]
    depths: Callable[[Any, dict[str, int]], tuple[int, ...]]
    no_depth: Callable[[Any, dict[str, int]], str] = lambda cfg, ranks: "no pipeline depth fits these ranks"
    """Why ``depths`` is empty for these ranks (the search counts it among the candidates it left out)."""
    check: Callable[[Any, Candidate], str | None]
    apply: Callable[[Any, Candidate], None]
    shorten: Callable[[Any, int], None]
    scale_batch: Callable[[Any, int], None]
    """Multiply one iteration's work by a factor (a simulated cluster plans for a larger batch)."""
    probes: tuple[Probe, ...]
    measure: Callable[[StepWindow, Probe, Any], dict[str, float]]
    offloads: bool = False
    """Whether the runner offloads a time-sharing component at each turn (``runtime.device_turn``).
    The embodied and reasoning runners keep every component resident, so they pay no switch."""
    fixed: Callable[[Any], dict[str, str]] = lambda cfg: {}
    """Components the search does not move (robots are hardware): name -> the spec the run uses."""
    paced: Callable[[Any], dict[str, float]] = lambda cfg: {}
    """Component -> wall-clock seconds per unit that real time sets (see :mod:`.cost`)."""
    driver_on_path: Callable[[Any], bool] = lambda cfg: True
    """Whether the driver's own time per iteration (the profile's overhead) adds to the iteration:
    a driver that only polls while its components work on their own adds nothing."""
    cluster: Callable[[Any], Any] = lambda cfg: cfg.cluster
    """The cluster section the runner starts (what ``infinirl plan`` starts to plan on)."""
    refuses: Callable[[Any], str | None] = lambda cfg: None
    """Why this config cannot be planned (one line with the placement to write instead), or None."""
    step_name: str = "iteration"
    """What one predicted step is (``placement=auto`` prints "predicted X s per <step_name>")."""
    step_text: str = ""
    """What one predicted step is when it is not one iteration of the runner (the plan's table says it)."""


RUNNER_MODELS: Registry[RunnerModel] = Registry("runner model")

UNPLANNED_RUNNERS: dict[str, str] = {
    "sft": "sft trains in one process of the driver, with no components to place; its device key chooses where "
           "(device=auto: the first GPU, else the CPU)",
    "runtime_demo": "runtime_demo demonstrates the placements you write; give placement.sampler and "
                    "placement.learner (e.g. sampler: '0', learner: '1')",
}
"""Runners with nothing for the scheduler to plan: runner -> why, and what to write instead."""


def probe_candidates(model: RunnerModel, num_slots: int) -> tuple[Probe, ...]:
    """The probes that fit on ``num_slots`` devices (one device: the collocated probe only)."""
    return tuple(p for p in model.probes if all(f + n <= num_slots for f, n in p.devices.values()))


# ----- the weight sync (runners whose trainer feeds a rollout) ------------------------------------

_PUBLISH_METHODS = ("_infinirl_publish_weights", "_infinirl_broadcast_weights", "_infinirl_send_buckets")
_LOAD_METHODS = ("_infinirl_receive_weights", "_infinirl_receive_broadcast")
# Staging beside running calls (asynchronous RL's interrupting sync) is off the iteration's path.


def _sync_phase(trainer: str, receiver: str) -> Phase:
    """The trainer gathering and publishing its weights, then the rollout loading them: one model's
    worth whatever the batch, and more with more trainer ranks (a sharded trainer gathers its
    shards first), which is what makes many small ranks slower than their compute alone says."""
    return Phase(name="sync", components=(trainer, receiver), per_iteration=True)


def _sync_measure(window: StepWindow, trainer: str, receiver: str) -> dict[str, float]:
    return {f"sync/{trainer}": sum(window.per_rank(trainer, m) for m in _PUBLISH_METHODS),
            f"sync/{receiver}": sum(window.per_rank(receiver, m) for m in _LOAD_METHODS)}


# ----- embodied ----------------------------------------------------------------------------------


def _embodied_phases(cfg) -> tuple[Phase, ...]:
    return (Phase(name="collect", components=("env", "rollout"), pipelined=True, round_trips=cfg.rollout_steps + 1),
            Phase(name="update", components=("actor",)), _sync_phase("actor", "rollout"))


def _embodied_units(cfg) -> dict[str, float]:
    decisions = float(cfg.env.num_envs * cfg.rollout_steps)
    return {"env": decisions, "rollout": decisions, "actor": decisions}


def _embodied_depths(cfg, ranks: dict[str, int]) -> tuple[int, ...]:
    envs = cfg.env.num_envs
    return tuple(k for k in (1, 2, 4) if envs % (ranks["env"] * k) == 0)


def _embodied_no_depth(cfg, ranks: dict[str, int]) -> str:
    return f"env.num_envs={cfg.env.num_envs} is not divisible by {ranks['env']} env ranks"


def _embodied_check(cfg, candidate: Candidate) -> str | None:
    a = candidate.allocations
    if a["env"].ranks != a["rollout"].ranks:
        return "env and rollout pair rank for rank"
    if cfg.env.num_envs % (a["env"].ranks * candidate.depth):
        return f"env.num_envs={cfg.env.num_envs} is not divisible by env ranks x pipeline stages"
    from infinirl.runners.embodied import task_blocks_conflict

    conflict = task_blocks_conflict(cfg, a["rollout"].ranks, candidate.depth)
    if conflict:
        return conflict
    per_mini = cfg.env.num_envs * cfg.rollout_steps // cfg.algorithm.mini_batches
    if per_mini % a["actor"].ranks:
        return "a mini-batch does not split evenly over the actor's ranks"
    if a["env"].overlaps(a["rollout"]) and candidate.depth > 1:
        return "a collocated env steps its stages in turn: depth > 1 adds nothing"
    return None


def _embodied_apply(cfg, candidate: Candidate) -> None:
    cfg.placement = candidate.placement()
    cfg.rollout.pipeline_stages = candidate.depth
    if candidate.allocations["env"].overlaps(candidate.allocations["rollout"]):
        cfg.env.stage_processes = False


def _profile_run_settings(cfg) -> None:
    """What every profiling run leaves out: evaluations, checkpoints, loggers, and any earlier run
    in its output folder (a profile never resumes)."""
    cfg.eval.every = 0
    cfg.eval.at_start = False
    cfg.save_every = 0
    cfg.loggers = []
    cfg.resume = False


def _simulated_shorten(cfg, iterations: int) -> None:
    """A short run of a simulator runner's config: no evaluation worth the name, no checkpoints."""
    cfg.iterations = iterations
    _profile_run_settings(cfg)
    cfg.eval.episodes = 1
    cfg.eval.num_envs = 1
    cfg.eval.video_episodes = 0


def _embodied_measure(window: StepWindow, probe: Probe, cfg) -> dict[str, float]:
    collect = window.per_rank("rollout", "collect")
    rollout_own = float(window.metrics.get("rollout/inference_s", 0.0)) + float(window.metrics.get("rollout/record_s",
                                                                                                   0.0))
    a = probe.candidate().allocations
    out = {"update/actor": window.per_rank("actor", "update"), "collect/rollout": rollout_own,
           **_sync_measure(window, "actor", "rollout")}
    if a["env"].overlaps(a["rollout"]):  # the env steps inside the rollout's collect call
        out["collect/env"] = max(collect - rollout_own, 0.0)
    else:
        env_own = float(window.metrics.get("env/simulate_s", 0.0))
        out["collect/env"] = env_own
        # One chunk's way round the loop, times the round trips (cost.py's closed loop; the
        # streamed probe runs one chunk, so nothing overlaps the messages there).
        out["hop"] = max(collect - (env_own + rollout_own) / probe.depth, 0.0) / (cfg.rollout_steps + 1)
        if "env/bytes_out" in window.metrics:  # observations over the env links, every env rank's
            out["bytes/env"] = float(window.metrics["env/bytes_out"])
        if "rollout/bytes_out" in window.metrics:  # rank 0's actions; the ranks send alike
            out["bytes/rollout"] = float(window.metrics["rollout/bytes_out"]) * a["rollout"].ranks
    return out


RUNNER_MODELS.add("embodied", RunnerModel(
    runner="embodied",
    step_metric="time/iteration_s",
    window_method=("rollout", "collect"),
    phases=_embodied_phases,
    units=_embodied_units,
    model_key=lambda cfg: f"{cfg.policy.name}:{cfg.env.name}",
    depths=_embodied_depths,
    no_depth=_embodied_no_depth,
    check=_embodied_check,
    apply=_embodied_apply,
    shorten=_simulated_shorten,
    scale_batch=lambda cfg, factor: setattr(cfg.env, "num_envs", cfg.env.num_envs * factor),
    probes=(Probe(name="collocated", devices={"env": (0, 1), "rollout": (0, 1), "actor": (0, 1)}),
            Probe(name="two_ranks", devices={"env": (0, 2), "rollout": (0, 2), "actor": (0, 2)}),
            Probe(name="streamed", devices={"env": (0, 1), "rollout": (1, 1), "actor": (0, 1)})),
    measure=_embodied_measure,
))


# ----- reasoning ---------------------------------------------------------------------------------


def _reasoning_needs_logprobs(cfg) -> bool:
    algo = cfg.algorithm
    return algo.mini_batches > 1 or algo.epochs > 1 or algo.kl_reward_coef > 0 or cfg.reference_mode == "actor_base"


def _reasoning_phases(cfg) -> tuple[Phase, ...]:
    phases = [Phase(name="generate", components=("rollout", "reward"), pipelined=True)]
    scorers = (("actor",) if _reasoning_needs_logprobs(cfg) else ()) + tuple(
        c for c in ("reference", "critic") if c in cfg.components())
    if scorers:
        phases.append(Phase(name="logprobs", components=scorers, concurrent=True))
    trainers = ("actor", "critic") if "critic" in cfg.components() else ("actor",)
    phases.append(Phase(name="train", components=trainers, concurrent=True))
    phases.append(_sync_phase("actor", "rollout"))
    return tuple(phases)


def _reasoning_units(cfg) -> dict[str, float]:
    samples = float(cfg.prompts_per_step * cfg.rollout.group_size)
    return {name: samples for name in cfg.components()}


def _reasoning_depths(cfg, ranks: dict[str, int]) -> tuple[int, ...]:
    return tuple(k for k in (1, 2, 4) if cfg.prompts_per_step % (ranks["rollout"] * k) == 0)


def _reasoning_no_depth(cfg, ranks: dict[str, int]) -> str:
    return f"prompts_per_step={cfg.prompts_per_step} is not divisible by {ranks['rollout']} rollout ranks"


def _reasoning_check(cfg, candidate: Candidate) -> str | None:
    a = candidate.allocations
    if cfg.prompts_per_step % (a["rollout"].ranks * candidate.depth):
        return (f"prompts_per_step={cfg.prompts_per_step} does not split evenly into chunks over the rollout's "
                "ranks")
    per_mini = cfg.prompts_per_step * cfg.rollout.group_size // cfg.algorithm.mini_batches
    for trainer in ("actor", "critic"):
        if trainer in a and per_mini < a[trainer].ranks:
            return f"a mini-batch has fewer samples than the {trainer}'s ranks"
    return None


def _reasoning_apply(cfg, candidate: Candidate) -> None:
    cfg.placement = candidate.placement()
    ranks = candidate.allocations["rollout"].ranks
    per_rank = math.ceil(cfg.prompts_per_step / ranks)
    cfg.rollout.stream_chunk_prompts = 0 if candidate.depth == 1 else math.ceil(per_rank / candidate.depth)


def _reasoning_shorten(cfg, iterations: int) -> None:
    cfg.iterations = iterations
    _profile_run_settings(cfg)
    cfg.task.eval_size = 0


def _reasoning_measure(window: StepWindow, probe: Probe, cfg) -> dict[str, float]:
    out = {"generate/rollout": window.per_rank("rollout", "generate_to"),
           "train/actor": window.per_rank("actor", "train_step"), **_sync_measure(window, "actor", "rollout")}
    # The reward scores chunks as they arrive; what it adds after the last chunk is its own share.
    drain = window.last_end.get(("reward", "score_stream"), 0.0) - window.last_end.get(("rollout", "generate_to"), 0.0)
    chunks_per_reward_rank = probe.devices["rollout"][1] * probe.depth / probe.devices["reward"][1]
    out["generate/reward"] = max(drain, 0.0) * chunks_per_reward_rank
    if _reasoning_needs_logprobs(cfg):
        out["logprobs/actor"] = window.per_rank("actor", "compute_logprobs") + window.per_rank(
            "actor", "compute_ref_logprobs")
    for name, methods in (("reference", ("compute_logprobs",)), ("critic", ("compute_values",))):
        if name in cfg.components():
            out[f"logprobs/{name}"] = sum(window.per_rank(name, m) for m in methods)
    if "critic" in cfg.components():
        out["train/critic"] = window.per_rank("critic", "train_step")
    return out


def _reasoning_probe_devices(width: int) -> dict[str, tuple[int, int]]:
    return {name: (0, width) for name in ("actor", "rollout", "reward", "critic", "reference")}


RUNNER_MODELS.add("reasoning", RunnerModel(
    runner="reasoning",
    step_metric="time/step_s",
    window_method=("rollout", "generate_to"),
    phases=_reasoning_phases,
    units=_reasoning_units,
    model_key=lambda cfg: cfg.model.path,
    depths=_reasoning_depths,
    no_depth=_reasoning_no_depth,
    check=_reasoning_check,
    apply=_reasoning_apply,
    shorten=_reasoning_shorten,
    scale_batch=lambda cfg, factor: setattr(cfg, "prompts_per_step", cfg.prompts_per_step * factor),
    probes=(Probe(name="collocated", devices=_reasoning_probe_devices(1)),
            Probe(name="two_ranks", devices=_reasoning_probe_devices(2))),
    measure=_reasoning_measure,
))


# ----- sac ---------------------------------------------------------------------------------------
# One collector and one learner rank. Without collect_ahead an iteration collects, then updates;
# with it the collector gathers the next iteration's steps while the learner trains on this one's,
# so on disjoint slots the two overlap (the longer one sets the pace) and on one slot they take turns.


def _sac_phases(cfg) -> tuple[Phase, ...]:
    if cfg.collect_ahead:
        return (Phase(name="iteration", components=("collector", "learner"), concurrent=True),)
    return (Phase(name="collect", components=("collector",)), Phase(name="update", components=("learner",)))


def _sac_phase_of(cfg, component: str) -> str:
    return next(p.name for p in _sac_phases(cfg) if component in p.components)


def _sac_units(cfg) -> dict[str, float]:
    steps = float(cfg.steps_per_iteration * cfg.env.num_envs)
    return {"collector": steps, "learner": cfg.algorithm.utd_ratio * steps}


def _sac_check(cfg, candidate: Candidate) -> str | None:
    if any(a.ranks != 1 for a in candidate.allocations.values()):
        return "the SAC runner runs one collector and one learner rank"
    return None


def _sac_shorten(cfg, iterations: int) -> None:
    _simulated_shorten(cfg, iterations)
    # Random warm-up steps make collection cheaper and leave the learner idle: the measured
    # iterations would not be the run's. Learning starts as early as the first mini-batch allows.
    cfg.algorithm.learning_starts = cfg.algorithm.batch_size


def _sac_measure(window: StepWindow, probe: Probe, cfg) -> dict[str, float]:
    return {f"{_sac_phase_of(cfg, 'collector')}/collector": float(window.metrics.get("rollout/collect_s", 0.0)),
            f"{_sac_phase_of(cfg, 'learner')}/learner": window.per_rank("learner", "add_and_update")}


RUNNER_MODELS.add("sac", RunnerModel(
    runner="sac",
    step_metric="time/iteration_s",
    window_method=("collector", "collect"),
    phases=_sac_phases,
    units=_sac_units,
    model_key=lambda cfg: f"{cfg.network.actor}:{cfg.env.name}",
    depths=lambda cfg, ranks: (1,),
    check=_sac_check,
    apply=lambda cfg, candidate: setattr(cfg, "placement", candidate.placement()),
    shorten=_sac_shorten,
    scale_batch=lambda cfg, factor: setattr(cfg.env, "num_envs", cfg.env.num_envs * factor),
    probes=(Probe(name="collocated", devices={"collector": (0, 1), "learner": (0, 1)}),
            Probe(name="split", devices={"collector": (1, 1), "learner": (0, 1)})),
    measure=_sac_measure,
))


# ----- realworld_sac -----------------------------------------------------------------------------
# Robots are hardware: the search never moves them (``fixed``) and only places the learner, one rank
# on a CPU slot or a device. A robot's steps take its control period of wall-clock time whatever
# runs beside it (``paced``), so the model's unit of time is one turn: every robot runs one episode
# (side by side: the cost model sees one robot's steps) and the learner does its updates per
# collected step. Synchronous mode takes the two in turn; asynchronous mode runs them side by side,
# so the robots' clock bounds an iteration and the learner keeps up or not. Both are profiled in
# turns (clean spans per turn, the same per-step and per-update work).


def _realworld_robots(cfg) -> int:
    """Robot ranks: one per fleet entry, else as many as placement.robot gives (one when it is auto)."""
    from infinirl.runtime.placement import parse_spec

    if cfg.robot.fleet:
        return len(cfg.robot.fleet)
    if "robot" not in cfg.pinned_placement():
        return 1
    parsed = parse_spec(cfg.placement["robot"], "robot")
    return parsed.num_processes or max(len(parsed.indices), 1)


def _realworld_robot_spec(cfg) -> str:
    """Where the robots run: placement.robot, or when it is ``auto`` the default one (slot or device 0,
    every fleet rank on it)."""
    if "robot" in cfg.pinned_placement():
        return cfg.placement["robot"]
    robots = _realworld_robots(cfg)
    return "0" if robots == 1 else f"0:0-{robots - 1}"


def _realworld_episode_steps(cfg) -> float:
    """Steps of one turn's episode: the longest any robot's task allows (the turn waits for it)."""
    if cfg.robot.fleet:
        return float(max(cfg.task_of(i).max_episode_steps for i in range(len(cfg.robot.fleet))))
    return float(cfg.task.max_episode_steps)


def _realworld_updates_per_step(cfg) -> float:
    """Learner updates per collected step: the asynchronous cap when one is set, else utd_ratio."""
    cap = cfg.pipeline.max_updates_per_step
    return float(cap) if cfg.pipeline.mode == "async" and cap is not None else float(cfg.algorithm.utd_ratio)


def _realworld_phases(cfg) -> tuple[Phase, ...]:
    if cfg.pipeline.mode == "async":
        return (Phase(name="iteration", components=("robot", "learner"), concurrent=True),)
    return (Phase(name="collect", components=("robot",)), Phase(name="update", components=("learner",)))


def _realworld_phase_of(cfg, component: str) -> str:
    return next(p.name for p in _realworld_phases(cfg) if component in p.components)


def _realworld_units(cfg) -> dict[str, float]:
    steps = _realworld_episode_steps(cfg)
    return {"robot": steps, "learner": _realworld_updates_per_step(cfg) * steps * _realworld_robots(cfg)}


def _realworld_paced(cfg) -> dict[str, float]:
    """The slowest robot's control period per step (a driver option; 0 when the config names no
    rate, e.g. a discovered robot: its measured steps stand)."""
    entries = [e.options for e in cfg.robot.fleet] or [cfg.robot.options]
    rates = [float(o["control_hz"]) for o in entries if o.get("control_hz")]
    return {"robot": 1.0 / min(rates)} if rates and len(rates) == len(entries) else {}


def _realworld_check(cfg, candidate: Candidate) -> str | None:
    learner = candidate.allocations["learner"]
    if learner.ranks != 1 or learner.count != 1:
        return "the learner is one rank on one device or CPU slot"
    return None


def _realworld_apply(cfg, candidate: Candidate) -> None:
    cfg.placement = {"robot": _realworld_robot_spec(cfg), "learner": candidate.allocations["learner"].spec()}


def _realworld_shorten(cfg, iterations: int) -> None:
    """Turns of the same work: one turn per iteration (a window shorter than any turn), in
    synchronous mode whatever the config's mode, with no demonstrations or evaluations (robot time
    that is not the iteration's) and updates from the first turn on (a batch is drawn with
    replacement, so an update costs the same on a small store)."""
    cfg.algorithm.utd_ratio = _realworld_updates_per_step(cfg)  # read before the mode changes
    cfg.iterations = iterations
    cfg.pipeline.mode = "sync"
    cfg.pipeline.iteration_s = 1e-3
    cfg.algorithm.learning_starts = 1
    cfg.demos.episodes = 0
    _profile_run_settings(cfg)
    cfg.eval.episodes = 1
    cfg.replay.path = None


def _realworld_measure(window: StepWindow, probe: Probe, cfg) -> dict[str, float]:
    """The turn's episode and updates, scaled to the config's units (episodes that end early on
    success have fewer steps than the config's longest)."""
    length = float(window.metrics.get("rollout/episode_length_mean", 0.0))
    episodes = float(window.metrics.get("rollout/episodes", 0.0))
    if length <= 0 or episodes <= 0:
        return {}
    units = _realworld_units(cfg)
    updates = _realworld_updates_per_step(cfg) * length * episodes
    return {f"{_realworld_phase_of(cfg, 'robot')}/robot": window.per_rank("robot", "collect") * units["robot"] / length,
            f"{_realworld_phase_of(cfg, 'learner')}/learner":
                window.per_rank("learner", "add_and_update") * units["learner"] / updates}


def _realworld_refuses(cfg) -> str | None:
    if cfg.pipeline.transport == "edge":
        return ("pipeline.transport=edge: the robot runs at the edge node, outside the cluster the scheduler "
                "profiles; give placement.learner by hand (one CPU slot or device, e.g. '0')")
    return None


def _robot_cluster(cfg):
    """The robot runners' cluster: the config's, with the robot drivers' discovery when it asks for it."""
    from infinirl.realworld.discovery import with_driver_discovery

    return with_driver_discovery(cfg.cluster)


#: What the robot runners' models share: robots fixed where the config puts them and paced by
#: their clock, one learner rank placed beside them or apart.
_ROBOT_RUNNER_MODEL = dict(
    step_metric="time/iteration_s",
    window_method=("robot", "collect"),
    depths=lambda cfg, ranks: (1,),
    check=_realworld_check,
    apply=_realworld_apply,
    scale_batch=lambda cfg, factor: None,  # robots are hardware: a larger cluster gets no more of them
    probes=(Probe(name="collocated", devices={"robot": (0, 1), "learner": (0, 1)}),
            Probe(name="split", devices={"robot": (0, 1), "learner": (1, 1)})),
    fixed=lambda cfg: {"robot": _realworld_robot_spec(cfg)},
    paced=_realworld_paced,
    cluster=lambda cfg: _robot_cluster(cfg),
)

RUNNER_MODELS.add("realworld_sac", RunnerModel(
    runner="realworld_sac",
    **_ROBOT_RUNNER_MODEL,
    phases=_realworld_phases,
    units=_realworld_units,
    model_key=lambda cfg: f"{'+'.join(e.kind for e in cfg.robot.fleet) or cfg.robot.kind}:realworld_sac",
    shorten=_realworld_shorten,
    measure=_realworld_measure,
    driver_on_path=lambda cfg: cfg.pipeline.mode == "sync",
    refuses=_realworld_refuses,
    step_name="turn",
    step_text="step_s = one turn: every robot runs one episode and the learner its updates on it (iterations "
              "are pipeline.iteration_s windows of turns)",
))


# ----- hg_dagger ---------------------------------------------------------------------------------
# The same robots and learner as realworld_sac, taking turns: every robot runs
# dagger.episodes_per_iteration episodes with the human watching, then the learner aggregates the
# human's labels and trains bc.updates_per_iteration mini-batches. A profile runs one episode per
# robot per iteration (robot time is real time) and scales it to the config's episodes.


def _dagger_units(cfg) -> dict[str, float]:
    return {"robot": float(cfg.dagger.episodes_per_iteration * cfg.task.max_episode_steps),
            "learner": float(cfg.bc.updates_per_iteration)}


def _dagger_shorten(cfg, iterations: int) -> None:
    """One episode per robot per iteration; one initial demonstration when the config records any (the
    learner then trains from the first iteration whatever the human labelled); no evaluations."""
    cfg.iterations = iterations
    cfg.dagger.episodes_per_iteration = 1
    cfg.dagger.initial_demos = min(cfg.dagger.initial_demos, 1)
    _profile_run_settings(cfg)
    cfg.eval.episodes = 1


_DAGGER_LEARNER_METHODS = ("action_error", "aggregate", "train")


def _dagger_measure(window: StepWindow, probe: Probe, cfg) -> dict[str, float]:
    """The iteration's episodes scaled to the config's (per robot: episodes x the longest episode),
    the learner's calls as they ran (its updates per iteration are the config's), and the driver's
    own time: the step less both."""
    length = float(window.metrics.get("rollout/episode_length_mean", 0.0))
    episodes = float(window.metrics.get("rollout/episodes", 0.0))
    if length <= 0 or episodes <= 0:
        return {}
    collect = window.per_rank("robot", "collect")
    learner = sum(window.per_rank("learner", m) for m in _DAGGER_LEARNER_METHODS)
    steps_per_robot = length * episodes / _realworld_robots(cfg)
    step = float(window.metrics.get("time/iteration_s", 0.0))
    return {"collect/robot": collect * _dagger_units(cfg)["robot"] / steps_per_robot, "update/learner": learner,
            "overhead": max(step - collect - learner, 0.0)}


RUNNER_MODELS.add("hg_dagger", RunnerModel(
    runner="hg_dagger",
    **_ROBOT_RUNNER_MODEL,
    phases=lambda cfg: (Phase(name="collect", components=("robot",)), Phase(name="update", components=("learner",))),
    units=_dagger_units,
    model_key=lambda cfg: f"{cfg.robot.kind}:hg_dagger",
    shorten=_dagger_shorten,
    measure=_dagger_measure,
))
