"""Blender glue for LPV GI: properties, panels, operators, extraction and the batch CLI."""


def register() -> None:
    from . import properties

    properties.register()


def unregister() -> None:
    from . import properties

    properties.unregister()
