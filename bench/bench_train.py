"""Training throughput, batched vs async, side by side: frames/s, ratio, memory.

Each (model, mode) runs in a fresh process for ``--seconds`` of training on the cached training
scenes (fresh models, real sampling, real updates: exactly ``mapless train`` with a time budget).
Frames/s is steady-state: it starts after the first batched update / the first async episode, so
worker start-up and scene loading are not counted (they are printed separately as start-up).
Memory is the peak resident set of the trainer process, plus the largest async worker.

    python bench/bench_train.py [--models cvmeta,savn,mjolnir_o,a3c,sp] [--seconds 60] [--batch 32]
                                [--modes batched,batched-bf16,async] [--workers 2] [--rounds 1]
                                [--scenes train:kitchen] [--json out.json]

Modes: ``batched`` and ``async`` (float32), ``batched-bf16`` (``a3c.precision: bf16``: bfloat16 encoders
and LSTM products). A batched mode with ``@N`` (e.g. ``batched-bf16@2``) runs N data-parallel ranks
under ``torchrun`` (docs/guide/training.md), each with ``threads / N`` threads and its own B episodes: on
this 2-core machine two 1-thread ranks use the cores better than one 2-thread process. The ratio is
the fastest batched mode over async.

This machine's speed drifts by 10-20 % within minutes, so a ratio of two rates measured one after
the other moves with it: ``--rounds R`` measures every (model, mode) R times for ``--seconds / R``
each, interleaved (round 1 of every mode, then round 2, ...), and reports the mean rate.

The originals train at about 42-49 frames/s (A3C), 34-46 (SAVN), 21-31 (Scene Priors), 33-61
(MJOLNIR-o) on this kind of machine with 2 workers; targets are ten times the best of those.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REFERENCE = {"a3c": 49, "savn": 46, "sp": 31, "mjolnir_o": 61}
TARGET = {"a3c": 490, "savn": 460, "sp": 310, "mjolnir_o": 610}


def _measure(
    model: str, mode: str, seconds: float, batch: int, workers: int, scenes: str, threads: int
) -> dict:
    """Runs inside a fresh interpreter (see main)."""
    from mapless.config import apply_overrides, from_dict
    from mapless.train.config import TrainConfig
    from mapless.train.run import train

    label = mode
    mode, _, precision = mode.partition("@")[0].partition("-")
    data = apply_overrides(
        {},
        [
            f"model.name={model}",
            f"a3c.mode={mode}",
            f"a3c.precision={precision or 'fp32'}",
            f"env.scenes={scenes}",
            f"a3c.batch_size={batch}",
            f"a3c.workers={workers}",
            "episodes=1000000000",
            f"max_seconds={seconds}",
            "checkpoint_every=1000000000",
            "log_every=1000000000",
            f"threads={threads}",
            "progress=false",
        ],
    )
    config = from_dict(TrainConfig, data)
    began = time.perf_counter()
    with tempfile.TemporaryDirectory() as run_dir:
        summary = train(config, Path(run_dir))  # under torchrun: every rank, counters of all ranks
    wall = time.perf_counter() - began
    usage = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    children = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
    return {
        "model": model,
        "mode": label,
        "frames_per_s": summary["steady_frames_per_s"],
        "frames": summary["frames"],
        "episodes": summary["episodes"],
        "mean_length": summary["frames"] / max(summary["episodes"], 1),
        "startup_s": max(wall - seconds, 0.0),  # scene loading, worker spawn, final checkpoint
        "rss_mb": usage,
        "worker_rss_mb": children if mode == "async" else 0.0,
    }


def _run(model: str, mode: str, seconds: float, args: argparse.Namespace) -> dict:
    """One (model, mode) measurement in a fresh interpreter (under torchrun for ``@N`` modes)."""
    ranks = int(mode.partition("@")[2] or 1)
    launcher = [sys.executable]
    if ranks > 1:
        launcher = [sys.executable, "-m", "torch.distributed.run", "--standalone",
                    "--nproc-per-node", str(ranks)]  # fmt: skip
    command = [*launcher, __file__, "--one", model, mode, "--seconds", str(seconds),
               "--batch", str(args.batch), "--workers", str(args.workers), "--scenes", args.scenes,
               "--threads", str(max(args.threads // ranks, 1))]  # fmt: skip
    out = subprocess.run(command, capture_output=True, text=True, env=os.environ.copy())
    line = next((x for x in out.stdout.splitlines() if x.startswith("RESULT ")), None)
    if line is None:
        print(out.stdout, out.stderr, file=sys.stderr)
        raise SystemExit(f"{model} {mode} failed")
    return json.loads(line[7:])


def _print_summary(results: list[dict], models: list[str], modes: list[str]) -> None:
    """One line per model: mean rate per mode, fastest batched over async, goal, reference."""
    print(
        f"\n{'model':10s} "
        + " ".join(f"{m:>13s}" for m in modes)
        + f" {'ratio':>7s} {'goal':>12s} {'reference':>9s}"
    )
    rates: dict[tuple[str, str], list[float]] = {}
    for r in results:
        rates.setdefault((r["model"], r["mode"]), []).append(r["frames_per_s"])
    by = {key: sum(values) / len(values) for key, values in rates.items()}

    def best_batched(model: str) -> float:
        return max((by[model, m] for m in modes if m.startswith("batched") and (model, m) in by),
                   default=float("nan"))  # fmt: skip

    for model in models:
        best, asynchronous = best_batched(model), by.get((model, "async"), float("nan"))
        # cvmeta's goal is relative: at least savn's rate (only judged when savn ran too).
        goal = TARGET.get(model, best_batched("savn") if model == "cvmeta" else float("nan"))
        verdict = "" if goal != goal or best != best else (" met" if best >= goal else " not")
        print(
            f"{model:10s} " + " ".join(f"{by[model, m]:13.1f}" for m in modes)
            + f" {best / asynchronous:6.1f}x {goal:8.0f}{verdict:4s}"
            f" {REFERENCE.get(model, float('nan')):9.0f}"
        )  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--models", default="cvmeta,savn,mjolnir_o,a3c,sp")
    parser.add_argument("--modes", default="batched,batched-bf16,async")
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--batch", type=int, default=32)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--rounds", type=int, default=1, help="interleaved repetitions (see above)")
    parser.add_argument(
        "--threads",
        type=int,
        default=2,
        help="torch threads of the batched trainer (1 on a machine shared with other jobs)",
    )
    parser.add_argument("--scenes", default="train:kitchen")
    parser.add_argument("--json", type=Path, help="also write the results here")
    parser.add_argument("--one", nargs=2, metavar=("MODEL", "MODE"), help=argparse.SUPPRESS)
    args = parser.parse_args()

    if args.one:
        result = _measure(*args.one, args.seconds, args.batch, args.workers, args.scenes, args.threads)
        if os.environ.get("RANK", "0") == "0":
            print("RESULT " + json.dumps(result))
        return

    results = []
    seconds = args.seconds / args.rounds
    for round_ in range(args.rounds):
        for model in args.models.split(","):
            for mode in args.modes.split(","):
                result = _run(model, mode, seconds, args)
                results.append(result)
                ranks = int(mode.partition("@")[2] or 1)
                print(
                    (f"[{round_ + 1}/{args.rounds}] " if args.rounds > 1 else "")
                    + f"{model:10s} {mode:14s} {result['frames_per_s']:8.1f} frames/s  "
                    f"({result['episodes']:.0f} episodes, mean length {result['mean_length']:.1f}, "
                    f"start-up {result['startup_s']:.1f} s, RSS {result['rss_mb']:.0f} MB"
                    + (f", worker {result['worker_rss_mb']:.0f} MB" if mode.startswith("async") else "")
                    + (f" per rank x {ranks}" if ranks > 1 else "")
                    + ")",
                    flush=True,
                )

    _print_summary(results, args.models.split(","), args.modes.split(","))
    if args.json:
        from mapless.provenance import command_line, stamped

        args.json.write_text(json.dumps(stamped({"results": results}, command_line()), indent=2))


if __name__ == "__main__":
    main()
