"""Checkpoint selection rule and the fixed episode sets as the evaluator loads them."""

from __future__ import annotations

import json
import os
from dataclasses import replace

import numpy as np
import pytest
from eval_fixtures import fixture_episodes, fixture_library
from train_fixtures import fixture_library as training_scenes
from train_fixtures import tiny_config

from mapless.checkpoint import load_file, training_clock, training_log
from mapless.cli import main
from mapless.episodes.protocols import PROTOCOLS
from mapless.errors import MaplessError
from mapless.evaluate.episode_sets import episodes_digest, load_episodes
from mapless.evaluate.figures import MODEL_COLOURS, model_style, validation_figure
from mapless.evaluate.runner import AgentSpec, EvalSettings, LibrarySpec
from mapless.evaluate.selection import (
    best_index,
    cache_file,
    cached_evaluate,
    candidates,
    select_and_report,
)
from mapless.experiments.pipelines import training_curve
from mapless.experiments.render import mean_near, training_curves
from mapless.scenes.catalogue import room_type_of, split_of
from mapless.sim.config import SimConfig
from mapless.train.run import train


def test_best_by_success_then_spl_then_earliest():
    scores = [
        {"success": 0.40, "spl": 0.20},
        {"success": 0.45, "spl": 0.10},
        {"success": 0.45, "spl": 0.15},
        {"success": 0.45, "spl": 0.15},
    ]
    assert best_index(scores) == 2
    assert best_index(scores[:2]) == 1


def test_training_clock_adds_up_the_logged_intervals_and_leaves_out_a_resume_pause(tmp_path):
    records = [
        {"frames": 100, "perf/frames_per_s": 50.0, "time": 1000.0},  # 2 s
        {"frames": 300, "perf/frames_per_s": 100.0, "time": 1002.0},  # +2 s
        {"frames": 500, "perf/frames_per_s": 100.0, "time": 1004.0},  # after the last checkpoint
        # killed, resumed an hour later from the checkpoint at 300 frames: the wall clock jumps, the
        # training clock does not, and the record at 500 describes work done again
        {"frames": 450, "perf/frames_per_s": 75.0, "time": 4600.0},  # +2 s after the 300 record
    ]
    lines = [json.dumps(r) for r in records]
    lines.insert(3, '{"frames": 550, "perf/fra')  # a record torn by the kill
    (tmp_path / "metrics.jsonl").write_text("\n".join(lines) + "\n")
    assert training_clock(tmp_path) == ([100, 300, 450], [2.0, 4.0, 6.0])
    assert training_clock(tmp_path / "no-such-run") == ([], [])


def test_training_log_keeps_each_scalar_beside_its_frames_through_a_resume(tmp_path):
    records = [
        {"frames": 100, "perf/frames_per_s": 50.0, "charts/success": 0.1},
        {"frames": 300, "perf/frames_per_s": 100.0, "charts/success": 0.3},
        {"frames": 350, "perf/frames_per_s": 100.0},  # no success logged: passed over
        {"frames": 500, "perf/frames_per_s": 100.0, "charts/success": 0.5},  # done again after a resume
        {"frames": 400, "perf/frames_per_s": 100.0, "charts/success": 0.4},
    ]
    (tmp_path / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))
    log = training_log(tmp_path, ("charts/success",))
    assert log == {"frames": [100, 300, 400], "seconds": [2.0, 4.0, 5.0], "charts/success": [0.1, 0.3, 0.4]}


def test_the_training_table_compares_runs_at_the_frames_every_run_reached(tmp_path):
    def curve(frames, success, entropy):
        return {"frames": frames, "success": success, "entropy": entropy}

    slow = curve([100, 200, 300, 400], [0.1, 0.2, 0.3, 0.4], [1.0, 0.9, 0.8, 0.7])
    fast = curve([200, 400, 600, 800], [0.2, 0.4, 0.6, 0.8], [1.0, 0.5, 0.4, 0.3])
    # two seeds of slow trained by PPO; fast (say, the references' A3C) logged no update statistics
    slow_seed2 = {**slow, "updates": {"approx_kl": 0.004, "clip_fraction": 0.05, "explained_variance": 0.5}}
    slow = {**slow, "updates": {"approx_kl": 0.002, "clip_fraction": 0.02, "explained_variance": 0.7}}
    records = [{"model": "slow", "runs": [{"training": slow}, {"training": slow_seed2}]},
               {"model": "fast", "runs": [{"training": fast}]}, {"model": "random", "runs": [{}]}]  # fmt: skip
    lines = training_curves(records, tmp_path / "t.png")
    assert (tmp_path / "t.png").stat().st_size > 10_000
    rows = [line for line in "\n".join(lines).splitlines() if line.startswith(("| slow", "| fast"))]
    # 400 frames are the fewest any run trained: quarter 100 (fast: nearest record, 200), half 200, all 400
    assert rows[0] == "| slow | 400 | 10.0 | 20.0 | 40.0 | 40.0 | 0.70 | 0.70 |"
    assert rows[1] == "| fast | 800 | 20.0 | 20.0 | 40.0 | 80.0 | 0.50 | 0.30 |"
    assert rows[2:] == ["| slow | 0.0030 | 3.5 | 0.60 |"]  # the update table: the seeds' mean, slow only
    assert mean_near(
        curve([95, 100, 104, 200], [0.1, 0.2, 0.6, 0.9], [0, 0, 0, 0]), "success", 100
    ) == pytest.approx(0.3)
    assert training_curves([{"model": "random", "runs": [{}]}], tmp_path / "none.png") == []
    assert not (tmp_path / "none.png").exists()


def test_training_curve_keeps_the_means_of_ppo_update_statistics_where_ppo_logged_them(tmp_path):
    def record(frames, **ppo):
        return {"frames": frames, "perf/frames_per_s": 100.0, "charts/success": 0.5, "losses/entropy": 1.0,
                **{f"ppo/{key}": value for key, value in ppo.items()}}  # fmt: skip

    ppo_run, a3c_run = tmp_path / "ppo", tmp_path / "a3c"
    ppo_run.mkdir()
    a3c_run.mkdir()
    (ppo_run / "metrics.jsonl").write_text(
        json.dumps(record(100, approx_kl=0.01, clip_fraction=0.1, explained_variance=0.2)) + "\n"
        + json.dumps(record(200, approx_kl=0.03, clip_fraction=0.3, explained_variance=0.6)) + "\n"
    )  # fmt: skip
    (a3c_run / "metrics.jsonl").write_text(json.dumps(record(100)) + "\n" + json.dumps(record(200)) + "\n")
    with_updates = training_curve(ppo_run)
    assert with_updates["frames"] == [100, 200] and with_updates["success"] == [0.5, 0.5]
    assert with_updates["updates"] == pytest.approx(
        {"approx_kl": 0.02, "clip_fraction": 0.2, "explained_variance": 0.4}
    )
    without = training_curve(a3c_run)
    assert without["frames"] == [100, 200] and "updates" not in without


def test_validation_figure_draws_only_candidates_that_know_their_frames(tmp_path):
    old_record = {"chosen": "s8.pt", "candidates": [{"path": "s8.pt", "success": 0.3, "episodes": 8}]}
    assert not validation_figure({"a3c": [old_record]}, tmp_path / "none.png")  # made before frames were kept
    assert not (tmp_path / "none.png").exists()
    seed = {
        "chosen": "s2.pt",
        "candidates": [
            {"path": "s1.pt", "success": 0.2, "frames": 1000, "minutes": 1.0},
            {"path": "s2.pt", "success": 0.4, "frames": 2000, "minutes": None},  # beyond the log
        ],
    }
    assert validation_figure({"a3c": [seed, seed], "cvmeta": [old_record]}, tmp_path / "v.png")
    assert (tmp_path / "v.png").stat().st_size > 10_000


def test_every_model_of_a_figure_gets_its_own_style_past_the_palette():
    styles = [model_style(i) for i in range(2 * len(MODEL_COLOURS))]
    assert len(set(styles)) == len(styles)
    # The medium ablation's 13 lines (cvmeta and 12 rows) each get a colour of their own.
    assert len({model_style(i)[0] for i in range(13)}) == 13


def test_paper_protocol_is_labelled():
    assert (PROTOCOLS["standard"].select_split, PROTOCOLS["standard"].report_split) == ("val", "test")
    assert (PROTOCOLS["paper"].select_split, PROTOCOLS["paper"].report_split) == ("paper", "paper")
    assert "PAPER PROTOCOL" in PROTOCOLS["paper"].label
    reference = PROTOCOLS["reference"]
    assert (reference.select_split, reference.report_split, reference.visibility_distance) == (
        "ref_val",
        "ref_test",
        1.5,
    )
    assert "REFERENCE PROTOCOL" in reference.label


def test_builtin_sets_prefix_per_room():
    full = load_episodes("test")
    assert len(full) == 1000 and {split_of(e.scene) for e in full} == {"test"}
    small = load_episodes("test", per_room=3, rooms=("kitchen", "bathroom"))
    assert [room_type_of(e.scene) for e in small] == ["kitchen"] * 3 + ["bathroom"] * 3
    # A prefix of each room's episodes of the full set: small budgets evaluate the same episodes.
    assert small[:3] == [e for e in full if room_type_of(e.scene) == "kitchen"][:3]
    assert all(e.optimal_length >= 2 for e in full)


def test_missing_episode_file_says_how_to_make_it(tmp_path):
    with pytest.raises(MaplessError, match="mapless episodes make"):
        load_episodes("val", tmp_path / "none.json.gz")


def test_episode_sets_are_refused_under_other_simulator_settings():
    assert len(load_episodes("val", per_room=2, library=LibrarySpec())) == 8
    other = LibrarySpec(sim=SimConfig(visibility_distance=1.5))
    with pytest.raises(MaplessError, match="regenerate it with `mapless episodes make`"):
        load_episodes("val", per_room=2, library=other)
    # Offline roots and test factories carry no simulator fingerprint: nothing to compare.
    assert LibrarySpec(offline_dir="somewhere").sim_fingerprint is None


def test_select_refuses_to_report_on_the_selection_split(tmp_path, capsys):
    assert main(["eval", str(tmp_path), "--select", "--split", "val"]) != 0
    assert "reports on --split test" in capsys.readouterr().err


@pytest.mark.usefixtures("single_torch_thread")
def test_evaluation_cache_hits_and_misses(tmp_path):
    run = tmp_path / "run"
    train(tiny_config("a3c", "episodes=4"), run, library_factory=training_scenes)
    model = run / "final_model.pt"
    spec, episodes = AgentSpec(checkpoint=str(model)), fixture_episodes(per_scene=2)
    settings, scenes = (
        EvalSettings(batch_size=4, workers=1),
        LibrarySpec(factory="eval_fixtures:fixture_library"),
    )
    cache = tmp_path / "eval" / "test_final_model.json"

    def evaluated(**changes) -> bool:
        """True if the call evaluated; False if it returned the cached results (marked below)."""
        run = cached_evaluate(spec, episodes, replace(settings, **changes), scenes, cache)
        return run.seconds != -1.0

    assert evaluated()
    stored = json.loads(cache.read_text())
    cache.write_text(json.dumps({**stored, "seconds": -1.0}))  # a marker only a cache hit returns
    assert not evaluated(workers=2)  # results do not depend on the worker count
    assert evaluated(seed=1)
    cache.write_text(json.dumps({**stored, "seconds": -1.0}))
    stat = model.stat()
    os.utime(model, ns=(stat.st_atime_ns, stat.st_mtime_ns + 10**9))  # as a resumed run rewrites it
    assert evaluated()
    cache.write_text(cache.read_text()[:100])  # torn by an older, non-atomic writer
    assert evaluated() and json.loads(cache.read_text())["episodes"]
    # Results cached before sightings were recorded: filled in from their poses, and stored.
    stored = json.loads(cache.read_text())
    recorded = [(e["first_seen"], e["ended_in_frame"]) for e in stored["episodes"]]
    assert all(f is not None and i is not None for f, i in recorded)
    first = stored["episodes"][0]
    assert first["first_seen"] == -1 and first["length"] >= 3  # never saw it; as if its third move had:
    first["poses"][2] = int(
        np.flatnonzero(fixture_library()[episodes[0].scene].goal_mask(episodes[0].target))[0]
    )
    recorded[0] = (3, recorded[0][1])
    for e in stored["episodes"]:
        del e["first_seen"], e["ended_in_frame"]
    cache.write_text(json.dumps({**stored, "seconds": -1.0}))
    run = cached_evaluate(spec, episodes, settings, scenes, cache)
    assert run.seconds == -1.0 and [(r.first_seen, r.ended_in_frame) for r in run.results] == recorded
    stored = json.loads(cache.read_text())["episodes"]
    assert [(e["first_seen"], e["ended_in_frame"]) for e in stored] == recorded


def test_cache_files_keep_one_file_per_episode_set_and_read_files_named_before(tmp_path):
    episodes = fixture_episodes(per_scene=2)
    first, second = episodes_digest(episodes[:3]), episodes_digest(episodes[3:])
    a, b = cache_file(tmp_path, "val_model_8", first), cache_file(tmp_path, "val_model_8", second)
    assert a != b and a.name.startswith("val_model_8_") and a.parent == tmp_path
    # A cache named before the digest serves its own set still; another set gets a file of its own.
    legacy = tmp_path / "val_model_8.json"
    legacy.write_text(json.dumps({"key": {"episodes": first}}))
    assert cache_file(tmp_path, "val_model_8", first) == legacy
    assert cache_file(tmp_path, "val_model_8", second) == b
    a.write_text("{}")  # once the set has a file by its digest, that one is used
    assert cache_file(tmp_path, "val_model_8", first) == a
    a.unlink()
    legacy.write_text("{torn")  # unreadable: left alone, and the set gets its own file
    assert cache_file(tmp_path, "val_model_8", first) == a and legacy.is_file()


@pytest.mark.usefixtures("single_torch_thread")
def test_selection_within_minutes_reads_only_the_snapshots_of_that_much_training(tmp_path):
    run = tmp_path / "run"
    train(tiny_config("a3c", "episodes=12"), run, library_factory=training_scenes)
    frames = [int(load_file(path)["counters"]["frames"]) for _, path in candidates(run)]
    assert len(frames) >= 3 and frames == sorted(frames)
    # A log that dates the snapshots: each one a minute of training after the one before.
    log = [{"frames": f, "perf/frames_per_s": (f - ([0, *frames][i])) / 60.0} for i, f in enumerate(frames)]
    (run / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in log))
    episodes, settings = fixture_episodes(per_scene=1), EvalSettings(batch_size=4, workers=1)
    scenes = LibrarySpec(factory="eval_fixtures:fixture_library")

    capped = select_and_report(run, episodes, episodes, settings, scenes, within_minutes=2.5)
    assert [c["frames"] for c in capped.scores] == frames[:2]
    assert [round(c["minutes"], 6) for c in capped.scores] == [1.0, 2.0]
    assert capped.chosen in {c["path"] for c in capped.scores}
    assert "first 2.5 training minutes" in capped.label
    whole = select_and_report(run, episodes, episodes, settings, scenes)
    assert [c["frames"] for c in whole.scores] == frames
    with pytest.raises(MaplessError, match=r"no snapshot within its first 0\.5 training minutes"):
        select_and_report(run, episodes, episodes, settings, scenes, within_minutes=0.5)
