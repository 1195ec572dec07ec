"""The core's worker threads: one pool shared by every stage whose compiled kernels or numpy
loops release the GIL and write disjoint parts (the octants of a propagation step, halves of a
lookup, RSM rows, injection slabs, geometry-volume chunks)."""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

_POOL: list = []  # [ThreadPoolExecutor] once created


def workers() -> int:
    """The pool's threads: one per core, at most 8 (the octants of a propagation step)."""
    return max(1, min(8, os.cpu_count() or 1))


def executor() -> ThreadPoolExecutor:
    """The shared pool (created on first use)."""
    if not _POOL:
        _POOL.append(ThreadPoolExecutor(workers(), thread_name_prefix="lpv-pool"))
    return _POOL[0]


def in_halves(run, n: int, smallest: int = 4096) -> None:
    """run(slice) over 0..n: below ``smallest`` in one call here, else in two halves on the
    pool's threads (for kernels that release the GIL and write disjoint parts); iterating
    re-raises a half's exception here."""
    if n < smallest:
        run(slice(0, n))
        return
    for _ in executor().map(run, (slice(0, n // 2), slice(n // 2, n))):
        pass
