"""The World: radiance arriving from infinitely far away in every direction, as an
equirectangular map in Blender's convention (Background colour x Strength, Sky or Environment
Texture), with the artist's GI intensity and on/off switch."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class World:
    """``radiance`` (H, W, 3) float32, W sr^-1 m^-2 per unit colour as Cycles reads the
    World's surface shader, equirectangular like Cycles' Environment Texture: rows bottom
    (nadir) first, column u = 0.5 - atan2(y, x) / (2 pi) (direction -X at the centre column's
    edge, as Cycles' direction_to_equirectangular), v = 0.5 + asin(z) / pi. A uniform world is
    a 1x1 map. ``gi_intensity`` scales its GI like a light's; ``enabled`` off: no World light
    at all (the Scene panel's switch); ``digest`` identifies the content."""

    name: str
    radiance: np.ndarray = field(default_factory=lambda: np.zeros((1, 1, 3), np.float32),
                                 repr=False)
    gi_intensity: float = 1.0
    enabled: bool = True
    digest: str = ""
