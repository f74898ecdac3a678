"""Spaces and batching: the checks every env call goes through."""

import numpy as np
import pytest
import torch

from infinirl.envs import ActionSpace, collate_obs


def test_wrong_action_shape_names_the_expected_shape():
    space = ActionSpace.box(-np.ones(4), np.ones(4))
    with pytest.raises(ValueError, match=r"expected actions of shape \(8, 4\).*got \(8, 3\)"):
        space.validate(np.zeros((8, 3)), num_envs=8)
    with pytest.raises(ValueError, match=r"\(8, 4\).*got \(4,\)"):
        space.validate(np.zeros(4), num_envs=8)


def test_validate_accepts_torch_tensors_as_numpy():
    space = ActionSpace.box(-np.ones(2), np.ones(2))
    actions = space.validate(torch.ones(3, 2), num_envs=3)
    assert isinstance(actions, np.ndarray) and actions.shape == (3, 2)


def test_discrete_space_rejects_float_actions_and_samples_in_range():
    space = ActionSpace.discrete(3)
    assert space.is_discrete and space.shape == ()
    with pytest.raises(ValueError, match="integer actions"):
        space.validate(np.zeros(5), num_envs=5)
    sample = space.sample(1000, np.random.default_rng(0))
    assert sample.shape == (1000,) and set(np.unique(sample)) == {0, 1, 2}


def test_chunked_space_repeats_bounds_per_step():
    space = ActionSpace.box([-1.0, -2.0], [1.0, 2.0]).chunked(3)
    assert space.shape == (3, 2)
    np.testing.assert_array_equal(space.high, [[1, 2]] * 3)
    sample = space.sample(100, np.random.default_rng(0))
    assert sample.shape == (100, 3, 2)
    assert (np.abs(sample[..., 1]) <= 2).all() and (np.abs(sample[..., 0]) <= 1).all()
    assert np.abs(sample[..., 1]).max() > 1  # the second dimension really uses its wider range


def test_collate_stacks_arrays_and_keeps_text_as_list():
    rows = [{"state": np.full(3, i, np.float32), "instruction": f"task {i}"} for i in range(4)]
    batch = collate_obs(rows)
    assert batch["state"].shape == (4, 3) and batch["state"][2, 0] == 2
    assert batch["instruction"] == ["task 0", "task 1", "task 2", "task 3"]


def test_action_spaces_compare_by_value():
    assert ActionSpace.box([-1.0, -1.0], [1.0, 1.0]) == ActionSpace.box(-np.ones(2), np.ones(2))
    assert ActionSpace.box([-1.0], [1.0]) != ActionSpace.box([-1.0], [2.0])
    assert ActionSpace.discrete(3) != ActionSpace.discrete(4)


def test_vector_and_chunk_envs_satisfy_the_env_protocol():
    from infinirl.envs import ActionChunkEnv, Env, SubEnv, VectorEnv
    from tests.unit.envs.toy_envs import CounterEnv, CounterFactory

    assert isinstance(CounterEnv(), SubEnv)
    with VectorEnv(CounterFactory(), 2, num_workers=0) as env:
        assert isinstance(env, Env) and isinstance(ActionChunkEnv(env, 2), Env)
        env.offload()  # CPU simulators: no device memory, a no-op that must not fail
        env.reload()
        assert env.observation_spec["state"].shape == (3,)
