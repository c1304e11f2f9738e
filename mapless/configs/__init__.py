"""The shipped configurations, as package data, so that an installed mapless runs them from any folder:
experiment files ``<experiment>_<budget>.yaml`` read over ``budgets/<budget>.yaml``
(:mod:`mapless.experiments.config`), training recipes ``recipes/<name>.yaml``
(:mod:`mapless.train.recipes`) and training configs ``train_<name>.yaml`` (``mapless train``)."""

from __future__ import annotations

from importlib import resources
from pathlib import Path

from mapless.errors import UnknownNameError

#: What ``mapless train CONFIG`` reads as a path rather than as a shipped config's name.
_PATH_MARKS = ("/", "\\")
_SUFFIXES = (".yaml", ".yml")


def configs_dir() -> Path:
    """This folder, wherever mapless is installed (a wheel unpacks its package data as plain files)."""
    return Path(str(resources.files(__name__)))


def train_config_names() -> tuple[str, ...]:
    """The shipped training configs, by the name ``mapless train NAME`` takes (``train_ppo``, ...)."""
    return tuple(sorted(p.stem for p in configs_dir().glob("train_*.yaml")))


def train_config_file(config: str | Path) -> Path:
    """The file ``mapless train CONFIG`` reads. One rule, with no look at the disk to tell the two
    apart: CONFIG is a path when it contains a path separator or ends in ``.yaml``/``.yml``
    (``configs/my.yaml``, ``./train_ppo.yaml``), and otherwise the name of a shipped training config
    (``train_ppo``: ``train_ppo.yaml`` of this folder)."""
    text = str(config)
    if any(m in text for m in _PATH_MARKS) or text.endswith(_SUFFIXES):
        return Path(text)
    if text not in train_config_names():
        names = train_config_names()
        hint = " (a YAML file is named by its path: with a '/' or ending in .yaml)"
        raise UnknownNameError("shipped training config", text, names, ", ".join(names) + hint)
    return configs_dir() / f"{text}.yaml"


def config_label(path: Path) -> str:
    """How ``--print-config`` names a config file's layer: its place among the shipped configs
    (``budgets/small.yaml``), or the path it was given by."""
    try:
        return str(Path(path).resolve().relative_to(configs_dir().resolve()))
    except ValueError:
        return str(path)
