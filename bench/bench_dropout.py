"""nn.Dropout against mapless.models.dropout.Dropout, side by side, at the models' shapes.

python bench/bench_dropout.py [--threads 1] [--rounds 20]
"""

from __future__ import annotations

import argparse
import time

import torch
from torch import nn

from mapless.models.dropout import Dropout

SHAPES = {
    "cvmeta context [512, 64, 101]": (512, 64, 101),
    "cvmeta fused [512, 32, 101]": (512, 32, 101),
    "savn map [512, 64, 7, 7]": (512, 64, 7, 7),
    "B = 32 context [32, 64, 101]": (32, 64, 101),
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--rounds", type=int, default=20)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    candidates = {"nn.Dropout": nn.Dropout(0.25).train(), "mapless Dropout": Dropout(0.25).train()}
    print(
        f"{'shape':32s} {'nn.Dropout ms':>14s} {'mapless ms':>11s} {'ratio':>6s}   (forward + backward, median)"
    )
    for label, shape in SHAPES.items():
        x = torch.randn(shape, requires_grad=True)
        times: dict[str, list[float]] = {name: [] for name in candidates}
        for _ in range(args.rounds):
            for name, dropout in candidates.items():  # alternating: the machine's speed drifts
                start = time.perf_counter()
                dropout(x).sum().backward()
                times[name].append(time.perf_counter() - start)
        old, new = (1000 * sorted(t)[len(t) // 2] for t in times.values())
        print(f"{label:32s} {old:14.2f} {new:11.2f} {old / new:5.2f}x")


if __name__ == "__main__":
    main()
