"""The batch CLI end to end: exit codes, EXR passes, stats.json shape, atomic outputs."""

import json
import subprocess
import sys

import numpy as np
import pytest
from conftest import ROOT

from lpv_core.render import exr


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "lpv_addon.batch", *args], cwd=ROOT,
                          capture_output=True, text=True, check=False)


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
    lines = [ln for ln in proc.stderr.splitlines() if ln.startswith("error")]
    assert len(lines) == 1 and message in lines[0], proc.stderr


def test_unreadable_file_exits_2(tmp_path):
    bad = tmp_path / "garbage.blend"
    bad.write_bytes(b"this is not a blend file")
    proc = _cli(str(bad), "--out", str(tmp_path / "o"))
    assert proc.returncode == 2
    assert "not a .blend file" in proc.stderr
