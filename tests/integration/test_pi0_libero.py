"""A π0 checkpoint in LeRobot's published layout, trained with PPO in LIBERO by the embodied runner
as the shipped ``ppo_pi0_libero`` config runs it.

The tiny π0 folder LeRobot wrote (``tests/fixtures/vla/pi0``) stands in for a user's 3B one. Its
weights depend only on the padded sizes (``max_state_dim`` / ``max_action_dim`` 8), not on the
env-facing ones, so the copy made here differs from it only in ``config.json`` and the statistics
files: LIBERO's 8-d proprio and 7-d actions, the camera names of LeRobot's LIBERO datasets, and an
instruction length that holds LIBERO's longer instructions."""

import json
import shutil
from pathlib import Path

import pytest
import torch
from safetensors.torch import save_file

from infinirl.cli import build_config

FIXTURES = Path(__file__).parents[1] / "fixtures" / "vla"
CAMERAS = {"observation.images.base_0_rgb": "observation.images.image",
           "observation.images.left_wrist_0_rgb": "observation.images.wrist_image"}
STATE_DIM, ACTION_DIM = 8, 7


def libero_statistics() -> dict[str, torch.Tensor]:
    """Statistics of LIBERO's width for every normalisation mode (fixed, so runs are reproducible)."""
    generator = torch.Generator().manual_seed(0)
    stats = {}
    for key, dim in (("observation.state", STATE_DIM), ("action", ACTION_DIM)):
        mean = 0.1 * torch.randn(dim, generator=generator)
        std = 0.2 + 0.1 * torch.rand(dim, generator=generator)
        stats.update({f"{key}.mean": mean, f"{key}.std": std, f"{key}.min": mean - 2 * std,
                      f"{key}.max": mean + 2 * std, f"{key}.q01": mean - 1.5 * std, f"{key}.q99": mean + 1.5 * std})
    return stats


def relabel_features(features: dict) -> dict:
    out = {}
    for key, feature in features.items():
        if key == "observation.images.right_wrist_0_rgb":
            continue
        feature = dict(feature)
        if key == "observation.state":
            feature["shape"] = [STATE_DIM]
        elif key == "action":
            feature["shape"] = [ACTION_DIM]
        out[CAMERAS.get(key, key)] = feature
    return out


def libero_shaped_pi0(folder: Path) -> Path:
    """The LeRobot-written tiny π0 with LIBERO's env-facing sizes (module docstring)."""
    shutil.copytree(FIXTURES / "pi0", folder)
    config = json.loads((folder / "config.json").read_text())
    config["input_features"] = relabel_features(config["input_features"])
    config["output_features"] = relabel_features(config["output_features"])
    config["tokenizer_max_length"] = 48
    (folder / "config.json").write_text(json.dumps(config, indent=2))
    stats = libero_statistics()
    for pipeline in ("policy_preprocessor", "policy_postprocessor"):
        spec = json.loads((folder / f"{pipeline}.json").read_text())
        for step in spec["steps"]:
            if "features" in step.get("config", {}):
                step["config"]["features"] = relabel_features(step["config"]["features"])
            if "state_file" in step:
                save_file(stats, str(folder / step["state_file"]))
        (folder / f"{pipeline}.json").write_text(json.dumps(spec, indent=2))
    return folder


@pytest.mark.slow  # LIBERO scenes and a VLA on CPU: minutes
def test_ppo_pi0_libero_config_trains_and_evaluates_a_published_format_checkpoint(ray_cluster, tmp_path):
    from infinirl.runners.embodied import run

    checkpoint = libero_shaped_pi0(tmp_path / "pi0_libero")
    _, cfg = build_config("ppo_pi0_libero", [
        f"policy.kwargs.checkpoint={checkpoint}", f"policy.kwargs.tokenizer={FIXTURES / 'tokenizer'}",
        f"policy.kwargs.architecture={FIXTURES / 'architecture.json'}", "policy.kwargs.dtype=float32",
        "policy.chunk=4", "policy.kwargs.chunk=4", "policy.kwargs.value_hidden=16",
        "env.name=libero:libero_spatial/0", "env.num_envs=2", "env.kwargs={image_size: 32}",
        "algorithm.mini_batches=1", "rollout_steps=2", "iterations=1",
        "eval.episodes=2", "eval.num_envs=2", "eval.at_start=false", "eval.max_episode_steps=8",
        f"output_dir={tmp_path / 'run'}", "loggers=[]",
        'placement={env: "node:0", rollout: "0", actor: "0"}'])
    summary = run(cfg)
    assert summary["iterations"] == 1 and summary["eval_after"] is not None
    assert summary["actor_weights_sha256"]


def test_ppo_pi0_libero_config_validates_and_needs_a_checkpoint():
    from infinirl.config import ConfigError

    with pytest.raises(ConfigError, match="needs policy.kwargs.checkpoint"):
        build_config("ppo_pi0_libero", [])
    _, cfg = build_config("ppo_pi0_libero", ["policy.kwargs.checkpoint=/models/pi0_libero"])
    assert cfg.policy.name == "pi0" and cfg.algorithm.name == "ppo" and not cfg.policy.normalize_obs
    assert cfg.policy.chunk == cfg.policy.kwargs["chunk"] == 5
    assert cfg.policy.kwargs["cameras"] == {"rgb": "observation.images.image",
                                            "wrist_rgb": "observation.images.wrist_image"}
