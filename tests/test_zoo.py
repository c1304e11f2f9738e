"""The zoo of shipped agents and results: `mapless zoo add` stores a finished run's chosen agent at half
precision with its per-episode results and a manifest, and refuses weights whose SR leaves the float32
interval; `mapless zoo` lists the entries; `mapless eval zoo:…` evaluates the shipped weights and
`mapless compare` pairs shipped results with each other, with a result file or with a run, on the
same episodes only. Tiny runs on the hand-made training scenes, in a zoo folder of the test's own."""

from __future__ import annotations

import gzip
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from train_fixtures import fixture_library, tiny_config

from mapless.checkpoint import FINAL_MODEL_FILE, load_file, load_model
from mapless.cli import main
from mapless.episodes import evalsets
from mapless.evaluate import zoo
from mapless.evaluate.metrics import EpisodeResult
from mapless.evaluate.runner import LibrarySpec
from mapless.evaluate.stats import difference_estimates
from mapless.provenance import run_provenance
from mapless.sim.episode import Episode
from mapless.train.run import train

pytestmark = pytest.mark.usefixtures("single_torch_thread")

WORKERS = ["--workers", "1", "--batch-size", "4"]


def _episodes(n_per_scene: int = 8) -> list[Episode]:
    """Episodes on the training fixture's two kitchens whose targets start out of sight."""
    rng = np.random.default_rng(3)
    library, episodes = fixture_library(), []
    for scene in ("FloorPlan1", "FloorPlan2"):
        data, made = library[scene], 0
        while made < n_per_scene:
            target = ("Mug", "Toaster", "DiningTable")[rng.integers(3)]
            start = int(rng.choice(np.flatnonzero(data.horizon == 0)))
            d = int(data.target_distances(target)[start])
            if d > 0:
                pose = (float(data.x[start]), float(data.z[start]), int(data.yaw[start]), 0)
                episodes.append(Episode(scene, target, pose, d + 1, episode_id=f"{scene}/{made}"))
                made += 1
    return episodes


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    """Two tiny trained runs, an episode file on their scenes, and an empty zoo folder."""
    root = tmp_path_factory.mktemp("zoo")
    runs = {}
    for model in ("a3c", "mlp"):
        runs[model] = root / f"run_{model}"
        train(tiny_config(model, "seed=2"), runs[model], library_factory=fixture_library)
    episode_file = root / "tiny_test.json.gz"
    evalsets.save(episode_file, _episodes(), "test", "mjolnir22", 0, "fixture")
    return {"runs": runs, "episodes": episode_file, "zoo": root / "zoo", "root": root}


@pytest.fixture
def fixture_scenes(monkeypatch, setup):
    """Runs evaluated on the hand-made scenes they trained on, and the test's zoo folder."""
    monkeypatch.setattr(
        LibrarySpec,
        "for_env",
        classmethod(lambda cls, env, offline_dir=None: cls(factory="train_fixtures:fixture_library")),
    )
    monkeypatch.setenv(zoo.ROOT_VARIABLE, str(setup["zoo"]))
    return setup


def _add(setup, model: str, *extra: str) -> int:
    return main(["zoo", "add", str(setup["runs"][model]), "--experiment", "tiny-smoke",
                 "--episodes", str(setup["episodes"]), *WORKERS, *extra])  # fmt: skip


@pytest.fixture(scope="module")
def added(setup):
    """Both runs added to the zoo (once for the module)."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(
            LibrarySpec, "for_env",
            classmethod(lambda cls, env, offline_dir=None: cls(factory="train_fixtures:fixture_library")),
        )  # fmt: skip
        patch.setenv(zoo.ROOT_VARIABLE, str(setup["zoo"]))
        assert _add(setup, "a3c") == 0
        assert _add(setup, "mlp") == 0
    return setup


def test_an_added_entry_holds_half_precision_weights_its_results_and_a_manifest(added):
    entry = zoo.entry("zoo:tiny-smoke/a3c", added["zoo"])
    assert sorted(p.name for p in entry.folder.iterdir()) == ["manifest.json", "model.pt", "results.json.gz"]
    manifest = entry.manifest
    run = added["runs"]["a3c"]
    final = load_file(run / FINAL_MODEL_FILE)
    assert (manifest["experiment"], manifest["model"], manifest["budget"]) == ("tiny-smoke", "a3c", "smoke")
    assert manifest["seed"] == 2 and manifest["protocol"] == "standard"
    assert manifest["training_commit"] == run_provenance(run / "config.yaml")[0]["commit"]
    assert manifest["frames"] == final["counters"]["frames"]
    assert manifest["snapshot"]["chosen_by"] == "the final model"
    episodes = evalsets.load(added["episodes"])[0]
    assert manifest["episodes"]["count"] == len(episodes) == 16
    assert entry.episodes() == episodes
    check = manifest["half_precision"]
    low, high = check["float32_ci"]
    assert low <= check["float16_sr"] <= high
    # SR is the share of successes among the stored results, as stored in the manifest.
    results = entry.results()[0]
    assert manifest["success"]["mean"] == pytest.approx(sum(r.success for r in results) / 16)
    assert manifest["success"]["mean"] == pytest.approx(check["float32_sr"])
    # The stored weights are float16 and load back into float32, rounded once.
    shipped = load_file(entry.model_file)
    floats = [k for k, v in final["model"].items() if v.is_floating_point()]
    assert floats and all(shipped["model"][k].dtype == torch.float16 for k in floats)
    model, _, _ = load_model(entry.model_file)
    state = model.state_dict()
    for key in floats:
        assert state[key].dtype == torch.float32
        assert torch.equal(state[key], final["model"][key].half().float())


def test_half_precision_keeps_integer_tensors_and_rounds_floats():
    weights = {"w": torch.tensor([1.0, 1e-4 + 1.0, 70000.0]), "steps": torch.tensor([3], dtype=torch.int64)}
    half = zoo.half_precision(weights)
    assert half["w"].dtype == torch.float16 and half["steps"].dtype == torch.int64
    assert half["w"][0].item() == 1.0 and half["w"][1].item() == 1.0  # below float16's resolution at 1
    assert torch.isinf(half["w"][2])  # past float16's range: load_file refuses such a model as diverged


def test_the_listing_names_each_entry_with_its_sr_and_commits(added, capsys, monkeypatch):
    monkeypatch.setenv(zoo.ROOT_VARIABLE, str(added["zoo"]))
    assert main(["zoo"]) == 0
    out = capsys.readouterr().out
    for model in ("a3c", "mlp"):
        manifest = zoo.entry(f"zoo:tiny-smoke/{model}").manifest
        line = next(line for line in out.splitlines() if f"zoo:tiny-smoke/{model} " in line)
        assert f"{100 * manifest['success']['mean']:.1f} [" in line
        assert (manifest["training_commit"] or "unknown")[:12] in line
    assert main(["zoo", "list"]) == 0 and capsys.readouterr().out == out


def test_the_shipped_random_rows_list_as_untrained_and_trained_rows_by_commit(monkeypatch):
    monkeypatch.delenv(zoo.ROOT_VARIABLE, raising=False)
    lines = {line.split(" | ")[0].strip("| "): line for line in zoo.listing().splitlines()[2:]}
    assert "| untrained |" in lines["zoo:table1-small-seeds/random"]
    trained_at = lines["zoo:table1-small/a3c"].split(" | ")[-2]
    assert trained_at == zoo.entry("zoo:table1-small/a3c").manifest["training_commit"][:12]


def test_an_empty_zoo_says_it_has_no_entries(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv(zoo.ROOT_VARIABLE, str(tmp_path / "none"))
    assert main(["zoo"]) == 0
    assert "no entries" in capsys.readouterr().out


def test_the_package_zoo_is_present_and_within_its_size(monkeypatch):
    monkeypatch.delenv(zoo.ROOT_VARIABLE, raising=False)
    root = zoo.zoo_root()
    assert root.is_dir() and (root / "README.md").is_file()
    assert zoo.folder_size() <= zoo.MAX_BYTES
    for entry in zoo.entries():  # every shipped entry is complete and consistent with its manifest
        assert (not entry.has_weights or entry.model_file.is_file()) and entry.results()
    assert {e.name for e in zoo.entries() if not e.has_weights} >= {
        f"zoo:table1-small-seeds/{model}" for model in ("random", "a3c", "mjolnir_o", "cvmeta", "mlp")
    }


def _signed(value: float) -> str:
    return f"{'−' if value < 0 else '+'}{abs(value):.1f}"


def test_the_readme_difference_row_is_what_the_shipped_results_give(monkeypatch):
    monkeypatch.delenv(zoo.ROOT_VARIABLE, raising=False)
    a, b = (zoo.entry(f"zoo:table1-small-seeds/{m}").results() for m in ("a3c", "cvmeta"))
    assert len(a) == len(b) == 3
    d = difference_estimates(a, b, ["success", "spl"])
    sr, spl = (d[k] for k in ("success", "spl"))
    row = (
        f"cvmeta − a3c = {_signed(100 * sr.mean)} SR [{_signed(100 * sr.ci_low)}, {_signed(100 * sr.ci_high)}] "
        f"and {_signed(100 * spl.mean)} SPL\n[{_signed(100 * spl.ci_low)}, {_signed(100 * spl.ci_high)}]"
    )
    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    assert row in readme


def _report(config: dict, episodes: list[Episode], seeds: dict[str, int], commit: str = "c0ffee") -> dict:
    """An experiment report as reproduce writes it, with crafted results on ``episodes``: episode i
    of seed s succeeds when i + s is even."""

    def results(seed: int) -> list[dict]:
        return [
            EpisodeResult(i, e.episode_id, e.scene, "kitchen", e.target, (i + seed) % 2 == 0, 5,
                          max(e.optimal_length, 1), True, 0, 0.0, 0).to_dict()
            for i, e in enumerate(episodes)
        ]  # fmt: skip

    models = []
    for model, count in seeds.items():
        runs = [
            {"run_dir": f"runs/{model}__all__s{s}__0000000{s}",
             "selection": {"chosen": f"runs/x/model_{s}.pt", "candidates": [
                 {"path": f"runs/x/model_{s}.pt", "frames": 100 * s}]}}
            for s in range(1, count + 1)
        ]  # fmt: skip
        models.append({"model": model, "runs": runs, "episodes": [results(s) for s in range(1, count + 1)]})
    return {"experiment": "table1", "config": config, "models": models, "provenance": {"commit": commit}}


def test_a_report_s_rows_become_results_only_entries_with_every_seed(tmp_path, monkeypatch, capsys):
    from mapless.config import to_dict
    from mapless.experiments.config import load_experiment
    from mapless.experiments.evaluator import Evaluator

    monkeypatch.setenv(zoo.ROOT_VARIABLE, str(tmp_path / "zoo"))
    config = load_experiment("table1", "smoke", overrides=["eval.per_room=2", "eval.select_per_room=2"])
    episodes = Evaluator(config, log=lambda line: None).report_episodes
    assert len(episodes) == 8  # two per room type, the standard protocol's test set: no scenes needed
    report = _report(to_dict(config), episodes, {"a3c": 2, "cvmeta": 2})
    path = tmp_path / "table1.json"
    path.write_text(json.dumps(report))
    assert main(["zoo", "add-results", str(path), "--experiment", "rows-smoke"]) == 0
    assert "zoo:rows-smoke/a3c: results only, 2 seed(s), SR 50.0 %" in capsys.readouterr().out
    entry = zoo.entry("zoo:rows-smoke/a3c")
    assert not entry.has_weights and sorted(p.name for p in entry.folder.iterdir()) == [
        "manifest.json", "results.json.gz"]  # fmt: skip
    assert entry.episodes() == episodes
    stored = entry.results()
    assert [[r.to_dict() for r in seed] for seed in stored] == report["models"][0]["episodes"]
    manifest = entry.manifest
    assert manifest["seeds"] == 2 and manifest["report_commit"] == "c0ffee"
    assert manifest["runs"] == [
        {"run": "a3c__all__s1__00000001", "snapshot": "model_1.pt", "frames": 100},
        {"run": "a3c__all__s2__00000002", "snapshot": "model_2.pt", "frames": 200},
    ]
    assert (manifest["protocol"], manifest["budget"], manifest["episodes"]["count"]) == (
        "standard",
        "smoke",
        8,
    )
    # Seed 1 succeeds on odd episodes, seed 2 on even ones: SR 0.5 in each, over the seeds too.
    assert manifest["success"]["mean"] == 0.5 and manifest["success"]["seeds"] == 2
    # No weights: eval names the entries that have some; compare reads the rows.
    assert main(["eval", "zoo:rows-smoke/a3c"]) == 2
    assert "ships per-episode results only" in capsys.readouterr().err
    assert main(["compare", "zoo:rows-smoke/a3c", "zoo:rows-smoke/cvmeta"]) == 0
    d = difference_estimates(stored, zoo.entry("zoo:rows-smoke/cvmeta").results(), ["success"])["success"]
    assert d.mean == 0.0
    assert _row(capsys.readouterr().out, "SR")[3].startswith("+0.0 [")


def test_a_report_row_off_its_episodes_or_over_weights_is_refused(tmp_path, monkeypatch, capsys):
    from mapless.config import to_dict
    from mapless.experiments.config import load_experiment
    from mapless.experiments.evaluator import Evaluator

    monkeypatch.setenv(zoo.ROOT_VARIABLE, str(tmp_path / "zoo"))
    config = load_experiment("table1", "smoke", overrides=["eval.per_room=1", "eval.select_per_room=1"])
    episodes = Evaluator(config, log=lambda line: None).report_episodes
    report = _report(to_dict(config), episodes, {"a3c": 1})
    report["models"][0]["episodes"][0][2]["episode_id"] = "elsewhere"
    path = tmp_path / "table1.json"
    path.write_text(json.dumps(report))
    assert main(["zoo", "add-results", str(path), "--experiment", "rows"]) == 2
    assert "results not on the entry's episodes (episode 2 is" in capsys.readouterr().err
    assert not (tmp_path / "zoo").exists()
    # A row of a name whose entry ships weights is refused: the weights stay.
    path.write_text(json.dumps(_report(to_dict(config), episodes, {"a3c": 1})))
    weights = tmp_path / "zoo" / "rows" / "a3c" / zoo.MODEL_FILE
    weights.parent.mkdir(parents=True)
    weights.write_bytes(b"weights")
    assert main(["zoo", "add-results", str(path), "--experiment", "rows"]) == 2
    assert "ships weights" in capsys.readouterr().err and weights.read_bytes() == b"weights"
    assert main(["zoo", "add-results", str(path), "--experiment", "rows", "--models", "savn"]) == 2
    assert "has no model savn (it has a3c)" in capsys.readouterr().err
    path.write_text(json.dumps({"models": []}))
    assert main(["zoo", "add-results", str(path), "--experiment", "rows"]) == 2
    assert "is not an experiment report" in capsys.readouterr().err


def test_eval_of_a_shipped_agent_gives_its_half_precision_results(added, fixture_scenes, tmp_path, capsys):
    out = tmp_path / "out"
    assert (
        main(
            ["eval", "zoo:tiny-smoke/a3c", "--episodes", str(added["episodes"]), *WORKERS, "--out", str(out)]
        )
        == 0
    )
    record = json.loads((out / "tiny_test.json").read_text())
    assert record["model"] == "zoo:tiny-smoke/a3c"
    assert record["model_file"] == str(zoo.entry("zoo:tiny-smoke/a3c").model_file)
    sr = np.mean([e["success"] for e in record["episodes"][0]])
    assert sr == pytest.approx(zoo.entry("zoo:tiny-smoke/a3c").manifest["half_precision"]["float16_sr"])


def test_a_missing_entry_is_a_clear_error_naming_those_there_are(added, fixture_scenes, capsys):
    assert main(["eval", "zoo:tiny-smoke/savn"]) == 2
    error = capsys.readouterr().err
    assert "no zoo entry zoo:tiny-smoke/savn" in error
    assert "zoo:tiny-smoke/a3c" in error and "zoo:tiny-smoke/mlp" in error
    assert main(["compare", "zoo:tiny-smoke/a3c", "zoo:other/a3c"]) == 2
    assert "no zoo entry zoo:other/a3c" in capsys.readouterr().err


def _row(out: str, label: str) -> list[str]:
    line = next(line for line in out.splitlines() if line.startswith(f"| {label} |"))
    return [cell.strip() for cell in line.strip("|").split("|")]


def test_compare_of_two_entries_prints_the_paired_difference_from_the_shipped_results(
    added, capsys, monkeypatch
):
    monkeypatch.setenv(zoo.ROOT_VARIABLE, str(added["zoo"]))
    assert main(["compare", "zoo:tiny-smoke/a3c", "zoo:tiny-smoke/mlp"]) == 0
    out = capsys.readouterr().out
    assert "A: zoo:tiny-smoke/a3c" in out and "B: zoo:tiny-smoke/mlp" in out
    a = zoo.entry("zoo:tiny-smoke/a3c").results()[0]
    b = zoo.entry("zoo:tiny-smoke/mlp").results()[0]
    difference = 100 * (np.mean([r.success for r in b]) - np.mean([r.success for r in a]))
    assert _row(out, "SR")[3].startswith(f"{difference:+.1f} [")
    d = difference_estimates([a], [b], ["success"])["success"]
    assert _row(out, "SR")[3] == f"{100 * d.mean:+.1f} [{100 * d.ci_low:+.1f}, {100 * d.ci_high:+.1f}]"


def test_compare_pairs_a_result_file_or_a_run_with_an_entry_on_the_same_episodes_only(
    added, fixture_scenes, tmp_path, capsys
):
    out = tmp_path / "eval"
    run = added["runs"]["mlp"]
    assert main(["eval", str(run), "--episodes", str(added["episodes"]), *WORKERS, "--out", str(out)]) == 0
    capsys.readouterr()
    result_file = out / "tiny_test.json"
    assert main(["compare", str(result_file), "zoo:tiny-smoke/a3c"]) == 0
    assert "B: zoo:tiny-smoke/a3c" in capsys.readouterr().out
    # A run folder beside an entry is evaluated on the entry's episodes, as its own eval was.
    assert main(["compare", "zoo:tiny-smoke/a3c", str(run)]) == 0
    assert _row(capsys.readouterr().out, "SR")[2].startswith(
        f"{100 * np.mean([e['success'] for e in json.loads(result_file.read_text())['episodes'][0]]):.1f}"
    )
    assert list((run / "eval").glob("zoo_final_model_*.json"))
    # Other episodes: fewer of them (both scenes are kitchens), or as many but not the same ones.
    assert main(["eval", str(run), "--episodes", str(added["episodes"]), "--per-room", "5", *WORKERS,
                 "--out", str(tmp_path / "fewer")]) == 0  # fmt: skip
    capsys.readouterr()
    assert main(["compare", str(tmp_path / "fewer" / "tiny_test.json"), "zoo:tiny-smoke/a3c"]) == 2
    assert "not the same episodes (5 episodes against 16)" in capsys.readouterr().err
    record = json.loads(result_file.read_text())
    record["episodes"][0][3]["episode_id"] = "FloorPlan1/elsewhere"
    (tmp_path / "other.json").write_text(json.dumps(record))
    assert main(["compare", "zoo:tiny-smoke/a3c", str(tmp_path / "other.json")]) == 2
    assert "episode 3 is" in capsys.readouterr().err


def test_add_ships_the_snapshot_a_result_file_chose_and_its_results(added, fixture_scenes, capsys):
    run = added["runs"]["a3c"]
    snapshot = sorted((run / "checkpoints").glob("model_*.pt"))[0]
    out = run / "eval_first"
    assert (
        main(["eval", str(snapshot), "--episodes", str(added["episodes"]), *WORKERS, "--out", str(out)]) == 0
    )
    assert _add(added, "a3c", "--model", "a3c_first", "--results", str(out / "tiny_test.json")) == 0
    entry = zoo.entry("zoo:tiny-smoke/a3c_first")
    assert entry.manifest["snapshot"]["file"] == snapshot.name
    assert entry.manifest["snapshot"]["chosen_by"] == "tiny_test.json"
    chosen, shipped = load_file(snapshot)["model"], load_file(entry.model_file)["model"]
    assert all(torch.equal(shipped[k], v.half()) for k, v in chosen.items() if v.is_floating_point())
    stored = [r.to_dict() for r in entry.results()[0]]
    assert stored == json.loads((out / "tiny_test.json").read_text())["episodes"][0]


def test_add_refuses_half_precision_weights_outside_the_float32_interval(
    added, fixture_scenes, tmp_path, capsys
):
    # A result file crafted to claim SR 0 or 1 (an interval of one point) the weights do not score.
    entry = zoo.entry("zoo:tiny-smoke/a3c")
    claimed = entry.manifest["half_precision"]["float16_sr"] < 1.0
    results = [EpisodeResult.from_dict({**r.to_dict(), "success": claimed}) for r in entry.results()[0]]
    crafted = tmp_path / "crafted.json"
    crafted.write_text(json.dumps({"model": "a3c", "episodes": [[r.to_dict() for r in results]]}))
    before = sorted(p.name for p in (added["zoo"] / "tiny-smoke").iterdir())
    assert _add(added, "a3c", "--model", "a3c_crafted", "--results", str(crafted)) == 2
    error = capsys.readouterr().err
    assert "outside the float32 SR" in error and "nothing was added" in error
    assert sorted(p.name for p in (added["zoo"] / "tiny-smoke").iterdir()) == before
    # And on its own: a check that passes and one that fails, by hand.
    full = [EpisodeResult.from_dict({**r.to_dict(), "success": i % 2 == 0}) for i, r in enumerate(results)]
    assert zoo.half_precision_check(full, full)["float16_sr"] == 0.5
    with pytest.raises(zoo.ZooError, match=r"SR 0\.0 %"):
        zoo.half_precision_check(
            full, [EpisodeResult.from_dict({**r.to_dict(), "success": False}) for r in full]
        )


def test_add_refuses_a_bad_name_or_an_unwritable_zoo_before_evaluating(
    added, fixture_scenes, tmp_path, monkeypatch, capsys
):
    def no_evaluation(*args, **kwargs):
        raise AssertionError("evaluated before the entry's name and folder were checked")

    monkeypatch.setattr("mapless.evaluate.runner.evaluate", no_evaluation)
    bad = [
        "zoo",
        "add",
        str(added["runs"]["a3c"]),
        "--experiment",
        "a/b",
        "--episodes",
        str(added["episodes"]),
    ]
    assert main(bad) == 2
    assert "named <experiment>/<model>" in capsys.readouterr().err
    taken = tmp_path / "a_file"
    taken.write_text("not a zoo")
    monkeypatch.setenv(zoo.ROOT_VARIABLE, str(taken))
    assert _add(added, "a3c") == 2
    error = capsys.readouterr().err
    assert f"cannot add zoo:tiny-smoke/a3c: {taken} is not a folder" in error and "$MAPLESS_ZOO" in error


def test_results_whose_episodes_the_manifest_does_not_match_are_refused(added, tmp_path):
    source = zoo.entry("zoo:tiny-smoke/a3c", added["zoo"]).folder
    copy = tmp_path / "zoo" / "tiny-smoke" / "a3c"
    copy.mkdir(parents=True)
    for name in ("manifest.json", "model.pt"):
        (copy / name).write_bytes((source / name).read_bytes())
    data = json.loads(gzip.decompress((source / zoo.RESULTS_FILE).read_bytes()))
    data["episode_set"][0]["target"] = "Apple"
    (copy / zoo.RESULTS_FILE).write_bytes(gzip.compress(json.dumps(data).encode()))
    with pytest.raises(zoo.ZooError, match="do not match the digest"):
        zoo.entry("zoo:tiny-smoke/a3c", tmp_path / "zoo").results()


def test_a_zoo_root_is_taken_from_the_argument_then_the_variable(tmp_path, monkeypatch):
    monkeypatch.setenv(zoo.ROOT_VARIABLE, str(tmp_path / "env"))
    assert zoo.zoo_root() == tmp_path / "env"
    assert zoo.zoo_root(tmp_path / "arg") == tmp_path / "arg"
    monkeypatch.delenv(zoo.ROOT_VARIABLE)
    assert zoo.zoo_root() == Path(zoo.__file__).parents[1] / "data" / "zoo"


def test_add_reads_the_choice_and_settings_of_an_evaluation_cache_and_of_an_experiment_report(
    added, fixture_scenes, tmp_path, capsys
):
    from mapless.evaluate.runner import AgentSpec, EvalSettings
    from mapless.evaluate.selection import cached_evaluate

    run = added["runs"]["mlp"]
    snapshot = sorted((run / "checkpoints").glob("model_*.pt"))[0]
    cache = tmp_path / "test_snapshot.json"
    settings = EvalSettings(batch_size=4, workers=1, seed=5, category_set="mjolnir101")
    library = LibrarySpec(factory="train_fixtures:fixture_library")
    cached = cached_evaluate(
        AgentSpec(checkpoint=str(snapshot)), _episodes(), settings, library, cache
    ).results
    assert _add(added, "mlp", "--model", "mlp_cache", "--results", str(cache)) == 0
    manifest = zoo.entry("zoo:tiny-smoke/mlp_cache").manifest
    assert manifest["snapshot"]["file"] == snapshot.name and manifest["eval_settings"]["seed"] == 5
    assert zoo.entry("zoo:tiny-smoke/mlp_cache").results()[0] == cached
    # An experiment report: the run's seed among the model's runs, and the snapshot its selection chose.
    other = {"run_dir": str(tmp_path / "another_run"), "selection": {"chosen": "elsewhere.pt"}}
    mine = {"run_dir": str(run), "selection": {"chosen": str(snapshot)}}
    episodes = [[r.to_dict() for r in cached]]
    report = {"models": [{"model": "mlp", "runs": [other, mine], "episodes": [episodes[0], episodes[0]]}]}
    (tmp_path / "table1.json").write_text(json.dumps(report))
    assert _add(added, "mlp", "--model", "mlp_report", "--results", f"{tmp_path / 'table1.json'}:mlp") == 0
    assert zoo.entry("zoo:tiny-smoke/mlp_report").manifest["snapshot"]["file"] == snapshot.name
    report["models"][0]["runs"] = [other]
    report["models"][0]["episodes"] = [episodes[0]]
    (tmp_path / "table1.json").write_text(json.dumps(report))
    assert _add(added, "mlp", "--model", "mlp_none", "--results", f"{tmp_path / 'table1.json'}:mlp") == 2
    assert f"holds no results of {run}" in capsys.readouterr().err
