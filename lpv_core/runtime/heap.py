"""Keep freed memory in the process for reuse: an update allocates and frees the same
multi-megabyte arrays each time (the launch and sweep light, the RSM's VPLs), and memory the
C allocator hands back to the OS comes back as fresh pages, each zero-filled on first touch.

glibc serves a block above its mmap threshold with its own mapping and unmaps it on free, and
trims the heap's free top above its trim threshold: every update then page-faults its big
arrays in again (docs/decisions.md has the figures); both thresholds are raised here.
The engine runs in its own process (the batch CLI, the live worker), so the setting touches
nothing of Blender's; elsewhere than glibc it does nothing. The cost: the process keeps its
peak heap, which the next update needs again anyway.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import sys

_M_TRIM_THRESHOLD = -1  # glibc malloc.h mallopt parameters
_M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD = 32 * 2**20  # glibc's largest (DEFAULT_MMAP_THRESHOLD_MAX on 64-bit)
TRIM_THRESHOLD = 1 * 2**30  # free heap top kept before any is returned
_DONE: list = []


def retain_freed_memory() -> bool:
    """Raise glibc's mmap and trim thresholds once per process; False where not glibc."""
    if _DONE:
        return _DONE[0]
    ok = False
    if sys.platform.startswith("linux"):
        try:
            libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
            ok = bool(libc.mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(
                libc.mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD))
        except (OSError, AttributeError):  # musl or another libc: no mallopt
            ok = False
    _DONE.append(ok)
    return ok
