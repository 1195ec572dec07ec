"""The compiled lookup (kernels.lookup: irradiance, gap_corrected) gives what the numpy
code gives: 9-coefficient irradiance with and without visibility, points inside, on the
border of and outside the grid, and the gap correction of sample points."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("numba")

from lpv_core import lookup
from lpv_core.grid import Grid
from lpv_core.runtime import jit

pytestmark = pytest.mark.skipif(not jit.enabled(), reason="LPV_JIT=0: the kernels are off")


def _case(r: int, m: int, seed: int):
    rng = np.random.default_rng(seed)
    grid = Grid((-1.3, 0.2, 5.0), 0.37, r)
    values = rng.normal(size=(r, r, r, 3, 9)).astype(np.float32)
    values[..., 0] = np.abs(values[..., 0]) + 1.0
    span = r * grid.cell_size
    pos = grid.origin_array + rng.uniform(-0.2 * span, 1.2 * span, (m, 3))  # some outside
    pos[: m // 8] = grid.origin_array + (rng.integers(0, r + 1, (m // 8, 3)) * grid.cell_size)
    nrm = rng.normal(size=(m, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    vis = rng.uniform(0.0, 1.0, (6, r, r, r)).astype(np.float32)
    vis[rng.uniform(size=vis.shape) < 0.2] = 0.0  # opaque faces: hidden corners
    vis[:, 0, 0, 0] = 0.0  # a boxed-in cell: every corner hidden, plain weights kept
    gaps = rng.uniform(0.0, 0.6, (6, r, r, r)).astype(np.float32)
    gaps[rng.uniform(size=gaps.shape) < 0.5] = 0.0
    return grid, values, pos, nrm, vis, gaps


@pytest.mark.parametrize("occluded", [True, False])
@pytest.mark.parametrize("r", [1, 2, 7])
def test_compiled_irradiance_is_the_numpy_one(r, occluded):
    grid, values, pos, nrm, vis, _ = _case(r, 9000, seed=r + 10 * occluded)
    kw = {"angular": "dom", "visibility": vis if occluded else None}
    got = lookup.irradiance(grid, values, pos, nrm, **kw)
    with jit.disabled():
        want = lookup.irradiance(grid, values, pos, nrm, **kw)
    assert got.shape == want.shape == (pos.shape[0], 3) and got.dtype == np.float64
    assert np.count_nonzero(want) > 100 and (got >= 0).all()
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12 * want.max())


@pytest.mark.parametrize("r", [1, 3, 8])
def test_compiled_gap_correction_is_the_numpy_one(r):
    grid, _, pos, nrm, _, gaps = _case(r, 9000, seed=r)
    got = lookup.sample_points(grid, pos, nrm, gaps)
    with jit.disabled():
        want = lookup.sample_points(grid, pos, nrm, gaps)
    assert not np.array_equal(want, pos + nrm * (lookup.OFFSET_CELLS * grid.cell_size))
    np.testing.assert_array_equal(got, want)
