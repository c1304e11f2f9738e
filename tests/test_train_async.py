"""The async (Hogwild) trainer: spawned workers update a shared model; a dead worker stops the run."""

from __future__ import annotations

import os
import signal
import threading
import time
from pathlib import Path

import pytest
import torch
from train_fixtures import fixture_library, tiny_config

from mapless import checkpoint as ckpt
from mapless.train.builders import new_model
from mapless.train.hogwild import AsyncTrainer, WorkerError
from mapless.train.runtime import seed_for


@pytest.mark.slow
def test_async_training_updates_the_shared_model(tmp_path: Path) -> None:
    config = tiny_config("a3c", "a3c.mode=async", "a3c.workers=2", "episodes=12", "checkpoint_every=6")
    summary = AsyncTrainer(config, tmp_path, fixture_library).run()
    assert summary["episodes"] == 12 and summary["updates"] == 12
    state = ckpt.load_file(tmp_path / ckpt.CHECKPOINT_FILE)
    assert state["counters"]["episodes"] == 12
    # Every worker step went through the shared AMSGrad state: its step counters moved.
    steps = [slot["step"] for slot in state["optimizer"]["state"].values()]
    assert all(s >= 1 for s in steps) and max(steps) >= 12
    torch.manual_seed(seed_for(config, 0))  # the main process builds the initial model like this
    initial = new_model(config).state_dict()
    assert any(not torch.equal(initial[k], v) for k, v in state["model"].items())
    assert [n for n, _ in ckpt.snapshots(tmp_path)] == [6, 12]


@pytest.mark.slow
def test_a_resumed_async_run_starts_from_the_checkpoints_model_optimizer_and_counters(tmp_path: Path) -> None:
    config = tiny_config("a3c", "a3c.mode=async", "a3c.workers=1", "episodes=6", "checkpoint_every=6")
    AsyncTrainer(config, tmp_path, fixture_library).run()
    saved = ckpt.load_file(tmp_path / ckpt.CHECKPOINT_FILE)
    trainer = AsyncTrainer(config, None, fixture_library)
    summary = trainer.run(saved)  # the budget is spent already: nothing is trained
    assert summary["episodes"] == 6
    assert trainer.counters == {k: saved["counters"][k] for k in ("episodes", "frames", "updates")}
    model = trainer.model.state_dict()
    assert model.keys() == saved["model"].keys()
    assert all(torch.equal(model[k], v) for k, v in saved["model"].items())
    optimizer = trainer.optimizer.state_dict()["state"]
    assert optimizer.keys() == saved["optimizer"]["state"].keys()
    for key, slot in saved["optimizer"]["state"].items():
        assert all(
            torch.equal(torch.as_tensor(optimizer[key][k]), torch.as_tensor(v)) for k, v in slot.items()
        )


@pytest.mark.slow
def test_killed_worker_is_reported_and_the_run_stops(tmp_path: Path) -> None:
    config = tiny_config("a3c", "a3c.mode=async", "a3c.workers=2", "episodes=1000000000")
    trainer = AsyncTrainer(config, tmp_path, fixture_library)
    outcome: dict[str, BaseException] = {}

    def run() -> None:
        try:
            trainer.run()
        except BaseException as error:
            outcome["error"] = error

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 120
    while trainer.counters["episodes"] < 4 and time.monotonic() < deadline:
        time.sleep(0.1)
    assert trainer.counters["episodes"] >= 4, "workers never reported an episode"
    victim = trainer.workers[1]
    others = [p for p in trainer.workers if p is not victim]
    os.kill(victim.pid, signal.SIGKILL)
    thread.join(timeout=60)
    assert not thread.is_alive(), "the trainer hung after a worker died"
    error = outcome.get("error")
    assert isinstance(error, WorkerError)
    assert "worker 1" in str(error) and "SIGKILL" in str(error)
    assert all(not p.is_alive() for p in others), "surviving workers were not stopped"


def broken_library():
    """A library factory that fails inside the spawned workers (module-level: picklable)."""
    raise RuntimeError("the scene files are unreadable")


@pytest.mark.slow
def test_a_failing_worker_reports_its_traceback(tmp_path: Path) -> None:
    config = tiny_config("a3c", "a3c.mode=async", "a3c.workers=2", "episodes=1000000000")
    with pytest.raises(WorkerError, match="RuntimeError: the scene files are unreadable"):
        AsyncTrainer(config, tmp_path, broken_library).run()


def test_async_refuses_cuda(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)  # as on a GPU machine
    with pytest.raises(Exception, match="async"):
        AsyncTrainer(tiny_config("a3c", "a3c.mode=async", "device=cuda"), None)


@pytest.mark.parametrize(
    ("device", "message"), [("cuda", "sees no CUDA device"), ("cudaXYZ", "cuda\\[:N\\]")]
)
def test_a_device_this_build_cannot_use_is_a_config_error(
    device: str, message: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    from mapless.config import ConfigError

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)  # as on a CPU build
    with pytest.raises(ConfigError, match=message):
        tiny_config("a3c", f"device={device}")
