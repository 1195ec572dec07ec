"""Time to the first LPV result as a new user meets it, and again after an extension reinstall.

    .venv/bin/python -m tools.first_run_bench [--zip lpv_gi.zip] [--json out.json]

A fresh Blender user folder (BLENDER_USER_RESOURCES, a temp dir) with an empty kernel cache
and an empty Mesa shader cache; the extension zip (built from this tree unless ``--zip``)
installed as a user does; LPV GI turned on in the shipped demo scene; the live viewport's timer
step (``live.tick``) run until the first result is in. Then until the worker's CPU kernels are
compiled, one more update, the zip installed again over itself (an update keeps the user
folder) and the same measurement. Prints the figures (docs/benchmarks.md) and, with ``--json``,
writes what tests/test_first_run.py checks.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MODULE = f"bl_ext.user_default.{tomllib.loads((ROOT / 'blender_manifest.toml').read_text())['id']}"

SCRIPT = r"""
import importlib, json, os, sys, time
import bpy, addon_utils
import numpy as np

zip_path, module, budget = sys.argv[1], sys.argv[2], float(sys.argv[3])
sub = lambda name: importlib.import_module(f"{module}.lpv_addon.{name}")

def tick_until(done, limit):
    live, t0 = sub("viewport.live"), time.monotonic()
    while not done() and time.monotonic() - t0 < limit:
        time.sleep(min(live.tick(require_viewport=False), 0.05))
    return time.monotonic() - t0

def first_result():
    live = sub("viewport.live")
    sub("scene_io.demo").cornell_box("SPOT", resolution=(64, 64))
    bpy.context.scene.lpv.enabled = True
    live.mark_dirty("bench")
    seconds = tick_until(lambda: live.STATE.current is not None, budget)
    cur = live.STATE.current
    info = cur.stats.get("info", {}) if cur is not None else {}
    return {"seconds": seconds, "cpu_kernels": info.get("cpu_kernels"),
            "kernels": dict(getattr(live.STATE, "kernels", {})), "lines": live.stats_lines(),
            "values": cur.values.tolist() if cur is not None else None}

def kernels_ready():
    live = sub("viewport.live")
    kernels = lambda: getattr(live.STATE, "kernels", {})  # (a zip from before the warm-up)
    seconds = tick_until(lambda: kernels().get("state") != "compiling", budget)
    serial = live.STATE.current.serial
    for ob in bpy.context.scene.objects:  # an edit the worker computes
        if ob.type == "LIGHT":
            ob.data.energy *= 1.25
    live.mark_dirty("bench")
    tick_until(lambda: live.STATE.current.serial > serial, budget)
    info = live.STATE.current.stats.get("info", {})
    return {"seconds": seconds, "kernels": dict(kernels()),
            "cpu_kernels": info.get("cpu_kernels")}

def install():
    t = time.monotonic()
    result = bpy.ops.extensions.package_install_files(
        filepath=zip_path, repo="user_default", enable_on_install=True)
    return sorted(result), time.monotonic() - t

def files(root, suffixes=(".nbi", ".nbc")):
    return sum(1 for _d, _s, names in os.walk(root or "-") for n in names if n.endswith(suffixes))

def kernel_cache():
    return getattr(sub("worker_client"), "kernel_cache", lambda: None)()

out = {"install": install()}
ext_dir = os.path.dirname(os.path.dirname(sub("worker_client").__file__))
out["kernel_cache"] = kernel_cache()
out["user_folder"] = os.environ["BLENDER_USER_RESOURCES"]
out["extension_dir"] = ext_dir
out["cold"] = first_result()
out["compile"] = kernels_ready()
out["cache_files"] = files(out["kernel_cache"])
out["extension_cache_files"] = files(ext_dir)
sub("viewport.live").shutdown()
out["reinstall"] = install()
out["warm"] = first_result()
out["warm_kernel_cache"] = kernel_cache()
out["warm_extension_cache_files"] = files(ext_dir)
a, b = (np.array(out[k].pop("values"), np.float64) for k in ("cold", "warm"))
out["values"] = {"max": float(np.abs(a).max()), "max_difference": float(np.abs(a - b).max())}
addon_utils.disable(module, default_set=True)
print("RESULT=" + json.dumps(out))
"""


def run(zip_path: Path, budget: float = 900.0) -> dict:
    """The measurement in a fresh user folder, in a child bpy process: the script's RESULT."""
    with tempfile.TemporaryDirectory(prefix="lpv_first_run_") as tmp:
        env = dict(os.environ)
        for var in ("LPV_GI_CACHE_DIR", "NUMBA_CACHE_DIR", "PYTHONPATH", "LPV_JIT"):
            env.pop(var, None)  # the user's own folders decide, as for a user
        env["BLENDER_USER_RESOURCES"] = str(Path(tmp, "blender_user"))
        env["MESA_SHADER_CACHE_DIR"] = str(Path(tmp, "mesa_cache"))
        proc = subprocess.run([sys.executable, "-c", SCRIPT, str(zip_path), MODULE, str(budget)],
                              cwd=tmp, env=env, capture_output=True, text=True, check=False,
                              timeout=4 * budget)
        lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT=")]
        if proc.returncode != 0 or not lines:
            raise RuntimeError((proc.stdout + proc.stderr)[-4000:])
        return json.loads(lines[-1][len("RESULT="):])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--zip", type=Path, help="the extension zip (default: built now)")
    parser.add_argument("--json", type=Path, help="write the measurement here")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as dist:
        if args.zip is None:
            from tools.build_extension import build_extension

            args.zip = build_extension(dist)
        r = run(args.zip)
    if args.json:
        args.json.write_text(json.dumps(r, indent=1))
    for key, label in (("cold", "empty kernel cache"), ("warm", "after reinstalling the zip")):
        f = r[key]
        print(f"first LPV result, {label}: {f['seconds']:.1f} s ({f['cpu_kernels']}, kernels "
              f"{f['kernels'].get('state')})")
    c = r["compile"]
    print(f"kernels compiled in the background: {c['kernels'].get('compiled')} of "
          f"{c['kernels'].get('of')} after {c['kernels'].get('seconds')} s; the next update "
          f"ran on {c['cpu_kernels']}")
    v = r["values"]
    print(f"the two first results differ by at most {v['max_difference']:.2e} "
          f"(largest value {v['max']:.3g})")
    print(f"kernel cache: {r['kernel_cache']} ({r['cache_files']} files; "
          f"{r['extension_cache_files']} inside the extension)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
