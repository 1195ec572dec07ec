"""Image textures a material's diffuse albedo reads per point: pixels in scene-linear colour
and how Blender's Image Texture node samples them (interpolation, extension)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

INTERPOLATIONS = ("Linear", "Closest", "Cubic", "Smart")
EXTENSIONS = ("REPEAT", "EXTEND", "CLIP", "MIRROR")


@dataclass
class Texture:
    """An image as the Image Texture node reads it: ``pixels`` (H, W, 3) float32 scene-linear
    colour (the image's colour space already applied; alpha already applied as the node's
    Color output gives it), rows bottom-first like Blender's ``Image.pixels``; ``digest``
    identifies the content (the change tracking and the worker's upload-once key)."""

    name: str
    pixels: np.ndarray = field(repr=False)
    interpolation: str = "Linear"
    extension: str = "REPEAT"
    digest: str = ""
