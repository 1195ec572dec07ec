"""Discrete-ordinates propagation (lpv_core/ordinates.py, angular="dom"): exact flux
bookkeeping, occluders, directions kept apart, hand-on to the next cascade."""

import numpy as np
import pytest

from lpv_core import grid, injection, propagation, sh
from lpv_core.propagation import emission, ordinates, quadrature
from tools import dom_steps


def _random_moments(r=8, seed=3):
    rng = np.random.default_rng(seed)
    values = np.zeros((r, r, r, 3, 4), np.float32)
    inner = rng.normal(size=(4, 4, 4, 3, 4)).astype(np.float32)
    inner[..., 0] = np.abs(inner[..., 0]) + 0.5
    values[2:6, 2:6, 2:6] = inner
    return values


def test_tables_cover_the_sphere_and_each_direction_splits_its_flux_exactly():
    dirs, basis, groups = ordinates.tables()
    assert dirs.shape == (64, 3)
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=1), 1.0, atol=1e-6)
    assert abs(dirs.mean(axis=0)).max() < 0.002  # near-uniform: an even spread barely drifts
    seen = np.zeros(64, int)
    for sl, pairs in groups:
        assert len(pairs) == 8  # every octant lands between 8 cells
        total = sum(w[:, 0, 0, 0, 0] for _, _, w in pairs)
        np.testing.assert_allclose(total, 1.0, atol=1e-6)  # trilinear weights sum to one
        seen[sl] += 1
        for _, off, _ in pairs:  # a direction only moves the way it points
            signs = np.sign(dirs[sl])
            for a in range(3):
                assert off[a] == 0 or np.all(signs[:, a] == off[a])
    assert np.all(seen == 1)
    np.testing.assert_allclose(basis, sh.evaluate_basis(dirs.astype(np.float64)), atol=1e-6)


def test_unfold_keeps_the_flux_sends_nothing_behind_an_emitter_and_folds_back():
    g = grid.Grid((0.0, 0.0, 0.0), 1.0, 8)
    n = np.array([[0.0, 0.6, 0.8]])
    values = injection.inject(g, np.array([[4.0, 4.0, 4.0]]), n, np.ones((1, 3)))
    flux = ordinates.unfold(values)
    np.testing.assert_allclose(flux.sum(axis=(0, 2, 3, 4)), propagation.flux(values), rtol=1e-5)
    dirs = ordinates.tables()[0]
    behind = dirs @ n[0] < 0
    assert flux[behind].max() == 0.0  # a diffuse emitter sends nothing through its surface
    assert flux.min() >= 0.0
    folded = ordinates.fold(flux)
    np.testing.assert_allclose(propagation.flux(folded), propagation.flux(values), rtol=1e-5)
    held, r, d = emission.moments(folded.reshape(-1, 4))
    lit = held > 1e-6 * held.max()
    # The folded lobe points the emitter's way with about a diffuse emitter's mean cosine.
    assert np.all(d[lit] @ n[0] > 0.99)
    np.testing.assert_allclose(r[lit], emission.LAMBERTIAN_MEAN_COSINE, atol=0.03)


def test_step_conserves_flux_and_respects_occluders():
    flux = ordinates.unfold(_random_moments())
    before = flux.sum()
    out = dom_steps.step(flux)
    np.testing.assert_allclose(out.sum(), before, rtol=1e-5)  # nothing reached the border
    closed = np.zeros((6, 8, 8, 8), np.float32)  # every face blocks
    offvis = quadrature.offset_visibilities(closed)
    out = dom_steps.step(flux, offvis)
    live = flux.sum(axis=(0, 1)) > 0
    # Only the "stay" share (offset 0, no face crossed) survives, in the cells it left.
    assert np.all(out.sum(axis=(0, 1))[~live] == 0)
    assert out.sum() < before


def test_beams_cross_without_merging():
    """Two beams crossing in one cell come out the other side along their own directions
    (a two-moment cell would merge them into one lobe along their mean)."""
    dirs, _, _ = ordinates.tables()
    r = 16
    flux = np.zeros((64, 3, r, r, r), np.float32)
    a = int(np.argmax(dirs @ np.array([1.0, 0.0, 0.0])))
    b = int(np.argmax(dirs @ np.array([0.0, 1.0, 0.0])))
    flux[a, :, 2, 8, 8] = 1.0
    flux[b, :, 8, 2, 8] = 1.0
    for _ in range(12):
        flux = dom_steps.step(flux)
    assert set(np.nonzero(flux.sum(axis=(1, 2, 3, 4)))[0]) == {a, b}
    np.testing.assert_allclose(flux[a].sum(), 3.0, rtol=1e-3)  # a sliver spreads out
    np.testing.assert_allclose(flux[b].sum(), 3.0, rtol=1e-3)


@pytest.mark.parametrize("occluded", [False, True])
def test_outflow_plus_what_stays_plus_absorbed_is_the_injected_flux(occluded):
    """capture_outflow hands on exactly what leaves the grid (to the next cascade)."""
    values = _random_moments()
    vis = None
    if occluded:
        vis = np.random.default_rng(5).uniform(0.5, 1.0, (6, 8, 8, 8)).astype(np.float32)
    free = propagation.propagate(values, visibility=None, angular="dom", capture_outflow=True)
    assert free.outflow.shape == (10, 10, 10, 3, 4)
    # Without occluders everything leaves in the end.
    np.testing.assert_allclose(propagation.flux(free.outflow), propagation.flux(values),
                               rtol=1e-4)
    res = propagation.propagate(values, visibility=vis, angular="dom", capture_outflow=True,
                                occlude_first_step=True)
    out = propagation.flux(res.outflow)
    assert np.all(out <= propagation.flux(values) * (1 + 1e-5))
    if occluded:
        assert np.all(out < 0.99 * propagation.flux(values))
    assert np.isfinite(res.values).all() and np.isfinite(res.outflow).all()


def test_the_steps_stop_once_a_step_moves_little_and_never_gain_energy():
    """The stepping reference (propagate_steps, what a stepping backend is checked against)."""
    values = _random_moments()
    res = dom_steps.propagate_steps(values, 500, min_fraction=1e-3)
    assert res.stopped_early and res.remaining_fraction < 1e-3
    assert res.iterations < 500
    flux = ordinates.unfold(values)
    last = flux.sum()
    for _ in range(40):
        flux = dom_steps.step(flux)
        now = flux.sum()
        assert now <= last * (1 + 1e-6)
        last = now


def test_large_grids_keep_weights_and_transmittances_apart_with_the_same_result(monkeypatch):
    """Above FACTOR_TABLE_BYTES the weight x transmittance table is not built (memory);
    the step multiplies by both instead and must give the same light."""
    values = _random_moments()
    vis = np.random.default_rng(9).uniform(0.3, 1.0, (6, 8, 8, 8)).astype(np.float32)
    fused = dom_steps.propagate_steps(values, 12, min_fraction=0.0, visibility=vis,
                                      occlude_first_step=True)
    monkeypatch.setattr(ordinates, "FACTOR_TABLE_BYTES", 0)
    table = ordinates.factors(8, quadrature.offset_visibilities(vis))
    assert all(v is not None for _, row in table for _, _, v in row)
    apart = dom_steps.propagate_steps(values, 12, min_fraction=0.0, visibility=vis,
                                      occlude_first_step=True)
    np.testing.assert_allclose(apart.values, fused.values, rtol=1e-5,
                               atol=1e-6 * np.abs(fused.values).max())


@pytest.mark.parametrize("iterations", [0, 40])
def test_a_grid_too_large_for_memory_is_refused_before_any_work(iterations):
    """grid_resolution 128 would need ~13.3 GB for the sweep with its shell ("dom" sweeps
    whatever the iterations setting): a clear error naming the setting with the memory
    guard's figure, raised by GISettings before the RSM is rendered (not a MemoryError)."""
    figure = "13.3"
    from lpv_core import engine
    from lpv_core.propagation import sweep
    from lpv_core.scene import GISettings
    from tools import core_scenes as demo

    ordinates.check_memory(64)  # ~0.9 GB: fine
    sweep.check_memory(64)  # ~2.4 GB: fine
    stats = engine.Stats()
    with pytest.raises(ValueError, match=f"grid_resolution 128 needs about {figure} GB"):
        sc = demo.cornell_box("SPOT", (8, 8), GISettings(grid_resolution=128, backend="numpy",
                                                         iterations=iterations))
        engine.Engine().update(sc, stats)
    assert "rsm" not in stats.ms
