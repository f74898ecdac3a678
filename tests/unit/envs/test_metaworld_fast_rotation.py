"""The MetaWorld object-quaternion fast path gives scipy's numbers bit for bit (and scipy's errors)."""

import numpy as np
import pytest

from infinirl.envs.fast_rotation import FastRotation, matrix_to_quaternion, use_fast_rotation

# scipy is the reference here and comes with the simulator extras (MetaWorld needs it), not with the
# base install
Rotation = pytest.importorskip("scipy.spatial.transform").Rotation


def _scipy(matrix):
    return Rotation.from_matrix(matrix).as_quat()


def _axis_angle(axis, angle):
    return Rotation.from_rotvec(np.asarray(axis, float) / np.linalg.norm(axis) * angle).as_matrix()


def test_random_rotations_match_scipy_bitwise():
    for matrix in Rotation.random(5000, random_state=0).as_matrix():
        np.testing.assert_array_equal(matrix_to_quaternion(matrix), _scipy(matrix))


@pytest.mark.parametrize("matrix", [
    np.eye(3),
    np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0]), np.diag([-1.0, -1.0, 1.0]),  # 180 deg: ties
    _axis_angle([1, 1, 1], 2 * np.pi / 3),  # m00 = m11 = m22: argmax ties among the diagonal
    _axis_angle([1, 1, 1], np.pi),
    _axis_angle([0, 0, 1], np.pi / 2), _axis_angle([1, 0, 0], -np.pi / 2),
    _axis_angle([1, 0, 0], np.pi - 1e-9),  # trace and m00 within rounding of each other
], ids=lambda m: np.array2string(np.round(m.ravel(), 2), separator=","))
def test_branch_boundaries_match_scipy_bitwise(matrix):
    np.testing.assert_array_equal(matrix_to_quaternion(matrix), _scipy(matrix))


@pytest.mark.parametrize("scale", [1e-15, 1e-13, 1e-12, 1e-11, 1e-8, 1e-3])
def test_nearly_orthogonal_matrices_take_scipys_path(scale):
    """Around scipy's orthogonality tolerance, where it switches to an SVD projection."""
    rng = np.random.default_rng(1)
    for matrix in Rotation.random(200, random_state=2).as_matrix():
        noisy = matrix + rng.normal(scale=scale, size=(3, 3))
        np.testing.assert_array_equal(matrix_to_quaternion(noisy), _scipy(noisy))


def test_other_dtypes_and_shapes_are_scipys_results():
    matrix = Rotation.random(random_state=3).as_matrix()
    for other in (matrix.astype(np.float32), matrix.tolist(), matrix[None]):
        np.testing.assert_array_equal(matrix_to_quaternion(other), _scipy(other))


def test_invalid_matrices_fail_as_in_scipy():
    for bad in (np.diag([1.0, 1.0, -1.0]), np.zeros((3, 3))):
        with pytest.raises(ValueError, match="determinant"):
            matrix_to_quaternion(bad)
    nan = np.full((3, 3), np.nan)
    with pytest.raises(ValueError):
        _scipy(nan)
    with pytest.raises(ValueError):
        matrix_to_quaternion(nan)


def test_fast_rotation_forwards_everything_else_to_scipy():
    assert FastRotation.from_quat is Rotation.from_quat
    quat = FastRotation.from_matrix(np.eye(3)).as_quat()
    quat[0] = 5.0  # a copy, as scipy returns
    np.testing.assert_array_equal(FastRotation.from_matrix(np.eye(3)).as_quat(), [0, 0, 0, 1])


def test_use_fast_rotation_swaps_only_scipys_rotation(monkeypatch):
    import sys
    import types

    module = types.ModuleType("fake_metaworld_task")
    module.Rotation = Rotation
    cls = type("Task", (), {"__module__": module.__name__})
    monkeypatch.setitem(sys.modules, module.__name__, module)
    assert use_fast_rotation(cls) and module.Rotation is FastRotation
    assert use_fast_rotation(cls)  # idempotent
    del module.Rotation
    assert not use_fast_rotation(cls) and not hasattr(module, "Rotation")


@pytest.mark.parametrize("task", ["reach-v3", "pick-place-v3", "door-open-v3"])
def test_metaworld_observations_equal_scipys(task, monkeypatch):
    """Real states of tasks whose observation holds an object quaternion: the observation
    assembled with the fast path equals the one assembled with scipy, at every step."""
    pytest.importorskip("metaworld")
    import sys

    from infinirl.envs.metaworld_env import MetaWorldSubEnv

    env = MetaWorldSubEnv(task)
    module = sys.modules[type(env._sim).__module__]
    assert module.Rotation is FastRotation
    rng = np.random.default_rng(0)
    env.reset(seed=3)
    try:
        for _ in range(60):
            env.step(rng.uniform(-1, 1, 4).astype(np.float32))
            fast = env._sim._get_curr_obs_combined_no_goal()
            with monkeypatch.context() as patch:
                patch.setattr(module, "Rotation", Rotation)
                reference = env._sim._get_curr_obs_combined_no_goal()
            np.testing.assert_array_equal(fast, reference)
            assert np.abs(fast[7:11]).sum() > 0  # a real quaternion was observed
    finally:
        env.close()
