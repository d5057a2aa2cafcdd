"""ICP on degenerate geometry: the depth-scaled normal matrix and its condition number, the weak directions that
solution remapping leaves at the initial guess, and the 6x6 eigen-decomposition behind them."""

from dataclasses import replace

import numpy as np
import pytest

from surfelslam.geometry import se3
from surfelslam.kernels import icp as kicp
from surfelslam.synth import make_scene, render
from surfelslam.synth.trajectories import look_at
from surfelslam.tracking.icp import ICPConfig, condition_number, depth_scaled, register_frames

from helpers import INTR, motion


def test_single_plane_is_degenerate():
    scene = make_scene("plane")
    T_w_t = look_at(np.array([1.5, 0.0, 1.5]), np.array([0.0, 0.1, 1.4]))[0]
    T_t_s = motion((0, 0, 1), 2, (0, 1, 0), 0.03)
    dt = render(scene, T_w_t, INTR).depth_m.copy()
    ds = render(scene, T_w_t @ T_t_s, INTR).depth_m.copy()
    res = register_frames(ds, dt, INTR)
    assert res.degenerate and not res.converged
    assert res.condition_number > ICPConfig().max_condition_number
    assert "degenerate" in res.reason


def test_remapped_step_drops_only_weak_directions():
    rng = np.random.default_rng(5)
    d = 2.0
    s = np.array([1 / d] * 3 + [1.0] * 3)
    V, _ = np.linalg.qr(rng.normal(size=(6, 6)))
    Atb = rng.normal(size=6)
    # scaled normal matrix S AtA S = V diag(lam) V^T: eigenvalue ratios 50 (kept) and 5000 (frozen at 1000)
    lam_ok = np.array([1.0, 2.0, 5.0, 10.0, 30.0, 50.0])
    AtA_ok = (V * lam_ok) @ V.T / s[:, None] / s[None, :]
    xi, n = kicp.remapped_step_ref(AtA_ok, Atb, d, 1000.0)
    assert xi is None and n == 0  # nothing weak: the ordinary solve is used
    lam = np.array([0.01, 2.0, 5.0, 10.0, 30.0, 50.0])
    AtA = (V * lam) @ V.T / s[:, None] / s[None, :]
    xi, n = kicp.remapped_step_ref(AtA, Atb, d, 1000.0)
    assert n == 1
    xi_s = xi / s
    assert abs(V[:, 0] @ xi_s) < 1e-12  # no step along the weak direction
    # along the kept directions it is the Gauss-Newton step: V_k^T (S AtA S xi_s + S Atb) = 0
    r = (AtA * s[:, None] * s[None, :]) @ xi_s + s * Atb
    np.testing.assert_allclose(V[:, 1:].T @ r, 0.0, atol=1e-12)
    # the numba kernel: same step, applied as T_out = exp(xi) T
    stats = np.zeros(kicp.N_STATS)
    stats[:21] = AtA[np.triu_indices(6)]
    stats[21:27] = Atb
    T = motion((1, 0, 0), 3, (0, 1, 0), 0.02)
    T_out = np.empty((4, 4))
    assert kicp.remapped_gauss_newton_step(stats, d, 1000.0, T, T_out) == (1, pytest.approx(np.linalg.norm(xi)))
    np.testing.assert_allclose(T_out, se3.exp(xi) @ T, atol=1e-12)
    stats[:21] = AtA_ok[np.triu_indices(6)]
    assert kicp.remapped_gauss_newton_step(stats, d, 1000.0, T, T_out)[0] == 0


@pytest.mark.parametrize("spread", ["even", "graded", "repeated"])
def test_jacobi_eigh6_matches_numpy(spread):
    """The step's hand-written 6x6 eigen-decomposition against numpy's (LAPACK): eigenvalues ascending, to 1e-12 of
    the largest, eigenvectors orthonormal and reproducing the matrix, also when eigenvalues span 15 decades (a
    near-degenerate ICP system) or repeat (a symmetric scene)."""
    rng = np.random.default_rng({"even": 1, "graded": 2, "repeated": 3}[spread])
    for _ in range(50):
        Q, _ = np.linalg.qr(rng.normal(size=(6, 6)))
        lam_true = 10.0 ** rng.uniform(-9, 6, 6) if spread == "graded" else rng.uniform(0.1, 10.0, 6)
        if spread == "repeated":
            lam_true[:3] = lam_true[3]
        A = (Q * lam_true) @ Q.T
        A = (A + A.T) / 2
        lam, V = np.empty(6), np.empty((6, 6))
        kicp.jacobi_eigh6(A.copy(), lam, V)
        scale = np.abs(lam_true).max()
        np.testing.assert_allclose(lam, np.linalg.eigvalsh(A), rtol=0, atol=1e-12 * scale)
        np.testing.assert_allclose(V.T @ V, np.eye(6), atol=1e-12)
        np.testing.assert_allclose((V * lam) @ V.T, A, rtol=0, atol=1e-12 * scale)


def test_weak_directions_keep_the_initial_guess_on_a_plane():
    """A single plane constrains 3 of 6 DoF: with solution remapping, ICP corrects the offset along the normal
    and leaves the in-plane offset of the initial guess exactly where it was (instead of sliding)."""
    scene = make_scene("plane")
    T_w_t = look_at(np.array([1.5, 0.0, 1.5]), np.array([0.0, 0.1, 1.4]))[0]
    T_t_s = motion((0, 0, 1), 2, (0, 1, 0), 0.03)
    rt = render(scene, T_w_t, INTR)
    ds = render(scene, T_w_t @ T_t_s, INTR).depth_m.copy()
    valid = rt.depth_m > 0
    n = np.median(rt.normal_cam[valid], axis=0)
    n /= np.linalg.norm(n)
    t_in = np.cross(n, [0.0, 1.0, 0.0])
    t_in /= np.linalg.norm(t_in)
    T_init = se3.exp(np.concatenate([np.zeros(3), 0.01 * t_in + 0.01 * n])) @ T_t_s
    cfg = replace(ICPConfig(), weak_direction_ratio=1000.0)
    res = register_frames(ds, rt.depth_m.copy(), INTR, T_init=T_init, icp_cfg=cfg)
    assert res.degenerate and all(li.frozen_directions == 3 for li in res.levels)
    dT = res.T_target_source @ se3.invert(T_t_s)
    np.testing.assert_allclose(dT[:3, 3], 0.01 * t_in, atol=5e-4)  # normal offset corrected, in-plane kept
    assert se3.rotation_angle_deg(dT[:3, :3]) < 0.05


def test_condition_number_scaling():
    rng = np.random.default_rng(3)
    A = rng.normal(size=(1000, 6))
    A[:, :3] *= 2.0  # rotation columns ~ depth (2 m) times the translation columns
    assert condition_number(A.T @ A, 2.0) < 2.0 * condition_number(A.T @ A * 1.0, 1e-6) ** 0.5


def test_depth_scaled_normal_matrix():
    """Rotation rows and columns divided by the mean depth, translation ones kept: S AtA S with S = (1/d)*3 + 1*3."""
    AtA = np.arange(36, dtype=float).reshape(6, 6) + 1.0
    M, s = depth_scaled(AtA, 2.0)
    np.testing.assert_array_equal(s, [0.5, 0.5, 0.5, 1.0, 1.0, 1.0])
    np.testing.assert_array_equal(M[:3, :3], AtA[:3, :3] / 4.0)
    np.testing.assert_array_equal(M[:3, 3:], AtA[:3, 3:] / 2.0)
    np.testing.assert_array_equal(M[3:, :3], AtA[3:, :3] / 2.0)
    np.testing.assert_array_equal(M[3:, 3:], AtA[3:, 3:])
