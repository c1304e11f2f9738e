"""The import map of the low layers, read from the source (nothing is imported): scenes/ is a
stack of modules each importing only those below it, at module level, and the action set is
declared once, below both the simulator and the models (issue 44, point 5)."""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "mapless"
#: scenes/ bottom to top: each module may import only modules earlier in this list.
SCENES_STACK = ("catalogue", "arrangements", "floor_plans", "categories", "generator", "variants", "layout")


def _imports(path: Path) -> list[tuple[str, bool]]:
    """``(imported module, at module level)`` of every ``import``/``from`` of a mapless module in a
    file; ``from mapless.x import y`` counts as ``mapless.x.y`` when ``y`` is a module."""
    tree = ast.parse(path.read_text())
    top = {id(node) for node in tree.body}
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("mapless"):
            for alias in node.names:
                target = f"{node.module}.{alias.name}"
                is_module = (PACKAGE.parent / target.replace(".", "/")).with_suffix(".py").is_file()
                found.append((target if is_module else node.module, id(node) in top))
        elif isinstance(node, ast.Import):
            found += [(a.name, id(node) in top) for a in node.names if a.name.startswith("mapless")]
    return found


def test_scenes_modules_form_a_stack_with_module_level_imports_only() -> None:
    modules = sorted(p.stem for p in (PACKAGE / "scenes").glob("*.py") if p.stem != "__init__")
    assert sorted(SCENES_STACK) == modules, "a new scenes module takes its place in SCENES_STACK"
    for level, name in enumerate(SCENES_STACK):
        for target, module_level in _imports(PACKAGE / "scenes" / f"{name}.py"):
            if not target.startswith("mapless.scenes."):
                continue
            other = target.split(".")[2]
            # A function-level import is how a circle is hidden; a stack needs none.
            assert module_level, f"scenes/{name}.py imports {target} inside a function"
            assert SCENES_STACK.index(other) < level, f"scenes/{name}.py imports {other}, which is above it"


def test_the_action_set_is_declared_once_below_the_simulator_and_the_models() -> None:
    declared = [
        path.relative_to(PACKAGE).as_posix()
        for path in PACKAGE.rglob("*.py")
        if any(
            isinstance(node, (ast.Assign, ast.AnnAssign))
            and any(
                isinstance(t, ast.Name) and t.id in ("ACTIONS", "NUM_ACTIONS")
                for t in (node.targets if isinstance(node, ast.Assign) else [node.target])
            )
            for node in ast.parse(path.read_text()).body
        )
    ]
    assert declared == ["actions.py"]
    # The models take the policy's width from there, not from the simulator.
    for path in (PACKAGE / "models").glob("*.py"):
        assert not [t for t, _ in _imports(path) if t.startswith("mapless.sim")], path.name
    assert {t for t, _ in _imports(PACKAGE / "actions.py")} == set()  # it stands on nothing
