"""Keep freed memory in the process: glibc's allocator settings for batched FE kernels.

The batched element kernels allocate and free tensors of tens to hundreds of MB at every Newton
iteration (per-Gauss-point gradients and element tangents of every member). glibc serves blocks
above its mmap threshold (at most 32 MB) with fresh ``mmap`` pages and returns them to the kernel
on ``free``, so each iteration pays the page faults of zeroing them again: measured on the restart
filter's reduced re-solves (20 members, resolution 1, 1 thread) as 1 min 13 s of system time in a
2 min 47 s run. With ``M_MMAP_MAX = 0`` (every block from the heap) and the largest trim threshold
(2 GB of free heap top before any is returned), freed blocks are reused: the same solve took 44.6 s instead of 82.8 s, system time
5.5 s. The price: the process keeps its peak memory until it exits (the working set of one
ensemble solve; the machine's memory is not otherwise shared with it).

:func:`keep_freed_memory` is called by every ``torchfra`` command (:func:`torchfra.cli.run.run`) and by
the test suite; importing ``torchfra`` does not change the host process (a notebook calls it itself
if it wants it). ``TORCHFRA_MALLOC=default`` in the environment leaves the allocator as it is. Elsewhere than Linux with glibc it does nothing.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import os
import sys

M_TRIM_THRESHOLD = -1  # glibc malloc.h
M_MMAP_MAX = -4
TRIM_THRESHOLD = 2**31 - 1  # bytes, the largest mallopt takes

state = {"tuned": False, "reason": "not attempted"}


def keep_freed_memory() -> dict:
    """Set glibc's ``M_MMAP_MAX = 0`` and ``M_TRIM_THRESHOLD`` huge (see the module docstring).
    Returns (and records in ``state``) whether it did, and why not."""
    if os.environ.get("TORCHFRA_MALLOC", "").lower() == "default":
        state.update(tuned=False, reason="TORCHFRA_MALLOC=default")
    elif not sys.platform.startswith("linux"):
        state.update(tuned=False, reason=f"not Linux ({sys.platform})")
    else:
        try:
            libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
            mallopt = libc.mallopt
        except (OSError, AttributeError):
            state.update(tuned=False, reason="no glibc mallopt")
        else:
            mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
            ok = mallopt(M_MMAP_MAX, 0) == 1 and mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD) == 1
            state.update(tuned=ok, reason="glibc mallopt" if ok else "mallopt refused")
    return dict(state)
