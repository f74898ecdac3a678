"""The main job learns: GRPO on the embedded SmolLM2-135M (slow).

This runs the shipped `default` config itself (what `infinirl train` runs, all 40 iterations) and
asserts 80% held-out greedy accuracy at its end, so a change that slows learning or breaks the
default config fails here rather than in a user's first run.
"""

import json

import pytest

from infinirl.config import compose, to_dataclass
from infinirl.runners.reasoning import run
from infinirl.runners.reasoning_config import ReasoningConfig


@pytest.mark.slow
def test_main_job_reaches_80_percent_heldout_greedy_accuracy(ray_cluster, tmp_path):
    raw = compose("default")
    raw.update({"save_every": 0, "output_dir": str(tmp_path), "resume": False})
    raw["eval"] = {**raw.get("eval", {}), "every": 10}
    raw["cluster"] = {**raw.get("cluster", {}), "log_to_driver": False}
    summary = run(to_dataclass(ReasoningConfig, raw))
    rows = [json.loads(line) for line in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    rewards = [r["rollout/reward_mean"] for r in rows if "rollout/reward_mean" in r]
    assert sum(rewards[-5:]) / 5 > sum(rewards[:5]) / 5 + 0.2, rewards
    assert summary["eval_before"] < 0.5, summary  # the task is not solved before training
    assert summary["eval_after"] >= 0.8, summary
    assert all(r["train/logprob_mismatch_mean"] < 0.1 for r in rows if "train/logprob_mismatch_mean" in r)
