"""Reference pages rendered from the code, so they say what the code accepts and cannot drift from
it: the command line from the argparse parsers (``python -m mapless.cli.docs cli >
docs/reference/cli.md``) and the training config's keys from its dataclasses (``... config >
docs/reference/config.md``); tests/test_docs.py checks that each page equals a fresh rendering."""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys

from mapless.cli import build_parser

HEADER = """# Command-line reference

Generated from the parsers by `python -m mapless.cli.docs cli > docs/reference/cli.md`; do not edit
by hand. Each section is the `--help` of one command."""


def _subcommands(parser: argparse.ArgumentParser) -> list[tuple[str, argparse.ArgumentParser]]:
    """``(name, parser)`` of each sub-command of ``parser``, in the order they were added."""
    found = []
    for action in parser._actions:  # argparse keeps sub-parsers only here
        if isinstance(action, argparse._SubParsersAction):
            found += list(action.choices.items())
    return found


def _walk(parser: argparse.ArgumentParser, path: str) -> list[tuple[str, argparse.ArgumentParser]]:
    """Every command below ``parser`` (itself first), depth first, as ``(full name, parser)``."""
    commands = [(path, parser)]
    for name, child in _subcommands(parser):
        commands += _walk(child, f"{path} {name}")
    return commands


def render_cli(parser: argparse.ArgumentParser | None = None) -> str:
    """The markdown page: one section per command with its help text, at a fixed width so that the
    page does not depend on the terminal it was made in."""
    previous = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = "100"  # argparse wraps to the terminal width
    try:
        parser = parser or build_parser()
        sections = [HEADER]
        for name, command in _walk(parser, parser.prog):
            sections.append(f"## `{name}`\n\n```text\n{command.format_help().rstrip()}\n```")
    finally:
        if previous is None:
            del os.environ["COLUMNS"]
        else:
            os.environ["COLUMNS"] = previous
    return "\n\n".join(sections) + "\n"


CONFIG_HEADER = """# Training config reference

Every key of a training config (`mapless train`, and the `train:` block of an experiment file), with
its default. Generated from `mapless.train.config.TrainConfig` by `python -m mapless.cli.docs config >
docs/reference/config.md`; do not edit by hand. How configs layer: [configuration](../guide/configuration.md)."""


def _default(field: dataclasses.Field) -> object:
    if field.default is not dataclasses.MISSING:
        return field.default
    if field.default_factory is not dataclasses.MISSING:
        return field.default_factory()
    return dataclasses.MISSING


def _config_rows(cls: type, prefix: str = "") -> list[str]:
    """One table row per leaf key of the dataclass ``cls``, nested blocks flattened with dots; read
    from the fields' defaults, since a whole config validates itself (a budget is required)."""
    rows = []
    for field in dataclasses.fields(cls):
        value = _default(field)
        if dataclasses.is_dataclass(value):
            rows += _config_rows(type(value), f"{prefix}{field.name}.")
            continue
        kind = field.type if isinstance(field.type, str) else getattr(field.type, "__name__", str(field.type))
        shown = "required" if value is dataclasses.MISSING else f"`{value!r}`"
        rows.append(f"| `{prefix}{field.name}` | `{kind}` | {shown} |".replace("\n", " "))
    return rows


def render_config() -> str:
    """The markdown page of every training config key, its type and its default."""
    from mapless.train.config import TrainConfig

    table = ["| key | type | default |", "|---|---|---|", *_config_rows(TrainConfig)]
    return CONFIG_HEADER + "\n\n" + "\n".join(table) + "\n"


PAGES = {"cli": render_cli, "config": render_config}

if __name__ == "__main__":
    if len(sys.argv) != 2 or sys.argv[1] not in PAGES:
        sys.exit(f"usage: python -m mapless.cli.docs {{{','.join(PAGES)}}}")
    sys.stdout.write(PAGES[sys.argv[1]]())
