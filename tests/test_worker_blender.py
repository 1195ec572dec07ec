"""RSM inside a Blender process: the GL work runs in the worker process, and Blender's own
`gpu` drawing gives the same pixels before and after it (moderngl in-process breaks it)."""

import json
import subprocess
import sys

from conftest import ROOT

SCRIPT = r"""
import json, os, sys, tempfile
import bpy, gpu
import numpy as np
from gpu_extras.batch import batch_for_shader
from lpv_core import demo, worker

scene = bpy.context.scene
scene.render.engine = "BLENDER_WORKBENCH"
scene.render.resolution_x = scene.render.resolution_y = 8
scene.render.filepath = os.path.join(tempfile.mkdtemp(), "warm.png")
bpy.ops.render.render(write_still=False)  # creates the GPU context headless

def draw():
    off = gpu.types.GPUOffScreen(64, 64)
    shader = gpu.shader.from_builtin("UNIFORM_COLOR")
    batch = batch_for_shader(shader, "TRIS", {"pos": [(-0.8, -0.8), (0.8, -0.6), (0.0, 0.9)]})
    with off.bind():
        fb = gpu.state.active_framebuffer_get()
        fb.clear(color=(0.0, 0.0, 0.0, 0.0))
        with gpu.matrix.push_pop():
            gpu.matrix.load_identity()
            gpu.matrix.load_projection_matrix(__import__("mathutils").Matrix.Identity(4))
            shader.uniform_float("color", (0.2, 0.6, 0.9, 1.0))
            batch.draw(shader)
        buf = fb.read_color(0, 0, 64, 64, 4, 0, "FLOAT")
    buf.dimensions = 64 * 64 * 4
    off.free()
    return np.array(buf.to_list(), np.float32)

before = draw()
core_scene = demo.cornell_box("SPOT", (32, 32))
vpls = worker.rsm_in_subprocess(core_scene, 64)
after = draw()
print("RESULT" + json.dumps({
    "covered": int((before[3::4] > 0).sum()),
    "identical": bool(np.array_equal(before, after)),
    "lights": len(vpls),
    "vpls": int(vpls[0]["position"].shape[0]),
    "flux": float(vpls[0]["flux"].sum()),
    "finite": bool(all(np.isfinite(v).all() for d in vpls for v in d.values())),
}))
"""


def test_rsm_in_worker_leaves_blender_drawing_intact(tmp_path):
    proc = subprocess.run([sys.executable, "-c", SCRIPT], cwd=ROOT, capture_output=True,
                          text=True, check=False, timeout=300)
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT")]
    assert proc.returncode == 0 and lines, proc.stderr[-3000:]
    r = json.loads(lines[-1][len("RESULT"):])
    assert r["covered"] > 500  # the triangle was drawn
    assert r["identical"]
    assert r["lights"] == 1 and r["vpls"] > 1000 and r["finite"]
    assert r["flux"] > 0
