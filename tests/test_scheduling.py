"""``make test`` runs tests that share expensive work as xdist groups on one worker (``--dist loadgroup``)."""

from __future__ import annotations

import pytest


@pytest.mark.xdist_group("scheduling_check")
def test_grouped_tests_carry_their_group_under_loadgroup(request: pytest.FixtureRequest):
    """pytest-xdist marks a grouped test by appending ``@group`` to its node id; with a pytest that ignores the
    rewrite (9.2) every group is silently split across workers and shared fixtures run once per worker."""
    if not getattr(request.config.option, "loadgroup", False):
        pytest.skip("not under pytest-xdist --dist loadgroup (make test uses it)")
    assert request.node.nodeid.endswith("@scheduling_check"), request.node.nodeid
