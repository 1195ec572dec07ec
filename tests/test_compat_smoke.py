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
TIMEOUT = 900  # a child compiles every kernel (background warm-up) on a cold cache
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


class _Run:
    """A child process, started on ``start()`` (or when first waited for), its output
    collected in a log file."""

    def __init__(self, cmd: list[str], cwd: Path, env: dict, log_path: Path):
        self.cmd, self.cwd, self.env, self.log_path = cmd, cwd, env, log_path
        self.proc: subprocess.Popen | None = None

    def start(self) -> None:
        if self.proc is None:
            self._log = open(self.log_path, "w")  # noqa: SIM115 - closed in wait()
            self.proc = subprocess.Popen(self.cmd, cwd=self.cwd, env=self.env,
                                         stdout=self._log, stderr=subprocess.STDOUT)

    def wait(self) -> tuple[int, str]:
        self.start()
        try:
            rc = self.proc.wait(timeout=TIMEOUT)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            rc = self.proc.wait()
        self._log.close()
        return rc, self.log_path.read_text()


@pytest.fixture(scope="module")
def runs(linux_zip: Path, tmp_path_factory: pytest.TempPathFactory):
    """The main venv's demo frame and every line's smoke run, two at a time on these 2-core
    machines (they are independent; most of their time is numba compiling the kernels in each
    worker): the reference and the first line start now, the rest once the reference is done."""
    started: dict = {}
    ref = tmp_path_factory.mktemp("reference")
    started["reference"] = (_Run(
        [sys.executable, "-m", "lpv_addon.batch", "--demo", "--out", str(ref / "frames"),
         "--quiet"], ROOT, {**_env(ref), "PYTHONPATH": str(ROOT)}, ref / "log.txt"), ref / "frames")
    for line, make in sorted(LINES.items()):
        tmp = tmp_path_factory.mktemp(f"bpy{line.replace('.', '')}")
        python = make(tmp)
        if not python.exists():
            started[line] = (None, python)
            continue
        out = tmp / "frames"
        started[line] = (_Run([str(python), str(ROOT / "tools" / "compat_smoke.py"),
                               str(linux_zip), str(out)], tmp, _env(tmp), tmp / "log.txt"), out)
    for key in ("reference", min(LINES)):
        if started[key][0] is not None:
            started[key][0].start()
    yield started
    for run, _ in started.values():
        if run is not None and run.proc is not None and run.proc.poll() is None:
            run.proc.kill()
            run.wait()


@pytest.fixture(scope="module")
def reference_frame(runs) -> Path:
    """The demo frame the main venv renders (its own moderngl/numba; bpy 5.3)."""
    run, out = runs["reference"]
    rc, log = run.wait()
    for other, _ in runs.values():
        if other is not None:
            other.start()
    assert rc == 0, log
    assert (out / "0001.exr").is_file(), log
    return out / "0001.exr"


@pytest.mark.parametrize("line", sorted(LINES))
def test_smoke(line: str, runs, reference_frame: Path) -> None:
    run, out = runs[line]
    if run is None:
        pytest.fail(f"{out} is missing: run `bash tools/setup.sh` (it makes .venv-bpy42)")
    rc, log = run.wait()
    lines = [ln for ln in log.splitlines() if ln.startswith("RESULT=")]
    log = log[-4000:]
    assert rc == 0 and lines, log
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
    assert res["f12"] == ["FINISHED"], log  # the LPV_GI render engine renders on this line
    # The batch frame's worker ran the compiled kernels (bundled numba) too.
    assert "numba" in json.dumps(res["stats"]), res["stats"]
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


def test_manifest_validates_with_the_oldest_supported_blender() -> None:
    """Blender 4.2 LTS's own extension tool (from .venv-bpy42's bpy) accepts the manifest, as
    the main venv's 5.3 does (tests/test_extension.py)."""
    if not BPY42.is_file():
        pytest.fail(f"{BPY42} is missing: run `bash tools/setup.sh` (it makes .venv-bpy42)")
    code = ("import sys; sys.path.insert(0, sys.argv[1]); "
            "from tools.build_extension import find_blender_ext, validate; "
            "print(find_blender_ext()); print(validate())")
    proc = subprocess.run([str(BPY42), "-c", code, str(ROOT)], capture_output=True, text=True,
                          timeout=TIMEOUT, env=_env(ROOT / ".cache"), check=False)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    tool, *rest = proc.stdout.splitlines()
    assert "/bpy/4.2/" in tool, tool
    assert "Success" in "\n".join(rest), proc.stdout
