"""``infinirl plan`` and ``placement: auto``: profile (or read the cached profile), search, choose.

:func:`plan` returns the ranked candidates of a config on this machine's cluster; the run of a
config with ``placement: auto`` takes the first one (:func:`resolve_auto_placement`, called by
``runners.run_support`` before its cluster starts) and writes it into the config, so the run's
``config.json`` records the placement and depth that ran.
"""

from __future__ import annotations

import json
import math

from infinirl.config import ConfigError
from infinirl.runtime.inventory import ClusterInventory, GiB
from infinirl.scheduler.profile import Profile, load_or_profile, profile_summary, workload_of
from infinirl.scheduler.search import PlanEntry, fixed_placements, search
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
         cache_dir: str | None = None, rounds: int = 1) -> tuple[Profile, list[PlanEntry]]:
    """``cfg``'s candidates on ``inventory`` (default: the cluster the profile ran on), best first."""
    model = runner_model(cfg)
    profile = load_or_profile(cfg, iterations=iterations, cache_dir=cache_dir, refresh=refresh, rounds=rounds)
    inventory = inventory or ClusterInventory.from_dict(profile.inventory)
    return profile, search(cfg, model, workload_of(cfg, profile), inventory)


def resolve_auto_placement(cfg, **plan_options) -> PlanEntry:
    """Write the best candidate's placement and depth into ``cfg`` (``placement: auto``)."""
    _, entries = plan(cfg, **plan_options)
    if not entries:
        raise ConfigError(f"placement=auto: no placement of {', '.join(cfg.components())} fits this cluster's "
                          "devices and memory; give placement.* explicitly")
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
    """``infinirl plan``: the table on this machine's cluster, or on a simulated one (``--gpus``)."""
    import time

    from infinirl.scheduler.simulate import simulated_plan

    _check_plan_flags(args)
    runner_model(cfg)  # a runner without a model fails before anything runs
    profile = load_or_profile(cfg, iterations=args.profile_iterations, refresh=args.refresh,
                              rounds=args.profile_rounds)
    start = time.perf_counter()
    if args.gpus is None:
        inventory = ClusterInventory.from_dict(profile.inventory)
        entries = search(cfg, runner_model(cfg), workload_of(cfg, profile), inventory)
        where = "this cluster"
    else:
        try:
            _, entries = simulated_plan(cfg, profile, args.gpus, speedup=args.speedup, gpus_per_node=args.gpus_per_node)
        except ValueError as exc:
            raise ConfigError(f"--gpus: {exc}") from None
        where = f"a simulated cluster of {args.gpus} GPUs (batch x{args.gpus}, device x{args.speedup:g} speed)"
    print(format_plan(cfg, profile, entries, args.top))
    print(f"searched {len(entries)} candidates on {where} in {time.perf_counter() - start:.2f} s")
    return 0 if entries else 1
