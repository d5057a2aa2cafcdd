"""The hybrid tracker's profile of the sparse back end: the values of ``[sparse]`` keys it needs differently from the
orb tracker, each in one place.

Two kinds (decided for issue 67, when the ``[hybrid]`` copies of ``[sparse]`` keys were removed):

- the keyframe spacing and loop candidates (:data:`HYBRID_PROFILE`) are user choices: ``[sparse]``
  ``keyframe_threshold``, ``keyframe_min_gap_frames`` and ``[sparse.loop]`` ``n_nearby``, ``n_random``,
  ``n_retrieved`` are unset by default, so each tracker runs with its own values, and a config that sets one sets it
  for the tracker it runs
  (a config file runs one tracker: the orb tracker is changed only when it runs with that file);
- the rest are constants of the hybrid's design (below): the hybrid applies them over ``[sparse]`` whatever it
  holds, and the ``[sparse]`` keys they replace (``graph.edge_information``, ``features_reference_width_px``,
  ``features.depth_edge_rel``, ``features.guided_radius_px``, ``graph.odometry_information``,
  ``graph.robust_scale_sigma``) are the orb tracker's only.
"""

from __future__ import annotations

import numpy as np

from surfelslam.backend.sparse_slam import SparseProfile, SparseSlamConfig, with_profile
from surfelslam.settings import from_dict
from surfelslam.slam.config import SlamConfig

#: keyframes every 0.12 m + rad but at most one every 3 frames (at 0.2 the keyframe edges spread more, fail the trust
#: gate and leave the odometry uncorrected; at 0.13 fr3/teddy lost 12 %; 0.12 makes 15 % fewer keyframes on hand-held
#: motion, each costing ORB and loop checks; the gap lets the loop-check thread keep up under fast motion); 3 nearby,
#: 2 retrieved and no random loop candidates per new keyframe (the random draws were most of the rejected checks:
#: with 0.12, 40 % fewer loop checks on the slow synthetic room, ATE within 2 % or better on the four synthetic rows
#: and teddy's 27 % better; 2 nearby lost 10 % on the hand-held row, a gap of 5 frames 19 % on the fast one); where the
#: graph has closed the loop, 2 retrieved candidates verified per keyframe (a quarter less loop-check time on a
#: revisit; 1 lost 8 % ATE on the slow synthetic orbit)
HYBRID_PROFILE = SparseProfile(keyframe_threshold=0.12, keyframe_min_gap_frames=3, loop_nearby=3, loop_random=0,
                               loop_closed_retrieved=2, loop_retrieved=2)
#: pose-graph edge weighting: its dense odometry edges carry no estimated information, and PnP Hessians must not
#: outweigh them
EDGE_INFORMATION = "isotropic"
#: px: [sparse] features_reference_width_px 0 keeps the PnP inlier bound as given at every width (its PnP poses only
#: guess or check ICP's)
FEATURES_REFERENCE_WIDTH_PX = 0
#: fraction: [sparse.features] depth_edge_rel 0 keeps keypoints on occluding contours for the keyframe edges (the
#: joint term leaves them out itself)
DEPTH_EDGE_REL = 0.0
#: deg: the per-frame PnP match seeks each keyframe keypoint within this angle of where the motion prediction puts it
#: (pixels = focal length x tan: 12 px at 320x240); brute force when that finds too few
GUIDED_MATCH_DEG = 2.6
#: m and rad: pose-graph sigma of the odometry edges between keyframes (dense poses), that of the refined loop edges'
#: floor (``[hybrid.loop_icp] sigma_m``): frame-to-model tracking drifts with a bias along the motion (about 0.5 % of
#: the keyframe step on fast synthetic motion), so 1 mm against their 3 mm kept that drift where the refined edges
#: measured it; PnP loop edges (10 cm) stay far looser
DENSE_ODOMETRY_SIGMA_M = 0.003
#: m: scale of the Cauchy kernel on the loop edges (PnP loop edges centimetres off are mostly wrong)
LOOP_ROBUST_SCALE_M = 0.03


def hybrid_sparse_config(cfg: SlamConfig, fx_px: float) -> SparseSlamConfig:
    """The sparse back end's settings in the hybrid tracker: ``[sparse]`` with :data:`HYBRID_PROFILE` for its unset
    keys and the hybrid's constants (the guided-match radius from :data:`GUIDED_MATCH_DEG` at focal length
    ``fx_px``; the loop kernel's scale in whitened units of ``[sparse.graph]`` loop_information)."""
    sp = with_profile(cfg.sparse, HYBRID_PROFILE)
    constants = {
        "features_reference_width_px": FEATURES_REFERENCE_WIDTH_PX,
        "features": {"depth_edge_rel": DEPTH_EDGE_REL,
                     "guided_radius_px": abs(fx_px) * float(np.tan(np.radians(GUIDED_MATCH_DEG)))},
        "graph": {"edge_information": EDGE_INFORMATION, "odometry_information": DENSE_ODOMETRY_SIGMA_M ** -2,
                  "robust_scale_sigma": float(LOOP_ROBUST_SCALE_M * np.sqrt(sp.graph.loop_information))},
    }
    return from_dict(SparseSlamConfig, constants, where="sparse", base=sp)
