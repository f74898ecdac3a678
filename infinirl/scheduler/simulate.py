"""A simulated cluster: plan for 8 to 1,024 GPUs from a profile measured on this machine.

The inventory is fake (:meth:`ClusterInventory.with_gpus`), the config's work per iteration is
scaled with the cluster (``batch_scale``, default: one probe batch per GPU), and every measured
cost is scaled to the simulated device: ``speedup`` times faster, ``memory_scale`` times the
bytes per rank. Nothing runs: the search and the cost model are the same as for a real plan, so
this checks that planning scales (a plan of 1,024 GPUs takes seconds) and stays valid.
"""

from __future__ import annotations

import copy
import math
from dataclasses import replace

from infinirl.runtime.inventory import ClusterInventory, GiB
from infinirl.scheduler.cost import Workload
from infinirl.scheduler.profile import Profile, workload_of
from infinirl.scheduler.search import SearchResult, search
from infinirl.scheduler.workloads import RUNNER_MODELS

__all__ = ["scaled_config", "scaled_workload", "simulated_inventory", "simulated_plan"]


def simulated_inventory(num_gpus: int, gpus_per_node: int = 8, gpu_memory_bytes: int = 80 * GiB) -> ClusterInventory:
    """``num_gpus`` GPUs on nodes of ``gpus_per_node`` (fewer GPUs than a node: one node of them)."""
    if num_gpus < 1:
        raise ValueError(f"num_gpus={num_gpus}: a simulated cluster needs at least one GPU")
    if gpus_per_node < 1:
        raise ValueError(f"gpus_per_node={gpus_per_node}: a simulated node needs at least one GPU")
    per_node = min(gpus_per_node, num_gpus)
    if num_gpus % per_node:
        raise ValueError(f"num_gpus={num_gpus} is not a multiple of gpus_per_node={gpus_per_node}")
    return ClusterInventory.with_gpus(num_gpus // per_node, per_node, gpu_memory_bytes=gpu_memory_bytes)


def scaled_config(cfg, batch_scale: int):
    """A copy of ``cfg`` with ``batch_scale`` times the work per iteration."""
    scaled = copy.deepcopy(cfg)
    RUNNER_MODELS.get(cfg.runner).scale_batch(scaled, batch_scale)
    return scaled


def scaled_workload(cfg, profile: Profile, speedup: float = 1.0, memory_scale: float = 1.0) -> Workload:
    """The workload of (an already scaled) ``cfg`` with every measured cost moved to the simulated device."""
    if not (math.isfinite(speedup) and speedup > 0) or not (math.isfinite(memory_scale) and memory_scale > 0):
        raise ValueError(f"speedup={speedup:g}, memory_scale={memory_scale:g}: both must be > 0 (1: as profiled)")
    base = workload_of(cfg, profile)
    costs = {key: cost.scaled(speedup=speedup, memory=memory_scale) for key, cost in base.costs.items()}
    return replace(base, costs=costs, overhead_s=base.overhead_s / speedup, hop_s=base.hop_s / speedup)


def simulated_plan(cfg, profile: Profile, num_gpus: int, batch_scale: int | None = None, speedup: float = 1.0,
                   memory_scale: float = 1.0, gpus_per_node: int = 8, gpu_memory_bytes: int = 80 * GiB,
                   limit: int | None = None) -> tuple[ClusterInventory, SearchResult]:
    """The ranked plan of ``cfg`` on a simulated cluster of ``num_gpus`` GPUs."""
    inventory = simulated_inventory(num_gpus, gpus_per_node, gpu_memory_bytes)
    scaled = scaled_config(cfg, batch_scale or num_gpus)
    workload = scaled_workload(scaled, profile, speedup, memory_scale)
    return inventory, search(scaled, RUNNER_MODELS.get(cfg.runner), workload, inventory, limit)
