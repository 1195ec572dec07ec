"""Sliver pixels (deferred.render): a pixel that a surface covers less than its 2 x 2 samples
can see still holds that surface's irradiance in Diffuse Direct, as Cycles' pass does (its
light over its colour), and a share of its colour in Diffuse Color."""

from __future__ import annotations

import numpy as np
import pytest

from lpv_core import engine
from lpv_core.render import deferred
from lpv_core.scene import GISettings
from lpv_core.scene.model import (
    Camera,
    Light,
    Material,
    look_at_matrix,
    make_scene,
    orthographic_matrix,
)
from tools.core_scenes import light_matrix

ALBEDO = np.array([0.6, 0.5, 0.4], np.float32)
SUN = 3.0  # W/m^2 straight down: E = 3 on the plane everywhere, Diffuse Direct 3 / pi


def sliver_scene(edge: float, antialias: int = 2):
    """An 8 x 8 orthographic view of 1 m pixels down onto a plane z = 0 that ends at
    x = ``edge``: the pixel column x in [0, 1] is covered from its left by ``edge``."""
    tris = np.array([[[-10, -10, 0], [edge, -10, 0], [edge, 10, 0]],
                     [[-10, -10, 0], [edge, 10, 0], [-10, 10, 0]]], np.float64)
    sun = Light("Sun", "SUN", light_matrix((0.0, 0.0, 5.0), (0.0, 0.0, -1.0)), power=SUN)
    cam = Camera(look_at_matrix((0.0, 0.0, 5.0), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0)),
                 orthographic_matrix(4.0, 4.0, 0.1, 20.0), (8, 8))
    return make_scene(tris, materials=[Material("plane", ALBEDO)], lights=[sun], camera=cam,
                      settings=GISettings(antialias=antialias))


def _render(scene):
    eng = engine.Engine()
    return deferred.render(eng, scene, eng.update(scene))


@pytest.mark.parametrize("cover", [0.2, 0.15])
def test_a_sliver_pixel_holds_its_surfaces_irradiance(cover):
    """Covered 0.15-0.2 from its left, the column is missed by the samples at 0.25 and 0.75
    and found by the 4 x 4 border's at 0.125: Diffuse Direct 3 / pi as inside the plane,
    Diffuse Color the 4 of 16 samples' share of the albedo; the next column sees nothing."""
    got = _render(sliver_scene(cover))
    inside = got["Diffuse Direct"][:, 3]
    np.testing.assert_allclose(inside, SUN / np.pi, rtol=1e-3)
    np.testing.assert_allclose(got["Diffuse Direct"][:, 4], inside, rtol=1e-4)
    np.testing.assert_allclose(got["Diffuse Color"][:, 4], np.broadcast_to(ALBEDO * 4 / 16,
                                                                           (8, 3)), rtol=1e-5)
    light = got["Diffuse Direct"] + got["Diffuse Indirect"]
    np.testing.assert_allclose(got["Combined"][:, 4, :3], got["Diffuse Color"][:, 4] * light[:, 4],
                               rtol=1e-5)
    assert not got["Diffuse Color"][:, 5:].any() and not got["Diffuse Direct"][:, 5:].any()


def test_a_pixel_its_samples_see_keeps_their_mean():
    """Covered 0.3 from its left, the samples at 0.25 see the plane: the column is the 2 x 2
    samples' mean (half of them), no border samples added."""
    got = _render(sliver_scene(0.3))
    np.testing.assert_allclose(got["Diffuse Direct"][:, 4], SUN / np.pi, rtol=1e-3)
    np.testing.assert_allclose(got["Diffuse Color"][:, 4], np.broadcast_to(ALBEDO / 2, (8, 3)),
                               rtol=1e-5)


def test_no_sliver_samples_at_four_samples_a_side():
    """4 x 4 samples already see an eighth of a pixel: the 0.2 column is their 4 of 16."""
    stats = engine.Stats()
    scene = sliver_scene(0.2, antialias=4)
    eng = engine.Engine()
    got = deferred.render(eng, scene, eng.update(scene), stats)
    assert "sliver_pixels" not in stats.info
    np.testing.assert_allclose(got["Diffuse Color"][:, 4], np.broadcast_to(ALBEDO * 4 / 16,
                                                                           (8, 3)), rtol=1e-5)
