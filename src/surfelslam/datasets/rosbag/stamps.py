"""Checking the header stamps of a bag's colour and depth topics before pairing (see :mod:`surfelslam.datasets.rosbag`).

Frames are paired and timed by header stamps, so stamps the driver did not set (all zero), a repeated stamp or a
stamp going backwards would silently merge or drop frames. Each is counted and reported as a warning line:

* **unusable** (more than :data:`UNUSABLE_STAMP_FRACTION` of a camera topic's messages repeat an earlier stamp,
  e.g. a driver that leaves them at zero): both camera topics take the bag's record (receive) times instead;
* otherwise a message repeating an earlier stamp is left out, and stamps going backwards are taken in stamp order;
  the counts are in the warning.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from surfelslam.datasets.rosbag.topics import stamp_seconds

#: Above this fraction of a camera topic's messages repeating an earlier header stamp, the driver is taken as not
#: setting stamps: record times replace them (a few repeats are a glitch: those messages are left out instead).
UNUSABLE_STAMP_FRACTION = 0.1
_NS_PER_S = 1_000_000_000


def record_seconds(log_ns: int) -> float:
    """A bag record time (ns) in seconds, as :func:`~surfelslam.datasets.rosbag.topics.stamp_seconds` reads one."""
    return stamp_seconds(int(log_ns) // _NS_PER_S, int(log_ns) % _NS_PER_S)


def stamp_faults(stamps: list[float]) -> dict[str, int]:
    """Counts among header stamps ``(N,)`` in receive order: ``repeated`` (a stamp seen before, zero included),
    ``zero`` (zero or negative: not set by the driver; counted when more than one) and ``backwards`` (earlier than
    the message received before it)."""
    st = np.asarray(stamps, np.float64)
    unset = int(np.sum(st <= 0))
    backwards = int(np.sum(np.diff(st) < 0)) if len(st) > 1 else 0
    return {"repeated": int(len(st) - len(np.unique(st))), "zero": unset if unset > 1 else 0, "backwards": backwards}


def usable_mask(stamps: list[float]) -> np.ndarray:
    """``(N,)`` bool: the messages kept (the first, in receive order, of each stamp)."""
    st = np.asarray(stamps, np.float64)
    _, first = np.unique(st, return_index=True)
    once = np.zeros(len(st), bool)
    once[first] = True
    return once


def check_camera_stamps(root: Path, topics: list) -> list[str]:
    """Check the header stamps of the camera ``topics`` (:class:`~.index.TopicIndex`, filled by the scan); when a
    topic's are unusable, replace every camera topic's ``stamps`` with its record times (``header_stamps`` keep the
    headers' values, which find the messages again). Returns the warning lines (one per fault found)."""
    notes: list[str] = []
    faults = {ti.name: stamp_faults(ti.stamps) for ti in topics}
    bad = [ti for ti in topics if ti.count
           and faults[ti.name]["repeated"] > UNUSABLE_STAMP_FRACTION * ti.count]
    if bad:
        for ti in topics:
            ti.header_stamps = list(ti.stamps)
            ti.stamps = [record_seconds(ns) for ns in ti.log_ns]
        why = "; ".join(f"{ti.name}: {_fault_text(faults[ti.name], ti.count)}" for ti in bad)
        notes.append(f"{root}: header stamps unusable ({why}): the frames take the bag's record times instead")
        faults = {ti.name: stamp_faults(ti.stamps) for ti in topics}
    for ti in topics:
        f = faults[ti.name]
        if f["repeated"]:
            notes.append(f"{root}: {ti.name}: {f['repeated']} of {ti.count} messages left out "
                         f"({_fault_text(f, ti.count)})")
        if f["backwards"]:
            notes.append(f"{root}: {ti.name}: {f['backwards']} of {ti.count} messages stamped earlier than the "
                         "message recorded before them (taken in stamp order)")
    return notes


def _fault_text(f: dict[str, int], count: int) -> str:
    text = f"{f['repeated']} of {count} repeat an earlier stamp"
    return text + (f", {f['zero']} of {count} stamps zero" if f["zero"] else "")
