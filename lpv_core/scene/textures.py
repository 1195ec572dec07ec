"""Image textures a material's diffuse albedo reads per point: pixels in scene-linear colour
and how Blender's Image Texture node samples them (interpolation, extension)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

INTERPOLATIONS = ("Linear", "Closest", "Cubic", "Smart")
EXTENSIONS = ("REPEAT", "EXTEND", "CLIP", "MIRROR")
# Cosines of the view angle at which Material.diffuse_share is given (those Cycles' layers
# were measured at: tools/measure_principled_layers.py --view), ascending.
SHARE_COS = (0.02, 0.04, 0.07, 0.1, 0.15, 0.2, 0.26, 0.33, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 0.95,
             1.0)


@dataclass
class Texture:
    """An image as the Image Texture node reads it: ``pixels`` (H, W, 3) float32 scene-linear
    colour (the image's colour space already applied; alpha already applied as the node's
    Color output gives it), rows bottom-first like Blender's ``Image.pixels``; ``digest``
    identifies the content (the change tracking and the worker's upload-once key)."""

    name: str
    pixels: np.ndarray = field(repr=False)
    interpolation: str = "Linear"
    extension: str = "REPEAT"
    digest: str = ""


# Texture memory the engine's process keeps for all textures together: 256 MiB of float32
# RGB (12 bytes a texel), 22.4M texels: twenty 1024^2 images whole, one 8192^2 image (768 MiB)
# at 4096^2. A sixteenth of the propagation's 4 GB state guard (sweep.ordinates.STATE_BYTES),
# beside the images Blender itself holds. Larger sets are box-filtered down (fitted_shapes).
BUDGET_BYTES = 256 * 2 ** 20
TEXEL_BYTES = 12


def digest_of(texture: Texture) -> str:
    """The texture's digest, or one of its pixels and sampling modes when it has none."""
    if texture.digest:
        return texture.digest
    import hashlib

    h = hashlib.blake2b(np.ascontiguousarray(texture.pixels, np.float32).tobytes(),
                        digest_size=16)
    h.update(f"{np.shape(texture.pixels)}".encode())
    return h.hexdigest()


def sample(texture: Texture, uv) -> np.ndarray:
    """Colour (N, 3) float32 of ``texture`` at texture coordinates ``uv`` (N, 2), as Cycles'
    Image Texture node reads it (intern/cycles/kernel/device/cpu/image.h): texel (i, j)'s
    centre at ((i + 0.5) / W, (j + 0.5) / H), row 0 the bottom; Closest the texel under the
    point, Linear bilinear, Cubic and Smart the uniform cubic B-spline over 4 x 4 texels
    (Cycles' CPU kernel takes Smart as Cubic); REPEAT wraps, EXTEND clamps to the edge texel,
    MIRROR reflects (the edge texel repeated), CLIP reads texels outside the image as 0.
    Non-finite coordinates read at 0."""
    px = np.asarray(texture.pixels, np.float32)
    if px.ndim != 3 or px.shape[2] != 3 or px.shape[0] < 1 or px.shape[1] < 1:
        raise ValueError(f"texture '{texture.name}': pixels must be (H, W, 3), not "
                         f"{px.shape}")
    if texture.interpolation not in INTERPOLATIONS:
        raise ValueError(f"texture '{texture.name}': interpolation {texture.interpolation!r} "
                         f"is not one of {', '.join(INTERPOLATIONS)}")
    if texture.extension not in EXTENSIONS:
        raise ValueError(f"texture '{texture.name}': extension {texture.extension!r} is not "
                         f"one of {', '.join(EXTENSIONS)}")
    h, w = px.shape[:2]
    flat = px.reshape(-1, 3)
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    uv = np.clip(np.nan_to_num(uv, nan=0.0, posinf=0.0, neginf=0.0), -1e6, 1e6)
    x, y = uv[:, 0] * w, uv[:, 1] * h
    ext = texture.extension
    if texture.interpolation == "Closest":
        (cols, cok), (rows, rok) = _axis(np.floor(x), w, ext), _axis(np.floor(y), h, ext)
        out = np.take(flat, rows * w + cols, axis=0)
        if ext == "CLIP":
            out[~(cok & rok)] = 0.0
        return out
    ix, tx = _split(x - 0.5)
    iy, ty = _split(y - 0.5)
    if texture.interpolation == "Linear":
        taps, wx, wy = (0, 1), (1.0 - tx, tx), (1.0 - ty, ty)
    else:
        taps, wx, wy = (-1, 0, 1, 2), _bspline(tx), _bspline(ty)
    cols = [_axis(ix + a, w, ext) for a in taps]
    out = np.zeros((uv.shape[0], 3), np.float32)
    for b, wyb in zip(taps, wy):
        rows, rok = _axis(iy + b, h, ext)
        rows = rows * w
        for (c, cok), wxa in zip(cols, wx):
            weight = (wxa * wyb).astype(np.float32)
            if ext == "CLIP":  # texels outside the image read as 0
                weight *= rok & cok
            out += weight[:, None] * np.take(flat, rows + c, axis=0)
    return out


def _split(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Integer part (floor) and fraction of ``x``."""
    i = np.floor(x)
    return i.astype(np.int64), x - i


def _bspline(t: np.ndarray) -> tuple:
    """The uniform cubic B-spline's four weights at fraction ``t`` (Cycles'
    SET_CUBIC_SPLINE_WEIGHTS)."""
    return (((-t / 6.0 + 0.5) * t - 0.5) * t + 1.0 / 6.0, (0.5 * t - 1.0) * t * t + 2.0 / 3.0,
            ((-0.5 * t + 0.5) * t + 0.5) * t + 1.0 / 6.0, t * t * t / 6.0)


def _axis(i: np.ndarray, n: int, extension: str) -> tuple[np.ndarray, np.ndarray | None]:
    """Texel indices ``i`` along an axis of ``n`` texels wrapped by ``extension`` (int64),
    and for CLIP whether each lies inside the image."""
    i = np.asarray(i).astype(np.int64)
    if extension == "REPEAT":
        return np.mod(i, n), None
    if extension == "MIRROR":  # Cycles' wrap_mirror: -1 -> 0, n -> n - 1
        m = np.abs(i + (i < 0)) % (2 * n)
        return np.where(m >= n, 2 * n - m - 1, m), None
    inside = (i >= 0) & (i < n) if extension == "CLIP" else None
    return np.clip(i, 0, n - 1), inside  # EXTEND clamps; CLIP's outside texels read 0


def mean(texture: Texture) -> np.ndarray:
    """The texture's mean colour (3,) float32 (every texel alike)."""
    return np.asarray(texture.pixels, np.float64).reshape(-1, 3).mean(axis=0).astype(np.float32)


# ------------------------------------------------------------------ the budget


def fitted_shapes(shapes: list[tuple[int, int]], budget: int = BUDGET_BYTES) -> list:
    """(H, W) of each texture once they fit ``budget`` bytes together: the largest texture
    halved (rounding up) until they fit; each keeps at least 1 x 1."""
    out = [tuple(int(v) for v in s) for s in shapes]
    limit = budget // TEXEL_BYTES
    total = sum(h * w for h, w in out)
    while total > limit:
        k = max(range(len(out)), key=lambda i: out[i][0] * out[i][1])
        h, w = out[k]
        if h * w <= 1:
            break
        out[k] = ((h + 1) // 2, (w + 1) // 2)
        total += out[k][0] * out[k][1] - h * w
    return out


def resampled(pixels: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """``pixels`` (H, W, 3) box-filtered down to ``shape`` (each new texel the area-weighted
    mean of the texels it covers), float32."""
    px = np.asarray(pixels, np.float32)
    if tuple(px.shape[:2]) == tuple(shape):
        return px
    return _box(_box(px, shape[0], 0), shape[1], 1)


def _box(px: np.ndarray, n: int, axis: int) -> np.ndarray:
    """Box filter along ``axis`` to ``n`` samples by the piecewise-linear integral of the
    texels (cumulative sums in float64, a band of rows at a time)."""
    m = px.shape[axis]
    if m == n:
        return px
    edges = np.arange(n + 1) * (m / n)
    i = np.minimum(np.floor(edges).astype(np.int64), m - 1)
    f = (edges - i)
    moved = np.moveaxis(px, axis, 0)
    out = np.empty((n,) + moved.shape[1:], np.float32)
    band = max(1, (16 * 2 ** 20) // max(1, m * 3 * 8))  # about 16 MiB of float64 per band
    for c0 in range(0, moved.shape[1], band):
        part = moved[:, c0:c0 + band].astype(np.float64)
        cum = np.concatenate([np.zeros((1,) + part.shape[1:]), np.cumsum(part, axis=0)])
        at = cum[i] + f[:, None, None] * part[i]
        out[:, c0:c0 + band] = ((at[1:] - at[:-1]) / (m / n)).astype(np.float32)
    return np.moveaxis(out, 0, axis)


# ------------------------------------------------------------- per-point albedo


@dataclass
class Layout:
    """What the per-point albedo of a scene's triangles reads: its distinct textures (by
    digest), each triangle's texture for the Diffuse Color and for the GI reflectance (-1:
    none; the GI one is -1 where the bleed colour replaces albedo x texture), whether its
    corner colours reach the GI, and the per-corner UVs and colours."""

    textures: list
    digests: list
    albedo_texture: np.ndarray  # (T,) int32
    gi_texture: np.ndarray  # (T,) int32
    gi_corners: np.ndarray  # (T,) bool
    uvs: np.ndarray | None
    corner_colors: np.ndarray | None


def layout(materials: list, material_index, uvs=None, corner_colors=None) -> Layout | None:
    """The Layout of a scene's triangles; None when no material has a texture and there are
    no corner colours (the albedo is then per triangle and nothing per point is done)."""
    if corner_colors is None and not any(m.texture is not None for m in materials):
        return None
    textures, digests, slot = [], [], {}
    albedo_id = np.full(len(materials) + 1, -1, np.int32)
    gi_id = np.full(len(materials) + 1, -1, np.int32)
    corners = np.ones(len(materials) + 1, bool)
    for k, m in enumerate(materials):
        corners[k] = m.bleed_color is None
        if m.texture is None:
            continue
        d = digest_of(m.texture)
        if d not in slot:
            slot[d] = len(textures)
            textures.append(m.texture)
            digests.append(d)
        albedo_id[k] = slot[d]
        gi_id[k] = slot[d] if m.bleed_color is None else -1
    mat = np.asarray(material_index, np.int64)
    if corner_colors is not None:
        corner_colors = np.asarray(corner_colors, np.float32)
        if not (np.isfinite(corner_colors).all() and corner_colors.min(initial=0) >= 0):
            corner_colors = np.where(np.isfinite(corner_colors),  # non-finite: no colour
                                     np.maximum(corner_colors, 0), 1).astype(np.float32)
    return Layout(textures, digests, albedo_id[mat], gi_id[mat], corners[mat],
                  None if uvs is None else np.asarray(uvs, np.float32), corner_colors)


class Store:
    """The textures one process holds, fitted to ``budget`` bytes, kept per digest: a texture
    whose digest and fitted size did not change is neither resampled nor copied again."""

    def __init__(self, budget: int = BUDGET_BYTES):
        self.budget = budget
        self._held: dict = {}  # digest -> Texture at its fitted size
        self.prepared = 0  # textures resampled or copied in (the upload-once check)

    def fitted(self, lay: Layout) -> list:
        """The Layout's textures at their fitted sizes (those no longer used are let go)."""
        for tex in lay.textures:
            shape = np.shape(tex.pixels)
            if len(shape) != 3 or shape[2] != 3 or min(shape[:2]) < 1:
                raise ValueError(f"texture '{tex.name}': pixels must be (H, W, 3), not {shape}")
        shapes = fitted_shapes([np.shape(t.pixels)[:2] for t in lay.textures], self.budget)
        held, out = {}, []
        for tex, d, shape in zip(lay.textures, lay.digests, shapes):
            entry = self._held.get(d)
            if entry is None or entry.pixels.shape[:2] != shape:
                px = resampled(tex.pixels, shape)
                if not (np.isfinite(px).all() and px.min() >= 0):  # no NaN reaches a stage
                    px = np.maximum(np.nan_to_num(px, nan=0.0, posinf=0.0, neginf=0.0), 0.0)
                entry = Texture(tex.name, px, tex.interpolation, tex.extension, d)
                self.prepared += 1
            held[d] = entry
            out.append(entry)
        self._held = held
        return out

    def info(self, lay: Layout) -> dict:
        """Stats: textures held, their texels and the ones the budget made smaller."""
        smaller = [t.name for t, d in zip(lay.textures, lay.digests)
                   if self._held[d].pixels.shape != np.shape(t.pixels)]
        return {"count": len(lay.textures), "budget_mib": self.budget / 2 ** 20,
                "texels": int(sum(self._held[d].pixels[..., 0].size for d in lay.digests)),
                "resampled": smaller}


class Surface:
    """A Layout with its fitted textures: the factor (albedo x corner colour x texture over
    the per-triangle albedo or GI reflectance) at points given by triangle and barycentric
    coordinates."""

    def __init__(self, lay: Layout, store: Store):
        self.layout = lay
        self.textures = store.fitted(lay)
        self.info = store.info(lay)

    def factor(self, tri: np.ndarray, bary: np.ndarray, gi: bool = False) -> np.ndarray:
        """(N, 3) float32 multiplier at the points of triangles ``tri`` (N,) with barycentric
        coordinates ``bary`` (N, 2) of corners 1 and 2; ``gi``: of the GI reflectance (the
        bleed colour, where set, replaces albedo x corner colour x texture)."""
        lay = self.layout
        tri = np.asarray(tri, np.int64)
        b = np.asarray(bary, np.float64).reshape(-1, 2)
        w = np.stack([1.0 - b[:, 0] - b[:, 1], b[:, 0], b[:, 1]], axis=1)
        out = np.ones((tri.shape[0], 3), np.float32)
        if lay.corner_colors is not None:
            col = np.einsum("nk,nkc->nc", w, lay.corner_colors[tri]).astype(np.float32)
            if gi:
                col[~lay.gi_corners[tri]] = 1.0
            out *= col
        ids = (lay.gi_texture if gi else lay.albedo_texture)[tri]
        used = np.unique(ids[ids >= 0])
        if used.size:
            uv = (np.zeros((tri.shape[0], 2)) if lay.uvs is None
                  else np.einsum("nk,nkc->nc", w, lay.uvs[tri]))
            for k in used:
                sel = ids == k
                out[sel] *= sample(self.textures[k], uv[sel])
        return out


# ------------------------------------------------- the pixel footprint and the view angle

# Sub-points per side of a cell whose texture varies (FOOTPRINT_TOL): 8^2 = 64 resolve an
# edge's area fraction to 1/16 of the step at worst (axis-aligned), far less when oblique; the
# renderer's 2x2 cells make it 16^2 per pixel, Cycles' 512 samples a noise of up to 2 %.
FOOTPRINT_SPLIT = 8
# A pixel is refined where the second difference of the centre factors along a row or a
# column exceeds half an 8-bit step: zero for a factor linear across the neighbours (a smooth
# gradient, a bilinear patch), so only texel edges, kinks and curvature are refined.
FOOTPRINT_TOL = 1.0 / 510.0
_CHUNK = 1 << 18  # sub-points a step (memory: a few float64 arrays of 3 each)


def footprint_factor(surface: Surface, tri: np.ndarray, centre: np.ndarray, covered: np.ndarray,
                     bary_at) -> tuple:
    """Surface.factor integrated over each pixel's cell instead of read at its centre: where
    the centre factors ``centre`` (N, 3) of the ``covered`` (H, W) pixels (row-major) bend
    across a pixel (its neighbours' second difference in x or y > FOOTPRINT_TOL: a texel edge
    within a pixel of it), the mean of FOOTPRINT_SPLIT^2 sub-points of its cell replaces it;
    ``bary_at(rows, offsets (K, 2) in cell units in [-0.5, 0.5])`` gives their barycentrics
    (len(rows), K, 2) on the pixel's triangle plane. Each read follows the texture's
    interpolation and extension (sample). Returns (factor (N, 3), pixels refined)."""
    out = np.array(centre, np.float32, copy=True)
    img = np.zeros(covered.shape + (3,), np.float32)
    img[covered] = out
    ids = np.zeros(covered.shape, np.int32)
    ids[covered] = surface.layout.albedo_texture[tri] + 2  # 0: uncovered, 1: untextured
    bend = np.zeros(covered.shape, bool)
    for im, idm, bd in ((img, ids, bend), (img.transpose(1, 0, 2), ids.T, bend.T)):
        # along rows, then columns (views); a neighbour off the image or of another texture
        # counts as the pixel's own value
        mid = im[1:-1]
        lo = np.where((idm[:-2] == idm[1:-1])[..., None], im[:-2], mid)
        hi = np.where((idm[2:] == idm[1:-1])[..., None], im[2:], mid)
        bd[1:-1] |= np.abs(lo + hi - 2 * mid).max(axis=2) > FOOTPRINT_TOL
        for e, nb in ((0, 1), (-1, -2)):
            same = (idm[e] == idm[nb])[:, None]
            bd[e] |= np.abs(np.where(same, im[nb] - im[e], 0)).max(axis=1) > FOOTPRINT_TOL
    # corner colours alone are linear over a triangle: their mean over a cell is the centre's
    rows = np.flatnonzero(bend[covered] & (ids[covered] > 1))
    k = FOOTPRINT_SPLIT
    g = (np.arange(k) + 0.5) / k
    wx, wy = (w.ravel() for w in np.meshgrid(g, g, indexing="ij"))
    # the sub-points' barycentrics bilinear between the rays through the cell's 4 corners:
    # exact for an orthographic view, off by (cell / depth)^2 of the cell in perspective
    weights = np.stack([(1 - wx) * (1 - wy), wx * (1 - wy), (1 - wx) * wy, wx * wy], axis=1)
    corners = np.array([[-0.5, -0.5], [0.5, -0.5], [-0.5, 0.5], [0.5, 0.5]])
    step = max(1, _CHUNK // (k * k))
    for c in range(0, rows.size, step):
        r = rows[c:c + step]
        b = np.einsum("sc,ncd->nsd", weights, bary_at(r, corners)).reshape(-1, 2)
        f = surface.factor(np.repeat(tri[r], k * k), b)
        out[r] = f.reshape(-1, k * k, 3).mean(axis=1)
    return out, int(rows.size)


def plane_barycentric(corners: np.ndarray, origins: np.ndarray, directions: np.ndarray,
                      fallback: np.ndarray) -> np.ndarray:
    """Barycentric coordinates (N, K, 2) where the rays ``origins`` + t ``directions``
    (N, K, 3) meet the planes of the triangles ``corners`` (N, 3, 3), extrapolated past the
    triangle; ``fallback`` (N, 2) where a ray misses the plane (parallel, behind, non-finite)."""
    c = np.asarray(corners, np.float64)
    n = np.cross(c[:, 1] - c[:, 0], c[:, 2] - c[:, 0])[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = ((c[:, None, 0] - origins) * n).sum(2) / (directions * n).sum(2)
    ok = np.isfinite(t) & (t > 0) & (np.abs(n).sum(2) > 0)  # a degenerate triangle: no plane
    hit = origins + np.where(ok, t, 0.0)[..., None] * directions
    k = hit.shape[1]
    b = barycentric(np.repeat(c, k, axis=0), hit.reshape(-1, 3)).reshape(-1, k, 2)
    ok &= np.isfinite(b).all(2)
    return np.where(ok[..., None], b, np.asarray(fallback, np.float64)[:, None])


def view_shares(materials: list, material_index) -> tuple | None:
    """(per-triangle row (T,) int32, -1 none; table (S, K, 3) float32) of the materials'
    diffuse_share over SHARE_COS, or None when no material has one."""
    rows = [k for k, m in enumerate(materials) if getattr(m, "diffuse_share", None) is not None]
    if not rows:
        return None
    ids = np.full(len(materials) + 1, -1, np.int32)
    ids[rows] = np.arange(len(rows))
    table = np.stack([np.asarray(materials[k].diffuse_share, np.float32).reshape(-1, 3)
                      for k in rows])
    return ids[np.asarray(material_index, np.int64)], table


def share_at(table: np.ndarray, rows: np.ndarray, cos_view: np.ndarray) -> np.ndarray:
    """(N, 3) diffuse share of rows ``rows`` (N,) of ``table`` (S, K, 3) at ``cos_view`` (N,):
    linear in the cosine between SHARE_COS, held at its ends."""
    grid = np.asarray(SHARE_COS, np.float64)
    x = np.clip(np.nan_to_num(np.abs(cos_view), nan=1.0), grid[0], grid[-1])
    i = np.clip(np.searchsorted(grid, x) - 1, 0, grid.size - 2)
    t = ((x - grid[i]) / (grid[i + 1] - grid[i]))[:, None]
    return ((1.0 - t) * table[rows, i] + t * table[rows, i + 1]).astype(np.float32)


def barycentric(corners: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Barycentric coordinates (N, 2) of corners 1 and 2 of ``points`` (N, 3) in the
    triangles ``corners`` (N, 3, 3) (the points' projection onto each triangle's plane)."""
    c = np.asarray(corners, np.float64)
    e1, e2, p = c[:, 1] - c[:, 0], c[:, 2] - c[:, 0], np.asarray(points, np.float64) - c[:, 0]
    d11, d12, d22 = (e1 * e1).sum(1), (e1 * e2).sum(1), (e2 * e2).sum(1)
    p1, p2 = (p * e1).sum(1), (p * e2).sum(1)
    det = d11 * d22 - d12 * d12
    det = np.where(det > 0, det, 1.0)
    return np.stack([(d22 * p1 - d12 * p2) / det, (d11 * p2 - d12 * p1) / det], axis=1)
