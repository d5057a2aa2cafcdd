"""The dense front end's motion state and its updates: velocity, failure streaks, plausible relocalisations.

:class:`TrackingState` is the public state of a surfel tracker's camera (current pose, last tracked pose, velocity,
counters); :class:`MotionModel` updates it after each frame. :func:`step_and_pose` is the one formula from an ICP
result to a pose that every surfel tracker uses.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from surfelslam.geometry import se3
from surfelslam.slam.config import TrackingConfig
from surfelslam.slam.frame import FrameStatus
from surfelslam.tracking.icp import ICPConfig, ICPResult, ICPStatus, weak_projector

#: ICP's own correction of a good prediction stays below this (m; at most 1.4 cm on the synthetic and TUM test rows)
CORRECTION_SLACK_M = 0.02
#: the same for the rotation (deg; TUM at 3x speed: up to 3.5 deg)
CORRECTION_SLACK_DEG = 2.0


def _identity() -> np.ndarray:
    return np.eye(4)


@dataclass
class TrackingState:
    """The camera's tracking state (poses ``(4, 4)`` camera to world; velocities ``T_prev_cur`` per frame).

    Attributes:
        T_world_cam: pose of the last processed frame (``None`` before the first posed frame).
        T_world_last_tracked: pose of the last tracked (fused) frame.
        t_last_tracked_s: time of the last tracked frame.
        velocity: the motion of the last good step (what the next prediction applies).
        v_tracked: the last fully tracked step (a weak frame's velocity fades from it); ``t_v_tracked_s`` its time.
        failures / failures_in_a_row / failure_reasons: frames not registered (all, the current streak, per reason).
        weak_frames: frames registered with weak directions held at the prediction.
        held_frames / held_in_a_row: frames posed at the prediction because their registration jumped implausibly
            (all, the current streak); ``t_last_posed_s``: time of the last registered or held frame.
        relocalisations: shape relocalisations ``tried``, ``tracked`` and ``refused_implausible``.
    """

    T_world_cam: np.ndarray | None = None
    T_world_last_tracked: np.ndarray | None = None
    t_last_tracked_s: float = 0.0
    velocity: np.ndarray = field(default_factory=_identity)
    v_tracked: np.ndarray = field(default_factory=_identity)
    t_v_tracked_s: float = 0.0
    failures: int = 0
    failures_in_a_row: int = 0
    failure_reasons: dict[str, int] = field(default_factory=dict)
    weak_frames: int = 0
    held_frames: int = 0
    held_in_a_row: int = 0
    t_last_posed_s: float = 0.0
    relocalisations: dict[str, int] = field(
        default_factory=lambda: {"tried": 0, "tracked": 0, "refused_implausible": 0})


def step_and_pose(T_ref: np.ndarray, res: ICPResult) -> tuple[np.ndarray, np.ndarray]:
    """``(step, T_world_cam)``: the ICP motion ``res.T_target_source`` re-projected onto SE(3) and the pose it
    gives from the render pose ``T_ref`` (both ``(4, 4)``). One formula for the dense and the hybrid
    trackers, so that their trajectories agree to the last bit where the hybrid adds nothing (real-data
    tracking amplifies rounding differences to about 0.5 % ATE)."""
    step = se3.orthonormalize(res.T_target_source)
    return step, se3.orthonormalize(T_ref @ step)


class MotionModel:
    """Updates a :class:`TrackingState` after each frame (``tracking`` and ``icp`` settings)."""

    def __init__(self, tracking: TrackingConfig, icp_cfg: ICPConfig, state: TrackingState):
        self.cfg = tracking
        self.icp_cfg = icp_cfg
        self.state = state

    def damp_frozen(self, step: np.ndarray, res: ICPResult | None) -> np.ndarray:
        """``step`` with its part along the directions the finest ICP level of ``res`` left at the prediction (solution
        remapping) moved only ``tracking.frozen_velocity_gain`` of the way from the current velocity: there the step
        is the prediction plus what the coarser levels did, not a measurement of the finest one."""
        g = self.cfg.frozen_velocity_gain
        fine = res.levels[-1] if res is not None and res.levels else None
        if g >= 1 or fine is None or fine.level != 0 or not fine.frozen_directions or res.normal_matrix is None:
            return step
        P = weak_projector(res.normal_matrix, res.mean_depth_m, self.icp_cfg.weak_direction_ratio)
        if P is None:
            return step
        delta = se3.log(self.state.velocity @ se3.invert(step))  # left difference, as ICP's: velocity = exp(delta) step
        return se3.orthonormalize(se3.exp((1 - g) * (P @ delta)) @ step)

    def velocity_after(self, step: np.ndarray, status: FrameStatus, t_s: float,
                       res: ICPResult | None = None, measured: bool = True) -> np.ndarray:
        """The velocity (``T_prev_cur`` per frame, ``(4, 4)``) after a registered frame at time ``t_s`` whose step
        was ``step`` (``res``: its ICP result against the map rendered at the previous pose, if it was;
        ``measured=False``: the step is no measurement of the camera's motion, see :meth:`jumped`).

        A tracked frame: its step, damped along frozen directions (:meth:`damp_frozen`). A relocalised frame, or one
        whose step is not measured (a recovery that corrected a stale prediction), has no known velocity
        (identity). A weak frame's step is known only along the directions the view constrains, so it is not used:
        the velocity of the last fully tracked frame goes on, fading by
        ``exp(-(t_s - t_tracked) / tracking.weak_velocity_decay_s)`` (a walk down a corridor keeps going; a weak step
        never feeds the next prediction, so ICP's slide along a free direction cannot build up speed).
        Updates the last fully tracked step; the caller sets ``state.velocity``."""
        s = self.state
        if status is FrameStatus.TRACKED and measured:
            step = self.damp_frozen(step, res)
            s.v_tracked, s.t_v_tracked_s = step, t_s
            return step
        tau_s = self.cfg.weak_velocity_decay_s
        if status is not FrameStatus.WEAK or tau_s <= 0 or not measured:
            s.v_tracked = np.eye(4)
            return np.eye(4)
        keep = float(np.exp(-max(t_s - s.t_v_tracked_s, 0.0) / tau_s))
        return se3.exp(keep * se3.log(s.v_tracked))

    def mark_tracked(self, T_world_cam: np.ndarray, time_s: float, status: FrameStatus) -> None:
        """Bookkeeping of a registered frame: the last tracked pose and time, the failure streak, weak counts."""
        s = self.state
        s.T_world_last_tracked = T_world_cam.copy()
        s.t_last_tracked_s = time_s
        s.failures_in_a_row = 0
        s.held_in_a_row = 0
        s.t_last_posed_s = time_s
        if status is FrameStatus.WEAK:
            s.weak_frames += 1

    def count_failure(self, reason: str, forget_tracked_step: bool = True) -> None:
        """A frame that was not registered, for ``reason``. After
        ``tracking.max_failures_in_a_row_before_reset_velocity`` in a row the velocity is reset to the identity (and,
        with ``forget_tracked_step``, the last fully tracked step a weak frame's velocity fades from)."""
        s = self.state
        s.failures += 1
        s.failures_in_a_row += 1
        s.held_in_a_row = 0
        s.failure_reasons[reason] = s.failure_reasons.get(reason, 0) + 1
        if s.failures_in_a_row >= self.cfg.max_failures_in_a_row_before_reset_velocity:
            if forget_tracked_step:
                s.velocity = s.v_tracked = np.eye(4)
            else:
                s.velocity = np.eye(4)

    def jumped(self, res: ICPResult, time_s: float) -> bool:
        """Whether ``res``, a registration from the constant-velocity prediction at time ``time_s``, corrected the
        prediction by more than a camera's change of velocity allows since the last registered or held frame
        (``tracking.max_velocity_change_m_s`` / ``max_rate_change_deg_s``, plus :data:`CORRECTION_SLACK_M` /
        :data:`CORRECTION_SLACK_DEG`): ICP slid along directions the view hardly constrains, though its system
        looked well conditioned. An identity velocity is no measurement (the first frame, after a reset or a
        relocalisation): then nothing is a jump."""
        if np.array_equal(self.state.velocity, np.eye(4)):
            return False
        return self._beyond_reach(res.motion_m, res.motion_deg, time_s)

    def slid_unconverged(self, res: ICPResult) -> bool:
        """Whether ``res``, a registration from the constant-velocity prediction after a tracked frame, ran out of
        iterations at the finest level (still moving) after correcting the prediction by more than ICP corrects a
        good one (:data:`CORRECTION_SLACK_M` / :data:`CORRECTION_SLACK_DEG`): a slide in progress, not a measurement,
        even within :meth:`jumped`'s bound (on a floor, 4.5 cm slides of this kind were fused and fed the next
        prediction). After a held frame, or with an identity velocity, the prediction is not that good: ``False``."""
        s = self.state
        if res.status is not ICPStatus.MAX_ITERATIONS or s.held_in_a_row > 0 or np.array_equal(s.velocity, np.eye(4)):
            return False
        return res.motion_m > CORRECTION_SLACK_M or res.motion_deg > CORRECTION_SLACK_DEG

    def within_reach(self, T_pred: np.ndarray, T: np.ndarray, time_s: float) -> bool:
        """Whether the pose ``T`` is within :meth:`jumped`'s bound of the prediction ``T_pred`` at ``time_s``; with an
        identity velocity (none measured) every pose is."""
        if np.array_equal(self.state.velocity, np.eye(4)):
            return True
        return not self._beyond_reach(*se3.pose_error(T, T_pred), time_s)

    def _beyond_reach(self, d_m: float, d_deg: float, time_s: float) -> bool:
        """Whether a correction of ``d_m`` / ``d_deg`` to the prediction at ``time_s`` exceeds the change of velocity
        a camera makes since the last posed frame (see :meth:`jumped`)."""
        tc = self.cfg
        dt_s = max(time_s - self.state.t_last_posed_s, 0.0)
        return (d_m > CORRECTION_SLACK_M + tc.max_velocity_change_m_s * dt_s
                or d_deg > CORRECTION_SLACK_DEG + tc.max_rate_change_deg_s * dt_s)

    def bridge_holds(self, T_pred: np.ndarray, T_bridge: np.ndarray, time_s: float) -> bool:
        """Whether a frame the map could not register may be posed at the features' pose ``T_bridge`` without starting
        a relocalisation: it is within reach of the prediction ``T_pred`` (:meth:`jumped`'s bound; a measured
        velocity) and fewer than ``tracking.max_held_frames`` frames were held in a row."""
        if np.array_equal(self.state.velocity, np.eye(4)) or not self.may_hold():
            return False
        return self.within_reach(T_pred, T_bridge, time_s)

    def may_hold(self) -> bool:
        """Whether one more frame may be held at the prediction (``tracking.max_held_frames`` in a row)."""
        return self.state.held_in_a_row < self.cfg.max_held_frames

    def mark_held(self, time_s: float) -> None:
        """Bookkeeping of a frame held at the prediction at time ``time_s``: the velocity and the last registered pose
        stay (the next prediction goes on from the held one)."""
        s = self.state
        s.held_frames += 1
        s.held_in_a_row += 1
        s.t_last_posed_s = time_s

    def count_not_localised(self, reason: str) -> None:
        """A frame not localised in a loaded map yet: a failure, not a streak (there is no motion to reset)."""
        s = self.state
        s.failures += 1
        s.failure_reasons[reason] = s.failure_reasons.get(reason, 0) + 1

    def plausible_jump(self, T_world_new: np.ndarray, time_s: float) -> bool:
        """Whether a relocalised pose is reachable from the last tracked one in the time since it
        (``tracking.relocalise_max_speed_m_s`` / ``_max_rate_deg_s`` plus a slack): a relocalisation that would
        move the camera faster than a hand-held or robot camera moves is refused rather than followed."""
        tc = self.cfg
        s = self.state
        if s.T_world_last_tracked is None:
            return True
        dt_s = max(time_s - s.t_last_tracked_s, 0.0)
        d_m, d_deg = se3.pose_error(T_world_new, s.T_world_last_tracked)
        ok = (d_m <= tc.relocalise_slack_m + tc.relocalise_max_speed_m_s * dt_s
              and d_deg <= tc.relocalise_slack_deg + tc.relocalise_max_rate_deg_s * dt_s)
        if not ok:
            s.relocalisations["refused_implausible"] += 1
        return ok
