"""SAVN/MJOLNIR offline scene folders: round trip, format details, bad input."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest
from offline_checks import assert_same_scene
from scene_fixtures import grid_scene

from mapless.actions import LOOK_DOWN, LOOK_UP, MOVE_AHEAD, ROTATE_LEFT, ROTATE_RIGHT
from mapless.errors import MaplessError
from mapless.offline import OfflineFormatError, export_scene, load_offline_scene, scene_folder_name
from mapless.offline.format import guess_next_keys


@pytest.fixture(scope="module")
def scene():
    return grid_scene()


@pytest.mark.parametrize("fmt", ["savn", "mjolnir"])
def test_round_trip_hand_made(scene, tmp_path, fmt):
    folder = export_scene(scene, tmp_path, fmt)
    read = load_offline_scene(folder)
    assert_same_scene(scene, read)
    assert (read.scene, read.room_type) == ("FloorPlan5", "kitchen")
    assert read.meta["feature_kind"] == "semantic" and read.meta["has_boxes"]


def test_round_trip_other_grids(tmp_path):
    # Negative coordinates, 90 degree turns, three horizons, no blocked move.
    positions = ((-0.5, -0.25), (-0.25, -0.25), (-0.25, 0.0), (0.0, 0.0))
    sd = grid_scene(
        positions=positions,
        horizons=(-30, 0, 30),
        rotation_step=90,
        blocked=(),
        seed=3,
        scene="FloorPlan301",
        room_type="bedroom",
    )
    folder = export_scene(sd, tmp_path, "savn")
    assert folder.name == "FloorPlan301"
    assert_same_scene(sd, load_offline_scene(folder))


def test_files_as_the_originals_read_them(scene, tmp_path):
    savn = export_scene(scene, tmp_path / "savn", "savn")
    mjolnir = export_scene(scene, tmp_path / "mjolnir", "mjolnir")
    assert savn.name == "FloorPlan5_physics" and mjolnir.name == "FloorPlan5"
    graph = json.loads((savn / "graph.json").read_text())
    assert graph["directed"] and "links" in graph and "edges" not in graph
    keys = {n["id"] for n in graph["nodes"]}
    assert keys == {scene.key(p) for p in range(scene.n_poses)}
    assert "0.25|0.25|45|30" in keys
    with (
        h5py.File(savn / "resnet18_featuremap.hdf5") as f_savn,
        h5py.File(mjolnir / "resnet18_featuremap.hdf5") as f_mj,
    ):
        key = scene.key(7)
        assert f_savn[key].shape == (1, 512, 7, 7) and f_savn[key].dtype == np.float32
        assert f_mj[key].shape == (512, 7, 7)
        values = f_mj[key][()]
        channels = scene.features.shape[1]
        np.testing.assert_allclose(values[:channels], scene.features[7] / 255.0, rtol=1e-6)
        assert not values[channels:].any()
    grid = json.loads((savn / "grid.json").read_text())
    assert {(g["x"], g["z"]) for g in grid} == {(0.0, 0.0), (0.25, 0.0), (0.0, 0.25), (0.25, 0.25)}
    boxes = json.loads((mjolnir / "objects_bb.json").read_text())
    assert set(boxes) == keys  # MJOLNIR looks every pose up
    with_tables = [k for k, v in boxes.items() if "DiningTable" in v]
    assert with_tables and all("TableTop" in boxes[k] for k in with_tables)
    savn_boxes = json.loads((savn / "objects_bb.json").read_text())
    assert not any("TableTop" in v for v in savn_boxes.values())
    visible = json.loads((savn / "visible_object_map.json").read_text())
    assert "Apple|+00.00|+00.80|+01.00" not in visible  # never visible: not a target


def test_networkx_reads_graph(scene, tmp_path):
    import networkx as nx  # a dependency of torch, so always installed

    folder = export_scene(scene, tmp_path, "savn")
    data = json.loads((folder / "graph.json").read_text())
    try:
        graph = nx.node_link_graph(data, edges="links").to_directed()
    except TypeError:  # networkx < 3.4 only knows "links"
        graph = nx.node_link_graph(data).to_directed()
    for p in range(scene.n_poses):
        out = {scene.key(int(q)) for q in scene.successors[p] if q != p}
        assert set(graph.successors(scene.key(p))) == out


def test_savn_folder_without_boxes(scene, tmp_path):
    folder = export_scene(scene, tmp_path, "savn")
    (folder / "objects_bb.json").unlink()
    (folder / "mapless.json").unlink()
    read = load_offline_scene(folder)
    assert not read.meta["has_boxes"] and read.meta["feature_kind"] == "resnet18"
    assert read.features.shape == (scene.n_poses, 512, 7, 7) and read.features.dtype == np.float32
    for p in range(scene.n_poses):
        ids = {read.instance_ids[i] for i in read.in_view(p)}
        assert ids == {scene.instance_ids[i] for i in scene.visible(p)}
    np.testing.assert_array_equal(read.target_distances("Mug"), scene.target_distances("Mug"))
    assert load_offline_scene(folder, features="none").features.shape == (scene.n_poses, 0, 7, 7)
    assert load_offline_scene(folder, feature_dtype="float16").features.dtype == np.float16


def test_guess_rule():
    assert guess_next_keys("0.25|1.00|45|0", MOVE_AHEAD) == ("0.50|1.25|45|0",)
    assert guess_next_keys("0.25|1.00|225|0", MOVE_AHEAD) == ("0.00|0.75|225|0",)
    assert guess_next_keys("-0.00|1.00|0|0", MOVE_AHEAD) == ("-0.00|1.25|0|0",)  # as the original
    assert guess_next_keys("0.25|1.00|0|0", ROTATE_LEFT) == ("0.25|1.00|315|0",)
    assert guess_next_keys("0.25|1.00|315|0", ROTATE_RIGHT) == ("0.25|1.00|0|0",)
    assert guess_next_keys("0.25|1.00|0|0", LOOK_UP) == ("0.25|1.00|0|-30", "0.25|1.00|0|330")
    assert guess_next_keys("0.25|1.00|0|330", LOOK_DOWN) == ("0.25|1.00|0|0",)


def _write_folder(folder, nodes, links, visible, features=None, directed=True, edge_key="links"):
    folder.mkdir(parents=True, exist_ok=True)
    graph = {
        "directed": directed,
        "multigraph": False,
        "graph": {},
        "nodes": [{"id": n} for n in nodes],
        edge_key: [{"source": s, "target": t} for s, t in links],
    }
    (folder / "graph.json").write_text(json.dumps(graph))
    (folder / "grid.json").write_text(json.dumps([{"x": 0.0, "y": 0.91, "z": 0.0}]))
    (folder / "visible_object_map.json").write_text(json.dumps(visible))
    with h5py.File(folder / "resnet18_featuremap.hdf5", "w") as f:
        for n in features if features is not None else nodes:
            f.create_dataset(n, data=np.ones((512, 7, 7), np.float32))


def test_reads_original_style_folder(tmp_path):
    # Undirected file (the originals call .to_directed()), 'edges' key of newer networkx,
    # horizon spelled 330, a '-0.00' coordinate, a pose-keyed metadata.json for visibility.
    nodes = ["-0.00|0.00|0|0", "-0.00|0.25|0|0", "-0.00|0.00|45|0", "-0.00|0.00|0|30", "-0.00|0.00|0|330"]
    links = [(nodes[0], nodes[1]), (nodes[0], nodes[2]), (nodes[0], nodes[3]), (nodes[0], nodes[4])]
    folder = tmp_path / "FloorPlan22_physics"
    _write_folder(folder, nodes, links, {}, directed=False, edge_key="edges")
    metadata = {
        n: {"objects": [{"objectId": "Box|+00.10|+00.00|+01.00", "visible": n == nodes[1]}]} for n in nodes
    }
    (folder / "metadata.json").write_text(json.dumps(metadata))
    sd = load_offline_scene(folder, visible_file="metadata.json")
    assert (sd.scene, sd.room_type, sd.meta["agent_y"]) == ("FloorPlan22", "kitchen", 0.91)
    assert [sd.key(p) for p in range(sd.n_poses)] == nodes
    assert sd.successors[0].tolist() == [1, 0, 2, 4, 3]
    # Undirected: MoveAhead from (0, 0.25) at yaw 0 would go to z=0.50, not back: only the reverse
    # rotation / look edges are real actions.
    assert sd.successors[1].tolist() == [1, 1, 1, 1, 1]
    assert sd.successors[2, ROTATE_LEFT] == 0 and sd.successors[3, LOOK_UP] == 0
    assert sd.successors[4, LOOK_DOWN] == 0
    assert sd.optimal_length(0, "Box") == 2  # MoveAhead + Done


def _good_folder(tmp_path):
    folder = tmp_path / "FloorPlan1"
    nodes = ["0.00|0.00|0|0", "0.00|0.25|0|0"]
    _write_folder(folder, nodes, [(nodes[0], nodes[1])], {"Box|+00.10|+00.00|+01.00": [nodes[1]]})
    return folder, nodes


@pytest.mark.parametrize(
    ("damage", "expected"),
    [
        (lambda f: (f / "graph.json").unlink(), "graph.json: missing"),
        (lambda f: (f / "grid.json").write_text('[{"x": 0,'), "grid.json: malformed JSON"),
        (lambda f: (f / "visible_object_map.json").write_text("[1, 2]"), "visible_object_map.json: expected"),
        (
            lambda f: (f / "graph.json").write_text('{"nodes": [{"id": "a|b"}], "links": []}'),
            "graph.json: node 0: pose key 'a|b'",
        ),
        (lambda f: (f / "graph.json").write_text('{"nodes": []}'), "no 'links' or 'edges'"),
        (lambda f: (f / "resnet18_featuremap.hdf5").write_bytes(b"not hdf5"), "not a readable HDF5"),
        (lambda f: (f / "resnet18_featuremap.hdf5").unlink(), "resnet18_featuremap.hdf5: missing"),
    ],
)
def test_bad_folders(tmp_path, damage, expected):
    folder, _ = _good_folder(tmp_path)
    load_offline_scene(folder)
    damage(folder)
    with pytest.raises(OfflineFormatError, match=expected.replace("(", r"\(").replace("[", r"\[")) as info:
        load_offline_scene(folder)
    assert str(folder) in str(info.value)


def test_pose_without_features_fails_at_load(tmp_path):
    folder = tmp_path / "FloorPlan1"
    nodes = ["0.00|0.00|0|0", "0.00|0.25|0|0"]
    _write_folder(folder, nodes, [(nodes[0], nodes[1])], {}, features=nodes[:1])
    with pytest.raises(
        OfflineFormatError, match=r"1 of the 2 poses of graph.json have no feature map.*0.00\|0.25"
    ):
        load_offline_scene(folder)
    with h5py.File(folder / "resnet18_featuremap.hdf5", "a") as f:
        f.create_dataset(nodes[1], data=np.ones((3, 7, 7), np.float32))
    with pytest.raises(OfflineFormatError, match="has shape"):
        load_offline_scene(folder)


def test_export_refuses_non_savn_transitions(scene, tmp_path):
    broken = grid_scene()
    broken.successors[0, MOVE_AHEAD] = 9  # not the pose one grid step ahead
    with pytest.raises(MaplessError, match="do not follow the SAVN geometric rule"):
        export_scene(broken, tmp_path, "savn")
    with pytest.raises(MaplessError, match="unknown offline format"):
        export_scene(scene, tmp_path, "habitat")


def test_folder_names():
    assert scene_folder_name("FloorPlan28", "savn") == "FloorPlan28_physics"
    assert scene_folder_name("FloorPlan228_physics", "savn") == "FloorPlan228_physics"
    assert scene_folder_name("FloorPlan328", "savn") == "FloorPlan328"
    assert scene_folder_name("FloorPlan28_physics", "mjolnir") == "FloorPlan28"


@pytest.fixture(scope="module")
def built_scenes():
    from mapless.scenes import load_scene
    from mapless.sim.build import build_scene_data
    from mapless.sim.config import SimConfig

    # The three smallest floor plans of three room types keep this under ~10 s.
    return [
        build_scene_data(load_scene(name), SimConfig())
        for name in ("FloorPlan420", "FloorPlan316", "FloorPlan25")
    ]


@pytest.mark.slow
def test_round_trip_built_in_scenes(built_scenes, tmp_path):
    for sd, fmt in zip(built_scenes, ("savn", "mjolnir", "savn"), strict=True):
        folder = export_scene(sd, tmp_path, fmt)
        read = load_offline_scene(folder)
        assert_same_scene(sd, read)
        assert read.meta["unattributed_types"] or read.instance_ids  # in-view-only boxes kept per type
        targets = {sd.instance_types[i] for i in sd.visible_matrix_csr[1]}
        for target in sorted(targets)[:5]:
            start = int(np.argmax(sd.target_distances(target)))
            assert read.optimal_length(read.pose_index[sd.key(start)], target) == sd.optimal_length(
                start, target
            )


@pytest.mark.slow
def test_cli_export_and_check(built_scenes, tmp_path, monkeypatch, capsys):
    import argparse

    from mapless.cli import interop
    from mapless.sim import cache

    sd = built_scenes[0]
    monkeypatch.setattr(cache, "load_or_build", lambda name, config, cache_dir=None: sd)
    parser = argparse.ArgumentParser()
    interop.register(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(["export", "FloorPlan420", "--format", "mjolnir", "--out", str(tmp_path)])
    assert args.func(args) == 0
    args = parser.parse_args(["interop", "check", str(tmp_path)])
    assert args.func(args) == 0
    out = capsys.readouterr().out
    assert f"FloorPlan420 (bathroom), {sd.n_poses} poses" in out and "features (104, 7, 7) semantic" in out
    (tmp_path / "empty").mkdir()
    args = parser.parse_args(["interop", "check", str(tmp_path / "empty")])
    with pytest.raises(MaplessError, match=r"no graph\.json"):
        args.func(args)


def test_offline_loader_finds_either_naming(scene, tmp_path):
    from mapless.offline import find_scene_folder, offline_loader

    export_scene(scene, tmp_path, "savn")  # FloorPlan5_physics
    assert find_scene_folder(tmp_path, "FloorPlan5").name == "FloorPlan5_physics"
    assert offline_loader(tmp_path, features="none")("FloorPlan5_physics").n_poses == scene.n_poses
    with pytest.raises(MaplessError, match="FloorPlan5_physics"):
        find_scene_folder(tmp_path, "FloorPlan6")
