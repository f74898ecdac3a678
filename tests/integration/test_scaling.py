"""Online scaling of the embodied runner's env component: 1 -> 2 -> 1 ranks while it trains.

Commands arrive through the command file the run polls between iterations. Every iteration's
samples are complete (each env's ``rollout_steps`` decisions, counted), and the run ends with the
weights of the same run without scaling, bit for bit: on Pendulum every iteration starts from
seeded resets and no episode ends within one, so where a stage is simulated changes nothing."""

import json
import os
import threading
import time

import pytest

pytest.importorskip("gymnasium")

from infinirl.config import ConfigError, to_dataclass  # noqa: E402
from infinirl.runners.embodied import run  # noqa: E402
from infinirl.runners.embodied_config import EmbodiedConfig  # noqa: E402

NUM_ENVS, STEPS, ITERATIONS = 4, 16, 7


def make_cfg(output_dir, **extra):
    raw = {
        "iterations": ITERATIONS, "rollout_steps": STEPS, "output_dir": str(output_dir), "save_every": 0,
        "env": {"name": "gym:Pendulum-v1", "num_envs": NUM_ENVS},
        "algorithm": {"epochs": 1, "mini_batches": 2},
        "rollout": {"pipeline_stages": 2},
        "eval": {"every": 0, "episodes": 2, "num_envs": 2, "video_episodes": 0},
        "placement": {"env": "0", "rollout": "1", "actor": "0-1"}, "cluster": {"log_to_driver": False},
        **extra,
    }
    return to_dataclass(EmbodiedConfig, raw)


def rows_of(output_dir) -> list[dict]:
    path = os.path.join(output_dir, "metrics.jsonl")
    if not os.path.exists(path):
        return []
    return [json.loads(line) for line in open(path).read().splitlines() if line.strip()]


def send_commands(output_dir, commands: list[tuple[int, dict]], errors: list) -> None:
    """Write each command once the run has logged iteration ``after``, and the previous one was taken."""
    command_file = os.path.join(output_dir, "scale.json")
    try:
        for after, command in commands:
            deadline = time.monotonic() + 600
            while not any(r["step"] >= after for r in rows_of(output_dir)) or os.path.exists(command_file):
                if time.monotonic() > deadline:
                    raise TimeoutError(f"the run never reached iteration {after}")
                time.sleep(0.05)
            if os.path.exists(command_file + ".applied"):
                os.remove(command_file + ".applied")
            with open(command_file + ".tmp", "w") as handle:
                json.dump(command, handle)
            os.replace(command_file + ".tmp", command_file)  # the run never reads half a command
    except BaseException as exc:
        errors.append(exc)


@pytest.mark.slow  # default-tier budget; run with pytest -m slow
def test_env_scales_1_2_1_mid_training_with_every_sample_complete(ray_cluster, tmp_path):
    scaled_dir = tmp_path / "scaled"
    errors: list = []
    sender = threading.Thread(target=send_commands, args=(str(scaled_dir), [(2, {"env": 2}), (4, {"env": 1})],
                                                          errors), daemon=True)
    sender.start()
    scaled = run(make_cfg(scaled_dir))
    sender.join(timeout=60)
    assert not errors, errors
    rows = [r for r in rows_of(scaled_dir) if r["step"] > 0]
    assert [r["step"] for r in rows] == list(range(1, ITERATIONS + 1))
    ranks = [int(r["env/ranks"]) for r in rows]
    assert [n for i, n in enumerate(ranks) if i == 0 or ranks[i - 1] != n] == [1, 2, 1], ranks
    # every iteration collected every env's decisions, whatever served them
    steps = [0] + [int(r["env/steps"]) for r in rows]
    assert [b - a for a, b in zip(steps, steps[1:])] == [NUM_ENVS * STEPS] * ITERATIONS
    assert all(r["train/grad_norm"] > 0 for r in rows)
    assert os.path.exists(scaled_dir / "scale.json.applied")

    fixed = run(make_cfg(tmp_path / "fixed", scaling={"commands": False}))
    fixed_rows = [r for r in rows_of(tmp_path / "fixed") if r["step"] > 0]
    assert all(int(r["env/ranks"]) == 1 for r in fixed_rows)
    assert [r["rollout/reward_mean"] for r in rows] == [r["rollout/reward_mean"] for r in fixed_rows]
    assert scaled["actor_weights_sha256"] == fixed["actor_weights_sha256"]


@pytest.mark.slow  # default-tier budget; run with pytest -m slow tests/integration
def test_a_command_the_layout_cannot_take_is_refused_and_the_run_goes_on(ray_cluster, tmp_path):
    out = tmp_path / "run"
    errors: list = []
    # 3 env ranks cannot share the rollout rank's 2 pipeline stages
    sender = threading.Thread(target=send_commands, args=(str(out), [(1, {"env": 3})], errors), daemon=True)
    sender.start()
    run(make_cfg(out, iterations=3))
    sender.join(timeout=60)
    assert not errors, errors
    assert os.path.exists(out / "scale.json.rejected")
    assert all(int(r["env/ranks"]) == 1 for r in rows_of(out) if r["step"] > 0)


@pytest.mark.slow  # default-tier budget; run with pytest -m slow tests/integration
def test_the_busy_ratio_policy_grows_the_env_when_it_is_the_bottleneck(ray_cluster, tmp_path):
    # grow_above=0.01 makes every iteration's env the bottleneck: after `patience` iterations, a rank more
    out = tmp_path / "run"
    run(make_cfg(out, iterations=4, scaling={"commands": False, "auto": True, "grow_above": 0.01,
                                             "shrink_below": 0.0, "patience": 2, "max_ranks": 2}))
    ranks = [int(r["env/ranks"]) for r in rows_of(out) if r["step"] > 0]
    assert ranks == [1, 1, 2, 2]


@pytest.mark.slow  # two runs; default-tier budget
def test_a_resumed_run_keeps_the_env_rank_count_it_was_scaled_to(ray_cluster, tmp_path):
    out = tmp_path / "run"
    errors: list = []
    sender = threading.Thread(target=send_commands, args=(str(out), [(1, {"env": 2})], errors), daemon=True)
    sender.start()
    run(make_cfg(out, iterations=3, save_every=3))
    sender.join(timeout=60)
    assert not errors, errors
    assert [int(r["env/ranks"]) for r in rows_of(out) if r["step"] > 0][-1] == 2
    run(make_cfg(out, iterations=5, save_every=0, scaling={"commands": False}))
    resumed = [int(r["env/ranks"]) for r in rows_of(out) if r["step"] > 3]
    assert resumed == [2, 2], resumed


def test_scaling_settings_that_contradict_each_other_are_refused():
    with pytest.raises(ConfigError, match="scaling.shrink_below"):
        make_cfg("/tmp/unused", scaling={"grow_above": 0.2, "shrink_below": 0.5})


def test_env_shares_split_each_rollout_ranks_stages_evenly():
    from infinirl.components.env_worker import env_shares, stage_seeds

    assert env_shares(1, 1, 2) == [(0, (0, 1))]
    assert env_shares(2, 1, 2) == [(0, (0,)), (0, (1,))]
    assert env_shares(4, 2, 4) == [(0, (0, 1)), (0, (2, 3)), (1, (0, 1)), (1, (2, 3))]
    with pytest.raises(ValueError, match="multiple of rollout ranks"):
        env_shares(3, 2, 2)
    with pytest.raises(ValueError, match="cannot share its 2 pipeline stage"):
        env_shares(3, 1, 2)
    seeds = [10, 11, 12, 13, 14]  # stages of 3 and 2 envs
    assert stage_seeds(seeds, [3, 2], (1,)) == [13, 14]
    assert stage_seeds(seeds, [3, 2], (0, 1)) == seeds
