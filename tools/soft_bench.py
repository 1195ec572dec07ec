"""Cost of soft shadows in the direct pass: the direct stage's milliseconds of a 128x128 frame
(2 x 2 samples per pixel, shadow maps cached, compiled kernels) per light, hard and with
Blender's default sizes (radius 0.1 m, sun angle 0.526 deg), on the core Cornell box (1024^2
maps) and the outdoor scene.

    python -m tools.soft_bench [--repeat 7] [--before REV] [--json]

``--before REV`` times the code of that git revision too (git archive into a temporary
folder), the two trees interleaved run by run in one process each; medians are printed, of
the wall time and of the CPU time of all threads (" cpu": the work, less sensitive to a shared
machine's load).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CASES = ("spot", "point", "sun", "area", "outdoor")


def _setup(case: str, soft: bool):
    """(engine, scene, light, shadow map, [(pos, nrm)] of the frame's 4 samples)."""
    import numpy as np

    from lpv_core import engine
    from lpv_core.scene import GISettings
    from tools import core_scenes as demo

    res = (128, 128)
    scene = (demo.outdoor(res, GISettings()) if case == "outdoor"
             else demo.cornell_box(case.upper(), res, GISettings()))
    light = scene.lights[0]
    if soft:
        light.radius, light.angle = 0.1, np.radians(0.526)
    else:
        light.radius, light.angle = 0.0, 0.0
    eng = engine.Engine()
    bounds = eng.upload(scene, engine.Stats())
    shadow = eng.shadow_map(scene, light, bounds, 1024)
    cam = scene.camera
    samples = []
    for i in range(2):
        for j in range(2):
            w, h = cam.resolution
            proj = np.array(cam.projection, np.float64)
            proj[0] += ((i + 0.5) / 2 - 0.5) * 2.0 / w * proj[3]
            proj[1] += ((j + 0.5) / 2 - 0.5) * 2.0 / h * proj[3]
            _, pos, nrm, *_ = eng.raster.gbuffer(cam.view, proj, w, h, 0.5)
            samples.append((pos, nrm))
    return eng, light, shadow, samples


def child(repeat: int) -> dict:
    """{case/hard|soft: [ms per frame, ...]} timed in this process."""
    from lpv_core.render import direct

    out = {}
    for case in CASES:
        for soft in (False, True):
            if case == "area" and not soft:
                continue  # an area light is always soft
            _, light, shadow, samples = _setup(case, soft)
            for pos, nrm in samples:  # warm-up: compilation, the map's caches
                direct.irradiance(light, pos, nrm, shadow)
            wall, cpu = [], []
            for _ in range(repeat):
                t0, c0 = time.perf_counter(), time.process_time()
                for pos, nrm in samples:
                    direct.irradiance(light, pos, nrm, shadow)
                wall.append((time.perf_counter() - t0) * 1000.0)
                cpu.append((time.process_time() - c0) * 1000.0)
            name = f"{case}/{'soft' if soft else 'hard'}"
            out[name], out[name + " cpu"] = wall, cpu
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--repeat", type=int, default=7)
    p.add_argument("--before", default=None, help="git revision to compare with")
    p.add_argument("--json", action="store_true")
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.child:
        print(json.dumps(child(args.repeat)))
        return 0
    trees = {"now": ROOT}
    with tempfile.TemporaryDirectory(prefix="lpv_softbench_") as tmp:
        if args.before:
            code = Path(tmp) / "before"
            code.mkdir()
            arc = subprocess.run(["git", "archive", args.before], cwd=ROOT, check=True,
                                 capture_output=True).stdout
            subprocess.run(["tar", "-x", "-C", str(code)], input=arc, check=True)
            (code / "tools" / "soft_bench.py").write_text(Path(__file__).read_text())
            trees = {"before": code, "now": ROOT}
        runs: dict = {name: {} for name in trees}
        for _ in range(max(1, args.repeat // 3)):  # interleaved: the load hits both alike
            for name, code in trees.items():
                env = dict(os.environ, PYTHONPATH=str(code))
                proc = subprocess.run([sys.executable, "-m", "tools.soft_bench", "--child",
                                       "--repeat", "3"], cwd=code, env=env, check=True,
                                      capture_output=True, text=True)
                for k, v in json.loads(proc.stdout.splitlines()[-1]).items():
                    runs[name].setdefault(k, []).extend(v)
    med = {name: {k: round(statistics.median(v), 1) for k, v in r.items()}
           for name, r in runs.items()}
    if args.json:
        print(json.dumps(med, indent=1))
        return 0
    keys = list(next(iter(med.values())))
    print("case".ljust(18) + "".join(n.rjust(10) for n in med))
    for k in keys:
        print(k.ljust(18) + "".join(f"{med[n][k]:10.1f}" for n in med))
    return 0


if __name__ == "__main__":
    sys.exit(main())
