"""Checkpoint identity: a run folder's files belong to one run. A checkpoint copied in from another
run is not resumed, snapshots of two runs are not evaluated as one, a hand-edited config.yaml is
reported on resume, and a resumed run keeps the commit of its first start beside each resume's."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import yaml
from train_fixtures import fixture_library, tiny_config

from mapless import checkpoint as ckpt
from mapless import provenance as prov
from mapless.cli import main as cli_main
from mapless.config import ConfigError
from mapless.errors import MaplessError
from mapless.evaluate.selection import candidates
from mapless.train.run import config_edits, resume_config, train


def _files(run_dir: Path) -> dict[str, tuple[int, int]]:
    return {str(p.relative_to(run_dir)): (p.stat().st_size, p.stat().st_mtime_ns) for p in run_dir.rglob("*")}


@pytest.fixture(scope="module")
def two_runs(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("runs")
    base, other = root / "base", root / "other"
    train(tiny_config("a3c", "episodes=8", "checkpoint_every=4"), base, library_factory=fixture_library)
    train(tiny_config("mlp", "episodes=4", "checkpoint_every=4"), other, library_factory=fixture_library)
    return base, other


def test_a_checkpoint_of_another_model_is_not_resumed_and_nothing_is_written(two_runs, tmp_path, capsys):
    base, other = two_runs
    mixed = tmp_path / "mixed"
    shutil.copytree(base, mixed)
    shutil.copy(other / ckpt.CHECKPOINT_FILE, mixed / ckpt.CHECKPOINT_FILE)
    before = _files(mixed)
    config, state = resume_config(mixed)
    with pytest.raises(
        ckpt.CheckpointError, match=r"model.name is 'mlp' in checkpoint.pt, 'a3c' in config.yaml"
    ):
        train(config, mixed, resume=state, library_factory=fixture_library)
    assert _files(mixed) == before
    # The command says so too: exit 2, no traceback, and no note that config.yaml was edited.
    assert cli_main(["train", "--resume", str(mixed)]) == 2
    err = capsys.readouterr().err
    assert "is not of the run in" in err and "Traceback" not in err and "differs from the run's" not in err
    assert _files(mixed) == before


def test_a_checkpoint_of_another_seed_of_the_same_model_is_not_resumed(two_runs, tmp_path):
    base, _ = two_runs
    other = tmp_path / "seed2"
    train(
        tiny_config("a3c", "episodes=4", "checkpoint_every=4", "seed=2"),
        other,
        library_factory=fixture_library,
    )
    shutil.copy(other / ckpt.CHECKPOINT_FILE, tmp_path / "ckpt.pt")
    mixed = tmp_path / "mixed"
    shutil.copytree(base, mixed)
    shutil.copy(tmp_path / "ckpt.pt", mixed / ckpt.CHECKPOINT_FILE)
    config, state = resume_config(mixed)
    with pytest.raises(ckpt.CheckpointError, match=r"seed is 2 in checkpoint.pt, 1 in config.yaml"):
        train(config, mixed, resume=state, library_factory=fixture_library)


def test_a_planned_config_of_another_seed_does_not_resume_a_run(two_runs, tmp_path):
    base, _ = two_runs
    run = tmp_path / "run"
    shutil.copytree(base, run)
    (run / ckpt.FINAL_MODEL_FILE).unlink()
    state = ckpt.load_file(run / ckpt.CHECKPOINT_FILE)
    planned = tiny_config("a3c", "episodes=8", "checkpoint_every=4", "seed=3")
    with pytest.raises(ConfigError, match=r"seed is 1 in checkpoint.pt, 3 in the config to resume with"):
        train(planned, run, resume=state, library_factory=fixture_library)


def test_snapshots_of_two_runs_in_one_folder_are_not_evaluated_as_one(two_runs, tmp_path):
    base, other = two_runs
    assert [e for e, _ in candidates(base)] == [4, 8]
    mixed = tmp_path / "mixed"
    shutil.copytree(base, mixed)
    (mixed / ckpt.FINAL_MODEL_FILE).unlink()
    shutil.copy(
        other / ckpt.SNAPSHOT_DIR / "model_0000000004.pt", mixed / ckpt.SNAPSHOT_DIR / "model_0000000012.pt"
    )
    with pytest.raises(MaplessError, match=r"mixes the snapshots of two runs: model.name is 'a3c'"):
        candidates(mixed)


def test_a_hand_edited_config_is_reported_as_overridden_on_resume(two_runs, tmp_path, capsys):
    base, _ = two_runs
    run = tmp_path / "run"
    shutil.copytree(base, run)
    (run / ckpt.FINAL_MODEL_FILE).unlink()
    state = ckpt.load_file(run / ckpt.CHECKPOINT_FILE)
    assert config_edits(run, state) == []
    text = (run / ckpt.CONFIG_FILE).read_text()
    (run / ckpt.CONFIG_FILE).write_text(text.replace("log_every: 4", "log_every: 7"))
    assert config_edits(run, state) == ["log_every: 7 in config.yaml, 4 in the checkpoint"]
    # A stored config that names another run's model is the trainer's to refuse, not an edit.
    (run / ckpt.CONFIG_FILE).write_text(text.replace("name: a3c", "name: mlp"))
    assert config_edits(run, state) == []


def test_the_resume_command_says_which_edits_it_undoes(two_runs, tmp_path, capsys, monkeypatch):
    import mapless.train.run as run_module

    base, _ = two_runs
    run = tmp_path / "run"
    shutil.copytree(base, run)
    (run / ckpt.FINAL_MODEL_FILE).unlink()
    text = (run / ckpt.CONFIG_FILE).read_text()
    (run / ckpt.CONFIG_FILE).write_text(text.replace("log_every: 4", "log_every: 7"))
    trained = []
    monkeypatch.setattr(run_module, "train", lambda config, run_dir, resume: trained.append(config) or {})
    assert cli_main(["train", "--resume", str(run)]) == 0
    err = capsys.readouterr().err
    assert "differs from the run's checkpoint in log_every: 7 in config.yaml, 4 in the checkpoint" in err
    assert trained[0].log_every == 4


def test_a_resumed_run_keeps_the_commit_of_its_first_start_and_adds_each_resumes(tmp_path, monkeypatch):
    commits = iter(["a" * 40, "b" * 40, "c" * 40])
    monkeypatch.setattr(prov, "git_state", lambda: (next(commits), False))
    run = tmp_path / "run"
    config = tiny_config("a3c", "episodes=4", "checkpoint_every=4")
    train(config, run, library_factory=fixture_library)
    for episodes in (8, 12):
        resumed, state = resume_config(run, [f"episodes={episodes}"])
        train(resumed, run, resume=state, library_factory=fixture_library)
    records = prov.run_provenance(run / ckpt.CONFIG_FILE)
    assert [r["commit"] for r in records] == ["a" * 40, "b" * 40, "c" * 40]
    lines = (run / ckpt.CONFIG_FILE).read_text().splitlines()
    assert lines[0].startswith("# Trained by mapless") and "commit aaaaaaaaaaaa" in lines[0]
    assert lines[2].startswith("# Resumed by mapless") and "commit bbbbbbbbbbbb" in lines[2]
    assert json.loads(lines[5].removeprefix("# resumed: "))["commit"] == "c" * 40
    assert yaml.safe_load((run / ckpt.CONFIG_FILE).read_text())["episodes"] == 12  # still a config


def test_a_folder_without_a_recorded_start_begins_its_record_at_the_resume():
    comment = prov.resumed_comment("a note someone wrote", threads=1)
    assert comment.startswith("Trained by mapless") and "\nprovenance: " in comment
