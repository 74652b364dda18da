"""The layout the design promises: floors (core, then io, then the add-on and the commands) with no
import running back up, no import circle anywhere in the product (lazy imports inside functions
count: they hide a circle, they do not remove it), and no source file over 1,000 lines.

The import graph is read from the sources with `ast`, not by importing them, so the add-on's modules
(which need bpy) are read too."""

import ast
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PRODUCT = ("core", "io", "splat_addon")
SCRIPTS = ("cli.py", "demo.py", "__init__.py", "__main__.py")
MAX_LINES = 1000
# What each floor may import: a floor never reaches the floors above it.
FLOORS = {"core": {"core"}, "io": {"core", "io"}, "splat_addon": {"core", "io", "splat_addon"}}


def product_files():
    files = [ROOT / name for name in SCRIPTS]
    for package in PRODUCT:
        files += sorted((ROOT / package).rglob("*.py"))
    return [f for f in files if f.exists() and "__pycache__" not in f.parts]


def module_name(path):
    """'core.render' for core/render.py, 'io' for io/__init__.py, 'cli' for cli.py, '' for the root."""
    parts = path.relative_to(ROOT).with_suffix("").parts
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _package_of(path):
    name = module_name(path)
    return name if path.name == "__init__.py" else name.rpartition(".")[0]


def imports_of(path, modules):
    """The product modules `path` imports (relative imports resolved, `from . import x` naming the
    module x where x is one), wherever the import stands in the file."""
    tree = ast.parse(path.read_text(), str(path))
    package = _package_of(path)
    found = set()
    for node in ast.walk(tree):
        if not isinstance(node, ast.ImportFrom) or node.level == 0:
            continue
        base = package.split(".") if package else []
        base = base[: len(base) - (node.level - 1)] if node.level > 1 else base
        target = ".".join(base + ([node.module] if node.module else []))
        for alias in node.names:
            candidate = f"{target}.{alias.name}" if target else alias.name
            found.add(candidate if candidate in modules else target)
    return {m for m in found if m in modules}


def import_graph():
    files = product_files()
    modules = {module_name(f): f for f in files}
    return {name: imports_of(path, modules) - {name} for name, path in modules.items()}


def cycles(graph):
    """Every strongly connected component of more than one module (Tarjan's algorithm)."""
    index, low, stack, on_stack, found = {}, {}, [], set(), []

    def visit(node):
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for nxt in sorted(graph[node]):
            if nxt not in index:
                visit(nxt)
                low[node] = min(low[node], low[nxt])
            elif nxt in on_stack:
                low[node] = min(low[node], index[nxt])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return found


def test_the_graph_reader_finds_a_circle():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert cycles(graph) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_the_graph_reader_sees_the_products_own_imports():
    graph = import_graph()
    assert "core.splats" in graph["io.ply"] and "core.sh" in graph["core.render"]
    assert "splat_addon.data" in graph["splat_addon.files.import_export"]


def test_no_import_circle_in_the_product():
    assert cycles(import_graph()) == []


def test_no_floor_imports_a_floor_above_it():
    wrong = [
        (name, target)
        for name, targets in import_graph().items()
        for target in targets
        if name.split(".")[0] in FLOORS and target.split(".")[0] not in FLOORS[name.split(".")[0]]
    ]
    assert wrong == []


def test_no_source_file_over_a_thousand_lines():
    long = {str(f.relative_to(ROOT)): n for f in product_files() if (n := len(f.read_text().splitlines())) > MAX_LINES}
    assert long == {}


def test_the_installed_packages_are_the_ones_on_disk():
    """pyproject.toml lists every package (a sub-package left out is missing from a pip install)."""
    listed = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    on_disk = {"splatwright"} | {
        "splatwright." + ".".join(init.parent.relative_to(ROOT).parts)
        for package in PRODUCT
        for init in (ROOT / package).rglob("__init__.py")
    }
    assert listed == on_disk


def test_every_compiled_kernel_loads_here():
    """numba is a dependency: every compiled twin must load, so the tests that set a kernel beside
    its NumPy path compare two paths, not NumPy with itself (where numba cannot load, as in Blender's
    Python, the NumPy paths run and are tested on their own)."""
    from kernels import missing_kernels

    from splatwright.core import jit

    assert jit.enabled(), "SPLATWRIGHT_JIT turns the compiled kernels off"
    assert missing_kernels() == []
