"""Many lights (issue 19 point 3): the shadow and RSM budgets (render/shadows.py) share the
maps out by each light's share of the light, the shadow-map cache evicts the least recently
used past its bytes, a few lights keep the set resolutions (the same bits), and a frame of many
point lights at 256x256 stays within 2 GB."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
from conftest import ROOT

from lpv_core import engine
from lpv_core.render import deferred, direct, shadows
from lpv_core.scene import GISettings
from tools import bench


def test_resolutions_keep_the_set_resolution_while_all_fit():
    views = [6, 6, 1]
    budget = 1024 ** 2 * 13  # exactly the three lights' texels
    got = shadows.resolutions([0.9, 0.09, 0.01], views, 1024, budget)
    np.testing.assert_array_equal(got, [1024, 1024, 1024])


def test_resolutions_share_the_texels_by_share():
    """Hand-derived: two cube lights, the budget one full cube. Shares 0.8 / 0.2: 0.8 and 0.2
    of 1024^2 texels per face, sides 916 and 458, rounded down to 1024 / 2^k: 512, 256.
    Shares 0.99 / 0.01: the small light's 10486 texels (side 102) rounds to 64, the large one
    keeps 0.99 of the face (side 1019): 512."""
    budget = 6 * 1024 ** 2
    np.testing.assert_array_equal(shadows.resolutions([0.8, 0.2], [6, 6], 1024, budget),
                                  [512, 256])
    np.testing.assert_array_equal(shadows.resolutions([0.99, 0.01], [6, 6], 1024, budget),
                                  [512, 64])
    # more floors than the budget holds: all at the floor; a light of no share at the floor
    np.testing.assert_array_equal(shadows.resolutions([0.5, 0.5, 0.0], [6, 6, 6], 1024,
                                                      6 * 64 ** 2), [64, 64, 64])
    many = shadows.resolutions(np.full(300, 1 / 300), np.full(300, 6), 1024,
                               shadows.SHADOW_BUDGET / 4)
    assert (6 * 4 * many.astype(float) ** 2).sum() <= shadows.SHADOW_BUDGET
    np.testing.assert_array_equal(many, 256)  # sqrt(2^27 / 1800) = 273 -> 256


def _map(resolution: int) -> direct.ShadowMap:
    stack = np.zeros((6, resolution, resolution), np.float32)
    return direct.ShadowMap(None, [None] * 6, list(stack), resolution, stack)


def test_shadow_cache_evicts_the_least_recently_used_past_its_bytes():
    one = _map(32).nbytes
    assert one == 6 * 32 * 32 * 4
    cache = shadows.ShadowCache(budget=3 * one)
    for k in "abc":
        cache.put(k, _map(32))
    assert cache.get("a") is not None  # "a" now the most recently used
    cache.put("d", _map(32))  # one over: "b", the least recently used, goes
    assert set(cache.maps) == {"c", "a", "d"} and cache.bytes == 3 * one
    assert cache.evicted == 1 and cache.get("b") is None
    cache.put("big", _map(64))  # 4 maps' bytes alone: it stays, every other goes
    assert list(cache.maps) == ["big"] and cache.bytes == 4 * one and cache.evicted == 4


def test_a_few_lights_keep_the_set_resolutions():
    """Three lights fit the budgets: every shadow map and RSM is at the settings' resolution
    and the Diffuse Direct pass is the sum of each light's direct light with its full-size
    map, bit for bit."""
    settings = GISettings(grid_resolution=8, rsm_resolution=64, shadow_resolution=512,
                          antialias=1)
    scene = bench.many_lights_scene(3, (32, 32), settings)
    eng = engine.Engine()
    stats = engine.Stats()
    out = deferred.render(eng, scene, eng.update(scene, stats), stats)
    assert "reduced" not in stats.info["shadow_maps"] and "rsm_reduced" not in stats.info
    assert all(e.resolution == 64 for e in eng._lights.values())
    lo, hi = eng.lpv_bounds(scene)
    mask, pos, nrm, _, _ = eng.raster.gbuffer(scene.camera.view, scene.camera.projection, 32, 32)
    want = sum(direct.irradiance(li, pos, nrm, direct.render_shadow_map(eng.raster, li,
                                                                        (lo, hi), 512))
               for li in scene.lights)
    assert all(m.resolution == 512 for m in eng._shadows.maps.values())
    np.testing.assert_array_equal(out["Diffuse Direct"][mask], (want / np.pi).astype(np.float32))


def test_grid_budget_keeps_the_set_resolution_while_the_grids_fit():
    """Hand-derived (108 bytes a cell: 9 float32 coefficients x 3 colours; 512 MiB): 50 lights
    x 3 cascades x 32^3 cells = 531 MB fit, 51 do not, floor((2^29 / (153 x 108))^(1/3)) = 31;
    300 lights: one cascade 25^3, three 17^3; never below 8^3, never above the setting."""
    s = GISettings(grid_resolution=32)
    assert engine.budget_resolution(s, 50, 3) == 32
    assert engine.budget_resolution(s, 51, 3) == 31
    assert engine.budget_resolution(s, 300, 1) == 25
    assert engine.budget_resolution(s, 300, 3) == 17
    assert engine.budget_resolution(s, 10**6, 3) == engine.MIN_BUDGET_RESOLUTION == 8
    assert engine.budget_resolution(GISettings(grid_resolution=6), 10**6, 3) == 6
    assert engine.budget_resolution(s, 0, 3) == 32


def test_lights_past_the_grid_budget_get_coarser_cascades_and_the_stats_say_so(monkeypatch):
    """Three point lights' 16^3 grids (3 x 442 KB) past a 1 MiB budget: the cascade is 14^3
    (floor((2^20 / (3 x 108))^(1/3))), stats name the budget; with two lights it fits."""
    monkeypatch.setattr(engine, "GRID_BUDGET", 2**20)
    settings = GISettings(grid_resolution=16, cascades=1, rsm_resolution=32, antialias=1)
    stats = engine.Stats()
    res = engine.Engine().update(bench.many_lights_scene(3, (16, 16), settings), stats)
    assert res.grid.resolution == 14 and not res.fine
    assert stats.info["grid_reduced"] == {"asked": 16, "resolution": 14, "entries": 3}
    assert any("grid budget" in s["reason"] for s in stats.skipped)
    assert all(np.isfinite(v).all() for v in res.per_light.values())
    stats = engine.Stats()
    res = engine.Engine().update(bench.many_lights_scene(2, (16, 16), settings), stats)
    assert res.grid.resolution == 16 and "grid_reduced" not in stats.info


def test_many_lights_share_the_budgets_by_their_light():
    """Forty point lights: their cube maps at 1024^2 (960 MiB) do not fit the 512 MiB budget.
    The cache holds at most the budget, the lights that light what the camera sees more get
    maps at least as fine, and the RSMs stay within their texel budget."""
    settings = GISettings(grid_resolution=8, antialias=1)
    scene = bench.many_lights_scene(40, (32, 32), settings)
    scene.lights[0].power *= 50.0  # one dominant light
    eng = engine.Engine()
    stats = engine.Stats()
    deferred.render(eng, scene, eng.update(scene, stats), stats)
    info = stats.info["shadow_maps"]
    assert eng._shadows.bytes <= shadows.SHADOW_BUDGET and info["evicted"] == 0
    res = {m.light.name: m.resolution for m in eng._shadows.maps.values()}
    assert len(res) == 40 and res["Point0"] == 1024 and max(res.values()) == 1024
    assert min(res.values()) < 1024 and info["reduced"] == {k: v for k, v in res.items()
                                                            if v < 1024}
    shares = shadows.frame_shares(scene.lights, eng._focus(scene, engine.Stats(),
                                                           engine.geometry_key(scene))[0])
    order = np.argsort(shares)
    got = np.array([res[scene.lights[i].name] for i in order])
    assert np.all(np.diff(got) >= 0)  # finer maps for larger shares
    rsm = {li.name: eng._lights[li.name].resolution for li in scene.lights}
    assert rsm["Point0"] == 256 and sum(6 * r * r for r in rsm.values()) <= shadows.RSM_BUDGET
    assert stats.info["rsm_reduced"] == {k: v for k, v in rsm.items() if v < 256}


def test_rsm_flux_past_its_budget_is_kept_as_a_digest(monkeypatch):
    """With FLUX_KEPT at 0 every light keeps its RSM flux's digest; an edit of the ceiling's
    material, which the two downward spots never see, still reuses their grids (same_vpls on
    the digest); an edit of the walls they see does not."""
    monkeypatch.setattr(engine, "FLUX_KEPT", 0)
    settings = GISettings(grid_resolution=8, rsm_resolution=32)
    scene = bench.many_lights_scene(2, (16, 16), settings)
    for light in scene.lights:
        light.type, light.spot_size = "SPOT", np.radians(60.0)  # light_matrix: facing down
    scene.materials.append(type(scene.materials[0])("ceiling", np.full(3, 0.8, np.float32)))
    scene.material_index = scene.material_index.copy()
    scene.material_index[2:4] = len(scene.materials) - 1  # cornell_box: triangles 2, 3
    eng = engine.Engine()
    eng.update(scene)
    assert all(isinstance(e.flux, str) for e in eng._lights.values())
    scene.materials[-1].albedo = np.full(3, 0.3, np.float32)
    stats = engine.Stats()
    eng.update(scene, stats)
    assert len([s for s in stats.skipped if "none its RSM sees" in s["reason"]]) == 2
    scene.materials[0].albedo = np.full(3, 0.5, np.float32)  # the white walls: seen
    stats = engine.Stats()
    eng.update(scene, stats)
    assert not any("none its RSM sees" in s["reason"] for s in stats.skipped)


PEAK_LIGHTS = 100  # the suite's frame; `python -m tools.bench --lights 300` the issue's


def test_many_point_lights_frame_stays_within_two_gb():
    """One frame (default settings, 256x256) of PEAK_LIGHTS point lights in a fresh process:
    peak resident memory (VmHWM) at most 2 GB. Without the budgets each light kept a
    48 MiB cube shadow map and 9 MiB of RSM flux (100 lights: 5.7 GB)."""
    proc = subprocess.run([sys.executable, "-m", "tools.bench", "--lights", str(PEAK_LIGHTS),
                           "--json"], cwd=ROOT, capture_output=True, text=True, timeout=900,
                          check=False)
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = json.loads(proc.stdout)
    print(f"\n{PEAK_LIGHTS} lights: {out['frame_s']:.1f} s, peak {out['peak_rss_mib']:.0f} MiB")
    assert out["resolution"] == [256, 256] and out["lights"] == PEAK_LIGHTS
    assert out["peak_rss_mib"] * 2**20 <= 2e9
    assert out["shadow_cached_mib"] * 2**20 <= shadows.SHADOW_BUDGET
    assert out["frame_per_light_ms"] > 0 and out["per_light_ms"]["direct"] > 0
