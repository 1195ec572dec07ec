"""Extraction benchmark: median ms per phase for a ~1M-triangle mesh and many instances.

Usage: python -m tools.extract_bench [--triangles 1000000] [--repeat 5] [--instances 100]
       python -m tools.extract_bench --textured 100 [--image-size 1024]
Runs headless with the bpy module; prints JSON. ``--textured N``: N objects, each with its own
material and its own image file (PNG, N x size^2): the cold extraction (every image read), a
second one (nothing changed), and one after one image file changed; time and peak memory.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import sys
import tempfile
import time

import numpy as np

PHASES = (
    "mesh_eval", "triangles", "positions", "normals", "materials", "transform",
    "lights", "camera", "make_scene", "corners",
)


def grid_arrays(triangles: int) -> tuple[np.ndarray, np.ndarray]:
    """Vertex positions (V, 3) and quad corners (Q, 4) of a wavy n x n grid with ~triangles."""
    n = max(1, math.ceil(math.sqrt(triangles / 2.0)))
    xs = np.linspace(-10.0, 10.0, n + 1, dtype=np.float32)
    x, y = np.meshgrid(xs, xs, indexing="xy")
    z = 0.5 * np.sin(x) * np.cos(0.7 * y)
    co = np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1).astype(np.float32)
    i = np.arange(n, dtype=np.int32)
    a = (i[None, :] + (n + 1) * i[:, None]).ravel()
    quads = np.stack([a, a + 1, a + n + 2, a + n + 1], axis=1).astype(np.int32)
    return co, quads


def build_mesh(bpy, name: str, co: np.ndarray, quads: np.ndarray, flat: bool = False):
    """A quad mesh filled through foreach_set (no from_pydata): about 0.5 s for 1M triangles."""
    me = bpy.data.meshes.new(name)
    me.vertices.add(len(co))
    me.loops.add(quads.size)
    me.polygons.add(len(quads))
    me.attributes["position"].data.foreach_set("vector", co.ravel())
    me.attributes[".corner_vert"].data.foreach_set("value", quads.ravel())
    me.polygons.foreach_set("loop_start", np.arange(0, quads.size, 4, dtype=np.int32))
    me.update()
    if flat:
        me.shade_flat()
    return me


def build_scene(bpy, triangles: int, instances: int, instance_triangles: int, flat: bool):
    """Big mesh (4 materials by face), ``instances`` linked duplicates, a light and a camera."""
    bpy.ops.wm.read_homefile(use_empty=True)
    scene = bpy.context.scene
    co, quads = grid_arrays(triangles)
    big = bpy.data.objects.new("big", build_mesh(bpy, "big", co, quads, flat))
    scene.collection.objects.link(big)
    for k in range(4):
        mat = bpy.data.materials.new(f"mat{k}")
        mat.diffuse_color = (0.2 * k, 0.5, 0.8, 1.0)
        big.data.materials.append(mat)
    mat_index = (np.arange(len(quads)) % 4).astype(np.int32)
    big.data.attributes.new("material_index", "INT", "FACE").data.foreach_set("value", mat_index)
    sco, squads = grid_arrays(instance_triangles)
    small = build_mesh(bpy, "small", sco * 0.05, squads, flat)
    small.materials.append(bpy.data.materials.new("small"))
    side = max(1, math.ceil(math.sqrt(instances)))
    for k in range(instances):
        ob = bpy.data.objects.new(f"inst{k}", small)
        ob.location = (k % side - side / 2, k // side - side / 2, 2.0)
        ob.rotation_euler = (0.1 * k, 0.2 * k, 0.0)
        ob.scale = (1.0, 1.0, -1.0 if k % 2 else 1.0)
        scene.collection.objects.link(ob)
    light = bpy.data.objects.new("sun", bpy.data.lights.new("sun", "SUN"))
    scene.collection.objects.link(light)
    cam = bpy.data.objects.new("cam", bpy.data.cameras.new("cam"))
    cam.location = (0.0, -25.0, 12.0)
    cam.rotation_euler = (1.1, 0.0, 0.0)
    scene.collection.objects.link(cam)
    scene.camera = cam
    return big, [o for o in scene.objects if o.name.startswith("inst")]


def measure(bpy, extract, repeat: int) -> dict:
    """Extract ``repeat`` times: first (cold) total, median ms per phase and in total."""
    runs, totals, tri = [], [], 0
    for _ in range(repeat):
        depsgraph = bpy.context.evaluated_depsgraph_get()
        timings: dict = {}
        t0 = time.perf_counter()
        result = extract.extract_scene(depsgraph, timings=timings)
        totals.append((time.perf_counter() - t0) * 1000.0)
        runs.append(timings)
        tri = result.triangle_count
    phases = {p: round(statistics.median(r.get(p, 0.0) for r in runs), 2) for p in PHASES}
    return {
        "triangles": tri,
        "first_total_ms": round(totals[0], 2),
        "median_ms": phases,
        "median_total_ms": round(statistics.median(totals), 2),
    }


def _memory_kb(field: str) -> int:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(field + ":"):
                return int(line.split()[1])
    return 0


def _reset_peak() -> None:
    """Start a new VmHWM window (Linux: clear_refs 5 resets the peak resident size)."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
    except OSError:
        pass


def build_textured(bpy, count: int, size: int, folder: str) -> list:
    """``count`` quads in a row, each with its own Principled material reading its own
    ``size``^2 PNG (a generated colour grid, saved and loaded like any file)."""
    bpy.ops.wm.read_homefile(use_empty=True)
    scene = bpy.context.scene
    images = []
    for k in range(count):
        img = bpy.data.images.new(f"tex{k}", size, size)
        img.generated_type = "COLOR_GRID"
        img.generated_color = ((k % 10) / 10.0, 0.5, 1.0 - (k % 7) / 7.0, 1.0)
        img.filepath_raw = os.path.join(folder, f"tex{k}.png")
        img.file_format = "PNG"
        img.save()
        images.append(img)
        mat = bpy.data.materials.new(f"mat{k}")
        nodes = mat.node_tree.nodes
        tex = nodes.new("ShaderNodeTexImage")
        tex.image = img
        mat.node_tree.links.new(tex.outputs["Color"], nodes["Principled BSDF"].inputs[0])
        me = bpy.data.meshes.new(f"quad{k}")
        me.from_pydata([(k, 0, 0), (k + 1, 0, 0), (k + 1, 1, 0), (k, 1, 0)], [], [(0, 1, 2, 3)])
        me.uv_layers.new(name="UVMap")
        me.materials.append(mat)
        scene.collection.objects.link(bpy.data.objects.new(f"quad{k}", me))
    return images


def textured(bpy, extract, count: int, size: int) -> dict:
    """Cold, unchanged and one-image-changed extraction of the textured scene."""
    from lpv_addon.scene_io import materials

    folder = tempfile.mkdtemp(prefix="lpv_tex_bench_")
    t0 = time.perf_counter()
    images = build_textured(bpy, count, size, folder)
    report = {"materials": count, "image_size": size, "build_s": round(time.perf_counter() - t0, 2)}

    def once(label: str) -> None:
        depsgraph = bpy.context.evaluated_depsgraph_get()
        rss = _memory_kb("VmRSS")
        cached = set(materials._textures)
        _reset_peak()
        t = time.perf_counter()
        s = extract.extract_scene(depsgraph, require_camera=False)
        ms = (time.perf_counter() - t) * 1000.0
        report[label] = {"ms": round(ms, 1),
                         "peak_extra_mb": round((_memory_kb("VmHWM") - rss) / 1024.0, 1),
                         "textured_materials": sum(m.texture is not None for m in s.materials),
                         "images_read": len(set(materials._textures) - cached)}

    once("cold")
    once("unchanged")
    img = images[count // 2]  # repaint one image and save it: its file changes
    px = np.empty(len(img.pixels), np.float32)
    img.pixels.foreach_get(px)
    img.pixels.foreach_set(1.0 - px)
    img.save()
    once("one_image_changed")
    report["rss_mb"] = round(_memory_kb("VmRSS") / 1024.0, 1)
    return report


def main(argv: list[str] | None = None) -> dict:
    """Build the scenes, time extraction, print and return the JSON report."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--triangles", type=int, default=1_000_000)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--instances", type=int, default=100)
    ap.add_argument("--instance-triangles", type=int, default=2_000)
    ap.add_argument("--flat", action="store_true", help="flat shading (face normals)")
    ap.add_argument("--textured", type=int, default=0,
                    help="instead: this many materials, each with its own image texture")
    ap.add_argument("--image-size", type=int, default=1024)
    args = ap.parse_args(argv)
    # Keep a headless run out of the user's Blender config (must precede `import bpy`).
    os.environ.setdefault("BLENDER_USER_RESOURCES", tempfile.mkdtemp(prefix="lpv_bench_"))
    import bpy

    from lpv_addon.scene_io import extract

    if args.textured:
        report = {"blender": bpy.app.version_string, "numpy": np.__version__,
                  **textured(bpy, extract, args.textured, args.image_size)}
        print(json.dumps(report, indent=2))
        return report

    t0 = time.perf_counter()
    big, insts = build_scene(bpy, args.triangles, args.instances, args.instance_triangles,
                             args.flat)
    build_s = time.perf_counter() - t0
    report = {
        "blender": bpy.app.version_string,
        "numpy": np.__version__,
        "shading": "flat" if args.flat else "smooth",
        "build_s": round(build_s, 3),
        "repeat": args.repeat,
    }
    for label, show_big, show_inst in (
        ("mesh", True, False), ("instances", False, True), ("combined", True, True)
    ):
        big.hide_render = not show_big
        for ob in insts:
            ob.hide_render = not show_inst
        report[label] = measure(bpy, extract, args.repeat)
    report["instances"]["count"] = len(insts)
    print(json.dumps(report, indent=2))
    return report


if __name__ == "__main__":
    main(sys.argv[1:])
