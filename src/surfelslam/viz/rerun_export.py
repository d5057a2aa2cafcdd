"""A finished run as a Rerun recording (``.rrd``): map, trajectories, loop edges, camera and images over time.

Needs the optional ``rerun-sdk`` (``pip install 'surfelslam[viz]'``); open the file with ``rerun FILE.rrd``.

What is logged (entity paths; ``world`` is the ground truth's frame when the run has ground truth, the estimate
then SE(3)-aligned to it as in the ATE (its first pose put on the ground truth's where that alignment is
degenerate), else the first camera's frame):

* ``world/map``: the run's ``map.ply`` points, with their colours and (surfel maps) radii; static.
* ``world/estimate``, ``world/ground_truth``: the whole trajectories as line strips; static.
* ``world/loops``: accepted loop edges (``metrics.json`` ``loop_edges``), a segment between the two keyframes.
* ``world/camera``: the estimated pose at each frame (timelines ``frame``, the frame's position in the run, and
  ``time``, seconds since the first frame), with a pinhole of the run's intrinsics when the sequence is
  available; ``world/camera/image/rgb`` and ``.../depth`` every ``images_every`` frames (colour as JPEG).
* ``plots/ate_m``: the per-frame ATE (m) when there is ground truth.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from surfelslam.errors import ConfigError, SurfelSlamError
from surfelslam.geometry import se3
from surfelslam.io.atomic import atomic_path
from surfelslam.types import Intrinsics, RGBDFrame, Trajectory

#: Colours (RGB, uint8) of the logged trajectories and loop edges.
ESTIMATE_RGB = (230, 120, 20)
GROUND_TRUTH_RGB = (40, 160, 60)
LOOP_RGB = (200, 40, 200)
#: Line radius (m) of the trajectories and loop edges, and point radius (m) of maps without surfel radii.
LINE_RADIUS_M = 0.003
POINT_RADIUS_M = 0.004
#: Colour images are logged JPEG-compressed at this quality (a tenth of the raw size; depth stays lossless).
RGB_JPEG_QUALITY = 90
#: Depth images are logged as uint16 in these units per metre (Rerun's ``meter``), half the size of float32.
DEPTH_UNITS_PER_M = 1000.0


def require_rerun():
    """The ``rerun`` module, or a :class:`ConfigError` saying how to install it."""
    try:
        import rerun
    except ImportError:
        raise ConfigError("rerun-sdk is not installed: pip install 'surfelslam[viz]' (or pip install rerun-sdk)"
                          ) from None
    return rerun


@dataclass
class RerunScene:
    """Everything a recording shows, already in the logged world frame.

    Attributes:
        trajectory: the estimated poses ``T_world_cam`` (world = the logged frame).
        ground_truth: the associated ground-truth poses, or ``None``.
        ate_errors_m: ``(N,)`` ATE per estimated pose, NaN where it has no ground truth; ``None`` without it.
        points_xyz: ``(M, 3)`` float32 map points; ``points_rgb``: ``(M, 3)`` uint8 or ``None``;
            ``points_radius_m``: ``(M,)`` float32 or ``None``.
        loop_edges: ``(L, 2, 3)`` segment end points of accepted loop edges.
        T_world_run: ``(4, 4)`` transform applied to the run's poses and map (the ATE alignment, or identity).
        alignment: ``"se3"`` (the ATE's Umeyama alignment), ``"origin"`` (the first associated poses made to
            coincide, when Umeyama is degenerate, e.g. a run lost throughout) or ``"none"`` (no ground truth, or
            fewer than 3 poses associated with it).
    """

    trajectory: Trajectory
    ground_truth: Trajectory | None
    ate_errors_m: np.ndarray | None
    points_xyz: np.ndarray
    points_rgb: np.ndarray | None
    points_radius_m: np.ndarray | None
    loop_edges: np.ndarray
    T_world_run: np.ndarray
    alignment: str = "none"


def build_scene(est: Trajectory, map_vertices: dict[str, np.ndarray] | None, loop_stamps: Iterable,
                gt: Trajectory | None = None, max_diff_s: float | None = None) -> RerunScene:
    """Put a run's outputs into one world frame (see the module docstring).

    Args:
        est: the run's trajectory.
        map_vertices: the ``map.ply`` vertex properties (:func:`~surfelslam.io.ply.read_ply`) or ``None``.
        loop_stamps: pairs ``(t_i, t_j)`` of keyframe timestamps (s) joined by accepted loop edges.
        gt: ground truth, or ``None``.
        max_diff_s: timestamp association tolerance for the ATE (default: the evaluation's).
    """
    T = np.eye(4)
    gt_assoc = errors = None
    alignment = "none"
    if gt is not None:
        from evo.core.geometry import GeometryException

        from surfelslam.errors import GroundTruthError
        from surfelslam.eval.metrics import DEFAULT_MAX_DIFF_S, ate

        tol = DEFAULT_MAX_DIFF_S if max_diff_s is None else max_diff_s
        try:
            a = ate(est, gt, tol)
            alignment = "se3"
        except GeometryException:  # e.g. every estimated pose at one place (tracking lost throughout)
            a = ate(est, gt, tol, align=False)
            alignment = "origin"
        except GroundTruthError:  # fewer than 3 poses associated: nothing to align or compare
            a = None
        if a is not None:
            if alignment == "origin":  # the first associated poses coincide (evo's --align_origin)
                k = int(np.searchsorted(est.timestamps, a.timestamps[0]))
                T = a.gt.T_world_cam[0] @ se3.invert(est.T_world_cam[min(k, len(est) - 1)])
                a = ate(Trajectory(est.timestamps, T @ est.T_world_cam), gt, tol, align=False)
            else:
                T = a.T_align
            gt_assoc = a.gt
            errors = np.full(len(est), np.nan)
            pos = np.searchsorted(est.timestamps, a.timestamps)
            errors[np.clip(pos, 0, len(est) - 1)] = a.errors_m
    traj = Trajectory(est.timestamps.copy(), T @ est.T_world_cam)
    xyz = np.zeros((0, 3), np.float32)
    rgb = radius = None
    if map_vertices is not None and all(k in map_vertices for k in ("x", "y", "z")):
        xyz_run = np.stack([map_vertices[k] for k in ("x", "y", "z")], axis=1).astype(np.float64)
        xyz = se3.transform_points(T, xyz_run).astype(np.float32)
        if all(k in map_vertices for k in ("red", "green", "blue")):
            rgb = np.stack([map_vertices[k] for k in ("red", "green", "blue")], axis=1).astype(np.uint8)
        if "radius" in map_vertices:
            radius = map_vertices["radius"].astype(np.float32)
    centres = traj.positions
    segs = []
    for ti, tj in loop_stamps:
        i, j = (int(np.argmin(np.abs(traj.timestamps - float(t)))) for t in (ti, tj))
        segs.append((centres[i], centres[j]))
    loops = np.asarray(segs, np.float64).reshape(-1, 2, 3)
    return RerunScene(traj, gt_assoc, errors, xyz, rgb, radius, loops, T, alignment)


@dataclass
class ExportSummary:
    """What :func:`write_recording` logged."""

    path: Path
    poses: int
    points: int
    loop_edges: int
    images: int
    frames_skipped: list[str]


def write_recording(path: Path, scene: RerunScene, intr: Intrinsics | None = None,
                    frame_at: Callable[[int], RGBDFrame | None] | None = None, images_every: int = 10,
                    application_id: str = "surfelslam") -> ExportSummary:
    """Write ``scene`` (and every ``images_every``-th frame's images, ``frame_at(k)`` giving the frame of pose
    ``k`` or ``None``) to ``path``, through a temp file renamed at the end (a failed export leaves no
    half-written recording). A frame that cannot be read (``SurfelSlamError``) is skipped and listed."""
    rr = require_rerun()
    if images_every < 1:
        raise ConfigError(f"images_every must be >= 1, got {images_every}")
    path = Path(path)
    skipped: list[str] = []
    with atomic_path(path) as tmp:
        rec = rr.RecordingStream(application_id, recording_id=path.stem)
        try:
            rec.save(tmp)
            n_images = _log_scene(rr, rec, scene, intr, frame_at, images_every, skipped)
            rec.flush()
        finally:
            rec.disconnect()  # closes the file before it is renamed (or deleted)
    return ExportSummary(path, len(scene.trajectory), len(scene.points_xyz), len(scene.loop_edges), n_images,
                         skipped)


def _log_scene(rr, rec, scene: RerunScene, intr: Intrinsics | None,
               frame_at: Callable[[int], RGBDFrame | None] | None, images_every: int, skipped: list[str]) -> int:
    """Log ``scene`` into ``rec`` (see :func:`write_recording`); returns the number of image pairs logged and
    appends unreadable frames' messages to ``skipped``."""
    n_images = 0
    if scene.ground_truth is None:  # the run's frame (its first camera's): x right, y down, z forward
        rec.log("world", rr.ViewCoordinates.RDF, static=True)
    rec.log("world/map", rr.Points3D(scene.points_xyz, colors=scene.points_rgb,
                                     radii=scene.points_radius_m if scene.points_radius_m is not None
                                     else POINT_RADIUS_M), static=True)
    rec.log("world/estimate", rr.LineStrips3D([scene.trajectory.positions], colors=[ESTIMATE_RGB],
                                              radii=LINE_RADIUS_M), static=True)
    if scene.ground_truth is not None:
        rec.log("world/ground_truth", rr.LineStrips3D([scene.ground_truth.positions], colors=[GROUND_TRUTH_RGB],
                                                      radii=LINE_RADIUS_M), static=True)
    if len(scene.loop_edges):
        rec.log("world/loops", rr.LineStrips3D(scene.loop_edges, colors=[LOOP_RGB], radii=LINE_RADIUS_M),
                static=True)
    if intr is not None:
        rec.log("world/camera/image", rr.Pinhole(image_from_camera=intr.K, resolution=[intr.width, intr.height],
                                                 camera_xyz=rr.ViewCoordinates.RDF), static=True)
    t0 = float(scene.trajectory.timestamps[0]) if len(scene.trajectory) else 0.0
    for k, (t, T) in enumerate(zip(scene.trajectory.timestamps, scene.trajectory.T_world_cam, strict=True)):
        rec.set_time("frame", sequence=k)
        rec.set_time("time", duration=float(t) - t0)
        rec.log("world/camera", rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]))
        if scene.ate_errors_m is not None and np.isfinite(scene.ate_errors_m[k]):
            rec.log("plots/ate_m", rr.Scalars(float(scene.ate_errors_m[k])))
        if frame_at is None or intr is None or k % images_every:
            continue
        try:
            frame = frame_at(k)
        except SurfelSlamError as exc:
            skipped.append(str(exc))
            continue
        if frame is None:
            continue
        rec.log("world/camera/image/rgb", rr.Image(frame.rgb).compress(jpeg_quality=RGB_JPEG_QUALITY))
        depth = np.where(np.isfinite(frame.depth_m), frame.depth_m, 0.0) * DEPTH_UNITS_PER_M
        rec.log("world/camera/image/depth",
                rr.DepthImage(np.clip(np.round(depth), 0, 65535).astype(np.uint16), meter=DEPTH_UNITS_PER_M))
        n_images += 1
    return n_images
