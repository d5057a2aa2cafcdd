"""Fixtures of the fault-injection suite: one tiny synthetic sequence per session, copied before a test breaks it,
and the check every case makes: the exit code, exactly one line on stderr naming the file or option, no traceback."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from surfelslam.synth.writer import generate_sequence

N_FRAMES = 10
WIDTH, HEIGHT = 160, 120


@pytest.fixture(scope="session")
def synth_seq(tmp_path_factory) -> Path:
    """10 noisy frames of the 'room' scene at 160x120 (TUM layout with ground truth, INFO.txt camera)."""
    out = tmp_path_factory.mktemp("faults") / "room"
    generate_sequence(out, scene="room", style="handheld", n_frames=N_FRAMES, noise="kinect", seed=3,
                      width=WIDTH, height=HEIGHT)
    return out


@pytest.fixture
def seq(synth_seq, tmp_path) -> Path:
    """A private copy of the synthetic sequence, free to break."""
    return Path(shutil.copytree(synth_seq, tmp_path / "seq"))
