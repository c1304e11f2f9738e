"""End to end on real (built) scenes: `mapless reproduce` trains, selects on val, reports on test and
writes the markdown/JSON/PNGs; `mapless eval` on an untrained baseline and on a run folder.

Three scenes only (train FloorPlan1, val FloorPlan21, test FloorPlan26), built once per module into a
temporary cache; episode files are made here so the test does not depend on the shipped sets."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
import torch

from mapless.cli import main
from mapless.config import ConfigError
from mapless.episodes import evalsets
from mapless.experiments import RunTally, load_experiment, planned_runs, run_dir_for, train_config
from mapless.provenance import provenance
from mapless.sim.cache import fingerprint
from mapless.sim.config import SimConfig
from mapless.sim.episode import Episode
from mapless.sim.library import SceneLibrary

pytestmark = pytest.mark.usefixtures("single_torch_thread")


MJOLNIR_KITCHEN = frozenset({"Mug", "Toaster", "Bread", "Apple", "Spatula", "CoffeeMachine"})
HOZ_KITCHEN = frozenset({"Toaster", "CoffeeMachine", "Fridge", "Microwave", "Sink", "StoveBurner"})


def make_episodes(
    library: SceneLibrary, scene: str, n: int, seed: int, targets: frozenset[str] = MJOLNIR_KITCHEN
) -> list[Episode]:
    rng = np.random.default_rng(seed)
    data = library[scene]
    types = sorted({data.instance_types[i] for i in np.unique(data.visible_matrix_csr[1])} & targets)
    out = []
    while len(out) < n:
        target = types[rng.integers(len(types))]
        start = int(rng.choice(np.flatnonzero(data.horizon == 0)))
        d = int(data.target_distances(target)[start])
        if d > 0:
            pose = (float(data.x[start]), float(data.z[start]), int(data.yaw[start]), 0)
            out.append(Episode(scene, target, pose, d + 1, episode_id=f"{scene}/{len(out)}"))
    return out


def _same_code(record: dict) -> bool:
    """A report's provenance names this code and machine (the dirty flag aside: others may be editing)."""
    here = provenance()
    return all(record[key] == here[key] for key in ("commit", "version", "torch", "cores"))


@pytest.fixture(scope="module")
def workspace(tmp_path_factory):
    root = tmp_path_factory.mktemp("reproduce")
    previous = os.environ.get("MAPLESS_CACHE")
    os.environ["MAPLESS_CACHE"] = str(root / "cache")  # spawn workers inherit it
    library = SceneLibrary.builtin()
    fp = fingerprint(SimConfig())
    evalsets.save(
        root / "val.json.gz", make_episodes(library, "FloorPlan21", 6, 0), "val", "mjolnir22", 0, fp
    )
    evalsets.save(
        root / "test.json.gz", make_episodes(library, "FloorPlan26", 6, 1), "test", "mjolnir22", 0, fp
    )
    library["FloorPlan1"]
    config = root / "table1.yaml"
    config.write_text(
        f"""experiment: table1
budget: smoke
models: [random, a3c]
focus: a3c
seeds: 1
gif: false
runs_dir: {root / "runs"}
train:
  episodes: 16
  a3c: {{batch_size: 8}}
  checkpoint_every: 8
  log_every: 8
  progress: false
  model: {{hidden_size: 64}}
  env: {{scenes: FloorPlan1}}
eval:
  per_room: 6
  rooms: [kitchen]
  select_file: {root / "val.json.gz"}
  report_file: {root / "test.json.gz"}
  batch_size: 6
  workers: 1
"""
    )
    yield root, config
    if previous is None:
        os.environ.pop("MAPLESS_CACHE", None)
    else:
        os.environ["MAPLESS_CACHE"] = previous


@pytest.mark.slow
def test_reproduce_table1_then_figures_reuse_runs(workspace, capsys):
    root, config = workspace
    reports = root / "reports"
    assert main(["reproduce", "table1", "--config", str(config), "--reports", str(reports)]) == 0
    assert "[run 1 of 1] a3c all, seed 1" in capsys.readouterr().out  # random is not trained
    md = (reports / "table1" / "table1.md").read_text()
    assert "| random |" in md and "| a3c |" in md and "SR L≥5" in md
    payload = json.loads((reports / "table1" / "table1.json").read_text())
    assert _same_code(payload["provenance"]) and "Made by mapless" in md
    a3c = next(m for m in payload["models"] if m["model"] == "a3c")
    # The focus model (a3c here) minus each other model, on the same episodes.
    random = next(m for m in payload["models"] if m["model"] == "random")
    minus = random["focus_minus_model"]["success"]
    assert minus["mean"] == pytest.approx(
        a3c["estimates"]["success"]["mean"] - random["estimates"]["success"]["mean"]
    )
    assert minus["ci_low"] <= minus["mean"] <= minus["ci_high"] and "a3c minus each model" in md
    selection = a3c["runs"][0]["selection"]
    # Snapshots at 8 and 16 episodes (the final model is the 16-episode snapshot): both scored on val.
    assert [c["episodes"] for c in selection["candidates"]] == [8, 16]
    assert selection["chosen"] in [c["path"] for c in selection["candidates"]]
    # Each candidate says how far training had got: its snapshot's frames and, from the training
    # log (a record every 8 episodes), the training minutes to that point; the report plots them.
    for c in selection["candidates"]:
        assert c["frames"] == torch.load(c["path"], weights_only=True)["counters"]["frames"] > 0
    first, last = selection["candidates"]
    assert 0 < first["minutes"] < last["minutes"] < 5
    assert (reports / "table1" / "table1_validation.png").stat().st_size > 10_000
    assert "![validation success per snapshot](table1_validation.png)" in md
    assert len(a3c["episodes"][0]) == 6 and {e["scene"] for e in a3c["episodes"][0]} == {"FloorPlan26"}
    run_dir = Path(a3c["runs"][0]["run_dir"])
    assert len(list((run_dir / "eval").glob("val_model_0000000008_*.json"))) == 1
    assert (run_dir / "config.yaml").read_text().startswith("# Trained by mapless")

    # Figures reuse the finished runs (no retraining) and write their PNGs.
    overrides = ["--set", "experiment=figure3"]
    assert main(["reproduce", "figure3", "--config", str(config), *overrides, "--reports", str(reports)]) == 0
    assert (reports / "figure3" / "figure3_exploration.png").stat().st_size > 10_000
    overrides = ["--set", "experiment=figures45"]
    assert (
        main(["reproduce", "figures45", "--config", str(config), *overrides, "--reports", str(reports)]) == 0
    )
    figures = json.loads((reports / "figures45" / "figures45.json").read_text())["figures"]
    assert figures, "at least one of Figure 4 / Figure 5 has an episode"
    for name in figures:
        assert (reports / "figures45" / f"{name}.png").stat().st_size > 10_000
    assert "reusing finished run" in capsys.readouterr().out


@pytest.mark.slow
def test_ctrl_c_stops_the_experiment_at_a_checkpoint_and_the_same_command_resumes(
    workspace, monkeypatch, capsys
):
    from mapless.checkpoint import CHECKPOINT_FILE, FINAL_MODEL_FILE
    from mapless.train.runtime import GracefulStop

    root, config = workspace
    # Runs and reports of its own: the module's other tests leave finished runs to reuse.
    runs, reports = root / "interrupted_runs", root / "interrupted_reports"
    command = ["reproduce", "table1", "--config", str(config), "--reports", str(reports)]
    command += ["--set", f"runs_dir={runs}"]
    enter = GracefulStop.__enter__

    def ctrl_c_at_once(self):  # as if Ctrl-C came during the first update
        enter(self)
        self.requested = True
        return self

    monkeypatch.setattr(GracefulStop, "__enter__", ctrl_c_at_once)
    assert main(command) == 130
    assert not (reports / "table1").exists(), "a half-trained model was evaluated and reported"
    (run_dir,) = runs.iterdir()
    assert (run_dir / CHECKPOINT_FILE).is_file() and not (run_dir / FINAL_MODEL_FILE).exists()
    monkeypatch.setattr(GracefulStop, "__enter__", enter)
    assert main(command) == 0
    assert f"resuming {run_dir} at 8 episodes" in capsys.readouterr().out
    assert (run_dir / FINAL_MODEL_FILE).is_file() and (reports / "table1" / "table1.md").is_file()


@pytest.mark.slow
def test_reproduce_table1_with_all_nine_models(workspace):
    """The paper's Table 1 lineup end to end: every trained model is selected on val and reported."""
    root, config = workspace
    reports = root / "reports_all"
    models = ["random", "a3c", "sp", "savn", "gve", "spatt", "mjolnir_o", "mjolnir_r", "cvmeta"]
    overrides = ["--set", f"models=[{','.join(models)}]", "--set", "focus=cvmeta"]
    assert main(["reproduce", "table1", "--config", str(config), *overrides, "--reports", str(reports)]) == 0
    payload = json.loads((reports / "table1" / "table1.json").read_text())
    assert [m["model"] for m in payload["models"]] == models
    for record in payload["models"][1:]:
        selection = record["runs"][0]["selection"]
        assert [c["episodes"] for c in selection["candidates"]] == [8, 16], record["model"]
        assert len(record["episodes"][0]) == 6
    md = (reports / "table1" / "table1.md").read_text()
    assert all(f"| {m} |" in md for m in models)


@pytest.mark.slow
def test_reproduce_with_two_seeds_reports_mean_and_std_over_seeds(workspace):
    root, config = workspace
    reports = root / "reports_seeds"
    overrides = ["--set", "models=[a3c]", "--set", "focus=a3c", "--seeds", "2"]
    assert main(["reproduce", "table1", "--config", str(config), *overrides, "--reports", str(reports)]) == 0
    (record,) = json.loads((reports / "table1" / "table1.json").read_text())["models"]
    assert [Path(r["run_dir"]).name.split("__")[2] for r in record["runs"]] == ["s1", "s2"]
    success = record["estimates"]["success"]
    assert success["seeds"] == 2 and success["episodes"] == 6  # report episodes per seed
    per_seed = [s["overall"]["success"] for s in record["per_seed"]]
    assert success["mean"] == pytest.approx(np.mean(per_seed))
    assert success["std"] == pytest.approx(np.std(per_seed, ddof=1))
    assert "±" in (reports / "table1" / "table1.md").read_text()


@pytest.mark.slow
def test_reproduce_table2_and_table3(workspace):
    root, config = workspace
    reports = root / "reports"
    common = [
        "--config",
        str(config),
        "--reports",
        str(reports),
        "--set",
        "models=[a3c]",
        "--set",
        "rooms=[kitchen]",
    ]
    table2 = [*common, "--set", "experiment=table2", "--set", "single_room_scenes={kitchen: FloorPlan1}"]
    assert main(["reproduce", "table2", *table2]) == 0
    md = (reports / "table2" / "table2.md").read_text()
    assert "| a3c | K-single |" in md and "Kitchen SR / SPL" in md
    assert main(["reproduce", "table3", *common, "--set", "experiment=table3"]) == 0
    payload = json.loads((reports / "table3" / "table3.json").read_text())
    labels = [m["model"] for m in payload["models"]]
    assert labels == ["a3c", "Kitchen_no_relationships"]
    full, ablated = payload["models"]
    kitchen = ablated["minus_full"]["kitchen"]["success"]
    assert kitchen["mean"] == pytest.approx(
        ablated["rooms"]["kitchen"]["success"]["mean"] - full["rooms"]["kitchen"]["success"]["mean"]
    )
    assert "Δ SR, its room type" in (reports / "table3" / "table3.md").read_text()
    run_dirs = [m["runs"][0]["run_dir"] for m in payload["models"]]
    assert "__no-kitchen__" in run_dirs[1] and run_dirs[0] != run_dirs[1]
    # The unablated model is Table 1's run of the same configuration (trained once for both).
    table1 = load_experiment("table1", "smoke", path=config, overrides=["models=[a3c]"])
    assert Path(run_dirs[0]) == run_dir_for(table1, train_config(table1, "a3c", seed=1), "all")
    from mapless.checkpoint import load_file

    # a3c has no graph: its runs lose the room's parent reward, and get no graph setting it never reads.
    ablated = load_file(Path(run_dirs[1]) / "final_model.pt")["config"]
    assert "kitchen" not in ablated["env"]["reward"]["parent_reward_rooms"]
    assert "kitchen" in ablated["model"]["hierarchy_rooms"]
    # The paper's model, which has the hierarchical graph, loses the room's edges in it too.
    from mapless.experiments.pipelines import table3_rows

    rows = table3_rows(load_experiment("table3", "smoke"))
    assert "kitchen" not in rows["kitchen"].extra["model"]["hierarchy_rooms"]


@pytest.mark.slow
def test_eval_cli_oracle_and_run_folder(workspace, capsys):
    root, _ = workspace
    out = root / "oracle"
    args = [
        "eval",
        "oracle",
        "--split",
        "test",
        "--episodes",
        str(root / "test.json.gz"),
        "--workers",
        "1",
        "--out",
        str(out),
    ]
    assert main(args) == 0
    record = json.loads((out / "test.json").read_text())
    assert record["estimates"]["success"]["mean"] == 1.0 and record["estimates"]["spl"]["mean"] == 1.0
    assert "| oracle | 100.0" in (out / "test.md").read_text()
    # Where the numbers came from: the commit, versions, threads and cores (mapless.provenance).
    assert _same_code(record["provenance"]) and "Made by mapless" in (out / "test.md").read_text()
    runs = sorted((root / "runs").glob("a3c__*"))
    if runs:  # the run of the reproduce test: select on val, report on test, with 2 workers
        val = ["--episodes", str(root / "test.json.gz")]
        assert (
            main(
                ["eval", str(runs[0]), "--split", "test", *val, "--workers", "2", "--out", str(root / "sel")]
            )
            == 0
        )
        assert (root / "sel" / "test.json").is_file()


@pytest.mark.slow
def test_eval_cli_adapted_unadapted_and_at_another_inner_rate(workspace, capsys):
    """`mapless eval` of one adaptive model file three ways, and `mapless compare` of two of them."""
    from train_fixtures import tiny_config

    from mapless import checkpoint as ckpt
    from mapless.models import build_model

    root, _ = workspace
    config = tiny_config("cvmeta")
    model = root / "cvmeta.pt"
    ckpt.atomic_save(
        ckpt.model_payload(build_model(config.model).state_dict(), config, {"episodes": 1}), model
    )
    episodes = str(root / "test.json.gz")
    common = ["eval", str(model), "--split", "test", "--episodes", episodes, "--workers", "1"]
    records = {}
    for name, extra in (("adapted", []), ("theta0", ["--no-adapt"]), ("fast", ["--inner-lr", "0.5"])):
        assert main([*common, *extra, "--out", str(root / name)]) == 0
        records[name] = json.loads((root / name / "test.json").read_text())
    assert "test_time_adaptation" not in records["adapted"]
    assert records["theta0"]["test_time_adaptation"] == {"adapt": False, "inner_lr": None}
    assert records["fast"]["test_time_adaptation"] == {"adapt": True, "inner_lr": 0.5}
    assert "never adapted at test time" in records["theta0"]["protocol_label"]
    capsys.readouterr()
    assert main(["compare", str(root / "theta0" / "test.json"), str(root / "adapted" / "test.json")]) == 0
    assert "A and B took exactly the same actions in" in capsys.readouterr().out
    # Selection scores checkpoints as trained; untrained baselines have nothing to adapt.
    assert main([*common, "--no-adapt", "--select", "--out", str(root / "x")]) == 2
    assert "selection scores each checkpoint as trained" in capsys.readouterr().err
    assert main(["eval", "random", "--inner-lr", "0.1", "--out", str(root / "x")]) == 2
    assert "for a trained adaptive model" in capsys.readouterr().err


@pytest.mark.slow
def test_reproduce_and_eval_under_the_reference_protocol(workspace, capsys):
    from mapless.episodes.protocols import PROTOCOLS

    root, config = workspace
    rule = PROTOCOLS["reference"].sim(SimConfig())
    library = SceneLibrary.builtin(rule)
    for split, scene, seed in (("ref_val", "FloorPlan21", 0), ("ref_test", "FloorPlan22", 1)):
        # The protocol's runs train on the published episodes' classes (hoz22): episodes of theirs.
        episodes = make_episodes(library, scene, 6, seed, HOZ_KITCHEN)
        evalsets.save(root / f"{split}.json.gz", episodes, split, "hoz22", 0, fingerprint(rule))
    text = (
        config.read_text()
        .replace("val.json.gz", "ref_val.json.gz")
        .replace("test.json.gz", "ref_test.json.gz")
    )
    reference_config = root / "table1_reference.yaml"
    reference_config.write_text(text.replace("models: [random, a3c]", "models: [a3c]"))
    argv = ["reproduce", "table1", "--budget", "smoke", "--config", str(reference_config)]
    assert main([*argv, "--protocol", "reference", "--reports", str(root / "reports")]) == 0
    report = (root / "reports" / "table1-reference" / "table1.md").read_text()
    assert "REFERENCE PROTOCOL" in report and "--protocol reference" in report
    experiment = load_experiment("table1", "smoke", reference_config, ["eval.protocol=reference"])
    cfg = train_config(experiment, "a3c", 1)
    run = run_dir_for(experiment, cfg, "all")
    assert cfg.env.sim.visibility_distance == 1.5 and (run / "final_model.pt").is_file()
    assert cfg.env.target_set == "hoz22"
    # The run scored on the reference test episodes, selected on the reference val set's episodes.
    out = root / "reference_eval"
    argv = [
        "eval",
        str(run),
        "--protocol",
        "reference",
        "--split",
        "test",
        "--episodes",
        str(root / "ref_test.json.gz"),
    ]
    assert main([*argv, "--workers", "1", "--out", str(out)]) == 0
    record = json.loads((out / "ref_test.json").read_text())
    assert record["protocol"] == "reference" and "within 1.5 m" in record["protocol_label"]


@pytest.mark.slow
def test_eval_on_a_published_episode_pickle(workspace, capsys):
    import pickle

    root, _ = workspace
    sample = Path(__file__).resolve().parent / "data" / "hoz_bathroom_val_22_sample.pkl"
    entries = [e for e in pickle.loads(sample.read_bytes()) if e["scene"] == "FloorPlan425"][:8]
    entries.append({**entries[0], "scene": "FloorPlan9999"})  # not an iTHOR scene: skipped, with the reason
    cut = root / "bathroom_val.pkl"
    cut.write_bytes(pickle.dumps(entries))
    out = root / "published"
    assert main(["eval", "oracle", "--episodes", str(cut), "--workers", "1", "--out", str(out)]) == 0
    assert "8 of 9 episodes mapped" in capsys.readouterr().err
    # Named after the file's episodes, not the protocol's val set (issue 45, point 6).
    assert sorted(p.name for p in out.iterdir()) == ["bathroom_val.json", "bathroom_val.md"]
    assert (out / "bathroom_val.md").read_text().startswith("# oracle on bathroom_val (8 episodes)")
    record = json.loads((out / "bathroom_val.json").read_text())
    assert record["mapping"]["mapped"] == 8 and record["mapping"]["skipped"][0][0] == 8
    assert record["estimates"]["success"]["mean"] == 1.0 and len(record["episodes"][0]) == 8


@pytest.mark.parametrize(
    "experiment, seeds, runs",
    [
        ("table1", 3, {"a3c": 3, "mjolnir_o": 3, "cvmeta": 3, "mlp": 3}),  # random is not trained
        ("table2", 2, {"cvmeta": 8, "mjolnir_o": 8}),  # 4 training room types x 2 seeds
        ("table3", 2, {"cvmeta": 10}),  # the full model and 4 ablations x 2 seeds
        ("figure3", 1, {"a3c": 1, "mjolnir_o": 1, "cvmeta": 1, "mlp": 1}),  # Table 1's runs
    ],
)
def test_planned_runs_of_the_shipped_small_configs(experiment, seeds, runs):
    assert planned_runs(load_experiment(experiment, "small", seeds=seeds)) == runs


def _fake_clock(monkeypatch, readings: list[float]) -> None:
    clock = iter(readings)
    monkeypatch.setattr("mapless.experiments.runs.time.perf_counter", lambda: next(clock))


def test_run_tally_estimates_the_time_left_from_the_runs_it_trained(monkeypatch):
    # A run trained in 10 min, one reused in 5 s, then one resumed half-way that took 6 min (12 a run).
    _fake_clock(monkeypatch, [0.0, 600.0, 600.0, 605.0, 965.0, 965.0])  # a reused run reads no clock
    lines: list[str] = []
    tally = RunTally(planned={"cvmeta": 4}, log=lines.append)
    tally.start("cvmeta", "all, seed 1")
    tally.finish(1.0)
    tally.start("cvmeta", "all, seed 2")
    tally.finish(0.0)
    tally.start("cvmeta", "no-kitchen, seed 1")
    tally.finish(0.5)
    tally.start("cvmeta", "no-kitchen, seed 2")
    assert lines == [
        "[run 1 of 4] cvmeta all, seed 1",
        "[run 2 of 4] cvmeta all, seed 2; about 30 min left (10 min per cvmeta run)",
        "[run 3 of 4] cvmeta no-kitchen, seed 1; about 20 min left (10 min per cvmeta run)",
        "[run 4 of 4] cvmeta no-kitchen, seed 2; about 11 min left (11 min per cvmeta run)",
    ]


def test_run_tally_times_each_model_by_its_own_runs(monkeypatch):
    # Table 1 order: a3c's runs (4 min each), then cvmeta's (20 min each; seed 1 reused).
    _fake_clock(monkeypatch, [0, 240, 240, 480, 480, 480, 1680, 1680])  # the reused run reads one
    lines: list[str] = []
    tally = RunTally(planned={"a3c": 2, "cvmeta": 3}, log=lines.append)
    for model, seed, share in [("a3c", 1, 1.0), ("a3c", 2, 1.0), ("cvmeta", 1, 0.0), ("cvmeta", 2, 1.0)]:
        tally.start(model, f"all, seed {seed}")
        tally.finish(share)
    tally.start("cvmeta", "all, seed 3")
    assert lines == [
        "[run 1 of 5] a3c all, seed 1",
        "[run 2 of 5] a3c all, seed 2; about 4 min left for a3c; no cvmeta run timed yet (4 min per a3c run)",
        "[run 3 of 5] cvmeta all, seed 1; no cvmeta run timed yet (4 min per a3c run)",
        "[run 4 of 5] cvmeta all, seed 2; no cvmeta run timed yet (4 min per a3c run)",
        "[run 5 of 5] cvmeta all, seed 3; about 20 min left (4 min per a3c run, 20 min per cvmeta run)",
    ]


@pytest.mark.parametrize(
    "args", [["--batch-size", "0"], ["--batch-size", "-3"], ["--per-room", "0"], ["--workers", "0"]]
)
def test_eval_refuses_non_positive_counts(args: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as stop:
        main(["eval", "random", *args])
    assert stop.value.code == 2
    assert "must be >= 1" in capsys.readouterr().err


def test_experiment_eval_settings_and_every_models_training_config_are_checked_on_load() -> None:
    from mapless.config import ConfigError

    with pytest.raises(ConfigError, match=r"eval\.batch_size"):
        load_experiment("table1", "smoke", overrides=["eval.batch_size=0"])
    with pytest.raises(ConfigError, match=r"eval\.within_minutes"):
        load_experiment("table1", "smoke", overrides=["eval.within_minutes=[60, 0]"])
    # a3c is not the focus model: its block is checked all the same, before any run starts
    with pytest.raises(ConfigError, match=r"ppo\.minibatches"):
        load_experiment(
            "table1", "smoke", overrides=["per_model.a3c.algo=ppo", "per_model.a3c.ppo.minibatches=999"]
        )


def test_the_time_limit_bootstrap_names_the_run_folders_of_the_models_it_trains() -> None:
    # A run folder is named after the whole training config as it is laid out, so the setting moves
    # the folders of the models whose training it changes: the adaptive models' whole episodes.
    experiment = load_experiment("table1", "small")

    def folder(model: str, *overrides: str) -> Path:
        config = load_experiment("table1", "small", overrides=list(overrides))
        return run_dir_for(experiment, train_config(config, model, seed=1), "all")

    off = "train.ppo.bootstrap_time_limit=false"
    assert folder("cvmeta") != folder("cvmeta", off)
    assert folder("savn") != folder("savn", off)


@pytest.mark.slow
def test_reproduce_ablation_rows_against_the_focus_model(workspace):
    """A row that trains (its own runs, named after it) and a row that only evaluates the focus
    model's chosen snapshot without test-time adaptation, each paired with the focus model."""
    root, config = workspace
    reports = root / "reports"
    ablation = root / "ablation.yaml"
    ablation.write_text(
        config.read_text().replace("experiment: table1", "experiment: ablation")
        .replace("models: [random, a3c]", "models: [cvmeta]").replace("focus: a3c", "focus: cvmeta")
        + """ablations:
  a_unadapted: {what: no test-time adaptation, test_time_adaptation: false}
  c_no_parent: {what: parent reward off, train: {env: {reward: {parent_reward: false}}}}
  z_unused: {what: not run, train: {model: {fusion_channels: 4}}}
ablation_rows: [a_unadapted, c_no_parent]
"""
    )  # fmt: skip
    assert main(["reproduce", "ablation", "--config", str(ablation), "--reports", str(reports)]) == 0
    payload = json.loads((reports / "ablation" / "ablation.json").read_text())
    focus, unadapted, no_parent = payload["models"]
    assert [m.get("row") for m in payload["models"]] == ["focus", "a_unadapted", "c_no_parent"]
    assert unadapted["runs"][0]["run_dir"] == focus["runs"][0]["run_dir"]
    assert "__ablation-c_no_parent__" in no_parent["runs"][0]["run_dir"]
    for row in (unadapted, no_parent):
        difference = row["minus_focus"]["success"]["mean"]
        assert difference == pytest.approx(
            row["estimates"]["success"]["mean"] - focus["estimates"]["success"]["mean"]
        )
    # Row a is the focus model's chosen snapshot evaluated by an agent that never adapts.
    chosen = Path(focus["runs"][0]["selection"]["chosen"])
    assert unadapted["runs"][0]["model_file"] == str(chosen)
    (cache,) = (chosen.parent.parent / "eval").glob("unadapted_*.json")
    assert json.loads(cache.read_text())["key"]["spec"]["adapt"] is False
    # How much adapting changes the agent: the share of episodes with every action equal.
    pairs = zip(focus["episodes"][0], unadapted["episodes"][0], strict=True)
    same = [a["actions"] == b["actions"] for a, b in pairs]
    assert unadapted["same_actions"] == [pytest.approx(sum(same) / len(same))]
    assert "same_actions" not in no_parent  # other runs: a different agent, not a measure of adapting
    md = (reports / "ablation" / "ablation.md").read_text()
    assert "Δ false Done" in md and "c_no_parent" in md and "z_unused" not in md
    assert "Row a_unadapted acts exactly as cvmeta (the same snapshots and action draws" in md
    # The trained runs' training logs, drawn and compared at equal frames; row a trained nothing.
    curve = no_parent["runs"][0]["training"]
    assert curve["frames"] == sorted(curve["frames"]) and len(curve["success"]) == len(curve["frames"])
    assert "training" not in unadapted["runs"][0]
    assert (reports / "ablation" / "ablation_training.png").is_file()
    assert "| model | frames trained | success at " in md


def test_an_ablation_row_that_changes_nothing_or_names_no_row_is_refused(tmp_path):
    path = tmp_path / "ablation.yaml"
    path.write_text("experiment: ablation\nbudget: smoke\nablations:\n  x: {what: nothing}\n")
    with pytest.raises(ConfigError, match="changes nothing"):
        load_experiment("ablation", "smoke", path=path)
    path.write_text(
        "experiment: ablation\nbudget: smoke\nablations:\n  x: {what: w, train: {model: {gcn_hidden: 8}}}\n"
    )
    with pytest.raises(ConfigError, match="unknown ablation row 'y'"):
        load_experiment("ablation", "smoke", path=path, overrides=["ablation_rows=[y]"])
    path.write_text(
        "experiment: ablation\nbudget: smoke\nablations:\n  x: {what: w, train: {model: {widht: 8}}}\n"
    )
    with pytest.raises(ConfigError, match="widht"):
        load_experiment("ablation", "smoke", path=path)


def test_the_medium_ablation_extends_the_small_one_and_plans_its_runs():
    small, medium = load_experiment("ablation", "small"), load_experiment("ablation", "medium")
    assert medium.ablations == small.ablations and medium.budget == "medium"
    assert medium.train["max_seconds"] == 3600 and small.train["max_seconds"] == 900
    # Two seeds of the focus model and of rows d, f, j, k, l, n, o, p, q and r, one of the seven rows
    # with `seeds: 1`; row a only evaluates the focus model's runs.
    assert planned_runs(small) == {"cvmeta": 2 * 11 + 7}
    assert planned_runs(load_experiment("ablation", "small", seeds=3)) == {"cvmeta": 3 * 11 + 7}


@pytest.mark.slow
def test_selection_may_read_a_subset_while_the_report_reads_every_episode(workspace):
    from mapless.experiments.evaluator import Evaluator

    _root, config = workspace
    ev = Evaluator(
        load_experiment("table1", "smoke", path=config, overrides=["eval.select_per_room=2"]), print
    )
    assert (len(ev.select_episodes), len(ev.report_episodes)) == (2, 6)
    whole = Evaluator(load_experiment("table1", "smoke", path=config), print)
    assert len(whole.select_episodes) == 6
    assert [e.start for e in ev.select_episodes] == [e.start for e in whole.select_episodes[:2]]
    with pytest.raises(ConfigError, match="select_per_room"):
        load_experiment("table1", "smoke", path=config, overrides=["eval.select_per_room=0"])


def test_an_adaptive_checkpoint_evaluated_without_adaptation_acts_as_a_plain_policy(tmp_path):
    from train_fixtures import tiny_config

    from mapless import checkpoint as ckpt
    from mapless.agent.evaluation import AdaptiveModelAgent, ModelAgent
    from mapless.evaluate.runner import AgentSpec
    from mapless.models import build_model

    config = tiny_config("cvmeta")
    path = tmp_path / "cvmeta.pt"
    ckpt.atomic_save(
        ckpt.model_payload(build_model(config.model).state_dict(), config, {"episodes": 1}), path
    )
    assert isinstance(AgentSpec(checkpoint=str(path)).build(2), AdaptiveModelAgent)
    agent = AgentSpec(checkpoint=str(path), adapt=False).build(2)
    assert isinstance(agent, ModelAgent) and not isinstance(agent, AdaptiveModelAgent)


def test_an_adaptive_checkpoint_adapts_at_a_test_time_inner_rate_when_given_one(tmp_path):
    from train_fixtures import tiny_config

    from mapless import checkpoint as ckpt
    from mapless.errors import MaplessError
    from mapless.evaluate.runner import AgentSpec
    from mapless.models import build_model

    paths = {}
    for name in ("cvmeta", "a3c"):
        config = tiny_config(name)
        paths[name] = tmp_path / f"{name}.pt"
        ckpt.atomic_save(
            ckpt.model_payload(build_model(config.model).state_dict(), config, {"episodes": 1}), paths[name]
        )
    assert AgentSpec(checkpoint=str(paths["cvmeta"])).build(2).adapter.loop.inner_lr == 1e-3  # the paper's
    assert AgentSpec(checkpoint=str(paths["cvmeta"]), inner_lr=0.05).build(2).adapter.loop.inner_lr == 0.05
    with pytest.raises(MaplessError, match="needs an adaptive model"):
        AgentSpec(checkpoint=str(paths["a3c"]), inner_lr=0.05).build(2)


@pytest.mark.slow
def test_the_paper_protocol_selects_and_reports_on_the_same_episodes_whatever_select_per_room(workspace):
    from mapless.experiments.evaluator import Evaluator

    _root, config = workspace
    overrides = ["eval.select_per_room=2", "eval.protocol=paper", "eval.select_file=null"]
    ev = Evaluator(load_experiment("table1", "smoke", path=config, overrides=overrides), print)
    assert ev.select_episodes is ev.report_episodes and len(ev.report_episodes) == 6


@pytest.mark.slow
def test_table1_within_minutes_chooses_each_run_again_among_its_early_snapshots(workspace):
    root, config = workspace
    reports = root / "reports_within"
    args = ["--config", str(config), "--reports", str(reports), "--set", "eval.within_minutes=[10000]"]
    assert main(["reproduce", "table1", *args]) == 0  # reuses the finished a3c run
    payload = json.loads((reports / "table1" / "table1.json").read_text())
    a3c = next(m for m in payload["models"] if m["model"] == "a3c")
    (capped,) = payload["by_minutes"]["10000"]  # random does not train: not listed
    assert capped["model"] == "a3c ≤ 10000 min" and capped["within_minutes"] == 10000
    # Every snapshot is within so long a cap: the same choice, the same episodes.
    assert capped["runs"][0]["selection"]["chosen"] == a3c["runs"][0]["selection"]["chosen"]
    assert capped["episodes"] == a3c["episodes"]
    md = (reports / "table1" / "table1.md").read_text()
    assert "Chosen among the snapshots of the first 10000 minutes of training" in md
    assert "| a3c ≤ 10000 min |" in md and "Chosen snapshots (per seed" in md
