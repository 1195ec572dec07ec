"""The render's sub-pixel samples (deferred.render, settings.antialias): each pass is the mean
over an s x s grid in the pixel, i.e. the box-filtered image of s times the resolution."""

import numpy as np
import pytest

from lpv_core import deferred, demo, engine
from lpv_core.scene import GISettings


def test_antialias_is_the_box_filtered_finer_image():
    eng = engine.Engine()
    coarse = demo.cornell_box("SPOT", (16, 12), GISettings(antialias=2))
    fine = demo.cornell_box("SPOT", (32, 24), GISettings(antialias=1))
    got = deferred.render(eng, coarse, eng.update(coarse))
    ref = deferred.render(eng, fine, eng.update(fine))
    edge = 0
    for name, arr in got.items():
        box = ref[name].reshape(12, 2, 16, 2, -1).mean(axis=(1, 3))
        assert arr.shape == box.shape and arr.dtype == np.float32
        np.testing.assert_allclose(arr, box, atol=1e-5 * np.abs(box).max(), err_msg=name)
        if name == "Diffuse Color":  # pixels where a red or green wall meets a white one
            red = ref[name][..., 0] - ref[name][..., 1]  # (24, 32): 0.7 red, -0.7 green, 0 white
            samples = red.reshape(12, 2, 16, 2)
            edge = int((samples.max(axis=(1, 3)) - samples.min(axis=(1, 3)) > 0.5).sum())
    assert edge > 0  # the test covers pixels that one centre sample would alias


def test_antialias_does_not_touch_the_lpv():
    eng = engine.Engine()
    scene = demo.cornell_box("SPOT", (8, 8), GISettings(antialias=1))
    eng.update(scene)
    stats = engine.Stats()
    eng.update(demo.cornell_box("SPOT", (8, 8), GISettings(antialias=3)), stats)
    assert "rsm" not in stats.ms and "propagation" not in stats.ms
    assert any(s["stage"] == "rsm" and "reused" in s["reason"] for s in stats.skipped)


@pytest.mark.parametrize("bad", [0, deferred.MAX_ANTIALIAS + 1, 1.5])
def test_bad_antialias_is_named(bad):
    eng = engine.Engine()
    scene = demo.cornell_box("SPOT", (8, 8), GISettings(antialias=bad))
    with pytest.raises(ValueError, match="antialias"):
        deferred.render(eng, scene, eng.update(scene))
