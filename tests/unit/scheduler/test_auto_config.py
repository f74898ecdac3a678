"""`placement: auto` in a config, and the plan table."""

import json
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
             "update/actor": WorkCost(per_unit_s=1e-3, memory_fixed_bytes=2**30),
             "sync/actor": WorkCost(per_unit_s=0.0, fixed_s=0.01), "sync/rollout": WorkCost(per_unit_s=0.0)}
    inventory = ClusterInventory.cpu_only(1, 2)
    profile = Profile(runner="embodied", key={}, costs=costs, overhead_s=0.0, hop_s=0.0,
                      inventory=inventory.to_dict(), probes=[])
    entries = search(cfg, runner_model(cfg), workload_of(cfg, profile), inventory)
    text = format_plan(cfg, profile, entries, top=3)
    lines = text.splitlines()
    assert "candidate placements of embodied" in lines[0] and "rollout.pipeline_stages" in lines[0]
    assert lines[2].split()[0] == "1" and "env=" in lines[2]
    assert lines[2].endswith("]") and "[collect " in lines[2] and " + sync " in lines[2]  # seconds per phase
    assert f"... {len(entries) - 3} more" in text


def _embodied_profile(inventory):
    costs = {"collect/env": WorkCost(per_unit_s=1e-3, memory_fixed_bytes=2**30),
             "collect/rollout": WorkCost(per_unit_s=1e-3, memory_fixed_bytes=2**30),
             "update/actor": WorkCost(per_unit_s=1e-3, memory_fixed_bytes=2**30),
             "sync/actor": WorkCost(per_unit_s=0.0, fixed_s=0.01), "sync/rollout": WorkCost(per_unit_s=0.0)}
    return Profile(runner="embodied", key={}, costs=costs, overhead_s=0.0, hop_s=0.0,
                   inventory=inventory.to_dict(), probes=[])


def test_auto_for_some_components_searches_only_those():
    cfg = build_config("ppo_metaworld_reach", ["placement.actor=auto", "placement.env=0-1", "placement.rollout=0-1"])[1]
    assert cfg.auto_placement and cfg.pinned_placement() == {"env": "0-1", "rollout": "0-1"}
    inventory = ClusterInventory.cpu_only(1, 2)
    entries = search(cfg, runner_model(cfg), workload_of(cfg, _embodied_profile(inventory)), inventory)
    assert {e.placement["actor"] for e in entries} == {"0", "1", "0-1"}  # every range for the auto one
    assert all(e.placement["env"] == "0-1" and e.placement["rollout"] == "0-1" for e in entries)
    assert entries[0].candidate.allocations["env"].ranks == 2  # a pinned component keeps its ranks
    assert "fixed (not searched): env=0-1, rollout=0-1" in format_plan(cfg, None, entries)
    full = build_config("ppo_metaworld_reach", [])[1]  # `infinirl plan` of an explicit config searches all
    assert len(search(full, runner_model(full), workload_of(full, _embodied_profile(inventory)), inventory)) > len(
        entries)


def test_auto_for_some_components_checks_the_others_and_names_the_key():
    with pytest.raises(ConfigError, match="placement.critic: the embodied runner has no such component"):
        build_config("ppo_metaworld_reach", ["placement.critic=auto"])
    with pytest.raises(ConfigError, match="placement.env"):
        build_config("ppo_metaworld_reach", ["placement.actor=auto", "placement.env=zero"])
    kept = ["placement.actor=auto", "placement.rollout=0-1"]
    cfg = build_config("ppo_metaworld_reach", [*kept, "placement.env='0,1'"])[1]
    inventory = ClusterInventory.cpu_only(1, 2)
    # "0,1" is contiguous; a gap is refused where the scheduler sees the cluster
    assert search(cfg, runner_model(cfg), workload_of(cfg, _embodied_profile(inventory)), inventory)
    gap = build_config("ppo_metaworld_reach", [*kept, "placement.env='0,2'"])[1]
    with pytest.raises(ConfigError, match=r"placement.env='0,2': beside components placed 'auto', give a contiguous"):
        search(gap, runner_model(gap), workload_of(gap, _embodied_profile(ClusterInventory.cpu_only(1, 4))),
               ClusterInventory.cpu_only(1, 4))


def test_no_placement_left_is_one_line_naming_the_reason_and_the_kept_key(tmp_path):
    """placement.env=0-2 beside auto components with 16 envs: the error says the envs do not split
    over 3 env ranks and names the key kept as written, not "devices and memory"."""
    from infinirl.scheduler import profile as profiling
    from infinirl.scheduler.auto import resolve_auto_placement

    cfg = build_config("ppo_metaworld_reach", ["placement.env=0-2", "placement.rollout=auto", "placement.actor=auto",
                                               "env.num_envs=16"])[1]
    inventory = ClusterInventory.cpu_only(1, 4)
    profile = _embodied_profile(inventory)
    key = profiling.profile_key(cfg, runner_model(cfg), inventory)
    profile = Profile(**{**vars(profile), "key": key})
    with open(profiling.cache_path(key, str(tmp_path)), "w") as handle:
        json.dump(profile.to_dict(), handle)
    with pytest.raises(ConfigError) as error:
        resolve_auto_placement(cfg, inventory, cache_dir=str(tmp_path))
    message = str(error.value)
    assert "\n" not in message
    assert message.startswith("placement=auto: no placement of env, rollout, actor fits this cluster (4 CPU slots): "
                              "env.num_envs=16 is not divisible by 3 env ranks (")
    assert "with placement.env=0-2 (3 ranks) kept as written; give placement.* explicitly" in message


@pytest.mark.parametrize(("flags", "named"), [(["--gpus", "8", "--gpus-per-node", "0"], "--gpus-per-node 0"),
                                              (["--gpus", "8", "--speedup", "0"], "--speedup 0"),
                                              (["--gpus", "8", "--speedup", "-2"], "--speedup -2"),
                                              (["--gpus", "8", "--speedup", "nan"], "--speedup nan"),
                                              (["--gpus", "0"], "--gpus 0")])
def test_plan_flags_out_of_range_are_one_line_naming_the_flag(flags, named, capsys):
    from infinirl.cli import main

    assert main(["plan", "ppo_metaworld_reach", *flags]) == 2  # before any cluster starts
    err = capsys.readouterr().err.strip()
    assert named in err and len(err.splitlines()) == 1


def test_simulated_cluster_parameters_are_checked_by_name():
    from infinirl.scheduler.simulate import scaled_workload, simulated_inventory

    with pytest.raises(ValueError, match="gpus_per_node=0"):
        simulated_inventory(8, gpus_per_node=0)
    cfg = build_config("ppo_metaworld_reach", [])[1]
    with pytest.raises(ValueError, match="speedup=0"):
        scaled_workload(cfg, _embodied_profile(ClusterInventory.cpu_only(1, 2)), speedup=0.0)
