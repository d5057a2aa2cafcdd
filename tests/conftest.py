"""Shared fixtures: paths to the real sequences in ../shared/data (skipped with a reason when absent).

Plain helpers (the standard camera, ATE, ``shared_sequence``) live in ``tests/helpers.py``.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))  # `from helpers import ...` in every test folder

from helpers import shared_sequence  # noqa: E402


@pytest.fixture
def sevenscenes_path() -> Path:
    return shared_sequence("7scenes_redkitchen_0000_0499")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Long work first, so the parallel workers start on the long tests and finish on the short ones instead of one
    worker running a 30 s test at the end while the other is idle: the groups that share a module fixture or a
    cached run (marker ``xdist_group``: one worker runs the whole group, ``make test`` uses ``--dist loadgroup``),
    then the whole-sequence tests (marker ``slow``), then the rest."""
    items.sort(key=lambda item: (item.get_closest_marker("xdist_group") is None,
                                 item.get_closest_marker("slow") is None))
