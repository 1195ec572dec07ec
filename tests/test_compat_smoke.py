"""Compatibility smoke test per supported Blender line: bpy 4.2 LTS (Python 3.11, .venv-bpy42)
and bpy 5.3 (Python 3.13, the main .venv).

For each line: the Linux zip from `build_extension.py --split-platforms` is installed into a
fresh Blender user folder with `bpy.ops.extensions.package_install_files`, enabled, one LPV
update and one batch frame of the demo scene run (tools/compat_smoke.py), and the frame is
compared with the one the main venv renders with `python -m lpv_addon.batch --demo`.

What it exercises: each line's Python imports moderngl, glcontext, OpenEXR, numba and llvmlite
from the wheels Blender unpacked from the zip, not from a venv. .venv-bpy42 holds bpy and numpy
only; for 5.3 the main venv's bpy and its dependencies are linked into a bare venv made here
(the main venv's own moderngl and numba would shadow the bundled ones: installed wheels go to
one site-packages appended to sys.path, and whatever is importable first wins).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tomllib
import venv
from importlib import metadata
from pathlib import Path

import numpy as np
import pytest

from tools.build_extension import build_all

ROOT = Path(__file__).resolve().parents[1]
MANIFEST = tomllib.loads((ROOT / "blender_manifest.toml").read_text())
BUNDLED = ("moderngl", "glcontext", "OpenEXR", "numba", "llvmlite")
PASSES = ("Combined", "Diffuse Direct", "Diffuse Indirect", "Diffuse Color")
BPY42 = ROOT / ".venv-bpy42" / "bin" / "python"
TIMEOUT = 600
# Same numbers within float noise: the max abs difference over each channel's peak value.
TOLERANCE = 1e-4

pytestmark = pytest.mark.bpy


@pytest.fixture(scope="module")
def linux_zip(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The zip an artist on Linux installs (one zip per platform)."""
    if not sys.platform.startswith("linux"):
        pytest.skip("the smoke test installs the linux-x64 zip")
    zips = build_all(tmp_path_factory.mktemp("dist"), split_platforms=True)
    (z,) = [z for z in zips if z.name.endswith("-linux_x64.zip")]
    return z


def _env(tmp: Path) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}
    env["BLENDER_USER_RESOURCES"] = str(tmp / "blender_user")
    env["MESA_SHADER_CACHE_DIR"] = str(tmp / "mesa_cache")
    env["PYTHONNOUSERSITE"] = "1"
    return env


@pytest.fixture(scope="module")
def reference_frame(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The demo frame the main venv renders (its own moderngl/numba; bpy 5.3)."""
    out = tmp_path_factory.mktemp("reference")
    proc = subprocess.run(
        [sys.executable, "-m", "lpv_addon.batch", "--demo", "--out", str(out), "--quiet"],
        cwd=ROOT, env={**_env(out), "PYTHONPATH": str(ROOT)}, capture_output=True,
        text=True, timeout=TIMEOUT, check=False)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert (out / "0001.exr").is_file()
    return out / "0001.exr"


def _bare_bpy_python(dest: Path) -> Path:
    """A bare venv of this interpreter holding links to bpy and its dependencies only."""
    venv.EnvBuilder(with_pip=False, symlinks=True).create(dest)
    site = dest / "lib" / f"python{sys.version_info[0]}.{sys.version_info[1]}" / "site-packages"
    todo, seen = ["bpy"], set()
    while todo:
        try:
            dist = metadata.distribution(todo.pop())
        except metadata.PackageNotFoundError:  # a dependency for other Pythons (a marker)
            continue
        name = dist.metadata["Name"].lower().replace("_", "-")
        if name in seen:
            continue
        seen.add(name)
        for req in dist.requires or []:
            if "extra ==" in req:
                continue
            dep = req.split(";")[0].strip()
            for sep in "<>=!~[ (":
                dep = dep.split(sep)[0]
            todo.append(dep)
        base = Path(dist.locate_file(""))
        for top in {f.parts[0] for f in dist.files or [] if f.parts and f.parts[0] != ".."}:
            link = site / top
            if not link.exists() and (base / top).exists():
                link.symlink_to(base / top)
    names = {p.name.split("-")[0].lower() for p in site.iterdir()}
    assert not names & {n.lower() for n in BUNDLED}, names
    return dest / "bin" / "python"


LINES = {"4.2": lambda tmp: BPY42, "5.3": lambda tmp: _bare_bpy_python(tmp / "bare_venv")}


def _read_exr(path: Path) -> dict[str, np.ndarray]:
    import OpenEXR

    with OpenEXR.File(str(path), separate_channels=True) as f:  # one part per layer
        return {name: np.asarray(ch.pixels, np.float64)
                for part in f.parts for name, ch in part.channels.items()}


@pytest.mark.parametrize("line", sorted(LINES))
def test_smoke(line: str, linux_zip: Path, reference_frame: Path, tmp_path: Path) -> None:
    python = LINES[line](tmp_path)
    if not python.exists():
        pytest.fail(f"{python} is missing: run `bash tools/setup.sh` (it makes .venv-bpy42)")
    out = tmp_path / "frames"
    proc = subprocess.run(
        [str(python), str(ROOT / "tools" / "compat_smoke.py"), str(linux_zip), str(out)],
        cwd=tmp_path, env=_env(tmp_path), capture_output=True, text=True, timeout=TIMEOUT,
        check=False)
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT=")]
    log = (proc.stdout + proc.stderr)[-4000:]
    assert proc.returncode == 0 and lines, log
    res = json.loads(lines[-1][len("RESULT="):])
    assert "error" not in res, res.get("traceback", res["error"]) + log
    assert ".".join(map(str, res["blender"][:2])) == line, res["blender"]
    assert res["install"] == ["FINISHED"], log
    assert res["enabled"] and res["loaded"] and res["has_lpv"], res
    # The bundled wheels, not a venv's, are what this Blender's Python imports.
    site = res["extension_site_packages"]
    for name in BUNDLED:
        assert (res["origins"][name] or "").startswith(site), (name, res["origins"][name])
    assert res["update"] == ["FINISHED"], log
    assert res["render_batch"] == ["FINISHED"], log
    assert res["frames"] == ["0001.exr"], res
    assert res["disabled"], res
    ours, ref = _read_exr(out / "0001.exr"), _read_exr(reference_frame)
    assert sorted(ours) == sorted(ref)
    errors = {}
    for layer in PASSES:
        names = sorted(n for n in ref if f".{layer}." in f".{n}")
        assert names, (layer, sorted(ref))
        for name in names:
            a, b = ours[name], ref[name]
            assert a.shape == b.shape, name
            scale = max(float(np.abs(b).max()), 1e-6)
            errors[name] = float(np.abs(a - b).max()) / scale
    print(f"{line}: largest difference to the main venv's frame, relative to each channel's "
          f"peak: {max(errors.values()):.2e}")
    bad = {k: f"{v:.2e}" for k, v in errors.items() if not v < TOLERANCE}
    assert not bad, f"{line}: channels differ from the main venv's frame: {bad}"
