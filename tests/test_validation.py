"""Inputs no scene should carry: settings out of range are refused with the setting, the value
and the range; non-finite scene data is dropped or defaulted before any stage sees it (no NaN
or Inf leaves a stage); indirect light is linear in light power from 1e-30 to 1e30 W."""

from __future__ import annotations

import contextlib
import dataclasses

import numpy as np
import pytest

from lpv_core import engine, lookup
from lpv_core.runtime import jit
from lpv_core.scene import GISettings, make_scene
from tools import core_scenes as demo

# --------------------------------------------------------------------------------------------
# Linear in power (issue 19.6)
# --------------------------------------------------------------------------------------------


def _floor_points():
    xs = np.linspace(-0.8, 0.8, 5)
    x, y = np.meshgrid(xs, xs)
    p = np.c_[x.ravel(), y.ravel(), np.full(x.size, 1e-3)]
    return p, np.tile([0.0, 0.0, 1.0], (len(p), 1))


def _scaled(scene, factor: float):
    return dataclasses.replace(scene, lights=[dataclasses.replace(li, power=li.power * factor)
                                              for li in scene.lights])


@pytest.mark.parametrize("compiled", [True, False], ids=["compiled", "numpy"])
def test_indirect_light_is_linear_in_power_from_1e_30_to_1e30_watts(compiled):
    # The transport is linear: indirect light / power is the same number at any power, up to
    # float32 rounding (1e-5 relative), whether the flux is 1e-30 W or 1e30 W.
    if compiled and not jit.enabled():
        pytest.skip("numba is not installed")
    base = demo.cornell_box("POINT", settings=GISettings(grid_resolution=12, rsm_resolution=48,
                                                         backend="numpy"))
    p, n = _floor_points()
    eng = engine.Engine()

    def indirect(k):
        r = eng.update(_scaled(base, 10.0**k))
        e = lookup.irradiance(r.grid, r.values, p, n, angular="dom", visibility=r.visibility)
        assert np.all(np.isfinite(e))
        return e / 10.0**k

    with contextlib.nullcontext() if compiled else jit.disabled():
        ref = indirect(0)
        assert ref.min() > 0
        worst = {k: float(np.abs(indirect(k) - ref).max() / ref.max())
                 for k in range(-30, 31, 6) if k}
    print("\nrelative deviation of indirect / power from the 1 W case:",
          {k: f"{v:.1e}" for k, v in worst.items()})
    assert max(worst.values()) <= 1e-5, worst

