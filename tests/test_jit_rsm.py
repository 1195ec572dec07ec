"""The compiled RSM texel pass (kernels.rsm.view_vpls) against the numpy reference
(rsm.view_vpls: texel_flux, lights.intensity): the same VPLs, in the same order, for every
light type."""

import dataclasses

import numpy as np
import pytest

pytest.importorskip("numba")

from lpv_core import engine, rsm
from lpv_core.kernels import rsm as rsm_kernels
from lpv_core.runtime import jit
from lpv_core.scene import GISettings
from tools import core_scenes as demo


def _rsms(light_type: str, resolution: int = 64, **light_changes):
    scene = demo.cornell_box(light_type, (16, 16), GISettings(), offset=(3.0, -2.0, 1.0))
    eng = engine.Engine()
    eng.upload(scene, engine.Stats())
    bounds = eng.lpv_bounds(scene)
    light = dataclasses.replace(scene.lights[0], **light_changes)
    with jit.disabled():
        ref = rsm.render_rsm(eng.raster, light, bounds, resolution)
    assert jit.enabled()
    return ref, rsm.render_rsm(eng.raster, light, bounds, resolution)


@pytest.mark.parametrize("light_type,changes", [
    ("SPOT", {}),
    ("SPOT", {"spot_blend": 0.0}),  # hard cone edge
    ("SPOT", {"spot_size": np.radians(150.0)}),  # wide cone: cube views
    ("POINT", {}),
    ("SUN", {}),
    ("AREA", {}),
    ("SPOT", {"color": np.array([1.0, 0.0, 0.5])}),  # a colour channel with no flux
    ("POINT", {"radius": 0.5}),  # a disk facing each texel (round_geometry)
    ("SPOT", {"radius": 0.5, "soft_falloff": False}),  # a sphere, the ceiling inside it
])
def test_compiled_rsm_matches_numpy(light_type, changes):
    ref, got = _rsms(light_type, **changes)
    assert ref.count > 100 and got.count == ref.count and got.texels == ref.texels
    for field in ("position", "normal", "flux", "area"):
        a, b = getattr(got, field), getattr(ref, field)
        assert a.dtype == b.dtype == np.float64 and a.shape == b.shape
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12 * np.abs(b).max(), err_msg=field)


def test_compiled_rsm_without_light_is_empty():
    ref, got = _rsms("SPOT", power=0.0)
    assert ref.count == got.count == 0
    assert got.flux.shape == (0, 3) and got.area.shape == (0,)


@pytest.mark.parametrize("light_type", ["SPOT", "POINT"])
def test_compiled_rsm_one_thread_below_split(light_type):
    """Maps of fewer than SPLIT_MIN rows are converted on one thread: the same VPLs."""
    ref, got = _rsms(light_type, resolution=rsm_kernels.SPLIT_MIN // 2)
    assert ref.count > 100 and got.count == ref.count
    for field in ("position", "normal", "flux", "area"):
        a, b = getattr(got, field), getattr(ref, field)
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12 * np.abs(b).max(), err_msg=field)


@pytest.mark.parametrize("light_type", ["SPOT", "SUN", "POINT"])
def test_rsm_pass_matches_main_pass(light_type):
    """Rasterizer.read_rsm gives read()'s position target bit for bit and the same coverage;
    its normal is the face's (the box's corner normals are its faces': the main pass's
    normal within the float32 rounding of the texels' position differences, 2e-5, gain 1);
    its triangles' reflectance is the uploaded float32 value, which the main pass's
    interpolated target only approximates (within a few float32 ulps)."""
    from lpv_core.scene import lights as lights_mod

    scene = demo.cornell_box(light_type, (16, 16), GISettings(), offset=(3.0, -2.0, 1.0))
    eng = engine.Engine()
    eng.upload(scene, engine.Stats())
    raster = eng.raster
    for view in lights_mod.light_views(scene.lights[0], eng.lpv_bounds(scene)):
        p4, n4, r4 = raster.read(view.view, view.projection, 64, 64, view.ortho, (0, 1, 3))
        q4, m4 = raster.read_rsm(view.view, view.projection, 64, view.ortho)
        cov = p4[..., 3] > 0.5
        assert cov.sum() > 100 and np.array_equal(cov, q4[..., 3] > 0.5)
        assert np.array_equal(q4[..., :3], p4[..., :3])
        np.testing.assert_allclose(m4[cov][:, :3], n4[cov][:, :3], rtol=0, atol=2e-5)
        tri = raster.triangles(q4[cov], m4[cov])
        assert tri.min() >= 0 and tri.max() < raster.reflectance.shape[0]
        np.testing.assert_allclose(raster.reflectance[tri], r4[cov][:, :3], rtol=4e-6, atol=0)


def test_triangle_index_beyond_float_precision():
    """Indices from 2^24 on (not exact as one float32) are split over the two w channels."""
    from lpv_core.render.raster import TRIANGLE_SPLIT, Rasterizer

    index = np.array([0, 5, TRIANGLE_SPLIT - 1, TRIANGLE_SPLIT, 3 * TRIANGLE_SPLIT + 7])
    pos = np.zeros((5, 4), np.float32)
    nrm = np.zeros((5, 4), np.float32)
    pos[:, 3] = 1 + index // TRIANGLE_SPLIT
    nrm[:, 3] = index % TRIANGLE_SPLIT
    assert np.array_equal(Rasterizer.triangles(pos, nrm), index)
