"""Evaluator throughput and memory: steps/s on 100-step episodes.

Models are freshly initialised (speed does not depend on the weights) and their ``Done`` action is
masked, so every episode runs its full 100 steps, as a trained agent's failures do; this measures
the evaluator, not how soon an untrained policy happens to stop. Episodes: the first N kitchen
episodes of the built-in test set (or, before the sets ship, episodes drawn the same way).

    python bench/bench_eval.py [--models a3c,mjolnir_o,savn,cvmeta] [--episodes 64] [--workers 2] [--bf16]

The originals evaluate at about 217 steps/s (A3C), 162 (MJOLNIR-o), 83 (SAVN with test-time
adaptation, 4.4 GB RSS) on this kind of machine; targets: 2,000 / 1,600 / 800 steps/s under 1 GB.
"""

from __future__ import annotations

import argparse
import resource
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

REFERENCE = {"a3c": 217, "mjolnir_o": 162, "savn": 83}
TARGET = {"a3c": 2000, "mjolnir_o": 1600, "savn": 800}


def masked_agent(name: str, batch_size: int, bf16: bool = False, hidden: int = 512):
    """An evaluation agent of a fresh ``name`` model that never calls Done."""
    import torch

    from mapless.agent.evaluation import AdaptiveModelAgent, ModelAgent
    from mapless.models import build_model

    torch.manual_seed(0)
    model = build_model(name, hidden_size=hidden)
    agent = AdaptiveModelAgent(model, batch_size) if model.adaptive else ModelAgent(model, batch_size, bf16)
    policy = agent.policy

    def no_done(obs, env):
        probs = policy(obs, env).copy()
        probs[:, 5] = 0.0
        return probs / probs.sum(axis=1, keepdims=True)

    agent.policy = no_done
    return agent


def _factory(name: str):
    def build(batch_size: int, bf16: bool = False):
        return masked_agent(name, batch_size, bf16)

    return build


# Picklable by reference for spawn workers (``bench_eval:a3c`` etc.).
a3c = _factory("a3c")
mjolnir_o = _factory("mjolnir_o")
savn = _factory("savn")
cvmeta = _factory("cvmeta")
sp = _factory("sp")
gve = _factory("gve")
spatt = _factory("spatt")
mjolnir_r = _factory("mjolnir_r")


def bench_episodes(n: int) -> list:
    from mapless.episodes import evalsets
    from mapless.evaluate.episode_sets import load_episodes
    from mapless.sim.library import SceneLibrary

    if evalsets.builtin_path("test").exists():
        return load_episodes("test", per_room=n, rooms=("kitchen",))
    return evalsets.make_eval_set(SceneLibrary.builtin(), "test", per_room=n, room_types=("kitchen",))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--models", default="a3c,mjolnir_o,savn,cvmeta")
    parser.add_argument("--episodes", type=int, default=64)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--batch-size", type=int, default=32)
    parser.add_argument("--bf16", action="store_true", help="precision bf16 (non-adaptive models)")
    args = parser.parse_args()

    from mapless.evaluate.runner import AgentSpec, EvalSettings, evaluate

    episodes = bench_episodes(args.episodes)
    print(
        f"{len(episodes)} kitchen test episodes of 100 steps, {args.workers} workers, batch {args.batch_size}"
        + (", precision bf16" if args.bf16 else "")
    )
    print(
        f"{'model':10s} {'steps/s':>8s} {'vs orig':>8s} {'target':>7s} {'total RSS MB':>12s}  peak RSS MB per process"
    )
    for name in args.models.split(","):
        spec = AgentSpec(kind="factory", factory=f"bench_eval:{name}")
        settings = EvalSettings(batch_size=args.batch_size, workers=args.workers, seed=0, bf16=args.bf16)
        start = time.perf_counter()
        run = evaluate(spec, episodes, settings)
        assert all(r.length == 100 for r in run.results), "Done is masked: every episode runs 100 steps"
        main_rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        total = main_rss + sum(run.worker_rss_mb) if args.workers > 1 else main_rss
        ref = REFERENCE.get(name)
        speed = run.loop_steps_per_second
        ratio = f"{speed / ref:.1f}x" if ref else "–"
        peaks = [main_rss, *run.worker_rss_mb] if args.workers > 1 else [main_rss]
        print(
            f"{name:10s} {speed:8.0f} {ratio:>8s} {TARGET.get(name, '–')!s:>7s} {total:12.0f}  "
            f"{', '.join(f'{m:.0f}' for m in peaks)} (wall {time.perf_counter() - start:.1f} s incl. start-up: "
            f"{run.steps_per_second:.0f} steps/s)"
        )


if __name__ == "__main__":
    main()
