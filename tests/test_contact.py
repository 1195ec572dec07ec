"""Contact light (lpv_core/render/contact.py): the bounce from surfaces nearer than a cell.

Hand-derived patches (the disk form factor without a footprint, a parallel square's
catalogued form factor, the part of a patch above the receiver's plane); the footprints'
half-edges against the rasteriser's steps; the ground beside the sunlit face of a 1 x 1 x 3 m
box against the face's exact single bounce (the form factor integrated over the face) at
several placements of the box in its cells; what it leaves alone; GI weights; the compiled
twin."""

from __future__ import annotations

import numpy as np
import pytest

from lpv_core import engine
from lpv_core.render import contact, deferred
from lpv_core.runtime import jit
from lpv_core.scene import (
    Area,
    Camera,
    GISettings,
    Light,
    Material,
    World,
    look_at_matrix,
    make_scene,
    orthographic_matrix,
    perspective_matrix,
)
from lpv_core.scene.lights import polygon_irradiance
from tools.core_scenes import box_triangles, light_matrix, quad

ELEVATION = np.radians(35.0)
SUN = 3.0  # W/m^2
ALBEDO = 0.8  # Material's default diffuse colour


def _pair(reach=0.25, region=(0, 0)):
    """A 1 x 3 image: a receiver facing +z at the origin, an emitting patch 0.1 m from it
    (cos 0.6 at the receiver, 0.8 at the patch) with no footprint (the disk form factor), an
    empty pixel."""
    pos = np.zeros((1, 3, 3))
    nrm = np.zeros((1, 3, 3))
    nrm[0, 0] = (0, 0, 1)
    pos[0, 1], nrm[0, 1] = (0.08, 0.0, 0.06), (-1.0, 0.0, 0.0)
    covered = np.array([[True, True, False]])
    radiosity = np.zeros((1, 3, 3))
    radiosity[0, 1] = 2.0
    area = np.array([[0.001, 0.002, 0.0]])
    size = np.full((1, 3), 0.1)
    return (pos, nrm, covered, radiosity, area, size, np.full((1, 3), reach),
            np.array([list(region) + [0]]), np.zeros((1, 3, 2, 3)))


def _gathered(args, compiled):
    if compiled and not jit.enabled():
        pytest.skip("numba is not installed or LPV_JIT=0")
    if compiled:
        return contact.gather(*args)
    with jit.disabled():
        return contact.gather(*args)


@pytest.mark.parametrize("compiled", [False, True])
def test_a_patch_without_a_footprint_gives_its_disk_form_factor_less_the_grids_share(compiled):
    got = _gathered(_pair(), compiled)
    cut = [_gathered(_pair(reach=0.09), compiled), _gathered(_pair(region=(0, 1)), compiled)]
    a, r2, rho = 0.002, 0.01, 0.25
    want = 2.0 * 0.6 * 0.8 * (a / (np.pi * r2 + a) - a / (np.pi * rho * rho))  # by hand
    np.testing.assert_allclose(got[0, 0], want, rtol=1e-12)
    assert got[0, 1].max() == 0 and got[0, 2].max() == 0  # no light towards the patch, no pixel
    for c in cut:  # beyond the reach, across a clip area's boundary: nothing
        assert c.max() == 0


def _facing(height, half, centre_z=None, reach=0.5):
    """A 1 x 2 image: a receiver facing +z at the origin and a square patch of half side
    ``half`` centred ``height`` above it facing down (its footprint's half-edges along x and
    y), radiosity 1; with ``centre_z``, the patch turned vertical instead (facing -x, 0.05 m
    away), centred at that height."""
    pos = np.zeros((1, 2, 3))
    nrm = np.zeros((1, 2, 3))
    nrm[0, 0] = (0, 0, 1)
    edges = np.zeros((1, 2, 2, 3))
    if centre_z is None:
        pos[0, 1], nrm[0, 1] = (0, 0, height), (0, 0, -1)
        edges[0, 1] = [(half, 0, 0), (0, half, 0)]
    else:
        pos[0, 1], nrm[0, 1] = (0.05, 0, centre_z), (-1, 0, 0)
        edges[0, 1] = [(0, half, 0), (0, 0, half)]
    radiosity = np.zeros((1, 2, 3))
    radiosity[0, 1] = 1.0
    area = np.array([[0.0, 4 * half * half]])
    return (pos, nrm, np.ones((1, 2), bool), radiosity, area, np.full((1, 2), 0.2),
            np.full((1, 2), reach), np.zeros((1, 2), np.int64), edges)


@pytest.mark.parametrize("compiled", [False, True])
def test_a_patch_gives_its_footprints_exact_form_factor_less_the_grids_share(compiled):
    """A square of side 2a centred c above a receiver and parallel to it: four times the
    catalogued form factor of a parallel rectangle with the receiver's normal through its
    corner (Howell's catalogue), for an a x a square F = (1 / pi) (X / sqrt(1 + X^2))
    atan(X / sqrt(1 + X^2)), X = a / c, less the grid's share A / (pi rho^2)."""
    c, a, rho = 0.1, 0.05, 0.5
    x = a / c
    corner = x / np.sqrt(1 + x * x) * np.arctan(x / np.sqrt(1 + x * x)) / np.pi  # by hand
    want = 4 * corner - 4 * a * a / (np.pi * rho * rho)
    got = _gathered(_facing(c, a, reach=rho), compiled)
    np.testing.assert_allclose(got[0, 0], want, rtol=1e-12)


@pytest.mark.parametrize("compiled", [False, True])
def test_a_patch_below_the_receivers_plane_counts_only_its_part_above(compiled):
    """A vertical square straddling the receiver's plane sends only its upper half's light:
    the same as the upper half alone, less the whole square's grid share (the cosines at its
    centre, here 0: the receiver lies in its centre's horizontal plane)."""
    whole = _gathered(_facing(None, 0.04, centre_z=0.0), compiled)[0, 0]
    half = _facing(None, 0.04, centre_z=0.02)
    half[8][0, 1] = [(0, 0.04, 0), (0, 0, 0.02)]
    half[4][0, 1] = 0.08 * 0.04
    upper = _gathered(half, compiled)[0, 0]
    rho, cc = 0.5, 0.02 * 0.05 / (0.05**2 + 0.02**2)  # the upper half's centre cosines
    share = cc * 0.0032 / (np.pi * rho * rho)
    assert whole.max() > 0
    np.testing.assert_allclose(whole, upper + share, rtol=1e-9)


def _box_scene(resolution: int, shift: float, gi: float = 1.0, angular: str = "dom",
               contact_light: bool = True, clip: bool = False):
    ground = quad([-6, -6, 0], [6, -6, 0], [6, 6, 0], [-6, 6, 0])
    move = np.array([0.0, shift, 0.0])
    box = box_triangles([-0.5, -0.5, 0.0], [0.5, 0.5, 3.0]) + move
    # the sun along +y and down: it lights the face at y = -0.5 (and the top); the side
    # faces, parallel to it, get none
    sun = Light("Sun", "SUN", light_matrix((0, -5, 5), (0, np.cos(ELEVATION),
                                                          -np.sin(ELEVATION))),
                power=SUN, gi_intensity=gi)
    cam = Camera(look_at_matrix(np.array([1.2, -3.0, 1.6]) + move,
                                np.array([0.0, -0.6, 0.3]) + move),
                 perspective_matrix(0.9, 1.0, 0.05, 200.0), (96, 96))
    # a clip area just around the box: its faces inside, the ground beside them outside
    around = np.diag([0.51, 0.51, 1.51, 1.0])
    around[:3, 3] = move + (0.0, 0.0, 1.5)
    return make_scene(np.concatenate([ground, box]), materials=[Material("grey")],
                      lights=[sun], camera=cam, areas=[Area("Clip", "CLIP", around)] if clip else [],
                      settings=GISettings(antialias=1, bounces=1, grid_resolution=resolution,
                                          angular=angular, contact_light=contact_light))


def _face_bounce(px: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Irradiance on the ground at (px, x from the face) from the lit 1 x 3 m face of radiosity
    ALBEDO x SUN cos(elevation): the point-to-point form factor z x / (pi r^4) integrated over
    the face (midpoint rule, 400 x 1200)."""
    u = (np.arange(400) + 0.5) / 400 - 0.5
    z = (np.arange(1200) + 0.5) / 400
    uu, zz = np.meshgrid(u, z, indexing="ij")
    out = np.empty(px.shape)
    for k, (p, d) in enumerate(zip(px, x)):
        r2 = (uu - p) ** 2 + d * d + zz * zz
        out[k] = (zz * d / (np.pi * r2 * r2)).sum() / 400**2
    return ALBEDO * SUN * np.cos(ELEVATION) * out


def _ground_beside_the_face(scene, shift: float):
    eng = engine.Engine()
    lpv = eng.update(scene)
    stats = engine.Stats()
    passes = deferred.render(eng, scene, lpv, stats)
    cam = scene.camera
    mask, pos, nrm, *_ = eng.raster.gbuffer(cam.view, cam.projection, *cam.resolution, 1.0)
    face = -0.5 + shift  # the lit face's plane, y
    ground = (nrm[:, 2] > 0.99) & (pos[:, 2] < 1e-3) & (np.abs(pos[:, 0]) < 0.4) & (
        pos[:, 1] < face)
    got = passes["Diffuse Indirect"][..., 0][mask][ground] * np.pi
    cell = min([lpv.grid.cell_size] + [g.cell_size for g, _, _ in lpv.fine])
    return pos[ground, 0], face - pos[ground, 1], got, cell, passes, stats


PLACEMENTS = (0.013, 0.061, 0.131)  # the box's shift (m): where its face falls in its cell


def test_ground_beside_a_sunlit_face_gets_the_faces_bounce_inside_the_first_cell():
    """16^3 (0.21 m cells; the face 1 m wide), 96^2: over three placements the first half
    cell's mean irradiance / the exact bounce averages 0.9-1.3 (measured 0.95 / 1.16 / 1.13),
    the next half cell's 0.85-1.2 (0.77 / 0.96 / 0.99); the grid alone reads 0.59 / 0.80 /
    0.77 and 0.72 / 0.90 / 0.93 there. From 1.5 cells out nothing changes."""
    ratios = {True: [], False: []}
    for shift in PLACEMENTS:
        for on in (True, False):
            px, x, got, cell, *_ = _ground_beside_the_face(
                _box_scene(16, shift, contact_light=on), shift)
            want = _face_bounce(px, x)
            bins = [(x < 0.5 * cell), (x >= 0.5 * cell) & (x < cell)]
            assert all(b.sum() > 10 for b in bins)
            ratios[on].append([got[b].mean() / want[b].mean() for b in bins])
            far = x > 1.5 * cell
            if on:
                kept = got[far]
            else:
                np.testing.assert_array_equal(got[far], kept)  # beyond the reach: the grid's
    with_contact, grid_alone = np.array(ratios[True]), np.array(ratios[False])
    print(f"\nfirst half cell: {with_contact[:, 0].round(3)} (grid alone "
          f"{grid_alone[:, 0].round(3)}); next: {with_contact[:, 1].round(3)} "
          f"({grid_alone[:, 1].round(3)})")
    assert 0.9 <= with_contact[:, 0].mean() <= 1.3
    assert 0.85 <= with_contact[:, 1].mean() <= 1.2
    assert grid_alone[:, 0].mean() < 0.85  # what the term is for


def test_contact_light_follows_gi_intensity_is_ours_not_kd10s_and_turns_off():
    one = _ground_beside_the_face(_box_scene(16, PLACEMENTS[0]), PLACEMENTS[0])
    two = _ground_beside_the_face(_box_scene(16, PLACEMENTS[0], gi=2.0), PLACEMENTS[0])
    near = one[1] < 0.5 * one[3]
    np.testing.assert_allclose(two[2][near], 2.0 * one[2][near], rtol=1e-5)
    assert "contact" in one[5].ms
    for off in (_box_scene(16, PLACEMENTS[0], angular="sh"),
                _box_scene(16, PLACEMENTS[0], contact_light=False)):
        assert "contact" not in _ground_beside_the_face(off, PLACEMENTS[0])[5].ms


def _box_gbuffer():
    """(w, h, mask, positions, normals, footprints' area and size, patch_edges) of the box
    scene's camera view."""
    scene = _box_scene(16, PLACEMENTS[1])
    eng = engine.Engine()
    eng.update(scene)
    cam = scene.camera
    w, h = cam.resolution
    mask, pos, nrm, *_ = eng.raster.gbuffer(cam.view, cam.projection, w, h, 1.0)
    area, size = contact.footprints(cam.view, cam.projection, w, h, pos, nrm)
    edges = contact.patch_edges(cam.view, cam.projection, w, h, pos, nrm)
    return w, h, mask, pos, nrm, area, size, edges


@pytest.mark.skipif(not jit.enabled(), reason="numba is not installed or LPV_JIT=0")
def test_compiled_gather_is_the_numpy_one_on_a_real_gbuffer():
    w, h, mask, pos, nrm, area, size, edges = _box_gbuffer()
    rng = np.random.default_rng(3)

    def image(v, shape=()):
        out = np.zeros((h, w) + shape)
        out[mask] = v
        return out

    args = (image(pos, (3,)), image(nrm, (3,)), mask,
            image(rng.uniform(0, 2, (pos.shape[0], 3)), (3,)), image(area), image(size),
            image(np.full(pos.shape[0], 0.3)), image(rng.integers(0, 2, pos.shape[0])),
            image(edges, (2, 3)))
    got = contact.gather(*args)
    with jit.disabled():
        want = contact.gather(*args)
    assert want.max() > 0
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-300)


def test_a_clip_area_between_a_face_and_the_ground_cuts_their_contact_light():
    """With a clip area around the box, its lit face and the ground beside it are on different
    sides: the ground there reads the grid's light alone, exactly."""
    on, off = (_ground_beside_the_face(_box_scene(16, PLACEMENTS[1], clip=True,
                                                  contact_light=c), PLACEMENTS[1])
               for c in (True, False))
    near = (on[1] > 0.02) & (on[1] < on[3])  # outside the box's 1 cm margin, within a cell
    assert near.sum() > 10 and off[2][near].max() > 0
    np.testing.assert_array_equal(on[2][near], off[2][near])
    unclipped = _ground_beside_the_face(_box_scene(16, PLACEMENTS[1]), PLACEMENTS[1])
    assert (unclipped[2][near] > on[2][near] * 1.05).mean() > 0.5  # the term, without the clip


def test_world_light_bounces_as_contact_light_weighted_by_the_worlds_gi_intensity():
    """The box under a uniform World and no lamp: the sky-lit face lights the ground beside it
    through the contact light too, scaled with the World's GI intensity like its grids."""
    def run(gi):
        scene = _box_scene(16, PLACEMENTS[0])
        scene.lights = []
        scene.world = World("Sky", np.full((1, 1, 3), 0.5, np.float32), digest="u", gi_intensity=gi)
        return _ground_beside_the_face(scene, PLACEMENTS[0])

    one, two = run(1.0), run(2.0)
    near = one[1] < 0.5 * one[3]
    assert "contact" in one[5].ms and near.sum() > 10 and one[2][near].min() > 0
    np.testing.assert_allclose(two[2][near], 2.0 * one[2][near], rtol=1e-5)


def test_a_pixels_footprint_edges_span_the_step_to_its_neighbours_on_the_same_face():
    """patch_edges on a real G-buffer: the half-edges lie in the surface's plane, span the
    area footprints gives (4 |du x dv|), and the sum of two neighbours' is the rasteriser's own
    step between them in x and in y on the same flat face (the ground, the box's faces)."""
    w, h, mask, pos, nrm, area, _, edges = _box_gbuffer()
    du, dv = edges[:, 0], edges[:, 1]
    assert np.all(np.abs((du * nrm).sum(-1)) <= 1e-9 * np.linalg.norm(du, axis=-1) + 1e-12)
    np.testing.assert_allclose(4 * np.linalg.norm(np.cross(du, dv), axis=-1), area, rtol=2e-3)
    img = np.zeros((h, w, 3))
    img[mask] = pos
    n_img = np.zeros((h, w, 3))
    n_img[mask] = nrm
    e_img = np.zeros((h, w, 2, 3))
    e_img[mask] = edges
    checked = 0
    for axis, (oy, ox) in enumerate(((0, 1), (1, 0))):
        a, b = img[:h - oy, :w - ox], img[oy:, ox:]
        same = (mask[:h - oy, :w - ox] & mask[oy:, ox:]
                & np.all(np.abs(n_img[:h - oy, :w - ox] - n_img[oy:, ox:]) < 1e-6, axis=-1)
                & (np.abs(((b - a) * n_img[:h - oy, :w - ox]).sum(-1)) < 1e-5))
        step = (b - a)[same]
        # rows run top-first: a step down the image is -y in NDC
        # (the half-edges at both ends: the footprint grows with depth)
        want = (e_img[:h - oy, :w - ox, axis] + e_img[oy:, ox:, axis])[same] * (
            1 if axis == 0 else -1)
        err = np.linalg.norm(step - want, axis=-1) / np.linalg.norm(want, axis=-1)
        assert err.max() < 5e-3, err.max()
        checked += same.sum()
    assert checked > 0.8 * 2 * mask.sum()


@pytest.mark.parametrize("ortho", [False, True])
def test_a_tilted_planes_footprint_is_the_pixel_stretched_by_its_tilt(ortho):
    """Hand-derived footprints: a camera at 2 m looking down -z at the origin, 100 x 50
    pixels over a 1 x 0.5 m view there (perspective: fov such that it is, at that depth;
    orthographic: the same box), a plane through the origin tilted by 60 deg about y (normal
    (sin 60, 0, cos 60)): along y a half pixel is 5 mm as seen; along x the footprint is that
    / cos 60 = 10 mm, and it runs down the slope (dz/dx = -tan 60). At a grazing 89.99 deg tilt
    there is none."""
    from lpv_core.scene import orthographic_matrix

    view = look_at_matrix(np.array([0.0, 0.0, 2.0]), np.zeros(3), up=(0.0, 1.0, 0.0))
    proj = (orthographic_matrix(0.5, 0.25, 0.1, 10.0) if ortho else
            perspective_matrix(2 * np.arctan(0.25 / 2.0), 2.0, 0.1, 10.0))
    t = np.radians(60.0)
    n = np.array([[np.sin(t), 0.0, np.cos(t)]])
    edges = contact.patch_edges(view, proj, 100, 50, np.zeros((1, 3)), n)[0]
    # 10 mm along the slope: 5 mm across the view, 5 tan 60 mm down
    np.testing.assert_allclose(edges[0], [0.005, 0.0, -0.005 * np.tan(t)], atol=1e-12)
    np.testing.assert_allclose(edges[1], [0.0, 0.005, 0.0], atol=1e-12)
    edge_on = np.array([[np.sin(np.radians(89.99)), 0.0, np.cos(np.radians(89.99))]])
    assert not contact.patch_edges(view, proj, 100, 50, np.zeros((1, 3)), edge_on).any()


def _parapet(contact_light: bool = True, **settings):
    """A sunlit 4 x 0.3 x 2 m wall on a 16 m ground (the sun 35 deg up, lighting its -y face)
    seen straight down by an orthographic camera, which sees none of its faces; (the ground
    pixels in front of the lit face, their rendered indirect irradiance, their distance to
    the face, the finest cell, their exact single bounce from the face: B x its contour form
    factor)."""
    ground = quad([-8, -8, 0], [8, -8, 0], [8, 8, 0], [-8, 8, 0])
    wall = box_triangles(np.array([-2.0, -0.15, 0.0]), np.array([2.0, 0.15, 2.0]))
    sun = Light("Sun", "SUN", light_matrix((0, -6, 6), (0, np.cos(ELEVATION),
                                                          -np.sin(ELEVATION))), power=SUN)
    cam = Camera(look_at_matrix([0.0, -1.0, 10.0], [0.0, -1.0, 0.0], (0.0, 1.0, 0.0)),
                 orthographic_matrix(1.0, 1.0, 0.1, 50.0), (64, 64))
    grey = Material("ground", albedo=np.full(3, 0.5, np.float32))
    scene = make_scene(np.concatenate([ground, wall]),
                       material_index=[0] * len(ground) + [1] * len(wall),
                       materials=[grey, Material("wall")], lights=[sun], camera=cam,
                       settings=GISettings(grid_resolution=16, antialias=1,
                                           contact_light=contact_light, **settings))
    eng = engine.Engine()
    lpv = eng.update(scene)
    passes = deferred.render(eng, scene, lpv)
    mask, pos, nrm, *_ = eng.raster.gbuffer(cam.view, cam.projection, 64, 64, 1.0)
    e = passes["Diffuse Indirect"][..., 0][mask] * np.pi
    g = (nrm[:, 2] > 0.99) & (np.abs(pos[:, 2]) < 1e-4) & (pos[:, 1] < -0.15)
    g &= np.abs(pos[:, 0]) < 1.0
    assert not ((np.abs(nrm[:, 2]) < 0.5) & mask[mask]).any()  # no face is seen
    face = np.array([[-2, -0.15, 0], [2, -0.15, 0], [2, -0.15, 2], [-2, -0.15, 2.0]])
    exact = (ALBEDO * SUN * np.cos(ELEVATION)) * polygon_irradiance(
        np.broadcast_to(face, (int(g.sum()), 4, 3)), pos[g], nrm[g]) / np.pi
    cell = lpv.fine[0][0].cell_size if lpv.fine else lpv.grid.cell_size
    return e[g], -0.15 - pos[g, 1], cell, exact


def test_a_sunlit_face_the_camera_cannot_see_lights_the_ground_at_its_foot():
    """The sun's first bounce is gathered in the sun's view, which sees the face the camera
    does not: the ground within half a cell of it reads 1.00 of the face's exact bounce
    (0.53 with the grid alone, as a gather of the camera's pixels read, which hold no face);
    from a cell out the grid's light alone is left (0.82 at 1-2 cells, both ways)."""
    e, dist, cell, exact = _parapet()
    e0, *_ = _parapet(contact_light=False)
    near = dist < 0.5 * cell
    assert near.sum() > 100
    assert 0.95 < e[near].mean() / exact[near].mean() < 1.05
    assert e0[near].mean() / exact[near].mean() < 0.6
    far = dist >= cell
    np.testing.assert_allclose(e[far], e0[far], rtol=1e-9, atol=1e-12)


def test_the_suns_view_lights_nothing_through_a_room_of_single_faces():
    """A closed room of single faces under a sun, the camera inside: the sun's view sees the
    roof's top and the walls' outsides, a float32 rounding from the ceiling and the inner
    walls; no tap is FRONT_TOLERANCE of the reach in front of a receiver inside, so the
    contact light adds nothing to the grid's light (none reaches inside)."""
    room = box_triangles(np.array([-2.05, -1.95, 0.0]), np.array([1.93, 2.07, 2.7]), inward=True)
    sun = Light("Sun", "SUN", light_matrix((0, -6, 6), (0.3, np.cos(ELEVATION),
                                                          -np.sin(ELEVATION))), power=SUN)
    cam = Camera(look_at_matrix([0.0, -1.8, 1.2], [0.0, 0.0, 1.5]),
                 perspective_matrix(1.6, 1.0, 0.05, 50.0), (48, 48))
    out = []
    for on in (True, False):
        scene = make_scene(room, materials=[Material("white")], lights=[sun], camera=cam,
                           settings=GISettings(grid_resolution=16, antialias=1,
                                               contact_light=on, cascades_auto=False,
                                               cascades=1))
        eng = engine.Engine()
        passes = deferred.render(eng, scene, eng.update(scene))
        assert (passes["Diffuse Color"][..., 0] > 0).all()  # the camera sees only the room
        out.append(passes["Diffuse Indirect"])
    np.testing.assert_array_equal(out[0], out[1])


@pytest.mark.skipif(not jit.enabled(), reason="numba is not installed or LPV_JIT=0")
def test_compiled_sun_view_gather_is_the_numpy_one():
    """gather_at on a sun's view (contact.sun_source) of the parapet, receivers the ground
    and the wall's lit face: compiled and numpy alike."""
    from lpv_core.engine import light_weight
    from lpv_core.scene import lights as lights_mod

    ground = quad([-8, -8, 0], [8, -8, 0], [8, 8, 0], [-8, 8, 0])
    wall = box_triangles(np.array([-2.0, -0.15, 0.0]), np.array([2.0, 0.15, 2.0]))
    sun = Light("Sun", "SUN", light_matrix((0, -6, 6), (0, np.cos(ELEVATION),
                                                          -np.sin(ELEVATION))), power=SUN)
    scene = make_scene(np.concatenate([ground, wall]), materials=[Material("grey")],
                       lights=[sun], camera=None)
    eng = engine.Engine()
    lo, hi = eng.upload(scene, engine.Stats())
    view = lights_mod.light_views(sun, (lo, hi), (np.array([-3.0, -3, -1]), np.array([3.0, 3, 3])))[0]
    size = contact.sun_view_size(view, 0.4)
    source = contact.sun_source(eng.raster, sun, view, size, light_weight(sun)[:, 0])
    rng = np.random.default_rng(5)
    n = 400
    pos = np.c_[rng.uniform(-2, 2, n), rng.uniform(-0.5, -0.16, n), np.zeros(n)]
    nrm = np.tile([0.0, 0.0, 1.0], (n, 1))
    pos[::2] = np.c_[rng.uniform(-2, 2, n // 2), np.full(n // 2, -0.15), rng.uniform(0, 2, n // 2)]
    nrm[::2] = (0.0, -1.0, 0.0)
    args = (pos, nrm, np.full(n, 0.4), np.full(n, 2.0 * view.half_extent / size),
            np.zeros(n, np.int64), contact.view_texels(view, size, pos), source, False)
    got = contact.gather_at(*args)
    with jit.disabled():
        want = contact.gather_at(*args)
    assert (want[1::2, 0] > 0).mean() > 0.9  # the ground by the face is lit by it
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-300)
