"""The public Python API: open a sequence, run SLAM frame by frame, register a pair, evaluate a trajectory.

    import surfelslam as ss

    seq = ss.open_sequence("rgbd_dataset_freiburg3_teddy")
    slam = ss.Slam.from_sequence(seq)  # the default tracker, hybrid, set up for this sequence's cameras
    for frame in seq:
        slam.track(frame)
    run = slam.finish()
    run.save("out/teddy")
    print(ss.evaluate(run.trajectory, seq.ground_truth)["ate_rmse_m"])

Everything here is a thin layer over :mod:`surfelslam.slam` (the trackers and the run loop),
:mod:`surfelslam.datasets`, :mod:`surfelslam.tracking.registration` and :mod:`surfelslam.eval`.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from surfelslam.config import dumps_toml, from_dict, load_toml
from surfelslam.datasets.base import DatasetOptions, RGBDSequence
from surfelslam.datasets.registry import open_sequence as _open_sequence
from surfelslam.errors import ConfigError, FrameError
from surfelslam.eval.metrics import DEFAULT_MAX_DIFF_S
from surfelslam.eval.metrics import evaluate as _evaluate
from surfelslam.io.trajectory import read_tum, write_tum
from surfelslam.slam import TRACKERS, FrameResult, SlamConfig, SlamResult, Tracker, build_slam
from surfelslam.slam.colour_check import colour_is_registered
from surfelslam.slam.saved_map import SavedMap, check_map_options
from surfelslam.slam.segments import segments_report, tracking_segments
from surfelslam.tracking.icp import ICPConfig
from surfelslam.tracking.preprocess import PreprocessConfig, Preprocessor
from surfelslam.tracking.registration import PairRegistration, register_pair
from surfelslam.types import ColourCamera, Intrinsics, RGBDFrame, Trajectory


def open_sequence(path: str | Path, **dataset_options: Any) -> RGBDSequence:
    """Open an RGB-D sequence folder (TUM, ICL-NUIM, 7-Scenes or plain ``rgb/`` + ``depth/``).

    ``dataset_options`` are :class:`~surfelslam.datasets.base.DatasetOptions` fields: ``intrinsics=(fx, fy, cx, cy)``,
    ``depth_scale``, ``start``, ``end``, ``stride``, ``downsample``. The sequence is indexable and iterable
    (``RGBDFrame`` objects) and has ``intrinsics`` and ``ground_truth``.
    """
    try:
        options = DatasetOptions(**dataset_options)
    except TypeError as exc:
        raise ConfigError(f"open_sequence: {exc}") from None
    return _open_sequence(path, options)


def _as_config(config: SlamConfig | dict | str | Path | None) -> SlamConfig:
    if config is None:
        return SlamConfig()
    if isinstance(config, SlamConfig):
        return config
    if isinstance(config, dict):
        return from_dict(SlamConfig, config)
    return load_toml(SlamConfig, config)


@dataclass
class SlamRun:
    """The outcome of a :class:`Slam` session.

    Attributes:
        trajectory: every tracked frame's final pose ``T_world_cam`` (after loop closure for the trackers with a
            pose graph), with the frames' timestamps.
        map: the map: a :class:`~surfelslam.mapping.surfel_map.SurfelMap` (surfel trackers) or ``None`` (``orb``,
            whose map is the keyframe cloud in ``points_xyz`` / ``points_rgb``).
        metrics: counts and summary numbers of the run (failures, relocalisations, keyframes, loops ...).
        config: the configuration used.
        tracker: the tracker's name.
        frames: the per-frame results in order.
    """

    trajectory: Trajectory
    map: Any
    metrics: dict
    config: SlamConfig
    tracker: str
    result: SlamResult = field(repr=False)
    frames: list[FrameResult] = field(default_factory=list, repr=False)

    @property
    def points_xyz(self) -> np.ndarray | None:
        """``(M, 3)`` float32 map points in the world frame (surfel positions or the keyframe cloud)."""
        arrays = self.result.map_arrays()
        return None if arrays is None else arrays["position"]

    def save(self, out_dir: str | Path) -> Path:
        """Write ``trajectory.txt`` (TUM), ``map.ply``, ``config.toml``, ``metrics.json`` and (surfel trackers)
        ``map.npz``, the map a later session continues from (:func:`load_map`), into ``out_dir``."""
        from surfelslam.io.atomic import write_text_atomic
        from surfelslam.io.jsonio import json_default
        from surfelslam.slam.map_file import MAP_FILE, write_map_file

        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        write_tum(self.trajectory, out / "trajectory.txt")
        self.result.write_map(out / "map.ply")
        recipe = dumps_toml(self.config)
        write_text_atomic(out / "config.toml", recipe)
        saved = self.result.saved_map
        if saved is not None:
            write_map_file(out / MAP_FILE, saved if saved.config_toml else replace(saved, config_toml=recipe))
        metrics = {"tracker": self.tracker, "frames_processed": len(self.trajectory), **self.metrics}
        write_text_atomic(out / "metrics.json", json.dumps(metrics, indent=2, default=json_default) + "\n")
        return out


class Slam:
    """A SLAM session: feed RGB-D frames in order with :meth:`track`, then :meth:`finish`.

    Args:
        intrinsics: the depth camera (``Intrinsics(fx, fy, cx, cy, width, height)``); frames must have its size.
        tracker: one of :data:`surfelslam.slam.TRACKERS`; default: the config's ``tracker`` (``hybrid``).
        config: a :class:`SlamConfig`, a nested dict of settings, or a TOML file; default settings otherwise.
        colour_registered: whether colour pixels see the same rays as depth pixels (photometric and feature terms
            are used only then, by default).
        colour_camera: a separate colour camera, if the colour is not registered to depth (map colours only).
        warmup: compile the numba kernels now (else on the first frame).
        prior_map: continue from a saved map (:func:`load_map`, or the path of a run folder or its ``map.npz``):
            the first frames are localised in it, then tracking and mapping go on in its frame (``dense``,
            ``hybrid``). Frames before that have ``posed`` False.
        localize_only: with ``prior_map``, track against it without changing it.
    """

    def __init__(self, intrinsics: Intrinsics, tracker: str | None = None,
                 config: SlamConfig | dict | str | Path | None = None, *, colour_registered: bool = True,
                 colour_camera: ColourCamera | None = None, warmup: bool = True,
                 prior_map: SavedMap | str | Path | None = None, localize_only: bool = False):
        cfg = _as_config(config)
        tracker = cfg.tracker if tracker is None else tracker
        if tracker not in TRACKERS:
            raise ConfigError(f"tracker must be one of {', '.join(TRACKERS)}, got {tracker!r}")
        check_map_options(tracker, prior_map, localize_only, None)
        self.intrinsics = intrinsics
        self.tracker_name = tracker
        self.config = replace(cfg, tracker=tracker)
        self.tracker: Tracker = build_slam(intrinsics, self.config, tracker, colour_registered, colour_camera)
        if prior_map is not None:
            self.tracker.use_prior_map(prior_map if isinstance(prior_map, SavedMap) else load_map(prior_map),
                                       localize_only)
        if warmup:
            self.tracker.warmup()
        self._results: list[FrameResult] = []
        self._finished = False
        #: the pre-run colour registration check (:meth:`from_sequence`; ``None``: not run or not applicable)
        self.colour_check: dict | None = None

    @classmethod
    def from_sequence(cls, seq: RGBDSequence, tracker: str | None = None,
                      config: SlamConfig | dict | str | Path | None = None, **kwargs: Any) -> Slam:
        """A session set up for ``seq``'s cameras, as ``surfelslam run`` sets it up: its intrinsics, whether its
        colour is registered to depth (the layout's word, checked on a few frames for the layouts that take it as
        registered: ``colour_registration.check``), and its separate colour camera if the layout knows one.
        ``kwargs``: the other :class:`Slam` arguments (``warmup``, ``prior_map``, ``localize_only``).
        """
        cfg = replace(_as_config(config), dataset=seq.options)
        registered, check = colour_is_registered(seq, cfg.colour_registration)
        slam = cls(seq.intrinsics, tracker, cfg, colour_registered=registered, colour_camera=seq.colour_camera,
                   **kwargs)
        slam.colour_check = check
        return slam

    def track(self, frame: RGBDFrame | np.ndarray, depth_m: np.ndarray | None = None,
              timestamp: float | None = None) -> FrameResult:
        """Track one frame: ``track(frame)`` or ``track(rgb, depth_m, timestamp)``.

        ``rgb``: ``(H, W, 3)`` uint8; ``depth_m``: ``(H, W)`` float32 metres, 0 or NaN = no depth; ``timestamp``: s.
        Returns the frame's result (``T_world_cam``, whether it was tracked, timings).
        """
        if self._finished:
            raise ConfigError("Slam.track: the session is finished; start a new Slam")
        if not isinstance(frame, RGBDFrame):
            frame = self._frame_from_arrays(frame, depth_m, timestamp)
        res = self.tracker.process(frame)
        self._results.append(res)
        return res

    def _frame_from_arrays(self, rgb: np.ndarray, depth_m: np.ndarray | None, timestamp: float | None) -> RGBDFrame:
        if depth_m is None or timestamp is None:
            raise ConfigError("Slam.track: give an RGBDFrame, or rgb, depth_m and timestamp")
        rgb = np.asarray(rgb)
        depth = np.asarray(depth_m, dtype=np.float32)
        h, w = self.intrinsics.height, self.intrinsics.width
        if rgb.shape != (h, w, 3) or rgb.dtype != np.uint8:
            raise FrameError(None, f"rgb must be ({h}, {w}, 3) uint8, got {rgb.shape} {rgb.dtype}", len(self._results))
        if depth.shape != (h, w):
            raise FrameError(None, f"depth_m must be ({h}, {w}), got {depth.shape}", len(self._results))
        depth = np.where(np.isfinite(depth) & (depth > 0), depth, np.float32(0.0)).astype(np.float32)
        return RGBDFrame(len(self._results), float(timestamp), rgb, depth)

    def finish(self) -> SlamRun:
        """End the session: run the back end (for ``orb`` / ``hybrid``) and return the final trajectory and map."""
        self._finished = True
        res = self.tracker.finish()
        if res.trajectory_override is not None:
            traj = res.trajectory_override
        else:
            posed = [r for r in self._results if r.posed]
            stamps = np.array([r.timestamp for r in posed], np.float64)
            poses = np.array([r.T_world_cam for r in posed], np.float64).reshape(-1, 4, 4)
            traj = Trajectory(stamps, poses)
        frames = [(r.index, r.timestamp, r.status, r.reason) for r in self._results]
        metrics = {**res.metrics, **segments_report(tracking_segments(frames))}
        if self.colour_check is not None:
            metrics["colour_check"] = self.colour_check
        return SlamRun(traj, res.surfel_map, metrics, self.config, self.tracker_name, res, self._results)


def load_map(path: str | Path) -> SavedMap:
    """A saved map (``map.npz``, or the run folder holding it) for ``Slam(..., prior_map=...)``.

    Raises:
        MapFileError: missing, truncated or corrupt, or of another format version (the message names the file).
    """
    from surfelslam.slam.map_file import read_map_file

    return read_map_file(path)


def register(source: RGBDFrame, target: RGBDFrame, intrinsics: Intrinsics, init: str = "auto",
             photometric: bool = False, icp: ICPConfig | None = None,
             preprocess: PreprocessConfig | None = None) -> PairRegistration:
    """Register two RGB-D frames: the pose ``T_target_source`` (``result.icp.T_target_source``) that maps source
    camera points into the target camera.

    ``init``: ``auto`` (ICP from the identity and from an image-feature guess, keeping what the depth agrees with),
    ``identity``, ``features`` or ``geometry`` (shape features); ``photometric``: add the intensity term (colour
    registered to depth only).
    """
    icp_cfg = ICPConfig() if icp is None else icp
    pre_cfg = PreprocessConfig(pyramid_levels=icp_cfg.levels) if preprocess is None else preprocess
    pre = Preprocessor(intrinsics, pre_cfg)
    p_src = pre.process(source.depth_m)
    p_tgt = pre.process(target.depth_m)
    return register_pair(source, target, p_src, p_tgt, intrinsics, icp_cfg, init, photometric=photometric,
                         preprocess_cfg=pre.cfg)


def evaluate(estimate: Trajectory | str | Path, ground_truth: Trajectory | str | Path,
             max_diff_s: float = DEFAULT_MAX_DIFF_S) -> dict:
    """ATE and RPE of ``estimate`` against ``ground_truth`` (trajectories or TUM files), as evo computes them.

    Returns plain numbers: ``ate_rmse_m``, ``ate_mean_m``, ``ate_max_m``, ``rpe_trans_rmse_m_per_frame``, ...
    (:func:`surfelslam.eval.metrics.evaluate`). ``max_diff_s``: the timestamp association bound.
    """
    est = estimate if isinstance(estimate, Trajectory) else read_tum(estimate)
    gt = ground_truth if isinstance(ground_truth, Trajectory) else read_tum(ground_truth)
    return _evaluate(est, gt, max_diff_s)
