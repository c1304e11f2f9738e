"""Arguments shared by several sub-commands."""

from __future__ import annotations

import argparse
import inspect
from collections.abc import Callable
from pathlib import Path
from typing import Any

from mapless.config import load_config
from mapless.scenes.categories import CATEGORY_SETS
from mapless.sim.config import SimConfig

#: Help of a SCENES argument (read by :func:`mapless.scenes.catalogue.resolve_scenes`).
SCENES_HELP = "split name, split:room, or FloorPlan names (comma-separated)"


def add_command(
    subparsers: argparse._SubParsersAction,
    name: str,
    handler: Callable[[argparse.Namespace], Any],
    *,
    sim: bool = False,
    **parser_options: Any,
) -> argparse.ArgumentParser:
    """A sub-command that runs ``handler(args)``; ``sim`` gives it the simulator options
    (:func:`add_sim_arguments`). ``parser_options`` go to ``add_parser`` (``help``, ``description``);
    the description defaults to the handler's docstring, so the two cannot drift apart."""
    parser_options.setdefault("description", inspect.getdoc(handler))
    parser = subparsers.add_parser(name, **parser_options)
    parser.set_defaults(func=handler)
    if sim:
        add_sim_arguments(parser)
    return parser


def add_sim_arguments(parser: argparse.ArgumentParser) -> None:
    """``--sim-config``, ``--sim KEY=VALUE`` and ``--cache-dir``, listed in their own help section."""
    group = parser.add_argument_group("simulator")
    group.add_argument("--sim-config", type=Path, help="YAML file with simulator settings (SimConfig fields)")
    group.add_argument(
        "--sim",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a simulator setting, e.g. visibility_distance=1.5",
    )
    group.add_argument(
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


def _int_at_least(text: str, minimum: int) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if value < minimum:
        raise argparse.ArgumentTypeError(f"must be >= {minimum}, got {value}")
    return value


def positive_int(text: str) -> int:
    """An argparse type: an integer >= 1 (a batch size, a worker or episode count)."""
    return _int_at_least(text, 1)


def seed_int(text: str) -> int:
    """An argparse type: an integer >= 0 (a seed: numpy's seed sequences take no negative one)."""
    return _int_at_least(text, 0)
