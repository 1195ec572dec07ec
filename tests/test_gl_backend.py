"""The GL compute backend (lpv_core/gl: dom propagation and its 9-coefficient lookup) against the
CPU path the engine runs (runs on Mesa llvmpipe: no GPU needed).

Propagation. The CPU solves the dom transport for infinitely many steps (a sweep); GL steps.
Run to the end (no early stop, enough steps for every ordinate to leave the grid) the two are
the same light: assert_allclose(gl, cpu, rtol=1e-4, atol=1e-4 x max|cpu|). With the engine's
early stop (a step moved < min_fraction of the injected flux) GL leaves out the tail of the
series, and the bound follows from the stopping rule: the tail is non-negative flux, each later
step moves at most what step k did (a step never gains flux), and an ordinate leaves the grid
after at most 3 (R - 1) steps that move it (``_tail_bound``). So the GL grid is the CPU grid
less some non-negative flux per direction D: its band 0 is Y0 D short, and every coefficient
differs in sum by at most max|Y_l| D (``_assert_short_by_a_tail``). Figures print with -s.
"""

import math
from types import SimpleNamespace

import numpy as np
import pytest

from lpv_core import engine, injection, lookup, propagation, sh
from lpv_core.grid import Grid
from lpv_core.propagation import ordinates
from lpv_core.render import deferred
from lpv_core.scene import GISettings
from tools import core_scenes as demo

RTOL = 1e-4


@pytest.fixture(scope="module")
def be(gl):
    return gl.backend()


def _agree(got, ref, what=""):
    got = np.asarray(got, np.float64)
    ref = np.asarray(ref, np.float64)
    assert got.shape == ref.shape, (what, got.shape, ref.shape)
    scale = float(np.abs(ref).max()) if ref.size else 0.0
    err = float(np.abs(got - ref).max()) / scale if scale > 0 else float(np.abs(got).max())
    print(f"{what}: max|gl-cpu|/max|cpu| = {err:.2e}")
    np.testing.assert_allclose(got, ref, rtol=RTOL, atol=RTOL * scale, err_msg=what)


def _grid(r, seed=0, far=False):
    rng = np.random.default_rng(seed)
    origin = rng.uniform(-3.0, 3.0, 3) + (np.array([1e5, -1e5, 3e4]) if far else 0.0)
    return Grid(tuple(origin), float(rng.uniform(0.05, 0.7)), r)


def _vpls(grid, n, rng):
    r = grid.resolution
    pos = grid.origin_array + rng.uniform(0.0, r, (n, 3)) * grid.cell_size
    nrm = rng.normal(size=(n, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    flux = rng.uniform(0.0, 2.0, (n, 3)) * rng.choice([1e-3, 1.0, 10.0], (n, 1))
    return pos, nrm, flux


def _visibility(r, rng):
    """(6, R, R, R) face transmittances: random, with fully blocking and open faces."""
    vis = rng.uniform(0.0, 1.0, (6, r, r, r)).astype(np.float32)
    vis[rng.uniform(size=vis.shape) < 0.2] = 0.0
    vis[rng.uniform(size=vis.shape) < 0.3] = 1.0
    return vis


def _case(r, seed, occluded=True, passing=False):
    """An injected grid, the propagate keywords the engine passes (light launched from its
    surfaces, every step occluded) and the grid."""
    g = _grid(r, seed)
    rng = np.random.default_rng(seed)
    injected = injection.inject(g, *_vpls(g, 1200, rng))
    kw = {"angular": "dom", "launch": True, "occlude_first_step": True,
          "visibility": _visibility(r, rng) if occluded else None}
    if passing:  # light handed on from a finer cascade
        kw["passing"] = 0.3 * injection.inject(g, *_vpls(g, 300, rng))
    return g, injected, kw


def _drain_steps(r: int, eps: float = 1e-9) -> int:
    """Steps after which less than ``eps`` of any launched light is still in an R^3 grid.

    Per step an ordinate's flux stays in its cell with the weight p0 = prod(1 - |w_a|) and
    otherwise moves one cell along at least one axis; after 3 (R - 1) moves some axis has
    left the grid. So the share still inside after n steps is at most
    P(Binomial(n, 1 - p0) <= 3 (R - 1))."""
    p0 = float(np.prod(1.0 - np.abs(ordinates.tables()[0].astype(np.float64)), axis=1).max())
    moves = 3 * (r - 1)
    n = moves
    while _still_inside(n, moves, p0) > eps:
        n += 1
    return n


def _still_inside(n: int, moves: int, p0: float) -> float:
    return sum(math.comb(n, j) * (1 - p0) ** j * p0 ** (n - j) for j in range(min(moves, n) + 1))


def _tail_bound(r: int, res) -> float:
    """Upper bound on the flux the early stop left out, as a share of the injected flux, from
    what the stopping rule saw: step k (= res.iterations) moved res.remaining_fraction; every
    later step moves at most that, and at most the share still inside after it."""
    p0 = float(np.prod(1.0 - np.abs(ordinates.tables()[0].astype(np.float64)), axis=1).max())
    k, moves = res.iterations, 3 * (r - 1)
    return sum(min(res.remaining_fraction, _still_inside(i - 1, moves, p0))
               for i in range(k + 1, _drain_steps(r) + 1))


def _assert_short_by_a_tail(got, ref, bound, what):
    """got = ref less non-negative flux per direction D, D <= bound x the injected flux."""
    ymax = np.abs(sh.evaluate_basis2(ordinates.tables()[0].astype(np.float64))).max(axis=0)
    band0 = ref.values[..., 0].sum(axis=(0, 1, 2), dtype=np.float64)
    missing = (band0 - got.values[..., 0].sum(axis=(0, 1, 2), dtype=np.float64)) / sh.Y0
    injected = ref.injected_flux.astype(np.float64)
    share = missing / injected
    print(f"{what}: {got.iterations} steps, last moved {got.remaining_fraction:.2e}; left out "
          f"{share.max():.2e} of the injected flux (bound {bound:.2e})")
    slack = 1e-5 * injected
    assert (missing >= -slack).all() and (missing <= bound * injected + slack).all(), what
    diff = np.abs(got.values.astype(np.float64) - ref.values).sum(axis=(0, 1, 2, 3))
    scale = np.abs(ref.values.astype(np.float64)).sum(axis=(0, 1, 2, 3))
    explained = ymax * np.maximum(missing, 0.0).sum()
    assert (diff <= explained + 1e-5 * scale).all(), (what, diff, explained)


@pytest.mark.parametrize("capture_outflow", [False, True])
@pytest.mark.parametrize("passing", [False, True])
@pytest.mark.parametrize("occluded", [False, True])
def test_dom_steps_converge_to_the_sweep(be, capture_outflow, passing, occluded):
    """Stepped until every ordinate has left the grid, GL's light is the sweep's."""
    r = 11
    _g, injected, kw = _case(r, 41, occluded, passing)
    kw["capture_outflow"] = capture_outflow
    before = be.fallbacks
    ref = propagation.propagate(injected, **kw)
    got = be.propagate(injected, _drain_steps(r), 0.0, **kw)
    assert be.fallbacks == before  # the shaders ran, not the CPU code
    assert got.values.shape == ref.values.shape == (r, r, r, 3, sh.BANDS2)
    assert got.values.dtype == np.float32
    what = f"dom occluded={occluded} passing={passing} outflow={capture_outflow}"
    _agree(got.values, ref.values, what)
    _agree(got.values[..., 4:], ref.values[..., 4:], what + " band 2")
    if capture_outflow:
        assert got.outflow.shape == ref.outflow.shape == (r + 2, r + 2, r + 2, 3, 4)
        _agree(got.outflow, ref.outflow, what + " outflow")
    else:
        assert got.outflow is None and ref.outflow is None
    np.testing.assert_allclose(got.injected_flux, ref.injected_flux, rtol=1e-6)


@pytest.mark.parametrize(("r", "occluded"), [(8, False), (11, True), (16, True)])
def test_early_stop_leaves_out_only_the_tail(be, r, occluded):
    """The engine's stop (min_fraction 1e-3, capped at engine.auto_iterations): GL's grid is the
    sweep's less a tail within the bound the stopping rule gives."""
    _g, injected, kw = _case(r, 7 + r, occluded)
    ref = propagation.propagate(injected, **kw)
    got = be.propagate(injected, engine.auto_iterations(r), 1e-3, **kw)
    assert got.stopped_early and got.remaining_fraction < 1e-3
    _assert_short_by_a_tail(got, ref, _tail_bound(r, got), f"early stop {r}^3 vis={occluded}")


def test_propagation_edge_cases(be):
    r = 9
    _g, injected, kw = _case(r, 3)
    ref = propagation.propagate(injected, **kw)
    none = be.propagate(injected, 0, **kw)  # no step: the injected light only
    assert (none.iterations, none.stopped_early) == (0, False)
    np.testing.assert_allclose(none.values[..., :4], injected, rtol=1e-6)
    one = be.propagate(injected, 1, **kw)  # the host's launch only
    assert one.iterations == 1 and one.remaining_fraction > 1e-3
    assert (one.values[..., 0].sum() < ref.values[..., 0].sum())
    zero = be.propagate(np.zeros_like(injected), 5, **kw)
    assert (zero.iterations, zero.stopped_early, zero.remaining_fraction) == (0, True, 0.0)
    assert not zero.values.any()


def test_what_gl_does_not_run_is_the_cpu_code(be):
    """KD10's "sh", dom light that was not launched from surfaces and a 4-coefficient lookup
    run the CPU code, counted in fallbacks; the injection is the CPU's."""
    r = 8
    g, injected, kw = _case(r, 8)
    before = be.fallbacks
    sh_kw = {"angular": "sh", "visibility": kw["visibility"]}
    np.testing.assert_array_equal(be.propagate(injected, 3, **sh_kw).values,
                                  propagation.propagate(injected, 3, **sh_kw).values)
    plain = dict(kw, launch=False)
    np.testing.assert_array_equal(be.propagate(injected, 3, **plain).values,
                                  propagation.propagate(injected, 3, **plain).values)
    rng = np.random.default_rng(8)
    pos, nrm, flux = _vpls(g, 500, rng)
    e = be.irradiance(g, injected, pos, nrm, angular="sh")
    np.testing.assert_array_equal(e, lookup.irradiance(g, injected, pos, nrm, angular="sh"))
    assert be.fallbacks == before + 3
    np.testing.assert_array_equal(be.inject(g, pos, nrm, flux), injection.inject(g, pos, nrm, flux))


@pytest.mark.parametrize(("r", "far"), [(6, False), (13, True), (19, False)])
def test_lookup_of_bands_0_to_2_agrees(be, r, far):
    """The irradiance of a 9-coefficient grid (lookup.irradiance: trilinear, corners behind
    occluders left out, the band 0-2 kernel), receivers in and around the grid."""
    g = _grid(r, 40 + r, far)
    rng = np.random.default_rng(r)
    values = rng.normal(size=(r, r, r, 3, sh.BANDS2)).astype(np.float32)
    values[..., 0] = np.abs(values[..., 0]) * 3.0
    m = 4000
    pos = g.origin_array + rng.uniform(-1.0, r + 1.0, (m, 3)) * g.cell_size
    nrm = rng.normal(size=(m, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    vis = _visibility(r, rng)
    before = be.fallbacks
    for v in (None, vis):
        for offset in (lookup.OFFSET_CELLS, 0.0):
            ref = lookup.irradiance(g, values, pos, nrm, offset, angular="dom", visibility=v)
            got = be.irradiance(g, values, pos, nrm, offset, angular="dom", visibility=v)
            assert got.dtype == ref.dtype and got.shape == ref.shape == (m, 3)
            assert (ref > 0).any() and (ref == 0).any()  # clamped somewhere, lit elsewhere
            _agree(got, ref, f"irradiance {r}^3 far={far} occluded={v is not None} "
                             f"offset={offset}")
    assert be.fallbacks == before
    assert be.irradiance(g, values, pos[:0], nrm[:0]).shape == (0, 3)
    with pytest.raises(ValueError):
        be.irradiance(g, values[:-1], pos, nrm)


def test_cornell_box_end_to_end(gl, be):
    """The engine on backend "gl" against "numpy" at the defaults (one cascade: the Cornell box
    is enclosed): the same light less the early stop's tail; the lookup of GL's grid agrees."""
    settings = GISettings(grid_resolution=24, rsm_resolution=96, shadow_resolution=128,
                          cascades=1)
    eng = engine.Engine()
    results = {}
    for name in ("numpy", "gl"):
        scene = demo.cornell_box("SPOT", (48, 48), settings.updated(backend=name))
        results[name] = eng.update(scene)
        assert results[name].stats.info["backend"] == name
    ref, got = results["numpy"], results["gl"]
    assert ref.stats.info["iterations"] == ["sweep"]
    steps = got.stats.info["iterations"]
    assert len(steps) == 1 and 1 < steps[0] < engine.auto_iterations(24)
    for light in ref.per_light:
        cpu, mine = ref.per_light[light], got.per_light[light]
        # upper bounds where the engine keeps no figure: the injected flux is at most all the
        # light the sweep's grid holds, the last step moved less than the stopping rule's 1e-3
        injected = cpu[..., 0].sum(axis=(0, 1, 2), dtype=np.float64) / sh.Y0
        stop = SimpleNamespace(values=mine, iterations=steps[0], remaining_fraction=1e-3)
        _assert_short_by_a_tail(stop, SimpleNamespace(values=cpu, injected_flux=injected),
                                _tail_bound(24, stop), f"Cornell box '{light}'")
    frame = eng.raster.render(scene.camera.view, scene.camera.projection, 48, 48)
    pos = frame.position[frame.covered]
    nrm = frame.normal[frame.covered].astype(np.float64)
    _agree(be.irradiance(got.grid, got.values, pos, nrm),
           lookup.irradiance(got.grid, got.values, pos, nrm), "Cornell box G-buffer irradiance")
    passes = deferred.render(eng, scene, got)
    assert np.isfinite(passes["Diffuse Indirect"]).all()


def test_engine_backend_choice(gl, be):
    eng = engine.Engine()
    settings = GISettings()
    assert eng.backend(settings.updated(backend="numpy")) is engine.NUMPY_BACKEND
    assert eng.backend(settings.updated(backend="gl")).name == "gl"
    with pytest.raises(ValueError, match="backend"):
        eng.backend(settings.updated(backend="cuda"))
    mixed = gl.MixedBackend({"propagate": "gl", "lookup": "numpy"},
                            {"numpy": engine.NUMPY_BACKEND, "gl": be})
    _g, injected, kw = _case(9, 11)
    got = mixed.propagate(injected, 3 * 9, 0.0, **kw)
    assert got.iterations > 1  # GL's steps
    _agree(got.values, propagation.propagate(injected, **kw).values, "mixed backend")
