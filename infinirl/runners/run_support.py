"""What every runner's driver does the same way around its flow: when the run started, placing and
starting its components together, and running the flow on the shared loop.

Kept out of the runners so that the reasoning, embodied and SAC macro flows read as their
algorithm and nothing else.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

from infinirl.config import ConfigError

__all__ = ["NODE_LOSS_WAIT_S", "RUN_OBSERVERS", "launch_all", "plan_placement", "raise_if_nodes_lost",
           "run_components", "run_staged", "run_start_time"]

_RUNS_IN_PROCESS = [0]

RUN_OBSERVERS: list[Callable] = []
"""Called as ``observe(groups, plan)`` once a run's loop has finished, before its components shut
down: the scheduler's profiler reads their spans and memory here."""


def run_start_time() -> float:
    """Wall-clock origin of ``time/elapsed_s``: the process start for the first run in a process
    (so interpreter and import start-up count, as a user timing the command sees them), the call
    for later ones (tests run several runs in one process)."""
    _RUNS_IN_PROCESS[0] += 1
    if _RUNS_IN_PROCESS[0] == 1:
        try:
            import psutil

            return psutil.Process().create_time()
        except Exception:
            pass
    return time.time()


def launch_all(plan, launches: dict):
    """Start every component at once (their start-up, mostly imports, overlaps).

    ``launches``: component name -> (Worker class, constructor args) or (Worker class, constructor
    args, environment variables of its processes from their start). If any component fails to
    start, the ones that did are shut down and the first error is raised (its root cause, not a
    secondary "actor died" from a sibling)."""
    from infinirl.runtime import WorkerGroup

    with ThreadPoolExecutor(len(launches)) as pool:
        futures = {name: pool.submit(WorkerGroup.launch, cls, name, placement=plan.ranks(name), args=args,
                                     env_vars=env_vars[0] if env_vars else None)
                   for name, (cls, args, *env_vars) in launches.items()}
        groups, error = {}, None
        for name, future in futures.items():
            try:
                groups[name] = future.result()
            except BaseException as exc:  # keep the first error, stop what did start
                error = error or exc
    if error is not None:
        for group in groups.values():
            group.shutdown()
        raise error
    return groups


def plan_placement(inventory, cfg):
    """The placement of ``cfg``'s components on the cluster; a spec the cluster cannot satisfy (a
    device or slot it does not have) is a ConfigError naming the component, before any worker starts."""
    from infinirl.runtime import place
    from infinirl.runtime.placement import PlacementError

    try:
        return place(inventory, cfg.placement_spec(), components=cfg.components())
    except PlacementError as exc:
        raise ConfigError(str(exc)) from None


def run_components(cfg, loop, launches: Callable, make_flow: Callable) -> dict:
    """Start the cluster, place and launch the components, run ``make_flow(groups, plan)`` on ``loop``.

    ``launches(plan)`` returns what :func:`launch_all` takes (every component at once); the rest is
    :func:`run_staged`'s."""
    def start(plan, groups: dict, on_exit: list):
        groups.update(launch_all(plan, launches(plan)))
        return make_flow(groups, plan)

    return run_staged(cfg, loop, start)


def run_staged(cfg, loop, start: Callable, cluster_config=None) -> dict:
    """Start the cluster, place ``cfg``'s components, and run the flow ``start`` builds on ``loop``.

    ``start(plan, groups, on_exit)`` launches components into ``groups`` (in stages where a later
    one needs what an earlier one reports, e.g. a learner sized by its robots), may add callables to
    ``on_exit`` (run last first, after the groups' shutdown: a channel to destroy, a link to close),
    and returns the flow. The flow's ``close()``, every group's shutdown and ``on_exit`` run however
    the loop ends; a failure that came with nodes leaving the cluster is a ClusterError naming them.
    ``placement: auto`` (or ``auto`` for some components) is resolved once the cluster is up, on its
    inventory, before any component starts: the scheduler profiles the config (its probe runs join
    this cluster) or reads the profile cached for a cluster of this shape, and writes its choice
    into ``cfg``. ``cluster_config``: the cluster section to start (default ``cfg.cluster``)."""
    from infinirl.runtime import Cluster

    with Cluster(cluster_config if cluster_config is not None else cfg.cluster) as cluster:
        if cfg.auto_placement:
            # The scheduler sits above the runners (it profiles by running them), hence the late import.
            from infinirl.scheduler.auto import resolve_auto_placement

            resolve_auto_placement(cfg, cluster.inventory)
        plan = plan_placement(cluster.inventory, cfg)
        print(plan.describe(), flush=True)
        groups: dict = {}
        on_exit: list[Callable[[], None]] = []
        try:
            flow = start(plan, groups, on_exit)
            try:
                summary = loop.run(flow)
                for observe in RUN_OBSERVERS:  # the scheduler's profiler reads spans and memory here
                    observe(groups, plan)
                return summary
            finally:
                flow.close()
        except Exception as exc:
            raise_if_nodes_lost(cluster, groups.values(), exc)
            raise
        finally:
            for group in groups.values():
                group.shutdown()
            for action in reversed(on_exit):
                action()


# How long a failed run waits for Ray to declare the node of a dead rank dead (its health checks
# take seconds to miss a node), so that the error names the lost node rather than one dead rank.
NODE_LOSS_WAIT_S = 60.0


def raise_if_nodes_lost(cluster, groups, error: BaseException) -> None:
    """Raise a ClusterError naming the lost nodes and components when ``error`` came with nodes of
    this run leaving the cluster (a node shut down, crashed or cut off), chained to ``error``."""
    from infinirl.runtime import ClusterError, WorkerError

    if cluster.inventory.num_nodes < 2:
        return  # the driver's own node cannot be lost while the driver runs
    died = isinstance(error, WorkerError) and error.cause.startswith("died")
    lost = cluster.lost_nodes(list(groups), wait_s=NODE_LOSS_WAIT_S if died else 0.0)
    if lost is not None:
        raise ClusterError(lost) from error
