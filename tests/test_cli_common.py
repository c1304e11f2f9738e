"""The sub-command helper every ``mapless`` command is registered with, and what every parser shares."""

from __future__ import annotations

import argparse
from collections.abc import Iterator

import pytest

from mapless.cli import build_parser, main
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


def _parsers(parser: argparse.ArgumentParser) -> Iterator[argparse.ArgumentParser]:
    yield parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in dict.fromkeys(action.choices.values()):  # aliases name one parser twice
                yield from _parsers(sub)


def test_every_help_text_formats(capsys) -> None:
    """argparse %-formats help texts: a bare '%' in one crashed ``mapless --help`` (issue 45, 10)."""
    parsers = list(_parsers(build_parser()))
    assert len(parsers) > 20  # the top level and every sub-command, nested ones included
    for parser in parsers:
        assert parser.format_help()
    with pytest.raises(SystemExit) as stop:
        main(["--help"])
    assert stop.value.code == 0 and "compare" in capsys.readouterr().out


def test_a_seed_below_zero_is_refused_by_the_parser(capsys) -> None:
    """numpy's seed sequences take no negative seed (issue 45, points 1 and 14)."""
    for argv in (["eval", "random", "--seed", "-1"], ["episodes", "make", "--seed", "-1"]):
        with pytest.raises(SystemExit) as stop:
            main(argv)
        assert stop.value.code == 2 and "--seed: must be >= 0, got -1" in capsys.readouterr().err
