"""Where a finer cascade ends (cascades.whole, cascades.reads): a receiver reads the finest
cascade holding it made whole, so its light does not depend on where a cascade's face falls.

A hand-derived restriction of a uniform field; which receivers make which read; the rendered
light on a box face lit by the sunlit ground with the finer cascade's face at several
distances."""

from __future__ import annotations

import numpy as np
import pytest

from lpv_core import cascades, engine, lookup
from lpv_core.grid import Grid
from lpv_core.render import deferred
from lpv_core.scene import (
    Camera,
    GISettings,
    Light,
    Material,
    look_at_matrix,
    make_scene,
    perspective_matrix,
)
from tools.core_scenes import box_triangles, light_matrix, quad

COARSE = Grid((0.0, 0.0, 0.0), 1.0, 8)
FINE = Grid((1.0, 2.0, 1.0), 0.5, 4)  # coarse cells [1, 3) x [2, 4) x [1, 3)


def test_whole_adds_a_finer_cascades_light_into_the_coarser_cells_inside_it():
    fine = np.zeros(FINE.shape(9), np.float32)
    fine[..., 0] = 1.0
    coarse = np.zeros(COARSE.shape(9), np.float32)
    coarse[..., 0] = 0.25
    whole = cascades.whole([FINE, COARSE], [fine, coarse])
    assert whole[0] is fine
    want = coarse.copy()
    want[1:3, 2:4, 1:3, :, 0] += 4.0  # 8 children of 1 / 2: a cell twice the side
    np.testing.assert_array_equal(whole[1], want)
    # a uniform field reads the same irradiance from either grid (intensity ~ cross-section)
    at, up = np.array([[2.0, 3.0, 2.0]]), np.array([[0.0, 0.0, 1.0]])
    grids = [(FINE, fine), (COARSE, whole[1] - coarse)]
    e = [lookup.irradiance(g, v, at, up, offset_cells=0.0) for g, v in grids]
    np.testing.assert_allclose(e[0], e[1], rtol=1e-6)


def test_each_receiver_reads_the_finest_cascade_holding_it_whole_and_the_coarser_as_they_are():
    fine, coarse = np.ones(FINE.shape(9), np.float32), np.ones(COARSE.shape(9), np.float32)
    whole = cascades.whole([FINE, COARSE], [fine, coarse])[1]
    result = engine.LPVResult(COARSE, coarse, {}, engine.Stats(), fine=[(FINE, fine, None)],
                              whole=[whole])
    reads = cascades.reads(result)
    inside, outside = np.array([[2.0, 3.0, 2.0]]), np.array([[5.0, 5.0, 5.0]])
    taken = [(r.grid, r.values is whole) for r in reads if r.takes(inside)[0]]
    assert taken == [(FINE, False), (COARSE, False)]
    taken = [(r.grid, r.values is whole) for r in reads if r.takes(outside)[0]]
    assert taken == [(COARSE, True)]
    # a result without them (KD10's grids, an older reply): each grid as it is
    result.whole = []
    assert all(r.values is not whole for r in cascades.reads(result))


HALF = 8.0  # the ground's half width (m)
PLACE = cascades.place
ELEVATION = np.radians(35.0)


def _face_light(monkeypatch, fine_face_y: float | None) -> tuple[float, float]:
    """(mean rendered indirect irradiance on the sunlit face (y = -0.5, facing -y) of a
    1 x 1 x 3 m box on a 16 x 16 m grey ground at 16^3 with two cascades, the finer one's +y
    face at ``fine_face_y`` (None: beyond the box); the finer cell size; that face's y)."""
    ground = quad([-HALF, -HALF, 0], [HALF, -HALF, 0], [HALF, HALF, 0], [-HALF, HALF, 0])
    box = box_triangles([-0.5, -0.5, 0.0], [0.5, 0.5, 3.0])
    sun = Light("Sun", "SUN", light_matrix((0, -5, 5), (0, np.cos(ELEVATION),
                                                          -np.sin(ELEVATION))), power=3.0)
    cam = Camera(look_at_matrix([0.0, -6.0, 1.5], [0.0, -0.5, 1.5]),
                 perspective_matrix(0.6, 1.0, 0.05, 200.0), (48, 48))
    scene = make_scene(np.concatenate([ground, box]), materials=[Material("grey")],
                       lights=[sun], camera=cam,
                       settings=GISettings(grid_resolution=16, cascades_auto=False, cascades=2,
                                           antialias=1, contact_light=False))

    def placed(lo, hi, resolution, count, camera=None, focus=None):
        outer = PLACE(lo, hi, resolution, 1)[0]
        cell = outer.cell_size / 2
        side = cell * resolution
        origin = np.array([-0.25 * side, -0.5 * side, -0.1 * side])
        if fine_face_y is not None:
            origin[1] = fine_face_y - side
        anchor = outer.origin_array  # on the coarser cells, as cascades.place snaps
        origin = anchor + np.round((origin - anchor) / outer.cell_size) * outer.cell_size
        return [Grid(tuple(float(v) for v in origin), cell, resolution), outer]

    monkeypatch.setattr(cascades, "place", placed)
    eng = engine.Engine()
    lpv = eng.update(scene)
    passes = deferred.render(eng, scene, lpv)  # as an artist's render reads the cascades
    mask, pos, nrm, *_ = eng.raster.gbuffer(cam.view, cam.projection, *cam.resolution, 1.0)
    face = (nrm[:, 1] < -0.99) & (np.abs(pos[:, 1] + 0.5) < 1e-3) & (pos[:, 2] > 0.1)
    assert face.sum() > 100
    e = passes["Diffuse Indirect"][..., 0][mask][face] * np.pi
    fine = lpv.fine[0][0]
    return float(e.mean()), fine.cell_size, fine.bounds()[1][1]


@pytest.mark.parametrize("cells_short", [1, 3, 5])
def test_a_face_just_outside_the_finer_cascade_keeps_its_light(monkeypatch, cells_short):
    """Rendered (deferred.render, the contact light off): with the finer cascade's face 1.1,
    3.1 or 5.1 of its cells short of the box face, the face reads 1.09 / 1.09 / 1.10 of its
    light with the finer cascade holding it (asserted 0.95-1.15: the coarser cascade's cells,
    twice as wide, read it a little higher). Reading each cascade's own grid it read 0.73 at
    1.1 cells: the coarser cells its lookup reached inside the finer cascade held none of the
    finer cascade's light."""
    held, cell, _ = _face_light(monkeypatch, None)
    # the finer cascade's face on the coarser lattice, about ``cells_short`` of its cells short
    short, _, face = _face_light(monkeypatch, -0.5 - cells_short * cell)
    print(f"\nfiner cascade's face {(-0.5 - face) / cell:.2f} cells short: {short / held:.3f}")
    assert 0.95 <= short / held <= 1.15
