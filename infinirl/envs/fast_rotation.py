"""MetaWorld's object quaternions without scipy's per-call overhead, bit for bit the same numbers.

Every MetaWorld v3 task that observes an object's orientation computes it on every step as
``Rotation.from_matrix(xmat.reshape(3, 3)).as_quat()`` (scipy). For one 3x3 matrix scipy's fixed
per-call work (array-API dispatch, determinant, Gram-matrix and ``isclose`` checks) outweighs the
arithmetic many times over, and it is paid on every simulator step, so it is a sizeable share of a
cheap task's step, physics included. :func:`matrix_to_quaternion` does the same arithmetic as
scipy (the orthogonality and handedness checks, then Markley's method and the normalisation, in
scipy's order of operations) on Python floats, and hands anything scipy would treat specially (a
matrix that is not orthogonal within scipy's tolerance, or not right-handed) to scipy itself, so
results and errors are scipy's own. ``tests/unit/envs/test_metaworld_fast_rotation.py`` checks
bitwise equality on random rotations, the branch boundaries and real MetaWorld states.

:func:`use_fast_rotation` puts :class:`FastRotation` in place of ``Rotation`` in the one module
that defines a MetaWorld task class (only if that name is scipy's ``Rotation``); the module's only
use of it is ``from_matrix(...).as_quat()``, and every other attribute is forwarded to scipy.
"""

from __future__ import annotations

import math
import sys
from typing import Any

import numpy as np

__all__ = ["FastRotation", "matrix_to_quaternion", "use_fast_rotation"]

_GRAM_ATOL, _GRAM_RTOL = 1e-12, 1e-5  # scipy's isclose(M @ M.T, I, atol=1e-12) (rtol default 1e-5)


def matrix_to_quaternion(matrix: Any) -> np.ndarray:
    """``scipy.spatial.transform.Rotation.from_matrix(matrix).as_quat()`` for one 3x3 matrix:
    the scalar-last quaternion ``[x, y, z, w]``, with scipy's sign choice (the component picked by
    Markley's method is positive)."""
    m = np.asarray(matrix)
    if m.shape != (3, 3) or m.dtype != np.float64:  # scipy keeps other dtypes: let it decide
        return _scipy_quaternion(m)
    m00, m01, m02, m10, m11, m12, m20, m21, m22 = m.ravel().tolist()
    if not _orthogonal_right_handed(m00, m01, m02, m10, m11, m12, m20, m21, m22):
        return _scipy_quaternion(m)
    trace = m00 + m11 + m22
    decision = (m00, m11, m22, trace)
    choice = max(range(4), key=decision.__getitem__)  # the first maximum, as numpy's argmax
    if choice == 0:
        q = (1 - trace + 2 * m00, m10 + m01, m20 + m02, m21 - m12)
    elif choice == 1:
        q = (m10 + m01, 1 - trace + 2 * m11, m21 + m12, m02 - m20)
    elif choice == 2:
        q = (m20 + m02, m21 + m12, 1 - trace + 2 * m22, m10 - m01)
    else:
        q = (m21 - m12, m02 - m20, m10 - m01, 1 + trace)
    norm = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    return np.array([q[0] / norm, q[1] / norm, q[2] / norm, q[3] / norm])


def _orthogonal_right_handed(m00, m01, m02, m10, m11, m12, m20, m21, m22) -> bool:
    """scipy's test for using a matrix as is: ``M @ M.T`` close to the identity and ``det > 0``."""
    rows = ((m00, m01, m02), (m10, m11, m12), (m20, m21, m22))
    for i, a in enumerate(rows):
        for j, b in enumerate(rows):
            dot = a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
            target = 1.0 if i == j else 0.0
            if not abs(dot - target) <= _GRAM_ATOL + _GRAM_RTOL * abs(target):
                return False
    det = m00 * (m11 * m22 - m12 * m21) - m01 * (m10 * m22 - m12 * m20) + m02 * (m10 * m21 - m11 * m20)
    return det > 0.5  # an orthogonal matrix has det +-1; scipy raises on det <= 0


def _scipy_quaternion(matrix: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(matrix).as_quat()


class _ForwardToScipy(type):
    def __getattr__(cls, name: str) -> Any:
        from scipy.spatial.transform import Rotation

        return getattr(Rotation, name)


class FastRotation(metaclass=_ForwardToScipy):
    """``FastRotation.from_matrix(m).as_quat()`` == scipy's, faster; other attributes are scipy's."""

    __slots__ = ("_quaternion",)

    def __init__(self, quaternion: np.ndarray):
        self._quaternion = quaternion

    @staticmethod
    def from_matrix(matrix: Any) -> "FastRotation":
        return FastRotation(matrix_to_quaternion(matrix))

    def as_quat(self) -> np.ndarray:
        return self._quaternion.copy()


def use_fast_rotation(task_class: type) -> bool:
    """Swap scipy's ``Rotation`` for :class:`FastRotation` in the module defining ``task_class``;
    True if that module uses it (now or already swapped)."""
    from scipy.spatial.transform import Rotation

    module = sys.modules.get(task_class.__module__)
    current = getattr(module, "Rotation", None)
    if current is Rotation:
        module.Rotation = FastRotation
        return True
    return current is FastRotation
