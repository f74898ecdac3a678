"""Env options are checked before anything is built: which names each family takes, read off
signatures, and the one-line error a YAML author sees for one it does not take."""

import subprocess
import sys
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from infinirl.envs import ENVS, check_env_kwargs, env_options, make_env
from infinirl.envs.libero_env import LiberoFactory
from infinirl.envs.metaworld_env import MetaWorldFactory
from infinirl.envs.options import keyword_names

CONFIGS = sorted((Path(__file__).resolve().parents[3] / "infinirl" / "configs").glob("*.yaml"))
OPTION_FIELDS = ("env.kwargs", "eval.env_kwargs", "eval.video_env_kwargs")


# ---- reading signatures -------------------------------------------------------------------------


class Base:
    def __init__(self, model_path, frame_skip, render_mode=None, width=480, *, camera=None):
        pass


class Task(Base):
    def __init__(self, reward_scale=1.0, **kwargs):
        super().__init__("task.xml", 5, **kwargs)


class Pickled:
    def __init__(self, *args, **kwargs):
        pass


class Unforwarded(Pickled):
    def __init__(self, speed=1.0, **kwargs):
        super().__init__(speed, **kwargs)


def test_kwargs_are_followed_into_the_parent_constructor():
    names, passes_others = keyword_names(Task)
    # the parent's positional parameters without a default are the subclass's to fill in
    assert names == {"reward_scale", "render_mode", "width", "camera"}
    assert not passes_others


def test_kwargs_that_lead_nowhere_readable_pass_anything():
    assert keyword_names(Unforwarded) == ({"speed"}, True)

    def entry(task, *, obs_mode="state", **kwargs):
        pass

    assert keyword_names(entry, skip=("task",)) == ({"obs_mode"}, True)


# ---- every family ---------------------------------------------------------------------------------


def test_metaworld_and_libero_take_their_factory_fields_without_importing_the_simulator():
    """Cheap: read off dataclass fields, in a fresh interpreter that never imports MetaWorld."""
    code = (
        "import sys\n"
        "from infinirl.envs import check_env_kwargs\n"
        "check_env_kwargs('metaworld:reach-v3', {'terminate_on_success': True, 'obs_mode': 'state+rgb',"
        " 'image_size': 64, 'camera': 'corner2'}, 'env.kwargs')\n"
        "check_env_kwargs('libero:libero_spatial', {'image_size': 64, 'settle_steps': 5}, 'env.kwargs')\n"
        "print(sorted(m for m in ('metaworld', 'mujoco', 'libero', 'gymnasium') if m in sys.modules))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
    fields = set(MetaWorldFactory.__dataclass_fields__) - {"tasks", "max_episode_steps"}
    assert env_options("metaworld:reach-v3").names - {"max_episode_steps"} == fields
    libero = {"image_size", "settle_steps", "max_episode_steps", "task_block"}
    assert env_options("libero:libero_spatial").names == libero
    assert set(LiberoFactory.__dataclass_fields__) >= env_options("libero:libero_spatial").names


def test_a_metaworld_only_option_on_a_gym_task_fails_naming_key_family_and_accepted_keys():
    pytest.importorskip("gymnasium")
    pytest.importorskip("mujoco")
    with pytest.raises(ValueError) as error:
        check_env_kwargs("gym:HalfCheetah-v5", {"terminate_on_success": True, "width": 64}, "eval.env_kwargs")
    message = str(error.value)
    assert "\n" not in message
    assert message.startswith("eval.env_kwargs: gym env 'HalfCheetah-v5' does not take 'terminate_on_success';")
    # the accepted keys: the adapter's, gymnasium.make's, HalfCheetah's and MujocoEnv's (via **kwargs)
    for key in ("obs_mode", "disable_env_checker", "forward_reward_weight", "width", "height", "camera_name"):
        assert key in message.split("it takes: ")[1], key


def test_gym_options_the_adapter_or_make_env_set_are_refused_with_the_reason():
    pytest.importorskip("gymnasium")
    assert {"g", "obs_mode", "clip_actions", "instruction"} <= env_options("gym:Pendulum-v1").names
    check_env_kwargs("gym:Pendulum-v1", {"g": 9.81, "obs_mode": "state"}, "env.kwargs")
    with pytest.raises(ValueError, match=r"^env.kwargs: gym env 'Pendulum-v1' does not take 'render_mode' \(the "
                                         r"adapter sets it"):
        check_env_kwargs("gym:Pendulum-v1", {"render_mode": "human"}, "env.kwargs")
    with pytest.raises(ValueError, match="'max_episode_steps' \\(a make_env argument, set from the env config"):
        check_env_kwargs("gym:Pendulum-v1", {"max_episode_steps": 10}, "env.kwargs")
    with pytest.raises(ValueError, match=r"obs_mode='rbg' is not one of \['state', 'rgb', 'state\+rgb'\]"):
        check_env_kwargs("gym:Pendulum-v1", {"obs_mode": "rbg"}, "env.kwargs")
    with pytest.raises(ValueError, match="unknown gymnasium env id 'Pendulum-v9'"):
        check_env_kwargs("gym:Pendulum-v9", {}, "env.kwargs")


def test_metaworld_and_libero_refuse_what_their_factories_do_not_take():
    with pytest.raises(ValueError, match="^eval.env_kwargs: metaworld env 'reach-v3' does not take 'control_mode'; "
                                         "it takes: camera, fast_render, image_size, obs_mode, "):
        check_env_kwargs("metaworld:reach-v3", {"control_mode": "x"}, "eval.env_kwargs")
    with pytest.raises(ValueError, match="libero env 'libero_10' does not take 'camera'; it takes: image_size"):
        check_env_kwargs("libero:libero_10", {"camera": "agentview"}, "env.kwargs")


def test_maniskill_reads_the_task_class_and_refuses_what_the_adapter_sets():
    pytest.importorskip("mani_skill", reason="ManiSkill not installed: pip install mani-skill")
    names = env_options("maniskill:PushCube-v1").names
    assert {"control_mode", "reward_mode", "render_mode", "robot_init_qpos_noise", "image_size"} <= names
    with pytest.raises(ValueError, match="maniskill env 'PushCube-v1' does not take 'sim_backend' \\(the adapter "
                                         "simulates on SAPIEN's CPU backend"):
        check_env_kwargs("maniskill:PushCube-v1", {"sim_backend": "gpu"}, "env.kwargs")
    with pytest.raises(ValueError, match="does not take 'terminate_on_success'; it takes: control_mode"):
        check_env_kwargs("maniskill:PushCube-v1", {"terminate_on_success": True}, "eval.env_kwargs")


def test_every_registered_family_says_what_it_takes():
    tasks = {"gym": "Pendulum-v1", "metaworld": "reach-v3", "maniskill": "PushCube-v1", "libero": "libero_goal",
             "vla_noise": "metaworld:reach-v3"}
    needs = {"gym": "gymnasium", "maniskill": "mani_skill"}
    for family in ENVS.names():
        if family in needs and not _installed(needs[family]):
            continue
        options = env_options(f"{family}:{tasks[family]}")
        assert "image_size" in options.names or "obs_mode" in options.names, family


def test_make_env_refuses_an_option_before_building_anything():
    pytest.importorskip("gymnasium")
    with pytest.raises(ValueError, match="^make_env: gym env 'Pendulum-v1' does not take 'terminate_on_success'"):
        make_env("gym:Pendulum-v1", 2, num_workers=1, terminate_on_success=True)


# ---- the shipped configs --------------------------------------------------------------------------


def _installed(module: str) -> bool:
    import importlib.util

    return importlib.util.find_spec(module) is not None


def _options_in(path: Path) -> list[tuple[str, dict, str]]:
    raw = OmegaConf.to_container(OmegaConf.load(path))
    name = (raw.get("env") or {}).get("name")
    if not name or ":" not in name:
        return []
    found = []
    for where in OPTION_FIELDS:
        section, key = where.split(".")
        value = (raw.get(section) or {}).get(key)
        if value:
            found.append((name, value, f"{path.name}: {where}"))
    return found


@pytest.mark.parametrize("path", CONFIGS, ids=[p.stem for p in CONFIGS])
def test_every_shipped_config_passes_the_check(path):
    needs = {"gym": "gymnasium", "maniskill": "mani_skill"}
    for name, kwargs, where in _options_in(path):
        family = name.split(":")[0]
        if family in needs and not _installed(needs[family]):
            pytest.skip(f"{needs[family]} is not installed")
        if family == "gym" and not _installed("mujoco"):  # the shipped gym configs are MuJoCo tasks
            pytest.skip("mujoco is not installed")
        check_env_kwargs(name, kwargs, where)


def test_the_shipped_configs_exercise_every_option_field():
    """So the parametrised check above covers env.kwargs, eval.env_kwargs and eval.video_env_kwargs."""
    seen = {where.split(": ")[1] for path in CONFIGS for _, _, where in _options_in(path)}
    assert seen == set(OPTION_FIELDS)
