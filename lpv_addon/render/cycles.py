"""Cycles reference renders: diffuse passes into a multi-layer EXR.

The Compare with Cycles operator (and the team's report, which caches them by scene content:
tools/scene_hash.py) calibrates LPV against these files. :func:`render_cycles_passes` renders
the current scene with Cycles on the CPU (Combined, Diffuse Direct/Indirect/Color; only
diffuse bounces; no clamping, denoising (unless asked) or adaptive sampling; fixed seed; 1-pixel box filter)
and puts every setting it touched back afterwards.

Cycles' units, measured with this module (tests/test_reference.py pins them): Diffuse Direct
= irradiance / pi; a point light of power P has intensity P / (4 pi) W/sr; a spot light the
same on its axis times smoothstep((cos t - cos(size/2)) / ((1 - cos(size/2)) * blend)); a sun
of strength S gives irradiance S cos(t); an area light of power P and area A has radiance
P / (pi A) (normalize on) or P / pi (normalize off).
"""

from __future__ import annotations

import os
import time
import uuid
from pathlib import Path
from typing import Any

import bpy

__all__ = ["PASSES", "render_cycles_passes"]

# The passes a reference holds, by Blender's pass names (as read_multilayer returns them).
PASSES = ("Combined", "Diffuse Direct", "Diffuse Indirect", "Diffuse Color")

# Pixel filter: a box exactly one pixel wide. Each pixel is the plain average of the light
# landing on its own footprint (no blur into neighbours, edges stay sharp) - the same thing a
# supersampled rasteriser computes, which is what LPV output is compared with.
PIXEL_FILTER_TYPE = "BOX"
PIXEL_FILTER_WIDTH = 1.0


def _settings(
    scene: bpy.types.Scene,
    view_layer: bpy.types.ViewLayer,
    filepath: str,
    samples: int,
    diffuse_bounces: int,
    resolution: tuple[int, int] | None,
    seed: int,
    denoise: bool = False,
    transmission_bounces: int = 0,
) -> list[tuple[Any, str, Any]]:
    """(owner, attribute, value) for every setting a reference render needs, in set order."""
    r = scene.render
    im = r.image_settings
    c = scene.cycles
    out: list[tuple[Any, str, Any]] = [
        (r, "engine", "CYCLES"),
        (c, "device", "CPU"),
        (c, "samples", int(samples)),
        (c, "use_adaptive_sampling", False),
        (c, "use_denoising", bool(denoise)),
        (c, "seed", int(seed)),
        (c, "use_animated_seed", False),
        (c, "sample_offset", 0),
        # A new scene (bpy.data.scenes.new) defaults to AUTOMATIC, the home file to tabulated
        # Sobol: pin the pattern so the same content renders the same noise in any file.
        (c, "sampling_pattern", "TABULATED_SOBOL"),
        (c, "auto_scrambling_distance", False),
        (c, "scrambling_distance", 1.0),
        (c, "use_layer_samples", "IGNORE"),
        (c, "min_light_bounces", 0),
        (c, "time_limit", 0.0),
        (c, "max_bounces", int(diffuse_bounces)),
        (c, "diffuse_bounces", int(diffuse_bounces)),
        (c, "glossy_bounces", 0),
        (c, "transmission_bounces", int(transmission_bounces)),
        (c, "volume_bounces", 0),
        (c, "sample_clamp_direct", 0.0),
        (c, "sample_clamp_indirect", 0.0),
        (c, "use_fast_gi", False),
        (c, "use_guiding", False),
        (c, "pixel_filter_type", PIXEL_FILTER_TYPE),
        (c, "film_exposure", 1.0),
        (r, "filter_size", PIXEL_FILTER_WIDTH),
        (r, "resolution_percentage", 100),
        (r, "use_border", False),
        (r, "use_motion_blur", False),
        (r, "use_simplify", False),
        (r, "use_compositing", False),
        (r, "use_sequencer", False),
        (r, "use_single_layer", False),
        (r, "filepath", filepath),
        (r, "use_file_extension", False),
        (r, "use_overwrite", True),
        (im, "media_type", "MULTI_LAYER_IMAGE"),
        (im, "file_format", "OPEN_EXR_MULTILAYER"),
        (im, "color_depth", "32"),
        (im, "exr_codec", "ZIP"),
        (view_layer, "use", True),
        (view_layer, "use_pass_combined", True),
        (view_layer, "use_pass_diffuse_direct", True),
        (view_layer, "use_pass_diffuse_indirect", True),
        (view_layer, "use_pass_diffuse_color", True),
    ]
    if denoise:  # OpenImageDenoise with Blender's default inputs, prefilter and quality
        out += [(c, "denoiser", "OPENIMAGEDENOISE"),
                (c, "denoising_input_passes", "RGB_ALBEDO_NORMAL"),
                (c, "denoising_prefilter", "ACCURATE")]
        if hasattr(c, "denoising_quality"):
            out.append((c, "denoising_quality", "HIGH"))
    if resolution is not None:
        w, h = (int(v) for v in resolution)
        out[1:1] = [(r, "resolution_x", w), (r, "resolution_y", h)]
    # Other view layers would be rendered too (and written into the file): switch them off.
    out += [(vl, "use", False) for vl in scene.view_layers if vl != view_layer]
    return out


def render_with_settings(scene: bpy.types.Scene, wanted: list, tmp: Path,
                         out_path: Path) -> float:
    """Render ``scene`` to ``tmp`` with the (owner, attribute, value) settings ``wanted``,
    rename it to ``out_path`` and put every setting back, even on error; the render's time."""
    # Snapshot everything first: setting one value can change another (file format -> depth).
    saved = [(owner, attr, getattr(owner, attr)) for owner, attr, _ in wanted]
    try:
        for owner, attr, value in wanted:
            if getattr(owner, attr) != value:
                setattr(owner, attr, value)
        t0 = time.perf_counter()
        bpy.ops.render.render(write_still=True, scene=scene.name)
        seconds = time.perf_counter() - t0
        if not tmp.is_file():
            raise RuntimeError(f"{scene.render.engine} did not write {tmp} "
                               f"(scene {scene.name!r})")
        os.replace(tmp, out_path)
    finally:
        # Restore in the order of setting: image format before depth/codec (later settings
        # are only valid for the earlier ones).
        for owner, attr, old in saved:
            try:
                if getattr(owner, attr) != old:
                    setattr(owner, attr, old)
            except (TypeError, ValueError, AttributeError):  # pragma: no cover - defensive
                pass
        tmp.unlink(missing_ok=True)
    return seconds


def default_view_layer(scene: bpy.types.Scene) -> bpy.types.ViewLayer:
    ctx = bpy.context
    if getattr(ctx, "scene", None) == scene and getattr(ctx, "view_layer", None) is not None:
        return ctx.view_layer
    return scene.view_layers[0]


def render_cycles_passes(
    out_path: str | os.PathLike,
    samples: int = 1024,
    diffuse_bounces: int = 1,
    resolution: tuple[int, int] | None = None,
    scene: bpy.types.Scene | None = None,
    seed: int = 0,
    denoise: bool = False,
    transmission_bounces: int = 0,
) -> dict:
    """Render ``scene`` (default: the context scene) with Cycles on the CPU into a
    multi-layer EXR with Combined, Diffuse Direct, Diffuse Indirect and Diffuse Color
    (``denoise``: Combined through OpenImageDenoise, the time including it).

    ``transmission_bounces`` (default 0) lets light through a Translucent BSDF's far side
    bounce too (Cycles counts that scattering as a transmission bounce).
    ``diffuse_bounces`` sets both max and diffuse bounces (1: direct light plus one bounce,
    what LPV models); glossy, transmission and volume bounces are 0. Every render, Cycles and
    view-layer setting changed here is restored afterwards, even on error. The file appears
    atomically (rendered under a temporary name, then renamed). Returns {"seconds": wall time
    of the render call, "path": str, "samples", "bounces", "resolution": (w, h)}.
    """
    scene = scene or bpy.context.scene
    view_layer = default_view_layer(scene)
    out_path = Path(out_path).resolve()
    out_path.parent.mkdir(parents=True, exist_ok=True)
    tmp = out_path.with_name(f".{out_path.stem}.{os.getpid()}.{uuid.uuid4().hex[:8]}.exr")

    wanted = _settings(scene, view_layer, str(tmp), samples, diffuse_bounces, resolution, seed,
                       denoise, transmission_bounces)
    res = (tuple(int(v) for v in resolution) if resolution is not None
           else (scene.render.resolution_x, scene.render.resolution_y))
    seconds = render_with_settings(scene, wanted, tmp, out_path)
    return {
        "seconds": seconds,
        "path": str(out_path),
        "samples": int(samples),
        "bounces": int(diffuse_bounces),
        "resolution": res,
    }
