"""RL after SFT, small: the embodied runner trains the ``pi0_smollm2`` VLA policy with PPO in MetaWorld
from its camera, instruction and proprio, on two tasks at once, with LoRA adapters on the
backbone (only they and the value head train; the rollout receives the merged weights), and resumes
exactly. The checkpoint is a tiny random one of the family (what `infinirl train sft_vla_metaworld`
writes, at test size)."""

import json
from pathlib import Path

import pytest

pytest.importorskip("metaworld")

import torch  # noqa: E402

from infinirl.cli import build_config  # noqa: E402
from infinirl.config import ConfigError, to_dataclass  # noqa: E402
from infinirl.models.vla import save_vla  # noqa: E402
from infinirl.runners.embodied import run  # noqa: E402
from infinirl.runners.embodied_config import EmbodiedConfig  # noqa: E402
from tests.integration.resume import killed_after_checkpoint  # noqa: E402
from tests.unit.models.test_vla_smollm2 import CAMERA, tiny_vla  # noqa: E402


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    return str(save_vla(tiny_vla(), tmp_path_factory.mktemp("vla") / "policy"))


def make_cfg(output_dir, checkpoint, **extra):
    raw = {
        "iterations": 2, "rollout_steps": 3, "output_dir": str(output_dir), "save_every": 1,
        "env": {"name": "metaworld:reach-v3,push-v3", "num_envs": 2,
                "kwargs": {"obs_mode": "state+rgb", "image_size": 16, "camera": "corner"}},
        "policy": {"name": "pi0_smollm2", "chunk": 2, "normalize_obs": False,
                   "kwargs": {"checkpoint": checkpoint, "action_dim": 4, "chunk": 2, "cameras": {"rgb": CAMERA},
                              "state_key": "proprio", "value_hidden": 8}},
        "algorithm": {"epochs": 1, "mini_batches": 2},
        "actor": {"anneal_lr": False, "lr": 1e-3, "lora": {"r": 2, "alpha": 4.0}},
        "eval": {"every": 0, "at_start": False, "episodes": 2, "num_envs": 2, "max_episode_steps": 4,
                 "video_episodes": 0},
        "placement": {"env": "0", "rollout": "0", "actor": "0"}, "cluster": {"log_to_driver": False},
        **extra,
    }
    return to_dataclass(EmbodiedConfig, raw)


@pytest.mark.slow  # three short runs with a VLA; default-tier budget (pytest -m slow tests/integration)
@pytest.mark.parametrize("strategy, schedule", [("ddp", {}), ("fsdp", {}),
                                               ("ddp", {"critic_warmup": 1, "desired_kl": 0.01})])
def test_ppo_with_lora_on_the_vla_trains_the_adapters_and_resumes_exactly(ray_cluster, tmp_path, checkpoint, strategy,
                                                                          schedule):
    """Also with the shipped demo's schedule: the value head alone in iteration 1, then the rate
    adapted to the KL (its scale resumes with the optimizer's state)."""
    def make(output_dir):
        actor = {"anneal_lr": False, "lr": 1e-3, "lora": {"r": 2, "alpha": 4.0}, "strategy": strategy}
        if "desired_kl" in schedule:
            actor["desired_kl"] = schedule["desired_kl"]
        algorithm = {"epochs": 1, "mini_batches": 2, "critic_warmup": schedule.get("critic_warmup", 0)}
        return make_cfg(output_dir, checkpoint, actor=actor, algorithm=algorithm)

    straight = run(make(tmp_path / "straight"))
    rows = [json.loads(line) for line in (tmp_path / "straight" / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows if "train/grad_norm" in r] == [1, 2]
    assert all(r["train/grad_norm"] > 0 for r in rows if "train/grad_norm" in r)
    # the rollout acts with the merged weights: its log-probs agree with the adapted trainer's
    assert all(r["train/logprob_mismatch"] < 1e-4 for r in rows if "train/logprob_mismatch" in r)
    if schedule:  # the warm-up iteration moved only the value head: the policy's ratios stayed at 1
        first, second = (r for r in rows if "train/approx_kl" in r)
        assert abs(first["train/approx_kl"]) < 1e-6 and first["train/grad_norm_policy"] == 0.0
        assert first["train/grad_norm_critic"] > 0.0 and second["train/grad_norm_policy"] > 0.0
        assert second["train/approx_kl"] > 1e-6 and "train/kl_scale" in second

    killed_after_checkpoint(tmp_path / "straight", tmp_path / "resumed", 1)
    resumed = run(make(tmp_path / "resumed"))
    assert resumed["actor_weights_sha256"] == straight["actor_weights_sha256"]


@pytest.mark.slow  # default-suite budget: the likelihoods have unit tests (tests/unit/models/test_vla_policy.py)
@pytest.mark.parametrize("likelihood", [{"likelihood": "fpo", "fpo_samples": 2},
                                        {"likelihood": "flow_noise", "critic_input": "expert"}],
                         ids=["fpo", "flow_noise_expert_critic"])
def test_other_likelihoods_and_critics_train_the_vla_and_resume_exactly(ray_cluster, tmp_path, checkpoint, likelihood):
    """``likelihood: fpo``: the rollout acts with the ODE sampler and records each chunk's
    flow-matching draws; ``flow_noise``: the rollout samples with the learned std (a head LoRA
    trains in full), here with ``critic_input: expert``, the value head on the action expert's output. The
    adapted trainer scores the chunks as the merged-weight rollout did, the policy moves, and a
    resumed run ends with the same weights."""
    def make(output_dir):
        cfg = make_cfg(output_dir, checkpoint)
        cfg.policy.kwargs.update(likelihood)
        return cfg

    straight = run(make(tmp_path / "straight"))
    rows = [json.loads(line) for line in (tmp_path / "straight" / "metrics.jsonl").read_text().splitlines()]
    trained = [r for r in rows if "train/approx_kl" in r]
    assert len(trained) == 2 and all(r["train/logprob_mismatch"] < 1e-4 for r in trained)
    assert all(r["train/grad_norm_policy"] > 0 for r in trained) and trained[1]["train/approx_kl"] != 0.0
    killed_after_checkpoint(tmp_path / "straight", tmp_path / "resumed", 1)
    resumed = run(make(tmp_path / "resumed"))
    assert resumed["actor_weights_sha256"] == straight["actor_weights_sha256"]


def test_lora_layers_the_policy_lacks_are_one_line_before_any_worker_starts(tmp_path, checkpoint):
    cfg = make_cfg(tmp_path / "bad", checkpoint, actor={"lora": {"target_modules": ["qkv"]}})
    with pytest.raises(ConfigError, match=r"^policy pi0_smollm2: actor.lora.target_modules=\['qkv'\] matches no"):
        run(cfg)
    assert not (tmp_path / "bad").exists()


def test_the_shipped_rl_after_sft_config_validates():
    cfg = build_config("ppo_vla_metaworld", [])[1]
    assert cfg.policy.name == "pi0_smollm2" and cfg.actor.lora is not None


# The residual's options together in one run (each one's own behaviour is unit tested in
# tests/unit/models/test_vla_residual.py): CNNs on the frames, a privileged critic, held noise.
FROZEN_FORMS = {"steered": ("steered", {"noise_hidden": [8]}), "residual": ("residual", {"residual_hidden": [8]}),
                "residual_pixels_critic_held_noise": ("residual", {
                    "residual_hidden": [8], "residual_pixels": True, "pixel_features": 8, "pixel_size": 16,
                    "critic_obs": "state", "held_noise": 0.5, "held_noise_every": 2})}


def frozen_policy(checkpoint, form="steered"):
    name, options = FROZEN_FORMS[form]
    return {"name": f"pi0_smollm2_{name}", "chunk": 2, "normalize_obs": False,
            "kwargs": {"checkpoint": checkpoint, "action_dim": 4, "chunk": 2, "cameras": {"rgb": CAMERA},
                       "state_key": "proprio", **options}}


def frozen_cfg(output_dir, checkpoint, form="steered"):
    return make_cfg(output_dir, checkpoint, policy=frozen_policy(checkpoint, form),
                    actor={"anneal_lr": False, "lr": 1e-3, "value_lr": 1e-2},
                    algorithm={"epochs": 2, "mini_batches": 2, "critic_warmup": 1})


@pytest.mark.parametrize("form", ["steered", "residual_pixels_critic_held_noise"])
def test_a_frozen_vla_steered_or_corrected_trains_end_to_end(ray_cluster, tmp_path, checkpoint, form):
    """``pi0_smollm2_steered`` / ``_residual`` (with its CNNs on the frames, a privileged critic and
    held noise): the rollout records the noise (the residual) and the VLA's features, the
    trainer's log-probs of them agree with the rollout's, the critic trains alone in iteration 1
    and the small policy from iteration 2."""
    result = run(frozen_cfg(tmp_path / form, checkpoint, form))
    rows = [json.loads(line) for line in (tmp_path / form / "metrics.jsonl").read_text().splitlines()]
    first, second = (r for r in rows if "train/approx_kl" in r)
    assert all(r["train/logprob_mismatch"] < 1e-5 for r in (first, second))
    assert first["train/grad_norm_policy"] == 0.0 and first["train/grad_norm_critic"] > 0.0
    assert second["train/grad_norm_policy"] > 0.0 and second["train/approx_kl"] != 0.0
    assert result["actor_weights_sha256"]


def three_residual_iterations(output_dir, checkpoint, **options) -> tuple[list[dict], dict]:
    """Three iterations of the tiny residual VLA with ``options`` (critic alone in the first, the
    residual updated from the second): the rows with an update, and the last checkpoint's weights."""
    policy = frozen_policy(checkpoint, "residual")
    policy["kwargs"].update(options)
    run(make_cfg(output_dir, checkpoint, policy=policy, iterations=3,
                 actor={"anneal_lr": False, "lr": 1e-3, "value_lr": 1e-2},
                 algorithm={"epochs": 2, "mini_batches": 2, "critic_warmup": 1}))
    rows = [json.loads(line) for line in (output_dir / "metrics.jsonl").read_text().splitlines()]
    model = torch.load(output_dir / "checkpoints" / "iter_000003" / "actor" / "actor.pt", map_location="cpu",
                       weights_only=False)["model"]
    return [r for r in rows if "train/approx_kl" in r], model


def test_the_residuals_readout_and_input_standardisation_are_fitted_and_reach_the_rollout(ray_cluster, tmp_path,
                                                                                          checkpoint):
    """The shipped demo's residual (``residual_readout`` per instruction, a privileged critic) with
    ``residual_input_norm``. The trainer fits the input statistics on its first batch (2 envs x 3
    decisions) and keeps them; it fits the ridge readout of the env's ``state`` after each update and
    scores it on the next batch before folding that in; the rows' instruction keys travel in the
    batch. Both fits travel with the weights, so once the residual trains (iteration 3, after the
    critic's warm-up and a first policy update) the rollout's log-probs still agree with the trainer's."""
    trained, model = three_residual_iterations(tmp_path / "readout", checkpoint, residual_readout="state",
                                               readout_groups=2, critic_obs="state", residual_input_norm=True)
    assert len(trained) == 3 and trained[1]["train/approx_kl"] != 0.0 and trained[2]["train/approx_kl"] != 0.0
    assert "train/readout_r2" not in trained[0] and all("train/readout_r2" in r for r in trained[1:])
    assert all(r["train/logprob_mismatch"] < 1e-5 for r in trained)
    assert float(model["policy.input_rms.count"]) == 6.0
    assert float(model["policy.input_rms.var"].min()) >= 0.0 and bool(model["policy.input_rms.mean"].abs().sum() > 0)
    counts, keys = model["policy.readout.count"], model["policy.readout.keys"]
    assert float(counts.sum()) == 18.0 and model["policy.readout.weight"].dtype == torch.float64
    assert bool((keys[counts > 0] != 0).all())  # each group that fitted has its instruction's key


@pytest.mark.parametrize("form", ["steered", "residual"])
def test_the_shipped_frozen_vla_configs_validate_and_refuse_lora(tmp_path, checkpoint, form):
    cfg = build_config(f"ppo_vla_metaworld_{form}", [])[1]
    assert cfg.policy.name == f"pi0_smollm2_{form}" and cfg.actor.lora is None
    bad = make_cfg(tmp_path / "bad", checkpoint, policy=frozen_policy(checkpoint, form))
    with pytest.raises(ConfigError, match=f"^actor.lora: policy pi0_smollm2_{form}: the VLA is frozen") as error:
        run(bad)
    assert "\n" not in str(error.value) and not (tmp_path / "bad").exists()


@pytest.mark.parametrize("option", ["critic_obs", "residual_readout"])
def test_a_privileged_field_the_env_lacks_is_refused_before_anything_starts(tmp_path, checkpoint, option):
    policy = frozen_policy(checkpoint, "residual")
    policy["kwargs"][option] = "objects"
    bad = make_cfg(tmp_path / "bad", checkpoint, policy=policy, actor={"anneal_lr": False, "lr": 1e-3})
    with pytest.raises(ConfigError, match=rf"{option}='objects' is not an observation field of this env; it has "
                                          r"\['instruction', 'proprio', 'rgb', 'state'\]") as error:
        run(bad)
    assert "\n" not in str(error.value) and not (tmp_path / "bad").exists()


@pytest.fixture(scope="module")
def demonstrations(tmp_path_factory):
    from tests.unit.runners.test_sft import synthetic_dataset

    root = tmp_path_factory.mktemp("demos") / "ds"
    synthetic_dataset(root)
    return str(root)


def anchored_cfg(output_dir, checkpoint, demonstrations, **bc):
    return make_cfg(output_dir, checkpoint, actor={"anneal_lr": False, "lr": 1e-3, "lora": {"r": 2, "alpha": 4.0},
                                                   "value_lr": 1e-2},
                    algorithm={"epochs": 1, "mini_batches": 2, "critic_warmup": 1,
                               "bc": {"data": demonstrations, "coef": 2.0, "decay": 0.5, "batch_size": 4, **bc}})


@pytest.mark.slow  # two short runs with a VLA (pytest -m slow tests/integration)
def test_the_bc_anchor_clones_the_demonstrations_beside_ppo_and_resumes_exactly(ray_cluster, tmp_path, checkpoint,
                                                                               demonstrations):
    """``algorithm.bc``: from the first policy iteration every step also lowers the VLA's
    flow-matching loss on the dataset (weighted ``coef * decay**iteration``); a resumed run draws
    the same frames and ends with the same weights."""
    straight = run(anchored_cfg(tmp_path / "straight", checkpoint, demonstrations))
    rows = [json.loads(line) for line in (tmp_path / "straight" / "metrics.jsonl").read_text().splitlines()]
    first, second = (r for r in rows if "train/approx_kl" in r)
    assert "train/bc_loss" not in first  # the critic's warm-up: the policy, and so the anchor, waits
    assert second["train/bc_loss"] > 0 and second["train/bc_weight"] == 2.0 * 0.5
    killed_after_checkpoint(tmp_path / "straight", tmp_path / "resumed", 1)
    resumed = run(anchored_cfg(tmp_path / "resumed", checkpoint, demonstrations))
    assert resumed["actor_weights_sha256"] == straight["actor_weights_sha256"]


def test_a_bc_anchor_that_cannot_work_is_one_line_before_any_worker_starts(tmp_path, checkpoint, demonstrations):
    cases = [
        (anchored_cfg(tmp_path / "a", checkpoint, str(tmp_path / "nope")),
         r"^algorithm.bc.data=.*nope: no such folder; `infinirl train sft_vla_metaworld` generates"),
        (anchored_cfg(tmp_path / "b", checkpoint, demonstrations, camera_key="observation.images.wrist"),
         r"^algorithm.bc.camera_key='observation.images.wrist': the dataset at .* has cameras"),
        (make_cfg(tmp_path / "c", checkpoint, policy=frozen_policy(checkpoint), actor={"lr": 1e-3},
                  algorithm={"epochs": 1, "mini_batches": 2, "bc": {"data": demonstrations}}),
         r"^algorithm.bc: policy pi0_smollm2_steered: the VLA is frozen .*; remove algorithm.bc.data"),
    ]
    for cfg, message in cases:
        with pytest.raises(ConfigError, match=message) as error:
            run(cfg)
        assert "\n" not in str(error.value) and not Path(cfg.output_dir).exists()
    with pytest.raises(ConfigError, match=r"^algorithm.bc.data adds a cloning loss to each step, which "
                                          r"actor.compile's fused step") as error:
        make_cfg(tmp_path / "d", checkpoint, actor={"compile": True},
                 algorithm={"epochs": 1, "mini_batches": 2, "bc": {"data": demonstrations}})
    assert "\n" not in str(error.value)
