"""Measure how Cycles' Principled BSDF layers scale its diffuse: the Diffuse Color pass of a
white-based Principled seen head-on (orthographic camera, one patch per setting).

Usage: python -m tools.measure_principled_layers   (headless bpy; prints the tables that
lpv_addon/scene_io/materials.py holds: the dielectric layer's transmitted fraction
1 - E(roughness, F0) and the sheen layer's albedo per sheen roughness)
       python -m tools.measure_principled_layers --view   (the same transmitted fraction over
roughness x IOR x the cosine of the view angle, patches tilted to an orthographic camera;
writes lpv_addon/scene_io/principled_view.json, which materials.py reads)
"""

from __future__ import annotations

import json
import os
import sys
import tempfile

import numpy as np

ROUGHNESS = (0.0, 0.125, 0.25, 0.375, 0.5, 0.625, 0.75, 0.875, 1.0)
IOR = (1.0, 1.1, 1.2, 1.33, 1.5, 1.75, 2.0, 2.5, 3.0, 4.0)
P = 4  # pixels a patch
# Cosines of the view angle of --view: dense towards grazing, where the layer's albedo grows.
COS_VIEW = (1.0, 0.95, 0.9, 0.8, 0.7, 0.6, 0.5, 0.4, 0.33, 0.26, 0.2, 0.15, 0.1, 0.07, 0.04,
            0.02)
VIEW_TABLE = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
                          "lpv_addon", "scene_io", "principled_view.json")


def measure_view(out: str = VIEW_TABLE, samples: int = 16) -> dict:
    """Diffuse Color of a white-based Principled (roughness x IOR, Specular IOR Level 0.5) on
    unit patches tilted so that the orthographic camera sees each at a cosine of COS_VIEW
    (each patch 1/cos long, so that all project to 1 x 1); below them the same for the coat
    (white base, no specular, Coat Weight 1, white tint; coat roughness x coat IOR) and the
    sheen layer's albedo (black base, no specular, Sheen Weight 1, white tint) per sheen
    roughness x COS_VIEW; written to ``out`` as JSON."""
    os.environ.setdefault("BLENDER_USER_RESOURCES", tempfile.mkdtemp(prefix="lpv_layers_"))
    import bpy

    from lpv_addon.render import cycles
    from lpv_core.render import exr

    bpy.ops.wm.read_homefile(use_empty=True)
    scene = bpy.context.scene
    cols = len(IOR) * len(COS_VIEW)
    n = len(ROUGHNESS)
    rows = 3 * n
    for row, r in enumerate(ROUGHNESS * 3):
        coat, sheen = n <= row < 2 * n, row >= 2 * n
        for c in range(len(COS_VIEW) if sheen else cols):
            ior, mu = IOR[c // len(COS_VIEW)], COS_VIEW[c % len(COS_VIEW)]
            mat = bpy.data.materials.new(f"view {row} {ior} {mu}")
            p = mat.node_tree.nodes["Principled BSDF"]
            p.inputs["Base Color"].default_value = (0, 0, 0, 1) if sheen else (1, 1, 1, 1)
            p.inputs["Roughness"].default_value = r
            p.inputs["IOR"].default_value = ior
            if coat:
                p.inputs["Specular IOR Level"].default_value = 0.0
                p.inputs["Coat Weight"].default_value = 1.0
                p.inputs["Coat Roughness"].default_value = r
                p.inputs["Coat IOR"].default_value = ior
            if sheen:
                p.inputs["Specular IOR Level"].default_value = 0.0
                p.inputs["Sheen Weight"].default_value = 1.0
                p.inputs["Sheen Roughness"].default_value = r
                p.inputs["Sheen Tint"].default_value = (1, 1, 1, 1)
            # the patch rises along +y towards z: its normal (0, -sin, cos) . view (0, 0, 1) = mu
            rise = float(np.sqrt(1.0 - mu * mu)) / mu
            y0 = -row - 1.0
            me = bpy.data.meshes.new("patch")
            me.from_pydata([(c, y0, 0), (c + 1, y0, 0), (c + 1, y0 + 1, rise),
                            (c, y0 + 1, rise)], [], [(0, 1, 2, 3)])
            me.materials.append(mat)
            scene.collection.objects.link(bpy.data.objects.new(mat.name, me))
    cam = bpy.data.cameras.new("cam")
    cam.type, cam.ortho_scale, cam.clip_end = "ORTHO", cols, 300.0
    ob = bpy.data.objects.new("cam", cam)
    ob.location = (cols / 2, -rows / 2, 100)
    scene.collection.objects.link(ob)
    scene.camera = ob
    path = os.path.join(tempfile.mkdtemp(), "view.exr")
    cycles.render_cycles_passes(path, samples=samples, resolution=(cols * P, rows * P))
    color = exr.read_multilayer(path)["Diffuse Color"][:, :, 0]
    t = np.array([[color[row * P + 1:row * P + 3, c * P + 1:c * P + 3].mean()
                   for c in range(cols)] for row in range(rows)])
    table = {"blender": bpy.app.version_string, "roughness": ROUGHNESS, "ior": IOR,
             "cos_view": COS_VIEW, "samples": samples,
             "transmitted": t[:n].reshape(n, len(IOR), len(COS_VIEW)).round(5).tolist(),
             "coat_transmitted": t[n:2 * n].reshape(n, len(IOR), len(COS_VIEW)).round(5).tolist(),
             "sheen_albedo": t[2 * n:, :len(COS_VIEW)].round(5).tolist()}
    with open(out, "w") as f:
        json.dump(table, f, indent=None, separators=(",", ":"))
        f.write("\n")
    print(f"wrote {out}")
    return table


def main(argv: list[str] | None = None) -> dict:
    if argv and "--view" in argv:
        return measure_view()
    os.environ.setdefault("BLENDER_USER_RESOURCES", tempfile.mkdtemp(prefix="lpv_layers_"))
    import bpy

    from lpv_addon.render import cycles
    from lpv_core.render import exr

    bpy.ops.wm.read_homefile(use_empty=True)
    scene = bpy.context.scene
    cases = [("spec", r, ior) for r in ROUGHNESS for ior in IOR]
    cases += [("sheen", r, 1.0) for r in ROUGHNESS]
    for i, (kind, r, ior) in enumerate(cases):
        mat = bpy.data.materials.new(f"{kind} {r} {ior}")
        nt = mat.node_tree
        p = nt.nodes["Principled BSDF"]
        p.inputs["Base Color"].default_value = (1, 1, 1, 1)
        if kind == "spec":
            p.inputs["Roughness"].default_value = r
            p.inputs["IOR"].default_value = ior
        else:  # no specular, black base: the sheen layer's own albedo
            p.inputs["Base Color"].default_value = (0, 0, 0, 1)
            p.inputs["Specular IOR Level"].default_value = 0.0
            p.inputs["Sheen Weight"].default_value = 1.0
            p.inputs["Sheen Roughness"].default_value = r
            p.inputs["Sheen Tint"].default_value = (1, 1, 1, 1)
        me = bpy.data.meshes.new("patch")
        me.from_pydata([(i, 0, 0), (i + 1, 0, 0), (i + 1, -1, 0), (i, -1, 0)], [],
                       [(0, 3, 2, 1)])
        me.materials.append(mat)
        scene.collection.objects.link(bpy.data.objects.new(mat.name, me))
    cam = bpy.data.cameras.new("cam")
    cam.type, cam.ortho_scale = "ORTHO", len(cases)
    ob = bpy.data.objects.new("cam", cam)
    ob.location = (len(cases) / 2, -0.5, 5)
    scene.collection.objects.link(ob)
    scene.camera = ob
    path = os.path.join(tempfile.mkdtemp(), "layers.exr")
    cycles.render_cycles_passes(path, samples=16, resolution=(len(cases) * P, P))
    color = exr.read_multilayer(path)["Diffuse Color"][:, :, 0]
    values = [float(color[1:3, i * P + 1:i * P + 3].mean()) for i in range(len(cases))]
    spec = np.array(values[:len(ROUGHNESS) * len(IOR)]).reshape(len(ROUGHNESS), len(IOR))
    sheen = np.array(values[len(ROUGHNESS) * len(IOR):])
    out = {"blender": bpy.app.version_string, "roughness": ROUGHNESS, "ior": IOR,
           "dielectric_transmitted": spec.round(5).tolist(),
           "sheen_albedo": sheen.round(5).tolist()}
    print(json.dumps(out))
    return out


if __name__ == "__main__":
    main(sys.argv[1:])
