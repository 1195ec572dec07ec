"""Pass requests to a worker: the batch's "render" command (the engine's update, then the
deferred passes of the scene's camera), answered with arrays instead of an EXR file."""

from __future__ import annotations

import os

import numpy as np

from ..worker_client import WorkerClient, WorkerError


def send(client: WorkerClient, scene, name: str) -> tuple:
    """Ask ``client`` for the passes of the core ``scene``'s camera (the batch's "render")."""
    out = client.path(f"{name}_passes.npz")
    rid, request = client.send_scene("render", scene, f"{name}.npz", passes=out)
    return rid, request, out


def receive(client: WorkerClient, handle: tuple, block: bool = False) -> tuple | None:
    """({pass name: (H, W, C) float32, rows top-first}, stats) once answered, else None."""
    rid, request, out = handle
    reply = client.wait(rid) if block else client.reply(rid)
    if reply is None:
        return None
    os.unlink(request)
    if not reply.get("ok"):
        raise WorkerError(reply.get("error", "unknown worker error"))
    with np.load(out) as data:
        passes = {k.replace("_", " "): data[k] for k in data.files}
    os.unlink(out)
    return passes, reply.get("stats", {})
