"""Arguments shared by several sub-commands."""

from __future__ import annotations

import argparse
from pathlib import Path

from mapless.config import load_config
from mapless.scenes.categories import CATEGORY_SETS
from mapless.sim.config import SimConfig

#: Help of a SCENES argument (read by :func:`mapless.scenes.catalogue.resolve_scenes`).
SCENES_HELP = "split name, split:room, or FloorPlan names (comma-separated)"


def add_sim_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--sim-config", type=Path, help="YAML file with simulator settings (SimConfig fields)"
    )
    parser.add_argument(
        "--sim",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a simulator setting, e.g. visibility_distance=1.5",
    )
    parser.add_argument(
        "--cache-dir",
        type=Path,
        help="cache root, the same as $MAPLESS_CACHE: scenes go in CACHE_DIR/scenes/ "
        "(default $MAPLESS_CACHE or ~/.cache/mapless)",
    )


def add_category_set_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--category-set",
        default="mjolnir101",
        choices=CATEGORY_SETS,
        help="object categories of the context rows and feature maps (default: %(default)s)",
    )


def sim_config_from(args: argparse.Namespace) -> SimConfig:
    return load_config(SimConfig, args.sim_config, args.sim)


def parse_pose(text: str) -> tuple[float, float, int, int]:
    """``"x,z,yaw,horizon"`` or the SAVN key ``"x|z|yaw|horizon"``."""
    parts = text.replace("|", ",").split(",")
    if len(parts) != 4:
        raise argparse.ArgumentTypeError(f"pose {text!r} must be x,z,yaw,horizon")
    try:
        return float(parts[0]), float(parts[1]), int(parts[2]), int(parts[3])
    except ValueError:
        raise argparse.ArgumentTypeError(f"pose {text!r} must be x,z,yaw,horizon (numbers)") from None


def positive_int(text: str) -> int:
    """An argparse type: an integer >= 1 (a batch size, a worker or episode count)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value
