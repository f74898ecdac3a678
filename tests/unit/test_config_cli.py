"""Config composition and strict validation; the CLI rejects bad input before anything starts."""

from dataclasses import dataclass, field
from typing import Literal

import pytest

from infinirl.cli import main
from infinirl.config import ConfigError, available_configs, check_override_keys, compose, to_dataclass
from infinirl.runners import load_runners


@dataclass
class Inner:
    lr: float = 1e-3
    mode: Literal["a", "b"] = "a"


@dataclass
class Outer:
    steps: int = 3
    name: str = "x"
    inner: Inner = field(default_factory=Inner)
    tags: list[str] = field(default_factory=list)


def test_to_dataclass_converts_and_checks_types():
    cfg = to_dataclass(Outer, {"steps": 5, "inner": {"lr": 1, "mode": "b"}, "tags": ["t"]})
    assert cfg.steps == 5 and cfg.inner.lr == 1.0 and isinstance(cfg.inner.lr, float) and cfg.tags == ["t"]
    with pytest.raises(ConfigError, match=r"unknown config key 'inner.lrr'. Did you mean 'inner.lr'"):
        to_dataclass(Outer, {"inner": {"lrr": 1}})
    with pytest.raises(ConfigError, match=r"steps: expected an integer, got 'many'"):
        to_dataclass(Outer, {"steps": "many"})
    with pytest.raises(ConfigError, match=r"inner.mode='c' is not allowed.*Choose one of: a, b"):
        to_dataclass(Outer, {"inner": {"mode": "c"}})


def test_override_keys_checked_with_suggestion():
    check_override_keys(Outer, ["steps=3", "inner.lr=0.1"])
    with pytest.raises(ConfigError, match=r"'inner.mod'.*Did you mean 'inner.mode'"):
        check_override_keys(Outer, ["inner.mod=b"])


def test_every_shipped_config_loads_and_validates():
    runners = load_runners()
    for name in available_configs():
        raw = compose(name)
        spec = runners.get(raw["runner"])
        to_dataclass(spec.config_cls, raw)


def test_cli_rejects_bad_key_value_and_config(capsys):
    assert main(["validate", "default"]) == 0
    assert main(["validate", "default", "iterationz=1"]) == 2
    assert "Did you mean 'iterations'" in capsys.readouterr().err
    assert main(["validate", "default", "iterations=-1"]) == 2
    assert "iterations=-1 must be >= 1" in capsys.readouterr().err
    assert main(["validate", "runtime_demo", "placement.learner=1-x"]) == 2
    assert "placement.learner" in capsys.readouterr().err
    assert main(["validate", "no_such_config"]) == 2
    assert "no config named 'no_such_config'" in capsys.readouterr().err


def test_train_reports_a_runner_check_as_a_config_error(capsys, tmp_path):
    """A check only the runner can make (here: the env task, by building one sub-env in the
    driver before any worker starts) exits 2 with the message, not a traceback."""
    pytest.importorskip("gymnasium")
    code = main(["train", "ppo_metaworld_reach", "env.name=gym:NoSuchEnv-v0", f"output_dir={tmp_path}"])
    assert code == 2
    assert "infinirl: config error: gym:NoSuchEnv-v0" in capsys.readouterr().err


def test_default_config_is_the_grpo_main_job():
    """`infinirl train` with no config name runs GRPO on the embedded model with a held-out set."""
    from infinirl.config import compose

    raw = compose("default")
    assert raw["runner"] == "reasoning" and raw["algorithm"]["advantage"] == "grpo"
    assert raw["model"]["path"] == "smollm2-135m-instruct" and raw["task"]["eval_size"] > 0


def test_one_placement_override_keeps_the_other_components_defaults():
    from infinirl.cli import build_config

    _, cfg = build_config("grpo_smoke", ["placement.actor=0"])
    assert cfg.placement_spec() == {"actor": "0", "rollout": "0", "reward": "0"}


def test_a_mapping_override_replaces_the_configs_mapping():
    from infinirl.cli import build_config

    _, cfg = build_config("ppo_metaworld_reach", ["eval.env_kwargs={}"])
    assert cfg.eval.env_kwargs == {}
    _, cfg = build_config("ppo_metaworld_reach", ["eval.env_kwargs={seeded_rand_vec: true}"])
    assert cfg.eval.env_kwargs == {"seeded_rand_vec": True}  # not merged with terminate_on_success


def test_a_mapping_override_of_a_typed_section_merges_into_the_configs_section():
    """``env={num_envs: 4}`` sets env.num_envs only: the YAML's other env keys (its task) stay, as
    ``env.num_envs=4`` would; a free-form mapping nested in it (env.kwargs) is still replaced."""
    from infinirl.cli import build_config

    _, shipped = build_config("ppo_metaworld_push", [])
    _, cfg = build_config("ppo_metaworld_push", ["env={num_envs: 4}"])
    assert cfg.env.num_envs == 4 and cfg.env.name == shipped.env.name == "metaworld:push-v3"
    assert cfg.env.kwargs == shipped.env.kwargs
    _, cfg = build_config("ppo_metaworld_push", ["env={num_envs: 4, kwargs: {}}", "eval={episodes: 3}"])
    assert cfg.env.kwargs == {} and cfg.env.name == "metaworld:push-v3"
    assert cfg.eval.episodes == 3 and cfg.eval.env_kwargs == shipped.eval.env_kwargs
    _, cfg = build_config("grpo_arithmetic", ["actor={lr: 0.001, lora: {r: 4}}"])
    _, base = build_config("grpo_arithmetic", [])
    assert cfg.actor.lr == 0.001 and cfg.actor.lora.r == 4
    assert cfg.actor.lora.top_layers == base.actor.lora.top_layers and cfg.actor.micro_batch_size == \
        base.actor.micro_batch_size
    _, cfg = build_config("grpo_chain_sum", ["actor.lora=null"])
    assert cfg.actor.lora is None
    _, cfg = build_config("grpo_smoke", ["actor.lora={r: 2}"])
    assert cfg.actor.lora.r == 2  # a mapping given for an optional section the config leaves unset sets it


def test_a_placement_mapping_merges_over_the_configs_placement_by_component():
    from infinirl.cli import build_config

    _, cfg = build_config("ppo_chain_sum", ["placement={critic: 1}"])
    assert cfg.placement_spec() == {"actor": "0", "rollout": "0", "reward": "0", "critic": "1"}
    _, cfg = build_config("ppo_chain_sum", ["placement={actor\\,critic: 1}"])
    assert cfg.placement_spec() == {"actor": "1", "rollout": "0", "reward": "0", "critic": "1"}
    _, cfg = build_config("ppo_chain_sum", ["placement=auto"])
    assert cfg.placement == "auto"
    _, cfg = build_config("ppo_pixels_metaworld_reach", ["placement={actor: 2}"])
    assert cfg.placement_spec() == {"env": "0", "rollout": "1", "actor": "2"}  # the config's rollout: 1 stays


def test_renamed_keys_still_work_with_a_warning(capsys):
    from infinirl.cli import build_config

    _, cfg = build_config("grpo_smoke", ["steps=3", "eval_every=2"])
    assert cfg.iterations == 3 and cfg.eval.every == 2
    err = capsys.readouterr().err
    assert "'steps' is now 'iterations'" in err or cfg.iterations == 3  # warned once per process


def test_eval_help_lists_only_eval_configs(capsys):
    with pytest.raises(SystemExit):
        main(["eval", "--help"])
    out = capsys.readouterr().out
    assert "Available: eval" in " ".join(out.split()) and "grpo_arithmetic" not in out
