"""A few of the fuzz inputs through the command line, in-process: ``info`` on a mutated sequence folder and bag,
``eval`` on mutated trajectories, ``run`` with a mutated ``--config`` and ``--set``. The property: exit 0, or exactly
one line on stderr with exit code 2 (1 would be an internal error) and no traceback; files only in ``--out``."""

from __future__ import annotations

from pathlib import Path

import pytest
from fuzzkit import copy_seed, example_dir, make_tum_seed, mutated_bytes, text_or_bytes, tree, unchanged
from hypothesis import example, given, settings
from hypothesis import strategies as st
from test_fuzz_config import LEAF_KEYS, SET_VALUES
from test_fuzz_trajectory import EST_TEXT, GT_TEXT
from typer.testing import CliRunner

from surfelslam.config import dumps_toml
from surfelslam.datasets import open_sequence
from surfelslam.datasets.rosbag.write import write_bag
from surfelslam.slam import SlamConfig

#: exit code of a command refusing its input (tools/common.py EXIT_BAD_INPUT)
EXIT_BAD_INPUT = 2
#: the CLI examples cost more (the command's set-up each time): a fraction of the profile's examples
CLI_EXAMPLES_SHARE = 0.5


def cli(*args: object):
    from surfelslam.cli import app

    return CliRunner().invoke(app, [str(a) for a in args])


def assert_clean_exit(res) -> None:
    """Exit 0, or one ``error:`` line on stderr with exit code 2; never a traceback or an internal error."""
    out = res.stdout + res.stderr
    assert "Traceback" not in out, out
    if res.exit_code == 0:
        return
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert res.exit_code == EXIT_BAD_INPUT, f"exit {res.exit_code}: {res.stderr}"
    assert len(lines) == 1 and lines[0].startswith("error:"), res.stderr


def fewer_examples(test):
    """The profile's settings with a share of its examples (the CLI path repeats what the library tests cover)."""
    current = settings()
    return settings(current, max_examples=max(2, int(current.max_examples * CLI_EXAMPLES_SHARE)))(test)


@pytest.fixture(scope="module")
def seeds(tmp_path_factory) -> dict[str, Path]:
    base = tmp_path_factory.mktemp("cli")
    folder = make_tum_seed(base / "seq")
    return {"tum": folder, "bag": write_bag(open_sequence(folder), base / "seq.bag", "ros1")}


@fewer_examples
@given(data=st.data(), name=st.sampled_from(("rgb.txt", "depth.txt", "groundtruth.txt", "INFO.txt")))
def test_info_on_a_mutated_folder(seeds, tmp_path, data, name):
    root = copy_seed(seeds["tum"], tmp_path)
    (root / name).write_bytes(data.draw(text_or_bytes((root / name).read_text())))
    with unchanged(root):
        assert_clean_exit(cli("info", root))


@fewer_examples
@given(data=st.data())
def test_info_on_a_mutated_bag(seeds, tmp_path, data):
    path = copy_seed(seeds["bag"], tmp_path)
    path.write_bytes(data.draw(mutated_bytes(path.read_bytes(), max_ops=3)))
    with unchanged(path.parent):
        assert_clean_exit(cli("info", path))


@fewer_examples
@given(est=text_or_bytes(EST_TEXT), gt=text_or_bytes(GT_TEXT), max_diff=st.sampled_from(("0.02", "-1", "nan", "1e400")))
def test_eval_on_mutated_trajectories(tmp_path, est, gt, max_diff):
    folder = example_dir(tmp_path)
    (folder / "est.txt").write_bytes(est)
    (folder / "gt.txt").write_bytes(gt)
    before = tree(folder)
    res = cli("eval", folder / "est.txt", folder / "gt.txt", "--out", folder / "out", "--no-figures",
              "--max-diff", max_diff)
    assert_clean_exit(res)
    written = {k for k in tree(folder) if k not in before}
    assert all(k == "out" or k.startswith("out/") for k in written), written


@fewer_examples
@given(content=text_or_bytes(dumps_toml(SlamConfig())),
       sets=st.lists(st.tuples(st.sampled_from(LEAF_KEYS), SET_VALUES).map(lambda kv: f"{kv[0]}={kv[1]}"),
                     max_size=2))
# found by make fuzz: a record separator (one of str.splitlines' line breaks) in a --set value split the message
@example(content=dumps_toml(SlamConfig()).encode(), sets=["colour_registration.check=\x1e"])
@example(content=dumps_toml(SlamConfig()).encode(), sets=["tracker=a\u2028b"])
def test_run_with_a_mutated_config(tmp_path, content, sets):
    """``run`` refuses the config or, when it is valid, the missing sequence: one line either way."""
    folder = example_dir(tmp_path)
    (folder / "config.toml").write_bytes(content)
    args = ["run", folder / "no-such-sequence", "--config", folder / "config.toml", "--out", folder / "out",
            "--no-figures", "--no-progress"]
    for item in sets:
        args += ["--set", item]
    res = cli(*args)
    assert_clean_exit(res)
    assert res.exit_code == EXIT_BAD_INPUT
    assert not (folder / "out").exists() or not any((folder / "out").iterdir())
