"""The transport sweep (lpv_core/sweep.py): the discrete-ordinates propagation solved in one
ordered pass must be the limit of the steps (dom_steps.propagate_steps, the stepping
reference), conserve flux, respect walls, and be what the engine runs whatever the iterations
setting."""

from __future__ import annotations

import numpy as np
import pytest

from lpv_core import engine, geometry_volume, injection, lookup, propagation, sh
from lpv_core.grid import Grid
from lpv_core.propagation import ordinates, sweep
from lpv_core.scene import GISettings
from tools import core_scenes as demo
from tools import dom_steps


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


@pytest.mark.parametrize("first", ["occluded", "free", "launch", "launch+passing"])
@pytest.mark.parametrize("capture_outflow", [True, False])
@pytest.mark.parametrize("occluded", [True, False])
def test_the_sweep_is_the_limit_of_the_steps(first, capture_outflow, occluded):
    """Stepping until nothing is left in flight (min_fraction 0, enough steps to cross the
    grid three times) and the sweep give the same grid and outflow to float precision, for
    every first step: occluded, free, launched from surfaces (with handed-on light)."""
    r = 9
    inj, vis = _case(r)
    kw = {"visibility": vis if occluded else None,
          "occlude_first_step": first != "free", "capture_outflow": capture_outflow,
          "launch": first.startswith("launch")}
    if first == "launch+passing":
        kw["passing"] = 0.3 * _case(r, seed=5, wall=False)[0]
    steps = dom_steps.propagate_steps(inj, 40 * r, min_fraction=0.0, **kw)
    assert steps.remaining_fraction < 1e-7  # the reference has converged
    swept = propagation.propagate(inj, 0, angular="dom", **kw)
    assert swept.swept and swept.iterations == 0 and not steps.swept
    scale = np.abs(steps.values).max()
    np.testing.assert_allclose(swept.values, steps.values, rtol=0, atol=1e-5 * scale)
    if capture_outflow:
        np.testing.assert_allclose(swept.outflow, steps.outflow, rtol=0,
                                   atol=1e-5 * np.abs(steps.outflow).max())
    else:
        assert swept.outflow is None


@pytest.mark.parametrize("launch", [False, True])
def test_without_occluders_all_the_injected_flux_leaves_the_grid(launch):
    """Nothing absorbs: every watt injected (and handed on) ends in the outflow
    (hand-derived: the steps' and the launch's weights sum to one per direction), per
    colour."""
    inj, _ = _case(8, wall=False)
    passing = 0.3 * _case(8, seed=5, wall=False)[0]
    res = propagation.propagate(inj, 0, angular="dom", capture_outflow=True,
                                occlude_first_step=True, launch=launch, passing=passing)
    np.testing.assert_allclose(propagation.flux(res.outflow),
                               propagation.flux(inj) + propagation.flux(passing), rtol=1e-5)


def test_launch_moves_each_direction_from_the_surface():
    """A Lambertian emitter facing +z in one cell: each direction's first-step arrivals are
    centred on w + (1/2) (w - m <w, m>) / max(<w, m>, |w - m <w, m>|) cells (the light
    leaving the surface half a cell below the injection point, sideways shift at most half a
    cell), clipped to one cell per axis; nothing goes backwards."""
    r, c = 7, 3
    inj = np.zeros((r, r, r, 3, 4), np.float32)
    inj[c, c, c] = sh.cosine_lobe(np.array([0.0, 0.0, 1.0])) / np.pi  # 1 W per colour
    dirs = ordinates.tables()[0].astype(np.float64)
    out = ordinates.launch(inj).reshape(len(dirs), 3, r + 2, r + 2, r + 2)[:, 0]
    grid = np.stack(np.meshgrid(*[np.arange(r + 2)] * 3, indexing="ij"), -1) - (c + 1)
    m = np.array([0.0, 0.0, 1.0])
    moved = 0
    for j, w in enumerate(dirs):
        total = out[j].sum()
        if w[2] <= 0:
            assert total == 0.0  # a Lambertian emitter sends nothing backwards
            continue
        side = w - m * w[2]
        expect = np.clip(w + 0.5 * side / max(w[2], np.linalg.norm(side)), -1, 1)
        centre = (out[j][..., None] * grid).sum(axis=(0, 1, 2)) / total
        np.testing.assert_allclose(centre, expect, atol=1e-5)
        moved += total
    assert moved == pytest.approx(1.0, rel=1e-5)  # the flux is kept


def test_launch_brings_the_light_above_a_lit_patch_closer_to_the_analytic_value():
    """A 1.8 m lit floor patch in a 5 x 4 x 2.8 m room at 16^3, averaged over four grid
    phases: without the launch the ceiling over the patch reads ~1.4x the analytic
    irradiance (sum of Phi/pi cos cos / r^2 over the patch's VPLs: light started half a cell
    off the floor), with it ~1.27x (the receiver's half cell remains)."""
    room = demo.box_triangles((0, 0, 0), (5, 4, 2.8), inward=True).reshape(-1, 3, 3)
    s = (np.arange(36) + 0.5) / 36
    xs, ys = np.meshgrid(1.6 + 1.8 * s, 1.1 + 1.8 * s, indexing="ij")
    pos = np.stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)], 1)
    nrm = np.tile([0.0, 0.0, 1.0], (xs.size, 1))
    flux = np.full((xs.size, 3), 1.0 / xs.size)
    pts = np.stack([np.linspace(2.1, 2.9, 3), np.full(3, 2.0), np.full(3, 2.8)], 1)
    down = np.tile([0.0, 0.0, -1.0], (3, 1))
    d = pos[None] - pts[:, None]
    r2 = (d * d).sum(-1)
    analytic = (flux[:, 0][None] / np.pi * d[..., 2] ** 2 / r2**2).sum(1)
    ratio = {}
    for launch in (False, True):
        got = []
        for shift in (0.0, 0.25, 0.5, 0.75):
            cs = 5.4 / 16
            g = Grid((-0.2 - shift * cs, -0.7 - shift * cs, -1.3 - shift * cs), cs, 16)
            vis, gaps = geometry_volume.occluder_volume(g, room)
            inj = injection.inject(g, pos, nrm, flux, visibility=vis)
            values = propagation.propagate(inj, 0, visibility=vis, angular="dom",
                                           occlude_first_step=True,
                                           launch=launch).values
            e = lookup.irradiance(g, values, lookup.sample_points(g, pts, down, gaps), down,
                                  offset_cells=0.0, angular="dom", visibility=vis)[:, 0]
            got.append(e / analytic)
        ratio[launch] = float(np.mean(got))
    print(f"ceiling over the patch / analytic: {ratio[False]:.3f} -> {ratio[True]:.3f}")
    assert ratio[False] > 1.35
    assert 1.0 < ratio[True] < 1.32


def test_an_opaque_wall_stops_the_light():
    """Light injected on one side of a fully blocking plane of cells never reaches the
    other side, and arrives on its own side."""
    r = 10
    inj = np.zeros((r, r, r, 3, 4), np.float32)
    inj[2, 5, 5, :, 0] = 1.0  # an isotropic source at x = 2
    vis = np.ones((6, r, r, r), np.float32)
    vis[:, 6] = 0.0  # cells at x = 6 send nothing on
    res = propagation.propagate(inj, 0, visibility=vis, angular="dom",
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


def test_the_engine_sweeps_whatever_the_iterations_setting():
    """Discrete ordinates always solve the limit of infinitely many steps: the stats say
    "sweep" and the image is the same bits with iterations 0 (automatic) and 48 (a setting
    for "sh" only, which the add-on can still hold)."""
    out = {}
    for iterations in (0, 48):
        settings = GISettings(grid_resolution=12, iterations=iterations, backend="numpy")
        sc = demo.cornell_box("SPOT", (24, 24), settings)
        stats = engine.Stats()
        res = engine.Engine().update(sc, stats)
        out[iterations] = (res, stats)
        assert stats.info["iterations"] == ["sweep"]
    np.testing.assert_array_equal(out[0][0].values, out[48][0].values)
