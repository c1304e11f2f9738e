"""A training process's runtime: torch threads and numerics, seeds per rank / worker / segment, and
the graceful stop on SIGINT or SIGTERM."""

from __future__ import annotations

import contextlib
import signal
from typing import Any

import numpy as np
import torch

from mapless.agent.allocator import keep_freed_memory
from mapless.agent.precision import keep_compiled_kernels
from mapless.train.config import TrainConfig


def configure_torch(threads: int) -> None:
    """Per-process settings of a trainer: ``threads`` (0 = torch's default), denormals
    flushed to zero, oneDNN's compiled kernels kept (:func:`keep_compiled_kernels`) and freed
    memory kept for the next update (:func:`keep_freed_memory`).

    Adam's second-moment estimate of weights that rarely receive gradient (the LSTM columns of
    mostly-zero ReLU features) decays into the subnormal range, where every multiply and square root
    takes the CPU's slow microcode path: a third of a SAVN optimizer step in profiles. Values below
    1.2e-38 are zero for all purposes here.
    """
    if threads:
        torch.set_num_threads(threads)
    torch.set_flush_denormal(True)
    keep_compiled_kernels()
    keep_freed_memory()


def seed_for(config: TrainConfig, *stream: int) -> int:
    """Independent seeds per rank / worker / resumed segment from one config seed."""
    return int(np.random.SeedSequence([config.seed, *stream]).generate_state(1)[0])


class GracefulStop:
    """First SIGINT or SIGTERM (what schedulers and ``timeout`` send): finish the current update,
    checkpoint and stop. A second one aborts at once."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self) -> None:
        self.requested = False
        self._previous: dict[int, Any] = {}

    def __enter__(self) -> GracefulStop:
        for signum in self.SIGNALS:
            # Outside the main thread (e.g. a test harness) there is no handler and no graceful stop.
            with contextlib.suppress(ValueError):
                self._previous[signum] = signal.signal(signum, self._handle)
        return self

    def _handle(self, signum: int, frame: Any) -> None:
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True
        name = signal.Signals(signum).name
        print(f"\nmapless: {name}: stopping after this update (again to abort)", flush=True)

    def __exit__(self, *exc: object) -> None:
        for signum, previous in self._previous.items():
            signal.signal(signum, previous)
