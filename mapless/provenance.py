"""Where a result came from: the code (git commit, uncommitted changes, package version), torch and
the machine's share of it (threads, cores). Every report and every run folder's config carries it,
so that a number can be tied to the code and the machine that made it."""

from __future__ import annotations

import contextlib
import functools
import json
import os
import shlex
import subprocess
import sys
import time
from pathlib import Path

import mapless

#: The package's folder; its parent is the repository root of a checkout (an editable install).
_PACKAGE_DIR = Path(mapless.__file__).resolve().parent


def cpu_cores() -> int:
    """Cores this process may run on (a container's or a Slurm job's share, not the whole machine's)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


@functools.cache
def _git(*args: str) -> str | None:
    try:
        done = subprocess.run(
            ["git", "-C", str(_PACKAGE_DIR.parent), *args], capture_output=True, text=True, timeout=10
        )
    except (OSError, subprocess.TimeoutExpired):  # no git on this machine
        return None
    return done.stdout.strip() if done.returncode == 0 else None


def git_state() -> tuple[str | None, bool | None]:
    """``(commit, dirty)`` of the checkout the package runs from; ``(None, None)`` when it does not
    run from one (an installed wheel, even one that lies inside some other repository)."""
    top = _git("rev-parse", "--show-toplevel")
    if top is None or Path(top).resolve() != _PACKAGE_DIR.parent:
        return None, None
    commit = _git("rev-parse", "HEAD")
    # Untracked files (runs, reports, caches) do not change the code that ran.
    status = _git("status", "--porcelain", "--untracked-files=no")
    return commit, None if status is None else bool(status)


def provenance(threads: int | None = None) -> dict:
    """The code and machine behind a result. ``threads``: the torch threads it ran with (default:
    this process's)."""
    import torch

    commit, dirty = git_state()
    return {
        "commit": commit,
        "dirty": dirty,
        "version": mapless.__version__,
        "torch": torch.__version__,
        "threads": threads or torch.get_num_threads(),
        "cores": cpu_cores(),
    }


def describe(record: dict) -> str:
    """One line of a :func:`provenance` record, for markdown reports and config comments."""
    if record["commit"] is None:
        code = "commit unknown (not a git checkout)"
    else:
        code = f"commit {record['commit'][:12]}" + (" with uncommitted changes" if record["dirty"] else "")
    return (
        f"mapless {record['version']}, {code}; torch {record['torch']}, "
        f"{record['threads']} thread(s) on a machine of {record['cores']} core(s)"
    )


def provenance_comment(threads: int | None = None) -> str:
    """The lines a run folder's config starts with (as YAML comments): :func:`describe`, then the
    record itself as JSON, for a program to read."""
    record = provenance(threads)
    return f"Trained by {describe(record)}.\nprovenance: {json.dumps(record)}"


def command_line(argv: list[str] | None = None) -> str:
    """The command this process runs, as a reader would type it: ``python SCRIPT ARGS`` for a
    script (its path relative to the working folder when it lies below it)."""
    script, *args = sys.argv if argv is None else argv
    path = Path(script)
    if path.is_absolute() and path.is_relative_to(Path.cwd()):
        path = path.relative_to(Path.cwd())
    return shlex.join(["python", str(path), *args])


def stamp(command: str) -> str:
    """The line every report starts its provenance with: the command and when it finished."""
    return f"Command: `{command}`; finished {time.strftime('%Y-%m-%d %H:%M')}."


def stamped(payload: dict, command: str, threads: int | None = None) -> dict:
    """``payload`` with the command, the time it finished and :func:`provenance`: what a benchmark's
    JSON report carries, as an experiment's does."""
    return {
        **payload,
        "command": command,
        "finished": time.strftime("%Y-%m-%d %H:%M"),
        "provenance": provenance(threads),
    }


def comment_of(path: str | Path) -> str:
    """The ``#`` lines a config file starts with, without their ``# `` (empty if it has none or
    cannot be read)."""
    try:
        lines = Path(path).read_text().splitlines()
    except (OSError, UnicodeDecodeError):
        return ""
    comment = []
    for line in lines:
        if not line.startswith("#"):
            break
        comment.append(line[1:].removeprefix(" "))
    return "\n".join(comment)


def resumed_comment(previous: str, threads: int | None = None) -> str:
    """The lines a resumed run's config starts with: those of its first start and of every earlier
    resume (``previous``: :func:`comment_of` its config.yaml), then this resume's, so that the
    folder names every commit that trained it. A folder whose config carries no provenance (written
    before it was recorded) starts its record here."""
    kept = [line for line in previous.splitlines() if line.startswith(_RECORD_LINES)]
    if not any(line.startswith("provenance: ") for line in kept):
        return provenance_comment(threads)
    record = provenance(threads)
    return "\n".join([*kept, f"Resumed by {describe(record)}.", f"resumed: {json.dumps(record)}"])


#: The comment lines of a run's config that make up its provenance.
_RECORD_LINES = ("Trained by ", "provenance: ", "Resumed by ", "resumed: ")


def run_provenance(path: str | Path) -> list[dict]:
    """The provenance records of a run's config file: its first start's, then each resume's."""
    records = []
    for line in comment_of(path).splitlines():
        for key in ("provenance: ", "resumed: "):
            if line.startswith(key):
                with contextlib.suppress(ValueError):  # a hand-edited line
                    records.append(json.loads(line.removeprefix(key)))
    return records
