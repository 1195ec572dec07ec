"""Inputs no scene should carry: settings out of range are refused with the setting, the value
and the range; non-finite scene data is dropped or defaulted before any stage sees it (no NaN
or Inf leaves a stage); indirect light is linear in light power from 1e-30 to 1e30 W."""

from __future__ import annotations

import contextlib
import dataclasses
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from lpv_core import engine, geometry_volume, injection, lookup, propagation, rsm
from lpv_core.propagation import sweep
from lpv_core.render import deferred, direct
from lpv_core.runtime import jit
from lpv_core.scene import Area, GISettings, Light, Material, make_scene, model
from tools import core_scenes as demo

ROOT = Path(__file__).resolve().parents[1]

# --------------------------------------------------------------------------------------------
# Linear in power (issue 19.6)
# --------------------------------------------------------------------------------------------


def _floor_points():
    xs = np.linspace(-0.8, 0.8, 5)
    x, y = np.meshgrid(xs, xs)
    p = np.c_[x.ravel(), y.ravel(), np.full(x.size, 1e-3)]
    return p, np.tile([0.0, 0.0, 1.0], (len(p), 1))


def _scaled(scene, factor: float):
    return dataclasses.replace(scene, lights=[dataclasses.replace(li, power=li.power * factor)
                                              for li in scene.lights])


@pytest.mark.parametrize("compiled, backend", [(True, "numpy"), (False, "numpy"),
                                               (True, "gl")], ids=["compiled", "numpy", "gl"])
def test_indirect_light_is_linear_in_power_from_1e_30_to_1e30_watts(compiled, backend, request):
    # The transport is linear: indirect light / power is the same number at any power, up to
    # float32 rounding (1e-5 relative), whether the flux is 1e-30 W or 1e30 W.
    if compiled and not jit.enabled():
        pytest.skip("numba is not installed")
    if backend == "gl":
        request.getfixturevalue("gl")  # skips without a GL 4.3 compute context
    base = demo.cornell_box("POINT", settings=GISettings(grid_resolution=12, rsm_resolution=48,
                                                         backend=backend))
    p, n = _floor_points()
    eng = engine.Engine()

    def indirect(k):
        r = eng.update(_scaled(base, 10.0**k))
        e = lookup.irradiance(r.grid, r.values, p, n, angular="dom", visibility=r.visibility)
        assert np.all(np.isfinite(e))
        return e / 10.0**k

    with contextlib.nullcontext() if compiled else jit.disabled():
        ref = indirect(0)
        assert ref.min() > 0
        worst = {k: float(np.abs(indirect(k) - ref).max() / ref.max())
                 for k in range(-30, 31, 6) if k}
    print("\nrelative deviation of indirect / power from the 1 W case:",
          {k: f"{v:.1e}" for k, v in worst.items()})
    assert max(worst.values()) <= 1e-5, worst




def test_rendered_passes_are_linear_in_power_for_a_sun():
    # Direct and indirect passes of a sunlit yard at 1e-30 and 1e30 times its irradiance: no
    # float32 overflow or underflow in the RSM flux, injection, direct light or the render.
    base = demo.outdoor((32, 24), GISettings(grid_resolution=12, rsm_resolution=48,
                                             shadow_resolution=128, antialias=1,
                                             backend="numpy"))
    eng = engine.Engine()

    def passes(k):
        sc = _scaled(base, 10.0**k)
        out = deferred.render(eng, sc, eng.update(sc))
        return {n: out[n] / np.float32(10.0**k) for n in ("Diffuse Direct", "Diffuse Indirect")}

    ref = passes(0)
    for k in (-30, 30):
        for name, image in passes(k).items():
            assert np.all(np.isfinite(image)), (k, name)
            assert np.abs(image - ref[name]).max() <= 1e-5 * ref[name].max(), (k, name)

# --------------------------------------------------------------------------------------------
# Settings validated (issue 19.4)
# --------------------------------------------------------------------------------------------

BAD_SETTINGS = [
    ("grid_resolution", 1e9), ("grid_resolution", float("inf")), ("grid_resolution", "inf"),
    ("grid_resolution", 0), ("grid_resolution", -16), ("grid_resolution", 2.5),
    ("grid_resolution", float("nan")), ("antialias", 0), ("antialias", -1), ("iterations", -1),
    ("bounces", -1), ("bounces", 0), ("intensity", float("nan")), ("intensity", "inf"),
    ("intensity", -1.0), ("rsm_resolution", 0), ("shadow_resolution", -1), ("cascades", 0),
    ("backend", "cuda"), ("cascades_auto", 2),
]


def test_every_setting_has_a_range():
    assert set(model.SETTING_RANGES) == {f.name for f in dataclasses.fields(GISettings)}


@pytest.mark.parametrize("key, value", BAD_SETTINGS)
def test_a_setting_out_of_range_is_refused_naming_setting_value_and_range(key, value):
    allowed = model.setting_range(key)
    with pytest.raises(ValueError) as info:
        GISettings().updated(**{key: value})
    text = str(info.value)
    assert f"'{key}'" in text
    shown = value if isinstance(value, str) else f"{value:g}"
    assert str(shown).lower() in text.lower(), text
    if allowed is None:
        assert "true or false" in text
    elif isinstance(allowed[0], str):
        assert all(name in text for name in allowed)
    else:
        assert f"from {allowed[0]} to {allowed[1]}" in text
    with pytest.raises(ValueError, match=f"'{key}'"):  # construction checks the same
        GISettings(**{key: float(value) if isinstance(value, str) and key != "backend"
                      else value})


def test_every_range_end_is_accepted():
    for key in model.SETTING_RANGES:
        allowed = model.setting_range(key)
        ends = (True, False) if allowed is None else allowed
        for value in ends:
            assert getattr(GISettings().updated(**{key: value}), key) == value
            assert getattr(GISettings().updated(**{key: str(value)}), key) == value


def test_the_largest_grid_is_the_largest_the_memory_guard_admits():
    # The UI and the CLI offer nothing the engine would then refuse for memory.
    r = model.max_grid_resolution()
    sweep.check_memory(r)
    with pytest.raises(ValueError, match=f"grid_resolution {r + 1} needs"):
        sweep.check_memory(r + 1)
    with pytest.raises(ValueError, match=f"from 4 to {r}: grid_resolution {r + 1} needs about"):
        GISettings(grid_resolution=r + 1)


@pytest.mark.parametrize("item", ["grid_resolution=1e9", "antialias=0", "intensity=nan",
                                  "backend=cuda"])
def test_the_cli_refuses_a_setting_out_of_range_with_exit_2(tmp_path, item):
    proc = subprocess.run([sys.executable, "-m", "lpv_addon.batch", "--demo", "--out",
                           str(tmp_path / "out"), "--set", item], cwd=ROOT,
                          capture_output=True, text=True, timeout=300, check=False)
    assert proc.returncode == 2, proc.stderr[-2000:]
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    key, value = item.split("=")
    shown = repr(value) if value.isalpha() and value != "nan" else f"{float(value):g}"
    assert len(lines) == 1 and f"'{key}': {shown}" in lines[0] and "Traceback" not in proc.stderr, lines
    assert not (tmp_path / "out").exists()


# --------------------------------------------------------------------------------------------
# Non-finite scene data (issue 19.5): make_scene drops or defaults it, no stage emits NaN/Inf
# --------------------------------------------------------------------------------------------

NAN, INF = float("nan"), float("inf")


def _hostile_inputs():
    """A Cornell box's arrays plus what a broken driver or script can put in a scene: lights
    with NaN/Inf power, transform, colour and GI values, a negative power, 1e30 W and 1e-30 W
    lights, materials with NaN albedo and Inf bleed colour, a NaN triangle, areas with a NaN
    transform and NaN values."""
    base = demo.cornell_box("SPOT", (24, 24), GISettings(
        grid_resolution=8, rsm_resolution=32, shadow_resolution=128, antialias=1,
        backend="numpy"))
    spot = base.lights[0]
    nan_matrix = spot.matrix.copy()
    nan_matrix[0, 3] = NAN
    lights = [spot, dataclasses.replace(spot, name="bright", power=1e30),
              dataclasses.replace(spot, name="dim", power=1e-30),
              dataclasses.replace(spot, name="nan power", power=NAN),
              dataclasses.replace(spot, name="inf power", power=INF),
              dataclasses.replace(spot, name="nan matrix", matrix=nan_matrix),
              dataclasses.replace(spot, name="negative", power=-50.0),
              dataclasses.replace(spot, name="nan colour",
                                  color=np.array([NAN, 1, 1], np.float32),
                                  gi_color=np.array([INF, 0.5, -1], np.float32),
                                  gi_intensity=NAN, spot_blend=NAN)]
    n = len(base.materials)
    materials = base.materials + [
        Material("nan albedo", np.array([NAN, 0.5, 0.5], np.float32)),
        Material("inf bleed", bleed_color=np.array([INF, 0, 0], np.float32),
                 bleed_intensity=NAN)]
    index = base.material_index.copy()
    index[:2], index[2:4] = n, n + 1
    positions = np.concatenate([base.positions, [[[0, 0, NAN], [1, 0, 0], [0, 1, 0]]]])
    normals = np.concatenate([base.normals, base.normals[:1]])
    box = np.diag([0.5, 0.5, 0.5, 1.0])
    box[:3, 3] = (0, 0, 1)
    areas = [Area("nan matrix", "TRANSITION", box * NAN),
             Area("nan values", "TRANSITION", box, falloff=NAN, intensity=NAN,
                  tint=np.array([INF, 1, 1], np.float32))]
    return {"positions": positions, "normals": normals, "material_index": np.r_[index, 0],
            "materials": materials, "lights": lights, "camera": base.camera,
            "settings": base.settings, "areas": areas}


def test_make_scene_drops_or_defaults_non_finite_lights_materials_and_areas():
    inputs = _hostile_inputs()
    before = [dataclasses.asdict(li) for li in inputs["lights"]]
    sc = make_scene(**inputs)
    assert sc.dropped == {
        "nonfinite_vertices": 1, "zero_area_triangles": 0, "zero_length_normals": 0,
        "lights_with_nonfinite_transform_or_power": 3, "lights_with_negative_power": 1,
        "lights_with_invalid_values_defaulted": 1, "areas_with_nonfinite_transform": 1,
        "areas_with_invalid_values_defaulted": 1, "materials_with_invalid_values_defaulted": 2}
    assert [li.name for li in sc.lights] == ["Spot", "bright", "dim", "nan colour"]
    fixed = sc.lights[-1]
    np.testing.assert_array_equal(fixed.color, [1, 1, 1])  # Light's defaults
    np.testing.assert_array_equal(fixed.gi_color, [1, 0.5, 0])  # NaN -> 1, negative -> 0
    assert fixed.gi_intensity == 1.0 and fixed.spot_blend == Light.spot_blend
    mats = {m.name: m for m in sc.materials}
    np.testing.assert_array_equal(mats["nan albedo"].albedo, np.float32([0.8, 0.5, 0.5]))
    assert mats["inf bleed"].bleed_color is None and mats["inf bleed"].bleed_intensity == 1.0
    assert [(a.falloff, a.intensity) for a in sc.areas] == [(0.5, 1.0)]
    np.testing.assert_array_equal(sc.areas[0].tint, [1, 1, 1])
    # The caller's objects are left as they were (the user's scene data is not modified).
    for was, li in zip(before, inputs["lights"]):
        np.testing.assert_array_equal(dataclasses.asdict(li)["color"], was["color"])



def test_negative_colours_and_strengths_are_raised_to_zero_and_counted():
    tri = np.array([[[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]])
    ok = Material("ok")
    neg = Material("neg", np.float32([-0.5, 0.5, 0.5]), bleed_intensity=-1.0)
    light = Light("L", "POINT", np.eye(4), color=np.float32([1, -1, 1]))
    sc = make_scene(tri, materials=[ok, neg], lights=[light, Light("fine", "POINT", np.eye(4))])
    assert sc.dropped["materials_with_invalid_values_defaulted"] == 1
    assert sc.dropped["lights_with_invalid_values_defaulted"] == 1
    assert sc.materials[0] is ok and sc.lights[1].name == "fine"
    np.testing.assert_array_equal(sc.materials[1].albedo, [0, 0.5, 0.5])
    assert sc.materials[1].bleed_intensity == 0.0
    np.testing.assert_array_equal(sc.lights[0].color, [1, 0, 1])

@pytest.fixture(scope="module")
def hostile():
    """The hostile scene through make_scene, and an engine that has run its update."""
    sc = make_scene(**_hostile_inputs())
    eng = engine.Engine()
    return sc, eng, eng.update(sc)


def _finite(*arrays):
    for a in arrays:
        assert a is not None and np.all(np.isfinite(a)), a


def test_no_nan_or_inf_leaves_the_rsm(hostile):
    sc, eng, _ = hostile
    for light in sc.lights:
        r = rsm.render_rsm(eng.raster, light, eng.lpv_bounds(sc), sc.settings.rsm_resolution)
        assert len(r.flux) > 0
        _finite(r.position, r.normal, r.flux, r.area)


def test_no_nan_or_inf_leaves_the_geometry_volume(hostile):
    sc, _, res = hostile
    _finite(geometry_volume.occluder_visibility(res.grid, sc.positions))


def _injected(sc, eng, grid):
    parts = [rsm.render_rsm(eng.raster, li, eng.lpv_bounds(sc), 32) for li in sc.lights]
    return injection.inject(grid, *(np.concatenate([getattr(p, k) for p in parts])
                                    for k in ("position", "normal", "flux")))


def test_no_nan_or_inf_leaves_the_injection(hostile):
    sc, eng, res = hostile
    _finite(_injected(sc, eng, res.grid))


def test_no_nan_or_inf_leaves_the_propagation(hostile):
    sc, eng, res = hostile
    vis = geometry_volume.occluder_visibility(res.grid, sc.positions)
    out = propagation.propagate(_injected(sc, eng, res.grid), visibility=vis, launch=True)
    _finite(out.values)
    _finite(res.values, *res.per_light.values(), *(v for _, v, _ in res.fine))


def test_no_nan_or_inf_leaves_the_lookup(hostile):
    res = hostile[2]
    p, n = _floor_points()
    e = lookup.irradiance(res.grid, res.values, p, n, angular="dom", visibility=res.visibility)
    _finite(e)
    assert e.max() > 0


def test_no_nan_or_inf_leaves_direct_light_and_the_rendered_passes(hostile):
    sc, eng, res = hostile
    p, n = _floor_points()
    for light in sc.lights:
        shadow = direct.render_shadow_map(eng.raster, light, sc.bounds(), 128)
        _finite(direct.irradiance(light, p, n, shadow))
    passes = deferred.render(eng, sc, res)
    assert {"Combined", "Diffuse Direct", "Diffuse Indirect", "Diffuse Color"} <= set(passes)
    for name, image in passes.items():
        assert np.all(np.isfinite(image)), name
    assert passes["Diffuse Indirect"].max() > 0
