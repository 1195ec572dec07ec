"""How wrong is the preview: the LPV passes of the scene's camera (rendered in the worker) and
the red/green map of where they are brighter or darker than a Cycles reference
(``cycles.render_cycles_passes``), with the core's relative RMSE (lpv_core.render.error)."""

from __future__ import annotations

import importlib

import bpy
import numpy as np

from .._core import core
from ..scene_io.extract import extract_scene
from ..worker_client import WorkerClient, WorkerError

error = importlib.import_module(core.__name__ + ".render.error")


def render_passes(scene: bpy.types.Scene, resolution, worker: WorkerClient | None = None,
                  timeout: float = 600.0, overrides: dict | None = None) -> tuple[dict, dict]:
    """LPV passes ({Cycles pass name: (H, W, C)}) and stats of ``scene``'s camera view."""
    own = worker is None
    worker = worker or WorkerClient()
    try:
        core_scene = extract_scene(bpy.context.evaluated_depsgraph_get(), scene, resolution,
                                   overrides)
        out = worker.path("compare_passes.npz")
        rid, _ = worker.send_scene("render", core_scene, "compare.npz", passes=out)
        reply = worker.wait(rid, timeout)
        if not reply.get("ok"):
            raise WorkerError(reply.get("error", "unknown worker error"))
        data = np.load(out)
        passes = {k.replace("_", " "): data[k] for k in data.files}
        return passes, reply.get("stats", {})
    finally:
        if own:
            worker.close()


def error_heatmap(ours: np.ndarray, ref: np.ndarray) -> tuple[np.ndarray, dict]:
    """(H, W, 4) red/green heatmap and metrics of two (H, W, 3) pictures. Red: LPV brighter
    than Cycles, green: darker; full colour at an error of the reference's mean luminance."""
    lum_a = ours.mean(axis=-1)
    lum_b = ref.mean(axis=-1)
    mean_b = float(lum_b.mean())
    norm = mean_b if mean_b > 0 else 1.0
    err = (lum_a - lum_b) / norm
    heat = np.zeros(ours.shape[:2] + (4,), np.float32)
    heat[..., 0] = np.clip(err, 0.0, 1.0)
    heat[..., 1] = np.clip(-err, 0.0, 1.0)
    heat[..., 3] = 1.0
    return heat, {"relative_rmse": error.relative_rmse(ours, ref),
                  "mean_ratio": error.mean_ratio(ours, ref),
                  "too_bright": float((err > 0.1).mean()), "too_dark": float((err < -0.1).mean())}
