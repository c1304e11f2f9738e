"""What every ``mapless`` command shares: ``--version``, a help that imports no torch and shows every
argument's default, one spelling of the success rule and of the cache folder, the README's defaults,
and a quiet end when the reader of its output leaves (``mapless scenes list | head``)."""

from __future__ import annotations

import argparse
import subprocess
import sys
from collections.abc import Iterator

import pytest

import mapless
from mapless.cli import BROKEN_PIPE_STATUS, HelpFormatter, build_parser, main

#: Options whose value, when not given, is "nothing" (off, none), not a setting to show.
UNSHOWN = (argparse._StoreTrueAction, argparse._StoreFalseAction, argparse._AppendAction)


def _commands(
    parser: argparse.ArgumentParser, path: tuple[str, ...] = ()
) -> Iterator[tuple[tuple[str, ...], argparse.ArgumentParser]]:
    yield path, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in {id(p): (n, p) for n, p in action.choices.items()}.values():
                yield from _commands(sub, (*path, name))


def _arguments(parser: argparse.ArgumentParser) -> Iterator[argparse.Action]:
    for action in parser._actions:
        if isinstance(action, (argparse._HelpAction, argparse._VersionAction, argparse._SubParsersAction)):
            continue
        if action.help == argparse.SUPPRESS:  # an old spelling, kept as a deprecated alias
            continue
        yield action


def test_version(capsys) -> None:
    with pytest.raises(SystemExit) as stop:
        main(["--version"])
    assert stop.value.code == 0 and capsys.readouterr().out == f"mapless {mapless.__version__}\n"


def test_building_the_parser_and_asking_for_help_imports_no_torch() -> None:
    """``mapless --help`` must not pay for torch: the handlers import what they run."""
    code = (
        "import sys, contextlib, io\n"
        "from mapless.cli import build_parser, main\n"
        "build_parser()\n"
        "assert 'torch' not in sys.modules, 'build_parser imported torch'\n"
        "for argv in (['--help'], ['eval', '--help'], ['train', '--help'], ['reproduce', '--help']):\n"
        "    with contextlib.suppress(SystemExit), contextlib.redirect_stdout(io.StringIO()):\n"
        "        main(argv)\n"
        "    assert 'torch' not in sys.modules, f'{argv} imported torch'\n"
        "print('ok')\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout == "ok\n"


def test_every_argument_has_help_and_shows_its_default() -> None:
    formatter = HelpFormatter("mapless")
    commands = list(_commands(build_parser()))
    assert len(commands) > 20
    checked = 0
    for path, parser in commands:
        for action in _arguments(parser):
            name = f"mapless {' '.join(path)} {'/'.join(action.option_strings) or action.dest}"
            assert action.help, f"{name} has no help"
            checked += 1
            if (
                action.required
                or isinstance(action, UNSHOWN)
                or (not action.option_strings and action.nargs is None)
            ):
                continue  # required, a flag, repeatable, or a positional that must be given
            if action.default is None:
                # No value unless given: the help says what happens then.
                assert "default" in action.help or "required with" in action.help, (
                    f"{name}: what if not given?"
                )
            else:
                shown = formatter._get_help_string(action)
                assert "%(default)" in shown or "(default" in shown, (
                    f"{name}: default {action.default!r} unshown"
                )
    assert checked > 120


def test_a_default_is_printed_in_the_help(capsys) -> None:
    with pytest.raises(SystemExit):
        main(["eval", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "(default: test)" in text and "(default: 2)" in text and "(default: 0)" in text


def test_eval_and_reproduce_default_to_what_the_readme_runs() -> None:
    """The README evaluates on test (``--split test --select``) and reproduces at ``--budget small``."""
    parser = build_parser()
    assert parser.parse_args(["eval", "some_run"]).split == "test"
    assert parser.parse_args(["reproduce", "table1"]).budget == "small"


def _options(parser: argparse.ArgumentParser) -> set[str]:
    return {o for action in _arguments(parser) for o in action.option_strings}


def test_one_spelling_of_the_success_rule_and_of_the_cache_folder() -> None:
    commands = dict(_commands(build_parser()))
    # Every command that sets the simulator's success rule does so with --sim, nothing else.
    rule_setters = [path for path, parser in commands.items() if "--sim" in _options(parser)]
    assert (
        ("train",) in rule_setters
        and ("thor", "scrape") in rule_setters
        and ("scenes", "build") in rule_setters
    )
    assert not [p for p, parser in commands.items() if "--visibility-distance" in _options(parser)]
    # Every command that reads the scene cache takes --cache-dir, evaluation and training included.
    for path in [*rule_setters, ("eval",), ("reproduce",)]:
        if path != ("thor", "scrape"):  # scrapes a live AI2-THOR; reads no cache
            assert "--cache-dir" in _options(commands[path]), path
    # One spelling of the evaluation split(s): --split, on eval and on episodes make.
    assert "--split" in _options(commands[("eval",)]) and "--split" in _options(
        commands[("episodes", "make")]
    )
    assert not [p for p, parser in commands.items() if "--splits" in _options(parser)]


def test_old_spellings_still_work_with_a_note(capsys) -> None:
    parser = build_parser()
    args = parser.parse_args(["episodes", "make", "--splits", "val,test"])
    assert args.splits == "val,test"
    assert capsys.readouterr().err == "mapless: note: --splits is deprecated; write --split val,test\n"
    args = parser.parse_args(["thor", "scrape", "FloorPlan1", "--out", "x", "--visibility-distance", "1.5"])
    assert args.sim == ["visibility_distance=1.5"]
    assert "write --sim visibility_distance=1.5" in capsys.readouterr().err


def test_train_reads_sim_and_cache_dir_as_its_config_keys(tmp_path) -> None:
    from mapless.cli.train import config_overrides

    args = build_parser().parse_args(
        [
            "train",
            "x.yaml",
            "--sim",
            "visibility_distance=1.5",
            "--cache-dir",
            str(tmp_path),
            "--set",
            "seed=3",
        ]
    )
    assert config_overrides(args) == [
        "seed=3",
        "env.sim.visibility_distance=1.5",
        f"env.cache_dir={tmp_path}",
    ]


def test_a_reader_that_leaves_early_ends_the_command_quietly() -> None:
    """``mapless scenes list | head``: the pipe is closed before the command writes."""
    command = [sys.executable, "-m", "mapless", "scenes", "list"]
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    process.stdout.close()  # the reader is gone before the first line
    err = process.stderr.read().decode()
    assert process.wait(timeout=120) == BROKEN_PIPE_STATUS
    assert err == ""
