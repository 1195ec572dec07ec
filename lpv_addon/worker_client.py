"""The ``lpv_core.worker`` child process and its line-based JSON protocol, client side.

Blender's process never runs moderngl (it breaks Blender's drawing): the live
viewport, the Render Batch operator and the Cycles comparison send scenes as .npz files to one
child process (``python -m lpv_core.worker``, see that module for the protocol) and read the
results back as arrays.

Compiled CPU kernels are cached in the extension's user folder (``kernel_cache``), which
Blender keeps across extension updates and reinstalls; the worker serves with the numpy
reference while a cold cache fills (lpv_core/runtime/warmup.py).
"""

from __future__ import annotations

import importlib
import json
import os
import platform
import queue
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from ._core import core

protocol = importlib.import_module(core.__name__ + ".worker")  # scene <-> npz
PACKAGE_PARENT = str(Path(core.__file__).resolve().parents[1])
WORKER_MODULE = "lpv_core.worker"


def kernel_cache() -> str | None:
    """Where the worker's numba keeps compiled kernels: ``$LPV_GI_CACHE_DIR`` or the extension's
    user folder (bpy.utils.extension_path_user), in a folder per extension, numba and Python
    version and CPU; None when the add-on runs from a source tree (numba's default place)."""
    ext = (__package__ or "").rpartition(".lpv_addon")[0]  # "bl_ext.<repo>.<id>" when installed
    if not ext.startswith("bl_ext."):
        return None
    import importlib.metadata
    import tomllib

    import bpy

    try:
        root = os.environ.get("LPV_GI_CACHE_DIR") or bpy.utils.extension_path_user(
            ext, path="cache", create=True)
        version = tomllib.loads(Path(PACKAGE_PARENT, "blender_manifest.toml").read_text())
        numba = importlib.metadata.version("numba")
    except (OSError, ValueError, KeyError, importlib.metadata.PackageNotFoundError):
        return None
    key = f"{version.get('version')}-numba{numba}-py{sys.version_info[0]}{sys.version_info[1]}"
    return os.path.join(root, "kernels", f"{key}-{platform.machine()}")


class WorkerError(RuntimeError):
    """The worker process failed, died or did not answer in time."""


class WorkerClient:
    """A ``lpv_core.worker`` child process with a line-based JSON protocol."""

    def __init__(self, python: str | None = None):
        self.dir = tempfile.mkdtemp(prefix="lpv_live_")
        self.log_path = os.path.join(self.dir, "worker.log")
        self._log = open(self.log_path, "wb")  # noqa: SIM115 - lives as long as the process
        env = dict(os.environ)
        paths = [PACKAGE_PARENT] + [p for p in sys.path if p and os.path.isdir(p)]
        env["PYTHONPATH"] = os.pathsep.join(dict.fromkeys(paths))
        env.setdefault("PYTHONNOUSERSITE", "1")
        cache = env.get("NUMBA_CACHE_DIR") or kernel_cache()
        if cache:  # set before the worker imports numba
            env["NUMBA_CACHE_DIR"] = cache
            env.setdefault("LPV_GI_CACHE_DIR", str(Path(cache).parents[1]))  # auto's choice
        flags = getattr(subprocess, "CREATE_NO_WINDOW", 0) if os.name == "nt" else 0
        self.proc = subprocess.Popen(
            [python or sys.executable, "-m", WORKER_MODULE],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=self._log, env=env,
            cwd=self.dir, text=True, encoding="utf-8", bufsize=1, creationflags=flags,
        )
        self._next = 0
        self._replies: dict = {}
        self._lock = threading.Lock()
        self._arrived = queue.Queue()
        self._reader = threading.Thread(target=self._read, name="lpv-worker-reader", daemon=True)
        self._reader.start()

    def _read(self) -> None:
        for line in self.proc.stdout:
            try:
                reply = json.loads(line)
                hash(reply.get("id"))
            except (ValueError, AttributeError, TypeError):  # not a reply of ours
                continue
            with self._lock:
                self._replies[reply.get("id")] = reply
            self._arrived.put(reply.get("id"))

    @property
    def alive(self) -> bool:
        return self.proc.poll() is None

    def path(self, name: str) -> str:
        return os.path.join(self.dir, name)

    def send(self, cmd: str, **kw) -> int:
        if not self.alive:
            raise WorkerError(f"LPV worker exited ({self.proc.returncode}): {self.log_tail()}")
        self._next += 1
        try:
            self.proc.stdin.write(json.dumps({"id": self._next, "cmd": cmd, **kw}) + "\n")
            self.proc.stdin.flush()
        except OSError as exc:
            raise WorkerError(f"LPV worker is gone ({exc}): {self.log_tail()}") from None
        return self._next

    def send_scene(self, cmd: str, scene, name: str, **kw) -> tuple[int, str]:
        """Write the core ``scene`` as ``name`` in the worker's folder and send ``cmd`` for it:
        (request id, the request file, which the caller removes once answered)."""
        request = self.path(name)
        protocol.save_scene(request, scene)
        return self.send(cmd, scene=request, **kw), request

    def reply(self, rid: int) -> dict | None:
        """The reply to request ``rid`` if it arrived (non-blocking), else None."""
        with self._lock:
            reply = self._replies.pop(rid, None)
        if reply is None and not self.alive and not self._reader.is_alive():
            with self._lock:
                reply = self._replies.pop(rid, None)
            if reply is None:
                raise WorkerError(f"LPV worker exited ({self.proc.returncode}): "
                                  f"{self.log_tail()}")
        return reply

    def wait(self, rid: int, timeout: float = 300.0) -> dict:
        deadline = time.monotonic() + timeout
        while True:
            reply = self.reply(rid)
            if reply is not None:
                return reply
            left = deadline - time.monotonic()
            if left <= 0:
                raise WorkerError(f"LPV worker did not answer within {timeout:.0f} s")
            try:
                self._arrived.get(timeout=min(left, 0.2))
            except queue.Empty:
                pass

    def log_tail(self, lines: int = 3) -> str:
        try:
            self._log.flush()
            text = Path(self.log_path).read_text(errors="replace").strip().splitlines()
        except OSError:
            return ""
        return " | ".join(text[-lines:])

    def close(self, timeout: float = 3.0) -> None:
        """Ask the worker to quit, kill it if it does not, and remove its folder."""
        if self.alive:
            try:
                self.proc.stdin.write(json.dumps({"id": 0, "cmd": "quit"}) + "\n")
                self.proc.stdin.flush()
            except OSError:
                pass
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()  # SIGKILL cannot be ignored: this returns
        for stream in (self.proc.stdin, self.proc.stdout):
            try:
                stream.close()
            except OSError:
                pass
        self._reader.join(timeout)
        self._log.close()
        shutil.rmtree(self.dir, ignore_errors=True)

    def kill(self) -> None:
        if self.alive:
            self.proc.kill()
        self.close(timeout=3.0)
