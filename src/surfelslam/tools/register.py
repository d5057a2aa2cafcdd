"""``surfelslam register SEQ --source I --target J --out DIR [--init identity|features]``: pairwise ICP.

Projective point-to-plane ICP from the identity, or from a feature-based guess (ORB + PnP-RANSAC,
:func:`surfelslam.tracking.features.feature_guess`) for pairs too far apart for ICP alone.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from surfelslam.errors import ConfigError
from surfelslam.tools.common import DatasetOptionsArgs, SeqArg, console, handle_errors, with_dataset_options

if TYPE_CHECKING:  # numpy and the library are imported when the command runs, not for its --help
    import numpy as np


def per_level(text: str | None, default: tuple, levels: int, name: str, cast=float,
              coarser_factor: float = 2.0) -> tuple:
    """Parse ``"a"`` (finest level; coarser levels multiplied by ``coarser_factor`` per level) or
    ``"a,b,c"`` (one value per level, finest first) into a tuple of ``levels`` values."""
    if text is None:
        vals = tuple(default)
        if len(vals) < levels:  # more levels than the defaults: extend the last one
            vals = vals + tuple(cast(vals[-1] * coarser_factor ** (k + 1)) for k in range(levels - len(vals)))
        return vals[:levels]
    try:
        vals = tuple(cast(x) for x in text.replace(" ", "").split(","))
    except ValueError:
        raise ConfigError(f"{name} must be a number or a comma list of numbers, got {text!r}") from None
    if len(vals) == 1:
        return tuple(cast(vals[0] * coarser_factor**k) for k in range(levels))
    if len(vals) != levels:
        raise ConfigError(f"{name} has {len(vals)} values but --levels is {levels}")
    return vals


def _icp_config(levels: int | None, dist_thresh: str | None, angle_thresh: str | None, iterations: str | None,
                solver: str):
    """``register``'s ICP settings (:func:`~surfelslam.tracking.icp.pairwise_config`) with the per-level options."""
    from surfelslam.tracking.icp import pairwise_config

    d = pairwise_config()
    n_levels = d.levels if levels is None else levels
    if n_levels < 1:
        raise ConfigError(f"--levels must be >= 1, got {n_levels}")
    return replace(
        d,
        levels=n_levels,
        dist_thresh_m=per_level(dist_thresh, d.dist_thresh_m, n_levels, "--dist-thresh"),
        angle_thresh_deg=per_level(angle_thresh, d.angle_thresh_deg, n_levels, "--angle-thresh",
                                   coarser_factor=1.0),
        iterations=per_level(iterations, d.iterations, n_levels, "--iterations", cast=int, coarser_factor=1.0),
        solver=solver,
    )


def _print_guesses(result: dict, init: str) -> None:
    for label, info, n_key, n_name in (("feature guess", result["features"], "good_matches", "good matches"),
                                       ("shape (FPFH) guess", result["geometric"], "matches", "mutual matches")):
        if info is not None:
            console.print(f"{label}: {info['inliers']} inliers of {info[n_key]} {n_name}" if info["ok"] else
                          f"{label} rejected ({info['reason']}: {info[n_key]} {n_name}, {info['inliers']} "
                          "inliers)", highlight=False)
    if init != "identity":
        console.print(f"ICP started from: {result['init_used']}", highlight=False)
    ctm = result["colour_timing"]
    if ctm["source"]["retimed"] or ctm["target"]["retimed"] or ctm["note"]:
        console.print("colour re-timed to the depth stamps (colour - depth: "
                      f"{1000 * ctm['source']['colour_minus_depth_s']:.1f} / "
                      f"{1000 * ctm['target']['colour_minus_depth_s']:.1f} ms)" if ctm["note"] is None else
                      f"colour not re-timed: {ctm['note']}", highlight=False)


def _print_result(result: dict, res, T: np.ndarray, agree: dict, written: list[Path]) -> None:
    import numpy as np

    source, target = result["source"], result["target"]
    console.print(f"registered frame {source} -> {target}: inliers {res.inliers} "
                  f"({100 * res.inlier_fraction:.1f}%), RMSE {1000 * res.rmse_m:.2f} mm, "
                  f"iterations {res.iterations}, converged {res.converged}"
                  + ("" if res.reason is None else f" ({res.reason})"), highlight=False)
    console.print(f"condition number {res.condition_number:.3g}, degenerate {res.degenerate}",
                  highlight=False)
    console.print("T_target_source =\n" + np.array2string(T, precision=6, suppress_small=True),
                  highlight=False)
    if "gt_error" in result:
        g = result["gt_error"]
        m = result["gt_motion"]
        if "init_gt_error" in result:
            gi = result["init_gt_error"]
            console.print(f"initial guess GT error: {1000 * gi['trans_m']:.1f} mm, {gi['rot_deg']:.3f} deg",
                          highlight=False)
        console.print(f"GT error: {1000 * g['trans_m']:.1f} mm, {g['rot_deg']:.3f} deg "
                      f"(GT motion {1000 * m['trans_m']:.1f} mm, {m['rot_deg']:.2f} deg)", highlight=False)
    else:
        console.print("no ground truth for these frames", highlight=False)
    text = ", ".join(f"{name.replace('_', ' ')} pose "
                     + ("no overlap" if a["median_abs_dz_m"] is None else
                        f"{1000 * a['median_abs_dz_m']:.1f} mm over {100 * a['overlap_fraction']:.0f}% "
                        "of the source")
                     for name, a in agree.items())
    console.print(f"depth agreement (median |dz| where the moved source meets target depth): {text}",
                  highlight=False)
    console.print(f"wrote {', '.join(str(p) for p in written)}", highlight=False, markup=False)


# the options of `surfelslam register`, one declaration each
SourceOpt = Annotated[int, typer.Option("--source", help="Source frame position (after selection).")]
TargetOpt = Annotated[int, typer.Option("--target", help="Target frame position (after selection).")]
OutOpt = Annotated[Path, typer.Option("--out", help="Output folder (registration.json, before/after.png).")]
LevelsOpt = Annotated[int | None, typer.Option("--levels", help="Pyramid levels (default 4).")]
DistOpt = Annotated[str | None, typer.Option(
    "--dist-thresh", help="Association distance in metres: finest level (doubled per coarser level) or a comma list "
                          "per level, finest first.")]
AngleOpt = Annotated[str | None, typer.Option(
    "--angle-thresh", help="Normal angle gate in degrees: one value for all levels or a comma list, finest first.")]
IterationsOpt = Annotated[str | None, typer.Option(
    "--iterations", help="Max iterations: one value for all levels or a comma list, finest first.")]
SolverOpt = Annotated[str, typer.Option("--solver", help="cholesky | lu | qr | pinv")]
InitOpt = Annotated[str, typer.Option(
    "--init", help="ICP initial guess: identity; features (SIFT/ORB + PnP-RANSAC between the two frames; when a "
                   "rejection rule fires, FPFH shape features of the depth + rigid consensus; identity when both "
                   "are rejected); geometry (the FPFH guess only); auto (ICP from the identity and the features "
                   "guess, keeping the pose whose depth agreement is better; the default).")]
PhotometricOpt = Annotated[str, typer.Option(
    "--photometric", help="Joint geometric + photometric ICP: auto (on when colour and depth are registered, e.g. "
                          "TUM, ICL-NUIM; off for 7-Scenes), on, off.")]
FeatureMaxNormOpt = Annotated[float | None, typer.Option(
    "--feature-max-norm", help="--init features / auto: largest accepted PnP motion norm (m + rad; default 2.0); "
                               "the odometry default 0.3 is too small for pairs far apart.")]
FeaturesOpt = Annotated[int | None, typer.Option(
    "--features", help="--init features / auto: keypoints per image (default 2000, twice the odometry's: pairs far "
                       "apart share little of the view).")]
DescriptorOpt = Annotated[str, typer.Option(
    "--descriptor", help="--init features / auto: sift (Lowe's ratio test; more correct matches between views far "
                         "apart, the default) or orb (the odometry's matching).")]
RetimeOpt = Annotated[str, typer.Option(
    "--retime-colour", help="With the photometric term: auto (a frame whose colour and depth stamps differ by 1-50 "
                            "ms, e.g. TUM, has its colour re-timed to its depth stamp with the camera velocity from "
                            "its neighbour frames), off.")]
FiguresOpt = Annotated[bool, typer.Option("--figures/--no-figures", help="Write before.png and after.png.")]


def _check_choices(init: str, retime_colour: str, photometric: str, features: int | None, descriptor: str) -> None:
    """Refuse an unknown mode or a bad feature count, naming the option."""
    from surfelslam.tracking.features import DETECTORS
    from surfelslam.tracking.photometric import PHOTOMETRIC_MODES
    from surfelslam.tracking.registration import INIT_MODES
    from surfelslam.tracking.retime import RETIME_MODES

    if init not in INIT_MODES:
        raise ConfigError(f"--init must be one of {', '.join(INIT_MODES)}, got {init!r}")
    if retime_colour not in RETIME_MODES:
        raise ConfigError(f"--retime-colour (colour re-timing) must be one of {', '.join(RETIME_MODES)}, "
                          f"got {retime_colour!r}")
    if photometric not in PHOTOMETRIC_MODES:
        raise ConfigError(f"--photometric must be one of {', '.join(PHOTOMETRIC_MODES)}, got {photometric!r}")
    if features is not None and features < 1:
        raise ConfigError(f"--features must be >= 1, got {features}")
    if descriptor not in DETECTORS:
        raise ConfigError(f"--descriptor must be one of {', '.join(DETECTORS)}, got {descriptor!r}")


def register_cmd(seq: SeqArg, source: SourceOpt, target: TargetOpt, out: OutOpt, dataset: DatasetOptionsArgs,
                 levels: LevelsOpt = None, dist_thresh: DistOpt = None, angle_thresh: AngleOpt = None,
                 iterations: IterationsOpt = None, solver: SolverOpt = "cholesky", init: InitOpt = "auto",
                 photometric: PhotometricOpt = "auto", feature_max_norm: FeatureMaxNormOpt = None,
                 features: FeaturesOpt = None, descriptor: DescriptorOpt = "sift", retime_colour: RetimeOpt = "auto",
                 figures: FiguresOpt = True) -> None:
    """Register frame SOURCE onto frame TARGET; print and save the pose, inliers, RMSE and GT error."""
    from surfelslam.datasets import open_sequence
    from surfelslam.eval.pair_registration import register_frames
    from surfelslam.tracking.photometric import colour_switch
    from surfelslam.tracking.registration import FEATURE_MAX_NORM, PAIR_FEATURES
    from surfelslam.tracking.retime import RetimeConfig
    from surfelslam.viz.registration import save_registration

    _check_choices(init, retime_colour, photometric, features, descriptor)
    sq = open_sequence(seq, dataset.resolve())
    cfg = _icp_config(levels, dist_thresh, angle_thresh, iterations, solver)
    report = register_frames(sq, source, target, cfg, init, colour_switch(photometric, sq.colour_registered),
                             RetimeConfig(mode=retime_colour),
                             FEATURE_MAX_NORM if feature_max_norm is None else feature_max_norm,
                             PAIR_FEATURES if features is None else features, descriptor)
    written = save_registration(out, report, figures)
    _print_guesses(report.result, init)
    _print_result(report.result, report.registration.icp, report.registration.icp.T_target_source,
                  report.agreement, written)


def register(app: typer.Typer) -> None:
    app.command("register")(handle_errors(with_dataset_options(register_cmd)))
