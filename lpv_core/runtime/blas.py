"""One BLAS thread in the engine's process: the engine splits its own work over two threads
(ordinates' pool), and numpy's OpenBLAS must not add threads of its own that spin between calls.

After each multi-threaded call (the fold to SH is one matrix product per cascade) OpenBLAS
keeps its worker threads spinning on sched_yield for a while, and an update calls it again
before they sleep, so they compete with the compiled kernels for the cores (the figures are in
docs/decisions.md). The fold itself runs well on one core.

The engine runs in its own process (the batch CLI, the live worker), so Blender's own numpy
is untouched. Only OpenBLAS is handled (numpy's wheels on Linux, Windows and macOS bundle it,
as ``libopenblas`` or, from numpy 2, ``libscipy_openblas``); elsewhere nothing changes.
"""

from __future__ import annotations

import ctypes
import sys
from pathlib import Path

_SETTERS = ("openblas_set_num_threads64_", "scipy_openblas_set_num_threads64_",
            "openblas_set_num_threads", "scipy_openblas_set_num_threads")
_DONE: list = []


def single_threaded() -> list[str]:
    """Set every loaded OpenBLAS to one thread, once per process; returns the libraries set
    (empty where none was found: the BLAS is left as it is)."""
    if _DONE:
        return _DONE[0]
    done = []
    for path in _openblas_paths():
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for name in _SETTERS:
            setter = getattr(lib, name, None)
            if setter is not None:
                setter.argtypes = [ctypes.c_int]
                setter.restype = None
                setter(1)
                done.append(path)
                break
    _DONE.append(done)
    return done


def _openblas_paths() -> list[str]:
    """Paths of the OpenBLAS libraries this process has loaded (Linux: its memory map), or
    bundled with numpy (elsewhere: numpy's wheel directories)."""
    import numpy  # loaded first: its BLAS is what is looked for

    found: list[str] = []
    maps = Path("/proc/self/maps")
    if sys.platform.startswith("linux") and maps.exists():
        for line in maps.read_text().splitlines():
            path = line.split(maxsplit=5)[-1] if line.count(" ") >= 5 else ""
            if "openblas" in Path(path).name.lower() and path not in found:
                found.append(path)
        return found
    base = Path(numpy.__file__).resolve().parent
    for folder in (base / ".dylibs", base.parent / "numpy.libs", base.parent / "scipy_openblas64",
                   base.parent / "scipy_openblas32"):
        if folder.is_dir():
            for lib in sorted(folder.rglob("*openblas*")):
                if lib.suffix in (".so", ".dylib", ".dll") and str(lib) not in found:
                    found.append(str(lib))
    return found
