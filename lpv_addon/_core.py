"""Finds lpv_core: a sibling subpackage inside the extension, or top-level from the repo."""

try:  # inside the extension package (bl_ext.<repo>.lpv_gi.lpv_addon)
    from .. import lpv_core as core
except (ImportError, ValueError):  # run from the repo root: python -m lpv_addon.batch
    import lpv_core as core

__all__ = ["core"]
