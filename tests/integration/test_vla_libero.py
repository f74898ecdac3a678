"""A VLA checkpoint in its published format, trained and evaluated in LIBERO by the embodied
runner as the shipped config runs it: the tiny OpenVLA-OFT folder written by OFT's own code
stands in for a user's 7B one (same files, same keys), so only sizes differ."""

from pathlib import Path

import pytest

from infinirl.cli import build_config

FIXTURE = Path(__file__).parents[1] / "fixtures" / "vla_oft"


@pytest.mark.slow  # LIBERO scenes on CPU: minutes
def test_grpo_openvla_oft_libero_config_trains_and_evaluates_a_published_format_checkpoint(ray_cluster, tmp_path):
    from infinirl.runners.embodied import run

    _, cfg = build_config("grpo_openvla_oft_libero", [
        f"policy.kwargs.checkpoint={FIXTURE / 'openvla_oft'}",
        f"policy.kwargs.architecture={FIXTURE / 'architecture.json'}",
        "policy.kwargs.unnorm_key=tiny_libero_no_noops", "policy.kwargs.dtype=float32",
        "env.num_envs=2", "env.kwargs={image_size: 32}",
        "algorithm.group_size=2", "algorithm.mini_batches=1", "rollout_steps=2", "iterations=1",
        "eval.episodes=2", "eval.num_envs=2", f"output_dir={tmp_path / 'run'}", "loggers=[]",
        'placement={env: "node:0", rollout: "0", actor: "0"}'])
    assert cfg.env.name == "libero:libero_spatial/0"  # the shipped task: grpo needs one task per run
    summary = run(cfg)
    assert summary["iterations"] == 1 and summary["eval_after"] is not None
    assert summary["actor_weights_sha256"]


def test_the_libero_vla_configs_need_a_checkpoint_before_anything_runs():
    from infinirl.config import ConfigError

    with pytest.raises(ConfigError, match="needs policy.kwargs.checkpoint"):
        build_config("grpo_openvla_oft_libero", [])


@pytest.mark.parametrize("name", ["grpo_openvla_oft_libero", "ppo_pi0_libero"])
def test_the_vla_configs_refuse_a_second_observation_normaliser(name):
    """A VLA normalises its state / proprio with its checkpoint's statistics: the runner's running
    normaliser in front would feed it twice-normalised values."""
    from infinirl.config import ConfigError

    with pytest.raises(ConfigError, match=r"^policy.normalize_obs=true: policy \w+ normalises its own inputs .* "
                                          "set policy.normalize_obs=false$"):
        build_config(name, ["policy.kwargs.checkpoint=/models/vla", "policy.normalize_obs=true"])
    _, cfg = build_config(name, ["policy.kwargs.checkpoint=/models/vla"])  # as shipped: off
    assert not cfg.policy.normalize_obs and not cfg.normalizes_obs()
    # left unset, it resolves off for a VLA and on for a plain policy
    _, cfg = build_config(name, ["policy.kwargs.checkpoint=/models/vla", "policy.normalize_obs=null"])
    assert cfg.policy.normalize_obs is None and not cfg.normalizes_obs()
    _, plain = build_config("ppo_metaworld_reach", [])
    assert plain.normalizes_obs()


def test_actor_compile_is_refused_only_where_the_actor_would_train_low_precision_weights(monkeypatch):
    """The driver asks the policy it builds (LoRA applied) what the actor's optimizer will hold: bf16
    adapters are refused like bf16 weights; float32 weights, and FSDP2 (its Adam stays eager), pass."""
    pytest.importorskip("libero")
    from infinirl.config import ConfigError
    from infinirl.engines.cpu_dtype import cpu_bf16_is_fast
    from infinirl.runners.embodied import _check_env_and_policy

    monkeypatch.setenv("INFINIRL_CPU_BF16", "1")  # bf16 stays bf16 on a CPU without native bf16
    cpu_bf16_is_fast.cache_clear()
    tiny = [f"policy.kwargs.checkpoint={FIXTURE / 'openvla_oft'}",
            f"policy.kwargs.architecture={FIXTURE / 'architecture.json'}",
            "policy.kwargs.unnorm_key=tiny_libero_no_noops", "env.kwargs={image_size: 32}", "actor.compile=true"]
    try:
        _, cfg = build_config("grpo_openvla_oft_libero", [*tiny, "actor.lora={r: 2, train_fully: []}"])
        with pytest.raises(ConfigError, match=r"^actor.compile=true: policy openvla_oft trains bfloat16 weights"):
            _check_env_and_policy(cfg)
        for passing in (["policy.kwargs.dtype=float32"], ["actor.strategy=fsdp"]):
            _, cfg = build_config("grpo_openvla_oft_libero", [*tiny, *passing])
            _check_env_and_policy(cfg)
    finally:
        monkeypatch.delenv("INFINIRL_CPU_BF16")
        cpu_bf16_is_fast.cache_clear()
