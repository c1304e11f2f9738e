"""Training an experiment's runs before it evaluates them: in this process one after another, side
by side in local processes (``mapless reproduce --jobs N``), or as Slurm jobs through submitit
(``--launcher slurm``). Whatever trains it, a run is its folder (runs.py): a finished one is reused
and an interrupted one resumes from its checkpoint, so a grid that was stopped or killed goes on
where it stopped when the same command runs again."""

from __future__ import annotations

import contextlib
import dataclasses
import fcntl
import json
import math
import multiprocessing as mp
import os
import queue
import shutil
import signal
import subprocess
import time
import traceback
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from tqdm import tqdm

from mapless import checkpoint as ckpt
from mapless.errors import MaplessError
from mapless.experiments.config import ExperimentConfig, train_config
from mapless.experiments.runs import RunTally, run_dir_for, train_run
from mapless.files import write_text
from mapless.processes import exit_with_parent
from mapless.provenance import cpu_cores

Log = Callable[[str], None]


@dataclass(frozen=True)
class PlannedRun:
    """One training run of an experiment: ``model`` trained one way (``variant``, its folder's
    name for the ``extra`` overrides) with one seed; its training config and its folder."""

    model: str
    variant: str
    seed: int
    config: Any  # TrainConfig
    run_dir: Path

    @classmethod
    def of(cls, experiment: ExperimentConfig, model: str, variant: str = "all", seed: int = 1,
           extra: dict | None = None) -> PlannedRun:  # fmt: skip
        config = train_config(experiment, model, seed=seed, extra=extra)
        return cls(model, variant, seed, config, run_dir_for(experiment, config, variant))

    @property
    def label(self) -> str:
        return f"{self.model} {self.variant}, seed {self.seed}"

    @property
    def finished(self) -> bool:
        return (self.run_dir / ckpt.FINAL_MODEL_FILE).is_file()

    def with_threads(self, threads: int, bar: bool = False) -> Any:
        """The config a run trains with ``threads`` unless the config names a count; without ``bar``,
        no bar of its own (a process of the grid, which shows one line per run). The folder stays the
        planned one: the thread count does not change what the run learns."""
        return dataclasses.replace(
            self.config, threads=self.config.threads or threads, progress=self.config.progress and bar
        )


class Launcher(Protocol):
    def train(self, runs: Sequence[PlannedRun], log: Log) -> bool:
        """Train the runs not finished yet; True when every run is finished (ready to evaluate),
        False when they were left to train elsewhere (submitted jobs not waited for)."""
        ...


def distinct(runs: Sequence[PlannedRun]) -> list[PlannedRun]:
    """The runs in order, each folder once (an experiment may list a run under two rows)."""
    seen: dict[Path, PlannedRun] = {}
    for run in runs:
        seen.setdefault(run.run_dir, run)
    return list(seen.values())


def default_jobs(runs: Sequence[PlannedRun], cores: int | None = None) -> int:
    """Every core busy: one run per core, or per ``train.threads`` cores where the config names a
    count; never more processes than runs. Two one-thread runs train about 1.6 times the frames of
    one two-thread run (bench/frame_cost.py), so runs side by side beat threads within a run."""
    todo = [run for run in runs if not run.finished]
    threads = max([run.config.threads for run in todo] or [1]) or 1
    return max(1, min(len(todo), (cores or cpu_cores()) // threads))


def core_share(jobs: int) -> int:
    """Torch threads for each of ``jobs`` runs side by side on this machine's cores."""
    return max(1, cpu_cores() // jobs)


#: ``evaluate(run, log)``: a finished run's evaluation, run in a lane of the grid that has no run
#: left to train (picklable: it runs in a spawned process); its results are cached where the
#: experiment's evaluation finds them afterwards.
EarlyEvaluation = Callable[[PlannedRun, Log], None]


@dataclass(frozen=True)
class LocalLauncher:
    """Runs on this machine: ``jobs`` at a time in processes of their own (None:
    :func:`default_jobs`), each with its share of the cores; one job trains in this process, as
    ``mapless reproduce`` always did. A run left to train alone under an explicit ``jobs`` > 1 still
    gets only its share (``cores // jobs`` threads): two such commands side by side, the lanes of
    a long experiment, would otherwise each take every core and slow each other several-fold.

    Side by side, the longest runs start first (:func:`expected_seconds`), and a lane with no run
    left to train evaluates the finished ones (``evaluate_early``), so no core idles while the last
    runs train."""

    jobs: int | None = None
    evaluate_early: EarlyEvaluation | None = None

    def train(self, runs: Sequence[PlannedRun], log: Log) -> bool:
        runs = distinct(runs)
        todo = [run for run in runs if not run.finished]
        jobs = min(self.jobs or default_jobs(runs), len(todo))
        if jobs <= 1:
            train_in_turn(runs, log, threads=core_share(self.jobs) if self.jobs and self.jobs > 1 else 0)
            return True
        for run in runs:
            if run.finished:
                train_run(run.config, run.run_dir, log)  # says it is reused
        train_side_by_side(todo, jobs, log, self.evaluate_early)
        return True


def train_in_turn(runs: Sequence[PlannedRun], log: Log, threads: int = 0) -> None:
    """Each run in this process, one after another, with the time left logged as they go;
    ``threads`` > 0: that many torch threads for the runs whose config names no count."""
    tally = RunTally(dict(Counter(run.model for run in runs)), log)
    for run in runs:
        config = run.with_threads(threads, bar=True)
        tally.start(run.model, f"{run.variant}, seed {run.seed}")
        tally.finish(train_run(config, run.run_dir, log))


def prepare_scenes(runs: Sequence[PlannedRun]) -> None:
    """Build the scenes the runs train on, once, before their processes start (each would otherwise
    ray-cast the same missing scenes at the same time)."""
    from mapless.train.builders import prepare_scenes as prepare

    done = set()
    for run in runs:
        key = json.dumps(dataclasses.asdict(run.config.env), sort_keys=True, default=str)
        if key not in done:
            done.add(key)
            prepare(run.config)


def expected_seconds(run: PlannedRun, frames_per_second: dict[str, float]) -> float:
    """How long ``run`` is expected to train: its wall-clock budget, or sooner its frames at the
    speed its model trained at in this grid so far (``frames_per_second``, by model)."""
    config = run.config
    budget = config.max_seconds or math.inf
    speed = frames_per_second.get(run.model)
    if speed and config.frames > 0:
        return min(budget, config.frames / speed)
    return budget


def next_run(
    waiting: list[tuple[int, PlannedRun]], frames_per_second: dict[str, float]
) -> tuple[int, PlannedRun]:
    """The longest of the ``waiting`` runs (the first planned among equals), taken out of the list:
    started first, the longest runs leave the short ones to fill the lanes at the end."""
    position = max(
        range(len(waiting)), key=lambda i: (expected_seconds(waiting[i][1], frames_per_second), -i)
    )
    return waiting.pop(position)


def train_side_by_side(
    runs: Sequence[PlannedRun], jobs: int, log: Log, evaluate_early: EarlyEvaluation | None = None
) -> None:
    """Train ``runs`` in ``jobs`` processes at a time (spawned: no state of this one is shared),
    each with ``cores // jobs`` torch threads, showing one line per run; the longest first
    (:func:`next_run`), and with ``evaluate_early``, a lane with no run left to train evaluates a
    finished one. Ctrl-C passes to every run in training, which checkpoints first; the same command
    resumes them."""
    threads = core_share(jobs)
    prepare_scenes(runs)
    context = mp.get_context("spawn")
    messages = context.Queue()
    waiting, active, outcomes = list(enumerate(runs)), {}, {}
    started: dict[int, float] = {}
    speeds: dict[str, float] = {}  # model -> frames/s of its runs trained here
    evaluations: dict[int, Any] = {}  # run index -> the process evaluating it
    unevaluated: list[int] = []  # finished runs not evaluated yet, in the order they finished
    display = GridDisplay(len(runs), log)
    display.write(f"training {len(runs)} runs, {jobs} at a time, {threads} torch thread(s) each")
    try:
        while waiting or active:
            while waiting and len(active) + len(evaluations) < jobs:
                index, run = next_run(waiting, speeds)
                args = (run.with_threads(threads), run.run_dir, index, messages, os.getpid())
                process = context.Process(target=_train_child, args=args)
                process.start()
                active[index], started[index] = process, time.monotonic()
                display.start(run)
            while evaluate_early and not waiting and unevaluated and len(active) + len(evaluations) < jobs:
                index = unevaluated.pop(0)
                args = (evaluate_early, runs[index], threads, index, messages, os.getpid())
                evaluations[index] = context.Process(target=_evaluate_child, args=args)
                evaluations[index].start()
                display.write(f"  {runs[index].label}: evaluating while the last runs train")
            _receive(messages, outcomes, display, timeout=0.5)
            for index, process in list(active.items()):
                if not process.is_alive():
                    process.join()
                    _receive(messages, outcomes, display, timeout=0)  # its last words, sent before it ended
                    del active[index]
                    kind, _ = outcomes.setdefault(index, ("failed", f"exit code {process.exitcode}"))
                    display.finish(runs[index], kind)
                    progress = read_progress(runs[index].run_dir)
                    if kind == "done" and progress:
                        speeds[runs[index].model] = progress["frames"] / (time.monotonic() - started[index])
                        unevaluated.append(index)
            for index, process in list(evaluations.items()):
                if not process.is_alive():
                    process.join()
                    del evaluations[index]  # a failure is the experiment's evaluation's to report
            display.refresh()
        for process in evaluations.values():  # what they cache, the experiment reads next
            process.join()
    except KeyboardInterrupt:
        display.write("mapless: stopping; every run in training writes a checkpoint first")
        for process in active.values():
            with contextlib.suppress(ProcessLookupError):
                os.kill(process.pid, signal.SIGINT)
        # Read on while they stop: a child ends only once what it sent is out of its queue.
        while any(process.is_alive() for process in active.values()):
            _receive(messages, outcomes, display, timeout=0.5)
        _receive(messages, outcomes, display, timeout=0)
        raise
    finally:
        display.close()
    failed = [(runs[i], detail) for i, (kind, detail) in sorted(outcomes.items()) if kind == "failed"]
    if any(kind == "stopped" for kind, _ in outcomes.values()):
        raise KeyboardInterrupt
    if failed:
        for run, detail in failed:
            log(f"{run.label} ({run.run_dir}) failed:\n{detail}")
        raise MaplessError(f"{len(failed)} of {len(runs)} runs failed (above); the others are kept")


def _receive(messages: Any, outcomes: dict, display: GridDisplay, timeout: float) -> None:
    """Show the children's log lines and record their outcomes (done, stopped, failed)."""
    while True:
        try:
            kind, index, text = messages.get(timeout=timeout) if timeout else messages.get_nowait()
        except queue.Empty:
            return
        timeout = 0
        if kind == "log":
            display.write(text)
        else:
            outcomes[index] = (kind, text)


def _evaluate_child(
    evaluate: EarlyEvaluation, run: PlannedRun, threads: int, index: int, messages: Any, parent: int
) -> None:
    """A finished run's evaluation in a spawned process of the grid (:class:`LocalLauncher`)."""
    import torch

    os.setsid()
    exit_with_parent(parent, signum=signal.SIGTERM)
    torch.set_num_threads(threads)
    with contextlib.suppress(Exception):  # the experiment evaluates it again, and reports a failure
        evaluate(run, lambda line: messages.put(("log", index, line)))


def _train_child(config: Any, run_dir: Path, index: int, messages: Any, parent: int) -> None:
    """One run in a spawned process: its log lines and its outcome go back through ``messages``.
    ``parent``: the grid's process id, as the grid knew it (it may be gone before this one starts)."""
    # Its own process group (setsid): the terminal's Ctrl-C goes to the parent only, which passes one on (two
    # would abort the run rather than checkpoint it).
    os.setsid()
    # Killed however, the parent leaves a run that checkpoints and ends, rather than an orphan that
    # holds its folder's lock and trains on what the next command would resume.
    exit_with_parent(parent, signum=signal.SIGTERM)
    try:
        train_run(config, run_dir, lambda line: messages.put(("log", index, line)))
        messages.put(("done", index, ""))
    except KeyboardInterrupt:
        messages.put(("stopped", index, ""))
    except BaseException as error:  # reported by the parent, which goes on with the other runs
        messages.put(("failed", index, "".join(traceback.format_exception(error)).rstrip()))


class GridDisplay:
    """The grid's progress: a line counting the runs ended, and a tqdm line per run started, fed by
    the progress file its trainer rewrites every few seconds (mapless.train.monitor), so that runs
    in other processes or on other machines are shown alike. Log lines print above the bars."""

    def __init__(self, total: int, log: Log) -> None:
        self.log = log
        self.grid = tqdm(total=total, desc="runs ended", unit="run", position=0, dynamic_ncols=True,
                         disable=None)  # fmt: skip
        self.bars: dict[Path, tuple[PlannedRun, tqdm, str]] = {}  # run folder -> run, bar, counter

    def write(self, line: str) -> None:
        with tqdm.external_write_mode():
            self.log(line)

    def start(self, run: PlannedRun) -> None:
        by_frames = run.config.episodes == 0
        bar = tqdm(
            total=run.config.frames if by_frames else run.config.episodes,
            desc=run.label,
            unit="frame" if by_frames else "ep",
            position=len(self.bars) + 1,
            dynamic_ncols=True,
            disable=None,
        )
        self.bars[run.run_dir] = (run, bar, "frames" if by_frames else "episodes")

    def refresh(self) -> None:
        for run, bar, counter in self.bars.values():
            progress = read_progress(run.run_dir)
            if progress:
                bar.n = progress[counter]
                bar.set_postfix(success=f"{progress['success']:.3f}", refresh=False)
                bar.refresh()

    def finish(self, run: PlannedRun, outcome: str) -> None:
        self.refresh()
        _, bar, _ = self.bars[run.run_dir]
        bar.set_postfix_str(outcome)
        self.grid.update(1)
        self.write(f"  {run.label}: {outcome}")

    def close(self) -> None:
        for _, bar, _ in self.bars.values():
            bar.close()
        self.grid.close()


def read_progress(run_dir: Path) -> dict | None:
    """A run's progress file (episodes, frames, running success), or None before it has one."""
    try:
        return json.loads((run_dir / ckpt.PROGRESS_FILE).read_text())
    except (OSError, ValueError):
        return None


def in_use(run_dir: Path) -> bool:
    """Whether a trainer holds ``run_dir`` (its lock, mapless.train.run.run_folder_lock)."""
    from mapless.train.run import LOCK_FILE

    if not run_dir.is_dir():
        return False
    with open(run_dir / LOCK_FILE, "a+") as handle:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            return True
        fcntl.flock(handle, fcntl.LOCK_UN)
    return False


# --- Slurm, through submitit ---------------------------------------------------------------------

#: Where the jobs of a runs folder keep their logs and the job index (run folder name -> job id).
SLURM_DIR = "slurm"
JOBS_FILE = "jobs.json"


def import_submitit() -> Any:
    try:
        import submitit
    except ImportError:
        raise MaplessError(
            "--launcher slurm submits through submitit, which is not installed: "
            'pip install -c constraints.txt -e ".[cluster]"'
        ) from None
    return submitit


#: The Slurm commands submitit runs: submission, the job step, and the query that shows the
#: scheduler answers.
SLURM_COMMANDS = ("sbatch", "srun", "sinfo")


def slurm_problem(timeout: float = 30.0) -> str | None:
    """Why jobs cannot be submitted to Slurm from this machine (None: they can), found before any
    run starts: submitit otherwise fails at the first submission, or in its job, with a traceback."""
    missing = [command for command in SLURM_COMMANDS if shutil.which(command) is None]
    if missing:
        return (
            f"--launcher slurm needs Slurm's {', '.join(SLURM_COMMANDS)} on PATH, and "
            f"{', '.join(missing)} {'is' if len(missing) == 1 else 'are'} not there: run the command "
            "on a machine of the cluster (its login node), or leave out --launcher slurm to train here"
        )
    try:
        done = subprocess.run(
            ["sinfo", "--noheader", "--format=%P"], capture_output=True, text=True, timeout=timeout
        )
    except (OSError, subprocess.TimeoutExpired) as error:
        return (
            f"--launcher slurm: the Slurm scheduler does not answer (sinfo: {error}); nothing was submitted"
        )
    if done.returncode != 0:
        reason = (done.stderr.strip().splitlines() or [f"exit status {done.returncode}"])[0]
        return (
            f"--launcher slurm: the Slurm scheduler does not answer (sinfo: {reason}); nothing was submitted"
        )
    return None


@dataclass(frozen=True)
class SlurmLauncher:
    """Each run not finished as a Slurm job (submitit), unless a job of it is still queued or
    running; waits for them (``wait``) or returns, and a later call collects what they trained.

    partition, minutes, cpus, gpus: the jobs' resources (minutes None: the runs' ``max_seconds``
    plus half an hour for loading, or a day for runs without one). ``cluster``: ``local`` runs the
    jobs as processes on this machine (submitit's local executor: how the tests run it)."""

    partition: str | None = None
    minutes: int | None = None
    cpus: int = 2
    gpus: int = 0
    wait: bool = True
    cluster: str = "slurm"
    poll_seconds: float = 10.0

    def __post_init__(self) -> None:
        # Made when the command is read, so a machine without Slurm is refused before any work.
        problem = slurm_problem() if self.cluster == "slurm" else None
        if problem is not None:
            raise MaplessError(problem)

    def train(self, runs: Sequence[PlannedRun], log: Log) -> bool:
        submitit = import_submitit()
        runs = distinct(runs)
        todo = [run for run in runs if not run.finished]
        for run in runs:
            if run.finished:
                train_run(run.config, run.run_dir, log)  # says it is reused
        if not todo:
            return True
        folder = todo[0].run_dir.parent / SLURM_DIR
        index_file = folder / JOBS_FILE
        index = json.loads(index_file.read_text()) if index_file.is_file() else {}
        job_class = submitit.SlurmJob if self.cluster == "slurm" else submitit.LocalJob
        executor = submitit.AutoExecutor(folder=folder, cluster=self.cluster)
        executor.update_parameters(
            name="mapless", timeout_min=self.minutes or _job_minutes(todo), cpus_per_task=self.cpus,
            gpus_per_node=self.gpus, tasks_per_node=1, nodes=1,
            **({"slurm_partition": self.partition} if self.partition else {}),
        )  # fmt: skip
        prepare_scenes(todo)
        jobs: dict[Path, Any] = {}
        for run in todo:
            known = index.get(run.run_dir.name)
            job = job_class(folder, known) if known else None
            if job is not None and not job.done():
                log(f"  {run.label}: job {known} is still queued or running")
            elif in_use(run.run_dir):
                log(f"  {run.label}: {run.run_dir} is being trained by another process")
                job = _HeldRun(run.run_dir)
            else:
                job = executor.submit(_train_job, run.with_threads(self.cpus), str(run.run_dir))
                index[run.run_dir.name] = job.job_id
                log(f"  {run.label}: submitted job {job.job_id} -> {run.run_dir}")
            jobs[run.run_dir] = job
        write_text(index_file, json.dumps(index, indent=1))
        if not self.wait:
            log(f"{len(todo)} run(s) training as jobs (logs in {folder}); the same command collects "
                "them once they have ended, and resubmits any that stopped before the end")  # fmt: skip
            return False
        self._wait(todo, jobs, log)
        failed = [run for run in todo if not run.finished]
        if failed:
            for run in failed:
                job = jobs[run.run_dir]
                where = getattr(job, "paths", None)
                log(f"{run.label} did not finish" + (f"; its log: {where.stderr}" if where else ""))
            raise MaplessError(
                f"{len(failed)} of {len(todo)} job(s) ended before their run finished (above); the same "
                "command submits them again, and they resume from their checkpoints"
            )
        return True

    def _wait(self, todo: Sequence[PlannedRun], jobs: dict[Path, Any], log: Log) -> None:
        display = GridDisplay(len(todo), log)
        for run in todo:
            display.start(run)
        pending = list(todo)
        try:
            while pending:
                for run in list(pending):
                    if jobs[run.run_dir].done():
                        pending.remove(run)
                        display.finish(run, "finished" if run.finished else "ended unfinished")
                display.refresh()
                if pending:
                    time.sleep(self.poll_seconds)
        except KeyboardInterrupt:
            display.write("mapless: no longer waiting; the jobs go on, and the same command collects them")
            raise
        finally:
            display.close()


@dataclass(frozen=True)
class _HeldRun:
    """A run another process trains (its folder locked): done when the lock is released."""

    run_dir: Path

    def done(self) -> bool:
        return not in_use(self.run_dir)


def _job_minutes(runs: Sequence[PlannedRun]) -> int:
    seconds = [run.config.max_seconds for run in runs]
    return 24 * 60 if 0 in seconds else math.ceil(max(seconds) / 60) + 30


def _train_job(config: Any, run_dir: str) -> float:
    """What a job runs (submitit pickles it by name): train or resume one run. submitit warns a job
    before its time limit with SIGUSR2 (90 s on Slurm), which here takes the trainer's graceful
    path of SIGTERM: the run checkpoints and ends, and the next ``reproduce`` resubmits it."""
    signal.signal(signal.SIGUSR2, lambda *_: os.kill(os.getpid(), signal.SIGTERM))
    return train_run(config, Path(run_dir), print)
