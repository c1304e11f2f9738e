"""`mapless reproduce` trains an experiment's runs side by side (``--jobs``) or as Slurm jobs
(``--launcher slurm``, run here by submitit's local executor: real processes, no cluster), and a
grid that was killed goes on where it stopped. On the real scenes and episode files of
test_eval_reproduce's workspace."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml
from test_eval_reproduce import workspace  # noqa: F401 - the fixture: three built scenes, episode files

from mapless import checkpoint as ckpt
from mapless.cli import main
from mapless.experiments import SlurmLauncher, experiment_runs, launch, load_experiment, reproduce
from mapless.experiments.launch import LocalLauncher, default_jobs, in_use, read_progress
from mapless.provenance import cpu_cores

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("single_torch_thread")]

#: Two runs: a3c with two seeds (random, untrained, is left out to keep it short).
TWO_RUNS = ["--set", "models=[a3c]", "--set", "focus=a3c", "--seeds", "2"]


def _command(workspace, name: str, *more: str) -> list[str]:  # noqa: F811 - the fixture's value
    root, config = workspace
    return ["reproduce", "table1", "--config", str(config), *TWO_RUNS, "--set", f"runs_dir={root / name}",
            "--reports", str(root / f"{name}_reports"), *more]  # fmt: skip


def _report(workspace, name: str) -> dict:  # noqa: F811
    return json.loads((workspace[0] / f"{name}_reports" / "table1" / "table1.json").read_text())


def _wait_until(condition, seconds: float, what: str) -> None:
    deadline = time.monotonic() + seconds
    while not condition():
        assert time.monotonic() < deadline, f"no {what} within {seconds} s"
        time.sleep(0.2)


def test_runs_train_side_by_side_with_the_results_of_one_after_another(workspace, capsys):  # noqa: F811
    assert main(_command(workspace, "side_by_side", "--jobs", "2")) == 0
    out = capsys.readouterr().out
    threads = max(1, cpu_cores() // 2)
    assert f"training 2 runs, 2 at a time, {threads} torch thread(s) each" in out
    assert "a3c all, seed 1: done" in out and "a3c all, seed 2: done" in out
    side_by_side = _report(workspace, "side_by_side")
    for run in side_by_side["models"][0]["runs"]:
        # Each process trained with its share of the cores, and its config says so.
        config = yaml.safe_load((Path(run["run_dir"]) / ckpt.CONFIG_FILE).read_text())
        assert (
            config["threads"] == threads
            and f"{threads} thread(s)" in (Path(run["run_dir"]) / "config.yaml").read_text()
        )

    assert main(_command(workspace, "in_turn", "--jobs", "1")) == 0
    out = capsys.readouterr().out
    assert "[run 1 of 2] a3c all, seed 1" in out and "[run 2 of 2] a3c all, seed 2" in out
    in_turn = _report(workspace, "in_turn")
    # The same runs (same folder names: the thread count is not part of what a run is) and the same
    # trained models: every episode of the report alike.
    names = [
        [Path(r["run_dir"]).name for r in report["models"][0]["runs"]] for report in (side_by_side, in_turn)
    ]
    assert names[0] == names[1]
    assert side_by_side["models"][0]["episodes"] == in_turn["models"][0]["episodes"]


def test_a_stopped_or_killed_grid_resumes_where_it_stopped(workspace, capsys):  # noqa: F811
    root, path = workspace
    budget = "train.episodes=480"  # long enough that no run ends between its first checkpoint and the signal
    command = _command(workspace, "killed", "--jobs", "2", "--set", budget)
    overrides = ["models=[a3c]", "focus=a3c", f"runs_dir={root / 'killed'}", budget]
    runs = experiment_runs(load_experiment("table1", "smoke", path, overrides, seeds=2))

    def start() -> subprocess.Popen:
        argv = [sys.executable, "-m", "mapless", *command]
        # Ctrl-C as a terminal delivers it. A non-interactive shell starts a background job (`cmd &`,
        # as CI harnesses do) with SIGINT ignored; pytest, and every child, inherits that, and Python
        # then installs no KeyboardInterrupt handler: the grid would be deaf to Ctrl-C.
        reset = lambda: signal.signal(signal.SIGINT, signal.SIG_DFL)  # noqa: E731
        return subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, preexec_fn=reset)

    def checkpointed(run) -> int:
        file = run.run_dir / ckpt.CHECKPOINT_FILE
        return ckpt.load_file(file)["counters"]["episodes"] if file.is_file() else 0

    # Ctrl-C: passed on to each run in training, which checkpoints and ends; the grid says interrupted.
    grid = start()
    try:
        _wait_until(lambda: all(checkpointed(r) for r in runs), 600, "checkpoints")
        grid.send_signal(signal.SIGINT)
        assert grid.wait(timeout=600) == 130
    finally:
        grid.kill()
    stopped = [checkpointed(r) for r in runs]
    assert not any(r.finished for r in runs) and not any(in_use(r.run_dir) for r in runs)

    # SIGKILL: the parent gets no chance to stop its runs; each sees it go, checkpoints and ends
    # rather than train on as an orphan that holds its folder.
    grid = start()
    try:
        progress = lambda r: (read_progress(r.run_dir) or {}).get("episodes", 0)  # noqa: E731
        _wait_until(
            lambda: all(progress(r) > s for r, s in zip(runs, stopped, strict=True)), 600, "resumed runs"
        )
    finally:
        grid.kill()
        grid.wait()
    _wait_until(lambda: not any(in_use(r.run_dir) for r in runs), 300, "run left its folder")
    assert not all(r.finished for r in runs), "the runs ended before the kill; nothing to resume"

    assert main(command) == 0
    out = capsys.readouterr().out
    assert all(run.finished for run in runs)
    assert "resuming" in out and (root / "killed_reports" / "table1" / "table1.md").is_file()


def test_slurm_jobs_run_by_submitits_local_executor_are_collected_by_a_later_call(workspace, capsys):  # noqa: F811
    import submitit  # the dev extra installs it

    root, path = workspace
    overrides = ["models=[a3c]", "focus=a3c", f"runs_dir={root / 'slurm_runs'}"]
    reports = root / "slurm_reports"
    one_seed = load_experiment("table1", "smoke", path, overrides)
    local = SlurmLauncher(cpus=1, cluster="local", poll_seconds=0.5)

    # Submit and return: nothing to report yet.
    no_wait = SlurmLauncher(cpus=1, cluster="local", wait=False)
    assert reproduce(one_seed, reports, launcher=no_wait) is None
    (run,) = experiment_runs(one_seed)
    folder = root / "slurm_runs" / "slurm"
    index = json.loads((folder / "jobs.json").read_text())
    assert list(index) == [run.run_dir.name]
    assert "submitted job" in capsys.readouterr().out
    # The job is a process of its own, as a Slurm job would be: it trains the run by itself.
    _wait_until(lambda: run.finished and not in_use(run.run_dir), 600, "finished job")
    job = submitit.LocalJob(folder, index[run.run_dir.name])
    assert job.result() == 1.0  # the share of the run it trained
    assert f"-> {run.run_dir}" in Path(job.paths.stdout).read_text()

    # A later call collects the finished run; the second seed is submitted and waited for.
    two_seeds = load_experiment("table1", "smoke", path, overrides, seeds=2)
    result = reproduce(two_seeds, reports, launcher=local)
    assert result is not None and (reports / "table1" / "table1.md").is_file()
    out = capsys.readouterr().out
    assert f"reusing finished run {run.run_dir}" in out
    assert out.count("submitted job") == 1 and "a3c all, seed 2: finished" in out
    record = result["payload"]["models"][0]
    assert [Path(r["run_dir"]).name.split("__")[2] for r in record["runs"]] == ["s1", "s2"]
    assert len(json.loads((folder / "jobs.json").read_text())) == 2


def test_slurm_without_submitit_or_local_with_slurm_options_is_a_clear_error(workspace, monkeypatch, capsys):  # noqa: F811
    monkeypatch.setitem(sys.modules, "submitit", None)  # as if not installed
    assert main(_command(workspace, "no_submitit", "--launcher", "slurm")) == 2
    assert 'pip install -c constraints.txt -e ".[cluster]"' in capsys.readouterr().err
    assert main(_command(workspace, "no_submitit", "--partition", "gpu")) == 2
    assert "--partition applies to --launcher slurm" in capsys.readouterr().err
    assert not (workspace[0] / "no_submitit").exists(), "work started before the error"


def test_the_default_keeps_every_core_busy_with_one_run_per_core(workspace, tmp_path):  # noqa: F811
    _, path = workspace
    overrides = ["models=[a3c,cvmeta]", f"runs_dir={tmp_path}"]
    runs = experiment_runs(load_experiment("table1", "smoke", path, overrides, seeds=2))  # four runs
    assert default_jobs(runs, cores=2) == 2  # the README's main job on 2 cores: two at a time
    assert default_jobs(runs, cores=16) == 4  # no more processes than runs
    assert default_jobs(runs, cores=1) == 1
    threaded = experiment_runs(
        load_experiment("table1", "smoke", path, [*overrides, "train.threads=2"], seeds=2)
    )
    assert default_jobs(threaded, cores=4) == 2  # runs that name their threads get that many cores
    first = runs[0].run_dir
    first.mkdir(parents=True)
    (first / ckpt.FINAL_MODEL_FILE).touch()  # a finished run needs no process
    assert default_jobs(runs, cores=16) == 3


def test_an_explicit_jobs_count_gives_a_lone_run_its_share_of_the_cores(workspace, tmp_path, monkeypatch):  # noqa: F811
    """Two ``reproduce --jobs 2`` lanes side by side, each down to its last run: that run trains in
    its command's process, and must keep to half the cores, not take both (each lane then ran ~8x
    slower, 2026-12-06). Without ``--jobs``, or with 1, it keeps the config's count (0: every core)."""
    _, path = workspace
    runs = experiment_runs(load_experiment("table1", "smoke", path, ["models=[a3c]", f"runs_dir={tmp_path}"]))
    assert len(runs) == 1 and runs[0].config.threads == 0
    trained = []
    monkeypatch.setattr(
        launch, "train_run", lambda config, run_dir, log: trained.append((config.threads, run_dir)) or 1.0
    )
    monkeypatch.setattr(launch, "cpu_cores", lambda: 4)
    for jobs in (2, 4, None, 1):
        LocalLauncher(jobs).train(runs, lambda message: None)
    assert trained == [(2, runs[0].run_dir), (1, runs[0].run_dir), (0, runs[0].run_dir), (0, runs[0].run_dir)]


def _planned(model: str, max_seconds: float, frames: int) -> launch.PlannedRun:
    from types import SimpleNamespace

    config = SimpleNamespace(max_seconds=max_seconds, frames=frames)
    return launch.PlannedRun(model, "all", 1, config, Path(model))


def test_the_longest_runs_start_first() -> None:
    """Every run has the same 15 minutes, but the mlp, once one of its runs has shown its speed,
    reaches its frames in 5: its other runs go last, so the lanes end together."""
    planned = [_planned("mlp", 900, 300_000), _planned("a3c", 900, 400_000), _planned("cvmeta", 900, 200_000)]
    runs = list(enumerate(planned))
    speeds: dict[str, float] = {}
    assert launch.expected_seconds(runs[0][1], speeds) == 900  # no speed yet: its wall-clock budget
    assert launch.next_run(list(runs), speeds)[1].model == "mlp"  # equals: the first planned
    speeds = {"mlp": 1000.0, "a3c": 300.0}
    assert launch.expected_seconds(runs[0][1], speeds) == 300
    assert launch.expected_seconds(runs[1][1], speeds) == 900  # its frames would take longer than 900 s
    waiting = list(runs)
    order = [launch.next_run(waiting, speeds)[1].model for _ in range(3)]
    assert order == ["a3c", "cvmeta", "mlp"] and waiting == []
    unbounded = _planned("a3c", 0, 1_000)
    assert launch.expected_seconds(unbounded, {}) == float("inf")


def test_a_run_evaluated_in_a_free_lane_is_not_evaluated_again(workspace, tmp_path, monkeypatch):  # noqa: F811
    """What a lane of the grid evaluates while the last runs train (EvaluateInLane, one worker) is
    what the experiment's evaluation reads back afterwards: it evaluates nothing again."""
    from mapless.evaluate import selection
    from mapless.experiments.evaluator import EvaluateInLane, Evaluator

    _, path = workspace
    config = load_experiment("table1", "smoke", path, ["models=[a3c]", "focus=a3c", f"runs_dir={tmp_path}"])
    (run,) = experiment_runs(config)
    launch.train_run(run.config, run.run_dir, lambda line: None)
    EvaluateInLane(config)(run, lambda line: None)
    evaluated = []
    monkeypatch.setattr(selection, "evaluate", lambda *args, **kwargs: evaluated.append(args))
    ev = Evaluator(config, lambda line: None)
    results, _ = ev.trained(run.run_dir, run.config)
    assert evaluated == [] and len(results) == len(ev.report_episodes)
