"""The layers of docs/architecture.md, enforced: no import goes up a layer, and no imports form a cycle.

An AST walk over ``src/surfelslam`` and ``benchmarks`` collects every import, at module level and inside functions:
``import x``, ``from x import y``, relative imports, and ``importlib.import_module`` / ``__import__`` with a literal
name (an f-string such as ``f"surfelslam.tools.{name}"`` counts as an import of the package its literal prefix
names). Imports under ``if TYPE_CHECKING:`` are exempt: they never run, so they neither order the layers nor close a
cycle (``io/ply.py`` names the surfel map's type that way). Importing ``a.b.c`` is an edge to ``a.b.c`` only, not
to the packages ``a`` and ``a.b`` that Python runs first, so that a package's ``__init__`` may gather its modules.

Three checks, each failing with the importing file:line and the imported module:
(a) an import from a module to a module of a higher layer (:data:`LAYERS`, one ordered table);
(b) a cycle between modules;
(c) a cycle between the parts of a package (its subpackages and modules, e.g. ``slam`` and ``io`` in ``surfelslam``).
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
    # bottom: errors, plain types, the settings machinery, geometry, numba kernels
    ("surfelslam.errors", "surfelslam.types", "surfelslam.config", "surfelslam.config_reference", "surfelslam.geometry",
     "surfelslam.kernels", "surfelslam.numba_cache"),
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
    # what users call: the API, the commands, batches, experiments (which drive runs), the kernel warm-up, the
    # generated settings reference
    ("surfelslam", "surfelslam.api", "surfelslam.cli", "surfelslam.__main__", "surfelslam.tools", "surfelslam.batch",
     "surfelslam.experiments", "surfelslam.warmup"),
    # the benchmark scripts drive anything in the library
    ("benchmarks",),
)

#: Imports allowed although they break a rule: (importing module, imported module) -> why. Keep it empty.
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


def _statements(tree: ast.AST) -> Iterator[tuple[ast.AST, str | None]]:
    """Every import statement or dynamic import call: (node, the dynamic call's module name), skipping
    ``if TYPE_CHECKING:`` blocks (their ``else`` still counts)."""
    stack: list[ast.AST] = [tree]
    while stack:
        node = stack.pop()
        if isinstance(node, ast.If) and _is_type_checking(node.test):
            stack.extend(node.orelse)
            continue
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            yield node, None
        elif isinstance(node, ast.Call) and (name := _dynamic_name(node)):
            yield node, name
        stack.extend(ast.iter_child_nodes(node))


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
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        is_package = path.name == "__init__.py"
        for node, dynamic in _statements(tree):
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
    """Modules that fall only into a top-level package's entry (a new subpackage must be given its layer)."""
    roots = {entry for entries in layers for entry in entries if "." not in entry}
    return sorted(m for m in names if (found := layer_of(m, layers)) is None or (found[1] in roots and m != found[1]
                                                                                   and found[1] == "surfelslam"))


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


def _cycles(edges: dict[str, dict[str, Import]]) -> list[list[str]]:
    """One shortest cycle through each strongly connected group of more than one node (Tarjan, iterative)."""
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
    return [_shortest_cycle(edges, group) for group in sorted(groups)]


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


def _describe(cycle: list[str], edges: dict[str, dict[str, Import]]) -> str:
    steps = "; ".join(edges[a][b].where() for a, b in zip(cycle, cycle[1:], strict=False))
    return f"{' -> '.join(cycle)}  [{steps}]"


def module_cycles(imports: Iterable[Import], exceptions: dict[tuple[str, str], str] | None = None) -> list[str]:
    """(b): cycles between modules, each named with the file:line of every import on it."""
    exceptions = EXCEPTIONS if exceptions is None else exceptions
    edges: dict[str, dict[str, Import]] = {}
    for imp in imports:
        if (imp.source, imp.target) not in exceptions:
            edges.setdefault(imp.source, {}).setdefault(imp.target, imp)
    return [_describe(cycle, edges) for cycle in _cycles(edges)]


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
        found += [f"in {package}: {_describe(cycle, edges)}" for cycle in _cycles(edges)]
    return found


@pytest.fixture(scope="module")
def project() -> tuple[dict[str, Path], list[Import]]:
    return collect_imports(ROOTS)


def test_the_walk_sees_the_project(project):
    """The checks below cannot pass vacuously: the walk finds the modules and the imports it must."""
    names, imports = project
    assert len(names) > 200
    assert len(imports) > 1000
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


def test_no_import_cycle_between_modules(project):
    _, imports = project
    assert module_cycles(imports) == []


def test_no_import_cycle_between_packages(project):
    names, imports = project
    assert package_cycles(names, imports) == []


def test_exceptions_are_used():
    """An allowed exception that no import needs any more goes from the table."""
    _, imports = collect_imports(ROOTS)
    edges = {(imp.source, imp.target) for imp in imports}
    assert [pair for pair in EXCEPTIONS if pair not in edges] == []
