"""The reference assignment's experiments on one sequence, as a report (``report.md`` + PNGs + ``results.json``).

``surfelslam experiments SEQ --out DIR`` runs them (:func:`run_experiments`).

Sections (every number comes from this run; ``DIR/results.json`` holds the same numbers):

1. ICP on frame pairs (single level at 0.07 m, single level at 0.17 m, coarse-to-fine defaults, and
   ``register --init features``);
2. the linear solvers on one Gauss-Newton system (cholesky, lu, qr, pinv);
3. fusion with ground-truth poses vs dense-tracker poses;
4. the dormant-point rule on / off;
5. feature odometry (ORB + PnP-RANSAC) on a pair;
6. every tracker of ``surfelslam.slam.TRACKERS`` against the ground truth.
"""

from surfelslam.experiments.common import (
    REFERENCE_DORMANT_MAX_AGE_FRAMES,
    REFERENCE_DORMANT_MIN_HITS,
    SECTION_TITLES,
    ExperimentOptions,
    choose_pairs,
)
from surfelslam.experiments.pairs import (
    FEATURES_SETTING,
    after_figures,
    feature_pair,
    icp_settings,
    section_features,
    section_icp_pairs,
    section_solvers,
    solver_comparison,
)
from surfelslam.experiments.report import run_experiments
from surfelslam.experiments.runs import section_dormant, section_fusion, section_trajectories

__all__ = ["FEATURES_SETTING", "REFERENCE_DORMANT_MAX_AGE_FRAMES", "REFERENCE_DORMANT_MIN_HITS", "SECTION_TITLES",
           "ExperimentOptions", "after_figures", "choose_pairs", "feature_pair", "icp_settings", "run_experiments",
           "section_dormant", "section_features", "section_fusion", "section_icp_pairs", "section_solvers",
           "section_trajectories", "solver_comparison"]
