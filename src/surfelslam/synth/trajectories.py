"""Camera trajectories with exact poses for the synthetic scenes.

Every style is a look-at rig: an eye position and a look-at target, both smooth functions of a progress
angle ``theta`` (radians), plus a small roll. Poses are ``T_world_cam`` (camera x right, y down, z forward;
world z up). Styles:

* ``slow``: a smooth orbit-with-wobble across the room centre, ``theta`` advancing a fixed step per frame
  (about 1-1.5 cm and 0.5 deg per frame at 30 Hz), looking across the room at furniture;
* ``fast``: the ``slow`` curve at 3x speed (3x the step per frame, same path);
* ``handheld``: the ``slow`` curve plus band-limited jitter (a few mm and a few tenths of a degree);
* ``loop``: one walking lap round the room (``n_frames`` per lap), looking outward-and-ahead at the walls;
  the last frame is one step before the start, so the loop closes.
* ``upward``: looking up at the ceiling and one wall, moving sideways along the wall (two planes);
* ``tour``: the ``slow`` orbit with an ``upward`` stretch inside it: the camera turns up to the ceiling and
  one wall, stays there for ``tour_upward_fraction`` of the frames, then turns back to the room (a degenerate
  stretch inside normal motion, as in the office benchmarks where a hand-held camera looks up).
* ``walk``: walking (``walk_speed_m_s``, varying a little) round the scene's closed route (``ViewHint.route``, only
  ``floor`` has one), corners smoothed, the gaze along the walking direction turned by the route's look offsets
  (into doorways, out at a room's walls), with a walker's bob and the ``handheld`` jitter; the route repeats, so
  a long sequence revisits every place once a lap.

For a ``"wall"`` scene (``plane``) the camera keeps facing the wall and sways / circles in front of it.

:func:`replay_motion` replays a *recorded* camera motion instead (a dataset's ground truth: real hand-held motion,
optionally sped up), placed in the scene's free space.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter1d

from surfelslam.config import Config, setting
from surfelslam.errors import ConfigError
from surfelslam.geometry.interpolation import interpolate_poses
from surfelslam.geometry.se3 import exp as se3_exp
from surfelslam.geometry.se3 import invert as se3_invert
from surfelslam.synth.scenes import Scene
from surfelslam.types import Trajectory

STYLES = ["slow", "fast", "handheld", "loop", "upward", "tour", "tour-across", "walk"]
UPWARD_LOOK_M, UPWARD_RISE_M = 1.6, 1.5  # "upward": the look-at point is this far ahead and up (about 43 deg)
REPLAY_HEADINGS = 8  # headings (evenly spaced) tried for a replayed motion in a "room" scene
_REPLAY_MAX_GAP_S = 0.1  # a recorded motion may not have a gap longer than this (s) where it is replayed
_REPLAY_MAX_DT_S = 0.02  # sample times may lie this far (s) past the first / last recorded stamp
WALK_SAMPLE_M = 0.02  # "walk": the route is resampled this finely (m) before its corners are smoothed
WALK_STEP_HZ, WALK_BOB_M = 1.9, 0.015  # a walker's steps per second and the eye's vertical bob (m) with them
WALK_SPEED_PERIOD_S = 7.0  # the walking speed drifts round its mean with this period (s)
WALK_GAZE_SMOOTH_S = 0.5  # the gaze heading is smoothed over this (s): a turn of the head is not instantaneous
WALK_TANGENT_M = 0.1  # the walking direction is taken over this distance (m) either side of the eye


@dataclass(frozen=True)
class TrajectoryConfig(Config):
    """Shape of the synthetic camera paths (orbit, loop, hand-held jitter, wall sway)."""

    slow_step_deg: float = setting(0.5, unit="deg", gt=0, le=90, doc="heading advance per frame of slow (the "
                                   "progress angle)")
    fast_factor: float = setting(3.0, gt=0, le=100, doc="fast = the slow curve at this many times the step")
    wobble_m: float = setting(0.3, unit="m", ge=0, le=10, doc="horizontal eye wobble amplitude around the orbit")
    bob_m: float = setting(0.1, unit="m", ge=0, le=10, doc="vertical eye bob amplitude")
    target_sway_rad: float = setting(0.25, unit="rad", ge=0, le=3.2, doc="look direction sway around the heading")
    target_bob_m: float = setting(0.3, unit="m", ge=0, le=10, doc="look-at height sway")
    roll_deg: float = setting(3.0, unit="deg", ge=0, le=180, doc="roll amplitude")
    loop_look_ahead_deg: float = setting(35.0, unit="deg", ge=-180, le=180,
                                         doc="loop: heading = outward direction + this (towards the walk direction)")
    loop_look_distance_m: float = setting(1.8, unit="m", gt=0, le=100, doc="loop: distance of the look-at point")
    jitter_trans_m: float = setting(0.003, unit="m", ge=0, le=1, doc="handheld: std of the translation jitter per "
                                    "axis")
    jitter_rot_deg: float = setting(0.3, unit="deg", ge=0, le=45, doc="handheld: std of the rotation jitter per axis")
    jitter_smooth_s: float = setting(0.12, unit="s", ge=0, le=10,
                                     doc="handheld: Gaussian smoothing of the white jitter (band limit)")
    wall_sway_m: float = setting(0.35, unit="m", ge=0, le=10, doc="wall scenes: lateral sway amplitude")
    tour_upward_fraction: float = setting(0.3, unit="fraction", gt=0, lt=1,
                                          doc="tour: share of the frames spent looking up (ceiling and one wall)")
    tour_turn_s: float = setting(3.0, unit="s", gt=0, le=60,
                                 doc="tour: duration of each turn between the room and the upward view")
    walk_speed_m_s: float = setting(1.2, unit="m/s", gt=0, le=5, doc="walk: mean walking speed")
    walk_speed_change: float = setting(0.08, unit="fraction", ge=0, lt=1,
                                       doc="walk: the speed drifts by up to this fraction of the mean")
    walk_corner_m: float = setting(0.4, unit="m", gt=0, le=5,
                                   doc="walk: the route's corners are rounded by a Gaussian of this std along it")
    across_radius_m: float = setting(
        1.5, unit="m", gt=0, le=100,
        doc="tour-across: the orbit's eye this far behind the room's centre, looking across it (far views)")


def look_at(eye: np.ndarray, target: np.ndarray, roll_rad: np.ndarray | float = 0.0) -> np.ndarray:
    """Poses ``(N, 4, 4)`` of cameras at ``eye (N, 3)`` looking at ``target (N, 3)``, world z up, rolled."""
    eye = np.atleast_2d(np.asarray(eye, np.float64))
    target = np.atleast_2d(np.asarray(target, np.float64))
    z = target - eye
    z /= np.linalg.norm(z, axis=1, keepdims=True)
    x = np.cross(z, np.array([0.0, 0.0, 1.0]))
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    y = np.cross(z, x)
    roll = np.broadcast_to(np.asarray(roll_rad, np.float64), (len(eye),))
    c, s = np.cos(roll)[:, None], np.sin(roll)[:, None]
    xr = c * x + s * y
    yr = -s * x + c * y
    T = np.zeros((len(eye), 4, 4))
    T[:, :3, 0] = xr
    T[:, :3, 1] = yr
    T[:, :3, 2] = z
    T[:, :3, 3] = eye
    T[:, 3, 3] = 1.0
    return T


def _orbit_rig(scene: Scene, theta: np.ndarray, ph: np.ndarray, cfg: TrajectoryConfig,
               radius_m: float | None = None):
    """``(eye, target)`` ``(N, 3)`` each along the scene's orbit (or wall sway); ``radius_m`` replaces the view's
    orbit radius (positive: the eye behind the centre, looking across the room)."""
    v = scene.view
    c = np.asarray(v.centre)
    if v.kind == "wall":
        f = np.asarray(v.facing, np.float64)
        lat = np.cross(f, [0.0, 0.0, 1.0])
        up = np.array([0.0, 0.0, 1.0])
        sway = cfg.wall_sway_m * np.sin(4.0 * theta + ph[0])
        eye = (c + sway[:, None] * lat + (cfg.bob_m * np.sin(5.2 * theta + ph[1]))[:, None] * up
               + (v.orbit_radius_m * np.sin(2.8 * theta + ph[2]))[:, None] * f)
        target = c + v.look_distance_m * f + (0.5 * sway)[:, None] * lat
        target[:, 2] = v.look_height_m + 0.3 * np.sin(3.6 * theta + ph[3])
        return eye, target
    r = v.orbit_radius_m if radius_m is None else radius_m
    eye = np.column_stack([
        c[0] - r * np.cos(theta) + cfg.wobble_m * np.sin(2.1 * theta + ph[0]),
        c[1] - r * np.sin(theta) + cfg.wobble_m * np.sin(1.6 * theta + ph[1]),
        v.eye_height_m + cfg.bob_m * np.sin(2.7 * theta + ph[2]),
    ])
    psi = theta + cfg.target_sway_rad * np.sin(1.3 * theta + ph[3])
    target = np.column_stack([
        c[0] + v.look_distance_m * np.cos(psi),
        c[1] + v.look_distance_m * np.sin(psi),
        v.look_height_m + cfg.target_bob_m * np.sin(1.9 * theta + ph[4]),
    ])
    return eye, target


def _corridor_rig(scene: Scene, theta: np.ndarray, ph: np.ndarray, cfg: TrajectoryConfig):
    """Walk back and forth along the corridor (``orbit_radius_m`` each way), looking ahead along ``facing``."""
    v = scene.view
    c = np.asarray(v.centre)
    f = np.asarray(v.facing, np.float64)
    lat = np.cross([0.0, 0.0, 1.0], f)
    along = v.orbit_radius_m * np.sin(theta)
    eye = (c + along[:, None] * f + (v.loop_radii_m[0] * np.sin(2.3 * theta + ph[0]))[:, None] * lat)
    eye[:, 2] = v.eye_height_m + cfg.bob_m * np.sin(3.1 * theta + ph[1])
    target = eye + v.look_distance_m * f + (0.4 * np.sin(1.7 * theta + ph[3]))[:, None] * lat
    target[:, 2] = v.look_height_m + 0.2 * np.sin(2.9 * theta + ph[4])
    return eye, target


def _upward_rig(scene: Scene, theta: np.ndarray, ph: np.ndarray, cfg: TrajectoryConfig):
    """Look up at the ceiling and one wall (their edge about ``look_distance_m`` ahead), moving sideways along
    that wall: two planes that leave the translation along their intersection to the texture and the motion
    prior."""
    v = scene.view
    c = np.asarray(v.centre)
    f = np.asarray(v.ceiling_facing if v.kind == "room" else v.facing, np.float64)
    lat = np.cross([0.0, 0.0, 1.0], f)
    side = 0.8 * np.sin(theta)
    eye = c + side[:, None] * lat + (cfg.wobble_m * 0.3 * np.sin(2.1 * theta + ph[0]))[:, None] * f
    eye[:, 2] = v.eye_height_m + cfg.bob_m * np.sin(2.7 * theta + ph[2])
    target = eye + UPWARD_LOOK_M * f
    target[:, 2] = eye[:, 2] + UPWARD_RISE_M + 0.15 * np.sin(1.9 * theta + ph[4])
    return eye, target


def _loop_rig(scene: Scene, theta: np.ndarray, ph: np.ndarray, cfg: TrajectoryConfig):
    v = scene.view
    c = np.asarray(v.centre)
    ax, ay = v.loop_radii_m
    if v.kind == "wall":
        f = np.asarray(v.facing, np.float64)
        lat = np.cross(f, [0.0, 0.0, 1.0])
        up = np.array([0.0, 0.0, 1.0])
        eye = c + (ax * np.cos(theta))[:, None] * lat + (ay * np.sin(theta))[:, None] * up
        target = np.tile(c + v.look_distance_m * f, (len(theta), 1))
        return eye, target
    eye = np.column_stack([
        c[0] + ax * np.cos(theta),
        c[1] + ay * np.sin(theta),
        v.eye_height_m + cfg.bob_m * np.sin(2.0 * theta + ph[2]),
    ])
    psi = theta + np.radians(cfg.loop_look_ahead_deg) + 0.5 * cfg.target_sway_rad * np.sin(2.0 * theta + ph[3])
    target = np.column_stack([
        eye[:, 0] + cfg.loop_look_distance_m * np.cos(psi),
        eye[:, 1] + cfg.loop_look_distance_m * np.sin(psi),
        v.look_height_m + cfg.target_bob_m * np.sin(3.0 * theta + ph[4]),
    ])
    return eye, target


def _jitter(rng: np.random.Generator, n: int, fps: float, cfg: TrajectoryConfig) -> np.ndarray:
    """``(n, 6)`` band-limited twists (rad, m): white noise smoothed by a Gaussian, scaled to the std."""
    sigma_frames = max(cfg.jitter_smooth_s * fps, 1e-6)
    white = rng.standard_normal((n, 6))
    smooth = gaussian_filter1d(white, sigma_frames, axis=0, mode="reflect")
    # std of unit white noise after a unit-sum Gaussian filter of std sigma: 1 / sqrt(2 sqrt(pi) sigma)
    gain = np.sqrt(2.0 * np.sqrt(np.pi) * sigma_frames) if sigma_frames >= 1.0 else 1.0
    scale = np.array([np.radians(cfg.jitter_rot_deg)] * 3 + [cfg.jitter_trans_m] * 3)
    return smooth * gain * scale


def _tour_weight(n_frames: int, fps: float, cfg: TrajectoryConfig) -> np.ndarray:
    """``(n_frames,)`` blend from the orbit (0) to the upward view (1): 0, a smooth (cosine) turn of ``tour_turn_s``,
    1 for ``tour_upward_fraction`` of the frames, the turn back, 0; the upward stretch centred in the sequence."""
    k = np.arange(n_frames, dtype=np.float64)
    hold = cfg.tour_upward_fraction * n_frames
    turn = max(cfg.tour_turn_s * fps, 1.0)
    start = 0.5 * (n_frames - hold) - turn
    ramp_up = np.clip((k - start) / turn, 0.0, 1.0)
    ramp_down = np.clip((start + 2.0 * turn + hold - k) / turn, 0.0, 1.0)
    return 0.5 - 0.5 * np.cos(np.pi * np.minimum(ramp_up, ramp_down))


def _blend_look(d0: np.ndarray, d1: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Look vectors ``(N, 3)`` from ``d0`` (``w`` 0) to ``d1`` (``w`` 1): azimuth along an arc continuous in time,
    elevation and length linearly. A linear blend of the look-at points can pass over the eye, where ``look_at``'s
    roll is undefined and the camera spins by up to 180 deg per frame; this one stays below the higher elevation."""
    def spherical(d: np.ndarray):
        r = np.linalg.norm(d, axis=1)
        return np.arctan2(d[:, 1], d[:, 0]), np.arcsin(np.clip(d[:, 2] / r, -1.0, 1.0)), r

    a0, e0, r0 = spherical(d0)
    a1, e1, r1 = spherical(d1)
    da = np.unwrap(a1 - a0)  # continuous in time (a per-frame shorter arc flips where the headings are opposite)
    turning = (w > 0.0) & (w < 1.0)
    if turning.any():  # the branch whose turning frames turn least on average
        da -= 2.0 * np.pi * np.round(da[turning].mean() / (2.0 * np.pi))
    a = a0 + w * da
    e, r = (1.0 - w) * e0 + w * e1, (1.0 - w) * r0 + w * r1
    return r[:, None] * np.column_stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])


def _smooth_route(route, corner_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A closed route ``((x, y, look_offset_rad), ...)`` resampled every ~``WALK_SAMPLE_M`` and its corners rounded
    (a Gaussian of std ``corner_m`` along it): ``xy (M + 1, 2)`` (the last row is the first), look offsets
    ``(M + 1,)`` and arc length ``(M + 1,)`` (m) from the start."""
    r = np.asarray(route, np.float64)
    seg = np.linalg.norm(np.diff(r[:, :2], axis=0), axis=1)
    r = r[np.concatenate([[True], seg > 0.0])]  # repeated waypoints would make the arc length non-increasing
    s = np.concatenate([[0.0], np.cumsum(seg[seg > 0.0])])
    n = max(int(s[-1] / WALK_SAMPLE_M), 8)
    ss = np.arange(n) * s[-1] / n
    dense = np.column_stack([np.interp(ss, s, r[:, i]) for i in range(3)])
    dense = gaussian_filter1d(dense, corner_m / (s[-1] / n), axis=0, mode="wrap")
    dense = np.vstack([dense, dense[:1]])
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(dense[:, :2], axis=0), axis=1))])
    return dense[:, :2], dense[:, 2], arc


def _walk_rig(scene: Scene, n_frames: int, fps: float, ph: np.ndarray, cfg: TrajectoryConfig):
    """``(eye, target, roll)`` walking round the scene's route (the ``walk`` style; see the module docstring)."""
    v = scene.view
    if not v.route:
        raise ConfigError(f"trajectory 'walk' needs a scene with a walking route (floor); scene {scene.name!r} has "
                          f"none")
    xy, offset, arc = _smooth_route(v.route, cfg.walk_corner_m)
    t = np.arange(n_frames) / fps
    w = 2.0 * np.pi / WALK_SPEED_PERIOD_S
    # distance walked: the integral of speed * (1 + change * sin(w t + ph))
    dist = cfg.walk_speed_m_s * (t + cfg.walk_speed_change / w * (np.cos(ph[0]) - np.cos(w * t + ph[0])))

    def at(d: np.ndarray, values: np.ndarray) -> np.ndarray:
        return np.interp(np.mod(d, arc[-1]), arc, values)

    pos = np.column_stack([at(dist, xy[:, 0]), at(dist, xy[:, 1])])
    ahead = np.column_stack([at(dist + WALK_TANGENT_M, xy[:, i]) - at(dist - WALK_TANGENT_M, xy[:, i])
                             for i in range(2)])
    heading = np.unwrap(np.arctan2(ahead[:, 1], ahead[:, 0])) + at(dist, offset)
    heading = gaussian_filter1d(heading, max(WALK_GAZE_SMOOTH_S * fps, 1e-6), mode="nearest")
    heading += 0.5 * cfg.target_sway_rad * np.sin(1.3 * t + ph[1])
    eye = np.column_stack([pos, v.eye_height_m + WALK_BOB_M * np.sin(2.0 * np.pi * WALK_STEP_HZ * t + ph[2])])
    target = eye + v.look_distance_m * np.column_stack([np.cos(heading), np.sin(heading), np.zeros(n_frames)])
    target[:, 2] = v.look_height_m + 0.5 * cfg.target_bob_m * np.sin(0.9 * t + ph[3])
    roll = np.radians(cfg.roll_deg) * 0.5 * np.sin(0.7 * t + ph[4])
    return eye, target, roll


def make_trajectory(
    style: str, n_frames: int, scene: Scene, fps: float = 30.0, seed: int = 0,
    cfg: TrajectoryConfig = TrajectoryConfig(),
) -> Trajectory:
    """Trajectory of ``n_frames`` poses at ``fps`` in ``scene``; deterministic from ``seed``.

    Timestamps are ``index / fps``. Unknown ``style`` -> ConfigError listing :data:`STYLES`.
    """
    if style not in STYLES:
        raise ConfigError(f"unknown trajectory style {style!r}; known styles: {', '.join(STYLES)}")
    if n_frames < 1:
        raise ConfigError(f"number of frames must be >= 1, got {n_frames}")
    if fps <= 0:
        raise ConfigError(f"fps must be positive, got {fps}")
    rng = np.random.default_rng([seed, 15485863])
    ph = rng.uniform(0.0, 2.0 * np.pi, 8)
    k = np.arange(n_frames, dtype=np.float64)
    theta0 = ph[7]
    roll_phase = ph[6]
    if style == "loop" and scene.view.kind != "corridor":
        theta = theta0 + 2.0 * np.pi * k / n_frames
        eye, target = _loop_rig(scene, theta, ph, cfg)
        roll = np.radians(cfg.roll_deg) * 0.5 * np.sin(2.0 * theta + roll_phase)
    elif style == "walk":
        eye, target, roll = _walk_rig(scene, n_frames, fps, ph, cfg)
    elif style == "upward":
        theta = theta0 + np.radians(cfg.slow_step_deg) * k
        eye, target = _upward_rig(scene, theta, ph, cfg)
        roll = np.radians(cfg.roll_deg) * np.sin(1.1 * theta + roll_phase)
    elif style in ("tour", "tour-across") and scene.view.kind == "room":
        theta = theta0 + np.radians(cfg.slow_step_deg) * k
        w = _tour_weight(n_frames, fps, cfg)[:, None]
        eye_o, target_o = _orbit_rig(scene, theta, ph, cfg, cfg.across_radius_m if style == "tour-across" else None)
        eye_u, target_u = _upward_rig(scene, theta, ph, cfg)
        eye = (1.0 - w) * eye_o + w * eye_u
        look = _blend_look(target_o - eye_o, target_u - eye_u, w[:, 0])
        target = np.where(w == 0.0, target_o, np.where(w == 1.0, target_u, eye + look))
        roll = np.radians(cfg.roll_deg) * np.sin(1.1 * theta + roll_phase)
    elif scene.view.kind == "corridor":
        step = np.radians(cfg.slow_step_deg) * (cfg.fast_factor if style == "fast" else 1.0)
        theta = theta0 + step * k
        eye, target = _corridor_rig(scene, theta, ph, cfg)
        roll = np.radians(cfg.roll_deg) * np.sin(1.1 * theta + roll_phase)
    else:
        step = np.radians(cfg.slow_step_deg) * (cfg.fast_factor if style == "fast" else 1.0)
        theta = theta0 + step * k
        eye, target = _orbit_rig(scene, theta, ph, cfg)
        roll = np.radians(cfg.roll_deg) * np.sin(1.1 * theta + roll_phase)
    T = look_at(eye, target, roll)
    if style in ("handheld", "walk"):
        xi = _jitter(rng, n_frames, fps, cfg)
        for i in range(n_frames):  # per pose (not per pixel): a 4x4 product each
            T[i] = T[i] @ se3_exp(xi[i])
    return Trajectory(k / fps, T)


def replay_motion(
    recorded: Trajectory, n_frames: int, scene: Scene, fps: float = 30.0, speed: float = 1.0,
    start_s: float = 0.0, clearance_m: float = 0.35, seed: int = 0,
) -> Trajectory:
    """A recorded camera motion replayed in ``scene`` (``n_frames`` poses at ``fps``, timestamps ``index / fps``).

    Frame ``k`` takes the recorded pose at ``t_first + start_s + k * speed / fps`` (translation interpolated
    linearly, rotation along the geodesic), relative to the pose at frame 0, and applies it to an anchor: a
    level camera at the scene's eye height, looking along a heading, the path's bounding box centred on the
    scene's free-space centre (``Scene.view``). ``speed`` 3 is the same motion at 3x speed. Headings are tried in
    turn (a ``"room"`` scene: :data:`REPLAY_HEADINGS` directions starting from one chosen by ``seed``; a ``"wall"``
    scene: facing the wall only) and the first whose whole path stays ``clearance_m`` from every surface is used.

    Args:
        recorded: the motion, e.g. a dataset's ``groundtruth.txt`` (any world frame: only relative motion is used).

    Raises:
        ConfigError: bad arguments, a recording too short for ``n_frames`` at ``speed`` or with a gap, or a path
        that fits the scene under no heading (the message gives its extent).
    """
    if n_frames < 1:
        raise ConfigError(f"number of frames must be >= 1, got {n_frames}")
    if fps <= 0 or speed <= 0 or start_s < 0 or clearance_m < 0:
        raise ConfigError(f"need fps > 0, speed > 0, start >= 0, clearance >= 0; got {fps}, {speed}, {start_s}, "
                          f"{clearance_m}")
    t = recorded.timestamps
    if len(t) < 2:
        raise ConfigError(f"a recorded motion needs at least 2 poses, got {len(t)}")
    stamps = t[0] + start_s + np.arange(n_frames) * speed / fps
    if stamps[-1] > t[-1] + _REPLAY_MAX_DT_S:
        raise ConfigError(
            f"the recorded motion lasts {t[-1] - t[0]:.2f} s; {n_frames} frames at {fps:g} fps and {speed:g}x speed "
            f"from {start_s:g} s need {stamps[-1] - t[0]:.2f} s"
        )
    T_rec, valid = interpolate_poses(recorded, stamps, _REPLAY_MAX_GAP_S, _REPLAY_MAX_DT_S)
    if not valid.all():
        k = int(np.argmin(valid))
        raise ConfigError(f"the recorded motion has a gap of more than {_REPLAY_MAX_GAP_S} s at "
                          f"{stamps[k] - t[0]:.2f} s from its start")
    T_rel = np.einsum("ij,njk->nik", se3_invert(T_rec[0]), T_rec)  # motion relative to frame 0
    v = scene.view
    centre = np.asarray(v.centre, np.float64)
    if v.kind == "wall":
        f = np.asarray(v.facing, np.float64)
        headings = [float(np.arctan2(f[1], f[0]))]
    else:
        first = seed % REPLAY_HEADINGS
        headings = [2.0 * np.pi * ((first + j) % REPLAY_HEADINGS) / REPLAY_HEADINGS for j in range(REPLAY_HEADINGS)]
    best = -np.inf
    for psi in headings:
        direction = np.array([np.cos(psi), np.sin(psi), 0.0])
        target = np.array([0.0, 0.0, v.look_height_m]) + v.look_distance_m * direction
        R_anchor = look_at(np.array([0.0, 0.0, v.eye_height_m]), target)[0, :3, :3]
        path = T_rel[:, :3, 3] @ R_anchor.T  # positions relative to the anchor eye
        eye = np.array([centre[0], centre[1], v.eye_height_m])
        eye[:2] -= 0.5 * (path[:, :2].min(axis=0) + path[:, :2].max(axis=0))
        eye[2] -= path[:, 2].mean()
        positions = path + eye
        # the signed distance to the nearest surface: in a scene of several rooms a point in one is behind the
        # walls of the others, so only the nearest primitive's sign says whether it is in free space
        clearance = float(scene.signed_distance(positions).min())
        if clearance >= clearance_m:
            T_anchor = np.eye(4)
            T_anchor[:3, :3] = R_anchor
            T_anchor[:3, 3] = eye
            return Trajectory(np.arange(n_frames) / fps, np.einsum("ij,njk->nik", T_anchor, T_rel))
        best = max(best, clearance)
    extent = np.ptp(T_rel[:, :3, 3], axis=0)
    raise ConfigError(
        f"the recorded motion (extent {extent[0]:.2f} x {extent[1]:.2f} x {extent[2]:.2f} m in its first camera "
        f"frame) does not fit in scene {scene.name!r}: at best it passes {best:.2f} m from a surface (needs "
        f"{clearance_m} m); replay fewer frames or a later part (start)"
    )
