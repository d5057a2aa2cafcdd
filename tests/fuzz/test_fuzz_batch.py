"""Fuzzing the batch specs: a mutated or random spec file (``surfelslam batch SPEC``) and the inline form (``SEQ...
--tracker a,b --set KEY=V1,V2``), loaded and expanded into jobs. A valid result is a list of jobs with checked
configs, one run folder each below the output folder."""

from __future__ import annotations

from pathlib import Path

from fuzzkit import example_dir, is_error, outcome, text_or_bytes, unchanged
from hypothesis import example, given
from hypothesis import strategies as st

from surfelslam.batch.spec import expand_jobs, inline_spec, load_spec
from surfelslam.config import validate
from surfelslam.slam import TRACKERS

SPEC = """\
sequences = ["data/fr1_xyz", "data/fr1_desk"]
trackers = ["dense", "hybrid"]
base = "fast"

[dataset]
end = 300
stride = 2

[[configs]]
name = "default"

[[configs]]
name = "more-inliers"
set = ["icp.min_inliers=321"]

[[configs]]
name = "nested"
icp = { min_inliers = 123 }
"""


def check_jobs(jobs, out_root: Path) -> None:
    names = [j.name for j in jobs]
    assert len(set(names)) == len(names), "two jobs share a run folder"
    for j in jobs:
        assert j.tracker in TRACKERS
        validate(j.config)
        assert Path(j.sequence).is_absolute()
        assert Path(j.folder).resolve().parent == out_root.resolve(), f"run folder {j.folder} outside {out_root}"


def load_and_expand(path: Path) -> None:
    out_root = path.parent / "out"
    with unchanged(path.parent):
        spec = outcome(lambda: load_spec(path))
        if is_error(spec):
            return
        jobs = outcome(lambda: expand_jobs(spec, out_root))
    if not is_error(jobs):
        check_jobs(jobs, out_root)


def test_seed_is_valid(tmp_path):
    path = tmp_path / "spec.toml"
    path.write_text(SPEC)
    jobs = expand_jobs(load_spec(path), tmp_path / "out")
    check_jobs(jobs, tmp_path / "out")
    assert len(jobs) == 2 * 2 * 3


@given(content=text_or_bytes(SPEC))
@example(content=b"sequences = ['a']\n\xff\xfe")  # found: invalid UTF-8 was a UnicodeDecodeError
@example(content=b'sequences = ["a\\u0000b", "~nosuchuser/seq"]')  # found: ValueError / RuntimeError
@example(content=b'sequences = ["a"]\nbase = "x\\u0000y.toml"')  # found: ValueError (embedded null byte)
@example(content=b'sequences = ["a"]\n[[configs]]\nname = "x\\ny"\n[[configs]]\nname = "x\\ny"\n')
def test_mutated_spec_file(tmp_path, content):
    path = example_dir(tmp_path) / "spec.toml"
    path.write_bytes(content)
    load_and_expand(path)


@given(content=st.one_of(st.binary(max_size=200), st.text(max_size=200).map(str.encode)))
def test_random_spec_file(tmp_path, content):
    path = example_dir(tmp_path) / "spec.toml"
    path.write_bytes(content)
    load_and_expand(path)


_NAME = st.one_of(st.sampled_from(("seq", "a/seq", "b/seq", ".", "..", "", " ", "fr1_xyz", "~", "x" * 300)),
                  st.text(max_size=12))
_SET = st.one_of(
    st.sampled_from(("icp.min_inliers=300,500", "icp.min_inliers=300,300", "icp.max_iterations=10",
                     "icp.min_inliers=", "icp.min_inliers", "=1", "icp.min_inliers=[1,2],3", "tracker=dense,orb",
                     "icp.min_inliers=nan,inf", "icp=1", "icp.min_inliers=\"a,b\"", "dataset.gt=a,b")),
    st.text(max_size=20))


@given(sequences=st.lists(_NAME, max_size=3), trackers=st.one_of(st.none(), st.text(max_size=15),
                                                                  st.sampled_from(("dense,hybrid", "orb", ",", ""))),
       sets=st.lists(_SET, max_size=3))
@example(sequences=["a\x00b"], trackers=None, sets=[])  # found: ValueError (embedded null byte)
@example(sequences=["~nosuchuser/seq"], trackers=None, sets=[])  # found: RuntimeError (no home directory)
@example(sequences=["a/\n", "b/\n"], trackers=None, sets=[])  # found: the paths' line breaks split the message
def test_inline_spec(tmp_path, sequences, trackers, sets):
    out_root = example_dir(tmp_path) / "out"
    with unchanged(tmp_path):
        spec = outcome(lambda: inline_spec(sequences, trackers, sets))
        if is_error(spec):
            return
        jobs = outcome(lambda: expand_jobs(spec, out_root))
    if not is_error(jobs):
        check_jobs(jobs, out_root)
