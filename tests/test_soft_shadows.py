"""Area lights' unoccluded irradiance against closed forms, and soft shadows: a penumbra's
width against similar triangles, no acne on lit surfaces, and the compiled twin against the
numpy reference for every light with a size."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import surface_points

from lpv_core import engine
from lpv_core.render import direct
from lpv_core.runtime import jit
from lpv_core.scene import GISettings
from lpv_core.scene import lights as lights_mod
from lpv_core.scene.model import Light, make_scene
from tools.core_scenes import cornell_box, light_matrix, quad

POWER = 100.0


def _corner(a, b):
    """Form factor from a point to a parallel rectangle a x b (in units of the height) with
    one corner straight above it (Siegel & Howell, view factor C-11)."""
    s, t = np.sqrt(1 + a * a), np.sqrt(1 + b * b)
    return (a / s * np.arctan(b / s) + b / t * np.arctan(a / t)) / (2 * np.pi)


def _square_light(side, h, **kw):
    return Light("Panel", "AREA", light_matrix((0, 0, h), (0, 0, -1)), power=POWER,
                 size=(side, side), **kw)


@pytest.mark.parametrize("compiled", [False, True])
@pytest.mark.parametrize("h", [0.1, 0.5, 3.0])
def test_square_light_over_a_parallel_plane_is_the_form_factor(compiled, h):
    if compiled and not jit.enabled():
        pytest.skip("the kernels are off")
    a = 1.0
    light = _square_light(a, h)
    xy = np.array([[0, 0], [0.2, 0.1], [0.49, -0.3], [0.8, 0.6], [-1.5, 0.2]])
    pos = np.c_[xy, np.zeros(len(xy))]
    nrm = np.tile([0.0, 0.0, 1.0], (len(xy), 1))
    if compiled:
        got = direct.irradiance(light, pos, nrm)[:, 0]
    else:
        with jit.disabled():
            got = direct.irradiance(light, pos, nrm)[:, 0]
    radiance = POWER / (np.pi * a * a)  # Cycles: P / (pi A)
    want = []
    for x, y in xy:
        f = 0.0
        for sx in (1, -1):
            for sy in (1, -1):
                dx, dy = a / 2 - sx * x, a / 2 - sy * y  # signed: a corner beyond the point
                f += np.sign(dx) * np.sign(dy) * _corner(abs(dx) / h, abs(dy) / h)
        want.append(np.pi * radiance * f)
    np.testing.assert_allclose(got, want, rtol=1e-9)
    # the old point-at-the-centre model (I = P cos / pi) is far off in the near field
    point = POWER / np.pi / h**2
    if h <= 0.5:
        assert abs(got[0] / point - 1) > 0.2


def test_disk_light_over_a_parallel_plane_is_the_disk_form_factor():
    r, h = 0.5, 0.4
    light = Light("Disk", "AREA", light_matrix((0, 0, h), (0, 0, -1)), power=POWER,
                  size=(2 * r, 2 * r), shape="DISK")
    off = np.array([0.0, 0.3, 0.6, 1.2])
    pos = np.c_[off, np.zeros((4, 2))]
    nrm = np.tile([0.0, 0.0, 1.0], (4, 1))
    with jit.disabled():
        got = direct.irradiance(light, pos, nrm)[:, 0]
    radiance = POWER / (np.pi * np.pi * r * r)
    # point to a parallel coaxial-offset disk (Siegel & Howell, view factor B-? / C-41)
    f = 0.5 * (1 - (h * h + off**2 - r * r) / np.sqrt((h * h + off**2 + r * r) ** 2
                                                       - 4 * off**2 * r * r))
    np.testing.assert_allclose(got, np.pi * radiance * f, rtol=5e-3)  # the 32-gon of equal area


def test_emitter_below_the_horizon_is_clipped():
    """A receiver tilted so that part of the light is below its tangent plane gets the
    integral over the visible part only (a fine quadrature of cos cos / r^2)."""
    h, a = 0.3, 1.0
    light = _square_light(a, h)
    p = np.array([[0.2, 0.0, 0.2]])
    n = np.array([[-1.0, 0.0, 0.3]]) / np.sqrt(1.09)  # its horizon cuts the light at x = 0.23
    with jit.disabled():
        got = direct.irradiance(light, p, n)[0, 0]
    k = 600
    s = (np.arange(k) + 0.5) / k * a - a / 2
    q = np.stack(np.meshgrid(s, s), -1).reshape(-1, 2)
    d = np.c_[q, np.full(len(q), h)] - p
    r = np.linalg.norm(d, axis=1)
    w = d / r[:, None]
    want = POWER / (np.pi * a * a) * np.sum(np.maximum(w @ n[0], 0) * w[:, 2] / r**2) * (a / k) ** 2
    assert got == pytest.approx(want, rel=1e-3)


def test_spread_keeps_the_power_and_narrows_the_beam():
    light = _square_light(1.0, 1.0, spread=np.radians(60))
    tan_half, norm = lights_mod.spread_constants(light)
    t = (np.arange(20000) + 0.5) / 20000 * (np.pi / 2)
    att = np.maximum((tan_half - np.tan(t)) * norm, 0)
    # over the hemisphere, cos-weighted: pi, as an unlimited Lambertian emitter's
    assert np.sum(att * np.cos(t) * np.sin(t)) * 2 * np.pi * (np.pi / 2 / 20000) == \
        pytest.approx(np.pi, rel=1e-3)
    far = 30.0
    pos = np.array([[0.0, 0.0, -far + 1.0], [far * np.tan(np.radians(40)), 0, -far + 1.0]])
    nrm = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    with jit.disabled():
        e = direct.irradiance(light, pos, nrm)[:, 0]
    # against a fine quadrature of L att(t) cos cos / r^2 over the emitter (the patches take
    # att at their centres: 0.5 % here)
    k = 400
    s = (np.arange(k) + 0.5) / k - 0.5
    q = np.stack(np.meshgrid(s, s), -1).reshape(-1, 2)
    d = np.c_[q, np.ones(len(q))] - pos[0]
    r = np.linalg.norm(d, axis=1)
    cos = d[:, 2] / r
    quad_e = np.sum(np.maximum((tan_half - np.sqrt(1 - cos**2) / cos) * norm, 0) * cos**2
                    / r**2) / k**2 * POWER / np.pi
    assert e[0] == pytest.approx(quad_e, rel=5e-3)
    assert e[0] < 0.99 * POWER / np.pi * tan_half * norm / far**2  # att falls off the axis
    assert e[1] == 0.0  # 40 degrees off the axis: outside the 30 degree half spread


def _edge_scene(light):
    """A 6 m floor at z = 0 and an occluding plate at z = 1 over x < 0."""
    tris = np.concatenate([quad((-3, -3, 0), (3, -3, 0), (3, 3, 0), (-3, 3, 0)),
                           quad((-2, -1.5, 1), (0, -1.5, 1), (0, 1.5, 1), (-2, 1.5, 1))])
    scene = make_scene(tris, lights=[light], settings=GISettings())
    eng = engine.Engine()
    lo, hi = eng.upload(scene, engine.Stats())
    return eng, scene, (lo, hi)


R = 0.25
LIGHTS = {
    "disk": lambda: Light("Disk", "AREA", light_matrix((0, 0, 2), (0, 0, -1)), power=POWER,
                          size=(2 * R, 2 * R), shape="DISK"),
    "point": lambda: Light("Bulb", "POINT", light_matrix((0, 0, 2), (0, 0, -1)), power=POWER,
                           radius=R),
    "sun": lambda: Light("Sun", "SUN", light_matrix((0, 0, 5), (0, 0, -1)), power=3.0,
                         angle=2 * np.arctan(R)),
}


@pytest.mark.parametrize("kind", sorted(LIGHTS))
def test_penumbra_width_is_the_similar_triangles_width(kind):
    """Light radius R at 2 m (the sun: angular radius atan(R) per metre), plate edge at 1 m
    over the floor: the penumbra spans x in [-R, R] with the disk's segment-area profile
    0.5 + (asin u + u sqrt(1 - u^2)) / pi, u = x / R. Its 10 %, 50 % and 90 % points agree
    within a texel (the filter's strata are smoothed over 1.5 texels)."""
    res = 512
    eng, scene, bounds = _edge_scene(LIGHTS[kind]())
    shadow = eng.shadow_map(scene, scene.lights[0], bounds, res)
    x = np.linspace(-0.5, 0.5, 2001)
    pos = np.c_[x, np.zeros((x.size, 2))]
    nrm = np.tile([0.0, 0.0, 1.0], (x.size, 1))
    with jit.disabled():
        vis = direct.visibility(shadow, pos, nrm)
    texel = 4.0 / res if kind != "sun" else 2 * shadow.views[0].half_extent / res
    window = round(1.5 * texel / (x[1] - x[0]))
    smooth = np.convolve(vis, np.ones(window) / window, mode="same")
    u = np.clip(x / R, -1, 1)
    want = 0.5 + (np.arcsin(u) + u * np.sqrt(1 - u * u)) / np.pi
    inner = slice(window, -window)
    for level in (0.1, 0.5, 0.9):
        got_x = x[inner][np.argmax(smooth[inner] > level)]
        want_x = x[np.argmax(want > level)]
        assert abs(got_x - want_x) <= texel, (level, got_x, want_x)
    assert vis[x < -R - 2 * texel].max() == 0.0  # umbra
    assert vis[x > R + 2 * texel].min() == 1.0  # lit


@pytest.mark.parametrize("kind", sorted(LIGHTS))
def test_lit_floor_has_no_acne_at_any_slope(kind):
    """A lone floor under a tilted light with a size: every point of it sees all the light
    (the taps compare against the floor's own plane, so no wide filter darkens it)."""
    light = LIGHTS[kind]()
    if kind == "sun":
        light.matrix = light_matrix((0, 0, 5), (0.8, 0.3, -0.4))
    else:
        light.matrix = light_matrix((0.5, 0, 1.0), (-0.3, 0.2, -1))
    tris = quad((-3, -3, 0), (3, -3, 0), (3, 3, 0), (-3, 3, 0))
    scene = make_scene(tris, lights=[light], settings=GISettings())
    eng = engine.Engine()
    bounds = eng.upload(scene, engine.Stats())
    shadow = eng.shadow_map(scene, light, bounds, 256)
    rng = np.random.default_rng(3)
    pos = np.c_[rng.uniform(-2.9, 2.9, (5000, 2)), np.zeros(5000)]
    nrm = np.tile([0.0, 0.0, 1.0], (5000, 1))
    with jit.disabled():
        vis = direct.visibility(shadow, pos, nrm)
    assert vis.min() == 1.0


@pytest.mark.skipif(not jit.enabled(), reason="LPV_JIT=0: the kernels are off")
@pytest.mark.parametrize("variant", ["square", "ellipse_spread", "point", "spot", "sun"])
def test_compiled_soft_shadows_are_the_numpy_ones(variant):
    kind = {"square": "AREA", "ellipse_spread": "AREA", "point": "POINT", "spot": "SPOT",
            "sun": "SUN"}[variant]
    scene = cornell_box(kind, (16, 16), GISettings())
    light = scene.lights[0]
    light.radius, light.angle = 0.25, np.radians(8.0)
    if variant == "ellipse_spread":
        light.shape, light.size, light.spread = "ELLIPSE", (0.7, 0.35), np.radians(90)
    eng = engine.Engine()
    bounds = eng.upload(scene, engine.Stats())
    shadow = eng.shadow_map(scene, light, bounds, 256)
    pos, nrm = surface_points(np.random.default_rng(7), scene.positions, 20000)
    got = direct.irradiance(light, pos, nrm, shadow)
    vis = direct.visibility(shadow, pos, nrm)
    with jit.disabled():
        want = direct.irradiance(light, pos, nrm, shadow)
        want_vis = direct.visibility(shadow, pos, nrm)
    penumbra = (want_vis > 0) & (want_vis < 1)
    assert penumbra.mean() > 0.02  # the soft path is exercised
    np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-12 * want.max())
    np.testing.assert_allclose(vis, want_vis, rtol=1e-10, atol=1e-12)


def test_a_box_side_under_a_wide_panel_is_not_shaded_by_its_own_box():
    """A box's side whose plane has the panel's centre behind it still sees the part of the
    panel in front of it: the rest of its own box (behind its plane) shades nothing."""
    box = np.concatenate([quad((-0.5, -0.5, 1), (0.5, -0.5, 1), (0.5, 0.5, 1), (-0.5, 0.5, 1)),
                          quad((0.5, -0.5, 0), (0.5, 0.5, 0), (0.5, 0.5, 1), (0.5, -0.5, 1)),
                          quad((-3, -3, 0), (3, -3, 0), (3, 3, 0), (-3, 3, 0))])
    light = Light("Panel", "AREA", light_matrix((0, 0, 2), (0, 0, -1)), power=POWER,
                  size=(2.0, 2.0))
    scene = make_scene(box, lights=[light], settings=GISettings())
    eng = engine.Engine()
    bounds = eng.upload(scene, engine.Stats())
    shadow = eng.shadow_map(scene, light, bounds, 512)
    z = np.linspace(0.3, 0.9, 7)
    pos = np.c_[np.full(7, 0.5), np.zeros(7), z]
    nrm = np.tile([1.0, 0.0, 0.0], (7, 1))
    with jit.disabled():
        vis = direct.visibility(shadow, pos, nrm)
        e = direct.irradiance(light, pos, nrm)[:, 0]
    assert (e > 0).all()  # the panel's part beyond x = 0.5 lights the side
    assert vis.min() == 1.0


@pytest.mark.parametrize("kind", ["POINT", "SPOT", "SUN", "AREA"])
def test_pyramid_early_outs_are_what_the_taps_give(kind, monkeypatch):
    """The depth pyramid settles receivers (lit: no texel of the search region can occlude;
    umbra: every texel of the search's and any filter's region does) with exactly the
    visibility the blocker search and filter give; most receivers read no taps (the cost)."""
    scene = cornell_box(kind, (16, 16), GISettings())
    light = scene.lights[0]
    light.radius, light.angle = 0.1, np.radians(0.526)  # Blender's defaults
    eng = engine.Engine()
    bounds = eng.upload(scene, engine.Stats())
    shadow = eng.shadow_map(scene, light, bounds, 512)
    pos, nrm = surface_points(np.random.default_rng(11), scene.positions, 20000)
    lit = direct.irradiance(light, pos, nrm)[:, 0] > 0
    pos, nrm = pos[lit], nrm[lit]
    tapped = []
    early = direct._early_outs

    def counted(*args):
        left = early(*args)
        tapped.append(left.size)
        return left

    with jit.disabled():
        monkeypatch.setattr(direct, "_early_outs", counted)
        got = direct.visibility(shadow, pos, nrm)
        monkeypatch.setattr(direct, "_early_outs", lambda *args: args[-2])
        want = direct.visibility(shadow, pos, nrm)
    np.testing.assert_array_equal(got, want)
    assert ((want > 0) & (want < 1)).mean() > 0.005  # penumbrae are there
    assert sum(tapped) < 0.5 * pos.shape[0]  # most receivers read no taps


def test_compiled_pyramid_blocks_are_the_numpy_ones():
    if not jit.enabled():
        pytest.skip("the kernels are off")
    scene = cornell_box("POINT", (16, 16), GISettings())
    eng = engine.Engine()
    bounds = eng.upload(scene, engine.Stats())
    shadow = eng.shadow_map(scene, scene.lights[0], bounds, 250)  # not a multiple of 4
    eye = np.asarray(scene.lights[0].position, np.float64)
    for view, depth in zip(shadow.views, shadow.stacked()):
        want = direct._blocks(view, depth, eye)
        got = direct._compiled.pyramid_blocks(view, depth, eye, 1 << direct.PYRAMID_FROM)
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)


def _rectangle_form_factor(x1, x2, y1, y2, h):
    """Form factor from a point to a parallel rectangle [x1, x2] x [y1, y2] at height h (its
    coordinates relative to the point): the corner rectangles' signed sum (_corner)."""
    f = 0.0
    for x, sx in ((x2, 1), (x1, -1)):
        for y, sy in ((y2, 1), (y1, -1)):
            f = f + sx * sy * np.sign(x) * np.sign(y) * _corner(np.abs(x) / h, np.abs(y) / h)
    return f


def test_penumbra_of_a_wide_panel_is_the_irradiance_of_its_unblocked_part():
    """A 2 x 0.5 m panel at 2 m over the plate edge at 1 m (_edge_scene): a floor point at x
    sees the panel's part beyond -x, the nearer part, which lights it most. Its shadowed
    irradiance is that sub-rectangle's form factor (Siegel & Howell), not the full panel's
    times the unblocked share of its area (8 % darker on the penumbra's lit half)."""
    a, b, h = 1.0, 0.25, 2.0
    light = Light("Panel", "AREA", light_matrix((0, 0, h), (0, 0, -1)), power=POWER,
                  size=(2 * a, 2 * b))
    eng, scene, bounds = _edge_scene(light)
    shadow = eng.shadow_map(scene, light, bounds, 512)
    rng = np.random.default_rng(5)
    n = 4000
    x, y = rng.uniform(-0.9, 0.9, n), rng.uniform(-0.5, 0.5, n)
    pos = np.c_[x, y, np.zeros(n)]
    nrm = np.tile([0.0, 0.0, 1.0], (n, 1))
    with jit.disabled():
        got = direct.irradiance(light, pos, nrm, shadow)[:, 0]
    radiance = POWER / (np.pi * 4 * a * b)
    want = np.pi * radiance * _rectangle_form_factor(-2 * x, a - x, -b - y, b - y, h)
    full = np.pi * radiance * _rectangle_form_factor(-a - x, a - x, -b - y, b - y, h)
    area_share = full * (a + x) / (2 * a)  # the unweighted taps' expectation
    # per quarter of the penumbra, from the umbra's side: the unblocked share of the area
    # reads 1.72, 1.15, 0.92, 0.92 of it; the taps weighted by their strata's form factors
    # 0.74 (a sliver of the panel: 1 to 2 of the 6 strata across it), 0.95, 1.00, 0.99
    for lo, tol in ((-0.45, 0.07), (0.0, 0.02), (0.45, 0.02)):
        k = (x >= lo) & (x < lo + 0.45)
        assert got[k].sum() / want[k].sum() == pytest.approx(1.0, abs=tol), lo
        assert abs(area_share[k].sum() / want[k].sum() - 1.0) > 2 * tol  # it tells them apart
