"""Synthetic sequences: in-memory frames and the TUM folder layout on disk.

Layout written by :func:`generate_sequence` (TUM RGB-D conventions)::

    rgb/<t>.png        colour, 8-bit RGB PNG
    depth/<t>.png      depth, uint16 PNG, DEPTH_SCALE units per metre, 0 = invalid
    rgb.txt depth.txt  "timestamp path" lines
    associations.txt   "t rgb/<t>.png t depth/<t>.png" lines
    groundtruth.txt    "t tx ty tz qx qy qz qw" (T_world_cam)
    INFO.txt           "key : value" lines (generator, scene, intrinsics, depth scale...)

Timestamps are ``index / fps`` formatted ``%.6f``. The same arguments give byte-identical files.

With a colour offset (``colour_offset_s``, ``colour_jitter_s``) each frame's colour is rendered at its own stamp,
``depth stamp + offset + U(-jitter, jitter)``, on the trajectory interpolated there (translation linear, rotation
SLERP; extrapolated from the end intervals), as from a sensor that does not expose colour and depth together (TUM's
Kinect: up to 20 ms apart). ``rgb.txt`` then holds the colour stamps, ``depth.txt`` and ``groundtruth.txt`` the depth
stamps: the ground truth is the depth camera's.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import numpy as np

from surfelslam.errors import ConfigError
from surfelslam.geometry.interpolation import pose_between
from surfelslam.io.atomic import write_text_atomic
from surfelslam.io.images import write_png_depth, write_png_rgb
from surfelslam.io.trajectory import write_tum
from surfelslam.synth.noise import KinectNoiseConfig, frame_rng, noisy_depth, noisy_rgb
from surfelslam.synth.render import RenderOutput, render
from surfelslam.synth.scenes import Scene, make_scene
from surfelslam.synth.textures import TextureConfig
from surfelslam.synth.trajectories import make_trajectory, replay_motion
from surfelslam.types import Intrinsics, RGBDFrame, Trajectory

NOISE_MODELS = ["kinect", "kinect-distorted", "icl", "none"]
# "kinect-distorted": disparity error at the image corners (px); 0.1 px is 0.25 cm at 1 m, 1.0 cm at 2 m (the
# order of the low-frequency errors of uncalibrated Kinect v1 depth)
DISTORTED_DISPARITY_PX = 0.1
#: "icl": ICL-NUIM's synthetic depth noise. Its disparity is 35130 / z (z in cm) in steps of 1 (1/8 px of a Kinect,
#: baseline 7.5 cm, focal 585.5 px) with Gaussian noise of 1/6 step, after a bilinear lookup at 0.5 px Gaussian
#: offsets; every pixel keeps a depth (no axial noise, holes, grazing or edge dropouts).
ICL_NOISE = KinectNoiseConfig(
    min_depth_m=0.1, max_depth_m=10.0, axial_sigma_base_m=0.0, axial_sigma_quad_per_m=0.0, baseline_m=0.075,
    disparity_focal_px=585.5, disparity_step_px=0.125, disparity_sigma_px=0.125 / 6, lateral_jitter_px=0.5,
    grazing_angle_deg=90.0, edge_dropout_prob=0.0, holes_per_frame_mean=0.0)
DEPTH_SCALE = 5000.0  # raw depth units per metre (TUM)
_UINT16_MAX = 65535
_BASE_FOCAL_PX = 525.0  # default intrinsics at 640x480 (TUM / Kinect v1 defaults)
_BASE_SIZE_PX = (640, 480)
DEFAULT_FPS = 30.0
MAX_COLOUR_OFFSET_S = 0.02  # |colour offset| + jitter: the TUM reader pairs colour and depth within 20 ms
_WRITER_THREADS = 2  # background PNG writers
_MAX_QUEUED_FRAMES = 4  # frames waiting to be written (bounds memory)


def default_intrinsics(width: int = 640, height: int = 480) -> Intrinsics:
    """525/525/319.5/239.5 at 640x480, scaled to ``width`` x ``height`` (pixel centres at integers)."""
    sx = width / _BASE_SIZE_PX[0]
    sy = height / _BASE_SIZE_PX[1]
    return Intrinsics(
        _BASE_FOCAL_PX * sx, _BASE_FOCAL_PX * sy, (_BASE_SIZE_PX[0] / 2) * sx - 0.5,
        (_BASE_SIZE_PX[1] / 2) * sy - 0.5, width, height,
    )


def noise_config(name: str) -> KinectNoiseConfig | None:
    """``"kinect"`` -> default :class:`KinectNoiseConfig`; ``"kinect-distorted"`` -> the same with a fixed
    low-frequency depth distortion (:data:`DISTORTED_DISPARITY_PX`); ``"icl"`` -> ICL-NUIM's synthetic noise
    (:data:`ICL_NOISE`); ``"none"`` -> None (exact depth and colour)."""
    if name == "kinect":
        return KinectNoiseConfig()
    if name == "kinect-distorted":
        return KinectNoiseConfig(disparity_distortion_px=DISTORTED_DISPARITY_PX)
    if name == "icl":
        return ICL_NOISE
    if name == "none":
        return None
    raise ConfigError(f"unknown noise model {name!r}; known: {', '.join(NOISE_MODELS)}")


def make_frame(
    index: int, timestamp: float, rendered: RenderOutput, intr: Intrinsics, noise_cfg: KinectNoiseConfig | None,
    seed: int, colour: RenderOutput | None = None,
) -> RGBDFrame:
    """Frame ``index`` from a rendering: exact (``noise_cfg`` None: depth > 0 kept) or Kinect-like noisy.
    ``colour``: the rendering the colour comes from when it is not ``rendered`` (colour taken at another time)."""
    rgb_src = rendered.rgb if colour is None else colour.rgb
    if noise_cfg is None:
        return RGBDFrame(index, timestamp, rgb_src.copy(), rendered.depth_m.copy())
    rng = frame_rng(seed, index)
    depth = noisy_depth(rendered.depth_m, rendered.normal_cam, intr, noise_cfg, rng)
    rgb = noisy_rgb(rgb_src, noise_cfg, rng)
    return RGBDFrame(index, timestamp, rgb, depth)


def iter_frames(
    scene: Scene, trajectory: Trajectory, intr: Intrinsics, noise_cfg: KinectNoiseConfig | None = None,
    seed: int = 0, T_world_colour: np.ndarray | None = None, indices: Iterable[int] | None = None,
) -> Iterator[RGBDFrame]:
    """Render every pose of ``trajectory`` -> :class:`RGBDFrame` (index, timestamp, rgb, depth_m).
    ``T_world_colour``: ``(N, 4, 4)`` the colour camera's pose per frame when colour is taken at another time.
    ``indices``: only these frames, each the same as in the whole sequence (its noise is seeded by its index)."""
    buf: RenderOutput | None = None
    cbuf: RenderOutput | None = None
    for i in range(len(trajectory.timestamps)) if indices is None else indices:
        buf = render(scene, trajectory.T_world_cam[i], intr, out=buf)
        if T_world_colour is not None:
            cbuf = render(scene, T_world_colour[i], intr, out=cbuf)
        yield make_frame(i, float(trajectory.timestamps[i]), buf, intr, noise_cfg, seed, colour=cbuf)


def colour_stamps(depth_stamps: np.ndarray, offset_s: float, jitter_s: float, seed: int) -> np.ndarray:
    """``(N,)`` colour capture stamps: ``depth_stamps + offset_s + U(-jitter_s, jitter_s)`` (seeded)."""
    rng = np.random.default_rng([seed, 0xC0105])
    jitter = rng.uniform(-jitter_s, jitter_s, len(depth_stamps)) if jitter_s > 0 else 0.0
    return np.asarray(depth_stamps, dtype=np.float64) + offset_s + jitter


def poses_at(trajectory: Trajectory, stamps: np.ndarray) -> np.ndarray:
    """``(M, 4, 4)`` poses of ``trajectory`` at ``stamps``: :func:`~surfelslam.geometry.interpolation.pose_between`
    the bracketing poses, extrapolated from the first / last interval outside the trajectory (needs 2 poses)."""
    t = trajectory.timestamps
    stamps = np.asarray(stamps, dtype=np.float64).reshape(-1)
    hi = np.clip(np.searchsorted(t, stamps, side="right"), 1, len(t) - 1)
    return np.stack([pose_between(trajectory, b - 1, b, (q - t[b - 1]) / (t[b] - t[b - 1]))
                     for b, q in zip(hi, stamps, strict=True)])


def depth_to_raw(depth_m: np.ndarray, depth_scale: float = DEPTH_SCALE) -> np.ndarray:
    """Metres ``(H, W)`` -> uint16 raw units (rounded); values that do not fit become 0 (invalid)."""
    raw = np.round(depth_m.astype(np.float64) * depth_scale)
    raw[(raw > _UINT16_MAX) | ~np.isfinite(raw) | (raw < 0)] = 0
    return raw.astype(np.uint16)


def info_text(
    scene: str, motion_desc: str, noise: str, seed: int, n_frames: int, intr: Intrinsics, fps: float,
    texture: str = "rich", colour_offset_s: float = 0.0, colour_jitter_s: float = 0.0,
) -> str:
    """INFO.txt of a generated sequence; ``motion_desc`` is the trajectory style or a replay's description."""
    rows = [
        ("generator", "surfelslam synth"),
        ("scene", scene),
        ("texture", texture),
        ("trajectory", motion_desc),
        ("noise", noise),
        ("seed", str(seed)),
        ("frames", str(n_frames)),
        ("fps", f"{fps:g}"),
        ("image size", f"{intr.width}x{intr.height}"),
        ("intrinsics", f"fx={intr.fx!r} fy={intr.fy!r} cx={intr.cx!r} cy={intr.cy!r}"),
        ("depth scale", f"{DEPTH_SCALE:g}"),
        ("ground truth", "groundtruth.txt, T_world_cam of every frame (exact)"),
    ]
    if colour_offset_s != 0 or colour_jitter_s > 0:
        rows.insert(-1, ("colour timing", f"colour stamp = depth stamp {1000 * colour_offset_s:+g} ms "
                                          f"(+- {1000 * colour_jitter_s:g} ms uniform jitter); ground truth at "
                                          "the depth stamps"))
    return "".join(f"{k:<15} : {v}\n" for k, v in rows)


def generate_sequence(
    out_dir: str | Path,
    scene: str = "room",
    style: str = "slow",
    n_frames: int = 300,
    noise: str = "kinect",
    seed: int = 0,
    width: int = 640,
    height: int = 480,
    fps: float = DEFAULT_FPS,
    progress: bool | Callable[[int], None] = False,
    motion: Trajectory | None = None,
    speed: float = 1.0,
    motion_start_s: float = 0.0,
    motion_label: str = "a recorded motion",
    texture: str = "rich",
    colour_offset_s: float = 0.0,
    colour_jitter_s: float = 0.0,
) -> Path:
    """Render and write a TUM-layout sequence to ``out_dir`` (created); returns its path.

    ``progress``: a callable ``progress(i)`` is called after frame ``i`` is written; ``True`` shows a tqdm
    bar on stderr (for the commands; library callers leave it False).
    ``texture``: the scene's texture style (:data:`~surfelslam.synth.textures.TEXTURE_STYLES`).
    ``motion``: replay this recorded camera motion (:func:`~surfelslam.synth.trajectories.replay_motion`, at
    ``speed`` from ``motion_start_s``; ``motion_label`` names it in INFO.txt) instead of the ``style``.
    ``colour_offset_s`` / ``colour_jitter_s``: colour taken at another stamp than depth (module docstring); their
    sum must stay below :data:`MAX_COLOUR_OFFSET_S` (the TUM reader pairs colour and depth within it) and half
    a frame interval (it pairs each colour image with the nearest depth stamp).
    Bad names, sizes, offsets or motions raise ConfigError before anything is written.
    """
    noise_cfg = noise_config(noise)
    _check_sequence_settings(width, height, fps, n_frames, colour_offset_s, colour_jitter_s)
    sc = make_scene(scene, seed, TextureConfig(style=texture))
    traj, motion_desc = _camera_motion(sc, style, n_frames, fps, seed, motion, speed, motion_start_s, motion_label)
    intr = default_intrinsics(width, height)
    out = Path(out_dir)
    (out / "rgb").mkdir(parents=True, exist_ok=True)
    (out / "depth").mkdir(parents=True, exist_ok=True)
    names = [f"{t:.6f}" for t in traj.timestamps]
    T_world_colour = None
    rgb_names = names
    if colour_offset_s != 0 or colour_jitter_s > 0:
        c_stamps = colour_stamps(traj.timestamps, colour_offset_s, colour_jitter_s, seed)
        T_world_colour = poses_at(traj, c_stamps)
        rgb_names = [f"{t:.6f}" for t in c_stamps]
    _write_frames(out, iter_frames(sc, traj, intr, noise_cfg, seed, T_world_colour), names, rgb_names, n_frames,
                  progress)
    _write_index_files(out, names, rgb_names)
    write_tum(traj, out / "groundtruth.txt")
    write_text_atomic(out / "INFO.txt", info_text(scene, motion_desc, noise, seed, n_frames, intr, fps,
                                                         texture, colour_offset_s, colour_jitter_s))
    return out


def _check_sequence_settings(width: int, height: int, fps: float, n_frames: int, colour_offset_s: float,
                             colour_jitter_s: float) -> None:
    """ConfigError for an empty image size or a colour offset the TUM reader could not pair back."""
    if width < 1 or height < 1:
        raise ConfigError(f"image size must be positive, got {width}x{height}")
    max_offset_s = min(MAX_COLOUR_OFFSET_S, 0.5 / fps) if fps > 0 else MAX_COLOUR_OFFSET_S
    if not (np.isfinite(colour_offset_s) and colour_jitter_s >= 0
            and abs(colour_offset_s) + colour_jitter_s < max_offset_s):
        raise ConfigError(f"colour offset {1000 * colour_offset_s:g} ms with jitter {1000 * colour_jitter_s:g} ms: "
                          f"need jitter >= 0 and |offset| + jitter < {1000 * max_offset_s:.4g} ms (colour is paired "
                          f"with the nearest depth stamp, within {1000 * MAX_COLOUR_OFFSET_S:g} ms)")
    if n_frames < 2 and (colour_offset_s != 0 or colour_jitter_s > 0):
        raise ConfigError("a colour offset needs at least 2 frames (the colour pose is interpolated)")


def _camera_motion(sc: Scene, style: str, n_frames: int, fps: float, seed: int, motion: Trajectory | None,
                   speed: float, motion_start_s: float, motion_label: str) -> tuple[Trajectory, str]:
    """The camera trajectory (a ``style`` or a replayed recording) and its description for INFO.txt."""
    if motion is None:
        return make_trajectory(style, n_frames, sc, fps=fps, seed=seed), style
    try:
        traj = replay_motion(motion, n_frames, sc, fps=fps, speed=speed, start_s=motion_start_s, seed=seed)
    except ConfigError as exc:  # name the recording the message is about
        raise ConfigError(f"{motion_label}: {exc}") from None
    return traj, f"replay of {motion_label} at {speed:g}x speed from {motion_start_s:g} s"


def _write_frames(out: Path, frames: Iterator[RGBDFrame], names: list[str], rgb_names: list[str], n_frames: int,
                  progress: bool | Callable[[int], None]) -> None:
    """Write each frame's colour and depth PNGs (``rgb_names`` / ``names`` by frame index) while the next renders."""
    bar = None
    if progress is True:
        from tqdm import tqdm

        bar = tqdm(total=n_frames, desc="synth", unit="frame")
    # PNG encoding releases the GIL: write in background threads while the next frame renders.
    # File contents do not depend on the order of completion.
    pending: deque[Future] = deque()

    def finish_one() -> None:
        index = pending.popleft().result()
        if bar is not None:
            bar.update(1)
        elif callable(progress):
            progress(index)

    def write_frame(frame: RGBDFrame) -> int:
        name = names[frame.index]
        write_png_rgb(out / "rgb" / f"{rgb_names[frame.index]}.png", frame.rgb)
        write_png_depth(out / "depth" / f"{name}.png", depth_to_raw(frame.depth_m))
        return frame.index

    try:
        with ThreadPoolExecutor(max_workers=_WRITER_THREADS) as pool:
            for frame in frames:
                pending.append(pool.submit(write_frame, frame))
                while len(pending) > _MAX_QUEUED_FRAMES:
                    finish_one()
            while pending:
                finish_one()
    finally:
        if bar is not None:
            bar.close()


def _write_index_files(out: Path, names: list[str], rgb_names: list[str]) -> None:
    """The TUM index files: ``rgb.txt``, ``depth.txt`` and ``associations.txt``."""
    write_text_atomic(
        out / "rgb.txt",
        "# color images\n# timestamp filename\n" + "".join(f"{n} rgb/{n}.png\n" for n in rgb_names),
    )
    write_text_atomic(
        out / "depth.txt",
        "# depth maps\n# timestamp filename\n" + "".join(f"{n} depth/{n}.png\n" for n in names),
    )
    write_text_atomic(out / "associations.txt", "".join(f"{c} rgb/{c}.png {n} depth/{n}.png\n"
                                                        for c, n in zip(rgb_names, names, strict=True)))
