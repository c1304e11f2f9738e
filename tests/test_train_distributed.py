"""Two local gloo ranks (as torchrun would start them) keep identical parameters while training on
different episodes, and only rank 0 writes the run folder."""

from __future__ import annotations

import os
import socket
from pathlib import Path

import pytest
import torch
import torch.multiprocessing as mp
from train_fixtures import fixture_library, tiny_config

from mapless import checkpoint as ckpt
from mapless.errors import TrainingDiverged
from mapless.train import distributed as dist
from mapless.train.batched import BatchedTrainer

pytestmark = pytest.mark.slow

WORLD = 2


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _as_torchrun_would(rank: int, port: int) -> None:
    os.environ.update(
        MASTER_ADDR="127.0.0.1",
        MASTER_PORT=str(port),
        RANK=str(rank),
        LOCAL_RANK=str(rank),
        WORLD_SIZE=str(WORLD),
    )


def _rank(rank: int, port: int, out: str) -> None:
    _as_torchrun_would(rank, port)
    config = tiny_config("savn", "a3c.batch_size=2", f"episodes={3 * 2 * WORLD}", "checkpoint_every=4")
    ctx = dist.init_distributed(config.device)
    try:
        trainer = BatchedTrainer(config, Path(out) / "run", fixture_library, ctx)
        summary = trainer.run()
        torch.save(
            {
                "model": trainer.model.state_dict(),
                "updates": summary["updates"],
                "episodes": summary["episodes"],
                "numpy": str(trainer.rng.bit_generator.state),
            },
            Path(out) / f"rank{rank}.pt",
        )
    finally:
        dist.shutdown(ctx)


def test_two_ranks_stay_identical(tmp_path: Path) -> None:
    mp.spawn(_rank, args=(_free_port(), str(tmp_path)), nprocs=WORLD, join=True)
    r0, r1 = (torch.load(tmp_path / f"rank{r}.pt", weights_only=True) for r in range(WORLD))
    assert r0["updates"] == r1["updates"] == 3
    assert r0["episodes"] == r1["episodes"] == 12  # global count: both ranks' episodes
    assert r0["numpy"] != r1["numpy"], "ranks should sample different episodes"
    for key, value in r0["model"].items():
        assert torch.equal(value, r1["model"][key]), key
    # Rank 0 alone wrote the run; its checkpoint holds both ranks' RNG states for an exact resume.
    state = ckpt.load_file(tmp_path / "run" / ckpt.CHECKPOINT_FILE)
    assert len(state["rng"]) == WORLD and state["counters"]["world_size"] == WORLD
    for key, value in state["model"].items():
        assert torch.equal(value, r0["model"][key])


def _reduce_rank(rank: int, port: int, out: str) -> None:
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), RANK=str(rank), WORLD_SIZE=str(WORLD))
    ctx = dist.init_distributed("cpu")
    try:
        params = [torch.zeros(3, requires_grad=True) for _ in range(3)]
        params[0].grad = torch.full((3,), float(rank + 1))  # every rank: 1 and 2
        if rank == 1:
            params[1].grad = torch.full((3,), 4.0)  # rank 1 only; no rank has one for params[2]
        dist.all_reduce_gradients(params, ctx)
        torch.save([p.grad for p in params], Path(out) / f"grads{rank}.pt")
    finally:
        dist.shutdown(ctx)


def test_gradients_missing_on_every_rank_stay_missing(tmp_path: Path) -> None:
    mp.spawn(_reduce_rank, args=(_free_port(), str(tmp_path)), nprocs=WORLD, join=True)
    for rank in range(WORLD):
        mean, partial, missing = torch.load(tmp_path / f"grads{rank}.pt", weights_only=True)
        assert torch.equal(mean, torch.full((3,), 1.5))
        assert torch.equal(partial, torch.full((3,), 2.0))  # a missing gradient counts as zeros
        assert missing is None  # so that the optimizer skips it, as in one process


def _diverging_rank(rank: int, port: int, out: str) -> None:
    _as_torchrun_would(rank, port)
    # Only rank 1's episodes diverge (a finite but absurd penalty: the value loss overflows, the
    # gradient becomes NaN): the all-reduced gradient carries its NaN to rank 0.
    config = tiny_config(
        "a3c", "a3c.batch_size=2", "episodes=400", *(["env.reward.step_penalty=-1e38"] if rank else [])
    )
    ctx = dist.init_distributed(config.device)
    try:
        BatchedTrainer(config, Path(out) / "run", fixture_library, ctx).run()
        outcome = "finished"
    except TrainingDiverged as error:
        outcome = str(error)
    finally:
        dist.shutdown(ctx)
    Path(out, f"rank{rank}.txt").write_text(outcome)


def test_every_rank_stops_at_a_divergence_on_one_of_them(tmp_path: Path) -> None:
    """The divergence rule of every trainer (tests/test_divergence.py), on the all-reduced gradient:
    no rank steps on, none waits for the others at a collective (issue 45, point 2)."""
    mp.spawn(_diverging_rank, args=(_free_port(), str(tmp_path)), nprocs=WORLD, join=True)
    outcomes = [(tmp_path / f"rank{r}.txt").read_text() for r in range(WORLD)]
    assert all("at update 1 " in o and "before the run wrote its first checkpoint" in o for o in outcomes)
