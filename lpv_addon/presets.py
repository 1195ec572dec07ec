"""Quality presets, bpy-free: the one table behind Scene > LPV > Quality and the batch CLI's
``--preset``."""

SETTINGS = {
    "DRAFT": {"grid_resolution": 16, "rsm_resolution": 128, "cascades": 3},
    "PREVIEW": {"grid_resolution": 32, "rsm_resolution": 256, "cascades": 3},
    "HIGH": {"grid_resolution": 48, "rsm_resolution": 512, "cascades": 3},
}
