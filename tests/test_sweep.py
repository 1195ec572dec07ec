"""The transport sweep (lpv_core/sweep.py): the discrete-ordinates propagation solved in one
ordered pass must be the limit of the steps, conserve flux, respect walls, and be what the
engine runs with automatic iterations."""

from __future__ import annotations

import numpy as np
import pytest

from lpv_core import demo, engine, propagation, sweep
from lpv_core.scene import GISettings


def _case(r: int, seed: int = 1, wall: bool = True):
    """A random injected grid (30 lit cells, tinted lobes) and face visibilities with an
    opaque wall across the middle of x."""
    rng = np.random.default_rng(seed)
    inj = np.zeros((r, r, r, 3, 4), np.float32)
    for _ in range(30):
        c = rng.integers(0, r, 3)
        n = rng.normal(size=3)
        n /= np.linalg.norm(n)
        lobe = np.concatenate([[1.0], 0.6 * n[[1, 2, 0]]]) * rng.uniform(0.5, 2.0)
        inj[c[0], c[1], c[2]] += lobe[None] * np.array([1.0, 0.5, 0.2])[:, None]
    vis = rng.uniform(0.3, 1.0, (6, r, r, r)).astype(np.float32)
    if wall:
        vis[:, r // 2] = 0.0
    return inj, vis


@pytest.mark.parametrize("occlude_first_step", [True, False])
@pytest.mark.parametrize("capture_outflow", [True, False])
@pytest.mark.parametrize("occluded", [True, False])
def test_the_sweep_is_the_limit_of_the_steps(occlude_first_step, capture_outflow, occluded):
    """Stepping until nothing is left in flight (min_fraction 0, enough steps to cross the
    grid three times) and the sweep give the same grid and outflow to float precision."""
    r = 9
    inj, vis = _case(r)
    kw = {"visibility": vis if occluded else None, "angular": "dom",
          "occlude_first_step": occlude_first_step, "capture_outflow": capture_outflow}
    steps = propagation.propagate(inj, 40 * r, min_fraction=0.0, **kw)
    assert steps.remaining_fraction < 1e-7  # the reference has converged
    swept = propagation.propagate(inj, 0, sweep=True, **kw)
    assert swept.swept and swept.iterations == 0 and not steps.swept
    scale = np.abs(steps.values).max()
    np.testing.assert_allclose(swept.values, steps.values, rtol=0, atol=1e-5 * scale)
    if capture_outflow:
        np.testing.assert_allclose(swept.outflow, steps.outflow, rtol=0,
                                   atol=1e-5 * np.abs(steps.outflow).max())
    else:
        assert swept.outflow is None


def test_without_occluders_all_the_injected_flux_leaves_the_grid():
    """Nothing absorbs: every watt injected ends in the outflow (hand-derived: the steps'
    weights sum to one in each direction), per colour."""
    inj, _ = _case(8, wall=False)
    res = propagation.propagate(inj, 0, angular="dom", sweep=True, capture_outflow=True,
                                occlude_first_step=True)
    np.testing.assert_allclose(propagation.flux(res.outflow), propagation.flux(inj), rtol=1e-5)


def test_an_opaque_wall_stops_the_light():
    """Light injected on one side of a fully blocking plane of cells never reaches the
    other side, and arrives on its own side."""
    r = 10
    inj = np.zeros((r, r, r, 3, 4), np.float32)
    inj[2, 5, 5, :, 0] = 1.0  # an isotropic source at x = 2
    vis = np.ones((6, r, r, r), np.float32)
    vis[:, 6] = 0.0  # cells at x = 6 send nothing on
    res = propagation.propagate(inj, 0, visibility=vis, angular="dom", sweep=True,
                                occlude_first_step=True)
    band0 = res.values[..., 0]
    assert band0[7:].max() == 0.0
    assert band0[3:6].min() > 0.0


def test_memory_estimate_grows_with_the_grid_and_refuses_beyond_the_limit():
    """memory_bytes counts what a sweep holds; check_memory refuses with the figure."""
    assert sweep.memory_bytes(32) > 8 * sweep.memory_bytes(16) * 0.8
    sweep.check_memory(32)
    with pytest.raises(ValueError, match="grid_resolution 96 needs about"):
        sweep.check_memory(96)


def test_the_engine_sweeps_with_automatic_iterations_and_steps_when_asked():
    """Automatic iterations (0) with discrete ordinates run the sweep (stats say "sweep");
    a set iteration count runs that many steps at most. The two images agree once the steps
    have converged (the early stop leaves < 1e-3 of the flux per step in flight)."""
    out = {}
    for iterations in (0, 48):
        settings = GISettings(grid_resolution=12, iterations=iterations, backend="numpy")
        sc = demo.cornell_box("SPOT", (24, 24), settings)
        stats = engine.Stats()
        res = engine.Engine().update(sc, stats)
        out[iterations] = (res, stats)
    assert out[0][1].info["iterations"] == ["sweep"]
    assert all(isinstance(n, int) and 0 < n <= 48 for n in out[48][1].info["iterations"])
    a, b = out[0][0].values, out[48][0].values
    assert np.abs(a - b).max() <= 0.02 * np.abs(b).max()
    assert propagation.flux(a[..., :4]).sum() >= propagation.flux(b[..., :4]).sum()
