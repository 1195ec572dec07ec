"""The moderngl compute backend against the numpy reference (runs on Mesa llvmpipe: no GPU).

Agreement is checked as assert_allclose(gl, numpy, rtol=1e-4, atol=1e-4 x max|numpy|): every
value within 1e-4 of itself or of the grid's largest value (values that cancel to near zero
can only be compared to the grid's scale). The figures are printed (pytest -s).
"""

import numpy as np
import pytest

from lpv_core import engine, injection, lookup, propagation
from lpv_core.grid import Grid
from lpv_core.render import deferred
from lpv_core.scene import GISettings, demo

RTOL = 1e-4



def _agree(got, ref, what=""):
    got = np.asarray(got, np.float64)
    ref = np.asarray(ref, np.float64)
    assert got.shape == ref.shape, (what, got.shape, ref.shape)
    scale = float(np.abs(ref).max()) if ref.size else 0.0
    err = float(np.abs(got - ref).max()) / scale if scale > 0 else float(np.abs(got).max())
    big = np.abs(ref) > 1e-2 * scale
    elem = float((np.abs(got - ref)[big] / np.abs(ref)[big]).max()) if big.any() else 0.0
    print(f"{what}: max|gl-np|/max|np| = {err:.2e}, max rel (|np| > 1% max) = {elem:.2e}")
    np.testing.assert_allclose(got, ref, rtol=RTOL, atol=RTOL * scale, err_msg=what)
    return err


def _vpls(grid, n, rng, spread=1.0):
    """n random VPLs, some near or beyond the grid's border (their flux partly leaves)."""
    r = grid.resolution
    lo = grid.origin_array - spread * grid.cell_size
    pos = lo + rng.uniform(0.0, r + 2 * spread, (n, 3)) * grid.cell_size
    nrm = rng.normal(size=(n, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    flux = rng.uniform(0.0, 2.0, (n, 3)) * rng.choice([1e-3, 1.0, 10.0], (n, 1))
    return pos, nrm, flux


def _grid(r, seed=0, far=False):
    rng = np.random.default_rng(seed)
    origin = rng.uniform(-3.0, 3.0, 3) + (np.array([1e5, -1e5, 3e4]) if far else 0.0)
    return Grid(tuple(origin), float(rng.uniform(0.05, 0.7)), r)


def _visibility(r, rng):
    """(6, R, R, R) face transmittances: random, with fully blocking walls."""
    vis = rng.uniform(0.0, 1.0, (6, r, r, r)).astype(np.float32)
    vis[rng.uniform(size=vis.shape) < 0.2] = 0.0
    vis[rng.uniform(size=vis.shape) < 0.3] = 1.0
    return vis


def _injected_case(r, seed, n):
    """An R^3 grid, its random generator (for what the caller draws next), N VPLs and their
    injected grid."""
    g = _grid(r, seed=seed)
    rng = np.random.default_rng(seed)
    pos, nrm, flux = _vpls(g, n, rng, spread=0.0)
    return g, rng, pos, nrm, flux, injection.inject(g, pos, nrm, flux)


def _lookup_case(r, seed, far, coefficients, m):
    """A random grid (R, R, R, 3, K) with positive band 0, M receivers (some outside the grid)
    with unit normals, and a random visibility."""
    g = _grid(r, seed=seed, far=far)
    rng = np.random.default_rng(seed)
    values = rng.normal(size=(r, r, r, 3, coefficients)).astype(np.float32)
    values[..., 0] = np.abs(values[..., 0]) * 3.0
    pos = g.origin_array + rng.uniform(-1.0, r + 1.0, (m, 3)) * g.cell_size
    nrm = rng.normal(size=(m, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    return g, values, pos, nrm, _visibility(r, rng)


@pytest.mark.parametrize("occluded", [False, True])
@pytest.mark.parametrize("r", [5, 8, 13, 16, 32])
def test_injection_agrees(gl, r, occluded):
    g = _grid(r, seed=r)
    rng = np.random.default_rng(r)
    pos, nrm, flux = _vpls(g, 3000, rng)
    vis = _visibility(r, rng) if occluded else None
    if occluded:  # boxed-in points (every corner hidden) keep their plain weights
        vis[:, :2] = 0.0
    ref = injection.inject(g, pos, nrm, flux, visibility=vis)
    got = gl.inject(g, pos, nrm, flux, visibility=vis)
    assert got.dtype == np.float32 and got.shape == ref.shape
    _agree(got, ref, f"inject {r}^3 occluded={occluded}")
    np.testing.assert_allclose(propagation.flux(got), propagation.flux(ref), rtol=1e-6)


def test_injection_is_exact_and_order_independent_at_any_scale(gl):
    g = _grid(12, seed=4, far=True)  # 1e5 m from the origin
    rng = np.random.default_rng(4)
    pos, nrm, flux = _vpls(g, 4000, rng, spread=0.0)
    first = gl.inject(g, pos, nrm, flux)
    perm = rng.permutation(len(pos))
    again = gl.inject(g, pos[perm], nrm[perm], flux[perm])
    np.testing.assert_array_equal(first, again)  # integer sums: no order dependence
    for k in (1e-9, 1e8):  # the fixed-point scale follows the flux
        _agree(gl.inject(g, pos, nrm, flux * k), injection.inject(g, pos, nrm, flux * k),
               f"inject flux x {k:g}")
    empty = gl.inject(g, pos[:0], nrm[:0], flux[:0])
    assert empty.shape == g.shape and not empty.any()


MODELS = [("sh", "kd10"), ("sh", "ray"), ("m1", "kd10")]  # (angular, reprojection)
# "dom" (ordinates.py) has no step on moments, only a propagation.
PROPAGATION_MODELS = MODELS + [("dom", "kd10")]


@pytest.mark.parametrize(("angular", "reprojection"), MODELS)
@pytest.mark.parametrize("occluded", [False, True])
@pytest.mark.parametrize("r", [5, 12, 17])
def test_step_agrees(gl, angular, reprojection, occluded, r):
    rng = np.random.default_rng(r)
    values = rng.normal(size=(r, r, r, 3, 4)).astype(np.float32)
    values[..., 0] = np.abs(values[..., 0]) * 2.0  # mostly positive band 0, peaked lobes too
    values[0, 1, 2] = 0.0  # empty cells send nothing
    values[1, 1, 1, :, 0] = -0.5  # negative band 0: nothing either
    vis = rng.uniform(0.0, 1.0, (6, r, r, r)).astype(np.float32) if occluded else None
    ref = propagation.step(values, vis, reprojection, angular)
    got = gl.step(values, vis, reprojection, angular)
    _agree(got, ref, f"step {r}^3 {angular}/{reprojection} vis={occluded}")


@pytest.mark.parametrize("occluded", [False, True])
def test_emission_step_agrees(gl, occluded):
    """The first step's reading of just-emitted light (closure.emission_density), m1."""
    r = 9
    rng = np.random.default_rng(3)
    values = rng.normal(size=(r, r, r, 3, 4)).astype(np.float32)
    values[..., 0] = np.abs(values[..., 0]) * 2.0
    values[2, 2, 2] = 0.0
    vis = rng.uniform(0.0, 1.0, (6, r, r, r)).astype(np.float32) if occluded else None
    ref = propagation.step(values, vis, angular="m1", emission=True)
    got = gl.step(values, vis, angular="m1", emission=True)
    _agree(got, ref, f"emission step vis={occluded}")
    assert not np.allclose(ref, propagation.step(values, vis, angular="m1"))  # it differs


def test_step_never_gains_energy(gl):
    rng = np.random.default_rng(7)
    values = rng.normal(size=(6, 6, 6, 3, 4)).astype(np.float32)
    values[..., 0] = np.abs(values[..., 0])
    for angular, reprojection in MODELS:
        out = gl.step(values, reprojection=reprojection, angular=angular)
        assert (propagation.flux(out) <= propagation.flux(values) * (1 + 1e-6)).all()


@pytest.mark.parametrize(("angular", "reprojection"), PROPAGATION_MODELS)
@pytest.mark.parametrize("occluded", [None, "first step open", "all steps"])
@pytest.mark.parametrize("r", [7, 16, 20])
def test_propagation_agrees(gl, angular, reprojection, occluded, r):
    g = _grid(r, seed=r)
    rng = np.random.default_rng(100 + r)
    injected = injection.inject(g, *_vpls(g, 2000, rng, spread=0.0))
    vis = rng.uniform(0.3, 1.0, (6, r, r, r)).astype(np.float32) if occluded else None
    kw = {"visibility": vis, "reprojection": reprojection, "angular": angular}
    if occluded == "all steps":
        kw["occlude_first_step"] = True
    ref = propagation.propagate(injected, r // 2, **kw)
    got = gl.propagate(injected, r // 2, **kw)
    _agree(got.values, ref.values, f"propagate {r}^3 x {ref.iterations} {angular}/"
                                   f"{reprojection} occlusion: {occluded}")
    assert got.iterations == ref.iterations
    assert got.stopped_early == ref.stopped_early
    assert got.remaining_fraction == pytest.approx(ref.remaining_fraction, rel=RTOL)
    np.testing.assert_allclose(got.injected_flux, ref.injected_flux, rtol=1e-5)  # f32 sums


@pytest.mark.parametrize("capture_outflow", [False, True])
@pytest.mark.parametrize("passing", [False, True])
def test_launched_dom_propagation_agrees(gl, capture_outflow, passing):
    """Light launched from its surfaces (ordinates.launch, computed on the host) and, in a
    coarser cascade, light handed on from a finer one: GL steps on from the launch and agrees
    with numpy's steps, without falling back."""
    r = 11
    g, rng, _pos, _nrm, _flux, injected = _injected_case(r, 41, 1200)
    kw = {"visibility": _visibility(r, rng), "angular": "dom", "occlude_first_step": True,
          "capture_outflow": capture_outflow, "launch": True}
    if passing:
        kw["passing"] = 0.3 * injection.inject(g, *_vpls(g, 300, rng, spread=0.0))
    be = gl.backend()
    before = be.fallbacks
    ref = propagation.propagate(injected, 9, min_fraction=0.0, **kw)
    got = be.propagate(injected, 9, min_fraction=0.0, **kw)
    assert be.fallbacks == before
    assert got.iterations == ref.iterations == 9
    _agree(got.values, ref.values, f"launched dom, passing {passing}")
    if capture_outflow:
        _agree(got.outflow, ref.outflow, f"launched dom outflow, passing {passing}")
    np.testing.assert_allclose(got.injected_flux, ref.injected_flux, rtol=1e-5)


def test_propagation_early_stop_and_edge_cases_agree(gl):
    g = _grid(10, seed=3)
    rng = np.random.default_rng(3)
    injected = injection.inject(g, *_vpls(g, 500, rng, spread=0.0))
    for kw in ({"iterations": 50, "min_fraction": 0.05}, {"iterations": 0},
               {"iterations": 3, "min_fraction": 0.0},
               {"iterations": 50, "min_fraction": 0.05, "angular": "m1"},
               {"iterations": 50, "min_fraction": 0.05, "angular": "dom"},
               {"iterations": 0, "angular": "dom"},
               {"iterations": 3, "min_fraction": 0.0, "angular": "dom"}):
        ref = propagation.propagate(injected, **kw)
        got = gl.propagate(injected, **kw)
        assert (got.iterations, got.stopped_early) == (ref.iterations, ref.stopped_early), kw
        assert got.remaining_fraction == pytest.approx(ref.remaining_fraction, rel=RTOL), kw
        _agree(got.values, ref.values, f"propagate {kw}")
    zero = np.zeros_like(injected)
    for iterations, angular in ((0, "sh"), (4, "sh"), (0, "dom"), (4, "dom")):
        ref = propagation.propagate(zero, iterations, angular=angular)
        got = gl.propagate(zero, iterations, angular=angular)
        assert (got.iterations, got.stopped_early, got.remaining_fraction) == \
            (ref.iterations, ref.stopped_early, ref.remaining_fraction)
        assert not got.values.any()
    with pytest.raises(ValueError):
        gl.propagate(injected, 2, reprojection="nope")


def test_propagation_stays_on_the_gpu_between_stages(gl):
    be = gl.backend()
    g = _grid(9, seed=9)
    pos, nrm, flux = _vpls(g, 800, np.random.default_rng(9), spread=0.0)
    on_gpu = be.inject(g, pos, nrm, flux)  # a GLGrid: no readback
    assert isinstance(on_gpu, gl.GLGrid)
    res = be.propagate(on_gpu, 4, readback=False, keep_gpu=True)
    assert res.values is None and isinstance(res.gpu, gl.GLGrid)
    ref = propagation.propagate(injection.inject(g, pos, nrm, flux), 4)
    _agree(res.gpu.read(), ref.values, "inject -> propagate on the GPU")
    on_gpu.release()
    res.gpu.release()


@pytest.mark.parametrize("r", [6, 16, 19])
def test_lookup_agrees(gl, r):
    g, values, pos, nrm, vis = _lookup_case(r, r, r == 19, 4, 5000)
    _agree(gl.sample(g, values, pos), lookup.sample(g, values, pos), f"sample {r}^3")
    _agree(gl.sample(g, values, pos, vis), lookup.sample(g, values, pos, vis),
           f"sample {r}^3 occluded")
    for angular in ("sh", "m1", "dom"):  # "dom" grids are read as "m1" (closure.LOBE_MODELS)
        for v in (None, vis):
            ref = lookup.irradiance(g, values, pos, nrm, angular=angular, visibility=v)
            got = gl.irradiance(g, values, pos, nrm, angular=angular, visibility=v)
            assert got.dtype == ref.dtype and got.shape == ref.shape
            _agree(got, ref, f"irradiance {r}^3 {angular} occluded={v is not None}")
    assert gl.irradiance(g, values, pos[:0], nrm[:0]).shape == (0, 3)


@pytest.mark.parametrize("angular", ["sh", "m1", "dom"])
def test_cornell_box_end_to_end_agrees(gl, angular):
    # Engine defaults otherwise (occlusion by the geometry volume, direction groups).
    settings = GISettings(grid_resolution=24, rsm_resolution=96, shadow_resolution=128,
                          angular=angular, iterations=12)
    results = {}
    eng = engine.Engine()
    for backend in ("numpy", "gl"):
        scene = demo.cornell_box("SPOT", (48, 48), settings.updated(backend=backend))
        res = eng.update(scene)
        assert res.stats.info["backend"] == backend
        results[backend] = (scene, res)
    (scene, ref), (_, got) = results["numpy"], results["gl"]
    assert got.stats.info["iterations"] == ref.stats.info["iterations"]
    assert got.per_light.keys() == ref.per_light.keys()
    for name in ref.per_light:
        _agree(got.per_light[name], ref.per_light[name], f"Cornell box {angular} light '{name}'")
    _agree(got.values, ref.values, f"Cornell box {angular} LPV")
    # Lookup on the camera's G-buffer through both backends.
    frame = eng.raster.render(scene.camera.view, scene.camera.projection, 48, 48)
    pos = frame.position[frame.covered]
    nrm = frame.normal[frame.covered].astype(np.float64)
    e_ref = lookup.irradiance(ref.grid, ref.values, pos, nrm, angular=angular)
    e_gl = eng.backend(scene.settings.updated(backend="gl")).irradiance(
        got.grid, got.values, pos, nrm, angular=angular)
    _agree(e_gl, e_ref, f"Cornell box {angular} G-buffer irradiance")
    passes = deferred.render(eng, scene, got)
    assert np.isfinite(passes["Diffuse Indirect"]).all()


def test_engine_backend_choice(gl):
    eng = engine.Engine()
    settings = GISettings()
    assert eng.backend(settings.updated(backend="numpy")).name == "numpy"
    assert eng.backend(settings.updated(backend="gl")).name == "gl"
    stats = engine.Stats()
    chosen = eng.backend(settings.updated(backend="auto"), stats)
    auto = stats.info["backend_auto"]
    print(f"auto backend on this machine: {auto}")
    assert auto["backend"] in ("numpy", "gl", "mixed")
    assert set(auto["stages"].values()) <= {"numpy", "gl"}
    assert chosen.name == stats.info["backend"]
    if auto["backend"] != "mixed":
        assert chosen.name == auto["backend"]
    assert auto["angular"] == settings.angular
    assert gl.auto_backend(angular=settings.angular) is gl.auto_backend(angular=settings.angular)
    # A mixed choice hands grids across (GL -> numpy by readback) and agrees with numpy.
    mixed = gl.MixedBackend({"inject": "gl", "propagate": "numpy", "lookup": "gl"},
                            {"numpy": engine.NUMPY_BACKEND, "gl": gl.backend()})
    g = _grid(9, seed=11)
    pos, nrm, flux = _vpls(g, 500, np.random.default_rng(11), spread=0.0)
    injected = mixed.inject(g, pos, nrm, flux)
    prop = mixed.propagate(injected, 3)
    mixed.discard(injected)
    _agree(prop.values, propagation.propagate(injection.inject(g, pos, nrm, flux), 3).values,
           "mixed backend")
    with pytest.raises(ValueError, match="backend"):
        eng.backend(settings.updated(backend="cuda"))


def test_auto_choice_needs_a_clear_margin(gl):
    """A near tie goes to numpy (the reference); gl is picked where it is clearly faster."""
    ms = {"inject": {"numpy": 50.0, "gl": 40.0}, "propagate": {"numpy": 90.0, "gl": 30.0},
          "lookup": {"numpy": 10.0, "gl": 12.0}}
    assert gl.choose(ms) == {"inject": "numpy", "propagate": "gl", "lookup": "numpy"}


def test_options_not_ported_fall_back_to_numpy(gl):
    be = gl.backend()
    g = _grid(8, seed=8)
    injected = injection.inject(g, *_vpls(g, 300, np.random.default_rng(8), spread=0.0))
    before = be.fallbacks
    ref = propagation.propagate(injected, 3, capture_outflow=True)
    got = gl.propagate(injected, 3, capture_outflow=True)
    assert be.fallbacks == before + 1
    _agree(got.values, ref.values, "propagate capture_outflow (numpy fallback)")
    np.testing.assert_array_equal(got.outflow, ref.outflow)
    with pytest.raises(ValueError):
        gl.step(injected, angular="nope")


def test_dom_runs_on_the_gpu(gl):
    """angular="dom": propagation (also capture_outflow, GPU grids in and out) and lookup run
    the shaders, not the numpy code; a single step on moments is refused as numpy does."""
    be = gl.backend()
    r = 9
    g, rng, pos, nrm, flux, injected = _injected_case(r, 21, 800)
    vis = _visibility(r, rng)
    before = be.fallbacks
    for kw in ({}, {"visibility": vis}, {"visibility": vis, "occlude_first_step": True}):
        ref = propagation.propagate(injected, 6, capture_outflow=True, angular="dom", **kw)
        got = gl.propagate(injected, 6, capture_outflow=True, angular="dom", **kw)
        assert (got.iterations, got.stopped_early) == (ref.iterations, ref.stopped_early)
        assert got.remaining_fraction == pytest.approx(ref.remaining_fraction, rel=RTOL)
        _agree(got.values, ref.values, f"dom capture_outflow {list(kw)}")
        _agree(got.outflow, ref.outflow, f"dom outflow {list(kw)}")
    on_gpu = be.inject(g, pos, nrm, flux)
    res = be.propagate(on_gpu, 4, angular="dom", readback=False, keep_gpu=True)
    assert res.values is None and isinstance(res.gpu, gl.GLGrid)
    ref = propagation.propagate(injected, 4, angular="dom")
    _agree(res.gpu.read(), ref.values, "dom inject -> propagate on the GPU")
    recv = g.origin_array + rng.uniform(0.0, r, (500, 3)) * g.cell_size
    rn = rng.normal(size=(500, 3))
    rn /= np.linalg.norm(rn, axis=1, keepdims=True)
    _agree(be.irradiance(g, res.gpu, recv, rn, angular="dom"),
           lookup.irradiance(g, ref.values, recv, rn, angular="dom"), "dom lookup of a GLGrid")
    on_gpu.release()
    res.gpu.release()
    assert be.fallbacks == before
    with pytest.raises(ValueError, match="dom"):
        propagation.step(injected, angular="dom")
    with pytest.raises(ValueError, match="dom"):
        gl.step(injected, angular="dom")


@pytest.mark.parametrize("occluded", [False, True])
def test_dom_values_hold_bands_0_to_2(gl, occluded):
    """angular="dom" folds into bands 0-2 (R, R, R, 3, 9): the propagated flux plus the
    injected grid extended to band 2 (ordinates.emission_band2); the outflow stays 4 moments.
    Each band is compared on its own scale (band 2 is smaller than band 0)."""
    be = gl.backend()
    r = 11
    g, rng, pos, nrm, flux, injected = _injected_case(r, 31, 1500)
    vis = _visibility(r, rng) if occluded else None
    before = be.fallbacks
    for kw in ({"iterations": 7}, {"iterations": 0}, {"iterations": 5, "capture_outflow": True},
               {"iterations": 5, "capture_outflow": True, "occlude_first_step": True}):
        ref = propagation.propagate(injected, angular="dom", visibility=vis, **kw)
        got = be.propagate(injected, angular="dom", visibility=vis, **kw)
        assert ref.values.shape == got.values.shape == (r, r, r, 3, 9)
        assert got.values.dtype == np.float32
        assert np.abs(ref.values[..., 4:]).max() > 1e-3 * np.abs(ref.values).max()  # band 2 held
        what = f"dom bands 0-2 vis={occluded} {kw}"
        _agree(got.values, ref.values, what)
        _agree(got.values[..., 4:], ref.values[..., 4:], what + " band 2")
        if kw.get("capture_outflow"):
            assert got.outflow.shape == ref.outflow.shape == (r + 2, r + 2, r + 2, 3, 4)
            _agree(got.outflow, ref.outflow, what + " outflow")
        else:
            assert got.outflow is None and ref.outflow is None
    # Kept on the GPU: a 9-coefficient GLGrid, read back and looked up as numpy's.
    on_gpu = be.inject(g, pos, nrm, flux)
    res = be.propagate(on_gpu, 5, angular="dom", visibility=vis, readback=False, keep_gpu=True)
    ref = propagation.propagate(injected, 5, angular="dom", visibility=vis)
    assert res.values is None and res.gpu.coefficients == 9 and res.gpu.shape == ref.values.shape
    assert res.gpu.nbytes == ref.values.nbytes
    _agree(res.gpu.read(), ref.values, "dom kept on the GPU")
    np.testing.assert_allclose(be.flux(res.gpu), propagation.flux(ref.values), rtol=1e-5)
    with pytest.raises(ValueError, match="coefficients"):  # propagation takes 4 moments
        be.propagate(res.gpu, 2, angular="dom")
    on_gpu.release()
    res.gpu.release()
    assert be.fallbacks == before + 1  # flux of a 9-coefficient grid: numpy after a readback


@pytest.mark.parametrize("r", [6, 13])
def test_lookup_of_bands_0_to_2_agrees(gl, r):
    """A 9-coefficient grid is read with sh.irradiance_weights whatever the angular model, on
    the GPU as in lookup.irradiance; sample returns (M, 3, 9)."""
    be = gl.backend()
    m = 4000
    g, values, pos, nrm, vis = _lookup_case(r, 40 + r, r == 13, 9, m)
    before = be.fallbacks
    on_gpu = be.upload(values)
    assert on_gpu.coefficients == 9 and on_gpu.shape == values.shape
    np.testing.assert_array_equal(on_gpu.read(), values)
    for v in (None, vis):
        occ = v is not None
        ref = lookup.sample(g, values, pos, v)
        got = be.sample(g, values, pos, v)
        assert got.shape == ref.shape == (m, 3, 9)
        _agree(got, ref, f"sample 9 coefficients {r}^3 occluded={occ}")
        for angular in ("sh", "m1", "dom"):
            ref = lookup.irradiance(g, values, pos, nrm, angular=angular, visibility=v)
            got = be.irradiance(g, values, pos, nrm, angular=angular, visibility=v)
            assert got.dtype == ref.dtype and got.shape == ref.shape == (m, 3)
            assert (ref > 0).any() and (ref == 0).any()  # clamped somewhere, lit elsewhere
            _agree(got, ref, f"irradiance 9 coefficients {r}^3 {angular} occluded={occ}")
        _agree(be.irradiance(g, on_gpu, pos, nrm, angular="dom", visibility=v),
               lookup.irradiance(g, values, pos, nrm, angular="dom", visibility=v),
               f"irradiance of a 9-coefficient GLGrid occluded={occ}")
    assert be.irradiance(g, values, pos[:0], nrm[:0]).shape == (0, 3)
    assert be.sample(g, values, pos[:0]).shape == (0, 3, 9)
    on_gpu.release()
    assert be.fallbacks == before
    with pytest.raises(ValueError):
        be.upload(values[..., :5])


def test_auto_measurement_runs_dom(gl):
    """measure() looks up a "dom" propagated grid (9 coefficients) on both backends."""
    ms = gl.measure(resolution=8, vpls=512, receivers=1024, iterations=2, repeat=1,
                    angular="dom")
    assert set(ms) == set(gl.STAGES)
    assert all(ms[stage][name] > 0 for stage in gl.STAGES for name in ("numpy", "gl"))
