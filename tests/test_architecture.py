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


# ------------------------------------------------------------------------- private names
#: At most this many private names (``_name``) may be imported from another jaxden module: a
#: private name used elsewhere says the boundary is in the wrong place (docs/DESIGN).
MAX_PRIVATE_IMPORTS = 10


def private_imports(root: Path) -> list[str]:
    """``"module: from X import _name"`` for every private name a module under ``root``
    imports from another jaxden module (also inside functions, also over several lines)."""
    found = []
    for name, path in module_names(root).items():
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if not isinstance(node, ast.ImportFrom):
                continue
            module = node.module or ""
            if not (node.level or module == root.name or module.startswith(root.name + ".")):
                continue
            found += [f"{name}: from {'.' * node.level}{module} import {alias.name}"
                      for alias in node.names
                      if alias.name.startswith("_") and not alias.name.startswith("__")]
    return found


def test_few_private_names_cross_modules():
    found = private_imports(PACKAGE)
    assert len(found) <= MAX_PRIVATE_IMPORTS, (
        f"{len(found)} private names imported across modules (at most "
        f"{MAX_PRIVATE_IMPORTS}): make shared helpers public where they live:\n"
        + "\n".join(found))


def test_private_import_counter_sees_lazy_and_multiline_imports(tmp_path):
    pkg = tmp_path / "jaxden"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("def _h():\n    pass\n")
    (pkg / "b.py").write_text("from jaxden.a import (\n    _h,\n)\n\n\ndef f():\n"
                              "    from jaxden.a import _h as h, __doc__\n    return h\n")
    assert private_imports(pkg) == ["jaxden.b: from jaxden.a import _h"] * 2


# ----------------------------------------------------------------------- model-name branches
#: Where no code may branch on a model's name: a model is looked up in the one name ->
#: definition table (jaxden.train.tasks), never compared with a name.
NO_MODEL_BRANCHES = ("train", "sweep.py")


def model_name_branches(path: Path) -> list[str]:
    """``"file:line"`` of every comparison of a ``.model`` attribute with a string literal
    (``config.model == "mixer"``, ``"mixer" != train.model``, ``model in ("a", "b")``)."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if not isinstance(node, ast.Compare):
            continue
        sides = [node.left, *node.comparators]
        names = [s for s in sides if isinstance(s, ast.Attribute) and s.attr == "model"]
        literals = [s for s in sides if isinstance(s, ast.Constant) and isinstance(s.value, str)
                    or isinstance(s, (ast.Tuple, ast.List, ast.Set)) and any(
                        isinstance(e, ast.Constant) and isinstance(e.value, str) for e in s.elts)]
        if names and literals:
            found.append(f"{path.name}:{node.lineno}")
    return found


def test_no_model_name_branches():
    paths = []
    for part in NO_MODEL_BRANCHES:
        target = PACKAGE / part
        paths += sorted(target.rglob("*.py")) if target.is_dir() else [target]
    found = [branch for path in paths for branch in model_name_branches(path)]
    assert not found, ("branches on a model name (look the model up in "
                       "jaxden.train.tasks.get_trainable instead): " + ", ".join(found))


def test_model_branch_detector(tmp_path):
    path = tmp_path / "m.py"
    path.write_text('if config.model == "mixer":\n    pass\nok = config.model == other\n'
                    'bad = "kp" != run.model\nalso = train.model in ("a", "b")\n')
    assert model_name_branches(path) == ["m.py:1", "m.py:4", "m.py:5"]
