"""Extension packaging: the manifest validates, the zip holds the right files, and Blender
installs, enables and disables it headless. Uses Blender's real tool and a real bpy."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import pytest

from tools.build_extension import build_all, build_extension, find_blender_ext, validate
from tools.fetch_wheels import fetch_wheels, manifest_wheels, missing_wheels, wheel_path

ROOT = Path(__file__).resolve().parents[1]
MANIFEST = tomllib.loads((ROOT / "blender_manifest.toml").read_text())
MODULE = f"bl_ext.user_default.{MANIFEST['id']}"


@pytest.fixture(scope="session")
def wheels() -> list[Path]:
    """The manifest's wheels on disk; fetched once if the set-up step did not do it."""
    if missing_wheels(ROOT):
        fetch_wheels(ROOT, quiet=True)
    return [wheel_path(s, ROOT) for s in manifest_wheels()]


@pytest.fixture(scope="session")
def ext_zip(wheels: list[Path], tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One all-platform build into a temp dir (never the repo's dist/)."""
    return build_extension(tmp_path_factory.mktemp("dist"))


def _zip_names(path: Path) -> set[str]:
    with zipfile.ZipFile(path) as zf:
        return set(zf.namelist())


def test_blender_ext_found_in_bpy() -> None:
    tool = find_blender_ext()
    assert tool.name == "blender_ext.py" and tool.is_file()


def test_validate_passes() -> None:
    assert "Success" in validate(ROOT)


# Wheels of the optional compiled CPU kernels (lpv_core/jit.py falls back to numpy without).
OPTIONAL = {"numba", "llvmlite"}
# The Pythons the supported Blenders embed: 3.11 (4.2 LTS to 5.0) and 3.13 (5.1 to 5.3).
PYTHONS = ("cp311", "cp313")


def test_manifest_wheels_fetched(wheels: list[Path]) -> None:
    """fetch_wheels and the manifest agree: every listed wheel is on disk under wheels/."""
    listed = MANIFEST["wheels"]
    assert len(listed) == len(wheels) > 0
    for rel, path in zip(listed, wheels):
        assert rel.startswith("./wheels/"), rel
        assert path.is_file() and path.name == Path(rel).name
        assert zipfile.is_zipfile(path), f"{path.name} is not a valid wheel archive"
    # Every (package, platform, Python) triple is covered, with one version per package; the
    # optional compiled kernels (numba, llvmlite: no wheel for Intel macOS) on every other
    # platform.
    specs = manifest_wheels()
    for name in {s.name for s in specs}:
        assert len({s.version for s in specs if s.name == name}) == 1, name
        for py in PYTHONS:
            count = len(MANIFEST["platforms"]) - (1 if name in OPTIONAL else 0)
            assert len([s for s in specs if s.name == name and s.python_tag == py]) == count, (
                name, py)
    assert OPTIONAL <= {s.name for s in specs}
    assert {s.python_tag for s in specs} == set(PYTHONS)


def test_zip_contents(ext_zip: Path, wheels: list[Path]) -> None:
    names = _zip_names(ext_zip)
    for required in (
        "blender_manifest.toml",
        "__init__.py",
        "lpv_core/scene/model.py",
        "lpv_addon/properties.py",
    ):
        assert required in names, required
    assert {f"wheels/{w.name}" for w in wheels} == {n for n in names if n.startswith("wheels/")}
    banned = ("tests/", "docs/", "tools/", ".venv/", ".cache/", ".ci/", ".git", "dist/", "out/")
    leaked = sorted(n for n in names if n.startswith(banned) or "__pycache__" in n)
    assert not leaked, leaked
    assert "pyproject.toml" not in names
    # Measurement tools (benchmarks, report, stability suite) are not shipped.
    tools = sorted(n for n in names if Path(n).name in ("bench.py", "report.py", "stability.py")
                   or Path(n).name.startswith("bench_") or Path(n).name.endswith("_bench.py"))
    assert not tools, tools


def test_split_platforms(wheels: list[Path], tmp_path: Path) -> None:
    """--split-platforms: one zip per platform, each holding only that platform's wheels."""
    zips = build_all(tmp_path, split_platforms=True)
    assert len(zips) == len(MANIFEST["platforms"])
    for z, platform in zip(zips, MANIFEST["platforms"]):
        whl = [n for n in _zip_names(z) if n.startswith("wheels/")]
        names = {s.name for s in manifest_wheels()}
        if platform == "macos-x64":
            names -= OPTIONAL
        assert len(whl) == len(names) * len(PYTHONS), (platform, whl)
        for py in PYTHONS:  # both Pythons' wheels in every platform's zip
            assert {Path(n).name.split("-")[0] for n in whl if f"-{py}-" in n} == names, (platform, py)


_INSTALL_SCRIPT = r"""
import json, os, sys
import bpy
import addon_utils

zip_path, module = sys.argv[1], sys.argv[2]
out = {}
ret = bpy.ops.extensions.package_install_files(
    filepath=zip_path, repo="user_default", enable_on_install=True)
out["install"] = sorted(ret)
out["enabled"] = module in bpy.context.preferences.addons
out["loaded"] = addon_utils.check(module)[1]
out["has_lpv"] = hasattr(bpy.context.scene, "lpv")
out["intensity"] = bpy.context.scene.lpv.intensity if out["has_lpv"] else None
site = os.path.join(bpy.utils.user_resource("EXTENSIONS"), ".local", "lib",
                    "python%d.%d" % sys.version_info[:2], "site-packages")
out["site_packages"] = sorted(os.listdir(site)) if os.path.isdir(site) else []
addon_utils.disable(module, default_set=True)
out["enabled_after"] = module in bpy.context.preferences.addons
out["has_lpv_after"] = hasattr(bpy.types.Scene, "lpv")
print("RESULT=" + json.dumps(out))
"""


def test_install_enable_disable(ext_zip: Path, tmp_path: Path) -> None:
    """Install the zip in a fresh headless bpy (own user dir), enable, then disable."""
    env = dict(os.environ)
    env["BLENDER_USER_RESOURCES"] = str(tmp_path / "blender_user")
    env["MESA_SHADER_CACHE_DIR"] = str(tmp_path / "mesa_cache")
    proc = subprocess.run(
        [sys.executable, "-c", _INSTALL_SCRIPT, str(ext_zip), MODULE],
        check=False, capture_output=True, text=True, cwd=tmp_path, env=env, timeout=120,
    )
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT=")]
    assert proc.returncode == 0 and lines, proc.stdout + proc.stderr
    out = json.loads(lines[-1][len("RESULT="):])
    assert out["install"] == ["FINISHED"]
    assert out["enabled"] and out["loaded"], out
    assert out["has_lpv"] and out["intensity"] == 1.0, out
    # The wheels for this platform were unpacked into Blender's shared extension site-packages.
    if sys.platform.startswith("linux") and "linux-x64" in MANIFEST["platforms"]:
        for spec in manifest_wheels():
            assert f"{spec.name}-{spec.version}.dist-info" in out["site_packages"], out
    assert not out["enabled_after"], out
    assert not out["has_lpv_after"], out
