"""Profiling: short real runs of a config under a few probe placements, measured from the tracer's spans.

For each probe of the runner (:mod:`.workloads`: collocated, two ranks per component, streamed)
that fits the cluster's devices (accelerators when it has them, else CPU slots) the profiler runs
the config for a few iterations with the probe's placement, and before the components shut down
reads every rank's spans (one per executed method), its peak resident host memory and, on
accelerators, the most accelerator memory torch reserved in it, and, for a runner that offloads
collocated components (``RunnerModel.offloads``), the time of one offload + reload. Iterations
are cut out of the spans at each call of the runner's first-phase method; the first iteration is
warm-up and dropped. The runner model turns each iteration into own seconds per
``"<phase>/<component>"``, and :func:`fit` turns the probes into one
:class:`~infinirl.scheduler.cost.WorkCost` each: seconds per unit of work from the one-rank probes
(fixed seconds for work that does not grow with the batch, the weight sync), the
cost of a second rank (the collective) from the two-rank probe.

Profiles are cached as JSON per (runner, model, config hash, hardware probe, cluster shape), so a
second plan of the same config on the same cluster runs no probe. The config hash leaves out what
does not change the work of an iteration: placement, the depth keys, length, cadences, output,
loggers and the cluster section, whose effect is the cluster's shape (:func:`inventory_shape`:
nodes, their CPU slots and accelerators), keyed from the inventory of the cluster the plan is for.
"""

from __future__ import annotations

import copy
import hashlib
import json
import os
import shutil
import socket
import statistics
import tempfile
from dataclasses import dataclass, field, replace
from typing import Any

from infinirl.config import ConfigError, to_plain
from infinirl.runtime.inventory import ClusterInventory
from infinirl.scheduler.cost import Candidate, Phase, WorkCost, Workload, predict
from infinirl.scheduler.search import pool_of
from infinirl.scheduler.workloads import RUNNER_MODELS, Probe, RunnerModel, StepWindow, probe_candidates
from infinirl.utils import capture_rng_state, restore_rng_state, write_json_atomic

__all__ = ["PROFILE_CACHE_ENV", "MeasuredRun", "Profile", "ProbeResult", "cache_path", "config_hash", "fit",
           "hardware_probe", "inventory_shape", "load_or_profile", "measure_candidate", "merge_rounds", "paced_costs",
           "probe_slots", "profile_key", "profile_summary", "run_probe", "step_windows", "workload_of"]

PROFILE_CACHE_ENV = "INFINIRL_PROFILE_CACHE"
"""Folder of cached profiles (default ``~/.cache/infinirl/profiles``)."""
PROFILE_FORMAT = 3  # 2: weight-sync phases; 3: keyed by cluster shape, accelerator memory

# Keys that do not change one iteration's work (the search varies the placement and depth keys).
_NOT_WORK = ("placement", "iterations", "output_dir", "resume", "save_every", "keep_checkpoints", "loggers", "eval",
             "cluster", "seed")
_DEPTH_KEYS = (("rollout", "pipeline_stages"), ("rollout", "stream_chunk_prompts"), ("env", "stage_processes"))


@dataclass(frozen=True, kw_only=True)
class ProbeResult:
    """What one probe run measured: per iteration (warm-up dropped) the model's own seconds and the
    step time; per component a rank's peak resident host bytes (``memory_bytes``), on accelerators
    its peak accelerator bytes (``accelerator_bytes``), and one offload + reload (runners that
    offload). A component none of whose ranks could be read is absent: unknown, not 0."""

    probe: Probe
    iterations: list[dict[str, float]]
    step_s: list[float]
    memory_bytes: dict[str, float] = field(default_factory=dict)
    switch_s: dict[str, float] = field(default_factory=dict)
    inventory: dict = field(default_factory=dict)
    accelerator_bytes: dict[str, float] = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {"probe": {"name": self.probe.name, "devices": {k: list(v) for k, v in self.probe.devices.items()},
                          "depth": self.probe.depth},
                "iterations": self.iterations, "step_s": self.step_s, "memory_bytes": self.memory_bytes,
                "accelerator_bytes": self.accelerator_bytes, "switch_s": self.switch_s, "inventory": self.inventory}

    @classmethod
    def from_dict(cls, data: dict) -> ProbeResult:
        p = data["probe"]
        probe = Probe(name=p["name"], devices={k: tuple(v) for k, v in p["devices"].items()}, depth=p["depth"])
        return cls(probe=probe, iterations=data["iterations"], step_s=data["step_s"],
                   memory_bytes=data["memory_bytes"], accelerator_bytes=data.get("accelerator_bytes", {}),
                   switch_s=data["switch_s"], inventory=data["inventory"])


@dataclass(frozen=True, kw_only=True)
class Profile:
    """A config's measured costs on this hardware (what the cost model and the search read)."""

    runner: str
    key: dict
    costs: dict[str, WorkCost]
    overhead_s: float
    hop_s: float
    inventory: dict
    probes: list[ProbeResult]

    def to_dict(self) -> dict:
        return {"format": PROFILE_FORMAT, "runner": self.runner, "key": self.key,
                "costs": {k: vars(c) for k, c in self.costs.items()}, "overhead_s": self.overhead_s,
                "hop_s": self.hop_s, "inventory": self.inventory, "probes": [p.to_dict() for p in self.probes]}

    @classmethod
    def from_dict(cls, data: dict) -> Profile:
        return cls(runner=data["runner"], key=data["key"],
                   costs={k: WorkCost(**c) for k, c in data["costs"].items()}, overhead_s=data["overhead_s"],
                   hop_s=data["hop_s"], inventory=data["inventory"],
                   probes=[ProbeResult.from_dict(p) for p in data["probes"]])


# ----- keys and cache ----------------------------------------------------------------------------


def config_hash(cfg) -> str:
    """Hash of the config's work-defining keys (see the module docstring)."""
    plain = to_plain(cfg)
    for key in _NOT_WORK:
        plain.pop(key, None)
    for section, key in _DEPTH_KEYS:
        if isinstance(plain.get(section), dict):
            plain[section].pop(key, None)
    text = json.dumps(plain, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def hardware_probe() -> dict:
    """What the measured costs depend on: CPU model and count, memory, accelerators."""
    from infinirl.results import host_probe

    probe = host_probe()
    return {k: probe.get(k) for k in ("cpu", "vcpus", "memory_gib", "gpus")}


def inventory_shape(inventory: ClusterInventory | dict) -> dict:
    """What of a cluster a profile depends on: per node its CPU slots and its accelerators' kind and
    memory (the probes that fit, the devices they ran on). A node's memory is left out: Ray sizes
    it from the memory free when it starts, so it moves between two starts of one cluster; the
    search reads it from the cluster the plan is for."""
    if isinstance(inventory, dict):
        inventory = ClusterInventory.from_dict(inventory)
    return {"nodes": [{"cpus": n.num_cpus, "accelerators": [[a.kind, a.memory_bytes] for a in n.accelerators]}
                      for n in inventory.nodes]}


def probe_slots(inventory: ClusterInventory) -> int:
    """Devices the probes may use: the accelerators when the cluster has them (components are
    placed on them then), else the CPU slots."""
    return pool_of(inventory).size


def profile_key(cfg, model: RunnerModel, inventory: ClusterInventory) -> dict:
    return {"runner": model.runner, "model": model.model_key(cfg), "config": config_hash(cfg),
            "hardware": hardware_probe(), "cluster": inventory_shape(inventory)}


def cache_path(key: dict, cache_dir: str | None = None) -> str:
    folder = cache_dir or os.environ.get(PROFILE_CACHE_ENV) or os.path.join(
        os.path.expanduser("~"), ".cache", "infinirl", "profiles")
    digest = hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:16]
    return os.path.join(folder, f"{key['runner']}-{key['config']}-{digest}.json")


# ----- measuring ---------------------------------------------------------------------------------


def step_windows(spans: list[tuple], rows: list[dict], model: RunnerModel, iterations: int) -> list[StepWindow]:
    """Cut spans into iterations at each rank-0 call of the model's window method; pair each with
    its metrics row (rows of steps 1..N, in order)."""
    component, method = model.window_method
    starts = sorted(s[3] for s in spans if s[0] == component and s[1] == 0 and s[2] == method)[:iterations]
    step_rows = [r for r in rows if model.step_metric in r]
    windows = []
    for i, start in enumerate(starts):
        end = starts[i + 1] if i + 1 < len(starts) else float("inf")
        busy: dict[tuple[str, str], dict[int, float]] = {}
        last_end: dict[tuple[str, str], float] = {}
        for name, rank, meth, s, e, _ in spans:
            if start <= s < end:
                per_rank = busy.setdefault((name, meth), {})
                per_rank[rank] = per_rank.get(rank, 0.0) + (e - s)
                last_end[(name, meth)] = max(last_end.get((name, meth), 0.0), e - start)
        windows.append(StepWindow(busy={k: list(v.values()) for k, v in busy.items()}, last_end=last_end,
                                  metrics=step_rows[i] if i < len(step_rows) else {}))
    return windows


def _peak_rss(pid: int) -> float | None:
    """A process's peak resident set (Linux ``VmHWM``), None if it cannot be read."""
    try:
        with open(f"/proc/{pid}/status") as handle:
            for line in handle:
                if line.startswith("VmHWM:"):
                    return float(line.split()[1]) * 1024
    except OSError:
        pass
    return None


def _known_peak(peaks: list[float | None]) -> float | None:
    """The largest of the ranks' peaks that could be read (ranks alike); None when none could."""
    known = [p for p in peaks if p is not None]
    return max(known) if known else None


class _Recorder:
    """The run observer: spans, peak memory (host; accelerator on accelerators) and, for a runner
    that offloads (``time_switch``), one offload + reload of every component."""

    def __init__(self, time_switch: bool = False):
        self.time_switch = time_switch
        self.spans: list[tuple] = []
        self.memory: dict[str, float] = {}
        self.accelerator: dict[str, float] = {}
        self.switch: dict[str, float] = {}
        self.inventory: dict = {}

    def __call__(self, groups: dict, plan) -> None:
        self.inventory = plan.inventory.to_dict()
        on_accelerators = plan.inventory.accelerator_kind is not None
        host = socket.gethostname()
        for name, group in groups.items():
            self.spans.extend(group.pop_spans())
            # A rank on another host cannot be read from here: unknown, not 0.
            peak = _known_peak([_peak_rss(info["pid"]) if info.get("hostname") == host and "pid" in info else None
                                for info in group.rank_info])
            if peak is not None:
                self.memory[name] = peak
            if on_accelerators:
                try:
                    device = _known_peak(group.call("_infinirl_accelerator_peak").wait(timeout=60))
                except Exception:  # a rank that cannot answer leaves the component's memory unknown
                    device = None
                if device is not None:
                    self.accelerator[name] = device
            if self.time_switch:
                group.call("offload").wait(timeout=120)
                group.call("reload").wait(timeout=120)
                turns = [s for s in group.pop_spans() if s[2] in ("offload", "reload")]
                self.switch[name] = sum(s[4] - s[3] for s in turns) / max(group.world_size, 1)


@dataclass(frozen=True, kw_only=True)
class MeasuredRun:
    """A short run under one candidate: its iterations (warm-up dropped) and what the observer read."""

    windows: list[StepWindow]
    step_s: list[float]
    memory_bytes: dict[str, float]
    switch_s: dict[str, float]
    inventory: dict
    accelerator_bytes: dict[str, float] = field(default_factory=dict)


def measure_candidate(cfg, model: RunnerModel, candidate: Candidate, iterations: int = 4,
                      label: str = "candidate") -> MeasuredRun:
    """Run ``cfg`` shortened to ``iterations`` under ``candidate``; its spans cut into iterations."""
    from infinirl.runners import load_runners
    from infinirl.runners.metrics_log import read_metrics
    from infinirl.runners.run_support import RUN_OBSERVERS

    run = copy.deepcopy(cfg)
    model.apply(run, candidate)
    model.shorten(run, iterations)
    folder = tempfile.mkdtemp(prefix=f"infinirl-profile-{label}-")
    run.output_dir = os.path.join(folder, "run")
    recorder = _Recorder(time_switch=model.offloads)
    RUN_OBSERVERS.append(recorder)
    try:
        print(f"measuring {model.runner} ({label}): placement {run.placement}, depth {candidate.depth}", flush=True)
        load_runners().get(run.runner).run(run)
        rows = read_metrics(os.path.join(run.output_dir, "metrics.jsonl"))
    finally:
        RUN_OBSERVERS.remove(recorder)
        shutil.rmtree(folder, ignore_errors=True)
    windows = step_windows(recorder.spans, rows, model, iterations)[1:]  # the first is warm-up
    if not windows:
        raise RuntimeError(f"measuring {label!r}: no iteration after the warm-up was traced; "
                           "run at least 2 iterations")
    return MeasuredRun(windows=windows, step_s=[float(w.metrics.get(model.step_metric, 0.0)) for w in windows],
                       memory_bytes=recorder.memory, switch_s=recorder.switch, inventory=recorder.inventory,
                       accelerator_bytes=recorder.accelerator)


def run_probe(cfg, model: RunnerModel, probe: Probe, iterations: int = 4) -> ProbeResult:
    """Run ``cfg`` shortened to ``iterations`` under ``probe``'s placement; measure it."""
    run = measure_candidate(cfg, model, probe.candidate(tuple(cfg.components())), iterations, probe.name)
    return ProbeResult(probe=probe, iterations=[model.measure(w, probe, cfg) for w in run.windows],
                       step_s=run.step_s, memory_bytes=run.memory_bytes, switch_s=run.switch_s,
                       inventory=run.inventory, accelerator_bytes=run.accelerator_bytes)


# ----- fitting -----------------------------------------------------------------------------------


def _median(values: list[float]) -> float:
    return statistics.median(values) if values else 0.0


def _fit_work(phase: Phase, component: str, units: float, results: list[ProbeResult],
              components: tuple[str, ...]) -> dict[str, float]:
    """One rank's work from the one-rank probes (mean of their medians): seconds per unit, or, for
    a phase whose work does not grow with the batch, fixed seconds per iteration; comm_s from the
    other probes' excess over that work (spread over their ranks unless it is per iteration)."""
    key = f"{phase.name}/{component}"
    by_ranks: dict[int, list[float]] = {}
    for result in results:
        ranks = result.probe.candidate(components).allocations[component].ranks
        by_ranks.setdefault(ranks, []).append(_median([it[key] for it in result.iterations if key in it]))
    single = by_ranks.pop(1, [])
    one_rank = statistics.fmean(single) if single else 0.0

    def work(seconds: float, ranks: int) -> dict[str, float]:
        if phase.per_iteration:
            return {"per_unit_s": 0.0, "fixed_s": seconds}
        return {"per_unit_s": seconds * ranks / units, "fixed_s": 0.0}

    comm = [(s - (one_rank if phase.per_iteration else one_rank / r)) / max(r.bit_length() - 1, 1)
            for r, values in by_ranks.items() for s in values]
    if not single and comm:  # only multi-rank probes: attribute everything to the work
        r, values = next(iter(by_ranks.items()))
        return {**work(statistics.fmean(values), r), "comm_s": 0.0}
    return {**work(one_rank, 1), "comm_s": max(0.0, statistics.fmean(comm)) if comm else 0.0}


def fit(cfg, model: RunnerModel, results: list[ProbeResult], key: dict | None = None) -> Profile:
    """One WorkCost per phase and component, the hop and the driver's overhead, from the probes."""
    components = tuple(cfg.components())
    units = model.units(cfg)
    inventory = next((r.inventory for r in results if r.inventory), None)
    on_accelerators = inventory is not None and ClusterInventory.from_dict(inventory).accelerator_kind is not None
    costs: dict[str, WorkCost] = {}
    for phase in model.phases(cfg):
        for component in phase.components:
            name = f"{phase.name}/{component}"
            work = _fit_work(phase, component, units[component], results, components)
            device, host, known = fit_memory(component, results, components, on_accelerators)
            switch = _median([r.switch_s.get(component, 0.0) for r in results])
            sent = [it[f"bytes/{component}"] for r in results for it in r.iterations if f"bytes/{component}" in it]
            costs[name] = WorkCost(per_unit_s=work["per_unit_s"], fixed_s=work["fixed_s"], comm_s=work["comm_s"],
                                   switch_s=switch, memory_fixed_bytes=device, host_memory_bytes=host,
                                   memory_known=known,
                                   bytes_out_per_unit=_median(sent) / units[component] if sent else 0.0)
    hops = [it["hop"] for r in results for it in r.iterations if "hop" in it]
    hop_s = _median(hops)
    bare = Workload(runner=model.runner, phases=model.phases(cfg), units=units, costs=paced_costs(model, cfg, costs),
                    hop_s=hop_s, offloads=model.offloads)
    excess = [_median(r.step_s) - predict(bare, r.probe.candidate(components)).step_s for r in results]
    # A model whose probes run less work than the config (fewer robot episodes) measures the
    # driver's own time directly ("overhead"); a driver off the iteration's path (it only polls)
    # has none to fit, whatever shape its probes ran in.
    direct = [it["overhead"] for r in results for it in r.iterations if "overhead" in it]
    overhead = max(0.0, _median(direct) if direct else _median(excess)) if model.driver_on_path(cfg) else 0.0
    return Profile(runner=model.runner, key=key or {}, costs=costs, overhead_s=overhead,
                   hop_s=hop_s, inventory=results[0].inventory if results else {}, probes=list(results))


def fit_memory(component: str, results: list[ProbeResult], components: tuple[str, ...],
               on_accelerators: bool) -> tuple[float, float, bool]:
    """A rank's memory on its device, its host memory, and whether the device's was measured: on
    accelerators the device's is the accelerator peak and the host's the resident set (each checked
    against its own limit); on CPU slots both are the resident set. The largest one-rank peak of
    the probes that read it (a probe that ran the component inside another's process has none),
    else the largest of any probe."""
    single = [r for r in results if r.probe.candidate(components).allocations[component].ranks == 1]

    def largest(read) -> float | None:
        for probes in (single, results):
            peaks = [read(r)[component] for r in probes if component in read(r)]
            if peaks:
                return max(peaks)
        return None

    host = largest(lambda r: r.memory_bytes)
    device = largest(lambda r: r.accelerator_bytes) if on_accelerators else host
    return device or 0.0, host or 0.0, device is not None


def paced_costs(model: RunnerModel, cfg, costs: dict[str, WorkCost]) -> dict[str, WorkCost]:
    """``costs`` with the config's real-time pace (``model.paced``) on its components' work: the
    pace is the config's (a control rate), not something measured, so it is never cached."""
    paced = model.paced(cfg)
    return {key: replace(cost, paced_per_unit_s=paced.get(key.split("/", 1)[1], cost.paced_per_unit_s))
            for key, cost in costs.items()}


def workload_of(cfg, profile: Profile) -> Workload:
    """The config's workload with the profile's measured costs (what :func:`~.cost.predict` reads)."""
    model = RUNNER_MODELS.get(cfg.runner)
    overhead = profile.overhead_s if model.driver_on_path(cfg) else 0.0
    return Workload(runner=cfg.runner, phases=model.phases(cfg), units=model.units(cfg),
                    costs=paced_costs(model, cfg, profile.costs), overhead_s=overhead, hop_s=profile.hop_s,
                    offloads=model.offloads)


def merge_rounds(results: list[ProbeResult]) -> ProbeResult:
    """One probe's runs of several rounds as one result: their iterations together (the fit takes
    medians over them), the largest peak memory of those read, the median offload + reload."""
    first = results[0]

    def largest(read) -> dict[str, float]:
        names = {c for r in results for c in read(r)}
        return {c: max(read(r)[c] for r in results if c in read(r)) for c in names}

    switched = {c for r in results for c in r.switch_s}
    return ProbeResult(probe=first.probe, iterations=[it for r in results for it in r.iterations],
                       step_s=[s for r in results for s in r.step_s],
                       memory_bytes=largest(lambda r: r.memory_bytes),
                       accelerator_bytes=largest(lambda r: r.accelerator_bytes),
                       switch_s={c: _median([r.switch_s[c] for r in results if c in r.switch_s]) for c in switched},
                       inventory=first.inventory)


def load_or_profile(cfg, inventory: ClusterInventory, iterations: int = 4, cache_dir: str | None = None,
                    refresh: bool = False, rounds: int = 1) -> Profile:
    """The cached profile of ``cfg`` on this hardware and a cluster shaped like ``inventory`` (the
    cluster the plan is for), or a new one: the probes that fit its devices (:func:`probe_slots`)
    run, on the cluster ``cfg.cluster`` starts, then the profile is cached. Probes that ran on a
    cluster of another shape than ``inventory``'s are a ConfigError naming ``cluster.*``.

    ``rounds`` > 1 runs every probe that many times, interleaved (A B C A B C): a load that drifts
    while profiling then shifts every probe alike instead of the later ones only."""
    if rounds < 1:
        raise ValueError(f"rounds={rounds} must be >= 1")
    model = RUNNER_MODELS.get(cfg.runner)
    key = profile_key(cfg, model, inventory)
    path = cache_path(key, cache_dir)
    if os.path.exists(path) and not refresh:
        with open(path) as handle:
            data = json.load(handle)
        if data.get("format") == PROFILE_FORMAT and data.get("key") == key:
            return Profile.from_dict(data)
    rng = capture_rng_state()  # probe runs seed and draw; the run that asked must not notice
    try:
        probes = probe_candidates(model, probe_slots(inventory))
        runs = [[run_probe(cfg, model, probe, iterations) for probe in probes] for _ in range(rounds)]
        results = [merge_rounds([round_[i] for round_ in runs]) for i in range(len(probes))]
    finally:
        restore_rng_state(rng)
    measured_on = [inventory_shape(r.inventory) for r in results if r.inventory]
    if any(shape != key["cluster"] for shape in measured_on):
        raise ConfigError(f"cluster.*: the probes ran on a cluster of {_shape_text(measured_on[0])}, not the "
                          f"{_shape_text(key['cluster'])} being planned for; set cluster.* (num_cpus, num_gpus, "
                          "address) to the cluster the run will use")
    profile = fit(cfg, model, results, key)
    os.makedirs(os.path.dirname(path), exist_ok=True)
    write_json_atomic(path, profile.to_dict())
    return profile


def _shape_text(shape: dict) -> str:
    nodes = shape["nodes"]
    per_node = sorted({(n["cpus"], len(n["accelerators"])) for n in nodes})
    return f"{len(nodes)} node(s) of " + " / ".join(f"{cpus} CPU slots and {gpus} accelerators"
                                                    for cpus, gpus in per_node)


def profile_summary(profile: Profile) -> dict[str, Any]:
    """The measured numbers a plan prints under its table."""
    return {"probes": {r.probe.name: round(_median(r.step_s), 3) for r in profile.probes},
            "overhead_s": round(profile.overhead_s, 4), "hop_s": round(profile.hop_s, 6)}
