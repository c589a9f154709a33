"""The package's shape: imports form no cycle, and no module outgrows one concept.

The import graph is read from the source with ``ast`` (every import, also those inside
functions), so a cycle fails here even when a lazy import keeps it from failing at run time.
An edge goes to the module that is imported: ``from jaxden.a import b`` points at
``jaxden.a.b`` when that is a module, else at ``jaxden.a`` (its ``__init__``).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parent.parent / "jaxden"
MAX_LINES = 600


def module_names(root: Path) -> dict[str, Path]:
    names = {}
    for path in sorted(root.rglob("*.py")):
        parts = path.relative_to(root.parent).with_suffix("").parts
        if parts[-1] == "__init__":
            parts = parts[:-1]
        names[".".join(parts)] = path
    return names


def import_graph(root: Path) -> dict[str, set[str]]:
    """``{module: {imported jaxden modules}}`` for every module under ``root``."""
    modules = module_names(root)
    package = root.name
    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        is_package = path.name == "__init__.py"
        edges = set()
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                targets = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:  # relative import
                    anchor = name.split(".") if is_package else name.split(".")[:-1]
                    anchor = anchor[: len(anchor) - (node.level - 1)]
                    base = ".".join([*anchor, *([base] if base else [])])
                targets = []
                for alias in node.names:
                    sub = f"{base}.{alias.name}"
                    targets.append(sub if sub in modules else base)
            else:
                continue
            edges.update(t for t in targets if t == package or t.startswith(package + "."))
        graph[name] = {e for e in edges if e in modules and e != name}
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import cycle as a list of modules (first == last), or None."""
    state: dict[str, int] = {}  # 1: on the stack, 2: done
    stack: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                return stack[stack.index(nxt):] + [nxt]
            if nxt not in state:
                found = visit(nxt)
                if found:
                    return found
        stack.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state:
            found = visit(node)
            if found:
                return found
    return None


def test_no_import_cycle():
    cycle = find_cycle(import_graph(PACKAGE))
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


def test_cycle_detector_finds_a_planted_cycle(tmp_path):
    """The detector itself: a package with a lazy (function-level) cycle a -> b -> a."""
    pkg = tmp_path / "jaxden"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "sub" / "__init__.py").write_text("")
    (pkg / "sub" / "a.py").write_text("from jaxden.sub.b import g\n")
    (pkg / "sub" / "b.py").write_text("def g():\n    from jaxden.sub import a\n    return a\n")
    (pkg / "c.py").write_text("from jaxden.sub import a\n")
    assert find_cycle(import_graph(pkg)) == ["jaxden.sub.a", "jaxden.sub.b", "jaxden.sub.a"]
    (pkg / "sub" / "b.py").write_text("def g():\n    return 1\n")
    assert find_cycle(import_graph(pkg)) is None


@pytest.mark.parametrize("name", sorted(module_names(PACKAGE)))
def test_module_size(name):
    lines = len(module_names(PACKAGE)[name].read_text().splitlines())
    assert lines <= MAX_LINES, f"{name} has {lines} lines (one concept per module: <= {MAX_LINES})"
