"""Where a result came from: the code (git commit, uncommitted changes, package version), torch and
the machine's share of it (threads, cores). Every report and every run folder's config carries it,
so that a number can be tied to the code and the machine that made it."""

from __future__ import annotations

import functools
import json
import os
import subprocess
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
