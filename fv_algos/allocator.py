"""glibc malloc settings for processes that allocate and free the same large arrays every cycle.

By default glibc serves every block above a *dynamic* mmap threshold (at most 32 MiB) with its
own mmap and returns it to the kernel when freed, so a loop that allocates the same large
tensors each step pays a page fault for every page again, each step (measured on the slip
ConvLSTM's training step: 7.8 million minor faults and 14 s of system time in 40 steps, 16 % of
the wall time). The dynamic threshold also moves as block sizes vary, which lets the heap grow
by fragmentation over hours. :func:`steady_malloc` fixes both thresholds, so freed memory is
kept and reused: resident memory settles at the working set's peak and stays there.
Process entry points call it: the `fv` command (so every node, training run and benchmark),
`python -m fv_algos.slip.train` (what torchrun starts) and the spawned processes of
:func:`fv_algos.trial_eval.map_folds` (cross-validation folds).
"""
from __future__ import annotations

import ctypes
import ctypes.util
import functools

M_TRIM_THRESHOLD = -1  # mallopt parameter numbers from glibc's <malloc.h>
M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD_BYTES = 1 << 30  # blocks below 1 GiB come from the heap, and are reused
TRIM_THRESHOLD_BYTES = 1 << 30  # give the heap top back only when 1 GiB of it is free


@functools.cache
def steady_malloc() -> bool:
    """Fix glibc's mmap and trim thresholds for this process (idempotent). Returns False, and
    changes nothing, where the C library is not glibc (musl, macOS, Windows)."""
    name = ctypes.util.find_library("c")
    try:
        mallopt = ctypes.CDLL(name).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)) and bool(mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES))
