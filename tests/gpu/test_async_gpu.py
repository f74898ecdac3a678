"""Asynchronous training (``algorithm.asynchronous.max_staleness: 1``) on a real GPU: both runners
with the trainer and the rollout sharing GPU 0 (weights by CUDA IPC, published without waiting for
the rollout), the schedule's staleness, and an exact resume. Skipped without CUDA (conftest.py)."""

import json

import pytest

from infinirl.runners.reasoning import run as run_reasoning
from tests.integration.resume import killed_after_checkpoint
from tests.integration.test_reasoning_pipeline import make_cfg as reasoning_cfg

pytestmark = pytest.mark.gpu


def trained_rows(run_dir, key):
    rows = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    return [r for r in rows if key in r]


def test_reasoning_eta_1_on_one_gpu_is_one_version_stale_and_resumes_exactly(ray_cluster, tiny_llama_dir, tmp_path):
    problems = tmp_path / "problems.jsonl"  # a data file: the GPU image need not carry reasoning-gym
    problems.write_text("".join(json.dumps({"question": f"What is {i} + {i}?", "answer": str(2 * i)}) + "\n"
                                for i in range(40)))
    eta1 = {"algorithm": {"asynchronous": {"max_staleness": 1}, "objective": {"is_cap": 2.0, "is_cap_mode": "mask"}},
            "placement": {"actor": "0", "rollout": "0", "reward": "0"},
            "task": {"source": "dataset", "name": str(problems), "eval_size": 2,
                     "verifier": "infinirl.tasks.toy_rewards:response_length"}}
    straight = run_reasoning(reasoning_cfg(tiny_llama_dir, tmp_path / "straight", iterations=4, **eta1))
    rows = trained_rows(tmp_path / "straight", "train/loss")
    assert [r["async/staleness_max"] for r in rows] == [0.0, 1.0, 1.0, 1.0]
    assert rows[0]["train/logprob_mismatch_mean"] < 1e-2  # rollout and trainer agree on the GPU too
    killed_after_checkpoint(tmp_path / "straight", tmp_path / "resumed", 2)
    resumed = run_reasoning(reasoning_cfg(tiny_llama_dir, tmp_path / "resumed", iterations=4, **eta1))
    resumed_rows = trained_rows(tmp_path / "resumed", "train/loss")
    assert [r["rollout/reward_mean"] for r in resumed_rows] == [r["rollout/reward_mean"] for r in rows]
    assert resumed["actor_weights_sha256"] == straight["actor_weights_sha256"]


def test_embodied_eta_1_on_one_gpu_resumes_exactly(ray_cluster, tmp_path):
    pytest.importorskip("gymnasium")
    from tests.integration.test_embodied_pipeline import straight_and_resumed

    algorithm = {"epochs": 2, "mini_batches": 4, "asynchronous": {"max_staleness": 1}, "is_cap": 2.0,
                 "is_cap_mode": "mask"}
    straight, _ = straight_and_resumed(tmp_path, 4, {"env": "0", "rollout": "0", "actor": "0"}, 1,
                                       algorithm=algorithm)
    assert straight["devices"] == {"rollout": "cuda:0", "actor": "cuda:0"}
    trained = trained_rows(tmp_path / "straight", "train/policy_loss")
    assert [r["async/staleness_max"] for r in trained] == [0.0, 1.0, 1.0, 1.0]
    assert trained[0]["train/behaviour_logprob_abs_diff"] < 1e-4 < trained[2]["train/behaviour_logprob_abs_diff"]


def test_partial_rollout_switch_on_cuda_matches_per_version_references():
    from tests.unit.engines.test_hf_generate import switch_mid_generation

    switch_mid_generation("cuda", 4)
