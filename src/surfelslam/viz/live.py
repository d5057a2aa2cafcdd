"""The live Rerun view of a run (``surfelslam run SEQ --viewer spawn|connect[=ADDR]|serve|save=FILE``).

The run loop calls :meth:`LiveViewer.on_frame` after each tracked frame, on the tracking thread. That call only takes
references and small copies (the pose; every ``images_every`` frames the frame's images; every ``map_every`` frames a
subsampled copy of the map) and hands them to a background thread through a bounded queue; when the queue is full
the images and map of that frame are dropped (counted), never the poses, and tracking never waits. The background
thread converts and logs (Rerun batches and sends from its own threads): the poses, plots and path go as column
batches of ``path_every`` frames (one call per entity instead of a few per frame), the colour image as a JPEG
encoded by OpenCV (a tenth of the CPU of rerun-sdk's encoder, without the GIL), so that the view costs little of
the CPU the tracking shares (``make bench``'s viewer section: issue 36 allows 10 % of FPS).

What is shown (entity paths and colours as in :mod:`surfelslam.viz.rerun_export`; ``world`` is the run's frame, the
first camera's: x right, y down, z forward):

* ``world/camera``: the estimated pose at each frame (timelines ``frame`` and ``time``; sent every ``path_every``
  frames), with a pinhole of the run's camera at ``world/camera/image`` and the colour (JPEG) and depth images
  every ``images_every`` frames;
* ``world/estimate``: the path so far, every ``path_every`` frames;
* ``world/map``: the map's points, every ``map_every`` frames, subsampled to at most ``map_max_points`` (a new
  snapshot replaces the previous one on the timeline: the map is not re-sent each frame);
* ``world/loops``: accepted loop edges (trackers with a sparse back end), when one is added;
* ``world/ground_truth`` and ``plots/ate_m``: with ground truth, its path put on the first estimated pose, and each
  frame's position error against it (m; no other alignment, so it grows with drift);
* ``plots/map_points``: the map's size.

At the end (:meth:`LiveViewer.close` with the run folder) the final trajectory (loop-corrected for the trackers
with a pose graph), the final map and the loop edges are logged at the last frame. Needs the optional
``rerun-sdk``; without it :func:`start_viewer` prints one line and the run goes on without a view.
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from surfelslam.types import Intrinsics, RGBDFrame, Trajectory
from surfelslam.viz.live_spec import (  # noqa: F401 - re-exported: the viewer's one import for callers
    DEFAULT_CONNECT,
    MODES,
    LiveViewerConfig,
    ViewerSpec,
    parse_viewer,
)
from surfelslam.viz.rerun_export import (
    DEPTH_UNITS_PER_M,
    ESTIMATE_RGB,
    GROUND_TRUTH_RGB,
    LINE_RADIUS_M,
    LOOP_RGB,
    POINT_RADIUS_M,
    RGB_JPEG_QUALITY,
)

MISSING_RERUN = "the live viewer needs rerun-sdk: pip install 'surfelslam[viz]'"
#: The largest depth a uint16 depth image holds, in its units (:data:`DEPTH_UNITS_PER_M` per metre).
DEPTH_MAX_UNITS = np.iinfo(np.uint16).max
#: Ground-truth association tolerance for the per-frame error (s), as the evaluation's.
GT_MAX_DT_S = 0.02


@dataclass
class ViewerStats:
    """What the viewer did: frames seen, image pairs and map snapshots logged or dropped (queue full)."""

    frames: int = 0
    images_logged: int = 0
    images_dropped: int = 0
    maps_logged: int = 0
    maps_dropped: int = 0
    loops: int = 0
    error: str | None = None
    #: seconds spent in :meth:`LiveViewer.on_frame` (on the tracking thread), and CPU seconds of the logging thread
    on_frame_s: float = 0.0
    logging_cpu_s: float = 0.0


@dataclass
class _Item:
    poses: list[tuple[int, float, np.ndarray, int]] = field(default_factory=list)  # (k, t, T, map points)
    k: int = 0
    rgb: np.ndarray | None = None
    depth_m: np.ndarray | None = None
    map_xyz: np.ndarray | None = None
    map_rgb: np.ndarray | None = None
    loops: list[tuple[int, int]] | None = None


def jpeg(rgb: np.ndarray, quality: int = RGB_JPEG_QUALITY) -> bytes:
    """``rgb`` (H, W, 3) uint8 as JPEG bytes, by OpenCV: about a tenth of the CPU of rerun-sdk's
    ``Image.compress`` at 320x240, and it releases the GIL while encoding (the tracking thread is not held up)."""
    import cv2

    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise ValueError("JPEG encoding failed")
    return buf.tobytes()


def map_snapshot(tracker, max_points: int) -> tuple[np.ndarray, np.ndarray] | None:
    """A subsampled copy of the tracker's surfel map: ``(positions (M, 3) float32, colours (M, 3) uint8)`` with
    ``M <= max_points``, or ``None`` for trackers without a surfel map (``orb``). Cheap: a strided slice."""
    m = getattr(tracker, "map", None)
    if m is None or not hasattr(m, "position"):
        return None
    n = len(m)
    if n == 0:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8)
    step = max(1, -(-m.n_alive // max_points))
    alive = m.dead[::step] == 0
    return m.position[::step][alive], np.clip(m.colour[::step][alive], 0, 255).astype(np.uint8)


def loop_frames(tracker) -> list[tuple[int, int]] | None:
    """Accepted loop edges as pairs of frame indices (trackers with a sparse back end), else ``None``."""
    sparse = getattr(tracker, "sparse", None)
    if sparse is None or not hasattr(sparse, "loops_accepted"):
        return None
    loops = list(sparse.loops_accepted)
    if not loops:
        return []
    kf = sparse.keyframe_frame_indices()
    return [(int(kf[i]), int(kf[j])) for i, j, *_ in loops if i < len(kf) and j < len(kf)]


class LiveViewer:
    """Logs a run to Rerun while it runs (module docstring). Use :func:`start_viewer` to make one."""

    def __init__(self, rr, rec, spec: ViewerSpec, intrinsics: Intrinsics, ground_truth: Trajectory | None = None,
                 cfg: LiveViewerConfig | None = None):
        self.rr, self.rec, self.spec = rr, rec, spec
        self.intrinsics = intrinsics
        self.ground_truth = ground_truth if ground_truth is not None and len(ground_truth) else None
        self.cfg = cfg or LiveViewerConfig()
        self.stats = ViewerStats()
        self._q: queue.Queue[_Item | None] = queue.Queue(maxsize=self.cfg.queue_size)
        self._pending: list[tuple[int, float, np.ndarray, int]] = []
        self._pending_loops: list[tuple[int, int]] | None = None
        self._n_loops = 0
        self._closed = False
        # worker state
        self._t0: float | None = None
        self._positions: dict[int, np.ndarray] = {}
        self._path: list[np.ndarray] = []
        self._rows: list[tuple[int, float, np.ndarray, int]] = []  # received, not yet sent (< path_every)
        self._T_align: np.ndarray | None = None
        self._loops: list[tuple[int, int]] = []
        self._log_static()
        self._thread = threading.Thread(target=self._work, name="surfelslam-viewer", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------------------------- tracking thread
    def __call__(self, frame: RGBDFrame, result, tracker=None) -> None:
        self.on_frame(frame, result, tracker)

    def on_frame(self, frame: RGBDFrame, result, tracker=None) -> None:
        """Queue what frame ``frame`` shows (its result's pose; images / map / loops when due); never blocks."""
        if self._closed or self.stats.error is not None:
            return
        t_in = time.perf_counter()
        try:
            self._on_frame(frame, result, tracker)
        finally:
            self.stats.on_frame_s += time.perf_counter() - t_in

    def _on_frame(self, frame: RGBDFrame, result, tracker) -> None:
        k = self.stats.frames
        self.stats.frames += 1
        self._pending.append((k, float(frame.timestamp), np.array(result.T_world_cam, np.float64),
                              int(getattr(result, "map_points", 0))))
        item = _Item(k=k)
        if k % self.cfg.images_every == 0:
            item.rgb, item.depth_m = frame.rgb, frame.depth_m
        if k % self.cfg.map_every == 0 and tracker is not None:
            snap = map_snapshot(tracker, self.cfg.map_max_points)
            if snap is not None:
                item.map_xyz, item.map_rgb = snap
        if tracker is not None:
            sparse = getattr(tracker, "sparse", None)
            n = len(getattr(sparse, "loops_accepted", ()) or ()) if sparse is not None else 0
            if n > self._n_loops:
                self._n_loops = n
                self._pending_loops = loop_frames(tracker)
        item.poses, item.loops = self._pending, self._pending_loops
        try:
            self._q.put_nowait(item)
        except queue.Full:
            self.stats.images_dropped += item.rgb is not None
            self.stats.maps_dropped += item.map_xyz is not None
            return  # the poses and loops stay pending for the next frame
        self._pending, self._pending_loops = [], None

    # ------------------------------------------------------------------------------------- end
    def close(self, run_dir: Path | None = None, timeout_s: float = 60.0) -> ViewerStats:
        """Send what is pending, stop the thread, log the run's final trajectory, map and loops from ``run_dir``
        (a finished run folder) when given, and flush. Returns the stats."""
        if self._closed:
            return self.stats
        self._closed = True
        if self._pending or self._pending_loops:
            try:
                self._q.put(_Item(poses=self._pending, k=self._pending[-1][0] if self._pending else 0,
                                  loops=self._pending_loops), timeout=timeout_s)
            except queue.Full:
                pass
        self._pending = []
        try:
            self._q.put(None, timeout=timeout_s)
        except queue.Full:
            pass
        self._thread.join(timeout_s)
        if run_dir is not None and self.stats.error is None:
            try:
                self._log_final(Path(run_dir))
            except Exception as exc:  # noqa: BLE001 - the view must not fail the run
                self.stats.error = f"{type(exc).__name__}: {exc}"
        try:
            try:
                self.rec.flush(timeout_sec=timeout_s)
            except TypeError:  # older rerun-sdk: flush(blocking=True)
                self.rec.flush()
            if self.spec.mode != "serve":  # a served view stays up until the process ends
                self.rec.disconnect()
        except Exception as exc:  # noqa: BLE001 - e.g. the viewer went away: the run's outputs are written anyway
            self.stats.error = self.stats.error or f"{type(exc).__name__}: {exc}"
        return self.stats

    # ------------------------------------------------------------------------------------- logging thread
    def _log_static(self) -> None:
        rr, rec, intr = self.rr, self.rec, self.intrinsics
        rec.log("world", rr.ViewCoordinates.RDF, static=True)
        rec.log("world/camera/image", rr.Pinhole(image_from_camera=intr.K, resolution=[intr.width, intr.height],
                                                 camera_xyz=rr.ViewCoordinates.RDF), static=True)

    def _work(self) -> None:
        cpu0 = time.thread_time()
        while True:
            item = self._q.get()
            self.stats.logging_cpu_s = time.thread_time() - cpu0
            if item is None:
                if self.stats.error is None:
                    try:
                        self._send_rows()  # the last, partial batch
                    except Exception as exc:  # noqa: BLE001 - a failing view stops logging, not the run
                        self.stats.error = f"{type(exc).__name__}: {exc}"
                self.stats.logging_cpu_s = time.thread_time() - cpu0
                return
            if self.stats.error is not None:
                continue  # drain
            try:
                self._log_item(item)
            except Exception as exc:  # noqa: BLE001 - a failing view stops logging, not the run
                self.stats.error = f"{type(exc).__name__}: {exc}"

    def _set_time(self, k: int, t: float) -> None:
        if self._t0 is None:
            self._t0 = t
        self.rec.set_time("frame", sequence=k)
        self.rec.set_time("time", duration=t - self._t0)

    def _log_item(self, item: _Item) -> None:
        rr, rec = self.rr, self.rec
        for k, t, T, _ in item.poses:
            if self._t0 is None:
                self._t0 = t
            self._positions[k] = T[:3, 3].copy()
            self._path.append(T[:3, 3].copy())
        self._rows += item.poses
        if len(self._rows) >= self.cfg.path_every:
            self._send_rows()
        if not item.poses:
            return
        self._set_time(item.k, next((t for k, t, _, _ in item.poses if k == item.k), item.poses[-1][1]))
        if item.rgb is not None and item.depth_m is not None:
            rec.log("world/camera/image/rgb", rr.EncodedImage(contents=jpeg(item.rgb), media_type="image/jpeg"))
            depth = np.where(np.isfinite(item.depth_m), item.depth_m, 0.0) * DEPTH_UNITS_PER_M
            rec.log("world/camera/image/depth",
                    rr.DepthImage(np.clip(np.round(depth), 0, DEPTH_MAX_UNITS).astype(np.uint16),
                                  meter=DEPTH_UNITS_PER_M))
            self.stats.images_logged += 1
        if item.map_xyz is not None:
            rec.log("world/map", rr.Points3D(item.map_xyz, colors=item.map_rgb, radii=POINT_RADIUS_M))
            self.stats.maps_logged += 1
        if item.loops is not None:
            self._loops = list(item.loops)
            self._log_loops()

    def _log_loops(self) -> None:
        segs = [(self._positions[a], self._positions[b]) for a, b in self._loops
                if a in self._positions and b in self._positions]
        self.stats.loops = len(segs)
        if segs:
            self.rec.log("world/loops", self.rr.LineStrips3D(np.asarray(segs, np.float64), colors=[LOOP_RGB],
                                                             radii=LINE_RADIUS_M))

    def _send_rows(self) -> None:
        """The pending frames' poses, map sizes and errors as one column batch per entity (one call each instead
        of a few per frame: Rerun's per-call cost dominated the logging thread), then the path so far."""
        rows, self._rows = self._rows, []
        if not rows:
            return
        rr, rec = self.rr, self.rec
        ks = np.array([r[0] for r in rows], np.int64)
        ts = np.array([r[1] for r in rows], np.float64)
        T = np.stack([r[2] for r in rows])
        assert self._t0 is not None
        index = [rr.TimeColumn("frame", sequence=ks), rr.TimeColumn("time", duration=ts - self._t0)]
        rec.send_columns("world/camera", index, rr.Transform3D.columns(translation=T[:, :3, 3], mat3x3=T[:, :3, :3]))
        rec.send_columns("plots/map_points", index,
                         rr.Scalars.columns(scalars=np.array([r[3] for r in rows], np.float64)))
        if self.ground_truth is not None:
            self._send_errors(ks, ts, T)
        self._set_time(int(ks[-1]), float(ts[-1]))
        rec.log("world/estimate", rr.LineStrips3D([np.asarray(self._path)], colors=[ESTIMATE_RGB],
                                                  radii=LINE_RADIUS_M))

    def _send_errors(self, ks: np.ndarray, ts: np.ndarray, T: np.ndarray) -> None:
        """Each frame's position error against the ground truth, put on the first estimated pose that has one."""
        gt = self.ground_truth
        assert gt is not None and self._t0 is not None
        T_gt, valid = gt.lookup(ts, GT_MAX_DT_S)
        if not valid.any():
            return
        if self._T_align is None:
            from surfelslam.geometry import se3

            i = int(np.argmax(valid))
            self._T_align = T[i] @ se3.invert(T_gt[i])
            pts = (self._T_align[:3, :3] @ gt.positions.T).T + self._T_align[:3, 3]
            self.rec.log("world/ground_truth", self.rr.LineStrips3D([pts], colors=[GROUND_TRUTH_RGB],
                                                                    radii=LINE_RADIUS_M), static=True)
        p_gt = T_gt[valid][:, :3, 3] @ self._T_align[:3, :3].T + self._T_align[:3, 3]
        err = np.linalg.norm(T[valid][:, :3, 3] - p_gt, axis=1)
        index = [self.rr.TimeColumn("frame", sequence=ks[valid]),
                 self.rr.TimeColumn("time", duration=ts[valid] - self._t0)]
        self.rec.send_columns("plots/ate_m", index, self.rr.Scalars.columns(scalars=err))

    def _log_final(self, run_dir: Path) -> None:
        """The finished run's trajectory, map and loop edges, at the last frame."""
        import json

        from surfelslam.io.ply import read_ply
        from surfelslam.io.trajectory import read_tum

        rr, rec = self.rr, self.rec
        traj_path = run_dir / "trajectory.txt"
        if not traj_path.is_file() or self._t0 is None:
            return
        est = read_tum(traj_path)
        if len(est) == 0:
            return
        self._set_time(self.stats.frames - 1, float(est.timestamps[-1]))
        rec.log("world/estimate", rr.LineStrips3D([est.positions], colors=[ESTIMATE_RGB], radii=LINE_RADIUS_M))
        ply = run_dir / "map.ply"
        if ply.is_file():
            v = read_ply(ply)
            if all(c in v for c in "xyz"):
                xyz = np.stack([v["x"], v["y"], v["z"]], axis=1).astype(np.float32)
                step = max(1, -(-len(xyz) // self.cfg.map_max_points))
                rgb = (np.stack([v["red"], v["green"], v["blue"]], axis=1).astype(np.uint8)[::step]
                       if all(c in v for c in ("red", "green", "blue")) else None)
                rec.log("world/map", rr.Points3D(xyz[::step], colors=rgb, radii=POINT_RADIUS_M))
                self.stats.maps_logged += 1
        metrics = run_dir / "metrics.json"
        if metrics.is_file():
            edges = json.loads(metrics.read_text()).get("loop_edges") or []
            if edges:
                segs = []
                for ta, tb in edges:
                    i, j = (int(np.argmin(np.abs(est.timestamps - float(x)))) for x in (ta, tb))
                    segs.append((est.positions[i], est.positions[j]))
                rec.log("world/loops", rr.LineStrips3D(np.asarray(segs), colors=[LOOP_RGB], radii=LINE_RADIUS_M))
                self.stats.loops = len(segs)


def _require_listening(url: str, why: str, wait_s: float = 3.0) -> None:
    """ConnectionError(``why``) unless a TCP connection to ``url``'s host and port opens within ``wait_s``."""
    import socket
    from urllib.parse import urlsplit

    parts = urlsplit(url)
    host, port = parts.hostname or "127.0.0.1", parts.port or 9876
    deadline = time.monotonic() + wait_s
    while True:
        try:
            with socket.create_connection((host, port), timeout=1.0):
                return
        except OSError:
            if time.monotonic() >= deadline:
                raise ConnectionError(why) from None
            time.sleep(0.2)


def start_viewer(spec: ViewerSpec | str, intrinsics: Intrinsics, ground_truth: Trajectory | None = None,
                 cfg: LiveViewerConfig | None = None, warn: Callable[[str], None] = print,
                 application_id: str = "surfelslam", recording_id: str | None = None) -> LiveViewer | None:
    """A :class:`LiveViewer` sending to ``spec``, or ``None`` (after one ``warn`` line) when rerun-sdk is missing
    or the sink cannot be opened: the run then goes on without a view. A bad ``spec`` is a ConfigError."""
    spec = parse_viewer(spec) if isinstance(spec, str) else spec
    try:
        import rerun as rr
    except ImportError:
        warn(MISSING_RERUN)
        return None
    rec = rr.RecordingStream(application_id, recording_id=recording_id or time.strftime("run-%Y%m%d-%H%M%S"))
    try:
        if spec.mode == "save":
            path = Path(spec.target or "run.rrd")
            path.parent.mkdir(parents=True, exist_ok=True)
            rec.save(path)
        elif spec.mode == "spawn":
            import sys

            beside = Path(sys.executable).parent / "rerun"  # the viewer the rerun-sdk wheel installs
            rr.spawn(connect=False, executable_path=str(beside) if beside.is_file() else None)
            _require_listening(DEFAULT_CONNECT, "the spawned viewer is not listening (no display?)")
            rec.connect_grpc(DEFAULT_CONNECT)
        elif spec.mode == "connect":
            _require_listening(spec.url(), "nothing listens there (start `rerun` first)")
            rec.connect_grpc(spec.url())
        else:
            url = rec.serve_grpc()
            if hasattr(rr, "serve_web_viewer"):
                rr.serve_web_viewer(open_browser=False, connect_to=url)
                warn(f"live viewer: open the web viewer it serves (http://localhost:9090), showing {url}")
            else:  # pragma: no cover - older rerun-sdk
                warn(f"live viewer: connect a Rerun viewer to {url}")
    except Exception as exc:  # noqa: BLE001 - no viewer binary, no display, unwritable file ...
        first = (str(exc).strip().splitlines() or [""])[0]
        warn(f"live viewer: cannot open {spec.describe()} ({type(exc).__name__}: {first}); running without it")
        try:
            rec.disconnect()
        except Exception:  # noqa: BLE001, S110
            pass
        return None
    return LiveViewer(rr, rec, spec, intrinsics, ground_truth, cfg)


# ------------------------------------------------------------------------------------------------ for `surfelslam run`
def viewer_for_run(spec_text: str | None, seq, images_every: int = 5, map_every: int = 30,
                   warn: Callable[[str], None] = print) -> LiveViewer | None:
    """The live viewer ``--viewer`` asks for, on ``seq``'s camera and ground truth (``None``: no ``--viewer``, or
    rerun-sdk missing / the sink unavailable, after one ``warn`` line). A malformed ``--viewer`` is a ConfigError
    (raised before the run starts)."""
    if spec_text is None:
        return None
    spec = parse_viewer(spec_text)
    cfg = LiveViewerConfig(images_every=images_every, map_every=map_every)
    return start_viewer(spec, seq.intrinsics, getattr(seq, "ground_truth", None), cfg, warn=warn,
                        recording_id=Path(str(seq.root)).name or None)


def finish_viewer(viewer: LiveViewer | None, run_dir: Path | None, warn: Callable[[str], None] = print,
                  wait_when_serving: bool | None = None) -> ViewerStats | None:
    """Close ``viewer`` (logging the finished run in ``run_dir`` when given) and say in one line what it logged. A
    served view stays up until Ctrl-C when ``wait_when_serving`` (default: when stdin is a terminal)."""
    if viewer is None:
        return None
    stats = viewer.close(run_dir)
    dropped = stats.images_dropped + stats.maps_dropped
    warn(f"live viewer -> {viewer.spec.describe()}: {stats.frames} poses, {stats.images_logged} image pairs, "
         f"{stats.maps_logged} map snapshots" + (f", {stats.loops} loop edges" if stats.loops else "")
         + (f" ({1e3 * stats.on_frame_s / max(stats.frames, 1):.2f} ms per frame on the tracking thread, "
            f"{1e3 * stats.logging_cpu_s / max(stats.frames, 1):.1f} ms CPU logging)")
         + (f"; {dropped} snapshots dropped (logging fell behind)" if dropped else "")
         + (f"; logging stopped: {stats.error}" if stats.error else ""))
    if viewer.spec.mode == "serve":
        import sys

        if wait_when_serving is None:
            wait_when_serving = sys.stdin is not None and sys.stdin.isatty()
        if wait_when_serving:
            warn("live viewer: still serving; Ctrl-C to stop")
            try:
                while True:
                    time.sleep(1.0)
            except KeyboardInterrupt:
                pass
        viewer.rec.disconnect()
    return stats
