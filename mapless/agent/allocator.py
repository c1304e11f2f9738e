"""Keep freed memory in the process, so that a training update does not pay the kernel for its
large activations again and again.

glibc's ``malloc`` serves every block above its mmap threshold (at most 32 MB by default) with a
fresh ``mmap`` and returns it on ``free``. An update allocates and frees the same large tensors every
time (MJOLNIR's object GCN holds ``[C, B, C + 300]`` activations of 30-40 MB per minibatch; a3c's
LSTM input gradient is of the same order), so each of them comes back as new zero pages, and every
page costs a fault on first touch: on a 2-core virtual machine that was a third of the GCN's
forward and backward. With the threshold raised and trimming deferred, freed blocks stay in the
heap and the next update reuses them: the same arithmetic on the same values (nothing changes but
where the bytes live), in about 0.7 of the time for the GCN (docs/results/speed.md).

The price is that the process keeps its peak heap until it exits, which a trainer does anyway
(its peak recurs every update). Only glibc has ``mallopt``; elsewhere this does nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import os

#: ``mallopt`` parameters (glibc's malloc.h).
_M_TRIM_THRESHOLD, _M_TOP_PAD, _M_MMAP_THRESHOLD = -1, -2, -3

#: Blocks below this come from the heap and return to it (1 GiB: every activation of an update).
MMAP_THRESHOLD = 1 << 30
#: Free heap at its top that may stay with the process before it is trimmed.
TRIM_THRESHOLD = (1 << 31) - 1
#: Extra heap asked for at each growth, so that a growing update grows the heap a few times only.
TOP_PAD = 64 << 20

#: Set ``MAPLESS_KEEP_FREED_MEMORY=0`` to leave the allocator as the C library configures it.
ENV_SWITCH = "MAPLESS_KEEP_FREED_MEMORY"


@functools.cache
def keep_freed_memory() -> bool:
    """Configure glibc's allocator as the module docstring says, once per process; False where it
    could not (another C library, or the switch off)."""
    if os.environ.get(ENV_SWITCH, "1") == "0":
        return False
    name = ctypes.util.find_library("c")
    if name is None:
        return False
    try:
        libc = ctypes.CDLL(name)
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    settings = (
        (_M_MMAP_THRESHOLD, MMAP_THRESHOLD),
        (_M_TRIM_THRESHOLD, TRIM_THRESHOLD),
        (_M_TOP_PAD, TOP_PAD),
    )
    return all(mallopt(parameter, value) == 1 for parameter, value in settings)
