"""Learning check (a benchmark, not a test): does a model's training success rate clearly beat the
random agent's within a wall-clock budget on this machine?

Trains with ``mapless train``'s code path (config: mapless/configs/train_learning_check.yaml plus
``--set`` overrides) for ``--minutes``, measures the random agent's success on episodes drawn by the
same training sampler, and writes the training-success curve against the random baseline as a PNG,
plus the numbers as JSON.

    python bench/learning_check.py [--minutes 30] [--set model.name=cvmeta ...] [--out reports/learning_check]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from mapless.configs import configs_dir
from mapless.provenance import command_line, stamped


def random_success(config, episodes: int) -> tuple[float, float]:
    """Training success rate of the uniform random agent, and its binomial standard error."""
    import torch

    from mapless.agent.acting import observation_keys
    from mapless.models import build_model
    from mapless.train.builders import BuiltinLibrary, training_env, training_sampler
    from mapless.train.rollout import make_actor, run_batch
    from mapless.train.runtime import seed_for

    library = BuiltinLibrary(config)()
    batch = 64
    env = training_env(config, library, batch)
    sampler = training_sampler(config, library, seed_for(config, 99))
    rng = np.random.default_rng(seed_for(config, 98))
    model = build_model(config.model.__class__(name="random", category_set=config.model.category_set))
    actor = make_actor(model)
    keys = observation_keys(model)
    successes = []
    with torch.no_grad():
        for _ in range(max(1, episodes // batch)):
            chunk = [sampler.sample(rng) for _ in range(batch)]
            trajectory = run_batch(actor, env, chunk, rng.random((batch, config.env.max_steps)), keys,
                                   torch.device("cpu"))  # fmt: skip
            successes.extend(trajectory.success.tolist())
    p = float(np.mean(successes))
    return p, float(np.sqrt(p * (1 - p) / len(successes)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--config",
        type=Path,
        default=configs_dir() / "train_learning_check.yaml",
    )
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    parser.add_argument("--minutes", type=float, default=30.0)
    parser.add_argument("--random-episodes", type=int, default=2048)
    parser.add_argument("--out", type=Path, default=Path("reports/learning_check"))
    args = parser.parse_args()

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from mapless.config import load_config
    from mapless.train.config import TrainConfig
    from mapless.train.run import train

    config = load_config(TrainConfig, args.config, [*args.set, f"max_seconds={args.minutes * 60}"])
    args.out.mkdir(parents=True, exist_ok=True)
    run_dir = args.out / f"run_{time.strftime('%Y%m%d-%H%M%S')}"
    summary = train(config, run_dir)
    baseline, stderr = random_success(config, args.random_episodes)

    records = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    minutes = np.array([r["time"] - records[0]["time"] for r in records]) / 60 if records else np.zeros(0)
    success = np.array([r.get("charts/success", np.nan) for r in records])
    final = float(np.nanmean(success[-5:])) if len(success) else float("nan")

    fig, ax = plt.subplots(figsize=(7, 4))
    ax.plot(minutes, success, label=f"{config.model.name} ({config.mode}, B={config.batch_size})")
    ax.axhline(baseline, color="gray", linestyle="--", label=f"random ({baseline:.3f} ± {stderr:.3f})")
    ax.set_xlabel("wall-clock minutes (after start-up)")
    ax.set_ylabel(f"training success (mean of {config.log_every} episodes)")
    ax.set_title(f"learning check: {summary['episodes']:.0f} episodes, {summary['frames']:.0f} frames")
    ax.legend()
    fig.tight_layout()
    fig.savefig(args.out / "learning_check.png", dpi=120)

    result = {
        "model": config.model.name,
        "mode": config.mode,
        "minutes": args.minutes,
        "episodes": summary["episodes"],
        "frames": summary["frames"],
        "frames_per_s": summary["steady_frames_per_s"],
        "final_success": final,
        "random_success": baseline,
        "random_stderr": stderr,
        "beats_random_by": final - baseline,
        "curve": [{"minutes": float(m), "episodes": r["episodes"], "success": r.get("charts/success")}
                  for m, r in zip(minutes, records, strict=True)],
        "run_dir": str(run_dir),
    }  # fmt: skip
    (args.out / "learning_check.json").write_text(json.dumps(stamped(result, command_line()), indent=2))
    print(json.dumps({k: v for k, v in result.items() if k != "curve"}, indent=2))
    print(f"curve: {args.out / 'learning_check.png'}")


if __name__ == "__main__":
    main()
