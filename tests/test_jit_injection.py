"""The compiled VPL injection (kernels.injection) against the numpy reference."""

import numpy as np
import pytest

pytest.importorskip("numba")

from lpv_core import injection
from lpv_core.grid import Grid
from lpv_core.kernels import injection as compiled
from lpv_core.runtime import jit


def _both(g, pos, nrm, flux, vis, offset=0.5):
    with jit.disabled():
        ref = injection.inject(g, pos, nrm, flux, offset, vis)
    assert jit.enabled()
    return ref, injection.inject(g, pos, nrm, flux, offset, vis)


def _agree(ref, got):
    assert got.shape == ref.shape and got.dtype == ref.dtype == np.float32
    scale = np.abs(ref).max(axis=(0, 1, 2))  # (3, 4): per channel
    assert np.all(np.abs(got - ref).max(axis=(0, 1, 2)) <= 1e-6 * scale)


def _vpls(g, n, rng):
    """Positions over the grid and a cell beyond it (partly outside), unit normals, flux > 0."""
    lo, hi = g.bounds()
    pos = lo - g.cell_size + rng.random((n, 3)) * (hi - lo + 2 * g.cell_size)
    nrm = rng.normal(size=(n, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    return pos, nrm, rng.random((n, 3)) + 0.01


def _visibility(r, rng):
    vis = rng.random((6, r, r, r)).astype(np.float32)
    vis[rng.random(vis.shape) < 0.2] = 0.0
    return vis


@pytest.mark.parametrize("r", [5, 16])
@pytest.mark.parametrize("with_vis", [False, True])
def test_compiled_inject_matches_numpy(r, with_vis):
    rng = np.random.default_rng(r + 10 * with_vis)
    g = Grid((-1.0, 0.5, -2.0), 0.3, r)
    vis = _visibility(r, rng) if with_vis else None
    for n in (1, 300, 20000):  # 20000: two threads at R <= 16 (SPLIT_MIN)
        ref, got = _both(g, *_vpls(g, n, rng), vis)
        assert n == 1 or np.all(np.abs(ref).max(axis=(0, 1, 2)) > 0)
        _agree(ref, got)


def test_compiled_inject_float64_visibility_and_float32_inputs():
    rng = np.random.default_rng(3)
    g = Grid((0.0, 0.0, 0.0), 0.25, 8)
    pos, nrm, flux = (a.astype(np.float32) for a in _vpls(g, 2000, rng))
    _agree(*_both(g, pos, nrm, flux, _visibility(8, rng).astype(np.float64)))


def test_compiled_inject_all_hidden_keeps_trilinear():
    """A visibility of zeros hides every corner: both paths keep the plain trilinear weights."""
    rng = np.random.default_rng(4)
    g = Grid((0.0, 0.0, 0.0), 1.0, 6)
    _agree(*_both(g, *_vpls(g, 500, rng), np.zeros((6, 6, 6, 6), np.float32)))


@pytest.mark.parametrize("r", [5, 16])
def test_compiled_inject_on_half_cell_planes(r):
    """VPLs landing exactly on half-cell planes (and within the 1e-3 tolerance of one) after
    the shift: the nearest-cell choice of visible_corners must be the same."""
    rng = np.random.default_rng(5 + r)
    g = Grid((-0.5, 0.25, 1.0), 0.5, r)
    n = 3000
    nrm = np.zeros((n, 3))
    axis = rng.integers(0, 3, n)
    nrm[np.arange(n), axis] = rng.choice([-1.0, 1.0], n)
    # Cell coords k + 0.5 (+- less than the tolerance) on every axis, then moved back by the
    # shift that inject applies along the normal.
    coords = rng.integers(-1, r + 1, (n, 3)) + 0.5
    coords += rng.choice([0.0, 0.0, 5e-4, -5e-4, 2e-3], (n, 3))
    pos = g.origin_array + (coords + 0.5) * g.cell_size - nrm * 0.5 * g.cell_size
    assert np.all(np.abs(g.cell_coords(pos + nrm * 0.5 * g.cell_size) - coords) < 1e-9)
    flux = rng.random((n, 3)) + 0.01
    vis = _visibility(r, rng)
    _agree(*_both(g, pos, nrm, flux, vis))
    _agree(*_both(g, pos, nrm, flux, None))


def test_compiled_inject_empty_and_far():
    g = Grid((0.0, 0.0, 0.0), 1.0, 5)
    rng = np.random.default_rng(6)
    vis = _visibility(5, rng)
    empty = np.zeros((0, 3))
    for v in (None, vis):
        ref, got = _both(g, empty, empty, empty, v)
        assert got.shape == (5, 5, 5, 3, 4) and not got.any() and not ref.any()
    # Far outside (and non-finite) positions add nothing on either path.
    pos = np.array([[1e30, 2.0, 2.0], [-1e30, 2.0, 2.0], [np.nan, 2.0, 2.0], [2.0, 2.0, 9.0]])
    nrm = np.tile([0.0, 0.0, 1.0], (4, 1))
    for v in (None, vis):
        with np.errstate(invalid="ignore"):  # numpy's int cast of inf / NaN cell coords
            ref, got = _both(g, pos, nrm, np.ones((4, 3)), v)
        assert not got.any() and not ref.any()


@pytest.mark.parametrize("with_vis", [False, True])
def test_compiled_inject_bit_identical(with_vis):
    """Same float64 products and sums per VPL and corner as numpy: identical output, for VPLs
    inside the grid (all 8 corners in) and at its border (some corners out)."""
    rng = np.random.default_rng(7 + with_vis)
    g = Grid((0.5, -1.0, 0.25), 0.2, 12)
    vis = _visibility(12, rng) if with_vis else None
    for n in (500, 20000):
        ref, got = _both(g, *_vpls(g, n, rng), vis)
        assert np.array_equal(ref, got)


def _grid_args(g, pos, nrm, flux, vis):
    r = g.resolution
    return (np.ascontiguousarray(pos, np.float64), np.ascontiguousarray(nrm, np.float64),
            np.ascontiguousarray(flux, np.float64), np.zeros(0, np.int64), g.origin_array,
            float(g.cell_size), 0.5 * g.cell_size, r, vis.reshape(6, -1), True)


def _splat(g, args, boxes):
    """The compiled splat run box by box into one sum grid (as the threads run the slabs):
    the float32 grid."""
    cells = g.resolution ** 3
    acc, touched = compiled._sums(cells)
    out = np.full((cells, 12), np.nan, np.float32)  # every cell must be written
    for k, box in enumerate(boxes):
        compiled._splat_box(args, args[0].shape[0], acc, touched, cells + k, box, out)
    return out


def test_compiled_inject_slabs_are_the_one_thread_result():
    """The two slabs of split_slabs, splatted apart, give the one-box result bit for bit (every
    cell sums its VPLs in VPL order either way), straddling VPLs included."""
    rng = np.random.default_rng(8)
    g = Grid((0.0, -0.5, 0.25), 0.125, 16)
    pos, nrm, flux = _vpls(g, 30000, rng)
    args = _grid_args(g, pos, nrm, flux, _visibility(16, rng))
    halves = compiled.split_slabs(*args[:2], *args[4:8])
    assert halves is not None
    lo, hi = halves
    axis = int(np.argmax(lo[:, 1] < 16))
    assert lo[axis, 1] == hi[axis, 0] and 4 <= lo[axis, 1] <= 12  # random VPLs: near the middle
    whole = np.array([[0, 16]] * 3, np.int64)
    one = _splat(g, args, [whole])
    assert np.array_equal(_splat(g, args, [lo, hi]), one)
    with jit.disabled():
        ref = injection.inject(g, pos, nrm, flux, 0.5, args[8].reshape(6, 16, 16, 16))
    assert np.array_equal(one.reshape(ref.shape), ref)


def test_split_slabs_balances_or_declines():
    """VPLs on one plane x = const: the cut goes across y or z, with about half on each side;
    VPLs all in one cell (or outside the grid): no cut is worth a thread."""
    rng = np.random.default_rng(9)
    g = Grid((0.0, 0.0, 0.0), 1.0, 32)
    n = 20000
    pos = np.column_stack([np.full(n, 10.3), rng.random(n) * 32, rng.random(n) * 32])
    nrm = np.tile([1.0, 0.0, 0.0], (n, 1))
    lo, hi = compiled.split_slabs(pos, nrm, g.origin_array, 1.0, 0.5, 32)
    axis = int(np.argmax(lo[:, 1] < 32))
    assert axis in (1, 2) and abs(lo[axis, 1] - 16) <= 2
    assert np.array_equal(np.delete(lo, axis, 0), np.delete(hi, axis, 0))
    one_cell = np.tile([5.2, 6.3, 7.4], (n, 1))
    assert compiled.split_slabs(one_cell, nrm, g.origin_array, 1.0, 0.5, 32) is None
    assert compiled.split_slabs(one_cell + 100.0, nrm, g.origin_array, 1.0, 0.5, 32) is None


@pytest.mark.parametrize("with_vis", [False, True])
def test_compiled_inject_32_cubed_two_threads(with_vis):
    """R = 32 from SPLIT_MIN VPLs (two slabs on two threads), VPLs in texel-like order on two
    walls and partly outside: the numpy reference to the last bit."""
    rng = np.random.default_rng(10 + with_vis)
    g = Grid((-1.0, -1.0, -1.0), 2.0 / 32, 32)
    n = 2 * compiled.SPLIT_MIN
    u, v = np.meshgrid(np.linspace(-1.1, 1.1, 128), np.linspace(-1.1, 1.1, n // 256))
    floor = np.column_stack([u.ravel(), np.full(u.size, -0.97), v.ravel()])
    wall = np.column_stack([np.full(u.size, 0.31), u.ravel(), v.ravel()])
    pos = np.concatenate([floor, wall])
    nrm = np.concatenate([np.tile([0.0, 1.0, 0.0], (u.size, 1)),
                          np.tile([-1.0, 0.0, 0.0], (u.size, 1))])
    flux = rng.random((n, 3)) + 0.01
    vis = _visibility(32, rng) if with_vis else None
    ref, got = _both(g, pos, nrm, flux, vis)
    assert np.array_equal(ref, got)


@pytest.mark.parametrize("n", [300, 3 * compiled.SPLIT_MIN])
def test_compiled_inject_index_reads_rows_in_place(n):
    """``index`` injects those rows in that order, as the gathered arrays would: the numpy
    reference of the gathered arrays to the last bit, on one thread and on two."""
    rng = np.random.default_rng(12)
    g = Grid((-1.0, 0.5, -2.0), 0.3, 16)
    pos, nrm, flux = _vpls(g, n, rng)
    vis = _visibility(16, rng)
    index = np.sort(rng.choice(n, size=n * 2 // 3, replace=False))
    index[:5] = index[:5][::-1]  # any order, not only increasing
    with jit.disabled():
        ref = injection.inject(g, pos[index], nrm[index], flux[index], 0.5, vis)
        assert np.array_equal(injection.inject(g, pos, nrm, flux, 0.5, vis, index=index), ref)
    assert np.array_equal(injection.inject(g, pos, nrm, flux, 0.5, vis, index=index), ref)
    empty = injection.inject(g, pos, nrm, flux, 0.5, vis, index=index[:0])
    assert empty.shape == ref.shape and not empty.any()
