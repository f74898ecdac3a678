"""make_env and the family registry: names, tasks and errors a YAML author would see."""

import pytest

from infinirl.envs import ENVS, make_env

pytest.importorskip("gymnasium")


def test_builtin_families_are_registered():
    assert {"gym", "metaworld", "maniskill", "libero"} <= set(ENVS.names())


def test_unknown_family_lists_the_registered_ones():
    with pytest.raises(KeyError, match="unknown environment 'metawrld'.*gym, libero.*metaworld"):
        make_env("metawrld:reach-v3", 2)


def test_unknown_gymnasium_id_suggests_close_ones():
    with pytest.raises(ValueError, match="unknown gymnasium env id 'CartPole-v9'.*CartPole-v1"):
        make_env("gym:CartPole-v9", 2)


def test_unknown_metaworld_task_lists_the_tasks():
    pytest.importorskip("metaworld")
    with pytest.raises(ValueError, match="unknown MetaWorld task 'rech-v3'.*MT10.*reach-v3"):
        make_env("metaworld", 2, task="rech-v3")


def test_a_metaworld_task_list_gives_env_i_the_i_mod_n_th_task():
    pytest.importorskip("metaworld")
    from infinirl.envs.metaworld_env import metaworld_factory

    factory = metaworld_factory("reach-v3, push-v3")
    assert factory.tasks == ("reach-v3", "push-v3")
    with pytest.raises(ValueError, match="unknown MetaWorld task 'psh-v3'"):
        metaworld_factory("reach-v3,psh-v3")


def test_task_given_twice_must_agree():
    with pytest.raises(ValueError, match="task given twice"):
        make_env("gym:CartPole-v1", 2, task="Pendulum-v1")


def test_chunk_size_wraps_the_env():
    with make_env("gym:Pendulum-v1", 2, num_workers=0, chunk_size=3) as env:
        assert env.action_space.shape == (3, 1)
        env.reset(seeds=0)
        result = env.step(env.action_space.sample(2))
        assert result.info["step_rewards"].shape == (2, 3)
