"""`placement: auto` in a config, and the plan table."""

import types

import pytest

from infinirl.cli import build_config
from infinirl.config import ConfigError
from infinirl.runtime import ClusterInventory
from infinirl.scheduler.auto import format_plan, runner_model
from infinirl.scheduler.cost import WorkCost
from infinirl.scheduler.profile import Profile, workload_of
from infinirl.scheduler.search import search


def test_placement_auto_is_accepted_and_resolved_later():
    cfg = build_config("ppo_metaworld_reach", ["placement=auto"])[1]
    assert cfg.auto_placement and cfg.placement == "auto"
    explicit = build_config("ppo_metaworld_reach", [])[1]
    assert not explicit.auto_placement and explicit.placement == {"env": "0", "rollout": "0", "actor": "0"}


def test_a_placement_string_other_than_auto_is_one_line_naming_the_fix():
    with pytest.raises(ConfigError, match="placement='fastest'.*'auto'"):
        build_config("ppo_metaworld_reach", ["placement=fastest"])


def test_a_runner_without_a_model_is_refused_by_name():
    cfg = types.SimpleNamespace(runner="unmodelled")  # a runner the scheduler knows nothing of
    with pytest.raises(ConfigError, match="no model of the 'unmodelled' runner; it plans embodied, .*realworld_sac, "
                                          "reasoning, sac. Give placement"):
        runner_model(cfg)


def test_the_plan_table_lists_candidates_best_first():
    cfg = build_config("ppo_metaworld_reach", [])[1]
    costs = {"collect/env": WorkCost(per_unit_s=1e-3, memory_fixed_bytes=2**30),
             "collect/rollout": WorkCost(per_unit_s=1e-3, memory_fixed_bytes=2**30),
             "update/actor": WorkCost(per_unit_s=1e-3, memory_fixed_bytes=2**30)}
    inventory = ClusterInventory.cpu_only(1, 2)
    profile = Profile(runner="embodied", key={}, costs=costs, overhead_s=0.0, hop_s=0.0,
                      inventory=inventory.to_dict(), probes=[])
    entries = search(cfg, runner_model(cfg), workload_of(cfg, profile), inventory)
    text = format_plan(cfg, profile, entries, top=3)
    lines = text.splitlines()
    assert "candidate placements of embodied" in lines[0] and "rollout.pipeline_stages" in lines[0]
    assert lines[2].split()[0] == "1" and "env=" in lines[2]
    assert f"... {len(entries) - 3} more" in text
