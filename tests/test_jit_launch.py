"""Compiled launch (lpv_core/kernels/ordinates.py, _launch_kernel and _unfold_kernel): the same
first-step arrivals as the numpy code, which stays the reference (jit.disabled())."""

import numpy as np
import pytest

pytest.importorskip("numba")

from lpv_core import grid, injection
from lpv_core.propagation import emission, ordinates, quadrature
from lpv_core.runtime import jit


def _vpls(r: int, seed: int, count: int = 200):
    """An injected grid of random VPLs: half with axis-aligned normals (a room's walls), half
    tilted; a quarter send no blue (a lit cell may hold a colour with band 0 = 0); some share
    cells (mean cosines below 1/2 too)."""
    rng = np.random.default_rng(seed)
    g = grid.Grid((0.0, 0.0, 0.0), 1.0, r)
    positions = rng.uniform(0.5, r - 0.5, (count, 3))
    normals = rng.normal(size=(count, 3))
    axis = rng.integers(0, 3, count // 2)
    normals[: count // 2] = 0.0
    normals[np.arange(count // 2), axis] = rng.choice([-1.0, 1.0], count // 2)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    flux = rng.uniform(0.1, 2.0, (count, 3))
    flux[rng.random(count) < 0.25, 2] = 0.0
    return injection.inject(g, positions, normals, flux)


def _visibility(r: int, seed: int):
    """Random face transmittances with an opaque wall across the middle of x."""
    vis = np.random.default_rng(seed).uniform(0.2, 1.0, (6, r, r, r)).astype(np.float32)
    vis[:, r // 2] = 0.0
    return vis


def _against_own_octant(injected: np.ndarray) -> int:
    """How many (direction, lit cell) pairs land outside their direction's octant offsets (the
    numpy code's np.add.at branch): tilted emitters must make some."""
    dirs = ordinates.tables()[0]
    geometry = injected.sum(axis=3).reshape(-1, 4)
    _, _, m = emission.moments(geometry[geometry[:, 0] > 0])
    cos = dirs @ m.T
    side = dirs[:, None] - cos[..., None] * m[None]
    sin = np.linalg.norm(side, axis=-1)
    scale = np.where(cos > 0, 0.5 / np.maximum(np.maximum(cos, sin), 1e-6), 0.0)
    move = np.clip(dirs[:, None] + scale[..., None] * side, -1, 1)
    base = np.minimum(np.floor(move), 0)
    own = np.minimum(np.sign(dirs), 0)[:, None]
    return int(np.sum(np.any(base != own, axis=-1)))


def _both(injected, offvis):
    got = ordinates.launch(injected, offvis)
    with jit.disabled():
        want = ordinates.launch(injected, offvis)
    return got, want


@pytest.mark.parametrize("r", [6, 16])
@pytest.mark.parametrize("occluded", [False, True])
def test_compiled_launch_is_the_numpy_launch(r, occluded):
    assert jit.enabled()
    injected = _vpls(r, seed=r + occluded)
    assert _against_own_octant(injected) > 0
    offvis = quadrature.offset_visibilities(_visibility(r, seed=r)) if occluded else None
    got, want = _both(injected, offvis)
    assert got.shape == want.shape == (ordinates.DIRECTIONS, 3, (r + 2) ** 3)
    assert got.dtype == want.dtype == np.float32
    scale = np.abs(want).max()
    assert scale > 0
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-5 * scale)
    # the flux sent out (what stays plus what the shell holds) is the same too
    assert got.sum(dtype=np.float64) == pytest.approx(want.sum(dtype=np.float64), rel=1e-5)


def test_compiled_launch_of_a_grid_with_no_lit_cell_is_zero():
    injected = np.zeros((6, 6, 6, 3, 4), np.float32)
    injected[1, 2, 3, :, 0] = -0.5  # band 0 <= 0: not lit
    injected[2, 2, 2, :, 1] = 0.3
    offvis = quadrature.offset_visibilities(_visibility(6, seed=1))
    for vis in (None, offvis):
        got, want = _both(injected, vis)
        assert got.shape == want.shape and got.dtype == want.dtype == np.float32
        assert not got.any() and not want.any()


@pytest.mark.parametrize("r", [6, 16])
def test_compiled_unfold_is_the_numpy_unfold(r):
    injected = _vpls(r, seed=7 * r)
    got = ordinates.unfold(injected)
    with jit.disabled():
        want = ordinates.unfold(injected)
    assert got.shape == want.shape and got.dtype == want.dtype == np.float32
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-5 * np.abs(want).max())
