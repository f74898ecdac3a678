"""GRPO on the embedded SmolLM2-135M learns single-digit additions (slow: minutes on 2 cores)."""

import json

import pytest

from infinirl.config import to_dataclass
from infinirl.runners.reasoning import run
from infinirl.runners.reasoning_config import ReasoningConfig


@pytest.mark.slow
def test_grpo_raises_reward_and_heldout_accuracy(ray_cluster, tmp_path):
    cfg = to_dataclass(ReasoningConfig, {
        "steps": 12, "prompts_per_step": 8, "eval_every": 12, "output_dir": str(tmp_path), "resume": False,
        "loggers": [], "num_threads": 2,
        "model": {"rollout_dtype": "bfloat16"},
        "task": {"config": {"min_terms": 2, "max_terms": 2, "min_digits": 1, "max_digits": 1}, "eval_size": 32,
                 "system_prompt": "Answer with the number only."},
        "rollout": {"group_size": 8, "max_new_tokens": 24},
        "algorithm": {"objective": {"clip_high": 0.28}},
        "actor": {"lr": 2e-4, "micro_batch_size": 16, "param_dtype": "bfloat16",
                  "lora": {"r": 16, "alpha": 32, "target_modules": "all-linear"}},
        "cluster": {"log_to_driver": False},
    })
    summary = run(cfg)
    rows = [json.loads(line) for line in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    rewards = [r["rollout/reward_mean"] for r in rows if "rollout/reward_mean" in r]
    assert sum(rewards[-4:]) / 4 > sum(rewards[:4]) / 4 + 0.05, rewards
    assert summary["eval_after"] >= summary["eval_before"], summary
