"""The sub-command helper every ``mapless`` command is registered with."""

from __future__ import annotations

import argparse

from mapless.cli.common import add_command


def _handler(args: argparse.Namespace) -> int:
    """Does the thing.

    In two paragraphs."""
    return 0


def test_a_commands_description_is_its_handlers_docstring_unless_given() -> None:
    subparsers = argparse.ArgumentParser(prog="m").add_subparsers()
    plain = add_command(subparsers, "plain", _handler, help="short")
    given = add_command(subparsers, "given", _handler, help="short", description="Given.")
    assert plain.description == "Does the thing.\n\nIn two paragraphs."
    assert given.description == "Given."
    assert plain.parse_args([]).func is _handler
