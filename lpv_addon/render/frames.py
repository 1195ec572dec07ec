"""Renders a frame range to multi-layer EXRs (Cycles' pass names) and stats.json: the one loop
behind ``python -m lpv_addon.batch`` and the Render Batch operator.

Each frame: ``frame_set`` (animated values, e.g. a keyframed ``Scene.lpv.intensity``),
extraction here, the engine's update and deferred render, the EXR written atomically, and its
record added to stats.json (valid JSON after every frame, constant cost per frame), so a
cancelled or failed batch keeps its finished frames. Where the engine runs is the only
difference between the two callers:
:class:`InProcess` for the CLI (no Blender drawing happens there), :class:`InWorker` inside
Blender, whose process must never run moderngl (it breaks Blender's drawing).
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import re
import signal
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import bpy

from .._core import core
from ..scene_io.extract import extract_scene
from ..worker_client import WorkerClient, WorkerError


def os_error_text(exc: OSError, path) -> str:
    """One line naming the path, the problem and its errno name (ENOSPC: the disk is full)."""
    code = errno.ENOTDIR if exc.errno == errno.EEXIST else exc.errno  # mkdir over a file
    if code is None:
        return f"cannot write to '{path}': {exc}"
    return f"cannot write to '{path}': {os.strerror(code)} ({errno.errorcode.get(code, code)})"


# What StatsFile and the EXR writer leave when killed: .NAME.PID[.HEX8].tmp
_TMP_NAME = re.compile(r"^\..+\.(?:exr|json)\.(\d+)(?:\.[0-9a-f]{8})?\.tmp$")


def _alive(pid: int) -> bool:
    if os.name == "nt":  # os.kill would terminate it; a live writer's file cannot be removed
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        pass
    return True


def remove_stale_tmp(folder: Path, own: bool = False) -> None:
    """Remove the hidden temporary files of atomic writes whose process is gone (and this
    process's own with ``own``): what a killed batch leaves in its output folder."""
    for tmp in folder.glob(".*.tmp"):
        m = _TMP_NAME.match(tmp.name)
        if m and (not _alive(int(m[1])) or (own and int(m[1]) == os.getpid())):
            try:
                tmp.unlink(missing_ok=True)
            except OSError:
                pass


class StatsFile:
    """stats.json, valid JSON after every frame at a constant cost per frame: the head is
    written once (atomically); each frame's record, one line, is written where the closing
    tail stood, followed by the tail again."""

    def __init__(self, path: Path, head: dict):
        text = json.dumps(head)[:-1] + ', "frames": [\n'
        tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        self.tail = self._tail(False)
        tmp.write_bytes(text.encode() + self.tail)
        os.replace(tmp, path)
        self.path, self.fd = path, os.open(path, os.O_RDWR | getattr(os, "O_BINARY", 0))
        self.end, self.count, self.cancelled = len(text), 0, False

    @staticmethod
    def _tail(cancelled: bool) -> bytes:
        return f'\n], "cancelled": {json.dumps(cancelled)}}}\n'.encode()

    def _write_at(self, offset: int, data: bytes) -> None:
        os.lseek(self.fd, offset, os.SEEK_SET)
        if os.write(self.fd, data) < len(data):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        os.ftruncate(self.fd, offset + len(data))
        os.fsync(self.fd)

    def _write(self, text: str) -> None:
        tail = self._tail(self.cancelled)
        try:
            self._write_at(self.end, text.encode() + tail)
        except OSError as exc:  # e.g. ENOSPC: put the last valid tail back, then report
            os.ftruncate(self.fd, self.end)
            self._write_at(self.end, self.tail)
            raise OSError(exc.errno, exc.strerror, str(self.path)) from None
        self.end, self.tail = self.end + len(text), tail

    def add(self, record: dict) -> None:
        self._write((",\n" if self.count else "") + json.dumps(record))
        self.count += 1

    def set_cancelled(self, cancelled: bool) -> None:
        self.cancelled = cancelled
        self._write("")

    def close(self) -> None:
        if self.fd is not None:
            os.close(self.fd)
            self.fd = None


def _exr_os_error(exc: RuntimeError, path: Path) -> OSError | None:
    """OpenEXR reports a failed write as RuntimeError with the system's message only."""
    for code in (errno.ENOSPC, errno.EDQUOT, errno.EACCES, errno.EROFS, errno.EIO):
        if os.strerror(code) in str(exc):
            return OSError(code, os.strerror(code), str(path))
    return None


def animation_frames(scene: bpy.types.Scene) -> tuple[int, int, int]:
    """The scene's frame range and step, as Render Animation (``blender -a``) renders it."""
    return scene.frame_start, scene.frame_end, max(1, scene.frame_step)


def render_output_file(scene: bpy.types.Scene, frame: int) -> Path:
    """Where Blender's render output path puts ``frame`` (``//`` and ``#`` as Blender reads
    them), as an EXR."""
    path, ext = scene.render.frame_path(frame=frame), scene.render.file_extension
    if scene.render.use_file_extension and ext and path.endswith(ext):
        path = path[: -len(ext)]
    return Path(os.path.abspath(path + ".exr"))


@contextlib.contextmanager
def interrupts_deferred() -> Iterator[None]:
    """Ctrl-C (SIGINT) held back while the block runs and delivered after it, so a frame's
    EXR and its record in stats.json are written together or not at all. Python runs signal
    handlers in the main thread whichever thread the signal meets, so the handler is swapped
    for one that notes it; where Python does not handle SIGINT (another thread, a host
    application's own handler) the block runs as it is."""
    handler = signal.getsignal(signal.SIGINT)
    if not callable(handler) or threading.current_thread() is not threading.main_thread():
        yield
        return
    got: list = []
    signal.signal(signal.SIGINT, lambda signum, frame: got.append(frame))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, handler)
        if got:
            handler(signal.SIGINT, got[0])


class InProcess:
    """The engine in this process, one frame at a time: submit renders it, collect (at once)
    writes its EXR."""

    def __init__(self):
        self.engine = core.engine.Engine()

    def submit(self, scene, exr_path: Path) -> tuple:
        stats = core.engine.Stats()
        result = self.engine.update(scene, stats)
        return core.render.deferred.render(self.engine, scene, result, stats), stats, exr_path

    def collect(self, handle: tuple, block: bool) -> dict:
        passes, stats, exr_path = handle
        t_w = time.perf_counter()
        try:
            core.render.exr.write_multilayer(exr_path, passes)
        except RuntimeError as exc:
            os_exc = _exr_os_error(exc, exr_path)
            if os_exc is None:
                raise
            raise os_exc from None
        stats.add_ms("write", time.perf_counter() - t_w)
        return stats.as_dict()

    def cancel(self) -> None:
        pass

    def close(self) -> None:
        pass


class InWorker:
    """The engine in the ``lpv_core.worker`` process; collect polls for the reply."""

    def __init__(self):
        self.worker = WorkerClient()

    def submit(self, scene, exr_path: Path) -> tuple[int, str]:
        return self.worker.send_scene("render", scene, f"{exr_path.stem}.npz", exr=str(exr_path))

    def collect(self, handle: tuple[int, str], block: bool) -> dict | None:
        rid, request = handle
        reply = self.worker.wait(rid) if block else self.worker.reply(rid)
        if reply is None:
            return None
        os.unlink(request)
        if not reply.get("ok"):
            raise WorkerError(reply.get("error", "unknown worker error"))
        return dict(reply.get("stats", {}))

    def cancel(self) -> None:
        """Drop the frame in flight: the worker is killed (its EXR never appears)."""
        self.worker.kill()

    def close(self) -> None:
        self.worker.close()


def approximation_warnings(approximated: list[str]) -> list[str]:
    """One line per source, shader or image the extraction approximated (also in
    stats.json's info), as the batch log, F12's report and the main panel show them."""
    return [f"approximated: {line}" for line in approximated]


class BatchJob:
    """Renders ``frames`` ((first, last) or (first, last, step); default: the scene's range)
    of ``scene`` into ``out_dir`` as NNNN.exr, or, with no ``out_dir``, where the scene's
    render output path puts each frame; one frame in flight at a time. ``run`` renders them
    all (blocking); ``step`` advances without blocking, as the modal operator's timer drives
    it; ``cancel`` keeps every finished frame and removes the unfinished one. ``log(message)``
    hears one line per finished frame and the warnings about unmodelled light."""

    def __init__(self, scene: bpy.types.Scene, out_dir, frames=None, resolution=None,
                 overrides: dict | None = None, in_process: bool = False,
                 log: Callable[[str], None] | None = None):
        self.scene_name = scene.name
        first, last, *step = frames or (scene.frame_start, scene.frame_end)
        if last < first or (step and step[0] < 1):
            raise ValueError(f"frame range {first}-{last} is empty")
        self.frames = list(range(int(first), int(last) + 1, int(step[0]) if step else 1))
        self.render_output = not out_dir
        self.out = (render_output_file(scene, self.frames[0]).parent if self.render_output
                    else Path(os.path.abspath(bpy.path.abspath(str(out_dir)))))
        self.resolution = resolution
        self.overrides = dict(overrides or {})
        self.in_process = in_process
        self.log = log
        self.done: list[int] = []
        self.record = {"scene": scene.name, "settings": None, "frames": [], "cancelled": False}
        self.original_frame = scene.frame_current
        self.renderer: InProcess | InWorker | None = None
        self.stats: StatsFile | None = None
        self.started = False
        self.pending = None
        self.cancelled = False
        self.error = ""

    @property
    def scene(self) -> bpy.types.Scene:
        scene = bpy.data.scenes.get(self.scene_name)
        if scene is None:
            raise ValueError(f"scene '{self.scene_name}' is gone")
        return scene

    @property
    def total(self) -> int:
        return len(self.frames)

    @property
    def finished(self) -> bool:
        return self.pending is None and (len(self.done) == self.total or self.cancelled
                                         or bool(self.error))

    def frame_file(self, frame: int) -> Path:
        """The EXR of ``frame``."""
        if self.render_output:
            return render_output_file(self.scene, frame)
        return self.out / f"{frame:04d}.exr"

    def start(self) -> None:
        """Create the output folder, remove what a killed run left there and check that it
        takes a write (ValueError naming the folder and the problem)."""
        try:
            self.out.mkdir(parents=True, exist_ok=True)
            remove_stale_tmp(self.out)
            with tempfile.TemporaryFile(dir=self.out) as fh:
                fh.write(b"\0")
                fh.flush()
                os.fsync(fh.fileno())
        except OSError as exc:
            raise ValueError(os_error_text(exc, self.out)) from None
        self.started = True
        self.renderer = InProcess() if self.in_process else InWorker()

    def _send(self, frame: int) -> None:
        t0 = time.perf_counter()
        scene = self.scene
        scene.frame_set(frame)
        depsgraph = bpy.context.evaluated_depsgraph_get()
        timings: dict = {}
        t_ex = time.perf_counter()
        core_scene = extract_scene(depsgraph, scene, self.resolution, self.overrides,
                                   timings=timings)
        t_ex = (time.perf_counter() - t_ex) * 1000.0
        if self.record["settings"] is None:
            self.record["settings"] = core_scene.settings.as_dict()
            self._open_stats()
            for line in approximation_warnings(core_scene.approximated):
                self._log(f"warning: {line}")
        entry = {"frame": frame, "t0": t0, "extract": t_ex, "timings": timings,
                 "intensity": core_scene.settings.intensity}
        self.pending = (entry, self.renderer.submit(core_scene, self.frame_file(frame)))

    def _collect(self, block: bool) -> bool:
        """Take the frame in flight if it is done; False while it is not. Its EXR (written
        here in-process) and its record go together: Ctrl-C waits for both."""
        if self.in_process:
            with interrupts_deferred():
                return self._take(self.renderer.collect(self.pending[1], block))
        stats = self.renderer.collect(self.pending[1], block)  # waiting stays interruptible
        with interrupts_deferred():
            return self._take(stats)

    def _take(self, stats: dict | None) -> bool:
        """Record the frame in flight, whose EXR is written, with ``stats`` (None: not done)."""
        if stats is None:
            return False
        entry, _ = self.pending
        self.pending = None
        frame = entry["frame"]
        stats.setdefault("ms", {})["extract"] = entry["extract"]
        stats["ms"]["total"] = (time.perf_counter() - entry["t0"]) * 1000.0
        record = {"frame": frame, **stats, "intensity": entry["intensity"],
                  "extract_ms": entry["timings"]}
        self.record["frames"].append(record)
        self.done.append(frame)
        self.stats.add(record)
        ms = stats["ms"]
        self._log(f"frame {frame} ({len(self.done)}/{self.total}): {ms['total']:.0f} ms, "
                  f"LPV {ms.get('lpv_update', 0):.0f} ms -> {self.frame_file(frame)}")
        return True

    def step(self, block: bool = False) -> bool:
        """Advance: collect a finished frame, send the next. Returns True while running."""
        if self.renderer is None:
            self.start()
        frame = self.pending[0]["frame"] if self.pending is not None else None
        try:
            if self.pending is not None and not self._collect(block):
                return True
            if self.cancelled or self.error or len(self.done) == self.total:
                return False
            frame = self.frames[len(self.done)]
            self._send(frame)
        except (ValueError, WorkerError, OSError) as exc:
            self.pending = None
            why = os_error_text(exc, exc.filename or self.out) if isinstance(exc, OSError) \
                else exc
            self.error = f"frame {frame}: {why}"
            return False
        return True

    def _log(self, message: str) -> None:
        if self.log is not None:
            self.log(message)

    def _open_stats(self) -> None:
        self.stats = StatsFile(self.out / "stats.json",
                               {"scene": self.scene_name, "settings": self.record["settings"]})

    def cancel(self) -> None:
        """Stop now: the frame in flight is dropped, finished frames stay."""
        self.cancelled = self.record["cancelled"] = True
        if self.pending is not None and self.in_process:  # already rendered: write and keep it
            try:
                self._collect(block=True)
            except OSError:  # it could not be written: dropped as an unfinished frame
                self.pending = None
        if self.pending is not None and self.renderer is not None:
            self.renderer.cancel()
            self.renderer = None
        self.pending = None
        if self.started:
            remove_stale_tmp(self.out, own=True)
            if self.stats is None:
                self._open_stats()
            self.stats.set_cancelled(True)

    def close(self) -> None:
        if self.stats is not None:
            self.stats.close()
        if self.renderer is not None:
            self.renderer.close()
            self.renderer = None
        try:
            self.scene.frame_set(self.original_frame)
        except ValueError:
            pass

    def run(self) -> None:
        """Render every frame, blocking (the CLI, scripts, the operator's execute)."""
        try:
            while self.step(block=True):
                pass
        except KeyboardInterrupt:
            self.cancel()
            raise
        finally:
            self.close()
        if self.error:
            raise ValueError(self.error)
