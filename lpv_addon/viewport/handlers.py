"""App handlers and the refresh timer of the live viewport.

- ``depsgraph_update_post``: records what changed (geometry, transforms, materials, lights,
  objects added or removed); camera moves and view-only changes do not touch the LPV.
- ``frame_change_post``: ``frame_set`` and playback fire this, not a depsgraph update.
- ``undo_post``/``redo_post``: the restored state is re-extracted (we keep no bpy references).
- ``load_pre``/``load_post``: results, GPU resources and the worker of the old file go
  (:func:`reset`); the new file starts clean.
All are ``@persistent`` so the add-on keeps working after a file load; ``unregister`` removes
every one of them (also stale copies from an earlier load of this module), the timer and the
overlay's draw handler.
"""

from __future__ import annotations

import bpy
from bpy.app.handlers import persistent

from . import live, overlay

# Data that does not change GI (cameras move the view, not the LPV grid).
_IGNORED_OBJECT_TYPES = frozenset({"CAMERA", "SPEAKER", "LIGHT_PROBE"})


def changes(depsgraph) -> list[str]:
    """What a depsgraph update changed that the LPV depends on ([]: nothing)."""
    out = []
    for update in depsgraph.updates:
        ident = update.id
        orig = getattr(ident, "original", ident)
        if isinstance(orig, bpy.types.Object):
            if orig.type in _IGNORED_OBJECT_TYPES:
                continue
            if orig.type == "EMPTY" and getattr(orig.lpv, "area_type", "NONE") == "NONE":
                continue
            kind = "geometry" if update.is_updated_geometry else "transform" \
                if update.is_updated_transform else "object"
            out.append(f"{kind}: {orig.name}")
        elif isinstance(orig, bpy.types.Material):
            out.append(f"material: {orig.name}")
        elif isinstance(orig, bpy.types.Light):
            out.append(f"light: {orig.name}")
        elif isinstance(orig, bpy.types.Collection):
            out.append("objects added or removed")
    return out


@persistent
def on_depsgraph_update(scene, depsgraph) -> None:
    for reason in changes(depsgraph):
        live.mark_dirty(reason)


@persistent
def on_frame_change(scene, depsgraph=None) -> None:
    live.mark_dirty("frame change")


@persistent
def on_undo(*_args) -> None:
    live.mark_dirty("undo/redo")


def reset() -> None:
    """Stop the worker, drop every result and the overlay's GPU resources made from them."""
    live.shutdown()
    overlay.free_resources()


@persistent
def on_load_pre(*_args) -> None:
    reset()


@persistent
def on_load_post(*_args) -> None:
    reset()
    live.mark_dirty("file loaded")
    if not bpy.app.timers.is_registered(timer):
        bpy.app.timers.register(timer, first_interval=0.5, persistent=True)


def timer() -> float | None:
    """The live refresh timer (bpy.app.timers): returns seconds to the next call."""
    try:
        return live.tick()
    except Exception as exc:  # noqa: BLE001 - a raising timer is dropped by Blender for good
        live.STATE.error = f"timer: {exc}"
        return 1.0


HANDLERS = (
    ("depsgraph_update_post", on_depsgraph_update),
    ("frame_change_post", on_frame_change),
    ("undo_post", on_undo),
    ("redo_post", on_undo),
    ("load_pre", on_load_pre),
    ("load_post", on_load_post),
)


def _ours(fn, mine) -> bool:
    """``fn`` is ``mine`` or a stale copy of it (same module and name, an earlier import)."""
    return fn is mine or (getattr(fn, "__module__", None) == mine.__module__
                          and getattr(fn, "__name__", None) == mine.__name__)


def registered_count() -> int:
    """Handlers, timers and draw handlers of ours that are installed right now."""
    n = sum(1 for name, fn in HANDLERS for h in getattr(bpy.app.handlers, name) if _ours(h, fn))
    n += int(bpy.app.timers.is_registered(timer))
    return n + overlay.handler_count()


def register() -> None:
    for name, fn in HANDLERS:
        lst = getattr(bpy.app.handlers, name)
        for h in [h for h in lst if _ours(h, fn)]:
            lst.remove(h)
        lst.append(fn)
    if not bpy.app.timers.is_registered(timer):
        bpy.app.timers.register(timer, first_interval=0.5, persistent=True)
    overlay.add_handler()


def unregister() -> None:
    overlay.remove_handler()
    if bpy.app.timers.is_registered(timer):
        bpy.app.timers.unregister(timer)
    for name, fn in HANDLERS:
        lst = getattr(bpy.app.handlers, name)
        for h in [h for h in lst if _ours(h, fn)]:
            lst.remove(h)
    reset()
