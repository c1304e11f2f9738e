"""Training on scene variants (``env.layouts``: validated, the sampler's mix) and the layout-shift
evaluation: shifted episode sets bit for bit, and ``mapless reproduce layout_shift`` end to end on
tiny settings (one training floor plan, coarse rays)."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
from test_eval_reproduce import make_episodes

from mapless.cli import main
from mapless.config import ConfigError, load_config
from mapless.episodes import evalsets
from mapless.episodes.sampler import TrainingSampler
from mapless.experiments import load_experiment, planned_runs
from mapless.scenes.catalogue import room_type_of, split_of
from mapless.sim.cache import fingerprint
from mapless.sim.config import SimConfig
from mapless.sim.library import SceneLibrary
from mapless.train.config import TrainConfig

FAST = SimConfig(ray_resolution=14)
pytestmark = pytest.mark.usefixtures("single_torch_thread")


@pytest.fixture(scope="module")
def cache_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("layouts")
    previous = os.environ.get("MAPLESS_CACHE")
    os.environ["MAPLESS_CACHE"] = str(root / "cache")  # spawned evaluation workers inherit it
    yield root
    if previous is None:
        os.environ.pop("MAPLESS_CACHE", None)
    else:
        os.environ["MAPLESS_CACHE"] = previous


@pytest.mark.parametrize(
    "layouts, message",
    [
        ("{fraction: 0.5}", "must be 0 with source default"),
        ("{source: gen}", r"in \(0, 1\]"),
        ("{source: gen, fraction: 1.5}", r"in \(0, 1\]"),
        ("{source: nowhere.pkl.gz, fraction: 0.5}", "neither default"),
        ("{source: gen, fraction: 0.5, per_scene: 0}", "must be >= 1"),
    ],
)
def test_layouts_are_validated_before_any_work(layouts, message):
    with pytest.raises(ConfigError, match=message):
        load_config(TrainConfig, overrides=["episodes=8", f"env.layouts={layouts}"])


def test_layouts_list_each_floor_plans_variants():
    config = load_config(
        TrainConfig,
        overrides=[
            "episodes=8",
            "env.scenes=FloorPlan1,FloorPlan26",
            "env.layouts={source: gen, fraction: 0.5}",
        ],
    )
    assert config.env.variant_map() == {
        "FloorPlan1": ["FloorPlan1@gen:0", "FloorPlan1@gen:1"],
        "FloorPlan26": ["FloorPlan26@gen:0", "FloorPlan26@gen:1"],
    }
    assert config.env.all_scenes()[:2] == ["FloorPlan1", "FloorPlan26"] and len(config.env.all_scenes()) == 6
    rearranged = load_config(
        TrainConfig,
        overrides=[
            "episodes=8",
            "env.scenes=FloorPlan1",
            "env.layouts={source: rearrange2023, fraction: 1, per_scene: 3}",
        ],
    )
    assert rearranged.env.variant_map() == {
        "FloorPlan1": [f"FloorPlan1@rearrange2023:{i}" for i in (0, 1, 2)]
    }
    with pytest.raises(ConfigError, match="has no arrangement of FloorPlan26"):
        load_config(
            TrainConfig,
            overrides=[
                "episodes=8",
                "env.scenes=FloorPlan26",
                "env.layouts={source: rearrange2023, fraction: 1}",
            ],
        ).env.variant_map()
    assert (
        load_config(TrainConfig, overrides=["episodes=8"]).env.variant_map() == {}
    )  # the paper's protocol: default arrangements


@pytest.mark.slow
def test_the_sampler_mixes_variants_in_and_draws_as_before_without_them(cache_root):
    library = SceneLibrary.builtin(FAST)
    scenes, variants = ["FloorPlan425"], {"FloorPlan425": ["FloorPlan425@gen:0", "FloorPlan425@gen:1"]}

    def draw(**kwargs) -> list:
        sampler = TrainingSampler(library, scenes, seed=0, **kwargs)
        rng = np.random.default_rng(5)
        return [sampler.sample(rng) for _ in range(200)]

    plain = draw()
    assert draw(variants=variants, variant_fraction=0.0) == plain  # bit for bit the default protocol
    assert {e.scene for e in draw(variants=variants, variant_fraction=1.0)} == set(variants["FloorPlan425"])
    mixed = [e.scene for e in draw(variants=variants, variant_fraction=0.5)]
    assert 0.35 < np.mean([s != "FloorPlan425" for s in mixed]) < 0.65


@pytest.mark.slow
def test_a_shifted_set_is_made_on_variants_bit_for_bit(cache_root):
    library = SceneLibrary.builtin(FAST)

    def make() -> list:
        return evalsets.make_eval_set(library, "test", per_room=3, room_types=("bathroom",), layouts="gen:2")

    first = make()
    assert {e.scene.partition("@")[2] for e in first} <= {"gen:0", "gen:1"}
    assert all(split_of(e.scene) == "test" and room_type_of(e.scene) == "bathroom" for e in first)
    for e in first:  # the optimal length is the variant's own shortest path
        data = library[e.scene]
        assert e.optimal_length == data.target_distances(e.target)[library.pose_of(e.scene, e.start)] + 1
    fp = fingerprint(FAST)
    blob = evalsets.dumps(first, "test", "mjolnir22", 0, fp, "gen:2")
    assert blob == evalsets.dumps(make(), "test", "mjolnir22", 0, fp, "gen:2")
    assert evalsets.builtin_path("test", layouts="gen:3").name == "test_gen3_mjolnir22.json.gz"


def test_planned_runs_of_the_layout_shift_configs():
    assert planned_runs(load_experiment("layout_shift", "small")) == {
        "a3c": 2,
        "mjolnir_o": 2,
        "cvmeta": 2,
        "mlp": 2,
    }
    assert planned_runs(load_experiment("layout_shift", "smoke", seeds=2)) == {"a3c": 4, "cvmeta": 4}


@pytest.mark.slow
def test_reproduce_layout_shift_end_to_end(cache_root, capsys):
    root = cache_root
    library = SceneLibrary.builtin(FAST)
    fp = fingerprint(FAST)
    files = {
        "val": (make_episodes(library, "FloorPlan21", 4, 0), "val"),
        "test": (make_episodes(library, "FloorPlan26", 4, 1), "test"),
        "shift": (make_episodes(library, "FloorPlan26@gen:0", 4, 2), "test"),
    }
    for name, (episodes, split) in files.items():
        evalsets.save(root / f"{name}.json.gz", episodes, split, "mjolnir22", 0, fp)
    config = root / "layout_shift.yaml"
    config.write_text(
        f"""experiment: layout_shift
models: [random, a3c]
focus: a3c
runs_dir: {root / "runs"}
variant_layouts: {{source: gen, fraction: 1.0, per_scene: 1}}
train:
  episodes: 8
  a3c: {{batch_size: 4}}
  checkpoint_every: 8
  log_every: 8
  progress: false
  model: {{hidden_size: 32}}
  env: {{scenes: FloorPlan1, sim: {{ray_resolution: 14}}}}
eval:
  per_room: 4
  rooms: [kitchen]
  select_file: {root / "val.json.gz"}
  report_file: {root / "test.json.gz"}
  shift_file: {root / "shift.json.gz"}
  batch_size: 4
  workers: 1
"""
    )
    reports = root / "reports"
    command = ["reproduce", "layout_shift", "--config", str(config), "--reports", str(reports), "--jobs", "1"]
    assert main(command) == 0
    out = capsys.readouterr().out
    # Table 1's run ("all"), then the one on scene variants ("layouts").
    assert "[run 1 of 2] a3c all, seed 1" in out and "[run 2 of 2] a3c layouts, seed 1" in out
    payload = json.loads((reports / "layout_shift" / "layout_shift.json").read_text())
    labels = [m["model"] for m in payload["models"]]
    assert labels == [
        "random | default | default", "random | default | shifted",
        "a3c | default | default", "a3c | default | shifted",
        "a3c | variants | default", "a3c | variants | shifted",
    ]  # fmt: skip
    shifted = next(m for m in payload["models"] if m["model"] == "a3c | variants | shifted")
    assert {e["scene"] for e in shifted["episodes"][0]} == {"FloorPlan26@gen:0"}
    assert "a3c__layouts__" in shifted["runs"][0]["run_dir"]
    # Each trained row's shifted results are kept beside its other evaluations, for the next reproduce.
    for row in ("all", "layouts"):
        (kept,) = (root / "runs").glob(f"a3c__{row}__*/eval/shifted_*.json")
        assert len(json.loads(kept.read_text())["episodes"]) == 4
    comparisons = {(d["comparison"], d["test_on"]) for d in payload["variants_minus_default"]}
    assert comparisons == {("a3c", "default"), ("a3c", "shifted")}
    focus = {(d["comparison"], d["test_on"]) for d in payload["focus_minus_model"]}
    assert ("a3c − random (default)", "shifted") in focus
    diff = payload["variants_minus_default"][1]["success"]
    assert diff["ci_low"] <= diff["mean"] <= diff["ci_high"]
    report = (reports / "layout_shift" / "layout_shift.md").read_text()
    assert "does its advantage grow or vanish" in report
    assert "| model | trained on | tested on | SR |" in report and "| a3c | variants | shifted | " in report
