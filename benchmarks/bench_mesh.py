"""Mesh quality and cost: our TSDF + marching cubes against the exact surfaces of a synthetic room, beside Open3D.

A ``surfelslam synth`` room (320x240, Kinect noise, the ``tour-across`` orbit looking across the room, so that
surfaces are seen from 0.4 m to the sensor's 4.5 m; 150 frames by default) is meshed

* from the ground-truth poses and from the poses a dense ``surfelslam run`` estimated (moved onto the first
  ground-truth pose: the run starts at the identity, the scene's frame is the ground truth's);
* by our TSDF (:mod:`surfelslam.mapping.mesh`, parallel kernels) and, when ``open3d`` imports, by Open3D's TSDF
  (``t.geometry.VoxelBlockGrid``, CPU) with the same voxel, truncation, depth range, frames and weight threshold,
  and by ``surfelslam mesh --method poisson`` (Open3D's Poisson on the run's ``map.ply``).

Each mesh gets accuracy (mesh to true surface: mean, 90th percentile), completeness (share of the surface the
frames saw within 1 cm of the mesh), :mod:`surfelslam.eval.mesh_quality`, and the topology counts mesh tools check
(:func:`surfelslam.mapping.mesh_topology.topology_report`: non-manifold edges and vertices, duplicated triangles,
inconsistently oriented edges, connected pieces). Times exclude image decoding (frames are
read first) and, for ours, numba's compilation (a warm-up fuse). With scikit-image importable the marching cubes
stage is also compared with ``skimage.measure.marching_cubes`` on the same TSDF made dense.

Usage: ``.venv/bin/python benchmarks/bench_mesh.py [--frames N] [--voxel M] [--repeats K] [--work DIR]
[--json PATH]``; prints Markdown tables (times: the fastest of ``--repeats``). ``run(...)`` returns the rows.
"""

from __future__ import annotations

import argparse
import json
import math
import tempfile
import time
from pathlib import Path

import numpy as np

from surfelslam.api import run_sequence
from surfelslam.datasets import open_sequence
from surfelslam.eval import mesh_quality as mq
from surfelslam.mapping.mesh import MeshConfig, TsdfVolume
from surfelslam.mapping.mesh_topology import topology_report
from surfelslam.slam import SlamConfig
from surfelslam.synth.noise import KinectNoiseConfig
from surfelslam.synth.writer import generate_sequence

DEFAULT_VOXEL_M = 0.01  # the voxel of `surfelslam mesh` (m)
OURS, GT = "surfelslam TSDF", "ground truth"  # the method and poses of the row the targets apply to
#: points drawn on each mesh to measure its accuracy
QUALITY_SAMPLES = 100_000
#: issue 37's and 70's targets, ground-truth poses on Kinect-noise data: mean accuracy (m) and completeness at 1 cm
TARGET_ACCURACY_MEAN_M = 0.005
TARGET_COMPLETENESS = 0.90
#: the camera motion: looking across the room, so that the frames see surfaces over the sensor's whole range
TRAJECTORY = "tour-across"
#: the surface that counts for completeness: what the frames saw within the synthetic Kinect's valid range (m)
TRUTH_MIN_DEPTH_M = KinectNoiseConfig().min_depth_m
TRUTH_MAX_DEPTH_M = KinectNoiseConfig().max_depth_m
#: topology_report's counts shown per mesh
TOPOLOGY_KEYS = ("non_manifold_edges", "non_manifold_vertices", "duplicated_triangles", "misoriented_edges",
                 "components")


def _open3d():
    try:
        import open3d as o3d
    except ImportError:
        return None
    return o3d


def _ours(frames, poses, intr, cfg: MeshConfig) -> tuple[np.ndarray, np.ndarray, dict]:
    t0 = time.perf_counter()
    vol = TsdfVolume.from_config(cfg)
    for f, T in zip(frames, poses, strict=True):
        vol.integrate(f.depth_m, f.rgb, intr, T)
    t1 = time.perf_counter()
    mesh = vol.extract_mesh(cfg.min_weight)
    t2 = time.perf_counter()
    return mesh.vertices, mesh.faces, {"fuse_s": t1 - t0, "extract_s": t2 - t1,
                                       "memory_mb": vol.memory_mb(vol.n_blocks)}


def _theirs(o3d, frames, poses, intr, cfg: MeshConfig) -> tuple[np.ndarray, np.ndarray, dict]:
    """Open3D's ``t.geometry.VoxelBlockGrid`` TSDF (8^3 blocks, CPU), float depth in metres and float colour (the
    legacy ``ScalableTSDFVolume`` gives an empty mesh with open3d-cpu 0.20 and numpy 2 here)."""
    o3c = o3d.core
    vbg = o3d.t.geometry.VoxelBlockGrid(
        attr_names=("tsdf", "weight", "color"), attr_dtypes=(o3c.float32, o3c.float32, o3c.float32),
        attr_channels=((1), (1), (3)), voxel_size=cfg.voxel_m, block_resolution=8, block_count=100_000,
        device=o3c.Device("CPU:0"))
    K = o3c.Tensor(intr.K, o3c.float64)
    mult = cfg.truncation_m / cfg.voxel_m
    t0 = time.perf_counter()
    for f, T in zip(frames, poses, strict=True):
        E = o3c.Tensor(np.linalg.inv(T), o3c.float64)
        depth = o3d.t.geometry.Image(o3c.Tensor(np.where(f.depth_m >= cfg.min_depth_m, f.depth_m, 0)
                                                .astype(np.float32)))
        colour = o3d.t.geometry.Image(o3c.Tensor(f.rgb.astype(np.float32) / 255.0))
        blocks = vbg.compute_unique_block_coordinates(depth, K, E, 1.0, cfg.max_depth_m, mult)
        vbg.integrate(blocks, depth, colour, K, K, E, 1.0, cfg.max_depth_m, mult)
    t1 = time.perf_counter()
    mesh = vbg.extract_triangle_mesh(weight_threshold=cfg.min_weight).to_legacy()
    t2 = time.perf_counter()
    return (np.asarray(mesh.vertices, np.float32), np.asarray(mesh.triangles, np.int32),
            {"fuse_s": t1 - t0, "extract_s": t2 - t1, "memory_mb": float("nan")})


def marching_cubes_comparison(frames, poses, intr, cfg: MeshConfig) -> dict | None:
    """Our marching cubes (without the topology clean-up) vs scikit-image's on the same TSDF (ours on the sparse
    blocks, theirs on the blocks' bounding box made dense, unobserved voxels masked out); None without
    scikit-image."""
    try:
        from skimage.measure import marching_cubes
    except ImportError:
        return None
    vol = TsdfVolume.from_config(cfg)
    for f, T in zip(frames, poses, strict=True):
        vol.integrate(f.depth_m, f.rgb, intr, T)
    vol.marching_cubes(cfg.min_weight)  # compiled
    t0 = time.perf_counter()
    ours = vol.marching_cubes(cfg.min_weight)  # without the clean-up, as scikit-image's
    t_ours = time.perf_counter() - t0
    t0 = time.perf_counter()
    tsdf, weight, _ = vol.dense_grid()
    t_dense = time.perf_counter() - t0
    t0 = time.perf_counter()
    verts, faces, _, _ = marching_cubes(tsdf, 0.0, mask=weight >= cfg.min_weight)
    t_sk = time.perf_counter() - t0
    return {"blocks": vol.n_blocks, "dense_voxels": int(tsdf.size), "dense_mb": 2 * tsdf.nbytes / 2**20,
            "ours_s": t_ours, "ours_vertices": ours.n_vertices, "ours_faces": ours.n_faces,
            "skimage_s": t_sk, "skimage_dense_grid_s": t_dense, "skimage_vertices": len(verts),
            "skimage_faces": len(faces)}


def run(frames: int = 150, voxel_m: float = 0.01, work: Path | None = None, open3d: bool = True,
        noise: str = "kinect", repeats: int = 1, width: int = 320, samples: int = QUALITY_SAMPLES) -> dict:
    """Generate (or reuse, in ``work``) the sequence and its dense run, mesh it every way; the rows (module
    docstring). ``samples``: points drawn on each mesh for its accuracy."""
    work = Path(tempfile.mkdtemp(prefix="bench_mesh_")) if work is None else Path(work)
    seq_dir = work / f"room_{TRAJECTORY}_{frames}_{noise}_{width}"
    if not (seq_dir / "INFO.txt").is_file():
        generate_sequence(seq_dir, scene="room", style=TRAJECTORY, n_frames=frames, noise=noise, seed=0,
                          width=width, height=width * 3 // 4)
    seq = open_sequence(seq_dir)
    run_dir = work / f"run_{TRAJECTORY}_{frames}_{noise}_{width}"
    if not (run_dir / "metrics.json").is_file():
        run_sequence(seq, run_dir, SlamConfig(), progress=False, figures=False)
    metrics = json.loads((run_dir / "metrics.json").read_text())
    from surfelslam.io.trajectory import read_tum

    gt, ok_gt = seq.ground_truth.lookup(seq.timestamps, 1e-4)
    est_raw, ok_est = read_tum(run_dir / "trajectory.txt").lookup(seq.timestamps, 1e-4)
    assert ok_gt.all() and ok_est.all()
    est = mq.first_pose_alignment(est_raw[0], gt[0]) @ est_raw
    frames_mem = [seq[i] for i in range(len(seq))]
    intr = seq.intrinsics
    cfg = MeshConfig(voxel_m=voxel_m)
    scene = mq.scene_of_sequence(seq_dir)
    truth = mq.visible_surface_points(scene, gt[::2], intr, TRUTH_MIN_DEPTH_M, TRUTH_MAX_DEPTH_M)

    _ours(frames_mem[:2], gt[:2], intr, cfg)  # compile
    o3d = _open3d() if open3d else None
    rows = []
    for poses_name, poses in ((GT, gt), ("estimated (dense run)", est)):
        methods = [(OURS, _ours)]
        if o3d is not None:
            methods.append((f"Open3D {o3d.__version__} VoxelBlockGrid TSDF",
                            lambda *a: _theirs(o3d, *a)))
        for name, fn in methods:
            v, f, cost = fn(frames_mem, poses, intr, cfg)
            for _ in range(repeats - 1):  # the fastest of the repeats (the machine may be shared)
                again = fn(frames_mem, poses, intr, cfg)[2]
                cost = {k: min(cost[k], again[k]) for k in ("fuse_s", "extract_s")} | {"memory_mb": cost["memory_mb"]}
            q = mq.mesh_quality(v, f, scene, truth, samples=samples)
            topo = topology_report(v, f)
            rows.append({"method": name, "poses": poses_name, **cost, **q, **{k: topo[k] for k in TOPOLOGY_KEYS}})
    if o3d is not None:  # Poisson on the run's surfels (estimated poses: the map is in the run's frame)
        from surfelslam.io.ply import read_ply
        from surfelslam.mapping.mesh import poisson_mesh

        m = read_ply(run_dir / "map.ply")
        t0 = time.perf_counter()
        mesh = poisson_mesh(*(np.stack([m[a], m[b], m[c]], 1) for a, b, c in
                              (("x", "y", "z"), ("nx", "ny", "nz"), ("red", "green", "blue"))), cfg)
        cost = {"fuse_s": float("nan"), "extract_s": time.perf_counter() - t0, "memory_mb": float("nan")}
        mesh = mesh.transformed(mq.first_pose_alignment(est_raw[0], gt[0]))
        q = mq.mesh_quality(mesh.vertices, mesh.faces, scene, truth, samples=samples)
        topo = topology_report(mesh.vertices, mesh.faces)
        rows.append({"method": "Poisson (Open3D) on map.ply's surfels", "poses": "estimated (dense run)", **cost,
                     **q, **{k: topo[k] for k in TOPOLOGY_KEYS}})
    return {"sequence": str(seq_dir), "frames": len(seq), "resolution": [intr.width, intr.height],
            "noise": noise, "repeats": repeats, "voxel_m": voxel_m, "trunc_m": cfg.truncation_m,
            "max_depth_m": cfg.max_depth_m,
            "run_ate_rmse_m": metrics.get("eval", {}).get("ate_rmse_m"), "rows": rows,
            "marching_cubes": marching_cubes_comparison(frames_mem, gt, intr, cfg)}


def section(frames: int, width: int, work: Path, open3d: bool = True, repeats: int = 1,
            voxel_m: float = DEFAULT_VOXEL_M) -> dict:
    """``make bench``'s ``mesh`` section: :func:`run` on the Kinect-noise room, times that do not apply as ``None``
    (JSON has no NaN), issue 37's targets checked on our mesh from the ground-truth poses."""
    res = run(frames, voxel_m, work, open3d, "kinect", repeats, width)
    for r in res["rows"]:
        r.update({k: None for k, v in r.items() if isinstance(v, float) and math.isnan(v)})
    ours = next(r for r in res["rows"] if r["method"] == OURS and r["poses"] == GT)
    res["sequence"] = "synthetic room, orbit looking across the room (far views), Kinect noise"
    res["targets"] = {"accuracy_mean_m": TARGET_ACCURACY_MEAN_M, "completeness": TARGET_COMPLETENESS,
                      "ok": ours["accuracy_mean_m"] <= TARGET_ACCURACY_MEAN_M
                      and ours["completeness"] >= TARGET_COMPLETENESS}
    return res


def section_markdown(res: dict) -> list[str]:
    """The ``make bench`` section: the quality table, the targets, the marching cubes comparison and what they say
    about the choice of libraries."""
    from benchmarks.common import fmt, table

    w, h = res["resolution"]
    t = res["targets"]
    md = [f"### Mesh quality: {res['frames']} synthetic frames at {w}x{h} (`surfelslam mesh`)", ""]
    md.append(table(["method", "poses", "accuracy mean mm", "accuracy p90 mm", "completeness @ 1 cm",
                     "triangles", "non-manifold edges / vertices", "pieces", "fuse s", "extract s"],
                    [[r["method"], r["poses"], fmt(1e3 * r["accuracy_mean_m"], 2), fmt(1e3 * r["accuracy_p90_m"], 2),
                      f"{100 * r['completeness']:.1f} %", f"{r['faces']:,}", _topology(r), f"{r['components']:,}",
                      fmt(r["fuse_s"], 2), fmt(r["extract_s"], 2)] for r in res["rows"]]))
    ate = res.get("run_ate_rmse_m")
    seq = res["sequence"][0].upper() + res["sequence"][1:]
    md += [f"{seq}; voxel {100 * res['voxel_m']:g} cm, truncation {100 * res['trunc_m']:g} cm (ours: widened "
           f"to 3 noise sigmas for far depth, each depth weighted by 1 / sigma^2), depth up to {res['max_depth_m']:g} "
           "m. Accuracy: distance from points sampled on the mesh to the scene's exact surfaces; completeness: share "
           f"of the surface the frames saw from {TRUTH_MIN_DEPTH_M:g} to {TRUTH_MAX_DEPTH_M:g} m within 1 cm of the "
           "mesh (`surfelslam.eval.mesh_quality`); topology: our own checker (`surfelslam.mapping.mesh_topology`), "
           "pieces = connected components. Estimated poses: a dense `surfelslam run` of the same frames"
           + (f" (ATE {100 * ate:.2f} cm)" if ate is not None else "") + ", put on the first ground-truth pose. "
           "Open3D: `t.geometry.VoxelBlockGrid` on the CPU with the same voxel, truncation, depth range, frames and "
           "weight threshold; Poisson: `surfelslam mesh --method poisson` on the run's `map.ply`. Times: wall "
           f"clock, the fastest of {res['repeats']}, frames decoded beforehand, ours with numba's parallel kernels "
           f"(as `surfelslam mesh`). Issues 37 and 70's target (ground-truth poses, Kinect noise: mean accuracy <= "
           f"{1e3 * t['accuracy_mean_m']:g} mm, completeness >= {100 * t['completeness']:g} % at 1 cm): "
           f"{fmt(t['ok'])}.", ""]
    mc = res.get("marching_cubes")
    if mc:
        md.append(table(["marching cubes (same TSDF, ground-truth poses)", "s", "triangles"],
                        [[f"ours (numba) on the {mc['blocks']:,} sparse blocks", fmt(mc["ours_s"], 2),
                          f"{mc['ours_faces']:,}"],
                         [f"scikit-image `marching_cubes` on the dense box ({mc['dense_voxels'] / 1e6:.1f} M voxels, "
                          f"{mc['dense_mb']:.0f} MiB, built in {mc['skimage_dense_grid_s']:.2f} s more)",
                          fmt(mc["skimage_s"], 2), f"{mc['skimage_faces']:,}"]]))
    md += [_choice(res), ""]
    return md


def _topology(row: dict) -> str:
    """Non-manifold edges / vertices, with the duplicated triangles and misoriented edges when there are any."""
    text = f"{row['non_manifold_edges']:,} / {row['non_manifold_vertices']:,}"
    extra = [f"{row[k]:,} {k.replace('_', ' ')}" for k in ("duplicated_triangles", "misoriented_edges") if row[k]]
    return text + (f" ({', '.join(extra)})" if extra else "")


def _choice(res: dict) -> str:
    """What the figures say about the libraries ``surfelslam mesh`` uses (worded from the figures themselves)."""
    rows = {(r["method"].split()[0], r["poses"]): r for r in res["rows"]}
    ours, theirs = rows.get(("surfelslam", GT)), rows.get(("Open3D", GT))
    text = ["Choice of libraries: the TSDF and marching cubes are our own numba code, with no further dependency"]
    if theirs is not None:
        ours_s = (ours["fuse_s"] or 0.0) + (ours["extract_s"] or 0.0)
        their_s = (theirs["fuse_s"] or 0.0) + (theirs["extract_s"] or 0.0)
        text.append("against Open3D's TSDF on the same frames and poses: mean accuracy "
                    f"{1e3 * ours['accuracy_mean_m']:.2f} mm vs {1e3 * theirs['accuracy_mean_m']:.2f} mm, completeness "
                    f"{100 * ours['completeness']:.1f} % vs {100 * theirs['completeness']:.1f} %, "
                    f"{ours_s:.1f} s vs {their_s:.1f} s to fuse and extract")
    mc = res.get("marching_cubes")
    if mc:
        text.append(f"scikit-image's marching cubes needs the dense box ({mc['dense_mb']:.0f} MiB here, growing with "
                    "the room's volume, where the sparse blocks grow with its surface): "
                    f"{mc['skimage_dense_grid_s'] + mc['skimage_s']:.2f} s with building it, ours "
                    f"{mc['ours_s']:.2f} s")
    poisson = next((r for r in res["rows"] if r["method"].startswith("Poisson")), None)
    if poisson is not None:
        text.append(f"Open3D's Poisson stays an option (`--method poisson`), not the default: it fills holes with "
                    f"surfaces that are not there (p90 {1e3 * poisson['accuracy_p90_m']:.1f} mm)")
    return "; ".join(text) + "."


def _secs(v: float) -> str:
    return "-" if np.isnan(v) else f"{v:.2f}"


def markdown(res: dict) -> str:
    ate = res["run_ate_rmse_m"]
    lines = [f"Synthetic room, {res['frames']} frames at {res['resolution'][0]}x{res['resolution'][1]}, "
             f"{res['noise']} noise; voxel {res['voxel_m'] * 100:g} cm, truncation {res['trunc_m'] * 100:g} cm, "
             f"depth <= {res['max_depth_m']:g} m" + (f"; dense run ATE {ate * 100:.2f} cm" if ate is not None else ""),
             "",
             "| method | poses | accuracy mean (mm) | accuracy p90 (mm) | completeness @ 1 cm | triangles | "
             "non-manifold edges / vertices | pieces | fuse (s) | extract (s) |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in res["rows"]:
        lines.append(f"| {r['method']} | {r['poses']} | {r['accuracy_mean_m'] * 1000:.2f} | "
                     f"{r['accuracy_p90_m'] * 1000:.2f} | {r['completeness'] * 100:.1f} % | {r['faces']:,} | "
                     f"{_topology(r)} | {r['components']:,} | {_secs(r['fuse_s'])} | {_secs(r['extract_s'])} |")
    mc = res.get("marching_cubes")
    if mc:
        lines += ["", "| marching cubes (same TSDF, ground-truth poses) | time (s) | triangles |", "|---|---:|---:|",
                  f"| ours, numba, on {mc['blocks']:,} sparse blocks | {mc['ours_s']:.2f} | {mc['ours_faces']:,} |",
                  f"| scikit-image `marching_cubes` on the dense box ({mc['dense_voxels'] / 1e6:.0f} M voxels, "
                  f"{mc['dense_mb']:.0f} MiB; + {mc['skimage_dense_grid_s']:.2f} s to build it) | "
                  f"{mc['skimage_s']:.2f} | {mc['skimage_faces']:,} |"]
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=150)
    ap.add_argument("--voxel", type=float, default=0.01, help="voxel size [m]")
    ap.add_argument("--noise", default="kinect")
    ap.add_argument("--work", type=Path, default=None, help="folder for the sequence and the run (kept)")
    ap.add_argument("--no-open3d", action="store_true")
    ap.add_argument("--repeats", type=int, default=1, help="time each TSDF this many times, report the fastest")
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args()
    res = run(a.frames, a.voxel, a.work, not a.no_open3d, a.noise, max(1, a.repeats))
    if a.json is not None:
        a.json.write_text(json.dumps(res, indent=2) + "\n")
    print(markdown(res))


if __name__ == "__main__":
    main()
