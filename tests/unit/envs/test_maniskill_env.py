"""ManiSkill3 on SAPIEN's CPU backend; skips with the reason when it cannot run here."""

import numpy as np
import pytest

from infinirl.envs import make_env

pytest.importorskip("mani_skill", reason="ManiSkill not installed: pip install mani-skill")
pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")  # numpy 2 notes in ManiSkill


@pytest.fixture(scope="module")
def pick_cube():
    try:
        env = make_env("maniskill:PickCube-v1", 2, num_workers=0)
    except RuntimeError as error:
        if "rendering device" in str(error):
            pytest.skip("SAPIEN finds no Vulkan device: install Mesa >= 23 mesa-vulkan-drivers "
                        "from bookworm-backports (docs/envs.md)")
        raise
    yield env
    env.close()


def test_seeded_reset_reproduces_and_steps_report_success(pick_cube):
    env = pick_cube
    assert env.action_space.shape == (8,)
    first = env.reset(seeds=[4, 4])["state"]
    np.testing.assert_array_equal(first[0], first[1])
    assert not np.array_equal(env.reset(seeds=[4, 5])["state"][1], first[1])
    result = env.step(np.zeros((2, 8), np.float32))
    assert result.obs["state"].dtype == np.float32 and result.obs["instruction"] == ["pick cube"] * 2
    assert result.info["success"].dtype == bool and np.isfinite(result.reward).all()


def test_episodes_truncate_at_the_task_limit(pick_cube):
    env = pick_cube
    env.reset(seeds=0)
    lengths = []
    for _ in range(60):
        result = env.step(np.zeros((2, 8), np.float32))
        lengths.append(result.info["episode_length"])
        if result.done.any():
            break
    assert len(lengths) == 50 and result.truncated.all()  # PickCube-v1 episodes last 50 steps
    np.testing.assert_array_equal(lengths[-1], [50, 50])


def test_unknown_task_lists_maniskill_tasks():
    with pytest.raises(ValueError, match="unknown ManiSkill task 'PickCub-v1'.*PickCube-v1"):
        make_env("maniskill:PickCub-v1", 1)
