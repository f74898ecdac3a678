"""``infinirl plan`` and ``placement: auto``: profile (or read the cached profile), search, choose.

:func:`plan` returns the ranked candidates of a config on the cluster its ``cluster`` section
starts; the run of a config with ``placement: auto`` takes the first one on the cluster it has just
started (:func:`resolve_auto_placement`, called by ``runners.run_support`` before any component
starts) and writes it into the config, so the run's ``config.json`` records the placement and
depth that ran.
"""

from __future__ import annotations

import json
import math

from infinirl.config import ConfigError
from infinirl.runtime.inventory import ClusterInventory, GiB
from infinirl.scheduler.profile import Profile, load_or_profile, profile_summary, workload_of
from infinirl.scheduler.search import MAX_LAYOUTS, PlanEntry, SearchResult, fixed_placements, pool_of, search
from infinirl.scheduler.workloads import RUNNER_MODELS, UNPLANNED_RUNNERS

__all__ = ["DEPTH_KEYS", "format_plan", "plan", "plan_command", "resolve_auto_placement", "runner_model"]

DEPTH_KEYS = {"embodied": "rollout.pipeline_stages", "reasoning": "rollout.stream_chunk_prompts"}
"""The config key each runner's pipeline depth is written to (for the table's header)."""


def runner_model(cfg):
    """The scheduler's model of ``cfg``'s runner; a runner or config it cannot plan is a one-line
    ConfigError saying why and what to write instead."""
    if cfg.runner in UNPLANNED_RUNNERS:
        raise ConfigError(f"placement=auto / infinirl plan: nothing to plan: {UNPLANNED_RUNNERS[cfg.runner]}")
    if cfg.runner not in RUNNER_MODELS:
        raise ConfigError(f"placement=auto / infinirl plan: the scheduler has no model of the {cfg.runner!r} runner; "
                          f"it plans {', '.join(RUNNER_MODELS.names())}. Give placement.* explicitly")
    model = RUNNER_MODELS.get(cfg.runner)
    why = model.refuses(cfg)
    if why is not None:
        raise ConfigError(f"placement=auto / infinirl plan: {why}")
    return model


def plan(cfg, inventory: ClusterInventory | None = None, iterations: int = 4, refresh: bool = False,
         cache_dir: str | None = None, rounds: int = 1) -> tuple[Profile, SearchResult]:
    """``cfg``'s candidates on ``inventory``, best first. Default: the inventory of the cluster
    ``cfg.cluster`` starts, started here for it (probes, when the profile is not cached, run in it)."""
    model = runner_model(cfg)
    if inventory is None:
        from infinirl.runtime import Cluster

        with Cluster(model.cluster(cfg)) as cluster:
            return plan(cfg, cluster.inventory, iterations, refresh, cache_dir, rounds)
    profile = load_or_profile(cfg, inventory, iterations=iterations, cache_dir=cache_dir, refresh=refresh,
                              rounds=rounds)
    return profile, search(cfg, model, workload_of(cfg, profile), inventory)


def _devices_text(inventory: ClusterInventory) -> str:
    pool = pool_of(inventory)
    return f"{pool.size} {'CPU slots' if pool.on_cpu else 'devices'}"


def resolve_auto_placement(cfg, inventory: ClusterInventory | None = None, **plan_options) -> PlanEntry:
    """Write the best candidate's placement and depth on ``inventory`` (the cluster about to run
    it) into ``cfg`` (``placement: auto``); no candidate is a ConfigError saying what ruled them out."""
    if inventory is None:
        from infinirl.runtime import Cluster

        with Cluster(runner_model(cfg).cluster(cfg)) as cluster:
            return resolve_auto_placement(cfg, cluster.inventory, **plan_options)
    _, entries = plan(cfg, inventory, **plan_options)
    if not entries:
        raise ConfigError(f"placement=auto: no placement of {', '.join(cfg.components())} fits this cluster "
                          f"({_devices_text(inventory)}): {entries.why_empty()}; give placement.* explicitly")
    best = entries[0]
    model = runner_model(cfg)
    model.apply(cfg, best.candidate)
    print(f"placement=auto: {json.dumps(best.placement)} depth {best.candidate.depth}, predicted "
          f"{best.prediction.step_s:.3f} s per {model.step_name} (`infinirl plan` lists the others)", flush=True)
    return best


def _memory_text(entry: PlanEntry) -> str:
    return f"{entry.memory_bytes / GiB:.2f}/{entry.memory_limit_bytes / GiB:.0f} GiB"


def format_plan(cfg, profile: Profile | None, entries: list[PlanEntry], top: int = 20) -> str:
    """The candidates as a table, best first, with the measured profile under it."""
    depth_key = DEPTH_KEYS.get(cfg.runner, "depth")
    lines = [f"{len(entries)} candidate placements of {cfg.runner} ({', '.join(cfg.components())}); "
             f"depth = pipeline stages ({depth_key})"]
    model = RUNNER_MODELS.get(cfg.runner) if cfg.runner in RUNNER_MODELS else None
    if model is not None and model.step_text:
        lines.append(model.step_text)
    fixed = fixed_placements(cfg, model) if model is not None else {}
    if fixed:
        lines.append(f"fixed (not searched): {', '.join(f'{k}={v}' for k, v in fixed.items())}")
    lines += _search_notes(entries)
    lines.append(f"{'#':>3}  {'step_s':>8}  {'memory':>14}  depth  placement  [seconds per phase]")
    for i, entry in enumerate(entries[:top]):
        spec = " ".join(f"{name}={entry.placement[name]}" for name in cfg.components())
        parts = dict(entry.prediction.phases)
        rest = entry.prediction.step_s - sum(parts.values())  # the driver's own time, offloads and reloads
        if rest > 5e-4:
            parts["driver+switch"] = rest
        phases = " + ".join(f"{name} {seconds:.3g}" for name, seconds in parts.items())
        lines.append(f"{i + 1:>3}  {entry.prediction.step_s:>8.3f}  {_memory_text(entry):>14}  "
                     f"{entry.candidate.depth:>5}  {spec}  [{phases}]")
    if len(entries) > top:
        lines.append(f"... {len(entries) - top} more (--top N shows more)")
    if profile is not None:
        lines.append("measured: " + json.dumps(profile_summary(profile)))
    return "\n".join(lines)


def _search_notes(entries) -> list[str]:
    """What the search left out, as lines under the table's header (nothing when it left nothing)."""
    lines = []
    if getattr(entries, "grid", None):
        lines.append(f"sizes of blocks and components beyond the first 4 devices: {entries.grid} (a finer grid "
                     f"gives more than {MAX_LAYOUTS} layouts)")
    if getattr(entries, "truncated", False):
        lines.append(f"only the first {MAX_LAYOUTS} layouts of the coarsest grid were tried")
    if getattr(entries, "unknown_memory", ()):
        lines.append(f"memory not measured for {', '.join(entries.unknown_memory)} (no rank could be read): "
                     "not checked against the limit")
    if not entries and getattr(entries, "rejected", None):
        lines.append(f"no candidate: {entries.why_empty()}")
    return lines


def _check_plan_flags(args) -> None:
    """The command's numbers, before anything runs: one line naming the flag."""
    if args.top < 1 or args.profile_iterations < 2 or args.profile_rounds < 1:
        raise ConfigError("--top and --profile-rounds must be >= 1 and --profile-iterations >= 2 (the first "
                          "iteration is warm-up)")
    if args.gpus is not None and args.gpus < 1:
        raise ConfigError(f"--gpus {args.gpus}: a simulated cluster needs at least 1 GPU")
    if args.gpus_per_node < 1:
        raise ConfigError(f"--gpus-per-node {args.gpus_per_node}: a simulated node needs at least 1 GPU")
    if not (math.isfinite(args.speedup) and args.speedup > 0):
        raise ConfigError(f"--speedup {args.speedup:g}: give how many times faster a simulated GPU is than the "
                          "profiled device, a number > 0 (1: as fast)")


def plan_command(cfg, args) -> int:
    """``infinirl plan``: the table on the cluster ``cfg.cluster`` starts, or on a simulated one
    (``--gpus``) from the profile measured on that cluster."""
    import time

    from infinirl.runtime import Cluster
    from infinirl.scheduler.simulate import simulated_plan

    _check_plan_flags(args)
    model = runner_model(cfg)  # a runner without a model fails before anything runs
    with Cluster(model.cluster(cfg)) as cluster:  # probes, when the profile is not cached, run in it
        inventory = cluster.inventory
        profile = load_or_profile(cfg, inventory, iterations=args.profile_iterations, refresh=args.refresh,
                                  rounds=args.profile_rounds)
    start = time.perf_counter()
    if args.gpus is None:
        entries = search(cfg, model, workload_of(cfg, profile), inventory)
        where = f"this cluster ({_devices_text(inventory)})"
    else:
        try:
            _, entries = simulated_plan(cfg, profile, args.gpus, speedup=args.speedup, gpus_per_node=args.gpus_per_node)
        except ValueError as exc:
            raise ConfigError(f"--gpus: {exc}") from None
        where = f"a simulated cluster of {args.gpus} GPUs (batch x{args.gpus}, device x{args.speedup:g} speed)"
    print(format_plan(cfg, profile, entries, args.top))
    print(f"searched {len(entries)} candidates on {where} in {time.perf_counter() - start:.2f} s")
    return 0 if entries else 1
