"""Options named alike across commands (issue 70.5): --sequence for rerun and mesh (rerun keeps --seq), and synth's
--progress/--no-progress as run's."""

from __future__ import annotations

import pytest
from typer.testing import CliRunner

from surfelslam.cli import _load_command, app


def _options(command: str) -> set[str]:
    cmd = _load_command(command)
    return {o for p in cmd.params for o in (*getattr(p, "opts", ()), *getattr(p, "secondary_opts", ()))}


@pytest.mark.parametrize(("command", "wanted"), [("rerun", {"--sequence", "--seq"}), ("mesh", {"--sequence"}),
                                                 ("synth", {"--progress", "--no-progress"}),
                                                 ("run", {"--progress", "--no-progress"})])
def test_commands_share_option_names(command, wanted):
    assert wanted - _options(command) == set()


@pytest.mark.parametrize(("flag", "expected"), [("--no-progress", False), ("--progress", True), (None, True)])
def test_synth_passes_the_progress_choice(tmp_path, monkeypatch, flag, expected):
    seen = {}

    def fake_generate(out, **kwargs):
        seen.update(kwargs)
        return out

    monkeypatch.setattr("surfelslam.synth.writer.generate_sequence", fake_generate)
    res = CliRunner().invoke(app, ["synth", str(tmp_path / "seq"), "--frames", "2", *([flag] if flag else [])])
    assert res.exit_code == 0, res.output
    assert seen["progress"] is expected
