"""The import map, read from the source (nothing is imported): mapless/ is a stack of layers along
the data flow (scene -> observation -> agent -> trainer/evaluator -> report) with no circle among
its modules or packages (docs/reference/architecture.md); scenes/ is a stack of modules each importing only those
below it, at module level; and the action set is declared once, below both the simulator and the
models."""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "mapless"
#: mapless/ bottom to top (docs/reference/architecture.md): a module imports only from its own layer or those
#: below, function-level imports included.
LAYERS: tuple[tuple[str, ...], ...] = (
    (
        "mapless",
        "errors",
        "files",
        "config",
        "configs",
        "actions",
        "observations",
        "provenance",
        "processes",
        "safe_pickle",
        "data",
    ),
    ("scenes", "knowledge"),  # floor plans, categories, arrangements; the priors over them
    ("sim",),  # the simulator: observations, rewards
    ("offline", "thor", "episodes"),  # other sources of scenes; episode sets and the sampler
    ("models",),  # the policy
    ("agent",),  # acting, adapting, the one episode loop
    ("checkpoint", "train", "evaluate"),  # trainer and evaluator, and the run folder between them
    ("experiments",),  # experiments and their reports
    ("cli", "__main__"),
)
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


def _module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _unit(module: str) -> str:
    """The layer unit of a module: its subpackage or top-level module (``mapless`` itself)."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else parts[0]


def _import_map() -> dict[str, set[str]]:
    """Every module of mapless/ and the mapless modules it imports, at any level."""
    return {
        _module_name(path): {target for target, _ in _imports(path)} - {_module_name(path)}
        for path in PACKAGE.rglob("*.py")
    }


def _circle(graph: dict[str, set[str]]) -> list[str] | None:
    """A circle of ``graph`` (a path that comes back to its start), or None."""
    done: set[str] = set()
    path: list[str] = []

    def visit(node: str) -> list[str] | None:
        if node in path:
            return [*path[path.index(node) :], node]
        if node in done:
            return None
        path.append(node)
        for other in sorted(graph.get(node, ())):
            if found := visit(other):
                return found
        path.pop()
        done.add(node)
        return None

    for node in sorted(graph):
        if found := visit(node):
            return found
    return None


def test_mapless_has_no_import_circle_between_modules_or_packages() -> None:
    imports = _import_map()
    circle = _circle(imports)
    assert circle is None, " -> ".join(circle or [])
    packages: dict[str, set[str]] = {}
    for module, targets in imports.items():
        packages.setdefault(_unit(module), set()).update(
            _unit(t) for t in targets if _unit(t) != _unit(module)
        )
    circle = _circle(packages)
    assert circle is None, " -> ".join(circle or [])


def test_no_module_imports_above_its_layer_and_the_evaluator_imports_no_trainer() -> None:
    layer = {unit: level for level, units in enumerate(LAYERS) for unit in units}
    imports = _import_map()
    units = {_unit(module) for module in imports} | {
        p.name for p in PACKAGE.iterdir() if p.is_dir() and p.name != "__pycache__"
    }
    assert units <= set(layer), f"{sorted(units - set(layer))}: place each in LAYERS"
    upward = [
        f"{module} imports {target}"
        for module, targets in sorted(imports.items())
        for target in sorted(targets)
        if layer[_unit(target)] > layer[_unit(module)]
    ]
    assert not upward, upward
    assert not [
        m
        for m, targets in imports.items()
        if _unit(m) == "evaluate" and any(_unit(t) == "train" for t in targets)
    ]
