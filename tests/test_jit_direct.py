"""The compiled direct light (kernels.direct.irradiance) gives what the numpy code gives: every
light type, shadowed and not, receivers lit, unlit, in and out of the shadow maps' views."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("numba")

from conftest import surface_points

from lpv_core import engine
from lpv_core.render import direct
from lpv_core.runtime import jit
from lpv_core.scene import GISettings
from tools import core_scenes as demo

pytestmark = pytest.mark.skipif(not jit.enabled(), reason="LPV_JIT=0: the kernels are off")


def _receivers(scene, m: int, seed: int):
    """Points on the scene's triangles (shadowed and lit ones) and a few off them, with
    their face normals, some flipped (facing away from the light)."""
    rng = np.random.default_rng(seed)
    pos, nrm = surface_points(rng, scene.positions, m)
    nrm[rng.uniform(size=m) < 0.1] *= -1.0
    pos[: m // 20] += rng.normal(scale=3.0, size=(m // 20, 3))  # some far outside
    return pos, nrm


@pytest.mark.parametrize("kind", ["SPOT", "POINT", "SUN", "AREA"])
@pytest.mark.parametrize("shadowed", [True, False])
def test_compiled_direct_light_is_the_numpy_one(kind, shadowed):
    scene = demo.cornell_box(kind, (16, 16), GISettings())
    eng = engine.Engine()
    lo, hi = eng.upload(scene, engine.Stats())
    light = scene.lights[0]
    shadow = eng.shadow_map(scene, light, (lo, hi), 256) if shadowed else None
    pos, nrm = _receivers(scene, 20000, seed=len(kind) + shadowed)
    got = direct.irradiance(light, pos, nrm, shadow)
    with jit.disabled():
        want = direct.irradiance(light, pos, nrm, shadow)
    assert got.shape == want.shape == (pos.shape[0], 3)
    lit = want[:, 0] > 0
    assert 0.2 < lit.mean() < 1.0
    if shadowed:  # some of the lit side is in shadow: the maps are read
        with jit.disabled():
            free = direct.irradiance(light, pos, nrm, None)
        assert np.count_nonzero(free[:, 0] > want[:, 0] * (1 + 1e-6)) > 100
    np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-12 * want.max())
