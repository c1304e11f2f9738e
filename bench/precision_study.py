"""Precision study (a benchmark, not a test): does bfloat16 make cvmeta's training collapse?

Trains the learning check's configuration (experiments/train_learning_check.yaml: cvmeta, training
kitchens, B = 32, lr 5e-4) once per precision and seed, on an episode budget (so the runs do not
depend on the machine's speed), one torch thread each and ``--parallel`` at a time. A run folder that
exists already is resumed up to the budget (resume is exact) or, when finished, only read. Then it
prints, per run, the training success of the last 3,200 episodes, the lowest policy entropy, the
largest gradient norm and where the policy fell into the no-``Done`` state seen in earlier bf16 runs
(a record with success at most 1 % and episodes within 10 % of the step limit: the agent stops
calling ``Done`` and wanders, collecting parent-object rewards, with its entropy high or low), and
plots success, episode length and entropy against episodes.

``--set KEY=VALUE`` changes every run's config beyond its precision and seed, so the same study
answers other questions of the kind "does this change hurt learning?": e.g. ``--precisions fp32
--set model.gcn_hidden=64 --runs runs/gcn64_study --out reports/gcn64_study`` (give such a study its
own ``--runs`` folder: runs are found by precision and seed only).

    python bench/precision_study.py [--seeds 2,3] [--precisions fp32,bf16] [--episodes 30000]
                                    [--parallel 2] [--runs runs/precision_study] [--out reports/precision_study]
                                    [--set KEY=VALUE ...] [--no-train]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

CONFIG = Path(__file__).resolve().parent.parent / "experiments" / "train_learning_check.yaml"
NO_DONE_SUCCESS = 0.01
NO_DONE_LENGTH = 0.9  # share of the step limit
LAST_RECORDS = 5  # 5 x log_every 640 = the last 3,200 episodes


def command(run_dir: Path, precision: str, seed: int, episodes: int, extra: list[str]) -> list[str]:
    """``mapless train`` for a run (``extra``: more ``--set`` overrides): fresh, or resumed from its
    checkpoint up to ``episodes``."""
    mapless = [sys.executable, "-m", "mapless", "train"]
    if (run_dir / "checkpoint.pt").is_file():
        return [*mapless, "--resume", str(run_dir), "--set", f"episodes={episodes}"]
    sets = [f"episodes={episodes}", f"seed={seed}", f"precision={precision}", "threads=1", "progress=false"]
    sets += extra
    return [*mapless, str(CONFIG), "--run-dir", str(run_dir), *(a for s in sets for a in ("--set", s))]


def records(run_dir: Path) -> list[dict]:
    path = run_dir / "metrics.jsonl"
    return [json.loads(line) for line in path.read_text().splitlines()] if path.is_file() else []


def finished(run_dir: Path, episodes: int) -> bool:
    found = records(run_dir)
    return (run_dir / "final_model.pt").is_file() and bool(found) and found[-1]["episodes"] >= episodes


def summary(run: str, found: list[dict], max_steps: int) -> dict:
    success = np.array([r["charts/success"] for r in found])
    entropy = np.array([r["losses/entropy"] for r in found])
    length = np.array([r["charts/episode_length"] for r in found])
    norms = [r["losses/grad_norm"] for r in found if "losses/grad_norm" in r]
    collapsed = (success <= NO_DONE_SUCCESS) & (length >= NO_DONE_LENGTH * max_steps)
    return {
        "run": run,
        "episodes": found[-1]["episodes"],
        "final_success": float(success[-LAST_RECORDS:].mean()),
        "best_success": float(success.max()),
        "min_entropy": float(entropy.min()),
        "max_grad_norm": float(max(norms)) if norms else None,
        "no_done_at": int(found[int(np.argmax(collapsed))]["episodes"]) if collapsed.any() else None,
        "no_done_records": int(collapsed.sum()),
        "frames_per_s": float(np.median([r["perf/frames_per_s"] for r in found])),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="2,3")
    parser.add_argument("--precisions", default="fp32,bf16")
    parser.add_argument("--episodes", type=int, default=30000)
    parser.add_argument("--parallel", type=int, default=2)
    parser.add_argument("--runs", type=Path, default=Path("runs/precision_study"))
    parser.add_argument("--out", type=Path, default=Path("reports/precision_study"))
    parser.add_argument(
        "--set", action="append", default=[], metavar="KEY=VALUE", help="config override of every run"
    )
    parser.add_argument("--no-train", action="store_true", help="only report on the runs as they stand")
    args = parser.parse_args()

    runs = [(p, int(s)) for s in args.seeds.split(",") for p in args.precisions.split(",")]
    pending = [(p, s) for p, s in runs if not finished(args.runs / f"{p}_s{s}", args.episodes)]
    if args.no_train:
        pending = []
    args.runs.mkdir(parents=True, exist_ok=True)
    for start in range(0, len(pending), args.parallel):
        jobs = []
        for precision, seed in pending[start : start + args.parallel]:
            run_dir = args.runs / f"{precision}_s{seed}"
            log = (args.runs / f"{run_dir.name}.log").open("a")
            print(f"training {run_dir.name} to {args.episodes} episodes (log: {log.name})", flush=True)
            jobs.append(
                subprocess.Popen(
                    command(run_dir, precision, seed, args.episodes, args.set), stdout=log, stderr=log
                )
            )
        for job in jobs:
            if job.wait() != 0:
                raise SystemExit(
                    f"a training run failed (exit {job.returncode}); see the logs in {args.runs}"
                )

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import yaml

    table = []
    fig, (top, middle, bottom) = plt.subplots(3, 1, figsize=(8, 8), sharex=True)
    styles = ("-", "--", ":", "-.")
    for precision, seed in runs:
        name = f"{precision}_s{seed}"
        found = records(args.runs / name)
        max_steps = yaml.safe_load((args.runs / name / "config.yaml").read_text())["env"]["max_steps"]
        table.append(summary(name, found, max_steps))
        x = [r["episodes"] for r in found]
        style = {"color": "C0" if precision == "fp32" else "C3", "linestyle": styles[seed % len(styles)]}
        top.plot(x, [r["charts/success"] for r in found], label=name, **style)
        middle.plot(x, [r["charts/episode_length"] for r in found], **style)
        bottom.plot(x, [r["losses/entropy"] for r in found], **style)
    top.set_ylabel("training success")
    middle.set_ylabel("episode length")
    middle.axhline(max_steps, color="gray", linestyle="--", linewidth=0.8)
    bottom.set_ylabel("policy entropy per step")
    bottom.set_xlabel(
        f"training episodes (points: means of {yaml.safe_load(CONFIG.read_text())['log_every']})"
    )
    top.legend(ncol=2, fontsize=8)
    top.set_title(f"cvmeta learning check, {' vs '.join(args.precisions.split(','))} {' '.join(args.set)}")
    fig.tight_layout()
    args.out.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out / "precision_study.png", dpi=120)
    (args.out / "precision_study.json").write_text(json.dumps(table, indent=2))
    header = "run         episodes  success(last 3200)  best   min entropy  max |g|  no Done at (records)  frames/s"
    print(header)
    for row in table:
        no_done = f"{row['no_done_at']} ({row['no_done_records']})" if row["no_done_at"] is not None else "-"
        norm = f"{row['max_grad_norm']:.0f}" if row["max_grad_norm"] is not None else "-"
        print(f"{row['run']:<11} {row['episodes']:>8}  {row['final_success']:>18.3f}  {row['best_success']:.3f}"
              f"  {row['min_entropy']:>11.2f}  {norm:>7}  {no_done:>20}  {row['frames_per_s']:>8.0f}")  # fmt: skip
    print(f"curves: {args.out / 'precision_study.png'}")


if __name__ == "__main__":
    main()
