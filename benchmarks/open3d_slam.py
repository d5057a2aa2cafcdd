"""Open3D's dense SLAM (``open3d.t.pipelines.slam``) on a surfelslam sequence, for side-by-side benchmarks.

Uses the settings of Open3D's own example (examples/python/t_reconstruction_system: voxel 0.0058 m,
16^3 blocks, 40000 blocks, depth 0.1-3.0 m, odometry distance 0.07 m, truncation 8 voxels) on the CPU.
Frames come from our dataset reader, so both systems see exactly the same images.
Needs the optional ``bench`` extra (open3d); :func:`available` tells whether it is installed.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from surfelslam.types import Trajectory


@dataclass(frozen=True)
class Open3DSlamConfig:
    """The example's defaults (units in names)."""

    voxel_size_m: float = 0.0058
    block_resolution: int = 16
    block_count: int = 40000
    depth_min_m: float = 0.1
    depth_max_m: float = 3.0
    odometry_distance_thr_m: float = 0.07
    trunc_voxel_multiplier: float = 8.0
    depth_scale: float = 1000.0  # we hand Open3D millimetre uint16 depth


def available() -> bool:
    return version() is not None


def version() -> str | None:
    """Open3D's version, or None when it cannot be imported."""
    try:
        import open3d
    except Exception:  # noqa: BLE001 - any import failure means "not available"
        return None
    return str(open3d.__version__)


def run_open3d_slam(seq, cfg: Open3DSlamConfig | None = None) -> dict:
    """Run Open3D dense SLAM over ``seq``; returns ``{"trajectory", "fps", "wall_s", "frames", "failed"}``.

    Frame reading is excluded from the timing (as for our FPS): frames are decoded first.
    """
    import open3d as o3d
    import open3d.core as o3c

    cfg = cfg or Open3DSlamConfig()
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)  # its range-map warnings flood the log
    intr = seq.intrinsics
    device = o3c.Device("CPU:0")
    K = o3c.Tensor(intr.K, dtype=o3c.Dtype.Float64)
    frames = [seq[i] for i in range(len(seq))]
    T = np.eye(4)
    model = o3d.t.pipelines.slam.Model(cfg.voxel_size_m, cfg.block_resolution, cfg.block_count,
                                       o3c.Tensor(T), device)
    input_frame = o3d.t.pipelines.slam.Frame(intr.height, intr.width, K, device)
    raycast_frame = o3d.t.pipelines.slam.Frame(intr.height, intr.width, K, device)
    poses = np.zeros((len(frames), 4, 4))
    failed = 0
    t0 = time.perf_counter()
    for i, fr in enumerate(frames):
        depth_mm = np.round(fr.depth_m * cfg.depth_scale).astype(np.uint16)
        input_frame.set_data_from_image("depth", o3d.t.geometry.Image(o3c.Tensor(depth_mm)))
        input_frame.set_data_from_image("color", o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(fr.rgb))))
        if i > 0:
            try:
                res = model.track_frame_to_model(input_frame, raycast_frame, cfg.depth_scale, cfg.depth_max_m,
                                                 cfg.odometry_distance_thr_m)
                T = T @ res.transformation.cpu().numpy()
            except RuntimeError:
                failed += 1
        poses[i] = T
        model.update_frame_pose(i, o3c.Tensor(T))
        model.integrate(input_frame, cfg.depth_scale, cfg.depth_max_m, cfg.trunc_voxel_multiplier)
        model.synthesize_model_frame(raycast_frame, cfg.depth_scale, cfg.depth_min_m, cfg.depth_max_m,
                                     cfg.trunc_voxel_multiplier, False)
    wall = time.perf_counter() - t0
    return {
        "trajectory": Trajectory(seq.timestamps, poses),
        "fps": len(frames) / wall if wall > 0 else 0.0,
        "wall_s": wall,
        "frames": len(frames),
        "failed": failed,
    }
