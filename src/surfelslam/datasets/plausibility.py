"""Plausibility of a sequence's camera, checked when it is opened (cheap: a few depth images are read).

* **Intrinsics**: the principal point must lie in the image and the focal lengths ``|fx|``, ``|fy|`` within
  :data:`FOCAL_RANGE_IMAGE_WIDTHS` image widths. Values from ``--intrinsics`` or a metadata file that fail are
  refused (the message names the option, or the file and the option that overrides it); a layout's built-in
  default that does not fit the files' size (e.g. TUM's 640x480 camera on other images) is only a warning.
* **Depth scale**: the median valid depth of up to :data:`DEPTH_SAMPLE_FRAMES` frames spread over the
  selection must lie within :data:`PLAUSIBLE_DEPTH_RANGE_M` (an indoor RGB-D sensor); outside, or without any
  valid pixel, the sequence is refused naming ``--depth-scale`` and the value used.

``policy="warn"`` (``surfelslam info``, a diagnosis) records every finding in ``seq.warnings`` instead.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from surfelslam.datasets.base import RGBDSequence
from surfelslam.errors import ConfigError, DatasetError, FrameError

#: Accepted focal lengths |fx|, |fy| in image widths [W]: 0.1 W is a 157 deg field of view, 100 W 0.6 deg.
FOCAL_RANGE_IMAGE_WIDTHS = (0.1, 100.0)
#: Accepted median valid depth of the sampled frames [m] (indoor RGB-D sensors: about 0.3-10 m).
PLAUSIBLE_DEPTH_RANGE_M = (0.1, 20.0)
#: Frames whose depth is sampled, spread evenly over the selection.
DEPTH_SAMPLE_FRAMES = 5
#: Refuse (raise) or only record findings in ``seq.warnings``.
POLICIES = ("refuse", "warn")


def number(x: float) -> str:
    """A value as the user would type it: ``1000000`` (not ``1e+06``), ``79.5``."""
    return str(int(x)) if float(x).is_integer() and abs(x) < 1e15 else f"{x:g}"


@dataclass(frozen=True)
class Finding:
    """One implausible value: ``message`` names the option; ``path`` is the file or folder to name."""

    path: Path
    message: str
    refuse: bool


def intrinsics_findings(seq: RGBDSequence) -> list[Finding]:
    """The principal point outside the image, or a focal length out of range (at the files' resolution)."""
    intr = seq.full_intrinsics
    w, h = intr.width, intr.height
    problems = []
    if not (0.0 <= intr.cx <= w and 0.0 <= intr.cy <= h):
        problems.append(f"the principal point ({number(intr.cx)}, {number(intr.cy)}) is outside the {w}x{h} image")
    lo, hi = FOCAL_RANGE_IMAGE_WIDTHS
    for name, f in (("fx", intr.fx), ("fy", intr.fy)):
        if not lo * w <= abs(f) <= hi * w:
            problems.append(f"{name} = {number(f)} px is outside {lo:g}-{hi:g} image widths "
                            f"({lo * w:g}-{hi * w:g} px)")
    if not problems:
        return []
    values = ",".join(number(v) for v in (intr.fx, intr.fy, intr.cx, intr.cy))
    what = "; ".join(problems)
    kind = seq.intrinsics_kind
    if kind == "option":
        return [Finding(seq.root, f"--intrinsics {values}: {what}; give fx,fy,cx,cy in pixels at the files' "
                                  f"resolution ({w}x{h})", True)]
    if kind == "topic":  # a bag's CameraInfo
        return [Finding(seq.root, f"intrinsics {values} from the {seq.intrinsics_source}: {what}; override them with "
                                  f"--intrinsics (fx,fy,cx,cy at {w}x{h})", True)]
    if kind == "file":
        source = seq.root / seq.intrinsics_source
        return [Finding(source, f"intrinsics {values}: {what}; fix the file or override it with --intrinsics "
                                f"(fx,fy,cx,cy at {w}x{h})", True)]
    return [Finding(seq.root, f"the {seq.layout} layout's default intrinsics {values} do not fit the {w}x{h} "
                              f"images ({what}); give --intrinsics", False)]


def _sample_positions(n: int, k: int = DEPTH_SAMPLE_FRAMES) -> list[int]:
    return sorted({int(round(x)) for x in np.linspace(0, n - 1, min(k, n))})


def depth_findings(seq: RGBDSequence) -> list[Finding]:
    """The median valid depth of a few frames outside :data:`PLAUSIBLE_DEPTH_RANGE_M`, or no valid depth."""
    medians, read = [], []
    for i in _sample_positions(len(seq.entries)):
        path = seq.entries[i].depth_path
        try:
            raw = seq.read_depth_raw(i)
        except FrameError:
            continue  # reported when the frame is loaded
        read.append(path)
        valid = np.isfinite(raw) & (raw > 0)
        for bad in seq.depth_invalid_raw:
            valid &= raw != bad
        if valid.any():
            medians.append(float(np.median(raw[valid])) / seq.depth_scale)
    if not read:
        return []  # nothing readable: the frames report themselves
    names = ", ".join(p.name for p in read)
    scale = f"--depth-scale {number(seq.depth_scale)} units per metre (from {seq.depth_scale_source})"
    if not medians:
        return [Finding(seq.root, f"no valid depth pixel in the {len(read)} depth images sampled ({names}); "
                                  f"check the depth files and {scale}", True)]
    med = float(np.median(medians))
    lo, hi = PLAUSIBLE_DEPTH_RANGE_M
    if lo <= med <= hi:
        return []
    return [Finding(seq.root, f"the median valid depth of {len(medians)} sampled frames is {med:.3g} m, outside "
                              f"{lo:g}-{hi:g} m: the depth scale looks wrong ({scale}; TUM uses 5000, millimetres "
                              "1000)", True)]


def check_plausibility(seq: RGBDSequence, policy: str = "refuse") -> None:
    """Check the camera of an opened sequence (module docstring).

    Raises:
        DatasetError: with ``policy="refuse"``, the first refusable finding (naming the option or file).
        ConfigError: unknown ``policy``.
    Findings not raised are appended to ``seq.warnings``.
    """
    if policy not in POLICIES:
        raise ConfigError(f"plausibility policy must be one of {', '.join(POLICIES)}, got {policy!r}")
    for check in (intrinsics_findings, depth_findings):
        for finding in check(seq):
            if finding.refuse and policy == "refuse":
                raise DatasetError(finding.path, finding.message)
            seq.warnings.append(f"{finding.path}: {finding.message}")
