"""Where a batched training update spends its time, operator by operator, models side by side.

Every ATen operator a real ``BatchedTrainer.update()`` dispatches (rollout, backward, optimizer
step) is timed under a ``TorchDispatchMode``, and the totals per operator are printed with one
column per model: milliseconds per update and calls per update. Timing every call adds overhead
(~10 µs per operator), so the operator figures run high; each round therefore also runs one untimed
update per model, and the table's first line is their mean wall time. The models take turns update
by update (this machine's speed drifts within minutes). What the table is for is the comparison:
which operators one model spends more on than another (``cvmeta`` against ``savn`` by default,
docs/training.md "Why cvmeta trains slower than savn"). ``--shapes`` splits the matrix products by
operand shapes, which tells an LSTM product (2048 gate columns) from a GCN one (101 nodes).

``--free-graph`` adds a counterfactual column, ``cvmeta/free-graph``: cvmeta with its graph
descriptor (the hierarchical object GCN) replaced by a stand-in that costs next to nothing, the
same shape and one parameter in the graph. Everything else, the LSTM, inner loop, fusion, context
and target encoders, is cvmeta's. Its frame rate is what cvmeta would reach with a free GCN, so it
bounds what any speed-up of the GCN can give.

    python bench/profile_update.py [--models cvmeta,savn] [--updates 6] [--warmup 2] [--batch 32]
                                   [--precision bf16] [--threads 1] [--top 25] [--shapes]
                                   [--free-graph] [--set KEY=VALUE ...]
"""

from __future__ import annotations

import argparse
import time
from collections import defaultdict

import torch
from torch.utils._python_dispatch import TorchDispatchMode

MATRIX_PRODUCTS = {"mm", "bmm", "addmm", "baddbmm"}


class OperatorTimer(TorchDispatchMode):
    """Seconds and calls per ATen operator (overload packet name) while active; with
    ``shapes``, matrix products are keyed by their operands' shapes too."""

    def __init__(self, shapes: bool = False) -> None:
        super().__init__()
        self.shapes = shapes
        self.seconds: dict[str, float] = defaultdict(float)
        self.calls: dict[str, int] = defaultdict(int)

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        began = time.perf_counter()
        out = func(*args, **(kwargs or {}))
        name = func.overloadpacket.__name__
        if self.shapes and name in MATRIX_PRODUCTS:
            name += " " + "x".join(str(list(a.shape)) for a in args if hasattr(a, "shape"))
        self.seconds[name] += time.perf_counter() - began
        self.calls[name] += 1
        return out


FREE_GRAPH = "cvmeta/free-graph"


def make_trainer(model: str, batch: int, precision: str, threads: int, warmup: int, sets: list[str]):
    """A fresh batched trainer on the kitchens, after ``warmup`` updates (``FREE_GRAPH``: cvmeta
    with a graph descriptor of (almost) no cost, see the top)."""
    from mapless.config import apply_overrides, from_dict
    from mapless.train.batched import BatchedTrainer
    from mapless.train.config import TrainConfig

    name = "cvmeta" if model == FREE_GRAPH else model
    overrides = [f"model.name={name}", "env.scenes=train:kitchen", f"batch_size={batch}"]
    overrides += [f"precision={precision}", f"threads={threads}", "progress=false"]
    overrides += ["episodes=1000000000", "checkpoint_every=1000000000", "log_every=1000000000"]
    overrides += sets
    trainer = BatchedTrainer(from_dict(TrainConfig, apply_overrides({}, overrides)), None)
    trainer._setup(None)
    if model == FREE_GRAPH:
        cvmeta = trainer.model

        def free_graph_descriptor(in_view):  # [B, C] -> [B, 64, C], as the GCN's output
            return torch.relu(in_view.unsqueeze(1) * cvmeta.W2.weight[:, :1].unsqueeze(0))

        cvmeta.graph_descriptor = free_graph_descriptor
    for _ in range(warmup):
        trainer.update()
    return trainer


def profile(
    models: list[str],
    updates: int,
    batch: int,
    precision: str,
    threads: int,
    shapes: bool,
    warmup: int,
    sets: list[str],
) -> dict:
    """Per-operator totals per update over ``updates`` timed updates of each model, plus the
    wall time of as many untimed ones; the models alternate update by update."""
    trainers = {m: make_trainer(m, batch, precision, threads, warmup, sets) for m in models}
    timers = {m: OperatorTimer(shapes) for m in models}
    wall = dict.fromkeys(models, 0.0)
    frames = dict.fromkeys(models, 0)
    for _ in range(updates):
        for m, trainer in trainers.items():
            with timers[m]:
                trainer.update()
            began = time.perf_counter()
            frames[m] += trainer.update()["trajectory"].frames
            wall[m] += time.perf_counter() - began
    return {
        m: {
            "wall_ms": wall[m] / updates * 1e3,
            "frames": frames[m] / updates,
            "ms": {k: v / updates * 1e3 for k, v in timers[m].seconds.items()},
            "calls": {k: v / updates for k, v in timers[m].calls.items()},
        }
        for m in models
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--models", default="cvmeta,savn")
    parser.add_argument("--updates", type=int, default=6)
    parser.add_argument(
        "--warmup", type=int, default=2, help="updates before timing (bf16: ~40 compile oneDNN's kernels)"
    )
    parser.add_argument("--batch", type=int, default=32)
    parser.add_argument("--precision", default="bf16", choices=["fp32", "bf16"])
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--top", type=int, default=25)
    parser.add_argument("--shapes", action="store_true", help="matrix products by operand shapes")
    parser.add_argument(
        "--set", action="append", default=[], metavar="KEY=VALUE", help="training config key, every model"
    )
    parser.add_argument("--free-graph", action="store_true", help=f"add {FREE_GRAPH} (see the top)")
    args = parser.parse_args()

    models = args.models.split(",") + ([FREE_GRAPH] if args.free_graph else [])
    results = profile(
        models, args.updates, args.batch, args.precision, args.threads, args.shapes, args.warmup, args.set
    )
    header = "".join(f" {m + ' ms':>12s} {'calls':>7s}" for m in models)
    print(f"per update, B = {args.batch}, {args.precision}, {args.threads} thread(s)")
    for label, key in [("wall (untimed)", "wall_ms"), ("frames (untimed)", "frames")]:
        print(f"{label:22s}" + "".join(f" {results[m][key]:12.0f} {'':7s}" for m in models))
    rates = {m: results[m]["frames"] / results[m]["wall_ms"] * 1e3 for m in models}
    print(f"{'frames/s (untimed)':22s}" + "".join(f" {rates[m]:12.1f} {'':7s}" for m in models))
    print(
        f"{'ratio to ' + models[0]:22s}"
        + "".join(f" {rates[m] / rates[models[0]]:12.2f} {'':7s}" for m in models)
    )
    totals = {m: (sum(results[m]["ms"].values()), sum(results[m]["calls"].values())) for m in models}
    print(f"{'all operators':22s}" + "".join(f" {totals[m][0]:12.0f} {totals[m][1]:7.0f}" for m in models))
    print(f"\n{'operator':22s}{header}" if not args.shapes else f"\n{header}  operator")
    names = {name for m in models for name in results[m]["ms"]}
    by_first = sorted(names, key=lambda n: -max(results[m]["ms"].get(n, 0.0) for m in models))
    for name in by_first[: args.top]:
        cells = "".join(
            f" {results[m]['ms'].get(name, 0.0):12.1f} {results[m]['calls'].get(name, 0.0):7.0f}"
            for m in models
        )
        print(f"{name[:22]:22s}{cells}" if not args.shapes else f"{cells}  {name}")


if __name__ == "__main__":
    main()
