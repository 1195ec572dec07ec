"""RSM inside a Blender process: the GL work runs in the worker process, and Blender's own
`gpu` drawing gives the same pixels before and after it (moderngl in-process breaks it)."""

import dataclasses
import json
import subprocess
import sys

import numpy as np
import pytest
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



def test_cell_gaps_survive_the_worker_round_trip():
    """The live worker's out.npz carries each cascade's cell gaps (geometry_volume.cell_gaps),
    and live.py reads them back keyed by the very Grid objects of the result: the arrays the
    engine's occlusion gives for each cascade (recomputed here, numpy only). Without occlusion
    no cascade has gaps."""
    pytest.importorskip("bpy")
    from lpv_addon import live
    from lpv_core import demo, engine, live_worker
    from lpv_core.scene import GISettings

    settings = GISettings(grid_resolution=12, cascades=2, cascades_auto=False,
                          rsm_resolution=32, occlusion=True)
    scene = demo.cornell_box("SPOT", (16, 16), settings=settings)
    worker = live.WorkerClient()
    try:
        results = []
        for occlusion in (True, False):
            scene.settings = settings.updated(occlusion=occlusion)
            request, reply_path = worker.path("in.npz"), worker.path(f"out_{occlusion}.npz")
            live_worker.save_scene(request, scene)
            reply = worker.wait(worker.send("update", scene=request, reply=reply_path), 300.0)
            assert reply.get("ok"), reply
            results.append((live._read_reply(reply, scene, "key", [], 0.0, reply_path, 0.0),
                            set(np.load(reply_path).files)))
    finally:
        worker.close()
    (result, files), (plain, plain_files) = results
    grids = [result.grid] + [g for g, _, _ in result.fine]
    assert len(grids) == 2  # both cascades
    assert len(result.gaps) == len(grids)
    assert {"gaps", "fine_0_gaps"} <= files
    for grid in grids:
        assert any(k is grid for k in result.gaps)  # the result's own Grid objects
        expect = engine.occlusion(dataclasses.replace(scene, settings=settings), grid)[1]
        assert expect is not None
        got = result.gaps[grid]
        assert got.dtype == np.float32 and got.shape == (6,) + (grid.resolution,) * 3
        np.testing.assert_array_equal(got, np.asarray(expect, np.float32))
    assert any(result.gaps[g].max() > 0 for g in grids)  # the walls lie off the face planes
    assert plain.values is not None and not plain.gaps
    assert not any(f.endswith("gaps") for f in plain_files)
