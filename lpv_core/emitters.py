"""Emissive triangles as light sources without any RSM: clusters of emitting triangles (per
material and object, split along their longest extent), each triangle's exact unoccluded
irradiance at a receiver by Lambert's contour integral over the triangle clipped to the
receiver's horizon (valid in the near field, beside a panel), times the visibility of the
cluster's centre (a cube shadow map, like a point light's, of the scene without emitters).
Emission is two-sided, as Cycles' mesh lights."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .scene.model import Light, Scene

MAX_CLUSTERS = 8  # shadow maps of 6 faces each; larger emitters split until this many
SPLIT_SHARE = 1.0 / 16.0  # a cluster wider than this share of the box diagonal is split
SHADOW_RESOLUTION = 256


@dataclass
class Cluster:
    """Emitting triangles of one material (and object) seen from one shadow-map centre."""

    name: str
    material: int
    triangles: np.ndarray  # (n,) indices into the scene's triangles
    corners: np.ndarray  # (n, 3, 3) float64
    radiance: np.ndarray  # (3,) float64
    centre: np.ndarray
    radius: float
    side: int = 0  # +1 / -1: emits only along / against ``normal`` (its other side capped)
    normal: np.ndarray | None = None  # area-weighted mean winding normal (unit), or None

    def light(self) -> Light:
        """The POINT light whose cube shadow map gives the cluster's visibility (radius: its
        size, the soft shadows' source size)."""
        m = np.eye(4)
        m[:3, 3] = self.centre
        return Light(f"emission {self.name}", "POINT", m, np.ones(3, np.float32), 1.0,
                     radius=self.radius)


def emissive_materials(scene: Scene) -> list[int]:
    """Indices of the materials that emit (radiance above 0 in some channel) and that some
    triangle uses."""
    used = set(np.unique(scene.material_index).tolist())
    return [i for i, m in enumerate(scene.materials)
            if i in used and np.isfinite(m.emission).all() and float(np.max(m.emission)) > 0]


def clusters(scene: Scene, diagonal: float) -> list[Cluster]:
    """The scene's emitters grouped per material and object, the widest split at the median
    of its triangles' centroids along its longest extent while wider than SPLIT_SHARE x
    ``diagonal`` (the LPV box's) and fewer than MAX_CLUSTERS."""
    groups = []
    obj = scene.object_index if scene.object_index is not None else np.zeros(
        scene.triangle_count, np.int32)
    for mi in emissive_materials(scene):
        tri = np.nonzero(scene.material_index == mi)[0]
        for o in np.unique(obj[tri]):
            groups.append((mi, int(o), tri[obj[tri] == o]))

    def extent(g):
        c = scene.positions[g[2]].reshape(-1, 3)
        return float(np.max(c.max(0) - c.min(0)))

    while len(groups) < MAX_CLUSTERS:
        widest = max(range(len(groups)), key=lambda i: extent(groups[i]), default=None)
        if widest is None or extent(groups[widest]) <= SPLIT_SHARE * diagonal \
                or groups[widest][2].size < 2:
            break
        mi, o, tri = groups.pop(widest)
        cen = scene.positions[tri].mean(axis=1)
        axis = int(np.argmax(cen.max(0) - cen.min(0)))
        order = tri[np.argsort(cen[:, axis], kind="stable")]
        half = order.size // 2
        groups += [(mi, o, np.sort(order[:half])), (mi, o, np.sort(order[half:]))]
    out, sides = [], {}
    for n, (mi, o, tri) in enumerate(groups):
        corners = scene.positions[tri].astype(np.float64)
        area = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0],
                                             corners[:, 2] - corners[:, 0]), axis=1)
        centre = (corners.mean(axis=1) * area[:, None]).sum(0) / max(area.sum(), 1e-300)
        radius = float(np.max(np.linalg.norm(corners.reshape(-1, 3) - centre, axis=1)))
        owner = (scene.object_names[o] if 0 <= o < len(scene.object_names) else "")
        name = f"'{scene.materials[mi].name}'" + (f" on '{owner}'" if owner else "") + \
            f" #{n}"
        vec = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]).sum(0)
        size = float(np.linalg.norm(vec))
        normal = vec / size if size > 0.5 * 2 * area.sum() else None  # a flat-ish cluster
        if o not in sides:  # once per object, whose clusters share it
            sides[o] = outward_side(scene, obj == o)
        out.append(Cluster(name, mi, tri, corners,
                           np.asarray(scene.materials[mi].emission, np.float64), centre, radius,
                           side=sides[o], normal=normal))
    return out


def outward_side(scene: Scene, mask: np.ndarray) -> int:
    """+1 / -1 when the triangles ``mask`` selects (an object's) close a volume, consistently
    wound, with their winding normals pointing out / in; 0 otherwise. Light a closed emitter
    sends from the inner side of its faces stays inside it (Cycles' two-sided emission meets
    the object's own faces), where its own shadow map, rendered without the emitters, would
    let it through: such an emitter emits from its outer side only."""
    p = np.asarray(scene.positions, np.float64)[mask]
    if p.shape[0] < 4:
        return 0
    _, vid = np.unique(p.reshape(-1, 3), axis=0, return_inverse=True)
    vid = vid.reshape(-1, 3).astype(np.int64)
    n = int(vid.max()) + 1
    a, b = vid, np.roll(vid, -1, axis=1)  # each triangle's directed edges a -> b
    edges = (a * n + b).ravel()
    reverse = (b * n + a).ravel()
    if np.unique(edges).size != edges.size:  # an edge used twice in one direction
        return 0
    if not np.isin(reverse, edges, assume_unique=True).all():  # an open or mis-wound edge
        return 0
    volume = float(np.einsum("ij,ij->i", p[:, 0], np.cross(p[:, 1], p[:, 2])).sum())
    return 1 if volume > 0 else -1 if volume < 0 else 0


CAPPED_SHARE = 0.9  # of a side's cosine-weighted view closed within the cluster's radius


def capped_side(cluster: Cluster, shadow) -> int:
    """+1 / -1 when the side of a flat cluster against / along its normal is covered, within
    its radius, over CAPPED_SHARE of that side's cosine-weighted view in its cube ``shadow`` (a
    luminaire's housing, a wall behind a screen): the cluster then emits only from the other
    side (0: both), since light under the cap stays under it and the grid cannot hold it."""
    from .scene.lights import texel_rays

    if cluster.normal is None or shadow is None:
        return 0
    res, step = shadow.resolution, max(1, shadow.resolution // 64)
    rows, cols = np.meshgrid(np.arange(0, res, step), np.arange(0, res, step), indexing="ij")
    near, total = np.zeros(2), np.zeros(2)
    for view, depth in zip(shadow.views, shadow.depths):
        dirs, solid = texel_rays(view, rows.ravel(), cols.ravel(), res, res)
        c = dirs @ cluster.normal
        w = solid * np.abs(c) * step * step
        closed = depth[rows.ravel(), cols.ravel()] < cluster.radius
        for i, sel in enumerate((c > 0, c < 0)):
            total[i] += w[sel].sum()
            near[i] += w[sel & closed].sum()
    share = near / np.maximum(total, 1e-300)
    if share[1] >= CAPPED_SHARE > share[0]:
        return 1
    if share[0] >= CAPPED_SHARE > share[1]:
        return -1
    return 0


def triangle_irradiance(corners: np.ndarray, positions: np.ndarray,
                        normals: np.ndarray, side: int = 0) -> np.ndarray:
    """(M,) irradiance at receivers (M, 3) with unit normals from unit-radiance triangles
    (T, 3, 3), summed: E = 1/2 |sum_edges theta_e n.(a x b)/|a x b||, Lambert's contour
    integral over each triangle clipped to the receiver's upper half-space (the clipped
    polygon's edge along the horizon included); ``side`` +1 / -1: only receivers in front of
    / behind each triangle's winding normal."""
    p = np.asarray(positions, np.float64)
    n = np.asarray(normals, np.float64)
    total = np.zeros(p.shape[0])
    for tri in np.asarray(corners, np.float64).reshape(-1, 3, 3):
        v = [tri[i][None, :] - p for i in range(3)]  # vertices relative to the receivers
        # above the horizon by more than rounding: a receiver in the triangle's own plane (the
        # emitter itself, a coplanar ceiling) gets nothing from it
        h = [np.einsum("ij,ij->i", vi, n) - 1e-9 * np.linalg.norm(vi, axis=1) for vi in v]
        acc = np.zeros(p.shape[0])
        x_out = np.zeros_like(p)
        x_in = np.zeros_like(p)
        cut = np.zeros(p.shape[0], bool)
        for i in range(3):
            a, b, ha, hb = v[i], v[(i + 1) % 3], h[i], h[(i + 1) % 3]
            up_a, up_b = ha > 0, hb > 0
            t = (ha / np.where(ha != hb, ha - hb, 1.0))[:, None]
            x = a + t * (b - a)  # where the edge crosses the horizon
            s = np.where((up_a | ~up_b)[:, None], a, x)
            e = np.where((up_b | ~up_a)[:, None], b, x)
            acc += np.where(up_a | up_b, _edge(s, e, n), 0.0)
            leaving, entering = up_a & ~up_b, ~up_a & up_b
            x_out = np.where(leaving[:, None], x, x_out)
            x_in = np.where(entering[:, None], x, x_in)
            cut |= leaving
        acc += np.where(cut, _edge(x_out, x_in, n), 0.0)
        if side:
            nt = np.cross(tri[1] - tri[0], tri[2] - tri[0])
            acc = np.where(side * ((p - tri[0]) @ nt) > 0, acc, 0.0)
        total += 0.5 * np.abs(acc)
    return total


def _edge(a: np.ndarray, b: np.ndarray, n: np.ndarray) -> np.ndarray:
    """theta n.(a x b)/|a x b| of the edge a -> b seen from the origin (0 where degenerate)."""
    c = np.cross(a, b)
    length = np.linalg.norm(c, axis=1)
    theta = np.arctan2(length, np.einsum("ij,ij->i", a, b))
    return np.where(length > 0, theta * np.einsum("ij,ij->i", c, n)
                    / np.where(length > 0, length, 1.0), 0.0)


def irradiance(cluster: Cluster, shadow, positions: np.ndarray,
               normals: np.ndarray) -> np.ndarray:
    """(M, 3) W/m^2 from ``cluster`` at receivers: contour irradiance x radiance x the
    visibility of its centre in ``shadow`` (a direct.ShadowMap, None: unoccluded)."""
    from .render import direct

    e = triangle_irradiance(cluster.corners, positions, normals, cluster.side)
    if shadow is not None:
        sel = np.nonzero(e > 0)[0]
        if sel.size:
            e[sel] *= direct.visibility(shadow, np.asarray(positions, np.float64)[sel],
                                        np.asarray(normals, np.float64)[sel])
    return e[:, None] * cluster.radiance
