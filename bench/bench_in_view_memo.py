"""The in-view memo (mapless.models.memo), on and off side by side: training frames/s and
evaluation steps/s of the models with an in-view GCN, and the share of rows it actually computed.

On and off alternate in rounds within one process (same model, same scenes, same thread count), so
the ratio is fair on a noisy machine; training uses real batched updates (the model changes between
rounds exactly as in ``mapless train``), evaluation runs fresh agents on the same test episodes with
``Done`` masked (100-step episodes, as bench_eval.py).

    python bench/bench_in_view_memo.py [--models cvmeta,mjolnir_o] [--updates 4] [--rounds 2]
                                       [--episodes 32] [--threads 2] [--precision bf16]
"""

from __future__ import annotations

import argparse
import contextlib
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))


@contextlib.contextmanager
def memo_switched(on: bool, used: dict | None = None) -> Iterator[None]:
    """Within the block, ``NavModel.memoizing_in_view`` does nothing unless ``on``; the memos it
    hands out are collected in ``used`` (by id)."""
    from mapless.models.base import NavModel

    original = NavModel.memoizing_in_view

    @contextlib.contextmanager
    def switched(self, memo=None):
        if not on:
            yield None
            return
        with original(self, memo) as active:
            if active is not None and used is not None:
                used[id(active)] = active
            yield active

    NavModel.memoizing_in_view = switched
    try:
        yield
    finally:
        NavModel.memoizing_in_view = original


def computed_share(used: dict) -> float:
    """Rows the memos sent through the GCN, over rows asked for."""
    requested = sum(m.requested_rows for m in used.values())
    return sum(m.computed_rows for m in used.values()) / max(requested, 1)


def alternate(work: Callable[[], tuple[int, float]], rounds: int) -> dict:
    """``work()`` (returns the steps it timed and their seconds) with the memo off, then on,
    ``rounds`` times: steps per second of each setting and the share of rows the memos computed."""
    totals = {True: [0, 0.0], False: [0, 0.0]}
    used: dict = {}
    for _ in range(rounds):
        for on in (False, True):
            with memo_switched(on, used):
                steps, seconds = work()
            totals[on][0] += steps
            totals[on][1] += seconds
    return {
        "off": totals[False][0] / totals[False][1],
        "on": totals[True][0] / totals[True][1],
        "computed": computed_share(used),
    }


def bench_training(model: str, updates: int, rounds: int, threads: int, precision: str) -> dict:
    from mapless.config import apply_overrides, from_dict
    from mapless.train.batched import BatchedTrainer
    from mapless.train.config import TrainConfig

    overrides = [f"model.name={model}", "env.scenes=train", "batch_size=32", f"precision={precision}"]
    overrides += ["episodes=1000000000", "checkpoint_every=1000000000", "log_every=1000000000"]
    overrides += [f"threads={threads}", "progress=false"]
    trainer = BatchedTrainer(from_dict(TrainConfig, apply_overrides({}, overrides)), None)
    trainer._setup(None)
    trainer.update()  # warm-up

    def train() -> tuple[int, float]:
        start = time.perf_counter()
        frames = sum(trainer.update()["trajectory"].frames for _ in range(updates))
        return frames, time.perf_counter() - start

    return alternate(train, rounds)


def bench_evaluation(model: str, episodes: int, rounds: int) -> dict:
    from bench_eval import bench_episodes, masked_agent

    from mapless.evaluate.runner import EvalSettings, run_episodes
    from mapless.sim.library import SceneLibrary

    chosen = bench_episodes(episodes)
    library = SceneLibrary.builtin()
    for scene in {e.scene for e in chosen}:
        library[scene]
    settings = EvalSettings(batch_size=32, max_steps=100)

    def evaluate() -> tuple[int, float]:
        agent = masked_agent(model, settings.batch_size)  # built outside the clock
        start = time.perf_counter()
        results = run_episodes(agent, library, chosen, list(range(len(chosen))), settings)
        return sum(r.length for r in results), time.perf_counter() - start

    return alternate(evaluate, rounds)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--models", default="cvmeta,mjolnir_o")
    parser.add_argument("--updates", type=int, default=4, help="training updates per round and setting")
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--episodes", type=int, default=32, help="evaluation episodes per round")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--precision", default="bf16", choices=("fp32", "bf16"))
    args = parser.parse_args()
    import torch

    torch.set_num_threads(args.threads)
    print(f"{args.threads} threads; training: B = 32, {args.precision}; evaluation: 100-step episodes")
    print(f"{'model':10} {'what':22} {'memo off':>9} {'memo on':>9} {'ratio':>6} {'rows computed':>14}")
    for model in args.models.split(","):
        train = bench_training(model, args.updates, args.rounds, args.threads, args.precision)
        evaluation = bench_evaluation(model, args.episodes, args.rounds)
        for what, r in (("training frames/s", train), ("evaluation steps/s", evaluation)):
            ratio = r["on"] / r["off"]
            print(f"{model:10} {what:22} {r['off']:9.0f} {r['on']:9.0f} {ratio:5.2f}x {r['computed']:13.0%}")


if __name__ == "__main__":
    main()
