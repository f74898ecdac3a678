"""Search: every placement and pipeline depth worth trying on a cluster, ranked by predicted step time.

Candidates give each component a contiguous range of devices (CPU slots on a CPU-only cluster)
with one rank per device, so every placement is a spec ``place()`` accepts (``"0"``, ``"2-5"``):

* every range for every component on the first :data:`EXHAUSTIVE_DEVICES` devices, so every
  collocated, disaggregated and hybrid layout there is tried and a larger pool never predicts
  worse than that part of it;
* on larger pools also: components split into groups that share a block (set partitions of the
  components), blocks side by side from device 0 (not necessarily filling the pool), sizes from a
  grid (powers of two and eighths of the pool), first with every member taking its whole block,
  then with each member taking any grid size of it; and each component spanning a grid-size
  prefix of the others' blocks past the first one (it time-shares with them, as a trainer
  collocated with a streamed stage does). Across nodes the blocks take every order; on one node
  disjoint blocks predict alike in any order, so they take one. At most :data:`MAX_LAYOUTS` of
  these: the finest grid within it is taken (:class:`Layouts`);
* one component to place (the others fixed): every block of a grid size, aligned to its size.

For each layout the runner model lists the depths it can run and its rules (paired ranks,
divisibility); a candidate over memory (a device's accelerator memory and its node's host memory,
or a node's memory for CPU slots) is left out. What is left out is counted by reason
(:class:`SearchResult`), so an empty plan says why.
Components the model holds fixed (robots: ``RunnerModel.fixed``) keep the placement the config
gives them (:func:`fixed_allocation`), and so do components the config places itself beside
``auto`` ones (``placement.learner=auto``: :func:`pinned_allocation`, with their ranks); only the
others are laid out.
"""

from __future__ import annotations

from bisect import bisect_right
from collections.abc import Iterator
from dataclasses import dataclass
from functools import cached_property
from itertools import accumulate, permutations, product

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
    """A device's memory (accelerators) or a node's (CPU slots): the smallest of the cluster's."""
    host_limit_bytes: float = float("inf")
    """A node's host memory, where the devices are accelerators (the smallest node's)."""

    def node_of(self, device: int) -> int:
        return min(bisect_right(self.starts, device) - 1, len(self.per_node) - 1)

    @cached_property
    def starts(self) -> tuple[int, ...]:
        return tuple(accumulate(self.per_node, initial=0))[:-1]

    @cached_property
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
                on_cpu=False, memory_limit_bytes=float(memory),
                host_limit_bytes=float(min(n.memory_bytes for n in inventory.nodes if n.accelerators)))


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

MAX_LAYOUTS = 4_000
"""Structured layouts tried at most (past the exhaustive ones of the first
:data:`EXHAUSTIVE_DEVICES` devices). Their number grows as (grid sizes) ** components, so the
search takes the finest size grid (:func:`_grids`) whose layouts number at most this: on one node
of 8 or 16 devices three components keep every size, on 64 or 1,024 GPUs over nodes (where every
order of the blocks counts) the sizes are powers of two or of four. ``infinirl plan`` prints the
grid when it is not the finest."""

Span = tuple[int, int]
"""(first device, device count) of one component; one rank per device."""


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


def _grids(size: int) -> list[list[int]]:
    """Block and member sizes, finest first: powers of two and eighths of the pool, powers of two,
    powers of four, then one device or all (each with the whole pool)."""
    grids = [_size_grid(size), sorted({1 << k for k in range(size.bit_length())} | {size}),
             sorted({4 ** k for k in range(size.bit_length()) if 4 ** k <= size} | {size}), sorted({1, size})]
    return [g for i, g in enumerate(grids) if i == 0 or g != grids[i - 1]]


def _exhaustive(components: tuple[str, ...], size: int) -> Iterator[dict[str, Span]]:
    ranges = [(first, count) for first in range(size) for count in range(1, size - first + 1)]
    for choice in product(ranges, repeat=len(components)):
        yield dict(zip(components, choice))


def _blocks(order: tuple[tuple[str, ...], ...], first: int, size: int, grid: list[int],
            prefixes: bool) -> Iterator[dict[str, Span]]:
    """Blocks side by side from ``first``, one per group of ``order``. Every member starts at its
    block's first device and takes the block's grid size, or (``prefixes``) any grid size, the
    block then being as wide as its widest member. The blocks need not fill the pool."""
    if not order:
        yield {}
        return
    group, rest = order[0], order[1:]
    sizes = [g for g in grid if g <= size - first]
    counts_of = product(sizes, repeat=len(group)) if prefixes and len(group) > 1 else (
        (s,) * len(group) for s in sizes)
    for counts in counts_of:
        head = {name: (first, count) for name, count in zip(group, counts)}
        for tail in _blocks(rest, first + max(counts), size, grid, prefixes):
            yield {**head, **tail}


def _orders(components: tuple[str, ...], every_order: bool) -> Iterator[tuple[tuple[str, ...], ...]]:
    """The set partitions of ``components``, each in every order of its blocks or in one."""
    for partition in _set_partitions(components):
        blocks = tuple(map(tuple, partition))
        yield from permutations(blocks) if every_order else (blocks,)


def _structured(components: tuple[str, ...], size: int, grid: list[int],
                every_order: bool) -> Iterator[dict[str, Span]]:
    """Groups of components sharing a block, blocks side by side, sizes from ``grid``; then each
    component spanning a grid-size prefix of the others' blocks, past the first block (it
    time-shares with them, as a trainer collocated with streamed stages does); first with every
    member taking its whole block, then with members taking any grid size of it.

    Disjoint blocks predict alike in any order on one node (nothing crosses a node, and every
    device and the node hold the same ranks), so without ``every_order`` the blocks take one
    order; a spanning component overlaps the first blocks only, so its layouts take every order."""
    for prefixes in (False, True):  # whole blocks first: the coarser layouts
        for order in _orders(components, every_order):
            yield from _blocks(order, 0, size, grid, prefixes)
        for spanner in components if len(components) > 1 else ():
            others = tuple(c for c in components if c != spanner)
            for order in _orders(others, True):
                if len(order) < 2:
                    continue  # one block: the spanner is one of its members (above)
                for layout in _blocks(order, 0, size, grid, prefixes):
                    width = max(f + n for f, n in layout.values())
                    head = max(n for f, n in layout.values() if f == 0)
                    for count in sorted({g for g in grid if head < g < width} | {width}):
                        yield {**layout, spanner: (0, count)}


def _aligned_blocks(component: str, size: int) -> Iterator[dict[str, Span]]:
    """One component alone (the others fixed): every block of a grid size at a multiple of its size."""
    for count in _size_grid(size):
        for first in range(0, size - count + 1, count):
            yield {component: (first, count)}


class Layouts:
    """The layouts to try on ``size`` devices (module docstring), each once; iterate it. After
    iterating, ``grid``: the sizes the structured layouts took (:data:`MAX_LAYOUTS`), ``fine``:
    whether that is the finest grid, ``truncated``: whether even the coarsest gave more than
    :data:`MAX_LAYOUTS` (then only the first ones are tried), ``count``: layouts yielded."""

    def __init__(self, components: tuple[str, ...], size: int, every_order: bool = True,
                 limit: int = MAX_LAYOUTS):
        if size < 1:
            raise ValueError("the cluster has no devices or CPU slots to place on")
        self.components, self.size, self.every_order, self.limit = components, size, every_order, limit
        self.grid: list[int] = []
        self.fine = True
        self.truncated = False
        self.count = 0

    def _structured(self, seen: set[tuple]) -> list[tuple]:
        """The structured layouts of the finest grid that gives at most ``limit`` new ones."""
        components, size = self.components, self.size
        if size <= EXHAUSTIVE_DEVICES:
            return []
        if len(components) == 1:
            self.grid = _size_grid(size)
            keys = ((layout[components[0]],) for layout in _aligned_blocks(components[0], size))
            return list(dict.fromkeys(key for key in keys if key not in seen))
        grids = _grids(size)
        for i, grid in enumerate(grids):
            found: dict[tuple, None] = {}
            for layout in _structured(components, size, grid, self.every_order):
                key = tuple(layout[c] for c in components)
                if key not in seen:
                    found[key] = None
                    if len(found) > self.limit:
                        break
            self.grid, self.fine = grid, i == 0
            if len(found) <= self.limit:
                return list(found)
        self.truncated = True
        return list(found)[:self.limit]

    def __iter__(self) -> Iterator[dict[str, Allocation]]:
        components = self.components
        seen: set[tuple] = set()
        self.count, self.truncated = 0, False
        for layout in _exhaustive(components, min(self.size, EXHAUSTIVE_DEVICES)):
            key = tuple(layout[c] for c in components)
            seen.add(key)
            self.count += 1
            yield self._allocations(key)
        for key in self._structured(seen):
            self.count += 1
            yield self._allocations(key)

    def _allocations(self, key: tuple) -> dict[str, Allocation]:
        return {c: Allocation(first=f, count=n, ranks=n) for c, (f, n) in zip(self.components, key)}


def candidate_layouts(components: tuple[str, ...], size: int, every_order: bool = True) -> Layouts:
    """Allocations to try on ``size`` devices (module docstring), each once."""
    return Layouts(components, size, every_order)


# ----- search ------------------------------------------------------------------------------------

class SearchResult(list):
    """:func:`search`'s candidates, best first (a list of :class:`PlanEntry`), with what the search
    left out: ``rejected`` (the reason -> candidates it ruled out), ``layouts`` tried, ``grid``
    (the sizes the structured layouts took when a finer grid gave more than :data:`MAX_LAYOUTS`,
    else None), ``truncated`` (even the coarsest grid gave more: only the first were tried),
    ``pinned`` (the specs kept as written: component -> (spec, ranks)) and ``unknown_memory``
    (components whose memory was not measured, so not checked)."""

    def __init__(self, entries=(), *, rejected: dict[str, int] | None = None, layouts: int = 0,
                 grid: list[int] | None = None, truncated: bool = False,
                 pinned: dict[str, tuple[str, int]] | None = None, unknown_memory: tuple[str, ...] = ()):
        super().__init__(entries)
        self.rejected = dict(rejected or {})
        self.layouts = layouts
        self.grid = grid
        self.truncated = truncated
        self.pinned = dict(pinned or {})
        self.unknown_memory = unknown_memory

    def why_empty(self) -> str:
        """Why no candidate is left: the reason that ruled out the most, and the specs kept as written."""
        if not self.rejected:
            return "no layout to try"
        reason, count = max(self.rejected.items(), key=lambda item: item[1])
        total = sum(self.rejected.values())
        text = f"{reason} ({count} of {total} candidates)"
        kept = [f"placement.{name}={spec} ({ranks} rank{'s' if ranks != 1 else ''})"
                for name, (spec, ranks) in self.pinned.items()]
        return text + (f", with {', '.join(kept)} kept as written" if kept else "")


def _gib(value: float) -> str:
    return f"{value / 2**30:.2f} GiB"


def search(cfg, model: RunnerModel, workload: Workload, inventory: ClusterInventory,
           limit: int | None = None) -> SearchResult:
    """Every valid candidate within memory, best predicted step time first (ties: fewer devices,
    then the placement's text, so the order is stable), with the reasons for those left out."""
    pool = pool_of(inventory)
    robots = model.fixed(cfg)
    fixed = fixed_placements(cfg, model)
    pinned = {name: fixed_allocation(spec, pool) if name in robots else pinned_allocation(name, spec, pool)
              for name, spec in fixed.items()}
    movable = tuple(c for c in cfg.components() if c not in fixed)
    entries: list[PlanEntry] = []
    rejected: dict[str, int] = {}
    over: dict[str, float] = {}  # the least memory a rejected candidate needed, per limit

    def reject(reason: str) -> None:
        rejected[reason] = rejected.get(reason, 0) + 1

    cache: dict = {}
    multi_node = len(pool.per_node) > 1
    node_of = pool.node_of if multi_node else None
    layouts = candidate_layouts(movable, pool.size, every_order=multi_node)
    for placed in layouts:
        layout = {**pinned, **placed}
        ranks = {name: a.ranks for name, a in layout.items()}
        depths = model.depths(cfg, ranks)
        if not depths:
            reject(model.no_depth(cfg, ranks))
            continue
        for depth in depths:
            candidate = Candidate(allocations=layout, depth=depth, fixed_specs=fixed)
            why = model.check(cfg, candidate)
            if why is not None:
                reject(why)
                continue
            prediction = predict(workload, candidate, node_of, cache)
            memory, host = _memory(workload, candidate, prediction, pool)
            if memory > pool.memory_limit_bytes:
                what = "a node's memory" if pool.on_cpu else "a device's memory"
                over[what] = min(over.get(what, float("inf")), memory)
                reject(what)
                continue
            if host > pool.host_limit_bytes:
                over["a node's host memory"] = min(over.get("a node's host memory", float("inf")), host)
                reject("a node's host memory")
                continue
            entries.append(PlanEntry(candidate=candidate, prediction=prediction, memory_bytes=memory,
                                     memory_limit_bytes=pool.memory_limit_bytes))
    entries.sort(key=lambda e: (round(e.prediction.step_s, 9), e.devices_used, sorted(e.placement.items()),
                                e.candidate.depth))
    limits = {"a node's memory": pool.memory_limit_bytes, "a device's memory": pool.memory_limit_bytes,
              "a node's host memory": pool.host_limit_bytes}
    reasons = {(f"over {what}: the smallest needs {_gib(over[what])} of {_gib(limits[what])}"
                if what in over else what): count for what, count in rejected.items()}
    unknown = tuple(sorted({key.split("/", 1)[1] for key, cost in workload.costs.items() if not cost.memory_known}))
    return SearchResult(entries[:limit] if limit else entries, rejected=reasons, layouts=layouts.count,
                        grid=None if layouts.fine else layouts.grid, truncated=layouts.truncated,
                        pinned={name: (spec, pinned[name].ranks) for name, spec in fixed.items() if name not in robots},
                        unknown_memory=unknown)


def _memory(workload: Workload, candidate: Candidate, prediction: Prediction, pool: Pool) -> tuple[float, float]:
    """The fullest device's (accelerators) or node's (CPU slots) resident bytes, and on
    accelerators the fullest node's host bytes (0 on CPU slots, where the first is host memory)."""
    if pool.on_cpu:
        return max(memory_by_range(workload, candidate, pool.node_ranges).values(), default=0.0), 0.0
    if not any(cost.host_memory_bytes for cost in workload.costs.values()):
        return prediction.peak_memory_bytes, 0.0
    host = memory_by_range(workload, candidate, pool.node_ranges, host=True)
    return prediction.peak_memory_bytes, max(host.values(), default=0.0)
