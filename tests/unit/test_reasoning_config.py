"""Reasoning config: bad values fail at validation, naming the key and the valid choices."""

import pytest

from infinirl.config import ConfigError, to_dataclass
from infinirl.engines.vllm_process import vllm_available
from infinirl.runners.reasoning_config import ReasoningConfig


def build(**raw):
    return to_dataclass(ReasoningConfig, raw)


def test_defaults_validate():
    cfg = build()
    assert cfg.algorithm.advantage == "grpo" and cfg.rollout.group_size == 8


@pytest.mark.parametrize("raw, message", [
    ({"algorithm": {"advantage": "grpoo"}}, r"algorithm.advantage='grpoo' is not registered; registered: .*grpo"),
    ({"algorithm": {"objective": {"aggregation": "mean"}}},
     r"aggregation='mean' is not registered; registered: .*token-mean"),
    ({"algorithm": {"mini_batches": 3}},
     r"mini_batches=3 does not divide the batch of prompts_per_step\*group_size=64"),
    ({"algorithm": {"objective": {"kl_coef": -0.1}}}, r"algorithm.objective.kl_coef=-0.1 must be >= 0"),
    ({"algorithm": {"kl_reward_coef": -1}}, r"algorithm.kl_reward_coef=-1.0 must be >= 0"),
    ({"algorithm": {"kl_reward_estimator": "k4"}}, r"kl_reward_estimator='k4' is not registered; registered: .*k1"),
    ({"algorithm": {"kl_reward_coef": 0.1}}, r"kl_reward_coef > 0 with algorithm.advantage=grpo.*objective.kl_coef"),
    ({"algorithm": {"advantage": "gae", "advantage_kwargs": {"lam": 1.5}}},
     r"advantage_kwargs.lam=1.5 must be in \[0, 1\]"),
    ({"algorithm": {"advantage": "gae", "advantage_kwargs": {"lambda": 0.9}}}, r"gae takes gamma, lam, not lambda"),
    ({"algorithm": {"advantage": "grpo", "advantage_kwargs": {"gamma": 0.9}}},
     r"algorithm.advantage_kwargs: grpo takes eps, norm_by_std, not gamma"),
    ({"algorithm": {"advantage": "rloo", "advantage_kwargs": {"gamma": 0.9}}}, r"rloo takes no options, not gamma"),
    ({"rollout": {"engine_options": {"kv_cahce": 1}}},
     r"rollout.engine_options.kv_cahce: the hf engine takes eos_token_ids, pad_token_id$"),
    ({"rollout": {"engine_options": {"max_batch_size": 8}}},
     r"rollout.engine_options.max_batch_size: the runner sets it for the hf engine"),
    ({"rollout": {"engine": "vllm", "engine_options": {"kv_cache_byte": 1}}},
     r"rollout.engine_options.kv_cache_byte: the vllm engine takes .*kv_cache_bytes"),
    ({"seed": -1}, r"seed=-1 must be >= 0"),
    ({"reference": {"mode": "actor_base"}}, r"reference.mode=actor_base needs actor.lora"),
    ({"reference": {"mode": "copy"}}, r"reference.mode='copy' is not allowed.*auto, actor_base, separate"),
    ({"reference": {"micro_batch_size": 0}}, r"reference.micro_batch_size=0 must be >= 1"),
    ({"critic": {"value_clip": 0}}, r"critic.value_clip=0.0 must be > 0"),
    ({"critic": {"lr": 0}}, r"critic.lr=0.0 must be > 0"),
    ({"critic": {"model_path": "/no/critic"}}, r"critic.model_path='/no/critic' is not a folder"),
    ({"rollout": {"max_prompt_length": 0}}, r"rollout.max_prompt_length=0 must be >= 1"),
    ({"placement": {"actor": "0", "rollout": "0", "reward": "0", "critc": "0"}},
     r"placement.critc: the reasoning runner has no such component; its components are actor, rollout, reward"),
    ({"rollout": {"group_size": 0}}, r"rollout.group_size=0 must be >= 1"),
    ({"algorithm": {"asynchronous": {"max_staleness": -1}}}, r"algorithm.asynchronous.max_staleness=-1 must be >= 0"),
    ({"algorithm": {"asynchronous": {"max_staleness": 1}, "dynamic_sampling": True}},
     r"algorithm.dynamic_sampling with algorithm.asynchronous.*max_staleness=null"),
    ({"algorithm": {"asynchronous": {"partial_rollout": True}}},
     r"partial_rollout=true needs max_staleness >= 1 \(got None\) and rollout.engine=hf"),
    ({"algorithm": {"asynchronous": {"max_staleness": 1, "partial_rollout": True}}, "rollout": {"engine": "vllm"}},
     r"partial_rollout=true needs .*\(got 'vllm'\)"),
    ({"algorithm": {"objective": {"is_cap": 0}}}, r"algorithm.objective.is_cap=0.0 must be > 0"),
    ({"algorithm": {"objective": {"is_cap_mode": "clip"}}}, r"is_cap_mode='clip' is not allowed.*truncate, mask"),
    ({"loggers": ["tensorbord"]}, r"unknown logger 'tensorbord'"),
    ({"placement": {"actor": "0", "rollout": "0", "reward": "x"}}, r"placement.reward"),
    ({"task": {"source": "hub"}}, r"task.source='hub' is not registered; registered: code, dataset, fictional_kb, "
                                  r"reasoning_gym"),
    ({"task": {"verifier": "no_such"}}, r"task.verifier='no_such': unknown verifier 'no_such'; registered: .*math"),
    ({"task": {"verifier": "no.such.module:fn"}}, r"task.verifier='no.such.module:fn': cannot import module"),
    ({"actor": {"lr": -1e-3}}, r"actor.lr=-0.001 must be > 0"),
    ({"actor": {"micro_batch_size": 0}}, r"actor.micro_batch_size=0 must be >= 1"),
    ({"rollout": {"max_new_tokens": 0}}, r"rollout.max_new_tokens=0 must be >= 1"),
    ({"runner": "embodied"}, r"runner='embodied': this config is for the 'reasoning' runner"),
    ({"steps": 3, "iterations": 4}, r"both 'steps' and its new name 'iterations' are set"),
    ({"rollout": {"max_new_token": 5}}, r"Did you mean 'rollout.max_new_tokens'"),
    ({"model": {"path": "/no/such/model"}}, r"model.path='/no/such/model' is not a folder"),
    ({"rollout": {"temperature": 0.8}, "actor": {"temperature": 0.5}},
     r"actor.temperature=0.5 differs from rollout.temperature=0.8: .*remove actor.temperature"),
])
def test_bad_values_are_named(raw, message):
    with pytest.raises(ConfigError, match=message):
        build(**raw)


@pytest.mark.parametrize("actor", [{}, {"temperature": 0.6}])
def test_the_trainer_scores_at_the_rollout_temperature(actor):
    cfg = build(rollout={"temperature": 0.6}, actor=actor)
    assert cfg.actor.temperature == 0.6
    assert build().actor.temperature == 1.0
    assert cfg.resume_may_change("actor.temperature") and not cfg.resume_may_change("rollout.temperature")


def test_ppo_launches_a_critic_placed_with_the_actor_by_default():
    cfg = build(algorithm={"advantage": "gae", "advantage_kwargs": {"gamma": 1.0, "lam": 0.95}})
    assert cfg.uses_critic and cfg.reference_mode is None
    assert cfg.components() == ["actor", "rollout", "reward", "critic"]
    assert cfg.placement_spec()["critic"] == cfg.placement["actor"]
    assert cfg.critic_model_path == cfg.model.path and cfg.critic.lr == 1e-5


@pytest.mark.parametrize("raw, mode, components", [
    ({}, None, ["actor", "rollout", "reward"]),  # no KL term: no reference at all
    ({"algorithm": {"objective": {"kl_coef": 0.05}}}, "separate", ["actor", "rollout", "reward", "reference"]),
    ({"algorithm": {"objective": {"kl_coef": 0.05}}, "actor": {"lora": {"r": 8}}}, "actor_base",
     ["actor", "rollout", "reward"]),
    ({"algorithm": {"advantage": "gae", "kl_reward_coef": 0.05}, "actor": {"lora": {"r": 8}},
      "reference": {"mode": "separate"}}, "separate", ["actor", "rollout", "reward", "critic", "reference"]),
])
def test_reference_mode_resolves_explicitly(raw, mode, components):
    cfg = build(**raw)
    assert cfg.reference_mode == mode
    assert cfg.components() == components


def test_placement_keys_may_name_several_components():
    cfg = build(algorithm={"advantage": "gae"}, placement={"actor,critic": "0", "rollout,reward": "1"})
    assert cfg.placement_spec() == {"actor": "0", "rollout": "1", "reward": "1", "critic": "0"}


def test_the_old_tis_cap_key_still_sets_is_cap():
    from infinirl.config import upgrade_renamed_overrides

    assert upgrade_renamed_overrides(ReasoningConfig, ["algorithm.objective.tis_cap=2"]) == [
        "algorithm.objective.is_cap=2"]


# ----------------------------------------------------------------------------- response caps, cut-off responses

AGENT = {"env": "infinirl.agents.toy_envs:EchoEnv", "max_response_tokens": 64}


def test_the_response_cap_is_the_agent_trajectorys_with_an_agent():
    assert build(rollout={"max_new_tokens": 8}).max_response_tokens == 8
    assert build(rollout={"max_new_tokens": 8, "agent": AGENT}).max_response_tokens == 64
    build(rollout={"max_new_tokens": 8, "agent": AGENT}, algorithm={"overlong_buffer": 16})  # per-turn cap is 8


@pytest.mark.parametrize("rollout, message", [
    ({"max_new_tokens": 8}, r"algorithm.overlong_buffer=16 is longer than the response cap rollout.max_new_tokens=8"),
    ({"max_new_tokens": 8, "agent": {**AGENT, "max_response_tokens": 12}},
     r"overlong_buffer=16 .* rollout.agent.max_response_tokens=12; set it to at most 12"),
])
def test_an_overlong_buffer_longer_than_the_response_cap_is_refused(rollout, message):
    with pytest.raises(ConfigError, match=message):
        build(rollout=rollout, algorithm={"overlong_buffer": 16})


def test_truncated_reward_takes_keep_or_zero():
    assert build().algorithm.truncated_reward == "keep"
    with pytest.raises(ConfigError, match=r"algorithm.truncated_reward='drop' is not allowed.*keep, zero"):
        build(algorithm={"truncated_reward": "drop"})


class FakeGroup:
    """An actor group of one rank that records what it is asked to train on."""

    world_size = 1

    def __init__(self):
        self.calls = []

    def call_each(self, method, args):
        from types import SimpleNamespace

        self.calls.append((method, args))
        return SimpleNamespace(wait=lambda: [{"train/loss": 0.0}])


def flow_of(cfg, actor=None):
    from types import SimpleNamespace

    from infinirl.runners.reasoning import ReasoningFlow

    return ReasoningFlow(cfg, actor=actor, rollout=None, reward=None, tokenizer=SimpleNamespace(pad_token_id=0))


def batch_of(response_lengths):
    from infinirl.data.batch import pack_sequences

    return pack_sequences([[1, 2]] * len(response_lengths), [[3] * n for n in response_lengths], 0)


def test_agent_runs_shape_and_normalise_by_the_trajectory_cap():
    import torch

    from infinirl.algorithms import aggregation_normaliser, overlong_penalty

    # Responses up to 64 tokens, each turn at most 8: the 8-token turn cap is no length limit here.
    cfg = build(prompts_per_step=1, rollout={"group_size": 4, "max_new_tokens": 8, "agent": AGENT},
                algorithm={"advantage": "dr_grpo", "overlong_buffer": 16, "overlong_penalty": 1.0,
                           "objective": {"aggregation": "seq-mean-token-sum-norm"}})
    lengths = [10, 40, 56, 64]
    batch, rewards = batch_of(lengths), torch.ones(4)
    actor = FakeGroup()
    flow = flow_of(cfg, actor)
    flow.add_advantages(batch, rewards)
    shaped = rewards + overlong_penalty(torch.tensor(lengths), 64, 16, 1.0)
    assert shaped.tolist() == [1.0, 1.0, 0.5, 0.0]  # only the last 16 of 64 tokens are penalised
    mask = batch["response_mask"]
    expected = (shaped - shaped.mean())[:, None] * mask  # dr_grpo: the group mean as baseline
    torch.testing.assert_close(batch["advantages"], expected.float())
    flow.update(batch)
    (method, shares), = actor.calls
    assert method == "train_step"
    assert shares[0][1] == aggregation_normaliser(mask, "seq-mean-token-sum-norm", max_response_length=64) == 4 * 64


@pytest.mark.parametrize("mode", ["keep", "zero"])
def test_cut_off_responses_keep_or_lose_their_reward(mode):
    from infinirl.engines.base import GenerationResult
    from infinirl.tasks.problem import Problem
    from infinirl.tasks.verifiers import RewardResult

    cfg = build(prompts_per_step=2, rollout={"group_size": 2}, algorithm={"truncated_reward": mode})
    flow = flow_of(cfg)
    problems = [Problem(uid=f"p/{i}", prompt="q", answer="1", verifier="gsm8k") for i in range(2)]
    finish = ["length", "stop", "length", "stop"]
    results = [GenerationResult([1], [2], [0.0], reason, 0) for reason in finish]
    scored = [RewardResult(1.0, True), RewardResult(1.0, True), RewardResult(0.0, False), RewardResult(0.5, False)]
    flow.train_stream = type("Stream", (), {"next_batch": lambda self, n: problems[:n]})()
    flow.submit_generation = lambda batch, sampling: None
    flow.collect_generation = lambda generation: (results, scored, 0.5)  # the rollout ranks' seconds last
    _, _, rewards, metrics = flow.generate_batch(step=0)
    assert metrics["time/rollout_generate_s"] == 0.5
    if mode == "keep":
        assert rewards.tolist() == [1.0, 1.0, 0.0, 0.5] and "rollout/truncated_zeroed" not in metrics
    else:  # the cut-off ones score 0, before advantages; one had a reward to lose
        assert rewards.tolist() == [0.0, 1.0, 0.0, 0.5] and metrics["rollout/truncated_zeroed"] == 1.0
        assert metrics["rollout/reward_mean"] == pytest.approx(1.5 / 4)


@pytest.mark.skipif(vllm_available(), reason="vLLM is installed here")
def test_the_vllm_engine_without_vllm_installed_is_a_config_error():
    with pytest.raises(ConfigError, match=r"rollout.engine=vllm: vLLM is not installed .*or set rollout.engine=hf"):
        build(rollout={"engine": "vllm"})


def test_the_rollout_context_holds_every_request_and_reaches_a_vllm_engine():
    from infinirl.runners.reasoning import _launches

    cfg = build(rollout={"max_prompt_length": 100, "max_new_tokens": 28})
    assert cfg.rollout_context() == (128, "rollout.max_prompt_length=100 + rollout.max_new_tokens=28")
    # with an agent, a nearly full trajectory (63 ids) can be asked for a whole turn (28)
    agent = build(rollout={"max_prompt_length": 100, "max_new_tokens": 28, "agent": AGENT})
    assert agent.rollout_context()[0] == 100 + 63 + 28
    assert "rollout.agent.max_response_tokens=64 - 1" in agent.rollout_context()[1]
    cfg.rollout.engine = "vllm"  # after validation: vLLM need not be installed to build the launch arguments
    assert _launches(cfg)["rollout"][1][5] == {"max_model_len": 128}
    cfg.rollout.engine_options = {"max_model_len": 4096}
    assert _launches(cfg)["rollout"][1][5] == {"max_model_len": 4096}


def test_the_longest_prompt_and_response_must_fit_the_models_context(tmp_path):
    """Read from the model folder's config.json (no weights needed): an agent's trajectory that
    outgrew the context would stop the run at its first generate past it, many steps in."""
    import json

    (tmp_path / "config.json").write_text(json.dumps({"model_type": "llama", "max_position_embeddings": 1024}))
    agent = {"env": "infinirl.agents.toy_envs:EchoEnv", "max_response_tokens": 512}
    with pytest.raises(ConfigError, match=r"rollout.max_prompt_length=768 \+ rollout.agent.max_response_tokens=512 = "
                                          r"1280 tokens do not fit the model's context \(max_position_embeddings of "
                                          r"model.path=1024\)"):
        build(model={"path": str(tmp_path)}, rollout={"max_prompt_length": 768, "agent": agent})
    with pytest.raises(ConfigError, match=r"rollout.max_new_tokens=48 = 1072 tokens"):
        build(model={"path": str(tmp_path)})  # the default max_prompt_length, 1024
    build(model={"path": str(tmp_path)}, rollout={"max_prompt_length": 512, "agent": agent})
    if not vllm_available():  # the vLLM engine is refused first where vLLM is missing
        return
    with pytest.raises(ConfigError, match=r"max_model_len=600"):
        build(model={"path": str(tmp_path)}, rollout={"max_prompt_length": 512, "agent": agent, "engine": "vllm",
                                                       "engine_options": {"max_model_len": 600}})
