"""Compiled CPU kernels: the numpy backend's hot loops, compiled with numba when it is installed.

The numpy code of each stage stays the reference (and the fallback where numba is missing, as in
a Blender without it). A stage with a kernel calls it when ``enabled()``; tests run both paths on
the same input and compare. Kernels are compiled single-threaded with the GIL released
(``nogil``), so a stage splits its work over ordinates' thread pool where that pays and the
live viewport's worker thread never meets a numba threading layer. Compiled code is cached on
disk (numba's cache: NUMBA_CACHE_DIR, which the add-on's worker gets in the user's cache folder,
else ``__pycache__`` beside the module), so only the first run on a machine pays the compile,
and the worker serves that run with the numpy reference meanwhile (warmup.py). Numba checks
only the kernel's own file (its content hash) for changes: a
kernel calling one from another module (sweep's fused kernel calls ordinates' launch) keeps
its cached copy of the callee until its own file changes; an installed release replaces every
file, and during development ``find . -name '*.nbi' -delete`` clears the cache.

LPV_JIT=0 in the environment turns the kernels off (pure numpy).

``flush_subnormals()`` runs a block with the calling thread's x86 MXCSR set to flush
subnormal floats to zero (FTZ) and read them as zero (DAZ), restoring it after: light fading
through occluders in the transport sweep reaches values below float32's normal range
(1.2e-38), where every arithmetic instruction takes a microcode assist of ~100 cycles.
"""

from __future__ import annotations

import contextlib
import os
import platform
from collections.abc import Callable, Iterator

try:  # optional: the numpy code runs without it
    import numba
except Exception:  # noqa: BLE001 - any import failure (missing, or a broken llvmlite) = no JIT
    numba = None

_STATE = {"on": numba is not None and os.environ.get("LPV_JIT", "1") != "0", "warming": False}
KERNELS: list = []  # every compiled kernel (the warm-up counts those compiled)


def enabled() -> bool:
    """True when stages should call their compiled kernels."""
    return _STATE["on"]


def name() -> str:
    """What the CPU stages run on, for stats: "numba <version>" or "numpy"."""
    return f"numba {numba.__version__}" if enabled() else "numpy"


def warming() -> bool:
    """True while the kernels compile in another process and the numpy reference serves."""
    return _STATE["warming"]


def switch(on: bool, warming: bool = False) -> None:
    """Turn this process's kernels on or off (the worker's first run: warmup.py)."""
    _STATE["on"], _STATE["warming"] = on and numba is not None, warming


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
    KERNELS.append(numba.njit(cache=True, nogil=True, error_model="numpy")(fn))
    return KERNELS[-1]


X86 = platform.machine().lower() in {"x86_64", "amd64", "i386", "i686", "x86"}
FTZ_DAZ = 0x8040  # MXCSR bit 15 (flush to zero) and bit 6 (denormals are zero)


def _mxcsr_swap_codegen(typingctx, value, mask):
    """numba intrinsic (value, mask) -> old MXCSR: the bits under ``mask`` set to value's
    (llvm.x86.sse.stmxcsr / ldmxcsr on a stack slot)."""
    from llvmlite import ir
    from numba.core import cgutils, types

    def codegen(context, builder, sig, args):
        i32, i8p = ir.IntType(32), ir.IntType(8).as_pointer()
        slot = cgutils.alloca_once(builder, i32)
        ptr = builder.bitcast(slot, i8p)
        fty = ir.FunctionType(ir.VoidType(), [i8p])
        store = cgutils.get_or_insert_function(builder.module, fty, "llvm.x86.sse.stmxcsr")
        load = cgutils.get_or_insert_function(builder.module, fty, "llvm.x86.sse.ldmxcsr")
        builder.call(store, [ptr])
        old = builder.load(slot)
        value_, mask_ = (builder.trunc(a, i32) for a in args)
        new = builder.or_(builder.and_(old, builder.not_(mask_)), builder.and_(value_, mask_))
        builder.store(new, slot)
        builder.call(load, [ptr])
        return builder.zext(old, ir.IntType(64))

    return types.int64(types.int64, types.int64), codegen


if numba is not None and X86:  # compiled once per machine (cached on disk like the kernels)
    from numba.extending import intrinsic as _intrinsic

    _swap_intrinsic = _intrinsic(_mxcsr_swap_codegen)

    @numba.njit(cache=True, nogil=True)
    def _mxcsr_swap(value, mask):  # pragma: no cover - compiled
        """Set the MXCSR bits under ``mask`` to value's in the calling thread; the old
        MXCSR."""
        return _swap_intrinsic(value, mask)


@contextlib.contextmanager
def flush_subnormals() -> Iterator[None]:
    """Run the block in this thread with subnormal floats flushed to zero (module docstring);
    the thread's previous mode comes back after. Results change by less than float32's
    smallest normal number (1.2e-38) per operation. A no-op off x86 or without the kernels
    (the numpy reference keeps IEEE subnormals)."""
    if not (enabled() and X86):
        yield
        return
    old = int(_mxcsr_swap(FTZ_DAZ, FTZ_DAZ))
    try:
        yield
    finally:
        _mxcsr_swap(old, FTZ_DAZ)
