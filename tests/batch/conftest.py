"""The batch tests' sequences: three tiny synthetic rooms (8 frames, 160x120, seeds 0-2), made once per session."""

from __future__ import annotations

from pathlib import Path

import pytest

from surfelslam.synth.writer import generate_sequence

TINY_FRAMES = 8
TINY_SIZE = (160, 120)


@pytest.fixture(scope="session")
def tiny_seqs(tmp_path_factory) -> list[Path]:
    root = tmp_path_factory.mktemp("batch_seqs")
    out = []
    for seed, name in enumerate(("roomA", "roomB", "roomC")):
        generate_sequence(root / name, "room", "slow", TINY_FRAMES, "kinect", seed, *TINY_SIZE)
        out.append(root / name)
    return out
