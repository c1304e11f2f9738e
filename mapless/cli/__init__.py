"""mapless: object-goal visual navigation in AI2-THOR floor plans, without the simulator.

Each sub-command group lives in its own module that exposes ``register(subparsers)``;
:data:`COMMAND_MODULES` lists them in help order."""

from __future__ import annotations

import argparse
import importlib
import sys

from mapless.errors import MaplessError

COMMAND_MODULES = (
    "mapless.cli.scenes",
    "mapless.cli.episodes",
    "mapless.cli.models",
    "mapless.cli.interop",
    "mapless.cli.evaluate",
    "mapless.cli.train",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="mapless", description=__doc__.splitlines()[0])
    subparsers = parser.add_subparsers(dest="command", required=True)
    for module_name in COMMAND_MODULES:
        importlib.import_module(module_name).register(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except MaplessError as error:
        print(f"mapless: error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("mapless: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
