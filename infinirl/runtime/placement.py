"""Placement: which node, devices and robot each rank of each component gets.

A pure function of a :class:`~infinirl.runtime.inventory.ClusterInventory` and a spec such as
``{"actor": "0-3", "rollout": "4-7", "reward": "node:0"}``; no Ray calls, so every case is unit
tested. ``Cluster`` builds the inventory; ``WorkerGroup`` launches one actor per
:class:`RankPlacement` and adds ``MASTER_ADDR``/``MASTER_PORT`` itself (rank 0 binds the port, see ``rendezvous``).

Spec grammar (one entry per component; whitespace ignored, keywords case-insensitive; an int ``4``
means ``"4"``)::

    spec      := devices [":" ranks] | "all" [":" ranks] | "node:" indices [":" ranks] | "robot:" indices
    indices   := item ("," item)*          item := INT | INT "-" INT      (inclusive, ascending)
    ranks     := "0" | "0-" INT            the component's process ranks: always 0..N-1

* ``"0-3"``, ``"0,2,5"``, ``"4"``: one process per listed global device, ranks in listed order.
* ``"0-1:0-7"``: 8 processes over devices 0-1, evenly and contiguously (ranks 0-3 on device 0,
  4-7 on device 1). N processes on D devices needs N to be a multiple of D (at most
  ``max_procs_per_device`` per device) or a divisor of D: ``"0-3:0-1"`` gives 2 processes with 2
  devices each (e.g. a tensor-parallel inference engine); a process's devices must share a node.
* ``"all"``: one process per device of the cluster (``"all:0-15"`` spreads 16 like above).
* ``"node:2"``: one device-less process on node 2; ``"node:0-1"`` one per node; ``"node:2:0-3"``
  4 processes on node 2 (the part after the node list is a rank range, as for devices, so the
  grammar reads the same everywhere); ``"node:0-1:0-3"`` 2 per node.
* ``"robot:0-1"``: one process per robot (global robot index), on the robot's node, with the robot
  attached to the rank. Robots are exclusive hardware, so there is no rank range here.

CPU-only clusters (no accelerators): device indices name **CPU slots** instead, numbered across
nodes from each node's ``num_cpus`` (node 0 has slots 0..c0-1, node 1 the next ones, ...). So
``"actor": "0-1"`` on a 2-CPU node is two ranks on node 0 with ``cpu_slots`` (0,) and (1,) and no
visible devices. The same config then runs on a laptop and on a GPU cluster.

Visible devices: on an accelerator cluster every rank gets ``CUDA_VISIBLE_DEVICES`` (or the kind's
variable, see :data:`VISIBLE_DEVICES_VARIABLE`) with its *local* device indices (numbered as the
node's processes see them: its host maps them through the mask the node was started with, see
:func:`physical_visible_devices`); device-less ranks
(node- and robot-placed) get it set to ``""`` so they cannot grab GPU 0 by accident. On CPU-only
clusters the variable is left out: there is nothing to hide and nothing to select.

Collocated vs disaggregated: a component *contends* for its devices (or CPU slots) and robots.
Two components are collocated when they contend for at least one common resource (they must take
turns: offload/reload under a device lock), disaggregated otherwise (they run side by side and
stream through channels). Node-placed components hold nothing exclusive, so they are
disaggregated from every other component and are left out of the plan-wide :attr:`~PlacementPlan.mode`.
"""

from __future__ import annotations

import difflib
import re
from collections.abc import Collection, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from itertools import combinations
from typing import Literal

from infinirl.runtime.inventory import ClusterInventory, Robot

Relation = Literal["collocated", "disaggregated"]
Mode = Literal["collocated", "disaggregated", "hybrid"]
SpecKind = Literal["devices", "all", "nodes", "robots"]

# The variable that restricts a process to its devices, per accelerator kind. Unknown kinds fall
# back to "<KIND>_VISIBLE_DEVICES", the convention most vendors follow.
VISIBLE_DEVICES_VARIABLE = {
    "cuda": "CUDA_VISIBLE_DEVICES",
    "rocm": "HIP_VISIBLE_DEVICES",
    "npu": "ASCEND_RT_VISIBLE_DEVICES",
    "xpu": "ZE_AFFINITY_MASK",
}



def is_visible_devices_variable(name: str) -> bool:
    return name in VISIBLE_DEVICES_VARIABLE.values() or name.endswith("_VISIBLE_DEVICES")


def physical_visible_devices(variable: str, local: str, inherited: str | None) -> str:
    """The value of ``variable`` that selects the rank's ``local`` devices (comma-separated indices
    as placement writes them) in a process that started with ``inherited`` as that variable.

    Discovery numbers a node's devices as its processes see them, i.e. under the mask the node was
    started with (``CUDA_VISIBLE_DEVICES=4,5,6,7``: local 0 is physical 4); a rank's mask has to
    name the same devices, so local indices are mapped through the inherited one."""
    if not local or inherited is None:
        return local
    mask = [entry.strip() for entry in inherited.split(",") if entry.strip()]
    mapped = []
    for index in local.split(","):
        position = int(index)
        if not 0 <= position < len(mask):
            raise ValueError(
                f"this rank was placed on local device {position}, but its process sees {len(mask)} device(s) "
                f"({variable}={inherited!r} on its node); start every node with the same {variable} it had when "
                "the cluster took its inventory, or refresh the inventory")
        mapped.append(mask[position])
    return ",".join(mapped)


ACCEPTED_FORMS = (
    "'0-3' (one process per device 0..3), '0,2,5', '4', "
    "'0-1:0-7' (8 processes over devices 0-1), '0-3:0-1' (2 processes with 2 devices each), "
    "'all', 'all:0-15', 'node:2', 'node:0-1', 'node:2:0-3' (4 processes on node 2), 'robot:0-1'"
)

_INDEX_ITEM = re.compile(r"^(\d+)(?:-(\d+))?$")


class PlacementError(ValueError):
    """A placement spec that cannot be satisfied; the message names the component and the resource."""


# ----- parsing ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ParsedSpec:
    """One component's spec, syntax-checked but not yet matched against a cluster.

    ``indices`` are global device (or CPU slot), node or robot indices in the order written; empty
    for ``all``. ``num_processes`` is None when the spec means "one per listed resource".
    """

    kind: SpecKind
    indices: tuple[int, ...]
    num_processes: int | None
    text: str


def _prefix(component: str | None) -> str:
    return f"placement for {component!r}: " if component is not None else "placement: "


def _malformed(component: str | None, text: str, why: str) -> PlacementError:
    return PlacementError(f"{_prefix(component)}cannot parse {text!r} ({why}); accepted forms: {ACCEPTED_FORMS}")


def _parse_indices(component: str | None, text: str, part: str, what: str) -> tuple[int, ...]:
    if not part:
        raise _malformed(component, text, f"missing {what} list")
    indices: list[int] = []
    for item in part.split(","):
        match = _INDEX_ITEM.match(item)
        if match is None:
            raise _malformed(component, text, f"{item!r} is not an index or an 'a-b' range")
        low = int(match.group(1))
        high = int(match.group(2)) if match.group(2) is not None else low
        if high < low:
            raise _malformed(component, text, f"range {item!r} is descending; write '{high}-{low}'")
        indices.extend(range(low, high + 1))
    repeated = sorted({i for i in indices if indices.count(i) > 1})
    if repeated:
        raise _malformed(component, text, f"{what} {_format_indices(repeated)} listed more than once")
    return tuple(indices)


def _parse_ranks(component: str | None, text: str, part: str) -> int:
    """Process ranks are always 0..N-1, so only '0' or '0-M' are meaningful; return N."""
    match = _INDEX_ITEM.match(part)
    if match is None:
        raise _malformed(component, text, f"process ranks {part!r} must be '0' or a range '0-N'")
    low = int(match.group(1))
    high = int(match.group(2)) if match.group(2) is not None else low
    if low != 0 or high < low:
        raise PlacementError(
            f"{_prefix(component)}process ranks {part!r} in {text!r} must be a range starting at 0 "
            f"(a component's ranks are 0..N-1); for 4 processes write ':0-3'"
        )
    return high + 1


def parse_spec(value: str | int, component: str | None = None) -> ParsedSpec:
    """Parse one spec value (see the module docstring for the grammar); ``component`` names errors."""
    if isinstance(value, bool) or not isinstance(value, (str, int)):
        raise PlacementError(
            f"{_prefix(component)}spec must be a string or int, got {type(value).__name__} {value!r}; "
            f"accepted forms: {ACCEPTED_FORMS}"
        )
    text = "".join(str(value).split()).lower()
    if not text:
        raise _malformed(component, str(value), "empty spec")
    parts = text.split(":")
    head = parts[0]
    if head == "all":
        kind: SpecKind = "all"
        indices: tuple[int, ...] = ()
        rest = parts[1:]
    elif head in ("node", "robot"):
        if len(parts) < 2:
            raise _malformed(component, text, f"'{head}:' must be followed by {head} indices")
        kind = "nodes" if head == "node" else "robots"
        indices = _parse_indices(component, text, parts[1], head)
        rest = parts[2:]
        if kind == "robots" and rest:
            raise _malformed(
                component, text, "robot placements take exactly one process per robot; drop the ':ranks' part"
            )
    else:
        kind = "devices"
        indices = _parse_indices(component, text, head, "device")
        rest = parts[1:]
    if len(rest) > 1:
        raise _malformed(component, text, "too many ':' separators")
    num_processes = _parse_ranks(component, text, rest[0]) if rest else None
    return ParsedSpec(kind=kind, indices=indices, num_processes=num_processes, text=text)


def resized_spec(value: str | int, num_processes: int, component: str | None = None) -> str:
    """The spec that places ``num_processes`` ranks on the resources ``value`` names (online scaling):
    ``resized_spec("0", 2)`` is ``"0:0-1"``, ``resized_spec("node:1", 3)`` is ``"node:1:0-2"``.

    Robot placements cannot be resized: a robot is exclusive hardware with one rank each."""
    if isinstance(num_processes, bool) or not isinstance(num_processes, int) or num_processes < 1:
        raise PlacementError(f"{_prefix(component)}a component needs at least 1 process, got {num_processes!r}")
    parsed = parse_spec(value, component)
    ranks = "0" if num_processes == 1 else f"0-{num_processes - 1}"
    if parsed.kind == "robots":
        raise PlacementError(f"{_prefix(component)}{parsed.text!r} gives one process per robot; a robot-placed "
                             "component cannot change its number of ranks")
    if parsed.kind == "all":
        return f"all:{ranks}"
    where = _format_indices(parsed.indices)
    return f"node:{where}:{ranks}" if parsed.kind == "nodes" else f"{where}:{ranks}"


# ----- results ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class RankPlacement:
    """Where one rank runs and the environment it starts with.

    ``global_devices``/``local_devices`` are accelerator indices (empty on CPU-only clusters);
    ``cpu_slots`` are global CPU slot indices, used only on CPU-only clusters.
    """

    component: str
    rank: int
    world_size: int
    node_index: int
    node_id: str
    node_ip: str
    local_devices: tuple[int, ...]
    global_devices: tuple[int, ...]
    cpu_slots: tuple[int, ...]
    robot: Robot | None
    env_vars: dict[str, str] = field(default_factory=dict, hash=False)

    @property
    def contended_resources(self) -> frozenset[tuple[str, object]]:
        """The exclusive things this rank holds; sharing any of them with another rank means taking turns."""
        held: set[tuple[str, object]] = {("device", d) for d in self.global_devices}
        held |= {("cpu_slot", s) for s in self.cpu_slots}
        if self.robot is not None:
            held.add(("robot", self.robot.name))
        return frozenset(held)


@dataclass(frozen=True)
class PlacementPlan:
    """Every component's ranks, in spec order, plus queries the runners and logs need."""

    inventory: ClusterInventory
    components: dict[str, tuple[RankPlacement, ...]] = field(hash=False)

    def with_component(self, component: str, ranks: tuple[RankPlacement, ...]) -> "PlacementPlan":
        """This plan with ``component``'s ranks replaced (a component scaled while the job runs)."""
        if component not in self.components:
            raise PlacementError(f"placement has no component {component!r}; it has {', '.join(self.components)}")
        return PlacementPlan(inventory=self.inventory, components={**self.components, component: tuple(ranks)})

    def ranks(self, component: str) -> tuple[RankPlacement, ...]:
        if component not in self.components:
            raise PlacementError(
                f"plan has no component {component!r}; components: {', '.join(self.components) or '(none)'}"
            )
        return self.components[component]

    def world_size(self, component: str) -> int:
        return len(self.ranks(component))

    def devices_of(self, component: str) -> tuple[int, ...]:
        """Sorted global devices the component uses (CPU slots on a CPU-only cluster)."""
        used = {d for r in self.ranks(component) for d in (r.global_devices or r.cpu_slots)}
        return tuple(sorted(used))

    def robots_of(self, component: str) -> tuple[Robot, ...]:
        return tuple(r.robot for r in self.ranks(component) if r.robot is not None)

    def components_on_device(self, global_device: int) -> tuple[str, ...]:
        """Components with a rank on this global device (CPU slot on a CPU-only cluster), in spec order."""
        pool_size, label = _device_pool(self.inventory)
        if not 0 <= global_device < pool_size:
            raise PlacementError(f"{label} {global_device} does not exist ({_pool_summary(self.inventory)})")
        return tuple(name for name in self.components if global_device in self.devices_of(name))

    def _holds(self, component: str) -> frozenset[tuple[str, object]]:
        return frozenset().union(*(r.contended_resources for r in self.ranks(component)))

    def relation(self, a: str, b: str) -> Relation:
        """'collocated' if ``a`` and ``b`` contend for a common device, CPU slot or robot, else 'disaggregated'.

        A component is collocated with itself.
        """
        holds_a, holds_b = self._holds(a), self._holds(b)
        if a == b or holds_a & holds_b:
            return "collocated"
        return "disaggregated"

    @property
    def mode(self) -> Mode:
        """Execution mode of the whole plan, over components that hold devices, CPU slots or robots.

        All such pairs collocated -> 'collocated'; all disaggregated -> 'disaggregated'; a mix ->
        'hybrid'. Fewer than two such components -> 'collocated' (nothing runs side by side on
        separate hardware). Node-placed components are ignored: they never take turns.
        """
        contending = [name for name in self.components if self._holds(name)]
        relations = {self.relation(a, b) for a, b in combinations(contending, 2)}
        if not relations or relations == {"collocated"}:
            return "collocated"
        if relations == {"disaggregated"}:
            return "disaggregated"
        return "hybrid"

    def describe(self) -> str:
        """A table of every rank, for logs: where it runs and what it holds."""
        on_cpu = self.inventory.accelerator_kind is None
        header = ("component", "rank", "node", "ip", "cpu slots" if on_cpu else "devices", "local", "robot")
        rows = [header]
        for name, ranks in self.components.items():
            for r in ranks:
                held = r.cpu_slots if on_cpu else r.global_devices
                rows.append((
                    name,
                    f"{r.rank}/{r.world_size}",
                    str(r.node_index),
                    r.node_ip,
                    _format_indices(held) or "-",
                    "-" if on_cpu else (",".join(map(str, r.local_devices)) or "-"),
                    r.robot.name if r.robot is not None else "-",
                ))
        widths = [max(len(row[i]) for row in rows) for i in range(len(header))]
        lines = [f"placement ({self.mode}) on {_cluster_label(self.inventory)}"]
        lines += ["  ".join(cell.ljust(w) for cell, w in zip(row, widths)).rstrip() for row in rows]
        return "\n".join(lines)


# ----- placing ------------------------------------------------------------------------------------


def _count(n: int, singular: str, plural: str | None = None) -> str:
    """'1 device', '3 devices': messages read as sentences."""
    return f"{n} {singular if n == 1 else (plural or singular + 's')}"


def _format_indices(indices: Iterable[int]) -> str:
    """[0,1,2,3,5] -> '0-3,5': compact and in the spec's own syntax."""
    values = sorted(set(indices))
    pieces: list[str] = []
    start = 0
    for i in range(1, len(values) + 1):
        if i == len(values) or values[i] != values[i - 1] + 1:
            low, high = values[start], values[i - 1]
            pieces.append(str(low) if low == high else f"{low}-{high}")
            start = i
    return ",".join(pieces)


def _device_pool(inventory: ClusterInventory) -> tuple[int, str]:
    """Size and name of what device indices refer to: accelerators, or CPU slots on CPU-only clusters."""
    if inventory.accelerator_kind is None:
        return inventory.num_cpu_slots, "CPU slot"
    return inventory.num_accelerators, "device"


def _cluster_label(inventory: ClusterInventory) -> str:
    """'2 nodes, 8 cuda devices' or '1 node, 2 CPU slots (CPU-only)': the header of describe()."""
    nodes = f"{inventory.num_nodes} node{'s' if inventory.num_nodes != 1 else ''}"
    robots = f", {inventory.num_robots} robots" if inventory.num_robots else ""
    if inventory.accelerator_kind is None:
        return f"{nodes}, {inventory.num_cpu_slots} CPU slots (CPU-only){robots}"
    return f"{nodes}, {inventory.num_accelerators} {inventory.accelerator_kind} devices{robots}"


def _pool_summary(inventory: ClusterInventory) -> str:
    nodes = f"{inventory.num_nodes} node{'s' if inventory.num_nodes != 1 else ''}"
    kind = inventory.accelerator_kind
    if kind is None:
        n = inventory.num_cpu_slots
        listed = f": {_format_indices(range(n))}" if n else ""
        return f"cluster has {n} CPU slots{listed} on {nodes}; on a CPU-only cluster device indices are CPU slots"
    n = inventory.num_accelerators
    return f"cluster has {n} {kind} devices: {_format_indices(range(n))}"


def _check_exist(component: str, indices: Sequence[int], size: int, label: str, summary: str) -> None:
    for index in indices:
        if index >= size:
            raise PlacementError(f"placement for {component!r}: {label} {index} does not exist ({summary})")


def _split(
    component: str,
    indices: Sequence[int],
    num_processes: int,
    unit: str,
    max_per_unit: int | None,
    may_share_units: bool,
) -> list[tuple[int, ...]]:
    """Give each of ``num_processes`` ranks its share of ``indices``: contiguous, even, in order.

    More processes than units: each unit gets the same number (at most ``max_per_unit``). Fewer:
    each process gets the same number of units, if ``may_share_units`` (devices yes, nodes no).
    """
    count = len(indices)
    where = f"{component!r}: {_count(num_processes, 'process', 'processes')}"
    units = f"{_count(count, unit)} ({_format_indices(indices)})"
    if num_processes >= count:
        if num_processes % count:
            hint = f", or a divisor of {count} to give each process several {unit}s" if may_share_units else ""
            raise PlacementError(
                f"placement for {where} cannot be spread evenly over {units}; "
                f"use a multiple of {count} processes{hint}"
            )
        per_unit = num_processes // count
        if max_per_unit is not None and per_unit > max_per_unit:
            raise PlacementError(
                f"placement for {where} on {units} puts {per_unit} on each {unit}, more than "
                f"max_procs_per_device={max_per_unit}; use more {unit}s or fewer processes"
            )
        return [(indices[rank // per_unit],) for rank in range(num_processes)]
    if not may_share_units:
        raise PlacementError(
            f"placement for {where} cannot cover {units}; a process runs on one {unit}, "
            f"so use at least one per {unit}"
        )
    if count % num_processes:
        raise PlacementError(
            f"placement for {where} cannot share {units} evenly; "
            f"use a divisor or a multiple of {count} processes"
        )
    width = count // num_processes
    return [tuple(indices[rank * width : (rank + 1) * width]) for rank in range(num_processes)]


@dataclass(frozen=True)
class _Draft:
    """A rank before its node-local numbering and env vars are known."""

    node_index: int
    global_devices: tuple[int, ...] = ()
    local_devices: tuple[int, ...] = ()
    cpu_slots: tuple[int, ...] = ()
    robot: Robot | None = None


def _draft_device_ranks(
    component: str, parsed: ParsedSpec, inventory: ClusterInventory, max_procs: int
) -> list[_Draft]:
    on_cpu = inventory.accelerator_kind is None
    locations = inventory.cpu_slot_locations if on_cpu else inventory.device_locations
    size, label = _device_pool(inventory)
    indices = parsed.indices if parsed.kind == "devices" else tuple(range(size))
    if not indices:
        raise PlacementError(
            f"placement for {component!r}: 'all' found nothing to place on ({_pool_summary(inventory)})"
        )
    _check_exist(component, indices, size, label, _pool_summary(inventory))
    num_processes = parsed.num_processes or len(indices)
    shares = _split(component, indices, num_processes, label, max_procs, may_share_units=True)
    drafts = []
    for rank, share in enumerate(shares):
        nodes = sorted({locations[i][0] for i in share})
        if len(nodes) > 1:
            raise PlacementError(
                f"placement for {component!r}: rank {rank} would get {label}s {_format_indices(share)} on "
                f"nodes {nodes}; a process's {label}s must be on one node, so use more processes"
            )
        if on_cpu:
            drafts.append(_Draft(node_index=nodes[0], cpu_slots=share))
        else:
            local = tuple(locations[i][1] for i in share)
            drafts.append(_Draft(node_index=nodes[0], global_devices=share, local_devices=local))
    return drafts


def _draft_node_ranks(component: str, parsed: ParsedSpec, inventory: ClusterInventory) -> list[_Draft]:
    n = inventory.num_nodes
    _check_exist(component, parsed.indices, n, "node", f"cluster has {n} nodes: {_format_indices(range(n))}")
    num_processes = parsed.num_processes or len(parsed.indices)
    shares = _split(component, parsed.indices, num_processes, "node", None, may_share_units=False)
    return [_Draft(node_index=share[0]) for share in shares]


def _draft_robot_ranks(component: str, parsed: ParsedSpec, inventory: ClusterInventory) -> list[_Draft]:
    n = inventory.num_robots
    summary = f"cluster has {n} robots: {_format_indices(range(n))}" if n else "cluster has no robots"
    _check_exist(component, parsed.indices, n, "robot", summary)
    return [
        _Draft(node_index=inventory.robot_locations[i][0], robot=inventory.robot_locations[i][1])
        for i in parsed.indices
    ]


def _finalise(component: str, drafts: list[_Draft], inventory: ClusterInventory) -> tuple[RankPlacement, ...]:
    """Number ranks within each node and build their env vars."""
    world_size = len(drafts)
    per_node: dict[int, list[int]] = {}
    for rank, draft in enumerate(drafts):
        per_node.setdefault(draft.node_index, []).append(rank)
    kind = inventory.accelerator_kind
    visible_var = None if kind is None else VISIBLE_DEVICES_VARIABLE.get(kind, f"{kind.upper()}_VISIBLE_DEVICES")
    placements = []
    for rank, draft in enumerate(drafts):
        node = inventory.nodes[draft.node_index]
        node_ranks = per_node[draft.node_index]
        env = {
            "RANK": str(rank),
            "WORLD_SIZE": str(world_size),
            "LOCAL_RANK": str(node_ranks.index(rank)),
            "LOCAL_WORLD_SIZE": str(len(node_ranks)),
        }
        if visible_var is not None:
            env[visible_var] = ",".join(map(str, draft.local_devices))
        placements.append(
            RankPlacement(
                component=component,
                rank=rank,
                world_size=world_size,
                node_index=node.node_index,
                node_id=node.node_id,
                node_ip=node.ip,
                local_devices=draft.local_devices,
                global_devices=draft.global_devices,
                cpu_slots=draft.cpu_slots,
                robot=draft.robot,
                env_vars=env,
            )
        )
    return tuple(placements)


def _component_entries(spec: Mapping[str, str | int], known: Collection[str] | None) -> list[tuple[str, str | int]]:
    """Expand keys like 'actor,rollout' (one spec shared by several components) and check names."""
    known_names = None if known is None else (sorted(known) if isinstance(known, (set, frozenset)) else list(known))
    entries: list[tuple[str, str | int]] = []
    key_of: dict[str, str] = {}
    for key, value in spec.items():
        if not isinstance(key, str) or not key.strip():
            raise PlacementError(f"placement keys must be component names, got {key!r}")
        for name in (part.strip() for part in key.split(",")):
            if not name:
                raise PlacementError(f"placement key {key!r} has an empty component name")
            if known_names is not None and name not in known_names:
                hint = difflib.get_close_matches(name, known_names, n=1)
                raise PlacementError(
                    f"placement names unknown component {name!r}; known components: {', '.join(known_names)}"
                    + (f" (did you mean {hint[0]!r}?)" if hint else "")
                )
            if name in key_of:
                raise PlacementError(
                    f"placement for {name!r} is given twice (keys {key_of[name]!r} and {key!r}); "
                    "give each component one entry"
                )
            key_of[name] = key
            entries.append((name, value))
    return entries


def place(
    inventory: ClusterInventory,
    spec: Mapping[str, str | int],
    components: Collection[str] | None = None,
    max_procs_per_device: int = 8,
) -> PlacementPlan:
    """Place every component of ``spec`` on ``inventory``; raise :class:`PlacementError` if impossible.

    ``components``, when given, is the set of names the caller knows; spec keys outside it are
    rejected (typos), while known components missing from the spec are the caller's business.
    A key may name several components ("actor,rollout": "0-3") that then share the same placement.
    ``max_procs_per_device`` caps one component's processes per device (or CPU slot).
    """
    if isinstance(max_procs_per_device, bool) or not isinstance(max_procs_per_device, int) or max_procs_per_device < 1:
        raise PlacementError(f"max_procs_per_device must be a positive int, got {max_procs_per_device!r}")
    if not isinstance(spec, Mapping):
        raise PlacementError(f"placement spec must be a mapping of component -> spec, got {type(spec).__name__}")
    if not spec:
        raise PlacementError(
            "placement spec is empty; give each component a placement, e.g. {'actor': '0-3', 'rollout': '4-7'}"
        )
    placed: dict[str, tuple[RankPlacement, ...]] = {}
    for name, value in _component_entries(spec, components):
        parsed = parse_spec(value, component=name)
        if parsed.kind in ("devices", "all"):
            drafts = _draft_device_ranks(name, parsed, inventory, max_procs_per_device)
        elif parsed.kind == "nodes":
            drafts = _draft_node_ranks(name, parsed, inventory)
        else:
            drafts = _draft_robot_ranks(name, parsed, inventory)
        placed[name] = _finalise(name, drafts, inventory)
    return PlacementPlan(inventory=inventory, components=placed)
