"""``mapless eval`` (one model on a fixed episode set), ``mapless compare`` (two results, paired) and
``mapless reproduce`` (a paper experiment)."""

from __future__ import annotations

import argparse
import os
import shlex
import sys
from pathlib import Path

from mapless.cli.common import add_cache_argument, add_command, positive_int, seed_int
from mapless.episodes.protocols import PROTOCOLS, SPLIT_ROLES, Protocol, get_protocol, split_for
from mapless.errors import MaplessError
from mapless.experiments.config import BUDGETS, EXPERIMENTS


def register(subparsers: argparse._SubParsersAction) -> None:
    ev = add_command(
        subparsers,
        "eval",
        _eval,
        help="evaluate a trained model (run folder or model file), or 'random'/'oracle', on a fixed episode set",
        description="Writes <out>/<split>.json (metrics, bootstrap intervals, every episode) and <split>.md; "
        "with --episodes FILE, <out>/<FILE's name>.json and .md.",
    )
    ev.add_argument(
        "model",
        help="run folder, model file (.pt), a shipped agent zoo:EXPERIMENT/MODEL (`mapless zoo`), or "
        "'random' / 'oracle' (untrained baselines)",
    )
    ev.add_argument(
        "--split",
        choices=SPLIT_ROLES,
        default="test",
        help="the protocol's fixed episode set: val (x21-x25 under the standard protocol), test "
        "(x26-x30) or paper (x21-x30, the paper protocol)",
    )
    ev.add_argument(
        "--protocol",
        choices=tuple(PROTOCOLS),
        help="standard (default; --split paper: the paper protocol): success within 1.0 m, val x21-x25, "
        "test x26-x30; reference: success within 1.5 m, val odd x21-x29, test even x22-x30, as the "
        "SAVN/MJOLNIR data, on the published HOZ episodes (a run trained on other classes: on its target "
        "set's sets; a model trained under another rule is scored under this one)",
    )
    ev.add_argument(
        "--episodes",
        type=Path,
        help="episode file instead of the built-in set of --split: a mapless set (.json.gz), or a published "
        "SAVN/MJOLNIR/HOZ pickle (.pkl), mapped onto the scenes as `mapless interop episodes-import` does "
        "(default: the built-in set)",
    )
    ev.add_argument(
        "--per-room",
        type=positive_int,
        help="only the first N episodes of each room type (default: every episode)",
    )
    ev.add_argument("--select", action="store_true",
                    help="run folders: evaluate every checkpoint on the protocol's val set and report the best by SR "
                         "(ties SPL) on --split (--split paper: select and report on x21-x30, the paper's protocol)")  # fmt: skip
    ev.add_argument(
        "--offline-dir",
        type=Path,
        help="evaluate on a SAVN/MJOLNIR offline data root, docs/guide/interop.md (default: the run's "
        "scenes, the built-in ones unless it trained offline)",
    )
    ev.add_argument("--workers", type=positive_int, default=2, help="evaluation processes")
    ev.add_argument(
        "--batch-size", type=positive_int, default=32, help="episodes stepped together per process"
    )
    ev.add_argument("--seed", type=seed_int, default=0, help="action-sampling seed (>= 0)")
    ev.add_argument(
        "--greedy", action="store_true", help="argmax actions instead of sampling (the references sample)"
    )
    ev.add_argument(
        "--bf16",
        action="store_true",
        help="non-adaptive models at training's precision bf16: bfloat16 encoders and LSTM products "
        "(faster GCNs on CPUs with BF16)",
    )
    ev.add_argument(
        "--no-adapt",
        dest="adapt",
        action="store_false",
        help="adaptive models: act with the trained θ_0, never adapted at test time (give another --out)",
    )
    ev.add_argument(
        "--inner-lr",
        type=float,
        help="adaptive models: the test-time inner learning rate instead of the trained one (give another "
        "--out; default: the trained one)",
    )
    ev.add_argument(
        "--out",
        type=Path,
        help="output folder (default: RUN/eval for a run folder, eval/ beside a model file, "
        "reports/eval/<model> for random and oracle, reports/eval/zoo/<experiment>/<model> for a zoo entry)",
    )
    ev.add_argument(
        "--render",
        type=positive_int,
        metavar="N",
        help="also draw the first N episodes: OUT/render/<episode>.png (the top-down trajectory) and "
        ".gif (its steps: agent, view cone, target, sightings, Done); default: draw none",
    )
    add_cache_argument(ev)

    compare = add_command(
        subparsers,
        "compare",
        _compare,
        help="B minus A on the same episodes: SR, SPL, L>=5 and false Done, with paired 95 %% intervals",
        description="Each side is a result file: a run's evaluation (RUN/eval/*.json), a `mapless eval` "
        "record (SPLIT.json), or REPORT.json:MODEL of an experiment report; or a shipped entry "
        "zoo:EXPERIMENT/MODEL (`mapless zoo`), whose results are read, not evaluated; beside one, a run "
        "folder is evaluated on the entry's episodes. Prints a markdown table.",
    )
    compare.add_argument("a", metavar="A", help="FILE, REPORT.json:MODEL, zoo:EXPERIMENT/MODEL or RUN_DIR")
    compare.add_argument("b", metavar="B", help="FILE, REPORT.json:MODEL, zoo:EXPERIMENT/MODEL or RUN_DIR")

    rep = add_command(
        subparsers,
        "reproduce",
        _reproduce,
        help="train, select, evaluate and report one of the paper's experiments",
        description=f"Experiments: {', '.join(EXPERIMENTS)}. Trains the runs (side by side on this "
        "machine, or as Slurm jobs), then selects, evaluates and writes reports/EXPERIMENT/. A run "
        "already finished is reused and an interrupted one resumes: the same command goes on where a "
        "stopped or killed one ended.",
    )
    rep.add_argument("experiment", choices=EXPERIMENTS, help="the experiment to reproduce")
    rep.add_argument(
        "--budget",
        choices=BUDGETS,
        default="small",
        help="training budget: smoke (a check that everything runs, minutes), small (the README's "
        "tables, about an hour), medium, long or full (the paper's)",
    )
    rep.add_argument(
        "--seeds",
        type=positive_int,
        help="training seeds of every trained model, model_seeds included (default: the config's seeds and model_seeds)",
    )
    rep.add_argument(
        "--config",
        type=Path,
        help="experiment YAML (default: the shipped EXPERIMENT_BUDGET.yaml, or the budget as it is "
        "where none ships)",
    )
    rep.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a config key")
    rep.add_argument(
        "--protocol",
        choices=tuple(PROTOCOLS),
        help="evaluation protocol (default: the config's eval.protocol, standard): reference = success "
        "within 1.5 m, val odd x21-x29, test even x22-x30, as the SAVN/MJOLNIR data, on the published "
        "HOZ episodes; its runs train under the 1.5 m rule on their classes (hoz22, unless "
        "train.env.target_set says otherwise) and its report goes to reports/EXPERIMENT-reference",
    )
    rep.add_argument(
        "--reports", type=Path, default=Path("reports"), help="parent of the report folder EXPERIMENT/"
    )
    rep.add_argument(
        "--no-train",
        action="store_true",
        help="train nothing: evaluate and report the finished runs found, each model on its first seeds "
        "that are finished (Table 3 and the ablation: leave out the rows not all finished), and name "
        "the runs that would have been trained",
    )
    rep.add_argument(
        "--print-config",
        action="store_true",
        help="print the resolved experiment and each run's training config, every key with the layer "
        "it came from (budget, experiment file, recipe, --set, default), and run nothing",
    )
    add_cache_argument(rep)
    rep.add_argument(
        "--jobs",
        type=positive_int,
        help="runs trained side by side, each in a process with its share of the cores (default: one "
        "per core, or per train.threads cores; 1: in this process, one after another); a last run "
        "left alone keeps its share of N, so two commands can run side by side as lanes",
    )
    rep.add_argument(
        "--launcher",
        choices=("local", "slurm"),
        default="local",
        help="local: this machine; slurm: each run a Slurm job through submitit (pip install -c "
        'constraints.txt -e ".[cluster]"; docs/guide/training.md, "On a cluster")',
    )
    slurm = rep.add_argument_group("Slurm (--launcher slurm)")
    slurm.add_argument("--partition", help="the jobs' partition (default: the cluster's)")
    slurm.add_argument(
        "--time",
        type=positive_int,
        metavar="MINUTES",
        help="each job's time limit (default: the budget's max_seconds plus 30 minutes; a day without one)",
    )
    slurm.add_argument(
        "--cpus-per-job", type=positive_int, default=2, help="CPUs (and torch threads) per run"
    )
    slurm.add_argument(
        "--gpus-per-job", type=int, default=0, help="GPUs per run (with --set train.device=cuda)"
    )
    slurm.add_argument(
        "--no-wait",
        action="store_true",
        help="submit and return; the same command later collects the finished runs and reports",
    )


def _eval(args: argparse.Namespace) -> int:
    from mapless.evaluate.episode_sets import load_episodes
    from mapless.evaluate.metrics import aggregate
    from mapless.evaluate.report import (
        details_table,
        model_record,
        model_table,
        room_table,
        write_report_files,
    )
    from mapless.evaluate.runner import AgentSpec, EvalSettings, LibrarySpec, evaluate
    from mapless.evaluate.selection import SELECTION_AS_TRAINED, evaluate_run
    from mapless.files import unwritable

    path = Path(args.model)
    shipped = None
    if args.model.startswith("zoo:"):
        from mapless.evaluate.zoo import entry

        shipped = entry(args.model)
        path = shipped.model_file
    settings = EvalSettings(
        batch_size=args.batch_size, workers=args.workers, seed=args.seed, greedy=args.greedy, bf16=args.bf16
    )
    if args.select and args.split == "val":
        raise MaplessError(
            "--select chooses a checkpoint on val, so it reports on --split test (or paper); "
            "the val scores of every checkpoint are in the selection table it prints"
        )
    if args.select and (not args.adapt or args.inner_lr is not None):  # before any episode loads
        raise MaplessError(SELECTION_AS_TRAINED)
    protocol = _protocol(args)
    eval_split = split_for(protocol.name, args.split)
    library = LibrarySpec(offline_dir=str(args.offline_dir) if args.offline_dir else None)
    target_set = protocol.target_set  # an untrained baseline is scored on the protocol's own sets
    trained_rule = None
    if path.exists():
        from mapless.checkpoint import load_file, resolve_model_file
        from mapless.train.config import stored_train_config

        cfg = stored_train_config(load_file(resolve_model_file(path))["config"])
        library = LibrarySpec.for_env(cfg.env, offline_dir=args.offline_dir)
        trained_rule = cfg.env.sim.visibility_distance
        target_set = cfg.env.target_set
        settings = EvalSettings(**{**settings.__dict__, "category_set": cfg.model.category_set})
        label = cfg.model.name
        baseline = None
        out = args.out or (path if path.is_dir() else path.parent) / "eval"
        if shipped is not None:  # never into the package's data
            label = shipped.name
            out = args.out or Path("reports") / "eval" / "zoo" / shipped.experiment / shipped.model
    elif args.model in ("random", "oracle"):
        if not args.adapt or args.inner_lr is not None:
            raise MaplessError("--no-adapt and --inner-lr are for a trained adaptive model")
        label = args.model
        baseline = AgentSpec(kind="oracle") if args.model == "oracle" else AgentSpec(model={"name": "random"})
        out = args.out or Path("reports") / "eval" / label
    else:
        raise MaplessError(f"{args.model!r} is neither a run folder, a model file, nor 'random' / 'oracle'")
    if args.select and not path.is_dir():  # before the episodes are loaded (a .pkl: mapped)
        raise MaplessError("--select needs a run folder (it compares the run's checkpoints)")
    # The report is named after the episodes it holds: an episode file's, else the protocol's split.
    name = _set_name(args.episodes) if args.episodes else eval_split
    problem = unwritable(out, [f"{name}.json", f"{name}.md"])
    if problem is not None:  # before the evaluation, whose results would be lost
        raise MaplessError(f"--out {out}: {problem}; nothing was evaluated")
    library = library.under(protocol, args.cache_dir)
    meta: dict = {"split": name, "protocol": protocol.name}
    sets = {"per_room": args.per_room, "library": library, "target_set": target_set}
    if args.episodes is not None and args.episodes.suffix == ".pkl":
        episodes = _published_episodes(args.episodes, library, args.per_room, meta)
    else:
        episodes = load_episodes(eval_split, args.episodes, **sets)
    report_name = args.episodes.name if args.episodes else None
    untrained = _untrained_targets(episodes, target_set, path.exists(), meta)
    rule = _rule(protocol, library, trained_rule)
    if baseline is not None:
        run, selection, model_file = evaluate(baseline, episodes, settings, library), None, None
    else:  # a trained run, or one model file of it
        select_eps = None
        if args.select:
            select_eps = (
                episodes if protocol.name == "paper" else load_episodes(protocol.select_split, **sets)
            )
        done = evaluate_run(
            path, episodes, settings, library, select_eps, protocol.name, print, report_name,
            adapt=args.adapt, inner_lr=args.inner_lr,
        )  # fmt: skip
        if not args.adapt or args.inner_lr is not None:
            meta["test_time_adaptation"] = {"adapt": args.adapt, "inner_lr": args.inner_lr}
            rule += (
                f"; test-time inner rate {args.inner_lr:g}" if args.adapt else "; never adapted at test time"
            )
        run, selection, model_file = done.report, done.selection, done.model_file
    if selection is not None:
        meta["selection"] = selection.summary()
        meta["protocol_label"] = selection.label if "trained" not in rule else f"{selection.label}; {rule}"
    else:
        meta["protocol_label"] = (
            f"{protocol.name} protocol, single model on {report_name or eval_split}, no checkpoint selection; {rule}"
        )
        meta["model_file"] = model_file
    results, seconds, steps = run.results, run.seconds, run.steps
    meta["steps_per_second"] = steps / seconds if seconds else None
    record = model_record(label, [results], meta)
    text = "\n".join(
        [
            f"# {label} on {name} ({len(results)} episodes)",
            "",
            f"Protocol: {meta['protocol_label']}.",
            "",
            *([f"**Not the training targets**: {untrained}.", ""] if untrained else []),
            model_table([record]),
            "",
            details_table([record]),
            "",
            room_table(record),
            "",
        ]
    )
    _, text = write_report_files(record, text, out / name)
    print(text)
    if args.render:
        _render(results[: args.render], library, label, out / "render")
    overall = aggregate(results)
    print(f"{len(results)} episodes, {steps} steps in {seconds:.1f} s ({steps / max(seconds, 1e-9):.0f} steps/s); "
          f"SR {overall['success']:.3f}; written to {out}", file=sys.stderr)  # fmt: skip
    return 0


def _render(results: list, library, label: str, folder: Path) -> None:
    """Each result's top-down trajectory (PNG) and its steps (GIF), named after its index, scene and
    target."""
    from mapless.evaluate.figures import steps_gif, trajectory_figure

    scenes = library.build()
    for result in results:
        stem = folder / f"{result.index:04d}_{result.scene}_{result.target}"
        trajectory_figure({label: result}, scenes, stem.with_suffix(".png"), sim=library.sim)
        frames = steps_gif(result, scenes, stem.with_suffix(".gif"), sim=library.sim, label=label)
        print(f"wrote {stem}.png and .gif ({frames} frames)", file=sys.stderr)


def _set_name(episodes: Path) -> str:
    """An episode file's name without its format's suffixes (``kitchen_test_22.pkl``, ``x.json.gz``)."""
    name = episodes.name
    for suffix in (".gz", ".json", ".pkl"):
        name = name.removesuffix(suffix)
    return name or episodes.name


def _compare(args: argparse.Namespace) -> int:
    from mapless.cli.zoo import zoo_or_run_results
    from mapless.evaluate.report import comparison_table
    from mapless.evaluate.zoo import is_zoo, key_mismatch, result_keys

    (label_a, a), (label_b, b) = zoo_or_run_results(args.a, args.b), zoo_or_run_results(args.b, args.a)
    if label_a == label_b:
        label_a, label_b = args.a, args.b
    mismatch = key_mismatch(result_keys(a[0]), result_keys(b[0]))
    if mismatch is not None and (is_zoo(args.a) or is_zoo(args.b)):
        raise MaplessError(f"cannot compare {args.a} with {args.b}: not the same episodes ({mismatch})")
    print(comparison_table(label_a, a, label_b, b))
    return 0


def _protocol(args: argparse.Namespace) -> Protocol:
    """``--protocol``, or the one ``--split`` implies (paper: the paper protocol, else standard)."""
    if args.split == "paper":
        if args.protocol not in (None, "paper"):
            raise MaplessError(
                f"--split paper is the paper protocol's set; it has no {args.protocol} version"
            )
        return get_protocol("paper")
    return get_protocol(args.protocol or "standard")


def _rule(protocol: Protocol, library, trained_rule: float | None) -> str:
    """The success rule a report states (and the one the model was trained under, if another)."""
    if library.offline_dir is not None:
        return "success as the offline data's visible-object maps say"
    rule = f"success within {protocol.visibility_distance} m"
    if trained_rule not in (None, protocol.visibility_distance):
        rule += f" (trained with success within {trained_rule} m)"
    return rule


def _untrained_targets(episodes: list, target_set: str, trained: bool, meta: dict) -> str | None:
    """A trained model scored on episodes whose targets it never trained for (a published pickle, a
    set of another target set) is said so, on stderr and in the record (``untrained_targets``), not
    passed silently: its score mixes in classes it never saw as targets. Returns the line, or None."""
    from mapless.episodes.evalsets import describe_untrained, untrained_targets

    found = untrained_targets(episodes, target_set) if trained else {}
    if not found:
        return None
    line = describe_untrained(found, len(episodes), target_set)
    meta["untrained_targets"] = {
        "target_set": target_set,
        "episodes": sum(n for per_room in found.values() for n in per_room.values()),
        "of": len(episodes),
        "classes": found,
    }
    print(f"warning: {line}", file=sys.stderr)
    return line


def _published_episodes(path: Path, library, per_room: int | None, meta: dict) -> list:
    """A SAVN/MJOLNIR/HOZ pickle mapped onto the evaluation scenes; the mapping report goes to stderr
    and into the record."""
    from mapless.evaluate.episode_sets import first_per_room
    from mapless.offline.episodes import import_episode_file

    scenes = library.build()
    report = import_episode_file(path, scene_data=scenes.__getitem__)
    print(f"{path}: {report.summary()}", file=sys.stderr)
    meta["mapping"] = {
        "total": report.total,
        "mapped": report.mapped,
        "skipped": [list(s) for s in report.skipped],
    }
    if not report.episodes:
        raise MaplessError(f"{path}: no episode could be mapped onto the scenes; nothing to evaluate")
    return first_per_room(report.episodes, per_room, source=str(path))


def _reproduce(args: argparse.Namespace) -> int:
    from mapless.experiments import load_experiment, reproduce

    if args.cache_dir is not None:
        # The variable, not train.env.cache_dir: the runs' folders are named after a hash of their
        # training config, which the cache's place must not change; the run processes inherit it.
        os.environ["MAPLESS_CACHE"] = str(args.cache_dir)
    overrides = [*args.set, *([f"eval.protocol={args.protocol}"] if args.protocol else [])]
    if args.print_config:
        from mapless.experiments.sources import experiment_text

        print(experiment_text(args.experiment, args.budget, args.config, overrides, args.seeds))
        return 0
    config = load_experiment(args.experiment, args.budget, args.config, overrides, args.seeds)
    launcher = _launcher(args)
    if args.no_train:
        from mapless.experiments.finished import NoTraining, finished_only

        config, launcher = finished_only(config), NoTraining()
    # The report records the exact command (overrides included) that produced it.
    parts = ["mapless", "reproduce", args.experiment, "--budget", args.budget]
    if args.protocol:
        parts += ["--protocol", args.protocol]
    if args.seeds is not None:
        parts += ["--seeds", str(args.seeds)]
    if args.config:
        parts += ["--config", str(args.config)]
    for item in args.set:
        parts += ["--set", item]
    if args.reports != Path("reports"):
        parts += ["--reports", str(args.reports)]
    if args.no_train:
        parts += ["--no-train"]
    result = reproduce(config, args.reports, command=shlex.join(parts), launcher=launcher)
    if result is not None:
        print(result["markdown"])
    return 0


def _launcher(args: argparse.Namespace):
    """What trains the runs: ``--jobs`` local processes, or Slurm jobs (``--launcher slurm``)."""
    from mapless.experiments.launch import LocalLauncher, SlurmLauncher, import_submitit

    if args.launcher == "local":
        given = [f"--{k.replace('_', '-')}" for k in ("partition", "time", "no_wait") if getattr(args, k)]
        if given or args.gpus_per_job:
            raise MaplessError(f"{', '.join(given) or '--gpus-per-job'} applies to --launcher slurm")
        return LocalLauncher(args.jobs)
    if args.jobs is not None:
        raise MaplessError("--jobs sets the local launcher's processes; Slurm runs every job it is given")
    if args.gpus_per_job < 0:
        raise MaplessError(f"--gpus-per-job must be >= 0, got {args.gpus_per_job}")
    import_submitit()  # before any work: a missing extra is an error, not a late surprise
    return SlurmLauncher(args.partition, args.time, args.cpus_per_job, args.gpus_per_job, not args.no_wait)
