"""The live viewer: `run --viewer save=FILE` writes a recording Rerun's own CLI verifies; logging never blocks
tracking (a full queue drops images and maps, never poses); without rerun-sdk the run goes on after one line."""

from __future__ import annotations

import builtins
import re
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from typer.testing import CliRunner

from surfelslam.cli import app
from surfelslam.errors import ConfigError
from surfelslam.synth.writer import generate_sequence
from surfelslam.types import Intrinsics, RGBDFrame, Trajectory
from surfelslam.viz.live import MISSING_RERUN, LiveViewer, LiveViewerConfig, map_snapshot, parse_viewer

runner = CliRunner()


@pytest.fixture(scope="module")
def seq_dir(tmp_path_factory) -> Path:
    return generate_sequence(tmp_path_factory.mktemp("live") / "seq", "room", "slow", 12, "kinect", 0, 160, 120)


def test_viewer_specs():
    assert parse_viewer("spawn").mode == "spawn"
    assert parse_viewer("connect").url() == "rerun+http://127.0.0.1:9876/proxy"
    assert parse_viewer("connect=10.0.0.5:9877").url() == "rerun+http://10.0.0.5:9877/proxy"
    assert parse_viewer("connect=rerun+http://h:1/proxy").url() == "rerun+http://h:1/proxy"
    assert parse_viewer("serve").mode == "serve"
    assert parse_viewer("save=out/x.rrd").target == "out/x.rrd"
    for bad in ("show", "save", "save=", "spawn=1"):
        with pytest.raises(ConfigError, match="--viewer"):
            parse_viewer(bad)


def test_missing_rerun_is_one_line_and_the_run_goes_on(seq_dir, tmp_path, monkeypatch):
    real_import = builtins.__import__

    def no_rerun(name, *args, **kwargs):
        if name == "rerun" or name.startswith("rerun."):
            raise ImportError("no rerun here")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_rerun)
    out = tmp_path / "run"
    res = runner.invoke(app, ["run", str(seq_dir), "--out", str(out), "--no-progress", "--no-figures", "--end", "3",
                              "--viewer", "spawn"])
    assert res.exit_code == 0, res.output
    assert [ln for ln in res.output.splitlines() if "rerun-sdk" in ln] == [MISSING_RERUN]
    assert (out / "trajectory.txt").is_file()


def test_bad_viewer_spec_stops_before_the_run(seq_dir, tmp_path):
    res = runner.invoke(app, ["run", str(seq_dir), "--out", str(tmp_path / "r"), "--viewer", "show"])
    assert res.exit_code == 2 and "--viewer" in res.output and not (tmp_path / "r").exists()


def _rows_per_entity(cli: Path, rrd: Path) -> dict[str, int]:
    out = subprocess.run([str(cli), "rrd", "print", str(rrd)], capture_output=True, text=True, check=True).stdout
    rows: dict[str, int] = {}
    for m in re.finditer(r"with (\d+) rows .*? - (/\S+) - data columns", out):
        rows[m.group(2)] = rows.get(m.group(2), 0) + int(m.group(1))
    return rows


def test_run_with_viewer_save_writes_a_verified_recording(seq_dir, tmp_path):
    pytest.importorskip("rerun", reason="rerun-sdk (the `viz` extra) is not installed")
    cli = Path(sys.executable).parent / "rerun"
    if not cli.is_file():
        pytest.skip(f"rerun CLI not found beside {sys.executable}")
    rrd, out = tmp_path / "live.rrd", tmp_path / "run"
    res = runner.invoke(app, ["run", str(seq_dir), "--out", str(out), "--no-progress", "--no-figures",
                              "--viewer", f"save={rrd}", "--viewer-images-every", "4", "--viewer-map-every", "5"])
    assert res.exit_code == 0, res.output
    assert "live viewer -> the recording" in res.output and "12 poses, 3 image pairs" in res.output
    subprocess.run([str(cli), "rrd", "verify", str(rrd)], capture_output=True, check=True)
    rows = _rows_per_entity(cli, rrd)
    assert rows["/world/camera"] == 12  # one pose per frame
    assert rows["/world/camera/image/rgb"] == 3 and rows["/world/camera/image/depth"] == 3
    assert rows["/world/map"] == 3 + 1  # frames 0, 5, 10, then the final map
    assert rows["/world/estimate"] >= 2 and rows["/plots/ate_m"] == 12 and "/world/ground_truth" in rows
    assert rows["/world/camera/image"] == 1  # the pinhole, static


# --- the logging thread, with a stand-in for rerun ----------------------------------------------------------------

class _Archetype:
    def __init__(self, *args, **kwargs):
        self.args, self.kwargs = args, kwargs

    def compress(self, **kwargs):
        return self


class _Columnar(_Archetype):
    @staticmethod
    def columns(**kwargs):
        return {k: np.asarray(v) for k, v in kwargs.items()}


def _time_column(name, **kwargs):
    return name, np.asarray(next(iter(kwargs.values())))


FAKE_RR = SimpleNamespace(ViewCoordinates=SimpleNamespace(RDF="RDF"), Pinhole=_Archetype, Transform3D=_Columnar,
                          Scalars=_Columnar, LineStrips3D=_Archetype, Image=_Archetype, DepthImage=_Archetype,
                          Points3D=_Archetype, TimeColumn=_time_column, EncodedImage=_Archetype)


class SlowRecording:
    """Records what is logged; logging an image takes ``image_s`` (a viewer that falls behind)."""

    def __init__(self, image_s: float = 0.0):
        self.image_s = image_s
        self.logged: list[tuple[str, object]] = []
        self.time: dict[str, float] = {}

    def log(self, path, obj, static=False):
        if path.endswith("/rgb"):
            time.sleep(self.image_s)
        self.logged.append((path, obj))

    def send_columns(self, path, indexes, columns):
        frames = dict(indexes)["frame"]
        assert all(len(v) == len(frames) for v in columns.values())
        self.logged.append((path, {"frame": frames, **columns}))

    def column(self, path: str, name: str) -> np.ndarray:
        """A column sent to ``path``, its batches concatenated."""
        return np.concatenate([o[name] for o in self.paths(path)])

    def set_time(self, timeline, sequence=None, duration=None):
        self.time[timeline] = sequence if sequence is not None else duration

    def flush(self, timeout_sec=None):
        pass

    def disconnect(self):
        pass

    def paths(self, path: str) -> list:
        return [o for p, o in self.logged if p == path]


INTR = Intrinsics(50.0, 50.0, 15.5, 11.5, 32, 24)


def _frame(k: int) -> RGBDFrame:
    return RGBDFrame(k, k / 30, np.zeros((24, 32, 3), np.uint8), np.ones((24, 32), np.float32))


def _result(k: int):
    T = np.eye(4)
    T[0, 3] = 0.01 * k
    return SimpleNamespace(T_world_cam=T, map_points=100 * k)


def test_a_full_queue_drops_images_not_poses_and_never_blocks():
    rec = SlowRecording(image_s=0.02)
    viewer = LiveViewer(FAKE_RR, rec, parse_viewer("save=x.rrd"), INTR,
                        cfg=LiveViewerConfig(images_every=1, map_every=1000, queue_size=2))
    worst = 0.0
    for k in range(60):
        t0 = time.perf_counter()
        viewer.on_frame(_frame(k), _result(k))
        worst = max(worst, time.perf_counter() - t0)
    stats = viewer.close()
    assert worst < 0.015  # never waits for the 20 ms image logging
    assert stats.images_dropped > 0 and stats.images_logged + stats.images_dropped == 60
    assert list(rec.column("world/camera", "frame")) == list(range(60))  # every pose, in batches
    assert rec.column("world/camera", "translation")[:, 0] == pytest.approx(np.arange(60) * 0.01)
    assert len(rec.paths("world/camera")) < 60 / LiveViewerConfig().path_every + 2


def test_poses_go_in_bounded_batches():
    """Poses, plots and path: one send per `path_every` frames (the rest at close), not a few calls per frame."""
    rec = SlowRecording()
    viewer = LiveViewer(FAKE_RR, rec, parse_viewer("save=x.rrd"), INTR,
                        cfg=LiveViewerConfig(images_every=1000, map_every=1000, path_every=4, queue_size=64))
    for k in range(10):
        viewer.on_frame(_frame(k), _result(k))
    viewer.close()
    assert [len(b["frame"]) for b in rec.paths("world/camera")] == [4, 4, 2]
    assert list(rec.column("plots/map_points", "scalars")) == [100.0 * k for k in range(10)]
    assert len(rec.paths("world/estimate")) == 3 and len(rec.paths("world/estimate")[-1].args[0][0]) == 10


class _FakeMap:
    def __init__(self, n: int):
        self.position = np.arange(n * 3, dtype=np.float32).reshape(n, 3)
        self.colour = np.full((n, 3), 300.0, np.float32)
        self.dead = (np.arange(n) % 2).astype(np.uint8)
        self.n_alive = int((self.dead == 0).sum())

    def __len__(self):
        return len(self.position)


def test_map_snapshots_loops_and_ground_truth_error():
    gt_T = np.tile(np.eye(4), (20, 1, 1))
    gt_T[:, 1, 3] = 5.0  # the ground truth's world is 5 m away along y: put on the first estimated pose
    gt_T[:, 0, 3] = 0.02 * np.arange(20)  # and it moves twice as fast: error 0.01 m per frame
    gt = Trajectory(np.arange(20) / 30, gt_T)
    sparse = SimpleNamespace(loops_accepted=[], keyframe_frame_indices=lambda: np.array([0, 4, 8]))
    tracker = SimpleNamespace(map=_FakeMap(1000), sparse=sparse)
    rec = SlowRecording()
    viewer = LiveViewer(FAKE_RR, rec, parse_viewer("save=x.rrd"), INTR, gt,
                        cfg=LiveViewerConfig(images_every=100, map_every=5, map_max_points=100, queue_size=64))
    for k in range(10):
        if k == 9:
            sparse.loops_accepted = [(0, 2, 50)]  # keyframes 0 and 2: frames 0 and 8
        viewer.on_frame(_frame(k), _result(k), tracker)
    stats = viewer.close()
    maps = rec.paths("world/map")
    assert stats.maps_logged == 2 and len(maps) == 2
    xyz = maps[0].args[0]
    assert 0 < len(xyz) <= 100 and maps[0].kwargs["colors"].max() == 255  # subsampled, dead dropped, clipped
    loops = rec.paths("world/loops")
    assert stats.loops == 1 and np.allclose(loops[-1].args[0][0], [[0, 0, 0], [0.08, 0, 0]])
    err = rec.column("plots/ate_m", "scalars")
    assert list(rec.column("plots/ate_m", "frame")) == list(range(10))
    assert err == pytest.approx(0.01 * np.arange(10), abs=1e-9)
    assert len(rec.paths("world/ground_truth")) == 1


def test_map_snapshot_of_a_tracker_without_surfels():
    assert map_snapshot(SimpleNamespace(), 10) is None


def test_connect_to_nothing_is_refused_up_front():
    """`--viewer connect=...` with no viewer listening: start_viewer warns in one line instead of the SDK retrying
    (and failing at the end of the run)."""
    from surfelslam.viz.live import _require_listening

    with pytest.raises(ConnectionError, match="nothing"):
        _require_listening("rerun+http://127.0.0.1:1/proxy", "nothing listens", wait_s=0.0)


def test_jpeg_keeps_the_colours():
    """The live view's JPEG (OpenCV, RGB in): decoded, the same colours within JPEG error."""
    import cv2

    from surfelslam.viz.live import jpeg

    rgb = np.zeros((24, 32, 3), np.uint8)
    rgb[..., 0], rgb[:, 16:, 2] = 200, 120  # red everywhere, blue on the right half
    back = cv2.cvtColor(cv2.imdecode(np.frombuffer(jpeg(rgb), np.uint8), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    assert np.abs(back[:, 2:12].astype(int) - rgb[:, 2:12]).max() <= 8
    assert np.abs(back[:, 20:30].astype(int) - rgb[:, 20:30]).max() <= 8
