"""Which memory layout of the LSTM weight the rollout's products should read, side by side.

A training rollout multiplies the 4H x (D + H) LSTM weight (2048 x 3744 for cvmeta) by a few rows at
a time: the forward product ``x Wᵀ``, the inner steps' transposed product ``g W``, and once per
update the weight gradient ``Gᵀ X`` of all rows (mapless/agent/rollout_lstm.py). The same product
can read a row-major copy of W or of Wᵀ; this prints both, measured in alternation, per row count:

    python bench/bench_lstm_layout.py [--threads 2] [--rounds 20]

"along" = the reduced dimension is contiguous in the weight (``rows @ Mᵀ``, M row-major),
"across" = it is strided (``rows @ M``). The gradient compares a transposed view of the gathered
gate rows with a contiguous transposed copy (the copy's time included).
"""

from __future__ import annotations

import argparse
import time

import torch

GATES, INPUTS = 2048, 3744


def _alternating(candidates: dict[str, callable], rounds: int) -> dict[str, float]:
    """Median ms of each candidate, run in alternation (this machine's speed drifts)."""
    times: dict[str, list[float]] = {name: [] for name in candidates}
    for f in candidates.values():
        f()
    for _ in range(rounds):
        for name, f in candidates.items():
            start = time.perf_counter()
            f()
            times[name].append(time.perf_counter() - start)
    return {name: 1000 * sorted(t)[len(t) // 2] for name, t in times.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--rounds", type=int, default=20)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    for dtype in (torch.bfloat16, torch.float32):
        gate_major = torch.randn(GATES, INPUTS).to(dtype)  # nn.LSTMCell's [weight_ih || weight_hh]
        input_major = gate_major.T.contiguous()
        print(f"\n{dtype}, {args.threads} threads: ms per product (median of {args.rounds})")
        print(
            f"{'rows':>5s} {'x Wᵀ along':>11s} {'across':>7s} {'ratio':>6s}   {'g W along':>10s} {'across':>7s} {'ratio':>6s}"
        )
        for rows in (1, 4, 16, 32, 128, 256):
            x, g = torch.randn(rows, INPUTS).to(dtype), torch.randn(rows, GATES).to(dtype)
            t = _alternating(
                {
                    "forward along": lambda x=x, w=gate_major: x @ w.T,
                    "forward across": lambda x=x, w=input_major: x @ w,
                    "transposed along": lambda g=g, w=input_major: g @ w.T,
                    "transposed across": lambda g=g, w=gate_major: g @ w,
                },
                args.rounds,
            )
            print(
                f"{rows:5d} {t['forward along']:11.2f} {t['forward across']:7.2f}"
                f" {t['forward across'] / t['forward along']:5.2f}x"
                f"   {t['transposed along']:10.2f} {t['transposed across']:7.2f}"
                f" {t['transposed across'] / t['transposed along']:5.2f}x"
            )
        print(f"{'rows':>5s} {'Gᵀ X view':>10s} {'copy + product':>15s} {'ratio':>6s}")
        for rows in (600, 4500):
            gate_rows, input_rows = torch.randn(rows, GATES).to(dtype), torch.randn(rows, INPUTS).to(dtype)
            out, columns = torch.empty(GATES, INPUTS, dtype=dtype), torch.empty(GATES, rows, dtype=dtype)
            t = _alternating(
                {
                    "view": lambda g=gate_rows, x=input_rows, o=out: torch.mm(g.T, x, out=o),
                    "copy": lambda g=gate_rows, x=input_rows, c=columns, o=out: torch.mm(
                        c.copy_(g.T), x, out=o
                    ),
                },
                max(args.rounds // 4, 3),
            )
            print(f"{rows:5d} {t['view']:10.1f} {t['copy']:15.1f} {t['view'] / t['copy']:5.2f}x")


if __name__ == "__main__":
    main()
