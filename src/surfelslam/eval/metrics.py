"""Trajectory error metrics (ATE, RPE) computed with evo's library.

Everything here is pure maths on :class:`~surfelslam.types.Trajectory` objects: no file I/O, no printing.
Association (:func:`evo.core.sync.associate_trajectories`), Umeyama alignment
(:meth:`evo.core.trajectory.PosePath3D.align`) and the APE/RPE error definitions (:mod:`evo.core.metrics`)
are evo's own, so the numbers agree with ``evo_ape`` / ``evo_rpe`` run on the same files.

Protocol (TUM RGB-D benchmark):

* **ATE**: associate estimate and ground-truth poses by nearest timestamp (``|dt| <= max_diff_s``),
  align the estimate to the ground truth with a rigid SE(3) Umeyama fit (no scale by default), and take
  the translation error ``|t_gt_i - t_est_aligned_i|`` per associated pose (metres).
* **RPE**: relative-motion error ``E_ij = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j)`` over pose pairs ``(i, j)`` of the
  associated trajectories; translation part ``|trans(E_ij)|`` (metres) and rotation angle of ``rot(E_ij)``
  (degrees). No alignment is needed (RPE is invariant to a rigid transform of either trajectory). The pairs'
  errors are computed together in numpy (:func:`relative_pose_errors`), with evo's definitions: evo's own loop
  over the pairs took most of a run's evaluation; a test holds the two to 1e-9.

  - ``delta_unit="frames"``: evo's pairs ``(i, i + delta)`` (``Unit.frames``; consecutive non-overlapping
    pairs as in ``evo_rpe``'s default, identical to all pairs for ``delta=1``): "per frame" RPE.
  - ``delta_unit="seconds"``: evo has no time unit for RPE deltas, so the pairs are chosen here by time,
    as TUM's ``evaluate_rpe.py --fixed_delta --delta 1 --delta_unit s`` does: for every associated pose
    ``i``, ``j`` is the pose whose timestamp is closest to ``t_i + delta``; the pair is kept only if
    ``|t_j - t_i - delta| <= rel_delta_tol * delta`` (evo's ``rel_delta_tol`` convention, default 0.1),
    which drops pairs across tracking gaps and at the end of the sequence. The error of each pair is then
    evo's :meth:`evo.core.metrics.RPE.rpe_base` and :func:`evo.core.lie_algebra.so3_log_angle`.
    With ``delta = 1`` s this is the drift per second (m/s, deg/s). Unlike a frame delta derived from the
    median frame interval, this stays correct when frames are dropped or the frame rate varies.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from evo.core import filters as evo_filters
from evo.core import lie_algebra as lie
from evo.core import metrics as evo_metrics
from evo.core import sync as evo_sync
from evo.core.geometry import GeometryException
from evo.core.trajectory import PoseTrajectory3D
from scipy.spatial.transform import Rotation  # evo's own rotation type: imported with evo

from surfelslam.errors import EvaluationError, GroundTruthError
from surfelslam.eval.protocol import DEFAULT_MAX_DIFF_S
from surfelslam.types import Trajectory

MIN_ASSOCIATED_POSES = 3  # fewer pairs cannot constrain an SE(3) alignment
DEFAULT_REL_DELTA_TOL = 0.1  # evo's default relative tolerance for non-frame RPE deltas
#: Absolute tolerance of evo's ``is_so3`` (determinant 1, orthonormal) that each RPE error rotation must pass.
SO3_ATOL = 1e-6
#: Positions closer than this to their mean (m) count as one point when explaining a failed alignment.
STILL_SPREAD_M = 1e-9
#: A second principal spread below this fraction of the first counts as motion along one line.
LINE_SPREAD_RATIO = 1e-9

# evo logs a warning for every unsorted/odd input; keep library calls quiet (the CLI reports errors itself).
logging.getLogger("evo").setLevel(logging.ERROR)


# --------------------------------------------------------------------------------------------- results
@dataclass
class AteResult:
    """Absolute trajectory error after alignment.

    Attributes:
        rmse_m, mean_m, median_m, max_m, std_m: statistics of ``errors_m`` (std is the population std).
        n_pairs: number of associated poses N.
        errors_m: ``(N,)`` translation error per associated pose, metres.
        timestamps: ``(N,)`` estimate timestamps of the associated poses, seconds.
        est_aligned: the N associated estimate poses after alignment (``T_align @ T_world_cam``).
        gt: the N associated ground-truth poses.
        T_align: ``(4, 4)`` alignment applied to the estimate (identity if ``align=False``; a similarity,
            ``[sR t; 0 1]``, if ``correct_scale=True``).
        scale: scale factor of the alignment (1.0 without scale correction).
    """

    rmse_m: float
    mean_m: float
    median_m: float
    max_m: float
    std_m: float
    n_pairs: int
    errors_m: np.ndarray = field(repr=False)
    timestamps: np.ndarray = field(repr=False)
    est_aligned: Trajectory = field(repr=False)
    gt: Trajectory = field(repr=False)
    T_align: np.ndarray = field(repr=False)
    scale: float = 1.0


@dataclass
class RpeResult:
    """Relative pose error over pose pairs ``(i, j)``.

    Attributes:
        trans_rmse_m, trans_mean_m, trans_median_m, trans_max_m: statistics of ``trans_errors_m``.
        rot_rmse_deg, rot_mean_deg, rot_median_deg, rot_max_deg: statistics of ``rot_errors_deg``.
        n_pairs: number of pose pairs M.
        delta, delta_unit: the pair spacing (``"frames"`` or ``"seconds"``).
        pairs: ``(M, 2)`` int indices into the associated trajectories.
        timestamps: ``(M,)`` estimate timestamp of the second pose of each pair, seconds.
        trans_errors_m: ``(M,)`` translation error of the relative motion, metres.
        rot_errors_deg: ``(M,)`` rotation angle of the relative-motion error, degrees.
    """

    trans_rmse_m: float
    rot_rmse_deg: float
    trans_mean_m: float
    rot_mean_deg: float
    trans_median_m: float
    rot_median_deg: float
    trans_max_m: float
    rot_max_deg: float
    n_pairs: int
    delta: float
    delta_unit: str
    pairs: np.ndarray = field(repr=False)
    timestamps: np.ndarray = field(repr=False)
    trans_errors_m: np.ndarray = field(repr=False)
    rot_errors_deg: np.ndarray = field(repr=False)


# ------------------------------------------------------------------------------------------ conversion
def to_evo(traj: Trajectory, name: str | None = None) -> PoseTrajectory3D:
    """Our :class:`Trajectory` -> evo ``PoseTrajectory3D`` (copies the poses)."""
    return PoseTrajectory3D(
        poses_se3=[T.copy() for T in traj.T_world_cam], timestamps=traj.timestamps.copy(), name=name
    )


def from_evo(traj: PoseTrajectory3D) -> Trajectory:
    """evo ``PoseTrajectory3D`` -> our :class:`Trajectory`."""
    return Trajectory(np.asarray(traj.timestamps, dtype=np.float64), np.asarray(traj.poses_se3))


def _time_range(traj: Trajectory) -> str:
    if len(traj) == 0:
        return "empty"
    return f"{traj.timestamps[0]:.3f}..{traj.timestamps[-1]:.3f} s"


def _association_error(est: Trajectory, gt: Trajectory, max_diff_s: float, n_found: int) -> GroundTruthError:
    return GroundTruthError(
        None,
        f"only {n_found} estimate/ground-truth pose pairs within max_diff {max_diff_s} s "
        f"(need >= {MIN_ASSOCIATED_POSES}): estimate has {len(est)} poses over {_time_range(est)}, "
        f"ground truth has {len(gt)} poses over {_time_range(gt)}",
    )


def _associate_evo(
    est: Trajectory, gt: Trajectory, max_diff_s: float
) -> tuple[PoseTrajectory3D, PoseTrajectory3D]:
    """Associate with evo exactly as ``evo_ape``/``evo_rpe`` do (reference first); returns (est, gt)."""
    if not (np.isfinite(max_diff_s) and max_diff_s >= 0):
        raise EvaluationError(f"max_diff must be a finite number of seconds >= 0, got {max_diff_s}")
    if len(est) == 0 or len(gt) == 0:
        raise _association_error(est, gt, max_diff_s, 0)
    try:
        gt_sync, est_sync = evo_sync.associate_trajectories(
            to_evo(gt, "ground truth"), to_evo(est, "estimate"), max_diff=max_diff_s
        )
    except evo_sync.SyncException:
        raise _association_error(est, gt, max_diff_s, 0) from None
    if est_sync.num_poses < MIN_ASSOCIATED_POSES:
        raise _association_error(est, gt, max_diff_s, est_sync.num_poses)
    return est_sync, gt_sync


# ------------------------------------------------------------------------------------------------- API
def associate(
    est: Trajectory, gt: Trajectory, max_diff_s: float = DEFAULT_MAX_DIFF_S
) -> tuple[Trajectory, Trajectory]:
    """Pair estimate and ground-truth poses by nearest timestamp (evo's ``associate_trajectories``).

    Returns ``(est_sync, gt_sync)`` with equal length N >= 3; ``est_sync.timestamps[k]`` and
    ``gt_sync.timestamps[k]`` differ by at most ``max_diff_s`` seconds.

    Raises:
        GroundTruthError: fewer than 3 poses could be associated.
    """
    est_sync, gt_sync = _associate_evo(est, gt, max_diff_s)
    return from_evo(est_sync), from_evo(gt_sync)


class AlignmentError(EvaluationError, GeometryException):
    """The SE(3) alignment is impossible (degenerate positions). Also evo's GeometryException, which callers that
    fall back to another alignment catch."""


def _motion_words(positions: np.ndarray) -> str | None:
    """``"does not move"`` / ``"moves along one line"`` for positions that cannot anchor a rigid alignment."""
    centred = positions - positions.mean(axis=0)
    s = np.linalg.svd(centred, compute_uv=False) if len(centred) else np.zeros(3)
    if not np.all(np.isfinite(s)) or s[0] <= STILL_SPREAD_M:
        return "does not move"
    if s[1] <= LINE_SPREAD_RATIO * s[0]:
        return "moves along one straight line"
    return None


def _alignment_error(est_sync: PoseTrajectory3D, gt_sync: PoseTrajectory3D, exc: Exception) -> AlignmentError:
    """Why the Umeyama alignment failed, in words (evo says 'Degenerate covariance rank')."""
    why = [f"the {name} {words}" for name, traj in (("estimate", est_sync), ("ground truth", gt_sync))
           if (words := _motion_words(np.asarray(traj.positions_xyz, np.float64))) is not None]
    detail = " and ".join(why) if why else f"{type(exc).__name__}: {exc}"
    return AlignmentError(
        f"cannot align the estimate to the ground truth over the {est_sync.num_poses} associated poses: "
        f"{detail}; the SE(3) alignment of the ATE needs positions spread in at least two directions")


def _stats(errors: np.ndarray) -> dict[str, float]:
    """rmse / mean / median / max / std exactly as evo's ``PE.get_statistic`` defines them."""
    m = evo_metrics.APE()
    m.error = np.asarray(errors, dtype=np.float64)
    S = evo_metrics.StatisticsType
    return {s.value: float(m.get_statistic(s)) for s in (S.rmse, S.mean, S.median, S.max, S.std)}


def ate(
    est: Trajectory,
    gt: Trajectory,
    max_diff_s: float = DEFAULT_MAX_DIFF_S,
    align: bool = True,
    correct_scale: bool = False,
) -> AteResult:
    """Absolute trajectory error (TUM protocol: associate, SE(3)-align the estimate, translation error).

    Equal to ``evo_ape tum GT EST -a --t_max_diff max_diff_s`` (add ``-s`` for ``correct_scale``).

    Raises:
        GroundTruthError: fewer than 3 poses could be associated.
        AlignmentError: an EvaluationError and evo GeometryException: the positions cannot anchor the alignment
            (no motion, motion along one line).
    """
    est_sync, gt_sync = _associate_evo(est, gt, max_diff_s)
    return _ate_associated(est_sync, gt_sync, align, correct_scale)


def _ate_associated(est_sync: PoseTrajectory3D, gt_sync: PoseTrajectory3D, align: bool = True,
                    correct_scale: bool = False) -> AteResult:
    """:func:`ate` of already associated trajectories (``est_sync`` is aligned in place: a copy of the caller's)."""
    T_align = np.eye(4)
    scale = 1.0
    if align or correct_scale:
        try:
            r_a, t_a, s = est_sync.align(gt_sync, correct_scale=correct_scale, correct_only_scale=not align)
        except (GeometryException, np.linalg.LinAlgError, ValueError, FloatingPointError) as exc:
            raise _alignment_error(est_sync, gt_sync, exc) from None
        scale = float(s)
        T_align = lie.sim3(r_a, t_a, s) if align else lie.sim3(np.eye(3), np.zeros(3), s)
    ape = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
    ape.process_data((gt_sync, est_sync))
    st = _stats(ape.error)
    return AteResult(
        rmse_m=st["rmse"],
        mean_m=st["mean"],
        median_m=st["median"],
        max_m=st["max"],
        std_m=st["std"],
        n_pairs=int(est_sync.num_poses),
        errors_m=np.asarray(ape.error, dtype=np.float64),
        timestamps=np.asarray(est_sync.timestamps, dtype=np.float64),
        est_aligned=from_evo(est_sync),
        gt=from_evo(gt_sync),
        T_align=np.asarray(T_align, dtype=np.float64),
        scale=scale,
    )


def time_delta_pairs(
    timestamps: np.ndarray, delta_s: float, rel_delta_tol: float = DEFAULT_REL_DELTA_TOL
) -> np.ndarray:
    """Pose pairs ``(i, j)`` about ``delta_s`` seconds apart.

    For every ``i``, ``j`` is the index whose timestamp is closest to ``t_i + delta_s``; the pair is kept
    if ``|t_j - t_i - delta_s| <= rel_delta_tol * delta_s`` and ``j > i``.

    Args:
        timestamps: ``(N,)`` ascending seconds.
    Returns:
        ``(M, 2)`` int64 index pairs.
    """
    t = np.asarray(timestamps, dtype=np.float64)
    if delta_s <= 0:
        raise EvaluationError(f"delta must be > 0 seconds, got {delta_s}")
    target = t + delta_s
    hi = np.clip(np.searchsorted(t, target), 1, len(t) - 1)
    lo = hi - 1
    j = np.where(np.abs(t[hi] - target) < np.abs(t[lo] - target), hi, lo)
    i = np.arange(len(t))
    keep = (np.abs(t[j] - target) <= rel_delta_tol * delta_s) & (j > i)
    return np.column_stack([i[keep], j[keep]]).astype(np.int64)


def _check_so3(R: np.ndarray) -> None:
    """Raise EvaluationError unless every ``(M, 3, 3)`` ``R`` is a rotation by evo's ``is_so3`` test (determinant 1
    and ``R^T R = I``, :func:`numpy.allclose` with ``atol`` 1e-6), which evo's per-pair RPE applies to each."""
    det_ok = np.isclose(np.linalg.det(R), 1.0, atol=SO3_ATOL)
    ortho_ok = np.isclose(np.swapaxes(R, 1, 2) @ R, np.eye(3), atol=SO3_ATOL).all(axis=(1, 2))
    bad = np.flatnonzero(~(det_ok & ortho_ok))
    if len(bad):
        raise EvaluationError(f"relative pose error: the error rotation of pair {int(bad[0])} is not a rotation "
                              "matrix (non-finite or non-orthonormal poses)")


def relative_pose_errors(Q: np.ndarray, P: np.ndarray, pairs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Translation (m) and rotation angle (deg) of ``E_ij = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j)`` for every pair ``(i, j)``
    of ``pairs`` ``(M, 2)``; ``Q`` ground truth, ``P`` estimate, ``(N, 4, 4)`` each.

    evo's :meth:`evo.core.metrics.RPE.rpe_base` and its ``translation_part`` / ``rotation_angle_deg`` relations
    (the norm of scipy's rotation vector of ``rot(E_ij)``), on all pairs at once: evo's loop over the pairs was most
    of a run's evaluation. Equal to evo's to rounding (a test holds them to 1e-9)."""
    def relative(T: np.ndarray) -> np.ndarray:
        a, b = T[pairs[:, 0]], T[pairs[:, 1]]
        return _inverse_se3(a) @ b

    E = _inverse_se3(relative(Q)) @ relative(P)
    R = E[:, :3, :3]
    _check_so3(R)
    trans = np.linalg.norm(E[:, :3, 3], axis=1)
    rot = np.abs(np.rad2deg(np.linalg.norm(Rotation.from_matrix(R).as_rotvec(), axis=1)))
    return trans, rot


def _inverse_se3(T: np.ndarray) -> np.ndarray:
    """``(M, 4, 4)`` inverses of rigid transforms, as evo's ``se3_inverse`` computes each: ``[R^T, -R^T t]``."""
    out = np.zeros_like(T)
    Rt = np.swapaxes(T[:, :3, :3], 1, 2)
    out[:, :3, :3] = Rt
    out[:, :3, 3] = -np.einsum("mij,mj->mi", Rt, T[:, :3, 3])
    out[:, 3, 3] = 1.0
    return out


def rpe(
    est: Trajectory,
    gt: Trajectory,
    delta: float = 1,
    delta_unit: str = "frames",
    max_diff_s: float = DEFAULT_MAX_DIFF_S,
    rel_delta_tol: float = DEFAULT_REL_DELTA_TOL,
) -> RpeResult:
    """Relative pose error, translation (m) and rotation angle (deg), over pairs ``delta`` apart.

    ``delta_unit="frames"`` equals ``evo_rpe tum GT EST --t_max_diff max_diff_s --delta delta
    --delta_unit f`` (``-r trans_part`` / ``-r angle_deg``). ``delta_unit="seconds"`` pairs poses by time
    (see the module docstring); with ``delta=1`` the errors are drift per second.

    Raises:
        GroundTruthError: fewer than 3 poses could be associated.
        EvaluationError (a ValueError): bad delta / unit, or no pose pair ``delta`` apart.
    """
    est_sync, gt_sync = _associate_evo(est, gt, max_diff_s)
    return _rpe_associated(est_sync, gt_sync, delta, delta_unit, rel_delta_tol)


def frame_delta_pairs(n: int, delta: int) -> np.ndarray:
    """evo's consecutive pairs ``delta`` frames apart among ``n`` poses (``filter_pairs_by_index``): ``(0, delta),
    (delta, 2 delta), ...``; ``(M, 2)`` int64."""
    ids = np.arange(0, n, delta, dtype=np.int64)
    return np.column_stack([ids[:-1], ids[1:]])


def _rpe_associated(est_sync: PoseTrajectory3D, gt_sync: PoseTrajectory3D, delta: float, delta_unit: str,
                    rel_delta_tol: float) -> RpeResult:
    """:func:`rpe` of already associated trajectories."""
    stamps = np.asarray(est_sync.timestamps, dtype=np.float64)
    if delta_unit == "frames":
        if delta < 1 or int(delta) != delta:
            raise EvaluationError(f"frame delta must be a positive integer, got {delta}")
        pairs = frame_delta_pairs(len(stamps), int(delta))
        if len(pairs) == 0:
            raise EvaluationError(f"relative pose error: delta = {delta} (frames) produced an empty index list - "
                                  "try lower values or a less strict tolerance")
    elif delta_unit == "seconds":
        pairs = time_delta_pairs(stamps, float(delta), rel_delta_tol)
        if len(pairs) == 0:
            raise EvaluationError(
                f"no pose pairs {delta} s apart (+/- {rel_delta_tol * delta:.3f} s) among {len(stamps)} "
                f"associated poses spanning {stamps[-1] - stamps[0]:.3f} s"
            )
    else:
        raise EvaluationError(f"delta_unit must be 'frames' or 'seconds', got {delta_unit!r}")
    trans, rot = relative_pose_errors(np.asarray(gt_sync.poses_se3, np.float64),
                                      np.asarray(est_sync.poses_se3, np.float64), pairs)
    st_t = _stats(trans)
    st_r = _stats(rot)
    return RpeResult(
        trans_rmse_m=st_t["rmse"],
        rot_rmse_deg=st_r["rmse"],
        trans_mean_m=st_t["mean"],
        rot_mean_deg=st_r["mean"],
        trans_median_m=st_t["median"],
        rot_median_deg=st_r["median"],
        trans_max_m=st_t["max"],
        rot_max_deg=st_r["max"],
        n_pairs=len(pairs),
        delta=float(delta),
        delta_unit=delta_unit,
        pairs=pairs,
        timestamps=stamps[pairs[:, 1]],
        trans_errors_m=trans,
        rot_errors_deg=rot,
    )


def evaluate_all(
    est: Trajectory, gt: Trajectory, max_diff_s: float = DEFAULT_MAX_DIFF_S
) -> tuple[AteResult, RpeResult, RpeResult | None]:
    """ATE, RPE per frame (delta 1 frame) and RPE per second (delta 1 s; None if the run spans < 1 s).

    Raises:
        GroundTruthError: fewer than 3 poses could be associated.
        EvaluationError: degenerate trajectories (no motion, motion along a line) or a bad ``max_diff_s``; any
            other failure inside evo is reported as one too, never as a traceback.
    """
    try:  # overflow (coordinates like 1e154 in a file): a FloatingPointError below, not warnings and NaN metrics
        with np.errstate(over="raise", invalid="raise"):
            est_sync, gt_sync = _associate_evo(est, gt, max_diff_s)  # once: the RPEs see the unaligned copy
            rf = _rpe_associated(est_sync, gt_sync, 1, "frames", DEFAULT_REL_DELTA_TOL)
            try:
                rs: RpeResult | None = _rpe_associated(est_sync, gt_sync, 1.0, "seconds", DEFAULT_REL_DELTA_TOL)
            except EvaluationError:
                rs = None
            a = _ate_associated(est_sync, gt_sync)
    except (GroundTruthError, EvaluationError):
        raise
    except (GeometryException, evo_filters.FilterException, evo_sync.SyncException, np.linalg.LinAlgError,
            ValueError, IndexError, FloatingPointError) as exc:
        raise EvaluationError(f"cannot evaluate the trajectories ({type(exc).__name__}: {exc})") from None
    return a, rf, rs


def summary(
    a: AteResult, rf: RpeResult, rs: RpeResult | None, n_est: int, n_gt: int, max_diff_s: float
) -> dict:
    """The JSON-serialisable dict of :func:`evaluate` from already computed results."""
    return {
        "ate_rmse_m": a.rmse_m,
        "ate_mean_m": a.mean_m,
        "ate_median_m": a.median_m,
        "ate_max_m": a.max_m,
        "ate_std_m": a.std_m,
        "rpe_trans_rmse_m_per_frame": rf.trans_rmse_m,
        "rpe_rot_rmse_deg_per_frame": rf.rot_rmse_deg,
        "rpe_trans_rmse_m_per_s": None if rs is None else rs.trans_rmse_m,
        "rpe_rot_rmse_deg_per_s": None if rs is None else rs.rot_rmse_deg,
        "rpe_pairs_per_frame": rf.n_pairs,
        "rpe_pairs_per_s": 0 if rs is None else rs.n_pairs,
        "n_pairs": a.n_pairs,
        "n_est": int(n_est),
        "n_gt": int(n_gt),
        "max_diff_s": float(max_diff_s),
    }


def evaluate(est: Trajectory, gt: Trajectory, max_diff_s: float = DEFAULT_MAX_DIFF_S) -> dict:
    """ATE and RPE (per frame and per second) as a JSON-serialisable dict of plain floats/ints.

    Keys: ate_rmse_m, ate_mean_m, ate_median_m, ate_max_m, ate_std_m, rpe_trans_rmse_m_per_frame,
    rpe_rot_rmse_deg_per_frame, rpe_trans_rmse_m_per_s, rpe_rot_rmse_deg_per_s, rpe_pairs_per_frame,
    rpe_pairs_per_s, n_pairs, n_est, n_gt, max_diff_s. The per-second values are ``None`` when no pose
    pair is 1 s apart (the associated trajectory spans less than about one second).

    Raises:
        GroundTruthError: fewer than 3 poses could be associated. EvaluationError: see :func:`evaluate_all`.
    """
    a, rf, rs = evaluate_all(est, gt, max_diff_s)
    return summary(a, rf, rs, len(est), len(gt), max_diff_s)
