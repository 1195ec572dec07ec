"""Light propagation between LPV cells [KD10 sec. 4.3], two transport models (``angular``):

- "dom" (the product, the default): each cell's injected light is unfolded into flux along 64
  fixed directions (quadrature.py), launched from where surface light leaves its surface
  (ordinates.py), and the limit of infinitely many semi-Lagrangian steps is solved in one
  transport sweep (sweep.py; compiled: one pass per octant, kernels/sweep.py). Returns bands
  0-2.
- "sh" (KD10's clamped 2-band SH, kd10.py, numpy only): the baseline, stepped ``iterations``
  times with an early stop. Returns KD10's 4 coefficients.

Both take KD10's grids of 4 SH coefficients per colour per cell (injection.py).
"""

from __future__ import annotations

import numpy as np

from .. import sh
from ..scene.model import ANGULAR_MODELS
from . import kd10
from . import sweep as transport_sweep
from .ordinates import first_arrivals
from .quadrature import AXES, OFFSETS
from .result import PropagationResult, flux

__all__ = [
    "ANGULAR_MODELS",
    "AXES",
    "OFFSETS",
    "PropagationResult",
    "coefficients",
    "first_arrivals",
    "flux",
    "propagate",
]



def coefficients(angular: str) -> int:
    """SH coefficients per colour of a propagated grid: 9 (bands 0-2) for "dom", whose
    per-direction flux is folded once for the lookup, else KD10's 4."""
    return sh.BANDS2 if angular == "dom" else 4


def propagate(
    injected: np.ndarray,
    iterations: int = 0,
    min_fraction: float = 1e-3,
    visibility: np.ndarray | None = None,
    *,
    angular: str = "dom",
    occlude_first_step: bool = False,
    capture_outflow: bool = False,
    launch: bool = False,
    passing: np.ndarray | None = None,
) -> PropagationResult:
    """Propagate the injected grid (R, R, R, 3, 4) through the face transmittances
    ``visibility`` (6, R, R, R) or None.

    ``angular="dom"`` solves the limit of infinitely many steps in one transport sweep
    (sweep.propagate): ``iterations`` and ``min_fraction`` do not apply, the result's
    ``iterations`` is 0 with ``swept`` set. ``launch``: ``injected`` is light just emitted by
    surfaces (VPLs half a cell off them), its first step starts from the surface
    (ordinates.launch); ``passing``: light handed on from an inner cascade
    (cascades.hand_on), which left no surface and takes plain steps.
    ``angular="sh"`` accumulates ``iterations`` KD10 steps, stopping once a step carries less
    than ``min_fraction`` of the injected flux (kd10.propagate); ``passing`` is added to
    ``injected`` and ``launch`` does not apply.
    The first step ignores ``visibility`` unless ``occlude_first_step`` (KD10: injected light
    sits next to the surface it left, which must not block it). ``capture_outflow`` keeps what
    leaves the volume (the result's ``outflow``, an (R+2)^3 grid whose shell holds it) for
    the next coarser cascade."""
    if angular == "dom":
        return transport_sweep.propagate(injected, visibility, occlude_first_step,
                                         capture_outflow, launch, passing)
    if angular != "sh":
        raise ValueError(f"angular must be one of {ANGULAR_MODELS}, not {angular!r}")
    if passing is not None:
        injected = injected + passing
    return kd10.propagate(injected, iterations, min_fraction, visibility, occlude_first_step,
                          capture_outflow)
