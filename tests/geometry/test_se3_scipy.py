"""The rotation conversions of :mod:`surfelslam.geometry.se3` are numpy ports of scipy's ``Rotation`` (which the
library does not import: a run's start-up needs no scipy.spatial); here they are checked against scipy, bit for bit,
on random rotations and on the edge cases: angles near 0, at the log's series bound, near and at pi, ties between the
diagonal and the trace, drifted and visibly non-orthogonal matrices, scaled quaternions."""

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from surfelslam.geometry import se3


def _edge_rotations(rng) -> np.ndarray:
    R = [np.eye(3), np.diag([1.0, -1, -1]), np.diag([-1.0, 1, -1]), np.diag([-1.0, -1, 1]),
         np.array([[0.0, -1, 0], [-1, 0, 0], [0, 0, -1]]), np.array([[-1.0, 0, 0], [0, 0, 1], [0, 1, 0]]),
         np.array([[0.0, 1, 0], [1, 0, 0], [0, 0, -1]]), np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])]
    for angle in (1e-9, 1e-4, 1e-3, 1.0000001e-3, 0.5, np.pi / 2, np.pi - 1e-7, np.pi - 1e-12, np.pi):
        axes = np.concatenate([rng.normal(size=(10, 3)), np.eye(3), -np.eye(3)])
        R += [se3.so3_exp(a / np.linalg.norm(a) * angle) for a in axes]
    return np.stack(R)


def _rotations() -> np.ndarray:
    rng = np.random.default_rng(11)
    base = Rotation.random(300, rng=rng).as_matrix()
    drifted = base + rng.normal(size=base.shape) * 1e-14  # rounding drift: taken as it is
    skewed = base + rng.normal(size=base.shape) * 1e-3  # visibly off: projected by SVD first
    return np.concatenate([Rotation.random(2000, rng=rng).as_matrix(), _edge_rotations(rng), drifted, skewed,
                           base * (1 + 1e-4)])


def test_quaternions_equal_scipy_bit_for_bit():
    R = _rotations()
    expected = Rotation.from_matrix(R).as_quat()
    expected *= np.where(expected[:, 3:4] < 0, -1.0, 1.0)
    np.testing.assert_array_equal(se3.rotation_to_quat_xyzw(R), expected)
    for k in (0, 2005, len(R) - 1):  # one matrix at a time (the streamed trajectory's path)
        np.testing.assert_array_equal(se3.rotation_to_quat_xyzw(R[k]), expected[k])


def test_so3_exp_of_a_stack_equals_scipy_and_the_single_rodrigues():
    rng = np.random.default_rng(5)
    omega = np.concatenate([rng.normal(size=(500, 3)), rng.normal(size=(50, 3)) * 1e-7, np.zeros((1, 3)),
                            [[np.pi, 0.0, 0.0], [0.0, 1e-3, 0.0]]])
    R = se3.so3_exp_many(omega)
    np.testing.assert_allclose(R, Rotation.from_rotvec(omega).as_matrix(), atol=2e-15)
    np.testing.assert_allclose(R[:3], [se3.so3_exp(w) for w in omega[:3]], atol=2e-15)
    assert se3.so3_exp_many(np.zeros((0, 3))).shape == (0, 3, 3)


def test_so3_log_of_a_stack_equals_scipy_bit_for_bit():
    R = _rotations()
    np.testing.assert_array_equal(se3.so3_log(R), Rotation.from_matrix(R).as_rotvec())
    assert se3.so3_log(R[:6].reshape(2, 3, 3, 3)).shape == (2, 3, 3)
    assert se3.so3_log(np.zeros((0, 3, 3))).shape == (0, 3)


def test_rotation_of_quaternions_equals_scipy_bit_for_bit():
    rng = np.random.default_rng(12)
    q = rng.normal(size=(3000, 4))
    q[:10] *= 1e-100  # tiny and huge file values: normalised first
    q[10:20] *= 1e150
    q[20:24] = np.eye(4)
    np.testing.assert_array_equal(se3.quat_xyzw_to_rotation(q), Rotation.from_quat(q).as_matrix())
    np.testing.assert_array_equal(se3.quat_xyzw_to_rotation(q[5]), Rotation.from_quat(q[5]).as_matrix())
    assert se3.quat_xyzw_to_rotation(q.reshape(3, 1000, 4)).shape == (3, 1000, 3, 3)


@pytest.mark.parametrize("R", [np.diag([1.0, 1.0, -1.0]), np.zeros((3, 3))])
def test_a_reflection_or_a_singular_matrix_is_refused(R):
    with pytest.raises(ValueError, match="non-positive determinant"):
        se3.rotation_to_quat_xyzw(R)
    with pytest.raises(ValueError, match="non-positive determinant"):
        se3.so3_log(np.stack([np.eye(3), R]))


def test_a_zero_quaternion_is_refused():
    with pytest.raises(ValueError, match="zero norm"):
        se3.quat_xyzw_to_rotation(np.array([[0.0, 0.0, 0.0, 1.0], [0.0, 0.0, 0.0, 0.0]]))


def test_stack_kernels_equal_the_scalar_helpers_bit_for_bit():
    """The compiled loops of the stack path (Markley's quaternion and the log's angle scale,
    :mod:`surfelslam.geometry.so3_kernels`) give, to the last bit, what the scalar helpers give one matrix at a
    time (ties, near 0, the series bound, near pi, drifted matrices): the stack path's numbers did not change."""
    from surfelslam.geometry import so3_kernels as kso3

    R = _rotations()
    R = R[np.linalg.det(R) > 0]
    q = kso3.markley_many(np.ascontiguousarray(R.reshape(-1, 9)))
    expected = np.array([se3._markley(*r) for r in R.reshape(-1, 9).tolist()])
    np.testing.assert_array_equal(q.view(np.int64), expected.view(np.int64))
    v_norm = np.sqrt(q[:, 0] * q[:, 0] + q[:, 1] * q[:, 1] + q[:, 2] * q[:, 2])
    w = np.abs(q[:, 3])
    scale = kso3.log_scales(v_norm, w, se3._LOG_SERIES_RAD)
    angles = [2.0 * math.atan2(n, c) for n, c in zip(v_norm.tolist(), w.tolist(), strict=True)]
    expected = np.array([se3._log_scale(a) for a in angles])
    np.testing.assert_array_equal(scale.view(np.int64), expected.view(np.int64))
    assert sum(a <= se3._LOG_SERIES_RAD for a in angles) > 10  # the series branch was taken too
