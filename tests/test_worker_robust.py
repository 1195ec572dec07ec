"""The live worker survives bad requests, and the live viewport survives a worker that stops.

A real ``python -m lpv_core.worker`` gets lines that are not JSON objects, an unknown command and
an id it cannot echo: each gets a one-line error reply and the next valid request is served. In
a child Blender process (the bpy module), the live viewport's worker is killed, then stopped
(SIGSTOP) mid-request: ``live.tick`` says so in the stats lines, starts a new worker and the
next result arrives from it. LPV_JIT=0 keeps the kernels (and their warm-up) out of both."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys

import numpy as np
import pytest
from conftest import ROOT

from lpv_core.worker import save_scene
from tools.core_scenes import cornell_box

BAD = [
    ("[1, 2]", "a JSON object per line, not list"),
    ("42", "a JSON object per line, not int"),
    ('"update"', "a JSON object per line, not str"),
    ("null", "a JSON object per line, not NoneType"),
    ("{not json", "not JSON"),
    ('{"id": 5, "cmd": "frobnicate"}', "unknown command 'frobnicate'"),
    ('{"id": 6, "scene": "x.npz"}', "unknown command None"),
]


@pytest.fixture(scope="module")
def worker(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("worker")
    env = {**os.environ, "LPV_JIT": "0", "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen([sys.executable, "-m", "lpv_core.worker"], cwd=tmp, env=env,
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            stderr=open(tmp / "log", "w"), text=True)  # noqa: SIM115

    def ask(line: str) -> dict:
        proc.stdin.write(line + "\n")
        proc.stdin.flush()
        return json.loads(proc.stdout.readline() or "null")

    save_scene(str(tmp / "scene.npz"), cornell_box())
    yield ask, proc, tmp
    proc.stdin.close()
    proc.wait(30)


@pytest.mark.parametrize("line,error", BAD)
def test_bad_request_gets_an_error_and_the_next_is_served(worker, line, error):
    ask, proc, tmp = worker
    reply = ask(line)
    assert reply is not None and reply["ok"] is False and error in reply["error"], reply
    assert proc.poll() is None
    if line.startswith('{"id"'):
        assert reply["id"] == json.loads(line)["id"]
    out = tmp / f"reply_{abs(hash(line))}.npz"
    served = ask(json.dumps({"id": 7, "cmd": "update", "scene": str(tmp / "scene.npz"),
                             "reply": str(out)}))
    assert served["ok"] is True and served["id"] == 7 and served["has_gi"], served
    assert served["kernels"]["state"] == "off"  # LPV_JIT=0
    values = np.load(out)["values"]
    assert np.isfinite(values).all() and values[..., 0].max() > 0


def test_an_id_that_cannot_be_echoed_is_replaced(worker):
    ask, proc, _ = worker
    reply = ask('{"id": [1, 2], "cmd": "ping"}')
    assert reply["ok"] is True and reply["id"] is None and reply["pid"] == proc.pid


SCRIPT = r"""
import json, os, signal, sys, time
import bpy
import lpv_addon
from lpv_addon.viewport import live
from tools import scenes

lpv_addon.register()
scenes.cornell_box("SPOT", resolution=(32, 32))
scene = bpy.context.scene
scene.lpv.enabled = True
scene.lpv.quality = "DRAFT"
scene.lpv.rsm_resolution = 32

def tick_until(done, limit=120.0):
    t0 = time.monotonic()
    while not done() and time.monotonic() - t0 < limit:
        time.sleep(min(live.tick(require_viewport=False), 0.05))
    return time.monotonic() - t0

def broken(sig, deadline):
    live.DEADLINE_S = deadline
    serial = live.STATE.current.serial
    light = next(ob for ob in scene.objects if ob.type == "LIGHT")
    light.data.energy *= 1.1  # light power: the worker's to compute
    live.mark_dirty("test")
    live.refresh(scene)
    assert live.STATE.pending is not None  # in flight
    pid = live.STATE.client.proc.pid
    os.kill(pid, sig)
    seconds = tick_until(lambda: live.STATE.error != "")
    out = {"pid": pid, "seconds": seconds, "lines": live.stats_lines(),
           "pending": live.STATE.pending is not None}
    tick_until(lambda: live.STATE.current.serial > serial)
    out.update(new_pid=live.STATE.client.proc.pid, served=live.STATE.current.serial > serial,
               error_after=live.STATE.error, has_gi=live.STATE.current.values is not None,
               old_alive=os.path.exists(f"/proc/{pid}") and
               open(f"/proc/{pid}/stat").read().split()[2] not in "ZX")
    return out

live.refresh(scene, wait=True)
result = {"killed": broken(signal.SIGKILL, 120.0), "stopped": broken(signal.SIGSTOP, 3.0)}
lpv_addon.unregister()
print("RESULT=" + json.dumps(result))
"""


@pytest.fixture(scope="module")
def restarts(tmp_path_factory):
    pytest.importorskip("bpy")
    tmp = tmp_path_factory.mktemp("restart")
    env = {**os.environ, "LPV_JIT": "0", "PYTHONPATH": str(ROOT)}
    proc = subprocess.run([sys.executable, "-c", SCRIPT], cwd=tmp, env=env, timeout=600,
                          capture_output=True, text=True, check=False)
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT=")]
    assert proc.returncode == 0 and lines, (proc.stdout + proc.stderr)[-4000:]
    return json.loads(lines[-1][len("RESULT="):])


@pytest.mark.bpy
@pytest.mark.skipif(not hasattr(signal, "SIGSTOP"), reason="POSIX signals")
def test_a_killed_worker_is_reported_and_replaced(restarts):
    r = restarts["killed"]
    assert r["seconds"] < 10.0  # noticed at the next tick, not after the deadline
    assert any("LPV worker stopped" in ln and "restarted it" in ln for ln in r["lines"]), r
    assert not r["pending"] and r["served"] and r["has_gi"]
    assert r["new_pid"] != r["pid"] and r["error_after"] == ""


@pytest.mark.bpy
@pytest.mark.skipif(not hasattr(signal, "SIGSTOP"), reason="POSIX signals")
def test_a_stuck_worker_is_reported_after_the_deadline_and_replaced(restarts):
    r = restarts["stopped"]
    assert 3.0 <= r["seconds"] < 15.0
    assert any("did not answer within" in ln and "restarted it" in ln for ln in r["lines"]), r
    assert r["served"] and r["has_gi"] and r["new_pid"] != r["pid"]
    assert not r["old_alive"]  # the stopped worker was killed, not left behind
