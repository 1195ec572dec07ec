"""bpy.ops.lpv.* and the live engine in a real headless Blender (engine in the worker process):
update, add_area, render_batch (blocking, and the modal job's steps with cancel),
compare_cycles, the depsgraph/frame handlers and the timer's planning."""

from __future__ import annotations

import json

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

from lpv_addon import operators, properties
from lpv_addon.render import compare
from lpv_addon.render.frames import BatchJob
from lpv_addon.viewport import handlers, live
from lpv_core.render import exr
from tools import scenes

pytestmark = pytest.mark.bpy


@pytest.fixture(scope="module", autouse=True)
def addon(registered_addon):
    """Every test here runs with the add-on registered (conftest.registered_addon)."""


@pytest.fixture()
def box():
    live.shutdown()
    scenes.cornell_box("SPOT", resolution=(32, 24))
    scene = bpy.context.scene
    scene.lpv.enabled = True  # LPV GI is off in a file until the user turns it on
    scene.lpv.quality = "DRAFT"
    scene.lpv.rsm_resolution = 64
    return scene


def test_update_computes_the_lpv_in_the_worker(box):
    assert bpy.ops.lpv.update() == {"FINISHED"}
    cur = live.STATE.current
    assert cur is not None and cur.values is not None
    r = properties.PRESETS["DRAFT"][2]["grid_resolution"]  # the preset the fixture chose
    assert cur.grid.resolution == r
    assert cur.values.shape == (r, r, r, 3, 9) and np.abs(cur.values).max() > 0  # "dom": bands 0-2
    assert set(cur.per_light) == {"Spot"}
    assert cur.vpl_position.shape[0] > 100
    assert cur.stats["ms"]["rsm"] > 0 and cur.stats["ms"]["propagation"] > 0
    assert live.STATE.client.alive and live.STATE.client.proc.pid != __import__("os").getpid()
    lines = live.stats_lines()
    assert any(line.startswith("propagation:") for line in lines)


def test_update_reports_a_disabled_scene(box):
    box.lpv.enabled = False
    assert bpy.ops.lpv.update() == {"CANCELLED"}


def test_update_poll_needs_lpv_settings():
    assert bpy.ops.lpv.update.poll()


def test_add_area_adds_cube_empties_at_the_cursor(box):
    box.cursor.location = (0.3, -0.2, 1.1)
    assert bpy.ops.lpv.add_area(type="CLIP", size=0.75) == {"FINISHED"}
    assert bpy.ops.lpv.add_area(type="TRANSITION") == {"FINISHED"}
    empties = [ob for ob in box.objects if ob.type == "EMPTY"]
    kinds = sorted(ob.lpv.area_type for ob in empties)
    assert kinds == ["CLIP", "TRANSITION"]
    clip = next(ob for ob in empties if ob.lpv.area_type == "CLIP")
    assert clip.empty_display_type == "CUBE" and clip.empty_display_size == 0.75
    np.testing.assert_allclose(tuple(clip.location), (0.3, -0.2, 1.1), atol=1e-6)
    core = live.extract(box)
    assert sorted(a.type for a in core.areas) == ["CLIP", "TRANSITION"]


def test_render_batch_renders_every_frame_with_keyframed_intensity(box, tmp_path):
    box.lpv.intensity = 1.0
    box.lpv.keyframe_insert("intensity", frame=1)
    box.lpv.intensity = 2.0
    box.lpv.keyframe_insert("intensity", frame=2)
    box.frame_start, box.frame_end = 1, 2
    assert bpy.ops.lpv.render_batch(directory=str(tmp_path), frames="ANIMATION") == {"FINISHED"}
    stats = json.loads((tmp_path / "stats.json").read_text())
    assert [f["frame"] for f in stats["frames"]] == [1, 2]
    assert [f["intensity"] for f in stats["frames"]] == [pytest.approx(1.0), pytest.approx(2.0)]
    assert stats["cancelled"] is False
    a, b = (exr.read_multilayer(tmp_path / f"{i:04d}.exr") for i in (1, 2))
    assert set(a) == {"Combined", "Diffuse Direct", "Diffuse Indirect", "Diffuse Color"}
    assert a["Diffuse Indirect"].shape[:2] == (24, 32)
    lit = a["Diffuse Indirect"] > 1e-3 * a["Diffuse Indirect"].max()
    np.testing.assert_allclose(b["Diffuse Indirect"][lit] / a["Diffuse Indirect"][lit], 2.0,
                               rtol=2e-3)
    assert box.frame_current == 1  # the frame was put back
    assert not live.STATE.paused


def test_render_batch_needs_a_camera(box, tmp_path):
    box.camera = None
    with pytest.raises(RuntimeError, match="active camera"):
        bpy.ops.lpv.render_batch(directory=str(tmp_path))


def test_batch_job_steps_like_the_modal_operator_and_cancel_keeps_frames(box, tmp_path):
    box.frame_start, box.frame_end = 1, 4
    job = BatchJob(box, tmp_path, (1, 4))
    job.start()
    steps = 0
    while len(job.done) < 2:  # non-blocking steps, as the modal timer drives them
        assert job.step()
        steps += 1
        __import__("time").sleep(0.02)
    assert steps > 2  # it returned while the worker was busy
    job.cancel()
    job.close()
    assert job.finished and job.cancelled
    frames = sorted(p.name for p in tmp_path.glob("*.exr"))
    assert frames[:2] == ["0001.exr", "0002.exr"] and len(frames) <= 3
    for name in frames:
        exr.read_multilayer(tmp_path / name)  # every file left is complete
    assert not list(tmp_path.glob(".*"))
    stats = json.loads((tmp_path / "stats.json").read_text())
    assert stats["cancelled"] is True and len(stats["frames"]) == 2


def test_the_cli_and_the_operator_share_one_frame_loop(box, tmp_path):
    """The same BatchJob with the engine in this process (the CLI) and in the worker (the
    operator): the same pixels and the same stats.json entries."""
    here, there = tmp_path / "here", tmp_path / "worker"
    BatchJob(box, here, (1, 1), in_process=True).run()
    BatchJob(box, there, (1, 1)).run()
    a, b = (exr.read_multilayer(d / "0001.exr") for d in (here, there))
    assert set(a) == set(b)
    for name in a:
        np.testing.assert_allclose(a[name], b[name], rtol=1e-4, atol=1e-6, err_msg=name)
    fa, fb = (json.loads((d / "stats.json").read_text())["frames"][0] for d in (here, there))
    assert set(fa) == set(fb) and fa["frame"] == fb["frame"] == 1
    assert fa["extract_ms"] and fb["ms"]["extract"] > 0


def test_compare_cycles_makes_a_red_green_heatmap(box):
    assert bpy.ops.lpv.compare_cycles(resolution=16, samples=4) == {"FINISHED"}
    img = bpy.data.images[operators.IMAGE_ERROR]
    assert tuple(img.size) == (16, 12)
    px = np.empty(16 * 12 * 4, np.float32)
    img.pixels.foreach_get(px)
    px = px.reshape(-1, 4)
    assert px[:, 2].max() == 0.0 and px[:, 3].min() == 1.0  # red/green only
    assert px[:, :2].max() > 0
    assert "rel. RMSE" in box.lpv.compare_summary
    for name in (operators.IMAGE_OURS, operators.IMAGE_CYCLES):
        assert bpy.data.images[name].size[0] == 16


def test_error_heatmap_colours():
    ref = np.ones((2, 2, 3), np.float32)
    ours = ref.copy()
    ours[0, 0] = 3.0  # too bright: red
    ours[1, 1] = 0.0  # too dark: green
    heat, metrics = compare.error_heatmap(ours, ref)
    np.testing.assert_array_equal(heat[0, 0], [1, 0, 0, 1])
    np.testing.assert_array_equal(heat[1, 1], [0, 1, 0, 1])
    np.testing.assert_array_equal(heat[0, 1], [0, 0, 0, 1])
    assert metrics["mean_ratio"] == pytest.approx(1.25)


def test_handlers_mark_what_changed(box):
    bpy.context.view_layer.update()  # the new scene's own first evaluation
    live.STATE.dirty, live.STATE.reasons = False, []
    bpy.data.objects["TallBlock"].location.x += 0.1
    bpy.context.view_layer.update()
    assert live.STATE.dirty and "transform: TallBlock" in live.STATE.reasons
    live.STATE.dirty, live.STATE.reasons = False, []
    box.camera.location.z += 0.2  # the view moved: the LPV does not depend on it
    bpy.context.view_layer.update()
    assert not live.STATE.dirty
    box.frame_set(3)
    assert live.STATE.dirty and "frame change" in live.STATE.reasons


def test_tick_updates_then_recombines_art_direction_only(box):
    assert handlers.timer() > 0  # the registered timer function: returns the next interval
    live.tick(require_viewport=False)
    live.wait_pending()
    first = live.STATE.current
    assert first is not None and first.values is not None
    # Only the light's GI intensity changes: cached per-light grids are re-combined here.
    bpy.data.lights["Spot"].lpv.gi_intensity = 2.0
    live.STATE.last_sent = 0.0
    live.tick(require_viewport=False)
    second = live.STATE.current
    assert second.serial == first.serial + 1 and live.STATE.pending is None
    np.testing.assert_allclose(second.values, 2.0 * first.values, rtol=1e-6)
    reasons = {s["reason"] for s in second.stats["skipped"]}
    assert any("re-combined" in r for r in reasons)
    assert live.STATE.previous is first and 0.0 <= live.fade(box.lpv) < 1.0
    # Geometry changes need the worker again.
    bpy.data.objects["ShortBlock"].location.y += 0.2
    bpy.context.view_layer.update()
    live.STATE.last_sent = 0.0
    live.tick(require_viewport=False)
    assert live.STATE.pending is not None


def test_shutdown_stops_the_worker(box):
    bpy.ops.lpv.update()
    proc = live.STATE.client.proc
    live.shutdown()
    assert proc.poll() is not None
    assert live.STATE.client is None and live.STATE.current is None
