"""No import cycle among the modules of src/ptovs.

Every `import` and `from ... import` of every module counts, at module level or
inside a function (an import inside a function still ties the two modules), as
an edge to the file it names: `a.b.c` is `a/b/c.py` (or the package
`a/b/c/__init__.py` when it is one), and `from a.b import c` is module `a.b.c`
when that file exists, else `a.b` itself. Importing `a.b.c` depends on that file
alone, not on the packages above it (their `__init__.py` files run first, but a
package's face only hands names on); a package imported by name depends on its
`__init__.py`. The files of each strongly connected component of more than one
file (or of a file that imports itself) form a cycle.
"""

from __future__ import annotations

import ast
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src"


def module_files(root: Path, package: str) -> dict[str, Path]:
    """{dotted module name: file} of every .py under `root / package`."""
    out = {}
    for path in sorted((root / package).rglob("*.py")):
        parts = list(path.relative_to(root).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        out[".".join(parts)] = path
    return out


def imported_modules(path: Path, module: str, modules: dict[str, Path]) -> set[str]:
    """The modules of `modules` that the file of `module` imports anywhere in it."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base_parts = package.split(".")
                base_parts = base_parts[: len(base_parts) - (node.level - 1)]
                base = ".".join(base_parts + ([node.module] if node.module else []))
            else:
                base = node.module or ""
            for alias in node.names:
                child = f"{base}.{alias.name}"
                found.add(child if child in modules else base)
    return {name for name in found if name in modules and name != ""}


def import_graph(root: Path, package: str) -> dict[str, set[str]]:
    """{module: the package's modules it imports}."""
    modules = module_files(root, package)
    return {
        name: imported_modules(path, name, modules) for name, path in modules.items()
    }


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components that are cycles (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    on_stack: set[str] = set()
    stack: list[str] = []
    found: list[list[str]] = []
    counter = 0
    for start in sorted(graph):
        if start in index:
            continue
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = counter
        counter += 1
        stack.append(start)
        on_stack.add(start)
        while work:
            node, edges = work[-1]
            for nxt in edges:
                if nxt not in index:
                    index[nxt] = low[nxt] = counter
                    counter += 1
                    stack.append(nxt)
                    on_stack.add(nxt)
                    work.append((nxt, iter(sorted(graph.get(nxt, ())))))
                    break
                if nxt in on_stack:
                    low[node] = min(low[node], index[nxt])
            else:
                work.pop()
                if work:
                    parent = work[-1][0]
                    low[parent] = min(low[parent], low[node])
                if low[node] == index[node]:
                    component = []
                    while True:
                        member = stack.pop()
                        on_stack.discard(member)
                        component.append(member)
                        if member == node:
                            break
                    if len(component) > 1 or node in graph.get(node, ()):
                        found.append(sorted(component))
    return found


def describe(found: list[list[str]], files: dict[str, Path], root: Path) -> str:
    return "\n".join(
        "import cycle: " + ", ".join(str(files[m].relative_to(root)) for m in cycle)
        for cycle in found
    )


def test_no_import_cycle_in_ptovs():
    graph = import_graph(SRC, "ptovs")
    assert "ptovs.stage" in graph and "ptovs.cli" in graph  # the walk found the code
    found = cycles(graph)
    assert not found, describe(found, module_files(SRC, "ptovs"), SRC)


def test_the_check_finds_a_cycle(tmp_path: Path):
    """A tiny package whose modules import each other in a ring, one of them
    inside a function and one relatively, and a module outside the ring."""
    pkg = tmp_path / "pkg"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "sub" / "__init__.py").write_text("")
    (pkg / "a.py").write_text("from pkg.sub import b\n")
    (pkg / "sub" / "b.py").write_text("def f():\n    from ..c import g\n")
    (pkg / "c.py").write_text("import pkg.a\n\ng = 1\n")
    (pkg / "d.py").write_text("from pkg import a, c\nimport pkg.sub\n")
    graph = import_graph(tmp_path, "pkg")
    assert graph["pkg.sub.b"] == {"pkg.c"}  # `from ..c import g`: g is no module
    assert graph["pkg.d"] == {"pkg.a", "pkg.c", "pkg.sub"}  # pkg.sub: its __init__
    found = cycles(graph)
    assert found == [["pkg.a", "pkg.c", "pkg.sub.b"]]
    text = describe(found, module_files(tmp_path, "pkg"), tmp_path)
    assert "pkg/a.py" in text and "pkg/sub/b.py" in text and "pkg/c.py" in text
    (pkg / "c.py").write_text("g = 1\n")  # the ring broken: no cycle
    assert cycles(import_graph(tmp_path, "pkg")) == []
