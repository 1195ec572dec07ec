"""The compiled transport sweep (sweep._sweep_kernel, lpv_core/jit.py): the same light as the
numpy sweep over hyperplanes (the reference, run under jit.disabled()), with and without
transmittances and the shell, and through propagate with the launch."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("numba")

from test_sweep import _case  # tests/ is on sys.path under pytest

from lpv_core import propagation
from lpv_core.propagation import sweep
from lpv_core.runtime import jit

pytestmark = pytest.mark.skipif(not jit.enabled(), reason="LPV_JIT=0: the kernels are off")


def _source(r: int, rng, sparse: bool) -> np.ndarray:
    """Light in the padded flat layout (64, 3, (R+2)^3): random in every interior cell, or
    (``sparse``) in a few cells of the far half, so that the directions along +x start with
    dark slabs (the kernel skips them); the far x face of the shell holds light too (the
    launch's arrivals that left the grid)."""
    p = r + 2
    grid = np.zeros((64, 3, p, p, p), np.float32)
    if sparse:
        for _ in range(4):
            c = rng.integers(r // 2, r, 3) + 1
            grid[:, :, c[0], c[1], c[2]] = rng.uniform(0.5, 2.0, (64, 3))
    else:
        grid[:, :, 1:-1, 1:-1, 1:-1] = rng.random((64, 3, r, r, r))
    grid[:, :, -1] = rng.random((64, 3, p, p))  # one face of the shell (the far x side)
    return grid.reshape(64, 3, -1)


def _visibility(r: int, rng) -> list:
    """Per propagation.OFFSETS entry a transmittance in [0, 1], a tenth of it exactly 0."""
    out = []
    for _ in propagation.OFFSETS:
        v = rng.random((r, r, r)).astype(np.float32)
        v[rng.random((r, r, r)) < 0.1] = 0.0
        out.append(v)
    return out


@pytest.mark.parametrize("r", [5, 16])
@pytest.mark.parametrize("shell", [True, False])
@pytest.mark.parametrize("occluded", [True, False])
@pytest.mark.parametrize("sparse", [False, True])
def test_the_compiled_sweep_is_the_numpy_sweep(r, shell, occluded, sparse):
    """Same A (interior and shell) to float32 summation order, 1e-5 of the largest value."""
    rng = np.random.default_rng(r * 7 + shell * 3 + occluded * 2 + sparse)
    source = _source(r, rng, sparse)
    vis = _visibility(r, rng) if occluded else None
    got = sweep.solve(source, r, vis, shell)
    with jit.disabled():
        want = sweep.solve(source, r, vis, shell)
    assert got.shape == want.shape and got.dtype == np.float32
    scale = np.abs(want).max()
    assert scale > 0
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-5 * scale)
    if not shell:  # light leaving the grid (and the source's shell) is dropped
        p = r + 2
        edge = got.reshape(64, 3, p, p, p).copy()
        edge[:, :, 1:-1, 1:-1, 1:-1] = 0.0
        assert not edge.any()


@pytest.mark.parametrize("r", [1, 3])
@pytest.mark.parametrize("shell", [True, False])
def test_the_compiled_sweep_on_tiny_grids(r, shell):
    """One and three cells across (the slab-edge ranges and the shell slabs at their
    smallest), lit everywhere, and lit only in the shell's far x face (the first lit slab is
    then the last one along +x, the first one along -x)."""
    rng = np.random.default_rng(r + 10 * shell)
    vis = _visibility(r, rng)
    face = np.zeros((64, 3, r + 2, r + 2, r + 2), np.float32)
    face[:, :, -1] = rng.random((64, 3, r + 2, r + 2))
    for source in (_source(r, rng, sparse=False), face.reshape(64, 3, -1)):
        got = sweep.solve(source, r, vis, shell)
        with jit.disabled():
            want = sweep.solve(source, r, vis, shell)
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-5 * np.abs(want).max())


def test_the_compiled_sweep_follows_the_visibility_list_it_is_given():
    """The stacked transmittances are cached by the list's identity: a second list on the
    same grid is read afresh (an opaque one lets nothing past the source cells)."""
    r = 6
    rng = np.random.default_rng(3)
    source = _source(r, rng, sparse=False)
    first = sweep.solve(source, r, _visibility(r, rng), True)
    opaque = [np.zeros((r, r, r), np.float32) for _ in propagation.OFFSETS]
    second = sweep.solve(source, r, opaque, True)
    with jit.disabled():
        want = sweep.solve(source, r, opaque, True)
    np.testing.assert_allclose(second, want, rtol=0, atol=1e-6 * np.abs(want).max())
    assert not np.allclose(first, second)


def test_propagate_with_the_launch_is_the_same_compiled_and_in_numpy():
    """propagate(angular="dom", sweep=True, launch=True) on an injected grid with an opaque
    wall: grid and outflow agree between the kernel and the numpy sweep."""
    inj, vis = _case(8, seed=11)  # test_sweep's random lit cells and opaque wall
    kw = {"visibility": vis, "angular": "dom", "sweep": True, "launch": True,
          "occlude_first_step": True, "capture_outflow": True}
    got = propagation.propagate(inj, 0, **kw)
    with jit.disabled():
        want = propagation.propagate(inj, 0, **kw)
    assert got.swept and want.swept
    np.testing.assert_allclose(got.values, want.values, rtol=0,
                               atol=1e-5 * np.abs(want.values).max())
    np.testing.assert_allclose(got.outflow, want.outflow, rtol=0,
                               atol=1e-5 * np.abs(want.outflow).max())
