"""``mapless runs migrate RUNS_DIR``: the one-time renaming of the run folders that ``mapless
reproduce`` named under an earlier rule to the folder names of today's run identity.

A run folder's hash (:func:`mapless.experiments.runs.run_dir_for`) reads the training config as it is
laid out, so each change of the layout (:data:`mapless.train.config.LAYOUT_CHANGES`) renames every
run: a finished run would otherwise be trained again under a new name. The earlier rules, kept here
and nowhere else: the first read the config in the layout before the ``a3c:`` and ``env.reward:``
blocks (2fdbb67) and left out the keys added later where they did not change the run
(:func:`old_run_hash`); each later one read the config as laid out before the next change
(:func:`earlier_run_hashes`). Each folder is checked before it moves: its config.yaml must parse (in
any layout) and must give the folder's own hash under one of the earlier rules; a folder whose new
name is taken, or whose trainer is still writing to it, stays where it is. The cached evaluations
under ``eval/`` name their model files by path, so they are moved along with the folder.
"""

from __future__ import annotations

import json
import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from mapless.config import move_keys, read_mapping
from mapless.errors import MaplessError
from mapless.experiments.runs import config_hash, hashed_config
from mapless.files import write_text
from mapless.models.registry import model_class
from mapless.train.config import LAYOUT_CHANGES, TrainConfig, stored_train_config

#: ``<model>__<variant>__s<seed>__<hash>``, the name of an experiment's run folder.
RUN_FOLDER = re.compile(r"^(?P<model>.+?)__(?P<variant>.+)__s(?P<seed>\d+)__(?P<hash>[0-9a-f]{8})$")


def _meta_learns_under_ppo(cfg) -> bool:
    return cfg.algo == "ppo" and model_class(cfg.model.name).is_adaptive() and cfg.model.adapt != "none"


#: The keys the old hash left out unless they changed the run (``section.key``, the rule).
_LATER_KEYS: tuple[tuple[str, Callable[..., bool]], ...] = (
    ("env.layouts", lambda c: c.env.layouts != type(c.env.layouts)()),
    ("model.semantic_map", lambda c: c.model.semantic_map),
    ("model.context_distance", lambda c: c.model.context_distance),
    ("ppo.bootstrap_time_limit", lambda c: c.ppo.bootstrap_time_limit and _meta_learns_under_ppo(c)),
    ("meta.navigation_loss", _meta_learns_under_ppo),
    ("meta.learned_loss_from_imitation", _meta_learns_under_ppo),
    ("env.parent_reward_rule", lambda c: c.parent_reward),
    ("meta.train_learned_loss", lambda c: not c.ppo.meta.train_learned_loss),
    ("ppo.whole_episodes", lambda c: c.ppo.whole_episodes and not _meta_learns_under_ppo(c)),
)


def _laid_out_before(train_cfg: TrainConfig, change: int) -> dict:
    """What a run hash reads of ``train_cfg`` (:func:`hashed_config`), in the layout from before
    ``LAYOUT_CHANGES[change]``: every later change's keys moved back, newest first."""
    data = hashed_config(train_cfg)
    for _, moves in reversed(LAYOUT_CHANGES[change:]):
        data = move_keys(data, [(new, old) for old, new in moves])
    return data


def old_run_hash(train_cfg: TrainConfig) -> str:
    """The first run-folder hash: the config in the layout before the ``a3c:`` and ``env.reward:``
    blocks, less the progress bar, the logger and the later keys that did not change the run."""
    data = _laid_out_before(train_cfg, 0)
    for path, changes_training in _LATER_KEYS:
        if not changes_training(train_cfg):
            section, key = path.split(".")
            del data[section][key]
    return config_hash(data)


def earlier_run_hashes(train_cfg: TrainConfig) -> list[str]:
    """The folder hashes ``train_cfg``'s run had under every earlier rule, newest first: the config
    as laid out before each change of :data:`LAYOUT_CHANGES` since the first, then the first rule
    (:func:`old_run_hash`)."""
    later = [config_hash(_laid_out_before(train_cfg, c)) for c in range(len(LAYOUT_CHANGES) - 1, 0, -1)]
    return [*later, old_run_hash(train_cfg)]


@dataclass(frozen=True)
class Migration:
    """One run folder: its new name, or why it stays (``reason``)."""

    folder: Path
    new_name: str | None = None
    reason: str = ""

    @property
    def line(self) -> str:
        if self.new_name is None:
            return f"skip {self.folder}: {self.reason}"
        return f"{self.folder} -> {self.folder.parent / self.new_name}"


def plan(folder: Path) -> Migration:
    """Where ``folder`` goes under today's hash, or why it stays."""
    from mapless.experiments.runs import run_hash

    match = RUN_FOLDER.match(folder.name)
    if match is None:
        return Migration(folder, reason="not named <model>__<variant>__s<seed>__<hash>")
    try:
        config = stored_train_config(read_mapping(folder / "config.yaml"))
    except MaplessError as error:
        return Migration(folder, reason=f"its config.yaml does not parse ({error})")
    # The grid gives a config that names no thread count its share of the cores, which config.yaml
    # records; the folder was named before, with the count the config named (0: none).
    for threads in dict.fromkeys((config.threads, 0)):
        planned = config.replace(threads=threads)
        if run_hash(planned) == match["hash"]:
            return Migration(folder, reason="named by today's hash already")
        if match["hash"] in earlier_run_hashes(planned):
            new = f"{match['model']}__{match['variant']}__s{match['seed']}__{run_hash(planned)}"
            if (folder.parent / new).exists():
                return Migration(folder, reason=f"{new} exists already; nothing is overwritten")
            return Migration(folder, new)
    return Migration(
        folder, reason="its config.yaml does not give the folder's hash (edited, or not a reproduce run)"
    )


def run_folders(runs_dir: Path) -> list[Path]:
    """The folders under ``runs_dir`` that hold a config.yaml (a folder that holds none is looked
    into: ``runs/experiments`` holds a folder per budget)."""
    found = []
    for child in sorted(p for p in runs_dir.iterdir() if p.is_dir()):
        if (child / "config.yaml").is_file():
            found.append(child)
        else:
            found.extend(run_folders(child))
    return found


def _move_cached_evaluations(new: Path, old_name: str) -> None:
    """Point the cached evaluations of ``new`` (a run folder renamed from ``old_name``) at its new
    path: each is keyed by the path of the model file it evaluated."""
    for cache in sorted((new / "eval").glob("*.json")):
        try:
            stored = json.loads(cache.read_text())
            spec = stored["key"]["spec"]
            parts = Path(spec["checkpoint"]).parts
        except (OSError, ValueError, KeyError, TypeError):
            continue  # not a cached evaluation: it stays as it is
        if old_name in parts:
            spec["checkpoint"] = str(Path(*(new.name if p == old_name else p for p in parts)))
            write_text(cache, json.dumps(stored))


def migrate(
    runs_dir: str | Path, dry_run: bool = False, log: Callable[[str], None] = print
) -> list[Migration]:
    """Rename every run folder under ``runs_dir`` made under the old hash to today's name (with
    ``dry_run``, only say so), logging ``old -> new`` or why a folder stays."""
    from mapless.train.run import run_folder_lock

    runs_dir = Path(runs_dir)
    if not runs_dir.is_dir():
        raise MaplessError(f"{runs_dir} is not a folder")
    done = []
    for folder in run_folders(runs_dir):
        step = plan(folder)
        if step.new_name is not None and not dry_run:
            target = folder.parent / step.new_name
            try:
                with run_folder_lock(folder):
                    if target.exists():  # made since the plan: an empty folder would be replaced
                        raise MaplessError(f"{step.new_name} exists already; nothing is overwritten")
                    folder.rename(target)
            except (MaplessError, OSError) as error:  # a trainer holds the folder, or the name is taken
                step = Migration(folder, reason=str(error))
            else:
                _move_cached_evaluations(folder.parent / step.new_name, folder.name)
        log(step.line)
        done.append(step)
    return done
