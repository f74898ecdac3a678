"""The first iterations of every runner on a tiny problem, pinned: a change in what a runner learns
(an estimator, a loss, a default, the order data is drawn in) changes these numbers and fails
here, in the default suite, without running the slow learning tests.

Each runner runs 2 iterations from fixed seeds; the metrics after them are compared with
``pinned_metrics.json``. A deliberate change of learning behaviour re-pins them:
``INFINIRL_REPIN=1 pytest tests/integration/test_pinned_metrics.py`` rewrites the file, and the
diff of that file shows in review what changed.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from infinirl.config import to_dataclass

PINS = Path(__file__).with_name("pinned_metrics.json")
# Loose enough for float rounding across CPUs and thread counts over two iterations, tight enough
# that any change to an estimator, loss or data order moves a value past it.
RELATIVE, ABSOLUTE = 2e-3, 1e-5


def _reasoning(tmp_path, model_dir):
    from infinirl.runners.reasoning import run
    from infinirl.runners.reasoning_config import ReasoningConfig

    cfg = to_dataclass(ReasoningConfig, {
        "iterations": 2, "prompts_per_step": 2, "output_dir": str(tmp_path), "loggers": [], "resume": False,
        "model": {"path": model_dir}, "rollout": {"group_size": 4, "max_new_tokens": 6},
        "task": {"eval_size": 2, "verifier": "infinirl.tasks.toy_rewards:response_length"},
        "actor": {"lr": 1e-3, "micro_batch_size": 4}, "eval": {"every": 2}, "cluster": {"log_to_driver": False}})
    run(cfg)
    return ["rollout/reward_mean", "rollout/response_length_mean", "train/loss", "train/grad_norm",
            "train/clip_fraction", "eval/greedy_accuracy"]


def _embodied(tmp_path, model_dir):
    from infinirl.runners.embodied import run
    from infinirl.runners.embodied_config import EmbodiedConfig

    cfg = to_dataclass(EmbodiedConfig, {
        "iterations": 2, "rollout_steps": 32, "output_dir": str(tmp_path), "loggers": [], "resume": False,
        "env": {"name": "gym:Pendulum-v1", "num_envs": 4}, "algorithm": {"epochs": 2, "mini_batches": 4},
        "eval": {"every": 2, "episodes": 2, "num_envs": 2, "video_episodes": 0},
        "cluster": {"log_to_driver": False}})
    run(cfg)
    return ["rollout/reward_mean", "train/policy_loss", "train/value_loss", "train/approx_kl", "train/grad_norm",
            "train/advantage_std", "eval/return_mean"]


def _sac(tmp_path, model_dir):
    from infinirl.runners.sac import run
    from infinirl.runners.sac_config import SACConfig

    cfg = to_dataclass(SACConfig, {
        "iterations": 2, "steps_per_iteration": 40, "output_dir": str(tmp_path), "loggers": [], "resume": False,
        "env": {"name": "gym:Pendulum-v1", "num_envs": 2},
        "network": {"actor_hidden": [32, 32], "critic_hidden": [32, 32]},
        "algorithm": {"batch_size": 16, "learning_starts": 50, "utd_ratio": 0.5},
        "buffer": {"capacity": 200}, "eval": {"every": 2, "episodes": 2, "num_envs": 2, "video_episodes": 0},
        "cluster": {"log_to_driver": False}})
    run(cfg)
    return ["rollout/reward_mean", "train/critic_loss", "train/actor_loss", "train/alpha", "eval/return_mean"]


RUNNERS = {"reasoning": _reasoning, "embodied": _embodied, "sac": _sac}


@pytest.mark.parametrize("runner", list(RUNNERS))
def test_first_iterations_match_the_pinned_metrics(ray_cluster, tiny_llama_dir, tmp_path, runner):
    if runner != "reasoning":
        pytest.importorskip("gymnasium")
    keys = RUNNERS[runner](tmp_path, tiny_llama_dir)
    rows = [json.loads(line) for line in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    measured = {f"{row['step']}:{key}": row[key] for row in rows for key in keys if key in row}
    pins = json.loads(PINS.read_text()) if PINS.exists() else {}
    if os.environ.get("INFINIRL_REPIN"):
        pins[runner] = measured
        PINS.write_text(json.dumps(pins, indent=2, sort_keys=True) + "\n")
        return
    assert runner in pins, f"no pinned metrics for {runner}: run with INFINIRL_REPIN=1 once"
    assert set(measured) == set(pins[runner]), "the runner logs other metrics than were pinned"
    for key, expected in pins[runner].items():
        assert measured[key] == pytest.approx(expected, rel=RELATIVE, abs=ABSOLUTE), key
