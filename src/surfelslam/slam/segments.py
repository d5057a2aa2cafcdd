"""Stretches of a run where tracking was weak or lost, from the per-frame statuses.

A run reports every such stretch (first and last frame, what went wrong, how it ended) in ``metrics.json`` and on
the console, so that a trajectory with a bad stretch never looks like a clean one. Frames are
:class:`~surfelslam.slam.frame.FrameStatus` values: ``weak`` frames (registered along the constrained directions
only) and ``held`` frames (posed at the motion prediction, their registration refused as a jump) form ``weak``
segments; ``lost`` and ``bridged`` frames (not registered) form ``lost`` segments.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import asdict, dataclass

from surfelslam.slam.frame import FrameStatus

_KIND = {FrameStatus.WEAK: "weak", FrameStatus.HELD: "weak", FrameStatus.LOST: "lost",
         FrameStatus.BRIDGED: "lost"}


@dataclass
class Segment:
    """One stretch of consecutive weak (or lost) frames.

    Attributes:
        kind: ``weak`` (pose held by the motion prior along some directions) or ``lost`` (no registration).
        first_frame, last_frame: frame indices (inclusive); ``first_stamp`` / ``last_stamp`` their timestamps (s).
        frames: number of frames.
        reason: the most frequent reason the frames give (e.g. ``degenerate``, ``too_few_inliers``).
        bridged_frames: lost frames whose pose came from the features (PnP) rather than the prediction.
        recovery: ``tracking resumed``, ``relocalised`` or ``not recovered`` (the run ended in it).
    """

    kind: str
    first_frame: int
    last_frame: int
    first_stamp: float
    last_stamp: float
    frames: int
    reason: str
    bridged_frames: int
    recovery: str

    def describe(self) -> str:
        """One line, e.g. ``tracking lost 950-1020 (71 frames, too_few_inliers); 40 bridged by features;
        relocalised``."""
        what = "weak" if self.kind == "weak" else "lost"
        text = (f"tracking {what} {self.first_frame}-{self.last_frame} ({self.frames} frames, {self.reason})")
        if self.bridged_frames:
            text += f"; {self.bridged_frames} bridged by features"
        return f"{text}; {self.recovery}"


def tracking_segments(frames: list[tuple[int, float, str, str | None]]) -> list[Segment]:
    """The weak and lost segments of a run from its ``(index, timestamp, status, reason)`` per frame, in order."""
    out: list[Segment] = []
    run: list[tuple[int, float, str, str | None]] = []

    def close(recovery: str) -> None:
        if not run:
            return
        reasons = Counter(r or "unknown" for _, _, _, r in run)
        bridged = sum(1 for _, _, s, _ in run if s == FrameStatus.BRIDGED)
        out.append(Segment(_KIND[FrameStatus(run[0][2])], run[0][0], run[-1][0], run[0][1], run[-1][1], len(run),
                           reasons.most_common(1)[0][0], bridged, recovery))
        run.clear()

    for item in frames:
        kind = _KIND.get(FrameStatus(item[2]))
        if run and kind != _KIND[FrameStatus(run[0][2])]:
            close("relocalised" if item[2] == FrameStatus.RELOCALISED else
                  "tracking resumed" if kind is None else f"then {kind}")
        if kind is not None:
            run.append(item)
    close("not recovered")
    return out


def segments_report(segments: list[Segment]) -> dict:
    """``metrics.json`` fields: every segment, their counts, and whether the run ended lost."""
    lost = [s for s in segments if s.kind == "lost"]
    return {
        "tracking_segments": [asdict(s) for s in segments],
        "lost_segments": len(lost),
        "weak_segments": len(segments) - len(lost),
        "lost_at_end": bool(lost) and lost[-1].recovery == "not recovered",
    }
