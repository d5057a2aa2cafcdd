"""The Python code blocks of the README and docs/ run as written, on a generated sequence in a scratch folder.

A block may open a sequence by a dataset's folder name (``rgbd_dataset_freiburg3_teddy``): every folder name a block
passes to ``open_sequence`` is generated there as a short synthetic sequence first, so the blocks cannot rot.
"""

from __future__ import annotations

import re

import pytest

from surfelslam.synth.writer import generate_sequence

from helpers import REPO

pytestmark = pytest.mark.slow

BLOCK = re.compile(r"```python\n(.*?)```", re.S)
SEQ_NAME = re.compile(r"open_sequence\(\s*\"([^\"]+)\"")


def _blocks() -> list[tuple[str, int, str]]:
    out = []
    for path in [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]:
        text = path.read_text()
        for m in BLOCK.finditer(text):
            out.append((path.relative_to(REPO).as_posix(), text[: m.start()].count("\n") + 1, m.group(1)))
    return out


def test_the_readme_has_a_python_example():
    assert any(name == "README.md" for name, _, _ in _blocks())


@pytest.fixture(scope="module")
def generated(tmp_path_factory):
    """One short synthetic sequence, generated once and linked under every name a block opens."""
    return generate_sequence(tmp_path_factory.mktemp("snippets") / "seq", "room", "slow", 12, "kinect", 0, 160, 120)


@pytest.mark.parametrize(("name", "line", "code"), _blocks(), ids=lambda v: str(v) if isinstance(v, int) else None)
def test_code_block_runs(name, line, code, tmp_path, monkeypatch, generated):
    monkeypatch.chdir(tmp_path)
    for seq in set(SEQ_NAME.findall(code)):
        (tmp_path / seq).symlink_to(generated, target_is_directory=True)
    exec(compile(code, f"{name}:{line}", "exec"), {"__name__": "__snippet__"})
