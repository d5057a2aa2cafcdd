"""Coarse-to-fine projective point-to-plane ICP (Gauss-Newton on SE(3)).

``icp(source, target)`` estimates ``T_target_source`` (maps source-camera points into the target
camera frame) from two :class:`~surfelslam.tracking.preprocess.FramePyramid` objects. At each
pyramid level, from the coarsest to the finest, it repeats: projective association + normal
equations (:mod:`surfelslam.kernels.icp`), solve ``(A^T W A) xi = -A^T W b``, ``T <- exp(xi) T``.

Per-level settings are tuples indexed by pyramid level: **index 0 is the finest level**, the last
entry the coarsest. ``iterations=(10, 8, 10, 40)`` thus runs up to 40 iterations at level 3 (1/8 resolution),
then 10 at level 2, 8 at level 1 and 10 at level 0.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np
import scipy.linalg

from surfelslam.config import Config, check, fmt_value, setting
from surfelslam.errors import ConfigError
from surfelslam.geometry import se3
from surfelslam.kernels import icp as kicp
from surfelslam.tracking.photometric import IntensityPyramid, PhotometricTerm
from surfelslam.tracking.preprocess import FramePyramid, PreprocessConfig, Preprocessor
from surfelslam.types import Intrinsics

SOLVERS = ("cholesky", "lu", "qr", "pinv")
_MIN_INLIERS_PER_STEP = 6  # a 6-DoF step needs at least 6 constraints


@dataclass(frozen=True)
class ICPConfig(Config):
    """Settings of :func:`icp`: coarse-to-fine point-to-plane ICP with optional photometric term.

    Per-level lists are indexed by pyramid level, 0 = finest.
    """

    levels: int = setting(4, ge=1, le=10, doc="pyramid levels used (at most the pyramids' depth); 1 = full "
                          "resolution only")
    iterations: tuple[int, ...] = setting((10, 8, 10, 40), unit="iterations", ge=1, le=1000, min_len=1,
                                          doc="maximum Gauss-Newton iterations per level")
    dist_thresh_m: tuple[float, ...] = setting((0.1, 0.2, 0.4, 1.0), unit="m", gt=0, le=100, min_len=1,
                                               doc="association gate on the point distance, per level")
    angle_thresh_deg: tuple[float, ...] = setting((30.0, 45.0, 60.0, 90.0), unit="deg", gt=0, le=180, min_len=1,
                                                  doc="association gate on the angle between the normals, per level")
    solver: str = setting("cholesky", choices=SOLVERS, doc="linear solver of the normal equations (cholesky runs "
                          "in numba)")
    robust_kernel: str = setting("huber", choices=tuple(kicp.ROBUST_KINDS),
                                 doc="m-estimator on the point-to-plane residual")
    robust_scale_m: float = setting(0.02, unit="m", gt=0, le=10,
                                    doc="Huber threshold / Tukey cut-off at the coarser levels (level >= 1)")
    min_update_norm: float = setting(2e-4, unit="rad + m", ge=0, le=1,
                                     doc="a level stops when the update's twist norm falls below this")
    min_relative_residual_change: float = setting(
        3e-3, unit="fraction", ge=0, le=1,
        doc="the finest level stops when the mean squared residual changes by less than this fraction")
    coarse_min_relative_residual_change: float = setting(
        3e-3, unit="fraction", ge=0, le=1,
        doc="the same rule at the coarser levels (they only need to reach the finest level's basin)")
    min_inliers: int = setting(500, unit="pairs", ge=0, le=10_000_000,
                               doc="inliers needed at the finest level (coarser levels: this / 4^level, at least 6)")
    min_inlier_fraction: float = setting(0.25, unit="fraction", ge=0, le=1,
                                         doc="inliers / valid source points needed at the finest level (frame "
                                             "tracking: of the points landing on the map, the rest of the view "
                                             "being space the map does not hold yet)")
    max_condition_number: float = setting(
        1e4, ge=1, allow_inf=True,
        doc="a finest-level normal matrix (rotation scaled by the mean depth) with a larger eigenvalue ratio marks "
            "the problem degenerate; inf: never")
    weak_direction_ratio: float = setting(
        1000.0, ge=0, le=1e12,
        doc="degeneracy-aware update: eigen-directions weaker than the strongest / this keep the predicted pose "
            "(ICP would slide along them); 0 = off")
    max_translation_m: float = setting(0.5, unit="m", gt=0, le=100,
                                       doc="a correction of the initial pose larger than this is rejected")
    max_rotation_deg: float = setting(30.0, unit="deg", gt=0, le=180,
                                      doc="a correction of the initial pose larger than this is rejected")
    finest_source_stride_px: int = setting(2, unit="px", ge=1, le=64,
                                           doc="at the finest level only every s-th source pixel (both axes) is "
                                               "associated; 1 = every pixel")
    finest_robust_scale_m: float = setting(0.005, unit="m", gt=0, le=10,
                                           doc="robust scale at the finest level (smaller: residuals beyond a few mm "
                                               "there are mostly noise and edges)")
    depth_weight_ref_m: float = setting(
        1.5, unit="m", ge=0, le=100,
        doc="finest level: residuals are measured in units of (z / this)^2 (axial noise grows with z^2); 0 = off")
    photometric_weight: float = setting(
        0.1, ge=0, le=1000,
        doc="joint photometric term: an intensity residual of photometric_sigma costs this many point-to-plane "
            "pairs at the level's robust scale")
    photometric_sigma: float = setting(0.02, unit="intensity", gt=0, le=1,
                                       doc="intensity noise on the [0, 1] scale (the residual unit)")
    photometric_huber: float = setting(2.0, unit="sigmas", gt=0, le=100,
                                       doc="Huber threshold of the intensity residual, in photometric_sigma")
    photometric_brightness_offset: bool = setting(True, doc="re-estimate a global brightness offset between the "
                                                  "two views at every iteration (auto-exposure)")

    @check
    def _one_value_per_level(self) -> str | None:
        """iterations, dist_thresh_m and angle_thresh_deg have at least levels values."""
        for name in ("iterations", "dist_thresh_m", "angle_thresh_deg"):
            vals = getattr(self, name)
            if len(vals) < self.levels:
                return f"{name} needs one value per level (levels = {self.levels}), got {fmt_value(vals)}"
        return None


def pairwise_config() -> ICPConfig:
    """Settings of ``surfelslam register`` (one-off registration of frames up to ~1 s apart).

    The :class:`ICPConfig` defaults with a wider basin of convergence: the coarse levels run longer (they stop at a
    1e-4 relative residual change, up to 20/20/80 iterations) with a 5 cm Huber scale, so large motions (20-30 cm,
    10-18 deg) are not frozen half-way by the robust kernel; the finest level stops at a 1e-3 relative residual
    change or a 1e-4 update. This fails less often on frames far apart (``benchmarks/icp_pairs.py``); in
    frame-to-model tracking, where consecutive frames are close, it only costs iterations, so the tracker keeps the
    :class:`ICPConfig` defaults. No solution remapping (``weak_direction_ratio = 0``): the initial guess of a
    one-off registration is the identity or a feature guess, not a motion prediction worth keeping.
    """
    return ICPConfig(iterations=(10, 20, 20, 80), robust_scale_m=0.05, coarse_min_relative_residual_change=1e-4,
                     min_relative_residual_change=1e-3, min_update_norm=1e-4, weak_direction_ratio=0.0)


@dataclass
class ReprojectionTerm:
    """Sparse point-to-pixel terms added to every ICP iteration (joint dense + feature tracking).

    Attributes:
        points_target: ``(M, 3)`` float64 points in the target camera frame (m), e.g. a keyframe's PnP inliers.
        uv_source: ``(M, 2)`` float64 their observed pixels in the source image, camera ``intrinsics``.
        intrinsics: the camera of ``uv_source`` (any resolution: only the projection is used).
        sigma_px: pixel noise; residuals are measured in units of it.
        huber: Huber threshold on the residual norm, in units of ``sigma_px``.
        weight: cost of one unit residual in the units of the point-to-plane cost (m^2): ``w sigma_ref^2``
            makes a feature residual of ``sigma_px`` weigh as much as one point-to-plane pair at ``sigma_ref``.
    """

    points_target: np.ndarray
    uv_source: np.ndarray
    intrinsics: Intrinsics
    sigma_px: float
    huber: float
    weight: float

    def add_to(self, stats: np.ndarray, T: np.ndarray) -> None:
        """Add the terms at the estimate ``T`` (``T_target_source``) to the accumulated vector ``stats``."""
        k = self.intrinsics
        kicp.accumulate_reprojection(self.points_target, self.uv_source, T, k.fx, k.fy, k.cx, k.cy,
                                     self.sigma_px, self.huber, self.weight, stats)


class ICPStatus(StrEnum):
    """How a registration ended. ``converged`` and ``max_iterations`` give a usable pose; the others do not."""

    CONVERGED = "converged"
    MAX_ITERATIONS = "max_iterations"  # still refined at the finest level when its iterations ran out: usable
    TOO_FEW_INLIERS = "too_few_inliers"
    SOLVER = "solver"  # the linear system could not be solved
    DEGENERATE = "degenerate"  # ill-conditioned finest-level system (one plane, two planes, a corridor)
    IMPLAUSIBLE_MOTION = "implausible_motion"


@dataclass
class LevelInfo:
    """What happened at one pyramid level (statistics of its last linearisation)."""

    level: int
    iterations: int
    inliers: int
    inlier_fraction: float
    rmse_m: float
    update_norm: float
    stop: str  # "update" | "residual" | "max_iterations" | "too_few_inliers" | "solver"
    frozen_directions: int = 0  # weak directions left at the initial guess in the level's last iteration
    # robust RMS of the point-to-plane residuals alone (m; in the level's depth-normalised units, Huber-weighted),
    # before any feature or photometric term: the depth data's own noise at the last linearisation
    geometric_noise_m: float = 0.0
    # inliers / the source points that land on a valid target pixel (1 when none does): the inliers' share of the
    # overlap with the target, blind to the part of the view the target does not hold
    overlap_inlier_fraction: float = 1.0


@dataclass
class ICPResult:
    """Result of :func:`icp`.

    Attributes:
        T_target_source: ``(4, 4)`` estimate (maps source-camera points into the target camera frame).
        inliers, inlier_fraction, rmse_m: finest level, at the last linearisation (``rmse_m`` is the
            unweighted RMS point-to-plane residual of the inliers).
        iterations: total Gauss-Newton iterations over all levels.
        converged: the finest level stopped on a small update / residual change, with enough inliers,
            a well-conditioned system and a plausible motion.
        degenerate: the finest-level system is ill-conditioned (e.g. a single plane).
        condition_number: eigenvalue ratio of the scaled finest-level normal matrix.
        levels: per-level details, coarsest first.
        reason: why ``converged`` is False (``None`` when converged).
        status: the same as a :class:`ICPStatus` (the first rule that fired, in the order of ``reason``).
        motion_m, motion_deg: size of the correction ``T T_init^-1`` (m, deg).
        normal_matrix: ``(6, 6)`` the finest level's Gauss-Newton matrix ``A^T W A`` at the last linearisation, for a
            left perturbation ``(omega, v)`` of ``T_target_source`` (how well each direction is constrained).
        mean_depth_m: mean depth of the finest level's inliers (scales rotations against translations).
    """

    T_target_source: np.ndarray
    inliers: int
    inlier_fraction: float
    rmse_m: float
    iterations: int
    converged: bool
    degenerate: bool
    condition_number: float
    levels: list[LevelInfo] = field(default_factory=list)
    reason: str | None = None
    status: ICPStatus = ICPStatus.CONVERGED
    motion_m: float = 0.0
    motion_deg: float = 0.0
    normal_matrix: np.ndarray | None = None
    mean_depth_m: float = 0.0


def solve(AtA: np.ndarray, Atb: np.ndarray, method: str = "cholesky",
          A: np.ndarray | None = None, b: np.ndarray | None = None) -> np.ndarray:
    """Gauss-Newton step ``xi (6,)`` minimising ``|A xi + b|^2``, i.e. ``AtA xi = -Atb``.

    Methods: ``cholesky`` (scipy ``cho_factor``/``cho_solve``), ``lu`` (``lu_factor``/``lu_solve``),
    ``pinv`` (pseudo-inverse of ``AtA``) and ``qr``: with the explicit ``A (N, 6)`` and ``b (N,)``
    (already weighted by ``sqrt(w)`` if a robust kernel is used) it solves ``R xi = -Q^T b`` from
    ``A = QR`` (never squares the condition number); without them it uses the QR factorisation of the
    6x6 normal matrix itself (the kernel path, which only has ``AtA``).

    Raises:
        numpy.linalg.LinAlgError / scipy.linalg.LinAlgError when the system is singular
        (not for ``pinv``).
    """
    if method == "cholesky":
        return scipy.linalg.cho_solve(scipy.linalg.cho_factor(AtA, check_finite=False), -Atb,
                                      check_finite=False)
    if method == "lu":
        return scipy.linalg.lu_solve(scipy.linalg.lu_factor(AtA, check_finite=False), -Atb,
                                     check_finite=False)
    if method == "qr":
        if A is not None and b is not None:
            Q, R = np.linalg.qr(A)
            return scipy.linalg.solve_triangular(R, -(Q.T @ b))
        Q, R = np.linalg.qr(AtA)
        return scipy.linalg.solve_triangular(R, -(Q.T @ Atb))
    if method == "pinv":
        return -(np.linalg.pinv(AtA) @ Atb)
    raise ConfigError(f"icp: unknown solver {method!r}; choose one of {SOLVERS}")


def depth_scaling(mean_depth_m: float) -> np.ndarray:
    """``(6,)`` scales ``(1/d, 1/d, 1/d, 1, 1, 1)`` of a twist ``(omega, v)``, ``d`` = mean depth (m): a rotation then
    compares with the translation that moves points as far."""
    d = max(mean_depth_m, 1e-6)
    return np.array([1 / d, 1 / d, 1 / d, 1.0, 1.0, 1.0])


def depth_scaled(AtA: np.ndarray, mean_depth_m: float) -> tuple[np.ndarray, np.ndarray]:
    """``(S AtA S (6, 6), s (6,))`` with ``S = diag(s)`` the :func:`depth_scaling`: the normal matrix ``(6, 6)`` of
    twists ``(omega, v)`` in which the condition number, the weak directions and the edges' information shape are
    judged."""
    s = depth_scaling(mean_depth_m)
    return AtA * s[:, None] * s[None, :], s


def weak_projector(AtA: np.ndarray, mean_depth_m: float, max_ratio: float) -> np.ndarray | None:
    """``(6, 6)`` projector onto the weak directions of ``AtA`` (twists ``(omega, v)``; eigenvalues of ``S AtA S`` below
    the largest over ``max_ratio``, the ones the solution remapping freezes), orthogonal in the depth-scaled metric;
    ``None`` when no direction is weak."""
    M, s = depth_scaled(AtA, mean_depth_m)
    lam, V = np.linalg.eigh(M)
    if not lam[-1] > 0 or max_ratio <= 0:
        return None
    Vw = V[:, lam * max_ratio < lam[-1]]
    if Vw.shape[1] == 0:
        return None
    return s[:, None] * (Vw @ Vw.T) / s[None, :]


def condition_number(AtA: np.ndarray, mean_depth_m: float) -> float:
    """Eigenvalue ratio of :func:`depth_scaled` ``AtA``: scaling the rotation columns by the mean depth makes
    rotational and translational constraints comparable (a rotation ``omega`` moves points at depth d by about
    ``d |omega|``)."""
    ev = np.linalg.eigvalsh(depth_scaled(AtA, mean_depth_m)[0])
    if ev[-1] <= 0:
        return float("inf")
    return float(ev[-1] / ev[0]) if ev[0] > 0 else float("inf")


def icp(source: FramePyramid, target: FramePyramid, T_init: np.ndarray | None = None,
        cfg: ICPConfig | None = None, reprojection: ReprojectionTerm | None = None,
        photometric: PhotometricTerm | None = None) -> ICPResult:
    """Estimate ``T_target_source`` by coarse-to-fine projective point-to-plane ICP.

    Args:
        source: pyramid of the frame being registered (source camera frame).
        target: pyramid in the target camera frame (a frame, or a model rendered at the target pose).
        T_init: ``(4, 4)`` initial ``T_target_source`` (identity when ``None``).
        cfg: settings (defaults: :class:`ICPConfig`).
        reprojection: optional sparse terms minimised jointly with the point-to-plane cost at every level
            (they also enter the convergence test, the weak-direction analysis and the condition number: a
            textured wall constrained by features is not degenerate for the joint system).
        photometric: optional dense intensity term (:func:`photometric_term`), minimised jointly at every level,
            with the same roles in the convergence test, the weak directions and the condition number.

    Returns:
        :class:`ICPResult`; on failure ``converged`` is False, ``reason`` says why and
        ``T_target_source`` holds the last estimate (the caller decides whether to use it).
    """
    cfg = cfg or ICPConfig()
    n_levels = min(cfg.levels, len(source), len(target))
    if n_levels < cfg.levels:
        raise ConfigError(f"icp: config asks for {cfg.levels} levels but the pyramids have "
                          f"{len(source)} (source) and {len(target)} (target)")
    T0 = np.eye(4) if T_init is None else np.array(T_init, dtype=np.float64)
    if T0.shape != (4, 4):
        raise ConfigError(f"icp: T_init must be 4x4, got {T0.shape}")
    T = T0.copy()
    stats = np.zeros(kicp.N_STATS)
    infos: list[LevelInfo] = []
    for lvl in range(n_levels - 1, -1, -1):
        T, info = _register_level(source[lvl], target[lvl], lvl, T, cfg, stats, reprojection, photometric)
        infos.append(info)
    return _verdict(T, T0, stats, infos, cfg)


def _register_level(src, tgt, lvl: int, T: np.ndarray, cfg: ICPConfig, stats: np.ndarray,
                    reprojection: ReprojectionTerm | None,
                    photometric: PhotometricTerm | None) -> tuple[np.ndarray, LevelInfo]:
    """Gauss-Newton iterations at pyramid level ``lvl`` from ``T``; ``stats`` holds the last linearisation."""
    ti = tgt.intrinsics
    T_next = np.empty((4, 4))
    robust = kicp.ROBUST_KINDS[cfg.robust_kernel]
    cos_thr = float(np.cos(np.radians(cfg.angle_thresh_deg[lvl])))
    # inlier count needed to take a step (coarse levels have 4x fewer pixels per level)
    stride = cfg.finest_source_stride_px if lvl == 0 else 1
    need = max(cfg.min_inliers / 4.0**lvl / stride**2, _MIN_INLIERS_PER_STEP)
    scale = cfg.finest_robust_scale_m if lvl == 0 else cfg.robust_scale_m
    depth_ref = cfg.depth_weight_ref_m if lvl == 0 else 0.0
    rel_change = cfg.min_relative_residual_change if lvl == 0 else cfg.coarse_min_relative_residual_change
    prev_mse = np.inf
    stop = "max_iterations"
    upd = np.inf
    its = 0
    frozen = 0
    geo_sse = geo_n = 0.0
    for _ in range(cfg.iterations[lvl]):
        kicp.accumulate_normal_equations(src.vertex, src.normal, tgt.vertex, tgt.normal, T,
                                         ti.fx, ti.fy, ti.cx, ti.cy, cfg.dist_thresh_m[lvl], cos_thr,
                                         robust, scale, stats, stride, depth_ref)
        geo_sse, geo_n = stats[27], stats[29]
        if reprojection is not None:
            reprojection.add_to(stats, T)
        if photometric is not None:
            photometric.add_to(stats, T, lvl, src.vertex, tgt.vertex, ti.fx, ti.fy, ti.cx, ti.cy,
                               cfg.dist_thresh_m[lvl], scale, stride)
        n_in = stats[29]
        if n_in < need:
            stop = "too_few_inliers"
            break
        frozen = 0
        if cfg.weak_direction_ratio > 0:
            frozen, upd = kicp.remapped_gauss_newton_step(stats, stats[30] / n_in, cfg.weak_direction_ratio,
                                                          T, T_next)
        if frozen:
            T, T_next = T_next, T
        elif cfg.solver == "cholesky":
            upd = kicp.gauss_newton_step(stats, T, T_next)
            if not upd >= 0.0:
                stop = "solver"
                break
            T, T_next = T_next, T
        else:
            T_solved = _solve_step(stats, T, cfg.solver)
            if T_solved is None:
                stop = "solver"
                break
            T, upd = T_solved
        its += 1
        mse = stats[27] / n_in
        if upd < cfg.min_update_norm:
            stop = "update"
            break
        if abs(prev_mse - mse) <= rel_change * mse:
            stop = "residual"
            break
        prev_mse = mse
    n_in = int(stats[29])
    return T, LevelInfo(lvl, its, n_in, n_in / max(stats[31], 1.0),
                        float(np.sqrt(stats[28] / max(stats[29], 1.0))), upd, stop, frozen,
                        float(np.sqrt(geo_sse / max(geo_n, 1.0))), n_in / max(stats[32], 1.0))


def _solve_step(stats: np.ndarray, T: np.ndarray, method: str) -> tuple[np.ndarray, float] | None:
    """One Gauss-Newton step by a scipy/numpy solver: ``(exp(xi) T, |xi|)``, or ``None`` when it fails."""
    AtA, Atb = kicp.unpack_normal_equations(stats)
    try:
        xi = solve(AtA, Atb, method)
    except (np.linalg.LinAlgError, scipy.linalg.LinAlgError):
        return None
    if not np.all(np.isfinite(xi)):
        return None
    return se3.exp(xi) @ T, float(np.linalg.norm(xi))


def _verdict(T: np.ndarray, T0: np.ndarray, stats: np.ndarray, infos: list[LevelInfo], cfg: ICPConfig) -> ICPResult:
    """The result of a registration ending at ``T`` from ``T0``: conditioning, plausibility and status."""
    fine = infos[-1]
    fine_stop = fine.stop
    mean_depth = stats[30] / max(stats[29], 1.0)
    AtA, _ = kicp.unpack_normal_equations(stats)
    cond = condition_number(AtA, mean_depth) if fine.inliers > 0 else float("inf")
    degenerate = cond > cfg.max_condition_number
    dT = T @ se3.invert(T0)
    dt_m = float(np.linalg.norm(dT[:3, 3]))
    dr_deg = se3.rotation_angle_deg(dT[:3, :3])
    reason, status = None, ICPStatus.CONVERGED
    if fine_stop == "too_few_inliers" or fine.inlier_fraction < cfg.min_inlier_fraction:
        reason = (f"too few inliers at the finest level ({fine.inliers}, "
                  f"{100 * fine.inlier_fraction:.1f}% of valid source points)")
        status = ICPStatus.TOO_FEW_INLIERS
    elif fine_stop == "solver":
        reason, status = "the linear system could not be solved (singular)", ICPStatus.SOLVER
    elif degenerate:
        reason = f"degenerate geometry (condition number {cond:.3g} > {cfg.max_condition_number:.3g})"
        status = ICPStatus.DEGENERATE
    elif dt_m > cfg.max_translation_m or dr_deg > cfg.max_rotation_deg:
        reason = (f"implausible motion ({dt_m:.3f} m, {dr_deg:.1f} deg; limits {cfg.max_translation_m} m, "
                  f"{cfg.max_rotation_deg} deg)")
        status = ICPStatus.IMPLAUSIBLE_MOTION
    elif fine_stop == "max_iterations":
        reason = f"not converged after {fine.iterations} iterations at the finest level"
        status = ICPStatus.MAX_ITERATIONS
    return ICPResult(
        T_target_source=T,
        inliers=fine.inliers,
        inlier_fraction=fine.inlier_fraction,
        rmse_m=fine.rmse_m,
        iterations=sum(i.iterations for i in infos),
        converged=reason is None,
        degenerate=bool(degenerate),
        condition_number=cond,
        levels=infos,
        reason=reason,
        status=status,
        motion_m=dt_m,
        motion_deg=dr_deg,
        normal_matrix=AtA,
        mean_depth_m=float(mean_depth),
    )


def icp_failure(res: ICPResult) -> str | None:
    """Category of a tracking failure (an :class:`ICPStatus` value), or ``None`` when the result can be used.

    Running out of iterations at the finest level is *not* a failure (the estimate is still refined);
    too few inliers (count or fraction of the valid source points), an unsolvable or degenerate system, and
    implausible motion are. An ill-conditioned system counts as degenerate even when another rule fired first.
    """
    if res.converged or res.status is ICPStatus.MAX_ITERATIONS:
        return None
    if res.degenerate:
        return ICPStatus.DEGENERATE.value
    stop = res.levels[-1].stop if res.levels else ICPStatus.SOLVER.value
    if stop in (ICPStatus.TOO_FEW_INLIERS, ICPStatus.SOLVER):
        return stop
    return res.status.value


def photometric_term(source: IntensityPyramid, target: IntensityPyramid, cfg: ICPConfig) -> PhotometricTerm:
    """The joint photometric term of one registration with ``cfg``'s settings (a fresh brightness offset)."""
    return PhotometricTerm(source, target, cfg.photometric_sigma, cfg.photometric_huber, cfg.photometric_weight,
                           cfg.photometric_brightness_offset)


def register_frames(src_depth_m: np.ndarray, tgt_depth_m: np.ndarray, intr: Intrinsics,
                    T_init: np.ndarray | None = None, icp_cfg: ICPConfig | None = None,
                    pre_cfg: PreprocessConfig | None = None) -> ICPResult:
    """Frame-to-frame registration of two depth images ``(H, W)`` float32 metres with the same camera.

    The pyramid depth is ``max(icp_cfg.levels, pre_cfg.pyramid_levels)``.
    """
    icp_cfg = icp_cfg or ICPConfig()
    pre_cfg = pre_cfg or PreprocessConfig()
    if pre_cfg.pyramid_levels < icp_cfg.levels:
        from dataclasses import replace

        pre_cfg = replace(pre_cfg, pyramid_levels=icp_cfg.levels)
    pre = Preprocessor(intr, pre_cfg)
    src = pre.process(src_depth_m)
    tgt = pre.process(tgt_depth_m)
    return icp(src, tgt, T_init, icp_cfg)
