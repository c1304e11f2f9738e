"""Data parallelism over processes and machines with ``torch.distributed`` (launched by ``torchrun``).

Every rank runs the batched trainer on its own episodes; before each optimizer step the gradients are
averaged over ranks with one all-reduce of a flat buffer, so every rank applies the same update to
the same parameters and they stay identical (rank 0's initial parameters are broadcast once). gloo
on the CPU; on GPUs nccl for the gradients and gloo for the CPU-side statistics. Only rank 0 writes
logs and checkpoints. See docs/guide/training.md.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

import torch
import torch.distributed as dist
from torch import Tensor

from mapless.errors import MaplessError


@dataclass(frozen=True)
class DistContext:
    rank: int = 0
    world_size: int = 1
    local_rank: int = 0

    @property
    def enabled(self) -> bool:
        return self.world_size > 1

    @property
    def is_main(self) -> bool:
        return self.rank == 0


def launched_by_torchrun() -> bool:
    return int(os.environ.get("WORLD_SIZE", "1")) > 1


def rank_device(device: str, local_rank: int = 0) -> torch.device:
    """The torch device of a rank: ``cuda`` means GPU ``LOCAL_RANK`` (one GPU per process),
    ``cuda:N`` that GPU, anything else the CPU."""
    if device == "cuda":
        return torch.device("cuda", local_rank)
    return torch.device(device) if device.startswith("cuda") else torch.device("cpu")


def init_distributed(device: str) -> DistContext:
    """Join the process group described by torchrun's environment (``RANK``, ``WORLD_SIZE``,
    ``MASTER_ADDR``...); a single process without those variables gets the trivial context.

    On GPUs the group has two backends: nccl for the gradients and parameters (on the GPU) and
    gloo for what stays on the CPU (the trainer's episode statistics, RNG states and other objects),
    which nccl cannot carry. nccl also needs every rank on its own GPU before the first collective.
    """
    if not launched_by_torchrun():
        return DistContext()
    local_rank = int(os.environ.get("LOCAL_RANK", "0"))
    if not dist.is_initialized():
        if device.startswith("cuda"):
            if not torch.cuda.is_available():
                raise MaplessError("device=cuda was requested under torchrun but no GPU is visible")
            gpu = rank_device(device, local_rank)
            torch.cuda.set_device(gpu)
            dist.init_process_group("cpu:gloo,cuda:nccl", device_id=gpu)
        else:
            dist.init_process_group("gloo")
    return DistContext(rank=dist.get_rank(), world_size=dist.get_world_size(), local_rank=local_rank)


def broadcast_parameters(params: list[Tensor], ctx: DistContext) -> None:
    """Copy rank 0's parameters to every rank."""
    if not ctx.enabled:
        return
    with torch.no_grad():
        for p in params:
            dist.broadcast(p.data, src=0)


def all_reduce_gradients(params: list[Tensor], ctx: DistContext) -> None:
    """Average ``.grad`` over ranks with one flat all-reduce. A gradient missing on some ranks counts
    as zeros there; one missing on every rank stays None, so that the optimizer skips the parameter
    as it does in a single process."""
    if not ctx.enabled:
        return
    grads = [p.grad if p.grad is not None else torch.zeros_like(p) for p in params]
    present = [torch.ones(1) if p.grad is not None else torch.zeros(1) for p in params]
    flat = torch.cat([g.reshape(-1) for g in grads] + [f.to(grads[0]) for f in present])
    dist.all_reduce(flat, op=dist.ReduceOp.SUM)
    anywhere = flat[-len(params) :] > 0
    flat /= ctx.world_size
    offset = 0
    for p, found in zip(params, anywhere.tolist(), strict=True):
        n = p.numel()
        p.grad = flat[offset : offset + n].view_as(p) if found else None  # views of one fresh buffer
        offset += n


def all_reduce_sum(values: Tensor, ctx: DistContext) -> Tensor:
    if ctx.enabled:
        dist.all_reduce(values, op=dist.ReduceOp.SUM)
    return values


def all_gather_rows(values: Tensor, ctx: DistContext) -> Tensor:
    """``[k, B]`` per rank -> ``[k, world * B]`` (rank-major along the batch axis)."""
    if not ctx.enabled:
        return values
    parts = [torch.empty_like(values) for _ in range(ctx.world_size)]
    dist.all_gather(parts, values.contiguous())
    return torch.cat(parts, dim=1)


def gather_objects(obj: Any, ctx: DistContext) -> list[Any]:
    """Every rank's ``obj`` (small picklable values such as RNG states), on every rank."""
    if not ctx.enabled:
        return [obj]
    out: list[Any] = [None] * ctx.world_size
    dist.all_gather_object(out, obj)
    return out


def broadcast_object(obj: Any, ctx: DistContext) -> Any:
    if not ctx.enabled:
        return obj
    box = [obj]
    dist.broadcast_object_list(box, src=0)
    return box[0]


def barrier(ctx: DistContext) -> None:
    if ctx.enabled:
        dist.barrier()


def shutdown(ctx: DistContext) -> None:
    if ctx.enabled and dist.is_initialized():
        dist.destroy_process_group()
