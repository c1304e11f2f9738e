"""One run identity: a run folder's hash reads the training config as it is laid out; the one-time
``mapless runs migrate`` renames the folders named under the former rule (whose copy lives only in
mapless/experiments/migrate.py, checked here against the folder names that rule pinned for every
shipped run) so that ``mapless reproduce`` finds them, checking each folder's config.yaml and
never overwriting one; ``mapless reproduce --no-train`` reports the finished runs it finds and names
the ones it would have trained; ``--print-config`` of ``train`` and ``reproduce`` prints every key
with the layer it came from and runs nothing."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml
from captures import captured_names, run_folders

from mapless.cli import main as cli_main
from mapless.config import move_keys, save_config, to_dict
from mapless.errors import MaplessError
from mapless.experiments import load_experiment, train_config
from mapless.experiments.finished import NoTraining, finished_only
from mapless.experiments.launch import PlannedRun
from mapless.experiments.migrate import earlier_run_hashes, migrate, old_run_hash
from mapless.experiments.pipelines import Row
from mapless.experiments.runs import run_dir_for
from mapless.train.config import LAYOUT_CHANGES

DATA = Path(__file__).parent / "data"


def _pinned_run_config(key: str):
    """The training config of a run pinned in tests/data/run_folders*.json, keyed ``experiment budget
    protocol row`` (tests/captures.py)."""
    experiment, budget, protocol, row = key.split()
    config = load_experiment(experiment, budget, overrides=[f"eval.protocol={protocol}", "train.threads=1"])
    extra = config.ablation_table()[row].train if row in config.ablations else None
    return train_config(config, config.focus if extra else row, 1, extra)


@pytest.mark.slow  # resolves every shipped experiment twice over: 12 s of the fast tier
def test_the_migrations_copy_of_the_former_rule_names_every_shipped_run_as_it_did() -> None:
    # run_folders_old_hash.json is run_folders.json as the former rule wrote it (git show of the
    # commit before the change): the copy in migrate.py must give those names, or it would
    # rename nothing of a real grid.
    old = json.loads((DATA / "run_folders_old_hash.json").read_text())
    new = run_folders(captured_names())
    # Runs a shipped experiment gained after the identity changed (Table 1 at the hour's whole
    # lineup) never had an old name.
    assert set(old) <= set(new) and len(old) > 100
    renamed = {}
    for key in old:
        cfg = _pinned_run_config(key)
        assert old_run_hash(cfg) == old[key].rsplit("__", 1)[1], key
        renamed.setdefault(old[key], new[key])
        assert renamed[old[key]] == new[key]  # runs shared under the former rule stay shared


@pytest.mark.slow  # resolves every shipped experiment twice over, per rule
@pytest.mark.parametrize(
    ("change", "pinned"),
    [(1, "run_folders_before_ppo_meta.json"), (2, "run_folders_before_a3c_precision.json")],
)
def test_each_later_rule_names_every_shipped_run_as_it_did(change: int, pinned: str) -> None:
    # Each file is run_folders.json as the rule before LAYOUT_CHANGES[change] wrote it: the config
    # as laid out then, hashed whole.
    before = json.loads((DATA / pinned).read_text())
    new = run_folders(captured_names())
    assert set(before) == set(new)
    for key in before:
        cfg = _pinned_run_config(key)
        assert earlier_run_hashes(cfg)[len(LAYOUT_CHANGES) - 1 - change] == before[key].rsplit("__", 1)[1], (
            key
        )
    # Every run's name changes with the layout, since its hash reads the whole config.
    assert not set(before.values()) & set(new.values())


def _grid_folder(config, cfg, rule: int = 0, laid_out_before: int | None = None) -> Path:
    """A finished run folder as a former rule named it (0: the first rule, n: the rule before
    ``LAYOUT_CHANGES[n]``), its config.yaml the config the grid trained with (its thread share, no
    bar) in today's layout or as laid out before ``LAYOUT_CHANGES[laid_out_before]``, a final
    model, a snapshot and a cached evaluation that names the model file by path."""
    trained = cfg.replace(threads=cfg.threads or 1, progress=False)
    named = old_run_hash(cfg) if rule == 0 else earlier_run_hashes(cfg)[len(LAYOUT_CHANGES) - 1 - rule]
    folder = Path(config.runs_dir) / f"{cfg.model.name}__all__s{cfg.seed}__{named}"
    (folder / "snapshots").mkdir(parents=True)
    data = to_dict(trained)
    for _, moves in reversed(LAYOUT_CHANGES[laid_out_before:] if laid_out_before is not None else ()):
        data = move_keys(data, [(new, old) for old, new in moves])
    (folder / "config.yaml").write_text(yaml.safe_dump(data))
    (folder / "final_model.pt").write_bytes(b"model")
    (folder / "snapshots" / "model_000064.pt").write_bytes(b"snapshot")
    (folder / "eval").mkdir()
    cache = {"key": {"spec": {"checkpoint": str(folder / "final_model.pt")}, "episodes": "e"}, "metrics": {}}
    (folder / "eval" / "val_final_model_0123abcd.json").write_text(json.dumps(cache))
    return folder


def test_migrate_renames_a_grids_folders_so_that_reproduce_finds_them(tmp_path: Path, capsys) -> None:
    runs = tmp_path / "runs" / "small"
    config = load_experiment("table1", "small", overrides=[f"runs_dir={runs}"])
    runs_of = [
        train_config(config, "a3c", 1),
        train_config(config, "cvmeta", 2),
        train_config(config, "cvmeta", 3),
        train_config(config, "a3c", 2),
    ]
    a3c = runs_of[0]
    folders = [
        _grid_folder(config, runs_of[0]),  # the first rule's name, config.yaml rewritten since
        _grid_folder(config, runs_of[1], laid_out_before=0),  # the first rule, the first layout
        _grid_folder(config, runs_of[2], rule=1, laid_out_before=1),  # before the ppo.meta: block
        _grid_folder(config, runs_of[3], rule=2, laid_out_before=2),  # before a3c.precision
    ]
    assert all(f != run_dir_for(config, c, "all") for f, c in zip(folders, runs_of, strict=True))
    bad = runs / "mlp__all__s1__0123abcd"  # a config.yaml that does not parse
    bad.mkdir()
    (bad / "config.yaml").write_text("model: [unclosed\n")
    edited = runs / "mjolnir_o__all__s1__89abcdef"  # parses, but not to its name
    edited.mkdir()
    save_config(train_config(config, "mjolnir_o", 1), edited / "config.yaml")

    assert cli_main(["runs", "migrate", str(tmp_path / "runs"), "--dry-run"]) == 0
    out = capsys.readouterr().out
    assert f"{folders[0]} -> {run_dir_for(config, a3c, 'all')}" in out
    assert "would rename 4 of 6 run folders" in out and all(f.is_dir() for f in folders)

    steps = migrate(tmp_path / "runs", log=lambda line: None)
    assert sorted(s.folder.name for s in steps if s.new_name is None) == [edited.name, bad.name]
    reasons = {s.folder.name: s.reason for s in steps}
    assert "does not parse" in reasons[bad.name] and "does not give the folder's hash" in reasons[edited.name]
    for folder, cfg in zip(folders, runs_of, strict=True):
        found = PlannedRun.of(config, cfg.model.name, "all", cfg.seed)
        assert not folder.exists() and found.run_dir == run_dir_for(config, cfg, "all") and found.finished
        assert (found.run_dir / "snapshots" / "model_000064.pt").read_bytes() == b"snapshot"
        cache = json.loads(next((found.run_dir / "eval").glob("*.json")).read_text())
        assert cache["key"]["spec"]["checkpoint"] == str(found.run_dir / "final_model.pt")
    # Once is enough: a second pass moves nothing.
    again = migrate(tmp_path / "runs", log=lambda line: None)
    assert not any(s.new_name for s in again)
    assert sum("today's hash already" in s.reason for s in again) == 4


def test_migrate_never_overwrites_a_folder(tmp_path: Path) -> None:
    config = load_experiment("table1", "small", overrides=[f"runs_dir={tmp_path}"])
    a3c = train_config(config, "a3c", 1)
    folder = _grid_folder(config, a3c)
    taken = run_dir_for(config, a3c, "all")
    taken.mkdir()
    (taken / "mine.txt").write_text("kept")
    (step,) = [s for s in migrate(tmp_path, log=lambda line: None) if s.folder == folder]
    assert step.new_name is None and "exists already" in step.reason
    assert folder.is_dir() and (taken / "mine.txt").read_text() == "kept"
    with pytest.raises(MaplessError, match="is not a folder"):
        migrate(tmp_path / "missing")


def test_no_train_reports_the_finished_runs_and_names_the_others(tmp_path: Path, capsys) -> None:
    config = load_experiment(
        "table1", "smoke", overrides=[f"runs_dir={tmp_path}", "models=[random,a3c,savn]"]
    )
    done = PlannedRun.of(config, "a3c")
    done.run_dir.mkdir(parents=True)
    (done.run_dir / "final_model.pt").write_bytes(b"model")
    lines: list[str] = []
    narrowed = finished_only(config, lines.append)
    assert narrowed.models == ("random", "a3c")
    assert any(f"savn all, seed 1 would go to {PlannedRun.of(config, 'savn').run_dir}" in x for x in lines)
    assert NoTraining().train([done], lines.append)
    with pytest.raises(MaplessError, match="savn all, seed 1 is not finished"):
        NoTraining().train([PlannedRun.of(config, "savn")], lines.append)
    # Nothing finished: refused before any evaluation, naming what it would have trained.
    empty = tmp_path / "empty"
    argv = ["reproduce", "table1", "--budget", "smoke", "--no-train", "--set", f"runs_dir={empty}"]
    assert cli_main([*argv, "--set", "models=[random,a3c]"]) == 2
    captured = capsys.readouterr()
    assert "would go to" in captured.out and "no trained model has its runs finished" in captured.err
    assert not empty.exists()


def test_no_train_reports_each_model_on_its_first_finished_seeds(tmp_path: Path) -> None:
    config = load_experiment(
        "table1",
        "smoke",
        overrides=[
            f"runs_dir={tmp_path}",
            "models=[random,a3c,savn,cvmeta]",
            "seeds=2",
            "model_seeds.cvmeta=3",
        ],
    )

    def finish(model: str, seed: int) -> None:
        run = PlannedRun.of(config, model, "all", seed)
        run.run_dir.mkdir(parents=True)
        (run.run_dir / "final_model.pt").write_bytes(b"model")

    # a3c: both seeds; savn: seed 2 only (no first seed); cvmeta: seeds 1 and 3, not 2.
    for model, seed in [("a3c", 1), ("a3c", 2), ("savn", 2), ("cvmeta", 1), ("cvmeta", 3)]:
        finish(model, seed)
    lines: list[str] = []
    narrowed = finished_only(config, lines.append)
    assert narrowed.models == ("random", "a3c", "cvmeta")
    assert narrowed.seeds_of("a3c") == 2 and narrowed.seeds_of("cvmeta") == 1
    assert "cvmeta on 1 of 3 seeds" in lines[-1] and "left out: savn" in lines[-1]
    # What it reports is exactly what is finished: the launcher finds nothing to train.
    runs = [run for model in narrowed.models if model != "random" for run in Row(model).runs(narrowed)]
    assert [(r.config.model.name, r.config.seed) for r in runs] == [("a3c", 1), ("a3c", 2), ("cvmeta", 1)]
    assert NoTraining().train(runs, lines.append)


def test_print_config_names_each_keys_layer_and_runs_nothing(tmp_path: Path, capsys) -> None:
    runs = tmp_path / "runs"
    argv = ["reproduce", "table1", "--budget", "small", "--print-config", "--set", f"runs_dir={runs}"]
    assert cli_main([*argv, "--set", "train.ppo.lr=0.001"]) == 0
    out = capsys.readouterr().out
    cvmeta = out[out.index("# run cvmeta all") :].split("\n\n")[0]
    assert f"runs_dir: {runs}  # --set" in out and "focus: cvmeta  # budgets/small.yaml" in out
    assert "frames: 200000  # budgets/small.yaml" in cvmeta  # per_model.cvmeta of the budget
    assert "ppo.minibatches: 1  # recipe laptop, per_model.cvmeta" in cvmeta
    assert "ppo.lr: 0.001  # --set" in cvmeta and "ppo.clip: 0.2  # default" in cvmeta
    assert not runs.exists()
    argv = ["train", "train_ppo", "--print-config", "--run-dir", str(tmp_path / "run")]
    assert cli_main([*argv, "--set", "model.name=a3c"]) == 0
    out = capsys.readouterr().out
    assert "model.name: a3c  # --set" in out and "frames: 2000000  # train_ppo.yaml" in out
    assert "model.target_context: true  # recipe laptop, per_model.a3c" in out
    assert not (tmp_path / "run").exists()
