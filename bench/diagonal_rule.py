"""The strict diagonal-move rule against SAVN's (the default): how many diagonal MoveAhead transitions
it removes and how it changes the optimal lengths of the built-in evaluation episodes.

    python bench/diagonal_rule.py [--scenes all] [--splits val,test]

Only the successor table is rebuilt under the strict rule (no ray casting); visibility comes from
the default scene cache, which the rule does not change.
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np

from mapless.episodes import evalsets
from mapless.scenes.catalogue import resolve_scenes
from mapless.scenes.layout import load_scene
from mapless.sim.build import build_transitions
from mapless.sim.config import SimConfig
from mapless.sim.library import SceneLibrary
from mapless.sim.scene_data import MOVE_AHEAD


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", default="all")
    parser.add_argument("--splits", default="val,test")
    args = parser.parse_args()
    start = time.perf_counter()
    library = SceneLibrary.builtin(SimConfig())
    strict_config = SimConfig(strict_diagonals=True)
    strict: dict[str, object] = {}
    diagonal = removed = 0
    for name in resolve_scenes(args.scenes):
        data = library[name]
        successors = build_transitions(load_scene(name), strict_config)
        moves = data.successors[:, MOVE_AHEAD] != np.arange(data.n_poses)
        diagonals = moves & (data.yaw % 90 != 0)
        diagonal += int(diagonals.sum())
        removed += int((diagonals & (successors[:, MOVE_AHEAD] == np.arange(data.n_poses))).sum())
        strict[name] = dataclasses.replace(data, successors=successors, _distance_cache={})
    print(
        f"diagonal MoveAhead transitions: {diagonal}; the strict rule removes {removed} ({removed / diagonal:.1%})"
    )
    for split in args.splits.split(","):
        episodes, _ = evalsets.load(evalsets.builtin_path(split))
        before, after = [], []
        for e in episodes:
            if e.scene not in strict:
                continue
            pose = library.pose_of(e.scene, e.start)
            before.append(e.optimal_length)
            after.append(strict[e.scene].optimal_length(pose, e.target))
        b, a = np.array(before), np.array(after)
        reachable = a > 0
        ratio = a[reachable] / b[reachable]
        print(
            f"{split}: {len(b)} episodes; longer under the strict rule {np.mean(a > b):.1%}, unreachable "
            f"{np.sum(~reachable)}; length ratio mean {ratio.mean():.3f}, max {ratio.max():.2f}; "
            f"L>=5 share {np.mean(b >= 5):.1%} -> {np.mean(a[reachable] >= 5):.1%}"
        )
    print(f"{time.perf_counter() - start:.0f} s")


if __name__ == "__main__":
    main()
