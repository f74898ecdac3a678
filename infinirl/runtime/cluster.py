"""Connect to or start Ray, wait for nodes, and take an inventory of every node.

A ``Cluster`` is created explicitly by the driver: parsing or validating configuration never starts
Ray. Ray's token authentication is left as Ray sets it up (on by default since Ray 2.5x); we never
disable it.
"""

from __future__ import annotations

import logging
import socket
import time
from dataclasses import dataclass, field

import ray
from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

from infinirl.runtime.errors import ClusterError
from infinirl.runtime.hardware import discover_node
from infinirl.runtime.inventory import ClusterInventory, NodeInventory, Robot
from infinirl.runtime.memory import device_lock_actor
from infinirl.runtime.ray_defaults import NAMESPACE, WORKER_ENV_DEFAULTS, worker_env
from infinirl.runtime.worker import shutdown_all_groups

# NAMESPACE and WORKER_ENV_DEFAULTS live in ray_defaults; they are read from here as well.
__all__ = ["LOCAL_RAY_SYSTEM_CONFIG", "NAMESPACE", "WORKER_ENV_DEFAULTS", "Cluster", "ClusterConfig"]

logger = logging.getLogger(__name__)

# Ray settings of an instance we start: keep Ray's own background work off small machines, where
# every Ray process's periodic work takes CPU from the components (simulators, models).
# * No pool of idle worker processes. Ray starts one per CPU when the driver connects and keeps as
#   many once they idle, so that tasks start fast; our components are actors with processes of
#   their own and we run tasks only at start-up, so the pool would only idle. An idle Ray worker
#   is not free: its main thread wakes every 10 ms, taking CPU from cores the components keep
#   busy. With these settings a task's worker ends once it has idled a second.
# * No metrics collection: every Ray process would export metrics for a dashboard we do not start.
LOCAL_RAY_SYSTEM_CONFIG = {"prestart_worker_first_driver": False, "num_workers_soft_limit": 0,
                           "enable_metrics_collection": False}


@dataclass
class ClusterConfig:
    """How to reach compute. Every field is optional; the default starts a local Ray instance."""

    address: str | None = None
    """None or "local": start a local Ray instance; "auto": join the running one; "host:port": join it."""
    num_cpus: int | None = None
    """CPUs of a *local* instance (default: all). Ignored when joining."""
    num_gpus: int | None = None
    """GPUs of a *local* instance (default: all visible); the inventory lists only the first this
    many of the visible ones, so placement never uses more. Ignored when joining."""
    wait_for_nodes: int = 1
    """Block in ``start()`` until this many nodes are alive (multi-node jobs)."""
    wait_timeout_s: float = 120.0
    """How long to wait for ``wait_for_nodes`` before failing with a clear error."""
    connect_timeout_s: float = 10.0
    """TCP probe timeout for ``address=host:port``: an unreachable head fails fast instead of hanging."""
    robot_plugins: dict[str, dict] = field(default_factory=dict)
    """Robot discovery plugins to run on every node, e.g. ``{"simulated": {"count": 1}}``. None by default."""
    robot_plugin_modules: list[str] = field(default_factory=list)
    """Modules imported on every node before discovery, to register robot plugins defined outside the
    runtime (e.g. ``infinirl.realworld.discovery`` for the ``drivers`` plugin)."""
    log_to_driver: bool = True
    """Stream worker stdout/stderr to the driver (progress of remote components)."""


class Cluster:
    """The driver's handle on Ray: start/join, inventory, shutdown. Use as a context manager."""

    def __init__(self, config: ClusterConfig | None = None, **overrides):
        if config is None:
            config = ClusterConfig(**overrides)
        elif overrides:
            raise TypeError("pass either a ClusterConfig or keyword overrides, not both")
        self.config = config
        self._started_here = False
        self._inventory: ClusterInventory | None = None

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> "Cluster":
        cfg = self.config
        joining = cfg.address not in (None, "", "local", "auto")
        if joining:
            _probe_address(cfg.address, cfg.connect_timeout_s)
        if ray.is_initialized():
            logger.info("Ray already initialised in this process; reusing it")
        elif cfg.address in (None, "", "local"):
            try:
                ray.init(
                    address="local",  # always a new instance: never silently join a stray `ray start`
                    num_cpus=cfg.num_cpus,
                    num_gpus=cfg.num_gpus,
                    namespace=NAMESPACE,
                    include_dashboard=False,
                    log_to_driver=cfg.log_to_driver,
                    configure_logging=False,
                    _system_config=LOCAL_RAY_SYSTEM_CONFIG,
                )
            except Exception as exc:  # Ray raises a bare Exception when its node does not come up
                first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
                raise ClusterError(
                    f"could not start a local Ray node: {first} Ray's own logs are under /tmp/ray/session_latest/logs; "
                    "on an overloaded machine run again, or join a running cluster with cluster.address=<head>"
                ) from exc
            self._started_here = True
        else:
            self._started_here = True  # we joined: disconnect on shutdown (the cluster stays up)
            try:
                ray.init(
                    address=cfg.address,
                    namespace=NAMESPACE,
                    log_to_driver=cfg.log_to_driver,
                    configure_logging=False,
                )
            except (ConnectionError, RuntimeError) as exc:
                raise ClusterError(
                    f"could not join Ray at address={cfg.address!r}: {exc}. Start the head with "
                    "`ray start --head` there, or set cluster.address=local to start one here."
                ) from exc
        self._wait_for_nodes()
        self._inventory = self._take_inventory()
        # The driver owns the cluster-wide device lock, so it lives exactly as long as the job.
        self._device_lock = device_lock_actor()
        return self

    def shutdown(self) -> None:
        """Disconnect; stop Ray too when this Cluster started it. Leaves no process of ours behind."""
        self._device_lock = None
        if self._started_here and ray.is_initialized():
            shutdown_all_groups()  # before Ray kills their ranks: they clean up after them
            ray.shutdown()
        self._inventory = None

    def __enter__(self) -> "Cluster":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.shutdown()

    # ------------------------------------------------------------------ inventory
    @property
    def inventory(self) -> ClusterInventory:
        if self._inventory is None:
            raise ClusterError("Cluster not started: call start() (or use `with Cluster(...)`).")
        return self._inventory

    def refresh(self) -> ClusterInventory:
        self._inventory = self._take_inventory()
        return self._inventory

    def lost_nodes(self, groups, wait_s: float = 0.0) -> str | None:
        """One line naming every node that ran a rank of ``groups`` (WorkerGroups) and has left the
        cluster, with the ranks lost on each; None when all those nodes are alive.

        ``wait_s``: a node that has just died can still be listed alive for some seconds (Ray
        notices a lost node by missed health checks), so when a rank died, wait up to this long for
        its node to be declared dead before concluding that it lives."""
        where: dict[str, list[str]] = {}
        for group in groups:
            for ctx in group.contexts:
                if ctx.node_id:
                    where.setdefault(ctx.node_id, []).append(f"{ctx.component}[rank {ctx.rank}]")
        deadline = time.monotonic() + wait_s
        while True:
            alive = {n["NodeID"] for n in self._alive_nodes()}
            lost = [node_id for node_id in where if node_id not in alive]
            if lost or time.monotonic() >= deadline:
                break
            time.sleep(0.5)
        if not lost:
            return None
        known = {n.node_id: n for n in self._inventory.nodes} if self._inventory is not None else {}
        parts = []
        for node_id in lost:
            node = known.get(node_id)
            name = f"node {node.node_index} ({node.ip}, id {node_id[:12]})" if node else f"node {node_id[:12]}"
            parts.append(f"{name} left the Ray cluster mid-run, taking {', '.join(where[node_id])}")
        head = self.config.address if self.config.address not in (None, "", "local", "auto") else "<head>"
        return (f"{'; '.join(parts)}; bring it back (`ray start --address={head}` on it) and run again: with "
                "resume=true the run continues from its last checkpoint")

    def _alive_nodes(self) -> list[dict]:
        return [n for n in ray.nodes() if n.get("Alive")]

    def _wait_for_nodes(self) -> None:
        want = self.config.wait_for_nodes
        deadline = time.monotonic() + self.config.wait_timeout_s
        while True:
            alive = len(self._alive_nodes())
            if alive >= want:
                return
            if time.monotonic() > deadline:
                raise ClusterError(
                    f"cluster has {alive} alive node(s) after {self.config.wait_timeout_s:.0f}s but "
                    f"cluster.wait_for_nodes={want}; start more nodes with `ray start --address=...` "
                    "or lower cluster.wait_for_nodes."
                )
            time.sleep(0.5)

    def _take_inventory(self) -> ClusterInventory:
        nodes = sorted(self._alive_nodes(), key=_node_sort_key)
        probes = []
        for node in nodes:
            task = ray.remote(num_cpus=0)(discover_node).options(
                scheduling_strategy=NodeAffinitySchedulingStrategy(node["NodeID"], soft=False),
                runtime_env={"env_vars": worker_env()},
            )
            probes.append(task.remote(self.config.robot_plugins, list(self.config.robot_plugin_modules)))
        found = ray.get(probes)
        local = self.config.address in (None, "", "local")
        inventory_nodes = []
        seen_robot_names: set[str] = set()
        for index, (node, info) in enumerate(zip(nodes, found)):
            robots = []
            for robot in info["robots"]:  # names identify robots cluster-wide: qualify collisions
                name = robot.name if robot.name not in seen_robot_names else f"{robot.name}@node{index}"
                seen_robot_names.add(name)
                robots.append(Robot(name=name, kind=robot.kind, local_index=robot.local_index,
                                    properties=robot.properties))
            resources = node.get("Resources", {})
            inventory_nodes.append(
                NodeInventory(
                    node_index=index,
                    node_id=node["NodeID"],
                    ip=node["NodeManagerAddress"],
                    num_cpus=int(resources.get("CPU", 0)),
                    memory_bytes=int(resources.get("memory", 0)),
                    accelerators=capped_accelerators(info["accelerators"], self.config.num_gpus if local else None),
                    robots=tuple(robots),
                )
            )
        return ClusterInventory(nodes=tuple(inventory_nodes))


def capped_accelerators(accelerators, limit: int | None) -> tuple:
    """The node's first ``limit`` accelerators (all if None): ``num_gpus`` of a local instance
    bounds what placement may use, as it bounds Ray's GPU resource."""
    ordered = sorted(accelerators, key=lambda a: a.local_index)
    return tuple(ordered if limit is None else ordered[:limit])


def _node_sort_key(node: dict) -> tuple:
    """Head node first, then by address: node indices stay stable across inventories."""
    is_head = node.get("Resources", {}).get("node:__internal_head__", 0) > 0
    return (not is_head, node["NodeManagerAddress"], node["NodeID"])


def _probe_address(address: str, timeout_s: float) -> None:
    """Fail within ``timeout_s`` when the Ray head is unreachable (ray.init would retry for minutes)."""
    host, sep, port = address.removeprefix("ray://").rpartition(":")
    if not sep or not port.isdigit():
        raise ClusterError(
            f"cluster.address={address!r} is not 'host:port', 'auto' or 'local'; e.g. 10.0.0.5:6379"
        )
    try:
        with socket.create_connection((host, int(port)), timeout=timeout_s):
            pass
    except OSError as exc:
        raise ClusterError(
            f"cannot reach the Ray head at {address} within {timeout_s:.0f}s ({exc}). Check the address "
            "and that `ray start --head --port=...` runs there, or use cluster.address=local."
        ) from None
