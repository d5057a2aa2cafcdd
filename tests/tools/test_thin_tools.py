"""The commands stay thin (issue 67.5): every function in ``surfelslam/tools/`` is at most 60 lines (the work is in
library functions; a command parses its options, calls one and prints)."""

from __future__ import annotations

import ast
from pathlib import Path

import surfelslam.tools

#: The longest function allowed in tools/ (lines, decorators included).
MAX_FUNCTION_LINES = 60


def long_functions(root: Path, limit: int = MAX_FUNCTION_LINES) -> list[str]:
    """``"file:line name (N lines)"`` for every function (nested ones too) in ``root``'s Python files longer than
    ``limit``."""
    found = []
    for path in sorted(root.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                first = min([node.lineno, *(d.lineno for d in node.decorator_list)])
                n = node.end_lineno - first + 1
                if n > limit:
                    found.append(f"{path.name}:{node.lineno} {node.name} ({n} lines)")
    return found


def test_no_function_in_tools_is_longer_than_60_lines():
    assert long_functions(Path(surfelslam.tools.__file__).parent) == []


def test_the_check_finds_a_long_function(tmp_path):
    body = "\n".join(f"        x{i} = {i}" for i in range(MAX_FUNCTION_LINES))
    (tmp_path / "cmd.py").write_text(f"def register(app):\n    @app.command()\n    def cmd():\n{body}\n")
    assert long_functions(tmp_path) == [f"cmd.py:1 register ({MAX_FUNCTION_LINES + 3} lines)",
                                        f"cmd.py:3 cmd ({MAX_FUNCTION_LINES + 2} lines)"]
