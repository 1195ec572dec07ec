"""First run without a silent minute: while numba compiles the CPU kernels, the worker serves
with the numpy reference (the same numbers: tests/test_jit_*.py hold every twin to it).

The worker's first scene goes to a child process (``python -m lpv_core.worker --warm-up
scene.npz``, niced) that runs the engine once with the kernels on, which compiles them into
numba's disk cache; then the worker turns its own kernels on and they load from that cache.
A marker beside the cache (READY, with a hash of the kernel sources and numba's version) lets
the next worker start with the kernels at once; without numba (or LPV_JIT=0) none of this runs.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

from . import jit

READY = "lpv_kernels_ready.json"
_CORE = Path(__file__).resolve().parents[1]


def fingerprint() -> str:
    """What the cached kernels depend on: the kernel sources and numba's version."""
    h = hashlib.sha256(str(getattr(jit.numba, "__version__", "-")).encode())
    for path in sorted([*(_CORE / "kernels").glob("*.py"), _CORE / "runtime" / "jit.py"]):
        h.update(path.read_bytes())
    return h.hexdigest()[:20]


def marker() -> Path:
    """The READY marker: in numba's cache folder (NUMBA_CACHE_DIR), else the kernels'
    __pycache__ (numba's default place)."""
    base = getattr(getattr(jit.numba, "config", None), "CACHE_DIR", "")
    return Path(base or _CORE / "kernels" / "__pycache__") / READY


def mark_ready(seconds: float) -> None:
    try:
        marker().parent.mkdir(parents=True, exist_ok=True)
        marker().write_text(json.dumps({"fingerprint": fingerprint(), "seconds": seconds}))
    except OSError:  # an unwritable cache: the next worker compiles again, in the background
        pass


def is_ready() -> bool:
    try:
        return json.loads(marker().read_text())["fingerprint"] == fingerprint()
    except (OSError, ValueError, KeyError, TypeError):
        return False


def compiled() -> int:
    """How many of the kernels this process has compiled (or loaded from the cache)."""
    return sum(1 for k in jit.KERNELS if k.signatures)


class Warmup:
    """The worker's side: kernels off until the child has filled the cache (``poll`` turns
    them on between requests); ``status`` goes into every reply."""

    def __init__(self):
        self.proc, self.compiled, self.error, self.t0 = None, 0, "", time.monotonic()
        self.state = "off" if not jit.enabled() else "ready" if is_ready() else "waiting"
        if self.state == "waiting":
            jit.switch(False, warming=True)

    def start(self, path: str, scene) -> None:
        """Compile with this scene (a copy of its file: the client removes the request)."""
        if self.state != "waiting" or not len(scene.positions):  # lamps, World or emitters
            return
        copy = path + ".warm-up.npz"
        shutil.copyfile(path, copy)
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "lpv_core.worker", "--warm-up", copy], text=True,
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=sys.stderr,
            creationflags=getattr(subprocess, "CREATE_NO_WINDOW", 0))  # no console on Windows
        self.state, self.t0 = "compiling", time.monotonic()
        threading.Thread(target=self._follow, name="lpv-warm-up", daemon=True).start()

    def _follow(self) -> None:
        for line in self.proc.stdout:
            try:
                msg = json.loads(line)
                self.compiled = msg.get("compiled", self.compiled)
                self.error = msg.get("error", self.error)
            except (ValueError, AttributeError):
                continue
        ok = self.proc.wait() == 0 and not self.error
        self.error = self.error or ("" if ok else f"exit status {self.proc.returncode}")
        self.state = "built" if ok else "failed"

    def poll(self) -> None:
        if self.state == "built":
            jit.switch(True)
            self.state = "ready"
        elif self.state == "failed":
            jit.switch(False)  # the numpy reference for good; "auto" may time GL now

    def status(self) -> dict:
        return {"state": self.state, "compiled": self.compiled, "of": len(jit.KERNELS),
                "seconds": round(time.monotonic() - self.t0, 1), "error": self.error}

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()
