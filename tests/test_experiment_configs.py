"""The shipped experiment configs: each experiment read over its budget resolves to exactly the
configuration captured in tests/data/experiment_configs_resolved.json, every run an experiment plans
keeps the folder recorded in tests/data/run_folders.json, and the composition rules (every layer
read over the one below key by key: an experiment over its budget, overrides last; budgets and
experiment files that extend others; an experiment without a file is its budget as it is) hold on
crafted files. A change
of what a shipped experiment trains, or of where its runs are kept, fails here until the captures
are regenerated with it, on purpose; git keeps the record of each such change."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from captures import run_folders

from mapless.config import ConfigError, read_mapping, to_dict
from mapless.errors import MaplessError, UnknownNameError
from mapless.experiments import (
    BUDGETS,
    EXPERIMENTS,
    config_path,
    load_experiment,
    read_experiment,
    train_config,
)
from mapless.experiments.config import read_budget, shipped_experiment
from mapless.experiments.runs import run_dir_for

DATA = Path(__file__).parent / "data"
RESOLVED = json.loads((DATA / "experiment_configs_resolved.json").read_text())
#: The run folder of seed 1 of every trained model (and ablation row) of the small, medium and long
#: experiments under both protocols: a refactor of the configs must not move one
#: (``python tests/captures.py`` regenerates both captures after a deliberate change).
RUN_FOLDERS = json.loads((DATA / "run_folders.json").read_text())


#: Every experiment and budget captured when each had its own file; since the configs became package
#: data, one that differs from its budget in nothing has no file (table1_small is the small budget).
SHIPPED = [(e, b) for e in EXPERIMENTS for b in BUDGETS if f"{e}_{b}" in RESOLVED]


def test_every_shipped_experiment_file_has_captured_values() -> None:
    files = {f"{e}_{b}" for e in EXPERIMENTS for b in BUDGETS if config_path(e, b).is_file()}
    assert files <= set(RESOLVED)
    # The ones whose files went, each now the budget as it is (Table 1 at the hour has its own).
    assert set(RESOLVED) - files == {
        *(f"table1_{b}" for b in BUDGETS if b != "medium"),
        "figure3_full",
        "figure3_small",
        "figures45_small",
    }


@pytest.mark.parametrize("experiment, budget", SHIPPED)
def test_every_experiment_and_budget_resolves_as_before(experiment: str, budget: str) -> None:
    # read_experiment does not build the runs' TrainConfigs, which the full budget's device: cuda
    # would refuse on a machine without a GPU.
    resolved = read_experiment(shipped_experiment(experiment, budget))
    assert to_dict(resolved) == RESOLVED[f"{experiment}_{budget}"]


def test_an_experiment_with_no_file_is_its_budget_as_it_is(tmp_path: Path) -> None:
    assert not config_path("layout_shift", "full").is_file()
    config = load_experiment("layout_shift", "full", overrides=["train.device=cpu"])
    budget = read_budget("full")
    assert config.experiment == "layout_shift" and list(config.models) == budget["models"]
    assert config.runs_dir == budget["runs_dir"] and config.seeds == budget["seeds"]
    with pytest.raises(UnknownNameError, match="tabel1"):
        load_experiment("tabel1", "small")
    # A file given by path must be there: no budget stands in for a missing file of one's own.
    with pytest.raises(MaplessError, match="no experiment config"):
        load_experiment("table1", "small", path=tmp_path / "table1_small.yaml")


@pytest.mark.parametrize("experiment, budget", [(e, b) for e, b in SHIPPED if b != "full"])
def test_every_experiment_below_the_full_budget_builds_every_runs_config(
    experiment: str, budget: str
) -> None:
    # load_experiment builds every model's and ablation row's TrainConfig, as `reproduce` does before
    # any work (the full budget's device: cuda needs a GPU); a row this budget's trainer cannot run
    # would stop `mapless reproduce EXPERIMENT --budget BUDGET` before it starts.
    config = load_experiment(experiment, budget)
    assert config.models and config.budget == budget


def test_figures_share_table1s_runs_folder_and_training() -> None:
    table1, figure3 = load_experiment("table1", "small"), load_experiment("figure3", "small")
    for key in ("runs_dir", "train", "per_model", "eval", "seeds"):
        assert getattr(figure3, key) == getattr(table1, key), key


def test_an_experiment_is_read_over_its_budget_key_by_key_and_overrides_apply_last(
    tmp_path: Path,
) -> None:
    path = tmp_path / "table1.yaml"
    path.write_text(
        "experiment: table1\nbudget: smoke\ntrain: {episodes: 8, model: {dropout: 0.1}}\nmodels: [a3c]\n"
    )
    config = read_experiment(path, ["eval.per_room=2", "models=[savn]"])
    budget = read_budget("smoke")["train"]
    # train: key by key over the budget's, nested mappings included
    assert config.train == {**budget, "episodes": 8, "model": {"hidden_size": 128, "dropout": 0.1}}
    assert config.eval.per_room == 2 and config.eval.batch_size == 16  # the rest of smoke's eval
    assert config.runs_dir == "runs/experiments/smoke"
    assert config.models == ("savn",)  # a list is a value: the layer above replaces it whole


def test_a_file_naming_no_budget_stands_alone_and_an_unknown_budget_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "table1.yaml"
    path.write_text("experiment: table1\nmodels: [a3c]\n")
    assert read_experiment(path).runs_dir == "runs/experiments"  # the dataclass default
    path.write_text("experiment: table1\nbudget: huge\n")
    with pytest.raises(UnknownNameError, match="huge"):
        read_experiment(path)


def test_a_misspelt_per_model_name_is_refused_on_load() -> None:
    with pytest.raises(ConfigError, match="cvmta"):
        load_experiment("table1", "smoke", overrides=["per_model.cvmta.episodes=8"])


def test_the_medium_budget_is_small_for_longer_nested_keys_merged() -> None:
    small, medium = load_experiment("table1", "small"), load_experiment("table1", "medium")
    assert medium.runs_dir != small.runs_dir and "savn" in medium.models
    cvmeta_small, cvmeta_medium = train_config(small, "cvmeta", 1), train_config(medium, "cvmeta", 1)
    assert (cvmeta_small.max_seconds, cvmeta_medium.max_seconds) == (900, 3600)
    # per_model.cvmeta of medium sets frames and checkpoints only: small's model widths and PPO
    # minibatches survive the merge.
    assert cvmeta_medium.model == cvmeta_small.model and cvmeta_medium.model.gcn_hidden == 64
    assert cvmeta_medium.ppo == cvmeta_small.ppo and cvmeta_medium.frames > cvmeta_small.frames
    # The one change of recipe: the hour's cvmeta takes the second-order meta-gradient (row f).
    assert cvmeta_small.meta.first_order and not cvmeta_medium.meta.first_order


def test_table1_at_the_hour_is_the_papers_whole_table_with_three_seeds_of_a3c_and_cvmeta() -> None:
    from mapless.experiments.pipelines import planned_runs
    from mapless.experiments.render import _seed_counts

    config = load_experiment("table1", "medium")
    assert config.eval.protocol == "reference" and len(config.models) == 10
    runs = planned_runs(config)
    assert runs == {m: 3 if m in ("a3c", "cvmeta") else 2 for m in config.models if m != "random"}
    assert sum(runs.values()) == 20
    assert _seed_counts(config) == "2 training seed(s) (a3c, cvmeta: 3)"
    # --seeds is every trained model's count, model_seeds' included; --set seeds=N leaves those.
    single = load_experiment("table1", "medium", seeds=1)
    assert set(planned_runs(single).values()) == {1} and _seed_counts(single) == "1 training seed(s)"
    assert planned_runs(load_experiment("table1", "medium", overrides=["seeds=1"]))["cvmeta"] == 3
    # A narrower lineup keeps the file's model_seeds; those of models left out train nothing.
    narrow = load_experiment("table1", "medium", overrides=["models=[random,sp]"])
    assert planned_runs(narrow) == {"sp": 2} and _seed_counts(narrow) == "2 training seed(s)"


@pytest.mark.parametrize(
    ("seeds", "message"),
    [
        ("{svan: 3}", "svan"),
        ("{random: 2}", "'model_seeds.random': the random agent trains no seeds"),
        ("{cvmeta: 0}", "'model_seeds.cvmeta': must be an integer >= 1, got 0"),
        ("{cvmeta: true}", "'model_seeds.cvmeta': must be an integer >= 1, got True"),
    ],
)
def test_model_seeds_of_no_trained_model_or_of_no_count_are_refused(seeds: str, message: str) -> None:
    with pytest.raises(ConfigError, match=message.replace("(", r"\(")):
        load_experiment("table1", "smoke", overrides=["models=[random,a3c,cvmeta]", f"model_seeds={seeds}"])


@pytest.mark.parametrize("budget", ["medium", "long"])
def test_the_hours_cvmeta_trains_as_the_ablations_row_f_on_its_first_order_base(budget: str) -> None:
    # On the paper's targets, the ablation's (the reference protocol's own default is hoz22's).
    table1 = load_experiment(
        "table1", budget, overrides=["eval.protocol=reference", "train.env.target_set=mjolnir22"]
    )
    ablation = load_experiment("ablation", budget, overrides=["eval.protocol=reference"])
    cvmeta = train_config(table1, "cvmeta", 1)
    base = train_config(ablation, "cvmeta", 1)
    row_f = train_config(ablation, "cvmeta", 1, ablation.ablation_table()["f_second_order"].train)
    assert base.meta.first_order and not row_f.meta.first_order
    # The same training, so the same hash: Table 1 reuses row f's runs once they sit in its folder.
    digest = run_dir_for(table1, cvmeta, "all").name.split("__")[-1]
    assert digest == run_dir_for(ablation, row_f, "ablation-f_second_order").name.split("__")[-1]
    assert digest != run_dir_for(ablation, base, "all").name.split("__")[-1]


@pytest.mark.parametrize("experiment", ["table1", "table2", "table3", "figure3"])
def test_the_reference_protocol_trains_on_the_published_episodes_classes_unless_told(experiment: str) -> None:
    reference = load_experiment(experiment, "small", overrides=["eval.protocol=reference"])
    standard = load_experiment(experiment, "small")
    assert train_config(reference, "cvmeta", 1).env.target_set == "hoz22"
    assert train_config(standard, "cvmeta", 1).env.target_set == "mjolnir22"
    told = load_experiment(
        experiment, "small", overrides=["eval.protocol=reference", "train.env.target_set=savn"]
    )
    assert train_config(told, "cvmeta", 1).env.target_set == "savn"
    # A model's own per_model entry names it too, and wins over the protocol's.
    per_model = load_experiment(
        experiment, "small", overrides=["eval.protocol=reference", "per_model.a3c.env.target_set=mjolnir22"]
    )
    assert train_config(per_model, "a3c", 1).env.target_set == "mjolnir22"
    assert train_config(per_model, "cvmeta", 1).env.target_set == "hoz22"


@pytest.mark.parametrize(
    "experiment, budget", [("ablation", "small"), ("layout_shift", "small"), ("table1", "long")]
)
def test_what_asks_about_the_papers_targets_keeps_them_under_every_protocol(
    experiment: str, budget: str
) -> None:
    # The ablation and the long budget's converged row ask about the paper's model on its targets;
    # a layout shift's episodes are sampled, and the published ones have no shifted version.
    for protocol in ("standard", "reference"):
        config = load_experiment(experiment, budget, overrides=[f"eval.protocol={protocol}"])
        assert train_config(config, "cvmeta", 1).env.target_set == "mjolnir22"


def test_a_budget_extending_in_a_circle_or_an_unknown_budget_is_refused(tmp_path: Path) -> None:
    (tmp_path / "small.yaml").write_text("extends: small\nseeds: 2\n")
    with pytest.raises(ConfigError, match="in a circle"):
        read_budget("small", tmp_path)
    (tmp_path / "smoke.yaml").write_text("extends: full\n")
    (tmp_path / "full.yaml").write_text("extends: smoke\n")
    with pytest.raises(ConfigError, match="smoke -> full -> smoke"):
        read_budget("smoke", tmp_path)
    (tmp_path / "medium.yaml").write_text("extends: large\n")
    with pytest.raises(ConfigError, match="'extends: large' names no file beside it"):
        read_budget("medium", tmp_path)
    with pytest.raises(UnknownNameError, match="large"):
        read_budget("large", tmp_path)


def test_budgets_and_experiment_files_extend_by_one_rule(tmp_path: Path) -> None:
    # A budget names another by its name, an experiment file a file beside it; either is read key by
    # key over what it extends, nested mappings included, and the same circle check refuses both.
    (tmp_path / "small.yaml").write_text("seeds: 2\ntrain: {episodes: 8, model: {hidden_size: 64}}\n")
    (tmp_path / "medium.yaml").write_text("extends: small\ntrain: {model: {dropout: 0.1}}\n")
    assert read_budget("medium", tmp_path) == {
        "seeds": 2,
        "train": {"episodes": 8, "model": {"hidden_size": 64, "dropout": 0.1}},
    }
    (tmp_path / "a.yaml").write_text("experiment: table1\nseeds: 3\neval: {per_room: 2, batch_size: 4}\n")
    (tmp_path / "b.yaml").write_text("extends: a.yaml\neval: {per_room: 3}\n")
    config = read_experiment(tmp_path / "b.yaml")
    assert (config.seeds, config.eval.per_room, config.eval.batch_size) == (3, 3, 4)


def test_every_shipped_run_keeps_its_folder() -> None:
    assert run_folders(sorted(RESOLVED)) == RUN_FOLDERS


def test_an_experiment_that_only_renames_another_is_an_alias() -> None:
    """Two shipped experiments that resolve alike but for ``experiment`` are not two copies to keep in
    step: one of them has no file (the budget as it is: the figures reuse Table 1's configuration)
    or says only ``extends:`` and ``experiment:``."""
    resolved = {
        (e, b): {**to_dict(read_experiment(shipped_experiment(e, b))), "experiment": None} for e, b in SHIPPED
    }
    pairs = [(a, b) for a in SHIPPED for b in SHIPPED if a < b and resolved[a] == resolved[b]]
    # figure3 = table1 (full); figure3 = figures45 = table1 (small: three pairs); figure3 = figures45
    # (smoke); table2 = table3 (smoke, since an experiment's train: merges into the budget's)
    assert len(pairs) == 6
    for pair in pairs:
        aliases = [
            p
            for p in pair
            if not config_path(*p).is_file()
            or set(read_mapping(config_path(*p))) == {"extends", "experiment"}
        ]
        assert aliases, f"{pair}: the same configuration written twice; make one `extends:` the other"
