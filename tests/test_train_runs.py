"""Run folders, checkpoints and exact resume of the batched trainer; bad configs fail early."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
import yaml
from train_fixtures import fixture_library, tiny_config

from mapless import checkpoint as ckpt
from mapless.agent.precision import KERNEL_CACHE_CAPACITY
from mapless.cli import main as cli_main
from mapless.config import ConfigError, from_dict, load_config
from mapless.configs import configs_dir
from mapless.train.builders import new_model
from mapless.train.config import TrainConfig
from mapless.train.gradients import clip_gradients
from mapless.train.recipes import load_train_config
from mapless.train.run import resume_config, train
from mapless.train.runtime import configure_torch


def _state(run_dir: Path) -> dict:
    return ckpt.load_file(run_dir / ckpt.CHECKPOINT_FILE)


def test_run_folder_and_exact_resume(tmp_path: Path) -> None:
    config = tiny_config("savn", "episodes=16", "checkpoint_every=8", "log_every=4")
    straight = tmp_path / "straight"
    summary = train(config, straight, library_factory=fixture_library)
    assert summary["episodes"] == 16 and summary["frames"] > 0

    # The run folder: resolved config, TensorBoard events, metrics, snapshots, checkpoint, final model.
    assert load_config(TrainConfig, straight / ckpt.CONFIG_FILE) == config
    assert list(straight.glob("events.out.tfevents.*"))
    records = [json.loads(line) for line in (straight / "metrics.jsonl").read_text().splitlines()]
    assert [r["episodes"] for r in records] == [4, 8, 12, 16]
    for key in (
        "charts/success",
        "charts/spl",
        "charts/reward",
        "charts/episode_length",
        "losses/total",
        "losses/entropy",
        "losses/grad_norm",
        "perf/frames_per_s",
    ):
        assert key in records[-1]
    # savn is adaptive, so nothing clips its gradient; its norm is logged all the same.
    assert all(r["losses/grad_norm"] > 0 for r in records)
    assert [n for n, _ in ckpt.snapshots(straight)] == [8, 16]
    assert (straight / ckpt.FINAL_MODEL_FILE).is_file()
    assert not list(straight.rglob("*.tmp"))

    # Stop half-way, then resume with the budget extended: bit-identical to the straight run.
    halted = tmp_path / "halted"
    train(config.replace(episodes=8), halted, library_factory=fixture_library)
    assert _state(halted)["counters"]["episodes"] == 8
    # As if the run had logged 12 episodes and been killed before its next checkpoint.
    with (halted / "metrics.jsonl").open("a") as f:
        f.write(json.dumps({"episodes": 12, "frames": 0, "time": 0.0, "lost": True}) + "\n")
        f.write('{"episodes": 16, "fra')  # and torn by the kill mid-line
    resumed_config, state = resume_config(halted, ["episodes=16"])
    assert resumed_config == config
    train(resumed_config, halted, resume=state, library_factory=fixture_library)
    resumed = [json.loads(line) for line in (halted / "metrics.jsonl").read_text().splitlines()]
    assert [r["episodes"] for r in resumed] == [4, 8, 12, 16]  # the lost record replaced, none twice
    assert not any("lost" in r for r in resumed)
    assert resumed[-1]["charts/success"] == records[-1]["charts/success"]

    a, b = _state(straight), _state(halted)
    assert a["counters"] == b["counters"]
    for key, value in a["model"].items():
        assert torch.equal(value, b["model"][key]), key
    for index, slot in a["optimizer"]["state"].items():
        for name, value in slot.items():
            assert torch.equal(value, b["optimizer"]["state"][index][name]), (index, name)

    # What evaluation loads: model + config, weights_only under the hood.
    model, loaded_config, counters = ckpt.load_model(straight)
    assert from_dict(TrainConfig, loaded_config) == config and counters["episodes"] == 16
    assert not model.training
    for key, value in model.state_dict().items():
        assert torch.equal(value, a["model"][key])


@pytest.mark.parametrize(("model", "clipped"), [("a3c", True), ("savn", False)])
def test_gradient_clipping_as_the_references(model: str, clipped: bool) -> None:
    """Non-adaptive models are clipped at norm 100, adaptive ones not; the norm before is returned."""
    config = tiny_config(model)
    net = new_model(config)
    for p in net.parameters():
        p.grad = torch.ones_like(p)
    count = sum(p.numel() for p in net.parameters())
    assert count > 100**2  # an all-ones gradient then has a norm above the limit
    assert clip_gradients(net, config) == pytest.approx(count**0.5, rel=1e-5)
    after = torch.cat([p.grad.flatten() for p in net.parameters()]).norm()
    assert float(after) == pytest.approx(config.a3c.grad_clip if clipped else count**0.5, rel=1e-3)


def test_trainers_keep_more_compiled_bf16_kernels_unless_the_user_chose(monkeypatch) -> None:
    """oneDNN's default 1,024 compiled kernels are too few for a cvmeta run's product shapes."""
    monkeypatch.delenv("ONEDNN_PRIMITIVE_CACHE_CAPACITY", raising=False)
    configure_torch(0)
    assert int(os.environ["ONEDNN_PRIMITIVE_CACHE_CAPACITY"]) == KERNEL_CACHE_CAPACITY > 1024
    monkeypatch.setenv("ONEDNN_PRIMITIVE_CACHE_CAPACITY", "512")
    configure_torch(0)
    assert os.environ["ONEDNN_PRIMITIVE_CACHE_CAPACITY"] == "512"


def test_the_last_partial_log_interval_is_written(tmp_path: Path) -> None:
    train(
        tiny_config("a3c", "a3c.batch_size=2", "episodes=6", "log_every=4"),
        tmp_path,
        library_factory=fixture_library,
    )
    records = [json.loads(line) for line in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    assert [r["episodes"] for r in records] == [4, 6]


def test_checkpoint_files_are_plain_data(tmp_path: Path) -> None:
    train(tiny_config("a3c", "episodes=4"), tmp_path, library_factory=fixture_library)
    for path in [tmp_path / ckpt.CHECKPOINT_FILE, tmp_path / ckpt.FINAL_MODEL_FILE]:
        payload = torch.load(path, weights_only=True)  # raises on anything but plain data
        assert payload["format"] == ckpt.FORMAT_VERSION
    with pytest.raises(ckpt.CheckpointError, match="no checkpoint"):
        resume_config(tmp_path / "missing")


@pytest.mark.parametrize(("every", "snapshots"), [(8, [8]), (16, [])])
def test_ctrl_c_checkpoints_but_adds_no_snapshot_off_the_schedule(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, every: int, snapshots: list[int]
) -> None:
    """Selection picks among the snapshots, so a run stopped and resumed must offer the ones a
    straight run offers: a stop writes one only where its update crossed the schedule."""
    from mapless.train.runtime import GracefulStop

    enter = GracefulStop.__enter__

    def ctrl_c_at_once(self):  # as if Ctrl-C came during the first update
        enter(self)
        self.requested = True
        return self

    config = tiny_config("a3c", "episodes=16", "a3c.batch_size=8", f"checkpoint_every={every}")
    monkeypatch.setattr(GracefulStop, "__enter__", ctrl_c_at_once)
    assert train(config, tmp_path, library_factory=fixture_library)["stopped_early"]
    assert _state(tmp_path)["counters"]["episodes"] == 8
    assert [n for n, _ in ckpt.snapshots(tmp_path)] == snapshots
    monkeypatch.setattr(GracefulStop, "__enter__", enter)
    train(config, tmp_path, resume=_state(tmp_path), library_factory=fixture_library)
    assert [n for n, _ in ckpt.snapshots(tmp_path)] == [*snapshots, 16]


def _curves(run_dir: Path) -> tuple[list[dict], dict[str, list[tuple[int, float]]]]:
    """metrics.jsonl and the TensorBoard scalars, without the wall-clock values."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    clock = ("time", "perf/frames_per_s", "perf/episodes_per_s")
    lines = (run_dir / "metrics.jsonl").read_text().splitlines()
    records = [{k: v for k, v in json.loads(line).items() if k not in clock} for line in lines]
    events = EventAccumulator(str(run_dir)).Reload()
    scalars = {
        tag: [(e.step, e.value) for e in events.Scalars(tag)]
        for tag in events.Tags()["scalars"]
        if tag not in clock
    }
    return records, scalars


@pytest.mark.parametrize("algo", ["a3c", "ppo"])
def test_ctrl_c_and_resume_log_the_curves_of_a_straight_run(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, algo: str
) -> None:
    """Stopped three times mid-interval (issue 25, item 12): no record at a stop, no short interval
    after it; metrics.jsonl and TensorBoard hold what the uninterrupted run logs."""
    from mapless.train.runtime import GracefulStop

    extra = (
        ["algo=ppo", "ppo.envs=2", "ppo.steps=4", "ppo.minibatches=1"]
        if algo == "ppo"
        else ["a3c.batch_size=2"]
    )
    config = tiny_config("a3c", "episodes=12", "log_every=4", "checkpoint_every=8", *extra)
    straight, stopped = tmp_path / "straight", tmp_path / "stopped"
    train(config, straight, library_factory=fixture_library)
    enter = GracefulStop.__enter__

    def ctrl_c_at_once(self):  # as if Ctrl-C came during the first update of each run
        enter(self)
        self.requested = True
        return self

    monkeypatch.setattr(GracefulStop, "__enter__", ctrl_c_at_once)
    assert train(config, stopped, library_factory=fixture_library)["stopped_early"]
    for _ in range(2):
        assert train(config, stopped, resume=_state(stopped), library_factory=fixture_library)[
            "stopped_early"
        ]
    monkeypatch.setattr(GracefulStop, "__enter__", enter)
    train(config, stopped, resume=_state(stopped), library_factory=fixture_library)
    assert _state(stopped)["counters"] == _state(straight)["counters"]
    records, scalars = _curves(straight)
    assert len(records) == 3 and records[-1]["episodes"] == 12  # PPO's updates end episodes unevenly
    assert _curves(stopped) == (records, scalars)


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("model.name=resnet9000", "model.name"),
        ("a3c.lr=-1e-4", "a3c.lr"),
        ("env.scenes=FloorPlan999", "env.scenes"),
        ("env.scenes=nosuchsplit", "env.scenes"),
        ("episodes=0", "episodes"),
        ("a3c.batch_size=0", "a3c.batch_size"),
        ("a3c.mode=sync", "a3c.mode"),
        ("a3c.precision=fp16", "a3c.precision"),
        ("a3c.learning_rate=1", "learning_rate"),
    ],
)
def test_bad_config_is_a_clear_error(override: str, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        tiny_config("a3c", override)


def test_cli_reports_bad_config_before_work(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    config = tmp_path / "bad.yaml"
    config.write_text(yaml.safe_dump({"model": {"name": "a3c"}, "episodes": 10, "a3c": {"lr": -1}}))
    assert cli_main(["train", str(config), "--run-dir", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err
    assert "a3c.lr" in err and "Traceback" not in err
    assert not (tmp_path / "run").exists()
    assert cli_main(["train", "--resume", str(tmp_path / "nothing")]) == 2
    assert "no checkpoint" in capsys.readouterr().err


@pytest.mark.slow
def test_cli_train_and_resume_on_a_built_scene(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The real path: `mapless train CONFIG.yaml --set ...`, then `--resume RUN_DIR` with a larger budget."""
    config = tmp_path / "train.yaml"
    config.write_text(
        yaml.safe_dump(
            {
                "model": {"name": "cvmeta", "hidden_size": 16, "fusion_channels": 2},
                "env": {"scenes": "FloorPlan401"},  # built once into the session's test cache
                "a3c": {"batch_size": 4},
                "episodes": 8,
                "checkpoint_every": 8,
                "log_every": 4,
                "threads": 1,
                "progress": False,
            }
        )
    )
    run_dir = tmp_path / "run"
    assert cli_main(["train", str(config), "--run-dir", str(run_dir), "--set", "meta.first_order=true"]) == 0
    first = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert first["episodes"] == 8 and first["run_dir"] == str(run_dir)
    assert load_config(TrainConfig, run_dir / ckpt.CONFIG_FILE).meta.first_order
    assert cli_main(["train", "--resume", str(run_dir), "--set", "episodes=16"]) == 0
    second = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert second["episodes"] == 16 and second["updates"] == 4
    assert [n for n, _ in ckpt.snapshots(run_dir)] == [8, 16]


@pytest.mark.parametrize("path", sorted(configs_dir().glob("train_*.yaml")), ids=lambda p: p.name)
def test_shipped_training_configs_load(path: Path) -> None:
    """As `mapless train` reads them: over the recipe a file names (mapless/configs/recipes/)."""
    config = load_train_config(path)
    assert config.episodes > 0 or config.frames > 0


def _wait_for(predicate, process: subprocess.Popen, seconds: float = 180.0) -> None:
    deadline = time.monotonic() + seconds
    while not predicate():
        assert process.poll() is None, process.communicate()
        assert time.monotonic() < deadline, "the trainer wrote no checkpoint in time"
        time.sleep(0.2)


@pytest.mark.slow
def test_sigint_stops_at_a_checkpoint_and_sigkill_loses_only_the_work_since_the_last(tmp_path: Path) -> None:
    """A real `mapless train` process: Ctrl-C finishes the update, checkpoints and exits 130 with the
    resume command; SIGKILL mid-run leaves the last checkpoint whole; `--resume` then finishes."""
    config = tmp_path / "train.yaml"
    budget = {"model": {"name": "a3c", "hidden_size": 16}, "env": {"scenes": "FloorPlan401"},
              "a3c": {"batch_size": 4}, "episodes": 1_000_000, "checkpoint_every": 8, "log_every": 4,
              "threads": 1, "progress": False}  # fmt: skip
    config.write_text(yaml.safe_dump(budget))
    run_dir, state = tmp_path / "run", tmp_path / "run" / ckpt.CHECKPOINT_FILE
    command = [sys.executable, "-m", "mapless", "train"]
    trainer = subprocess.Popen([*command, str(config), "--run-dir", str(run_dir)], stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True)  # fmt: skip
    _wait_for(state.exists, trainer)
    trainer.send_signal(signal.SIGINT)
    out, err = trainer.communicate(timeout=120)
    assert trainer.returncode == 130, err
    assert f"mapless train --resume {run_dir}" in err and "Traceback" not in err
    stopped = _state(run_dir)["counters"]
    assert json.loads(out.strip().splitlines()[-1])["episodes"] == stopped["episodes"] >= 8
    assert stopped["episodes"] % 4 == 0  # a whole update, not part of one
    assert not (run_dir / ckpt.FINAL_MODEL_FILE).exists()

    resumed = subprocess.Popen([*command, "--resume", str(run_dir)], stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True)  # fmt: skip
    _wait_for(lambda: _state(run_dir)["counters"]["episodes"] >= stopped["episodes"] + 8, resumed)
    resumed.kill()
    resumed.communicate(timeout=60)
    killed = _state(run_dir)["counters"]  # the last checkpoint before the kill loads whole
    assert killed["episodes"] > stopped["episodes"]
    records = [
        json.loads(line)
        for line in (run_dir / "metrics.jsonl").read_text().splitlines()
        if line.endswith("}")
    ]
    # What the killed process had done past its last checkpoint is all that is lost: under one interval.
    assert 0 <= records[-1]["episodes"] - killed["episodes"] <= 8

    finish = ["--resume", str(run_dir), "--set", f"episodes={killed['episodes'] + 8}"]
    done = subprocess.run([*command, *finish], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert _state(run_dir)["counters"]["episodes"] == killed["episodes"] + 8
    assert (run_dir / ckpt.FINAL_MODEL_FILE).is_file()


def test_a_resumed_run_removes_the_torn_writes_of_a_killed_one(tmp_path: Path) -> None:
    run = tmp_path / "run"
    train(tiny_config("a3c", "episodes=8", "checkpoint_every=4"), run, library_factory=fixture_library)
    torn = [run / ".checkpoint.pt.0badc0de.tmp", run / "checkpoints" / ".model_0000000012.pt.0badc0de.tmp"]
    for path in torn:
        path.write_bytes(b"half a checkpoint")
    config, state = resume_config(run, ["episodes=12"])
    train(config, run, resume=state, library_factory=fixture_library)
    assert not any(path.exists() for path in torn)
    assert not list(run.rglob("*.tmp"))


def test_a_run_folder_in_use_refuses_a_second_trainer(tmp_path: Path) -> None:
    from mapless.errors import MaplessError
    from mapless.train.run import run_folder_lock

    run = tmp_path / "run"
    run.mkdir()
    with run_folder_lock(run), pytest.raises(MaplessError, match="in use by another trainer"):
        train(tiny_config("a3c", "episodes=4"), run, library_factory=fixture_library)
    train(tiny_config("a3c", "episodes=4"), run, library_factory=fixture_library)  # free again
    assert (run / ckpt.FINAL_MODEL_FILE).is_file()


@pytest.mark.parametrize("override", ["seed=7", "model.hidden_size=8", "algo=ppo", "a3c.batch_size=2"])
def test_resume_refuses_settings_the_checkpoint_depends_on(tmp_path: Path, override: str) -> None:
    run = tmp_path / "run"
    train(tiny_config("a3c", "episodes=4"), run, library_factory=fixture_library)
    with pytest.raises(ConfigError, match="a resumed run keeps"):
        resume_config(run, ["episodes=8", override])


def test_sigterm_takes_the_graceful_path_of_ctrl_c() -> None:
    from mapless.train.runtime import GracefulStop

    with GracefulStop() as stop:
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(0.05)  # the handler runs between bytecodes of this thread
        assert stop.requested
        with pytest.raises(KeyboardInterrupt):  # a second signal aborts
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.05)
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL  # the handler is put back


def _children(pid: int) -> list[int]:
    listed = subprocess.run(["ps", "-o", "pid=", "--ppid", str(pid)], capture_output=True, text=True)
    return [int(line) for line in listed.stdout.split()]


def _alive(pid: int) -> bool:
    """Running (a zombie has ended: only its exit status is left to collect)."""
    state = subprocess.run(["ps", "-o", "stat=", "-p", str(pid)], capture_output=True, text=True).stdout
    return bool(state.strip()) and not state.strip().startswith("Z")


@pytest.mark.slow
def test_async_workers_do_not_outlive_a_killed_trainer(tmp_path: Path) -> None:
    config = tmp_path / "train.yaml"
    budget = {"model": {"name": "a3c", "hidden_size": 16}, "env": {"scenes": "FloorPlan401"},
              "a3c": {"mode": "async", "workers": 2}, "episodes": 1_000_000, "checkpoint_every": 8,
              "log_every": 4, "progress": False}  # fmt: skip
    config.write_text(yaml.safe_dump(budget))
    run_dir = tmp_path / "run"
    trainer = subprocess.Popen([sys.executable, "-m", "mapless", "train", str(config), "--run-dir", str(run_dir)],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)  # fmt: skip
    _wait_for((run_dir / ckpt.CHECKPOINT_FILE).exists, trainer)
    workers = _children(trainer.pid)
    assert len(workers) >= 2
    trainer.kill()
    trainer.communicate(timeout=60)
    deadline = time.monotonic() + 60
    while any(_alive(pid) for pid in workers) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not any(_alive(pid) for pid in workers), "workers kept training after their trainer died"


def test_a_flipped_byte_in_a_checkpoint_is_an_error_never_a_silent_change(tmp_path: Path) -> None:
    from damage import one_byte_flips

    run = tmp_path / "run"
    train(tiny_config("a3c", "episodes=4"), run, library_factory=fixture_library)
    path = run / ckpt.CHECKPOINT_FILE
    original = _state(run)
    detected = 0
    for _ in one_byte_flips(path, 40, mask=0x5A):
        try:
            loaded = ckpt.load_file(path)
        except ckpt.CheckpointError as error:
            assert str(path) in str(error)
            detected += 1
            continue
        assert ckpt.digest(loaded) == ckpt.digest(original)  # a flip in the zip's padding changes nothing
    assert detected >= 30
    path.write_bytes(b"")
    with pytest.raises(ckpt.CheckpointError, match=r"cannot read checkpoint .+: \S"):
        ckpt.load_file(path)


def test_a_failed_checkpoint_write_says_what_happened_and_keeps_the_previous(tmp_path, monkeypatch) -> None:
    run = tmp_path / "run"
    train(tiny_config("a3c", "episodes=4"), run, library_factory=fixture_library)
    before = (run / ckpt.CHECKPOINT_FILE).read_bytes()

    def full_disk(obj, f, *args, **kwargs):
        Path(f).write_bytes(b"partial")
        raise RuntimeError("basic_ios::clear: iostream error")  # what torch.save says on a full disk

    monkeypatch.setattr(torch, "save", full_disk)
    with pytest.raises(
        ckpt.CheckpointError, match=r"the previous checkpoint\.pt is intact: make room, then resume"
    ):
        ckpt.atomic_save({"format": ckpt.FORMAT_VERSION}, run / ckpt.CHECKPOINT_FILE)
    assert (run / ckpt.CHECKPOINT_FILE).read_bytes() == before
    assert not list(run.glob("*.tmp"))


def _files(folder: Path) -> dict[Path, bytes]:
    return {p: p.read_bytes() for p in folder.rglob("*") if p.is_file()}


def test_a_new_run_refuses_a_folder_that_holds_a_run_or_other_files(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Issue 45, point 8: a second run into a finished run's folder overwrote its models and mixed its
    snapshots with the first run's, silently."""
    config = tmp_path / "train.yaml"
    config.write_text(yaml.safe_dump({"model": {"name": "a3c", "hidden_size": 16}, "episodes": 4}))
    run = tmp_path / "run"
    train(tiny_config("a3c", "episodes=4"), run, library_factory=fixture_library)
    before = _files(run)
    assert cli_main(["train", str(config), "--set", "seed=2", "--run-dir", str(run)]) == 2
    err = capsys.readouterr().err
    expected = (
        f"{run} already holds a finished run (checkpoint.pt, final_model.pt, checkpoints/); continue it "
        f"with `mapless train --resume {run}`"
    )
    assert "Traceback" not in err and expected in err
    assert _files(run) == before  # nothing written, not even config.yaml
    resumed, state = resume_config(run, ["episodes=8"])  # what the message says works
    assert train(resumed, run, resume=state, library_factory=fixture_library)["episodes"] == 8

    mine = tmp_path / "mine"  # a folder mapless did not make
    mine.mkdir()
    (mine / "notes.txt").write_text("keep me")
    assert cli_main(["train", str(config), "--run-dir", str(mine)]) == 2
    assert "is not empty and holds no run (it has notes.txt)" in capsys.readouterr().err
    assert _files(mine) == {mine / "notes.txt": b"keep me"}

    # A run that wrote no checkpoint (it failed or diverged first) starts over in its folder.
    failed = tmp_path / "failed"
    failed.mkdir()
    (failed / ckpt.CONFIG_FILE).write_text("model: {name: a3c}\n")
    (failed / ckpt.METRICS_FILE).write_text('{"episodes": 2, "frames": 9}\n')  # its records go
    assert train(tiny_config("a3c", "episodes=4"), failed, library_factory=fixture_library)["episodes"] == 4
    records = [json.loads(line) for line in (failed / ckpt.METRICS_FILE).read_text().splitlines()]
    assert [r["episodes"] for r in records] == [4]


def test_snapshots_follow_a_share_of_the_episode_budget(tmp_path: Path) -> None:
    # a3c.batch_size=4 episodes per update: a snapshot after each quarter of 16 episodes.
    config = tiny_config("a3c", "episodes=16", "snapshots=4", "checkpoint_every=1000")
    train(config, tmp_path, library_factory=fixture_library)
    assert [n for n, _ in ckpt.snapshots(tmp_path)] == [4, 8, 12, 16]


def test_snapshots_follow_the_clock_of_a_run_stopped_by_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A run stopped by max_seconds takes its snapshots from the clock, however large its frame
    budget: on a clock that advances 1 s per update, 8 s split in 4 give one every 2 updates."""
    from types import SimpleNamespace

    from mapless.train import loop

    now = [0.0]
    monkeypatch.setattr(loop, "time", SimpleNamespace(perf_counter=lambda: now[0]))
    count = loop.TrainingLoop._count

    def one_second_per_update(self, *args, **kwargs):
        now[0] += 1.0
        return count(self, *args, **kwargs)

    monkeypatch.setattr(loop.TrainingLoop, "_count", one_second_per_update)
    config = tiny_config(
        "a3c", "episodes=0", "frames=100000000", "max_seconds=8", "snapshots=4", "checkpoint_every=1000"
    )
    train(config, tmp_path, library_factory=fixture_library)
    # a3c.batch_size=4 episodes per update: after updates 2, 4, 6 and 8, then the final model.
    taken = [n for n, _ in ckpt.snapshots(tmp_path)]
    assert taken[:4] == [8, 16, 24, 32] and len(taken) <= 5


def test_a_negative_snapshot_count_is_refused() -> None:
    with pytest.raises(ConfigError, match="snapshots"):
        tiny_config("a3c", "snapshots=-1")
