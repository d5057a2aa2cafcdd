"""Shared fixtures: paths to the real sequences in ../shared/data (skipped with a reason when absent)."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"


def shared_sequence(name: str) -> Path:
    """Path of ../shared/data/<name>; skips the test when it is not there."""
    path = SHARED_DATA / name
    if not path.is_dir():
        pytest.skip(f"real data not available: {path} is absent (needs ../shared beside the repo)")
    return path


@pytest.fixture
def sevenscenes_path() -> Path:
    return shared_sequence("7scenes_redkitchen_0000_0499")
