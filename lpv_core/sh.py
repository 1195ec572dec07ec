"""Spherical harmonics: KD10's two bands (4 coefficients), and a third band for the
discrete-ordinates result (9 coefficients, ``angular="dom"``).

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


# Band 2 (real, orthonormal), appended after the 4 above in this order:
# (Y2-2, Y2-1, Y20, Y21, Y22) = (Y2A xy, Y2A yz, Y2B (3 z^2 - 1), Y2A xz, Y2C (x^2 - y^2)).
Y2A = 1.0925484305920792  # sqrt(15 / (4 pi))
Y2B = 0.31539156525252005  # sqrt(5 / (16 pi))
Y2C = 0.5462742152960396  # sqrt(15 / (16 pi))
BANDS2 = 9  # coefficients of bands 0-2

# Irradiance from radiance in SH (Ramamoorthi & Hanrahan 2001, "An efficient representation
# for irradiance environment maps", eq. 8): the clamped cosine max(0, cos) has Legendre
# coefficients 1/4, 1/2, 5/16 for l = 0, 1, 2, times 4 pi / (2l + 1) from the addition
# theorem: A_l = pi, 2 pi / 3, pi / 4. Odd bands above 1 vanish, so bands 0-2 leave out only
# l = 4 (A_4 = -pi / 24) and beyond.
IRRADIANCE_KERNEL = (np.pi, 2.0 * np.pi / 3.0, np.pi / 4.0)


def evaluate_basis2(d: np.ndarray) -> np.ndarray:
    """Y(w) of bands 0-2 for unit directions (..., 3) -> (..., 9), the first 4 as
    ``evaluate_basis``."""
    d = np.asarray(d, np.float64)
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    band2 = np.stack([Y2A * x * y, Y2A * y * z, Y2B * (3.0 * z * z - 1.0), Y2A * x * z,
                      Y2C * (x * x - y * y)], axis=-1)
    return np.concatenate([evaluate_basis(d), band2], axis=-1)


def irradiance_weights(n: np.ndarray, bands: int = 3) -> np.ndarray:
    """(..., 4 or 9) weights w with <coeffs, w> = sum_j Phi_j max(0, <w_j, -n>) for a cell whose
    coefficients are sum_j Phi_j Y(w_j) (flux Phi_j travelling along w_j), exact up to band
    ``bands - 1`` of the clamped cosine: the light arriving at a receiver with normal n."""
    y = evaluate_basis2(-np.asarray(n, np.float64))
    k = np.array([IRRADIANCE_KERNEL[0]] + [IRRADIANCE_KERNEL[1]] * 3
                 + [IRRADIANCE_KERNEL[2]] * 5)
    count = bands * bands
    return y[..., :count] * k[:count]
