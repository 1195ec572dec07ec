"""The LPV grid: a regular lattice of cells holding SH coefficients per colour channel.

Storage is (R, R, R, 3, K) float32 indexed [x, y, z, colour, coefficient]. A cell's value is
the radiant intensity (W/sr) of the light passing through it [KD10 sec. 4]. Injected light
holds KD10's 2 bands (K = 4); a propagated discrete-ordinates grid (``angular="dom"``) holds
bands 0-2 (K = 9, sh.evaluate_basis2), KD10's own propagation ("sh") stays at K = 4.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

INJECTED_COEFFICIENTS = 4  # KD10's 2-band SH of injected light per colour


@dataclass(frozen=True)
class Grid:
    """Placement of one cascade: world origin of its min corner, cell size and resolution."""

    origin: tuple[float, float, float]
    cell_size: float
    resolution: int

    @property
    def origin_array(self) -> np.ndarray:
        return np.asarray(self.origin, np.float64)

    def shape(self, coefficients: int = INJECTED_COEFFICIENTS) -> tuple[int, int, int, int, int]:
        """(R, R, R, 3, coefficients): the array shape of a grid of this placement."""
        r = self.resolution
        return (r, r, r, 3, coefficients)

    def zeros(self, coefficients: int = INJECTED_COEFFICIENTS) -> np.ndarray:
        return np.zeros(self.shape(coefficients), np.float32)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        lo = self.origin_array
        return lo, lo + self.cell_size * self.resolution

    def cell_coords(self, positions: np.ndarray) -> np.ndarray:
        """Continuous cell coordinates: integer values sit on cell centres."""
        return (np.asarray(positions, np.float64) - self.origin_array) / self.cell_size - 0.5


def fit_grid(lo, hi, resolution: int, padding_cells: float = 1.0) -> Grid:
    """A cubic grid enclosing the box [lo, hi] with ``padding_cells`` of margin on each side.

    The placement depends only on the box, so translating or scaling the scene moves the grid
    with it (results do not depend on where the scene sits in the world).
    """
    lo = np.asarray(lo, np.float64)
    hi = np.asarray(hi, np.float64)
    extent = float(np.max(hi - lo))
    if not np.isfinite(extent) or extent <= 0:
        extent = max(float(np.max(np.abs(lo))) * 1e-6, 1e-6)
    usable = max(resolution - 2.0 * padding_cells, 1.0)
    cell = extent / usable
    centre = 0.5 * (lo + hi)
    origin = centre - 0.5 * cell * resolution
    return Grid(tuple(float(v) for v in origin), float(cell), int(resolution))
