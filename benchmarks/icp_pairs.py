"""Pairwise ICP on real data (7-Scenes redkitchen): success rate up to 30 frames apart, and the reference
assignment's experiment.

Sequence: ../shared/data/7scenes_redkitchen_0000_0499 (real Kinect v1, 30 Hz, GT from KinectFusion).

``--table success`` (default): the issue's accuracy criterion. Pairs ``s -> s + gap`` for gaps 1, 5, 10, 20, 30
from the starts 0, 20, ..., 460 (24 per gap), registered with ``surfelslam register``'s ICP settings
(:func:`pairwise_config`) from the identity (``--init identity``) and as the command's default does
(``--init auto``); ``--downsample 1`` = 640x480, the command's default, and 2 = 320x240. Per gap: pairs
within 1 cm & 1 deg of GT, median errors, and the same for ICP started AT the GT pose ("from GT": where the
depth data's own optimum lies relative to the GT, i.e. the floor of any depth-only registration judged against
this GT). The "depth agreement" table takes the pairs ``register --init identity`` misses and compares how well our pose
and the GT pose explain the two depth images (:func:`surfelslam.tracking.depth_agreement.depth_agreement`: median
``|dz|`` where the moved source meets target depth): where ours is lower, the depth data prefer our pose to the
GT's. ``ICPConfig() (tracker)`` is the frame-to-model tracker's setting (shorter coarse levels);
``register --init auto (default)`` the command's default start (identity and ORB + PnP guess, the pose with the
better depth agreement kept); ``previous`` the setting before depth weighting (finest Huber 2 cm, 5 finest iterations).

``--table open3d``: an independent check of that floor. Open3D's point-to-plane ICP (``registration_icp``, at
640x480 on 1 cm voxel clouds with normals from 5 cm neighbourhoods, correspondence distance 2 cm and 5 cm) started
at the GT pose of the same pairs, beside ours from GT: if another implementation also leaves the GT, the GT is not
where these depth images agree. Needs the ``bench`` extra (open3d).

``--table reference``: the reference assignment's experiment, pairs 10, 40 and 90 apart at 320x240, single level at
0.07 m (10 fixed iterations, no angle gate, no robust kernel) vs the register command's coarse-to-fine defaults.

Usage: ``.venv/bin/python -m benchmarks.icp_pairs [--table success|reference|open3d] [--downsample 1,2] [--starts ...]
[--gaps ...]``.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace

import numpy as np

from benchmarks.common import REDKITCHEN
from surfelslam.geometry import se3
from surfelslam.tracking.depth_agreement import depth_agreement
from surfelslam.tracking.icp import ICPConfig, icp, pairwise_config
from surfelslam.tracking.preprocess import PreprocessConfig, Preprocessor
from surfelslam.tracking.registration import register_pair

REFERENCE_CFG = ICPConfig(levels=1, iterations=(10,), dist_thresh_m=(0.07,), angle_thresh_deg=(180.0,),
                          robust_kernel="none", min_update_norm=0.0, min_relative_residual_change=0.0,
                          finest_source_stride_px=1, depth_weight_ref_m=0.0)
PREVIOUS_CFG = replace(ICPConfig(), depth_weight_ref_m=0.0, finest_robust_scale_m=0.02, iterations=(5, 8, 10, 40),
                       min_update_norm=1e-4, min_relative_residual_change=1e-3)
SUCCESS_M = 0.01  # the criterion: < 1 cm and < 1 deg against GT
SUCCESS_DEG = 1.0
SUCCESS_STARTS = tuple(range(0, 461, 20))
SUCCESS_GAPS = (1, 5, 10, 20, 30)


def _open(downsample: int):
    from surfelslam.datasets import open_sequence
    from surfelslam.datasets.base import DatasetOptions

    if not REDKITCHEN.is_dir():
        raise SystemExit(f"{REDKITCHEN} is absent: this experiment needs the shared 7-Scenes data")
    return open_sequence(REDKITCHEN, DatasetOptions(downsample=downsample))


def _pyramids(seq, pre: Preprocessor, frames) -> dict:
    return {i: pre.process(seq[i].depth_m) for i in sorted(set(frames))}


def success_rows(downsample: int, starts=SUCCESS_STARTS, gaps=SUCCESS_GAPS) -> list[dict]:
    """One row per (pair, method): errors (mm, deg) vs GT, converged, CPU ms of the ICP call."""
    seq = _open(downsample)
    T_wc, valid = seq.gt_poses(at_depth_time=True)  # as register does
    pairs = [(s, s + g, g) for g in gaps for s in starts if s + g < len(seq) and valid[s] and valid[s + g]]
    pyr = _pyramids(seq, Preprocessor(seq.intrinsics, PreprocessConfig()), [i for p in pairs for i in p[:2]])
    methods = (("register --init identity", pairwise_config(), False),
               ("register ICP from GT", pairwise_config(), True),
               ("ICPConfig() (tracker)", ICPConfig(), False), ("previous", PREVIOUS_CFG, False))
    icp(pyr[pairs[0][0]], pyr[pairs[0][1]])  # JIT warm-up / cache load
    rows = []
    for s, t, gap in pairs:
        T_gt = se3.invert(T_wc[t]) @ T_wc[s]
        for name, cfg, from_gt in methods:
            t0 = time.thread_time()
            res = icp(pyr[s], pyr[t], T_gt if from_gt else None, cfg)
            ms = 1000 * (time.thread_time() - t0)
            e_t, e_r = se3.pose_error(res.T_target_source, T_gt)
            row = {"pair": (s, t), "gap": gap, "method": name, "err_mm": 1000 * e_t, "err_deg": e_r,
                   "converged": res.converged, "ms": ms}
            if name == "register --init identity":
                d_s, d_t, k = seq[s].depth_m, seq[t].depth_m, seq.intrinsics
                row["dz_ours_mm"] = 1000 * depth_agreement(d_s, d_t, k, res.T_target_source).median_abs_dz_m
                row["dz_gt_mm"] = 1000 * depth_agreement(d_s, d_t, k, T_gt).median_abs_dz_m
            rows.append(row)
        rows.append(_auto_row(seq, pyr, s, t, gap, T_gt))
    return rows


def _auto_row(seq, pyr, s: int, t: int, gap: int, T_gt: np.ndarray) -> dict:
    """``register --init auto`` (the command's default): ICP from the identity and from the ORB + PnP guess, the
    pose with the better depth agreement kept (:func:`surfelslam.tracking.registration.register_pair`)."""
    t0 = time.thread_time()
    res = register_pair(seq[s], seq[t], pyr[s], pyr[t], seq.intrinsics, pairwise_config(), "auto").icp
    ms = 1000 * (time.thread_time() - t0)
    e_t, e_r = se3.pose_error(res.T_target_source, T_gt)
    return {"pair": (s, t), "gap": gap, "method": "register --init auto (default)", "err_mm": 1000 * e_t,
            "err_deg": e_r, "converged": res.converged, "ms": ms}


def print_agreement(rows: list[dict], size: str) -> None:
    """Pairs ``register --init identity`` misses (1 cm & 1 deg): does the depth prefer our pose or the GT's?"""
    gaps = sorted({r["gap"] for r in rows})
    print(f"\n{size}: pairs missing 1 cm & 1 deg (register --init identity): median |dz| at our pose vs at the "
          "GT pose")
    print("| gap | missed | ours fits the depth better | median |dz| ours / GT (mm), missed pairs |")
    print("|---|---|---|---|")
    for g in gaps:
        miss = [r for r in rows if r["method"] == "register --init identity" and r["gap"] == g
                and not (r["err_mm"] < 1000 * SUCCESS_M and r["err_deg"] < SUCCESS_DEG)]
        if not miss:
            print(f"| {g} | 0 | - | - |")
            continue
        better = sum(r["dz_ours_mm"] <= r["dz_gt_mm"] for r in miss)
        print(f"| {g} | {len(miss)} | {better}/{len(miss)} | {np.median([r['dz_ours_mm'] for r in miss]):.1f} / "
              f"{np.median([r['dz_gt_mm'] for r in miss]):.1f} |")


def print_success(rows: list[dict], size: str, start: str = "registered from the identity unless the row says "
                  "otherwise", timed: bool = True) -> None:
    gaps = sorted({r["gap"] for r in rows})
    methods = list(dict.fromkeys(r["method"] for r in rows))
    print(f"\n{size}: pairs within 1 cm & 1 deg of GT (median error mm / deg), {start}")
    print("| method | " + " | ".join(f"gap {g}" for g in gaps) + " | all |" + (" CPU ms per pair (median) |"
                                                                              if timed else ""))
    print("|---|" + "---|" * (len(gaps) + 1 + timed))
    for m in methods:
        cells = []
        n_ok = n_all = 0
        for g in gaps:
            sel = [r for r in rows if r["method"] == m and r["gap"] == g]
            ok = sum(r["err_mm"] < 1000 * SUCCESS_M and r["err_deg"] < SUCCESS_DEG for r in sel)
            n_ok += ok
            n_all += len(sel)
            cells.append(f"{ok}/{len(sel)} ({np.median([r['err_mm'] for r in sel]):.1f} / "
                         f"{np.median([r['err_deg'] for r in sel]):.2f})")
        ms = np.median([r["ms"] for r in rows if r["method"] == m]) if timed else 0.0
        print(f"| {m} | " + " | ".join(cells) + f" | {n_ok}/{n_all} |" + (f" {ms:.1f} |" if timed else ""))


OPEN3D_VOXEL_M = 0.01  # Open3D clouds: voxel size (m)
OPEN3D_NORMAL_RADIUS_M = 0.05  # normal estimation neighbourhood (m), at most OPEN3D_NORMAL_NN points
OPEN3D_NORMAL_NN = 30
OPEN3D_MAX_DEPTH_M = 4.0  # depth truncation of the Open3D clouds (m)
OPEN3D_CORRESPONDENCE_M = (0.02, 0.05)  # Open3D ICP correspondence distances tried (m)


def open3d_rows(starts=SUCCESS_STARTS, gaps=SUCCESS_GAPS) -> list[dict]:
    """Per pair: Open3D point-to-plane ICP from the GT pose (each correspondence distance) and ours from GT (640x480),
    errors against the GT (mm, deg)."""
    try:
        import open3d as o3d
    except ImportError:
        raise SystemExit("--table open3d needs open3d: pip install -e '.[bench]'") from None
    seq = _open(1)
    T_wc, valid = seq.gt_poses(at_depth_time=True)
    k = seq.intrinsics
    pairs = [(s, s + g, g) for g in gaps for s in starts if s + g < len(seq) and valid[s] and valid[s + g]]
    frames = sorted({i for p in pairs for i in p[:2]})
    pyr = _pyramids(seq, Preprocessor(k, PreprocessConfig()), frames)
    pin = o3d.camera.PinholeCameraIntrinsic(k.width, k.height, k.fx, k.fy, k.cx, k.cy)
    reg = o3d.pipelines.registration

    def cloud(i):
        img = o3d.geometry.Image(np.ascontiguousarray(seq[i].depth_m, dtype=np.float32))
        pc = o3d.geometry.PointCloud.create_from_depth_image(img, pin, depth_scale=1.0,
                                                             depth_trunc=OPEN3D_MAX_DEPTH_M)
        pc = pc.voxel_down_sample(OPEN3D_VOXEL_M)
        pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=OPEN3D_NORMAL_RADIUS_M,
                                                                  max_nn=OPEN3D_NORMAL_NN))
        pc.orient_normals_towards_camera_location()
        return pc

    clouds = {i: cloud(i) for i in frames}
    crit = reg.ICPConvergenceCriteria(relative_fitness=1e-8, relative_rmse=1e-8, max_iteration=100)
    rows = []
    for s, t, gap in pairs:
        T_gt = se3.invert(T_wc[t]) @ T_wc[s]
        for d in OPEN3D_CORRESPONDENCE_M:
            r = reg.registration_icp(clouds[s], clouds[t], d, T_gt, reg.TransformationEstimationPointToPlane(), crit)
            e_t, e_r = se3.pose_error(np.asarray(r.transformation), T_gt)
            rows.append({"pair": (s, t), "gap": gap, "method": f"Open3D from GT, {100 * d:g} cm",
                         "err_mm": 1000 * e_t, "err_deg": e_r})
        res = icp(pyr[s], pyr[t], T_gt, pairwise_config())
        e_t, e_r = se3.pose_error(res.T_target_source, T_gt)
        rows.append({"pair": (s, t), "gap": gap, "method": "ours (register ICP) from GT", "err_mm": 1000 * e_t,
                     "err_deg": e_r})
    return rows


def reference_rows(starts=(10, 60, 110, 160, 210, 260, 310, 360), gaps=(10, 40, 90)) -> list[dict]:
    """The reference assignment's experiment at 320x240: single level at 0.07 m vs the register ICP settings
    (coarse-to-fine)."""
    seq = _open(2)
    T_wc, valid = seq.gt_poses(at_depth_time=True)  # as register does
    pairs = [(s, s + g, g) for g in gaps for s in starts if s + g < len(seq) and valid[s] and valid[s + g]]
    pyr = _pyramids(seq, Preprocessor(seq.intrinsics, PreprocessConfig()), [i for p in pairs for i in p[:2]])
    rows = []
    for s, t, gap in pairs:
        T_gt = se3.invert(T_wc[t]) @ T_wc[s]
        m_t, m_r = se3.pose_error(np.eye(4), T_gt)
        for name, cfg in (("reference 1 level 0.07 m", REFERENCE_CFG), ("register --init identity", pairwise_config())):
            res = icp(pyr[s], pyr[t], None, cfg)
            e_t, e_r = se3.pose_error(res.T_target_source, T_gt)
            rows.append({"pair": f"{s}->{t}", "gap": gap, "motion_mm": 1000 * m_t, "motion_deg": m_r,
                         "method": name, "inliers": res.inliers, "inlier_fraction": res.inlier_fraction,
                         "err_mm": 1000 * e_t, "err_deg": e_r, "iterations": res.iterations,
                         "converged": res.converged})
    return rows


def print_reference(rows: list[dict]) -> None:
    print("| pair | GT motion | method | inliers | trans err (mm) | rot err (deg) | iterations | converged |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['pair']} | {r['motion_mm']:.0f} mm, {r['motion_deg']:.1f} deg | {r['method']} | "
              f"{r['inliers']} ({100 * r['inlier_fraction']:.0f}%) | {r['err_mm']:.1f} | {r['err_deg']:.2f} | "
              f"{r['iterations']} | {'yes' if r['converged'] else 'no'} |")
    for name in dict.fromkeys(r["method"] for r in rows):
        for gap in sorted({r["gap"] for r in rows}):
            sel = [r for r in rows if r["method"] == name and r["gap"] == gap]
            ok = sum(r["err_mm"] < 10 and r["err_deg"] < 1 for r in sel)
            ok3 = sum(r["err_mm"] < 30 and r["err_deg"] < 2 for r in sel)
            print(f"{name}, gap {gap}: {ok}/{len(sel)} within 1 cm & 1 deg, {ok3}/{len(sel)} within 3 cm & 2 deg, "
                  f"median error {np.median([r['err_mm'] for r in sel]):.1f} mm")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--table", choices=("success", "reference", "open3d"), default="success")
    ap.add_argument("--downsample", default="1,2", help="success table: comma list (1 = 640x480, 2 = 320x240)")
    ap.add_argument("--starts", default=None, help="comma list of start frames")
    ap.add_argument("--gaps", default=None, help="comma list of frame gaps")
    a = ap.parse_args()

    def ints(text):
        return None if text is None else tuple(int(x) for x in text.split(","))

    if a.table == "open3d":
        kw = {k: v for k, v in (("starts", ints(a.starts)), ("gaps", ints(a.gaps))) if v is not None}
        print_success(open3d_rows(**kw), "640x480", "every ICP started at the GT pose", timed=False)
        return
    if a.table == "reference":
        kw = {k: v for k, v in (("starts", ints(a.starts)), ("gaps", ints(a.gaps))) if v is not None}
        print_reference(reference_rows(**kw))
        return
    for ds in ints(a.downsample):
        rows = success_rows(ds, ints(a.starts) or SUCCESS_STARTS, ints(a.gaps) or SUCCESS_GAPS)
        print_success(rows, f"{640 // ds}x{480 // ds}")
        print_agreement(rows, f"{640 // ds}x{480 // ds}")


if __name__ == "__main__":
    main()
