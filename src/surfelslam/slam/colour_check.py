"""Check, before a run, that colour the layout takes as registered to depth really lines up with it.

A sequence folder says nothing about its cameras beyond its layout: a renamed 7-Scenes copy, or a capture from
two uncalibrated cameras, reads as TUM or a plain folder, and the colour terms (photometric, joint features) would
then use colour from another viewpoint. :func:`check_colour_registration` fits a separate colour camera on a few
frames (:func:`~surfelslam.geometry.colour_fit.fit_colour_camera`, well under a second) and reports whether it lines
colour edges up with depth edges much better than the same pixel does.
"""

from __future__ import annotations

import numpy as np

from surfelslam.errors import ConfigError, FrameError
from surfelslam.geometry.camera import ColourRegistrationConfig
from surfelslam.geometry.colour_fit import ColourFitConfig, fit_colour_camera, fit_says_unregistered

#: Layouts whose colour is taken as registered without a camera model, and whose frames can be read in any order.
CHECKED_LAYOUTS = ("tum", "icl", "folder")


def check_colour_registration(seq, cfg: ColourRegistrationConfig) -> dict | None:
    """``{"registered", "edge_distance_same_pixel_px", "edge_distance_fitted_px", "frames"}`` for a sequence of a
    :data:`CHECKED_LAYOUTS` layout that takes colour as registered; ``None`` when the check does not apply or has
    nothing to go on (too few readable frames, no depth edges)."""
    if not cfg.check or not getattr(seq, "colour_registered", True) or seq.layout not in CHECKED_LAYOUTS:
        return None
    frames = []
    for i in np.unique(np.linspace(0, len(seq) - 1, cfg.check_frames).astype(int)):
        try:
            frames.append(seq[int(i)])
        except FrameError:  # the run reports unreadable frames itself
            continue
    if not frames:
        return None
    try:
        fit = fit_colour_camera(frames, seq.intrinsics, ColourFitConfig())
    except ConfigError:  # no depth discontinuities: nothing to compare
        return None
    unregistered = fit_says_unregistered(fit, seq.intrinsics.width, cfg.check_min_gain_px,
                                         cfg.check_min_gain_fraction)
    return {"registered": not unregistered, "edge_distance_same_pixel_px": round(fit.edge_distance_same_pixel_px, 3),
            "edge_distance_fitted_px": round(fit.edge_distance_px, 3), "frames": len(frames)}


def colour_is_registered(seq, cfg: ColourRegistrationConfig) -> tuple[bool, dict | None]:
    """``(registered, check)``: whether ``seq``'s colour is taken as registered to depth (its layout's word, unless
    :func:`check_colour_registration` finds otherwise) and that check's report (``None``: not run)."""
    check = check_colour_registration(seq, cfg)
    return getattr(seq, "colour_registered", True) and (check is None or check["registered"]), check
