"""Blender glue for LPV GI, everything that touches bpy:

- ``properties``, ``ui``, ``operators``: Scene/Light/Object/Material.lpv, panels, bpy.ops.lpv;
- ``viewport/``: the live LPV (``live``), app handlers and the refresh timer (``handlers``),
  the overlay drawn with ``gpu`` (``overlay``);
- ``scene_io/``: Blender -> core scene (``extract``), the built-in Cornell box (``demo``);
- ``render/``: the render engine ``LPV_GI`` (``engine``; its Rendered viewport:
  ``viewport/rendered``), frame ranges to EXR (``frames``), the Cycles comparison (``compare``,
  ``cycles``);
- ``worker_client``: the ``lpv_core.worker`` process the engine runs in;
- ``batch``: the CLI, ``python -m lpv_addon.batch``.

``register`` installs properties, operators, panels, app handlers, the refresh timer, the
viewport draw handler and the render engine; ``unregister`` removes all of them, stops the
worker processes and drops every GPU resource, so enabling and disabling the add-on leaves nothing behind.
"""

_MODULES = ("properties", "operators", "ui", "viewport.handlers", "render.engine")


def _modules():
    import importlib

    return [importlib.import_module(f"{__name__}.{name}") for name in _MODULES]


def register() -> None:
    done = []
    try:
        for module in _modules():
            module.register()
            done.append(module)
    except Exception:
        for module in reversed(done):
            module.unregister()
        raise


def unregister() -> None:
    errors = []
    for module in reversed(_modules()):
        try:
            module.unregister()
        except (RuntimeError, ValueError, AttributeError) as exc:  # keep removing the rest
            errors.append(f"{module.__name__}: {exc}")
    if errors:
        raise RuntimeError("LPV GI unregister: " + "; ".join(errors))
