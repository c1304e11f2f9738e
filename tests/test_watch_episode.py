"""Watching an episode: ``mapless eval ... --render N --out DIR`` draws N episodes as a top-down PNG of
the trajectory and a GIF of its steps (agent, view cone, target, sightings, Done)."""

from __future__ import annotations

import dataclasses
import itertools
import json

import numpy as np
import pytest
from PIL import Image

from mapless.cli import main
from mapless.config import from_dict
from mapless.episodes import evalsets
from mapless.episodes.sampler import TrainingSampler
from mapless.evaluate.figures import steps_gif
from mapless.evaluate.metrics import EpisodeResult
from mapless.sim.cache import fingerprint
from mapless.sim.config import SimConfig
from mapless.sim.library import SceneLibrary
from mapless.sim.scene_data import pose_key
from mapless.train.config import TrainConfig
from mapless.train.run import train

SCENE = "FloorPlan1"


@pytest.fixture(scope="module")
def episode_file(tmp_path_factory) -> str:
    """Three training draws in one kitchen, with their optimal lengths, as an episode file."""
    library = SceneLibrary.builtin()
    sampler, rng, episodes = (
        TrainingSampler(library, [SCENE], "mjolnir22", seed=0),
        np.random.default_rng(0),
        [],
    )
    for i in range(3):
        episode = sampler.sample(rng)
        data = library[episode.scene]
        distance = int(data.target_distances(episode.target)[data.pose_index[pose_key(*episode.start)]])
        episodes.append(dataclasses.replace(episode, optimal_length=distance + 1, episode_id=f"watch/{i}"))
    path = tmp_path_factory.mktemp("episodes") / "watch.json.gz"
    evalsets.save(path, episodes, "val", "mjolnir22", 0, fingerprint(SimConfig()))
    return str(path)


def _gif_frames(path) -> int:
    with Image.open(path) as image:
        assert image.format == "GIF"
        return image.n_frames


def _png_size(path) -> tuple[int, int]:
    with Image.open(path) as image:
        assert image.format == "PNG"
        image.load()  # a truncated file fails here
        return image.size


@pytest.mark.slow
def test_eval_render_draws_the_first_n_episodes_of_the_oracle(tmp_path, episode_file) -> None:
    out = tmp_path / "eval"
    argv = [
        "eval",
        "oracle",
        "--episodes",
        episode_file,
        "--workers",
        "1",
        "--render",
        "2",
        "--out",
        str(out),
    ]
    assert main(argv) == 0
    results = json.loads((out / "watch.json").read_text())["episodes"][0]  # one seed
    drawn = sorted((out / "render").iterdir())
    expected = [f"{r['index']:04d}_{r['scene']}_{r['target']}" for r in results[:2]]
    assert [p.name for p in drawn] == sorted(f"{stem}.{ext}" for stem in expected for ext in ("gif", "png"))
    for result, stem in zip(results[:2], expected, strict=True):
        width, height = _png_size(out / "render" / f"{stem}.png")
        assert width > 200 and height > 200
        # The oracle walks the optimal path and stops: the start, then one frame per action.
        assert result["success"] and result["length"] == result["optimal_length"]
        assert _gif_frames(out / "render" / f"{stem}.gif") == result["length"] + 1 > 1


@pytest.mark.slow  # trains a run first
def test_eval_render_draws_a_trained_runs_episode(tmp_path, episode_file) -> None:
    run = tmp_path / "run"
    model = {"name": "a3c", "hidden_size": 16, "dropout": 0.0}
    config = {"model": model, "env": {"scenes": SCENE, "max_steps": 8}, "a3c": {"batch_size": 4}}
    train(from_dict(TrainConfig, {**config, "episodes": 4, "threads": 1, "progress": False}), run)
    out = tmp_path / "eval"
    argv = [
        "eval",
        str(run),
        "--episodes",
        episode_file,
        "--workers",
        "1",
        "--render",
        "1",
        "--out",
        str(out),
    ]
    assert main(argv) == 0
    (first, *_) = json.loads((out / "watch.json").read_text())["episodes"][0]  # one seed
    stem = out / "render" / f"0000_{first['scene']}_{first['target']}"
    _png_size(stem.with_suffix(".png"))
    assert _gif_frames(stem.with_suffix(".gif")) == first["length"] + 1 > 1
    assert len(list((out / "render").iterdir())) == 2  # one episode: --render 1


def test_the_steps_gif_marks_sightings_and_how_the_episode_ended(tmp_path) -> None:
    """One frame per pose, each different from the one before: the agent turns, turns back (the
    sighting and the trail change) and stops (the Done)."""
    library = SceneLibrary.builtin()
    data = library[SCENE]
    seen = np.flatnonzero(data.goal_mask("Fridge") & (data.horizon == 0))
    end = int(seen[0])
    # Two rotations in place at a pose that sees the fridge, then Done: a successful three-step episode.
    left = int(data.successors[end, 1])
    right_back = int(data.successors[left, 2])
    assert right_back == end
    result = EpisodeResult(
        index=0, episode_id="x", scene=SCENE, room_type="kitchen", target="Fridge", success=True,
        length=3, optimal_length=1, called_done=True, failed_actions=0, reward=5.0, start_pose=end,
        poses=(left, end, end), actions=(1, 2, 5),
    )  # fmt: skip
    path = tmp_path / "steps.gif"
    assert steps_gif(result, library, path) == 4
    frames = []
    with Image.open(path) as image:
        for i in range(image.n_frames):
            image.seek(i)
            frames.append(np.asarray(image.convert("RGB"), dtype=np.int16))
    assert len(frames) == 4 and image.info["loop"] == 0
    # The rotation back and the Done change the picture; the start and the pose after it differ too.
    assert all(np.abs(a - b).sum() > 0 for a, b in itertools.pairwise(frames))
