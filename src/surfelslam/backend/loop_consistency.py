"""Chi-square gate of keyframe edges against the odometry chain (false-loop-closure guard).

A verified loop edge ``T_i_j`` may still be wrong (repetitive or plain texture, a far keyframe that only looks
alike); a robust kernel only limits its pull, and many wrong edges together still bend the map. Before an edge
enters the graph it is compared with the relative pose that the odometry alone chains between its keyframes, whose
uncertainty grows along the path: each odometry step adds a random-walk drift (variance proportional to the step's
translation and rotation), propagated to keyframe ``j`` through the chain's adjoints. The edge is rejected when its
squared Mahalanobis distance (residual covariance: chain plus edge) exceeds a chi-square quantile (6 dof).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from surfelslam.config import Config, setting
from surfelslam.geometry.se3 import adjoint, invert, log, rotation_angle_deg
from surfelslam.geometry.stats import chi2_quantile_6dof
from surfelslam.types import GrowingRows, PoseArray


@dataclass(frozen=True)
class LoopConsistencyConfig(Config):
    """Chi-square gate of keyframe edges against the odometry chain (:mod:`surfelslam.backend.loop_consistency`)."""

    enabled: bool = setting(True, doc="reject loop edges that disagree with the odometry chain between their "
                                      "keyframes", user=True)
    gate_nearby: bool = setting(False, doc="gate the nearby edges too (off: a nearby edge that disagrees with a few "
                                           "odometry steps more likely corrects a bad step than is wrong)")
    quantile: float = setting(0.99, unit="probability", gt=0, lt=1,
                              doc="an edge is rejected when its squared Mahalanobis distance exceeds this chi-square "
                                  "(6 dof) quantile")
    drift_m_per_sqrt_m: float = setting(
        0.02, unit="m/sqrt(m)", ge=0, le=100,
        doc="odometry translation drift: per-axis sigma after 1 m of path (random walk: grows with the square root)")
    drift_rad_per_sqrt_m: float = setting(0.02, unit="rad/sqrt(m)", ge=0, le=100,
                                          doc="odometry rotation drift per square root of metres travelled")
    drift_rad_per_sqrt_rad: float = setting(0.02, unit="rad/sqrt(rad)", ge=0, le=100,
                                            doc="odometry rotation drift per square root of radians turned")
    graph_gate: bool = setting(True, doc="also gate far loop edges against the graph of the edges accepted so far "
                                         "(:mod:`surfelslam.backend.edge_graph_gate`): once loops are closed on the "
                                         "way it is much tighter than the odometry chain; an edge must pass both")
    edge_sigma_m: float = setting(0.01, unit="m", gt=0, le=100,
                                  doc="floor of the edge's own translation sigma (added to its estimated covariance)")
    edge_sigma_rad: float = setting(0.01, unit="rad", gt=0, le=100, doc="the same on the rotation")


class OdometryChain:
    """Keyframe poses chained from odometry alone (a tree: each keyframe hangs from the one it was tracked against)
    and the chi-square test of an edge against it.

    Args:
        cfg: the drift model and the gate.
    """

    def __init__(self, cfg: LoopConsistencyConfig) -> None:
        self.cfg = cfg
        self.threshold = chi2_quantile_6dof(cfg.quantile)
        self._poses = PoseArray()  # T_world_kf from odometry alone
        self._parent: list[int] = []  # -1: a root (the first keyframe, or one placed without odometry)
        # per keyframe: the first of the run of keyframes that each hang from the one before, ending at it (a path
        # inside one run is a range of ids, found without walking the tree)
        self._run_start: list[int] = []
        # per keyframe: (6,) drift variance of the step from the parent, (omega, v), and its sum
        self._step_var = GrowingRows((6,))
        self._step_trace = GrowingRows()
        # per keyframe: the running sum over keyframes 0..k of each step's drift covariance in the world frame,
        # Ad(T_world_c) diag(var_c) Ad(T_world_c)^T: a path inside one run sums it in O(1) (a difference of two rows)
        self._world_cov_sum = GrowingRows((6, 6))
        self._unknown: set[int] = set()  # keyframes whose step from the parent is unknown (a new segment)

    def __len__(self) -> int:
        return len(self._poses)

    @property
    def poses(self) -> np.ndarray:
        """``(K, 4, 4)`` T_world_kf of every keyframe from odometry alone (a view: valid until the next keyframe)."""
        return self._poses.poses

    def add(self, T_world_kf: np.ndarray, parent: int | None, T_parent_kf: np.ndarray | None) -> None:
        """Append a keyframe reached from ``parent`` by ``T_parent_kf`` (``None``: a root at ``T_world_kf``)."""
        c = self.cfg
        if parent is None or T_parent_kf is None:
            self._poses.append(np.asarray(T_world_kf, np.float64))
            self._parent.append(-1)
            self._run_start.append(len(self._parent) - 1)
            self._append_step(np.zeros(6))
            return
        T = np.asarray(T_parent_kf, np.float64)
        dist_m = float(np.linalg.norm(T[:3, 3]))
        angle_rad = float(np.radians(rotation_angle_deg(T[:3, :3])))
        var_rot = c.drift_rad_per_sqrt_m ** 2 * dist_m + c.drift_rad_per_sqrt_rad ** 2 * angle_rad
        var_t = c.drift_m_per_sqrt_m ** 2 * dist_m
        self._poses.append(self.poses[parent] @ T)
        self._parent.append(parent)
        k = len(self._parent) - 1
        self._run_start.append(self._run_start[parent] if parent == k - 1 else k)
        self._append_step(np.array([var_rot] * 3 + [var_t] * 3))

    def _append_step(self, var: np.ndarray) -> None:
        """Record the ``(6,)`` drift variance of the newest keyframe's step (its sum, and the running sum of the
        steps' world-frame covariances)."""
        self._step_var.append(var)
        self._step_trace.append(np.sum(var))
        A = adjoint(self.poses[-1])
        before = self._world_cov_sum.rows[-1] if len(self._world_cov_sum) else np.zeros((6, 6))
        self._world_cov_sum.append(before + (A * var) @ A.T)

    def parent(self, kf: int) -> int:
        """The keyframe that ``kf`` hangs from (-1: a root)."""
        return self._parent[kf]

    def step_covariance(self, kf: int) -> np.ndarray:
        """``(6, 6)`` drift covariance of the odometry step into ``kf`` (right perturbation, ``(omega, v)``)."""
        return np.diag(self._step_var.rows[kf])

    def path_variance(self, path: list[int]) -> float:
        """Total drift variance (sum of the covariance traces) of the odometry steps into the keyframes of ``path``
        (see :meth:`path`)."""
        # summed in path order, one addition at a time (np.cumsum, not np.sum's pairwise sum): the limit the graph gate
        # searches under stays what it was when each step's variance was summed in a Python loop
        return float(np.cumsum(self._step_trace.rows[np.asarray(path, np.intp)])[-1]) if path else 0.0

    def edge_covariance(self, information: np.ndarray | None) -> np.ndarray:
        """``(6, 6)`` covariance of an edge with ``information`` (``None``: the sigma floors alone)."""
        c = self.cfg
        cov = np.diag([c.edge_sigma_rad ** 2] * 3 + [c.edge_sigma_m ** 2] * 3)
        if information is not None:
            info = 0.5 * (np.asarray(information, np.float64) + np.asarray(information, np.float64).T)
            cov += np.linalg.pinv(info, hermitian=True)
        return cov

    def mark_unknown(self, kf: int) -> None:
        """The step into keyframe ``kf`` is unknown (it starts a segment after a loss): edges across it are not
        tested."""
        self._unknown.add(kf)

    def path(self, i: int, j: int) -> list[int] | None:
        """Keyframes whose odometry step lies on the chain between ``i`` and ``j`` (``None``: not connected, or across
        an unknown step), newest first."""
        lo, hi = min(i, j), max(i, j)
        if self._run_start[hi] <= lo:  # one run: the steps into lo + 1 .. hi
            out = list(range(hi, lo, -1))
        else:
            out = self._walk(i, j)
            if out is None:
                return None
        return None if not self._unknown.isdisjoint(out) else out

    def _walk(self, i: int, j: int) -> list[int] | None:
        """:meth:`path` by walking up the tree from both ends (unknown steps not checked)."""
        a, b, out = i, j, []
        while a != b:
            if a < 0 or b < 0:
                return None
            if a > b:  # a parent always precedes its child
                out.append(a)
                a = self._parent[a]
            else:
                out.append(b)
                b = self._parent[b]
        return out

    def relative(self, i: int, j: int) -> np.ndarray:
        """``T_i_j`` ``(4, 4)`` from the odometry alone."""
        return invert(self.poses[i]) @ self.poses[j]

    def covariance(self, i: int, j: int, path: list[int]) -> np.ndarray:
        """``(6, 6)`` covariance of the odometry's ``T_i_j`` (right perturbation, ``(omega, v)``) over ``path``."""
        if not path:
            return np.zeros((6, 6))
        if len(path) == path[0] - path[-1] + 1 and path[0] == max(i, j) and path[-1] == min(i, j) + 1:
            # the steps into keyframes lo + 1 .. hi: the difference of the running sums, moved into keyframe j's frame
            # (a far loop's path holds thousands of steps; the sum over them took milliseconds per edge)
            S = self._world_cov_sum.rows[path[0]] - self._world_cov_sum.rows[path[-1] - 1]
            A = adjoint(invert(self.poses[j]))
            return A @ S @ A.T
        rows = np.asarray(path, np.intp)
        T_j_c = invert(self.poses[j])[None] @ self.poses[rows]
        A = adjoint(T_j_c)
        var = self._step_var.rows[rows]
        return np.einsum("nab,nb,ncb->ac", A, var, A)

    def mahalanobis2(self, i: int, j: int, T_i_j: np.ndarray, information: np.ndarray | None) -> float | None:
        """Squared Mahalanobis distance of the edge ``T_i_j`` ``(4, 4)`` (with its ``(6, 6)`` information, or
        ``None``: the sigma floors alone) from the odometry chain; ``None`` when the chain cannot tell."""
        p = self.path(i, j)
        if p is None:
            return None
        cov = self.covariance(i, j, p) + self.edge_covariance(information)
        r = log(invert(np.asarray(T_i_j, np.float64)) @ self.relative(i, j))
        return float(r @ np.linalg.solve(cov, r))

    def consistent(self, d2: float | None) -> bool:
        """Whether a distance from :meth:`mahalanobis2` passes the gate (``None``: untested, passes)."""
        return d2 is None or d2 <= self.threshold
