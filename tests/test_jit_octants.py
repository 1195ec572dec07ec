"""The octant sweep (lpv_core/kernels/sweep.py): launch, sweep and fold of all directions of an
octant at once must give what the numpy reference gives (sweep.launch_solve folded by
sweep.fold_parts under jit.disabled()), for every combination of shell, transmittances,
handed-on light and occluded launch, also on the 32^3 Cornell box and in the engine's
images."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("numba")

from test_jit_fused import _passing  # tests/ is on sys.path under pytest
from test_jit_launch import _visibility, _vpls

from lpv_core import propagation, sh
from lpv_core.kernels import ordinates as compiled_ordinates
from lpv_core.kernels import sweep as octants
from lpv_core.propagation import ordinates, quadrature
from lpv_core.propagation import sweep as transport_sweep
from lpv_core.runtime import jit

pytestmark = pytest.mark.skipif(not jit.enabled(), reason="LPV_JIT=0: the kernels are off")


def _reference(injected, visibility, passing, shell, occlude_launch):
    """fold_parts(launch_solve(...)) in numpy: what launch_sweep_fold must return."""
    r = injected.shape[0]
    offvis = quadrature.offset_visibilities(visibility)
    with jit.disabled():
        acc = transport_sweep.launch_solve(injected, offvis if occlude_launch else None,
                                           passing, offvis, shell)
        return transport_sweep.fold_parts(acc, r, shell)


def _assert_same(got: tuple, want: tuple, shell: bool, rel: float = 1e-5) -> None:
    """Values and outflow equal to ``rel`` of the largest value; outflow's interior 0."""
    values, outflow = got
    assert values.shape == want[0].shape and values.dtype == np.float32
    scale = np.abs(want[0]).max()
    assert scale > 0
    np.testing.assert_allclose(values, want[0], rtol=0, atol=rel * scale)
    if not shell:
        assert outflow is None and want[1] is None
        return
    assert outflow.shape == want[1].shape == (values.shape[0] + 2,) * 3 + (3, 4)
    np.testing.assert_allclose(outflow, want[1], rtol=0, atol=rel * np.abs(want[1]).max())
    assert not outflow[1:-1, 1:-1, 1:-1].any()


@pytest.mark.parametrize("shell", [True, False])
@pytest.mark.parametrize("occluded", [True, False])
@pytest.mark.parametrize("handed_on", [True, False])
@pytest.mark.parametrize("occlude_launch", [True, False])
def test_the_octant_sweep_is_the_numpy_propagation(shell, occluded, handed_on, occlude_launch):
    """Random VPLs (half of them tilted: some directions land off their octant's corners),
    an opaque wall, handed-on light: the same values and outflow as the numpy reference."""
    r = 7
    seed = shell * 8 + occluded * 4 + handed_on * 2 + occlude_launch
    injected = _vpls(r, seed=seed)
    visibility = _visibility(r, seed=seed + 20) if occluded else None
    passing = _passing(r, seed=seed + 40) if handed_on else None
    got = octants.launch_sweep_fold(injected, visibility, passing, shell, occlude_launch)
    _assert_same(got, _reference(injected, visibility, passing, shell, occlude_launch), shell)


@pytest.mark.parametrize("r", [1, 2, 3, 5])
@pytest.mark.parametrize("shell", [True, False])
def test_the_octant_sweep_on_small_grids(r, shell):
    """One to five cells across (the ring's slots, the shell's slabs and rows at their
    smallest), lit cells on the grid's faces (their launch partly leaves the grid)."""
    rng = np.random.default_rng(r + 10 * shell)
    injected = _vpls(r, seed=r, count=20)
    injected[0, :, -1] += np.array([1.0, 0.3, -0.4, 0.5], np.float32)  # lit faces
    passing = _passing(r, seed=r + 1)
    visibility = rng.uniform(0.3, 1.0, (6, r, r, r)).astype(np.float32)
    got = octants.launch_sweep_fold(injected, visibility, passing, shell, True)
    _assert_same(got, _reference(injected, visibility, passing, shell, True), shell)


def test_dark_and_handed_on_only():
    """Nothing lit and nothing handed on: all zero; only handed-on light: its propagation,
    less itself."""
    r = 6
    dark = np.zeros((r, r, r, 3, 4), np.float32)
    values, outflow = octants.launch_sweep_fold(dark, None, None, True, True)
    assert values.shape == (r, r, r, 3, sh.BANDS2) and not values.any() and not outflow.any()
    passing = _passing(r, seed=3)
    got = octants.launch_sweep_fold(dark, _visibility(r, seed=4), passing, True, True)
    _assert_same(got, _reference(dark, _visibility(r, seed=4), passing, True, True), True)


def test_propagate_runs_the_octant_sweep():
    """propagate(angular="dom", launch=True) compiled is the octant sweep plus the
    emission's band 2, and equals the numpy propagate (both cascades' settings)."""
    r = 8
    injected, visibility, passing = _vpls(r, seed=7), _visibility(r, seed=8), _passing(r, 9)
    for capture, handed in ((True, None), (False, passing)):
        kw = {"visibility": visibility, "angular": "dom", "launch": True,
              "occlude_first_step": True, "capture_outflow": capture, "passing": handed}
        got = propagation.propagate(injected, 0, **kw)
        with jit.disabled():
            want = propagation.propagate(injected, 0, **kw)
        assert got.swept and want.swept
        _assert_same((got.values, got.outflow), (want.values, want.outflow), capture)
        values, _ = octants.launch_sweep_fold(injected, visibility, handed, capture, True)
        total = injected if handed is None else injected + handed
        ordinates.add_emission_band2(values, total)
        np.testing.assert_allclose(got.values, values, rtol=0, atol=0)


def _cornell_inputs() -> list:
    """The arguments of each propagation in a stated-quality Cornell box update (32^3,
    occlusion, the second cascade with handed-on light; in a fresh process also those of the
    backend's calibration, on a smaller grid)."""
    from lpv_core import engine
    from lpv_core.scene import GISettings
    from tools import core_scenes as demo
    from tools.bench import STATED

    calls = []
    real = transport_sweep.propagate

    def record(*args, **kwargs):
        calls.append((args, kwargs))
        return real(*args, **kwargs)

    settings = GISettings().updated(**STATED)
    scene = demo.cornell_box("SPOT", (64, 64), settings)
    transport_sweep.propagate = record
    try:
        engine.Engine().update(scene)
    finally:
        transport_sweep.propagate = real
    return calls


def test_the_cornell_box_is_the_numpy_sweep():
    """The stated-quality Cornell box's cascades: the octant sweep gives the numpy sweep's
    values and outflow (sweep.launch_solve, fold_parts) to float32 rounding."""
    calls = [c for c in _cornell_inputs() if c[0][0].shape[0] == 32]  # not the calibration's
    assert len(calls) >= 2 and any(c[0][5] is not None for c in calls)
    for args, kwargs in calls:
        injected, visibility, occlude, capture, launch, passing = args
        assert launch and not kwargs
        got = octants.launch_sweep_fold(injected, visibility, passing, capture, occlude)
        offvis = quadrature.offset_visibilities(visibility)
        with jit.disabled():
            acc = transport_sweep.launch_solve(injected, offvis if occlude else None, passing,
                                               offvis, capture)
            want = transport_sweep.fold_parts(acc, 32, capture)
        _assert_same(got, want, capture, rel=1e-5)


def test_emission_directions_compiled_are_numpy_bits():
    """ordinates.emission_directions compiled: emission.moments' directions bit for bit."""
    for seed, r in ((1, 6), (2, 9)):
        injected = _vpls(r, seed=seed)
        injected[0, 0, 0] = 0.0
        injected[0, 0, 0, 0, 0] = 0.5  # lit, band 1 zero: no direction
        cells, lit, _ = compiled_ordinates.lit_rows(injected)
        got = ordinates.emission_directions(cells, lit)
        with jit.disabled():
            want = ordinates.emission_directions(cells, lit)
        assert got.dtype == want.dtype == np.float32 and np.array_equal(got, want)
        assert not got[0].any()


def test_unfold_reusing_a_density_is_the_numpy_unfold():
    """Rows whose mean cosine and direction repeat the row before (a cell's colours in
    proportion) reuse its density in the compiled unfold: the same light as numpy."""
    injected = _vpls(6, seed=12)
    injected[..., 1, :] = 0.5 * injected[..., 0, :]  # green half of red: the same lobe
    injected[..., 2, :] = injected[..., 0, :]
    got = ordinates.unfold(injected)
    with jit.disabled():
        want = ordinates.unfold(injected)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-6 * np.abs(want).max())
    assert np.array_equal(got[:, 0], got[:, 2])


def _offset_visibility_at(visibility: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """quadrature.offset_visibilities(visibility) at the flat ``cells`` only, side by side
    (n, 27) float32: the same products in the same order, for n cells instead of R^3."""
    v = np.asarray(visibility).reshape(6, -1)[:, cells]
    one = np.ones((1, cells.size), v.dtype)
    f = [np.concatenate([v[2 * a + 1][None], one, v[2 * a][None]]) for a in range(3)]
    prod = (f[0][:, None, None] * f[1][None, :, None]) * f[2][None, None, :]
    return np.ascontiguousarray(prod.reshape(27, -1).T.astype(np.float32))


@pytest.mark.parametrize("r", [1, 4, 7])
def test_compiled_inputs_are_the_numpy_ones(r):
    """The lit cells, the launch's transmittances and the handed-on cells compiled
    (_lit_cells_kernel, _offset_visibility_kernel, _passing_cells_kernel): numpy's, bit for
    bit."""
    injected = _vpls(r, seed=r + 3, count=3 * r)
    visibility = _visibility(r, seed=r + 5)
    passing = _passing(r, seed=r + 7)
    p = r + 2
    cells, lit, rows = compiled_ordinates.lit_rows(injected)
    got = octants._lit_cells_kernel(cells, r)
    _, start, _, _ = compiled_ordinates.launch_geometry(cells, lit, r, None)
    xyz = np.stack(np.unravel_index(start, (p, p, p)), axis=1)
    first = np.searchsorted(start, np.arange(p + 1) * p * p)
    for g, want in zip(got, (lit, rows, xyz, first), strict=True):
        np.testing.assert_array_equal(g, want)
    lvis = np.empty((lit.size, 27), np.float32)
    octants._offset_visibility_kernel(visibility, lit, lvis)
    np.testing.assert_array_equal(lvis, _offset_visibility_at(visibility, lit))
    pcells = np.ascontiguousarray(passing, np.float32).reshape(-1, 4)
    prows = np.flatnonzero(pcells[:, 0] > 0)
    cell, colour = np.divmod(prows, 3)
    i, j, k = np.unravel_index(cell, (r, r, r))
    pcell = ((i + 1) * p + j + 1) * p + k + 1
    want = (prows, pcell, colour, np.searchsorted(pcell, np.arange(p + 1) * p * p))
    for g, w in zip(octants._passing_cells_kernel(pcells, r), want, strict=True):
        np.testing.assert_array_equal(g, w)


@pytest.mark.parametrize("kind", ["SPOT", "POINT", "SUN", "AREA"])
def test_engine_images_with_and_without_the_octant_sweep(kind, monkeypatch):
    """Every light type, three 20^3 cascades, two bounces: the Diffuse Indirect image of the
    engine on the octant sweep is the one on the numpy sweep (sweep.launch_sweep_fold under
    jit.disabled()) to 1e-5 of its largest value."""
    from lpv_core import engine
    from lpv_core.render import deferred
    from lpv_core.scene import GISettings
    from tools import core_scenes as demo

    settings = GISettings().updated(grid_resolution=20, cascades=3, cascades_auto=False,
                                    bounces=2)
    scene = demo.cornell_box(kind, (32, 32), settings)
    images = []

    def numpy_sweep(*args):
        with jit.disabled():
            return transport_sweep.launch_sweep_fold(*args)

    for octant_sweep in (True, False):
        if not octant_sweep:
            monkeypatch.setattr(octants, "launch_sweep_fold", numpy_sweep)
        eng = engine.Engine()
        images.append(deferred.render(eng, scene, eng.update(scene))["Diffuse Indirect"])
    octant, numpy = images
    assert np.isfinite(octant).all() and numpy.max() > 0
    np.testing.assert_allclose(octant, numpy, rtol=0, atol=1e-5 * numpy.max())
