"""A model kept in one's own package, outside mapless: named by its import path ``package.module:Class``
or registered under the ``mapless.models`` entry-point group, it is built, trained, resumed, evaluated
and reproduced like a built-in one, and its checkpoint records the path it was trained under."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import yaml

from mapless import checkpoint as ckpt
from mapless.config import ConfigError
from mapless.errors import UnknownNameError
from mapless.experiments import load_experiment, run_dir_for, train_config
from mapless.models import build_model, model_class, model_names
from mapless.models.base import RecurrentNavModel

#: A package of the user's own: the out-of-tree model of the guide's "Adding a model". It reads the
#: target's own context row and the previous policy (docs/guide/simulator.md, "Observations").
PLUGIN = textwrap.dedent(
    """
    import torch
    import torch.nn.functional as F
    from torch import nn

    from mapless.models.base import NUM_ACTIONS, RECURRENT_CORE_ROLES, RecurrentNavModel
    from mapless.models.layers import target_row
    from mapless.models.roles import ParameterRoles


    class TargetRowModel(RecurrentNavModel):
        description = "example: the target's context row -> LSTM"
        parameter_roles = RECURRENT_CORE_ROLES | ParameterRoles(policy=("embed",))
        settings = {"category_set": "", "feature_channels": "", "hidden_size": ""}

        def __init__(self, config, knowledge=None):
            super().__init__(config, knowledge)
            self.embed = nn.Linear(4 + NUM_ACTIONS, 32)
            self.build_recurrent_core(32, glorot=False)

        def encode(self, obs, hidden, prev_policy):
            row = target_row(obs["context"], obs["target_index"])
            return F.relu(self.embed(torch.cat([row, prev_policy], dim=1))), None


    NOT_A_MODEL = 3
    """
)
PATH = "tinynav.models:TargetRowModel"


def _package(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A folder outside the repository holding the package ``tinynav``."""
    root = tmp_path_factory.mktemp("outside")
    (root / "tinynav").mkdir()
    (root / "tinynav" / "__init__.py").write_text("")
    (root / "tinynav" / "models.py").write_text(PLUGIN)
    return root


@pytest.fixture
def plugin(tmp_path_factory: pytest.TempPathFactory, monkeypatch: pytest.MonkeyPatch) -> Path:
    """The package folder (outside the repository), on ``sys.path`` for this test."""
    root = _package(tmp_path_factory)
    monkeypatch.syspath_prepend(str(root))
    yield root
    for name in [m for m in sys.modules if m == "tinynav" or m.startswith("tinynav.")]:
        del sys.modules[name]


def test_an_import_path_names_a_model_of_ones_own_package(plugin: Path) -> None:
    cls = model_class(PATH)
    assert issubclass(cls, RecurrentNavModel) and cls.__module__ == "tinynav.models"
    model = build_model(PATH, hidden_size=16)
    assert type(model) is cls and model.config.name == PATH
    assert PATH not in model_names()  # listed are the names, not every importable path


def test_an_import_path_that_leads_nowhere_is_a_clear_error(plugin: Path) -> None:
    with pytest.raises(ConfigError, match=r"cannot import 'tinynav\.nothing'.*PYTHONPATH"):
        model_class("tinynav.nothing:TargetRowModel")
    with pytest.raises(ConfigError, match=r"tinynav\.models has no 'Missing'"):
        model_class("tinynav.models:Missing")
    with pytest.raises(ConfigError, match=r"not a subclass of mapless\.models\.NavModel"):
        model_class("tinynav.models:NOT_A_MODEL")
    with pytest.raises(UnknownNameError, match=r"'tinynav'.*or an import path package\.module:Class"):
        model_class("tinynav")


def test_an_installed_package_registers_its_models_under_the_entry_point_group(plugin: Path) -> None:
    # What pip writes for [project.entry-points."mapless.models"] tiny = "tinynav.models:TargetRowModel".
    info = plugin / "tinynav-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: tinynav\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(f"[mapless.models]\ntiny = {PATH}\ncvmeta = {PATH}\n")
    assert model_class("tiny") is model_class(PATH)
    assert model_names().count("tiny") == 1 and model_names().count("cvmeta") == 1
    assert model_class("cvmeta").__module__ == "mapless.models.cvmeta"  # a built-in name is not replaced
    assert build_model("tiny", hidden_size=16).config.name == "tiny"


def test_an_experiment_takes_an_import_path_among_its_models(plugin: Path) -> None:
    config = load_experiment("table1", "smoke", overrides=[f"models=[random,{PATH}]"])
    assert list(config.models) == ["random", PATH]
    cfg = train_config(config, PATH, 1)
    assert cfg.model.name == PATH and cfg.model.hidden_size == 128  # the smoke budget's
    # A folder name any file system takes: the path's ':' becomes '.'.
    assert run_dir_for(config, cfg, "all").name.startswith("tinynav.models.TargetRowModel__all__s1__")
    with pytest.raises(ConfigError, match="cannot import"):
        load_experiment("table1", "smoke", overrides=["models=[random,tinynav.nothing:X]"])


def _cli(*args: str, plugin: Path, cwd: Path) -> dict:
    """``python -m mapless ARGS`` in a fresh process that finds the package through PYTHONPATH only."""
    env = {**os.environ, "PYTHONPATH": str(plugin)}
    done = subprocess.run(
        [sys.executable, "-m", "mapless", *args], cwd=cwd, env=env, capture_output=True, text=True
    )
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.strip().splitlines()[-1]) if done.stdout.strip().startswith("{") else {}


@pytest.mark.slow
def test_the_cli_trains_resumes_evaluates_and_reproduces_a_model_of_ones_own_package(
    tmp_path: Path, tmp_path_factory: pytest.TempPathFactory
) -> None:
    from test_eval_reproduce import make_episodes

    from mapless.episodes import evalsets
    from mapless.sim.cache import fingerprint
    from mapless.sim.config import SimConfig
    from mapless.sim.library import SceneLibrary

    plugin = _package(tmp_path_factory)
    work = tmp_path / "work"
    work.mkdir()
    library = SceneLibrary.builtin()  # FloorPlan1, built once into the test cache the processes share
    episodes = work / "episodes.json.gz"
    evalsets.save(
        episodes, make_episodes(library, "FloorPlan1", 4, 0), "test", "mjolnir22", 0, fingerprint(SimConfig())
    )
    config = work / "tiny.yaml"
    # A tiny A3C run on one floor plan: two checkpoints, then two more on resume.
    config.write_text(
        f"model: {{name: '{PATH}', hidden_size: 16}}\nenv: {{scenes: FloorPlan1}}\na3c: {{batch_size: 4}}\n"
        "episodes: 8\ncheckpoint_every: 8\nlog_every: 4\nthreads: 1\nprogress: false\n"
    )
    run_dir = work / "run"
    first = _cli("train", str(config), "--run-dir", str(run_dir), plugin=plugin, cwd=work)
    assert first["episodes"] == 8
    second = _cli("train", "--resume", str(run_dir), "--set", "episodes=16", plugin=plugin, cwd=work)
    assert second["episodes"] == 16
    # The checkpoint records the path, and rebuilds the model from it (here, where it is importable).
    payload = ckpt.load_file(run_dir / ckpt.FINAL_MODEL_FILE)
    assert ckpt.model_config_of(payload).name == PATH
    assert yaml.safe_load((run_dir / ckpt.CONFIG_FILE).read_text())["model"]["name"] == PATH

    out = work / "eval"
    args = ["--split", "test", "--episodes", str(episodes), "--workers", "1", "--out", str(out)]
    _cli("eval", str(run_dir), *args, plugin=plugin, cwd=work)
    record = json.loads((out / "episodes.json").read_text())  # named after the episode file
    assert record["model"] == PATH and len(record["episodes"][0]) == 4

    experiment = work / "table1.yaml"
    experiment.write_text(
        yaml.safe_dump(
            {
                "experiment": "table1",
                "budget": "smoke",
                "models": ["random"],
                "focus": "random",
                "gif": False,
                "runs_dir": str(work / "runs"),
                "train": {"episodes": 8, "model": {"hidden_size": 16}, "env": {"scenes": "FloorPlan1"}},
                "eval": {
                    "per_room": 4,
                    "rooms": ["kitchen"],
                    "select_file": str(episodes),
                    "report_file": str(episodes),
                    "batch_size": 4,
                    "workers": 1,
                },
            }
        )
    )
    reports = work / "reports"
    models = ["--set", f"models=[random,{PATH}]", "--set", f"focus={PATH}"]
    _cli("reproduce", "table1", "--budget", "smoke", "--config", str(experiment), *models,
         "--jobs", "1", "--reports", str(reports), plugin=plugin, cwd=work)  # fmt: skip
    (trained,) = (work / "runs").glob("tinynav.models.TargetRowModel__*")
    assert ckpt.model_config_of(ckpt.load_file(trained / ckpt.FINAL_MODEL_FILE)).name == PATH
    assert PATH in (reports / "table1" / "table1.md").read_text()
