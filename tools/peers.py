"""The peers a Blender user would preview with instead of LPV, measured like LPV: Cycles with
OpenImageDenoise, EEVEE with ray tracing on and off, and KD10's own method (``angular="sh"``).

Each peer is a curve of (time_s, combined, flip[, indirect]) rows against the report's
reference. The verdicts compare LPV with each peer at equal time (the peer's error at LPV's
frame time) and at equal error (the time the peer needs to reach LPV's error), in
:func:`verdicts`. Denoised Cycles and EEVEE have no separable indirect pass (the denoiser and
EEVEE's Combined mix direct and indirect light): they are compared on Combined only.
"""

from __future__ import annotations

import itertools
import math
import os
import statistics
import uuid
from pathlib import Path

import numpy as np

# EEVEE's render samples: Blender's default (scene.eevee.taa_render_samples), what a user gets.
EEVEE_SAMPLES = 64
# The GL renderers that are not a GPU: an EEVEE time measured on one is not an EEVEE time.
SOFTWARE_GL = ("llvmpipe", "softpipe", "swrast", "lavapipe")


def eevee_engine_id(bpy) -> str:
    """EEVEE's engine identifier in this Blender ('BLENDER_EEVEE_NEXT' in 4.2-4.4)."""
    items = bpy.types.RenderSettings.bl_rna.properties["engine"].enum_items.keys()
    return "BLENDER_EEVEE_NEXT" if "BLENDER_EEVEE_NEXT" in items else "BLENDER_EEVEE"


def gl_renderer(bpy) -> str:
    """The OpenGL renderer string Blender draws with ('' when there is no GPU module)."""
    try:
        import gpu

        return str(gpu.platform.renderer_get())
    except Exception:  # noqa: BLE001 - no GPU context: nothing to name
        return ""


def is_software(renderer: str) -> bool:
    return any(name in renderer.lower() for name in SOFTWARE_GL)


def render_eevee_passes(out_path, scene, raytracing: bool, samples: int = EEVEE_SAMPLES,
                        resolution: tuple[int, int] | None = None) -> dict:
    """Render ``scene`` with EEVEE into a multi-layer EXR (Combined), ray tracing on or off;
    every setting changed is restored afterwards. Returns {"seconds", "path"}."""
    import bpy

    r = scene.render
    im = r.image_settings
    out_path = Path(out_path).resolve()
    out_path.parent.mkdir(parents=True, exist_ok=True)
    tmp = out_path.with_name(f".{out_path.stem}.{os.getpid()}.{uuid.uuid4().hex[:8]}.exr")
    wanted = [
        (r, "engine", eevee_engine_id(bpy)),
        (scene.eevee, "use_raytracing", bool(raytracing)),
        (scene.eevee, "taa_render_samples", int(samples)),
        (r, "filter_size", 1.0),
        (r, "resolution_percentage", 100),
        (r, "use_border", False),
        (r, "use_compositing", False),
        (r, "use_sequencer", False),
        (r, "filepath", str(tmp)),
        (r, "use_file_extension", False),
        (im, "media_type", "MULTI_LAYER_IMAGE"),
        (im, "file_format", "OPEN_EXR_MULTILAYER"),
        (im, "color_depth", "32"),
    ]
    if resolution is not None:
        wanted[1:1] = [(r, "resolution_x", int(resolution[0])),
                       (r, "resolution_y", int(resolution[1]))]
    from lpv_addon.render.cycles import render_with_settings

    seconds = render_with_settings(scene, wanted, tmp, out_path)
    return {"seconds": seconds, "path": str(out_path)}


def eevee_points(blend: Path, tag: str, prof: dict, resolution, cache: Path, fresh: bool,
                 read_exr, errors) -> list[dict]:
    """EEVEE with ray tracing on and off, rendered in a child process (moderngl, which the
    report's LPV runs use, breaks Blender's own GL drawing in the same process), cached like
    the Cycles sweep; the child's first render compiles shaders and is not timed."""
    import json
    import subprocess
    import sys

    folder = cache / "eevee"
    folder.mkdir(parents=True, exist_ok=True)
    samples = prof["eevee_samples"]
    paths = {rt: folder / f"{tag}_rt{int(rt)}_s{samples}.exr" for rt in (True, False)}
    metas = {rt: p.with_suffix(".json") for rt, p in paths.items()}
    if fresh or not all(m.is_file() for m in metas.values()):
        cmd = [sys.executable, "-m", "tools.peers", "eevee", str(blend), str(folder), tag,
               str(samples), f"{resolution[0]}x{resolution[1]}"]
        proc = subprocess.run(cmd, cwd=Path(__file__).resolve().parents[1],
                              capture_output=True, text=True, check=False)
        if proc.returncode != 0:
            raise RuntimeError(f"EEVEE child failed ({proc.returncode}): {proc.stderr[-500:]}")
    points = []
    for rt in (True, False):
        row = json.loads(metas[rt].read_text())
        row["peer"] = f"EEVEE, ray tracing {'on' if rt else 'off'}"
        row.update(errors(read_exr(paths[rt])))  # Combined only: no separable indirect pass
        points.append(row)
    return points


def _eevee_child(blend: str, folder: str, tag: str, samples: int, resolution: str) -> None:
    """The child of eevee_points: open ``blend``, render EEVEE with ray tracing on and off."""
    import json
    import tempfile

    os.environ.setdefault("BLENDER_USER_RESOURCES", tempfile.mkdtemp(prefix="lpv_eevee_"))
    import bpy

    bpy.ops.wm.open_mainfile(filepath=blend, load_ui=False)
    scene = bpy.context.scene
    res = tuple(int(v) for v in resolution.split("x"))
    warm = Path(folder) / f".warm_{os.getpid()}.exr"
    render_eevee_passes(warm, scene, True, 1, res)
    warm.unlink(missing_ok=True)
    renderer = gl_renderer(bpy)
    for rt in (True, False):
        path = Path(folder) / f"{tag}_rt{int(rt)}_s{samples}.exr"
        times = [render_eevee_passes(path, scene, rt, samples, res)["seconds"]]
        meta = {"raytracing": rt, "samples": samples, "times_s": times,
                "time_s": statistics.median(times), "renderer": renderer,
                "software": is_software(renderer)}
        path.with_suffix(".json").write_text(json.dumps(meta, indent=1))


# ---------------------------------------------------------------------------------------------
# Verdicts
# ---------------------------------------------------------------------------------------------


def loglog(pts: list[tuple[float, float]], t: float) -> tuple[float | None, str]:
    """The error at time ``t`` between sorted (time, error) points, log-log interpolated;
    (None, "none") outside them."""
    for (t0, e0), (t1, e1) in itertools.pairwise(pts):
        if t0 <= t <= t1:
            if t1 == t0:
                return min(e0, e1), "measured"
            a = (math.log(t) - math.log(t0)) / (math.log(t1) - math.log(t0))
            return math.exp(math.log(e0) + a * (math.log(e1) - math.log(e0))), "interpolated"
    return None, "none"


def error_at(curve: list[dict], t: float, key: str) -> tuple[float | None, str]:
    """A peer's error at time ``t``: log-log interpolation between its points, its last
    point's error beyond them (a peer is not assumed to improve past what was measured),
    None below its fastest point."""
    pts = sorted((c["time_s"], c[key]) for c in curve
                 if c.get(key) is not None and np.isfinite(c[key]) and c[key] > 0)
    if not pts:
        return None, "none"
    if t < pts[0][0]:
        return None, "below"
    if t >= pts[-1][0]:
        return min(e for _, e in pts), "held"
    return loglog(pts, t)


def time_to(curve: list[dict], target: float, key: str) -> tuple[float | None, str]:
    """The time a peer needs to reach error ``target``: the first point at or below it,
    log-log interpolated from the point before; None when no point reaches it."""
    pts = sorted((c["time_s"], c[key]) for c in curve
                 if c.get(key) is not None and np.isfinite(c[key]) and c[key] > 0)
    prev = None
    for t, e in pts:
        if e <= target:
            if prev is None or prev[1] <= e:
                return t, ("at or below its fastest point" if prev is None else "measured")
            t0, e0 = prev
            a = (math.log(target) - math.log(e0)) / (math.log(e) - math.log(e0))
            return math.exp(math.log(t0) + a * (math.log(t) - math.log(t0))), "interpolated"
        prev = (t, e)
    return None, "not reached"


def verdicts(lpv: dict, peer: str, curve: list[dict], key: str = "combined",
             time_is_meaningful: bool = True) -> dict:
    """LPV row ``lpv`` against one peer's curve on error ``key``: equal-time error ratio
    (peer / LPV, > 1: LPV better) and equal-error time ratio (peer / LPV, > 1: LPV faster)."""
    e_lpv, t_lpv = lpv[key], lpv["time_s"]
    out = {"peer": peer, "key": key, "lpv_label": lpv["label"], "lpv_error": e_lpv,
           "lpv_time_s": t_lpv, "time_meaningful": time_is_meaningful,
           "peer_best": min((c[key] for c in curve if c.get(key) is not None), default=None)}
    if time_is_meaningful:
        e_peer, how = error_at(curve, t_lpv, key)
        t_peer, how_t = time_to(curve, e_lpv, key)
        out.update({"eq_time_peer_error": e_peer, "eq_time_how": how,
                    "eq_time_ratio": None if e_peer is None else e_peer / e_lpv,
                    "eq_error_peer_time_s": t_peer, "eq_error_how": how_t,
                    "eq_error_ratio": None if t_peer is None else t_peer / t_lpv})
    best = out["peer_best"]
    if best is None:
        out["wins"] = None
    elif not time_is_meaningful:
        out["wins"] = bool(e_lpv < best)
    elif out["eq_time_how"] == "below":
        out["wins"] = True  # the peer has no image yet at LPV's frame time
    else:
        out["wins"] = out["eq_time_ratio"] > 1.0
    return out


def verdict_text(v: dict) -> str:
    """One line in plain words for a verdict dict."""
    name, e = v["peer"], v["lpv_error"]
    if v["peer_best"] is None:
        return f"{name}: no measurement"
    if not v["time_meaningful"]:
        ratio = v["peer_best"] / e
        word = "lower" if ratio > 1 else "higher"
        return (f"{name}: LPV's {v['key']} error {e:.3f} is {max(ratio, 1 / ratio):.1f}x "
                f"{word} than its {v['peer_best']:.3f} (its time here is a software-renderer "
                "time, not compared)")
    parts = []
    r = v.get("eq_time_ratio")
    if r is None:
        parts.append(f"at LPV's {v['lpv_time_s']:.2f} s it has no image yet "
                     "(its fastest point is slower): LPV wins on time")
    elif r > 1:
        parts.append(f"at equal time LPV's error is {r:.1f}x lower ({e:.3f} vs "
                     f"{v['eq_time_peer_error']:.3f})")
    else:
        parts.append(f"at equal time LPV's error is {1 / r:.1f}x higher ({e:.3f} vs "
                     f"{v['eq_time_peer_error']:.3f})")
    t = v.get("eq_error_peer_time_s")
    if t is None:
        parts.append(f"it never reaches LPV's error (best {v['peer_best']:.3f})")
    else:
        q = v["eq_error_ratio"]
        parts.append(f"it reaches LPV's error in {t:.2f} s ({q:.1f}x LPV's time"
                     f"{', ' + v['eq_error_how'] if v['eq_error_how'] != 'interpolated' else ''})")
    return f"{name}: " + "; ".join(parts)


def table(lpv_rows: dict[str, dict], curves: dict[str, list[dict]]) -> list[dict]:
    """Verdicts of each named LPV row (e.g. defaults, most accurate) against every peer curve:
    on Combined for all, and on the indirect term where the peer has that pass. A peer whose
    points were timed on a software renderer is compared on error only."""
    out = []
    for label, row in lpv_rows.items():
        if row is None or "error" in row:
            continue
        for peer, curve in curves.items():
            if not curve:
                continue
            meaningful = not any(c.get("software") for c in curve)
            keys = ["combined"] + (["indirect"] if all("indirect" in c for c in curve) else [])
            for key in keys:
                v = verdicts(row, peer, curve, key, meaningful)
                v["lpv_row"] = label
                v["text"] = verdict_text(v)
                out.append(v)
    return out


if __name__ == "__main__":
    import sys

    if len(sys.argv) == 7 and sys.argv[1] == "eevee":
        _eevee_child(sys.argv[2], sys.argv[3], sys.argv[4], int(sys.argv[5]), sys.argv[6])
    else:
        sys.exit("usage: python -m tools.peers eevee BLEND FOLDER TAG SAMPLES WxH")
