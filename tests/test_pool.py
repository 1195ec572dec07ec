"""The worker pool's split: every index of 0..n in exactly one part, one part per thread (or
``per_worker`` parts) whatever the machine's core count, small inputs in one call."""

import threading

import numpy as np
import pytest

from lpv_core.runtime import pool


@pytest.mark.parametrize("cores", [1, 2, 8])
@pytest.mark.parametrize("per_worker", [1, 8])
@pytest.mark.parametrize("n", [0, 1, 4095, 4096, 10_001])
def test_in_parts_covers_each_index_once(monkeypatch, cores, per_worker, n):
    monkeypatch.setattr(pool, "workers", lambda: cores)
    hits = np.zeros(n, np.int64)
    parts = []
    lock = threading.Lock()

    def run(sl):
        with lock:
            parts.append(sl)
        hits[sl] += 1

    pool.in_parts(run, n, per_worker)
    assert (hits == 1).all()
    if n >= 4096:
        assert len(parts) == min(n, cores * per_worker)
        sizes = [p.stop - p.start for p in parts]
        assert max(sizes) - min(sizes) <= 1  # balanced
    else:
        assert parts == [slice(0, n)]


def test_in_parts_reraises_a_parts_error():
    def run(sl):
        if sl.start > 0:
            raise RuntimeError("part failed")

    with pytest.raises(RuntimeError, match="part failed"):
        pool.in_parts(run, 100_000)
