"""Search: every placement and pipeline depth worth trying on a cluster, ranked by predicted step time.

Candidates give each component a contiguous range of devices (CPU slots on a CPU-only cluster)
with one rank per device, so every placement is a spec ``place()`` accepts (``"0"``, ``"2-5"``):

* small pools (up to :data:`EXHAUSTIVE_DEVICES` devices): every range for every component, so
  every collocated, disaggregated and hybrid layout is tried;
* larger pools: components are split into groups that share a block (set partitions of the
  components, blocks side by side), block sizes from a grid (powers of two and eighths of the
  pool, the last block taking the rest), plus each layout with one component spanning every block
  (it time-shares with all the others, as a trainer collocated with streamed stages does);
* one component to place (the others fixed): every block of a grid size, aligned to its size.

For each layout the runner model lists the depths it can run and its rules (paired ranks,
divisibility); a candidate over memory (a device's, or a node's for CPU slots) is left out.
Components the model holds fixed (robots: ``RunnerModel.fixed``) keep the placement the config
gives them (:func:`fixed_allocation`), and so do components the config places itself beside
``auto`` ones (``placement.learner=auto``: :func:`pinned_allocation`, with their ranks); only the
others are laid out.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from itertools import product

from infinirl.runtime.inventory import ClusterInventory
from infinirl.scheduler.cost import Allocation, Candidate, Prediction, Workload, memory_by_range, predict
from infinirl.scheduler.workloads import RunnerModel

__all__ = ["EXHAUSTIVE_DEVICES", "PlanEntry", "candidate_layouts", "fixed_allocation", "fixed_placements",
           "pinned_allocation", "pool_of", "search"]

EXHAUSTIVE_DEVICES = 4


@dataclass(frozen=True, kw_only=True)
class PlanEntry:
    candidate: Candidate
    prediction: Prediction
    memory_bytes: float
    """The fullest device's (accelerators) or node's (CPU slots) resident bytes."""
    memory_limit_bytes: float

    @property
    def placement(self) -> dict[str, str]:
        return self.candidate.placement()

    @property
    def devices_used(self) -> int:
        """Distinct devices the placement holds (the union of its ranges)."""
        total, reach = 0, 0
        for a in sorted(self.candidate.allocations.values(), key=lambda a: a.first):
            end = a.first + a.count
            total += max(0, end - max(a.first, reach))
            reach = max(reach, end)
        return total


@dataclass(frozen=True, kw_only=True)
class Pool:
    """What device indices mean on a cluster: their count, where the nodes start, the memory limit."""

    size: int
    per_node: tuple[int, ...]
    on_cpu: bool
    memory_limit_bytes: float

    def node_of(self, device: int) -> int:
        for node, start in enumerate(self.starts):
            if device < start + self.per_node[node]:
                return node
        return len(self.per_node) - 1

    @property
    def starts(self) -> tuple[int, ...]:
        out, total = [], 0
        for count in self.per_node:
            out.append(total)
            total += count
        return tuple(out)

    def node_ranges(self) -> dict[int, range]:
        return {node: range(start, start + count) for node, (start, count) in enumerate(zip(self.starts,
                                                                                           self.per_node))}


def pool_of(inventory: ClusterInventory) -> Pool:
    """Accelerators (memory per device), or CPU slots (memory per node) on a CPU-only cluster."""
    if inventory.accelerator_kind is None:
        return Pool(size=inventory.num_cpu_slots, per_node=tuple(n.num_cpus for n in inventory.nodes), on_cpu=True,
                    memory_limit_bytes=float(min(n.memory_bytes for n in inventory.nodes)))
    memory = min(a.memory_bytes for n in inventory.nodes for a in n.accelerators)
    return Pool(size=inventory.num_accelerators, per_node=tuple(n.num_accelerators for n in inventory.nodes),
                on_cpu=False, memory_limit_bytes=float(memory))


def fixed_allocation(spec: str, pool: Pool) -> Allocation:
    """Where a fixed component's spec sits among the pool's devices, as one rank (its ranks work side by
    side, each on its own robot, so the model's units for it are one rank's): the devices or CPU slots
    it names (their span), the whole pool for ``all``, and past the pool's end for robots and nodes,
    which hold none of the pool's devices."""
    from infinirl.runtime.placement import parse_spec

    parsed = parse_spec(spec)
    if parsed.kind == "all":
        return Allocation(first=0, count=pool.size, ranks=1)
    if parsed.kind == "devices":
        first = min(parsed.indices)
        return Allocation(first=first, count=max(parsed.indices) - first + 1, ranks=1)
    return Allocation(first=pool.size, count=1, ranks=1)


def pinned_allocation(component: str, spec: str, pool: Pool) -> Allocation:
    """A component the config places itself beside ``auto`` ones, with its ranks: a contiguous
    range of the pool's devices (``"0"``, ``"2-5"``, ``"0-1:0-3"``); any other spec is a one-line
    ConfigError naming the key."""
    from infinirl.config import ConfigError
    from infinirl.runtime.placement import parse_spec

    parsed = parse_spec(spec, component)
    indices = sorted(parsed.indices) if parsed.kind == "devices" else []
    if not indices or indices != list(range(indices[0], indices[-1] + 1)) or indices[-1] >= pool.size:
        raise ConfigError(f"placement.{component}={spec!r}: beside components placed 'auto', give a contiguous "
                          f"range of this cluster's {pool.size} devices or CPU slots (e.g. '0', '0-1'), or 'auto'")
    return Allocation(first=indices[0], count=len(indices), ranks=parsed.num_processes or len(indices))


def fixed_placements(cfg, model: RunnerModel) -> dict[str, str]:
    """Components the search does not move: the model's (robots), then, when some components are
    ``auto``, those the config places itself (``infinirl plan`` of a config without ``auto`` searches
    every component)."""
    fixed = model.fixed(cfg)
    pinned = cfg.pinned_placement() if cfg.auto_placement else {}
    return {**fixed, **{name: spec for name, spec in pinned.items() if name not in fixed}}


# ----- layouts -----------------------------------------------------------------------------------


def _set_partitions(items: tuple[str, ...]) -> Iterator[list[list[str]]]:
    if not items:
        yield []
        return
    first, rest = items[0], items[1:]
    for partition in _set_partitions(rest):
        yield [[first], *partition]
        for i in range(len(partition)):
            yield partition[:i] + [[first, *partition[i]]] + partition[i + 1:]


def _size_grid(size: int) -> list[int]:
    powers = {1 << k for k in range(size.bit_length()) if 1 << k <= size}
    eighths = {size * k // 8 for k in range(1, 9) if size * k // 8 >= 1}
    return sorted(powers | eighths)


def _block_sizes(groups: int, size: int) -> Iterator[tuple[int, ...]]:
    """Sizes of ``groups`` blocks side by side: grid sizes, the last block taking the rest (or the
    largest power of two in it)."""
    grid = _size_grid(size)
    for head in product(grid, repeat=groups - 1):
        left = size - sum(head)
        if left < 1:
            continue
        for last in sorted({left, 1 << (left.bit_length() - 1)}):
            yield (*head, last)


def _exhaustive(components: tuple[str, ...], size: int) -> Iterator[dict[str, Allocation]]:
    ranges = [(first, count) for first in range(size) for count in range(1, size - first + 1)]
    for choice in product(ranges, repeat=len(components)):
        yield {c: Allocation(first=f, count=n, ranks=n) for c, (f, n) in zip(components, choice)}


def _structured(components: tuple[str, ...], size: int) -> Iterator[dict[str, Allocation]]:
    for partition in _set_partitions(components):
        for sizes in _block_sizes(len(partition), size):
            first, layout = 0, {}
            for group, count in zip(partition, sizes):
                for name in group:
                    layout[name] = Allocation(first=first, count=count, ranks=count)
                first += count
            yield layout
            if len(partition) > 1:
                for name in components:  # one component spanning every block
                    yield {**layout, name: Allocation(first=0, count=first, ranks=first)}


def _aligned_blocks(component: str, size: int) -> Iterator[dict[str, Allocation]]:
    """One component alone (the others fixed): every block of a grid size at a multiple of its size."""
    for count in _size_grid(size):
        for first in range(0, size - count + 1, count):
            yield {component: Allocation(first=first, count=count, ranks=count)}


def candidate_layouts(components: tuple[str, ...], size: int) -> Iterator[dict[str, Allocation]]:
    """Allocations to try on ``size`` devices (module docstring)."""
    if size < 1:
        raise ValueError("the cluster has no devices or CPU slots to place on")
    if size <= EXHAUSTIVE_DEVICES:
        return _exhaustive(components, size)
    return _aligned_blocks(components[0], size) if len(components) == 1 else _structured(components, size)


# ----- search ------------------------------------------------------------------------------------


def _memory(workload: Workload, candidate: Candidate, prediction: Prediction, pool: Pool) -> float:
    if not pool.on_cpu:
        return prediction.peak_memory_bytes
    return max(memory_by_range(workload, candidate, pool.node_ranges()).values(), default=0.0)


def search(cfg, model: RunnerModel, workload: Workload, inventory: ClusterInventory,
           limit: int | None = None) -> list[PlanEntry]:
    """Every valid candidate within memory, best predicted step time first (ties: fewer devices,
    then the placement's text, so the order is stable)."""
    pool = pool_of(inventory)
    robots = model.fixed(cfg)
    fixed = fixed_placements(cfg, model)
    pinned = {name: fixed_allocation(spec, pool) if name in robots else pinned_allocation(name, spec, pool)
              for name, spec in fixed.items()}
    movable = tuple(c for c in cfg.components() if c not in fixed)
    entries, seen = [], set()
    node_of = pool.node_of if len(pool.per_node) > 1 else None
    for placed in candidate_layouts(movable, pool.size):
        layout = {**pinned, **placed}
        ranks = {name: a.ranks for name, a in layout.items()}
        for depth in model.depths(cfg, ranks):
            candidate = Candidate(allocations=layout, depth=depth, fixed_specs=fixed)
            signature = (tuple(sorted(candidate.placement().items())), depth)
            if signature in seen or model.check(cfg, candidate) is not None:
                continue
            seen.add(signature)
            prediction = predict(workload, candidate, node_of)
            memory = _memory(workload, candidate, prediction, pool)
            if memory > pool.memory_limit_bytes:
                continue
            entries.append(PlanEntry(candidate=candidate, prediction=prediction, memory_bytes=memory,
                                     memory_limit_bytes=pool.memory_limit_bytes))
    entries.sort(key=lambda e: (round(e.prediction.step_s, 9), e.devices_used, sorted(e.placement.items()),
                                e.candidate.depth))
    return entries[:limit] if limit else entries
