"""First run of the installed extension in a fresh Blender user folder (tools/first_run_bench.py,
behaviour only; the bench prints the times): with an empty kernel cache the first LPV result
comes from the numpy reference while the kernels compile in the background, and the stats lines
say so; once compiled the next update runs on them; the cache lies in Blender's user folder for
the extension, nothing inside the extension; after installing the zip again the first result
comes from the cached kernels, with the same numbers as the numpy reference's."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

pytest.importorskip("bpy")
pytestmark = [pytest.mark.bpy, pytest.mark.skipif(
    os.environ.get("LPV_JIT") == "0", reason="LPV_JIT=0: no kernels to compile")]


@pytest.fixture(scope="module")
def first_run(tmp_path_factory):
    from tools.build_extension import build_extension
    from tools.first_run_bench import run

    return run(build_extension(tmp_path_factory.mktemp("dist")))


def test_cold_cache_serves_numpy_while_compiling(first_run):
    cold = first_run["cold"]
    assert cold["cpu_kernels"] == "numpy"
    assert cold["kernels"]["state"] == "compiling"
    assert any(ln.startswith("compiling CPU kernels") for ln in cold["lines"]), cold["lines"]


def test_compiled_kernels_take_over(first_run):
    done = first_run["compile"]
    assert done["kernels"]["state"] == "ready" and done["kernels"]["error"] == ""
    assert 0 < done["kernels"]["compiled"] <= done["kernels"]["of"]
    assert done["cpu_kernels"].startswith("numba")


def test_cache_is_in_the_user_folder_not_the_extension(first_run):
    user = Path(first_run["user_folder"], "extensions", ".user", "user_default", "lpv_gi")
    cache = Path(first_run["kernel_cache"])
    assert cache.is_relative_to(user)
    assert not cache.is_relative_to(first_run["extension_dir"])
    assert first_run["cache_files"] > 0
    assert first_run["extension_cache_files"] == first_run["warm_extension_cache_files"] == 0


def test_reinstall_starts_warm_with_the_same_numbers(first_run):
    assert first_run["reinstall"][0] == ["FINISHED"]
    assert first_run["warm_kernel_cache"] == first_run["kernel_cache"]
    warm = first_run["warm"]
    assert warm["cpu_kernels"].startswith("numba") and warm["kernels"]["state"] == "ready"
    values = first_run["values"]  # numpy (cold) against compiled (warm), the same scene
    assert values["max"] > 0
    assert values["max_difference"] <= 1e-5 * values["max"]  # the twins' widest tolerance


def test_warm_up_of_a_scene_without_lamps(tmp_path):
    """A scene lit only by the World (no lamp) still warms up every kernel: the warm-up child
    adds the light types and a World it lacks, and ends with its kernels compiled."""
    import json
    import subprocess
    import sys

    import numpy as np

    from lpv_core.scene import World, make_scene
    from lpv_core.worker import save_scene

    tris = np.array([[[-2, -2, 0], [2, -2, 0], [2, 2, 0]], [[-2, -2, 0], [2, 2, 0], [-2, 2, 0]],
                     [[0, -1, 0], [0, 1, 0], [0, 1, 2]]], float)
    path = str(tmp_path / "scene.npz")
    save_scene(path, make_scene(tris, world=World("sky", np.ones((1, 1, 3), np.float32))))
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    child = subprocess.Popen([sys.executable, "-m", "lpv_core.worker", "--warm-up", path],
                             stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                             text=True, env=env)
    out = child.stdout.read()
    err = child.stderr.read()
    assert child.wait(timeout=600) == 0, err[-2000:]
    last = json.loads(out.strip().splitlines()[-1])
    assert last["compiled"] > 0, out
