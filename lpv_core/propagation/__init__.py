"""Light propagation between LPV cells [KD10 sec. 4.3], three angular models (``angular``):
"dom" (the default: flux along 64 directions per cell for the whole propagation,
ordinates.py), "m1" (a maximum-entropy lobe re-read from the moments at every step, step_m1)
and "sh" (KD10's clamped 2-band SH, below). All of them take and return KD10's grids of
4 SH coefficients per colour per cell.

"sh": each destination cell gathers from its 6 face neighbours. For a source at -d, light reaches
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

from dataclasses import dataclass

import numpy as np

from .. import sh
from ..runtime import jit
from . import closure, octants, ordinates
from . import sweep as transport_sweep

FRONT_SOLID_ANGLE = 4.0 * np.arctan(np.sqrt(11.0) / 33.0)  # 0.4006696846
SIDE_SOLID_ANGLE = 2.0 * np.arctan(3.0 * np.sqrt(11.0) / 11.0) - np.pi / 3.0  # 0.4234313544
REPROJECTIONS = ("kd10", "ray")
AXES = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], np.float64)


def face_tables(reprojection: str = "kd10"):
    """Evaluation directions x solid angle (4, 30) and re-projection lobes / pi (6, 5, 4).

    ``reprojection``: "kd10" re-emits side-face flux along the face normal (the paper);
    "ray" re-emits it along the ray through the face centre (w_eval), which keeps light moving
    forward and measured less diffusive (our variant, selectable for comparison).
    """
    if reprojection not in REPROJECTIONS:
        raise ValueError(f"reprojection must be one of {REPROJECTIONS}, not {reprojection!r}")
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
                reproj[i, f] = sh.cosine_lobe(s * e if reprojection == "kd10" else w_eval) / np.pi
                f += 1
    return evals.reshape(30, 4).T.copy(), reproj


EVAL_TABLE, REPROJ_TABLE = face_tables()
_TABLES = {}


def tables(reprojection: str = "kd10"):
    """Cached float32 face tables for a re-projection mode."""
    if reprojection not in _TABLES:
        ev, rp = face_tables(reprojection)
        _TABLES[reprojection] = (ev.astype(np.float32), rp.astype(np.float32))
    return _TABLES[reprojection]


def flux(grid_values: np.ndarray) -> np.ndarray:
    """Flux (W) per colour held by a grid (..., 3, 4): the integral of positive band-0 terms.
    Summed colour by colour over a contiguous copy (numpy's pairwise sum: 32^3, 0.6 ->
    0.08 ms, and closer to the float64 sum than the column sums it replaced)."""
    band0 = np.maximum(grid_values[..., 0], 0.0).reshape(-1, 3)
    return np.ascontiguousarray(band0.T).sum(axis=1) * sh.SQRT_4PI


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


ANGULAR_MODELS = ("sh", "m1", "dom")
_M1 = {}


def quadrature_directions(q: int = 64) -> np.ndarray:
    """(q, 3) near-uniform unit directions (Fibonacci sphere), each standing for 4 pi / q sr."""
    i = np.arange(q) + 0.5
    z = 1.0 - 2.0 * i / q
    phi = np.pi * (1.0 + 5.0**0.5) * i
    rho = np.sqrt(1.0 - z * z)
    return np.stack([rho * np.cos(phi), rho * np.sin(phi), z], axis=1)


M1_DIRECTIONS = 64
OFFSETS = [(a, b, c) for a in (-1, 0, 1) for b in (-1, 0, 1) for c in (-1, 0, 1)]


def _m1_tables(q: int = M1_DIRECTIONS):
    """Bundle directions (q, 3), the mean-cosine cap, and the (q, 27 x 4) advection matrix.

    A bundle moving one cell length along w from a cell spreads over the 27 neighbours with
    trilinear weights prod_axis (1 - |w_a|) or |w_a| (on the side w_a points to); it arrives as
    SH Y(w) per unit flux.

    The cap: a cell's lobe is read no narrower than the emission of a diffuse surface, mean
    cosine 2/3 (int cos^2 / int cos over the hemisphere), which is what every injected VPL
    holds. Two moments cannot tell a beam from a cell-sized bundle of diverging rays, and a
    vMF reading is more peaked about its mean than such a bundle, so a narrower reading pushes
    light towards the mean direction at every step and the error compounds: above a wide
    diffuse emitter the light piles up over its centre (measured: 1.8x too bright 4 cells
    above a 4-cell patch, 0.5x to the sides, the same at 32^3; docs/algorithm.md). The bundle
    spacing allows narrower lobes (kappa <= q / (4 pi), mean cosine 0.804 for q = 64), so the
    2/3 cap is the binding one.
    """
    if q not in _M1:
        dirs = quadrature_directions(q)
        adv = np.zeros((q, len(OFFSETS), 4))
        basis = sh.evaluate_basis(dirs)
        for k, off in enumerate(OFFSETS):
            w = np.ones(q)
            for axis in range(3):
                comp = dirs[:, axis]
                if off[axis] == 0:
                    w *= 1.0 - np.abs(comp)
                else:
                    w *= np.where(np.sign(comp) == off[axis], np.abs(comp), 0.0)
            adv[:, k, :] = w[:, None] * basis
        k_max = q / (4.0 * np.pi)
        r_max = min(1.0 / np.tanh(k_max) - 1.0 / k_max, closure.LAMBERTIAN_MEAN_COSINE)
        _M1[q] = (dirs.astype(np.float32), adv.reshape(q, -1).astype(np.float32), float(r_max))
    return _M1[q]


def step_m1(values: np.ndarray, visibility: np.ndarray | None = None,
            emission: bool = False) -> np.ndarray:
    """One step with the maximum-entropy reading: the cell's lobe (closure.py) is split into
    bundles along fixed directions, each advected one cell length semi-Lagrangian, and the
    arrivals summed as SH moments. Flux is conserved exactly (weights sum to one).
    ``emission``: the grid holds light just emitted by diffuse surfaces (the injected grid),
    read with closure.emission_density instead of the vMF.

    Only the box of cells holding light is read; arrivals are computed offset-major
    ((27 x 4, cells), one matmul) so each neighbour's share is one contiguous block."""
    r = values.shape[0]
    box = _live_box(values)
    if box is None:
        return np.zeros_like(values)
    dirs, _, r_max = _m1_tables()
    # Colour-major cells (3, x, y, z): per-offset work runs over long contiguous rows.
    sub = np.ascontiguousarray(values[box[0][0]:box[0][1], box[1][0]:box[1][1],
                                      box[2][0]:box[2][1]].transpose(3, 0, 1, 2, 4),
                               dtype=np.float32)
    shape = sub.shape[:4]
    held, mean_cos, d = closure.moments(sub.reshape(-1, 4))
    if emission:  # light just emitted by diffuse surfaces: no backward tail
        bundles = closure.emission_density(mean_cos[None, :], dirs @ d.T).astype(np.float32)
        bundles = np.where(bundles.sum(axis=0) > 0, bundles, np.float32(1.0))
    else:
        k = closure.kappa(np.minimum(mean_cos, r_max)).astype(np.float32)
        # kappa <= kappa(2/3) ~ 3.1, so exp(kappa cos) cannot overflow.
        bundles = np.exp(dirs @ (d * k[:, None]).T)  # (q, cells): empty ones get weight 0
    bundles *= (held / bundles.sum(axis=0)).astype(np.float32)[None, :]
    arr = (_m1_adv_t() @ bundles).reshape(len(OFFSETS), 4, *shape)
    offvis = _offset_visibilities(visibility)
    out = np.zeros((4, 3, r, r, r), np.float32)  # coefficient, colour, x, y, z
    for k_off, off in enumerate(OFFSETS):
        src_sl, dst_sl = [slice(None), slice(None)], [slice(None), slice(None)]
        vis_sl = []
        for axis in range(3):
            lo, hi = box[axis]
            s_lo, s_hi = max(lo, -off[axis]), min(hi, r - off[axis])  # sources landing inside
            if s_hi <= s_lo:
                break  # every source of this offset lands outside the grid
            src_sl.append(slice(s_lo - lo, s_hi - lo))
            dst_sl.append(slice(s_lo + off[axis], s_hi + off[axis]))
            vis_sl.append(slice(s_lo, s_hi))
        else:
            sent = arr[k_off][tuple(src_sl)]
            if offvis is not None:
                sent = sent * offvis[k_off][tuple(vis_sl)]
            out[tuple(dst_sl)] += sent
    return np.ascontiguousarray(out.transpose(2, 3, 4, 1, 0)).astype(values.dtype, copy=False)


def _live_box(values: np.ndarray):
    """Per axis [lo, hi) cell range of the cells holding light (band 0 > 0), or None."""
    live = (values[..., 0] > 0).any(axis=-1)
    box = []
    for axis in range(3):
        hit = np.nonzero(live.any(axis=tuple(a for a in range(3) if a != axis)))[0]
        if hit.size == 0:
            return None
        box.append((int(hit[0]), int(hit[-1]) + 1))
    return box


_ADV_T = {}
_OFFVIS: list = []  # [(visibility array, its 27 offset transmittances)], most recent first
OFFVIS_CACHE = 4  # visibility arrays whose offset transmittances are kept (one per cascade)


def _m1_adv_t() -> np.ndarray:
    """The advection matrix transposed to (27 x 4, q), contiguous (offset-major arrivals)."""
    if M1_DIRECTIONS not in _ADV_T:
        _ADV_T[M1_DIRECTIONS] = np.ascontiguousarray(_m1_tables()[1].T)
    return _ADV_T[M1_DIRECTIONS]


def _offset_visibilities(visibility: np.ndarray | None):
    """Transmittance towards each of the 27 offsets (float32 (R, R, R) each, OFFSETS order):
    ``_offset_visibility`` of every offset at once, as the outer product of the three axes'
    factors (-1: the lower face, 0: 1, +1: the upper face), multiplied in the same order.
    Cached for the last OFFVIS_CACHE visibility arrays (a propagation reuses one array for
    all its steps; an update of several cascades alternates between theirs)."""
    if visibility is None:
        return None
    for vis, table in _OFFVIS:
        if vis is visibility:
            return table
    v = np.asarray(visibility)
    one = np.ones((1,) + v.shape[1:], v.dtype)
    f = [np.concatenate([v[2 * a + 1][None], one, v[2 * a][None]]) for a in range(3)]
    prod = (f[0][:, None, None] * f[1][None, :, None]) * f[2][None, None, :]
    table = list(prod.reshape((27,) + v.shape[1:]).astype(np.float32, copy=False))
    _OFFVIS.insert(0, (visibility, table))
    del _OFFVIS[OFFVIS_CACHE:]
    return table


def _offset_visibility(visibility: np.ndarray, off) -> np.ndarray:
    """Transmittance towards a neighbour offset: the product over the axis faces it crosses."""
    v = np.ones(visibility.shape[1:], visibility.dtype)
    for axis in range(3):
        if off[axis] == 1:
            v = v * visibility[2 * axis]
        elif off[axis] == -1:
            v = v * visibility[2 * axis + 1]
    return v


def refuse_single_step(angular: str) -> None:
    """ValueError for "dom": a single step of moments is not defined there (the flux stays
    per direction between steps; every backend's ``step`` says so the same way)."""
    if angular == "dom":
        raise ValueError('angular="dom" keeps flux per direction between steps: use '
                         "propagate() or ordinates.step()")


def step(values: np.ndarray, visibility: np.ndarray | None = None,
         reprojection: str = "kd10", angular: str = "sh", emission: bool = False) -> np.ndarray:
    """One propagation step of an (R, R, R, 3, 4) grid; returns the newly arrived intensity.

    ``visibility`` (6, R, R, R) optionally scales what each cell sends towards each axis
    direction (1 - blocking potential of the face it crosses). ``angular``: "sh" evaluates the
    clamped 2-band SH (KD10); "m1" reads the cell as its maximum-entropy lobe and advects it
    (step_m1; ``reprojection`` unused). "dom" has no step on moments (see propagate).
    """
    refuse_single_step(angular)
    if angular == "m1":
        return step_m1(values, visibility, emission)
    r = values.shape[0]
    src = values.reshape(-1, 4)
    if angular == "sh":
        eval_table, reproj_table = tables(reprojection)
        face_flux = np.maximum(src @ eval_table, 0.0)  # (M, 30)
        total = face_flux.sum(axis=1)
        held = np.maximum(src[:, 0], 0.0) * np.float32(sh.SQRT_4PI)
        with np.errstate(divide="ignore", invalid="ignore"):
            scale = np.where(total > held, held / total, 1.0).astype(np.float32)
        face_flux *= scale[:, None]
    else:
        raise ValueError(f"angular must be one of {ANGULAR_MODELS}, not {angular!r}")
    face_flux = face_flux.reshape(r, r, r, 3, 6, 5)
    out = np.zeros_like(values)
    for i in range(6):
        sent = face_flux[..., i, :] @ reproj_table[i]  # (R,R,R,3,4)
        if visibility is not None:
            sent *= visibility[i][..., None, None]
        _shift_add(out, sent, i)
    return out


@dataclass
class PropagationResult:
    """Accumulated intensity sum_k P^k(I0) and how the iterations went."""

    values: np.ndarray
    iterations: int
    injected_flux: np.ndarray
    remaining_fraction: float
    stopped_early: bool
    # With capture_outflow: (R+2)^3 grid whose one-cell shell holds what left the volume
    # (summed over steps), to be handed on to the next coarser cascade.
    outflow: np.ndarray | None = None
    swept: bool = False  # solved by a transport sweep (the limit of infinitely many steps)


def coefficients(angular: str) -> int:
    """SH coefficients per colour of a propagated grid: 9 (bands 0-2) for "dom", whose
    per-direction flux is folded once for the lookup, else KD10's 4."""
    return sh.BANDS2 if angular == "dom" else 4


def propagate(
    injected: np.ndarray,
    iterations: int,
    min_fraction: float = 1e-3,
    visibility: np.ndarray | None = None,
    reprojection: str = "kd10",
    angular: str = "sh",
    occlude_first_step: bool = False,
    capture_outflow: bool = False,
    sweep: bool = False,
    launch: bool = False,
    passing: np.ndarray | None = None,
) -> PropagationResult:
    """Accumulate ``iterations`` propagation steps, stopping once a step carries less than
    ``min_fraction`` of the injected flux (light moves one cell per step).

    The first step ignores ``visibility`` unless ``occlude_first_step`` (KD10: injected light
    sits next to the surface it left, which must not block it). ``capture_outflow`` keeps what
    leaves the volume instead of dropping it (light passing on to an outer cascade).
    ``sweep`` (angular="dom" only; ignored by the others): solve for the limit of infinitely
    many steps in one transport sweep (sweep.py); ``iterations`` and ``min_fraction`` are
    then unused and the result's ``iterations`` is 0 with ``swept`` set.
    ``launch`` (angular="dom" only): ``injected`` is light just emitted by surfaces (VPLs
    injected half a cell off them); its first step starts from the surface (ordinates.launch).
    ``passing``: light handed on from an inner cascade (cascades.hand_on), which left no
    surface: it takes plain steps (the other models add it to ``injected``)."""
    if angular == "dom":
        if sweep:
            return _sweep_ordinates(injected, visibility, occlude_first_step, capture_outflow,
                                    launch, passing)
        return _propagate_ordinates(injected, iterations, min_fraction, visibility,
                                    occlude_first_step, capture_outflow, launch, passing)
    if passing is not None:
        injected = injected + passing
    if capture_outflow:
        return _propagate_capturing(injected, iterations, min_fraction, visibility,
                                    reprojection, angular, occlude_first_step)
    acc = injected.astype(np.float32, copy=True)
    cur = injected
    total0 = float(flux(injected).sum())
    fraction = 1.0 if total0 > 0 else 0.0
    done = 0
    early = False
    for _ in range(max(int(iterations), 0)):
        if total0 <= 0:
            early = True
            break
        vis = visibility if (done > 0 or occlude_first_step) else None
        cur = step(cur, vis, reprojection, angular, emission=done == 0)
        acc += cur
        done += 1
        fraction = float(flux(cur).sum()) / total0
        if fraction < min_fraction:
            early = True
            break
    return PropagationResult(acc, done, flux(injected), fraction, early)


def _propagate_capturing(injected, iterations, min_fraction, visibility, reprojection, angular,
                         occlude_first_step) -> PropagationResult:
    """propagate() on a grid padded by one cell; arrivals in the pad are moved to ``outflow``."""
    pad = ((1, 1), (1, 1), (1, 1), (0, 0), (0, 0))
    cur = np.pad(injected.astype(np.float32), pad)
    vis_pad = None
    if visibility is not None:
        vis_pad = np.pad(visibility, ((0, 0), (1, 1), (1, 1), (1, 1)), constant_values=1.0)
    shell = np.ones(cur.shape[:3], bool)
    shell[1:-1, 1:-1, 1:-1] = False
    outflow = np.zeros_like(cur)
    acc = injected.astype(np.float32, copy=True)
    total0 = float(flux(injected).sum())
    fraction = 1.0 if total0 > 0 else 0.0
    done = 0
    early = total0 <= 0
    for _ in range(0 if early else max(int(iterations), 0)):
        vis = vis_pad if (done > 0 or occlude_first_step) else None
        cur = step(cur, vis, reprojection, angular, emission=done == 0)
        outflow[shell] += cur[shell]
        cur[shell] = 0.0
        acc += cur[1:-1, 1:-1, 1:-1]
        done += 1
        fraction = float(flux(cur).sum()) / total0
        if fraction < min_fraction:
            early = True
            break
    return PropagationResult(acc, done, flux(injected), fraction, early, outflow)


def first_arrivals(injected: np.ndarray, visibility: np.ndarray | None,
                   occlude_first_step: bool, passing: np.ndarray | None = None):
    """(arrivals, total): the first dom step of ``injected`` launched from its surfaces
    (ordinates.launch) plus the plain first step of ``passing``, in the padded flat layout
    (q, 3, (R+2)^3; the shell holds what left), and the grid both came from (their sum):
    where another backend takes over the steps after the launch."""
    r = injected.shape[0]
    offvis = _offset_visibilities(visibility)
    arrivals = ordinates.launch(injected, offvis if occlude_first_step else None)
    if passing is None:
        return arrivals, injected
    table = ordinates.factors(r, offvis if occlude_first_step else None)
    arrivals += ordinates.advance(ordinates.pad(ordinates.unfold(passing)), table)
    return arrivals, injected + passing


def _propagate_ordinates(injected, iterations, min_fraction, visibility, occlude_first_step,
                         capture_outflow, launch=False, passing=None) -> PropagationResult:
    """propagate() with angular="dom" (ordinates.py): the injected lobes are unfolded once into
    flux per direction, advected step by step in the padded flat layout (ordinates.advance),
    and folded back into moments once at the end. What lands in the layout's one-cell shell
    left the grid: with ``capture_outflow`` it is kept as ``outflow`` ((R+2)^3 grid).
    With ``launch`` the first step of ``injected`` is ordinates.launch (``passing`` steps
    plainly); otherwise the two are one grid."""
    r = injected.shape[0]
    ordinates.check_memory(r, capture_outflow)
    total = injected if passing is None else injected + passing
    offvis = _offset_visibilities(visibility)
    free = ordinates.factors(r)
    occluded = free if visibility is None else ordinates.factors(r, offvis)
    acc = np.zeros((ordinates.DIRECTIONS, 3, (r + 2) ** 3), np.float32)
    outflow = np.zeros_like(acc) if capture_outflow else None
    done = 0
    if launch:
        cur, _ = first_arrivals(injected, visibility, occlude_first_step, passing)
        total0 = float(ordinates.unfold(total).sum(dtype=np.float64))
        if total0 > 0 and iterations > 0:
            ordinates.take_shell(cur, r, outflow)
            acc += cur
            done = 1
            moved = float(cur.sum(dtype=np.float64))
    else:
        cur = ordinates.pad(ordinates.unfold(total))
        total0 = float(cur.sum(dtype=np.float64))
    fraction = 1.0 if total0 > 0 else 0.0
    early = total0 <= 0
    if done:
        fraction = moved / total0
        early = fraction < min_fraction
    for _ in range(0 if early else max(int(iterations) - done, 0)):
        table = occluded if (done > 0 or occlude_first_step) else free
        cur, moved = ordinates.loop_step(cur, table, r, acc, outflow)
        done += 1
        fraction = moved / total0
        if fraction < min_fraction:
            early = True
            break
    values = ordinates.fold(np.ascontiguousarray(ordinates.interior(acc, r)), sh.BANDS2)
    ordinates.add_emission_band2(values, total)
    if outflow is not None:
        q = outflow.shape[0]
        outflow = ordinates.fold(outflow.reshape(q, 3, r + 2, r + 2, r + 2))
    return PropagationResult(values, done, flux(total), fraction, early, outflow)


def _sweep_ordinates(injected, visibility, occlude_first_step, capture_outflow, launch=False,
                     passing=None) -> PropagationResult:
    """propagate(angular="dom", sweep=True): A = y + T A solved by sweep.solve, y the first
    step's arrivals (ordinates.launch of ``injected`` with ``launch``), or the unfolded light
    itself when ``occlude_first_step`` (A then less it). With ``launch``, ``passing`` is
    always the latter; without, it is part of the injected grid. Compiled, the launch's case
    runs octants.launch_sweep_fold: launch, sweep and fold in one pass per octant."""
    r = injected.shape[0]
    transport_sweep.check_memory(r, capture_outflow)
    shell = capture_outflow
    total = injected if passing is None else injected + passing
    if launch and jit.enabled() and octants.supported():  # all of it in one pass per octant
        values, outflow = octants.launch_sweep_fold(injected, visibility, passing, shell,
                                                    occlude_first_step)
        ordinates.add_emission_band2(values, total)
        return PropagationResult(values, 0, flux(total), 0.0, False, outflow, swept=True)
    offvis = _offset_visibilities(visibility)
    if launch:
        acc = transport_sweep.launch_solve(injected, offvis if occlude_first_step else None,
                                           passing, offvis, shell)
    elif occlude_first_step:  # the unfolded light is not an arrival: taken off A
        source = ordinates.pad(ordinates.unfold(total))
        acc = transport_sweep.solve(source, r, offvis, shell)
        acc -= source
    else:  # the first step is unoccluded: take it as a step, sweep its arrivals
        source = ordinates.advance(ordinates.pad(ordinates.unfold(total)), ordinates.factors(r))
        acc = transport_sweep.solve(source, r, offvis, shell)
    values, outflow = transport_sweep.fold_parts(acc, r, shell)
    ordinates.add_emission_band2(values, total)
    return PropagationResult(values, 0, flux(total), 0.0, False, outflow, swept=True)
