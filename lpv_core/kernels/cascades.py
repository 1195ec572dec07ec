"""Compiled cascade bookkeeping: the twins of cascades.assign and cascades.hand_on
(kernels/__init__.py), with the numpy reference's comparisons and arithmetic.
"""

from __future__ import annotations

import numpy as np

from ..grid import Grid
from ..runtime import jit


def assign(chain: list[Grid], positions: np.ndarray, margin_cells: float = 1.0) -> np.ndarray:
    """cascades.assign of a chain of two or more cascades by ``_assign_kernel``."""
    boxes = np.empty((len(chain) - 1, 2, 3))
    for i, g in enumerate(chain[:-1]):
        lo, hi = g.bounds()
        m = margin_cells * g.cell_size
        boxes[i, 0], boxes[i, 1] = lo + m, hi - m
    level = np.empty(positions.shape[0], np.int64)
    _assign_kernel(np.asarray(positions, np.float64), boxes, level)
    return level


def hand_on(finer: Grid, outflow: np.ndarray, coarser: Grid, target: np.ndarray) -> None:
    """cascades.hand_on of a C-contiguous ``outflow`` whose interior is empty into a
    C-contiguous ``target`` of its dtype, by ``_hand_on_kernel`` (the shell cells only)."""
    rp = outflow.shape[0]
    _hand_on_kernel(outflow.reshape(rp, rp, rp, 12), finer.origin_array,
                    float(finer.cell_size), coarser.origin_array, float(coarser.cell_size),
                    coarser.resolution, target.reshape(-1, 12))


@jit.kernel
def _assign_kernel(points, boxes, level):  # pragma: no cover - compiled
    """``assign`` point by point: the first box (lo, hi) holding it (bounds included), else
    the coarsest cascade (one past the boxes)."""
    for n in range(points.shape[0]):
        level[n] = boxes.shape[0]
        for i in range(boxes.shape[0]):
            x, y, z = points[n, 0], points[n, 1], points[n, 2]
            if (boxes[i, 0, 0] <= x <= boxes[i, 1, 0] and boxes[i, 0, 1] <= y <= boxes[i, 1, 1]
                    and boxes[i, 0, 2] <= z <= boxes[i, 1, 2]):
                level[n] = i
                break


@jit.kernel
def _hand_on_kernel(outflow, f_origin, f_cell, c_origin, c_cell, r, target):  # pragma: no cover
    """``hand_on`` over the shell cells of ``outflow`` (Rp, Rp, Rp, 12), in C order as its
    np.add.at adds them, with its arithmetic: a live cell's centre, the coarse cell holding
    it, its 12 values added there when that cell is inside."""
    rp = outflow.shape[0]
    for i in range(rp):
        for j in range(rp):
            inner = 0 < i < rp - 1 and 0 < j < rp - 1
            step = rp - 1 if inner else 1  # inside the shell's walls only k = 0 and rp - 1
            for k in range(0, rp, step):
                live = False
                for m in range(12):
                    if abs(outflow[i, j, k, m]) > 0:
                        live = True
                        break
                if not live:
                    continue
                ci = np.floor((f_origin[0] + (i - 1 + 0.5) * f_cell - c_origin[0]) / c_cell)
                cj = np.floor((f_origin[1] + (j - 1 + 0.5) * f_cell - c_origin[1]) / c_cell)
                ck = np.floor((f_origin[2] + (k - 1 + 0.5) * f_cell - c_origin[2]) / c_cell)
                if not (0 <= ci < r and 0 <= cj < r and 0 <= ck < r):
                    continue
                dest = (np.int64(ci) * r + np.int64(cj)) * r + np.int64(ck)
                for m in range(12):
                    target[dest, m] += outflow[i, j, k, m]
