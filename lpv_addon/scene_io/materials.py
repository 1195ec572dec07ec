"""Blender material -> core Material: the diffuse albedo Cycles reports as Diffuse Color, the
image it is textured with, the UV map and colour attribute it reads, and what it emits.

The rule (measured on Cycles' Diffuse Color pass, Blender 5.3.0; docs/algorithm.md
"Materials"): Principled = base colour x (1 - metallic) x (1 - transmission) x alpha x what its
specular, sheen and coat layers pass down head-on (measured tables below), plus the sheen's own
albedo; Diffuse, Translucent, Subsurface Scattering, Toon (diffuse) and Sheen (x its albedo):
their colour; Mix Shader: the weighted sum, Add Shader the sum; Emission, Glossy, Glass,
Refraction, Transparent, Metallic: 0. Node groups, reroutes and muted nodes (their internal
links) are followed as Blender evaluates them.

Images through one UV map combine texel by texel into one image (``compose``: mixes,
products, factor images, Metallic and Transmission maps); other colour graphs take a mean,
reported. Textures are read once per content digest and kept in a bounded cache across extractions, so
changing one image re-reads only that image. Budget: at most ``TEXTURE_BUDGET`` (1024^2)
pixels per image; larger images are box-filtered down by a whole factor per axis.
"""

from __future__ import annotations

import hashlib
import math
import os
import sys
from collections import OrderedDict
from dataclasses import dataclass, field

import bpy
import numpy as np

from .._core import core

DEFAULT_ALBEDO = (0.8, 0.8, 0.8)
MAGENTA = (1.0, 0.0, 1.0)  # what Cycles shows for a missing image
TEXTURE_BUDGET = 1 << 20  # pixels per image after resampling
# Texture pixels kept across extractions (1.5 GiB of float32 RGB: 128 images at the budget);
# the extracted Scene holds the same arrays, so the cache adds nothing while a Scene lives.
_CACHE_PIXELS = 128 << 20
# Blender's colour -> float socket conversion: Rec.709 luminance (measured: a magenta image on
# Metallic gives metallic 0.2848 in Cycles).
_LUMA = np.array([0.2126, 0.7152, 0.0722])
# Shaders with no diffuse closure (Cycles' Diffuse Color pass is 0 on them).
NO_DIFFUSE = frozenset({
    "ShaderNodeEmission", "ShaderNodeBsdfGlossy", "ShaderNodeBsdfAnisotropic",
    "ShaderNodeBsdfGlass", "ShaderNodeBsdfRefraction", "ShaderNodeBsdfTransparent",
    "ShaderNodeBsdfMetallic", "ShaderNodeHoldout", "ShaderNodeBsdfRayPortal",
    "ShaderNodeBackground", "ShaderNodeBsdfHair", "ShaderNodeBsdfHairPrincipled",
})
# What a Principled dielectric layer (specular, or coat) lets through to the layer below, seen
# head-on: 1 - E(roughness, F0), Cycles' layering by the layer's albedo. Measured from Cycles'
# Diffuse Color pass (python -m tools.measure_principled_layers, Blender 5.3.0; roughness 0
# is 1 - F0 exactly), rows by _ROUGHNESS, columns by _F0 = ((ior - 1) / (ior + 1))^2.
_ROUGHNESS = np.linspace(0.0, 1.0, 9)
_F0 = ((np.array([1.0, 1.1, 1.2, 1.33, 1.5, 1.75, 2.0, 2.5, 3.0, 4.0]) - 1.0)
       / (np.array([1.0, 1.1, 1.2, 1.33, 1.5, 1.75, 2.0, 2.5, 3.0, 4.0]) + 1.0)) ** 2
_TRANSMITTED = np.array([
    [1.0, 0.99773, 0.99174, 0.97994, 0.96, 0.92562, 0.88889, 0.81633, 0.75, 0.64],
    [1.0, 0.99773, 0.99174, 0.97994, 0.96001, 0.92563, 0.88891, 0.81636, 0.75005, 0.64006],
    [1.0, 0.99774, 0.99175, 0.97999, 0.96011, 0.92585, 0.88924, 0.81691, 0.75077, 0.641],
    [1.0, 0.99776, 0.99185, 0.98026, 0.96069, 0.92698, 0.89095, 0.81968, 0.75439, 0.6457],
    [1.0, 0.99785, 0.99222, 0.98119, 0.96261, 0.9306, 0.89631, 0.82822, 0.76547, 0.66006],
    [1.0, 0.99808, 0.99308, 0.98331, 0.96683, 0.93836, 0.9077, 0.84621, 0.78878, 0.6905],
    [1.0, 0.99845, 0.99442, 0.98654, 0.97319, 0.94993, 0.92461, 0.87298, 0.82371, 0.73686],
    [1.0, 0.99887, 0.99591, 0.9901, 0.98016, 0.96262, 0.94322, 0.90277, 0.86306, 0.79044],
    [1.0, 0.99923, 0.9972, 0.99318, 0.98621, 0.9737, 0.95962, 0.9295, 0.89901, 0.84104],
])
# The sheen layer's albedo head-on per sheen roughness (_ROUGHNESS; same tool): Cycles counts
# sheen as diffuse, over a base scaled by 1 - that albedo.
_SHEEN_ALBEDO = np.array([0.0, 0.0, 0.00026, 0.00328, 0.01864, 0.06185, 0.13803, 0.237,
                          0.34187])
DIFFUSE_COLOR = frozenset({  # shaders whose Color input is their Diffuse Color
    "ShaderNodeBsdfDiffuse", "ShaderNodeBsdfTranslucent", "ShaderNodeSubsurfaceScattering",
})

# Colour spaces whose byte values are used as they are.
_LINEAR_SPACES = frozenset({"Non-Color", "Linear Rec.709", "Linear CIE-XYZ E", "Raw"})
_defaulted: dict[str, int] = {}  # image digest -> texels set to 0 (non-finite or negative)
# image digest -> ((H, W, 3) colour, mean alpha)
_textures: OrderedDict[str, tuple[np.ndarray, float]] = OrderedDict()


@dataclass
class MaterialInfo:
    """A core Material and what the mesh must supply for it: ``uv_map`` (None: no texture;
    "": the mesh's active render UV map), ``uv_transform`` (3x3 affine on (u, v, 1), a Mapping
    node) and ``color_attribute`` (None: none; "": the render colour attribute)."""

    material: core.scene.Material
    uv_map: str | None = None
    uv_transform: np.ndarray | None = None
    color_attribute: str | None = None
    notes: list[str] = field(default_factory=list)
    defaulted_texels: int = 0  # non-finite or negative texels of its images set to 0
    holdout: bool = False  # its surface is a Holdout shader: its pixels are cut out


_MEANS: dict[str, np.ndarray] = {}  # pixels' digest -> their mean colour
_COMPOSED: dict[str, np.ndarray] = {}  # compose's key -> its per-texel colour


def _same_uv(a: tuple | None, b: tuple | None) -> bool:
    """Whether two images read the same texture coordinates (UV map and Mapping transform)."""
    if a is None or b is None or a[0] != b[0]:
        return False
    return (a[1] is None and b[1] is None) or (
        a[1] is not None and b[1] is not None and np.allclose(a[1], b[1], rtol=0, atol=1e-9))


@dataclass
class _Color:
    """A colour as a product: ``const`` x image ``pixels`` at the UV (when set) x the colour
    attribute ``attr`` (when set)."""

    const: np.ndarray
    pixels: np.ndarray | None = None
    node: object = None  # the Image Texture node the pixels come from (or whose grid they use)
    digest: str = ""
    attr: str | None = None
    uv: tuple | None = None  # (UV map, 3x3 transform or None) the pixels are read through

    def mean(self) -> np.ndarray:
        if self.pixels is None:
            return self.const
        m = _MEANS.get(self.digest) if self.digest else None
        if m is None:  # kept per digest: the view share's walk asks each extraction
            m = self.pixels.reshape(-1, 3).mean(axis=0, dtype=np.float64)
            if self.digest:
                if len(_MEANS) > 4096:
                    _MEANS.clear()
                _MEANS[self.digest] = m
        return self.const * m


def _const(c) -> _Color:
    return _Color(np.asarray(c, np.float64)[:3].copy())


class _Evaluator:
    """Walks one material's node tree (context: the stack of group nodes entered)."""

    def __init__(self, mat) -> None:
        self.mat = mat
        self.notes: list[str] = []
        self.uv: tuple[str, np.ndarray | None] | None = None
        self.defaulted = 0
        self.share: np.ndarray | None = None  # the last Principled's view_share

    def note(self, text: str) -> None:
        line = f"material '{self.mat.name}': {text}"
        if line not in self.notes:
            self.notes.append(line)

    # ------------------------------------------------------------------ socket resolution

    def resolve(self, socket, stack=()):
        """(node, output socket, stack) feeding ``socket`` through reroutes, muted nodes and
        group boundaries, or (None, unlinked input socket whose default holds, stack)."""
        for _ in range(256):
            links = [lk for lk in socket.links if not lk.is_muted] if socket.is_linked else []
            if not links:
                return None, socket, stack
            node, out = links[0].from_node, links[0].from_socket
            if node.bl_idname == "NodeReroute":
                socket = node.inputs[0]
            elif node.mute:
                passed = [lk.from_socket for lk in node.internal_links if lk.to_socket == out]
                if not passed:
                    return None, None, stack  # a muted node with nothing passed: black
                socket = passed[0]
            elif node.bl_idname == "ShaderNodeGroup" and node.node_tree is not None:
                outs = [n for n in node.node_tree.nodes if n.bl_idname == "NodeGroupOutput"]
                target = next((n for n in outs if n.is_active_output), outs[0] if outs else None)
                inner = None if target is None else _by_identifier(target.inputs, out.identifier)
                if inner is None:
                    return None, None, stack
                socket, stack = inner, stack + (node,)
            elif node.bl_idname == "NodeGroupInput" and stack:
                outer = _by_identifier(stack[-1].inputs, out.identifier)
                if outer is None:
                    return None, None, stack
                socket, stack = outer, stack[:-1]
            else:
                return node, out, stack
        return None, None, stack

    # ------------------------------------------------------------------------- shaders

    def shader(self, socket, stack=(), depth=0) -> tuple[_Color, np.ndarray]:
        """(diffuse colour, emitted radiance) of the shader feeding ``socket``."""
        node, _, stack = self.resolve(socket, stack)
        if node is None or depth > 32:
            return _const(np.zeros(3)), np.zeros(3)
        return self.node_shader(node, stack, depth)

    def node_shader(self, node, stack, depth) -> tuple[_Color, np.ndarray]:
        """shader() of the (resolved) ``node``."""
        zero = np.zeros(3)
        kind = node.bl_idname
        if kind == "ShaderNodeBsdfPrincipled":
            return self.principled(node, stack)
        if kind in DIFFUSE_COLOR:
            return self.color(node.inputs["Color"], stack), zero
        if kind == "ShaderNodeBsdfToon":
            if node.component == "DIFFUSE":
                return self.color(node.inputs["Color"], stack), zero
            return _const(zero), zero
        if kind == "ShaderNodeEmission":
            strength = self.value(node.inputs["Strength"], stack)
            return _const(zero), self.mean(node.inputs["Color"], stack, "emission") * strength
        if kind in NO_DIFFUSE:
            return _const(zero), zero
        if kind in ("ShaderNodeMixShader", "ShaderNodeAddShader"):
            shaders = [s for s in node.inputs if s.type == "SHADER"]
            a, ea = self.shader(shaders[0], stack, depth + 1)
            b, eb = self.shader(shaders[1], stack, depth + 1)
            if kind == "ShaderNodeAddShader":
                return self.combine(a, 1.0, b, 1.0), ea + eb
            fac = self.factor_map(node.inputs[0], stack)
            if fac is not None and not np.array_equal(ea, eb):
                fac = None  # the emission takes the factor's mean, so the colour does too
            mixed = None if fac is None else self.compose(
                (fac, a, b), lambda f, x, y: x + np.clip(f, 0.0, 1.0) * (y - x), "mix shader")
            if mixed is not None:
                return mixed, ea
            f = float(np.clip(self.value(node.inputs[0], stack), 0.0, 1.0))
            return self.combine(a, 1.0 - f, b, f), (1.0 - f) * ea + f * eb
        if kind == "ShaderNodeBsdfSheen":  # Cycles counts sheen as diffuse: its albedo x Color
            rough = np.clip(self.value(node.inputs["Roughness"], stack), 0.0, 1.0)
            c = self.color(node.inputs["Color"], stack)
            c.const = c.const * np.interp(rough, _ROUGHNESS, _SHEEN_ALBEDO)
            return c, zero
        self.note(f"shader '{node.name}' ({kind}) is not evaluated: grey 0.8")
        return _const(DEFAULT_ALBEDO), zero

    def principled(self, node, stack) -> tuple[_Color, np.ndarray]:
        """Principled BSDF's diffuse weight as Cycles 5.0 layers it (module docstring)."""
        inp = node.inputs

        def val(name, default=0.0):
            return self.value(inp[name], stack) if name in inp else default

        base = self.color(inp["Base Color"], stack)
        # Metallic and Transmission read from an image scale the base colour per texel.
        kept = {}
        for name in ("Metallic", "Transmission Weight"):
            fac = self.factor_map(inp[name], stack) if name in inp else None
            scaled = None if fac is None else self.compose(
                (base, fac), lambda c, f: c * (1.0 - np.clip(f, 0.0, 1.0)), f"1-{name}")
            if scaled is not None:
                base, kept[name] = scaled, 0.0
        metallic, transmission = (kept[n] if n in kept else np.clip(val(n), 0.0, 1.0)
                                  for n in ("Metallic", "Transmission Weight"))
        alpha = np.clip(val("Alpha", 1.0), 0.0, 1.0)
        ior = max(val("IOR", 1.5), 1e-6)
        f0 = ((ior - 1.0) / (ior + 1.0)) ** 2 * 2.0 * max(val("Specular IOR Level", 0.5), 0.0)
        rough = val("Roughness", 0.5)
        k = (1.0 - metallic) * (1.0 - transmission) * alpha
        # The specular layer's untinted albedo: Specular Tint leaves Cycles' Diffuse Color as
        # it is (measured: tint (1, 0.4, 0.2) at IOR 1.8, every view angle, within 0.03 %).
        spec = 1.0 - layer_transmitted(rough, f0)
        weight = k * np.clip(1.0 - spec, 0.0, 1.0)
        over = self.coat_over(inp, stack)  # the coat above both the base and the sheen
        sheen = np.clip(val("Sheen Weight"), 0.0, 1.0) * np.interp(
            np.clip(val("Sheen Roughness", 0.5), 0.0, 1.0), _ROUGHNESS, _SHEEN_ALBEDO)
        self.share = self.view_share(inp, stack, base.mean() * k, alpha, f0)
        base.const = base.const * weight * (1.0 - sheen) * over
        if sheen > 0:
            sheen_tint = self.color(inp["Sheen Tint"], stack).mean()
            base = self.combine(base, 1.0, _const(sheen * sheen_tint * over * alpha), 1.0)
        emission = np.zeros(3)
        if "Emission Strength" in inp:
            strength = val("Emission Strength")
            if strength != 0:
                emission = self.mean(inp["Emission Color"], stack, "emission") * strength
        return base, emission

    def coat_over(self, inp, stack) -> np.ndarray | float:
        """What a Principled's coat lets through to the layers under it, head-on: 1 - weight x
        its albedo, times its tint's share (1 without a coat)."""
        coat = float(np.clip(self.value(inp["Coat Weight"], stack), 0.0, 1.0)) \
            if "Coat Weight" in inp else 0.0
        if coat == 0:
            return 1.0
        ior = max(self.value(inp["Coat IOR"], stack), 1e-6)
        # the coat's own measured table: it reflects more than the specular layer of the
        # same roughness and IOR once rough (0.889 against 0.891 at 0.375, IOR 2)
        albedo = 1.0 - float(_view_table("coat_transmitted", self.value(inp["Coat Roughness"],
                                                                        stack),
                                         ((ior - 1.0) / (ior + 1.0)) ** 2)[-1, 0])
        tint = self.mean(inp["Coat Tint"], stack, "coat tint")
        return (1.0 - coat * albedo) * (1.0 - coat + coat * tint)

    def view_share(self, inp, stack, base: np.ndarray, alpha: float, f0: float) -> np.ndarray:
        """(K, 3) Principled's Diffuse Color at core SHARE_COS over its head-on value, as
        principled() layers it with each layer's albedo at the view angle (measured tables,
        _view_table) and the coat tint's absorption along the refracted path
        (Cycles: tint^(1 / cos refracted)); ``base``: mean base colour x (1 - metallic) x
        (1 - transmission) x alpha (exact without a texture; a texture's sheen share uses its
        mean); ``f0``: the specular layer's normal reflectance."""
        def val(name, default=0.0):
            return self.value(inp[name], stack) if name in inp else default

        mu = np.asarray(core.scene.textures.SHARE_COS, np.float64)[:, None]
        spec = np.clip(_view_table("transmitted", val("Roughness", 0.5), f0), 0.0, 1.0)
        sheen = np.clip(val("Sheen Weight"), 0.0, 1.0) * _view_table(
            "sheen_albedo", np.clip(val("Sheen Roughness", 0.5), 0.0, 1.0))
        tint = self.color(inp["Sheen Tint"], stack).mean() if "Sheen Tint" in inp else 1.0
        total = base * spec * (1.0 - sheen) + sheen * tint * alpha
        coat = np.clip(val("Coat Weight"), 0.0, 1.0)
        if coat > 0:
            ior = max(val("Coat IOR", 1.5), 1e-6)
            layer = _view_table("coat_transmitted", val("Coat Roughness", 0.03),
                                ((ior - 1.0) / (ior + 1.0)) ** 2)
            cos_t = np.sqrt(np.clip(1.0 - (1.0 - mu * mu) / (ior * ior), 1e-6, 1.0))
            absorbed = np.clip(self.color(inp["Coat Tint"], stack).mean(), 1e-6, None) ** (
                1.0 / cos_t)
            total = total * (1.0 - coat * (1.0 - layer)) * (1.0 - coat + coat * absorbed)
        return _over_head(total)

    def weighted(self, socket, leaf, zero: np.ndarray, stack=(), depth=0,
                 purpose: str = "") -> np.ndarray:
        """``leaf(node, stack, depth)`` of the shaders feeding ``socket``, Mix and Add Shader
        weighted by their factors' means (a varying factor reported ``purpose``); ``zero``
        where no shader is."""
        node, _, stack = self.resolve(socket, stack)
        if node is None or depth > 32:
            return zero
        kind = node.bl_idname
        if kind in ("ShaderNodeMixShader", "ShaderNodeAddShader"):
            a, b = (self.weighted(x, leaf, zero, stack, depth + 1, purpose) for x in node.inputs
                    if x.type == "SHADER")
            if kind == "ShaderNodeAddShader":
                return a + b
            if np.array_equal(a, b):  # the factor changes nothing (nor is it reported)
                return a
            f = float(np.clip(self.value(node.inputs[0], stack, purpose), 0.0, 1.0))
            return (1.0 - f) * a + f * b
        return leaf(node, stack, depth)

    def view_total(self, socket) -> np.ndarray:
        """(K, 3) the mean Diffuse Color of the shader feeding ``socket`` at core SHARE_COS: a
        Principled's head-on mean x its view_share, Mix and Add Shader weighted (weighted),
        every other shader its head-on mean (no view table)."""
        k = len(core.scene.textures.SHARE_COS)

        def leaf(node, stack, depth):
            self.share = None
            mean = np.broadcast_to(self.node_shader(node, stack, depth)[0].mean(), (3,))
            return mean * (1.0 if self.share is None else self.share) * np.ones((k, 1))

        return self.weighted(socket, leaf, np.zeros((k, 3)),
                             purpose="for the Diffuse Color's view-angle share")

    # ---------------------------------------------------------------------- colour algebra

    def combine(self, a: _Color, wa: float, b: _Color, wb: float) -> _Color:
        """wa a + wb b, kept exact where one side is constant (the image's pixels take it)."""
        if wb == 0 or not b.const.any():
            return _Color(a.const * wa, a.pixels, a.node, a.digest, a.attr, a.uv)
        if wa == 0 or not a.const.any():
            return _Color(b.const * wb, b.pixels, b.node, b.digest, b.attr, b.uv)
        if a.attr is None and b.attr is None:
            if a.pixels is not None and a.digest == b.digest and a.node == b.node:
                # One image on both sides (the same node): its factors add.
                return _Color(wa * a.const + wb * b.const, a.pixels, a.node, a.digest,
                              uv=a.uv)
            if a.pixels is not None and b.pixels is not None:
                both = self.compose((a, b), lambda x, y: wa * x + wb * y, f"{wa}a+{wb}b")
                if both is not None:
                    return both
                self.note(f"two images mixed ('{a.node.image.name}', '{b.node.image.name}') "
                          f"through different UV maps: the mean colour of "
                          f"'{b.node.image.name}' used")
                b = _const(b.mean())
            if a.pixels is None and b.pixels is None:
                return _const(wa * a.const + wb * b.const)
            tex, other, wt, wo = (a, b, wa, wb) if a.pixels is not None else (b, a, wb, wa)
            pixels = (tex.pixels * (wt * tex.const).astype(np.float32)
                      + (wo * other.const).astype(np.float32))
            key = f"{tex.digest}*{wt * tex.const}+{wo * other.const}"
            return _Color(np.ones(3), pixels, tex.node, _hash(key), uv=tex.uv)
        keep, drop, wk, wd = (a, b, wa, wb) if a.attr is not None else (b, a, wb, wa)
        self.note(f"colour attribute '{keep.attr or 'render'}' mixed with another input: "
                  "the other input's mean added to its weight")
        scale = wk + wd * float(np.mean(drop.mean()))
        return _Color(keep.const * scale, keep.pixels, keep.node, keep.digest, keep.attr,
                      keep.uv)

    def product(self, a: _Color, b: _Color) -> _Color:
        """a x b, per texel for two images through one UV map (compose); a second colour
        attribute, or an image through another UV map, is taken at its mean."""
        if a.pixels is not None and b.pixels is not None:
            if a.attr is None and b.attr is None:
                both = self.compose((a, b), lambda x, y: x * y, "a*b")
                if both is not None:
                    return both
            self.note(f"two images multiplied: the mean colour of '{b.node.image.name}' used")
            b = _Color(b.mean(), attr=b.attr)
        if a.attr is not None and b.attr is not None:
            self.note("two colour attributes multiplied: the second left out")
            b = _Color(b.const, b.pixels, b.node, b.digest, uv=b.uv)
        tex = a if a.pixels is not None else b
        return _Color(a.const * b.const, tex.pixels, tex.node, tex.digest,
                      a.attr if a.attr is not None else b.attr, tex.uv)

    def compose(self, parts, fn, what: str) -> _Color | None:
        """``fn`` of the parts' colours per texel, as one image: the parts that are images are
        read at the texel centres of the one with the most texels (with their own
        interpolation and extension), constants broadcast; None where an image reads another
        UV map or transform, or a part has a colour attribute (the callers fall back to a
        mean and report it)."""
        images = [c for c in parts if c.pixels is not None]
        if not images or any(c.attr is not None for c in parts):
            return None
        grid = max(images, key=lambda c: c.pixels.shape[0] * c.pixels.shape[1])
        if any(not _same_uv(c.uv, grid.uv) for c in images):
            return None
        key = _hash(repr([what] + [(c.digest, c.const.tobytes(), getattr(c.node, "name", ""),
                                    getattr(c.node, "interpolation", ""),
                                    getattr(c.node, "extension", "")) for c in parts]
                         + [grid.digest]))
        pixels = _COMPOSED.get(key)
        if pixels is None:
            h, w = grid.pixels.shape[:2]
            u, v = np.meshgrid((np.arange(w) + 0.5) / w, (np.arange(h) + 0.5) / h)
            uv = np.stack([u.ravel(), v.ravel()], axis=1)

            def texels(c: _Color) -> np.ndarray:
                if c.pixels is None:
                    return np.broadcast_to(c.const.astype(np.float32), (h, w, 3))
                if c is grid or (c.pixels.shape == grid.pixels.shape
                                 and c.node.interpolation in ("Closest", "Linear")):
                    px = c.pixels  # read at its own texel centres: its texels
                else:
                    tex = core.scene.Texture(c.node.image.name, c.pixels, c.node.interpolation,
                                             c.node.extension)
                    px = core.scene.textures.sample(tex, uv).reshape(h, w, 3)
                return px * c.const.astype(np.float32)

            pixels = np.clip(np.nan_to_num(fn(*(texels(c) for c in parts))), 0.0, None)
            pixels = np.ascontiguousarray(pixels, np.float32)
            if sum(p.shape[0] * p.shape[1] for p in _COMPOSED.values()) > _CACHE_PIXELS // 4:
                _COMPOSED.clear()
            _COMPOSED[key] = pixels
        return _Color(np.ones(3), pixels, grid.node, key, uv=grid.uv)

    # ---------------------------------------------------------------------- colour inputs

    def color(self, socket, stack=()) -> _Color:
        """The value of a colour input as a _Color."""
        node, out, stack = self.resolve(socket, stack)
        if node is None:
            return _const(_default_color(out))
        kind = node.bl_idname
        if kind == "ShaderNodeTexImage":
            return self.image(node, out, stack)
        if kind == "ShaderNodeRGB":
            return _const(out.default_value[:3])
        if kind == "ShaderNodeValue":
            return _const([out.default_value] * 3)
        if kind in ("ShaderNodeVertexColor", "ShaderNodeAttribute"):
            name = node.layer_name if kind == "ShaderNodeVertexColor" else node.attribute_name
            if kind == "ShaderNodeAttribute" and node.attribute_type != "GEOMETRY":
                self.note(f"attribute '{name}' is not a mesh attribute: grey 0.8")
                return _const(DEFAULT_ALBEDO)
            return _Color(np.ones(3), attr=name)
        if kind in ("ShaderNodeMix", "ShaderNodeMixRGB"):
            mixed = self.mix(node, stack)
            if mixed is not None:
                return mixed
        self.note(f"colour from '{node.name}' ({kind}) is not evaluated: its socket's "
                  "default colour used")
        return _const(_default_color(socket))

    def mix(self, node, stack) -> _Color | None:
        """Mix Color MIX / MULTIPLY / ADD with its factor (None: another blend or data type)."""
        if node.bl_idname == "ShaderNodeMix":
            if node.data_type != "RGBA":
                return None
            fac_s, a_s, b_s = (_by_identifier(node.inputs, i)
                               for i in ("Factor_Float", "A_Color", "B_Color"))
        else:
            fac_s, a_s, b_s = node.inputs[0], node.inputs[1], node.inputs[2]
        blend = node.blend_type
        if blend not in ("MIX", "MULTIPLY", "ADD"):
            return None
        clamp = getattr(node, "clamp_factor", True)
        if getattr(node, "clamp_result", False) or getattr(node, "use_clamp", False):
            self.note(f"'{node.name}': Clamp Result not applied")
        a, b = self.color(a_s, stack), self.color(b_s, stack)
        fac = self.factor_map(fac_s, stack)
        if fac is not None:  # a factor image: the blend per texel
            lo, hi = (0.0, 1.0) if clamp else (-np.inf, np.inf)
            blends = {"MIX": lambda f, x, y: x + f * (y - x), "ADD": lambda f, x, y: x + f * y,
                      "MULTIPLY": lambda f, x, y: x * (1.0 + f * (y - 1.0))}

            def per_texel(f, x, y, op=blends[blend]):
                return op(np.clip(f, lo, hi), x, y)

            mixed = self.compose((fac, a, b), per_texel, f"mix {blend} {clamp}")
            if mixed is not None:
                return mixed
        f = float(self.value(fac_s, stack))
        if clamp:
            f = float(np.clip(f, 0.0, 1.0))
        if blend == "MIX":
            return self.combine(a, 1.0 - f, b, f)
        if blend == "ADD":
            return self.combine(a, 1.0, b, f)
        # MULTIPLY: a x ((1 - f) + f b)
        return self.product(a, self.combine(_const(np.ones(3)), 1.0 - f, b, f))

    def factor_map(self, socket, stack) -> _Color | None:
        """A float input read from an image through a UV map, as a grey image (Blender's
        colour -> float conversion, _LUMA, per texel); None when it is constant or has no such
        image (value() then gives its mean)."""
        node, out, _ = self.resolve(socket, stack)
        if node is None or (node.bl_idname == "ShaderNodeTexImage" and out.name == "Alpha"):
            return None
        c = self.color(socket, stack)
        if c.pixels is None or c.attr is not None or c.uv is None:
            return None
        weights = (_LUMA * c.const).astype(np.float32)
        grey = np.repeat((c.pixels @ weights)[..., None], 3, axis=2)
        return _Color(np.ones(3), np.ascontiguousarray(grey, np.float32), c.node,
                      _hash(f"luma {c.digest} {weights.tobytes()}"), uv=c.uv)

    def mean(self, socket, stack, what: str) -> np.ndarray:
        """A colour input's mean, reported when it varies over the surface."""
        c = self.color(socket, stack)
        if c.pixels is not None or c.attr is not None:
            self.note(f"the {what} colour varies over the surface: its mean "
                      f"({', '.join(f'{v:.3f}' for v in c.mean())}) used")
        return c.mean()

    def value(self, socket, stack=(), purpose: str = "") -> float:
        """A float input: its default, a Value/RGB node, or the mean (luminance) of what feeds
        it, reported (with ``purpose``, what the mean is used for) when that varies over the
        surface."""
        node, out, stack = self.resolve(socket, stack)
        if node is None:
            if out is None:
                return 0.0
            v = out.default_value
            return float(v) if np.ndim(v) == 0 else float(_LUMA @ np.asarray(v[:3], np.float64))
        if node.bl_idname == "ShaderNodeValue":
            return float(out.default_value)
        if node.bl_idname == "ShaderNodeTexImage" and out.name == "Alpha":
            alpha = self.image_alpha_mean(node)
            self.note(f"'{socket.name}' driven by the alpha of image "
                      f"'{getattr(node.image, 'name', '')}': its mean {alpha:.3f} used"
                      + (f" {purpose}" if purpose else ""))
            return alpha
        c = self.color(socket, stack)
        v = float(_LUMA @ c.mean())
        if c.pixels is not None or c.attr is not None:
            self.note(f"'{socket.name}' varies over the surface: its mean {v:.3f} used"
                      + (f" {purpose}" if purpose else ""))
        return v

    # ---------------------------------------------------------------------------- images

    def image(self, node, out, stack) -> _Color:
        image = node.image
        if out.name == "Alpha":
            return _const([self.image_alpha_mean(node)] * 3)
        if image is None:
            self.note(f"Image Texture '{node.name}' has no image: black, as Cycles shows it")
            return _const(np.zeros(3))
        digest, rgb, _ = image_pixels(image)
        if _defaulted.get(digest):
            self.defaulted += _defaulted[digest]
            self.note(f"image '{image.name}': {_defaulted[digest]} non-finite or negative "
                      "texels set to 0")
        if rgb is None and image.source in ("SEQUENCE", "MOVIE"):
            kind = "an image sequence" if image.source == "SEQUENCE" else "a movie"
            line = (f"image '{image.name}' is {kind}, whose frames are not read: magenta "
                    "(use a still image)")
            self.note(line)
            _warn(f"LPV GI: material '{self.mat.name}': {line}")
            return _const(MAGENTA)
        if rgb is None:
            path = bpy.path.abspath(image.filepath) if image.filepath else "(no file)"
            line = f"image '{image.name}' is missing ({path}): magenta, as Cycles shows it"
            self.note(line)
            _warn(f"LPV GI: material '{self.mat.name}': {line}")
            return _const(MAGENTA)
        if image.source == "TILED":
            self.note(f"image '{image.name}' has UDIM tiles: its first tile used")
        uv = self.uv_source(node, stack)
        if uv is None:
            self.note(f"image '{image.name}' is not mapped by a UV map: its mean colour used")
            return _const(rgb.reshape(-1, 3).mean(axis=0, dtype=np.float64))
        if self.uv is not None and self.uv[0] != uv[0]:
            self.note(f"images read different UV maps: '{image.name}' reads "
                      f"'{self.uv[0] or 'render'}' as the first image does")
        elif self.uv is None:
            self.uv = uv
        return _Color(np.ones(3), rgb, node, digest, uv=uv)

    def image_alpha_mean(self, node) -> float:
        if node.image is None:
            return 0.0
        _, rgb, alpha = image_pixels(node.image)
        return 1.0 if rgb is None else alpha

    def uv_source(self, node, stack) -> tuple[str, np.ndarray | None] | None:
        """(UV map name, "" for the render one; 3x3 affine or None) the image node reads, or
        None when it is projected by something else (Generated, Object, a box projection)."""
        if getattr(node, "projection", "FLAT") != "FLAT":
            return None
        src, out, stack = self.resolve(node.inputs["Vector"], stack)
        transform = None
        if src is not None and src.bl_idname == "ShaderNodeMapping":
            transform = _mapping_matrix(src, self, stack)
            if transform is None:
                return None
            src, out, stack = self.resolve(src.inputs["Vector"], stack)
        if src is None:
            return ("", transform) if out is not None and not out.is_linked else None
        if src.bl_idname == "ShaderNodeUVMap":
            return src.uv_map, transform
        if src.bl_idname == "ShaderNodeTexCoord" and out.name == "UV":
            return "", transform
        return None


def _mapping_matrix(node, ev: _Evaluator, stack) -> np.ndarray | None:
    """The Mapping node's transform of (u, v, 0) as a 3x3 affine on (u, v, 1) (POINT,
    TEXTURE, VECTOR; its inputs constant), as Blender's node_mapping defines it."""
    def vec(name):
        src, sock, _ = ev.resolve(node.inputs[name], stack)
        return None if src is not None or sock is None else np.array(sock.default_value[:3])

    loc = vec("Location") if "Location" in node.inputs else np.zeros(3)
    rot, scale = vec("Rotation"), vec("Scale")
    if loc is None or rot is None or scale is None:
        ev.note(f"Mapping '{node.name}' has linked inputs: not applied")
        return np.eye(3)
    cx, cy, cz = np.cos(rot)
    sx, sy, sz = np.sin(rot)
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    r = rz @ ry @ rx  # Euler XYZ
    kind = node.vector_type
    m4 = np.eye(4)
    if kind in ("POINT", "VECTOR"):
        m4[:3, :3] = r @ np.diag(scale)
        if kind == "POINT":
            m4[:3, 3] = loc
    elif kind == "TEXTURE":
        safe = np.where(scale != 0, scale, 1.0)
        m4[:3, :3] = np.diag(1.0 / safe) @ r.T
        m4[:3, 3] = -m4[:3, :3] @ loc
    else:  # NORMAL: not a texture-coordinate transform
        return np.eye(3)
    # (u, v, 0, 1) -> the first two components.
    return np.array([[m4[0, 0], m4[0, 1], m4[0, 3]], [m4[1, 0], m4[1, 1], m4[1, 3]],
                     [0.0, 0.0, 1.0]])


def layer_transmitted(roughness: float, f0: float) -> float:
    """Fraction a dielectric layer of ``roughness`` and normal-incidence reflectance ``f0``
    passes to the layer below (bilinear in the measured table; 1 - f0 beyond its last F0)."""
    r = float(np.clip(roughness, 0.0, 1.0))
    f0 = float(np.clip(f0, 0.0, 1.0))
    if f0 > _F0[-1]:
        return 1.0 - f0
    col = np.array([np.interp(f0, _F0, row) for row in _TRANSMITTED])
    return float(np.interp(r, _ROUGHNESS, col))


def f82_average(f0, tint) -> np.ndarray:
    """Cosine-weighted hemispherical average of Cycles' F82-tint conductor Fresnel of normal
    reflectance ``f0`` and edge ``tint`` (Cycles' fresnel_f82_Fss and fresnel_f82tint_B): a
    metal's glossy albedo under uniform light, as its multiscatter GGX keeps it (f0 + (1 -
    f0) / 21 for a white tint, which makes F82-tint Schlick's Fresnel)."""
    f0, tint = (np.clip(np.asarray(v, np.float64), 0.0, 1.0) for v in (f0, tint))
    f = 6.0 / 7.0
    b = (f0 + (1.0 - f0) * f ** 5) * (7.0 / f ** 6) * (1.0 - tint)
    return np.clip(f0 + (1.0 - f0) / 21.0 - b / 126.0, 0.0, 1.0)


def glossy_reflectance(ev: _Evaluator, socket) -> np.ndarray:
    """The share of incident flux the shader feeding ``socket`` reflects glossily (RGB; the
    RSM's mirror VPLs): Principled's metal part (metallic x alpha x coat x f82_average of the
    base colour and specular tint), Glossy BSDF's colour, Metallic BSDF's f82_average,
    weighted through Mix and Add Shader like the diffuse rule. Dielectric specular layers
    (F0 ~ 0.04) are left out; colours that vary take their mean (reported)."""
    return ev.weighted(socket, lambda node, stack, depth: _glossy_node(ev, node, stack),
                       np.zeros(3), purpose="for the glossy bounce")


def _glossy_node(ev: _Evaluator, node, stack) -> np.ndarray:
    """glossy_reflectance of one (resolved) shader node."""
    zero = np.zeros(3)
    kind, inp = node.bl_idname, node.inputs
    if kind == "ShaderNodeBsdfAnisotropic":  # Glossy BSDF: its colour, no Fresnel
        return ev.mean(inp["Color"], stack, "glossy")
    if kind == "ShaderNodeBsdfMetallic":
        if getattr(node, "fresnel_type", "F82") != "F82":
            n, k = ev.mean(inp["IOR"], stack, "IOR"), ev.mean(inp["Extinction"], stack, "k")
            ev.note(f"'{node.name}': physical conductor as F82 of its normal reflectance")
            return f82_average(((n - 1) ** 2 + k * k) / ((n + 1) ** 2 + k * k), 1.0)
        return f82_average(ev.mean(inp["Base Color"], stack, "metal"),
                           ev.mean(inp["Edge Tint"], stack, "edge tint"))
    if kind != "ShaderNodeBsdfPrincipled":
        return zero
    metallic = float(np.clip(ev.value(inp["Metallic"], stack, "for the glossy bounce"), 0.0,
                             1.0))
    if metallic == 0:
        return zero
    alpha = float(np.clip(ev.value(inp["Alpha"], stack), 0.0, 1.0)) if "Alpha" in inp else 1.0
    over = ev.coat_over(inp, stack)  # the coat over the metal, as over the diffuse base
    tint = ev.mean(inp["Specular Tint"], stack, "specular tint") if "Specular Tint" in inp \
        else 1.0
    return metallic * alpha * over * f82_average(ev.mean(inp["Base Color"], stack, "metal"),
                                                 tint)


_VIEW: dict = {}  # principled_view.json, read on first use


def _view_table(name: str, roughness: float, f0: float | None = None) -> np.ndarray:
    """(K, 1) a measured table of principled_view.json at core SHARE_COS: "transmitted" or
    "coat_transmitted" (the specular or coat layer's 1 - E, bilinear in roughness^2 (GGX's
    alpha, where the tables are smooth) and F0, clamped to the table) or "sheen_albedo"
    (linear in sheen roughness) (python -m tools.measure_principled_layers --view)."""
    if not _VIEW:
        import json

        with open(os.path.join(os.path.dirname(__file__), "principled_view.json")) as f:
            data = json.load(f)
        order = np.argsort(data["cos_view"])
        _VIEW.update({k: np.asarray(v, np.float64) for k, v in data.items() if k != "blender"})
        _VIEW["order"] = order
        _VIEW["f0"] = ((_VIEW["ior"] - 1.0) / (_VIEW["ior"] + 1.0)) ** 2
    t = _VIEW[name]
    r = float(np.clip(roughness, 0.0, 1.0))
    if f0 is None:  # (roughness, cos)
        at = _lerp(_VIEW["roughness"], r, t)
    else:  # (roughness, ior, cos)
        f = float(np.clip(f0, 0.0, 1.0))
        at = _lerp(_VIEW["roughness"] ** 2, r * r, _lerp(_VIEW["f0"], f, t.swapaxes(0, 1)))
    o = _VIEW["order"]
    return np.interp(core.scene.textures.SHARE_COS, _VIEW["cos_view"][o], at[o])[:, None]


def _over_head(total: np.ndarray) -> np.ndarray:
    """(K, 3) a table over SHARE_COS as multiples of its head-on (last) row; 1 where that is 0."""
    head = total[-1]
    return np.where(head > 0, total / np.where(head > 0, head, 1.0), 1.0)


def _lerp(grid: np.ndarray, x: float, values: np.ndarray) -> np.ndarray:
    """``values`` (len(grid), ...) linear in ``x`` along its first axis (held at the ends)."""
    i = int(np.clip(np.searchsorted(grid, x) - 1, 0, grid.size - 2))
    w = float(np.clip((x - grid[i]) / (grid[i + 1] - grid[i]), 0.0, 1.0))
    return (1.0 - w) * values[i] + w * values[i + 1]


def _by_identifier(sockets, identifier: str):
    return next((s for s in sockets if s.identifier == identifier), None)


def _default_color(socket) -> np.ndarray:
    if socket is None:
        return np.zeros(3)
    v = getattr(socket, "default_value", None)
    if v is None:
        return np.zeros(3)
    if np.ndim(v) == 0:
        return np.full(3, float(v))
    return np.array(v[:3], np.float64)


_warned: set[str] = set()


def _warn(line: str) -> None:
    """``line`` on stderr, once per session (live updates extract again and again)."""
    if line not in _warned:
        _warned.add(line)
        print(line, file=sys.stderr)


def _hash(text: str) -> str:
    return hashlib.blake2b(text.encode(), digest_size=12).hexdigest()


# --------------------------------------------------------------------------------- public


def material_info(mat) -> MaterialInfo:
    """The core Material of ``mat`` (None: the default grey) and what its texture reads."""
    if mat is None:  # Cycles' default surface: a Principled BSDF of base 0.8, its defaults
        f0 = ((1.5 - 1.0) / (1.5 + 1.0)) ** 2  # IOR 1.5, Specular IOR Level 0.5
        albedo = np.array(DEFAULT_ALBEDO) * layer_transmitted(0.5, f0)
        m = core.scene.Material("(none)", albedo.astype(np.float32))
        spec = np.clip(_view_table("transmitted", 0.5, f0), 0.0, 1.0)  # principled's layering
        m.diffuse_share = np.ascontiguousarray(np.broadcast_to(
            _over_head(spec), (len(core.scene.textures.SHARE_COS), 3)), np.float32)
        return MaterialInfo(m)
    ev = _Evaluator(mat)
    diffuse, emission = _const(mat.diffuse_color[:3]), np.zeros(3)
    glossy = np.zeros(3)
    tree = getattr(mat, "node_tree", None)
    use_nodes = tree is not None and (bpy.app.version >= (5, 0, 0) or mat.use_nodes)
    output = _active_output(tree) if use_nodes else None
    holdout = False
    if output is not None:
        surface = output.inputs.get("Surface")
        diffuse, emission = ev.shader(surface)
        glossy = glossy_reflectance(ev, surface)
        node = ev.resolve(surface)[0] if surface is not None else None
        holdout = node is not None and node.bl_idname == "ShaderNodeHoldout"
    m = core.scene.Material(mat.name, np.clip(diffuse.const, 0.0, None).astype(np.float32))
    m.emission = np.clip(np.asarray(emission, np.float64), 0.0, None).astype(np.float32)
    if output is not None:
        counted = ev.defaulted  # (the second walk reads the same images again)
        total = ev.view_total(surface)
        ev.defaulted = counted
        share = _over_head(total)
        if np.isfinite(share).all() and not np.allclose(share, 1.0):
            m.diffuse_share = np.ascontiguousarray(share, np.float32)
    m.specular = np.clip(np.nan_to_num(glossy), 0.0, None).astype(np.float32)
    alpha_uv = None
    if output is not None:
        m.translucency = translucency(ev, surface, float(np.mean(diffuse.mean())))
        alpha = coverage(ev, surface)
        if alpha < 1.0:  # hashed alpha: the covered part's colours (Material.alpha)
            m.alpha = alpha
            scale = np.float32(1.0 / max(alpha, 1e-3))
            m.albedo, m.emission, m.specular = (a * scale for a in (m.albedo, m.emission,
                                                                    m.specular))
            alpha_uv = alpha_map(ev, surface, m, diffuse.uv or ev.uv)
    normal_uv = None
    if output is not None:
        normal_uv = normal_map(ev, tree, surface, m, diffuse.uv or ev.uv or alpha_uv)
        displace = output.inputs.get("Displacement")
        if displace is not None and ev.resolve(displace)[0] is not None:
            ev.note("Displacement (a bump, or moved surfaces, in Cycles): left out, the "
                    "mesh's own surface and normals are used")
        volume = output.inputs.get("Volume")
        inside = ev.resolve(volume)[0] if volume is not None else None
        if inside is not None and (surface is None or ev.resolve(surface)[0] is None):
            # a volume without a surface shader (a fog box): Cycles' rays pass its surface
            m.alpha, m.albedo, m.emission, m.specular = (0.0, *(np.zeros(3, np.float32)
                                                                for _ in range(3)))
            ev.note(f"a volume only ('{inside.name}'): its surface is transparent, as in "
                    "Cycles; the volume's scattering, absorption and emission are left out")
    info = MaterialInfo(m, color_attribute=diffuse.attr, notes=ev.notes,
                        defaulted_texels=ev.defaulted, holdout=holdout)
    if alpha_uv is not None and diffuse.pixels is None:  # the alpha image's UV map alone
        info.uv_map, info.uv_transform = alpha_uv
    elif normal_uv is not None and diffuse.pixels is None:  # the normal map's alone
        info.uv_map, info.uv_transform = normal_uv
    if diffuse.pixels is not None:
        node = diffuse.node
        m.texture = core.scene.Texture(
            name=node.image.name, pixels=np.ascontiguousarray(diffuse.pixels, np.float32),
            interpolation=node.interpolation, extension=node.extension, digest=diffuse.digest)
        uv = diffuse.uv or ev.uv
        info.uv_map, info.uv_transform = uv if uv is not None else ("", None)
    props = getattr(mat, "lpv", None)
    if props is not None and hasattr(props, "bleed_intensity"):
        if props.use_bleed_color:
            m.bleed_color = np.array(props.bleed_color[:3], np.float32)
        m.bleed_intensity = float(props.bleed_intensity)
        m.emission_gi_intensity = float(getattr(props, "emission_gi_intensity", 1.0))
    return info


def coverage(ev, surface) -> float:
    """The share of a surface that is there, as Cycles' transparency sees it: a Transparent
    BSDF's weight is not, a Principled's Alpha is its share (an image's mean alpha), Mix
    Shader weighted; every other shader is opaque."""
    def leaf(node, stack, depth):
        kind = node.bl_idname
        if kind == "ShaderNodeBsdfTransparent":
            return np.zeros(1)
        if kind == "ShaderNodeBsdfPrincipled" and "Alpha" in node.inputs:
            return np.clip([ev.value(node.inputs["Alpha"], stack)], 0.0, 1.0)
        return np.ones(1)

    if surface is None:
        return 1.0
    return float(np.clip(ev.weighted(surface, leaf, np.ones(1), purpose="the coverage")[0],
                         0.0, 1.0))


def alpha_map(ev, surface, m, uv) -> tuple | None:
    """A Principled Alpha read from an image's Alpha through a UV map becomes the material's
    alpha_texture (the coverage per point; m.alpha 1), when that UV map is the one the
    material's colour image reads (or it has none); returns the UV source, else None (the
    mean alpha stays, named)."""
    node, _, stack = ev.resolve(surface)
    if node is None or node.bl_idname != "ShaderNodeBsdfPrincipled":
        return None
    image_node, out, stack = ev.resolve(node.inputs["Alpha"], stack)
    if (image_node is None or image_node.bl_idname != "ShaderNodeTexImage"
            or out.name != "Alpha" or image_node.image is None):
        return None
    source = ev.uv_source(image_node, stack)
    if source is None or (uv is not None and not _same_uv(source, uv)):
        return None
    digest, pixels = image_alpha(image_node.image)
    if pixels is None:
        return None
    m.alpha_texture = core.scene.textures.Texture(
        image_node.image.name, pixels, image_node.interpolation, image_node.extension,
        digest)
    m.alpha = 1.0
    ev.notes[:] = [n for n in ev.notes if "driven by the alpha of image" not in n]
    return source


def normal_map(ev, tree, surface, m, uv) -> tuple | None:
    """A tangent-space Normal Map node on the surface BSDF's Normal input, its Color an image
    read through a UV map, becomes the material's normal_texture and normal_strength (the
    G-buffer's normal per point) when that UV map is the node's own and the one the material's
    other images read (or they have none); returns the UV source. Any other normal input (a
    Bump, another space, a second UV map) is named and left out: the mesh's normals stay."""
    def left_out(what: str) -> None:
        ev.note(f"{what}: left out, the mesh's normals are used")

    node, _, stack = ev.resolve(surface)
    src = None
    if node is not None and "Normal" in node.inputs:
        src, _, st = ev.resolve(node.inputs["Normal"], stack)
    if src is None:
        used = [n for n in tree.nodes if n.bl_idname in ("ShaderNodeNormalMap", "ShaderNodeBump")
                and any(o.is_linked for o in n.outputs)]
        if used:
            left_out(f"'{used[0].name}' ({used[0].bl_idname.removeprefix('ShaderNode')}) "
                     "does not feed the surface BSDF's Normal")
        return None
    if src.bl_idname != "ShaderNodeNormalMap":
        left_out(f"Normal from '{src.name}' ({src.bl_idname.removeprefix('ShaderNode')})")
        return None
    if src.space != "TANGENT":
        left_out(f"Normal Map '{src.name}' in {src.space.title()} space")
        return None
    image, out, ist = ev.resolve(src.inputs["Color"], st)
    if (image is None or image.bl_idname != "ShaderNodeTexImage" or image.image is None
            or out.name != "Color"):
        left_out(f"Normal Map '{src.name}' whose Color is not an image's Color")
        return None
    source = ev.uv_source(image, ist)
    if (source is None or (uv is not None and not _same_uv(source, uv))
            or (src.uv_map or "") != source[0]):
        left_out(f"Normal Map '{src.name}' with image '{image.image.name}' read through "
                 "another UV map or projection than its tangents' or the material's colour")
        return None
    digest, pixels, _ = image_pixels(image.image)
    if pixels is None:
        left_out(f"Normal Map '{src.name}': image '{image.image.name}' has no pixels")
        return None
    m.normal_texture = core.scene.textures.Texture(
        image.image.name, pixels, image.interpolation, image.extension, digest)
    m.normal_strength = max(ev.value(src.inputs["Strength"], st), 0.0)
    return source


_ALPHAS: dict[str, np.ndarray] = {}  # image digest -> its alpha (H, W, 1)


def image_alpha(image) -> tuple[str, np.ndarray | None]:
    """(digest, (H, W, 1) float32 alpha in 0-1, rows bottom-first, at most TEXTURE_BUDGET
    pixels; None for an empty image) of ``image``, kept per digest (bounded)."""
    digest = image_digest(image) + ":alpha"
    if digest in _ALPHAS and not image.is_dirty:
        return digest, _ALPHAS[digest]
    w, h = image.size[:]
    channels = image.channels
    if w <= 0 or h <= 0 or channels != 4:
        return digest, None
    px = np.empty(w * h * channels, np.float32)
    image.pixels.foreach_get(px)
    alpha = np.nan_to_num(px.reshape(h, w, 4)[..., 3:], nan=1.0)
    alpha = np.ascontiguousarray(np.clip(resample_to_budget(alpha, TEXTURE_BUDGET), 0.0, 1.0),
                                 np.float32)
    alpha.flags.writeable = False
    while len(_ALPHAS) >= 32:
        _ALPHAS.pop(next(iter(_ALPHAS)))
    _ALPHAS[digest] = alpha
    return digest, alpha


def translucency(ev, surface, total: float) -> float:
    """The share of a surface's Diffuse Color (``total``, its mean) that Translucent BSDFs
    give, Mix and Add Shader weighted: the light of that share comes from the far side."""
    def leaf(node, stack, depth):
        if node.bl_idname == "ShaderNodeBsdfTranslucent":
            return np.array([float(np.mean(ev.color(node.inputs["Color"], stack).mean()))])
        return np.zeros(1)

    if surface is None or not total > 0:
        return 0.0
    part = float(ev.weighted(surface, leaf, np.zeros(1), purpose="the translucency")[0])
    return float(np.clip(part / total, 0.0, 1.0))


def material_albedo(mat) -> np.ndarray:
    """The mean diffuse albedo of ``mat`` (its factor x its texture's mean colour): the single
    colour a material shows where one colour is asked for."""
    info = material_info(mat)
    albedo = info.material.albedo.astype(np.float64)
    if info.material.texture is not None:
        albedo = albedo * info.material.texture.pixels.reshape(-1, 3).mean(axis=0)
    return albedo.astype(np.float32)


def material_emits(mat) -> bool:
    """Whether ``mat``'s surface shader emits light (non-zero radiance)."""
    return mat is not None and bool(material_info(mat).material.emission.any())


def _active_output(tree):
    outputs = [n for n in tree.nodes if n.bl_idname == "ShaderNodeOutputMaterial"]
    for node in outputs:
        if node.is_active_output and node.target in ("ALL", "CYCLES"):
            return node
    for node in outputs:
        if node.is_active_output:
            return node
    return outputs[0] if outputs else None


# --------------------------------------------------------------------------------- images


def image_digest(image) -> str:
    """A cheap content key: name, file, size, source, generated settings, colour space, alpha
    mode, packed size; an image painted in this session (is_dirty) is keyed by its pixels."""
    parts = [image.name, image.filepath, image.source, tuple(image.size), image.is_float,
             image.colorspace_settings.name, image.alpha_mode, image.channels]
    if image.source == "GENERATED":
        parts += [image.generated_type, tuple(image.generated_color),
                  image.generated_width, image.generated_height]
    packed = image.packed_file
    if packed is not None:
        parts.append(packed.size)
    elif image.filepath:
        path = bpy.path.abspath(image.filepath)
        try:
            st = os.stat(path)
            parts += [st.st_size, st.st_mtime_ns]
        except OSError:
            parts.append("missing")
    return _hash(repr(parts))


def image_pixels(image) -> tuple[str, np.ndarray | None, float]:
    """(digest, (H, W, 3) float32 colour as the Image Texture node's Color output gives it:
    scene-linear, alpha associated as Cycles does, rows bottom-first, at most TEXTURE_BUDGET
    pixels, None for a missing or empty image; the mean alpha). Cached by digest across
    extractions (bounded)."""
    digest = image_digest(image)
    dirty = image.is_dirty
    if not dirty and digest in _textures:
        _textures.move_to_end(digest)
        return (digest, *_textures[digest])
    w, h = image.size[:]
    channels = image.channels
    if w <= 0 or h <= 0 or channels <= 0:
        return digest, None, 1.0
    px = np.empty(w * h * channels, np.float32)
    image.pixels.foreach_get(px)
    if dirty:
        digest = _hash(digest + hashlib.blake2b(px.tobytes(), digest_size=12).hexdigest())
    rgba = px.reshape(h, w, channels)
    if channels != 4:
        rgba = _as_rgba(rgba)
    rgb, alpha = rgba[..., :3], rgba[..., 3:]
    mean_alpha = float(np.nan_to_num(alpha.mean(dtype=np.float64), nan=1.0))
    straight = image.alpha_mode == "STRAIGHT" and channels == 4 and mean_alpha != 1.0
    space = image.colorspace_settings.name
    if not image.is_float:
        # Byte values k / 255. Cycles associates straight alpha in the bytes, c x a // 255
        # (truncated), then decodes (measured, docs/algorithm.md).
        q = (rgb * np.float32(255.0) + np.float32(0.5)).astype(np.uint8)
        if straight:
            a = (alpha * np.float32(255.0) + np.float32(0.5)).astype(np.uint16)
            q = (q * a // 255).astype(np.uint8)
        if space == "sRGB":
            rgb = _BYTE_SRGB[q]
        else:
            if space not in _LINEAR_SPACES:
                _warn(f"LPV GI: image '{image.name}': colour space '{space}' read as linear")
            rgb = q * np.float32(1.0 / 255.0)
    else:
        rgb = rgb * alpha if straight else np.ascontiguousarray(rgb)
        with np.errstate(invalid="ignore"):
            bad = ~(np.isfinite(rgb) & (rgb >= 0))
        if bad.any():
            _defaulted[digest] = int(bad.any(axis=2).sum())
            _warn(f"LPV GI: image '{image.name}': {_defaulted[digest]} non-finite or "
                  "negative texels set to 0")
            rgb[bad] = 0.0
    rgb = resample_to_budget(rgb, TEXTURE_BUDGET)
    rgb = np.ascontiguousarray(rgb, np.float32)
    rgb.flags.writeable = False  # shared by every Scene extracted while it is cached
    entry = rgb, mean_alpha
    _textures[digest] = entry
    while sum(t[0].shape[0] * t[0].shape[1] for t in _textures.values()) > _CACHE_PIXELS and \
            len(_textures) > 1:
        _textures.popitem(last=False)
    return (digest, *entry)


def _as_rgba(px: np.ndarray) -> np.ndarray:
    c = px.shape[2]
    if c == 4:
        return px.copy()
    out = np.ones(px.shape[:2] + (4,), np.float32)
    if c >= 3:
        out[..., :3] = px[..., :3]
    else:
        out[..., :3] = px[..., :1]
        if c == 2:
            out[..., 3] = px[..., 1]
    return out


def resample_to_budget(rgba: np.ndarray, budget: int) -> np.ndarray:
    """Box-filter ``rgba`` (H, W, C) down by the smallest whole factor per axis that brings it
    within ``budget`` pixels (rows and columns past a whole multiple are cut)."""
    h, w = rgba.shape[:2]
    if h * w <= budget:
        return rgba
    k = math.ceil(math.sqrt(h * w / budget))
    while (h // k) * (w // k) > budget:
        k += 1
    hh, ww = max(1, h // k), max(1, w // k)
    ky, kx = max(1, h // hh), max(1, w // ww)
    cut = rgba[:hh * ky, :ww * kx]
    return cut.reshape(hh, ky, ww, kx, -1).mean(axis=(1, 3), dtype=np.float32)


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    """The sRGB transfer function's inverse (IEC 61966-2-1)."""
    c = np.clip(np.asarray(c, np.float32), 0.0, None)
    return np.where(c <= 0.04045, c / np.float32(12.92),
                    ((c + np.float32(0.055)) / np.float32(1.055)) ** np.float32(2.4))


# Byte values k / 255 decoded (indexed by k).
_BYTE_SRGB = srgb_to_linear(np.arange(256, dtype=np.float32) / np.float32(255.0))
