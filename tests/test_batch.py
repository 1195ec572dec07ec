"""The batch CLI end to end: exit codes, EXR passes, stats.json shape, atomic outputs, output
errors (unwritable, not a folder, disk full), Ctrl-C, stale temporary files, presets, which
frames a .blend renders and where they go."""

import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
from conftest import ROOT

from lpv_core.render import exr


def _cli(*args, prefix=(), cwd=ROOT):
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run([*prefix, sys.executable, "-m", "lpv_addon.batch", *args], cwd=cwd,
                          env=env, capture_output=True, text=True, check=False, timeout=300)


SMALL = ("--resolution", "32x24", "--set", "grid_resolution=8", "--set", "rsm_resolution=32")


def _error_line(proc) -> str:
    lines = [ln for ln in proc.stderr.splitlines() if ln.startswith("error")]
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr[-2000:]
    return lines[0]


# ``python -m lpv_addon.batch`` with the measurement tools unimportable, as in the extension
# zip (which leaves tools/ out): the demo is the add-on's own.
WITHOUT_TOOLS = ("import runpy, sys; sys.modules['tools'] = None; "
                 "runpy.run_module('lpv_addon.batch', run_name='__main__', alter_sys=True)")


@pytest.fixture(scope="module")
def demo_out(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo")
    proc = subprocess.run([sys.executable, "-c", WITHOUT_TOOLS, "--demo", "--out", str(out),
                           "--resolution", "64x48", "--set", "grid_resolution=16",
                           "--set", "rsm_resolution=64"],
                          cwd=ROOT, capture_output=True, text=True, check=False)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return out, proc


def test_demo_writes_multilayer_exr_with_cycles_pass_names(demo_out):
    out, proc = demo_out
    assert "frame 1 (1/1)" in proc.stderr  # progress on stderr
    passes = exr.read_multilayer(out / "0001.exr")
    assert set(passes) == {"Combined", "Diffuse Direct", "Diffuse Indirect", "Diffuse Color"}
    for name, arr in passes.items():
        assert arr.shape[:2] == (48, 64), name
        assert np.isfinite(arr).all(), name
    combined = passes["Combined"][..., :3]
    expect = (passes["Diffuse Direct"] + passes["Diffuse Indirect"]) * passes["Diffuse Color"]
    # Each pass averages the pixel's sub-pixel samples (settings.antialias), so Combined is
    # (Direct + Indirect) x Color wherever the pixel sees one colour; where two surfaces meet,
    # the mean of the products lies between, as in Cycles.
    color = passes["Diffuse Color"]
    pad = np.pad(color, ((1, 1), (1, 1), (0, 0)), mode="edge")
    plain = np.ones(color.shape[:2], bool)
    for dy in (0, 1, 2):
        for dx in (0, 1, 2):
            plain &= np.all(pad[dy:dy + 48, dx:dx + 64] == color, axis=-1)
    assert plain.sum() > 500  # of 48 x 64
    np.testing.assert_allclose(combined[plain], expect[plain], rtol=1e-5, atol=1e-6)
    assert abs(combined.sum() / expect.sum() - 1.0) < 0.05
    assert passes["Diffuse Indirect"].max() > 0
    assert not list(out.glob(".*"))  # no temporary files left behind


def test_stats_json_has_the_documented_shape(demo_out):
    out, _ = demo_out
    stats = json.loads((out / "stats.json").read_text())
    assert stats["settings"]["grid_resolution"] == 16
    assert stats["settings"]["rsm_resolution"] == 64
    (frame,) = stats["frames"]
    assert frame["frame"] == 1
    for key in ("rsm", "injection", "propagation", "lpv_update", "total"):
        assert frame["ms"][key] >= 0, key
    assert frame["ms"]["total"] >= frame["ms"]["lpv_update"]
    assert isinstance(frame["dropped"], dict) and "zero_area_triangles" in frame["dropped"]
    assert isinstance(frame["skipped"], list)


@pytest.mark.parametrize(
    "args, message",
    [
        (["--out", "OUT"], "no .blend file"),
        (["MISSING", "--out", "OUT"], "no such file"),
        (["--demo", "--out", "OUT", "--frames", "5-2"], "before start"),
        (["--demo", "--out", "OUT", "--resolution", "big"], "expected WxH"),
        (["--demo", "--out", "OUT", "--set", "grid_resolution"], "key=value"),
        (["--demo", "--out", "OUT", "--set", "colour=1"], "unknown GI setting 'colour'"),
        (["--demo", "--out", "OUT", "--set", "occlusion=maybe"], "cannot read 'maybe'"),
        (["--demo", "--out", "OUT", "--set", "grid_resolution=160"], "grid_resolution 160 needs"),
    ],
)
def test_bad_arguments_exit_2_with_one_line(tmp_path, args, message):
    names = {"OUT": str(tmp_path / "out"), "MISSING": str(tmp_path / "missing.blend")}
    proc = _cli(*[names.get(a, a) for a in args])
    assert proc.returncode == 2
    assert message in _error_line(proc)
    assert not (tmp_path / "out").exists()  # no output folder for a run that cannot start


def test_unreadable_file_exits_2(tmp_path):
    bad = tmp_path / "garbage.blend"
    bad.write_bytes(b"this is not a blend file")
    proc = _cli(str(bad), "--out", str(tmp_path / "o"))
    assert proc.returncode == 2
    assert "not a .blend file" in proc.stderr
    assert not (tmp_path / "o").exists()


def _as_plain_user():
    """A command prefix under which file permissions apply (root ignores them): a user
    namespace mapping this user to an unprivileged one."""
    if os.geteuid() != 0:
        return ()
    prefix = ("unshare", "-U", "--map-user=1000", "--map-group=1000")
    if shutil.which("unshare") is None or subprocess.run([*prefix, "true"],
                                                         check=False).returncode:
        pytest.skip("running as root without user namespaces: permissions cannot apply")
    return prefix


@pytest.mark.parametrize("case", ["read-only folder", "parent is a file"])
def test_unwritable_output_exits_2_naming_the_folder(tmp_path, case):
    if case == "read-only folder":
        out = tmp_path / "locked"
        out.mkdir()
        out.chmod(0o555)
        want = f"cannot write to '{out}': Permission denied (EACCES)"
    else:
        (tmp_path / "file").write_text("x")
        out = tmp_path / "file" / "frames"
        want = f"cannot write to '{out}': Not a directory (ENOTDIR)"
    proc = _cli("--demo", "--out", str(out), *SMALL,
                prefix=_as_plain_user() if case == "read-only folder" else ())
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert want in _error_line(proc)
    assert "frame 1 (" not in proc.stderr  # refused before rendering


def test_full_disk_exits_2_with_enospc_and_valid_stats(tmp_path):
    """A real full disk: a 4 KiB tmpfs in a private mount namespace (root or user namespaces
    needed), which takes the probe and stats.json's head but not the first EXR."""
    mnt = tmp_path / "tiny"
    mnt.mkdir()
    prefix = ("unshare", "-rm") if os.geteuid() else ("unshare", "-m")
    script = (f'mount -t tmpfs -o size=4k tmpfs "{mnt}" || exit 99; "{sys.executable}" -m '
              f'lpv_addon.batch --demo --out "{mnt}/out" {" ".join(SMALL)}; rc=$?; '
              f'echo "STATS=$(cat "{mnt}/out/stats.json" | tr -d "\\n")"; '
              f'echo "FILES=$(ls -A "{mnt}/out" | tr "\\n" " ")"; exit $rc')
    if shutil.which("unshare") is None:
        pytest.skip("no unshare")
    proc = subprocess.run([*prefix, "sh", "-c", script], cwd=ROOT, capture_output=True,
                          text=True, check=False, timeout=300)
    if proc.returncode == 99:
        pytest.skip(f"cannot mount a tmpfs here: {proc.stderr.strip()[-200:]}")
    assert proc.returncode == 2, proc.stderr[-2000:]
    line = _error_line(proc)
    assert f"cannot write to '{mnt}/out/0001.exr': No space left on device (ENOSPC)" in line
    out = dict(ln.split("=", 1) for ln in proc.stdout.splitlines() if "=" in ln)
    stats = json.loads(out["STATS"])
    assert stats["frames"] == [] and stats["settings"]["grid_resolution"] == 8
    assert out["FILES"].split() == ["stats.json"]  # no partial EXR, no temporary file


def test_ctrl_c_exits_130_and_keeps_finished_frames(tmp_path):
    out = tmp_path / "out"
    # Ctrl-C as a terminal sends it, also where this job runs with SIGINT ignored (a shell's
    # background job), which the child would inherit
    start = ("import runpy, signal; signal.signal(signal.SIGINT, signal.default_int_handler); "
             "runpy.run_module('lpv_addon.batch', run_name='__main__', alter_sys=True)")
    proc = subprocess.Popen([sys.executable, "-c", start, "--demo", "--out",
                             str(out), "--frames", "1-400", *SMALL], cwd=ROOT,
                            stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 240
    while not (out / "0001.exr").exists() and proc.poll() is None:
        assert time.monotonic() < deadline
        time.sleep(0.05)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err[-2000:]
    assert "Traceback" not in err
    (line,) = [ln for ln in err.splitlines() if ln.startswith("cancelled after")]
    n = int(line.split()[2])
    frames = sorted(p.name for p in out.glob("*.exr"))
    assert 1 <= n < 400 and frames == [f"{i:04d}.exr" for i in range(1, n + 1)]
    for name in frames:  # every finished frame is complete
        assert exr.read_multilayer(out / name)["Diffuse Indirect"].shape[:2] == (24, 32)
    stats = json.loads((out / "stats.json").read_text())
    assert stats["cancelled"] is True and [f["frame"] for f in stats["frames"]] == list(
        range(1, n + 1))
    assert not list(out.glob(".*"))


def _dead_pid() -> int:
    child = subprocess.Popen(["true"])
    child.wait()
    return child.pid


def test_a_killed_runs_temporary_files_are_removed_by_the_next_run(tmp_path):
    """The hidden files of an interrupted atomic write (.NAME.PID[.HEX].tmp) go when their
    process is gone; a live process's and other files stay. Also: --preset, with --set on
    top."""
    out = tmp_path / "out"
    out.mkdir()
    dead, live = _dead_pid(), os.getpid()
    stale = [f".0001.exr.{dead}.0123abcd.tmp", f".stats.json.{dead}.tmp"]
    kept = [f".0002.exr.{live}.0123abcd.tmp", ".notes.tmp", "notes.txt"]
    for name in stale + kept:
        (out / name).write_bytes(b"partial")
    proc = _cli("--demo", "--out", str(out), "--resolution", "32x24", "--preset", "draft",
                "--set", "rsm_resolution=32")
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert sorted(p.name for p in out.iterdir()) == sorted(["0001.exr", "stats.json", *kept])
    settings = json.loads((out / "stats.json").read_text())["settings"]
    assert (settings["grid_resolution"], settings["cascades"]) == (16, 3)  # Draft: 16^3 grid
    assert settings["rsm_resolution"] == 32



STILL_SCRIPT = r"""
import sys
import bpy
from lpv_addon.scene_io import demo
demo.cornell_box("SPOT", resolution=(32, 24))
scene = bpy.context.scene
scene.frame_start, scene.frame_end, scene.frame_step = 1, 3, 2
scene.frame_current = 2
scene.render.filepath = "//render/shot_"
bpy.ops.wm.save_as_mainfile(filepath=sys.argv[1])
"""


def test_a_blend_renders_its_current_frame_to_the_render_output_path(tmp_path):
    """As `blender -b file.blend -f N` / `-a`: the current frame unless --frames or
    --animation (the scene's range and step) say otherwise; without --out the frames go
    where the render output path puts them ('//' is the .blend's folder)."""
    blend = tmp_path / "shot.blend"
    proc = subprocess.run([sys.executable, "-c", STILL_SCRIPT, str(blend)], cwd=ROOT,
                          capture_output=True, text=True, check=False, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    proc = _cli(str(blend), *SMALL, cwd=tmp_path.parent)
    assert proc.returncode == 0, proc.stderr[-2000:]
    render = tmp_path / "render"
    assert sorted(p.name for p in render.iterdir()) == ["shot_0002.exr", "stats.json"]
    assert [f["frame"] for f in json.loads((render / "stats.json").read_text())["frames"]] == [2]
    anim = tmp_path / "anim"
    proc = _cli(str(blend), "--animation", "--out", str(anim), *SMALL)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert sorted(p.name for p in anim.glob("*.exr")) == ["0001.exr", "0003.exr"]


def test_ctrl_c_while_a_frames_record_is_written_keeps_the_record(tmp_path, monkeypatch):
    """Ctrl-C arriving as the first frame's record reaches stats.json (here: sent from inside
    the write, as it would land during its fsync) stops the batch after that frame: the EXR
    and the record stay together (the tail written on cancel once overwrote the record)."""
    bpy = pytest.importorskip("bpy")
    from lpv_addon.render import frames
    from lpv_addon.scene_io import demo

    demo.cornell_box("SPOT", resolution=(32, 24))
    real, sent = frames.StatsFile._write_at, []

    def write_then_ctrl_c(self, offset, data):
        real(self, offset, data)
        if b'"frame": 1' in data and not sent:
            sent.append(True)
            # to the main thread itself: a process-wide signal may land on a kernel's or
            # the GL driver's thread, and Python then runs the handler only later
            signal.pthread_kill(threading.main_thread().ident, signal.SIGINT)

    monkeypatch.setattr(frames.StatsFile, "_write_at", write_then_ctrl_c)
    # Python's own Ctrl-C handler, also where this process inherited SIGINT ignored (started
    # as a shell's background job), where Ctrl-C could not reach a batch at all
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        job = frames.BatchJob(bpy.context.scene, tmp_path / "out", (1, 3),
                              overrides={"grid_resolution": 8, "rsm_resolution": 32,
                                         "antialias": 1}, in_process=True)
        with pytest.raises(KeyboardInterrupt):
            job.run()
    finally:
        signal.signal(signal.SIGINT, previous)
    assert sent
    stats = json.loads((tmp_path / "out" / "stats.json").read_text())
    assert stats["cancelled"] is True and [f["frame"] for f in stats["frames"]] == [1]
    assert sorted(p.name for p in (tmp_path / "out").glob("*.exr")) == ["0001.exr"]
