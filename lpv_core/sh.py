"""Two-band spherical harmonics (4 coefficients) as used by KD10.

Order (Y00, Y1-1, Y10, Y11) = (0.282094792, -0.488602512 y, 0.488602512 z, -0.488602512 x).
The clamped cosine lobe max(0, <n, w>) projects to (c0, -c1 n_y, c1 n_z, -c1 n_x) with
c0 = sqrt(pi)/2 and c1 = sqrt(pi/3), so that lobe(n) . Y(w) = 1/4 + <n, w>/2.
"""

from __future__ import annotations

import numpy as np

Y0 = 0.28209479177387814  # 1 / (2 sqrt(pi))
Y1 = 0.4886025119029199  # sqrt(3) / (2 sqrt(pi))
C0 = 0.886226925452758  # sqrt(pi) / 2: clamped cosine, band 0
C1 = 1.0233267079464885  # sqrt(pi / 3): clamped cosine, band 1
SQRT_4PI = 3.5449077018110318  # integral of Y00 over the sphere is SQRT_4PI * Y0 = 1


def _signs_xyz(d: np.ndarray) -> np.ndarray:
    """(..., 3) directions -> (..., 3) in coefficient order (-y, z, -x)."""
    d = np.asarray(d)
    return np.stack([-d[..., 1], d[..., 2], -d[..., 0]], axis=-1)


def evaluate_basis(d: np.ndarray) -> np.ndarray:
    """Y(w) for unit directions (..., 3) -> (..., 4)."""
    d = np.asarray(d, np.float64)
    band0 = np.full(d.shape[:-1] + (1,), Y0)
    return np.concatenate([band0, Y1 * _signs_xyz(d)], axis=-1)


def cosine_lobe(n: np.ndarray) -> np.ndarray:
    """SH projection of max(0, <n, w>) for unit normals (..., 3) -> (..., 4)."""
    n = np.asarray(n, np.float64)
    band0 = np.full(n.shape[:-1] + (1,), C0)
    return np.concatenate([band0, C1 * _signs_xyz(n)], axis=-1)


def integral(coeffs: np.ndarray) -> np.ndarray:
    """Integral over the sphere of the function with these coefficients (only band 0 counts)."""
    return np.asarray(coeffs)[..., 0] * (SQRT_4PI * Y0) * SQRT_4PI
