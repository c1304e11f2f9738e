"""Arguments shared by several sub-commands."""

from __future__ import annotations

import argparse
import inspect
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from mapless.config import load_config
from mapless.scenes.categories import CATEGORY_SETS, TARGET_SETS
from mapless.sim.config import SimConfig

#: Help of a SCENES argument (read by :func:`mapless.scenes.catalogue.resolve_scenes`).
SCENES_HELP = "split name, split:room, or FloorPlan names (comma-separated)"
#: Help of a --target-set argument.
TARGET_SET_HELP = f"target list per room type: {', '.join(TARGET_SETS)}"


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


def add_sim_arguments(parser: argparse.ArgumentParser, cache: bool = True) -> None:
    """``--sim-config``, ``--sim KEY=VALUE`` and (``cache``) ``--cache-dir``, in their own help section.
    ``--sim visibility_distance=M`` is the one spelling of the success rule on every command that
    takes one (``mapless train`` reads it as ``--set env.sim.KEY=VALUE``)."""
    group = parser.add_argument_group("simulator")
    group.add_argument(
        "--sim-config",
        type=Path,
        help="YAML file with simulator settings (SimConfig fields; default: the built-in settings)",
    )
    add_sim_override_argument(group)
    if cache:
        add_cache_argument(group)


def add_sim_override_argument(parser: argparse.ArgumentParser | argparse._ArgumentGroup) -> None:
    parser.add_argument(
        "--sim",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a simulator setting (SimConfig field), e.g. --sim visibility_distance=1.5 for "
        "the reference protocol's success rule",
    )


def add_cache_argument(parser: argparse.ArgumentParser | argparse._ArgumentGroup) -> None:
    parser.add_argument(
        "--cache-dir",
        type=Path,
        help="cache root, the same as $MAPLESS_CACHE: scenes go in CACHE_DIR/scenes/ "
        "(default: $MAPLESS_CACHE, else ~/.cache/mapless)",
    )


class DeprecatedAlias(argparse.Action):
    """An old spelling of an option, hidden from the help: it does what its replacement does, after a
    one-line note on stderr. ``sim_key`` set: the value goes to ``--sim`` as ``sim_key=VALUE``
    (``to_yaml`` rewrites it first), else it is stored where the replacement stores it."""

    def __init__(
        self,
        option_strings: list[str],
        dest: str,
        *,
        replacement: str,
        sim_key: str | None = None,
        to_yaml: Callable[[str], str] = str,
        **kwargs: Any,
    ) -> None:
        super().__init__(option_strings, "sim" if sim_key else dest, help=argparse.SUPPRESS, **kwargs)
        self.replacement, self.sim_key, self.to_yaml = replacement, sim_key, to_yaml

    def __call__(self, parser, namespace, values, option_string=None) -> None:
        if self.sim_key is None:
            setattr(namespace, self.dest, values)
            new = f"{self.replacement} {values}"
        else:
            new = f"--sim {self.sim_key}={self.to_yaml(values)}"
            namespace.sim = [*(namespace.sim or []), new.removeprefix("--sim ")]
        print(f"mapless: note: {option_string} is deprecated; write {new}", file=sys.stderr)


def add_category_set_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--category-set",
        default="mjolnir101",
        choices=CATEGORY_SETS,
        help="object categories of the context rows and feature maps",
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
