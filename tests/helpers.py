"""Helpers shared by the test modules: the standard synthetic camera, an unaligned ATE and the real-data paths.

Imported as ``from helpers import ...`` (``tests/`` is on ``sys.path`` through the root ``conftest.py``).
"""

from __future__ import annotations

import os
import threading
from pathlib import Path

import numpy as np
import pytest

from surfelslam.geometry.se3 import exp as se3_exp
from surfelslam.geometry.se3 import make_T, so3_exp
from surfelslam.synth.writer import default_intrinsics
from surfelslam.types import Intrinsics

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"

# The synthetic generator's camera at 320x240 (525 px focal length at 640x480, scaled): most tests' frames.
INTR = default_intrinsics(320, 240)


def ate_m(est: np.ndarray, gt: np.ndarray) -> float:
    """RMS position error (m) of ``est`` ``(N, 4, 4)`` against the first ``N`` poses of ``gt`` ``(M >= N, 4, 4)``,
    without alignment (the estimate starts at the ground truth's first pose)."""
    return float(np.sqrt(np.mean(np.sum((est[:, :3, 3] - gt[: len(est), :3, 3]) ** 2, axis=1))))


def square_walk(n_side: int, side_m: float) -> np.ndarray:
    """Ground-truth poses walking a square of side ``side_m`` (m), ``n_side`` steps a side, turning 90 deg at the
    corners: ``(4 n_side, 4, 4)`` (pose-graph tests)."""
    from surfelslam.geometry.se3 import make_T, so3_exp

    poses, T = [], np.eye(4)
    step, turn = make_T(np.eye(3), [side_m / n_side, 0.0, 0.0]), make_T(so3_exp([0.0, 0.0, np.pi / 2]), [0.0, 0.0, 0.0])
    for k in range(4 * n_side):
        poses.append(T.copy())
        T = T @ step
        if (k + 1) % n_side == 0:
            T = T @ turn
    return np.array(poses)


def thread_nice() -> int:
    """The calling thread's nice value (Linux: nice is per thread)."""
    return os.getpriority(os.PRIO_PROCESS, threading.get_native_id())


def shared_sequence(name: str) -> Path:
    """Path of ../shared/data/<name>; skips the test when it is not there."""
    path = SHARED_DATA / name
    if not path.is_dir():
        pytest.skip(f"real data not available: {path} is absent (needs ../shared beside the repo)")
    return path


# ---- a textured box room ray-cast in numpy (features, PnP and sparse SLAM tests) ------------------------------

ROOM_INTR = Intrinsics(260.0, 260.0, 159.5, 119.5, 320, 240)  # the camera those tests render the room with
ROOM_HALF_M = np.array([2.0, 1.2, 2.5])  # axis-aligned room [-h, h]^3 around the origin (y down)
TEX_CELL_M = (0.09, 0.035)  # two layers of random blocks


def _textures(seed: int = 7) -> np.ndarray:
    """``(6, 2, 128, 128)`` uint8 random block values per face and layer."""
    return np.random.default_rng(seed).integers(0, 256, size=(6, 2, 128, 128), dtype=np.uint8)


_TEX = _textures()
_TINT = np.array([[1.0, 0.8, 0.7], [0.7, 1.0, 0.8], [0.8, 0.7, 1.0], [1.0, 1.0, 0.7], [0.7, 1.0, 1.0], [1.0, 0.7, 1.0]])


def render_room(T_world_cam: np.ndarray, intr: Intrinsics, supersample: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Ray-cast the textured box room: ``(rgb (H, W, 3) uint8, depth_m (H, W) float32)``.

    Colour is anti-aliased by averaging ``supersample^2`` rays per pixel; depth is the centre ray's.
    """
    s = supersample
    v, u = np.mgrid[0 : intr.height * s, 0 : intr.width * s].astype(np.float64)
    u = (u - (s - 1) / 2) / s
    v = (v - (s - 1) / 2) / s
    d_cam = np.stack([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, np.ones_like(u)], axis=-1)
    d = d_cam @ T_world_cam[:3, :3].T
    o = T_world_cam[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        t_hi = (ROOM_HALF_M - o) / d
        t_lo = (-ROOM_HALF_M - o) / d
    t_axis = np.where(d > 0, t_hi, t_lo)  # (H, W, 3): exit distance through each axis' wall
    t_axis = np.where(np.isfinite(t_axis) & (t_axis > 0), t_axis, np.inf)
    axis = np.argmin(t_axis, axis=-1)
    t = np.take_along_axis(t_axis, axis[..., None], -1)[..., 0]
    p = o + t[..., None] * d
    face = axis * 2 + (np.take_along_axis(d, axis[..., None], -1)[..., 0] > 0)
    other = np.array([[1, 2], [0, 2], [0, 1]])[axis]  # the two in-plane axes
    a = np.take_along_axis(p, other[..., :1], -1)[..., 0]
    b = np.take_along_axis(p, other[..., 1:], -1)[..., 0]
    grey = np.zeros(a.shape)
    for layer, (cell, w) in enumerate(zip(TEX_CELL_M, (0.6, 0.4), strict=True)):
        ia = np.floor(a / cell).astype(np.int64) % 128
        ib = np.floor(b / cell).astype(np.int64) % 128
        grey += w * _TEX[face, layer, ia, ib]
    rgb = grey[..., None] * _TINT[face]
    rgb = rgb.reshape(intr.height, s, intr.width, s, 3).mean(axis=(1, 3))
    rgb = np.clip(rgb + 0.5, 0, 255).astype(np.uint8)
    if s > 1:  # depth of the exact pixel centre (a planar room: one more cheap ray cast)
        _, depth = render_room(T_world_cam, intr, supersample=1)
        return rgb, depth
    return rgb, t.astype(np.float32)  # d_cam has z = 1, so the ray parameter is the depth


def motion(rot_axis, rot_deg: float, trans_dir, trans_m: float) -> np.ndarray:
    """``(4, 4)`` rigid motion ``exp([w, v])``: ``rot_deg`` about ``rot_axis`` with ``trans_m`` along ``trans_dir``
    (the axes need not be unit vectors)."""
    a = np.asarray(rot_axis, float)
    t = np.asarray(trans_dir, float)
    return se3_exp(np.concatenate([a / np.linalg.norm(a) * np.radians(rot_deg), t / np.linalg.norm(t) * trans_m]))


def look_pose(position: np.ndarray, yaw_rad: float, pitch_rad: float = 0.0) -> np.ndarray:
    """Camera at ``position`` turned by yaw (about world y) then pitch (about camera x)."""
    R = so3_exp([0.0, yaw_rad, 0.0]) @ so3_exp([pitch_rad, 0.0, 0.0])
    return make_T(R, position)


def command_app(name: str):
    """A Typer app holding only the command module ``surfelslam.tools.<name>`` (independent of the other commands)."""
    import importlib

    import typer

    app = typer.Typer(pretty_exceptions_enable=False)

    @app.callback()
    def _root() -> None:
        pass

    importlib.import_module(f"surfelslam.tools.{name}").register(app)
    return app


def register_app():
    """A Typer app holding only the ``register`` command."""
    return command_app("register")
