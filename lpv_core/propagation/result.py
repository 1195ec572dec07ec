"""What a propagation returns, and the flux a grid holds (shared by both transport models)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import sh


@dataclass
class PropagationResult:
    """Accumulated intensity sum_k P^k(I0) and how the propagation went."""

    values: np.ndarray
    iterations: int
    injected_flux: np.ndarray
    remaining_fraction: float
    stopped_early: bool
    # With capture_outflow: (R+2)^3 grid whose one-cell shell holds what left the volume
    # (summed over steps), to be handed on to the next coarser cascade.
    outflow: np.ndarray | None = None
    swept: bool = False  # solved by a transport sweep (the limit of infinitely many steps)


def flux(grid_values: np.ndarray) -> np.ndarray:
    """Flux (W) per colour held by a grid (..., 3, 4): the integral of positive band-0 terms.
    Summed colour by colour over a contiguous copy (numpy's pairwise sum: closer to the
    float64 sum than column sums)."""
    band0 = np.maximum(grid_values[..., 0], 0.0).reshape(-1, 3)
    return np.ascontiguousarray(band0.T).sum(axis=1) * sh.SQRT_4PI
