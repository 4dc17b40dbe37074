"""The packages are layers, each importing only those below it:
numerics < tasks < models < estimators < harness."""

import ast
import pathlib

import pytest

LAYERS = ["numerics", "tasks", "models", "estimators", "harness"]
ROOT = pathlib.Path(__file__).resolve().parent.parent


def imported_packages(path: pathlib.Path) -> set[str]:
    """The project's packages that a module imports anywhere in it (top level or inside functions)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found |= {alias.name.split(".")[0] for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            found.add(node.module.split(".")[0])
    return found & set(LAYERS)


@pytest.mark.parametrize("layer", LAYERS)
def test_a_layer_imports_only_the_layers_below_it(layer):
    allowed = set(LAYERS[: LAYERS.index(layer) + 1])
    upward = {str(path.relative_to(ROOT)): sorted(imported_packages(path) - allowed)
              for path in sorted((ROOT / layer).glob("*.py"))}
    assert {module: packages for module, packages in upward.items() if packages} == {}


def module_imports(path: pathlib.Path) -> set[str]:
    """The project's modules that a module imports anywhere in it (top level or inside functions), as dotted
    names ("harness.learn"); ``from harness import learn`` counts as ``harness.learn``."""
    modules = {".".join(p.relative_to(ROOT).with_suffix("").parts) for layer in LAYERS
               for p in (ROOT / layer).glob("*.py")}
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            found.add(node.module)
            found |= {f"{node.module}.{alias.name}" for alias in node.names}
    return {name for name in found if name in modules and not name.endswith("__init__")}


def test_no_import_cycle_anywhere():
    """No module reaches itself through imports, counting those inside functions (a hidden cycle is a
    cycle: the two modules cannot be understood, tested or moved apart)."""
    graph = {".".join(p.relative_to(ROOT).with_suffix("").parts): module_imports(p)
             for layer in LAYERS for p in sorted((ROOT / layer).glob("*.py"))}
    cycles = []

    def visit(node, path, on_path, done):
        for nxt in sorted(graph.get(node, ())):
            if nxt in on_path:
                cycles.append(path[path.index(nxt):] + [nxt])
            elif nxt not in done:
                on_path.add(nxt)
                visit(nxt, path + [nxt], on_path, done)
                on_path.discard(nxt)
        done.add(node)

    done = set()
    for start in sorted(graph):
        if start not in done:
            visit(start, [start], {start}, done)
    assert cycles == [], "import cycles: " + "; ".join(" -> ".join(c) for c in cycles)
