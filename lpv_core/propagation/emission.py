"""The angular density of light just emitted by diffuse surfaces, read from a cell's 2-band SH.

A cell of the injected grid stores 4 SH coefficients per colour: band 0 is its flux, band 1 its
net flux vector (``moments``). The discrete-ordinates transport unfolds that light into flux per
direction (ordinates.unfold) with ``emission_density``: a cos^n lobe around the mean direction
whose mean cosine matches the moments' (n = 1 for one Lambertian emitter), never emitting behind
the mean direction; KD10's clamped 2-band SH instead emits a quarter of its peak sideways and
keeps emitting 30 degrees below its own surface.
"""

from __future__ import annotations

import numpy as np

from .. import sh

# Flux-weighted mean cosine of a diffuse emitter's light, int cos^2 / int cos = 2/3: the
# injected VPL lobe and the emission reading's cos^1.
LAMBERTIAN_MEAN_COSINE = 2.0 / 3.0
MAX_MEAN_COSINE = 0.995  # a beam narrower than any cell's solid angles
# Net flux vector from band-1 coefficients: F = a1 * Y1 * 4 pi / 3 per axis.
FLUX_FROM_BAND1 = sh.Y1 * 4.0 * np.pi / 3.0


def moments(coeffs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(..., 4) SH -> flux Phi (...), mean cosine r in [0, MAX] (...), unit direction (..., 3).
    Scale-free: the same r and direction for any flux float32 holds (1e-30 W to 1e30 W)."""
    c = np.asarray(coeffs)
    held = np.maximum(c[..., 0], 0.0) * np.float32(sh.SQRT_4PI)
    # Coefficient order (Y00, Y1-1 ~ -y, Y10 ~ z, Y11 ~ -x).
    vec = np.stack([-c[..., 3], -c[..., 1], c[..., 2]], axis=-1) * np.float32(FLUX_FROM_BAND1)
    wide = vec.astype(np.float64)  # squared in float64: no overflow or underflow at any flux
    norm = np.sqrt((wide * wide).sum(axis=-1)).astype(vec.dtype)
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.where(held > 0, norm / held, 0.0)
        d = np.where(norm[..., None] > 0, vec / norm[..., None], 0.0)
    r = np.clip(r, 0.0, MAX_MEAN_COSINE).astype(c.dtype, copy=False)
    return held, r, d.astype(c.dtype, copy=False)


def emission_exponent(r: np.ndarray) -> np.ndarray:
    """n of emission_density's cos^n for mean cosine r: (2r - 1) / (1 - r) with r clipped to
    [1/2, 2/3], exactly 1 at the Lambertian bound (a flat emitter; the formula in float32
    gives 1 + 2e-7 there, and a cosine needs no power)."""
    rr = np.clip(r, 0.5 + 1e-6, LAMBERTIAN_MEAN_COSINE)
    return np.where(rr >= LAMBERTIAN_MEAN_COSINE, 1.0, (2.0 * rr - 1.0) / (1.0 - rr)).astype(
        rr.dtype, copy=False)


def emission_density(r: np.ndarray, cosines: np.ndarray) -> np.ndarray:
    """Unnormalised angular density of light just emitted by diffuse surfaces, for mean
    cosine r (broadcast against ``cosines`` = <d, w>).

    A VPL emits max(0, cos)/pi (its injected SH is that lobe, mean cosine 2/3); a maximum-entropy
    (vMF) reading of the same moments would send 4 % of it backwards through its own surface. For the first step
    out of the injected grid we read cos^n with n = (2r - 1) / (1 - r) (mean cosine
    (n + 1) / (n + 2) = r: n = 1 for one emitter), and below r = 1/2 (emitters facing apart
    in one cell) the mix (1 - 2r) isotropic + 2r uniform hemisphere, whose mean cosine is r.
    Neither emits behind the mean direction once r >= 1/2."""
    r = np.asarray(r)
    c = np.asarray(cosines)
    up = c > 0
    n = emission_exponent(r)
    with np.errstate(divide="ignore"):
        powered = np.where(up, np.where(n == 1.0, c, np.exp(n * np.log(np.where(up, c, 1.0)))),
                           0.0)
    return np.where(r > 0.5, powered, (1.0 - 2.0 * r) + 4.0 * r * up)
