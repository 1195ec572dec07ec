"""The error-vs-time report: sweep construction, error measures, curve helpers, and one
end-to-end run of the real command, `python -m tools.report --quick` (issue 5: part of the
tests and under 10 minutes; the Cornell box at 128x128, a 512-spp reference, the quick settings
sweep, Cycles at 1-256 spp, the stability suite at test sizes: about 70 s here on 2 cores).
"""

import dataclasses
import json
import math
import subprocess
import sys
import time

import numpy as np
import pytest
from conftest import CACHE, ROOT

from lpv_core.scene import GISettings
from tools import report

# ---------------------------------------------------------------------------------------------
# Sweep construction
# ---------------------------------------------------------------------------------------------


@dataclasses.dataclass
class _Extended(GISettings):
    """GISettings plus fields the report has never heard of."""

    new_flag: bool = False
    damping: float = 0.5
    taps: int = 3


def test_every_known_field_is_swept_and_new_fields_too():
    base = _Extended()
    swept = {(f, v) for f, v, _ in report.one_at_a_time(base, "full")}
    fields = {f for f, _ in swept}
    # Every quality setting GISettings has (a name it lacks fails here, not skipped).
    for name in ("grid_resolution", "iterations", "rsm_resolution", "occlusion", "bounces",
                 "cascades", "angular"):
        assert name in {f.name for f in dataclasses.fields(GISettings)}, name
        assert name in fields, name
    assert fields == {f.name for f in dataclasses.fields(base)} - report.NOT_SWEPT
    assert ("new_flag", True) in swept
    assert {("damping", 0.25), ("damping", 1.0)} <= swept
    assert {("taps", 1), ("taps", 6)} <= swept
    assert "intensity" not in fields  # an artist multiplier, not a quality setting
    # Every swept settings object differs from the base in exactly that field.
    for f, v, s in report.one_at_a_time(base, "full"):
        assert getattr(s, f) == v and report.settings_label(s, base) == f"{f}={v}"


def test_string_choices_come_from_lpv_core_constants():
    from lpv_core import propagation

    field = next(f for f in dataclasses.fields(GISettings) if f.name == "angular")
    assert set(report.sweep_values(field, "dom")) == set(propagation.ANGULAR_MODELS) - {"dom"}
    unknown = dataclasses.field(default="x")
    unknown.name = "no_such_setting_anywhere"
    assert report.sweep_values(unknown, "x") == []


def test_quick_and_smoke_sweeps_are_small():
    base = GISettings()
    full = report.one_at_a_time(base, "full")
    quick = report.one_at_a_time(base, "quick")
    smoke = report.one_at_a_time(base, "smoke")
    assert len(smoke) <= 2 < len(quick) <= len(full)
    assert len({f for f, _, _ in quick}) == len(quick)  # one alternative per field
    assert report.grid_iteration_pairs(base, "quick") == []
    assert len(report.grid_iteration_pairs(base, "full")) == 9
    q = report.PROFILES["quick"]
    assert len(q["scenes"]) == 1 and max(q["resolution"]) <= 128
    assert min(report.PROFILES["full"]["resolution"]) >= 256


# ---------------------------------------------------------------------------------------------
# Measures and curves
# ---------------------------------------------------------------------------------------------


def _passes(value, shape=(8, 8)):
    p = {k: np.full((*shape, 3), value, np.float32) for k in
         ("Diffuse Direct", "Diffuse Indirect")}
    p["Diffuse Color"] = np.full((*shape, 3), 0.5, np.float32)
    p["Combined"] = np.ones((*shape, 4), np.float32)
    p["Combined"][..., :3] = (p["Diffuse Direct"] + p["Diffuse Indirect"]) * 0.5
    return p


def test_errors_of_identical_and_scaled_images():
    ref = _passes(1.0)
    rng = np.random.default_rng(0)
    ref["Diffuse Indirect"] *= rng.uniform(0.5, 1.5, ref["Diffuse Indirect"].shape).astype(
        np.float32)
    same = report.errors(ref, ref)
    assert same["indirect"] == 0 and same["combined"] == 0
    assert same["flip"] == pytest.approx(0.0, abs=1e-6)
    twice = {k: v.copy() for k, v in ref.items()}
    twice["Diffuse Indirect"] = ref["Diffuse Indirect"] * 2
    e = report.errors(twice, ref)
    # Relative RMSE of 2x - x is RMS(x) / mean(x).
    x = report.indirect_term(ref)
    assert e["indirect"] == pytest.approx(np.sqrt((x ** 2).mean()) / x.mean())
    assert e["indirect_mean_ratio"] == pytest.approx(2.0)
    assert math.isnan(report.relative_rmse(np.ones(3), np.zeros(3)))


def test_pareto_front():
    rows = [{"label": n, "time_s": t, "indirect": e} for n, t, e in
            (("a", 1.0, 2.0), ("b", 2.0, 1.0), ("c", 3.0, 1.5), ("d", 0.5, 3.0), ("e", 4.0, 0.5))]
    assert [r["label"] for r in report.pareto_front(rows)] == ["d", "a", "b", "e"]


def test_cycles_curve_interpolation_and_extrapolation():
    curve = [{"time_s": 1.0, "indirect": 1.0, "samples": 1},
             {"time_s": 4.0, "indirect": 0.5, "samples": 4}]
    assert report.curve_at(curve, 0.5) == (None, "below")
    e, how = report.curve_at(curve, 2.0)
    assert how == "interpolated" and e == pytest.approx(math.sqrt(0.5))  # log-log midpoint
    e, how = report.curve_at(curve, 16.0)
    assert how == "extrapolated" and e == pytest.approx(0.25)  # error ~ time^-1/2
    e, how = report.curve_at(curve, 16.0, slope=1.0)
    assert e == pytest.approx(0.125)
    assert report.curve_at([], 1.0) == (None, "none")


@pytest.mark.parametrize("p", [0.5, 0.7])
def test_noise_fit_recovers_the_reference_noise_and_convergence_rate(p):
    s, m = 3.0, 1024
    curve = [{"samples": n, "indirect": s * math.sqrt(n ** (-2 * p) + m ** (-2 * p))}
             for n in (1, 4, 16, 64, 256)]
    floor, rate = report.noise_fit(curve, m)
    assert rate == pytest.approx(p, abs=0.01)
    assert floor == pytest.approx(s * m ** -p, rel=0.05)
    assert report.noise_floor(curve[:1], m) is None  # one usable point: no fit
    assert report.denoised(0.5, 0.3) == pytest.approx(0.4)
    assert report.denoised(0.2, 0.3) == 0.0 and report.denoised(0.2, None) == 0.2


def test_time_cap_interrupts_and_restores():
    import signal

    before = signal.getsignal(signal.SIGALRM)
    with pytest.raises(report.OverTimeCap), report._time_cap(0.05):
        time.sleep(1.0)
    assert signal.getsignal(signal.SIGALRM) == before
    with report._time_cap(0.5):
        pass
    time.sleep(0.6)  # disarmed: nothing fires


# ---------------------------------------------------------------------------------------------
# The command, end to end (tiny)
# ---------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    out = tmp_path_factory.mktemp("report")
    (out / "sources_other_tool.png").write_bytes(b"another tool's figure")  # must stay
    (out / "gone_scene_images.png").write_bytes(b"a stale figure of this report")  # replaced
    t0 = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, "-m", "tools.report", "--quick", "--out", str(out),
         "--cache", str(CACHE / "report"), "--fresh-cycles"],
        cwd=ROOT, capture_output=True, text=True, check=False, timeout=600)  # issue 5: < 10 min
    seconds = time.perf_counter() - t0
    assert proc.returncode == 0, proc.stderr[-3000:]
    print(f"\nreport --quick: {seconds:.1f} s")
    return out, proc, json.loads((out / "results.json").read_text())


def test_quick_report_writes_readme_figures_and_numbers(quick):
    out, proc, data = quick
    readme = (out / "README.md").read_text()
    for heading in ("## Verdict", "## Summary", "## cornell_spot", "Pareto front",
                    "## What each setting buys", "## Stability", "LPV time by stage"):
        assert heading in readme, heading
    assert ("Where LPV is worse than Cycles at equal time" in readme
            or "not worse than Cycles at equal time" in readme)
    pngs = sorted({p.name for pattern in report.OWN_FIGURES for p in out.glob(pattern)})
    assert "gone_scene_images.png" not in pngs  # the last run's figures are replaced
    assert (out / "sources_other_tool.png").read_bytes() == b"another tool's figure"
    assert {"cornell_spot_error_vs_time.png", "cornell_spot_images.png",
            "stability_invariance.png", "stability_energy.png"} <= set(pngs)
    for name in pngs:
        assert f"]({name})" in readme, name  # every figure is linked
        assert (out / name).stat().st_size > 1000
    (scene,) = data["scenes"]
    ok = [r for r in scene["lpv"] if "error" not in r]
    assert len(ok) >= 2
    for r in ok:
        for key in ("indirect", "combined", "flip", "time_s"):
            assert np.isfinite(r[key]) and r[key] >= 0, (r["label"], key)
        assert r["stages_ms"].get("propagation", 0) >= 0 and "rsm" in r["stages_ms"]
    curve = scene["cycles"]["1"]
    assert [c["samples"] for c in curve] == list(report.PROFILES["quick"]["cycles_samples"])
    assert all(c["time_s"] > 0 and np.isfinite(c["indirect"]) for c in curve)
    # Monte Carlo: more samples, less error (16x the samples: about 1/4 of the noise).
    assert curve[-1]["indirect"] < curve[0]["indirect"]
    assert data["stability"] and all(f["rows"] for f in data["stability"])
    # The peers (issue 21): denoised Cycles over its samples, EEVEE with ray tracing on and
    # off, KD10's SH over grid resolutions; each on Combined, with verdicts per peer.
    quick_prof = report.PROFILES["quick"]
    oidn = scene["peers"][report.PEER_OIDN]
    assert [c["samples"] for c in oidn] == list(quick_prof["denoised_samples"])
    # The denoiser's error at 1 spp is far below raw Cycles' at 1 spp (same samples).
    assert oidn[0]["combined"] < curve[0]["combined"]
    assert all("indirect" not in c for c in oidn)
    eevee = [p for p in scene["peers"] if p.startswith("EEVEE")]
    assert sorted(eevee) == ["EEVEE, ray tracing off", "EEVEE, ray tracing on"]
    for p in eevee:
        (point,) = scene["peers"][p]
        assert np.isfinite(point["combined"]) and point["software"] is True  # llvmpipe here
    kd10 = scene["peers"][report.PEER_KD10]
    # the profile's grids, and the defaults' own from the one-at-a-time "angular=sh" row
    assert sorted({r["settings"]["grid_resolution"] for r in kd10}) == sorted(
        set(quick_prof["kd10_grids"]) | {GISettings().grid_resolution})
    assert all(r["settings"]["angular"] == report.KD10_ANGULAR for r in kd10)
    assert not any(report._kd10(r) for r in ok if r["label"] in scene["pareto"])
    peers_seen = {v["peer"] for v in scene["peer_verdicts"]}
    assert peers_seen == {report.PEER_RAW, report.PEER_OIDN, report.PEER_KD10, *eevee}
    assert all(v["wins"] in (True, False) for v in scene["peer_verdicts"])
    assert "## Against the peers a user would pick instead" in readme
    # The one-line verdict per scene goes to stdout.
    assert "cornell_spot:" in proc.stdout and "criterion" in proc.stdout


def test_readme_can_be_rewritten_from_results_json(quick):
    out, _, _ = quick
    before = (out / "README.md").read_text()
    (out / "README.md").unlink()
    proc = subprocess.run([sys.executable, "-m", "tools.report", "--readme-only", "--out",
                           str(out)], cwd=ROOT, capture_output=True, text=True, check=False)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert (out / "README.md").read_text() == before
