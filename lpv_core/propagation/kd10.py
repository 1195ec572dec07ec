"""KD10's propagation (``angular="sh"``): clamped 2-band SH, face to face [KD10 sec. 4.3].
Numpy only: the baseline the report measures the product's transport against.

Each destination cell gathers from its 6 face neighbours. For a source at -d, light reaches
the destination's far face (w_eval = w_reproj = d, solid angle 4 atan(sqrt(11)/33)) and its four
side faces (w_eval from the source centre to the side-face centre, (+-1/sqrt5, 0, 2/sqrt5) in
d's frame, w_reproj the side face's normal, solid angle 2 atan(3 sqrt(11)/11) - pi/3). The flux
through a face, Phi_f = dOmega_f max(0, <I_src, Y(w_eval)>), is re-emitted in the destination
as a Lambertian VPL: (Phi_f / pi) lobe(w_reproj).

The 30 face solid angles tile the sphere (6 (0.4006696846 + 4 x 0.4234313544) = 4 pi), so an
isotropic cell passes on exactly its flux. Clamping the 2-band SH at zero can inflate the flux of
a peaked lobe (by up to 1/8); we scale each cell's outgoing flux down to the flux it holds, so
that energy never grows under propagation (our addition; KD10 leaves this implicit).
"""

from __future__ import annotations

import numpy as np

from .. import sh
from .quadrature import AXES
from .result import PropagationResult, flux

FRONT_SOLID_ANGLE = 4.0 * np.arctan(np.sqrt(11.0) / 33.0)  # 0.4006696846
SIDE_SOLID_ANGLE = 2.0 * np.arctan(3.0 * np.sqrt(11.0) / 11.0) - np.pi / 3.0  # 0.4234313544


def face_tables():
    """Evaluation directions x solid angle (4, 30) and re-projection lobes / pi (6, 5, 4): the
    far face re-emits along d, a side face along its own normal (KD10)."""
    evals = np.zeros((6, 5, 4))
    reproj = np.zeros((6, 5, 4))
    inv5 = 1.0 / np.sqrt(5.0)
    for i, d in enumerate(AXES):
        a = int(np.argmax(np.abs(d)))
        others = [np.eye(3)[j] for j in range(3) if j != a]
        evals[i, 0] = sh.evaluate_basis(d) * FRONT_SOLID_ANGLE
        reproj[i, 0] = sh.cosine_lobe(d) / np.pi
        f = 1
        for e in others:
            for s in (1.0, -1.0):
                w_eval = s * e * inv5 + d * 2.0 * inv5
                evals[i, f] = sh.evaluate_basis(w_eval) * SIDE_SOLID_ANGLE
                reproj[i, f] = sh.cosine_lobe(s * e) / np.pi
                f += 1
    return evals.reshape(30, 4).T.copy(), reproj


EVAL_TABLE, REPROJ_TABLE = face_tables()
_TABLES: list = []


def tables():
    """The face tables in float32 (cached): what ``step`` multiplies by."""
    if not _TABLES:
        ev, rp = face_tables()
        _TABLES.append((ev.astype(np.float32), rp.astype(np.float32)))
    return _TABLES[0]


def _shift_add(dst: np.ndarray, src: np.ndarray, axis_index: int) -> None:
    """dst[cell + d] += src[cell] for the axis direction AXES[axis_index]."""
    axis = axis_index // 2
    lo = [slice(None)] * 3
    hi = [slice(None)] * 3
    if axis_index % 2 == 0:  # +axis
        lo[axis], hi[axis] = slice(1, None), slice(None, -1)
    else:
        lo[axis], hi[axis] = slice(None, -1), slice(1, None)
    dst[tuple(lo)] += src[tuple(hi)]


def step(values: np.ndarray, visibility: np.ndarray | None = None) -> np.ndarray:
    """One propagation step of an (R, R, R, 3, 4) grid; returns the newly arrived intensity.

    ``visibility`` (6, R, R, R) optionally scales what each cell sends towards each axis
    direction (1 - blocking potential of the face it crosses)."""
    r = values.shape[0]
    src = values.reshape(-1, 4)
    eval_table, reproj_table = tables()
    face_flux = np.maximum(src @ eval_table, 0.0)  # (M, 30)
    total = face_flux.sum(axis=1)
    held = np.maximum(src[:, 0], 0.0) * np.float32(sh.SQRT_4PI)
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(total > held, held / total, 1.0).astype(np.float32)
    face_flux *= scale[:, None]
    face_flux = face_flux.reshape(r, r, r, 3, 6, 5)
    out = np.zeros_like(values)
    for i in range(6):
        sent = face_flux[..., i, :] @ reproj_table[i]  # (R,R,R,3,4)
        if visibility is not None:
            sent *= visibility[i][..., None, None]
        _shift_add(out, sent, i)
    return out


def propagate(injected: np.ndarray, iterations: int, min_fraction: float = 1e-3,
              visibility: np.ndarray | None = None, occlude_first_step: bool = False,
              capture_outflow: bool = False) -> PropagationResult:
    """Accumulate ``iterations`` steps, stopping once a step carries less than
    ``min_fraction`` of the injected flux (light moves one cell per step).

    The first step ignores ``visibility`` unless ``occlude_first_step`` (KD10: injected light
    sits next to the surface it left, which must not block it). ``capture_outflow``: the grid
    is stepped padded by one cell, and what arrives in the pad (what left the volume) is moved
    to the result's ``outflow`` ((R+2)^3 grid) instead of being dropped."""
    cur, vis_all, outflow, shell = injected, visibility, None, None
    if capture_outflow:
        cur = np.pad(injected.astype(np.float32), ((1, 1), (1, 1), (1, 1), (0, 0), (0, 0)))
        if visibility is not None:
            vis_all = np.pad(visibility, ((0, 0), (1, 1), (1, 1), (1, 1)), constant_values=1.0)
        shell = np.ones(cur.shape[:3], bool)
        shell[1:-1, 1:-1, 1:-1] = False
        outflow = np.zeros_like(cur)
    acc = injected.astype(np.float32, copy=True)
    total0 = float(flux(injected).sum())
    fraction = 1.0 if total0 > 0 else 0.0
    done = 0
    early = total0 <= 0 and (capture_outflow or int(iterations) > 0)
    for _ in range(0 if total0 <= 0 else max(int(iterations), 0)):
        cur = step(cur, vis_all if (done > 0 or occlude_first_step) else None)
        if outflow is not None:
            outflow[shell] += cur[shell]
            cur[shell] = 0.0
            acc += cur[1:-1, 1:-1, 1:-1]
        else:
            acc += cur
        done += 1
        fraction = float(flux(cur).sum()) / total0
        if fraction < min_fraction:
            early = True
            break
    return PropagationResult(acc, done, flux(injected), fraction, early, outflow)
