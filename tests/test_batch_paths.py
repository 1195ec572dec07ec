"""The batch frame loop in this process: stats.json's constant cost per frame and validity
after every frame, where frames go (Blender's render output path and '//' rules), which
frames the Render Batch operator renders, and the one preset table."""

from __future__ import annotations

import json
import os

import pytest

bpy = pytest.importorskip("bpy")

import lpv_addon
from lpv_addon import presets, properties
from lpv_addon.render.frames import BatchJob, StatsFile
from lpv_addon.scene_io import demo

pytestmark = pytest.mark.bpy


def _bytes_written() -> int:
    """This process's bytes passed to write(2) so far (Linux)."""
    with open("/proc/self/io") as fh:
        return int(next(ln for ln in fh if ln.startswith("wchar:")).split()[1])


@pytest.mark.skipif(not os.path.exists("/proc/self/io"), reason="needs Linux /proc/self/io")
def test_stats_file_costs_the_same_bytes_per_frame_and_parses_after_every_frame(tmp_path):
    path = tmp_path / "stats.json"
    stats = StatsFile(path, {"scene": "S", "settings": {"grid_resolution": 16}})
    record = {"ms": {f"stage{i}": 12.345678 for i in range(20)}, "dropped": {}, "skipped": []}
    size = len(json.dumps({"frame": 1000, **record}))
    written = []
    for frame in range(1000, 1400):  # four-digit frames: every record the same length
        before = _bytes_written()
        stats.add({"frame": frame, **record})
        written.append(_bytes_written() - before)
        data = json.loads(path.read_text())
        assert len(data["frames"]) == frame - 999 and data["frames"][-1]["frame"] == frame
    assert min(written[1:]) == max(written[1:]) < size + 64  # the record and the tail only
    stats.set_cancelled(True)
    stats.close()
    data = json.loads(path.read_text())
    assert data["cancelled"] is True and len(data["frames"]) == 400
    assert data["settings"] == {"grid_resolution": 16}


@pytest.fixture()
def box():
    demo.cornell_box("SPOT", resolution=(32, 24))
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end, scene.frame_step = 1, 3, 2
    scene.frame_current = 2
    return scene


SMALL = {"grid_resolution": 8, "rsm_resolution": 32}


def test_the_loop_leaves_stats_json_valid_after_every_frame(box, tmp_path):
    seen = []

    def log(msg):
        if msg.startswith("frame "):
            seen.append([f["frame"] for f in json.loads((tmp_path / "stats.json").read_text())
                         ["frames"]])

    BatchJob(box, tmp_path, (1, 3), overrides=SMALL, in_process=True, log=log).run()
    assert seen == [[1], [1, 2], [1, 2, 3]]


def test_frames_follow_blenders_render_output_path(box, tmp_path, monkeypatch):
    """No folder given: Blender's own frame path (``#`` and prefix), as an EXR. For an
    unsaved file '//' is relative to the working directory, as Blender renders it, once."""
    monkeypatch.chdir(tmp_path)
    assert not bpy.data.filepath
    box.render.filepath = "//render/shot_"
    assert box.render.frame_path(frame=7) == os.path.join("render", "shot_0007.png")  # Blender
    job = BatchJob(box, None, (7, 7))
    assert job.out == tmp_path / "render"
    assert job.frame_file(7) == tmp_path / "render" / "shot_0007.exr"
    box.render.filepath = "//out/f_##_v"
    assert BatchJob(box, "", (7, 7)).frame_file(7) == tmp_path / "out" / "f_07_v.exr"
    job = BatchJob(box, "//lpv_frames/", (7, 7))
    assert job.out == tmp_path / "lpv_frames" and job.frame_file(7).parent == job.out
    blend = tmp_path / "saved" / "scene.blend"
    blend.parent.mkdir()
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    scene = bpy.context.scene
    scene.render.filepath = "//render/"
    assert BatchJob(scene, None, (3, 3)).frame_file(3) == blend.parent / "render" / "0003.exr"


def test_presets_are_one_table_for_the_addon_and_the_cli():
    assert properties.PRESETS.keys() == presets.SETTINGS.keys()
    for key, (_, _, settings) in properties.PRESETS.items():
        assert settings is presets.SETTINGS[key]
    assert presets.SETTINGS["DRAFT"]["grid_resolution"] == 16  # its label: "16^3 grid"


@pytest.fixture()
def addon():
    lpv_addon.register()
    yield
    lpv_addon.unregister()


def test_render_batch_renders_the_current_frame_unless_told_the_animation(addon, box,
                                                                          tmp_path,
                                                                          monkeypatch):
    box.lpv.quality = "DRAFT"
    box.lpv.rsm_resolution = 32
    monkeypatch.chdir(tmp_path)  # an unsaved file: '//' is the working directory, once
    assert bpy.ops.lpv.render_batch(directory="//still/") == {"FINISHED"}
    assert sorted(p.name for p in (tmp_path / "still").iterdir()) == ["0002.exr", "stats.json"]
    box.render.filepath = str(tmp_path / "anim" / "f_")  # no folder given: the output path
    assert box.lpv.batch_directory == ""
    assert bpy.ops.lpv.render_batch(frames="ANIMATION") == {"FINISHED"}
    assert sorted(p.name for p in (tmp_path / "anim").iterdir()) == [
        "f_0001.exr", "f_0003.exr", "stats.json"]
    assert bpy.ops.lpv.render_batch(directory=str(tmp_path / "range"), frames="RANGE",
                                    frame_start=2, frame_end=3) == {"FINISHED"}
    assert sorted(p.name for p in (tmp_path / "range").glob("*.exr")) == ["0002.exr",
                                                                          "0003.exr"]


FULL_SCRIPT = r"""
import json, resource, signal, sys
from pathlib import Path
from lpv_addon.render.frames import StatsFile
path = Path(sys.argv[1])
stats = StatsFile(path, {"scene": "S", "settings": None})
stats.add({"frame": 1})
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # past the limit write(2) is cut short
resource.setrlimit(resource.RLIMIT_FSIZE, (path.stat().st_size + 100, resource.RLIM_INFINITY))
try:
    stats.add({"frame": 2, "pad": "x" * 1000})
except OSError as exc:
    print("ERROR", exc.filename)
print("FRAMES", [f["frame"] for f in json.loads(path.read_text())["frames"]])
"""


@pytest.mark.skipif(os.name != "posix", reason="RLIMIT_FSIZE is POSIX")
def test_a_record_cut_short_by_a_full_disk_leaves_stats_json_valid(tmp_path):
    """A write cut short (the file-size limit, as a full disk does) is undone: the file keeps
    the frames it had, and the error names it."""
    import subprocess
    import sys

    from conftest import ROOT

    path = tmp_path / "stats.json"
    proc = subprocess.run([sys.executable, "-c", FULL_SCRIPT, str(path)], cwd=ROOT,
                          capture_output=True, text=True, check=False, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert f"ERROR {path}" in proc.stdout and "FRAMES [1]" in proc.stdout, proc.stdout
