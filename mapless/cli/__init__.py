"""mapless: object-goal visual navigation in AI2-THOR floor plans, without the simulator.

Each sub-command group lives in its own module that exposes ``register(subparsers)``;
:data:`COMMAND_MODULES` lists them in help order. Building the parser imports no torch (a command's
handler imports what it runs), so ``mapless --help`` answers at once."""

from __future__ import annotations

import argparse
import importlib
import os
import sys

from mapless import __version__
from mapless.errors import MaplessError

COMMAND_MODULES = (
    "mapless.cli.scenes",
    "mapless.cli.episodes",
    "mapless.cli.models",
    "mapless.cli.interop",
    "mapless.cli.evaluate",
    "mapless.cli.train",
    "mapless.cli.runs",
    "mapless.cli.zoo",
)
#: The exit status of a process killed by SIGPIPE (128 + 13), what `yes | head` leaves to the shell.
BROKEN_PIPE_STATUS = 141


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Shows each option's default, except where the help text states it, and where there is nothing
    to show: a flag (off unless given), a repeatable option (none unless given), an option with no
    value unless given (its help says what happens then)."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        default = action.default
        # Identity, not equality: a default of 0 is shown, though 0 == False.
        nothing = default is None or default is False or default is argparse.SUPPRESS or default == []
        if nothing or "%(default)" in text or "(default" in text:
            return text
        return super()._get_help_string(action)


class Parser(argparse.ArgumentParser):
    """An argument parser whose help shows defaults; sub-command parsers inherit the class."""

    def __init__(self, *args, **kwargs) -> None:
        kwargs.setdefault("formatter_class", HelpFormatter)
        super().__init__(*args, **kwargs)


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(prog="mapless", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    subparsers = parser.add_subparsers(dest="command", required=True)
    for module_name in COMMAND_MODULES:
        importlib.import_module(module_name).register(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    try:
        args = build_parser().parse_args(argv)
        try:
            status = int(args.func(args) or 0)
        except MaplessError as error:
            print(f"mapless: error: {error}", file=sys.stderr)
            return 2
        except KeyboardInterrupt:
            print("mapless: interrupted", file=sys.stderr)
            return 130
        sys.stdout.flush()  # a closed pipe shows here, not in the interpreter's exit
        return status
    except BrokenPipeError:
        # The reader left (`mapless scenes list | head`): stop quietly, as a command killed by SIGPIPE
        # does. stdout points at /dev/null so that the interpreter's last flush fails no more.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return BROKEN_PIPE_STATUS


if __name__ == "__main__":
    sys.exit(main())
