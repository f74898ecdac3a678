"""What a cluster has: nodes, their CPUs and memory, accelerators and robots.

The inventory is plain data so that placement can be a pure function of it: ``Cluster`` builds one
from Ray, tests build one by hand (``ClusterInventory.with_gpus(2, 4)``), and a run can save it as
JSON next to its checkpoints to show where it ran.

Robots are resources like accelerators (the RLinf-USER idea): each has a node and a local index, and
a component can be placed on them by index just as it is placed on GPUs.

Global numbering (what placement specs refer to): accelerators are numbered across nodes in node
order, node 0's first, each node's in ``local_index`` order. With 2 nodes of 4 GPUs, global device 5
is node 1, local device 1. Robots and CPU slots are numbered the same way.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

GiB = 1024**3


class InventoryError(ValueError):
    """An inventory that cannot describe a real cluster (duplicate indices, bad JSON, ...)."""


def _check_keys(what: str, data: Mapping[str, Any], required: set[str], optional: set[str] = frozenset()) -> None:
    """Reject missing or unknown keys by name: a typo in saved JSON should not pass silently."""
    if not isinstance(data, Mapping):
        raise InventoryError(f"{what}.from_dict expects a mapping, got {type(data).__name__}")
    missing = sorted(required - data.keys())
    unknown = sorted(data.keys() - required - optional)
    if missing:
        raise InventoryError(f"{what}.from_dict: missing key(s) {missing}; required: {sorted(required)}")
    if unknown:
        raise InventoryError(
            f"{what}.from_dict: unknown key(s) {unknown}; accepted: {sorted(required | optional)}"
        )


def _require_non_negative(what: str, **values: int) -> None:
    for name, value in values.items():
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise InventoryError(f"{what}: {name} must be a non-negative int, got {value!r}")


@dataclass(frozen=True)
class Accelerator:
    """One accelerator on a node. ``local_index`` is the ordinal the node's runtime uses (cuda:N)."""

    kind: str
    local_index: int
    memory_bytes: int

    def __post_init__(self) -> None:
        if not self.kind:
            raise InventoryError("Accelerator: kind must be a non-empty string such as 'cuda'")
        _require_non_negative("Accelerator", local_index=self.local_index, memory_bytes=self.memory_bytes)

    def to_dict(self) -> dict[str, Any]:
        return {"kind": self.kind, "local_index": self.local_index, "memory_bytes": self.memory_bytes}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Accelerator:
        _check_keys("Accelerator", data, {"kind", "local_index", "memory_bytes"})
        return cls(kind=data["kind"], local_index=data["local_index"], memory_bytes=data["memory_bytes"])


@dataclass(frozen=True)
class Robot:
    """A robot attached to a node. ``properties`` carries driver details (model, serial, ip, ...)."""

    name: str
    kind: str
    local_index: int
    # Excluded from hashing because dicts are unhashable; equality still compares it.
    properties: dict[str, Any] = field(default_factory=dict, hash=False)

    def __post_init__(self) -> None:
        if not self.name:
            raise InventoryError("Robot: name must be a non-empty string (it identifies the robot in logs)")
        _require_non_negative(f"Robot {self.name!r}", local_index=self.local_index)

    def to_dict(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "kind": self.kind,
            "local_index": self.local_index,
            "properties": dict(self.properties),
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Robot:
        _check_keys("Robot", data, {"name", "kind", "local_index"}, {"properties"})
        return cls(
            name=data["name"],
            kind=data["kind"],
            local_index=data["local_index"],
            properties=dict(data.get("properties", {})),
        )


@dataclass(frozen=True)
class NodeInventory:
    """One node. Accelerators and robots are kept sorted by ``local_index`` (global numbering uses it)."""

    node_index: int
    node_id: str
    ip: str
    num_cpus: int
    memory_bytes: int
    accelerators: tuple[Accelerator, ...] = ()
    robots: tuple[Robot, ...] = ()

    def __post_init__(self) -> None:
        what = f"node {self.node_index}"
        _require_non_negative(what, node_index=self.node_index, num_cpus=self.num_cpus,
                              memory_bytes=self.memory_bytes)
        # Accept lists (from JSON or hand-written tests) but store sorted tuples, so numbering is stable.
        accelerators = tuple(sorted(self.accelerators, key=lambda a: a.local_index))
        robots = tuple(sorted(self.robots, key=lambda r: r.local_index))
        object.__setattr__(self, "accelerators", accelerators)
        object.__setattr__(self, "robots", robots)
        for label, items in (("accelerator", accelerators), ("robot", robots)):
            indices = [item.local_index for item in items]
            duplicates = sorted({i for i in indices if indices.count(i) > 1})
            if duplicates:
                raise InventoryError(f"{what}: duplicate {label} local_index {duplicates}; each must be unique")

    @property
    def num_accelerators(self) -> int:
        return len(self.accelerators)

    def to_dict(self) -> dict[str, Any]:
        return {
            "node_index": self.node_index,
            "node_id": self.node_id,
            "ip": self.ip,
            "num_cpus": self.num_cpus,
            "memory_bytes": self.memory_bytes,
            "accelerators": [a.to_dict() for a in self.accelerators],
            "robots": [r.to_dict() for r in self.robots],
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> NodeInventory:
        _check_keys(
            "NodeInventory", data, {"node_index", "node_id", "ip", "num_cpus", "memory_bytes"},
            {"accelerators", "robots"},
        )
        return cls(
            node_index=data["node_index"],
            node_id=data["node_id"],
            ip=data["ip"],
            num_cpus=data["num_cpus"],
            memory_bytes=data["memory_bytes"],
            accelerators=tuple(Accelerator.from_dict(a) for a in data.get("accelerators", ())),
            robots=tuple(Robot.from_dict(r) for r in data.get("robots", ())),
        )


@dataclass(frozen=True)
class ClusterInventory:
    """All nodes, with ``node_index`` equal to the position (0..N-1) so specs can say ``node:2``."""

    nodes: tuple[NodeInventory, ...]

    def __post_init__(self) -> None:
        nodes = tuple(self.nodes)
        object.__setattr__(self, "nodes", nodes)
        if not nodes:
            raise InventoryError("ClusterInventory: a cluster needs at least one node")
        for position, node in enumerate(nodes):
            if node.node_index != position:
                raise InventoryError(
                    f"ClusterInventory: node at position {position} has node_index {node.node_index}; "
                    "nodes must be listed in node_index order 0..N-1"
                )
        kinds = sorted({a.kind for node in nodes for a in node.accelerators})
        if len(kinds) > 1:
            # One global device numbering and one *_VISIBLE_DEVICES variable assume a single kind.
            raise InventoryError(
                f"ClusterInventory: mixed accelerator kinds {kinds} are not supported; "
                "build one inventory per accelerator kind"
            )
        names = [r.name for node in nodes for r in node.robots]
        duplicates = sorted({n for n in names if names.count(n) > 1})
        if duplicates:
            raise InventoryError(f"ClusterInventory: duplicate robot name(s) {duplicates}; names must be unique")

    # ----- counts -------------------------------------------------------------------------------
    @property
    def num_nodes(self) -> int:
        return len(self.nodes)

    @property
    def num_accelerators(self) -> int:
        return len(self.device_locations)

    @property
    def num_robots(self) -> int:
        return len(self.robot_locations)

    @property
    def num_cpu_slots(self) -> int:
        return len(self.cpu_slot_locations)

    @property
    def accelerator_kind(self) -> str | None:
        """The single accelerator kind ("cuda", ...), or None on a CPU-only cluster."""
        for node in self.nodes:
            if node.accelerators:
                return node.accelerators[0].kind
        return None

    # ----- global numbering ---------------------------------------------------------------------
    @cached_property
    def device_locations(self) -> tuple[tuple[int, int], ...]:
        """Global device index -> (node_index, local_index)."""
        return tuple((n.node_index, a.local_index) for n in self.nodes for a in n.accelerators)

    @cached_property
    def robot_locations(self) -> tuple[tuple[int, Robot], ...]:
        """Global robot index -> (node_index, robot)."""
        return tuple((n.node_index, r) for n in self.nodes for r in n.robots)

    @cached_property
    def cpu_slot_locations(self) -> tuple[tuple[int, int], ...]:
        """Global CPU slot index -> (node_index, local slot). Slots number each node's ``num_cpus``."""
        return tuple((n.node_index, slot) for n in self.nodes for slot in range(n.num_cpus))

    # ----- serialisation ------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        return {"nodes": [n.to_dict() for n in self.nodes]}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> ClusterInventory:
        _check_keys("ClusterInventory", data, {"nodes"})
        return cls(nodes=tuple(NodeInventory.from_dict(n) for n in data["nodes"]))

    # ----- constructors for tests and docs ------------------------------------------------------
    @classmethod
    def cpu_only(
        cls, num_nodes: int = 1, cpus_per_node: int = 2, robots_per_node: int = 0, robot_kind: str = "arm"
    ) -> ClusterInventory:
        """A cluster of identical CPU-only nodes (what CI and laptops have)."""
        return cls._uniform(num_nodes, cpus_per_node, 0, "cuda", 0, robots_per_node, robot_kind)

    @classmethod
    def with_gpus(
        cls,
        num_nodes: int,
        gpus_per_node: int,
        cpus_per_node: int = 16,
        gpu_memory_bytes: int = 80 * GiB,
        kind: str = "cuda",
        robots_per_node: int = 0,
        robot_kind: str = "arm",
    ) -> ClusterInventory:
        """A cluster of identical accelerator nodes."""
        return cls._uniform(
            num_nodes, cpus_per_node, gpus_per_node, kind, gpu_memory_bytes, robots_per_node, robot_kind
        )

    @classmethod
    def _uniform(
        cls,
        num_nodes: int,
        cpus_per_node: int,
        accelerators_per_node: int,
        kind: str,
        accelerator_memory_bytes: int,
        robots_per_node: int,
        robot_kind: str,
    ) -> ClusterInventory:
        _require_non_negative(
            "ClusterInventory", num_nodes=num_nodes, cpus_per_node=cpus_per_node,
            accelerators_per_node=accelerators_per_node, robots_per_node=robots_per_node,
        )
        nodes = []
        for i in range(num_nodes):
            accelerators = tuple(Accelerator(kind, j, accelerator_memory_bytes) for j in range(accelerators_per_node))
            robots = tuple(
                Robot(name=f"{robot_kind}{i * robots_per_node + j}", kind=robot_kind, local_index=j)
                for j in range(robots_per_node)
            )
            nodes.append(
                NodeInventory(
                    node_index=i,
                    node_id=f"node-{i}",
                    ip=f"10.0.0.{i + 1}",
                    num_cpus=cpus_per_node,
                    memory_bytes=64 * GiB,
                    accelerators=accelerators,
                    robots=robots,
                )
            )
        return cls(nodes=tuple(nodes))
