"""Backend "auto"'s choice kept on disk (gl_backend.auto_backend): reused by later processes,
measured again when its key changes, and never a reason for a render to fail."""

import json

import pytest

FAKE_MS = {"inject": {"numpy": 10.0, "gl": 40.0}, "propagate": {"numpy": 5.0, "gl": 1.0},
           "lookup": {"numpy": 20.0, "gl": 30.0}}



@pytest.fixture
def cache(gl, tmp_path, monkeypatch):
    """A fresh cache dir and no in-process memo (restored afterwards)."""
    monkeypatch.setenv("LPV_GI_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.delenv("LPV_GI_NO_CACHE", raising=False)
    monkeypatch.setattr(gl, "_AUTO", {})
    return tmp_path / "cache" / gl.CACHE_FILE


def _fake_measure(calls):
    def measure(gl=None, angular="sh", **_):
        calls.append(angular)
        return json.loads(json.dumps(FAKE_MS))
    return measure


def _no_measure(**_):
    raise AssertionError("measure() must not run on a cache hit")


def test_real_measure_then_cached(gl, cache, monkeypatch):
    first = gl.auto_backend(angular="sh")
    assert first["cached"] is False
    assert "reason" not in first
    stored = json.loads(cache.read_text())
    assert len(stored) == 1
    key = gl.cache_key(gl.backend(), "sh")
    assert stored[key]["stages"] == first["stages"]
    assert "cached" not in stored[key]
    monkeypatch.setattr(gl, "_AUTO", {})
    monkeypatch.setattr(gl, "measure", _no_measure)
    second = gl.auto_backend(angular="sh")
    assert second["cached"] is True
    assert second["stages"] == first["stages"]
    assert list(second["stages"]) == list(gl.STAGES)  # in the stages' order, as measured
    assert second["backend"] == first["backend"]
    assert second["ms"] == first["ms"]
    assert gl.auto_backend(angular="sh") is second  # then the in-process memo


def test_engine_cache_hit_records_no_time(gl, cache, monkeypatch):
    from lpv_core import engine
    from lpv_core.scene import GISettings

    monkeypatch.setattr(gl, "measure", _fake_measure([]))
    settings = GISettings().updated(backend="auto")
    stats = engine.Stats()
    engine.Engine().backend(settings, stats)
    assert stats.info["backend_auto"]["cached"] is False
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
    rec = gl.auto_backend(angular="sh")
    assert calls == ["sh"] and rec["cached"] is False
    assert rec["stages"] == {"inject": "numpy", "propagate": "gl", "lookup": "numpy"}
    assert rec["backend"] == "mixed"
    stored = json.loads(cache.read_text())
    assert next(iter(stored.values()))["stages"] == rec["stages"]
    # a JSON file that is not a {key: record} object, or a malformed record, is ignored too
    for junk in ("[1, 2]", json.dumps({gl.cache_key(gl.backend(), "sh"): {"stages": 3}})):
        cache.write_text(junk)
        monkeypatch.setattr(gl, "_AUTO", {})
        assert gl.auto_backend(angular="sh")["cached"] is False
    assert calls == ["sh"] * 3


def test_other_key_measures_again(gl, cache, monkeypatch):
    calls = []
    monkeypatch.setattr(gl, "measure", _fake_measure(calls))
    gl.auto_backend(angular="sh")
    monkeypatch.setattr(gl, "_AUTO", {})
    assert gl.auto_backend(angular="sh")["cached"] is True
    assert gl.auto_backend(angular="dom")["cached"] is False  # another angular model
    assert calls == ["sh", "dom"]
    monkeypatch.setattr(gl, "_AUTO", {})
    monkeypatch.setattr(gl, "code_fingerprint", lambda: "changed code")
    assert gl.auto_backend(angular="sh")["cached"] is False  # the timed code changed
    monkeypatch.setattr(gl, "_AUTO", {})
    monkeypatch.setattr(gl, "AUTO_MARGIN", 3.0)
    assert gl.auto_backend(angular="sh")["cached"] is False  # another margin
    assert calls == ["sh", "dom", "sh", "sh"]
    assert len(json.loads(cache.read_text())) == 4  # every key kept side by side


def test_fingerprint_covers_timed_sources(gl):
    fp = gl.code_fingerprint()
    assert isinstance(fp, str) and len(fp) == 16
    assert gl.code_fingerprint() == fp
    for name in ("gl_backend", "propagation", "ordinates", "injection", "lookup"):
        assert name in gl._TIMED_MODULES


def test_unwritable_dir_still_chooses(gl, tmp_path, monkeypatch):
    blocker = tmp_path / "a_file"
    blocker.write_text("not a directory")
    monkeypatch.setenv("LPV_GI_CACHE_DIR", str(blocker / "cache"))
    monkeypatch.setattr(gl, "_AUTO", {})
    calls = []
    monkeypatch.setattr(gl, "measure", _fake_measure(calls))
    rec = gl.auto_backend(angular="sh")
    assert rec["cached"] is False and rec["backend"] == "mixed"
    monkeypatch.setattr(gl, "_AUTO", {})
    assert gl.auto_backend(angular="sh")["cached"] is False  # nothing could be stored
    assert calls == ["sh", "sh"]
    assert list(tmp_path.iterdir()) == [blocker]  # no temp file left behind


def test_opt_out(gl, cache, monkeypatch):
    calls = []
    monkeypatch.setattr(gl, "measure", _fake_measure(calls))
    monkeypatch.setenv("LPV_GI_NO_CACHE", "1")
    gl.auto_backend(angular="sh")
    assert not cache.exists()  # not written
    monkeypatch.delenv("LPV_GI_NO_CACHE")
    monkeypatch.setattr(gl, "_AUTO", {})
    gl.auto_backend(angular="sh")
    assert cache.exists()
    monkeypatch.setenv("LPV_GI_NO_CACHE", "1")
    monkeypatch.setattr(gl, "_AUTO", {})
    assert gl.auto_backend(angular="sh")["cached"] is False  # not read
    assert calls == ["sh"] * 3


def test_gl_failure_is_not_cached(gl, cache, monkeypatch):
    def broken(**_):
        raise RuntimeError("context lost")

    monkeypatch.setattr(gl, "measure", broken)
    rec = gl.auto_backend(angular="sh")
    assert rec["backend"] == "numpy" and rec["reason"].startswith("gl unavailable")
    assert not cache.exists()
    monkeypatch.setattr(gl, "_AUTO", {})
    calls = []
    monkeypatch.setattr(gl, "measure", _fake_measure(calls))
    assert gl.auto_backend(angular="sh")["cached"] is False
    assert calls == ["sh"]


def test_default_location(gl, monkeypatch, tmp_path):
    monkeypatch.delenv("LPV_GI_CACHE_DIR")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert gl.cache_dir() == tmp_path / "xdg" / "lpv_gi"
    monkeypatch.delenv("XDG_CACHE_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert gl.cache_dir() == tmp_path / "home" / ".cache" / "lpv_gi"
