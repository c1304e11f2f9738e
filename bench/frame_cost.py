"""Per-frame cost of every trainable model in the PPO recipe, side by side with the mlp sanity model.

For each model a real segment is collected in the training scenes (``ppo.envs`` slots; whole episodes
for adaptive models and under ``ppo.whole_episodes``) and then, model by model in turns (this
machine's speed drifts), timed:

* acting: frames/s of the collection (forward passes without gradient, memo on);
* update: frame-passes/s of one PPO minibatch's replay, forward + backward (segments through
  ``model.replay``; adaptive models through the meta-learning inner loop);
* PPO: the frames/s a run reaches from those two, ``1 / (1/acting + epochs/update)``;
* the split of a non-adaptive replay's forward (``encoder`` incl. ``graph``, ``lstm``, ``heads``)
  from the profiler's labels.

    python bench/frame_cost.py [--models a3c,mjolnir_o,cvmeta,mlp] [--threads 1,2] [--repeats 3]
                               [--set KEY=VALUE ...] [--profile] [--runs RUN_DIR,RUN_DIR]

``--runs`` measures trained policies instead of fresh ones (each run folder's config and
``final_model.pt``): a trained agent plays longer episodes, which changes an adaptive model's cost
per frame (its replay's LSTM products cost per step, not per frame).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from mapless.configs import configs_dir

PPO_CONFIG = configs_dir() / "train_ppo.yaml"


def build(model: str, overrides: list[str]):
    import yaml

    from mapless.config import apply_overrides, from_dict
    from mapless.train.config import TrainConfig
    from mapless.train.ppo import PPOTrainer
    from mapless.train.recipes import with_recipe
    from mapless.train.segments import SegmentCollector

    data = yaml.safe_load(PPO_CONFIG.read_text())
    data["model"] = {"name": model}
    data.update(progress=False, threads=0)
    trainer = PPOTrainer(from_dict(TrainConfig, with_recipe(apply_overrides(data, overrides))), None)
    trainer.build()
    assert isinstance(trainer.collector, SegmentCollector)
    return trainer


def build_trained(run_dir: Path):
    """A PPO trainer with a run's final weights and the configuration they were trained with."""
    from dataclasses import replace

    from mapless import checkpoint as ckpt
    from mapless.train.config import TrainConfig
    from mapless.train.ppo import PPOTrainer

    payload = ckpt.load_file(run_dir / ckpt.FINAL_MODEL_FILE)
    config = replace(ckpt.config_of(payload, TrainConfig), progress=False, threads=0)
    if config.algo != "ppo":
        raise SystemExit(f"{run_dir}: trained with {config.algo}; this bench times the PPO recipe")
    trainer = PPOTrainer(config, None)
    trainer.build()
    trainer.model.load_state_dict(payload["model"])
    return trainer


def time_acting(trainer) -> tuple[float, object]:
    start = time.perf_counter()
    segment = trainer.collector.collect(trainer.rollout_steps, trainer.rng)
    return segment.frames / (time.perf_counter() - start), segment


def time_update(trainer, segment) -> float:
    from mapless.train.ppo import gae

    ppo = trainer.config.ppo
    adv, ret = gae(segment.rewards, segment.values, segment.next_value, segment.terminated,
                   segment.truncated, segment.bootstrap, ppo.gamma, ppo.lam)  # fmt: skip
    columns = torch.arange(segment.mask.shape[1] // ppo.minibatches)
    start = time.perf_counter()
    trainer.minibatch_step(segment, columns, adv, ret)
    trainer.optimizer.zero_grad(set_to_none=True)
    return float(segment.mask[:, columns].sum()) / (time.perf_counter() - start)


def forward_split(trainer, segment) -> dict[str, float]:
    """Milliseconds of the labelled parts of one non-adaptive replay's forward pass."""
    from torch.profiler import ProfilerActivity, profile

    from mapless.models.memo import InViewMemo

    if trainer.inner is not None:
        return {}
    columns = torch.arange(segment.mask.shape[1] // trainer.config.ppo.minibatches)
    memo = trainer.model.memoizing_in_view(InViewMemo(max_rows=None))
    with profile(activities=[ProfilerActivity.CPU]) as prof, torch.no_grad(), memo:
        trainer.model.replay({k: v[:, columns] for k, v in segment.obs.items()},
                           segment.prev_policy[:, columns], segment.starts[:, columns],
                           tuple(t[columns] for t in segment.hidden))  # fmt: skip
    totals = {
        e.key: e.cpu_time_total / 1000
        for e in prof.key_averages()
        if e.key in ("encoder", "graph", "lstm", "heads")
    }
    return totals


def replay_profile(trainer, segment, rows: int = 12) -> str:
    """The operators of one minibatch's replay (forward + backward) by self time, with their shapes:
    where an adaptive model's update goes, which the labelled split cannot show."""
    from torch.profiler import ProfilerActivity, profile

    from mapless.train.ppo import gae

    ppo = trainer.config.ppo
    adv, ret = gae(segment.rewards, segment.values, segment.next_value, segment.terminated,
                   segment.truncated, segment.bootstrap, ppo.gamma, ppo.lam)  # fmt: skip
    columns = torch.arange(segment.mask.shape[1] // ppo.minibatches)
    with profile(activities=[ProfilerActivity.CPU], record_shapes=True) as prof:
        trainer.minibatch_step(segment, columns, adv, ret)
    trainer.optimizer.zero_grad(set_to_none=True)
    by_name = prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=rows)
    by_shape = prof.key_averages(group_by_input_shape=True).table(
        sort_by="self_cpu_time_total", row_limit=rows, max_shapes_column_width=80
    )
    return f"{by_name}\n{by_shape}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--models", default="a3c,mjolnir_o,cvmeta,mlp")
    parser.add_argument("--threads", default="1,2")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    parser.add_argument("--profile", action="store_true", help="also print each model's replay operators")
    parser.add_argument(
        "--runs", help="comma-separated run folders: their trained policies instead of --models"
    )
    args = parser.parse_args()
    runs = [Path(r) for r in args.runs.split(",")] if args.runs else []
    models = [r.name for r in runs] or args.models.split(",")
    for threads in [int(t) for t in args.threads.split(",")]:
        torch.set_num_threads(threads)
        if runs:
            trainers = {r.name: build_trained(r) for r in runs}
        else:
            trainers = {m: build(m, args.set) for m in models}
        acting = {m: [] for m in models}
        update = {m: [] for m in models}
        segments = {}
        for _ in range(args.repeats):
            for m, trainer in trainers.items():  # models take turns
                fps, segments[m] = time_acting(trainer)
                acting[m].append(fps)
                update[m].append(time_update(trainer, segments[m]))
        print(f"\n{threads} thread(s), median of {args.repeats} turns")
        print(
            "| model | acting frames/s | update frame-passes/s | PPO frames/s | vs mlp | forward split (ms: encoder / graph / lstm / heads) |"
        )
        print("|---|---|---|---|---|---|")
        best = {}
        for m in models:
            a, u = sorted(acting[m])[len(acting[m]) // 2], sorted(update[m])[len(update[m]) // 2]
            # every frame is acted once and replayed (forward + backward) once per epoch
            best[m] = (a, u, 1.0 / (1.0 / a + trainers[m].config.ppo.epochs / u))
        reference = next((best[m][2] for m in models if trainers[m].config.model.name == "mlp"), 0)
        for m in models:
            a, u, ppo = best[m]
            split = forward_split(trainers[m], segments[m])
            parts = (
                " / ".join(f"{split.get(k, 0):.0f}" for k in ("encoder", "graph", "lstm", "heads"))
                if split
                else "(inner loop)"
            )
            ratio = f"{reference / ppo:.1f}x dearer" if reference else ""
            print(f"| {m} | {a:.0f} | {u:.0f} | {ppo:.0f} | {ratio} | {parts} |")
        if args.profile:
            for m in models:
                print(f"\n{m}: one replay, operators by self time ({threads} thread(s))")
                print(replay_profile(trainers[m], segments[m]))


if __name__ == "__main__":
    main()
