"""The package's layers: imports point down only (docs/concepts.md, "Layers").

Lowest first; modules of one layer may import their own capability (the same folder) and
anything in a lower layer, never a peer of their layer or anything above. Function-level imports
are allowed only for optional heavy dependencies (ray, torch), so no import hides a cycle.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parent.parent / "ms_drake"
LAYERS = [  # lowest first
    ("types", "geometry", "shelf_geometry", "errors", "paths", "parallel", "jit", "config_files"),
    ("objects", "robots"),
    ("scenario",),
    ("station",),
    ("perception", "grasping", "pushing", "planning", "scenes", "foss"),
    # Point-cloud collision checking uses planning's batched kinematics for the robot's links.
    ("collision",),
    # The controller Diagrams that policies/ builds hold the ActionExecutor and its motion
    # backends, so execution sits below policies.
    ("execution",),
    ("policies",),
    ("experiments",),
    ("cli",),
]
LEVEL = {name: k for k, names in enumerate(LAYERS) for name in names}
FUNCTION_LEVEL_ALLOWED = {"ray", "torch", "pytorch_mppi"}  # optional or heavy; imported where used


def _modules():
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(PACKAGE)
        yield rel, ast.parse(path.read_text(), str(path))


def _capability(rel: Path) -> str:
    return rel.parts[0].removesuffix(".py")


def _imports(rel: Path, tree: ast.Module):
    """(imported module, line, inside a function) of every import of the file."""
    parents = {c: n for n in ast.walk(tree) for c in ast.iter_child_nodes(n)}

    def in_function(node):
        while node in parents:
            node = parents[node]
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                return True
        return False

    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name, node.lineno, in_function(node)
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative: resolve against the file's package
                base = ("ms_drake",) + rel.parent.parts
                base = base[:len(base) - node.level + 1]
                yield ".".join(base + ((node.module,) if node.module else ())), node.lineno, in_function(node)
            else:
                yield node.module, node.lineno, in_function(node)


def test_every_capability_has_a_layer():
    unknown = {_capability(rel) for rel, _ in _modules()} - set(LEVEL) - {"__init__"}
    assert not unknown, f"add {sorted(unknown)} to LAYERS in tests/test_layers.py (and docs/concepts.md)"


@pytest.mark.parametrize("rel, tree", list(_modules()), ids=lambda x: str(x) if isinstance(x, Path) else "")
def test_imports_point_down(rel, tree):
    here = _capability(rel)
    bad = []
    for module, line, in_function in _imports(rel, tree):
        parts = module.split(".")
        if parts[0] == "ms_drake" and len(parts) > 1 and here != "__init__":
            there = parts[1]
            same_foundation = LEVEL.get(there) == LEVEL.get(here) == 0  # single-file modules, no cycles
            if there != here and there in LEVEL and LEVEL[there] >= LEVEL[here] and not same_foundation:
                bad.append(f"ms_drake/{rel}:{line} imports {module} (layer {LEVEL[there]} >= {LEVEL[here]})")
        if in_function and parts[0] not in FUNCTION_LEVEL_ALLOWED:
            bad.append(f"ms_drake/{rel}:{line} imports {module} inside a function (only "
                       f"{', '.join(sorted(FUNCTION_LEVEL_ALLOWED))} may be; move it to the top)")
    assert not bad, "\n".join(bad)


def test_the_layer_test_catches_an_upward_import(tmp_path):
    tree = ast.parse("from ms_drake.policies import selector\n")
    rel = Path("station") / "fake.py"
    here = _capability(rel)
    found = [m for m, _, _ in _imports(rel, tree) if LEVEL[m.split(".")[1]] >= LEVEL[here]]
    assert found == ["ms_drake.policies"]
