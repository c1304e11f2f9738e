"""The speed table: how fast every model trains under the laptop recipe (recurrent PPO) on one
thread, where its time goes, and how far it is from what this CPU can do.

Part 1, in this process on one thread, one model after another: for each model a PPO trainer of ``train_ppo`` (the small budget's recipe), one warm-up update, then
``--updates`` updates, each split into

* rollout: the collection of the update's segment (the policy acting, no gradient);
* update: PPO's epochs of minibatch steps (replay forward, backward, Adam);
* replay: of which the adaptive models' forward through the meta-learning inner loop;

the training frames/s they make; the matrix-product FLOPs of one whole update per frame, counted by
``torch.utils.flop_counter``; and the share of this CPU's measured matmul roofline (one thread,
float32, a large square product, measured in the same run) that the model's FLOPs per second reach.

Part 2, ``--pairs``: the goal's own measurement, models side by side as the grid runs them. Each
pair trains ``mapless train train_ppo --set model.name=M --set threads=1`` for ``--seconds`` each,
both at once, one core each, and their frames/s and ratio are read from the runs' summaries.

    python bench/speed_table.py [--models a3c,mjolnir_o,cvmeta,mlp,...] [--updates 3]
                                [--pairs a3c:mjolnir_o,a3c:cvmeta] [--seconds 150] [--out DIR]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

from mapless.configs import configs_dir
from mapless.provenance import command_line, describe, provenance, stamp, stamped

ALL_MODELS = "a3c,sp,savn,gve,spatt,mjolnir_o,mjolnir_r,cvmeta,mlp"


def build(model: str):
    """A PPO trainer of train_ppo's recipe for ``model``, with no run folder, set up as a trainer
    sets up its process (one thread, freed memory kept: mapless.train.runtime)."""
    from mapless.train.ppo import PPOTrainer
    from mapless.train.recipes import load_train_config
    from mapless.train.runtime import configure_torch

    configure_torch(1)
    config = load_train_config(
        configs_dir() / "train_ppo.yaml", [f"model.name={model}", "progress=false", "threads=1"]
    )
    trainer = PPOTrainer(config, None)
    trainer.build()
    return trainer


class Timed:
    """Wraps a bound method of ``owner`` and adds its wall time to ``seconds``."""

    def __init__(self, owner, name: str):
        self.owner, self.name, self.seconds = owner, name, 0.0
        self.inner = getattr(owner, name, None)
        if self.inner is not None:
            setattr(owner, name, self)

    def __call__(self, *args, **kwargs):
        start = time.perf_counter()
        try:
            return self.inner(*args, **kwargs)
        finally:
            self.seconds += time.perf_counter() - start


def one_update(trainer) -> dict[str, float]:
    """Seconds of rollout, update and replay, and the frames, of one update."""
    collect = Timed(trainer.collector, "collect")
    # The adaptive models' minibatches replay through the inner loop (mapless.agent.meta).
    replay = Timed(trainer.inner if trainer.inner is not None else trainer, "replay")
    start = time.perf_counter()
    result = trainer.update()
    total = time.perf_counter() - start
    for timed in (collect, replay):
        if timed.inner is not None:
            setattr(timed.owner, timed.name, timed.inner)
    frames = int(result["segment"].frames)
    trainer.counters["frames"] += frames  # the imitation weight and learning rate follow the frames
    return {
        "rollout": collect.seconds,
        "update": total - collect.seconds,
        "replay": replay.seconds if trainer.inner is not None else 0.0,
        "frames": frames,
    }


def flops_per_frame(trainer) -> float:
    """Matrix-product FLOPs of one whole update (rollout and PPO's epochs) per frame."""
    from torch.utils.flop_counter import FlopCounterMode

    with FlopCounterMode(display=False) as counter:
        result = trainer.update()
    return counter.get_total_flops() / int(result["segment"].frames)


def matmul_roofline(size: int = 2048, repeats: int = 5) -> float:
    """GFLOP/s of one thread's best float32 square product of ``size``."""
    a, b = torch.randn(size, size), torch.randn(size, size)
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        torch.mm(a, b)
        best = min(best, time.perf_counter() - start)
    return 2 * size**3 / best / 1e9


def speed_rows(models: list[str], updates: int) -> tuple[list[dict], float]:
    """One model at a time (a trainer holds its environments and its peak memory; nine at once do
    not fit 24 GB), each after a warm-up update."""
    import gc

    torch.set_num_threads(1)
    roofline = matmul_roofline()
    rows = []
    for m in models:
        trainer = build(m)
        one_update(trainer)  # warm-up: allocations, kernels, the memo's first rows
        splits = [one_update(trainer) for _ in range(updates)]
        total = {k: sum(s[k] for s in splits) for k in ("rollout", "update", "replay", "frames")}
        seconds = total["rollout"] + total["update"]
        flops = flops_per_frame(trainer)
        fps = total["frames"] / seconds
        rows.append(
            {
                "model": m,
                "frames_per_s": fps,
                "rollout_share": total["rollout"] / seconds,
                "update_share": total["update"] / seconds,
                "replay_share": total["replay"] / seconds,
                "mflop_per_frame": flops / 1e6,
                "gflop_per_s": flops * fps / 1e9,
                "roofline_share": flops * fps / 1e9 / roofline,
            }
        )
        del trainer
        gc.collect()
    return rows, roofline


def side_by_side(pair: tuple[str, str], seconds: float) -> dict[str, float]:
    """frames/s of two ``mapless train train_ppo`` runs trained at once, one thread each."""
    with tempfile.TemporaryDirectory() as folder:
        processes = {}
        for model in pair:
            command = [
                sys.executable, "-m", "mapless", "train", "train_ppo", "--set", f"model.name={model}",
                "--set", "threads=1", "--set", f"max_seconds={seconds}", "--set", "progress=false",
                "--run-dir", str(Path(folder) / model),
            ]  # fmt: skip
            processes[model] = subprocess.Popen(command, stdout=subprocess.PIPE, text=True)
        speeds = {}
        for model, process in processes.items():
            out, _ = process.communicate()
            if process.returncode != 0:
                raise SystemExit(f"{model}: mapless train exited {process.returncode}")
            summary = json.loads(out.strip().splitlines()[-1])
            speeds[model] = summary["frames_per_s"]
    return speeds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--models", default=ALL_MODELS, help="models of part 1 (default: %(default)s)")
    parser.add_argument(
        "--updates", type=int, default=3, help="timed updates per model (default: %(default)s)"
    )
    parser.add_argument("--pairs", default="a3c:mjolnir_o,a3c:cvmeta",
                        help="part 2's pairs trained side by side, A:B,... ('' skips it; default: %(default)s)")  # fmt: skip
    parser.add_argument("--seconds", type=float, default=150, help="part 2's training seconds per pair")
    parser.add_argument("--out", type=Path, default=Path("reports/speed"), help="folder for speed.md/.json")
    args = parser.parse_args()
    command = command_line()

    models = [m for m in args.models.split(",") if m]
    rows, roofline = speed_rows(models, args.updates) if models else ([], matmul_roofline())
    lines = [
        stamp(command),
        "",
        f"One thread; this CPU's float32 matmul roofline: {roofline:.0f} GFLOP/s (2048² product).",
        "",
        "| model | training frames/s | rollout | update | of which replay (inner loop) | MFLOP per frame "
        "| GFLOP/s | share of roofline |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        replay = f"{100 * r['replay_share']:.0f} %" if r["replay_share"] else "–"
        lines.append(
            f"| {r['model']} | {r['frames_per_s']:.0f} | {100 * r['rollout_share']:.0f} % "
            f"| {100 * r['update_share']:.0f} % | {replay} | {r['mflop_per_frame']:.1f} "
            f"| {r['gflop_per_s']:.1f} | {100 * r['roofline_share']:.0f} % |"
        )
    pairs = []
    for text in [p for p in args.pairs.split(",") if p]:
        pair = tuple(text.split(":"))
        speeds = side_by_side(pair, args.seconds)
        pairs.append({"pair": pair, "frames_per_s": speeds, "ratio": speeds[pair[1]] / speeds[pair[0]]})
    if pairs:
        lines += ["", f"Side by side, `mapless train train_ppo` for {args.seconds:.0f} s each, one thread each:", "",
                  "| pair | frames/s | ratio |", "|---|---|---|"]  # fmt: skip
        for p in pairs:
            a, b = p["pair"]
            fps = p["frames_per_s"]
            lines.append(f"| {b} beside {a} | {fps[b]:.0f} / {fps[a]:.0f} | {p['ratio']:.2f}× |")
    lines += ["", f"Made by {describe(provenance(1))}."]
    text = "\n".join(lines) + "\n"
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "speed.md").write_text(text)
    payload = stamped({"roofline_gflop_per_s": roofline, "models": rows, "pairs": pairs}, command, threads=1)
    (args.out / "speed.json").write_text(json.dumps(payload, indent=1))
    print(text)


if __name__ == "__main__":
    main()
