"""The captures that pin what the shipped experiment configs resolve to and where their runs live
(tests/data/experiment_configs_resolved.json and tests/data/run_folders.json), and the command
that regenerates them after a deliberate change of a shipped config:

    python tests/captures.py

tests/test_experiment_configs.py compares the code with these files, so a change of what a shipped
experiment trains, or of where its runs are kept, shows up in the diff of a commit, never silently.
"""

from __future__ import annotations

import json
from pathlib import Path

DATA = Path(__file__).parent / "data"
RESOLVED_FILE = DATA / "experiment_configs_resolved.json"
RUN_FOLDERS_FILE = DATA / "run_folders.json"


def captured_names() -> list[str]:
    """The ``<experiment>_<budget>`` pairs the capture covers (those that ever had a file)."""
    return sorted(json.loads(RESOLVED_FILE.read_text()))


def resolved_configs(names: list[str]) -> dict[str, dict]:
    from mapless.config import to_dict
    from mapless.experiments import BUDGETS
    from mapless.experiments.config import read_experiment, shipped_experiment

    out = {}
    for name in names:
        budget = next(b for b in BUDGETS if name.endswith(f"_{b}"))
        experiment = name[: -len(budget) - 1]
        out[name] = to_dict(read_experiment(shipped_experiment(experiment, budget)))
    return out


def run_folders(names: list[str]) -> dict[str, str]:
    """The folder of seed 1 of every trained model (and ablation row) of the small, medium and long
    experiments under both protocols."""
    from mapless.experiments import load_experiment, train_config
    from mapless.experiments.runs import run_dir_for
    from mapless.models import MODELS

    folders = {}
    for experiment in ("table1", "table2", "table3", "layout_shift", "ablation"):
        for budget in ("small", "medium", "long"):
            if f"{experiment}_{budget}" not in names:
                continue
            for protocol in ("standard", "reference"):
                overrides = [f"eval.protocol={protocol}", "train.threads=1"]
                config = load_experiment(experiment, budget, overrides=overrides)
                rows = {m: None for m in sorted({*config.models, config.focus} - {"random"})}
                if experiment == "ablation":
                    rows |= {name: row.train for name, row in config.ablation_table().items() if row.train}
                for name, extra in rows.items():
                    model = config.focus if name not in MODELS else name
                    cfg = train_config(config, model, 1, extra)
                    variant = "all" if name in MODELS else f"ablation-{name}"
                    folders[f"{experiment} {budget} {protocol} {name}"] = run_dir_for(
                        config, cfg, variant
                    ).name
    return folders


def main() -> None:
    names = captured_names()
    RESOLVED_FILE.write_text(json.dumps(resolved_configs(names), indent=1, sort_keys=True) + "\n")
    RUN_FOLDERS_FILE.write_text(json.dumps(run_folders(names), indent=1, sort_keys=True) + "\n")
    print(f"wrote {RESOLVED_FILE.name} and {RUN_FOLDERS_FILE.name}")


if __name__ == "__main__":
    main()
