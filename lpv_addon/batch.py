"""Headless batch renderer: LPV GI frames as multi-layer EXR with Cycles' pass names.

    python -m lpv_addon.batch SCENE.blend [--out DIR] [--frames A-B | --animation]
                              [--resolution WxH] [--preset draft|preview|high]
                              [--set key=value ...]
    python -m lpv_addon.batch --demo --out DIR

Like ``blender -b SCENE.blend -f N`` / ``-a`` it renders the scene's current frame, or with
``--animation`` its frame range and step. Per frame it writes DIR/NNNN.exr (Combined, Diffuse
Direct, Diffuse Indirect, Diffuse Color; without --out: where the scene's render output path
puts the frame) atomically and adds the frame to stats.json, so a cancelled batch keeps
finished frames. Progress goes to stderr. Exit 0 on success, 2 with a one-line reason on bad
arguments, input or output, 130 when interrupted (Ctrl-C). The frames go through the Render
Batch operator's loop (render/frames.py) with the engine in this process: no Blender drawing
happens here.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .presets import SETTINGS as PRESETS

USAGE_ERROR = 2
INTERRUPTED = 130  # 128 + SIGINT, as shells report Ctrl-C


class BatchError(Exception):
    """Bad arguments or unreadable input: reported as one line, exit code 2."""


def parse_frames(text: str | None) -> tuple[int, int] | None:
    """'A-B' or 'A' -> (A, B); None stays None (the scene's frame range)."""
    if text is None:
        return None
    try:
        if "-" in text.strip()[1:]:
            head, tail = text.strip()[0], text.strip()[1:]
            a, b = tail.split("-", 1)
            a, b = int(head + a), int(b)
        else:
            a = b = int(text)
    except ValueError:
        raise BatchError(f"--frames: expected A-B or A, got '{text}'") from None
    if b < a:
        raise BatchError(f"--frames: end {b} is before start {a}")
    return a, b


def parse_resolution(text: str | None) -> tuple[int, int] | None:
    if text is None:
        return None
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise BatchError(f"--resolution: expected WxH, got '{text}'") from None
    if w <= 0 or h <= 0 or w > 16384 or h > 16384:
        raise BatchError(f"--resolution: {w}x{h} is out of range 1..16384")
    return w, h


def parse_settings(items: list[str]) -> dict:
    """['key=value', ...] -> dict, checked against the GI settings."""
    from ._core import core

    out = {}
    for item in items or []:
        if "=" not in item:
            raise BatchError(f"--set: expected key=value, got '{item}'")
        key, value = item.split("=", 1)
        out[key.strip()] = value.strip()
    try:
        core.scene.GISettings().updated(**out)
    except ValueError as exc:
        raise BatchError(f"--set: {exc}") from None
    return out


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m lpv_addon.batch", description=__doc__.split("\n")[0])
    p.add_argument("blend", nargs="?", help="the .blend file to render")
    p.add_argument("--demo", action="store_true", help="render the built-in Cornell box")
    p.add_argument("--out", help="output folder, created if missing (default: the scene's "
                   "render output path)")
    which = p.add_mutually_exclusive_group()
    which.add_argument("--frames", help="frame range A-B or frame A (default: the current frame)")
    which.add_argument("--animation", action="store_true",
                       help="the scene's frame range and step, as blender -a")
    p.add_argument("--resolution", help="WxH (default: the scene's render resolution)")
    p.add_argument("--preset", type=str.lower, choices=[k.lower() for k in PRESETS],
                   help="quality preset, as Scene > LPV > Quality (--set goes on top)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a GI setting (repeatable), e.g. grid_resolution=32")
    p.add_argument("--quiet", action="store_true", help="no progress on stderr")
    return p


def _ensure_properties() -> None:
    """Register Scene/Light/Object/Material.lpv when the add-on is not enabled (the CLI), so
    the .blend's GI settings, flags and their animation (keyframed intensity) are read."""
    import bpy

    if not hasattr(bpy.types.Scene, "lpv"):
        from . import properties

        properties.register()


def open_scene(args) -> object:
    """Load the .blend (or build the demo) and return the bpy scene to render."""
    import bpy

    _ensure_properties()
    if args.demo:
        if args.blend:
            raise BatchError("give either a .blend file or --demo, not both")
        from .scene_io import demo

        demo.cornell_box("SPOT", resolution=(256, 256))
        scene = bpy.context.scene
        scene.frame_start = scene.frame_end = 1  # a still: one frame unless --frames says more
        return scene
    if not args.blend:
        raise BatchError("no .blend file given (or use --demo)")
    path = Path(args.blend)
    if not path.is_file():
        raise BatchError(f"cannot read '{path}': no such file")
    with open(path, "rb") as fh:
        magic = fh.read(7)
    if magic not in (b"BLENDER",) and magic[:2] not in (b"\x1f\x8b", b"\x28\xb5"):
        raise BatchError(f"cannot read '{path}': not a .blend file")
    try:
        bpy.ops.wm.open_mainfile(filepath=str(path), load_ui=False)
    except RuntimeError as exc:
        raise BatchError(f"cannot read '{path}': {str(exc).strip().splitlines()[-1]}") from None
    scene = bpy.context.scene
    if scene.camera is None:
        raise BatchError(f"scene '{scene.name}' in '{path}' has no active camera")
    return scene


def run(argv: list[str] | None = None) -> int:
    """The CLI; returns the exit code."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # argparse already printed its one-line reason
        return USAGE_ERROR if exc.code else 0
    try:
        frames = parse_frames(args.frames)
        resolution = parse_resolution(args.resolution)
        overrides = {**PRESETS.get((args.preset or "").upper(), {}), **parse_settings(args.set)}
        scene = open_scene(args)  # the output folder is made only once the input is good
        if args.animation:
            from .render.frames import animation_frames

            frames = animation_frames(scene)
        frames = frames or (scene.frame_current, scene.frame_current)
    except BatchError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return USAGE_ERROR
    except KeyboardInterrupt:
        print("cancelled after 0 frames", file=sys.stderr)
        return INTERRUPTED
    return render_frames(scene, args.out, frames, resolution, overrides, args.quiet)


def render_frames(scene, out, frames, resolution, overrides: dict, quiet: bool) -> int:
    """Render ``frames`` (default: the scene's range) into ``out`` (None: the render output
    path) in this process. Returns the exit code: 2 with a one-line reason when the output
    cannot be written, a frame cannot be extracted or the engine refuses its settings; 130
    on Ctrl-C, finished frames kept."""
    job = None
    try:
        from .render.frames import BatchJob

        def log(msg: str) -> None:
            if not quiet or msg.startswith("warning:"):
                print(msg, file=sys.stderr, flush=True)

        job = BatchJob(scene, out, frames, resolution, overrides, in_process=True, log=log)
        job.run()
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return USAGE_ERROR
    except KeyboardInterrupt:
        n = len(job.done) if job is not None else 0
        print(f"cancelled after {n} frame{'s' * (n != 1)}", file=sys.stderr)
        return INTERRUPTED
    return 0


def main() -> None:
    sys.exit(run())


if __name__ == "__main__":
    main()
