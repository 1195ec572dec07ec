"""Validate and build the LPV GI extension zip with Blender's own `blender_ext.py`.

The tool ships inside the bpy wheel, so no Blender install is needed. Missing wheels are
fetched first (tools/fetch_wheels.py). Usage:
    python tools/build_extension.py [--split-platforms] [--output-dir DIR]
"""

from __future__ import annotations

import argparse
import importlib.util
import subprocess
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # Run as a script: make `tools` importable.
    sys.path.insert(0, str(ROOT))

from tools.fetch_wheels import fetch_wheels, missing_wheels


class BuildError(RuntimeError):
    """Blender's extension tool rejected the manifest or failed to build."""


def _bpy_scripts_dirs() -> list[Path]:
    """`<site-packages>/bpy/<X.Y>/scripts` folders of the importable bpy (without importing it)."""
    spec = importlib.util.find_spec("bpy")
    if spec is None:
        raise BuildError("bpy is not installed in this Python; install bpy (see pyproject.toml)")
    roots = list(spec.submodule_search_locations or [])
    if not roots and spec.origin:
        roots = [str(Path(spec.origin).parent)]
    return sorted((p for r in roots for p in Path(r).glob("*/scripts")), reverse=True)


def find_blender_ext() -> Path:
    """Locate Blender's `blender_ext.py` inside the installed bpy package."""
    for scripts in _bpy_scripts_dirs():
        tool = scripts / "addons_core" / "bl_pkg" / "cli" / "blender_ext.py"
        if tool.is_file():
            return tool
    raise BuildError("blender_ext.py not found in the bpy package (bpy/*/scripts/addons_core/...)")


def find_valid_tags() -> Path | None:
    """Blender's list of allowed tags, which Blender itself passes to `blender_ext.py`."""
    for scripts in _bpy_scripts_dirs():
        tags = scripts / "modules" / "_bpy_internal" / "extensions" / "tags.py"
        if tags.is_file():
            return tags
    return None


def _run_tool(args: list[str]) -> str:
    """Run blender_ext.py with this interpreter; return its output or raise BuildError."""
    cmd = [sys.executable, str(find_blender_ext()), *args]
    proc = subprocess.run(cmd, check=False, capture_output=True, text=True, cwd=ROOT)
    out = (proc.stdout + proc.stderr).strip()
    if proc.returncode != 0:
        raise BuildError(f"blender_ext.py {args[0]} failed (exit {proc.returncode}):\n{out}")
    return out


def _tags_args() -> list[str]:
    tags = find_valid_tags()
    return ["--valid-tags", str(tags)] if tags else []


def validate(source_dir: Path = ROOT) -> str:
    """Check the manifest the way Blender does (including the allowed-tags list)."""
    return _run_tool(["validate", str(source_dir), *_tags_args()])


def expected_zip_names(source_dir: Path = ROOT, split_platforms: bool = False) -> list[str]:
    """The file names blender_ext.py gives the zip(s): `<id>-<version>[-<platform>].zip`."""
    with open(source_dir / "blender_manifest.toml", "rb") as fh:
        manifest = tomllib.load(fh)
    stem = f"{manifest['id']}-{manifest['version']}"
    if not split_platforms:
        return [f"{stem}.zip"]
    return [f"{stem}-{p.replace('-', '_')}.zip" for p in manifest.get("platforms", [])]


def build_all(
    output_dir: Path | str | None = None,
    split_platforms: bool = False,
    source_dir: Path = ROOT,
) -> list[Path]:
    """Fetch missing wheels, validate, build; return the zip path(s)."""
    source_dir = Path(source_dir).resolve()
    out_dir = Path(output_dir).resolve() if output_dir else source_dir / "dist"
    out_dir.mkdir(parents=True, exist_ok=True)
    if missing_wheels(source_dir):
        fetch_wheels(source_dir, quiet=True)
    validate(source_dir)
    names = expected_zip_names(source_dir, split_platforms)
    for name in names:  # Never report a stale zip from an earlier build as this build's output.
        (out_dir / name).unlink(missing_ok=True)
    args = ["build", "--source-dir", str(source_dir), "--output-dir", str(out_dir), *_tags_args()]
    if split_platforms:
        args.append("--split-platforms")
    out = _run_tool(args)
    zips = [out_dir / n for n in names]
    missing = [z for z in zips if not z.is_file()]
    if missing:
        raise BuildError(f"build reported success but did not write {missing}:\n{out}")
    return zips


def build_extension(output_dir: Path | str | None = None, source_dir: Path = ROOT) -> Path:
    """Build the single all-platform zip and return its path."""
    return build_all(output_dir, split_platforms=False, source_dir=source_dir)[0]


def main(argv: list[str] | None = None) -> int:
    """CLI entry: print the zip path(s), or the tool's message and exit 1."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--split-platforms", action="store_true", help="one zip per platform")
    parser.add_argument("--output-dir", type=Path, default=None, help="default: <repo>/dist")
    args = parser.parse_args(argv)
    try:
        zips = build_all(args.output_dir, split_platforms=args.split_platforms)
    except (BuildError, RuntimeError, OSError) as ex:
        print(f"build_extension: error: {ex}", file=sys.stderr)
        return 1
    for z in zips:
        print(z)
    return 0


if __name__ == "__main__":
    sys.exit(main())
