"""Live AI2-THOR backend against a fake controller with the documented Event surface."""

from __future__ import annotations

import math

import h5py
import numpy as np
import pytest
from offline_checks import assert_same_scene
from thor_fake import OBJECTS, REACHABLE, FakeController

from mapless.actions import MOVE_AHEAD, N_MOVEMENT_ACTIONS
from mapless.errors import MaplessError
from mapless.offline import load_offline_scene
from mapless.offline.format import parse_pose_key
from mapless.sim.config import SimConfig
from mapless.thor import LiveThorScene, ThorConfig, make_controller, scrape, scrape_scene

CONFIG = ThorConfig(SimConfig(visibility_distance=1.0))


@pytest.fixture(scope="module")
def scraped():
    controller = FakeController(visibilityDistance=CONFIG.sim.visibility_distance)
    return controller, scrape_scene(controller, "FloorPlan5", CONFIG)


def _expected_successor(key: str, action: int) -> tuple[float, float, int, int]:
    x, z, yaw, horizon = parse_pose_key(key)
    if action == MOVE_AHEAD:
        sx, sz = round(math.sin(math.radians(yaw))), round(math.cos(math.radians(yaw)))
        dest = (round(x + 0.25 * sx, 2), round(z + 0.25 * sz, 2))
        return (*dest, yaw, horizon) if dest in REACHABLE else (x, z, yaw, horizon)
    if action in (1, 2):
        return x, z, (yaw + (45 if action == 2 else -45)) % 360, horizon
    new = horizon + (30 if action == 4 else -30)
    return (x, z, yaw, new) if new in CONFIG.sim.horizons else (x, z, yaw, horizon)


def test_scrape_covers_every_pose_with_thor_semantics(scraped):
    controller, sd = scraped
    assert sd.n_poses == len(REACHABLE) * 8 * 2
    assert sd.instance_ids == tuple(o[0] for o in OBJECTS)
    for p in range(sd.n_poses):
        key = sd.key(p)
        for action in range(N_MOVEMENT_ACTIONS):
            assert parse_pose_key(sd.key(sd.successors[p, action])) == _expected_successor(key, action)
        pose = parse_pose_key(key)
        assert {sd.instance_ids[i] for i in sd.visible(p)} == controller.visible_ids(pose)
        projected = controller.project(pose)
        s = slice(sd.view_ptr[p], sd.view_ptr[p + 1])
        for i, box, distance in zip(sd.view_instance[s], sd.view_box[s], sd.view_distance[s], strict=True):
            x1, y1, x2, y2 = projected[sd.instance_ids[i]][0]
            assert box.tolist() == [x1, y1, x2 + 1, y2 + 1]
            assert distance == pytest.approx(projected[sd.instance_ids[i]][1], rel=1e-6)
    assert sd.visible_matrix_csr[0].size > 0  # the fake world does show objects
    n_cat = sd.context.shape[1]
    assert sd.features.shape == (sd.n_poses, n_cat + 3, 7, 7) and sd.features.dtype == np.uint8
    # Floor covers the bottom third, wall the top sixth of the fake frames; depth 2 m -> 51.
    assert sd.features[0, n_cat, 6].min() == 255 and sd.features[0, n_cat + 1, 0].min() == 255
    assert sd.features[0, n_cat + 2, 3, 3] == 51


@pytest.mark.parametrize("fmt", ["savn", "mjolnir"])
def test_scrape_writes_an_offline_folder(tmp_path, scraped, fmt):
    _, reference = scraped
    controller = FakeController(visibilityDistance=CONFIG.sim.visibility_distance)
    folder = scrape(controller, "FloorPlan5", tmp_path, fmt, CONFIG, images=True)
    assert folder.name == ("FloorPlan5_physics" if fmt == "savn" else "FloorPlan5")
    read = load_offline_scene(folder)
    assert_same_scene(reference, read)
    with h5py.File(folder / "images.hdf5") as f:
        assert len(f) == reference.n_poses and f[reference.key(0)].shape == (300, 300, 3)


def test_feature_extractor_hook(tmp_path):
    controller = FakeController()
    calls = []

    def extractor(frame: np.ndarray) -> np.ndarray:
        calls.append(frame.shape)
        return np.full((512, 7, 7), frame[0, 0, 0] / 10, dtype=np.float32)

    folder = scrape(controller, "FloorPlan5", tmp_path, "mjolnir", CONFIG, feature_extractor=extractor)
    read = load_offline_scene(folder)
    assert read.meta["feature_kind"] == "resnet18" and read.features.shape[1:] == (512, 7, 7)
    assert len(calls) == read.n_poses
    yaws = read.yaw.astype(np.float32)
    np.testing.assert_allclose(read.features[:, 0, 0, 0], (yaws % 256) / 10, rtol=1e-6)


def test_live_scene_follows_the_scraped_graph(scraped):
    _, sd = scraped
    live = LiveThorScene(FakeController(visibilityDistance=CONFIG.sim.visibility_distance), CONFIG)
    obs = live.reset("FloorPlan5", start="0.00|0.25|0|0")
    p = sd.pose_index["0.00|0.25|0|0"]
    rng = np.random.default_rng(1)
    for _ in range(60):
        assert obs["pose"] == sd.key(p)
        np.testing.assert_allclose(obs["context"], sd.context[p], atol=1e-6)
        np.testing.assert_allclose(obs["features"], sd.features[p] * np.float32(sd.feature_scale), atol=1e-6)
        assert set(obs["visible_ids"]) == {sd.instance_ids[i] for i in sd.visible(p)}
        action = int(rng.integers(0, 6))
        obs, moved = live.step(action)
        if action < N_MOVEMENT_ACTIONS:
            assert moved == (sd.successors[p, action] != p)
            p = int(sd.successors[p, action])
        else:
            assert not moved


def test_live_scene_errors():
    live = LiveThorScene(FakeController(), CONFIG)
    with pytest.raises(MaplessError, match="before reset"):
        live.step(0)
    with pytest.raises(MaplessError, match="not reachable"):
        live.reset("FloorPlan5", start="5.00|5.00|0|0")


def test_controller_settings_and_missing_ai2thor():
    kwargs = ThorConfig(SimConfig(visibility_distance=1.5), extra={"commit_id": "abc"}).controller_kwargs()
    assert kwargs["gridSize"] == 0.25 and kwargs["rotateStepDegrees"] == 45
    assert kwargs["renderInstanceSegmentation"] and kwargs["width"] == kwargs["height"] == 300
    assert kwargs["fieldOfView"] == 90.0 and kwargs["renderDepthImage"]
    assert kwargs["visibilityDistance"] == 1.5 and kwargs["commit_id"] == "abc"
    try:
        import ai2thor  # noqa: F401
    except ImportError:
        with pytest.raises(MaplessError, match=r"mapless\[thor\]"):
            make_controller("FloorPlan1")
    # Frames are square by construction (SimConfig.image_size); a step with no grid neighbour fails.
    with pytest.raises(MaplessError, match="rotation_step"):
        ThorConfig(SimConfig(rotation_step=30))


def test_cli_scrape(tmp_path, monkeypatch, capsys):
    import argparse

    import mapless.thor
    from mapless.cli import interop

    made = []

    def fake_make_controller(scene, config):
        made.append(config)
        return FakeController(scene, visibilityDistance=config.sim.visibility_distance)

    monkeypatch.setattr(mapless.thor, "make_controller", fake_make_controller)
    parser = argparse.ArgumentParser()
    interop.register(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(
        [
            "thor",
            "scrape",
            "FloorPlan5,FloorPlan301",
            "--out",
            str(tmp_path),
            "--format",
            "mjolnir",
            "--sim",
            "visibility_distance=1.5",
            "--sim",
            "horizontal_fov=80",
            "--platform",
            "CloudRendering",
        ]
    )
    assert args.func(args) == 0
    assert made[0].sim.visibility_distance == 1.5 and made[0].sim.horizontal_fov == 80.0
    assert made[0].platform == "CloudRendering"
    assert load_offline_scene(tmp_path / "FloorPlan301").room_type == "bedroom"
    assert "FloorPlan5: scraped" in capsys.readouterr().out
    # The old spellings still work, each with a note naming the --sim setting it stands for.
    old = ["--visibility-distance", "1.5", "--horizons", "0,x", "--field-of-view", "80"]
    args = parser.parse_args(["thor", "scrape", "FloorPlan5", "--out", str(tmp_path), *old])
    notes = capsys.readouterr().err.splitlines()
    assert notes == [
        "mapless: note: --visibility-distance is deprecated; write --sim visibility_distance=1.5",
        "mapless: note: --horizons is deprecated; write --sim horizons=[0,x]",
        "mapless: note: --field-of-view is deprecated; write --sim horizontal_fov=80",
    ]
    with pytest.raises(MaplessError, match=r"horizons\[1\]': expected int, got 'x'"):
        args.func(args)
