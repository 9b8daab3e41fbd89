"""glibc ``malloc`` settings that keep a training step's memory mapped between steps.

A CPU step allocates and frees hundreds of MB in blocks of a few MB (per-sample activations, hash-table gradients).
glibc serves blocks above its mmap threshold with fresh ``mmap`` calls and returns the top of its heap to the system
whenever more than its trim threshold is free there; both thresholds move with what the process last freed. Late
steps timed from a checkpoint kept asking the kernel for zeroed pages: up to 8000 page faults and 13 ms of system
time a step, about 15% of it (benchmarks/RESULTS.md, "Allocator"; a whole 10-minute run trained as many steps
either way). :func:`tune_malloc` fixes the thresholds: blocks up to 32 MB come from the heap, the heap keeps up
to 1 GB of free memory, and it grows 256 MB at a time. The process holds on to memory it has used once, which a
training run reuses every step anyway.

``ANISDF_MALLOC=default`` leaves glibc's own settings; other C libraries (macOS, musl) are left alone.
"""

from __future__ import annotations

import ctypes
import logging
import os
import platform

log = logging.getLogger("anisdf")

M_TRIM_THRESHOLD, M_TOP_PAD, M_MMAP_THRESHOLD = -1, -2, -3  # <malloc.h>
SETTINGS = {M_MMAP_THRESHOLD: 32 << 20, M_TRIM_THRESHOLD: 1 << 30, M_TOP_PAD: 256 << 20}
"""``mallopt`` parameter -> value. 32 MB is the largest mmap threshold glibc accepts on 64-bit."""

_applied = False


def tune_malloc() -> bool:
    """Apply :data:`SETTINGS` once per process (glibc only, unless ``ANISDF_MALLOC=default``); whether they apply."""
    global _applied
    if _applied:
        return True
    if os.environ.get("ANISDF_MALLOC", "") == "default" or platform.libc_ver()[0] != "glibc":
        return False
    try:
        mallopt = ctypes.CDLL("libc.so.6").mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    _applied = all(mallopt(param, value) == 1 for param, value in SETTINGS.items())
    log.debug("malloc thresholds fixed: %s", _applied)
    return _applied
