"""Simulator benchmarks: scene build time, cached-scene load time, single and batched step rates.

    python bench/bench_sim.py            # quick: builds 4 scenes (one per room type), steps, loads
    python bench/bench_sim.py --all      # also builds all 120 scenes with 2 workers into a fresh cache

Targets (the results are in docs/results/speed.md): all 120 scenes < 15 min on 2 cores;
>= 100,000 single-env steps/s; >= 1,000,000 episode-steps/s batched at B=256; cached load < 0.2 s.
Every figure is printed with its ratio to the target, measured in this one run.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from mapless.episodes import Episode
from mapless.scenes.catalogue import scene_names
from mapless.scenes.layout import load_scene
from mapless.sim.build import build_scene_data
from mapless.sim.cache import build_many, cache_path, load, load_or_build
from mapless.sim.config import SimConfig
from mapless.sim.env import NavEnv
from mapless.sim.library import SceneLibrary
from mapless.sim.vector import BatchedNavEnv

SAMPLE = ["FloorPlan1", "FloorPlan201", "FloorPlan301", "FloorPlan401"]


def report(name: str, value: float, unit: str, target: float, higher_is_better: bool = True) -> None:
    ratio = value / target if higher_is_better else target / value
    verdict = "ok" if ratio >= 1 else "BELOW TARGET"
    print(f"{name:<44}{value:>14,.2f} {unit:<14} target {target:>12,.2f}  ratio {ratio:6.2f}x  {verdict}")


def bench_build(cache_dir: Path, all_scenes: bool) -> None:
    config = SimConfig()
    times = []
    for name in SAMPLE:
        start = time.perf_counter()
        build_scene_data(load_scene(name), config)
        times.append(time.perf_counter() - start)
    per_scene = float(np.mean(times))
    print(f"build, one process: {', '.join(f'{n} {t:.1f}s' for n, t in zip(SAMPLE, times, strict=True))}")
    report(
        "build 120 scenes, projected on 2 cores", 120 * per_scene / 2 / 60, "min", 15, higher_is_better=False
    )
    if all_scenes:
        start = time.perf_counter()
        build_many(scene_names("all"), config, cache_dir, workers=2, progress=True)
        report("build 120 scenes, measured, 2 workers", (time.perf_counter() - start) / 60, "min", 15, False)


def bench_load(cache_dir: Path) -> None:
    config = SimConfig()
    times = []
    for name in SAMPLE:
        load_or_build(name, config, cache_dir)
        start = time.perf_counter()
        load(cache_path(name, config, cache_dir), config)
        times.append(time.perf_counter() - start)
    report("load one cached scene (worst of 4)", max(times), "s", 0.2, higher_is_better=False)


def bench_steps(cache_dir: Path) -> None:
    library = SceneLibrary.builtin(SimConfig(), cache_dir)
    data = library["FloorPlan201"]
    starts = np.flatnonzero(data.horizon == 0)
    episodes = [Episode("FloorPlan201", "Laptop", data.pose_tuple(p)) for p in starts[:50]]
    env = NavEnv(library, episodes)
    env.reset(seed=0)
    actions = np.random.default_rng(0).integers(0, 6, 300_000).tolist()
    start = time.perf_counter()
    for action in actions:
        _, _, terminated, truncated, _ = env.step(action)
        if terminated or truncated:
            env.reset()
    # NavEnv plays a batched env of size 1 (one implementation of the task rules): ~20 µs of numpy
    # per step instead of the former dedicated loop's ~3 µs, against milliseconds per model step.
    report(
        "single env steps/s (gymnasium API)", len(actions) / (time.perf_counter() - start), "steps/s", 20_000
    )

    batch = 256
    env = BatchedNavEnv(library, ["FloorPlan201"], batch, max_steps=10**9)
    env.reset(np.arange(batch), [episodes[i % len(episodes)] for i in range(batch)])
    moves = np.random.default_rng(1).integers(0, 5, (2000, batch))
    start = time.perf_counter()
    for row in moves:
        env.step(row)
    report(
        "batched episode-steps/s, B=256", moves.size / (time.perf_counter() - start), "ep-steps/s", 1_000_000
    )
    start = time.perf_counter()
    for row in moves[:200]:
        env.step(row)
        env.observe(("context", "target_embedding", "target_index"))
    rate = moves[:200].size / (time.perf_counter() - start)
    report("batched + context observation, B=256", rate, "ep-steps/s", 1_000_000)
    start = time.perf_counter()
    for row in moves[:200]:
        env.step(row)
        env.observe()
    rate = moves[:200].size / (time.perf_counter() - start)
    print(f"{'batched + all observations (incl. feature map)':<44}{rate:>14,.0f} ep-steps/s (information)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--all", action="store_true", help="build all 120 scenes into a fresh cache")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="mapless-bench-") as tmp:
        cache_dir = Path(tmp)
        bench_build(cache_dir, args.all)
        bench_load(cache_dir)
        bench_steps(cache_dir)


if __name__ == "__main__":
    main()
