"""Benchmark: per-stage medians of the LPV update and render on the built-in Cornell box.

    python -m tools.bench [--quick] [--json] [--repeat N] [--resolution WxH]
                             [--sweep | --sweep-quick] [--sweep-only] [--lights N] [--world]

Prints one JSON object (--json) or a table. Times are medians over the repeats, measured in one
run on this machine; compare ratios, not absolute numbers, across machines.

The Cornell box runs the default settings (GISettings(): the "dom" transport, propagated to
convergence, 16^3 cascades picked per view); ``angular`` in the output names the model.
``stated`` / ``full_update_stated_ms`` time the full update at issue 6's stated quality
(STATED: 3 x 32^3, occlusion, RSM 256^2).

``--sweep`` adds the scaling sweep of bench_sweep.py (grids 16^3-64^3, 1-4 cascades, RSM
64^2-512^2, 1k-1M triangles, 1-16 lights, numpy and gl backends, cost-growth exponents, a
roofline of the dense propagation step of each transport model (dom, sh) and the 1280x720
lookup) under the key "sweep";
``--sweep-quick`` a tiny version of it (for tests); ``--sweep-only`` skips the Cornell box
figures. ``--lights N`` times only one frame of the box lit by N point lights, per light,
with its peak memory (the shadow and RSM budgets, render/shadows.py). ``--world`` times only the
update with and without a uniform World. See docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import sys
import time

import numpy as np

from lpv_core import engine
from lpv_core.render import deferred
from lpv_core.runtime import jit
from lpv_core.scene import GISettings
from tools import core_scenes as demo


def run(repeat: int, resolution: tuple[int, int], settings: GISettings) -> dict:
    """Median milliseconds per stage over ``repeat`` full updates + renders."""
    scene = demo.cornell_box("SPOT", resolution, settings)
    eng = engine.Engine()
    samples: dict[str, list[float]] = {}
    result = None
    for _ in range(repeat + 1):  # the first run warms up shaders and caches
        eng.clear_cache()  # time full updates, not reuse
        stats = engine.Stats()
        t0 = time.perf_counter()
        result = eng.update(scene, stats)
        deferred.render(eng, scene, result, stats)
        stats.ms["total"] = (time.perf_counter() - t0) * 1000.0
        if result is not None and samples.get("_warm") is None:
            samples["_warm"] = []
            continue
        for k, v in stats.ms.items():
            samples.setdefault(k, []).append(v)
    samples.pop("_warm", None)
    medians = {k: statistics.median(v) for k, v in samples.items()}
    return {
        "scene": "cornell_box_spot",
        "resolution": list(resolution),
        "repeat": repeat,
        "settings": settings.as_dict(),
        "backend": settings.backend,
        "angular": settings.angular,
        # what "auto" chose per stage on this run (measured once per process)
        "backend_used": result.stats.info.get("backend") if result else None,
        "cpu_kernels": jit.name(),  # numba-compiled CPU stages, or "numpy" (jit.py)
        "median_ms": medians,
        "full_update_ms": medians.get("lpv_update", 0.0),
        "iterations": result.stats.info.get("iterations") if result else None,
        "machine": {"python": platform.python_version(), "processor": platform.machine()},
    }


# Issue 6's stated quality for its 25 ms limit: three 32^3 cascades, occlusion on, one light,
# RSM 256^2 (the KD10 / CryENGINE 3 configuration). The engine's own defaults are smaller
# (GISettings: 16^3, cascades picked per view); the benchmark reports both.
STATED = {"grid_resolution": 32, "cascades": 3, "cascades_auto": False, "occlusion": True,
          "rsm_resolution": 256}


STATED_REPEAT = 11  # fewest updates behind the stated figure's median


def stated(repeat: int) -> dict:
    """Median full update of the Cornell box (one spot light) at STATED: the figure the 25 ms
    limit names, with its stages and the cascades the planner ran and skipped."""
    settings = GISettings().updated(**STATED)
    scene = demo.cornell_box("SPOT", (64, 64), settings)
    eng = engine.Engine()
    eng.update(scene)  # warm-up
    times, stages, stats = [], {}, None
    for _ in range(repeat):
        eng.clear_cache()
        stats = engine.Stats()
        t0 = time.perf_counter()
        eng.update(scene, stats)
        times.append((time.perf_counter() - t0) * 1000.0)
        for k, v in stats.ms.items():
            stages.setdefault(k, []).append(v)
    return {
        "settings": dict(STATED),
        "repeat": repeat,
        "full_update_ms": statistics.median(times),
        "median_ms": {k: statistics.median(v) for k, v in stages.items()},
        "cascades_run": len(stats.info.get("cascades", [])),
        "skipped": [s for s in stats.skipped if s["stage"] == "cascades"],
    }


def _median_update_ms(eng, scene, mutate, repeat: int) -> float:
    """Median ms of eng.update after ``mutate(scene, i)`` (the change being timed)."""
    times = []
    for i in range(repeat):
        mutate(scene, i)
        t0 = time.perf_counter()
        eng.update(scene)
        times.append((time.perf_counter() - t0) * 1000.0)
    return statistics.median(times)


def incremental(repeat: int, settings: GISettings) -> dict:
    """Issue-6 figures on the Cornell box: full update (1 light), then with 8 lights a GI
    intensity tweak, one light moved, and a camera move within a cell."""
    one = demo.cornell_box("SPOT", (64, 64), settings)
    eng = engine.Engine()
    eng.update(one)  # warm-up: shaders, tables

    full = _median_update_ms(eng, one, lambda scene, i: eng.clear_cache(), repeat)
    eight = demo.cornell_box("SPOT", (64, 64), settings)
    base = eight.lights[0]
    eight.lights = []
    for k in range(8):
        m = base.matrix.copy()
        m[:3, 3] += [0.5 * np.cos(k), 0.5 * np.sin(k), -0.05 * k]
        eight.lights.append(type(base)(f"Spot{k}", "SPOT", m, power=base.power / 8,
                                       spot_size=base.spot_size, spot_blend=base.spot_blend))
    eng8 = engine.Engine()
    eng8.update(eight)

    def tweak(scene, i):
        scene.lights[0].gi_intensity = 1.0 + 0.1 * (i + 1)

    def move(scene, i):
        scene.lights[0].matrix = scene.lights[0].matrix.copy()
        scene.lights[0].matrix[0, 3] += 0.01

    def camera(scene, i):
        scene.camera.view = scene.camera.view.copy()
        scene.camera.view[0, 3] += 1e-3

    # One run per 3 repeats: an 8-light full update is long (keeps --quick under a minute).
    full8 = _median_update_ms(eng8, eight, lambda scene, i: eng8.clear_cache(),
                              max(1, repeat // 3))
    eng8.update(eight)  # cache filled again for the incremental cases
    moved = _median_update_ms(eng8, eight, move, repeat)
    return {
        "full_update_ms": full,
        "full_update_8_lights_ms": full8,
        "light_intensity_tweak_ms": _median_update_ms(eng8, eight, tweak, repeat),
        "one_light_moved_ms": moved,
        # Issue 6 asks for <= 1/4: one light's work out of the 8-light scene's full update.
        "one_light_moved_over_full_8": moved / full8 if full8 > 0 else None,
        "camera_in_cell_ms": _median_update_ms(eng8, eight, camera, repeat),
    }


def world(repeat: int) -> dict:
    """The Cornell box (one spot) at STATED with and without a uniform World (Blender's default
    grey 0.05): median full update (caches cleared), the ratio the issue bounds, and the update
    after the lamp moved (the World's grids and maps reused). The two scenes' updates take
    turns, so that a change in the machine's load weighs on both alike."""
    from lpv_core.scene import World

    settings = GISettings().updated(**STATED)
    names = ("without", "with")
    engines, scenes = {}, {}
    for name, w in zip(names, (None, World("World", np.full((1, 1, 3), 0.05, np.float32)))):
        scenes[name] = demo.cornell_box("SPOT", (64, 64), settings)
        scenes[name].world = w
        engines[name] = engine.Engine()
        engines[name].update(scenes[name])  # warm-up
    times = {n: [] for n in names}
    cpu = {n: [] for n in names}  # all the process's threads (the kernels', the GL driver's)
    stages = {n: {} for n in names}
    for _ in range(repeat):
        for name in names:
            engines[name].clear_cache()
            stats = engine.Stats()
            t0, c0 = time.perf_counter(), time.process_time()
            engines[name].update(scenes[name], stats)
            times[name].append((time.perf_counter() - t0) * 1000.0)
            cpu[name].append((time.process_time() - c0) * 1000.0)
            for k, v in stats.ms.items():
                stages[name].setdefault(k, []).append(v)
    moved = {n: [] for n in names}
    for name in names:
        engines[name].update(scenes[name])
    for _ in range(repeat):
        for name in names:
            light = scenes[name].lights[0]
            light.matrix = light.matrix.copy()
            light.matrix[0, 3] += 0.01
            t0 = time.perf_counter()
            engines[name].update(scenes[name])
            moved[name].append((time.perf_counter() - t0) * 1000.0)
    out = {n: {"full_update_ms": statistics.median(times[n]),
               "full_update_cpu_ms": statistics.median(cpu[n]),
               "median_ms": {k: statistics.median(v) for k, v in stages[n].items()},
               "light_moved_ms": statistics.median(moved[n])} for n in names}
    out["full_ratio"] = out["with"]["full_update_ms"] / out["without"]["full_update_ms"]
    out["full_cpu_ratio"] = (out["with"]["full_update_cpu_ms"]
                             / out["without"]["full_update_cpu_ms"])
    out["light_moved_ratio"] = (out["with"]["light_moved_ms"]
                                / out["without"]["light_moved_ms"])
    return out


def many_lights_scene(n: int, resolution: tuple[int, int], settings: GISettings | None = None):
    """The Cornell box lit by ``n`` point lights (300 W in all) at fixed pseudo-random places
    in the layer above the tall block (z 1.3-1.9 m)."""
    from lpv_core.scene.model import Light

    scene = demo.cornell_box("NONE", resolution, settings or GISettings())
    rng = np.random.default_rng(19)
    for k, p in enumerate(rng.uniform([-0.9, -0.9, 1.3], [0.9, 0.9, 1.9], (n, 3))):
        scene.lights.append(Light(f"Point{k}", "POINT", demo.light_matrix(p, (0, 0, -1)),
                                  power=300.0 / n))
    return scene


def peak_rss_mib() -> float:
    """This process's peak resident memory: VmHWM, whose high-water mark starts at exec
    (ru_maxrss keeps the parent's peak at the fork/vfork that started this process)."""
    import resource

    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def many_lights(n: int, resolution: tuple[int, int]) -> dict:
    """One frame (update + render, default settings) of many_lights_scene: its stages, their
    time per light, the shadow and RSM budgets' resolutions, and this process's peak memory
    (VmHWM: run it alone, ``--lights N``)."""
    scene = many_lights_scene(n, resolution)
    eng = engine.Engine()
    stats = engine.Stats()
    t0 = time.perf_counter()
    result = eng.update(scene, stats)
    t1 = time.perf_counter()
    deferred.render(eng, scene, result, stats)
    t2 = time.perf_counter()
    shadow = stats.info.get("shadow_maps", {})
    reduced = shadow.get("reduced", {})
    rsm = stats.info.get("rsm_reduced", {})
    s = GISettings()
    return {
        "lights": n, "resolution": list(resolution),
        "frame_s": t2 - t0, "update_s": t1 - t0, "render_s": t2 - t1,
        "frame_per_light_ms": (t2 - t0) * 1000.0 / n,
        "per_light_ms": {k: v / n for k, v in stats.ms.items()},
        "peak_rss_mib": peak_rss_mib(),
        "shadow_cached_mib": shadow.get("cached_mib"), "shadow_budget_mib": shadow.get(
            "budget_mib"), "shadow_evicted": shadow.get("evicted"),
        "shadow_resolutions": sorted(set(reduced.values())) or [s.shadow_resolution],
        "rsm_resolutions": sorted(set(rsm.values())) or [s.rsm_resolution],
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m tools.bench", description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true", help="3 repeats at 128x128")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--repeat", type=int, default=None)
    p.add_argument("--resolution", default=None, help="WxH of the rendered image")
    sweep = p.add_mutually_exclusive_group()
    sweep.add_argument("--sweep", action="store_true",
                       help="add the full scaling sweep (bench_sweep.py, several minutes)")
    sweep.add_argument("--sweep-quick", action="store_true",
                       help="add a tiny scaling sweep (seconds; for tests)")
    p.add_argument("--sweep-only", action="store_true",
                   help="with --sweep/--sweep-quick: only the sweep, no Cornell box figures")
    p.add_argument("--lights", type=int, default=None, metavar="N",
                   help="only one frame of the Cornell box lit by N point lights (default "
                        "256x256): time per light and peak memory")
    p.add_argument("--world", action="store_true",
                   help="only the update with and without a uniform World (STATED settings)")
    args = p.parse_args(argv)
    if args.sweep_only and not (args.sweep or args.sweep_quick):
        p.error("--sweep-only needs --sweep or --sweep-quick")
    repeat = args.repeat or (3 if args.quick else 7)
    res = (128, 128) if args.quick else (256, 256)
    if args.resolution:
        w, h = args.resolution.lower().split("x")
        res = (int(w), int(h))
    if args.world:
        out = world(max(repeat, 5))
        if args.json:
            print(json.dumps(out))
            return 0
        for name in ("without", "with"):
            o = out[name]
            print(f"Cornell box at 3 x 32^3 {name} a World: full update "
                  f"{o['full_update_ms']:.1f} ms ({o['full_update_cpu_ms']:.1f} ms CPU), after "
                  f"the lamp moved {o['light_moved_ms']:.1f} ms")
            for k, v in sorted(o["median_ms"].items(), key=lambda kv: -kv[1])[:8]:
                print(f"    {k:<16} {v:9.1f} ms")
        print(f"  with / without: full {out['full_ratio']:.2f} (CPU {out['full_cpu_ratio']:.2f}), "
              f"lamp moved {out['light_moved_ratio']:.2f}")
        return 0
    if args.lights is not None:
        if args.lights < 1:
            p.error(f"--lights must be at least 1, not {args.lights}")
        out = many_lights(args.lights, res)
        if args.json:
            print(json.dumps(out))
            return 0
        print(f"{out['lights']} point lights, {res[0]}x{res[1]}, one frame: "
              f"{out['frame_s']:.1f} s ({out['frame_per_light_ms']:.0f} ms per light), peak "
              f"memory {out['peak_rss_mib']:.0f} MiB, shadow maps {out['shadow_cached_mib']} "
              f"MiB cached at {out['shadow_resolutions']}^2, RSMs at {out['rsm_resolutions']}^2")
        for k, v in sorted(out["per_light_ms"].items(), key=lambda kv: -kv[1]):
            print(f"  {k:<16} {v:9.2f} ms per light")
        return 0
    out: dict = {}
    if not args.sweep_only:
        out = run(repeat, res, GISettings())
        out.update(incremental(repeat, GISettings()))
        # at least 11 updates (~0.3 s): a median of 3 moved by 1.4x with the machine's noise
        out["stated"] = stated(max(repeat, STATED_REPEAT))
        out["full_update_stated_ms"] = out["stated"]["full_update_ms"]
    if args.sweep or args.sweep_quick:
        from tools import bench_sweep

        out["sweep"] = bench_sweep.run_sweep(quick=args.sweep_quick)
    if args.json:
        print(json.dumps(out))
        return 0
    if not args.sweep_only:
        print(f"Cornell box, {res[0]}x{res[1]}, median of {repeat}:")
        for k, v in sorted(out["median_ms"].items(), key=lambda kv: -kv[1]):
            print(f"  {k:<14} {v:9.1f} ms")
        for k in ("full_update_ms", "full_update_8_lights_ms", "light_intensity_tweak_ms",
                  "one_light_moved_ms", "camera_in_cell_ms"):
            print(f"  {k:<26} {out[k]:9.1f} ms")
        st = out["stated"]
        print(f"  full update at 3 x 32^3 (issue 6's quality; {st['cascades_run']} cascades "
              f"run, {len(st['skipped'])} skipped as empty): {st['full_update_ms']:.1f} ms")
        for k, v in sorted(st["median_ms"].items(), key=lambda kv: -kv[1]):
            print(f"    {k:<14} {v:9.1f} ms")
        print(f"  one light moved / full update with 8 lights: "
              f"{out['one_light_moved_over_full_8']:.3f}")
    if "sweep" in out:
        from tools import bench_sweep

        print()
        print(bench_sweep.table(out["sweep"]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
