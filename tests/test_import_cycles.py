"""No import cycle between the package's modules (docs/ARCHITECTURE.md, section 1).

Every import counts, at module level and inside functions (a function-level import only hides a
cycle until that function runs). ``from brave6d.serve import X`` counts as an import of the module
that defines ``X`` (the package's lazy ``_LAZY`` table says which), so a cycle through a lazy
public name is found too.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGE = ROOT / "src" / "brave6d"


def _module_name(path: Path, package: Path) -> str:
    parts = list(path.relative_to(package.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _lazy_table(tree: ast.Module, package: str) -> dict[str, str]:
    """A package's ``_LAZY`` (public name -> defining module), evaluated from its assignment alone."""
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(isinstance(t, ast.Name) and t.id == "_LAZY" for t in node.targets):
            namespace: dict[str, object] = {}
            exec(compile(ast.Module([node], []), "<_LAZY>", "exec"), namespace)  # noqa: S102 - our own source
            table = namespace["_LAZY"]
            assert isinstance(table, dict)
            return {name: package + target if target.startswith(".") else target for name, target in table.items()}
    return {}


def import_graph(package: Path = PACKAGE) -> dict[str, set[str]]:
    """``module -> the package's modules it imports`` (module- and function-level imports)."""
    files = {_module_name(p, package): p for p in sorted(package.rglob("*.py"))}
    trees = {name: ast.parse(p.read_text(encoding="utf-8"), filename=str(p)) for name, p in files.items()}
    packages = {name for name, p in files.items() if p.name == "__init__.py"}
    lazy = {name: _lazy_table(trees[name], name) for name in packages}

    def target(base: str, name: str) -> str | None:
        if f"{base}.{name}" in files:
            return f"{base}.{name}"
        if name in lazy.get(base, {}):
            return lazy[base][name]
        return base if base in files else None

    graph: dict[str, set[str]] = {}
    for name, tree in trees.items():
        here = name if name in packages else name.rpartition(".")[0]
        edges: set[str] = set()
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom):
                if node.level:
                    parts = here.split(".")
                    base = ".".join(parts[:len(parts) - node.level + 1])
                    base = f"{base}.{node.module}" if node.module else base
                else:
                    base = node.module or ""
                edges |= {t for alias in node.names if (t := target(base, alias.name)) is not None}
            elif isinstance(node, ast.Import):
                edges |= {alias.name for alias in node.names if alias.name in files}
        edges.discard(name)
        graph[name] = edges
    return graph


def import_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
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
                cycles.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return sorted(cycles)


def _shown(cycle: list[str], graph: dict[str, set[str]]) -> str:
    return "  " + ", ".join(f"{m} -> {sorted(graph[m] & set(cycle))}" for m in cycle)


def test_the_package_has_no_import_cycle() -> None:
    graph = import_graph()
    assert "brave6d.serve.catalog" in graph and graph["brave6d.serve.catalog"]  # the graph is not empty
    cycles = import_cycles(graph)
    assert not cycles, "import cycles (break each with a module both sides import):\n" + "\n".join(
        _shown(c, graph) for c in cycles)


def test_the_cycle_check_sees_function_level_and_lazy_cycles(tmp_path: Path) -> None:
    pkg = tmp_path / "brave6d"
    (pkg / "stage").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "stage" / "__init__.py").write_text('_LAZY = {name: ".b" for name in ("B",)}\n')
    (pkg / "stage" / "a.py").write_text("def f():\n    from brave6d.stage.b import B\n")
    (pkg / "stage" / "b.py").write_text("from . import c\nB = 1\n")
    (pkg / "stage" / "c.py").write_text("def g():\n    from brave6d.stage import B\n")  # the lazy name: b
    (pkg / "stage" / "d.py").write_text("import brave6d.stage.a\n")  # into a cycle, not part of one
    graph = import_graph(pkg)
    assert graph["brave6d.stage.c"] == {"brave6d.stage.b"} and graph["brave6d.stage.b"] == {"brave6d.stage.c"}
    assert import_cycles(graph) == [["brave6d.stage.b", "brave6d.stage.c"]]
