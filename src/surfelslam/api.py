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

import sys
import threading
import time
from collections.abc import Callable, Collection
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from surfelslam.config import dumps_toml, from_dict, load_toml
from surfelslam.datasets.base import DatasetOptions, RGBDSequence
from surfelslam.datasets.registry import open_sequence as _open_sequence
from surfelslam.errors import ConfigError, FrameError
from surfelslam.eval.protocol import DEFAULT_MAX_DIFF_S
from surfelslam.io.trajectory import read_tum
from surfelslam.kernels.threads import lower_thread_priority
from surfelslam.slam import FrameResult, SlamConfig, SlamResult, Tracker
from surfelslam.slam.colour_check import colour_is_registered
from surfelslam.slam.runner import run_sequence as _run_sequence
from surfelslam.slam.saved_map import SavedMap, check_map_options
from surfelslam.slam.session import RunOutcome, Session
from surfelslam.slam.writer import RunWriter
from surfelslam.tracking.icp import ICPConfig
from surfelslam.tracking.preprocess import PreprocessConfig, Preprocessor
from surfelslam.tracking.registration import PairRegistration, register_pair
from surfelslam.types import ColourCamera, Intrinsics, RGBDFrame, Trajectory
from surfelslam.viz.run_report import preload_figure_modules, run_report

#: The progress bar's FPS and map size are refreshed every this many frames (a redraw costs a little).
PROGRESS_EVERY = 10
#: s: the interpreter's thread switch interval while the report's modules are preloaded beside the tracking (Python's
#: default is 5 ms). The preload holds the GIL nearly all its second; a tracking thread coming back from a kernel (the
#: kernels release the GIL, ~50 times a frame) waits up to one interval for it, so at 5 ms the frames of that second
#: ran at a quarter of their speed. At 0.5 ms the main thread's GIL waits on a 100-frame run fell from ~5 to ~2.5 ms
#: per frame; the old interval is back once the preload is done.
PRELOAD_SWITCH_INTERVAL_S = 0.0005
#: nice levels below the tracking thread for the preload thread (Linux): its imports are wanted at the run's end, so
#: it takes the cores the frames' threads leave idle (:func:`~surfelslam.kernels.threads.lower_thread_priority`)
PRELOAD_NICE = 10


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
        metrics: counts and summary numbers of the run (failures, relocalisations, keyframes, loops, timings ...):
            ``metrics.json`` without the evaluation and the start and end times.
        config: the configuration used.
        tracker: the tracker's name.
        frames: the per-frame results in order.
        sequence: the sequence the frames came from (:meth:`Slam.from_sequence`), else ``None``.
    """

    trajectory: Trajectory
    map: Any
    metrics: dict
    config: SlamConfig
    tracker: str
    result: SlamResult = field(repr=False)
    frames: list[FrameResult] = field(default_factory=list, repr=False)
    sequence: RGBDSequence | None = field(default=None, repr=False)

    @property
    def points_xyz(self) -> np.ndarray | None:
        """``(M, 3)`` float32 map points in the world frame (surfel positions or the keyframe cloud)."""
        arrays = self.result.map_arrays()
        return None if arrays is None else arrays["position"]

    def save(self, out_dir: str | Path, *, figures: bool | Collection[str] = False, overwrite: bool = True,
             formats: Collection[str] = ("tum",)) -> Path:
        """Write the run folder as ``surfelslam run`` writes it (the same writer): ``trajectory.txt`` (TUM),
        ``map.ply``, ``config.toml``, ``metrics.json`` (with the evaluation when the sequence has ground truth),
        ``map.npz`` (surfel trackers; the map a later session continues from, :func:`load_map`) and the
        ``figures`` asked for, ``keyframes.txt`` where the tracker saved keyframes, and ``trajectory_kitti.txt`` when
        ``formats`` has ``"kitti"``. ``overwrite``: replace a previous run in ``out_dir`` (else refuse it)."""
        writer = RunWriter(out_dir, overwrite=overwrite, report=run_report(figures), formats=formats)
        writer.check()
        outcome = RunOutcome(self.trajectory, self.result, self.metrics, self.frames)
        with writer:
            writer.open(dumps_toml(self.config))
            writer.finish(outcome, None if self.sequence is None else self.sequence.ground_truth)
            return writer.commit()


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
        if prior_map is not None and not isinstance(prior_map, SavedMap):
            check_map_options(tracker, prior_map, localize_only, None)  # before reading a large file
            prior_map = load_map(prior_map)
        self.intrinsics = intrinsics
        self.session = Session(intrinsics, cfg, tracker, colour_registered=colour_registered,
                               colour_camera=colour_camera, prior_map=prior_map, localize_only=localize_only,
                               warmup=warmup)
        self.tracker_name = self.session.tracker_name
        self.config = self.session.config
        self.tracker: Tracker = self.session.tracker
        #: the sequence the session was set up for (:meth:`from_sequence`), recorded by :meth:`SlamRun.save`
        self.sequence: RGBDSequence | None = None

    @property
    def colour_check(self) -> dict | None:
        """The pre-run colour registration check (:meth:`from_sequence`; ``None``: not run or not applicable)."""
        return self.session.colour_check

    @classmethod
    def from_sequence(cls, seq: RGBDSequence, tracker: str | None = None,
                      config: SlamConfig | dict | str | Path | None = None, **kwargs: Any) -> Slam:
        """A session set up for ``seq``'s cameras, as ``surfelslam run`` sets it up: its intrinsics, whether its
        colour is registered to depth (the layout's word, checked on a few frames for the layouts that take it as
        registered: ``colour_registration.check``), and its separate colour camera if the layout knows one. The
        session remembers ``seq``: its run saves as ``surfelslam run`` would write it.
        ``kwargs``: the other :class:`Slam` arguments (``warmup``, ``prior_map``, ``localize_only``).
        """
        cfg = replace(_as_config(config), dataset=seq.options)
        registered, check = colour_is_registered(seq, cfg.colour_registration)
        slam = cls(seq.intrinsics, tracker, cfg, colour_registered=registered, colour_camera=seq.colour_camera,
                   **kwargs)
        slam.session.colour_check = check
        slam.sequence = seq
        return slam

    def track(self, frame: RGBDFrame | np.ndarray, depth_m: np.ndarray | None = None,
              timestamp: float | None = None) -> FrameResult:
        """Track one frame: ``track(frame)`` or ``track(rgb, depth_m, timestamp)``.

        ``rgb``: ``(H, W, 3)`` uint8; ``depth_m``: ``(H, W)`` float32 metres, 0 or NaN = no depth; ``timestamp``: s.
        Returns the frame's result (``T_world_cam``, whether it was tracked, timings).
        """
        if self.session.finished:
            raise ConfigError("Slam.track: the session is finished; start a new Slam")
        if not isinstance(frame, RGBDFrame):
            frame = self._frame_from_arrays(frame, depth_m, timestamp)
        return self.session.track(frame)

    def _frame_from_arrays(self, rgb: np.ndarray, depth_m: np.ndarray | None, timestamp: float | None) -> RGBDFrame:
        if depth_m is None or timestamp is None:
            raise ConfigError("Slam.track: give an RGBDFrame, or rgb, depth_m and timestamp")
        rgb = np.asarray(rgb)
        depth = np.asarray(depth_m, dtype=np.float32)
        h, w = self.intrinsics.height, self.intrinsics.width
        n = len(self.session.frames)
        if rgb.shape != (h, w, 3) or rgb.dtype != np.uint8:
            raise FrameError(None, f"rgb must be ({h}, {w}, 3) uint8, got {rgb.shape} {rgb.dtype}", n)
        if depth.shape != (h, w):
            raise FrameError(None, f"depth_m must be ({h}, {w}), got {depth.shape}", n)
        depth = np.where(np.isfinite(depth) & (depth > 0), depth, np.float32(0.0)).astype(np.float32)
        return RGBDFrame(n, float(timestamp), rgb, depth)

    def finish(self) -> SlamRun:
        """End the session: run the back end (for ``orb`` / ``hybrid``) and return the final trajectory and map."""
        out = self.session.finish(self.sequence)
        return SlamRun(out.trajectory, out.result.surfel_map, out.metrics, self.config, self.tracker_name,
                       out.result, out.frames, self.sequence)


def run_sequence(seq: RGBDSequence, out_dir: str | Path, cfg: SlamConfig, tracker: str | None = None,
                 poses: str | None = None, progress: bool = True, figures: bool | Collection[str] = True,
                 **kwargs: Any) -> dict:
    """Run the pipeline on an opened sequence into the run folder ``out_dir``, as ``surfelslam run`` does: with a
    progress bar (``progress``), the evaluation against the ground truth, and the ``figures`` (every PNG of
    :data:`~surfelslam.viz.run_report.RUN_FIGURES`, none, or those named).

    ``kwargs``: :func:`surfelslam.slam.runner.run_sequence`'s other arguments (``overwrite``, ``on_start``,
    ``before_commit``, ``on_frame``, ``prior_map``, ``localize_only``, ``formats``, ``started_perf_s``). Returns
    the metrics (``metrics.json``).
    """
    report = run_report(figures)  # checks the names before anything runs
    with progress_bar(len(seq), progress) as on_progress, preloading(figures, on_progress) as on_slot:
        return _run_sequence(seq, Path(out_dir), cfg, tracker, poses, report=report, on_progress=on_slot, **kwargs)


@contextmanager
def preloading(figures: bool | Collection[str], on_progress: Callable[[int, Any], None] | None):
    """An ``on_progress`` callback (calling ``on_progress``) that, once the first frame is done, imports the report's
    modules (evo, matplotlib, the figures') in a background thread
    (:func:`~surfelslam.viz.run_report.preload_figure_modules`): the import overlaps the tracking instead of adding to
    the run's end, at a short thread switch interval (:data:`PRELOAD_SWITCH_INTERVAL_S`) so that it holds the tracking
    up less. The thread is joined on leaving."""
    thread = threading.Thread(target=_preload_politely, args=(figures,), name="surfelslam-preload")

    def on_slot(done: int, res: FrameResult | None) -> None:
        if thread.ident is None:
            thread.start()
        if on_progress is not None:
            on_progress(done, res)

    try:
        yield on_slot
    finally:
        if thread.ident is not None:
            thread.join()


_PRELOADS = {"active": 0, "interval_before": 0.0}  # preloads under way in this process, and the interval before them
_PRELOADS_LOCK = threading.Lock()


def _preload_politely(figures: bool | Collection[str]) -> None:
    """:func:`~surfelslam.viz.run_report.preload_figure_modules` with the thread switch interval at
    :data:`PRELOAD_SWITCH_INTERVAL_S` meanwhile (it only changes how soon the GIL changes hands: no result does); the
    interval from before the first of overlapping preloads (runs in threads) is set again when the last one ends.
    Runs at a lower priority (:data:`PRELOAD_NICE`)."""
    lower_thread_priority(PRELOAD_NICE)
    with _PRELOADS_LOCK:
        if _PRELOADS["active"] == 0:
            _PRELOADS["interval_before"] = sys.getswitchinterval()
            sys.setswitchinterval(min(_PRELOADS["interval_before"], PRELOAD_SWITCH_INTERVAL_S))
        _PRELOADS["active"] += 1
    try:
        preload_figure_modules(figures)
    finally:
        with _PRELOADS_LOCK:
            _PRELOADS["active"] -= 1
            if _PRELOADS["active"] == 0:
                sys.setswitchinterval(_PRELOADS["interval_before"])


@dataclass
class FolderRun:
    """What :func:`run_folder` made: the run's metrics, and the mesh and Rerun recording when asked for."""

    metrics: dict
    mesh: Any = None  # surfelslam.slam.run_mesh.MeshResult
    export: Any = None  # (surfelslam.viz.rerun_export.ExportSummary, notes)


def run_folder(source: str | Path, out_dir: str | Path, cfg: SlamConfig, *, poses: str | None = None,
               map_dir: str | Path | None = None, localize_only: bool = False, record: str | Path | None = None,
               mesh: bool = False, rerun: bool = False, viewer: Callable[[RGBDSequence], Any] | None = None,
               **kwargs: Any) -> FolderRun:
    """``surfelslam run`` without its printing: open ``source`` with ``cfg.dataset`` (``record``: the live camera,
    its frames also written to this bag), continue from the map of ``map_dir`` if given, run (:func:`run_sequence`;
    ``kwargs``: its ``overwrite``, ``progress``, ``figures``, ``on_start``, ``formats``, ``started_perf_s``), and with
    ``mesh`` / ``rerun`` also write ``mesh.ply`` (TSDF, default settings, the run's depth range) / ``run.rrd`` into
    the staging folder before the hand-over, so that an interrupted run leaves neither half written.
    ``viewer(seq)``: the live viewer's ``on_frame`` callback for the opened sequence (``None``: none). Everything is
    checked before the run starts. The modules of the options not taken (the mesh's TSDF, Rerun, the camera) are not
    imported: a run's start does not pay for them."""
    check_map_options(cfg.tracker, map_dir, localize_only, poses)  # before reading a large map
    prior = None if map_dir is None else load_map(map_dir)
    if rerun:
        from surfelslam.viz.rerun_export import require_rerun

        require_rerun()  # before the run, not after it
    if record is None:
        seq = _open_sequence(source, cfg.dataset)
    else:
        from surfelslam.datasets.realsense import open_realsense

        seq = open_realsense(cfg.dataset, record, path=source)
    made = FolderRun({})

    def before_commit(stage: Path) -> None:
        if mesh:
            from surfelslam.mapping.mesh import MeshConfig
            from surfelslam.slam.run_mesh import mesh_run

            made.mesh = mesh_run(stage, MeshConfig(), sequence=Path(str(seq.root)),
                                 progress=tsdf_bar if kwargs.get("progress", True) else None, run_depth_range=True)
        if rerun:
            from surfelslam.viz.run_export import export_run

            made.export = export_run(stage, seq=seq)

    try:
        made.metrics = run_sequence(seq, out_dir, cfg, None, poses, prior_map=prior, localize_only=localize_only,
                                    before_commit=before_commit if mesh or rerun else None,
                                    on_frame=None if viewer is None else viewer(seq), **kwargs)
    finally:
        if hasattr(seq, "close"):  # a bag, a live camera (and its recording)
            seq.close()
    return made


def tsdf_bar(positions):
    """The frame positions fused into a mesh's TSDF, with a progress bar."""
    from tqdm import tqdm

    return tqdm(positions, unit="frame", leave=False, desc="tsdf")


@contextmanager
def progress_bar(total: int, show: bool):
    """An ``on_progress`` callback drawing a tqdm bar of ``total`` frames (FPS and map size every
    :data:`PROGRESS_EVERY` frames), or ``None`` when not ``show``."""
    if not show:
        yield None
        return
    from tqdm import tqdm

    bar = tqdm(total=total, unit="frame", dynamic_ncols=True, leave=False)
    t_start = time.perf_counter()

    def on_progress(done: int, res: FrameResult | None) -> None:
        bar.update(1)
        if res is not None and done % PROGRESS_EVERY == 0:
            bar.set_postfix(fps=f"{done / max(time.perf_counter() - t_start, 1e-9):.1f}", pts=f"{res.map_points:,}")

    try:
        yield on_progress
    finally:
        bar.close()


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
    from surfelslam.eval.metrics import evaluate as evaluate_trajectories  # evo: imported when first needed

    est = estimate if isinstance(estimate, Trajectory) else read_tum(estimate)
    gt = ground_truth if isinstance(ground_truth, Trajectory) else read_tum(ground_truth)
    return evaluate_trajectories(est, gt, max_diff_s)
