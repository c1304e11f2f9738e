"""``mapless train CONFIG [--set key=value ...]`` and ``mapless train --resume RUN_DIR``."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from mapless.cli.common import add_cache_argument, add_command, add_sim_override_argument
from mapless.config import apply_overrides, format_sources, merge_layers, read_mapping, to_dict
from mapless.configs import train_config_file
from mapless.episodes.protocols import PROTOCOLS


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = add_command(subparsers, "train", _train, help="train a model (PPO or A3C); writes a run folder")
    parser.add_argument(
        "config",
        nargs="?",
        metavar="CONFIG",
        help="a YAML training config: a path when it contains '/' or ends in .yaml (my/run.yaml, "
        "./train_ppo.yaml), otherwise the name of a shipped one (train_ppo, train_smoke, train_cvmeta, "
        "...: `mapless train train_ppo --set model.name=a3c`; default: none, required unless --resume)",
    )
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a config value, e.g. --set model.name=savn --set episodes=1000",
    )
    parser.add_argument(
        "--resume",
        type=Path,
        metavar="RUN_DIR",
        help="continue a run from its last checkpoint (--set may extend the budget; default: a new run "
        "from CONFIG)",
    )
    parser.add_argument(
        "--run-dir", type=Path, help="run folder (default: runs/<config>__<model>__<mode>__s<seed>__<time>)"
    )
    parser.add_argument(
        "--runs-root", type=Path, default=Path("runs"), help="parent of the default run folder"
    )
    parser.add_argument("--device", help="shortcut for --set device=... (default: the config's, cpu)")
    parser.add_argument(
        "--print-config",
        action="store_true",
        help="print the resolved training config, every key with the layer it came from (recipe, "
        "CONFIG, --set, default; with --resume: the checkpoint), and train nothing",
    )
    add_sim_override_argument(parser)
    add_cache_argument(parser)
    parser.add_argument(
        "--protocol",
        choices=tuple(PROTOCOLS),
        help="train for an evaluation protocol's success rule and episodes' classes: reference = within "
        "1.5 m, as the SAVN/MJOLNIR data (--sim visibility_distance=1.5), on the published HOZ "
        "episodes' classes where CONFIG and --set name no env.target_set (hoz22); standard and "
        "paper = 1.0 m (default: the config's rule, 1.0 m unless it sets env.sim)",
    )


def _train(args: argparse.Namespace) -> int:
    """Train a model: recurrent PPO, or the references' batched or async A3C (docs/guide/training.md).
    Under torchrun every rank runs this command."""
    from mapless.config import ConfigError
    from mapless.train.config import in_current_layout
    from mapless.train.recipes import load_train_config, train_file_layers
    from mapless.train.run import config_edits, default_run_dir, resume_config, train

    overrides = config_overrides(args)
    config_file = None if args.config is None else train_config_file(args.config)
    if args.protocol:
        overrides += protocol_overrides(args.protocol, config_file, overrides)
    if args.resume is not None:
        if args.config is not None:
            raise ConfigError("give either CONFIG or --resume RUN_DIR, not both")
        if args.protocol:
            raise ConfigError("a resumed run keeps the success rule it was trained under; drop --protocol")
        config, state = resume_config(args.resume, overrides)
        if args.print_config:
            layers = [(str(args.resume / "checkpoint"), in_current_layout(state["config"]))]
            layers += [("--set", apply_overrides({}, overrides))] if overrides else []
            print(format_sources(to_dict(config), merge_layers(layers)[1]))
            return 0
        run_dir = args.resume
        edits = config_edits(run_dir, state)
        if edits:
            print(
                f"mapless: {run_dir / 'config.yaml'} differs from the run's checkpoint in "
                f"{'; '.join(edits)}. The run resumes with the checkpoint's config (and --set), which "
                "config.yaml now says again: change a setting with --resume RUN_DIR --set KEY=VALUE",
                file=sys.stderr,
            )
    else:
        if config_file is None:
            raise ConfigError("mapless train needs CONFIG (or --resume RUN_DIR)")
        config = load_train_config(config_file, overrides)
        if args.print_config:
            print(format_sources(to_dict(config), merge_layers(train_file_layers(config_file, overrides))[1]))
            return 0
        state = None
        run_dir = args.run_dir or default_run_dir(config, args.runs_root, config_file.stem)
    summary = train(config, run_dir, resume=state)
    print(json.dumps({"run_dir": str(run_dir), **{k: round(v, 3) for k, v in summary.items()}}))
    if summary.get("stopped_early"):
        print(
            f"mapless: stopped at {summary['episodes']:.0f} episodes, checkpoint written; "
            f"continue with: mapless train --resume {run_dir}",
            file=sys.stderr,
        )
        return 130  # the shell's code for a run ended by SIGINT
    return 0


def config_overrides(args: argparse.Namespace) -> list[str]:
    """``--set`` and the options that stand for config keys: ``--sim KEY=VALUE`` (``env.sim.KEY``, the
    spelling every command shares), ``--cache-dir`` (``env.cache_dir``) and ``--device``."""
    return [
        *args.set,
        *(f"env.sim.{item}" for item in args.sim),
        *([f"env.cache_dir={args.cache_dir}"] if args.cache_dir is not None else []),
        *([f"device={args.device}"] if args.device else []),
    ]


def protocol_overrides(protocol: str, config: Path | None, overrides: list[str]) -> list[str]:
    """The ``--set`` overrides that train for an evaluation protocol: its success rule, and its
    episodes' classes (``Protocol.target_set``) where neither the config file nor ``overrides`` name
    a target set."""
    data = apply_overrides(read_mapping(config) if config is not None else {}, overrides)
    return PROTOCOLS[protocol].train_overrides(data)
