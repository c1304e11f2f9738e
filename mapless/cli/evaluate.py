"""``mapless eval`` (one model on a fixed episode set) and ``mapless reproduce`` (a paper experiment)."""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path

from mapless.cli.common import positive_int
from mapless.errors import MaplessError


def register(subparsers: argparse._SubParsersAction) -> None:
    ev = subparsers.add_parser(
        "eval",
        help="evaluate a trained model (run folder or model file), or 'random'/'oracle', on a fixed episode set",
        description="Writes <out>/<split>.json (metrics, bootstrap intervals, every episode) and <split>.md.",
    )
    ev.add_argument(
        "model", help="run folder, model file (.pt), or 'random' / 'oracle' (untrained baselines)"
    )
    ev.add_argument("--split", choices=("val", "test", "paper"), default="val")
    ev.add_argument("--episodes", type=Path, help="episode file instead of the built-in set of --split")
    ev.add_argument("--per-room", type=positive_int, help="only the first N episodes of each room type")
    ev.add_argument("--select", action="store_true",
                    help="run folders: evaluate every checkpoint on val and report the best by SR (ties SPL) on --split "
                         "(--split paper: select and report on x21-x30, the paper's protocol)")  # fmt: skip
    ev.add_argument(
        "--offline-dir", type=Path, help="evaluate on a SAVN/MJOLNIR offline data root (docs/interop.md)"
    )
    ev.add_argument("--workers", type=positive_int, default=2)
    ev.add_argument("--batch-size", type=positive_int, default=32)
    ev.add_argument("--seed", type=int, default=0, help="action-sampling seed")
    ev.add_argument(
        "--greedy", action="store_true", help="argmax actions instead of sampling (the references sample)"
    )
    ev.add_argument(
        "--bf16",
        action="store_true",
        help="bfloat16 autocast for non-adaptive models (faster GCNs on CPUs with BF16)",
    )
    ev.add_argument(
        "--out",
        type=Path,
        help="output folder (default: RUN/eval for a run folder, eval/ beside a model file, "
        "reports/eval/<model> for random and oracle)",
    )
    ev.set_defaults(func=_eval)

    rep = subparsers.add_parser(
        "reproduce",
        help="train, select, evaluate and report one of the paper's experiments",
        description="Experiments: table1, table2, table3, figure3, figures45. Writes reports/EXPERIMENT/.",
    )
    rep.add_argument("experiment", choices=("table1", "table2", "table3", "figure3", "figures45"))
    rep.add_argument("--budget", choices=("smoke", "small", "full"), default="smoke")
    rep.add_argument("--seeds", type=positive_int, help="training seeds per run (overrides the config)")
    rep.add_argument(
        "--config", type=Path, help="experiment YAML (default experiments/EXPERIMENT_BUDGET.yaml)"
    )
    rep.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a config key")
    rep.add_argument("--reports", type=Path, default=Path("reports"))
    rep.set_defaults(func=_reproduce)


def _eval(args: argparse.Namespace) -> int:
    from mapless.evaluate.metrics import aggregate
    from mapless.evaluate.report import details_table, model_record, model_table, room_table, write_json
    from mapless.evaluate.runner import AgentSpec, EvalSettings, LibrarySpec, evaluate
    from mapless.evaluate.selection import load_episodes, select_and_report
    from mapless.files import write_text

    path = Path(args.model)
    settings = EvalSettings(
        batch_size=args.batch_size, workers=args.workers, seed=args.seed, greedy=args.greedy, bf16=args.bf16
    )
    if args.select and args.split == "val":
        raise MaplessError(
            "--select chooses a checkpoint on val, so it reports on --split test (or paper); "
            "the val scores of every checkpoint are in the selection table it prints"
        )
    library = LibrarySpec(offline_dir=str(args.offline_dir) if args.offline_dir else None)
    target_set = "mjolnir22"
    meta: dict = {"split": args.split}
    if path.exists():
        from mapless.checkpoint import config_of, load_file, resolve_model_file
        from mapless.train.config import TrainConfig

        model_file = resolve_model_file(path)
        cfg = config_of(load_file(model_file), TrainConfig)
        library = LibrarySpec.for_env(cfg.env, offline_dir=args.offline_dir)
        target_set = cfg.env.target_set
        settings = EvalSettings(**{**settings.__dict__, "category_set": cfg.model.category_set})
        label = cfg.model.name
        spec = AgentSpec(checkpoint=str(model_file))
        out = args.out or (path if path.is_dir() else path.parent) / "eval"
    elif args.model in ("random", "oracle"):
        label = args.model
        spec = AgentSpec(kind="oracle") if args.model == "oracle" else AgentSpec(model={"name": "random"})
        out = args.out or Path("reports") / "eval" / label
    else:
        raise MaplessError(f"{args.model!r} is neither a run folder, a model file, nor 'random' / 'oracle'")
    sets = {"per_room": args.per_room, "library": library, "target_set": target_set}
    episodes = load_episodes(args.split, args.episodes, **sets)
    report_name = args.episodes.name if args.episodes else None
    if args.select:
        if not path.is_dir():
            raise MaplessError("--select needs a run folder (it compares the run's checkpoints)")
        protocol = "paper" if args.split == "paper" else "standard"
        select_eps = episodes if protocol == "paper" else load_episodes("val", **sets)
        sel = select_and_report(
            path, select_eps, episodes, settings, library, protocol, progress=print, report_name=report_name
        )
        results, seconds, steps = sel.report.results, sel.report.seconds, sel.report.steps
        meta["selection"] = sel.summary()
        meta["protocol_label"] = sel.label
    else:
        run = evaluate(spec, episodes, settings, library)
        results, seconds, steps = run.results, run.seconds, run.steps
        meta["protocol_label"] = f"single model on {report_name or args.split}, no checkpoint selection"
        meta["model_file"] = spec.checkpoint
    meta["steps_per_second"] = steps / seconds if seconds else None
    record = model_record(label, [results], meta)
    write_json(record, out / f"{args.split}.json")
    text = "\n".join(
        [
            f"# {label} on {args.split} ({len(results)} episodes)",
            "",
            f"Protocol: {meta['protocol_label']}.",
            "",
            model_table([record]),
            "",
            details_table([record]),
            "",
            room_table(record),
            "",
        ]
    )
    write_text(out / f"{args.split}.md", text)
    print(text)
    overall = aggregate(results)
    print(f"{len(results)} episodes, {steps} steps in {seconds:.1f} s ({steps / max(seconds, 1e-9):.0f} steps/s); "
          f"SR {overall['success']:.3f}; written to {out}", file=sys.stderr)  # fmt: skip
    return 0


def _reproduce(args: argparse.Namespace) -> int:
    from mapless.experiments import load_experiment, reproduce

    config = load_experiment(args.experiment, args.budget, args.config, args.set, args.seeds)
    # The report records the exact command (overrides included) that produced it.
    parts = ["mapless", "reproduce", args.experiment, "--budget", args.budget]
    if args.seeds is not None:
        parts += ["--seeds", str(args.seeds)]
    if args.config:
        parts += ["--config", str(args.config)]
    for item in args.set:
        parts += ["--set", item]
    if args.reports != Path("reports"):
        parts += ["--reports", str(args.reports)]
    result = reproduce(config, args.reports, command=shlex.join(parts))
    print(result["markdown"])
    return 0
