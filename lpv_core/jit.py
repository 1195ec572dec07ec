"""Compiled CPU kernels: the numpy backend's hot loops, compiled with numba when it is installed.

The numpy code of each stage stays the reference (and the fallback where numba is missing, as in
a Blender without it). A stage with a kernel calls it when ``enabled()``; tests run both paths on
the same input and compare. Kernels are compiled single-threaded with the GIL released
(``nogil``), so a stage splits its work over ordinates' thread pool where that pays and the
live viewport's worker thread never meets a numba threading layer. Compiled code is cached on
disk (numba's cache: ``__pycache__`` beside the module, or NUMBA_CACHE_DIR), so only the first
run on a machine pays the compile. Numba checks only the kernel's own file for changes: a
kernel calling one from another module (sweep's fused kernel calls ordinates' launch) keeps
its cached copy of the callee until its own file changes; an installed release replaces every
file, and during development ``find . -name '*.nbi' -delete`` clears the cache.

LPV_JIT=0 in the environment turns the kernels off (pure numpy).
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Callable, Iterator

try:  # optional: the numpy code runs without it
    import numba
except Exception:  # noqa: BLE001 - any import failure (missing, or a broken llvmlite) = no JIT
    numba = None

_STATE = {"on": numba is not None and os.environ.get("LPV_JIT", "1") != "0"}


def enabled() -> bool:
    """True when stages should call their compiled kernels."""
    return _STATE["on"]


def name() -> str:
    """What the CPU stages run on, for stats: "numba <version>" or "numpy"."""
    return f"numba {numba.__version__}" if enabled() else "numpy"


@contextlib.contextmanager
def disabled() -> Iterator[None]:
    """Run the pure numpy code inside the block (tests compare it with the kernels)."""
    before = _STATE["on"]
    _STATE["on"] = False
    try:
        yield
    finally:
        _STATE["on"] = before


def kernel(fn: Callable) -> Callable:
    """Compile ``fn`` with numba (lazily, at its first call; cached on disk, GIL released);
    without numba ``fn`` is returned as it is and never called (``enabled()`` is False)."""
    if numba is None:
        return fn
    return numba.njit(cache=True, nogil=True, error_model="numpy")(fn)
