"""The reasoning runner with multi-turn agent rollouts, end to end on a tiny random model: the
environment's tokens are in the trajectories but not trained on, and the run resumes exactly."""

import json

from infinirl.runners.reasoning import run
from tests.integration.pins import check_pinned
from tests.integration.resume import killed_after_checkpoint
from tests.integration.test_reasoning_pipeline import make_cfg

# A random model's tokens contain an "e" often: every trajectory really takes several turns.
# Sampled at 0.6: the trainer must score the model's tokens with logits / 0.6 too, not the untempered policy.
AGENT = {"rollout": {"group_size": 2, "max_new_tokens": 6, "temperature": 0.6,
                     "agent": {"env": "infinirl.agents.toy_envs:EchoEnv", "env_options": {"answers": 2},
                               "max_turns": 3, "max_response_tokens": 40, "schedule": "lockstep"}}}


def test_agent_rollouts_train_on_model_tokens_and_resume_exactly(ray_cluster, tiny_llama_dir, tmp_path):
    straight = run(make_cfg(tiny_llama_dir, tmp_path / "straight", iterations=4, **AGENT))
    killed_after_checkpoint(tmp_path / "straight", tmp_path / "resumed", 2)
    resumed = run(make_cfg(tiny_llama_dir, tmp_path / "resumed", iterations=4, **AGENT))
    assert resumed["actor_weights_sha256"] == straight["actor_weights_sha256"]

    rows = [json.loads(line) for line in (tmp_path / "straight" / "metrics.jsonl").read_text().splitlines()]
    train = rows[1:]
    assert all(r["agent/turns_mean"] > 1 for r in train), "trajectories take several turns"
    assert all(r["agent/observation_tokens_mean"] > 0 for r in train)
    assert all(r["agent/echoes_mean"] > 0 for r in train)
    assert all(r["agent/knows_problem_mean"] == r["agent/echoes_mean"] for r in train), "envs get their problem"
    # the trainer scores the model's tokens as the rollout sampled them (at its temperature),
    # environment tokens excluded
    assert all(r["train/logprob_mismatch_mean"] < 1e-3 for r in train)
    assert any(r["train/grad_norm"] > 0 for r in train)
    check_pinned("reasoning_agent", tmp_path / "straight", [
        "rollout/reward_mean", "rollout/response_length_mean", "agent/turns_mean", "agent/observation_tokens_mean",
        "train/loss", "train/grad_norm"])

