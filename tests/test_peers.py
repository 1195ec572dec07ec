"""The report's peer verdicts (tools/peers.py) on hand-derived curves: equal-time errors
interpolate in log-log, equal-error times invert the same interpolation, a peer timed on a
software renderer is compared on error only."""

import math

import pytest

from tools import peers

# A peer curve: error 0.4 at 1 s, 0.1 at 4 s (error ~ time^-1 between them).
CURVE = [{"time_s": 1.0, "combined": 0.4}, {"time_s": 4.0, "combined": 0.1}]


def test_error_at_interpolates_in_log_log_and_holds_past_the_last_point():
    assert peers.error_at(CURVE, 2.0, "combined") == (pytest.approx(0.2), "interpolated")
    assert peers.error_at(CURVE, 0.5, "combined") == (None, "below")
    assert peers.error_at(CURVE, 100.0, "combined") == (0.1, "held")


def test_time_to_inverts_the_interpolation():
    assert peers.time_to(CURVE, 0.2, "combined")[0] == pytest.approx(2.0)
    assert peers.time_to(CURVE, 0.5, "combined") == (1.0, "at or below its fastest point")
    assert peers.time_to(CURVE, 0.05, "combined") == (None, "not reached")


def test_verdict_at_equal_time_and_equal_error():
    lpv = {"label": "defaults", "time_s": 2.0, "combined": 0.1}
    v = peers.verdicts(lpv, "peer", CURVE, "combined")
    # At 2 s the peer reads 0.2: LPV's error is 2x lower; the peer needs 4 s for 0.1 (2x).
    assert v["eq_time_ratio"] == pytest.approx(2.0)
    assert v["eq_error_peer_time_s"] == pytest.approx(4.0)
    assert v["eq_error_ratio"] == pytest.approx(2.0)
    assert v["wins"] is True
    assert "2.0x lower" in peers.verdict_text(v)
    worse = peers.verdicts({"label": "x", "time_s": 2.0, "combined": 0.3}, "peer", CURVE,
                           "combined")
    assert worse["wins"] is False and worse["eq_time_ratio"] == pytest.approx(0.2 / 0.3)
    assert "1.5x higher" in peers.verdict_text(worse)
    # Faster than the peer's first image: LPV wins on time whatever its error.
    early = peers.verdicts({"label": "x", "time_s": 0.5, "combined": 0.3}, "peer", CURVE,
                           "combined")
    assert early["wins"] is True and early["eq_time_peer_error"] is None


def test_software_renderer_peer_is_compared_on_error_only():
    point = [{"time_s": 30.0, "combined": 0.37, "software": True}]
    rows = peers.table({"defaults": {"label": "d", "time_s": 0.5, "combined": 0.156}},
                       {"EEVEE": point})
    assert len(rows) == 1 and rows[0]["time_meaningful"] is False
    assert "eq_time_ratio" not in rows[0] and rows[0]["wins"] is True
    assert "2.4x lower" in rows[0]["text"]


def test_indirect_verdicts_only_for_peers_with_the_pass():
    lpv = {"label": "d", "time_s": 2.0, "combined": 0.1, "indirect": 0.2}
    with_pass = [dict(c, indirect=c["combined"] * 2) for c in CURVE]
    rows = peers.table({"defaults": lpv}, {"raw": with_pass, "denoised": CURVE})
    keys = {(r["peer"], r["key"]) for r in rows}
    assert keys == {("raw", "combined"), ("raw", "indirect"), ("denoised", "combined")}
    assert all(math.isfinite(r["lpv_error"]) for r in rows)


def test_software_renderer_names():
    assert peers.is_software("llvmpipe (LLVM 19.1.7, 256 bits)")
    assert not peers.is_software("NVIDIA H200/PCIe/SSE2")
