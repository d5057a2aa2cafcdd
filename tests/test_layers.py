"""The layers of docs/architecture.md, enforced: no import goes up a layer, and no imports form a cycle.

An AST walk over ``src/surfelslam`` and ``benchmarks`` collects every import, at module level and inside functions:
``import x``, ``from x import y``, relative imports, and ``importlib.import_module`` / ``__import__`` with a literal
name (an f-string such as ``f"surfelslam.tools.{name}"`` counts as an import of the package its literal prefix
names). Imports under ``if TYPE_CHECKING:`` are exempt: they never run, so they neither order the layers nor close a
cycle (``io/ply.py`` names the surfel map's type that way). Importing ``a.b.c`` is an edge to ``a.b.c`` only, not
to the packages ``a`` and ``a.b`` that Python runs first, so that a package's ``__init__`` may gather its modules.

The checks, each failing with the importing file:line and the imported module:
(a) an import from a module to a module of a higher layer (:data:`LAYERS`, one ordered table, where every module
    must have its place), or of the command line by anything but ``__main__`` (:data:`ENTRY_POINTS`);
(b) a cycle between modules;
(c) a cycle between the parts of a package (its subpackages and modules, e.g. ``slam`` and ``io`` in ``surfelslam``).
The checker itself is tested on a small planted tree (``tmp_path``) with one violation of each kind.
"""

from __future__ import annotations

import ast
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
#: the trees checked: directory -> the top-level package its files belong to
ROOTS = {REPO / "src" / "surfelslam": "surfelslam", REPO / "benchmarks": "benchmarks"}

#: The layers, bottom first. A module belongs to the longest entry that is it or a package holding it; it may import
#: from its own layer and the layers below, never from above. Within a layer, parts import each other freely as long as
#: no cycle forms. ``surfelslam`` itself (the lazy public names of ``__init__.py``) sits on top with the API.
LAYERS: tuple[tuple[str, ...], ...] = (
    # bottom: errors, plain types, the settings machinery (config.py or settings/, and the reference page), geometry,
    # numba kernels and where numba caches them
    ("surfelslam.errors", "surfelslam.types", "surfelslam.config", "surfelslam.config_reference", "surfelslam.geometry",
     "surfelslam.kernels", "surfelslam.numba_cache", "surfelslam.settings"),
    # sources and files: dataset readers, the synthetic generator (a source too), atomic files, PLY, TUM, run folders
    ("surfelslam.io", "surfelslam.datasets", "surfelslam.synth"),
    # frame-to-frame and frame-to-model registration: preprocessing, ICP, features, initial guesses
    ("surfelslam.tracking",),
    # the surfel map, TSDF and mesh; keyframes, loops, the pose graph, the sparse back end
    ("surfelslam.mapping", "surfelslam.backend"),
    # the trackers, the run loop and the run writer
    ("surfelslam.slam",),
    # metrics and figures over finished runs
    ("surfelslam.eval", "surfelslam.viz"),
    # what users call: the API, the command line and its commands, batches, experiments (which drive runs), the
    # kernel warm-up
    ("surfelslam", "surfelslam.api", "surfelslam.cli", "surfelslam.__main__", "surfelslam.tools", "surfelslam.batch",
     "surfelslam.experiments", "surfelslam.warmup"),
    # the benchmark scripts drive anything in the library
    ("benchmarks",),
)

#: Modules only the listed modules may import: the library never imports the command line.
ENTRY_POINTS: dict[str, tuple[str, ...]] = {"surfelslam.cli": ("surfelslam.__main__",)}

#: Imports allowed although they break a rule: (importing module, imported module) -> why. Keep it empty;
#: :func:`test_exceptions_are_used` fails on an entry no import needs any more.
EXCEPTIONS: dict[tuple[str, str], str] = {}


@dataclass(frozen=True)
class Import:
    """One import statement's edge: ``source`` (module) imports ``target`` (module) at ``path``:``line``."""

    source: str
    target: str
    path: Path
    line: int

    def where(self) -> str:
        try:
            shown = self.path.relative_to(REPO)
        except ValueError:
            shown = self.path
        return f"{shown}:{self.line}: {self.source} imports {self.target}"


def module_names(roots: dict[Path, str]) -> dict[str, Path]:
    """Every module under ``roots``: dotted name -> file (a package is named by its ``__init__.py``)."""
    names = {}
    for root, package in roots.items():
        for path in sorted(root.rglob("*.py")):
            parts = [package, *path.relative_to(root).with_suffix("").parts]
            if parts[-1] == "__init__":
                parts.pop()
            names[".".join(parts)] = path
    return names


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def _dynamic_name(call: ast.Call) -> str | None:
    """The module an ``importlib.import_module(...)`` / ``__import__(...)`` call names, if written down."""
    func = call.func
    name = func.attr if isinstance(func, ast.Attribute) else func.id if isinstance(func, ast.Name) else None
    if name not in ("import_module", "__import__") or not call.args:
        return None
    arg = call.args[0]
    if isinstance(arg, ast.Constant) and isinstance(arg.value, str):
        return arg.value
    if isinstance(arg, ast.JoinedStr) and arg.values and isinstance(arg.values[0], ast.Constant):
        prefix = str(arg.values[0].value)
        return prefix.rsplit(".", 1)[0] if "." in prefix else None
    return None


def _statements(tree: ast.AST, calls: bool) -> Iterator[tuple[ast.AST, str | None]]:
    """Every import statement, and with ``calls`` every dynamic import call: (node, the call's module name),
    skipping ``if TYPE_CHECKING:`` blocks (their ``else`` still counts). Without ``calls`` only statements are
    visited (imports are statements; expressions can only hold the calls)."""
    stack: list[ast.AST] = [tree]
    while stack:
        node = stack.pop()
        if isinstance(node, ast.If) and _is_type_checking(node.test):
            stack.extend(node.orelse)
            continue
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            yield node, None
        elif calls and isinstance(node, ast.Call) and (name := _dynamic_name(node)):
            yield node, name
        stack.extend(child for child in ast.iter_child_nodes(node)
                     if calls or isinstance(child, (ast.stmt, ast.excepthandler, ast.match_case)))


def _resolve(node: ast.AST, dynamic: str | None, module: str, is_package: bool, known: set[str]) -> list[str]:
    """The known modules one statement of ``module`` imports (other packages' modules are left out)."""
    if dynamic is not None:
        candidates = [dynamic]
    elif isinstance(node, ast.Import):
        candidates = [alias.name for alias in node.names]
    else:
        assert isinstance(node, ast.ImportFrom)
        base = node.module or ""
        if node.level:
            package = module.split(".") if is_package else module.split(".")[:-1]
            anchor = package[:len(package) - (node.level - 1)]
            base = ".".join([*anchor, *([base] if base else [])])
        candidates = [f"{base}.{alias.name}" if f"{base}.{alias.name}" in known else base for alias in node.names]
    out = []
    for name in candidates:
        while name and name not in known:  # `import a.b.x` where x is no module: the closest module holding it
            name = name.rpartition(".")[0]
        if name and name not in out:
            out.append(name)
    return out


def collect_imports(roots: dict[Path, str]) -> tuple[dict[str, Path], list[Import]]:
    """The modules under ``roots`` and every import between them (module level and inside functions)."""
    names = module_names(roots)
    known = set(names)
    imports = []
    for module, path in names.items():
        text = path.read_text(encoding="utf-8")
        tree = ast.parse(text, filename=str(path))
        is_package = path.name == "__init__.py"
        for node, dynamic in _statements(tree, calls="import_module" in text or "__import__" in text):
            for target in _resolve(node, dynamic, module, is_package, known):
                if target != module:
                    imports.append(Import(module, target, path, node.lineno))
    imports.sort(key=lambda imp: (str(imp.path), imp.line, imp.target))
    return names, imports


def layer_of(module: str, layers: tuple[tuple[str, ...], ...] = LAYERS) -> tuple[int, str] | None:
    """(layer index, the table's entry) of ``module``: its longest entry; None if no entry holds it."""
    best = None
    for index, entries in enumerate(layers):
        for entry in entries:
            if module == entry or module.startswith(entry + "."):
                if best is None or len(entry) > len(best[1]):
                    best = (index, entry)
    return best


def unplaced(names: Iterable[str], layers: tuple[tuple[str, ...], ...] = LAYERS) -> list[str]:
    """Modules without an entry of their own: none holds them, or only a bare top-level name whose parts have
    entries (``surfelslam`` is split into parts, so a new subpackage or module must be given its layer; the bare
    ``surfelslam`` stands for its ``__init__.py``; ``benchmarks`` is not split and holds all its modules)."""
    entries = [entry for layer in layers for entry in layer]
    split = {entry for entry in entries if "." not in entry and any(e.startswith(entry + ".") for e in entries)}
    out = []
    for module in names:
        found = layer_of(module, layers)
        if found is None or (found[1] in split and module != found[1]):
            out.append(module)
    return sorted(out)


def upward_imports(imports: Iterable[Import], layers: tuple[tuple[str, ...], ...] = LAYERS,
                   exceptions: dict[tuple[str, str], str] | None = None) -> list[str]:
    """(a): every import of a module from a higher layer than the importer's."""
    exceptions = EXCEPTIONS if exceptions is None else exceptions
    found = []
    for imp in imports:
        src, dst = layer_of(imp.source, layers), layer_of(imp.target, layers)
        if src and dst and dst[0] > src[0] and (imp.source, imp.target) not in exceptions:
            found.append(f"{imp.where()} (layer of {dst[1]} is above that of {src[1]})")
    return found


def entry_point_imports(imports: Iterable[Import],
                        entry_points: dict[str, tuple[str, ...]] = ENTRY_POINTS) -> list[str]:
    """Imports of an entry point (:data:`ENTRY_POINTS`) by a module it does not list."""
    return [f"{imp.where()} (only {', '.join(entry_points[imp.target])} may)" for imp in imports
            if imp.target in entry_points and imp.source not in entry_points[imp.target]]


def _cycles(edges: dict[str, dict[str, Import]]) -> list[tuple[list[str], list[str]]]:
    """(one shortest cycle, the group) of each strongly connected group of more than one node (Tarjan, iterative):
    fixing that cycle may leave others in the group, which the next run shows."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    groups = []
    for start in sorted(edges):
        if start in index:
            continue
        work = [(start, iter(sorted(edges.get(start, {}))))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is None:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[node])
                if low[node] == index[node]:
                    group = []
                    while True:
                        member = stack.pop()
                        on_stack.discard(member)
                        group.append(member)
                        if member == node:
                            break
                    if len(group) > 1:
                        groups.append(sorted(group))
            elif child not in index:
                index[child] = low[child] = len(index)
                stack.append(child)
                on_stack.add(child)
                work.append((child, iter(sorted(edges.get(child, {})))))
            elif child in on_stack:
                low[node] = min(low[node], index[child])
    return [(_shortest_cycle(edges, group), group) for group in sorted(groups)]


def _shortest_cycle(edges: dict[str, dict[str, Import]], group: list[str]) -> list[str]:
    """The shortest cycle from the group's first node back to it, inside the group (breadth first)."""
    members, start = set(group), group[0]
    previous: dict[str, str] = {}
    frontier = [start]
    while frontier:
        following = []
        for node in frontier:
            for child in sorted(edges.get(node, {})):
                if child == start:
                    path = [node]
                    while path[-1] != start:
                        path.append(previous[path[-1]])
                    return [*reversed(path), start]
                if child in members and child not in previous:
                    previous[child] = node
                    following.append(child)
        frontier = following
    raise AssertionError(f"no cycle in the strongly connected group {group}")


def _describe(cycle: list[str], group: list[str], edges: dict[str, dict[str, Import]]) -> str:
    """``a -> b -> a`` (and the whole group when it is larger), then each import on the cycle with its file:line."""
    steps = "; ".join(edges[a][b].where() for a, b in zip(cycle, cycle[1:], strict=False))
    more = f" (one of the cycles among {', '.join(group)})" if len(group) > len(cycle) - 1 else ""
    return f"{' -> '.join(cycle)}{more}  [{steps}]"


def module_cycles(imports: Iterable[Import], exceptions: dict[tuple[str, str], str] | None = None) -> list[str]:
    """(b): cycles between modules, each named with the file:line of every import on it."""
    exceptions = EXCEPTIONS if exceptions is None else exceptions
    edges: dict[str, dict[str, Import]] = {}
    for imp in imports:
        if (imp.source, imp.target) not in exceptions:
            edges.setdefault(imp.source, {}).setdefault(imp.target, imp)
    return [_describe(cycle, group, edges) for cycle, group in _cycles(edges)]


def _part(module: str, package: str) -> str | None:
    """The part of ``package`` (its direct subpackage or module) that holds ``module``; None if outside it."""
    if not module.startswith(package + "."):
        return None
    return package + "." + module[len(package) + 1:].split(".")[0]


def package_cycles(names: Iterable[str], imports: Iterable[Import],
                   exceptions: dict[tuple[str, str], str] | None = None) -> list[str]:
    """(c): for every package, cycles between its parts through imports between modules in them."""
    exceptions = EXCEPTIONS if exceptions is None else exceptions
    imports = [imp for imp in imports if (imp.source, imp.target) not in exceptions]
    names = set(names)
    packages = {m for m in names if any(other.startswith(m + ".") for other in names)}
    found = []
    for package in sorted(packages):
        edges: dict[str, dict[str, Import]] = {}
        for imp in imports:
            a, b = _part(imp.source, package), _part(imp.target, package)
            if a and b and a != b:
                edges.setdefault(a, {}).setdefault(b, imp)
        found += [f"in {package}: {_describe(cycle, group, edges)}" for cycle, group in _cycles(edges)]
    return found


@pytest.fixture(scope="module")
def project() -> tuple[dict[str, Path], list[Import]]:
    return collect_imports(ROOTS)


def test_the_walk_sees_the_project(project):
    """The checks below cannot pass vacuously: the walk finds the modules and the imports it must."""
    names, imports = project
    assert len(names) > 150 and "benchmarks.run_all" in names and "surfelslam.slam.dense" in names
    assert len(imports) > 700
    edges = {(imp.source, imp.target) for imp in imports}
    assert ("surfelslam.slam.dense", "surfelslam.mapping.surfel_map") in edges  # module level
    assert ("surfelslam.cli", "surfelslam.tools") in edges  # importlib.import_module(f"surfelslam.tools.{...}")
    assert ("surfelslam.io.ply", "surfelslam.mapping.surfel_map") not in edges  # under TYPE_CHECKING


def test_every_module_has_a_layer(project):
    names, _ = project
    assert unplaced(names) == [], "give these modules their layer in LAYERS"


def test_no_import_goes_up_a_layer(project):
    _, imports = project
    assert upward_imports(imports) == []


def test_the_library_never_imports_the_cli(project):
    _, imports = project
    assert entry_point_imports(imports) == []


def test_no_import_cycle_between_modules(project):
    _, imports = project
    assert module_cycles(imports) == []


def test_no_import_cycle_between_packages(project):
    names, imports = project
    assert package_cycles(names, imports) == []


def test_exceptions_are_used(project):
    """An allowed exception that no import needs any more goes from the table."""
    _, imports = project
    edges = {(imp.source, imp.target) for imp in imports}
    assert [pair for pair in EXCEPTIONS if pair not in edges] == []


# ------------------------------------------------------------------------------- the checker on a planted tree
_FAKE_LAYERS = (("pkg.low", "pkg.util"), ("pkg.high",), ("pkg", "pkg.cli"))
_FAKE_TREE = {
    "__init__.py": "",
    "cli.py": "import pkg.high\n",
    "util.py": "from pkg import low\n",
    "low/__init__.py": "",
    "low/a.py": (
        "from typing import TYPE_CHECKING\n"
        "from . import b\n"  # a <-> b: a cycle of two modules in one package
        "if TYPE_CHECKING:\n"
        "    from pkg.high import H\n"  # exempt: never runs
        "def f():\n"
        "    from pkg.high import mod\n"  # upward, inside a function
        "    return mod\n"
    ),
    "low/b.py": "import importlib\nX = importlib.import_module('pkg.low.a')\nfrom ..util import helper\n",
    "high/__init__.py": "H = 1\n",
    "high/mod.py": "import pkg.low.a\nfrom pkg import cli\n",
}


@pytest.fixture
def planted(tmp_path) -> tuple[dict[str, Path], list[Import]]:
    root = tmp_path / "pkg"
    for rel, text in _FAKE_TREE.items():
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_text(text)
    return collect_imports({root: "pkg"})


def test_the_checker_finds_each_planted_import(planted):
    names, imports = planted
    assert sorted(names) == ["pkg", "pkg.cli", "pkg.high", "pkg.high.mod", "pkg.low", "pkg.low.a", "pkg.low.b",
                             "pkg.util"]
    assert {(imp.source, imp.target, imp.line) for imp in imports} == {
        ("pkg.cli", "pkg.high", 1), ("pkg.util", "pkg.low", 1), ("pkg.low.a", "pkg.low.b", 2),
        ("pkg.low.a", "pkg.high.mod", 6), ("pkg.low.b", "pkg.low.a", 2), ("pkg.low.b", "pkg.util", 3),
        ("pkg.high.mod", "pkg.low.a", 1), ("pkg.high.mod", "pkg.cli", 2)}


def test_the_checker_fails_on_planted_violations(planted):
    names, imports = planted
    assert unplaced(names, _FAKE_LAYERS) == []
    up = upward_imports(imports, _FAKE_LAYERS, exceptions={})
    assert [line.split("/pkg/", 1)[1] for line in up] == [
        "high/mod.py:2: pkg.high.mod imports pkg.cli (layer of pkg.cli is above that of pkg.high)",
        "low/a.py:6: pkg.low.a imports pkg.high.mod (layer of pkg.high is above that of pkg.low)"]
    assert entry_point_imports(imports, {"pkg.cli": ()}) == [
        f"{planted[0]['pkg.high.mod']}:2: pkg.high.mod imports pkg.cli (only  may)"]
    cycles = module_cycles(imports, exceptions={})
    assert len(cycles) == 1 and cycles[0].startswith(
        "pkg.high.mod -> pkg.low.a -> pkg.high.mod (one of the cycles among pkg.high.mod, pkg.low.a, pkg.low.b)  [")
    assert "a.py:6: pkg.low.a imports pkg.high.mod" in cycles[0]
    parts = package_cycles(names, imports, exceptions={})
    assert [c.split("  [")[0] for c in parts] == [
        "in pkg: pkg.cli -> pkg.high -> pkg.cli (one of the cycles among pkg.cli, pkg.high, pkg.low, pkg.util)",
        "in pkg.low: pkg.low.a -> pkg.low.b -> pkg.low.a"]
    # an allowed exception removes its import from every check
    allowed = {("pkg.low.a", "pkg.high.mod"): "planted"}
    assert [line.split("/pkg/", 1)[1] for line in upward_imports(imports, _FAKE_LAYERS, allowed)] == [
        "high/mod.py:2: pkg.high.mod imports pkg.cli (layer of pkg.cli is above that of pkg.high)"]
    assert [c.split("  [")[0] for c in module_cycles(imports, allowed)] == ["pkg.low.a -> pkg.low.b -> pkg.low.a"]
    assert unplaced([*names, "pkg.new"], (("pkg",), *_FAKE_LAYERS[:2])) == ["pkg.cli", "pkg.new"]
