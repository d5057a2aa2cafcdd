"""The command line: lazy start-up, --version, help texts with brackets, Ctrl-C at any moment (exit 130), unexpected
errors as one line (exit 1), numba's cache on a read-only install."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
import typer
from faultkit import assert_one_line, cli
from typer.testing import CliRunner

import surfelslam
from surfelslam import cli as cli_module
from surfelslam import numba_cache
from surfelslam.tools.common import handle_errors

HEAVY = ("numba", "cv2", "matplotlib", "evo", "surfelslam.datasets", "surfelslam.tools.run", "surfelslam.kernels")


def _python(code: str, env: dict | None = None, timeout: float = 60, unset: tuple[str, ...] = ()
            ) -> subprocess.CompletedProcess:
    """Run ``code`` in a fresh interpreter with the caller's environment, ``env`` added and ``unset`` removed."""
    full = {**os.environ, **(env or {})}
    for name in ("SURFELSLAM_DEBUG", *unset):
        full.pop(name, None)
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True,
                          env=full, timeout=timeout)


@pytest.fixture
def restore_sigint():
    old = signal.getsignal(signal.SIGINT)
    yield
    signal.signal(signal.SIGINT, old)


# ---------------------------------------------------------------------------------------- start-up, help
def test_version():
    res = cli("--version")
    assert res.exit_code == 0 and res.stdout.strip() == f"surfelslam {surfelslam.__version__}"


def test_help_imports_no_command_module():
    res = _python(f"""
        import json, sys
        from surfelslam import cli
        try:
            cli.main(["--help"])
        except SystemExit as exc:
            code = exc.code
        print(json.dumps({{"code": code, "heavy": [m for m in {HEAVY!r} if m in sys.modules]}}), file=sys.stderr)
    """)
    report = json.loads(res.stderr.strip().splitlines()[-1])
    assert report == {"code": 0, "heavy": []}, res.stderr
    for name in cli_module.COMMANDS:
        assert f"\n  {name} " in res.stdout


#: What a command's --help must not import: the library's heavy dependencies, and pydantic (typer's value coercion,
#: which only the options given need)
HELP_HEAVY = ("numpy", "scipy", "numba", "cv2", "matplotlib", "evo", "pydantic", "surfelslam.datasets",
              "surfelslam.kernels", "surfelslam.slam", "surfelslam.api")


def test_each_commands_help_is_light():
    res = _python(f"""
        import json, sys
        from surfelslam import cli
        report = {{}}
        for name in cli.COMMANDS:
            try:
                cli.main([name, "--help"])
            except SystemExit as exc:
                code = exc.code
            report[name] = [code, [m for m in {HELP_HEAVY!r} if m in sys.modules]]
        print(json.dumps(report), file=sys.stderr)
    """)
    report = json.loads(res.stderr.strip().splitlines()[-1])
    assert report == {name: [0, []] for name in cli_module.COMMANDS}, res.stderr
    assert res.stdout.count("Show this message and exit.") == len(cli_module.COMMANDS)


def test_eval_default_window_is_the_metrics_one():
    from surfelslam.eval.metrics import DEFAULT_MAX_DIFF_S
    from surfelslam.tools.eval import MAX_DIFF_DEFAULT_S

    assert MAX_DIFF_DEFAULT_S == DEFAULT_MAX_DIFF_S == 0.02


def test_run_help_describes_every_tracker():
    from surfelslam.slam import TRACKERS
    from surfelslam.tools.run import TRACKER_HELP

    assert len(TRACKERS) == 3 and all(f"{name}: " in TRACKER_HELP for name in TRACKERS)


def test_listed_help_is_each_commands_docstring():
    app = cli_module.get_app()
    group = typer.main.get_command(app)
    ctx = group.make_context("surfelslam", ["info"])
    for name, (module, short) in cli_module.COMMANDS.items():
        cmd = group.get_command(ctx, name)
        assert cmd is not None and cmd.name == name, module
        first_paragraph = " ".join(cmd.help.split("\n\n")[0].split())
        assert first_paragraph == short, name


@pytest.mark.parametrize("command, text", [
    ("run", "Sample images [::N, ::N] (intrinsics / N)."),
    ("eval", "Max timestamp difference for association [s]."),
    ("rerun", "pip install 'surfelslam[viz]'"),
])
def test_help_keeps_brackets(command, text):
    res = cli(command, "--help")
    assert res.exit_code == 0
    assert text in " ".join(res.stdout.split())


# ---------------------------------------------------------------------------------------- unexpected errors
def _failing_app(exc: BaseException) -> typer.Typer:
    app = typer.Typer()

    @app.command("boom")
    @handle_errors
    def boom() -> None:
        raise exc

    @app.command("noop")
    def noop() -> None:
        pass

    return app


def test_unexpected_exception_is_one_line_exit_1(monkeypatch):
    monkeypatch.delenv("SURFELSLAM_DEBUG", raising=False)
    res = CliRunner().invoke(_failing_app(RuntimeError("kernel blew up\nsecond line")), ["boom"])
    assert_one_line(res, 1, "error: internal error: RuntimeError: kernel blew up second line (please report")


def test_debug_env_keeps_the_traceback(monkeypatch):
    monkeypatch.setenv("SURFELSLAM_DEBUG", "1")
    res = CliRunner().invoke(_failing_app(RuntimeError("kernel blew up")), ["boom"])
    assert isinstance(res.exception, RuntimeError)


def test_error_outside_any_command_is_one_line(monkeypatch, capsys):
    monkeypatch.delenv("SURFELSLAM_DEBUG", raising=False)
    monkeypatch.setitem(cli_module.COMMANDS, "broken", ("no_such_module", "A command whose module is missing."))
    with pytest.raises(SystemExit) as exit_:
        cli_module.main(["broken"])
    assert exit_.value.code == 1
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1 and err[0].startswith("error: internal error: ModuleNotFoundError: ")


def test_ctrl_c_inside_a_command(restore_sigint):
    res = CliRunner().invoke(_failing_app(KeyboardInterrupt()), ["boom"])
    assert_one_line(res, 130, "interrupted")


# ---------------------------------------------------------------------------------------- Ctrl-C, real signals
SIGINT_SELF = "import os, signal; os.kill(os.getpid(), signal.SIGINT)"
#: Seconds into a run with an empty kernel cache: past the imports, inside the JIT compilation (about a minute).
WARM_UP_SIGINT_AFTER_S = 4.0
#: Seconds of work after a callback dropped the Ctrl-C (as a compilation going on): well past its re-delivery.
WORK_AFTER_THE_CALLBACK_S = 1.0


@pytest.mark.parametrize("where, patch", [
    ("building the app (typer import)", f"""
        real = cli._build_app
        def build():
            {SIGINT_SELF}
            return real()
        cli._build_app = build"""),
    ("importing the command's module", f"""
        real = cli.importlib.import_module
        def slow_import(name, *a, **k):
            if name.startswith("surfelslam.tools."):
                {SIGINT_SELF}
            return real(name, *a, **k)
        cli.importlib.import_module = slow_import"""),
    ("inside the command", f"""
        import surfelslam.datasets as ds
        def opening(*a, **k):
            {SIGINT_SELF}
        ds.open_sequence = opening"""),
    # as llvmlite's PassBuilder when Ctrl-C lands in its constructor during the JIT warm-up: its destructor fails
    # when the interrupted frames are freed ("Exception ignored in: ... no attribute '_as_parameter_'")
    ("constructing an object whose destructor then fails", f"""
        import surfelslam.datasets as ds
        class HalfBuilt:
            def __init__(self):
                {SIGINT_SELF}
                self._as_parameter_ = 1
            def __del__(self):
                self._as_parameter_
        def opening(*a, **k):
            HalfBuilt()
        ds.open_sequence = opening"""),
    # as llvmlite's object-cache callback when Ctrl-C lands in it: the interrupt is only printed ("Exception ignored
    # on calling ctypes callback function"), then the compilation fails with a RuntimeError
    ("a callback, and the work then fails", f"""
        import ctypes
        import surfelslam.datasets as ds
        def callback():
            {SIGINT_SELF}
        def opening(*a, **k):
            ctypes.CFUNCTYPE(None)(callback)()
            raise RuntimeError("no compiled object yet")
        ds.open_sequence = opening"""),
    # as llvmlite's object-cache callback when the compilation does not depend on it: the interrupt is dropped
    # inside the callback and the work goes on; it must still stop
    ("a callback, and the work goes on", f"""
        import ctypes, time
        import surfelslam.datasets as ds
        real = ds.open_sequence
        def callback():
            {SIGINT_SELF}
        def opening(*a, **k):
            ctypes.CFUNCTYPE(None)(callback)()
            time.sleep({WORK_AFTER_THE_CALLBACK_S})
            return real(*a, **k)
        ds.open_sequence = opening"""),
])
def test_ctrl_c_at_start_up_and_later(synth_seq, where, patch):
    code = "import sys\nfrom surfelslam import cli\n" + textwrap.dedent(patch).strip() + (
        f"\ncli.main(['info', {str(synth_seq)!r}])\n")
    res = _python(code)
    assert res.returncode == 130, (where, res.stderr)
    assert res.stderr.strip().splitlines() == ["interrupted"], (where, res.stderr)


@pytest.mark.slow
def test_ctrl_c_during_the_jit_warm_up_is_one_line(synth_seq, tmp_path):
    """A real run with an empty numba cache (so it compiles), Ctrl-C after a few seconds: 'interrupted', exit 130,
    nothing else (no llvmlite destructor or callback traceback)."""
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "cache")}
    env.pop("SURFELSLAM_DEBUG", None)
    proc = subprocess.Popen([sys.executable, "-m", "surfelslam", "run", str(synth_seq), "-o", str(tmp_path / "out"),
                             "--no-progress"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    time.sleep(WARM_UP_SIGINT_AFTER_S)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130 and err.splitlines() == ["interrupted"], err


# ---------------------------------------------------------------------------------------- numba cache
def test_numba_cache_kept_when_set_by_the_user(tmp_path):
    blocked = tmp_path / "file"
    blocked.write_text("")
    env = {"NUMBA_CACHE_DIR": str(tmp_path / "mine"), "HOME": str(blocked / "home")}
    assert numba_cache.numba_cache_fallback(env, in_tree=blocked / "__pycache__") is None


def test_numba_cache_default_when_writable(tmp_path):
    assert numba_cache.numba_cache_fallback({"HOME": str(tmp_path)}, in_tree=tmp_path / "__pycache__") is None


def test_numba_cache_falls_back_to_a_temp_folder(tmp_path):
    blocked = tmp_path / "file"  # a regular file: nothing can be created below it, not even by root
    blocked.write_text("")
    env = {"HOME": str(blocked / "home")}
    got = numba_cache.numba_cache_fallback(env, in_tree=blocked / "__pycache__", temp_root=tmp_path / "tmp")
    assert got == str(tmp_path / "tmp" / f"surfelslam-numba-{os.getuid()}") and Path(got).is_dir()
    env_xdg = {"HOME": str(tmp_path), "XDG_CACHE_HOME": str(blocked / "cache")}
    assert numba_cache.numba_cache_fallback(env_xdg, in_tree=blocked / "__pycache__",
                                            temp_root=tmp_path / "tmp") is not None


def test_cached_kernel_compiles_on_a_read_only_install(tmp_path):
    """The kernels' folder holds a file named __pycache__ and HOME is unusable: numba alone raises
    'cannot cache function'; after the CLI's fallback the cached kernel compiles."""
    pkg = tmp_path / "install"
    pkg.mkdir()
    (pkg / "__pycache__").write_text("")  # in-tree cache impossible
    (pkg / "kern.py").write_text("from numba import njit\n\n@njit(cache=True)\ndef inc(x):\n    return x + 1\n")
    (tmp_path / "homefile").write_text("")
    res = _python(f"""
        import os, sys
        from pathlib import Path
        sys.path.insert(0, {str(pkg)!r})
        import surfelslam.numba_cache as cache
        cache.KERNEL_CACHE_DIR = Path({str(pkg / "__pycache__")!r})
        cache.configure_numba_cache()
        import kern
        print(kern.inc(1), os.environ["NUMBA_CACHE_DIR"])
    """, env={"HOME": str(tmp_path / "homefile" / "home"), "XDG_CACHE_HOME": str(tmp_path / "homefile" / "c")},
        unset=("NUMBA_CACHE_DIR",))  # the caller's NUMBA_CACHE_DIR would be kept (and no fallback made)
    assert res.returncode == 0, res.stderr
    value, cache = res.stdout.split()
    assert value == "2" and "surfelslam-numba" in cache


def test_help_with_an_unwritable_home(tmp_path):
    (tmp_path / "homefile").write_text("")
    res = subprocess.run([sys.executable, "-m", "surfelslam", "--help"], capture_output=True, text=True,
                         env={**os.environ, "HOME": str(tmp_path / "homefile" / "home")}, timeout=60)
    assert res.returncode == 0 and "Commands" in res.stdout and res.stderr == ""
