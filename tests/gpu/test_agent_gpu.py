"""Multi-turn agent rollouts on a real GPU: the loop over the HF engine on CUDA gives the trainer's
log-probs on the model's tokens and zeros on the environment's, and the reasoning runner trains an
agent with trainer and rollout on GPU 0 and resumes exactly. Skipped without CUDA (conftest.py)."""

import json

import pytest
import torch

from infinirl.agents.loop import AgentBudget, AgentRollout
from infinirl.data.batch import ATTENTION_MASK, INPUT_IDS, POSITION_IDS, RESPONSE_MASK, ROLLOUT_LOGPROBS, pack_sequences
from infinirl.engines.base import SamplingParams
from infinirl.engines.hf_generate import HFGenerateEngine
from infinirl.runners.reasoning import run
from tests.integration.resume import killed_after_checkpoint
from tests.integration.test_agent_pipeline import AGENT
from tests.integration.test_reasoning_pipeline import make_cfg
from tests.unit.agents.test_agent_loop import PROMPTS, CountingEnv

pytestmark = pytest.mark.gpu


def test_agent_loop_on_cuda_scores_model_tokens_like_the_trainer():
    from infinirl.models.hf_causal_lm import tiny_causal_lm

    model, tokenizer = tiny_causal_lm(tokenizer="byte", seed=0)
    model = model.cuda()
    engine = HFGenerateEngine(model, tokenizer, max_batch_size=64, eos_token_ids=[])
    budget = AgentBudget(max_turns=4, max_response_tokens=80, schedule="lockstep")
    results = AgentRollout(engine, tokenizer, CountingEnv, budget).generate(
        PROMPTS, SamplingParams(n=2, max_new_tokens=16, seed=3))
    assert max(r.extra["agent"]["turns"] for r in results) >= 2 and any(0 in r.response_mask for r in results)
    batch = pack_sequences([r.prompt_ids for r in results], [r.response_ids for r in results],
                           tokenizer.pad_token_id, [r.response_logprobs for r in results],
                           [r.response_mask for r in results])
    with torch.no_grad():
        logits = model(input_ids=batch[INPUT_IDS].cuda(), attention_mask=batch[ATTENTION_MASK].cuda(),
                       position_ids=batch[POSITION_IDS].cuda()).logits.float().cpu()
    scored = torch.zeros_like(batch[ROLLOUT_LOGPROBS])
    scored[:, 1:] = torch.log_softmax(logits[:, :-1], dim=-1).gather(-1, batch[INPUT_IDS][:, 1:, None]).squeeze(-1)
    mask = batch[RESPONSE_MASK].bool()
    torch.testing.assert_close(batch[ROLLOUT_LOGPROBS][mask], scored[mask], atol=1e-3, rtol=0)
    for r in results:
        assert all(lp == 0.0 for lp, m in zip(r.response_logprobs, r.response_mask, strict=True) if not m)


def test_agent_training_on_one_gpu_resumes_exactly(ray_cluster, tiny_llama_dir, tmp_path):
    problems = tmp_path / "problems.jsonl"  # a data file: the GPU image need not carry reasoning-gym
    problems.write_text("".join(json.dumps({"question": f"What is {i} + {i}?", "answer": str(2 * i)}) + "\n"
                                for i in range(40)))
    on_gpu = {"placement": {"actor": "0", "rollout": "0", "reward": "0"},
              "task": {"source": "dataset", "name": str(problems), "eval_size": 2}}
    straight = run(make_cfg(tiny_llama_dir, tmp_path / "straight", iterations=4, **AGENT, **on_gpu))
    killed_after_checkpoint(tmp_path / "straight", tmp_path / "resumed", 2)
    resumed = run(make_cfg(tiny_llama_dir, tmp_path / "resumed", iterations=4, **AGENT, **on_gpu))
    assert resumed["actor_weights_sha256"] == straight["actor_weights_sha256"]
    rows = [json.loads(line) for line in (tmp_path / "straight" / "metrics.jsonl").read_text().splitlines()]
    train = rows[1:]
    assert all(r["agent/turns_mean"] > 1 for r in train)
    assert all(r["train/logprob_mismatch_mean"] < 1e-2 for r in train)
    assert any(r["train/grad_norm"] > 0 for r in train)
