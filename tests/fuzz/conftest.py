"""Property-based fuzzing of the readers and loaders (hypothesis): the budget profiles, and the check that a test
writes nothing outside its own temp folder.

Profiles (``--hypothesis-profile NAME``, hypothesis's own pytest option):

* ``fast`` (the default, used by ``make test``): few examples, derandomized (the same examples on every run), so that
  the whole folder takes seconds;
* ``fuzz`` (``make fuzz``): many random examples, within the 10 minutes of the target on two cores.

Neither keeps hypothesis's example database (``database=None``), and its caches go to the temp folder: nothing is
written into the repository.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import pytest
from hypothesis import HealthCheck, settings
from hypothesis.configuration import set_hypothesis_home_dir

#: the longest one example may take before hypothesis reports it as too slow [ms] (a call that never returns is
#: stopped by :data:`fuzzkit.HANG_LIMIT_S`); generous because two cores are shared by the whole suite
DEADLINE_MS = 20_000
#: examples per test of each profile
FAST_EXAMPLES = 12
FUZZ_EXAMPLES = 500

_COMMON = dict(
    database=None,
    deadline=DEADLINE_MS,
    # each example makes its own folder below the test's tmp_path (fuzzkit.example_dir); seeds are built once
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow, HealthCheck.data_too_large],
)
# hypothesis's caches (extracted constants, unicode tables) go to the temp folder, not into the repository's .hypothesis
set_hypothesis_home_dir(Path(tempfile.gettempdir()) / f"surfelslam-hypothesis-{os.getuid()}")
settings.register_profile("fast", max_examples=FAST_EXAMPLES, derandomize=True, print_blob=False, **_COMMON)
settings.register_profile("fuzz", max_examples=FUZZ_EXAMPLES, print_blob=True, **_COMMON)  # a find can be replayed
# no --hypothesis-profile given: hypothesis's own default, or its "ci" profile, which it loads by itself where CI is
# set (CI=true, as in .ci/run's environment) and which keeps the health checks this folder's tests opt out of
if settings.get_current_profile_name() in ("default", "ci"):
    settings.load_profile("fast")


@pytest.fixture(autouse=True)
def _cwd_untouched(tmp_path, monkeypatch):
    """Every fuzz test runs in an empty working folder that must stay empty: relative paths a reader might write to
    land there and fail the test."""
    cwd = tmp_path / "cwd"
    cwd.mkdir()
    monkeypatch.chdir(cwd)
    yield cwd
    left = sorted(os.listdir(cwd))
    assert not left, f"written into the working folder: {left}"
    assert Path.cwd() == cwd, f"the working folder changed to {Path.cwd()}"
