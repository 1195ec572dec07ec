"""Compiled parts of the discrete-ordinates propagation around the sweep (ordinates.launch
inside sweep.launch_solve, ordinates.unfold_sparse and add_emission_band2, cascades' hand-on
and assign): the same numbers as the numpy code, which stays the reference
(jit.disabled())."""

import numpy as np
import pytest

pytest.importorskip("numba")

from test_jit_launch import _visibility, _vpls

from lpv_core import sh
from lpv_core.propagation import ordinates, quadrature
from lpv_core.propagation import sweep as transport_sweep
from lpv_core.runtime import jit


def _passing(r: int, seed: int) -> np.ndarray:
    """Handed-on light in a few cells (as cascades.hand_on leaves it), one colour dark."""
    rng = np.random.default_rng(seed)
    out = np.zeros((r, r, r, 3, 4), np.float32)
    cells = rng.integers(0, r, (12, 3))
    out[cells[:, 0], cells[:, 1], cells[:, 2], :, 0] = rng.uniform(0.1, 1.0, (12, 3))
    out[cells[:, 0], cells[:, 1], cells[:, 2], :, 1:] = rng.uniform(-0.2, 0.2, (12, 3, 3))
    out[cells[0, 0], cells[0, 1], cells[0, 2], 2] = 0.0
    return out


@pytest.mark.parametrize("shell", [True, False])
@pytest.mark.parametrize("handed_on", [False, True])
def test_launch_solve_is_launch_then_solve_less_the_handed_on_light(shell, handed_on):
    r = 10
    injected = _vpls(r, seed=3)
    offvis = quadrature.offset_visibilities(_visibility(r, seed=4))
    passing = _passing(r, seed=5) if handed_on else None
    got = transport_sweep.launch_solve(injected, offvis, passing, offvis, shell)
    # the steps apart, compiled: launch, the handed-on light unfolded densely, solve, less it
    source = ordinates.launch(injected, offvis)
    in_place = np.zeros_like(source)
    if handed_on:
        in_place = ordinates.pad(ordinates.unfold(passing))
    apart = transport_sweep.solve(source + in_place, r, offvis, shell) - in_place
    with jit.disabled():
        want = transport_sweep.launch_solve(injected, offvis, passing, offvis, shell)
    scale = np.abs(want).max()
    assert scale > 0 and got.shape == want.shape == (ordinates.DIRECTIONS, 3, (r + 2) ** 3)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-5 * scale)
    np.testing.assert_allclose(got, apart, rtol=0, atol=1e-6 * scale)
    if not shell:
        grid = got.reshape(-1, 3, r + 2, r + 2, r + 2)
        assert not grid[..., 0, :, :].any() and not grid[..., -1].any()


def test_unfold_sparse_is_the_dense_unfold():
    r = 8
    passing = _passing(r, seed=9)
    for enabled in (True, False):
        with jit.disabled() if not enabled else _null():
            index, flux = ordinates.unfold_sparse(passing)
            dense = np.zeros((ordinates.DIRECTIONS, 3 * (r + 2) ** 3), np.float32)
            dense[:, index] = flux
            want = ordinates.pad(ordinates.unfold(passing)).reshape(ordinates.DIRECTIONS, -1)
        assert len(np.unique(index)) == index.size == int((passing[..., 0] > 0).sum())
        np.testing.assert_allclose(dense, want, rtol=0, atol=1e-6 * np.abs(want).max())


class _null:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


def test_add_emission_band2_is_emission_band2():
    injected = _vpls(8, seed=11)
    injected[0, 0, 0, :, 0] = -0.1  # band 0 <= 0: the moments are copied, no band 2
    injected[0, 0, 0, :, 1:] = 0.2
    base = np.random.default_rng(1).uniform(0, 1, injected.shape[:-1] + (sh.BANDS2,))
    got = base.astype(np.float32)
    ordinates.add_emission_band2(got, injected)
    want = base.astype(np.float32) + ordinates.emission_band2(injected)
    assert np.abs(ordinates.emission_band2(injected)[..., 4:]).max() > 0.01
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-6 * np.abs(want).max())
    with pytest.raises(ValueError, match="contiguous"):
        ordinates.add_emission_band2(got[..., ::2, :], injected[..., ::2, :])


def test_compiled_hand_on_is_numpy_hand_on():
    """cascades.hand_on over the shell only (compiled) adds the same bits as np.add.at; an
    outflow with light inside (not what propagation leaves) takes the numpy path, the same."""
    from lpv_core import cascades, grid

    rng = np.random.default_rng(4)
    r = 6
    finer = grid.Grid((0.13, -0.4, 0.27), 0.25, r)
    coarser = grid.Grid((0.6, -1.15, -0.48), 0.5, r)  # holds only part of finer's shell
    outflow = rng.uniform(0.1, 1.0, (r + 2, r + 2, r + 2, 3, 4)).astype(np.float32)
    outflow[1:-1, 1:-1, 1:-1] = 0.0
    outflow[0, 3, 4] = 0.0  # a dark shell cell
    inside = np.pad(np.ones((r, r, r, 3, 4), np.float32), ((1, 1),) * 3 + ((0, 0),) * 2)
    for flow in (outflow, outflow + inside):
        before = rng.uniform(0.0, 1.0, (r, r, r, 3, 4)).astype(np.float32)
        got, want = before.copy(), before.copy()
        cascades.hand_on(finer, flow, coarser, got)
        with jit.disabled():
            cascades.hand_on(finer, flow, coarser, want)
        assert np.array_equal(got, want)
        added = float((got - before).sum(dtype=np.float64))
        assert 0 < added < 0.9 * float(flow.sum(dtype=np.float64))  # some of it left


def test_compiled_assign_is_numpy_assign():
    """cascades.assign compiled: the same finest cascade per point as numpy's, points on the
    margins and NaN included."""
    from lpv_core import cascades, grid

    chain = [grid.Grid((0.0, 0.0, 0.0), 0.25, 8), grid.Grid((-1.0, -1.0, -1.0), 0.5, 8),
             grid.Grid((-3.0, -3.0, -3.0), 1.0, 8)]
    rng = np.random.default_rng(6)
    points = rng.uniform(-3.5, 5.5, (4000, 3))
    points[:5] = [[0.25, 0.25, 0.25], [1.75, 1.75, 1.75], [0.2499, 1.0, 1.0],
                  [np.nan, 0.5, 0.5], [-0.5, -0.5, -0.5]]  # margins, NaN
    got = cascades.assign(chain, points)
    with jit.disabled():
        want = cascades.assign(chain, points)
    assert np.array_equal(got, want) and got.dtype == want.dtype
    assert set(np.unique(want)) == {0, 1, 2}
