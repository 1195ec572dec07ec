"""The compiled RSM texel pass (rsm._vpl_kernel) against the numpy reference (texel_flux,
lights.intensity): the same VPLs, in the same order, for every light type."""

import dataclasses

import numpy as np
import pytest

pytest.importorskip("numba")

from lpv_core import demo, engine, jit, rsm
from lpv_core.scene import GISettings


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
