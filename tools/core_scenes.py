"""A Cornell-style box built from numpy arrays (no bpy): for core tests and benchmarks."""

from __future__ import annotations

import numpy as np

from lpv_core.scene import Camera, GISettings, Light, Material, Scene, make_scene


def box_triangles(lo, hi, inward: bool = False) -> np.ndarray:
    """12 triangles (12, 3, 3) of an axis-aligned box; normals outward (or inward)."""
    lo = np.asarray(lo, np.float64)
    hi = np.asarray(hi, np.float64)
    c = np.array([[x, y, z] for z in (lo[2], hi[2]) for y in (lo[1], hi[1])
                  for x in (lo[0], hi[0])])
    quads = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
    tris = []
    for a, b, cc, d in quads:
        t1, t2 = (a, b, cc), (a, cc, d)
        if inward:
            t1, t2 = t1[::-1], t2[::-1]
        tris += [c[list(t1)], c[list(t2)]]
    return np.array(tris)


def quad(p0, p1, p2, p3) -> np.ndarray:
    """Two triangles of the quad p0-p1-p2-p3 (counter-clockwise seen from the normal side)."""
    p = np.asarray([p0, p1, p2, p3], np.float64)
    return np.array([p[[0, 1, 2]], p[[0, 2, 3]]])


def light_matrix(position, direction) -> np.ndarray:
    """Light-to-world 4x4 whose local -Z points along ``direction``."""
    d = np.asarray(direction, np.float64)
    d = d / np.linalg.norm(d)
    z = -d
    up = np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(up, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = x, y, z, position
    return m


def cornell_box(
    light_type: str = "SPOT",
    resolution: tuple[int, int] = (128, 128),
    settings: GISettings | None = None,
    scale: float = 1.0,
    offset=(0.0, 0.0, 0.0),
    power: float = 300.0,
) -> Scene:
    """A 2 m box (x: -1..1, y: -1..1 depth, z: 0..2), red left, green right, open front (y=-1)."""
    off = np.asarray(offset, np.float64)
    s = float(scale)
    mats = [Material("white", np.array([0.8, 0.8, 0.8], np.float32)),
            Material("red", np.array([0.8, 0.1, 0.1], np.float32)),
            Material("green", np.array([0.1, 0.8, 0.1], np.float32))]
    tris, mat = [], []

    def add(t, m):
        tris.append(t)
        mat.extend([m] * len(t))

    add(quad((-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)), 0)  # floor
    add(quad((-1, -1, 2), (-1, 1, 2), (1, 1, 2), (1, -1, 2)), 0)  # ceiling
    add(quad((-1, 1, 0), (1, 1, 0), (1, 1, 2), (-1, 1, 2)), 0)  # back
    add(quad((-1, -1, 0), (-1, 1, 0), (-1, 1, 2), (-1, -1, 2)), 1)  # left (red)
    add(quad((1, -1, 0), (1, -1, 2), (1, 1, 2), (1, 1, 0)), 2)  # right (green)
    add(box_triangles((-0.7, -0.1, 0), (-0.1, 0.6, 1.2)), 0)  # tall block
    add(box_triangles((0.15, -0.6, 0), (0.75, 0.0, 0.6)), 0)  # short block
    pos = np.concatenate(tris) * s + off
    lights = []
    if light_type == "SPOT":
        lights.append(Light("Spot", "SPOT", light_matrix(np.array([0, 0, 1.9]) * s + off,
                                                        (0, 0, -1)),
                            power=power * s * s, spot_size=np.radians(120), spot_blend=0.15))
    elif light_type == "POINT":
        lights.append(Light("Point", "POINT", light_matrix(np.array([0, 0, 1.6]) * s + off,
                                                          (0, 0, -1)), power=power * s * s))
    elif light_type == "SUN":
        lights.append(Light("Sun", "SUN", light_matrix(off, (0.3, 0.5, -0.8)), power=3.0))
    elif light_type == "AREA":
        lights.append(Light("Area", "AREA", light_matrix(np.array([0, 0, 1.95]) * s + off,
                                                        (0, 0, -1)), power=power * s * s,
                            size=(0.5 * s, 0.5 * s)))
    elif light_type != "NONE":
        raise ValueError(f"unknown light type {light_type!r}")
    eye = np.array([0.0, -3.8, 1.0]) * s + off
    cam = Camera.look_at(eye, np.array([0.0, 0.0, 1.0]) * s + off, fov_y=np.radians(40),
                         resolution=resolution, near=0.05 * s, far=100.0 * s)
    return make_scene(pos, material_index=np.array(mat), materials=mats, lights=lights,
                      camera=cam, settings=settings or GISettings())


def outdoor(resolution: tuple[int, int] = (128, 96), settings: GISettings | None = None,
            sun_elevation_deg: float = 20.0) -> Scene:
    """A 200 m square of ground with 14 buildings 4-30 m tall under a low sun, camera at
    street level (deterministic layout)."""
    mats = [Material("ground", np.array([0.35, 0.33, 0.3], np.float32)),
            Material("plaster", np.array([0.75, 0.7, 0.6], np.float32)),
            Material("brick", np.array([0.6, 0.25, 0.15], np.float32))]
    tris = [quad((-100, -100, 0), (100, -100, 0), (100, 100, 0), (-100, 100, 0))]
    mat = [0, 0]
    rng = np.random.default_rng(7)
    for i in range(14):
        cx, cy = rng.uniform(-70, 70, 2)
        if abs(cx) < 12 and -60 < cy < 20:
            cx += 30.0  # keep the street in front of the camera open
        w, d = rng.uniform(8, 25, 2)
        h = rng.uniform(4, 30)
        tris.append(box_triangles((cx - w / 2, cy - d / 2, 0), (cx + w / 2, cy + d / 2, h)))
        mat += [1 + i % 2] * 12
    pos = np.concatenate(tris)
    el = np.radians(sun_elevation_deg)
    sun = Light("Sun", "SUN", light_matrix((0, 0, 0), (-np.cos(el) * 0.6, -np.cos(el) * 0.8,
                                                        -np.sin(el))), power=4.0)
    cam = Camera.look_at((0.0, -60.0, 1.7), (0.0, 40.0, 8.0), fov_y=np.radians(50),
                         resolution=resolution, near=0.1, far=500.0)
    return make_scene(pos, material_index=np.array(mat), materials=mats, lights=[sun],
                      camera=cam, settings=settings or GISettings())


def two_rooms(settings: GISettings | None = None, wall: float = 0.2) -> Scene:
    """Two 4 x 4 x 3 m rooms side by side (x), sharing a ``wall``-thick wall; the left one is
    lit by a sun through a 1.6 m hole in its roof, the right one is closed on every side."""
    t = wall
    boxes = []
    for x0 in (0.0, 4.0 + t):
        x1 = x0 + 4.0
        boxes += [((x0 - t, -t, -t), (x1 + t, 4.0 + t, 0.0)),  # floor slab
                  ((x0 - t, -t, 0.0), (x1 + t, 0.0, 3.0)),  # front wall
                  ((x0 - t, 4.0, 0.0), (x1 + t, 4.0 + t, 3.0))]  # back wall
    boxes += [((-t, 0.0, 0.0), (0.0, 4.0, 3.0)),  # outer left wall
              ((4.0, 0.0, 0.0), (4.0 + t, 4.0, 3.0)),  # the shared wall
              ((8.0 + t, 0.0, 0.0), (8.0 + 2 * t, 4.0, 3.0))]  # outer right wall
    # Left roof with a hole from 1.2 to 2.8 in x and y; right roof closed.
    boxes += [((-t, -t, 3.0), (1.2, 4.0 + t, 3.0 + t)), ((2.8, -t, 3.0), (4.0 + t, 4.0 + t, 3.0 + t)),
              ((1.2, -t, 3.0), (2.8, 1.2, 3.0 + t)), ((1.2, 2.8, 3.0), (2.8, 4.0 + t, 3.0 + t)),
              ((4.0, -t, 3.0), (8.0 + 2 * t, 4.0 + t, 3.0 + t))]
    pos = np.concatenate([box_triangles(lo, hi) for lo, hi in boxes])
    sun = Light("Sun", "SUN", light_matrix((0, 0, 0), (0.15, 0.1, -1.0)), power=5.0)
    cam = Camera.look_at((2.0, 0.5, 1.5), (2.0, 4.0, 1.0), resolution=(32, 32))
    return make_scene(pos, materials=[Material("white", np.full(3, 0.7, np.float32))],
                      lights=[sun], camera=cam, settings=settings or GISettings())
