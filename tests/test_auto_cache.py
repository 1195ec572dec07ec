"""Backend "auto" (lpv_core.gl.backend.auto_backend): on a software renderer (llvmpipe here) the
CPU path for every stage, nothing timed, the reason reported; on a hardware renderer (pretended
here) measured once, kept on disk, reused by later processes, measured again when its key
changes, and never a reason for a render to fail."""

import functools
import json

import pytest

from lpv_core import engine
from lpv_core.scene import GISettings

FAKE_MS = {"propagate": {"numpy": 5.0, "gl": 1.0}, "lookup": {"numpy": 20.0, "gl": 30.0}}


def _no_measure(**_):
    raise AssertionError("measure() must not run")


@pytest.fixture
def fresh(gl, tmp_path, monkeypatch):
    """A fresh cache dir and no in-process memo (restored afterwards)."""
    monkeypatch.setenv("LPV_GI_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.delenv("LPV_GI_NO_CACHE", raising=False)
    monkeypatch.setattr(gl, "_AUTO", {})
    return tmp_path / "cache" / gl.CACHE_FILE


@pytest.fixture
def cache(gl, fresh, monkeypatch):
    """``fresh``, on a renderer taken for hardware (the measure-and-cache path)."""
    monkeypatch.setattr(gl, "software_renderer", lambda renderer: False)
    return fresh


def _fake_measure(calls):
    def measure(gl=None, **_):
        calls.append("dom")
        return json.loads(json.dumps(FAKE_MS))
    return measure


def test_software_renderers_are_named(gl):
    for renderer in ("llvmpipe (LLVM 15.0.6, 256 bits)", "softpipe", "Google SwiftShader",
                     "Microsoft Basic Render Driver (Software)"):
        assert gl.software_renderer(renderer), renderer
    for renderer in ("NVIDIA H200/PCIe/SSE2", "AMD Radeon RX 7900 XTX (radeonsi, navi31)",
                     "Mesa Intel(R) Arc(tm) A770 Graphics (DG2)", ""):
        assert not gl.software_renderer(renderer), renderer


def test_software_renderer_takes_the_cpu_untimed(gl, fresh, monkeypatch):
    """On this machine's llvmpipe "auto" measures nothing, picks the CPU for every stage and
    says why in the stats."""
    renderer = gl.backend().renderer
    if not gl.software_renderer(renderer):
        pytest.skip(f"a hardware renderer: {renderer}")
    monkeypatch.setattr(gl, "measure", _no_measure)
    stats = engine.Stats()
    be = engine.Engine().backend(GISettings().updated(backend="auto"), stats)
    assert be is engine.NUMPY_BACKEND and stats.info["backend"] == "numpy"
    auto = stats.info["backend_auto"]
    assert auto["backend"] == "numpy" and set(auto["stages"].values()) == {"numpy"}
    assert auto["reason"].startswith("software renderer") and renderer in auto["reason"]
    assert auto["ms"] == {} and "backend_choice" not in stats.ms
    assert not fresh.exists()  # nothing to keep


def test_models_gl_does_not_run_are_not_timed(gl, cache, monkeypatch):
    monkeypatch.setattr(gl, "measure", _no_measure)
    rec = gl.auto_backend(angular="sh")
    assert rec["backend"] == "numpy" and "dom" in rec["reason"]
    assert not cache.exists()


def test_real_measure_then_cached(gl, cache, monkeypatch):
    monkeypatch.setattr(gl, "measure", functools.partial(gl.measure, resolution=8, vpls=512,
                                                         receivers=1024, repeat=1))
    first = gl.auto_backend(angular="dom")
    assert first["cached"] is False and "reason" not in first
    assert all(first["ms"][stage][name] > 0 for stage in gl.STAGES for name in ("numpy", "gl"))
    stored = json.loads(cache.read_text())
    key = gl.cache_key(gl.backend(), "dom")
    assert list(stored) == [key] and stored[key]["stages"] == first["stages"]
    assert "cached" not in stored[key]
    monkeypatch.setattr(gl, "_AUTO", {})
    monkeypatch.setattr(gl, "measure", _no_measure)
    second = gl.auto_backend(angular="dom")
    assert second["cached"] is True
    assert list(second["stages"]) == list(gl.STAGES)  # in the stages' order, as measured
    assert (second["stages"], second["backend"], second["ms"]) == \
        (first["stages"], first["backend"], first["ms"])
    assert gl.auto_backend(angular="dom") is second  # then the in-process memo


def test_engine_cache_hit_records_no_time(gl, cache, monkeypatch):
    monkeypatch.setattr(gl, "measure", _fake_measure([]))
    settings = GISettings().updated(backend="auto")
    stats = engine.Stats()
    be = engine.Engine().backend(settings, stats)
    assert stats.info["backend_auto"]["cached"] is False
    assert isinstance(be, gl.MixedBackend) and be.stages == {"propagate": "gl",
                                                             "lookup": "numpy"}
    monkeypatch.setattr(gl, "_AUTO", {})
    monkeypatch.setattr(gl, "measure", _no_measure)
    stats = engine.Stats()
    be = engine.Engine().backend(settings, stats)
    assert stats.info["backend_auto"]["cached"] is True
    assert "backend_choice" not in stats.ms
    assert be.name == stats.info["backend"]


def test_corrupt_file_is_ignored_and_overwritten(gl, cache, monkeypatch):
    calls = []
    monkeypatch.setattr(gl, "measure", _fake_measure(calls))
    cache.parent.mkdir(parents=True)
    cache.write_text("{not json")
    rec = gl.auto_backend(angular="dom")
    assert calls == ["dom"] and rec["cached"] is False
    assert rec["stages"] == {"propagate": "gl", "lookup": "numpy"}
    assert rec["backend"] == "mixed"
    stored = json.loads(cache.read_text())
    assert next(iter(stored.values()))["stages"] == rec["stages"]
    # a JSON file that is not a {key: record} object, or a malformed record, is ignored too
    for junk in ("[1, 2]", json.dumps({gl.cache_key(gl.backend(), "dom"): {"stages": 3}})):
        cache.write_text(junk)
        monkeypatch.setattr(gl, "_AUTO", {})
        assert gl.auto_backend(angular="dom")["cached"] is False
    assert calls == ["dom"] * 3


def test_other_key_measures_again(gl, cache, monkeypatch):
    calls = []
    monkeypatch.setattr(gl, "measure", _fake_measure(calls))
    gl.auto_backend(angular="dom")
    monkeypatch.setattr(gl, "_AUTO", {})
    assert gl.auto_backend(angular="dom")["cached"] is True
    monkeypatch.setattr(gl, "_AUTO", {})
    monkeypatch.setattr(gl, "code_fingerprint", lambda: "changed code")
    assert gl.auto_backend(angular="dom")["cached"] is False  # the timed code changed
    monkeypatch.setattr(gl, "_AUTO", {})
    monkeypatch.setattr(gl, "AUTO_MARGIN", 3.0)
    assert gl.auto_backend(angular="dom")["cached"] is False  # another margin
    assert calls == ["dom"] * 3
    assert len(json.loads(cache.read_text())) == 3  # every key kept side by side


def test_fingerprint_covers_timed_sources(gl, monkeypatch):
    fp = gl.code_fingerprint()
    assert isinstance(fp, str) and len(fp) == 16 and gl.code_fingerprint() == fp
    root = gl.SHADERS.parents[1]
    for name in gl.TIMED_SOURCES:
        assert (root / name).exists(), name  # no name that hashes nothing
    for name in ("gl", "propagation", "lookup.py"):
        assert name in gl.TIMED_SOURCES
    monkeypatch.setattr(gl, "_FINGERPRINT", None)
    monkeypatch.setattr(gl, "TIMED_SOURCES", ("gl/backend.py",))
    assert gl.code_fingerprint() != fp  # the shaders are part of it


def test_auto_choice_needs_a_clear_margin(gl):
    """A near tie goes to the CPU (the reference); gl is picked where it is clearly faster."""
    ms = {"propagate": {"numpy": 90.0, "gl": 30.0}, "lookup": {"numpy": 10.0, "gl": 8.0}}
    assert gl.choose(ms) == {"propagate": "gl", "lookup": "numpy"}


def test_unwritable_dir_still_chooses(gl, cache, tmp_path, monkeypatch):
    blocker = tmp_path / "a_file"
    blocker.write_text("not a directory")
    monkeypatch.setenv("LPV_GI_CACHE_DIR", str(blocker / "cache"))
    calls = []
    monkeypatch.setattr(gl, "measure", _fake_measure(calls))
    rec = gl.auto_backend(angular="dom")
    assert rec["cached"] is False and rec["backend"] == "mixed"
    monkeypatch.setattr(gl, "_AUTO", {})
    assert gl.auto_backend(angular="dom")["cached"] is False  # nothing could be stored
    assert calls == ["dom", "dom"]
    assert list(tmp_path.iterdir()) == [blocker]  # no temp file left behind


def test_opt_out(gl, cache, monkeypatch):
    calls = []
    monkeypatch.setattr(gl, "measure", _fake_measure(calls))
    monkeypatch.setenv("LPV_GI_NO_CACHE", "1")
    gl.auto_backend(angular="dom")
    assert not cache.exists()  # not written
    monkeypatch.delenv("LPV_GI_NO_CACHE")
    monkeypatch.setattr(gl, "_AUTO", {})
    gl.auto_backend(angular="dom")
    assert cache.exists()
    monkeypatch.setenv("LPV_GI_NO_CACHE", "1")
    monkeypatch.setattr(gl, "_AUTO", {})
    assert gl.auto_backend(angular="dom")["cached"] is False  # not read
    assert calls == ["dom"] * 3


def test_gl_failure_is_not_cached(gl, cache, monkeypatch):
    def broken(**_):
        raise RuntimeError("context lost")

    monkeypatch.setattr(gl, "measure", broken)
    rec = gl.auto_backend(angular="dom")
    assert rec["backend"] == "numpy" and rec["reason"].startswith("gl unavailable")
    assert not cache.exists()
    monkeypatch.setattr(gl, "_AUTO", {})
    calls = []
    monkeypatch.setattr(gl, "measure", _fake_measure(calls))
    assert gl.auto_backend(angular="dom")["cached"] is False
    assert calls == ["dom"]


def test_default_location(gl, monkeypatch, tmp_path):
    monkeypatch.delenv("LPV_GI_CACHE_DIR")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert gl.cache_dir() == tmp_path / "xdg" / "lpv_gi"
    monkeypatch.delenv("XDG_CACHE_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert gl.cache_dir() == tmp_path / "home" / ".cache" / "lpv_gi"
