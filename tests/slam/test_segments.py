"""Weak and lost stretches of a run: the segment summary in metrics.json and on the console."""

from __future__ import annotations

from surfelslam.slam.frame import FrameStatus as S
from surfelslam.slam.segments import segments_report, tracking_segments


def _frames(codes: str, reason: str = "degenerate"):
    """One frame per character: t tracked, w weak, h held, l lost, b bridged, r relocalised."""
    status = {"t": S.TRACKED, "w": S.WEAK, "h": S.HELD, "l": S.LOST, "b": S.BRIDGED, "r": S.RELOCALISED}
    return [(i, i / 30.0, status[c], None if c in "tr" else reason) for i, c in enumerate(codes)]


def test_segments_name_their_frames_reason_and_recovery():
    segs = tracking_segments(_frames("ttwwwtllbbrttll", "too_few_inliers"))
    assert [(s.kind, s.first_frame, s.last_frame, s.frames, s.bridged_frames, s.recovery) for s in segs] == [
        ("weak", 2, 4, 3, 0, "tracking resumed"),
        ("lost", 6, 9, 4, 2, "relocalised"),
        ("lost", 13, 14, 2, 0, "not recovered"),
    ]
    assert segs[1].reason == "too_few_inliers" and abs(segs[1].first_stamp - 0.2) < 1e-12
    assert segs[1].describe() == ("tracking lost 6-9 (4 frames, too_few_inliers); 2 bridged by features; relocalised")
    rep = segments_report(segs)
    assert rep["lost_segments"] == 2 and rep["weak_segments"] == 1 and rep["lost_at_end"] is True


def test_a_weak_stretch_that_turns_lost_is_two_segments_and_a_clean_run_has_none():
    segs = tracking_segments(_frames("twwllt"))
    assert [(s.kind, s.first_frame, s.last_frame, s.recovery) for s in segs] == [
        ("weak", 1, 2, "then lost"), ("lost", 3, 4, "tracking resumed")]
    assert segments_report(segs)["lost_at_end"] is False
    assert segments_report(tracking_segments(_frames("ttttr"))) == {
        "tracking_segments": [], "lost_segments": 0, "weak_segments": 0, "lost_at_end": False}


def test_held_frames_are_weak_stretches_not_lost_ones():
    segs = tracking_segments(_frames("tthhhtwhlt", "implausible_correction"))
    assert [(s.kind, s.first_frame, s.last_frame, s.frames, s.recovery) for s in segs] == [
        ("weak", 2, 4, 3, "tracking resumed"), ("weak", 6, 7, 2, "then lost"), ("lost", 8, 8, 1, "tracking resumed")]
    assert segments_report(segs)["lost_segments"] == 1
