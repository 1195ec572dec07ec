"""Stability suite invariants (tools/stability.py) at the suite's "test" sizes, at the engine's
default settings (the "dom" transport, solved by the sweep).

One run of every case (a few seconds) feeds all assertions. Tolerances and their reasons are
in tools.stability.TOLERANCES: the engine is covariant under scaling and translation and
linear in light power and (one bounce) albedo in exact arithmetic; float32 rounding remains.
Energy: every propagation the engine runs is re-stepped (stability.energy_balance); a step
never carries more flux than it started from, and what the engine returned is the sum of the
steps to TOL["energy"] (1e-5): a transport that gains 1 % anywhere fails.
"""

import math

import numpy as np
import pytest

from lpv_core import propagation
from tools import stability

TOL = stability.TOLERANCES


@pytest.fixture(scope="module")
def suite():
    return {f["name"]: f for f in stability.run_suite("test")}


def _rows(suite, name):
    rows = suite[name]["rows"]
    assert rows, name
    return rows


def test_every_case_reports_the_four_measures(suite):
    assert set(suite) == {c.__name__[len("case_"):] for c in stability.CASES}
    for f in suite.values():
        for r in f["rows"]:
            for key in ("nonfinite", "energy_growth", "energy_balance", "deviation", "time_s"):
                assert key in r, (f["name"], r["label"], key)
            assert r["time_s"] >= 0


def test_no_nan_or_inf_in_grids_or_passes(suite):
    # float16 is the exception by design: it shows where an unscaled half-float grid overflows.
    for name, f in suite.items():
        if name == "float16":
            continue
        for r in f["rows"]:
            assert r["nonfinite"] == 0, (name, r["label"])
            assert r["deviation"] is not None and not math.isnan(r["deviation"]), (name, r)


def test_energy_never_grows_in_any_propagation_step(suite):
    for name, f in suite.items():
        for r in f["rows"]:
            assert r["energy_growth"] <= 1.0 + TOL["energy"], (name, r["label"],
                                                                r["energy_growth"])


def test_propagated_flux_is_the_sum_of_the_conserving_steps(suite):
    # flux(the engine's propagated grid) / sum of its steps' flux inside the grid (and the
    # outflow handed on / what the steps sent out): 1 up to float32 rounding.
    for name, f in suite.items():
        for r in f["rows"]:
            assert r["energy_balance"] <= TOL["energy"], (name, r["label"], r["energy_balance"])


def test_every_engine_run_had_its_propagations_measured(suite):
    # The energy measures mean something only where the engine's propagations went through
    # record_propagations: every engine row (energy and float16 step grids directly).
    for name, f in suite.items():
        if name in ("energy", "float16"):
            continue
        for r in f["rows"]:
            nothing = name == "albedo" and r["x"] == 0.0  # no light leaves a black surface
            assert (r["propagations"] == 0) if nothing else r["propagations"] > 0, (name, r)


@pytest.mark.parametrize("case", ["scale", "translation"])
def test_scale_and_translation_invariance(suite, case):
    # Covers scales 1e-3 .. 1e4 and offsets up to 1e6 m.
    xs = [r["x"] for r in _rows(suite, case)]
    assert (min(xs), max(xs)) == ((1e-3, 1e4) if case == "scale" else (1.0, 1e6))
    for r in _rows(suite, case):
        assert r["deviation"] <= TOL[case], (case, r["label"], r["deviation"])
        assert r["deviation_direct"] <= TOL["direct"], (case, r["label"])


def test_linear_in_light_power_from_1e_minus_6_to_1e9_watts(suite):
    rows = _rows(suite, "power")
    assert min(r["x"] for r in rows) == 1e-6 and max(r["x"] for r in rows) == 1e9
    for r in rows:
        assert r["deviation"] <= TOL["power"], (r["label"], r["deviation"])
        assert r["deviation_direct"] <= TOL["power"], r["label"]


def test_linear_in_albedo_and_no_gi_at_albedo_zero(suite):
    rows = {r["x"]: r for r in _rows(suite, "albedo")}
    assert rows[0.0]["deviation"] == 0.0  # exactly nothing bounces
    assert rows[1.0]["nonfinite"] == 0
    for a, r in rows.items():
        assert r["deviation"] <= TOL["albedo"], (a, r["deviation"])


def test_degenerate_triangles_are_dropped_or_harmless(suite):
    rows = {r["label"]: r for r in _rows(suite, "degenerate")}
    for label, key in (("zero-area", "zero_area_triangles"), ("collinear", "zero_area_triangles"),
                       ("NaN vertex", "nonfinite_vertices"), ("Inf vertex", "nonfinite_vertices")):
        assert rows[label]["dropped"][key] == 64, label
        assert rows[label]["deviation"] == 0.0, label
    # Kept but sub-pixel: they may cover a texel or pixel centre now and then.
    for label in ("needle (1e-7 m)", "tiny (1e-9 m)"):
        assert rows[label]["deviation"] <= 1e-2, (label, rows[label]["deviation"])


def test_duplicated_coplanar_triangles_change_nothing_without_occlusion(suite):
    rows = {r["label"]: r for r in _rows(suite, "coplanar")}
    assert rows["duplicated, same albedo"]["deviation"] <= 1e-3


def test_duplicated_coplanar_triangles_change_nothing_with_occlusion(suite):
    rows = {r["label"]: r for r in _rows(suite, "coplanar")}
    assert rows["duplicated, same albedo, occlusion"]["deviation"] <= 1e-3


def test_energy_traces_decay_for_every_propagation_mode(suite):
    traces = suite["energy"]["traces"]
    assert set(traces) == {"angular=dom", "angular=sh"}
    for mode, tr in traces.items():
        for name, t in tr.items():
            flux = np.asarray(t["flux"])
            assert len(flux) == 1001, (mode, name)
            assert t["nonfinite"] == 0, (mode, name)
            above = flux[:-1] > stability.FLUX_FLOOR  # float32 subnormals below
            assert np.all(flux[1:][above] <= flux[:-1][above] * (1 + TOL["energy"])), (mode,
                                                                                     name)
            assert t["max_growth"] <= 1 + TOL["energy"], (mode, name, t["max_growth"])
        assert tr["single VPL"]["flux"][-1] < 1e-3 * tr["single VPL"]["flux"][0]  # left the grid
    # dom counts what leaves the grid too: free space passes on all of it, to rounding.
    for name, t in traces["angular=dom"].items():
        assert t["max_growth"] >= 1 - TOL["energy"], (name, t["max_growth"])


def test_leak_cases_run_with_and_without_occlusion(suite):
    for case in ("thin_wall", "one_cell", "light_inside"):
        rows = _rows(suite, case)
        assert all(np.isfinite(r["deviation"]) and r["deviation"] >= 0 for r in rows), case
    labels = [r["label"] for r in _rows(suite, "thin_wall")]
    assert any("1 cells" in lab for lab in labels)  # the one-cell-thick wall


def test_float16_storage_is_close_in_range_and_flags_overflow_and_underflow(suite):
    rows = {r["x"]: r for r in _rows(suite, "float16")}
    assert rows[300.0]["deviation"] <= 1e-2  # 11-bit mantissa: ~5e-4 per rounding
    assert rows[300.0]["nonfinite"] == 0
    assert rows[1e9]["nonfinite"] > 0  # intensities beyond 65504 overflow to Inf
    assert rows[1e-6]["underflow"] > 0.5  # below 6e-8 they flush to zero


def test_grids_from_4_to_32_cells_run(suite):
    rows = _rows(suite, "grids")
    assert [r["x"] for r in rows] == [4, 8, 16, 32]
    assert all(r["indirect_mean"] > 0 for r in rows)


def _launched(r=6):
    from lpv_core import injection
    from lpv_core.grid import Grid

    g = Grid((0.0, 0.0, 0.0), 1.0, r)
    rng = np.random.default_rng(3)
    pos = rng.uniform(1.0, r - 1.0, size=(40, 3))
    nrm = rng.normal(size=(40, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    return injection.inject(g, pos, nrm, rng.uniform(0.5, 2.0, size=(40, 3)))


def test_energy_balance_of_a_free_grid_is_exact_and_sees_a_one_percent_gain():
    # The engine's call: launched from the surfaces, solved by the sweep, outflow kept.
    injected = _launched()
    res = propagation.propagate(injected, 0, angular="dom", launch=True,
                                capture_outflow=True, occlude_first_step=True)
    b = stability.energy_balance(injected, res)
    assert b["growth"] == pytest.approx(1.0, abs=TOL["energy"])  # free space: all passed on
    assert b["values"] == pytest.approx(1.0, abs=TOL["energy"])
    assert b["outflow"] == pytest.approx(1.0, abs=TOL["energy"])
    res.values *= np.float32(1.01)
    assert stability.energy_balance(injected, res)["values"] > 1 + 100 * TOL["energy"]


def test_record_propagations_measures_the_engines_calls_and_restores_propagate():
    original = propagation.propagate
    injected = _launched()
    vis = np.full((6,) + injected.shape[:3], 0.5, np.float32)  # half of every face absorbed
    with stability.record_propagations() as log:
        assert propagation.propagate is not original
        propagation.propagate(injected, 0, angular="dom", launch=True,
                              visibility=vis, occlude_first_step=True)
    assert propagation.propagate is original
    (b,), got = log["balances"], log["injected"]
    np.testing.assert_array_equal(got, injected)
    assert 0.4 < b["growth"] < 1.0  # absorbed: each step carries on less than it got
    assert b["values"] == pytest.approx(1.0, abs=TOL["energy"])
    with pytest.raises(ValueError, match="angular='dom'"), stability.record_propagations():
        propagation.propagate(injected, 2, angular="sh")


def test_rel_dev():
    a = np.array([1.0, 2.0])
    assert stability.rel_dev(a, a) == 0.0
    assert stability.rel_dev(a * 1.1, a) == pytest.approx(0.1)
    assert stability.rel_dev(np.zeros(2), np.zeros(2)) == 0.0
    assert stability.rel_dev(a, np.zeros(2)) == math.inf
    assert stability.rel_dev(np.array([np.nan, 2.0]), a) == pytest.approx(1 / 3)


def test_suite_settings_refuse_a_key_the_engine_does_not_have():
    # A retired or misspelt setting fails the suite instead of being left out silently.
    with pytest.raises(ValueError, match="unknown GI setting 'colour'"):
        stability.Runner("test").settings(colour=1)
    with pytest.raises(ValueError, match="'direction_groups'"):  # retired
        stability.Runner("test").settings(direction_groups=1)
    assert stability.Runner("test").settings().angular == "dom"  # the default transport
