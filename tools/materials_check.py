"""Acceptance figures of extracted materials (issue 18) on tools.scenes.checker_room.

    python -m tools.materials_check [--cache .cache/materials] [--samples 4096]
        [--out docs/report/materials.md]

Renders, or takes from the cache, a Cycles reference of checker_room at 128x128 with one
diffuse bounce (tools/make_references.ensure_reference), extracts the scene as the add-on does,
runs the in-process core engine at the default settings and measures:
- Diffuse Color relative RMSE (lpv_core/render/error.py) outside one-pixel geometry edges
  (asked: at most 0.02). Edges come from OUR G-buffer: a covered pixel is an edge pixel when
  any 8-neighbour is uncovered, lies more than EDGE_DISTANCE away or its normal differs by more
  than EDGE_COS (a face or object boundary), so an edge is a pixel a silhouette or crease
  crosses, where Cycles' pixel filter mixes the two sides; also printed without the checker's
  texel edges (Cycles' own Diffuse Color discontinuities), which the filter mixes likewise;
- indirect (Diffuse Indirect x Diffuse Color) relative RMSE over all pixels (asked: <= 0.30),
  also with the reference's own noise removed in quadrature (tools.report.denoised): the noise
  is the relative RMSE between the reference and a second render at another seed, over sqrt 2;
- the metallic block's largest Diffuse Color component, ours and Cycles' (asked: 0 like Cycles').
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
RESOLUTION = (128, 128)
SCENE = "checker_room"
EDGE_DISTANCE = 0.15  # m; well above the neighbour spacing on the floor at this resolution
EDGE_COS = 0.95
METAL_BOX = ((0.4, -0.2, 0.0), (1.2, 0.6, 0.8))  # tools.scenes.checker_room's Metal block
WALLS = 2.0  # and its walls, at x = 2 and y = 2
COLOUR_STEP = 0.05  # well above Cycles' Diffuse Color noise, well below a checker step (0.6)
LIMITS = {"color": 0.02, "indirect": 0.30}


def geometry_edges(covered: np.ndarray, pos: np.ndarray, nrm: np.ndarray) -> np.ndarray:
    """(H, W) bool: uncovered pixels and covered ones beside a silhouette, a depth jump or a
    normal change (see the module docstring)."""
    h, w = covered.shape
    P = np.full((h, w, 3), np.nan)
    P[covered] = pos
    N = np.zeros((h, w, 3))
    N[covered] = nrm
    Pp = np.pad(P, ((1, 1), (1, 1), (0, 0)), constant_values=np.nan)
    Np = np.pad(N, ((1, 1), (1, 1), (0, 0)))
    edge = ~covered.copy()
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            q = Pp[1 + dy:h + 1 + dy, 1 + dx:w + 1 + dx]
            m = Np[1 + dy:h + 1 + dy, 1 + dx:w + 1 + dx]
            with np.errstate(invalid="ignore"):
                edge |= (~np.isfinite(q).all(-1) | (np.abs(q - P).max(-1) > EDGE_DISTANCE)
                         | ((m * N).sum(-1) < EDGE_COS))
    return edge


def colour_edges(color: np.ndarray, step: float = COLOUR_STEP) -> np.ndarray:
    """(H, W) bool: pixels with an 8-neighbour whose Diffuse Color (Cycles') differs by more
    than ``step`` in a channel: texel boundaries of the checker, mixed by the pixel filter."""
    h, w = color.shape[:2]
    cp = np.pad(color, ((1, 1), (1, 1), (0, 0)), mode="edge")
    edge = np.zeros((h, w), bool)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            edge |= np.abs(cp[1 + dy:h + 1 + dy, 1 + dx:w + 1 + dx] - color).max(-1) > step
    return edge


def black_metal_indirect(blend: Path, cache: Path, samples: int, raster, engine) -> tuple:
    """Indirect rel. RMSE with the metallic block's surface swapped for a black Diffuse BSDF
    in both renderers (on the opened .blend, not saved): what LPV scores when the light the
    metal reflects is out of Cycles' reference too; and that reference's indirect term."""
    import bpy

    from lpv_addon.render import cycles
    from lpv_addon.scene_io.extract import extract_scene
    from lpv_core.render.error import indirect_term, relative_rmse
    from tools import report

    bpy.ops.wm.open_mainfile(filepath=str(blend), load_ui=False)
    nt = bpy.data.materials["Metal"].node_tree
    black = nt.nodes.new("ShaderNodeBsdfDiffuse")
    black.inputs["Color"].default_value = (0.0, 0.0, 0.0, 1.0)
    nt.links.new(black.outputs["BSDF"], nt.nodes["Material Output"].inputs["Surface"])
    exr = cache / f"{blend.stem}_black_metal_s{samples}.exr"
    if not exr.is_file():
        cycles.render_cycles_passes(str(exr), samples=samples, resolution=RESOLUTION)
    core_scene = extract_scene(bpy.context.evaluated_depsgraph_get(), bpy.context.scene,
                               RESOLUTION)
    run = report.run_lpv(core_scene, dataclasses.replace(core_scene.settings), engine, 1)
    ref = indirect_term(report._read_exr(str(exr)))
    return relative_rmse(indirect_term(run["passes"]), ref), ref


def reference_noise(blend: Path, cache: Path, samples: int, ref_indirect: np.ndarray) -> float:
    """The reference's own indirect relative error: relative RMSE against a second Cycles render
    of the same .blend at another seed, over sqrt 2 (two independent errors of equal size)."""
    import bpy

    from lpv_addon.render import cycles
    from lpv_core.render.error import indirect_term, relative_rmse
    from tools import report

    exr = cache / f"{blend.stem}_seed1_s{samples}.exr"
    if not exr.is_file():
        bpy.ops.wm.open_mainfile(filepath=str(blend), load_ui=False)
        cycles.render_cycles_passes(str(exr), samples=samples, resolution=RESOLUTION, seed=1)
    other = indirect_term(report._read_exr(str(exr)))
    return relative_rmse(other, ref_indirect) / np.sqrt(2.0)


def measure(cache: Path, samples: int) -> dict:
    os.environ.setdefault("BLENDER_USER_RESOURCES", tempfile.mkdtemp(prefix="lpv_materials_"))
    import bpy

    import lpv_core as core
    from lpv_addon.scene_io.extract import extract_scene
    from lpv_core.render.error import indirect_term, relative_rmse
    from tools import report
    from tools.make_references import ensure_reference

    blend, exr = ensure_reference(SCENE, cache, samples=samples, bounces=1,
                                  resolution=RESOLUTION)
    ref = report._read_exr(exr)
    bpy.ops.wm.open_mainfile(filepath=str(blend), load_ui=False)
    core_scene = extract_scene(bpy.context.evaluated_depsgraph_get(), bpy.context.scene,
                               RESOLUTION)
    raster = core.render.raster.Rasterizer()
    engine = report._make_engine(raster)
    run = report.run_lpv(core_scene, dataclasses.replace(core_scene.settings), engine, 1)
    test = run["passes"]
    cam = core_scene.camera
    covered, pos, nrm, _, _ = raster.gbuffer(cam.view, cam.projection, *RESOLUTION)
    keep = ~geometry_edges(covered, pos, nrm)
    P = np.full((*covered.shape, 3), np.nan)
    P[covered] = pos
    lo, hi = (np.asarray(b) for b in METAL_BOX)
    with np.errstate(invalid="ignore"):
        metal = keep & (P >= lo - 1e-3).all(-1) & (P <= hi + 1e-3).all(-1)
    ours = np.asarray(test["Diffuse Color"], np.float64)[..., :3]
    cyc = np.asarray(ref["Diffuse Color"], np.float64)[..., :3]
    tex = colour_edges(cyc)
    bare = dataclasses.replace(core_scene, materials=[
        dataclasses.replace(m, specular=np.zeros(3, np.float32)) for m in core_scene.materials])
    no_glossy = report.run_lpv(bare, dataclasses.replace(bare.settings), engine, 1)["passes"]
    black, black_ref = black_metal_indirect(blend, cache, samples, raster, engine)
    # the metal's reflected light per surface: LPV with and without its mirror VPLs, Cycles
    # with the metal and with it black
    ours_metal = (indirect_term(test) - indirect_term(no_glossy)).sum(-1)
    cycles_metal = (indirect_term(ref) - black_ref).sum(-1)
    with np.errstate(invalid="ignore"):
        walls = keep & (P[..., :2] > WALLS - 1e-3).any(-1)
        floor = keep & (P[..., 2] < 1e-3) & ~metal
    metal_light = {name: (float(ours_metal[m].sum()), float(cycles_metal[m].sum()))
                   for name, m in (("floor", floor), ("walls", walls))}
    noise = reference_noise(blend, cache, samples, indirect_term(ref))
    indirect = relative_rmse(indirect_term(test), indirect_term(ref))
    return {
        "reference_noise": noise, "indirect_denoised": report.denoised(indirect, noise),
        "black_metal_indirect": black, "metal_light": metal_light,
        "no_glossy_indirect": relative_rmse(indirect_term(no_glossy), indirect_term(ref)),
        "samples": samples, "kept": int(keep.sum()), "pixels": int(keep.size),
        "color": relative_rmse(ours[keep], cyc[keep]),
        "color_all": relative_rmse(ours, cyc),
        "color_tex": relative_rmse(ours[keep & ~tex], cyc[keep & ~tex]),
        "kept_tex": int((keep & ~tex).sum()),
        "indirect": indirect,
        "metal_pixels": int(metal.sum()),
        "metal_ours": float(ours[metal].max(initial=0.0)),
        "metal_cycles": float(cyc[metal].max(initial=0.0)),
        "lpv_s": run["time_s"], "approximated": list(core_scene.approximated),
    }


def table(r: dict) -> list[str]:
    ok = {k: "ok" if r[k] <= v else "OUT" for k, v in LIMITS.items()}
    return [
        "| figure | LPV | asked |", "|---|---|---|",
        (f"| Diffuse Color rel. RMSE, off geometry edges ({r['kept']} of {r['pixels']} px) | "
        f"{r['color']:.4f} {ok['color']} | <= {LIMITS['color']} |"),
        (f"| Diffuse Color rel. RMSE, off geometry and texel edges ({r['kept_tex']} px) | "
         f"{r['color_tex']:.4f} | - |"),
        f"| Diffuse Color rel. RMSE, all pixels | {r['color_all']:.4f} | - |",
        (f"| indirect rel. RMSE (Diffuse Indirect x Diffuse Color) | {r['indirect']:.3f} "
        f"{ok['indirect']} | <= {LIMITS['indirect']} |"),
        (f"| same, the reference's noise ({r['reference_noise']:.3f}) removed in quadrature | "
         f"{r['indirect_denoised']:.3f} | - |"),
        (f"| same, metallic block swapped for black diffuse in both | "
         f"{r['black_metal_indirect']:.3f} | - |"),
        (f"| same, LPV without the glossy bounce (no mirror VPLs) | "
         f"{r['no_glossy_indirect']:.3f} | - |"),
        (f"| metallic block's max Diffuse Color ({r['metal_pixels']} px), Cycles | "
        f"{r['metal_ours']:.4f}, Cycles {r['metal_cycles']:.4f} | 0 like Cycles |"),
    ]


def write(r: dict, out: Path, argv: list[str]) -> None:
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, check=False,
                            capture_output=True, text=True).stdout.strip()
    lines = [
        "# Materials against Cycles (issue 18)", "",
        (f"Measured {datetime.datetime.now(datetime.UTC):%Y-%m-%d %H:%M} UTC at commit "
         f"`{commit}` (and the working tree then) with "
         f"`python -m tools.materials_check {' '.join(argv)}`."), "",
        (f"Scene `checker_room` (tools/scenes.py), {RESOLUTION[0]}x{RESOLUTION[1]}, default GI "
         f"settings; Cycles {r['samples']} spp, max and diffuse bounces 1 "
         "(tools/make_references.py), so Cycles' floor also gets the light the metal block "
         "reflects, which LPV bounces as mirror VPLs (docs/algorithm.md, RSM). Geometry edges from our G-buffer (uncovered neighbour, "
         f"position jump > {EDGE_DISTANCE} m or normal cosine < {EDGE_COS}); texel edges from "
         f"Cycles' Diffuse Color (an 8-neighbour differing by > {COLOUR_STEP})."), "",
        *table(r), "",
        f"Approximated: {'; '.join(r['approximated']) or 'nothing'}. LPV time {r['lpv_s']:.2f} s.", "",
        ("Where the Diffuse Color error was (0.0355 off geometry edges before): the checker's "
         "texel edges (Cycles integrates each pixel's 1-pixel box, we read the texture at "
         "2x2 points: now integrated over each sample's cell where the texture bends, "
         "textures.footprint_factor: 0.0149 alone) and a uniform 1.7 % floor bias (Cycles' "
         "Diffuse Color of a Principled dielectric falls with the specular layer's albedo "
         "at the view angle: now Material.diffuse_share, measured on Cycles: 0.0315 alone, "
         "0.0002 off texel edges)."),
        "",
        ("Where the indirect error is: with the metal block black in both renderers it is "
         "the black-metal row, the diffuse LPV error of this scene; the metal's reflected "
         "light (paths light -> metal -> floor) adds the rest: the mirror VPLs' lobe (the "
         "cosine lobe's part above the surface, mirror_lobe) is wider than the roughness-0.3 "
         "GGX lobe, so light Cycles' block top reflects out over the walls partly lands on "
         "them. The metal's light (sum of the indirect term, LPV / Cycles): "
         + ", ".join(f"{k} {a:.0f} / {b:.0f}" for k, (a, b) in r["metal_light"].items())
         + " (docs/decisions.md, Glossy bounce)."),
    ]
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(lines) + "\n")


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--cache", type=Path, default=ROOT / ".cache" / "materials")
    p.add_argument("--samples", type=int, default=4096)
    p.add_argument("--out", type=Path, default=ROOT / "docs" / "report" / "materials.md")
    p.add_argument("--no-write", action="store_true", help="print only")
    args = p.parse_args(argv)
    if str(ROOT) not in sys.path:
        sys.path.insert(0, str(ROOT))
    r = measure(args.cache.resolve(), args.samples)
    print("\n".join(table(r)))
    if not args.no_write:
        write(r, args.out, argv)
    return 0


if __name__ == "__main__":
    sys.exit(main())
