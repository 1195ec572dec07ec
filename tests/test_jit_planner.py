"""The planner's compiled geometry tests (triangle/box overlap, clipping to a box, polygon/cone
hits) against their numpy reference: the same decisions on random triangles, and the same
light decisions on the demo scenes."""

import numpy as np
import pytest

pytest.importorskip("numba")

from lpv_core import planner
from lpv_core.grid import Grid
from lpv_core.runtime import jit
from lpv_core.scene import GISettings
from tools import core_scenes as demo


def _triangles(n: int, seed: int) -> np.ndarray:
    """Triangles of all sizes around the unit box: inside, across its faces, outside."""
    rng = np.random.default_rng(seed)
    centre = rng.uniform(-2.0, 2.0, (n, 1, 3))
    size = 10.0 ** rng.uniform(-2.0, 0.7, (n, 1, 1))
    return centre + size * rng.normal(size=(n, 3, 3))


def test_tri_box_overlap_matches_numpy():
    tris = _triangles(20000, 1)
    lo, hi = np.array([-1.0, -0.5, -1.5]), np.array([1.0, 0.75, 0.5])
    got = planner._tri_box_overlap(tris, lo, hi)
    with jit.disabled():
        ref = planner._tri_box_overlap(tris, lo, hi)
    assert 2000 < ref.sum() < 18000  # both outcomes well represented
    np.testing.assert_array_equal(got, ref)
    # a triangle only touching the box counts; one a hair away does not
    touch = np.array([[[1.0, 0.0, 0.0], [2.0, 0.0, 0.0], [2.0, 0.5, 0.0]]])
    assert planner._tri_box_overlap(touch, lo, hi)[0]
    assert not planner._tri_box_overlap(touch + [1e-9, 0, 0], lo, hi)[0]


def test_clip_to_box_matches_numpy():
    tris = _triangles(3000, 2)
    lo, hi = np.array([-1.0, -1.0, -1.0]), np.array([1.0, 0.5, 1.0])
    poly, count = planner._clip_to_box(tris, lo, hi)
    with jit.disabled():
        ref_poly, ref_count = planner._clip_to_box(tris, lo, hi)
    np.testing.assert_array_equal(count, ref_count)
    assert count.max() >= 6 and (count == 0).sum() > 100
    for t in np.flatnonzero(count):
        np.testing.assert_allclose(poly[t, :count[t]], ref_poly[t, :count[t]], rtol=0,
                                   atol=1e-12)


@pytest.mark.parametrize("half_deg", [5.0, 30.0, 60.0, 89.0, 90.0, 120.0])
def test_cone_hits_matches_numpy(half_deg):
    tris = _triangles(4000, 3)
    lo, hi = -np.ones(3), np.ones(3)
    poly, count = planner._clip_to_box(tris, lo, hi)
    apex = np.array([0.2, -0.3, 0.9])
    axis = np.array([0.3, 0.2, -1.0]) / np.linalg.norm([0.3, 0.2, -1.0])
    if half_deg >= 90.0:  # wide cones: pointing out of the box, so that some polygons are dark
        axis = -axis
    half = np.radians(half_deg)
    got = planner._cone_hits(poly, count, apex, axis, half)
    with jit.disabled():
        ref = planner._cone_hits(poly, count, apex, axis, half)
    assert 0 < ref.sum() < (count > 0).sum()
    np.testing.assert_array_equal(got, ref)


def test_cone_hits_hand_cases():
    """A triangle straddling the cone's axis far away (no vertex in it) is hit; one beside
    the cone is not; one behind the apex is not."""
    apex, axis, half = np.zeros(3), np.array([0.0, 0.0, -1.0]), np.radians(10.0)
    big = np.array([[[-5.0, -5.0, -3.0], [5.0, -5.0, -3.0], [0.0, 5.0, -3.0]]])
    beside = np.array([[[2.0, 2.0, -3.0], [3.0, 2.0, -3.0], [2.0, 3.0, -3.0]]])
    behind = big * [1, 1, -1]
    count = np.array([3])
    for poly, expect in ((big, True), (beside, False), (behind, False)):
        assert planner._cone_hits(poly, count, apex, axis, half)[0] == expect
        with jit.disabled():
            assert planner._cone_hits(poly, count, apex, axis, half)[0] == expect


@pytest.mark.parametrize("light_type", ["SPOT", "AREA", "POINT", "SUN"])
def test_light_decisions_match_numpy(light_type):
    settings = GISettings().updated(grid_resolution=16)
    scene = demo.cornell_box(light_type, (16, 16), settings)
    for cell in (0.02, 0.05, 0.2):  # grids inside the box, around it, and far larger
        grid = Grid((-0.3, -0.4, 0.5), cell, 16)
        got = planner.light_reach(scene.lights[0], grid, scene)
        with jit.disabled():
            ref = planner.light_reach(scene.lights[0], grid, scene)
        assert (got.keep, got.reason) == (ref.keep, ref.reason)
