"""The core's worker threads: one pool shared by every stage whose compiled kernels or numpy
loops release the GIL and write disjoint parts (the octants of a propagation step, parts of a
lookup, RSM rows, injection slabs, geometry-volume chunks)."""

from __future__ import annotations

import itertools
import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np

_POOL: list = []  # [ThreadPoolExecutor] once created


def workers() -> int:
    """The pool's threads: one per core, at most 8 (the octants of a propagation step)."""
    return max(1, min(8, os.cpu_count() or 1))


def executor() -> ThreadPoolExecutor:
    """The shared pool (created on first use)."""
    if not _POOL:
        _POOL.append(ThreadPoolExecutor(workers(), thread_name_prefix="lpv-pool"))
    return _POOL[0]


def in_parts(run, n: int, per_worker: int = 1, smallest: int = 4096) -> None:
    """run(slice) over 0..n: below ``smallest`` in one call here, else in ``per_worker``
    contiguous parts per pool thread (for kernels that release the GIL and write disjoint
    parts; more than one where some rows cost many times others, as soft shadows' do);
    iterating re-raises a part's exception here."""
    if n < smallest:
        run(slice(0, n))
        return
    edges = np.linspace(0, n, max(1, per_worker) * workers() + 1).astype(np.int64)
    for _ in executor().map(run, [slice(a, b) for a, b in itertools.pairwise(edges)
                                  if b > a]):
        pass
