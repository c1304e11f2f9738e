"""``mapless zoo``: the shipped agents and results (:mod:`mapless.evaluate.zoo`): list them, and add
one from a finished run (a maintainer's step). ``zoo:<experiment>/<model>`` names an entry wherever
``mapless eval`` takes a model and ``mapless compare`` takes results."""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import tempfile
from pathlib import Path

from mapless.cli.common import add_cache_argument, add_command, positive_int, seed_int
from mapless.episodes.protocols import PROTOCOLS, SPLIT_ROLES, get_protocol, split_for
from mapless.errors import MaplessError


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = add_command(
        subparsers,
        "zoo",
        list_entries,
        help="shipped agents and their per-episode results: list them (zoo:<experiment>/<model>), add one",
        description="Without a sub-command: the entries, each with its SR and SPL (95 % intervals), "
        "the commit that trained it and the one that added it. The zoo is the package's data/zoo "
        "folder, or $MAPLESS_ZOO.",
    )
    sub = parser.add_subparsers(
        dest="zoo_command", metavar="{list,add,add-results}", help="list (the default), add or add-results"
    )
    add_command(sub, "list", list_entries, help="the entries (the default)")
    add = add_command(
        sub,
        "add",
        add_entry,
        help="add a finished run's chosen agent at half precision, with its per-episode results",
    )
    add.add_argument("run", type=Path, metavar="RUN_DIR", help="the finished run folder")
    add.add_argument(
        "--experiment", required=True, help="the entry's experiment, e.g. table1-small (zoo:EXPERIMENT/MODEL)"
    )
    add.add_argument("--model", help="the entry's model name (default: the run's model.name)")
    add.add_argument(
        "--results",
        help="the run's evaluation to ship: RUN/eval/*.json, a `mapless eval` record, or REPORT.json:MODEL of "
        "an experiment report; its chosen snapshot is shipped (default: evaluate the run's final model)",
    )
    add.add_argument(
        "--budget",
        help="the budget the run trained at (default: the experiment name's last part, if a budget)",
    )
    add.add_argument(
        "--split",
        choices=SPLIT_ROLES,
        default="test",
        help="the protocol's episode set the results are on (as `mapless eval --split`)",
    )
    add.add_argument("--protocol", choices=tuple(PROTOCOLS), default="standard", help="evaluation protocol")
    add.add_argument(
        "--episodes",
        type=Path,
        help="episode file instead of the built-in set of --split (default: the built-in set)",
    )
    add.add_argument(
        "--per-room", type=positive_int, help="only the first N episodes of each room type (default: all)"
    )
    add.add_argument("--workers", type=positive_int, default=2, help="evaluation processes")
    add.add_argument(
        "--batch-size", type=positive_int, default=32, help="episodes stepped together per process"
    )
    add.add_argument(
        "--seed", type=seed_int, default=0, help="action-sampling seed, unless --results records one"
    )
    add_cache_argument(add)
    rows = add_command(
        sub,
        "add-results",
        add_results,
        help="add an experiment report's rows as results-only entries: every seed's per-episode results",
        description="Each model of the report (or of --models) becomes zoo:EXPERIMENT/MODEL with the "
        "per-episode results of all its seeds on the report's episodes, rebuilt from the report's "
        "config and checked against the results, and no weights: `mapless compare` pairs a new run "
        "or result file with it without training the row again.",
    )
    rows.add_argument("report", type=Path, metavar="REPORT_JSON", help="an experiment report (table1.json)")
    rows.add_argument(
        "--experiment", required=True, help="the entries' experiment, e.g. table1-medium-reference"
    )
    rows.add_argument(
        "--models", help="comma-separated models of the report to add (default: every model it holds)"
    )
    add_cache_argument(rows)


def list_entries(args: argparse.Namespace) -> int:
    """The entries of the zoo."""
    from mapless.evaluate.zoo import listing

    print(listing())
    return 0


@dataclasses.dataclass
class Recorded:
    """What a result file says of a run: the model file it evaluated, its results on the report
    episodes, and the evaluation settings it ran with where it keeps them."""

    model_file: Path | None
    results: list
    settings: dict
    source: str


def add_entry(args: argparse.Namespace) -> int:
    """Copy the run's chosen snapshot at half precision into the zoo with its per-episode results,
    after checking that the half-precision weights score inside the float32 SR's 95 % interval on the
    same episodes."""
    from mapless.checkpoint import (
        CONFIG_FILE,
        FORMAT_VERSION,
        atomic_save,
        load_file,
        resolve_model_file,
    )
    from mapless.evaluate.episode_sets import load_episodes
    from mapless.evaluate.runner import AgentSpec, EvalSettings, LibrarySpec, evaluate
    from mapless.evaluate.zoo import (
        half_precision,
        half_precision_check,
        key_mismatch,
        result_keys,
        set_keys,
        writable_entry,
        write_entry,
    )
    from mapless.experiments.config import BUDGETS
    from mapless.provenance import provenance, run_provenance
    from mapless.train.config import stored_train_config

    run_dir: Path = args.run
    if not run_dir.is_dir():
        raise MaplessError(f"{run_dir} is not a run folder")
    recorded = _recorded(args.results, run_dir) if args.results else None
    model_file = recorded.model_file if recorded and recorded.model_file else resolve_model_file(run_dir)
    payload = load_file(model_file)
    cfg = stored_train_config(payload["config"])
    name = (args.model or cfg.model.name).replace(":", ".")
    writable_entry(args.experiment, name, with_weights=True)  # before two evaluations are spent on it
    protocol = get_protocol(args.protocol)
    library = LibrarySpec.for_env(cfg.env).under(protocol, args.cache_dir)
    split = split_for(protocol.name, args.split)
    episodes = load_episodes(
        split, args.episodes, per_room=args.per_room, library=library, target_set=cfg.env.target_set
    )
    known = ("batch_size", "seed", "greedy", "bf16", "max_steps", "category_set")
    stored = {k: v for k, v in (recorded.settings if recorded else {}).items() if k in known}
    settings = EvalSettings(
        **{
            "batch_size": args.batch_size,
            "seed": args.seed,
            "category_set": cfg.model.category_set,
            **stored,
        },
        workers=args.workers,
    )
    if recorded is not None:
        full = recorded.results
        mismatch = key_mismatch(result_keys(full), set_keys(episodes))
        if mismatch is not None:
            raise MaplessError(
                f"{recorded.source} was not evaluated on the episodes of --split {args.split} --protocol "
                f"{args.protocol} (--per-room, --episodes as it was): {mismatch}; nothing was added"
            )
    else:
        print(f"evaluating {model_file} (float32) on {len(episodes)} episodes", file=sys.stderr)
        full = evaluate(AgentSpec(checkpoint=str(model_file)), episodes, settings, library).results
    counters = {k: v for k, v in payload.get("counters", {}).items() if k != "world_size"}
    half = {"format": FORMAT_VERSION, "kind": "model", "config": payload["config"],
            "model": half_precision(payload["model"]), "counters": counters}  # fmt: skip
    with tempfile.TemporaryDirectory() as folder:
        half_file = Path(folder) / "model.pt"
        atomic_save(half, half_file)
        print(f"evaluating the half-precision weights on the same {len(episodes)} episodes", file=sys.stderr)
        half_results = evaluate(AgentSpec(checkpoint=str(half_file)), episodes, settings, library).results
    check = half_precision_check(full, half_results)
    training = run_provenance(run_dir / CONFIG_FILE)
    budget = args.budget or next((b for b in BUDGETS if args.experiment.endswith(f"-{b}")), None)
    manifest = {
        "budget": budget,
        "protocol": protocol.name,
        "episodes": {
            "split": split,
            "file": args.episodes.name if args.episodes else None,
            "per_room": args.per_room,
            "target_set": cfg.env.target_set,
        },
        "seed": cfg.seed,
        "training_commit": training[0]["commit"] if training else None,
        "training_commits": [r.get("commit") for r in training],
        "added_commit": provenance()["commit"],
        "snapshot": {
            "file": model_file.name,
            "chosen_by": recorded.source if recorded else "the final model",
            "episodes": counters.get("episodes"),
            "frames": counters.get("frames"),
        },
        "frames": counters.get("frames"),
        "eval_settings": {"seed": settings.seed, "greedy": settings.greedy, "bf16": settings.bf16},
        "half_precision": check,
    }
    entry = write_entry(args.experiment, name, half, [full], episodes, manifest)
    print(
        f"added {entry.name}: SR {100 * check['float32_sr']:.1f} % (float32), "
        f"{100 * check['float16_sr']:.1f} % (float16), in {entry.folder}"
    )
    return 0


def add_results(args: argparse.Namespace) -> int:
    """An experiment report's rows as results-only zoo entries (:func:`report_rows`)."""
    from mapless.evaluate.report import read_json
    from mapless.evaluate.zoo import writable_entry, write_entry

    try:
        report = read_json(args.report)
    except (OSError, ValueError) as error:
        raise MaplessError(f"cannot read the report {args.report}: {error}") from None
    if not isinstance(report, dict) or not isinstance(report.get("models"), list) or "config" not in report:
        raise MaplessError(
            f"{args.report} is not an experiment report (a JSON object with 'config' and 'models')"
        )
    if args.cache_dir is not None:  # where the report's episodes are rebuilt from, as reproduce reads it
        os.environ["MAPLESS_CACHE"] = str(args.cache_dir)
    wanted = args.models.split(",") if args.models else None
    for model in wanted or [str(r.get("model")) for r in report["models"]]:
        writable_entry(args.experiment, model.replace(":", "."), with_weights=False)
    for model, (results, episodes, manifest) in report_rows(report, args.report, wanted).items():
        entry = write_entry(args.experiment, model.replace(":", "."), None, results, episodes, manifest)
        sr = entry.manifest["success"]["mean"]
        print(f"added {entry.name}: results only, {len(results)} seed(s), SR {100 * sr:.1f} %")
    return 0


def report_rows(report: dict, path: Path, models: list[str] | None) -> dict:
    """``{model: (per-seed results, episodes, manifest)}`` of an experiment report's rows. The
    episodes are rebuilt from the report's config as the experiment chose them, and each seed's
    results must be on them, episode by episode."""
    from mapless.config import from_dict
    from mapless.episodes.protocols import get_protocol
    from mapless.evaluate.report import read_results
    from mapless.experiments.config import ExperimentConfig
    from mapless.experiments.evaluator import Evaluator, experiment_scenes
    from mapless.provenance import provenance, run_provenance

    source = path.name
    config = from_dict(ExperimentConfig, report["config"])
    episodes = Evaluator(config, log=lambda line: None).report_episodes
    records = {r.get("model"): r for r in report["models"]}
    unknown = sorted(set(models or []) - set(records))
    if unknown:
        raise MaplessError(
            f"{source} has no model {', '.join(unknown)} (it has {', '.join(map(str, records))})"
        )
    rows = {}
    for model in models or list(records):
        record = records[model]
        _, results = read_results(f"{path}:{model}")  # its checks of the records, one reader
        runs = [r for r in record.get("runs", []) if r.get("run_dir")]
        trained = [run_provenance(Path(r["run_dir"]) / "config.yaml") for r in runs]
        manifest = {
            "budget": config.budget,
            "protocol": config.eval.protocol,
            "episodes": {
                "split": get_protocol(config.eval.protocol).report_split,
                "file": config.eval.report_file,
                "per_room": config.eval.per_room,
                "target_set": experiment_scenes(config)[1],
            },
            "seeds": len(results),
            "source": f"{source}:{model}",
            "report_commit": report.get("provenance", {}).get("commit"),
            "training_commit": next((t[0]["commit"] for t in trained if t), None),
            "training_commits": sorted({row.get("commit") for t in trained for row in t} - {None}),
            "added_commit": provenance()["commit"],
            "runs": [_chosen(r) for r in runs],
            "eval_settings": {"seed": config.eval.seed, "greedy": config.eval.greedy, "bf16": False},
        }
        rows[model] = (results, episodes, manifest)
    return rows


def _chosen(run: dict) -> dict:
    """A report's run record, shortened to its folder's name and the snapshot its selection chose."""
    selection = run.get("selection", {})
    chosen = selection.get("chosen")
    frames = next((c.get("frames") for c in selection.get("candidates", []) if c.get("path") == chosen), None)
    return {
        "run": Path(run["run_dir"]).name,
        "snapshot": Path(chosen).name if chosen else None,
        "frames": frames,
    }


def _recorded(spec: str, run_dir: Path) -> Recorded:
    """The model file, results and settings a result file (an evaluation cache, a `mapless eval`
    record, or an experiment report's model) records for ``run_dir``."""
    from mapless.evaluate.report import result_record, results_of

    path, data = result_record(spec)
    _, per_seed = results_of(path, data)
    settings, seed = {}, 0
    if "key" in data:  # an evaluation cache: one model file on one episode set
        choice = data["key"].get("spec", {}).get("checkpoint")
        settings = data["key"].get("settings", {})
    elif "runs" in data:  # an experiment report's model: one run per seed
        names = [Path(run.get("run_dir", "")).name for run in data["runs"]]
        if run_dir.resolve().name not in names:
            raise MaplessError(f"{spec} holds no results of {run_dir} (its runs: {', '.join(names)})")
        seed = names.index(run_dir.resolve().name)
        run = data["runs"][seed]
        choice = run.get("selection", {}).get("chosen") or run.get("model_file")
    else:  # a `mapless eval` record
        if len(per_seed) != 1:
            raise MaplessError(f"{spec} holds {len(per_seed)} seeds; name one run's results")
        choice = data.get("selection", {}).get("chosen") or data.get("model_file")
    return Recorded(
        _in_run(choice, run_dir, spec) if choice else None, per_seed[seed], settings, Path(spec).name
    )


def _in_run(choice: str, run_dir: Path, spec: str) -> Path:
    """The model file ``choice`` (a path recorded at evaluation time) in ``run_dir``, found by its
    name when the run folder has moved since."""
    from mapless.checkpoint import SNAPSHOT_DIR

    recorded = Path(choice)
    if recorded.is_file() and recorded.resolve().is_relative_to(run_dir.resolve()):
        return recorded
    for candidate in (run_dir / SNAPSHOT_DIR / recorded.name, run_dir / recorded.name):
        if candidate.is_file():
            return candidate
    raise MaplessError(f"{spec} chose {choice}, which {run_dir} does not hold; give the run it evaluated")


def zoo_or_run_results(spec: str, other: str) -> tuple[str, list]:
    """``mapless compare``'s side ``spec``: a zoo entry's shipped results; a run folder evaluated on
    the episodes of the zoo entry ``other`` (cached in RUN/eval/), or a result file."""
    from mapless.evaluate import zoo
    from mapless.evaluate.report import read_results

    if zoo.is_zoo(spec):
        found = zoo.entry(spec)
        return found.name, found.results()
    if Path(spec).is_dir():
        if not zoo.is_zoo(other):
            raise MaplessError(f"{spec} is a run folder: compare it with a zoo:<experiment>/<model> entry, or "
                               "give its evaluation's result file")  # fmt: skip
        return _run_on_entry(Path(spec), zoo.entry(other))
    return read_results(spec)


def _run_on_entry(run_dir: Path, entry) -> tuple[str, list]:
    """A run's final model (or latest snapshot) on a zoo entry's episodes, under its protocol and
    action-sampling settings; cached in RUN/eval/ as other evaluations are."""
    from mapless.checkpoint import load_file, resolve_model_file
    from mapless.evaluate.episode_sets import episodes_digest
    from mapless.evaluate.runner import AgentSpec, EvalSettings, LibrarySpec
    from mapless.evaluate.selection import cache_file, cached_evaluate
    from mapless.train.config import stored_train_config

    model_file = resolve_model_file(run_dir)
    cfg = stored_train_config(load_file(model_file)["config"])
    manifest = entry.manifest
    library = LibrarySpec.for_env(cfg.env).under(get_protocol(manifest["protocol"]))
    episodes = entry.episodes()
    given = manifest.get("eval_settings", {})
    settings = EvalSettings(
        seed=given.get("seed", 0), greedy=given.get("greedy", False), bf16=given.get("bf16", False),
        category_set=cfg.model.category_set,
    )  # fmt: skip
    name = f"zoo_{model_file.stem}"
    cache = cache_file(run_dir / "eval", name, episodes_digest(episodes))
    print(f"evaluating {model_file} on the {len(episodes)} episodes of {entry.name}", file=sys.stderr)
    run = cached_evaluate(AgentSpec(checkpoint=str(model_file)), episodes, settings, library, cache)
    return cfg.model.name, [run.results]
