"""Benchmark of the CPU and GL (moderngl compute shader) paths of the stages GL can run.

    python -m tools.bench_backends [--sizes 16,32,64] [--repeat 5] [--json]

Per grid size, median ms of: propagation as the engine runs it (VPLs of a 256^2 RSM injected on
the CPU, launched from their surfaces; the CPU's sweep to the infinite-step limit against GL's
steps to the early stop, 1e-3, including the upload of the first step and the readback of the
grid) and the lookup of its bands 0-2 grid (a 1280x720 G-buffer, including upload and
readback). ``auto`` shows what Engine.backend picks for "auto" on this machine and why (on a
software renderer such as llvmpipe: the CPU, without timing).
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import sys
import time

import numpy as np

from lpv_core import injection, lookup, propagation
from lpv_core.gl import backend as gl_backend
from lpv_core.grid import Grid


def _median_ms(fn, repeat: int, budget_s: float) -> float:
    fn()  # warm-up: shader compilation, scratch buffers, kernels, page faults
    times = []
    t_start = time.perf_counter()
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1000.0)
        if time.perf_counter() - t_start > budget_s:
            break
    return statistics.median(times)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def _stages(be, g: Grid, injected, values, rpos, rnrm, kw: dict) -> dict:
    """Callables per stage: GL's with ``be`` (a GLBackend), else the CPU's."""
    if be is None:
        return {"propagate": lambda: propagation.propagate(injected, **kw),
                "lookup": lambda: lookup.irradiance(g, values, rpos, rnrm)}
    cap = 3 * g.resolution  # the engine's cap on steps (engine.auto_iterations)
    return {"propagate": lambda: be.propagate(injected, cap, **kw),
            "lookup": lambda: be.irradiance(g, values, rpos, rnrm)}


def run(sizes=(16, 32, 64), repeat: int = 5, vpls: int = 256 * 256,
        receivers: int = 1280 * 720, backends=("numpy", "gl"), budget_s: float = 20.0) -> dict:
    rng = np.random.default_rng(0)
    gl = gl_backend.backend() if "gl" in backends else None
    kw = {"angular": "dom", "launch": True}
    rows = []
    for r in sizes:
        g = Grid((-1.0, -1.0, 0.0), 2.0 / r, r)
        lo = g.origin_array + g.cell_size
        span = (r - 2) * g.cell_size
        pos, rpos = (lo + rng.uniform(0.0, span, (n, 3)) for n in (vpls, receivers))
        nrm, rnrm = (_unit(rng.normal(size=(n, 3))) for n in (vpls, receivers))
        injected = injection.inject(g, pos, nrm, rng.uniform(0.0, 1e-3, (vpls, 3)))
        values = propagation.propagate(injected, **kw).values
        for name in backends:
            be = gl if name == "gl" else None
            stages = _stages(be, g, injected, values, rpos, rnrm, kw)
            ms = {k: _median_ms(fn, repeat, budget_s) for k, fn in stages.items()}
            row = {"backend": name, "resolution": r, "median_ms": ms}
            if be:
                row["steps"] = be.propagate(injected, 3 * r, **kw).iterations
            rows.append(row)
    out = {"vpls": vpls, "receivers": receivers, "repeat": repeat, "rows": rows,
           "machine": {"python": platform.python_version(), "processor": platform.machine()}}
    if gl is not None:
        out["gl_renderer"] = gl.renderer
        out["gl_version"] = gl.ctx.info.get("GL_VERSION")
        out["auto"] = gl_backend.auto_backend(gl, "dom")
    return out


def table(out: dict) -> str:
    title = (f"VPLs {out['vpls']}, receivers {out['receivers']}, median of {out['repeat']} "
             f"(ms); GL: {out.get('gl_renderer', '-')}")
    lines = [title, "", "| backend | grid | steps | propagate | lookup |", "|---|---|---|---|---|"]
    for row in out["rows"]:
        ms = row["median_ms"]
        lines.append(f"| {row['backend']} | {row['resolution']}^3 | {row.get('steps', 'sweep')} "
                     f"| {ms['propagate']:.1f} | {ms['lookup']:.1f} |")
    if "auto" in out:
        a = out["auto"]
        why = a.get("reason") or "ms " + json.dumps(a["ms"])
        lines += ["", f"auto: {a['backend']} {a['stages']}, {why}"]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m tools.bench_backends",
                                description=__doc__.split("\n")[0])
    p.add_argument("--sizes", default="16,32,64")
    p.add_argument("--repeat", type=int, default=5)
    p.add_argument("--vpls", type=int, default=256 * 256)
    p.add_argument("--receivers", type=int, default=1280 * 720)
    p.add_argument("--backends", default="numpy,gl")
    p.add_argument("--budget", type=float, default=20.0, help="seconds per stage at most")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    args = p.parse_args(argv)
    out = run(tuple(int(s) for s in args.sizes.split(",")), args.repeat, args.vpls,
              args.receivers, tuple(args.backends.split(",")), args.budget)
    print(json.dumps(out) if args.json else table(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
