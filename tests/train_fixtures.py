"""Small, fast training setups: hand-made kitchen scenes and tiny model configs (no scene building)."""

from __future__ import annotations

from scene_fixtures import grid_scene

from mapless.config import apply_overrides, from_dict
from mapless.errors import MaplessError
from mapless.models import model_class
from mapless.scenes.catalogue import room_type_of
from mapless.sim.library import SceneLibrary
from mapless.train.config import TrainConfig

SCENES = "FloorPlan1,FloorPlan2"
#: A 3x3 grid so that episodes last a few steps and targets are sometimes out of view.
POSITIONS = tuple((0.25 * i, 0.25 * j) for i in range(3) for j in range(3))


def _scene(name: str):
    return grid_scene(POSITIONS, scene=name, room_type=room_type_of(name), seed=int(name[9:]), blocked=())


def fixture_library() -> SceneLibrary:
    """Module-level (picklable) factory: spawned async workers build the same scenes."""
    return SceneLibrary(_scene)


def tiny_config(model: str = "a3c", *overrides: str) -> TrainConfig:
    # The small A3C batch is the A3C runs' only: a PPO run may not set the a3c: block.
    a3c = {} if "algo=ppo" in overrides else {"a3c": {"batch_size": 4}}
    base = {
        "model": {"name": model, "hidden_size": 16, "fusion_channels": 2, "dropout": 0.0},
        "env": {"scenes": SCENES, "max_steps": 8},
        **a3c,
        "episodes": 8,
        "checkpoint_every": 4,
        "log_every": 4,
        "threads": 1,
        "progress": False,
    }
    data = apply_overrides(base, list(overrides))
    # The small widths for the models that have them: a setting a model does not read is refused.
    model = data["model"]
    try:
        declared = model_class(model["name"]).settings
    except MaplessError:  # an unknown name keeps them all: TrainConfig refuses the name itself
        declared = {"fusion_channels": "", "dropout": ""}
    for key in ("fusion_channels", "dropout"):
        if not any(o.startswith(f"model.{key}=") for o in overrides) and key not in declared:
            del model[key]
    return from_dict(TrainConfig, data)
