"""The run folder format, shared by the trainers (writing) and evaluation (loading): run folders,
atomic checkpoints and loading trained models.

A run folder holds::

    config.yaml                 the resolved TrainConfig (every default written out)
    events.out.tfevents.*       TensorBoard logs
    metrics.jsonl               the same scalars, one JSON line per log interval
    progress.json               episodes, frames and running success so far, rewritten every few
                                seconds (what ``mapless reproduce`` shows of runs in other processes)
    checkpoint.pt               the latest resumable state (model, optimizer, RNG states, counters, config)
    checkpoints/model_<episodes>.pt   a model snapshot per checkpoint (what evaluation selects from)
    final_model.pt              the model at the end of the budget

Every file is written to a temporary name in the same folder and renamed over the target, so a
killed trainer leaves either the previous or the new file, never a torn one. Files contain only
tensors, numbers, strings, lists and dicts and are read with ``torch.load(weights_only=True)``.

The run's config is stored as plain data: the trainers write their
:class:`~mapless.train.config.TrainConfig`, and this module, which evaluation imports, reads back
only the :class:`~mapless.models.ModelConfig` it builds the model from (:func:`model_config_of`);
whoever wants the whole config reads it with
:func:`mapless.train.config.stored_train_config` (any layout), so nothing here imports train/.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import re
import shutil
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

from mapless.config import from_dict, read_mapping, to_dict
from mapless.errors import MaplessError
from mapless.files import replacing
from mapless.models import ModelConfig, NavModel, build_model

CONFIG_FILE = "config.yaml"
METRICS_FILE = "metrics.jsonl"
PROGRESS_FILE = "progress.json"
CHECKPOINT_FILE = "checkpoint.pt"
FINAL_MODEL_FILE = "final_model.pt"
SNAPSHOT_DIR = "checkpoints"
FORMAT_VERSION = 1
_SNAPSHOT = re.compile(r"model_(\d+)\.pt$")


class CheckpointError(MaplessError):
    pass


def digest(tree: Any) -> str:
    """SHA-256 of a payload's content (every tensor's dtype, shape and bytes, every other value's
    repr, keys in order), stored in the file and checked when it loads: a checkpoint holds hours of
    work, and a flipped byte would otherwise load as a silently altered tensor."""
    hasher = hashlib.sha256()

    def visit(value: Any) -> None:
        if isinstance(value, torch.Tensor):
            t = value.detach().cpu().contiguous()
            hasher.update(f"T{t.dtype}{tuple(t.shape)}".encode())
            hasher.update(t.reshape(-1).view(torch.uint8).numpy().tobytes() if t.numel() else b"")
        elif isinstance(value, dict):
            hasher.update(b"D%d" % len(value))
            for key, item in value.items():
                hasher.update(repr(key).encode())
                visit(item)
        elif isinstance(value, list | tuple):
            hasher.update(b"L%d" % len(value))
            for item in value:
                visit(item)
        else:
            hasher.update(repr(value).encode())

    visit(tree)
    return hasher.hexdigest()


def atomic_save(payload: dict, path: str | Path) -> None:
    """``torch.save`` of ``payload`` with its :func:`digest`, atomically (:func:`mapless.files.replacing`)."""
    path = Path(path)
    try:
        with replacing(path) as tmp:
            torch.save({**payload, "digest": digest(payload)}, tmp)
    except (OSError, RuntimeError) as error:  # a full disk surfaces as "basic_ios::clear: iostream error"
        free = shutil.disk_usage(path.parent).free if path.parent.exists() else 0
        full = " (no space left on the device)" if free < 64 << 20 else ""
        raise CheckpointError(
            f"could not write {path}{full}: {error}. {free / 2**20:.0f} MiB free there; the previous "
            f"{path.name} is intact: make room, then resume with `mapless train --resume {path.parent}`"
        ) from error


def load_file(path: str | Path, map_location: str | torch.device = "cpu") -> dict:
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"no checkpoint at {path}")
    try:
        payload = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as error:  # a torn or foreign file: say which one
        reason = str(error) or type(error).__name__
        raise CheckpointError(f"cannot read checkpoint {path}: {reason}") from error
    if not isinstance(payload, dict) or payload.get("format") != FORMAT_VERSION:
        raise CheckpointError(f"{path} is not a mapless checkpoint (format {FORMAT_VERSION})")
    stored = payload.pop("digest", None)  # files written before digests existed have none
    if stored is not None and stored != digest(payload):
        raise CheckpointError(f"{path} is corrupt: its content does not match the digest it was written with")
    problem = _malformed(payload)
    if problem:  # a digest proves no origin (anyone can compute one), so the structure is checked too
        raise CheckpointError(f"{path} is not a valid mapless checkpoint: {problem}")
    diverged = next((k for k, v in payload["model"].items() if not torch.isfinite(v).all()), None)
    if diverged is not None:  # NaN weights act (and score SR 0) as if they were a model
        raise CheckpointError(
            f"{path} holds a diverged model: its weight {diverged!r} has NaN or infinite values; it is "
            "neither evaluated nor resumed (an earlier snapshot in checkpoints/ may be finite)"
        )
    return payload


def _malformed(payload: dict) -> str | None:
    """What is wrong with the structure of a checkpoint's payload, or None."""
    if payload.get("kind") not in ("model", "checkpoint"):
        return f"kind {payload.get('kind')!r} is neither 'model' nor 'checkpoint'"
    if not isinstance(payload.get("config"), dict):
        return "it has no config mapping"
    weights = payload.get("model")
    if not (isinstance(weights, dict) and all(isinstance(v, torch.Tensor) for v in weights.values())):
        return "its model is not a mapping of tensors"
    counters = payload.get("counters", {})
    if not (isinstance(counters, dict) and all(isinstance(v, int) for v in counters.values())):
        return "its counters are not a mapping of integers"
    if payload["kind"] == "checkpoint" and not (
        isinstance(payload.get("optimizer"), dict) and isinstance(payload.get("rng"), list)
    ):
        return "a resumable checkpoint without an optimizer state or random streams"
    return None


def model_payload(weights: dict[str, torch.Tensor], config: Any, counters: dict[str, int]) -> dict:
    """What evaluation needs: weights (a CPU state dict), the run's config (a config dataclass whose
    ``model`` field builds the model), and how far training got."""
    return {
        "format": FORMAT_VERSION,
        "kind": "model",
        "config": to_dict(config),
        "model": weights,
        "counters": dict(counters),
    }


def save_run_state(
    run_dir: Path,
    model: NavModel,
    optimizer: torch.optim.Optimizer,
    config: Any,
    counters: dict[str, int],
    rngs: list,
    world_size: int,
    final: bool,
    snapshot: bool = True,
    monitor: dict | None = None,
) -> None:
    """Everything a trainer writes at a checkpoint: the resumable state (:data:`CHECKPOINT_FILE`), a
    model snapshot (unless ``snapshot`` is False) and, at the end of the budget, the final model.
    ``monitor`` is the logging state (:meth:`mapless.train.monitor.RunMonitor.state`) a resumed run
    continues from.

    Snapshots are what checkpoint selection chooses from, so they follow the ``checkpoint_every``
    schedule alone: a run stopped by Ctrl-C between two of them writes only the resumable state, and
    once resumed it offers the same candidates as a run that was never stopped.

    Weights and optimizer moments are copied once, up front, and every file is written from the
    copies: Hogwild workers keep updating the shared tensors while the files are written, and the
    three files must hold one and the same state."""
    weights = _copy(model.state_dict())
    state = {
        "format": FORMAT_VERSION,
        "kind": "checkpoint",
        "model": weights,
        "optimizer": _copy(optimizer.state_dict()),
        "rng": rngs,
        "counters": {**counters, "world_size": world_size},
        "config": to_dict(config),
    }
    if monitor is not None:
        state["monitor"] = monitor
    atomic_save(state, Path(run_dir) / CHECKPOINT_FILE)
    model_file = model_payload(weights, config, counters)
    if snapshot or final:
        atomic_save(model_file, Path(run_dir) / SNAPSHOT_DIR / f"model_{counters['episodes']:010d}.pt")
    if final:
        atomic_save(model_file, Path(run_dir) / FINAL_MODEL_FILE)


def _copy(tree: Any) -> Any:
    """``tree`` with every tensor replaced by a CPU copy (dicts and lists rebuilt, the rest kept)."""
    if isinstance(tree, torch.Tensor):
        return tree.detach().to("cpu", copy=True)
    if isinstance(tree, dict):
        return {k: _copy(v) for k, v in tree.items()}
    if isinstance(tree, list | tuple):
        return type(tree)(_copy(v) for v in tree)
    return tree


def model_config_of(payload: dict) -> ModelConfig:
    """The :class:`ModelConfig` of a checkpoint or model file (the ``model`` entry of its config)."""
    config = payload.get("config")
    if not isinstance(config, dict) or not isinstance(config.get("model"), dict):
        raise CheckpointError("the file's config has no model entry (a mapping)")
    return from_dict(ModelConfig, config["model"], prefix="model.")


def snapshots(run_dir: str | Path) -> list[tuple[int, Path]]:
    """``(episodes, path)`` of every model snapshot of a run, oldest first."""
    folder = Path(run_dir) / SNAPSHOT_DIR
    found = []
    for path in folder.glob("model_*.pt") if folder.is_dir() else []:
        match = _SNAPSHOT.search(path.name)
        if match:
            found.append((int(match.group(1)), path))
    return sorted(found)


def training_log(run_dir: str | Path, keys: Sequence[str] = ()) -> dict[str, list[float]]:
    """``frames``, ``seconds`` (the training clock) and each scalar of ``keys`` at every record of a
    run's :data:`METRICS_FILE`; empty lists when it has none. Each record holds its interval's
    frames/s, so the seconds add up the intervals timed at their own rate: the pause before a resumed
    run is left out, and so are the records a killed run wrote after its last checkpoint, whose work
    the resumed run did again (frames go back). Lines that do not parse (a record torn by a kill) or
    lack one of ``keys`` are passed over."""
    path = Path(run_dir) / METRICS_FILE
    log: dict[str, list[float]] = {"frames": [], "seconds": [], **{key: [] for key in keys}}
    frames, seconds = log["frames"], log["seconds"]
    for line in path.read_text().splitlines() if path.is_file() else []:
        try:
            record = json.loads(line)
            now, rate = int(record["frames"]), float(record["perf/frames_per_s"])
            values = [float(record[key]) for key in keys]
        except (ValueError, KeyError, TypeError):
            continue
        while frames and frames[-1] >= now:
            for series in log.values():
                series.pop()
        interval = (now - frames[-1] if frames else now) / rate if rate > 0 else 0.0
        seconds.append((seconds[-1] if seconds else 0.0) + interval)
        frames.append(now)
        for key, value in zip(keys, values, strict=True):
            log[key].append(value)
    return log


def training_clock(run_dir: str | Path) -> tuple[list[int], list[float]]:
    """``(frames, training seconds)`` at every record of a run's :data:`METRICS_FILE`
    (:func:`training_log`)."""
    log = training_log(run_dir)
    return [int(f) for f in log["frames"]], log["seconds"]


#: The settings a run's trained state depends on (its model, its random streams, its batch layout):
#: every file of one run agrees on them, while a resume may change any other (a larger budget).
RUN_IDENTITY = (
    "model",
    "seed",
    "algo",
    "a3c.mode",
    "a3c.batch_size",
    "a3c.workers",
    "ppo.envs",
    "env.scenes",
)


def run_identity(config: dict) -> dict[str, Any]:
    """The :data:`RUN_IDENTITY` settings of a stored run config, as dotted keys. The model entry
    has every default written out, so that a file written before a model setting existed agrees
    with a later one of the same run; a key the file's layout does not hold is left out."""
    flat: dict[str, Any] = {}
    model = config.get("model")
    if isinstance(model, dict):
        with contextlib.suppress(MaplessError):  # a malformed one is compared as stored
            model = to_dict(from_dict(ModelConfig, model, prefix="model."))
        flat.update({f"model.{k}": v for k, v in model.items()})
    for key in RUN_IDENTITY[1:]:
        node: Any = config
        for part in key.split("."):
            node = node.get(part, _ABSENT) if isinstance(node, dict) else _ABSENT
        if node is not _ABSENT:
            flat[key] = node
    return flat


_ABSENT = object()


def identity_difference(config: dict, other: dict, names: tuple[str, str]) -> str | None:
    """How two stored run configs differ in :func:`run_identity` (None: they are of one run);
    ``names`` say where each comes from."""
    mine, theirs = run_identity(config), run_identity(other)
    keys = [k for k in mine if k in theirs and mine[k] != theirs[k]]
    if not keys:
        return None
    shown = "; ".join(f"{k} is {mine[k]!r} in {names[0]}, {theirs[k]!r} in {names[1]}" for k in keys[:3])
    return shown + (f" (and {len(keys) - 3} more settings)" if len(keys) > 3 else "")


def foreign_files(run_dir: str | Path, payload: dict, name: str = CHECKPOINT_FILE) -> str | None:
    """Why ``payload`` (the run folder's ``name``) is not of the run that the rest of ``run_dir``
    holds (its config.yaml, final model and newest snapshot), or None. A file copied in from another
    run would otherwise be resumed or evaluated as this run's, and overwrite or mix in with it."""
    run_dir = Path(run_dir)
    config_file = run_dir / CONFIG_FILE
    others: list[tuple[str, dict]] = []
    if config_file.is_file():
        # A damaged config.yaml is no evidence of another run (a resume rewrites it).
        with contextlib.suppress(MaplessError):
            others.append((CONFIG_FILE, read_mapping(config_file)))
    newest = snapshots(run_dir)[-1:]
    for path in [run_dir / FINAL_MODEL_FILE, *(p for _, p in newest)]:
        if path.is_file() and path.name != name:
            others.append((str(path.relative_to(run_dir)), load_file(path)["config"]))
    for other, config in others:
        difference = identity_difference(payload["config"], config, (name, other))
        if difference is not None:
            return (
                f"{run_dir / name} is not of the run in {run_dir}: {difference}. It was copied from "
                "another run, or the folder mixes two runs; nothing was written. Put the run's own "
                "file back, or train the other run in its own folder"
            )
    return None


def mixed_runs(files: Sequence[Path]) -> str | None:
    """Why the model files ``files`` (one run folder's snapshots) are not all of one run, or None."""
    first = None
    for path in files:
        config = load_file(path)["config"]
        if first is None:
            first = (path, config)
            continue
        difference = identity_difference(first[1], config, (first[0].name, path.name))
        if difference is not None:
            return (
                f"{path.parent} mixes the snapshots of two runs: {difference}; evaluate each run from "
                "its own folder"
            )
    return None


def resolve_model_file(path: str | Path) -> Path:
    """A model file, or a run folder (-> its final model, else its latest snapshot or checkpoint)."""
    path = Path(path)
    if path.is_file():
        return path
    if not path.is_dir():
        raise CheckpointError(f"{path} is neither a model file nor a run folder")
    for candidate in (
        path / FINAL_MODEL_FILE,
        *(p for _, p in reversed(snapshots(path))),
        path / CHECKPOINT_FILE,
    ):
        if candidate.is_file():
            return candidate
    raise CheckpointError(
        f"run folder {path} holds no model yet ({FINAL_MODEL_FILE}, {SNAPSHOT_DIR}/ or {CHECKPOINT_FILE})"
    )


def load_model(
    path: str | Path, device: str | torch.device = "cpu"
) -> tuple[NavModel, dict[str, Any], dict[str, int]]:
    """Build the model of a run folder, model snapshot or resumable checkpoint and load its weights.

    Returns ``(model in eval mode on device, the run's config as plain data, counters)``; the model is
    built from the config's ``model`` entry (inner learning rate and steps for adaptive models
    included), and ``mapless.train.config.stored_train_config(config)`` types the rest.
    """
    file = resolve_model_file(path)
    payload = load_file(file, map_location=device)
    model = build_model(model_config_of(payload))
    try:
        model.load_state_dict(payload["model"])
    except RuntimeError as error:  # missing or unexpected keys, other shapes
        reason = str(error).splitlines()[0]
        raise CheckpointError(f"{file}: its weights do not fit the model of its config ({reason})") from None
    return model.to(device).eval(), payload["config"], dict(payload.get("counters", {}))
