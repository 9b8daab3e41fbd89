"""The modules of src/anisdf import each other without a cycle.

The graph is read with :mod:`ast` from the source, so it covers imports inside functions too (the lazy imports
that hide a circle from Python's import machinery but still tie two modules together). An import of a package
counts as an edge to its ``__init__``; importing a submodule does not add an edge to the parent package (that is
how packages re-export their parts). Imports under ``if TYPE_CHECKING:`` are left out: they never run.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src"
ROOT = "anisdf"


def module_files(src: Path = SRC, root: str = ROOT) -> dict[str, Path]:
    """Dotted module name -> file, for every ``.py`` under ``src/root`` (packages by their ``__init__``)."""
    out = {}
    for path in sorted((src / root).rglob("*.py")):
        parts = list(path.relative_to(src).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def _import_nodes(tree: ast.AST) -> list[ast.Import | ast.ImportFrom]:
    """Every import statement in ``tree`` at any depth, except those under ``if TYPE_CHECKING:``."""
    found: list[ast.Import | ast.ImportFrom] = []

    def visit(node: ast.AST) -> None:
        if isinstance(node, ast.If) and _is_type_checking(node.test):
            for child in node.orelse:
                visit(child)
            return
        if isinstance(node, ast.Import | ast.ImportFrom):
            found.append(node)
        for child in ast.iter_child_nodes(node):
            visit(child)

    visit(tree)
    return found


def imports_of(name: str, path: Path, modules: dict[str, Path]) -> set[str]:
    """The project modules that module ``name`` (file ``path``) imports."""
    is_package = path.name == "__init__.py"
    targets: set[str] = set()
    for node in _import_nodes(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            bases = [alias.name for alias in node.names]
            names: list[str] = []
        else:
            if node.level:
                package = name.split(".") if is_package else name.split(".")[:-1]
                package = package[: len(package) - (node.level - 1)]
                base = ".".join([*package, node.module] if node.module else package)
            else:
                base = node.module or ""
            bases = [base]
            names = [alias.name for alias in node.names]
        for base in bases:
            subs = [f"{base}.{n}" for n in names if f"{base}.{n}" in modules]
            if subs:  # ``from package import submodule``
                targets.update(subs)
                if len(subs) == len(names):
                    continue
            # the most specific project module that ``base`` names (``import a.b.c`` with c a function: a.b)
            parts = base.split(".")
            while parts and ".".join(parts) not in modules:
                parts.pop()
            if parts:
                targets.add(".".join(parts))
    targets.discard(name)
    return targets


def import_graph(src: Path = SRC, root: str = ROOT) -> dict[str, set[str]]:
    modules = module_files(src, root)
    return {name: imports_of(name, path, modules) for name, path in modules.items()}


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle ``[a, b, ..., a]`` of ``graph`` if there is one (iterative depth-first search), else ``None``."""
    white, grey, black = 0, 1, 2
    colour = dict.fromkeys(graph, white)
    for start in sorted(graph):
        if colour[start] != white:
            continue
        path = [start]
        stack = [iter(sorted(graph[start]))]
        colour[start] = grey
        while stack:
            nxt = next(stack[-1], None)
            if nxt is None:
                colour[path.pop()] = black
                stack.pop()
            elif colour.get(nxt, black) == grey:
                return [*path[path.index(nxt):], nxt]
            elif colour.get(nxt, black) == white:
                colour[nxt] = grey
                path.append(nxt)
                stack.append(iter(sorted(graph[nxt])))
    return None


def test_src_anisdf_has_no_import_cycle() -> None:
    graph = import_graph()
    assert len(graph) > 50 and graph["anisdf.cli"], "the import graph of src/anisdf was not read"
    cycle = find_cycle(graph)
    if cycle:
        print("import cycle: " + " -> ".join(cycle))
    assert cycle is None, "import cycle: " + " -> ".join(cycle or [])


def test_layering_of_the_hash_grid_and_the_benchmarks() -> None:
    """The reference hash grid imports no backend; nothing in the library imports the benchmark package."""
    graph = import_graph()
    assert not {m for m in graph["anisdf.fields.hash_grid.reference"] if m.startswith("anisdf.fields.hash_grid")}
    assert "anisdf.fields.hash_grid.triton" not in graph["anisdf.fields.hash_grid.cpu_kernel"]
    upward = sorted((a, b) for a, deps in graph.items() for b in deps
                    if b.startswith("anisdf.benchmarks") and not a.startswith(("anisdf.benchmarks", "anisdf.cli")))
    assert not upward, f"library modules import the benchmarks: {upward}"


def _write(root: Path, files: dict[str, str]) -> None:
    for rel, text in files.items():
        path = root / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)


def test_the_checker_finds_function_level_and_relative_cycles(tmp_path: Path) -> None:
    _write(tmp_path, {
        "pkg/__init__.py": "",
        "pkg/a.py": "def f():\n    from pkg.sub import b\n",
        "pkg/sub/__init__.py": "from pkg.sub.b import g\n",
        "pkg/sub/b.py": "from ..c import h\n",
        "pkg/c.py": "import os\nfrom typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from pkg import a\n"
                    "def h():\n    import pkg.a\n",
        "pkg/d.py": "from pkg.sub import g\nif TYPE_CHECKING:\n    import pkg.a\n",
    })
    graph = import_graph(tmp_path, "pkg")
    assert graph["pkg.a"] == {"pkg.sub.b"}
    assert graph["pkg.sub.b"] == {"pkg.c"}
    assert graph["pkg.c"] == {"pkg.a"}  # the function-level import; the TYPE_CHECKING one is left out
    assert graph["pkg.d"] == {"pkg.sub"}
    assert find_cycle(graph) == ["pkg.a", "pkg.sub.b", "pkg.c", "pkg.a"]
    (tmp_path / "pkg/c.py").write_text("def h():\n    pass\n")
    assert find_cycle(import_graph(tmp_path, "pkg")) is None


@pytest.mark.parametrize(("graph", "expected"), [
    ({"a": {"a"}}, ["a", "a"]),
    ({"a": {"b"}, "b": {"c"}, "c": set()}, None),
    ({"a": {"b", "c"}, "b": {"c"}, "c": {"b"}}, ["b", "c", "b"]),
])
def test_find_cycle(graph: dict[str, set[str]], expected: list[str] | None) -> None:
    assert find_cycle(graph) == expected


LAYERS = (
    ("anisdf.errors", "anisdf.utils", "anisdf.run_dir", "anisdf.config"),
    ("anisdf.data", "anisdf.demo"),
    ("anisdf.eval",),
    ("anisdf.model_components",),
    ("anisdf.fields",),
    ("anisdf.models",),
    ("anisdf.training",),
    ("anisdf.export",),
    ("anisdf.materials",),
    ("anisdf.tasks",),
    ("anisdf.viewer",),
    ("anisdf.orchestration",),
    ("anisdf.benchmarks",),
    ("anisdf.cli", "anisdf.__main__"),
)
"""The library's floors, bottom first: a module may import its own floor and those below, never one above."""


def floor_of(module: str) -> int | None:
    for i, names in enumerate(LAYERS):
        if any(module == n or module.startswith(n + ".") for n in names):
            return i
    return None


def test_every_module_has_a_floor_and_imports_only_downwards() -> None:
    graph = import_graph()
    homeless = sorted(m for m in graph if m != ROOT and floor_of(m) is None)
    assert not homeless, f"modules outside every floor of LAYERS: {homeless}"
    upward = sorted((a, b) for a, deps in graph.items() for b in deps
                    if a != ROOT and b != ROOT and floor_of(b) > floor_of(a))
    assert not upward, "imports that run back up a floor: " + ", ".join(f"{a} -> {b}" for a, b in upward)


MAX_MODULE_LINES = 450
MAX_FUNCTION_LINES = 120


def test_modules_and_functions_can_be_read_in_one_sitting() -> None:
    long_modules, long_functions = [], []
    for name, path in module_files().items():
        text = path.read_text()
        if len(text.splitlines()) > MAX_MODULE_LINES:
            long_modules.append(f"{name} ({len(text.splitlines())} lines)")
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                n = node.end_lineno - node.lineno + 1
                if n > MAX_FUNCTION_LINES:
                    long_functions.append(f"{name}.{node.name} ({n} lines)")
    assert not long_modules, f"modules over {MAX_MODULE_LINES} lines: {long_modules}"
    assert not long_functions, f"functions over {MAX_FUNCTION_LINES} lines: {long_functions}"


def test_the_floor_check_catches_an_upward_import() -> None:
    assert floor_of("anisdf.fields.sdf_field") < floor_of("anisdf.models.anisdf") < floor_of("anisdf.cli.train")
    assert floor_of("anisdf.nowhere") is None
