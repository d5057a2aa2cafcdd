"""SE(3) helpers on 4x4 homogeneous matrices.

Twist convention: ``xi = (omega, v)`` with rotation first, matching the ICP linearisation
``A_i = n_i^T [-[p'_i]x  I]``; ``exp(xi)`` is the closed-form SE(3) exponential.
All functions accept a single pose ``(4, 4)`` or a batch ``(N, 4, 4)`` where noted.
"""

from __future__ import annotations

import math

import numpy as np

from surfelslam.errors import ConfigValueError

_SMALL_ANGLE_RAD = 1e-8  # below this angle, series expansions replace the closed forms
_LOG_SERIES_RAD = 1e-3  # below this angle the log's scale angle / sin(angle / 2) is its series (as scipy)
#: A stack's rotation whose ``R R^T`` differs from ``I`` by more than ``atol + rtol |I|`` (numpy's ``isclose``, as
#: scipy's ``Rotation.from_matrix``) is first replaced by its nearest rotation (SVD); the others are taken as they are.
_ORTHO_ATOL = 1e-12
_ORTHO_RTOL = 1e-5


def skew(w: np.ndarray) -> np.ndarray:
    """``(3,)`` vector -> ``(3, 3)`` cross-product matrix ``[w]x`` with ``[w]x p = w x p``."""
    w = np.asarray(w, dtype=np.float64)
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def make_T(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Rotation(s) ``(..., 3, 3)`` and translation(s) ``(..., 3)`` -> pose(s) ``(..., 4, 4)``."""
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    T = np.zeros(R.shape[:-2] + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def invert(T: np.ndarray) -> np.ndarray:
    """Inverse of pose(s) ``(..., 4, 4)`` using ``R^T``, not a general matrix inverse."""
    T = np.asarray(T, dtype=np.float64)
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    Rt = np.swapaxes(R, -1, -2)
    return make_T(Rt, -np.einsum("...ij,...j->...i", Rt, t))


def orthonormalize(T: np.ndarray) -> np.ndarray:
    """Nearest rigid transform: the rotation block projected onto SO(3) (SVD), translation kept.

    Products of many poses drift off SO(3) by rounding; :func:`invert` assumes ``R^T = R^-1``, so a
    tracker that chains poses must re-project them, or the error compounds frame after frame.
    """
    T = np.array(T, dtype=np.float64)
    U, _, Vt = np.linalg.svd(T[:3, :3])
    R = U @ Vt
    if np.linalg.det(R) < 0:
        U[:, -1] *= -1
        R = U @ Vt
    T[:3, :3] = R
    T[3] = (0.0, 0.0, 0.0, 1.0)
    return T


def adjoint(T: np.ndarray) -> np.ndarray:
    """Adjoint ``(..., 6, 6)`` of poses ``(..., 4, 4)`` on twists ``(omega, v)`` (gtsam's tangent order):
    ``T exp(xi) T^-1 = exp(adjoint(T) xi)``."""
    T = np.asarray(T, dtype=np.float64)
    R, t = T[..., :3, :3], T[..., :3, 3]
    out = np.zeros(T.shape[:-2] + (6, 6))
    out[..., :3, :3] = R
    out[..., 3:, 3:] = R
    t_x = np.zeros(T.shape[:-2] + (3, 3))
    t_x[..., 0, 1], t_x[..., 0, 2], t_x[..., 1, 2] = -t[..., 2], t[..., 1], -t[..., 0]
    out[..., 3:, :3] = (t_x - np.swapaxes(t_x, -1, -2)) @ R
    return out


def compose(*Ts: np.ndarray) -> np.ndarray:
    """``compose(A, B, C) = A @ B @ C``."""
    out = np.asarray(Ts[0], dtype=np.float64)
    for T in Ts[1:]:
        out = out @ T
    return out


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply pose ``(4, 4)`` to points ``(..., 3)``."""
    return points @ T[:3, :3].T + T[:3, 3]


def so3_exp(omega: np.ndarray) -> np.ndarray:
    """Rodrigues: axis-angle ``(3,)`` -> rotation ``(3, 3)``."""
    omega = np.asarray(omega, dtype=np.float64)
    theta = float(np.linalg.norm(omega))
    W = skew(omega)
    if theta < _SMALL_ANGLE_RAD:
        return np.eye(3) + W + 0.5 * W @ W
    return np.eye(3) + np.sin(theta) / theta * W + (1 - np.cos(theta)) / theta**2 * W @ W


def so3_exp_many(omega: np.ndarray) -> np.ndarray:
    """Rodrigues for many: axis-angles ``(N, 3)`` -> rotations ``(N, 3, 3)`` (Taylor terms below the small angle)."""
    omega = np.asarray(omega, dtype=np.float64).reshape(-1, 3)
    theta = np.linalg.norm(omega, axis=1)
    small = theta < _SMALL_ANGLE_RAD
    t = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta**2 / 6.0, np.sin(t) / t)
    b = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(t)) / t**2)
    W = np.zeros((len(omega), 3, 3))
    W[:, 0, 1], W[:, 0, 2], W[:, 1, 2] = -omega[:, 2], omega[:, 1], -omega[:, 0]
    W[:, 1, 0], W[:, 2, 0], W[:, 2, 1] = omega[:, 2], -omega[:, 1], omega[:, 0]
    return np.eye(3) + a[:, None, None] * W + b[:, None, None] * (W @ W)


def so3_log(R: np.ndarray) -> np.ndarray:
    """Rotation(s) ``(..., 3, 3)`` -> axis-angle(s) ``(..., 3)``, robust near 0 and pi.

    One matrix goes through :func:`_so3_log_one` (the trackers call this per frame and per edge); a stack through
    :func:`_quaternions` and the same angle formula: scipy's ``Rotation.from_matrix(R).as_rotvec()`` in numpy
    (a run's start-up does not import scipy.spatial for it).
    """
    R = np.asarray(R, dtype=np.float64)
    if R.shape == (3, 3):
        return _so3_log_one(R)
    q = _quaternions(R.reshape(-1, 3, 3))
    # the canonical cover (scipy's): w > 0, or w = 0 and the first non-zero of x, y, z positive
    x, y, z, w = q.T
    flip = (w < 0) | ((w == 0) & ((x < 0) | ((x == 0) & ((y < 0) | ((y == 0) & (z < 0))))))
    q[flip] = -q[flip]
    v_norm = np.sqrt(q[:, 0] * q[:, 0] + q[:, 1] * q[:, 1] + q[:, 2] * q[:, 2])
    # libm's atan2 and sin, one value at a time: numpy's vectorised ones may differ in the last bit from the scalar
    # path's (math), and a stack must give what its matrices give one by one
    from surfelslam.geometry import so3_kernels  # here: importing se3 does not import numba (the CLI sets
    # numba's cache folder first)

    scale = so3_kernels.log_scales(v_norm, np.ascontiguousarray(q[:, 3]), _LOG_SERIES_RAD)
    return (q[:, :3] * scale.reshape(-1, 1)).reshape(R.shape[:-2] + (3,))


def _log_scale(angle: float) -> float:
    """``angle / sin(angle / 2)``: the factor from a unit quaternion's vector part to its axis-angle (series below
    :data:`_LOG_SERIES_RAD`)."""
    if angle <= _LOG_SERIES_RAD:
        a2 = angle * angle
        return 2.0 + a2 / 12.0 + 7.0 * a2 * a2 / 2880.0
    return angle / math.sin(angle / 2.0)


def _quaternions(R: np.ndarray) -> np.ndarray:
    """Unit quaternions ``(N, 4)`` (``x, y, z, w``; either sign) of rotations ``(N, 3, 3)``: scipy's
    ``Rotation.from_matrix`` (numbers bit for bit, checks as its): a matrix with a non-positive determinant is
    refused (ConfigValueError, a ValueError as scipy's), one visibly off a rotation (:func:`_is_rotation`) is
    projected onto SO(3) by SVD, then :func:`_markley` gives the quaternion."""
    R = np.array(R, dtype=np.float64)
    if len(R) == 1 and _is_rotation(R[0]):  # one pose per frame (the streamed trajectory): scalars are quicker
        return np.array([_markley(*R[0].ravel().tolist())])
    if len(R) == 0:
        return np.zeros((0, 4))
    det = np.linalg.det(R)
    if np.any(det <= 0):
        bad = int(np.flatnonzero(det <= 0)[0])
        raise ConfigValueError(f"rotation {bad} has a non-positive determinant ({det[bad]:g}): not a rotation")
    gram = R @ np.swapaxes(R, 1, 2)
    eye = np.eye(3)
    off = ~np.all(np.abs(gram - eye) <= _ORTHO_ATOL + _ORTHO_RTOL * eye, axis=(1, 2))
    if off.any():
        U, _, Vt = np.linalg.svd(R[off])
        R[off] = U @ Vt
    from surfelslam.geometry import so3_kernels  # here, as in so3_log

    return so3_kernels.markley_many(np.ascontiguousarray(R.reshape(-1, 9)))


def _is_rotation(R: np.ndarray) -> bool:
    """Whether ``R`` ``(3, 3)`` has a positive determinant and ``R R^T`` within :data:`_ORTHO_ATOL` /
    :data:`_ORTHO_RTOL` of ``I`` (then :func:`_quaternions` takes it as it is)."""
    rows = R.tolist()
    (a, b, c), (d, e, f), (g, h, i) = rows
    if not a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g) > 0:
        return False
    for k in range(3):
        for m in range(k, 3):
            dot = rows[k][0] * rows[m][0] + rows[k][1] * rows[m][1] + rows[k][2] * rows[m][2]
            if not abs(dot - (k == m)) <= _ORTHO_ATOL + _ORTHO_RTOL * (k == m):
                return False
    return True


def _markley(r00: float, r01: float, r02: float, r10: float, r11: float, r12: float, r20: float, r21: float,
             r22: float) -> tuple[float, float, float, float]:
    """Markley's unit quaternion ``(x, y, z, w)`` of a rotation given row by row, as scipy computes it: from the
    largest of the diagonal entries and the trace (the first on ties), the others from the (anti)symmetric parts."""
    d = (r00, r11, r22, r00 + r11 + r22)
    choice = max(range(4), key=d.__getitem__)  # the first of equal maxima, as numpy's argmax
    if choice == 0:
        q = (1.0 - d[3] + 2.0 * r00, r10 + r01, r20 + r02, r21 - r12)
    elif choice == 1:
        q = (r01 + r10, 1.0 - d[3] + 2.0 * r11, r21 + r12, r02 - r20)
    elif choice == 2:
        q = (r02 + r20, r12 + r21, 1.0 - d[3] + 2.0 * r22, r10 - r01)
    else:
        q = (r21 - r12, r02 - r20, r10 - r01, 1.0 + d[3])
    x, y, z, w = q
    n = math.sqrt(x * x + y * y + z * z + w * w)
    return x / n, y / n, z / n, w / n


def _so3_log_one(R: np.ndarray) -> np.ndarray:
    """Axis-angle ``(3,)`` of one rotation ``(3, 3)``: scipy's method in scalars (Markley's quaternion from the
    largest of four candidates, sign fixed to ``w >= 0``, then ``2 atan2(|v|, w)``, series below 1e-3 rad)."""
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = R.tolist()
    tr = r00 + r11 + r22
    if tr >= r00 and tr >= r11 and tr >= r22:
        x, y, z, w = r21 - r12, r02 - r20, r10 - r01, 1.0 + tr
    elif r00 >= r11 and r00 >= r22:
        x, y, z, w = 1.0 - tr + 2.0 * r00, r10 + r01, r20 + r02, r21 - r12
    elif r11 >= r22:
        x, y, z, w = r01 + r10, 1.0 - tr + 2.0 * r11, r21 + r12, r02 - r20
    else:
        x, y, z, w = r02 + r20, r12 + r21, 1.0 - tr + 2.0 * r22, r10 - r01
    n = math.sqrt(x * x + y * y + z * z + w * w)
    if w < 0.0:
        n = -n
    x, y, z, w = x / n, y / n, z / n, w / n
    scale = _log_scale(2.0 * math.atan2(math.sqrt(x * x + y * y + z * z), w))
    return np.array([scale * x, scale * y, scale * z])


def _left_jacobian(omega: np.ndarray) -> np.ndarray:
    theta = float(np.linalg.norm(omega))
    W = skew(omega)
    if theta < _SMALL_ANGLE_RAD:
        return np.eye(3) + 0.5 * W + W @ W / 6.0
    return (
        np.eye(3)
        + (1 - np.cos(theta)) / theta**2 * W
        + (theta - np.sin(theta)) / theta**3 * W @ W
    )


def exp(xi: np.ndarray) -> np.ndarray:
    """SE(3) exponential: twist ``(6,) = (omega, v)`` -> pose ``(4, 4)``."""
    xi = np.asarray(xi, dtype=np.float64).reshape(6)
    omega, v = xi[:3], xi[3:]
    return make_T(so3_exp(omega), _left_jacobian(omega) @ v)


def log(T: np.ndarray) -> np.ndarray:
    """SE(3) logarithm: pose ``(4, 4)`` -> twist ``(6,) = (omega, v)``."""
    T = np.asarray(T, dtype=np.float64)
    omega = so3_log(T[:3, :3])
    v = np.linalg.solve(_left_jacobian(omega), T[:3, 3])
    return np.concatenate([omega, v])


def small_angle_update(xi: np.ndarray) -> np.ndarray:
    """First-order update ``[[I + [omega]x, v], [0, 1]]`` re-orthonormalised by SVD.

    This is the reference assignment's linearised increment; :func:`exp` is the exact one.
    """
    xi = np.asarray(xi, dtype=np.float64).reshape(6)
    return orthonormalize(make_T(np.eye(3) + skew(xi[:3]), xi[3:]))


def rotation_to_quat_xyzw(R: np.ndarray) -> np.ndarray:
    """Rotation(s) ``(..., 3, 3)`` -> unit quaternion(s) ``(..., 4)`` in ``(qx, qy, qz, qw)`` order, qw >= 0."""
    R = np.asarray(R, dtype=np.float64)
    q = _quaternions(R.reshape(-1, 3, 3))
    q *= np.where(q[:, 3:4] < 0, -1.0, 1.0)
    return q.reshape(R.shape[:-2] + (4,))


def quat_xyzw_to_rotation(q: np.ndarray) -> np.ndarray:
    """Quaternion(s) ``(..., 4)`` in ``(qx, qy, qz, qw)`` order -> rotation(s) ``(..., 3, 3)``.

    Quaternions are normalised first, so slightly non-unit file values are accepted; a zero one is refused
    (ConfigValueError, a ValueError as scipy's). The numbers are scipy's ``Rotation.from_quat(q).as_matrix()``'s,
    bit for bit.
    """
    q = np.asarray(q, dtype=np.float64)
    flat = q.reshape(-1, 4)
    x, y, z, w = flat.T
    norm = np.sqrt(x * x + y * y + z * z + w * w)
    if np.any(norm == 0):
        raise ConfigValueError("a quaternion of zero norm is not a rotation")
    x, y, z, w = x / norm, y / norm, z / norm, w / norm
    x2, y2, z2, w2 = x * x, y * y, z * z, w * w
    xy, zw, xz, yw, yz, xw = x * y, z * w, x * z, y * w, y * z, x * w
    R = np.empty((len(flat), 3, 3))
    R[:, 0, 0], R[:, 0, 1], R[:, 0, 2] = x2 - y2 - z2 + w2, 2 * (xy - zw), 2 * (xz + yw)
    R[:, 1, 0], R[:, 1, 1], R[:, 1, 2] = 2 * (xy + zw), -x2 + y2 - z2 + w2, 2 * (yz - xw)
    R[:, 2, 0], R[:, 2, 1], R[:, 2, 2] = 2 * (xz - yw), 2 * (yz + xw), -x2 - y2 + z2 + w2
    return R.reshape(q.shape[:-1] + (3, 3))


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle of a rotation ``(3, 3)`` in degrees (robust for small angles)."""
    return float(np.degrees(np.linalg.norm(so3_log(R))))


def pose_error(T_est: np.ndarray, T_ref: np.ndarray) -> tuple[float, float]:
    """``(translation error m, rotation error deg)`` of ``T_ref^-1 T_est``."""
    E = invert(T_ref) @ T_est
    return float(np.linalg.norm(E[:3, 3])), rotation_angle_deg(E[:3, :3])


def motion_norm(T: np.ndarray) -> float:
    """The reference assignment's motion norm ``||t|| + min(||r||, 2 pi - ||r||)`` (metres + radians)."""
    r = float(np.linalg.norm(so3_log(T[:3, :3])))
    return float(np.linalg.norm(T[:3, 3])) + min(r, 2 * np.pi - r)
