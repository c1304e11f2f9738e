"""What cvmeta's hierarchical object GCN costs per training update, the part of cvmeta that savn
does not have: forward + backward of ``--rows`` new in-view rows (a fresh cvmeta model at B = 32
sends ~110 per update through it, ``bench/bench_in_view_memo.py`` counts them), in one batch and
in ``--chunks`` per-step pieces as a rollout produces them, float32 and bfloat16 side by side.

    python bench/bench_object_gcn.py [--rows 110] [--chunks 25] [--repeats 10] [--threads 2]
"""

from __future__ import annotations

import argparse
import time

import torch


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", type=int, default=110)
    parser.add_argument("--chunks", type=int, default=25)
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()

    from mapless.models import ModelConfig, build_model

    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    model = build_model(ModelConfig(name="cvmeta"))
    in_view = (torch.rand(args.rows, model.num_categories) < 0.05).float()
    nodes, width = model.num_categories, model.num_categories + model.glove_dim
    # Per row: Â X and X W1ᵀ at width C + 300, then X W2ᵀ (-> 64) and Â X at 64 (layer 1 is shared).
    flop = 2 * nodes * (nodes * width + width * width + width * 64 + nodes * 64)
    print(f"{args.rows} rows, {3 * flop * args.rows / 1e9:.1f} GFLOP forward + backward")

    def run(chunks: int, dtype: torch.dtype | None) -> float:
        def once() -> None:
            for part in in_view.chunk(chunks):
                with torch.autocast("cpu", dtype=torch.bfloat16, enabled=dtype is not None):
                    out = model.graph_descriptor(part)
                out.float().square().sum().backward()

        once()  # kernel selection and allocation
        began = time.perf_counter()
        for _ in range(args.repeats):
            once()
        return (time.perf_counter() - began) / args.repeats * 1e3

    for label, dtype in (("float32", None), ("bfloat16", torch.bfloat16)):
        batched, chunked = run(1, dtype), run(args.chunks, dtype)
        print(
            f"{label:9s} one batch {batched:6.1f} ms   {args.chunks} chunks {chunked:6.1f} ms"
            f"   ({chunked / batched:.2f}x)"
        )


if __name__ == "__main__":
    main()
