"""Our batch renderer against Cycles' own passes on the team's scenes (real Cycles references).

References are rendered by tools/make_references.py (cached in .cache/tests by scene hash);
our frames come from the real CLI (`python -m lpv_addon.batch`) in a child process.
"""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import CACHE, ROOT

from lpv_core.render import error, exr

sys.path.insert(0, str(ROOT / "tools"))
from make_references import ensure_reference

RES = (96, 96)
SAMPLES = 512


def _render_ours(blend: Path, out: Path, *extra: str) -> dict:
    cmd = [sys.executable, "-m", "lpv_addon.batch", str(blend), "--out", str(out), "--frames",
           "1", "--resolution", f"{RES[0]}x{RES[1]}", "--quiet", *extra]
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, check=False)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return exr.read_multilayer(out / "0001.exr")


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    """(ours, cycles) passes per scene name, rendered once per test module."""
    cache = {}

    def get(name: str):
        if name not in cache:
            blend, ref = ensure_reference(name, CACHE / "references", samples=SAMPLES,
                                          bounces=1, resolution=RES)
            out = tmp_path_factory.mktemp(name)
            cache[name] = (_render_ours(blend, out), exr.read_multilayer(ref))
        return cache[name]

    return get


def _erode(mask: np.ndarray) -> np.ndarray:
    out = mask.copy()
    padded = np.pad(mask, 1)
    h, w = mask.shape
    for dy in (0, 1, 2):
        for dx in (0, 1, 2):
            out &= padded[dy:dy + h, dx:dx + w]
    return out


@pytest.mark.parametrize("name", ["cornell_spot", "cornell_point", "cornell_sun", "point_room"])
def test_diffuse_direct_matches_cycles_within_5_percent(pair, name):
    ours, ref = pair(name)
    a, b = ours["Diffuse Direct"][..., :3], ref["Diffuse Direct"][..., :3]
    # Lit: lit in both images, shadow edges excluded (pixels whose 8 neighbours are all lit):
    # at an edge one renderer's pixel filter and the other's shadow filter disagree by a pixel,
    # which says nothing about units.
    lit = _erode((a.mean(-1) > 1e-4) & (b.mean(-1) > 1e-4))
    assert lit.sum() > 40, "the scene should have lit pixels"
    ratio = a[lit].mean() / b[lit].mean()
    print(f"\n{name}: Diffuse Direct ours/Cycles over {lit.sum()} lit pixels = {ratio:.4f}")
    assert abs(ratio - 1.0) <= 0.05


def test_diffuse_color_matches_cycles(pair):
    ours, ref = pair("cornell_spot")
    diff = np.abs(ours["Diffuse Color"][..., :3] - ref["Diffuse Color"][..., :3])
    # Edges may differ by a pixel's coverage; the bulk must agree.
    assert np.median(diff) < 1e-3
    assert (diff.max(-1) > 0.05).mean() < 0.05


def _indirect_error(ours, ref):
    a, b = error.indirect_term(ours), error.indirect_term(ref)
    return error.relative_rmse(a, b), error.mean_ratio(a, b)


@pytest.mark.parametrize("name", ["cornell_spot", "cornell_point", "cornell_sun", "point_room"])
def test_indirect_energy_matches_cycles_within_a_factor_of_two(pair, name):
    ours, ref = pair(name)
    rmse, ratio = _indirect_error(ours, ref)
    print(f"\n{name} indirect: relative RMSE {rmse:.3f}, mean ours/Cycles {ratio:.3f}")
    assert 0.5 <= ratio <= 2.0


def test_indirect_relative_rmse_on_spot_lit_cornell_box_at_most_quarter(pair):
    """Issue 3: the Cornell box lit by a spot light, indirect relative RMSE <= 0.25."""
    ours, ref = pair("cornell_spot")
    rmse, ratio = _indirect_error(ours, ref)
    print(f"\ncornell_spot indirect: relative RMSE {rmse:.3f} (target 0.25), mean ratio {ratio:.3f}")
    assert rmse <= 0.25


def test_point_lit_room_indirect_relative_rmse_at_most_a_quarter(pair):
    """Issue 3: a room lit by a point light, indirect relative RMSE <= 0.25 vs Cycles."""
    ours, ref = pair("point_room")
    rmse, ratio = _indirect_error(ours, ref)
    print(f"\npoint_room indirect: relative RMSE {rmse:.3f} (target 0.25), mean ratio {ratio:.3f}")
    assert rmse <= 0.25


def _error_with(tmp_path, name: str, samples: int, **settings) -> float:
    """Indirect relative RMSE of the batch CLI with ``settings`` against a Cycles reference of
    ``samples`` spp (printed with the mean ratio)."""
    blend, ref_path = ensure_reference(name, CACHE / "references", samples=samples, bounces=1,
                                       resolution=RES)
    sets = [a for k, v in settings.items() for a in ("--set", f"{k}={v}")]
    rmse, ratio = _indirect_error(_render_ours(blend, tmp_path, *sets),
                                  exr.read_multilayer(ref_path))
    print(f"\n{name} {settings} vs Cycles {samples} spp: indirect relative RMSE {rmse:.3f} "
          f"(target 0.35), mean ratio {ratio:.3f}")
    return rmse


def test_sunlit_room_indirect_relative_rmse_at_most_0_35_with_a_finer_grid(tmp_path):
    """Issue 3: a room lit by the sun through a window (walls 0.2 m, camera inside), indirect
    relative RMSE <= 0.35 against Cycles: with a 32^3 grid and 4^2 samples per pixel (the
    defaults read ~0.39; over half- and quarter-cell shifts of the grid this setting reads
    0.325-0.358 against 4096 spp: docs/algorithm.md). The reference has 2048 spp: at 512 its
    own noise (~0.15) would dominate the comparison."""
    assert _error_with(tmp_path, "sunlit_room", 2048, grid_resolution=32, antialias=4) <= 0.35


def test_city_indirect_relative_rmse_at_most_0_35_with_fine_cascades(tmp_path):
    """Issue 3: the 200 m city (buildings 4-30 m, low sun), cascades on (3 picked), indirect
    relative RMSE <= 0.35 against Cycles: with 64^3 cascades and 4^2 samples per pixel (at
    the defaults, 16^3 and 2^2, it reads ~0.64: docs/algorithm.md)."""
    assert _error_with(tmp_path, "city", SAMPLES, grid_resolution=64, antialias=4) <= 0.35


def test_multiple_bounces_match_cycles_with_four_diffuse_bounces(tmp_path):
    """Issue 3: bounces = 4 against Cycles with four diffuse bounces, relative RMSE <= 0.3;
    and one bounce against the same reference is clearly worse (the bounces carry light)."""
    blend, ref_path = ensure_reference("cornell_spot", CACHE / "references", samples=SAMPLES,
                                       bounces=4, resolution=RES)
    ref = exr.read_multilayer(ref_path)
    multi = _render_ours(blend, tmp_path / "multi", "--set", "bounces=4")
    single = _render_ours(blend, tmp_path / "single")
    rmse, ratio = _indirect_error(multi, ref)
    rmse_1, ratio_1 = _indirect_error(single, ref)
    print(f"\ncornell_spot vs Cycles 4 bounces: bounces=4 relative RMSE {rmse:.3f} "
          f"(target 0.3), mean ratio {ratio:.3f}; bounces=1 {rmse_1:.3f}, ratio {ratio_1:.3f}")
    assert rmse <= 0.3
    assert ratio > ratio_1 + 0.2


def test_multiple_bounces_run_with_cascades_and_converge():
    """Bounces work on a cascade chain: more bounces add light in every cascade (the inner
    one as well as the outer), each bounce less than the last."""
    from lpv_core import engine
    from lpv_core.scene import GISettings
    from tools import core_scenes as demo

    fine, coarse = [], []
    for bounces in (1, 2, 3):
        settings = GISettings(grid_resolution=12, cascades_auto=False, cascades=2, bounces=bounces)
        scene = demo.cornell_box("SPOT", (32, 32), settings)
        res = engine.Engine().update(scene)
        assert len(res.fine) == 1
        assert all(np.isfinite(v).all() for _, v, _ in res.fine)
        fine.append(float(res.fine[0][1][..., 0].sum()))
        coarse.append(float(res.values[..., 0].sum()))
    print(f"\ncascaded LPV band-0 totals for 1, 2, 3 bounces: inner {fine}, outer {coarse}")
    for means in (fine, coarse):
        assert means[0] < means[1] < means[2]
        assert means[2] - means[1] < means[1] - means[0]
