"""Entry point of a training run: run folder, resolved config, resume, trainer dispatch."""

from __future__ import annotations

import contextlib
import fcntl
import shutil
import time
from collections.abc import Callable, Iterator
from pathlib import Path

from mapless import checkpoint as ckpt
from mapless.config import ConfigError, apply_overrides, leaves, read_mapping, save_config, to_dict
from mapless.errors import MaplessError
from mapless.files import unwritable
from mapless.models import model_folder_name
from mapless.provenance import comment_of, provenance_comment, resumed_comment
from mapless.train import distributed as dist
from mapless.train.batched import BatchedTrainer
from mapless.train.builders import LibraryFactory, prepare_scenes
from mapless.train.config import TrainConfig, in_current_layout, train_config_from
from mapless.train.hogwild import AsyncTrainer
from mapless.train.ppo import PPOTrainer


def default_run_dir(config: TrainConfig, root: str | Path = "runs", label: str = "") -> Path:
    """``runs/<label>__<model>__<mode>__s<seed>__<time>`` (CleanRL-style: readable and unique)."""
    stamp = time.strftime("%Y%m%d-%H%M%S")
    model = model_folder_name(config.model.name)
    parts = [p for p in (label, model, config.mode, f"s{config.seed}", stamp) if p]
    return Path(root) / "__".join(parts)


def resume_config(run_dir: str | Path, overrides: list[str] | None = None) -> tuple[TrainConfig, dict]:
    """The saved config of a run (plus ``overrides``, e.g. a larger budget) and its last checkpoint."""
    run_dir = Path(run_dir)
    payload = ckpt.load_file(run_dir / ckpt.CHECKPOINT_FILE)
    if payload.get("kind") != "checkpoint":
        raise ckpt.CheckpointError(f"{run_dir / ckpt.CHECKPOINT_FILE} is not a resumable checkpoint")
    fixed = [o for o in overrides or [] if o.split("=", 1)[0].strip().startswith(FIXED_ON_RESUME)]
    if fixed:
        raise ConfigError(
            f"config key {fixed[0].split('=', 1)[0]!r}: a resumed run keeps its model, seed, algorithm, mode "
            "and batch layout (the checkpoint's state was made with them); start a new run to change them"
        )
    data = apply_overrides(in_current_layout(payload["config"]), overrides or [])
    return train_config_from(data), payload


def config_edits(run_dir: str | Path, resume: dict) -> list[str]:
    """The settings in which a run folder's config.yaml differs from its checkpoint's config (a hand
    edit, or a resume stopped before its first checkpoint): a resume trains with the checkpoint's
    and rewrites config.yaml, so each is reported rather than silently undone."""
    try:
        edited = read_mapping(Path(run_dir) / ckpt.CONFIG_FILE)
    except ConfigError:
        return []
    stored = resume["config"]
    if ckpt.identity_difference(edited, stored, ("", "")) is not None:
        return []  # another run's checkpoint, which the trainer refuses
    mine, theirs = leaves(edited), leaves(stored)
    return [
        f"{k}: {mine[k]!r} in config.yaml, {theirs.get(k)!r} in the checkpoint"
        for k in mine
        if mine[k] != theirs.get(k)
    ]


LOCK_FILE = ".lock"
#: Settings a checkpoint's state depends on: ``--resume --set`` may not change them.
FIXED_ON_RESUME = ("model.", *ckpt.RUN_IDENTITY[1:])


@contextlib.contextmanager
def run_folder_lock(run_dir: Path) -> Iterator[None]:
    """Hold ``run_dir``'s lock while a trainer writes there: a second trainer (two ``--resume`` of
    one run) is refused instead of writing a second set of logs and checkpoints. The operating system
    releases the lock when the process ends, however it ends."""
    handle = open(run_dir / LOCK_FILE, "a+")  # noqa: SIM115 - held for the whole run
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        handle.close()
        raise MaplessError(
            f"{run_dir} is in use by another trainer; wait for it to end or stop it first"
        ) from None
    try:
        yield
    finally:
        fcntl.flock(handle, fcntl.LOCK_UN)
        handle.close()


def remove_torn_writes(run_dir: Path) -> None:
    """Delete the temporary files of writes a killed run left half done (``.<name>.<hex>.tmp``,
    :func:`mapless.files.replacing`): the file they were to replace is intact, and they can be as
    large as a checkpoint."""
    for folder in (run_dir, run_dir / ckpt.SNAPSHOT_DIR):
        for torn in folder.glob(".*.tmp"):
            torn.unlink(missing_ok=True)


def run_folder_problem(run_dir: Path, resuming: bool) -> str | None:
    """Why a trainer may not write into ``run_dir`` (None: it may), checked before any work. A new
    run takes a missing or empty folder, or one whose run wrote no checkpoint (it starts over); a
    folder that holds a run's models is continued with ``--resume`` only, and one that mapless did
    not make is left alone: a new run would overwrite the models in either, or mix its files in."""
    unusable = unwritable(run_dir)
    if unusable is not None:
        return f"cannot write the run folder {run_dir}: {unusable}"
    if resuming or not run_dir.is_dir():
        return None
    names = {p.name for p in run_dir.iterdir()} - {LOCK_FILE}
    models = sorted(names & {ckpt.CHECKPOINT_FILE, ckpt.FINAL_MODEL_FILE})
    models += [f"{ckpt.SNAPSHOT_DIR}/"] if ckpt.snapshots(run_dir) else []
    if models:
        kind = "a finished run" if ckpt.FINAL_MODEL_FILE in names else "a run"
        return (
            f"{run_dir} already holds {kind} ({', '.join(models)}); continue it with `mapless train "
            f"--resume {run_dir}`, or train into another folder (a new run would overwrite it)"
        )
    if names and ckpt.CONFIG_FILE not in names:
        return (
            f"{run_dir} is not empty and holds no run (it has {', '.join(sorted(names)[:3])}); train into "
            "a new or empty folder"
        )
    return None


def _remove_if_unused(run_dir: Path) -> Callable[..., bool]:
    """An exit callback that deletes the run folder this call made when the run fails before
    writing anything but its config and lock (a bad scene root, a scene that cannot load): a folder
    holding only config.yaml looks like a run and would be picked up by --resume or selection. A
    failure after logs or a checkpoint were written keeps them, for the diagnosis or the resume."""

    def callback(kind: type | None, error: BaseException | None, tb: object) -> bool:
        if error is not None and run_dir.is_dir():
            names = {p.name for p in run_dir.iterdir()}
            if names <= {ckpt.CONFIG_FILE, LOCK_FILE}:
                shutil.rmtree(run_dir, ignore_errors=True)
        return False

    return callback


def train(
    config: TrainConfig,
    run_dir: str | Path,
    resume: dict | None = None,
    library_factory: LibraryFactory | None = None,
) -> dict[str, float]:
    """Train ``config`` into ``run_dir`` (resuming from the loaded checkpoint ``resume`` if given).

    Under torchrun (``WORLD_SIZE`` > 1) every rank calls this; rank 0's ``run_dir`` is used by all.
    Returns the final counters and throughput.
    """
    ctx = dist.init_distributed(config.device) if config.mode == "batched" else dist.DistContext()
    if config.mode == "async" and dist.launched_by_torchrun():
        raise ConfigError(
            "config key 'a3c.mode': async (Hogwild) runs on one machine; use a3c.mode=batched under torchrun"
        )
    with contextlib.ExitStack() as stack:
        stack.callback(dist.shutdown, ctx)
        # Checked on rank 0, which writes the folder, and raised on every rank (none waits for it).
        problem = run_folder_problem(Path(run_dir), resume is not None) if ctx.is_main else None
        shown, problem = dist.broadcast_object((str(run_dir), problem), ctx)
        run_dir = Path(shown)
        if problem is not None:
            raise MaplessError(problem)
        if resume is not None and ckpt.model_config_of(resume) != config.model:
            raise ConfigError("config key 'model': a run cannot be resumed with another model configuration")
        if resume is not None:
            stored = resume["config"]
            names = (ckpt.CHECKPOINT_FILE, "the config to resume with")
            if (difference := ckpt.identity_difference(stored, to_dict(config), names)) is not None:
                raise ConfigError(f"{run_dir} cannot be resumed so: {difference}")
        foreign = ckpt.foreign_files(run_dir, resume) if resume is not None and ctx.is_main else None
        if (foreign := dist.broadcast_object(foreign, ctx)) is not None:
            raise ckpt.CheckpointError(foreign)
        if ctx.is_main:
            if not run_dir.exists():
                stack.push(_remove_if_unused(run_dir))
            run_dir.mkdir(parents=True, exist_ok=True)
            stack.enter_context(run_folder_lock(run_dir))
            remove_torn_writes(run_dir)
            config_file = run_dir / ckpt.CONFIG_FILE
            threads = config.threads or None
            # A resumed run keeps the record of its first start and adds this one's.
            comment = (
                provenance_comment(threads)
                if resume is None
                else resumed_comment(comment_of(config_file), threads)
            )
            save_config(config, config_file, comment)
        if library_factory is None and ctx.local_rank == 0:
            prepare_scenes(config)  # once per machine: each has its own scene cache
        dist.barrier(ctx)
        if config.mode == "async":
            return AsyncTrainer(config, run_dir, library_factory).run(resume)
        trainer = PPOTrainer if config.algo == "ppo" else BatchedTrainer
        return trainer(config, run_dir, library_factory, ctx).run(resume)
