"""Training throughput in real runs: models trained from scratch side by side, frames/s over the run.

``bench_train.py`` times updates of freshly initialised models, whose episodes all last ~5 steps.
A real run changes that: cvmeta learns to search (15-20 steps per episode after a few thousand
episodes, so each distinct in-view row of its GCN serves more frames), while savn keeps calling
``Done`` within ~4 steps at these budgets. This script trains each model with ``mapless train`` on the
learning check's configuration (experiments/train_learning_check.yaml) for ``--minutes``, all models
at the same time with one torch thread each (so they share the machine's drift), and prints each
run's frames/s, episodes, mean episode length and training success, and the ratio to the first
model.

    python bench/train_side_by_side.py [--models cvmeta,savn] [--minutes 15] [--precision bf16]
                                       [--out runs/side_by_side]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

CONFIG = Path(__file__).resolve().parent.parent / "experiments" / "train_learning_check.yaml"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--models", default="cvmeta,savn")
    parser.add_argument("--minutes", type=float, default=15.0)
    parser.add_argument("--precision", default="bf16")
    parser.add_argument("--out", type=Path, default=Path("runs/side_by_side"))
    args = parser.parse_args()

    models = args.models.split(",")
    stamp = time.strftime("%Y%m%d-%H%M%S")
    jobs = {}
    for model in models:
        run_dir = args.out / f"{model}_{stamp}"
        sets = [f"model.name={model}", f"max_seconds={args.minutes * 60}", "threads=1",
                f"precision={args.precision}", "progress=false"]  # fmt: skip
        cmd = [sys.executable, "-m", "mapless", "train", str(CONFIG), "--run-dir", str(run_dir)]
        cmd += [a for s in sets for a in ("--set", s)]
        run_dir.parent.mkdir(parents=True, exist_ok=True)
        log = (args.out / f"{run_dir.name}.log").open("w")
        jobs[model] = (run_dir, subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT), log)
    print(f"training {', '.join(models)} side by side for {args.minutes:g} minutes ...", flush=True)
    rows = []
    for model, (run_dir, job, log) in jobs.items():
        if job.wait() != 0:
            raise SystemExit(f"{model} failed (exit {job.returncode}); see {log.name}")
        lines = Path(log.name).read_text().splitlines()
        summary = json.loads(next(line for line in reversed(lines) if line.startswith('{"run_dir"')))
        records = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
        last = records[-5:]
        rows.append({
            "model": model,
            "frames_per_s": summary["steady_frames_per_s"],
            "episodes": int(summary["episodes"]),
            "frames": int(summary["frames"]),
            "episode_length": summary["frames"] / max(summary["episodes"], 1),
            "final_success": sum(r["charts/success"] for r in last) / len(last),
        })  # fmt: skip
    base = rows[0]["frames_per_s"]
    print(
        f"{'model':<10} {'frames/s':>9} {'ratio':>6} {'episodes':>9} {'frames':>8} {'steps/ep':>8} {'success':>8}"
    )
    for row in rows:
        print(f"{row['model']:<10} {row['frames_per_s']:>9.1f} {row['frames_per_s'] / base:>6.2f} {row['episodes']:>9} "
              f"{row['frames']:>8} {row['episode_length']:>8.1f} {row['final_success']:>8.3f}")  # fmt: skip
    (args.out / f"side_by_side_{stamp}.json").write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
