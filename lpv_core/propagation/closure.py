"""Maximum-entropy (M1) reading of a cell's 2-band SH: a von Mises-Fisher lobe.

A cell stores 4 SH coefficients per colour: band 0 is its flux, band 1 its net flux vector.
KD10 evaluates the 2-band SH itself, clamped at zero. That function is broad: a Lambertian VPL
emits a quarter of its peak intensity sideways and keeps emitting 30 degrees below its own
surface, so light diffuses (travels ~sqrt(k) cells in k steps) and surfaces light themselves.
The same two moments are also met by the maximum-entropy distribution
p(w) ~ exp(kappa <d, w>) (the M1 closure of radiative transfer), which keeps a beam a beam
(kappa -> inf as |F| / Phi -> 1), is isotropic for a zero flux vector, and is never negative.
The discrete-ordinates transport reads injected cells as emitted light (``emission_density``,
ordinates.unfold) and a 4-coefficient "dom" grid as such a lobe at lookup
(``cosine_expectation``); storage, injection and the moments themselves are unchanged.

For the mean cosine r = |F| / Phi we solve coth(kappa) - 1/kappa = r with the approximation
kappa = r (3 - r^2) / (1 - r^2) (Banerjee et al. 2005, JMLR 6, "Clustering on the unit
hypersphere using von Mises-Fisher distributions", eq. 4.4 with p = 3).
"""

from __future__ import annotations

import numpy as np

from .. import sh

# Flux-weighted mean cosine of a diffuse emitter's light, int cos^2 / int cos = 2/3: the
# injected VPL lobe and the emission reading's cos^1.
LAMBERTIAN_MEAN_COSINE = 2.0 / 3.0
# Angular models whose 4-coefficient cells are read as maximum-entropy lobes at lookup: "dom"
# (ordinates.py: folded into moments once, at the end; its lookup grid has 9 coefficients).
LOBE_MODELS = ("dom",)
MAX_MEAN_COSINE = 0.995  # kappa ~ 200: a beam narrower than any cell's solid angles
# Net flux vector from band-1 coefficients: F = a1 * Y1 * 4 pi / 3 per axis.
FLUX_FROM_BAND1 = sh.Y1 * 4.0 * np.pi / 3.0


def moments(coeffs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(..., 4) SH -> flux Phi (...), mean cosine r in [0, MAX] (...), unit direction (..., 3)."""
    c = np.asarray(coeffs)
    held = np.maximum(c[..., 0], 0.0) * np.float32(sh.SQRT_4PI)
    # Coefficient order (Y00, Y1-1 ~ -y, Y10 ~ z, Y11 ~ -x).
    vec = np.stack([-c[..., 3], -c[..., 1], c[..., 2]], axis=-1) * np.float32(FLUX_FROM_BAND1)
    norm = np.sqrt((vec * vec).sum(axis=-1))
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.where(held > 0, norm / held, 0.0)
        d = np.where(norm[..., None] > 0, vec / norm[..., None], 0.0)
    r = np.clip(r, 0.0, MAX_MEAN_COSINE).astype(c.dtype, copy=False)
    return held, r, d.astype(c.dtype, copy=False)


def kappa(r: np.ndarray) -> np.ndarray:
    """vMF concentration with mean cosine r (Banerjee et al. 2005 approximation)."""
    r = np.asarray(r)
    return r * (3.0 - r * r) / (1.0 - r * r)


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

    A VPL emits max(0, cos)/pi (its injected SH is that lobe, mean cosine 2/3); the vMF reading
    of the same moments sends 4 % of it backwards through its own surface. For the first step
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


def _azimuthal_mean(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Mean over phi of max(0, a cos(phi) + b) for a >= 0 (closed form)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        phi0 = np.arccos(np.clip(-b / np.where(a > 0, a, 1.0), -1.0, 1.0))
        partial = (a * np.sin(phi0) + b * phi0) / np.pi
    return np.where(b >= a, b, np.where(b <= -a, 0.0, partial))


def _integrand_table(n_r: int = 96, n_t: int = 129):
    """T[i, j] = E_p[max(0, <c, w>)] for a unit vMF p with mean cosine R[i], <c, mu> = T_[j]."""
    rs = np.linspace(0.0, MAX_MEAN_COSINE, n_r)
    ts = np.linspace(-1.0, 1.0, n_t)
    # Nodes in u = cos(theta) around mu = +z, dense near the pole for concentrated lobes.
    u = np.unique(np.concatenate([np.linspace(-1.0, 0.9, 600),
                                  1.0 - np.logspace(-6.0, -1.0, 1200), [1.0]]))
    du = np.gradient(u)  # trapezoid-like weights on the non-uniform nodes
    sin_t = np.sqrt(np.clip(1.0 - u * u, 0.0, 1.0))
    st = np.sqrt(np.clip(1.0 - ts * ts, 0.0, 1.0))
    g = _azimuthal_mean(st[:, None] * sin_t[None, :], ts[:, None] * u[None, :])  # (n_t, n_u)
    table = np.zeros((n_r, n_t))
    for i, r in enumerate(rs):
        w = np.exp(float(kappa(r)) * (u - 1.0)) * du  # vMF density in u (stable for large kappa)
        table[i] = g @ (w / w.sum())
    return rs, ts, table


_TABLE = None


def cosine_expectation(r: np.ndarray, t: np.ndarray) -> np.ndarray:
    """E_p[max(0, <c, w>)] for a vMF p with mean cosine r and <c, mean direction> = t.

    For r = 0 it is 1/4; for a beam (r -> 1) it tends to max(0, t).
    """
    global _TABLE
    if _TABLE is None:
        _TABLE = _integrand_table()
    rs, ts, table = _TABLE
    fr = np.clip(np.asarray(r, np.float64), 0, rs[-1]) / rs[-1] * (len(rs) - 1)
    ft = (np.clip(np.asarray(t, np.float64), -1, 1) + 1.0) / 2.0 * (len(ts) - 1)
    i0 = np.minimum(np.floor(fr).astype(int), len(rs) - 2)
    j0 = np.minimum(np.floor(ft).astype(int), len(ts) - 2)
    a = fr - i0
    b = ft - j0
    return ((1 - a) * (1 - b) * table[i0, j0] + a * (1 - b) * table[i0 + 1, j0]
            + (1 - a) * b * table[i0, j0 + 1] + a * b * table[i0 + 1, j0 + 1])
