"""``mapless runs migrate RUNS_DIR``: the run folders of an older run identity renamed to today's."""

from __future__ import annotations

import argparse
from pathlib import Path

from mapless.cli.common import add_command


def register(subparsers: argparse._SubParsersAction) -> None:
    runs = subparsers.add_parser("runs", help="manage the run folders of mapless reproduce")
    sub = runs.add_subparsers(dest="runs_command", required=True)
    migrate = add_command(
        sub,
        "migrate",
        _migrate,
        help="rename run folders named under an earlier run-folder hash to today's (once per change)",
        description="Renames each run folder under RUNS_DIR (e.g. runs/experiments/small, or "
        "runs/experiments for every budget) whose config.yaml gives its name under an earlier run-folder "
        "hash (each change of the config's layout renames every run: mapless.train.config.LAYOUT_CHANGES, "
        "docs/changelog.md) to its name under today's, so that mapless reproduce "
        "finds it instead of training it again. Prints OLD -> NEW per folder; a folder whose config.yaml does not parse or "
        "does not give its name, whose new name is taken, or that a trainer holds, stays (skip: why).",
    )
    migrate.add_argument("runs_dir", type=Path, metavar="RUNS_DIR", help="the folder holding run folders")
    migrate.add_argument("--dry-run", action="store_true", help="print what would be renamed; rename nothing")


def _migrate(args: argparse.Namespace) -> int:
    from mapless.experiments.migrate import migrate

    steps = migrate(args.runs_dir, dry_run=args.dry_run)
    moved = sum(step.new_name is not None for step in steps)
    verb = "would rename" if args.dry_run else "renamed"
    print(f"{verb} {moved} of {len(steps)} run folders")
    return 0
