"""The render's sub-pixel samples (deferred.render, settings.antialias): each pass is the mean
over an s x s grid in the pixel, i.e. the box-filtered image of s times the resolution."""

import numpy as np
import pytest

from lpv_core import engine
from lpv_core.render import deferred
from lpv_core.scene import GISettings
from tools import core_scenes as demo


def test_antialias_is_the_box_filtered_finer_image():
    """The 2 x 2 samples of a pixel are the finer image's 2 x 2 pixels: Combined and Diffuse
    Color their mean, the diffuse light passes their light over their colour (as Cycles)."""
    eng = engine.Engine()
    coarse = demo.cornell_box("SPOT", (16, 12), GISettings(antialias=2))
    fine = demo.cornell_box("SPOT", (32, 24), GISettings(antialias=1))
    got = deferred.render(eng, coarse, eng.update(coarse))
    ref = deferred.render(eng, fine, eng.update(fine))
    edge = 0
    def blocks(a):
        return a.reshape(12, 2, 16, 2, -1).sum(axis=(1, 3), dtype=np.float64)

    for name, arr in got.items():
        box = blocks(ref[name]) / 4.0
        if name in deferred.LIGHT_PASSES:  # Cycles': the light over the colour, per block
            box = deferred.even_divide(blocks(ref[name] * ref["Diffuse Color"]),
                                       blocks(ref["Diffuse Color"]))
        assert arr.shape == box.shape and arr.dtype == np.float32
        np.testing.assert_allclose(arr, box, atol=1e-5 * np.abs(box).max(), err_msg=name)
        if name == "Diffuse Color":  # pixels where a red or green wall meets a white one
            red = ref[name][..., 0] - ref[name][..., 1]  # (24, 32): 0.7 red, -0.7 green, 0 white
            samples = red.reshape(12, 2, 16, 2)
            edge = int((samples.max(axis=(1, 3)) - samples.min(axis=(1, 3)) > 0.5).sum())
    assert edge > 0  # the test covers pixels that one centre sample would alias


def test_antialias_does_not_touch_the_lpv():
    eng = engine.Engine()
    scene = demo.cornell_box("SPOT", (8, 8), GISettings(antialias=1))
    eng.update(scene)
    stats = engine.Stats()
    eng.update(demo.cornell_box("SPOT", (8, 8), GISettings(antialias=3)), stats)
    assert "rsm" not in stats.ms and "propagation" not in stats.ms
    assert any(s["stage"] == "rsm" and "reused" in s["reason"] for s in stats.skipped)


@pytest.mark.parametrize("bad", [0, deferred.MAX_ANTIALIAS + 1, 1.5])
def test_bad_antialias_is_named(bad):
    with pytest.raises(ValueError, match="antialias"):
        GISettings(antialias=bad)
    # A settings object changed after it was checked is refused by the render itself.
    eng = engine.Engine()
    scene = demo.cornell_box("SPOT", (8, 8), GISettings())
    result = eng.update(scene)
    scene.settings.antialias = bad
    with pytest.raises(ValueError, match="antialias"):
        deferred.render(eng, scene, result)


@pytest.mark.parametrize("offset", [0.0, 1.0e5])
@pytest.mark.parametrize("kind", ["SPOT", "SUN"])
def test_shadow_map_depths_of_a_floor_are_the_analytic_distances(kind, offset):
    """A light 2 m above a 4 m floor (z = 0), the scene moved by ``offset`` on every axis:
    a spot's map holds |p - light| = 2 / cos(angle) at every covered texel (its minimum 2 m,
    straight down), a sun pointing down the same depth 2 m + the view's near offset
    everywhere; float32 distances from the rasteriser's origin keep 1e-4 m at 1e5 m."""
    from lpv_core.render import direct
    from lpv_core.render.raster import Rasterizer
    from lpv_core.scene import Light

    shift = np.full(3, offset)
    corners = np.array([[[-2, -2, 0], [2, -2, 0], [2, 2, 0]],
                        [[-2, -2, 0], [2, 2, 0], [-2, 2, 0]]], np.float64) + shift
    raster = Rasterizer()
    raster.upload(corners, np.tile([0.0, 0.0, 1.0], (2, 3, 1)), np.ones((2, 3)),
                  np.ones((2, 3)))
    matrix = np.eye(4)
    matrix[:3, 3] = shift + [0.0, 0.0, 2.0]  # local -Z points down
    light = Light("L", kind, matrix, spot_size=np.radians(60.0))
    bounds = (shift + [-2.0, -2.0, 0.0], shift + [2.0, 2.0, 2.0])
    shadow = direct.render_shadow_map(raster, light, bounds, 64)
    (depth,) = shadow.depths
    covered = np.isfinite(depth)
    assert depth.dtype == np.float32 and covered.mean() > 0.5
    view = shadow.views[0]
    if kind == "SPOT":
        # texel centres' rays: the floor point along each is at 2 / cos from the light
        n = depth.shape[0]
        u = (np.arange(n) + 0.5) / n * 2.0 - 1.0
        x, y = np.meshgrid(u * view.tan_half, -u * view.tan_half)  # rows top-first
        expected = 2.0 * np.sqrt(1.0 + x**2 + y**2)
        np.testing.assert_allclose(depth[covered], expected[covered], rtol=0, atol=1e-4)
        assert abs(depth[covered].min() - expected.min()) < 1e-4
    else:
        near = float(-(np.asarray(view.view)[2, :3] @ (shift + [0, 0, 2]) + view.view[2, 3]))
        np.testing.assert_allclose(depth[covered], 2.0 + near, rtol=0, atol=1e-4)


def test_gbuffer_is_the_rendered_frame_at_its_covered_pixels():
    """Rasterizer.gbuffer (covered pixels only) gives render()'s frame at frame.covered, in
    row-major order: positions, normals, albedo and the receiver flags."""
    scene = demo.cornell_box("SPOT", (40, 30), GISettings())
    eng = engine.Engine()
    eng.upload(scene, engine.Stats())
    cam = scene.camera
    frame = eng.raster.render(cam.view, cam.projection, 40, 30)
    covered, pos, nrm, albedo, receiver = eng.raster.gbuffer(cam.view, cam.projection, 40, 30)
    assert covered.shape == (30, 40) and 0.3 < covered.mean() < 1.0
    np.testing.assert_array_equal(covered, frame.covered)
    np.testing.assert_array_equal(pos, frame.position[covered])
    np.testing.assert_array_equal(nrm, frame.normal[covered].astype(np.float64))
    np.testing.assert_array_equal(albedo, frame.albedo[covered])
    np.testing.assert_array_equal(receiver, frame.receiver[covered])
