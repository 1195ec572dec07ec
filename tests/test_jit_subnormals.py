"""jit.flush_subnormals: inside the block this thread flushes subnormal floats to zero (the
transport sweep's light fading behind walls, 3x faster), after it the thread's IEEE mode is
back, even when the block raises; and the octant sweep with light fading into subnormals
still gives the numpy reference's values."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("numba")

from test_jit_fused import _passing  # tests/ is on sys.path under pytest
from test_jit_launch import _vpls
from test_jit_octants import _assert_same, _reference

from lpv_core.kernels import sweep as octants
from lpv_core.runtime import jit

pytestmark = pytest.mark.skipif(not (jit.enabled() and jit.X86),
                                reason="FTZ/DAZ is x86's MXCSR; needs the kernels")

SUBNORMAL = np.float32(1e-39)  # below float32's smallest normal number, 1.18e-38


def _product() -> np.float32:
    """A subnormal times one, as this thread computes it."""
    return np.multiply(np.array([SUBNORMAL]), np.float32(1.0))[0]


def test_flushed_inside_restored_after():
    assert _product() == SUBNORMAL  # IEEE: kept
    with jit.flush_subnormals():
        assert _product() == 0.0
        with jit.flush_subnormals():  # nested: still flushed, and the outer mode comes back
            assert _product() == 0.0
        assert _product() == 0.0
    assert _product() == SUBNORMAL


def test_restored_when_the_block_raises():
    with pytest.raises(RuntimeError), jit.flush_subnormals():
        raise RuntimeError("inside")
    assert _product() == SUBNORMAL


def test_nothing_flushed_with_the_kernels_off():
    with jit.disabled(), jit.flush_subnormals():
        assert _product() == SUBNORMAL


def test_octant_sweep_through_nearly_opaque_walls():
    """Transmittances of 1e-25 to 1e-15: after a cell or two the light is subnormal, flushed in
    the sweep, kept by the numpy reference; the two agree to 1e-5 of the largest value, and
    nothing is NaN, Inf or negative in band 0."""
    r = 9
    rng = np.random.default_rng(3)
    injected = _vpls(r, seed=5)
    passing = _passing(r, seed=6)
    visibility = (10.0 ** rng.uniform(-25, -15, (6, r, r, r))).astype(np.float32)
    got = octants.launch_sweep_fold(injected, visibility, passing, True, True)
    want = _reference(injected, visibility, passing, True, True)
    assert np.isfinite(got[0]).all() and np.isfinite(got[1]).all()
    assert np.count_nonzero((want[0] != 0) & (np.abs(want[0]) < np.finfo(np.float32).tiny))
    _assert_same(got, want, True)
    assert _product() == SUBNORMAL  # the pool's threads' mode did not leak into this one
