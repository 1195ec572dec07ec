"""The LPV worker process: runs GL work (RSM) away from Blender's own GPU context.

moderngl inside Blender's process breaks Blender's drawing (design.md), so the add-on sends the
scene's arrays to ``python -m lpv_core.worker IN.npz OUT.npz`` and reads the VPLs back.
"""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from .scene import Light, Scene

PACKAGE_PARENT = str(Path(__file__).resolve().parents[1])


def _light_to_json(light: Light) -> dict:
    d = dataclasses.asdict(light)
    return {k: (np.asarray(v).tolist() if isinstance(v, (np.ndarray, tuple)) else v)
            for k, v in d.items()}


def _light_from_json(d: dict) -> Light:
    d = dict(d)
    d["matrix"] = np.asarray(d["matrix"], np.float64)
    d["color"] = np.asarray(d["color"], np.float32)
    d["size"] = tuple(d["size"])
    return Light(**d)


def save_request(path: str, scene: Scene, resolution: int) -> None:
    """Write what the worker needs for the RSMs of ``scene``'s lights."""
    lo, hi = scene.bounds()
    np.savez(
        path,
        positions=scene.positions, normals=scene.normals,
        albedo=scene.albedo_per_triangle(), reflectance=scene.reflectance_per_triangle(),
        bounds=np.stack([lo, hi]), resolution=np.int64(resolution),
        lights=np.array(json.dumps([_light_to_json(li) for li in scene.lights])),
    )


def serve(request: str, reply: str) -> None:
    """Compute the RSM of every light in ``request`` and write VPL arrays to ``reply``."""
    from .raster import Rasterizer
    from .rsm import render_rsm

    req = np.load(request)
    raster = Rasterizer()
    raster.upload(req["positions"], req["normals"], req["albedo"], req["reflectance"])
    lights = [_light_from_json(d) for d in json.loads(str(req["lights"]))]
    bounds = (req["bounds"][0], req["bounds"][1])
    out = {}
    for i, light in enumerate(lights):
        rsm = render_rsm(raster, light, bounds, int(req["resolution"]))
        out[f"position_{i}"], out[f"normal_{i}"] = rsm.position, rsm.normal
        out[f"flux_{i}"], out[f"area_{i}"] = rsm.flux, rsm.area
    tmp = reply + ".tmp.npz"
    np.savez(tmp, count=np.int64(len(lights)), **out)
    os.replace(tmp, reply)
    raster.release()


def rsm_in_subprocess(scene: Scene, resolution: int, python: str | None = None) -> list[dict]:
    """RSM VPLs per light computed in a child process (safe inside Blender's UI process)."""
    with tempfile.TemporaryDirectory(prefix="lpv_worker_") as tmp:
        request, reply = os.path.join(tmp, "in.npz"), os.path.join(tmp, "out.npz")
        save_request(request, scene, resolution)
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join([PACKAGE_PARENT] + sys.path)
        proc = subprocess.run(
            [python or sys.executable, "-m", "lpv_core.worker", request, reply],
            env=env, capture_output=True, text=True, check=False,
        )
        if proc.returncode != 0:
            tail = (proc.stderr or proc.stdout).strip().splitlines()[-1:]
            raise RuntimeError(f"LPV worker failed ({proc.returncode}): {' '.join(tail)}")
        data = np.load(reply)
        return [
            {k: data[f"{k}_{i}"] for k in ("position", "normal", "flux", "area")}
            for i in range(int(data["count"]))
        ]


if __name__ == "__main__":
    if len(sys.argv) != 3:
        print("usage: python -m lpv_core.worker REQUEST.npz REPLY.npz", file=sys.stderr)
        sys.exit(2)
    serve(sys.argv[1], sys.argv[2])
