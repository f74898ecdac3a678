"""Off-policy steering of a VLA (DSRL-SAC): the SAC runner in ``vla_noise:metaworld:...``, whose
action is the frozen ``pi0_smollm2`` VLA's initial noise and whose observation is its features. It
trains end to end with collection and learning pipelined, reports per-task held-out success, and
resumes exactly: the collector's open episodes are replayed through the VLA into the same features.
The checkpoint is a tiny random one of the family (what `infinirl train sft_vla_metaworld` writes,
at test size)."""

import json

import pytest

pytest.importorskip("metaworld")

from infinirl.cli import build_config  # noqa: E402
from infinirl.config import ConfigError, to_dataclass  # noqa: E402
from infinirl.models.vla import save_vla  # noqa: E402
from infinirl.runners.sac import run  # noqa: E402
from infinirl.runners.sac_config import SACConfig  # noqa: E402
from tests.integration.resume import killed_after_checkpoint  # noqa: E402
from tests.unit.models.test_vla_smollm2 import CAMERA, tiny_vla  # noqa: E402


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    return str(save_vla(tiny_vla(), tmp_path_factory.mktemp("vla") / "policy"))


def make_cfg(output_dir, checkpoint, **vla):
    raw = {
        "iterations": 3, "steps_per_iteration": 5, "output_dir": str(output_dir), "save_every": 1,
        "collect_ahead": True,
        "env": {"name": "vla_noise:metaworld:reach-v3,push-v3", "num_envs": 2, "max_episode_steps": 4,
                "kwargs": {"obs_mode": "state+rgb", "image_size": 16, "camera": "corner", "noise_bound": 1.5,
                           "vla": {"checkpoint": checkpoint, "chunk": 2, "cameras": {"rgb": CAMERA},
                                   "state_key": "proprio", **vla}}},
        "network": {"obs_key": "features", "actor_hidden": [16], "critic_hidden": [16], "layer_norm": True},
        "algorithm": {"batch_size": 8, "learning_starts": 8, "utd_ratio": 1.0, "target_entropy": 0.0},
        "eval": {"every": 2, "episodes": 4, "num_envs": 2, "headline": "success_rate", "video_episodes": 0},
        "cluster": {"log_to_driver": False},
    }
    return to_dataclass(SACConfig, raw)


def test_sac_steers_the_vla_and_resumes_exactly(ray_cluster, tmp_path, checkpoint):
    straight = run(make_cfg(tmp_path / "straight", checkpoint))
    rows = [json.loads(line) for line in (tmp_path / "straight" / "metrics.jsonl").read_text().splitlines()]
    assert straight["env_steps"] == 3 * 2 * 5  # decisions
    trained = [r for r in rows if "train/critic_loss" in r]
    assert trained and all(r["train/critic_loss"] > 0 for r in trained)
    evaluated = [r for r in rows if "eval/success_rate" in r]
    assert [r["step"] for r in evaluated] == [0, 2, 3]
    assert all(r["eval/episodes/reach-v3"] == 2 and r["eval/episodes/push-v3"] == 2 for r in evaluated)
    assert json.loads((tmp_path / "straight" / "summary.json").read_text())["eval_metric"] == "eval/success_rate"

    killed_after_checkpoint(tmp_path / "straight", tmp_path / "resumed", 2)
    resumed = run(make_cfg(tmp_path / "resumed", checkpoint))
    for key in ("weights_sha256", "actor_weights_sha256", "buffer_sha256", "env_steps"):
        assert resumed[key] == straight[key], key


def test_a_missing_checkpoint_is_one_line_before_any_worker_starts(tmp_path):
    with pytest.raises(ConfigError, match=r"^env.name='vla_noise:metaworld:reach-v3,push-v3': .*no_such_vla") as error:
        run(make_cfg(tmp_path / "bad", str(tmp_path / "no_such_vla")))
    assert "\n" not in str(error.value) and not (tmp_path / "bad").exists()


def test_the_shipped_config_validates():
    cfg = build_config("sac_vla_metaworld", [])[1]
    assert cfg.env.name.startswith("vla_noise:metaworld:") and cfg.network.obs_key == "features"
    assert cfg.eval.headline == "success_rate"
