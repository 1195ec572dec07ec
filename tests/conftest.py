"""Test isolation: Blender user resources, Mesa's shader cache and the auto-backend cache go
to a temp dir."""

import os
import sys
import tempfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
_TMP = Path(tempfile.mkdtemp(prefix="lpv_test_"))
# Must happen before anything imports bpy: keeps tests out of the user's Blender config.
os.environ.setdefault("BLENDER_USER_RESOURCES", str(_TMP / "blender_user"))
os.environ.setdefault("MESA_SHADER_CACHE_DIR", str(_TMP / "mesa_cache"))
# backend "auto"'s choice (gl_backend.auto_backend) is cached on disk: never in the user's home
# (set, not setdefault; subprocesses such as the batch CLI inherit it).
os.environ["LPV_GI_CACHE_DIR"] = str(_TMP / "lpv_gi_cache")
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

# Cycles references and other expensive artefacts are cached here between runs.
CACHE = Path(os.environ.get("LPV_TEST_CACHE", ROOT / ".cache" / "tests"))


@pytest.fixture(scope="module")
def gl():
    """lpv_core.gl.backend with a working compute context, or the test is skipped."""
    try:
        from lpv_core.gl import backend as gl_backend

        gl_backend.backend().check()  # compiles and runs a compute shader
    except Exception as exc:  # noqa: BLE001 - no GL 4.3 context on this machine
        pytest.skip(f"no OpenGL 4.3 compute context: {exc}")
    return gl_backend


@pytest.fixture(scope="module")
def registered_addon():
    """The add-on registered in this process's bpy for a test module, unregistered after it."""
    import lpv_addon

    lpv_addon.register()
    yield
    lpv_addon.unregister()


def surface_points(rng, positions, m: int):
    """``m`` points spread uniformly over random triangles of ``positions`` (T*3, 3) and their
    unit face normals, drawn from ``rng``."""
    import numpy as np

    tri = positions.reshape(-1, 3, 3)
    pick = rng.integers(0, tri.shape[0], m)
    a, b = rng.uniform(size=(2, m, 1))
    flip = a + b > 1
    a, b = np.where(flip, 1 - a, a), np.where(flip, 1 - b, b)
    t = tri[pick]
    pos = t[:, 0] + a * (t[:, 1] - t[:, 0]) + b * (t[:, 2] - t[:, 0])
    nrm = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    return pos, nrm / np.linalg.norm(nrm, axis=1, keepdims=True)


def factory_scene(resolution):
    """Blender's factory file (the default cube, light, camera and World) rendering
    ``resolution`` at 100 %: the scene artists start from."""
    import bpy

    bpy.ops.wm.read_factory_settings(use_empty=False)
    sc = bpy.context.scene
    sc.render.resolution_x, sc.render.resolution_y = resolution
    sc.render.resolution_percentage = 100
    return sc


def lpv_and_cycles(tmp_path, scene, resolution, samples: int = 32, rgb: bool = False,
                   **cycles_settings):
    """(LPV's passes, Cycles' passes, the extracted core scene) of the bpy ``scene``: Cycles
    (render_cycles_passes, one diffuse bounce, ``cycles_settings``) into ``tmp_path``, then
    LPV at the scene's settings; passes float64, (H, W, 3) with ``rgb``."""
    import bpy
    import numpy as np

    import lpv_core as core
    from lpv_addon.render import cycles
    from lpv_addon.scene_io.extract import extract_scene
    from tools import report

    exr = tmp_path / "cycles.exr"
    cycles.render_cycles_passes(str(exr), samples=samples, resolution=resolution,
                                **cycles_settings)
    core_scene = extract_scene(bpy.context.evaluated_depsgraph_get(), scene, resolution)
    eng = report._make_engine(core.render.raster.Rasterizer())
    ours = report.run_lpv(core_scene, core_scene.settings, eng, 1)["passes"]
    keep = slice(0, 3) if rgb else slice(None)
    return ({k: np.asarray(v, np.float64)[..., keep] for k, v in ours.items()},
            {k: np.asarray(v, np.float64)[..., keep]
             for k, v in report._read_exr(str(exr)).items()}, core_scene)
