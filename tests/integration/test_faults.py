"""Faults in a real run: a component dying mid-step stops the run within seconds with a report that
names it, instead of hanging; the output and checkpoints written before stay usable."""

from __future__ import annotations

import re
import time

import pytest

from infinirl.config import to_dataclass
from infinirl.runtime.errors import WorkerError


def test_a_reward_worker_killed_mid_step_is_reported_not_waited_for(ray_cluster, tiny_llama_dir, tmp_path,
                                                                    deliberate_deaths):
    from infinirl.runners.reasoning import run
    from infinirl.runners.reasoning_config import ReasoningConfig

    cfg = to_dataclass(ReasoningConfig, {
        "iterations": 2, "prompts_per_step": 2, "output_dir": str(tmp_path), "loggers": [], "resume": False,
        "model": {"path": tiny_llama_dir}, "rollout": {"group_size": 2, "max_new_tokens": 4},
        "task": {"eval_size": 2, "verifier": "infinirl.tasks.toy_rewards:kill_own_process"},
        "eval": {"at_start": False}, "actor": {"micro_batch_size": 2}, "cluster": {"log_to_driver": False}})
    start = time.monotonic()
    with pytest.raises(WorkerError, match=r"reward\[rank 0\]") as failure:
        run(cfg)
    assert time.monotonic() - start < 120  # start-up included; a hang would be cut by the suite's timeout
    pid = re.search(r"pid (\d+)", str(failure.value))
    deliberate_deaths(int(pid.group(1)) if pid else 0)  # Ray's own report of the kill stays out of the log
