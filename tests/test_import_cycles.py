"""No import cycles among the package's modules (warpgs/ and kernels/, shipped as warpgs.kernels).

The graph is read from the source with `ast`: an edge for every import statement of a module, at module level or
inside a function (an import moved into a function still makes the two modules depend on each other; it only hides
the cycle from the interpreter), except those under `if TYPE_CHECKING:`. `from package import name` points at the
submodule when `name` is one, else at the package's __init__. Importing a submodule also runs its parents'
__init__ files, but that alone is no cycle (Python finishes a package after its submodules), so only the modules
an import names count."""
import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SOURCES = {"warpgs": ROOT / "warpgs", "warpgs.kernels": ROOT / "kernels"}


def module_files(sources: dict) -> dict:
    """{dotted module name: file} for every .py file under {package name: folder} (a package is named by its
    __init__.py)."""
    files = {}
    for prefix, folder in sources.items():
        for path in sorted(folder.rglob("*.py")):
            parts = list(path.relative_to(folder).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            files[".".join([prefix, *parts])] = path
    return files


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or \
        (isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def _imports(node: ast.AST):
    """Every import statement under `node`, skipping the bodies of `if TYPE_CHECKING:` blocks."""
    for child in ast.iter_child_nodes(node):
        if isinstance(child, (ast.Import, ast.ImportFrom)):
            yield child
        elif isinstance(child, ast.If) and _is_type_checking(child.test):
            for other in child.orelse:
                yield from _imports(ast.Module(body=[other], type_ignores=[]))
        else:
            yield from _imports(child)


def import_graph(sources: dict = SOURCES) -> dict:
    """{module: set of the package's modules it imports}."""
    files = module_files(sources)
    graph = {}
    for name, path in files.items():
        is_package = path.name == "__init__.py"
        edges = set()
        for node in _imports(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, ast.Import):
                targets = [alias.name for alias in node.names]
            else:
                base = node.module or ""
                if node.level:  # relative: from the module's package, one level up per extra dot
                    package = name.split(".") if is_package else name.split(".")[:-1]
                    package = package[: len(package) - (node.level - 1)]
                    base = ".".join(package + ([base] if base else []))
                targets = [f"{base}.{alias.name}" if f"{base}.{alias.name}" in files else base
                           for alias in node.names]
            edges.update(t for t in targets if t in files and t != name)
        graph[name] = edges
    return graph


def cycles(graph: dict) -> list:
    """The strongly connected components with more than one module (Tarjan), each sorted."""
    index, low, on_stack, stack, found = {}, {}, set(), [], []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_the_graph_sees_every_kind_of_import(tmp_path):
    pkg = tmp_path / "pkg"
    (pkg / "sub").mkdir(parents=True)
    files = {
        "__init__.py": "from pkg.sub import b\n",
        "a.py": "import os\nfrom pkg.sub import b\n",
        "sub/__init__.py": "",
        "sub/b.py": "def f():\n    from .. import a\n    return a\n",  # inside a function, relative
        "sub/c.py": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from pkg import a\nfrom . import b\n",
        "d.py": "from pkg.sub import c as other\nfrom pkg import __version__\n",  # a name of pkg's __init__
    }
    for name, text in files.items():
        (pkg / name).write_text(text)
    graph = import_graph({"pkg": pkg})
    assert graph == {"pkg": {"pkg.sub.b"}, "pkg.a": {"pkg.sub.b"}, "pkg.sub": set(), "pkg.sub.b": {"pkg.a"},
                     "pkg.sub.c": {"pkg.sub.b"}, "pkg.d": {"pkg.sub.c", "pkg"}}
    assert cycles(graph) == [["pkg.a", "pkg.sub.b"]]
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_no_import_cycles():
    graph = import_graph()
    assert "warpgs.kernels.blend" in graph["warpgs.render.fast_pipeline"]  # kernels/ is read as warpgs.kernels
    found = cycles(graph)
    assert not found, "import cycles (modules that import each other, directly or in a ring): " + "; ".join(
        " <-> ".join(c) for c in found)
