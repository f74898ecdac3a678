"""Predicted step time and memory of a placement: pure functions of measured costs.

A runner's iteration is a sequence of **phases** run one after another (the embodied runner:
collect, update, then the weight sync; the reasoning runner: generate and score, log-probs,
update, weight sync). A phase is the work of one or more components; several components in one
phase stream to each other in order (env -> rollout, rollout -> reward), split into ``depth``
chunks (pipeline stages).

Each component's work in a phase has a :class:`WorkCost` measured by the profiler: one rank's
seconds for ``units`` of work spread over ``ranks`` ranks,
``seconds = fixed_s + per_unit_s * units / ranks + comm_s * log2(ranks)``
(the log term: the collective that joins the ranks), and its memory per rank. Work that does not
grow with the batch (``Phase.per_iteration``: the trainer gathering and publishing its weights,
the rollout loading them) has ``fixed_s`` and the log term only.

How a phase's components share hardware decides how their times combine:

* **time-sharing** (collocated: they hold a common device or CPU slot): they take turns, so
  their times add up on the devices they share; a runner that offloads a component at each turn
  (``Workload.offloads``) also pays each one's measured offload/reload (``switch_s``) once per
  iteration, one that keeps every component resident (every shipped runner model) pays none;
* **space-sharing** (disaggregated: disjoint devices): a pipeline over groups of components; with
  ``depth`` chunks each group works on a chunk while the next group works on the previous one.
  A stream that passes once (rollout -> reward) takes the slowest group plus the fill and drain
  of the others: ``sum(T_g) / depth + (depth - 1) / depth * max(T_g)``. A closed loop
  (``Phase.round_trips``: env -> rollout -> env, once per env step) takes the longer of the
  slowest group and one chunk's way round, ``max(max(T_g), sum(T_g) / depth + hop_s *
  round_trips)``: while one chunk's message is in flight the groups work on the others, so the
  hop is paid once per round trip whatever the depth. Across nodes the bytes sent downstream (and,
  in a closed loop, back to the first component) go over ``link_bytes_per_s`` on top;
* **independent work** (``Phase.concurrent``: e.g. the reference's and the critic's forward passes)
  on disjoint devices takes the longest group's time;
* **hybrids**: a phase with some groups time-sharing inside and space-sharing between them.

**Paced** work (a robot's control loop) takes the wall-clock time real time gives it
(``paced_per_unit_s``: the control period per step), on any device; it waits on the clock
rather than computing, so a component that time-shares its device works meanwhile: a group with
paced members takes the longer of its paced members' time and the sum of the others'.

Memory: every rank of every component stays resident, so the sum over the ranks on a device
(accelerators: their accelerator memory) or on a node (CPU slots share the node's memory; on
accelerators, the ranks' host memory) must fit.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

__all__ = ["Allocation", "Candidate", "NodeOf", "Phase", "Prediction", "WorkCost", "Workload", "memory_by_range",
           "memory_per_device", "peak_device_memory", "phase_seconds", "predict", "switch_seconds",
           "time_sharing_groups"]


@dataclass(frozen=True, kw_only=True)
class WorkCost:
    """Measured cost of one component's work in one phase (see the module docstring)."""

    per_unit_s: float
    fixed_s: float = 0.0
    comm_s: float = 0.0
    switch_s: float = 0.0
    """Offload + reload of the component, paid once per iteration when it time-shares a device."""
    memory_fixed_bytes: float = 0.0
    """A rank's resident bytes on its device: accelerator memory on accelerators, the process's
    host memory on CPU slots (which share their node's memory)."""
    memory_per_unit_bytes: float = 0.0
    host_memory_bytes: float = 0.0
    """A rank's resident host memory, checked against its node's memory where the devices are
    accelerators (on CPU slots ``memory_*`` are already host memory)."""
    memory_known: bool = True
    """False when no rank's peak could be read (a rank on another host, an unreadable process):
    the component's memory is then unknown, not zero, and the plan says it was not checked."""
    bytes_out_per_unit: float = 0.0
    """Bytes this component sends downstream per unit of work."""
    paced_per_unit_s: float = 0.0
    """Wall-clock seconds per unit that real time sets (a robot's control period per step): the
    work takes at least this long on any hardware. 0: the work is compute-bound."""

    @property
    def paced(self) -> bool:
        return self.paced_per_unit_s > 0

    def seconds(self, units: float, ranks: int) -> float:
        computed = self.fixed_s + self.per_unit_s * units / ranks + self.comm_s * math.log2(ranks)
        return max(computed, self.paced_per_unit_s * units / ranks)

    def memory_bytes(self, units: float, ranks: int) -> float:
        return self.memory_fixed_bytes + self.memory_per_unit_bytes * units / ranks

    def scaled(self, speedup: float = 1.0, memory: float = 1.0) -> WorkCost:
        """The same work on hardware ``speedup`` times faster, ``memory`` times the bytes per rank."""
        return WorkCost(per_unit_s=self.per_unit_s / speedup, fixed_s=self.fixed_s / speedup,
                        comm_s=self.comm_s / speedup, switch_s=self.switch_s / speedup,
                        memory_fixed_bytes=self.memory_fixed_bytes * memory,
                        memory_per_unit_bytes=self.memory_per_unit_bytes * memory,
                        host_memory_bytes=self.host_memory_bytes, memory_known=self.memory_known,
                        bytes_out_per_unit=self.bytes_out_per_unit, paced_per_unit_s=self.paced_per_unit_s)


@dataclass(frozen=True, kw_only=True)
class Phase:
    """Components that work in the same part of an iteration, in stream order (producer first)."""

    name: str
    components: tuple[str, ...]
    pipelined: bool = False
    """Whether the candidate's depth splits this phase into chunks (only streamed phases)."""
    concurrent: bool = False
    """The components work independently (no stream between them): disjoint groups take the
    longest group's time, not a pipeline's."""
    round_trips: int = 0
    """Times each chunk goes round the components when they form a closed loop (env -> rollout ->
    env: once per env step), each round trip a message there and back between processes when
    they are disaggregated. 0: a stream that passes once, through channels in every placement, so
    the hop is inside the components' measured times."""
    per_iteration: bool = False
    """The work does not grow with the batch (a weight sync moves one model whatever the batch):
    its costs are ``fixed_s`` plus the collective term, and a larger batch leaves them alone."""


@dataclass(frozen=True, kw_only=True)
class Workload:
    """What one iteration of a runner's config does: units of work, phases, measured costs."""

    runner: str
    phases: tuple[Phase, ...]
    units: Mapping[str, float]
    """Units of work per iteration of each component (env steps, decisions, samples)."""
    costs: Mapping[str, WorkCost]
    """Keyed ``"<phase>/<component>"``."""
    overhead_s: float = 0.0
    """The driver's own time per iteration (advantages, logging), placement-independent."""
    hop_s: float = 0.0
    """One message between processes of a streamed phase."""
    link_bytes_per_s: float = 12.5e9
    """Bandwidth between nodes, for bytes streamed across them."""
    offloads: bool = True
    """Whether the runner offloads and reloads a component that time-shares a device at each turn
    (then ``switch_s`` is paid); a runner that keeps every component resident pays none."""

    @property
    def components(self) -> tuple[str, ...]:
        seen: dict[str, None] = {}
        for phase in self.phases:
            seen.update(dict.fromkeys(phase.components))
        return tuple(seen)

    def cost(self, phase: str, component: str) -> WorkCost:
        return self.costs[f"{phase}/{component}"]


@dataclass(frozen=True, kw_only=True)
class Allocation:
    """A component's contiguous devices (or CPU slots) and its number of ranks over them."""

    first: int
    count: int
    ranks: int

    @property
    def devices(self) -> range:
        return range(self.first, self.first + self.count)

    def spec(self) -> str:
        """The placement spec ``place()`` takes: ``"3"``, ``"0-3"``, ``"0-1:0-3"``."""
        last = self.first + self.count - 1
        devices = str(self.first) if last == self.first else f"{self.first}-{last}"
        return devices if self.ranks == self.count else f"{devices}:0-{self.ranks - 1}"

    def overlaps(self, other: Allocation) -> bool:
        return self.first < other.first + other.count and other.first < self.first + self.count

    def load_factor(self) -> float:
        """Ranks stacked on each device (several ranks of one component on a device take turns)."""
        return max(1.0, self.ranks / self.count)


@dataclass(frozen=True, kw_only=True)
class Candidate:
    """One placement to predict: every component's allocation, and the pipeline depth."""

    allocations: Mapping[str, Allocation]
    depth: int = 1
    fixed_specs: Mapping[str, str] = field(default_factory=dict)
    """Components the search does not move (robots): their placement as the config gives it."""

    def placement(self) -> dict[str, str]:
        return {name: self.fixed_specs.get(name, a.spec()) for name, a in self.allocations.items()}

    def ranks(self) -> dict[str, int]:
        return {name: a.ranks for name, a in self.allocations.items()}


@dataclass(frozen=True, kw_only=True)
class Prediction:
    step_s: float
    phases: dict[str, float] = field(default_factory=dict)
    peak_memory_bytes: float = 0.0
    """The fullest device (accelerators) or node (CPU slots)."""


def time_sharing_groups(names: tuple[str, ...], allocations: Mapping[str, Allocation]) -> list[list[str]]:
    """Components connected by shared devices, in stream order of each group's first member."""
    groups: list[list[str]] = []
    for name in names:
        joined = [g for g in groups if any(allocations[name].overlaps(allocations[m]) for m in g)]
        merged = [m for g in joined for m in g] + [name]
        groups = [g for g in groups if g not in joined] + [merged]
    order = {name: i for i, name in enumerate(names)}
    return sorted(groups, key=lambda g: min(order[m] for m in g))


NodeOf = Callable[[int], int]
"""Global device (or CPU slot) -> node index; devices are numbered node by node, so a range's
nodes run from its first device's node to its last one's."""


def phase_seconds(workload: Workload, phase: Phase, candidate: Candidate, node_of: NodeOf | None = None) -> float:
    """One phase's predicted seconds (module docstring); ``node_of`` maps device -> node."""
    alloc = candidate.allocations
    times = {c: workload.cost(phase.name, c).seconds(workload.units[c], alloc[c].ranks) * alloc[c].load_factor()
             for c in phase.components}
    groups = time_sharing_groups(phase.components, alloc)
    paced = {c for c in phase.components if workload.cost(phase.name, c).paced}
    group_s = [max(sum(times[c] for c in g if c not in paced), max((times[c] for c in g if c in paced), default=0.0))
               for g in groups]
    if len(groups) == 1:
        return group_s[0]
    if phase.concurrent:
        return max(group_s)
    depth = candidate.depth if phase.pipelined else 1
    if phase.round_trips:  # a closed loop: each chunk goes round the groups round_trips times
        seconds = max(max(group_s), sum(group_s) / depth + workload.hop_s * phase.round_trips)
    else:
        seconds = sum(group_s) / depth + (depth - 1) / depth * max(group_s)
    return seconds + _cross_node_seconds(workload, phase, candidate, node_of)


def _nodes(allocation: Allocation, node_of: NodeOf) -> tuple[int, int]:
    return node_of(allocation.first), node_of(allocation.first + allocation.count - 1)


def _cross_node_seconds(workload: Workload, phase: Phase, candidate: Candidate, node_of: NodeOf | None) -> float:
    """Bytes each producer streams to a consumer on another node, over the link, per rank; in a
    closed loop (``round_trips``) the last component sends back to the first as well (the
    rollout's actions to the env)."""
    if node_of is None:
        return 0.0
    seconds = 0.0
    alloc = candidate.allocations
    names = phase.components
    legs = list(zip(names, names[1:]))
    if phase.round_trips and len(names) > 1:
        legs.append((names[-1], names[0]))
    for producer, consumer in legs:
        nodes_p, nodes_c = _nodes(alloc[producer], node_of), _nodes(alloc[consumer], node_of)
        if nodes_p != nodes_c or nodes_p[0] != nodes_p[1]:
            per_unit = workload.cost(phase.name, producer).bytes_out_per_unit
            seconds += per_unit * workload.units[producer] / alloc[producer].ranks / workload.link_bytes_per_s
    return seconds


def switch_seconds(workload: Workload, candidate: Candidate) -> float:
    """Offload + reload of every component that time-shares a device with another one."""
    if not workload.offloads:
        return 0.0
    alloc, total = candidate.allocations, 0.0
    names = workload.components
    for name in names:
        if any(other != name and alloc[name].overlaps(alloc[other]) for other in names):
            total += max(workload.cost(p.name, name).switch_s for p in workload.phases if name in p.components)
    return total


def memory_per_device(workload: Workload, candidate: Candidate, host: bool = False) -> dict[str, float]:
    """Resident bytes each component puts on each of its devices (its largest per-rank memory
    over its phases, times its ranks per device); ``host``: its host memory instead."""
    out = {}
    for name, a in candidate.allocations.items():
        costs = [workload.cost(p.name, name) for p in workload.phases if name in p.components]
        per_rank = max(c.host_memory_bytes if host else c.memory_bytes(workload.units[name], a.ranks) for c in costs)
        out[name] = per_rank * a.ranks / a.count
    return out


def peak_device_memory(workload: Workload, candidate: Candidate) -> float:
    """The fullest device's resident bytes: a sweep over the allocations' boundaries, so a plan of
    1,024 devices costs as much as one of 2."""
    per_device = memory_per_device(workload, candidate)
    allocations = candidate.allocations
    cuts = sorted({a.first for a in allocations.values()} | {a.first + a.count for a in allocations.values()})
    peak = 0.0
    for low in cuts[:-1]:
        peak = max(peak, sum(per_device[n] for n, a in allocations.items() if a.first <= low < a.first + a.count))
    return peak


def memory_by_range(workload: Workload, candidate: Candidate, ranges: Mapping[int, range],
                    host: bool = False) -> dict[int, float]:
    """Resident bytes per range of devices (e.g. the CPU slots of each node, which share its
    memory); ``host``: the ranks' host memory (a node's accelerators share its host memory)."""
    per_device = memory_per_device(workload, candidate, host)
    used = {}
    for key, block in ranges.items():
        total = 0.0
        for name, a in candidate.allocations.items():
            shared = min(block.stop, a.first + a.count) - max(block.start, a.first)
            total += per_device[name] * max(shared, 0)
        used[key] = total
    return used


def predict(workload: Workload, candidate: Candidate, node_of: NodeOf | None = None,
            cache: dict | None = None) -> Prediction:
    """Predicted iteration time of ``candidate`` and its fullest device's memory. ``cache``: a dict
    kept across calls with the same workload and ``node_of`` (a search), where a phase's seconds
    are looked up by what they depend on: its components' allocations and the depth."""
    missing = [c for c in workload.components if c not in candidate.allocations]
    if missing:
        raise ValueError(f"candidate places no {', '.join(missing)}; every component needs an allocation")
    if cache is None:
        phases = {p.name: phase_seconds(workload, p, candidate, node_of) for p in workload.phases}
    else:
        phases = {}
        alloc = candidate.allocations
        for p in workload.phases:
            key = (p.name, candidate.depth if p.pipelined else 1, *(alloc[c] for c in p.components))
            if key not in cache:
                cache[key] = phase_seconds(workload, p, candidate, node_of)
            phases[p.name] = cache[key]
    step = sum(phases.values()) + switch_seconds(workload, candidate) + workload.overhead_s
    return Prediction(step_s=step, phases=phases, peak_memory_bytes=peak_device_memory(workload, candidate))
