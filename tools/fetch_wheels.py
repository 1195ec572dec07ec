"""Download exactly the wheels listed in blender_manifest.toml into wheels/.

The manifest is the single source of truth: each listed file name gives the package name,
version, Python tag and platform tags, which become one `pip download` call. Files already
present are skipped. Exits non-zero if any listed wheel could not be fetched.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import tomllib
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MANIFEST = ROOT / "blender_manifest.toml"


@dataclass(frozen=True)
class WheelSpec:
    """One wheel listed in the manifest, split into the parts pip needs."""

    relpath: str  # As written in the manifest, e.g. "./wheels/x.whl".
    filename: str
    name: str
    version: str
    python_tag: str  # e.g. "cp311".
    platforms: tuple[str, ...]  # Compressed tag set split on ".", e.g. ("win_amd64",).

    @property
    def python_version(self) -> str:
        """Python version for `pip download --python-version`: cp311 -> 3.11."""
        digits = self.python_tag.lstrip("abcdefghijklmnopqrstuvwxyz")
        return f"{digits[0]}.{digits[1:]}" if len(digits) > 1 else digits

    @property
    def implementation(self) -> str:
        """Implementation for `pip download --implementation`: cp311 -> cp."""
        return self.python_tag.rstrip("0123456789")


def parse_wheel_filename(relpath: str) -> WheelSpec:
    """Split a wheel path from the manifest into name/version/tags (PEP 427 file names)."""
    filename = Path(relpath).name
    if not filename.endswith(".whl"):
        raise ValueError(f"not a wheel file name: {relpath!r}")
    parts = filename[: -len(".whl")].split("-")
    if len(parts) == 6:  # Optional build tag: name-ver-build-py-abi-plat.
        parts = parts[:2] + parts[3:]
    if len(parts) != 5:
        raise ValueError(f"cannot parse wheel file name: {relpath!r}")
    name, version, python_tag, _abi, platform = parts
    return WheelSpec(
        relpath=relpath,
        filename=filename,
        name=name,
        version=version,
        python_tag=python_tag.split(".")[0],
        platforms=tuple(platform.split(".")),
    )


def manifest_wheels(manifest: Path = MANIFEST) -> list[WheelSpec]:
    """Return the wheels the manifest lists, parsed from their file names."""
    with open(manifest, "rb") as fh:
        data = tomllib.load(fh)
    return [parse_wheel_filename(p) for p in data.get("wheels", [])]


def wheel_path(spec: WheelSpec, root: Path = ROOT) -> Path:
    """Where a listed wheel lives on disk (manifest paths are relative to the repo root)."""
    return (root / spec.relpath).resolve()


def missing_wheels(root: Path = ROOT, manifest: Path | None = None) -> list[WheelSpec]:
    """Listed wheels that are not on disk yet."""
    specs = manifest_wheels(manifest or root / "blender_manifest.toml")
    return [s for s in specs if not wheel_path(s, root).is_file()]


def _download(spec: WheelSpec, dest: Path) -> tuple[bool, str]:
    """Run one `pip download` into a scratch dir and move the exact listed file to `dest`."""
    with tempfile.TemporaryDirectory(prefix="lpv_wheel_") as tmp:
        cmd = [
            sys.executable, "-m", "pip", "download", f"{spec.name}=={spec.version}",
            "--only-binary=:all:", "--no-deps", "--disable-pip-version-check",
            "--python-version", spec.python_version,
            "--implementation", spec.implementation,
            "-d", tmp,
        ]
        for plat in spec.platforms:
            cmd += ["--platform", plat]
        proc = subprocess.run(cmd, check=False, capture_output=True, text=True)
        got = Path(tmp) / spec.filename
        if proc.returncode != 0 or not got.is_file():
            found = sorted(p.name for p in Path(tmp).glob("*.whl"))
            detail = proc.stderr.strip().splitlines()[-1:] if proc.returncode else []
            why = detail[0] if detail else f"pip fetched {found or 'nothing'} instead"
            return False, why
        dest.parent.mkdir(parents=True, exist_ok=True)
        got.replace(dest)
        return True, ""


def fetch_wheels(root: Path = ROOT, quiet: bool = False) -> list[Path]:
    """Download every missing listed wheel; return all listed wheel paths.

    Raises RuntimeError naming each wheel that could not be fetched.
    """
    specs = manifest_wheels(root / "blender_manifest.toml")
    failures: list[str] = []
    for spec in specs:
        dest = wheel_path(spec, root)
        if dest.is_file():
            if not quiet:
                print(f"present  {spec.relpath}")
            continue
        ok, why = _download(spec, dest)
        if ok:
            if not quiet:
                print(f"fetched  {spec.relpath}")
        else:
            failures.append(f"{spec.filename}: {why}")
    if failures:
        raise RuntimeError(
            "could not fetch wheels listed in blender_manifest.toml:\n  " + "\n  ".join(failures)
        )
    return [wheel_path(s, root) for s in specs]


def main(argv: list[str] | None = None) -> int:
    """CLI entry: fetch the wheels, print what happened, return the exit code."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("-q", "--quiet", action="store_true", help="only print errors")
    args = parser.parse_args(argv)
    try:
        fetch_wheels(quiet=args.quiet)
    except (RuntimeError, OSError, ValueError, tomllib.TOMLDecodeError) as ex:
        print(f"fetch_wheels: error: {ex}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
