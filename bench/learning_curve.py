"""Learning benchmark: validation SR against wall-clock minutes and frames, model by model.

Trains each run from scratch with its recipe (default: mapless/configs/train_ppo.yaml, recurrent PPO;
``MODEL@a3c`` uses the references' A3C recipe of mapless/configs/table2_small.yaml's and table3_small.yaml's training blocks),
pauses every ``--eval-every`` minutes of training to evaluate the current policy on a fixed subset of
the built-in val set (``--val-episodes``, the same episodes for every run, actions sampled as the
evaluator does), and prints SR / SPL against minutes and frames, the time to reach ``--target`` val SR
(46 %: MJOLNIR-o's test SR after 100k episodes), and one PNG of SR against minutes.
``--protocol reference`` trains under the 1.5 m success rule on the published episodes' classes and
evaluates on its ``ref_val`` set (the published val episodes; ``--set env.target_set=mjolnir22``:
the project's sampled ones); the scenes must be built for it: ``mapless scenes build --sim
visibility_distance=1.5``.

Runs go ``--parallel`` at a time, each in its own spawned process on one thread (this machine has 2
cores), so two runs side by side see the same machine.

    python bench/learning_curve.py --run mlp --run cvmeta --minutes 10
    python bench/learning_curve.py --run "cvmeta model.target_context=true" --run cvmeta@a3c
    python bench/learning_curve.py --protocol reference --run cvmeta --run "cvmeta ppo.minibatches=4"
"""

from __future__ import annotations

import argparse
import copy
import json
import multiprocessing
import time
from pathlib import Path

from mapless.configs import configs_dir
from mapless.episodes.protocols import get_protocol
from mapless.provenance import command_line, describe, provenance, stamp, stamped

ROOT = Path(__file__).resolve().parent.parent
PPO_CONFIG = configs_dir() / "train_ppo.yaml"
A3C_TRAIN = {"algo": "a3c", "a3c": {"batch_size": 32, "lr": 0.0005}, "frames": 0, "episodes": 10**9}


def run_config(run: str, overrides: list[str]):
    """The TrainConfig of a run ``MODEL[@a3c] [KEY=VALUE ...]``: the PPO recipe (``@a3c``: the
    references'), then ``overrides`` (every run's), then the run's own ``KEY=VALUE`` settings."""
    import yaml

    from mapless.config import apply_overrides, from_dict
    from mapless.train.config import TrainConfig
    from mapless.train.recipes import with_recipe

    name, *own = run.split()
    model, _, recipe = name.partition("@")
    data = yaml.safe_load(PPO_CONFIG.read_text())
    data["model"] = {**data.get("model", {}), "name": model}
    if recipe == "a3c":
        data.update(A3C_TRAIN)
    elif recipe not in ("", "ppo"):
        raise SystemExit(f"unknown recipe {recipe!r} in {run!r}: use MODEL or MODEL@a3c")
    data.update(threads=1, progress=False)
    return from_dict(TrainConfig, with_recipe(apply_overrides(data, [*overrides, *own])))


def val_subset(count: int, split: str = "val", target_set: str = "mjolnir22"):
    """The first ``count / 4`` episodes of every room type in the built-in ``split`` set of
    ``target_set`` (the reference protocol's of hoz22: the published val episodes)."""
    from mapless.episodes.evalsets import builtin_path, load
    from mapless.scenes.catalogue import ROOM_TYPES, room_type_of

    episodes, _ = load(builtin_path(split, target_set))
    per_room = max(1, count // len(ROOM_TYPES))
    chosen = [[e for e in episodes if room_type_of(e.scene) == room][:per_room] for room in ROOM_TYPES]
    return [e for room in chosen for e in room]


def evaluate_policy(model, library, episodes) -> dict[str, float]:
    """SR, SPL and their L>=5 parts of ``model`` (a copy is evaluated) on ``episodes``."""
    from mapless.agent.evaluation import AdaptiveModelAgent, ModelAgent
    from mapless.evaluate.metrics import aggregate
    from mapless.evaluate.runner import EvalSettings, run_episodes

    model = copy.deepcopy(model).cpu().eval()  # a GPU-trained policy is evaluated on the CPU
    batch = 32
    agent = AdaptiveModelAgent(model, batch) if model.adaptive else ModelAgent(model, batch)
    settings = EvalSettings(batch_size=batch, workers=1, category_set=model.config.category_set)
    results = run_episodes(agent, library, episodes, list(range(len(episodes))), settings)
    metrics = aggregate(results)
    return {
        "sr": 100 * metrics["success"],
        "spl": 100 * metrics["spl"],
        "sr_l5": 100 * metrics["l5_success"],
        "spl_l5": 100 * metrics["l5_spl"],
    }


def train_and_evaluate(job: tuple[str, list[str], float, float, int, str]) -> dict:
    """One run: train for ``minutes`` of training time, evaluating every ``eval_every`` minutes."""
    import torch

    torch.set_num_threads(1)
    from mapless.train.batched import BatchedTrainer
    from mapless.train.builders import BuiltinLibrary, prepare_scenes
    from mapless.train.ppo import PPOTrainer

    run, overrides, minutes, eval_every, val_episodes, val_split = job
    config = run_config(run, overrides)
    prepare_scenes(config)
    trainer = (PPOTrainer if config.algo == "ppo" else BatchedTrainer)(config, None)
    trainer.build()
    library = BuiltinLibrary(config)()
    episodes = val_subset(val_episodes, val_split, config.env.target_set)
    points = [{"minutes": 0.0, "frames": 0, **evaluate_policy(trainer.model, library, episodes)}]
    print(f"{run}: 0.0 min, 0 frames, val SR {points[0]['sr']:.1f}", flush=True)
    trained, frames, next_eval = 0.0, 0, eval_every * 60
    while trained < minutes * 60:
        start = time.perf_counter()
        result = trainer.update()
        trained += time.perf_counter() - start
        frames += result["segment"].frames if "segment" in result else result["trajectory"].frames
        if trained >= next_eval or trained >= minutes * 60:
            next_eval += eval_every * 60
            point = {"minutes": trained / 60, "frames": frames}
            point.update(evaluate_policy(trainer.model, library, episodes))
            points.append(point)
            print(
                f"{run}: {point['minutes']:.1f} min, {frames} frames ({frames / trained:.0f}/s), "
                f"val SR {point['sr']:.1f} SPL {point['spl']:.1f} (L>=5 {point['sr_l5']:.1f} / {point['spl_l5']:.1f})",
                flush=True,
            )
    return {"run": run, "overrides": overrides, "frames_per_s": frames / trained, "points": points}


def first_reaching(points: list[dict], target: float) -> dict | None:
    return next((p for p in points if p["sr"] >= target), None)


def report(results: list[dict], target: float) -> str:
    lines = [
        f"| run | frames/s | val SR / SPL at the end | L≥5 SR / SPL | best val SR | time to {target:.0f} % val SR |",
        "|---|---|---|---|---|---|",
    ]
    for r in results:
        last, best = r["points"][-1], max(r["points"], key=lambda p: p["sr"])
        hit = first_reaching(r["points"], target)
        reach = f"{hit['minutes']:.1f} min ({hit['frames'] / 1000:.0f}k frames)" if hit else "not reached"
        lines.append(
            f"| {r['run']} | {r['frames_per_s']:.0f} | {last['sr']:.1f} / {last['spl']:.1f} "
            f"({last['minutes']:.1f} min, {last['frames'] / 1000:.0f}k frames) | {last['sr_l5']:.1f} / "
            f"{last['spl_l5']:.1f} | {best['sr']:.1f} ({best['minutes']:.1f} min) | {reach} |"
        )
    return "\n".join(lines)


def plot(results: list[dict], target: float, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4), sharey=True)
    for r in results:
        minutes = [p["minutes"] for p in r["points"]]
        frames = [p["frames"] / 1000 for p in r["points"]]
        sr = [p["sr"] for p in r["points"]]
        axes[0].plot(minutes, sr, marker="o", label=r["run"])
        axes[1].plot(frames, sr, marker="o", label=r["run"])
    for ax, xlabel in zip(axes, ("training minutes (1 thread)", "training frames (thousands)"), strict=True):
        ax.axhline(target, color="grey", linestyle="--", linewidth=1)
        ax.set_xlabel(xlabel)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("val SR (%)")
    axes[1].legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--run",
        action="append",
        default=[],
        help="a run: 'MODEL[@a3c] [KEY=VALUE ...]' (repeat the flag; default: mlp and cvmeta)",
    )
    parser.add_argument("--minutes", type=float, default=10.0, help="training minutes per run")
    parser.add_argument("--eval-every", type=float, default=2.0, help="training minutes between evaluations")
    parser.add_argument("--val-episodes", type=int, default=400)
    parser.add_argument("--target", type=float, default=46.0, help="val SR (%%) to time")
    parser.add_argument("--parallel", type=int, default=2)
    parser.add_argument(
        "--protocol",
        choices=("standard", "reference"),
        default="standard",
        help="standard: success within 1.0 m, val x21-x25; reference: 1.5 m (training too), ref_val, "
        "on the published episodes' classes",
    )
    parser.add_argument(
        "--set", action="append", default=[], metavar="KEY=VALUE", help="config override for every run"
    )
    parser.add_argument("--out", type=Path, default=Path("reports/learning_curve"))
    args = parser.parse_args()
    runs = args.run or ["mlp", "cvmeta"]
    protocol = get_protocol(args.protocol)
    overrides = [*protocol.train_overrides(), *args.set]  # a run's own target set wins
    for run in runs:  # every config is validated before any training starts
        run_config(run, overrides)
    jobs = [
        (run, overrides, args.minutes, args.eval_every, args.val_episodes, protocol.select_split)
        for run in runs
    ]
    with multiprocessing.get_context("spawn").Pool(max(1, min(args.parallel, len(jobs)))) as pool:
        results = pool.map(train_and_evaluate, jobs)
    args.out.mkdir(parents=True, exist_ok=True)
    table = report(results, args.target)
    command = command_line()
    (args.out / "learning_curve.json").write_text(json.dumps(stamped({"runs": results}, command), indent=1))
    text = f"{stamp(command)}\n\n{table}\n\nMade by {describe(provenance())}.\n"
    (args.out / "learning_curve.md").write_text(text)
    plot(results, args.target, args.out / "learning_curve.png")
    print(table)
    print(f"wrote {args.out}/learning_curve.{{json,md,png}}")


if __name__ == "__main__":
    main()
