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
