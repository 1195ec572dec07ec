"""Core scene model: triangle arrays, materials, lights, camera and GI settings.

Everything is plain numpy in Blender's units (metres, W for point/spot/area power, W/m^2 for
sun irradiance, scene-linear colour). The add-on fills it from a depsgraph; tests and the demo
build it directly. Nothing here imports bpy.
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass, field

import numpy as np

from .textures import Texture, digest_of
from .world import World

LIGHT_TYPES = ("POINT", "SPOT", "SUN", "AREA")


@dataclass
class Material:
    """A material as LPV sees it: the diffuse albedo Cycles reports as Diffuse Color (times
    ``texture`` at each point's UV where set, and the corner colours where the scene has
    them), the radiance it emits, and the artist's GI bleed overrides."""

    name: str
    albedo: np.ndarray = field(default_factory=lambda: np.full(3, 0.8, np.float32))
    # Image the albedo is multiplied by per point (Scene.uvs), None: the albedo alone.
    texture: Texture | None = None
    # Emitted radiance (W sr^-1 m^-2 per unit colour: Emission colour x Strength, Cycles'
    # units) and the GI intensity of that light, like a light's.
    emission: np.ndarray = field(default_factory=lambda: np.zeros(3, np.float32))
    emission_gi_intensity: float = 1.0
    # Diffuse Color over the view angle as multiples of ``albedo`` (textures.SHARE_COS, 3), 1 head-on:
    # Cycles' layers above the diffuse reflect more towards grazing. None: view-independent.
    diffuse_share: np.ndarray | None = None
    # Colour and strength this material bounces into GI (None: use albedo).
    bleed_color: np.ndarray | None = None
    bleed_intensity: float = 1.0
    # Glossy (mirror-like) reflectance: the share of incident flux a metal or Glossy BSDF
    # reflects around the mirror direction (rsm.view_vpls' mirror VPLs); zeros: none.
    specular: np.ndarray = field(default_factory=lambda: np.zeros(3, np.float32))
    # Coverage (0-1): the share of the surface that is there (Principled Alpha, a Transparent
    # BSDF's share); every pass keeps a fragment with this probability (hashed alpha), so
    # the albedo, emission and glossy reflectance above are those of the covered part.
    alpha: float = 1.0
    # An image's alpha (pixels (H, W, 1), rows bottom-first) the coverage takes per point of
    # the material's UV map instead of ``alpha`` (which is then 1); None: none
    alpha_texture: Texture | None = None
    # Share of the Diffuse Color that is a Translucent BSDF's: its light comes through the
    # surface from the far side (the side away from the viewer), not from the near side
    translucency: float = 0.0
    # A tangent-space normal map (a Normal Map node's Color: pixels (H, W, 3) in 0-1, rows
    # bottom-first) read through the material's UV map (Scene.uvs, Scene.tangents), and its
    # Strength; None: the mesh's own normals
    normal_texture: Texture | None = None
    normal_strength: float = 1.0

    def gi_reflectance(self) -> np.ndarray:
        """Reflectance used for injected (bounced) flux: bleed colour x intensity, else albedo."""
        base = self.albedo if self.bleed_color is None else self.bleed_color
        return np.asarray(base, np.float32) * np.float32(self.bleed_intensity)


@dataclass
class Light:
    """A light in Blender units.

    ``power`` is W for POINT/SPOT/AREA (exposure, normalize and temperature already applied by
    the extractor) and W/m^2 for SUN. ``matrix`` is the 4x4 light-to-world transform; the light
    shines along its local -Z axis like Blender's.
    """

    name: str
    type: str
    matrix: np.ndarray
    color: np.ndarray = field(default_factory=lambda: np.ones(3, np.float32))
    power: float = 100.0
    spot_size: float = np.pi / 4.0  # full cone angle (rad)
    spot_blend: float = 0.15
    radius: float = 0.0  # shadow_soft_size
    soft_falloff: bool = True  # point / spot: use_soft_falloff (a disk facing the receiver)
    size: tuple[float, float] = (1.0, 1.0)  # area light extent (m) along local X and Y
    gi_intensity: float = 1.0
    gi_color: np.ndarray = field(default_factory=lambda: np.ones(3, np.float32))  # GI tint
    cast_shadow: bool = True
    shape: str = "SQUARE"  # area light: SQUARE, RECTANGLE, DISK or ELLIPSE
    spread: float = np.pi  # area light: Blender's spread angle (rad)
    angle: float = 0.0  # sun: angular diameter (rad)

    @property
    def position(self) -> np.ndarray:
        return np.asarray(self.matrix, np.float64)[:3, 3]

    @property
    def direction(self) -> np.ndarray:
        """Unit world-space direction the light points to (local -Z)."""
        d = -np.asarray(self.matrix, np.float64)[:3, 2]
        n = np.linalg.norm(d)
        return d / n if n > 0 else np.array([0.0, 0.0, -1.0])


@dataclass
class Camera:
    """A pinhole or orthographic camera: world-to-view and OpenGL projection matrices."""

    view: np.ndarray  # 4x4 world -> camera (camera looks along -Z)
    projection: np.ndarray  # 4x4 OpenGL clip matrix
    resolution: tuple[int, int] = (256, 256)  # (width, height)

    @property
    def position(self) -> np.ndarray:
        return np.linalg.inv(np.asarray(self.view, np.float64))[:3, 3]

    @staticmethod
    def look_at(
        eye,
        target,
        up=(0.0, 0.0, 1.0),
        fov_y: float = np.radians(40.0),
        resolution: tuple[int, int] = (256, 256),
        near: float = 0.05,
        far: float = 1000.0,
    ) -> Camera:
        """A perspective camera at ``eye`` looking at ``target`` (vertical field of view)."""
        view = look_at_matrix(eye, target, up)
        aspect = resolution[0] / resolution[1]
        return Camera(view, perspective_matrix(fov_y, aspect, near, far), tuple(resolution))


@dataclass
class GISettings:
    """Quality and artist settings for one LPV update. Each value must lie in its
    SETTING_RANGES entry (grid_resolution 4 to max_grid_resolution(), 85 at the 4 GB guard;
    cascades, bounces and antialias 1 to 8; iterations 0 to 1000; rsm_resolution 16 to 2048;
    shadow_resolution 16 to 4096, all whole numbers; intensity 0.0 to 100.0; angular dom or
    sh; backend auto, numpy or gl; docs/user-guide.md): construction and ``updated`` raise
    ValueError naming the setting, the value and the range."""

    grid_resolution: int = 32
    cascades: int = 3  # at most this many; with cascades_auto the planner picks per view
    cascades_auto: bool = True  # planner.cascade_count: 1 for an enclosed view, more if open
    # Propagation steps of "sh" (0: automatic, engine.auto_iterations). "dom" always solves
    # the limit of infinitely many steps in one sweep and ignores it.
    iterations: int = 0
    # Transport (propagation/): "dom" flux along 64 directions, swept to convergence (the
    # product); "sh" KD10's clamped 2-band SH (the baseline)
    angular: str = "dom"
    rsm_resolution: int = 256
    occlusion: bool = True
    bounces: int = 1
    backend: str = "auto"  # "numpy", "gl" (moderngl compute) or "auto" (fastest per stage)
    intensity: float = 1.0  # global GI multiplier (keyframable in the add-on)
    shadow_resolution: int = 1024
    # Sub-pixel samples per pixel side of a render (deferred.render; Cycles' 1-pixel box
    # filter): 1 = one sample at the centre. Output only: the LPV does not depend on it.
    antialias: int = 2
    # The render's contact light (render/contact.py): the bounce from within a cell, gathered
    # from each sample's pixels. Output only, like antialias; the viewport overlay has none.
    contact_light: bool = True

    def __post_init__(self) -> None:
        if self.angular not in ANGULAR_MODELS:
            raise ValueError(_angular_error(self.angular))
        for f in dataclasses.fields(self):  # a subclass's own fields are its own to check
            if f.name in SETTING_RANGES:
                setattr(self, f.name, _checked(f.name, getattr(self, f.name)))

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)

    def updated(self, **changes) -> GISettings:
        """A copy with ``changes`` applied; unknown keys raise ValueError naming the key, a
        retired setting or transport model a ValueError saying what to use instead."""
        known = {f.name: f for f in dataclasses.fields(self)}
        values = {}
        for key, value in changes.items():
            if key in RETIRED_SETTINGS:
                raise ValueError(f"GI setting '{key}' was retired: {RETIRED_SETTINGS[key]}")
            if key not in known:
                raise ValueError(f"unknown GI setting '{key}' (known: {', '.join(sorted(known))})")
            current = getattr(self, key)
            values[key] = _coerce(key, value, current)
        return dataclasses.replace(self, **values)


ANGULAR_MODELS = ("dom", "sh")  # the transport models (propagation/)
BACKENDS = ("auto", "numpy", "gl")
# What each GI setting may be (GISettings refuses the rest; the add-on's properties take their
# limits from here): numbers (low, high) inclusive, whole numbers where the bounds are ints;
# names: the choices; None: on/off. grid_resolution's upper end is what the propagation's
# memory guard admits (max_grid_resolution).
SETTING_RANGES = {
    "grid_resolution": (4, None), "cascades": (1, 8), "cascades_auto": None,
    "iterations": (0, 1000), "angular": ANGULAR_MODELS, "rsm_resolution": (16, 2048),
    "occlusion": None, "bounces": (1, 8), "backend": BACKENDS, "intensity": (0.0, 100.0),
    "shadow_resolution": (16, 4096), "antialias": (1, 8), "contact_light": None,
}


@functools.cache
def max_grid_resolution() -> int:
    """The largest grid the engine's memory guard admits (sweep.check_memory, with the shell
    several cascades need): the upper end of grid_resolution."""
    from ..propagation import sweep  # the propagation imports this module

    r = SETTING_RANGES["grid_resolution"][0]
    while sweep.memory_bytes(r + 1) <= sweep.ordinates.STATE_BYTES:
        r += 1
    return r


def setting_range(key: str):
    """SETTING_RANGES[key], grid_resolution's upper end filled in."""
    if key == "grid_resolution":
        return SETTING_RANGES[key][0], max_grid_resolution()
    return SETTING_RANGES[key]


def _checked(key: str, value):
    """``value`` as setting ``key`` holds it, or ValueError naming the setting, the value and
    what it may be."""
    allowed = setting_range(key)
    shown = f"{value:g}" if isinstance(value, float) else repr(value)
    if allowed is None:
        if isinstance(value, (bool, np.bool_)) or (isinstance(value, int) and value in (0, 1)):
            return bool(value)
        raise ValueError(f"GI setting '{key}': {shown} is not on or off (true or false)")
    if isinstance(allowed[0], str):
        if value in allowed:
            return value
        raise ValueError(f"GI setting '{key}': {shown} is not one of {', '.join(allowed)}")
    lo, hi = allowed
    whole = isinstance(lo, int)
    try:
        number = float(value)
    except (TypeError, ValueError):
        number = float("nan")
    if lo <= number <= hi and (not whole or number.is_integer()):
        return int(number) if whole else number
    why = f"{'a whole number' if whole else 'a number'} from {lo} to {hi}"
    if key == "grid_resolution" and hi < number < 4096:  # the guard's figure (cheap below 4096)
        from ..propagation import sweep

        try:
            sweep.check_memory(int(number))
        except ValueError as exc:
            why += f": {exc}"
    raise ValueError(f"GI setting '{key}': {shown} is out of range ({why})")
RETIRED_SETTINGS = {
    "reprojection": "KD10's re-projection (side faces re-emit along their normal) is the only "
                    "one; remove the setting",
    "direction_groups": "the discrete-ordinates transport (angular='dom') keeps directions "
                        "apart by itself; remove the setting",
}
RETIRED_ANGULAR = {"m1": "the maximum-entropy transport 'm1' was retired"}


def _angular_error(value) -> str:
    why = RETIRED_ANGULAR.get(value, f"unknown transport model {value!r}")
    return (f"GI setting 'angular': {why}; use 'dom' (discrete ordinates, the default) or "
            "'sh' (KD10's clamped SH, the baseline)")


def _coerce(key: str, value, current):
    """A string (the CLI's --set) read as the setting's type; _checked then checks the range."""
    if isinstance(value, str) and not isinstance(current, str):
        low = value.strip().lower()
        if isinstance(current, bool) and low in ("1", "0", "true", "false", "on", "off", "yes",
                                                  "no"):
            return low in ("1", "true", "on", "yes")
        try:
            if not isinstance(current, bool):
                return float(low)
        except ValueError:
            pass
        raise ValueError(f"setting '{key}': cannot read '{value}' as {type(current).__name__}")
    return value


AREA_TYPES = ("CLIP", "TRANSITION")


@dataclass
class Area:
    """A GI area: a box, the image of [-1, 1]^3 under ``matrix`` (like an Empty's cube).

    CLIP: light does not propagate across the box's boundary. TRANSITION: GI inside the box is
    scaled by ``intensity`` and tinted by ``tint``, blending into the outside over ``falloff``
    metres.
    """

    name: str
    type: str
    matrix: np.ndarray
    falloff: float = 0.5
    intensity: float = 1.0
    tint: np.ndarray = field(default_factory=lambda: np.ones(3, np.float32))


@dataclass
class Scene:
    """World-space triangles with per-corner normals, materials, lights and a camera."""

    positions: np.ndarray  # (T, 3, 3) float64 triangle corners (precision far from origin)
    normals: np.ndarray  # (T, 3, 3) float32, per-corner unit normals
    material_index: np.ndarray  # (T,) int32 into ``materials``
    materials: list[Material]
    lights: list[Light]
    camera: Camera | None = None
    settings: GISettings = field(default_factory=GISettings)
    object_index: np.ndarray | None = None  # (T,) int32 into ``object_names``
    object_names: list[str] = field(default_factory=list)
    dropped: dict = field(default_factory=dict)
    # Per-triangle GI flags (None: all True): bounces light / blocks propagation / receives GI.
    caster: np.ndarray | None = None
    occluder: np.ndarray | None = None
    receiver: np.ndarray | None = None
    # Per-triangle ray-visibility bits (T,) uint8 of Cycles' object visibility (None: all
    # seen): HIDDEN_FROM_CAMERA, CASTS_NO_SHADOW, HOLDOUT
    ray_hidden: np.ndarray | None = None
    areas: list[Area] = field(default_factory=list)
    # Per-corner texture coordinates (T, 3, 2) float32 (materials with a texture read them)
    # and colours (T, 3, 3) float32 multiplying the albedo (Color Attribute); None: none.
    uvs: np.ndarray | None = None
    corner_colors: np.ndarray | None = None
    # Per-corner tangents (T, 3, 4) float32 of that UV map, world space: unit tangent and the
    # bitangent's sign (MikkTSpace, as Blender computes them), for Material.normal_texture;
    # None: none
    tangents: np.ndarray | None = None
    world: World | None = None
    # What the extraction or make_scene approximated, one line each naming the object or
    # material and what was done (an unsupported shader, a missing image...): the stats and
    # the UI show them.
    approximated: list[str] = field(default_factory=list)
    # Film > Transparent: Combined's alpha is what covers each pixel and the World is not
    # drawn behind it (Cycles' film_transparent)
    film_transparent: bool = False

    def flag(self, name: str) -> np.ndarray:
        """Per-triangle bool array for 'caster', 'occluder' or 'receiver' (default all True)."""
        value = getattr(self, name)
        if value is None:
            return np.ones(self.triangle_count, bool)
        return np.asarray(value, bool)

    @property
    def triangle_count(self) -> int:
        return int(self.positions.shape[0])

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounds of all triangles (zeros for an empty scene)."""
        if self.triangle_count == 0:
            return np.zeros(3), np.zeros(3)
        p = self.positions.reshape(-1, 3)
        return p.min(axis=0).astype(np.float64), p.max(axis=0).astype(np.float64)

    def albedo_per_triangle(self) -> np.ndarray:
        table = _material_table(self.materials, "albedo")
        return table[self.material_index]

    def reflectance_per_triangle(self) -> np.ndarray:
        """GI reflectance (bleed colour where set) per triangle, (T, 3); 0 for non-casters
        (they inject no light into the LPV but still cast shadows in the RSM)."""
        if not self.materials:
            out = np.full((self.triangle_count, 3), 0.8, np.float32)
        else:
            table = np.array([m.gi_reflectance() for m in self.materials], np.float32)
            out = table[self.material_index]
        if self.caster is not None:
            out = out * self.flag("caster")[:, None].astype(np.float32)
        return out

    def _share_per_triangle(self, name: str, idle: float) -> np.ndarray | None:
        """(T,) float32 of the materials' share ``name`` (0-1, at most 1) per triangle; None
        when every material's is ``idle`` (nothing to do)."""
        shares = np.array([min(float(getattr(m, name)), 1.0) for m in self.materials] or [idle],
                          np.float32)
        if (shares == idle).all():
            return None
        return shares[np.clip(self.material_index, 0, shares.size - 1)]

    def alpha_per_triangle(self) -> np.ndarray | None:
        """(T,) float32 coverage (Material.alpha) per triangle; None when all are opaque."""
        return self._share_per_triangle("alpha", 1.0)

    def _texture_layers(self, attr: str) -> tuple[np.ndarray, list, list]:
        """(layer per material (M + 1,) int32, -1: none, the last for out-of-range indices;
        the distinct textures' pixels, one per layer; their keys, textures.digest_of) of the
        materials' ``attr`` textures."""
        layers, maps, seen = np.full(len(self.materials) + 1, -1, np.int32), [], {}
        for i, m in enumerate(self.materials):
            tex = getattr(m, attr)
            if tex is not None:
                key = digest_of(tex)
                if key not in seen:
                    seen[key] = len(maps)
                    maps.append(tex.pixels)
                layers[i] = seen[key]
        return layers, maps, list(seen)

    def _per_triangle(self, table: np.ndarray) -> np.ndarray:
        """A per-material table (M + 1, ...) read per triangle (Blender clamps the index)."""
        return table[np.clip(self.material_index, 0, len(self.materials))]

    def alpha_maps(self) -> tuple[np.ndarray, list, list] | None:
        """(per-triangle layer (T,) int32, -1: none; the distinct Material.alpha_texture
        pixels, one per layer; their keys) for the rasteriser's per-point coverage; None
        without any (or without texture coordinates)."""
        if self.uvs is None or not any(m.alpha_texture is not None for m in self.materials):
            return None
        layers, maps, keys = self._texture_layers("alpha_texture")
        return self._per_triangle(layers), maps, keys

    def normal_maps(self) -> tuple[np.ndarray, np.ndarray, list, list] | None:
        """(per-triangle layer (T,) int32, -1: none; Strength (T,) float32; the distinct
        Material.normal_texture pixels, one per layer; their keys) for the G-buffer's
        per-point normal; None without any (or without texture coordinates and tangents)."""
        if (self.uvs is None or self.tangents is None
                or not any(m.normal_texture is not None for m in self.materials)):
            return None
        layers, maps, keys = self._texture_layers("normal_texture")
        strength = np.array([max(float(m.normal_strength), 0.0) for m in self.materials]
                            + [0.0], np.float32)
        return self._per_triangle(layers), self._per_triangle(strength), maps, keys

    def translucency_per_triangle(self) -> np.ndarray | None:
        """(T,) float32 Material.translucency per triangle; None when no material has any."""
        return self._share_per_triangle("translucency", 0.0)

    def specular_per_triangle(self) -> np.ndarray | None:
        """Glossy reflectance x GI bleed intensity per triangle (T, 3), 0 for non-casters;
        None when no caster's material has any (the RSM then makes no mirror VPLs)."""
        if not any(np.any(np.asarray(m.specular) > 0) for m in self.materials):
            return None
        table = np.array([np.asarray(m.specular, np.float32) * np.float32(m.bleed_intensity)
                          for m in self.materials], np.float32)
        out = table[self.material_index]
        if self.caster is not None:
            out = out * self.flag("caster")[:, None].astype(np.float32)
        return out if out.any() else None


def _material_table(materials: list[Material], attr: str) -> np.ndarray:
    if not materials:
        return np.full((1, 3), 0.8, np.float32)
    return np.array([np.asarray(getattr(m, attr), np.float32) for m in materials], np.float32)


HIDDEN_FROM_CAMERA = 1  # Object.visible_camera off: not in the camera's passes
CASTS_NO_SHADOW = 2  # Object.visible_shadow off: left out of shadow and sky maps
HOLDOUT = 4  # Object.is_holdout: its pixels are 0 with alpha 0 in every pass


def make_scene(
    positions,
    normals=None,
    material_index=None,
    materials=None,
    lights=None,
    camera=None,
    settings=None,
    object_index=None,
    object_names=None,
    caster=None,
    occluder=None,
    receiver=None,
    areas=None,
    uvs=None,
    corner_colors=None,
    world=None,
    ray_hidden=None,
    tangents=None,
) -> Scene:
    """Build a validated Scene from loose arrays: bad triangles are dropped and counted.

    Drops triangles with NaN/Inf corners, zero area, or a zero-length (or non-finite) normal;
    missing normals default to the face normal. Material indices out of range fall back to a
    default grey material appended at the end. Lights with a non-finite transform or power, or
    a negative power, and areas with a non-finite transform are dropped; non-finite colours and
    values of lights, materials and areas take their defaults, negative ones 0 (a light's GI
    intensity may be negative); each counted in ``dropped``.
    """
    pos = np.asarray(positions, np.float64).reshape(-1, 3, 3)
    t = pos.shape[0]
    materials = list(materials or [])
    mat = np.zeros(t, np.int32) if material_index is None else np.asarray(material_index, np.int32)
    if mat.shape != (t,):
        raise ValueError(f"material_index has shape {mat.shape}, expected ({t},)")
    obj = None if object_index is None else np.asarray(object_index, np.int32).reshape(t)
    with np.errstate(invalid="ignore", over="ignore"):
        finite = np.isfinite(pos).all(axis=(1, 2))
        p64 = np.where(finite[:, None, None], pos, 0).astype(np.float64)
        cross = np.cross(p64[:, 1] - p64[:, 0], p64[:, 2] - p64[:, 0])
        area2 = np.linalg.norm(cross, axis=1)
        # Relative to the triangle's own size so the test does not depend on unit scale.
        edge = np.abs(p64[:, 1:] - p64[:, :1]).max(axis=(1, 2))
        degenerate = ~(area2 > (edge * edge) * 1e-12) | ~np.isfinite(area2)
    if normals is None:
        fn = cross / np.where(area2 > 0, area2, 1.0)[:, None]
        nrm = np.repeat(fn[:, None, :], 3, axis=1).astype(np.float32)
        bad_normal = np.zeros(t, bool)
    else:
        nrm = np.asarray(normals, np.float32).reshape(-1, 3, 3).copy()
        if nrm.shape[0] != t:
            raise ValueError(f"normals describe {nrm.shape[0]} triangles, positions {t}")
        with np.errstate(invalid="ignore", over="ignore"):
            length = np.linalg.norm(nrm.astype(np.float64), axis=2)
        bad_normal = ~(np.isfinite(length) & (length > 1e-12)).all(axis=1)
        nrm = (nrm / np.where(length > 1e-12, length, 1.0)[..., None]).astype(np.float32)
    keep = finite & ~degenerate & ~bad_normal
    dropped = {
        "nonfinite_vertices": int((~finite).sum()),
        "zero_area_triangles": int((finite & degenerate).sum()),
        "zero_length_normals": int((finite & ~degenerate & bad_normal).sum()),
    }
    if mat.size and (mat.min() < 0 or mat.max() >= len(materials)):
        out = (mat < 0) | (mat >= len(materials))
        mat = np.where(out, len(materials), mat).astype(np.int32)
        materials.append(Material("default"))
    flags = {}
    for fname, fvalue in (("caster", caster), ("occluder", occluder), ("receiver", receiver)):
        if fvalue is not None:
            arr = np.asarray(fvalue, bool).reshape(-1)
            if arr.shape != (t,):
                raise ValueError(f"{fname} flags have shape {arr.shape}, expected ({t},)")
            flags[fname] = np.ascontiguousarray(arr[keep])
    if ray_hidden is not None:
        arr = np.asarray(ray_hidden, np.uint8).reshape(-1)
        if arr.shape != (t,):
            raise ValueError(f"ray_hidden has shape {arr.shape}, expected ({t},)")
        flags["ray_hidden"] = np.ascontiguousarray(arr[keep]) if arr.any() else None
    corners = {}
    for cname, cvalue, width in (("uvs", uvs, 2), ("corner_colors", corner_colors, 3),
                                 ("tangents", tangents, 4)):
        if cvalue is not None:
            arr = np.asarray(cvalue, np.float32).reshape(-1, 3, width)
            if cname == "tangents":  # a non-finite tangent: none there (the mesh's normal)
                arr = np.where(np.isfinite(arr), arr, np.float32(0.0))
            if arr.shape[0] != t:
                raise ValueError(f"{cname} describe {arr.shape[0]} triangles, positions {t}")
            corners[cname] = np.ascontiguousarray(arr[keep])
    lights, areas = _valid_lights(lights or [], dropped), _valid_areas(areas or [], dropped)
    materials = _repaired_all(materials, "materials", _MATERIAL_LOWS, dropped)
    return Scene(
        **flags,
        areas=areas,
        positions=np.ascontiguousarray(pos[keep]),
        normals=np.ascontiguousarray(nrm[keep]),
        material_index=np.ascontiguousarray(mat[keep]),
        materials=materials or [Material("default")],
        lights=lights,
        camera=camera,
        settings=settings or GISettings(),
        object_index=None if obj is None else np.ascontiguousarray(obj[keep]),
        object_names=list(object_names or []),
        dropped=dropped,
        world=world,
        **corners,
    )


# Per field, the lowest value make_scene keeps (None: any finite value).
_LIGHT_LOWS = {"color": 0.0, "gi_color": 0.0, "gi_intensity": None, "spot_size": 0.0,
               "spot_blend": 0.0, "radius": 0.0, "size": 0.0, "spread": 0.0, "angle": 0.0}
_MATERIAL_LOWS = {"albedo": 0.0, "bleed_color": 0.0, "bleed_intensity": 0.0, "emission": 0.0,
                  "emission_gi_intensity": None, "diffuse_share": 0.0, "specular": 0.0,
                  "alpha": 0.0, "translucency": 0.0, "normal_strength": 0.0}
_AREA_LOWS = {"falloff": 0.0, "intensity": 0.0, "tint": 0.0}


def _repaired(item, lows: dict):
    """``item`` (a Light, Material or Area) with each field of ``lows`` finite and at least its
    low: a non-finite entry takes the field's default, a lower one the low. The item itself
    when nothing changes, else (a fixed copy, True)."""
    fixes = {}
    for f in dataclasses.fields(item):
        value = getattr(item, f.name)
        if f.name not in lows or value is None:
            continue
        default = f.default_factory() if f.default is dataclasses.MISSING else f.default
        with np.errstate(invalid="ignore"):
            v = np.asarray(value, np.float64)
            fixed = v if default is None else np.where(np.isfinite(v), v, default)
            if lows[f.name] is not None:
                fixed = np.maximum(fixed, lows[f.name])
        if not np.isfinite(fixed).all():
            fixes[f.name] = default  # the bleed colour: None (the albedo)
        elif not np.array_equal(fixed, v):
            fixes[f.name] = (float(fixed) if fixed.ndim == 0 else tuple(fixed.tolist())
                             if isinstance(value, tuple) else fixed.astype(np.float32))
    return (dataclasses.replace(item, **fixes), True) if fixes else (item, False)


def _repaired_all(items: list, kind: str, lows: dict, dropped: dict) -> list:
    """_repaired over the ``items`` holding a non-finite or low value (each field checked for
    all items at once: 1000 materials in about a millisecond), counting the fixed ones."""
    suspect = np.zeros(len(items), bool)
    for name, low in lows.items():
        rows = [i for i, item in enumerate(items) if getattr(item, name) is not None]
        if not rows:
            continue
        try:
            a = np.array([getattr(items[i], name) for i in rows], np.float64).reshape(len(rows), -1)
        except ValueError:  # ragged shapes: each item on its own
            suspect[:] = True
            break
        ok = np.isfinite(a).all(axis=1) & ((a >= low).all(axis=1) if low is not None else True)
        suspect[np.asarray(rows, np.int64)[~ok]] = True
    out, fixed = list(items), 0
    for i in np.flatnonzero(suspect):
        out[i], changed = _repaired(items[i], lows)
        fixed += changed
    if fixed:
        dropped[f"{kind}_with_invalid_values_defaulted"] = fixed
    return out


def _valid_lights(lights: list, dropped: dict) -> list:
    """Lights with a finite transform and a finite, non-negative power, their other values
    repaired (_repaired); the rest counted in ``dropped``."""
    keep = []
    for light in lights:
        m = np.asarray(light.matrix, np.float64)
        if m.shape != (4, 4) or not np.isfinite(m).all() or not np.isfinite(light.power):
            key = "lights_with_nonfinite_transform_or_power"
        elif light.power < 0:
            key = "lights_with_negative_power"
        else:
            keep.append(light)
            continue
        dropped[key] = dropped.get(key, 0) + 1
    return _repaired_all(keep, "lights", _LIGHT_LOWS, dropped)


def _valid_areas(areas: list, dropped: dict) -> list:
    """Areas with a finite transform, their values repaired; the rest counted."""
    keep = [a for a in areas if np.isfinite(np.asarray(a.matrix, np.float64)).all()]
    if len(keep) < len(areas):
        dropped["areas_with_nonfinite_transform"] = len(areas) - len(keep)
    return _repaired_all(keep, "areas", _AREA_LOWS, dropped)


def cross3(a, b) -> np.ndarray:
    """np.cross of two 3-vectors, formed the same way without its per-call overhead (~10 us,
    which the planner and the light views pay many times per update)."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2],
                     a[0] * b[1] - a[1] * b[0]], np.float64)


def look_at_matrix(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """World-to-view matrix for a camera at ``eye`` looking at ``target`` (OpenGL, -Z forward)."""
    eye = np.asarray(eye, np.float64)
    f = np.asarray(target, np.float64) - eye
    f /= np.linalg.norm(f)
    up = np.asarray(up, np.float64)
    if abs(np.dot(f, up / np.linalg.norm(up))) > 0.999:
        up = np.array([0.0, 1.0, 0.0]) if abs(f[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    s = cross3(f, up)
    s /= np.linalg.norm(s)
    u = cross3(s, f)
    m = np.eye(4)
    m[0, :3], m[1, :3], m[2, :3] = s, u, -f
    m[:3, 3] = -m[:3, :3] @ eye
    return m


def perspective_matrix(fov_y: float, aspect: float, near: float, far: float) -> np.ndarray:
    """OpenGL perspective projection (vertical field of view in radians)."""
    f = 1.0 / np.tan(fov_y / 2.0)
    m = np.zeros((4, 4))
    m[0, 0] = f / aspect
    m[1, 1] = f
    m[2, 2] = (far + near) / (near - far)
    m[2, 3] = 2.0 * far * near / (near - far)
    m[3, 2] = -1.0
    return m


def orthographic_matrix(half_w: float, half_h: float, near: float, far: float) -> np.ndarray:
    """OpenGL orthographic projection of a box [-half_w, half_w] x [-half_h, half_h]."""
    m = np.eye(4)
    m[0, 0] = 1.0 / half_w
    m[1, 1] = 1.0 / half_h
    m[2, 2] = -2.0 / (far - near)
    m[2, 3] = -(far + near) / (far - near)
    return m
