"""SE(3) helpers on 4x4 homogeneous matrices.

Twist convention: ``xi = (omega, v)`` with rotation first, matching the ICP linearisation
``A_i = n_i^T [-[p'_i]x  I]``; ``exp(xi)`` is the closed-form SE(3) exponential.
All functions accept a single pose ``(4, 4)`` or a batch ``(N, 4, 4)`` where noted.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation

_SMALL_ANGLE_RAD = 1e-8  # below this angle, series expansions replace the closed forms
_LOG_SERIES_RAD = 1e-3  # below this angle the log's scale angle / sin(angle / 2) is its series (as scipy)


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


def so3_log(R: np.ndarray) -> np.ndarray:
    """Rotation(s) ``(..., 3, 3)`` -> axis-angle(s) ``(..., 3)``, robust near 0 and pi.

    One matrix goes through :func:`_so3_log_one` (the trackers call this per frame and per edge: scipy's
    ``Rotation`` costs about 0.1 ms a call in object overhead); stacks go through scipy.
    """
    R = np.asarray(R, dtype=np.float64)
    if R.shape == (3, 3):
        return _so3_log_one(R)
    return Rotation.from_matrix(R).as_rotvec()


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
    angle = 2.0 * math.atan2(math.sqrt(x * x + y * y + z * z), w)
    if angle <= _LOG_SERIES_RAD:
        a2 = angle * angle
        scale = 2.0 + a2 / 12.0 + 7.0 * a2 * a2 / 2880.0
    else:
        scale = angle / math.sin(angle / 2.0)
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
    q = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_quat()
    q *= np.where(q[:, 3:4] < 0, -1.0, 1.0)
    return q.reshape(R.shape[:-2] + (4,))


def quat_xyzw_to_rotation(q: np.ndarray) -> np.ndarray:
    """Quaternion(s) ``(..., 4)`` in ``(qx, qy, qz, qw)`` order -> rotation(s) ``(..., 3, 3)``.

    Quaternions are normalised first, so slightly non-unit file values are accepted.
    """
    q = np.asarray(q, dtype=np.float64)
    R = Rotation.from_quat(q.reshape(-1, 4)).as_matrix()
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
