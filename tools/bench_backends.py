"""Benchmark of the numpy and moderngl (compute shader) backends, stage by stage.

    python -m tools.bench_backends [--sizes 16,32,64] [--repeat 5] [--json]

Per grid size: median ms of injection (VPLs from a 256^2 RSM by default), propagation
(resolution / 4 steps, no early stop, for each angular model, including the readback of the accumulated grid that the
engine caches per light) and lookup (a 1280x720 G-buffer, including upload and readback), on
random data of the same shape as the engine's. The GL figures include every transfer the engine
makes; ``auto`` shows what Engine.backend picks for "auto" on this machine.
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
    fn()  # warm-up: shader compilation, scratch buffers, page faults
    times = []
    t_start = time.perf_counter()
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1000.0)
        if time.perf_counter() - t_start > budget_s and len(times) >= 1:
            break
    return statistics.median(times)


def _stages(name: str, gl, g: Grid, data: dict, angular: str) -> dict:
    """Callables per stage for one backend (inputs bound now, not at call time)."""
    pos, nrm, flux = data["pos"], data["nrm"], data["flux"]
    injected, values, iterations = data["injected"], data["values"], data["iterations"]
    rpos, rnrm = data["rpos"], data["rnrm"]
    kw = {"min_fraction": 0.0, "angular": angular}
    if name == "numpy":
        return {
            "inject": lambda: injection.inject(g, pos, nrm, flux),
            "propagate": lambda: propagation.propagate(injected, iterations, **kw),
            "lookup": lambda: lookup.irradiance(g, values, rpos, rnrm, angular=angular),
        }
    on_gpu = data["on_gpu"]
    return {
        "inject": lambda: gl.inject(g, pos, nrm, flux).release(),
        "propagate": lambda: gl.propagate(on_gpu, iterations, **kw),
        "propagate_gpu": lambda: gl.propagate(on_gpu, iterations, readback=False, **kw),
        "lookup": lambda: gl.irradiance(g, values, rpos, rnrm, angular=angular),
        "readback": lambda: on_gpu.read(),
    }


def run(sizes=(16, 32, 64), repeat: int = 5, vpls: int = 256 * 256,
        receivers: int = 1280 * 720, backends=("numpy", "gl"), budget_s: float = 20.0,
        angulars=("sh", "m1")) -> dict:
    rng = np.random.default_rng(0)
    gl = gl_backend.backend() if "gl" in backends else None
    rows = []
    for r in sizes:
        g = Grid((-1.0, -1.0, 0.0), 2.0 / r, r)
        lo = g.origin_array + g.cell_size
        span = (r - 2) * g.cell_size
        data = {"pos": lo + rng.uniform(0.0, span, (vpls, 3)),
                "nrm": _unit(rng.normal(size=(vpls, 3))),
                "flux": rng.uniform(0.0, 1e-3, (vpls, 3)),
                "rpos": lo + rng.uniform(0.0, span, (receivers, 3)),
                "rnrm": _unit(rng.normal(size=(receivers, 3))),
                "iterations": max(1, round(r / 4))}
        data["injected"] = injection.inject(g, data["pos"], data["nrm"], data["flux"])
        for angular in angulars:
            data["values"] = propagation.propagate(data["injected"], data["iterations"],
                                                   min_fraction=0.0, angular=angular).values
            for name in backends:
                if name == "gl":
                    data["on_gpu"] = gl.upload(data["injected"])
                stages = _stages(name, gl, g, data, angular)
                ms = {k: _median_ms(fn, repeat, budget_s) for k, fn in stages.items()}
                ms["step"] = ms["propagate"] / data["iterations"]
                ms["total"] = ms["inject"] + ms["propagate"] + ms["lookup"]
                rows.append({"backend": name, "angular": angular, "resolution": r,
                             "iterations": data["iterations"], "median_ms": ms})
                if name == "gl":
                    data.pop("on_gpu").release()
    out = {"vpls": vpls, "receivers": receivers, "repeat": repeat, "rows": rows,
           "machine": {"python": platform.python_version(), "processor": platform.machine()}}
    if gl is not None:
        out["gl_renderer"] = gl.ctx.info.get("GL_RENDERER")
        out["gl_version"] = gl.ctx.info.get("GL_VERSION")
        out["auto"] = {a: gl_backend.auto_backend(gl, a) for a in ("sh", "m1")}
    return out


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def table(out: dict) -> str:
    title = (f"VPLs {out['vpls']}, receivers {out['receivers']}, median of {out['repeat']} "
             f"(ms); GL: {out.get('gl_renderer', '-')}")
    head = ("| backend | model | grid | steps | inject | propagate | per step "
            "| propagate, no readback | lookup | readback | total |")
    lines = [title, "", head, "|---|---|---|---|---|---|---|---|---|---|---|"]
    for row in out["rows"]:
        ms = row["median_ms"]
        rb = f"{ms['readback']:.2f}" if "readback" in ms else "-"
        pg = f"{ms['propagate_gpu']:.2f}" if "propagate_gpu" in ms else "-"
        lines.append(f"| {row['backend']} | {row['angular']} | {row['resolution']}^3 | "
                     f"{row['iterations']} | "
                     f"{ms['inject']:.2f} | {ms['propagate']:.2f} | {ms['step']:.2f} | {pg} | "
                     f"{ms['lookup']:.1f} | {rb} | {ms['total']:.1f} |")
    for angular, choice in out.get("auto", {}).items():
        note = f"auto ({angular}): {choice['backend']} {choice['stages']}, ms {choice['ms']}"
        lines += ["", note]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m tools.bench_backends",
                                description=__doc__.split("\n")[0])
    p.add_argument("--sizes", default="16,32,64")
    p.add_argument("--repeat", type=int, default=5)
    p.add_argument("--vpls", type=int, default=256 * 256)
    p.add_argument("--receivers", type=int, default=1280 * 720)
    p.add_argument("--backends", default="numpy,gl")
    p.add_argument("--angular", default="sh,m1", help="angular models: sh, m1")
    p.add_argument("--budget", type=float, default=20.0, help="seconds per stage at most")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    args = p.parse_args(argv)
    out = run(tuple(int(s) for s in args.sizes.split(",")), args.repeat, args.vpls,
              args.receivers, tuple(args.backends.split(",")), args.budget,
              tuple(args.angular.split(",")))
    print(json.dumps(out) if args.json else table(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
