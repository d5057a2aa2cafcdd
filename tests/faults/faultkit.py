"""Checks shared by the fault-injection tests (imported as ``from faultkit import ...``)."""

from __future__ import annotations

from pathlib import Path

from typer.testing import CliRunner


def cli(*args) -> object:
    """``surfelslam ARGS`` in-process (stdout and stderr apart)."""
    from surfelslam.cli import app

    return CliRunner().invoke(app, [str(a) for a in args])


def assert_one_line(res, code: int, *fragments: str) -> str:
    """Exit ``code``, exactly one non-empty stderr line holding every fragment, no traceback anywhere."""
    out = res.stdout + res.stderr
    assert res.exit_code == code, f"exit {res.exit_code} (want {code}): {out}"
    assert "Traceback" not in out, out
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, res.stderr
    for frag in fragments:
        assert frag in lines[0], f"{frag!r} not in {lines[0]!r}"
    return lines[0]


def no_temp_files(folder: Path) -> bool:
    return not [p for p in Path(folder).rglob("*") if p.name.endswith(".tmp")]


def index_rows(path: Path) -> list[str]:
    return [ln for ln in path.read_text().splitlines() if ln.strip() and not ln.startswith("#")]
