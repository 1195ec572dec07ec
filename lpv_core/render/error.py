"""How far a picture is from a reference: the one relative RMSE that the report, the add-on's
Compare with Cycles operator and the tests quote, and the indirect term they compare."""

from __future__ import annotations

import math

import numpy as np


def indirect_term(passes: dict) -> np.ndarray:
    """Diffuse Indirect x Diffuse Color, (H, W, 3) float64: the indirect diffuse light a pixel
    shows (Cycles' pass names)."""
    return (np.asarray(passes["Diffuse Indirect"])[..., :3].astype(np.float64)
            * np.asarray(passes["Diffuse Color"])[..., :3].astype(np.float64))


def relative_rmse(test: np.ndarray, ref: np.ndarray) -> float:
    """sqrt(mean((test - ref)^2)) / mean(ref) over every pixel and channel; NaN where the
    reference is black (no light to be relative to)."""
    ref = np.asarray(ref, np.float64)
    m = float(np.mean(ref))
    if not m > 0:
        return math.nan
    return float(np.sqrt(np.mean((np.asarray(test, np.float64) - ref) ** 2)) / m)


def mean_ratio(test: np.ndarray, ref: np.ndarray) -> float:
    """mean(test) / mean(ref): above 1 the picture is too bright overall; NaN where the
    reference is black."""
    m = float(np.mean(np.asarray(ref, np.float64)))
    return float(np.mean(np.asarray(test, np.float64)) / m) if m > 0 else math.nan
