"""Rendezvous addresses for torch.distributed groups: a free TCP port on the right node."""

from __future__ import annotations

import socket
from typing import Any

import ray
from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

__all__ = ["free_port", "pick_master"]


def free_port() -> tuple[str, int]:
    """(this node's IP, a TCP port free on it right now)."""
    with socket.socket() as sock:
        sock.bind(("", 0))
        return ray.util.get_node_ip_address(), sock.getsockname()[1]


def pick_master(rank0: Any) -> tuple[str, int]:
    """A free TCP port on rank 0's node (a ``RankContext``), found *on that node*.

    On this process's own node (or with no node asked for) the port is found here: a Ray task
    would need a worker process of its own, started (importing torch) for a moment's work, since
    a Cluster we start keeps no idle workers (``cluster.LOCAL_RAY_SYSTEM_CONFIG``)."""
    if rank0.node_id is None or rank0.node_id == ray.get_runtime_context().get_node_id():
        return free_port()
    task = ray.remote(num_cpus=0)(free_port).options(
        scheduling_strategy=NodeAffinitySchedulingStrategy(rank0.node_id, soft=False))
    return ray.get(task.remote())
