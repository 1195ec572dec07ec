"""Acceptance figures of the World, emissive and soft-shadow light sources against Cycles.

    python -m tools.sources_check [--scenes sky_room,sky_yard,panel_room,soft_room]
        [--cache .cache/sources] [--out docs/report/sources.md] [--repeats 3]

For each scene (tools.scenes) it renders, or takes from the cache, a Cycles reference at
128x128 with one diffuse bounce (tools/make_references.ensure_reference), opens its .blend,
extracts it as the add-on does and runs the in-process core engine at the default settings,
then measures, as issue 17 asks:
- Diffuse Direct: the mean over the pixels Cycles lights (Diffuse Direct above 2 % of its 99th
  percentile) against Cycles' mean there (asked: within 5 %);
- Indirect (Diffuse Indirect x Diffuse Color): relative RMSE (lpv_core/render/error.py;
  asked: at most 0.30 in rooms, 0.35 outdoors);
- HDR-FLIP of Combined (tools/report.hdr_flip) and the LPV time (update + render, median);
- the reference's own noise (unless ``--no-noise``): a second Cycles render of the same spp
  with another seed (cached beside the reference); the two differ by sqrt(2) x the noise of
  one, which adds in quadrature to the measured error: noise-removed error
  sqrt(e^2 - noise^2) (the lamp report's tools/report.denoised), shown beside the measured one.
It prints a table and writes it, with the commit and the commands, to ``--out``.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import math
import os
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
RESOLUTION = (128, 128)
# Scene -> (Cycles samples, kind): samples enough for low noise (a skylight is hard to sample).
SCENES = {
    "sky_room": (4096, "room"),
    "sky_room_thin": (4096, "room"),
    "sky_room_thin_ground": (4096, "room"),
    "sky_yard": (1024, "outdoors"),
    "panel_room": (2048, "room"),
    "soft_room": (2048, "room"),
    "window_room": (4096, "room"),
    "window_room_thick": (4096, "room"),
}
DIRECT_TOLERANCE = 0.05
INDIRECT_LIMIT = {"room": 0.30, "outdoors": 0.35}
LIT_FRACTION = 0.02  # of Cycles' 99th-percentile Diffuse Direct: the pixels it lights


def lit_mask(ref_direct: np.ndarray) -> np.ndarray:
    """Pixels Cycles lights directly: Diffuse Direct (channel mean) above LIT_FRACTION of its
    99th percentile."""
    d = np.asarray(ref_direct, np.float64)[..., :3].mean(axis=-1)
    return d > LIT_FRACTION * float(np.percentile(d, 99))


def direct_ratio(test: dict, ref: dict) -> float:
    """mean(LPV Diffuse Direct) / mean(Cycles Diffuse Direct) over the lit pixels."""
    mask = lit_mask(ref["Diffuse Direct"])
    r = float(np.asarray(ref["Diffuse Direct"], np.float64)[..., :3][mask].mean())
    t = float(np.nan_to_num(np.asarray(test["Diffuse Direct"], np.float64)[..., :3][mask]).mean())
    return t / r if r > 0 else math.nan


def _manifest_seconds(cache: Path, exr: Path) -> float | None:
    try:
        data = json.loads((cache / "references.json").read_text())
    except (OSError, ValueError):
        return None
    times = [e["seconds"] for e in data.values() if e.get("exr") == exr.name and e.get("seconds")]
    return max(times) if times else None


def save_comparison(path: Path, ref: dict, test: dict) -> str:
    """A PNG: Cycles (top) and LPV (bottom); Diffuse Direct, the indirect term and Combined,
    each pair on one exposure (Cycles' 99th percentile), sRGB."""
    from PIL import Image

    from lpv_core.render.error import indirect_term

    rows = []
    for passes in (ref, test):
        rows.append([np.asarray(passes["Diffuse Direct"])[..., :3], indirect_term(passes),
                     np.asarray(passes["Combined"])[..., :3]])
    white = [max(float(np.percentile(img, 99)), 1e-6) for img in rows[0]]
    tiles = [np.concatenate([np.clip(np.nan_to_num(img) / w, 0, 1) ** (1 / 2.2)
                             for img, w in zip(r, white, strict=True)], 1) for r in rows]
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray((np.concatenate(tiles, 0) * 255).astype(np.uint8)).save(path)
    return path.name


def reference_noise(exr: Path, samples: int, ref_indirect: np.ndarray) -> float:
    """The relative RMSE of the reference's indirect term from its own noise: RMSE between it
    and a render of the open scene at the same samples with seed 1 (cached as
    ``<exr>_seed1.exr``), / sqrt(2) / mean(reference)."""
    from lpv_addon.render.cycles import render_cycles_passes
    from lpv_core.render.error import indirect_term, relative_rmse
    from tools import report

    other = exr.with_name(f"{exr.stem}_seed1.exr")
    if not other.is_file():
        render_cycles_passes(other, samples=samples, diffuse_bounces=1, resolution=RESOLUTION,
                             seed=1)
    return relative_rmse(indirect_term(report._read_exr(other)), ref_indirect) / math.sqrt(2)


def check_scene(name: str, cache: Path, repeats: int, images: Path | None = None,
                noise: bool = True) -> dict:
    """Reference, LPV run and figures of one scene."""
    os.environ.setdefault("BLENDER_USER_RESOURCES", tempfile.mkdtemp(prefix="lpv_sources_"))
    import bpy

    import lpv_core as core
    from lpv_addon.scene_io.extract import extract_scene
    from lpv_core.render.error import indirect_term, relative_rmse
    from tools import report
    from tools.make_references import ensure_reference

    samples, kind = SCENES[name]
    blend, exr = ensure_reference(name, cache, samples=samples, bounces=1, resolution=RESOLUTION)
    ref = report._read_exr(exr)
    bpy.ops.wm.open_mainfile(filepath=str(blend), load_ui=False)
    scene = bpy.context.scene
    timings: dict = {}
    core_scene = extract_scene(bpy.context.evaluated_depsgraph_get(), scene, RESOLUTION,
                               timings=timings)
    engine = report._make_engine(core.render.raster.Rasterizer())
    settings = dataclasses.replace(core_scene.settings)
    run = report.run_lpv(core_scene, settings, engine, repeats)
    test = run["passes"]
    row = {
        "scene": name, "kind": kind, "samples": samples,
        "cycles_s": _manifest_seconds(cache, exr),
        "direct_ratio": direct_ratio(test, ref),
        "indirect": relative_rmse(indirect_term(test), indirect_term(ref)),
        "flip": report.hdr_flip(report.combined_term(test), report.combined_term(ref)),
        "lpv_s": run["time_s"], "extract_ms": sum(timings.values()),
        "world_ms": timings.get("world", 0.0),
        "lights": [f"{lt.type.lower()} {lt.name}" for lt in core_scene.lights],
        "world": None if core_scene.world is None else list(core_scene.world.radiance.shape),
        "approximated": list(core_scene.approximated),
    }
    if noise:
        from tools.report import denoised

        row["noise"] = reference_noise(exr, samples, indirect_term(ref))
        row["indirect_corr"] = denoised(row["indirect"], row["noise"])
    if images is not None:
        row["image"] = save_comparison(images / f"sources_{name}.png", ref, test)
    row["direct_ok"] = abs(row["direct_ratio"] - 1.0) <= DIRECT_TOLERANCE
    row["indirect_ok"] = row["indirect"] <= INDIRECT_LIMIT[kind]
    return row


def _f(v, fmt=".3f") -> str:
    return "-" if v is None or (isinstance(v, float) and not math.isfinite(v)) else format(v, fmt)


def table(rows: list[dict]) -> list[str]:
    out = [("| scene | Diffuse Direct / Cycles (lit pixels) | Indirect rel. RMSE (limit) | "
            "reference noise / noise removed | HDR-FLIP Combined | LPV time | "
            "extraction (World) | Cycles reference |"),
           "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if "error" in r:
            out.append(f"| {r['scene']} | failed: {r['error']} | | | | | | |")
            continue
        out.append(
            f"| {r['scene']} | {_f(r['direct_ratio'])} {'ok' if r['direct_ok'] else 'OUT'} | "
            f"{_f(r['indirect'])} ({INDIRECT_LIMIT[r['kind']]:.2f}) "
            f"{'ok' if r['indirect_ok'] else 'OUT'} | "
            f"{_f(r.get('noise'))} / {_f(r.get('indirect_corr'))} | {_f(r['flip'])} | {_f(r['lpv_s'], '.2f')} s | "
            f"{_f(r['extract_ms'], '.0f')} ms ({_f(r['world_ms'], '.0f')} ms) | "
            f"{r['samples']} spp, {_f(r['cycles_s'], '.0f')} s |")
    return out


def write(rows: list[dict], out: Path, argv: list[str]) -> None:
    import subprocess

    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, check=False,
                            capture_output=True, text=True).stdout.strip()
    lines = [
        "# Light sources against Cycles (issue 17)", "",
        (f"Measured {datetime.datetime.now(datetime.UTC):%Y-%m-%d %H:%M} UTC at commit "
        f"`{commit}` (and the working tree then) with "
        f"`python -m tools.sources_check {' '.join(argv)}`."), "",
        (f"{RESOLUTION[0]}x{RESOLUTION[1]} pixels, the default GI settings, one diffuse bounce "
        "in Cycles (CPU, tools/make_references.py; the time is Cycles' render of the "
        "reference on this machine, cached in `.cache/sources`). *Lit pixels*: Cycles' "
        f"Diffuse Direct above {LIT_FRACTION:.0%} of its 99th percentile. Asked: direct within "
        f"{DIRECT_TOLERANCE:.0%}; indirect at most 0.30 in rooms, 0.35 outdoors (the verdict "
        "is on the measured error). *Reference noise*: the reference's own relative RMSE, from "
        "a second render of the same samples with another seed (their difference / sqrt 2); "
        "it adds in quadrature to the measured error, so *noise removed* = sqrt(e^2 - noise^2) "
        "estimates the error against a noiseless Cycles."), "",
        *table(rows), "",
    ]
    for r in rows:
        if "error" in r:
            continue
        lines.append(f"- **{r['scene']}**: lights {', '.join(r['lights']) or 'none'}; World "
                     f"map {r['world'] or 'none'}; approximated: "
                     f"{'; '.join(r['approximated']) or 'nothing'}.")
        if r.get("image"):
            lines += ["", (f"![{r['scene']}: Cycles (top), LPV (bottom); Diffuse Direct, "
                      f"indirect, Combined]({r['image']})"), ""]
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(lines) + "\n")


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenes", default=",".join(SCENES))
    p.add_argument("--cache", type=Path, default=ROOT / ".cache" / "sources")
    p.add_argument("--out", type=Path, default=ROOT / "docs" / "report" / "sources.md")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--no-write", action="store_true", help="print only")
    p.add_argument("--no-noise", action="store_true",
                   help="skip the second-seed reference (no noise estimate)")
    args = p.parse_args(argv)
    if str(ROOT) not in sys.path:
        sys.path.insert(0, str(ROOT))
    from tools import scenes

    rows = []
    for name in [n.strip() for n in args.scenes.split(",") if n.strip()]:
        if name not in SCENES or name not in scenes.SCENES:
            print(f"[sources_check] {name}: no such scene (yet); skipped", file=sys.stderr)
            continue
        try:
            rows.append(check_scene(name, args.cache.resolve(), args.repeats,
                                    None if args.no_write else args.out.parent,
                                    not args.no_noise))
        except Exception as exc:  # noqa: BLE001 - a failing scene is reported, others still run
            rows.append({"scene": name, "error": f"{type(exc).__name__}: {exc}"[:300]})
        print("\n".join(table(rows[-1:])[2:]), flush=True)
    print("\n".join(table(rows)))
    if not args.no_write:
        write(rows, args.out, argv)
    return 0


if __name__ == "__main__":
    sys.exit(main())
