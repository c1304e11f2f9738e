"""Training and evaluating on a SAVN/MJOLNIR-format offline data root instead of the built-in
simulator: the exported folder of a real floor plan goes through ``env.offline_dir`` and
``mapless eval --offline-dir`` end to end."""

from __future__ import annotations

import json
from pathlib import Path

from train_fixtures import tiny_config

from mapless.cli import main as cli_main
from mapless.episodes import Episode, evalsets
from mapless.offline import export_scene, offline_library
from mapless.sim.library import SceneLibrary
from mapless.train.run import train

SCENE = "FloorPlan425"


def test_train_and_evaluate_on_an_offline_root(tmp_path: Path, capsys) -> None:
    built = SceneLibrary.builtin()[SCENE]
    root = tmp_path / "offline"
    export_scene(built, root, "mjolnir")
    offline = offline_library(root)[SCENE]
    # Our own export carries a side file that restores the semantic maps exactly (real SAVN/MJOLNIR
    # roots give 512-channel ResNet maps and need model.feature_channels=512).
    assert offline.n_poses == built.n_poses and offline.features.shape == built.features.shape

    config = tiny_config(
        "a3c", "episodes=8", "checkpoint_every=8", f"env.offline_dir={root}", f"env.scenes={SCENE}"
    )  # fmt: skip
    run = tmp_path / "run"
    summary = train(config, run)
    assert summary["episodes"] == 8

    target = "Towel"
    pose = int(
        next(
            p
            for p in range(offline.n_poses)
            if offline.target_distances(target)[p] > 3 and offline.horizon[p] == 0
        )
    )
    episodes = [
        Episode(
            SCENE,
            target,
            offline.pose_tuple(pose),
            offline.optimal_length(pose, target),
            episode_id="x/bathroom/0",
        )
    ]
    episode_file = tmp_path / "eps.json.gz"
    evalsets.save(episode_file, episodes, "val", "mjolnir22", 0, "offline")
    out = tmp_path / "eval"
    code = cli_main(["eval", str(run), "--offline-dir", str(root), "--episodes", str(episode_file),
                     "--workers", "1", "--out", str(out)])  # fmt: skip
    assert code == 0, capsys.readouterr().err
    assert "1 episodes" in capsys.readouterr().out
    assert json.loads(next(out.glob("*.json")).read_text())
