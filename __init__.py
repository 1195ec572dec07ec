"""LPV GI: real-time diffuse global illumination with Cascaded Light Propagation Volumes."""


def register() -> None:
    from . import lpv_addon

    lpv_addon.register()


def unregister() -> None:
    from . import lpv_addon

    lpv_addon.unregister()
