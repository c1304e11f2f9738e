"""Where a batched training update spends its time, operator by operator, models side by side.

Every ATen operator a real ``BatchedTrainer.update()`` dispatches (rollout, backward, optimizer
step) is timed under a ``TorchDispatchMode``, and the totals per operator are printed with one
column per model: milliseconds per update and calls per update. Timing every call adds overhead
(~10 µs per operator), so the absolute figures run high; what the table is for is the comparison:
which operators one model spends more on than another (``cvmeta`` against ``savn`` by default,
docs/training.md "Why cvmeta trains slower than savn").

    python bench/profile_update.py [--models cvmeta,savn] [--updates 6] [--batch 32]
                                   [--precision bf16] [--threads 1] [--top 25]
"""

from __future__ import annotations

import argparse
import time
from collections import defaultdict

from torch.utils._python_dispatch import TorchDispatchMode


class OperatorTimer(TorchDispatchMode):
    """Seconds and calls per ATen operator (overload packet name) while active."""

    def __init__(self) -> None:
        super().__init__()
        self.seconds: dict[str, float] = defaultdict(float)
        self.calls: dict[str, int] = defaultdict(int)

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        began = time.perf_counter()
        out = func(*args, **(kwargs or {}))
        name = func.overloadpacket.__name__
        self.seconds[name] += time.perf_counter() - began
        self.calls[name] += 1
        return out


def profile(model: str, updates: int, batch: int, precision: str, threads: int) -> dict:
    """Per-operator totals over ``updates`` updates of a fresh trainer (after two warm-up ones)."""
    from mapless.config import apply_overrides, from_dict
    from mapless.train.batched import BatchedTrainer
    from mapless.train.config import TrainConfig

    overrides = [f"model.name={model}", "env.scenes=train:kitchen", f"batch_size={batch}"]
    overrides += [f"precision={precision}", f"threads={threads}", "progress=false"]
    overrides += ["episodes=1000000000", "checkpoint_every=1000000000", "log_every=1000000000"]
    trainer = BatchedTrainer(from_dict(TrainConfig, apply_overrides({}, overrides)), None)
    trainer._setup(None)
    for _ in range(2):
        trainer.update()
    timer, frames = OperatorTimer(), 0
    began = time.perf_counter()
    with timer:
        for _ in range(updates):
            frames += trainer.update()["trajectory"].frames
    wall = time.perf_counter() - began
    return {
        "wall_ms": wall / updates * 1e3,
        "frames": frames / updates,
        "ms": {k: v / updates * 1e3 for k, v in timer.seconds.items()},
        "calls": {k: v / updates for k, v in timer.calls.items()},
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--models", default="cvmeta,savn")
    parser.add_argument("--updates", type=int, default=6)
    parser.add_argument("--batch", type=int, default=32)
    parser.add_argument("--precision", default="bf16", choices=["fp32", "bf16"])
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--top", type=int, default=25)
    args = parser.parse_args()

    models = args.models.split(",")
    results = {m: profile(m, args.updates, args.batch, args.precision, args.threads) for m in models}
    header = "".join(f" {m + ' ms':>12s} {'calls':>7s}" for m in models)
    print(f"per update, B = {args.batch}, {args.precision}, {args.threads} thread(s)")
    for label, key in [("wall (timed)", "wall_ms"), ("frames", "frames")]:
        print(f"{label:22s}" + "".join(f" {results[m][key]:12.0f} {'':7s}" for m in models))
    totals = {m: (sum(results[m]["ms"].values()), sum(results[m]["calls"].values())) for m in models}
    print(f"{'all operators':22s}" + "".join(f" {totals[m][0]:12.0f} {totals[m][1]:7.0f}" for m in models))
    print(f"\n{'operator':22s}{header}")
    names = {name for m in models for name in results[m]["ms"]}
    by_first = sorted(names, key=lambda n: -max(results[m]["ms"].get(n, 0.0) for m in models))
    for name in by_first[: args.top]:
        cells = "".join(
            f" {results[m]['ms'].get(name, 0.0):12.1f} {results[m]['calls'].get(name, 0.0):7.0f}"
            for m in models
        )
        print(f"{name[:22]:22s}{cells}")


if __name__ == "__main__":
    main()
