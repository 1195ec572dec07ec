"""Blender scenes -> lpv_core scenes (``extract``: an evaluated depsgraph into a core Scene) and
the built-in Cornell box that ``python -m lpv_addon.batch --demo`` renders (``demo``)."""
