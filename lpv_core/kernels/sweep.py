"""The octant sweep: the compiled twin of sweep.launch_sweep_fold (kernels/__init__.py), the
transport sweep of all directions of an octant at once, launched, swept and folded to SH slab
by slab, so the per-direction light is never written out.

All directions of an octant share their signs, their upwind neighbour offsets and the
transmittances they read (``direction_tables``: the same koff); only the trilinear weights
and 1 / (1 - w_0) differ. So a cell holds the light of its octant's directions side by side,
colour-major (lane = w colour + direction, w = 9 for the octants of 9 directions, 7 for
those of 7), and one cell update is 4 (or 3) AVX2 vectors per neighbour: the serial
recurrence along z (cell by cell in upwind order: slabs along x, rows along y), run once per
octant instead of once per direction. numba does not vectorize such a lane loop by itself (every array may alias every
other: it emitted runtime checks and index arithmetic worth ~60 ns a cell), so the vector
code is written out as LLVM IR (numba intrinsics: ``_cell*``, ``_fold4*``,
``_launch_lanes*``). The lanes after the light hold the cell's face transmittances towards
the octant: a neighbour's transmittance is their product (quadrature.offset_visibilities),
read with its light (7 rows of 27 streamed beside it cost ~10 ns a cell).

Per octant, slabs along x in upwind order live in a ring of 4 slabs: the one swept, the one
behind it (final) and the two ahead that the launch scatters into (a lit cell's launch lands
within one slab of it). A cell's light is folded into bands 0-2 (interior cells) or 0-1 (the
shell: the outflow) as soon as it is swept, a row at a time into the worker's sums; rows no
light reaches are skipped. The handed-on light (``passing``) is a source, and its fold is
taken off at the end (it is not an arrival). Layout and meaning of the result are those of
``sweep.fold_parts(sweep.launch_solve(...))``, whose numpy code stays the reference.
"""

from __future__ import annotations

import numpy as np

from .. import sh
from ..propagation.quadrature import DIRECTIONS, LAUNCH_CELLS, SIGNED_OFFSETS
from ..propagation.quadrature import tables as ordinate_tables
from ..runtime import jit, pool
from .ordinates import emission_directions, launch_corners_kernel, unfold_rows_at

LANES = 32  # floats per cell: 3 colours x 9 (or 7) directions, then VIS, padded to 4 x 8
WIDE, NARROW = 9, 7  # an octant's directions per colour block (64 directions: 9 or 7)
ROWS = 16  # rows of an octant's factor table: scale + 7 offsets, inside and in the shell
BASIS_STRIDE = 16  # floats per direction in an octant's basis table (9 used)
B8 = WIDE * BASIS_STRIDE  # then the last coefficient's basis per lane (LANES)
RING = 4  # slabs of an octant held at once (one more slot takes launches that leave the grid)
GEOMETRY = 16  # lanes of a lit cell's launch geometry: one per direction of the octant
_TABLES: dict = {}
_DIRECTION_TABLES: dict = {}  # q -> per-direction tables (direction_tables, _basis2)


def width(count: int) -> int:
    """The colour block of an octant of ``count`` directions: WIDE or NARROW lanes."""
    return NARROW if count <= NARROW else WIDE


def vis_lane(colour_lanes: int) -> int:
    """Lanes VIS..VIS+2 of a cell: its faces' transmittances (x, y, z), after the light."""
    return 3 * colour_lanes


def chunks(colour_lanes: int) -> int:
    """8-float vectors a cell's light and transmittances take: 4 (WIDE) or 3 (NARROW)."""
    return (vis_lane(colour_lanes) + 3 + 7) // 8


def direction_tables() -> dict:
    """Per direction, in ordinates.tables order (cached): its octant's signs (q, 3), per
    SIGNED_OFFSETS entry its trilinear weight (q, 7) and its index into propagation.OFFSETS
    (q, 7) ("none": all 0), 1 / (1 - w_0) (q,), the SIGNED_OFFSETS themselves (7, 3) and
    each octant's (first, stop) direction: what the octant tables are built from (the numpy sweep's
    ``plan`` and ``factors`` hold the same per position)."""
    q = DIRECTIONS
    if q in _DIRECTION_TABLES:
        return _DIRECTION_TABLES[q]
    dirs, _, groups = ordinate_tables()
    sign = np.where(dirs < 0, -1, 1).astype(np.int64)
    weight = np.zeros((q, len(SIGNED_OFFSETS)), np.float32)
    koff = np.zeros((q, len(SIGNED_OFFSETS)), np.int64)
    inv = np.empty(q, np.float32)
    for sl, pairs in groups:
        for k_off, off, w in pairs:
            w = w[:, 0, 0, 0, 0]
            soff = tuple(abs(x) for x in off)
            if soff == (0, 0, 0):
                inv[sl] = 1.0 / (1.0 - w)
                continue
            m = SIGNED_OFFSETS.index(soff)
            weight[sl, m] = w
            koff[sl, m] = k_off
    _DIRECTION_TABLES[q] = {"sign": sign, "weight": weight, "koff": koff,
                            "none": np.zeros_like(koff), "inv": inv,
                            "offsets": np.array(SIGNED_OFFSETS, np.int64),
                            "octants": [(sl.start, sl.stop) for sl, _ in groups]}
    return _DIRECTION_TABLES[q]


def _basis2() -> np.ndarray:
    """The band 0-2 basis of the directions, transposed (9, q) float32 (cached)."""
    dirs = ordinate_tables()[0]
    key = ("basis2", len(dirs))
    if key not in _DIRECTION_TABLES:
        _DIRECTION_TABLES[key] = np.ascontiguousarray(
            sh.evaluate_basis2(dirs).astype(np.float32).T)
    return _DIRECTION_TABLES[key]


def tables() -> dict:
    """Per octant (cached), what ``_octant_kernel`` reads: signs (8, 3), first direction and
    count (8, 2), factor table (8, ROWS * LANES) - per lane 1 / (1 - w_0) then
    w_m / (1 - w_0) for the interior, 1 then w_m for shell cells, 1 then 0 in the lanes VIS
    (the transmittances pass through), 0 in unused lanes - the band 0-2 basis of each
    direction then the last coefficient's per lane (8, B8 + LANES), and the directions' x,
    y, z components and a 1 for each (8, 4 GEOMETRY), 0 past the octant's count."""
    q = DIRECTIONS
    if q in _TABLES:
        return _TABLES[q]
    tab = direction_tables()
    basis2 = _basis2()  # (9, q)
    octants = tab["octants"]
    k = len(octants)
    sign = np.zeros((k, 3), np.int64)
    span = np.zeros((k, 2), np.int64)
    factors = np.zeros((k, ROWS, LANES), np.float32)
    basis = np.zeros((k, B8 + LANES), np.float32)
    dirs = np.zeros((k, 4, GEOMETRY), np.float32)
    for o, (d0, d1) in enumerate(octants):
        dirs[o, :3, :d1 - d0] = ordinate_tables()[0][d0:d1].T
        dirs[o, 3, :d1 - d0] = 1.0
        sign[o], span[o] = tab["sign"][d0], (d0, d1 - d0)
        w = width(d1 - d0)
        for dd, d in enumerate(range(d0, d1)):
            lanes = dd + w * np.arange(3)
            factors[o, 0, lanes] = tab["inv"][d]
            factors[o, 1:8, lanes] = tab["weight"][d] * tab["inv"][d]
            factors[o, 8, lanes] = 1.0
            factors[o, 9:16, lanes] = tab["weight"][d]
            basis[o, dd * BASIS_STRIDE:dd * BASIS_STRIDE + sh.BANDS2] = basis2[:, d]
            basis[o, B8 + lanes] = basis2[8, d]
        factors[o, [0, 8], vis_lane(w):vis_lane(w) + 3] = 1.0
    _TABLES[q] = {"sign": sign, "span": span, "factors": factors.reshape(k, -1),
                  "basis": basis, "dirs": dirs.reshape(k, -1)}
    return _TABLES[q]


# ---------------------------------------------------------------- vector code (LLVM IR)


def _intrinsic(codegen_of):
    """A numba intrinsic built by ``codegen_of`` (a function of the argument types returning
    (signature, codegen)); without numba a stub, never called (``jit.enabled()`` is False)."""
    if jit.numba is None:
        return codegen_of
    from numba.extending import intrinsic

    return intrinsic(codegen_of)


def _ir():
    """llvmlite's IR module and numba's cgutils (imported where numba is installed)."""
    from llvmlite import ir
    from numba.core import cgutils

    return ir, cgutils


def _data(context, builder, ty, value):
    """The float pointer to an array argument's data."""
    return context.make_array(ty)(context, builder, value).data


def _vec_ptr(builder, ptr, index, lanes: int):
    """Pointer to the <lanes x float> at ptr + index (elements)."""
    ir, _ = _ir()
    return builder.bitcast(builder.gep(ptr, [index]),
                           ir.VectorType(ir.FloatType(), lanes).as_pointer())


def _load(builder, ptr, index, lanes: int, invariant: bool = False):
    """<lanes x float> from ptr + index (no alignment assumed); ``invariant``: memory that
    no store of the kernel changes (the factor and basis tables), so LLVM may keep it in
    registers across cells instead of loading it again after every store to the ring."""
    value = builder.load(_vec_ptr(builder, ptr, index, lanes), align=4)
    if invariant:
        value.set_metadata("invariant.load", builder.module.add_metadata([]))
    return value


def _store(builder, value, ptr, index, lanes: int) -> None:
    """Store <lanes x float> at ptr + index."""
    builder.store(value, _vec_ptr(builder, ptr, index, lanes), align=4)


def _splat(builder, scalar, lanes: int):
    """<lanes x float> (or i1) of one scalar."""
    ir, _ = _ir()
    vt = ir.VectorType(scalar.type, lanes)
    one = builder.insert_element(ir.Constant(vt, ir.Undefined), scalar,
                                 ir.Constant(ir.IntType(32), 0))
    return builder.shuffle_vector(one, ir.Constant(vt, ir.Undefined),
                                  ir.Constant(ir.VectorType(ir.IntType(32), lanes), [0] * lanes))


def _fma(builder, lanes: int):
    """llvm.fma on <lanes x float>."""
    ir, cgutils = _ir()
    t = ir.VectorType(ir.FloatType(), lanes)
    return cgutils.get_or_insert_function(builder.module, ir.FunctionType(t, [t, t, t]),
                                          f"llvm.fma.v{lanes}f32")


def _offset(builder, base, k: int):
    """base + k, in base's integer type."""
    ir, _ = _ir()
    return builder.add(base, ir.Constant(base.type, k))


def _sweep_ir(builder, rp, o_v, srcs_v, vis_v, fp, t_v, open_space: bool, count: int) -> list:
    """IR of one cell of the sweep: ring[o:o+8 count] = f_0 ring[o:...] + sum_m (vis[m]
    f_{m+1}) ring[srcs[m]:...], f_k the floats at factors[t + k LANES] (``open_space``: every
    vis is 1 and not read, 7 multiplies a vector fewer), in ``count`` vectors, every load
    before the store. The cell behind along z (the serial step) comes last."""
    fma = _fma(builder, 8)
    scales = None if open_space else [_splat(builder, builder.extract_value(vis_v, m), 8)
                                      for m in range(7)]
    out = []
    for v in range(count):
        acc = builder.fmul(_load(builder, fp, _offset(builder, t_v, 8 * v), 8, True),
                           _load(builder, rp, _offset(builder, o_v, 8 * v), 8))
        for m in (1, 2, 3, 4, 5, 6, 0):
            f = _load(builder, fp, _offset(builder, t_v, (m + 1) * LANES + 8 * v), 8, True)
            if scales is not None:
                f = builder.fmul(scales[m], f)
            src = _load(builder, rp, _offset(builder, builder.extract_value(srcs_v, m), 8 * v), 8)
            acc = builder.call(fma, [f, src, acc])
        out.append(acc)
    for v, acc in enumerate(out):
        _store(builder, acc, rp, _offset(builder, o_v, 8 * v), 8)
    return out


def _fold_ir(builder, vectors: list, cell, bp, op, oi_v, coefficients: int, w: int) -> None:
    """IR of out[oi + c coefficients + t] += sum_d A[w c + d] basis[d 16 + t] for the 3
    colours c and t < coefficients, A a cell's lanes (``vectors``; in memory at ``cell``:
    (pointer, offset)): t < 8 as vectors (each direction's light, broadcast from memory,
    times its basis row, in partial sums of 3: one chain of 9 dependent multiply-adds kept
    the sweep waiting), t = 8 from the lanes times the basis' lane row B8, summed across (32
    scalar multiply-adds fewer)."""
    lanes = min(coefficients, 8)
    fma = _fma(builder, lanes)
    for c in range(3):
        oc = _offset(builder, oi_v, c * coefficients)
        parts = []
        for g in range(0, w, 3):
            acc = None
            for d in range(g, min(g + 3, w)):
                av = _splat(builder, builder.load(builder.gep(cell[0], [_offset(
                    builder, cell[1], c * w + d)])), lanes)
                b = _load(builder, bp, _offset(builder, oi_v.type(0), d * BASIS_STRIDE), lanes,
                          True)
                acc = builder.fmul(av, b) if acc is None else builder.call(fma, [av, b, acc])
            parts.append(acc)
        total = parts[0]
        for part in parts[1:]:
            total = builder.fadd(total, part)
        _store(builder, builder.fadd(_load(builder, op, oc, lanes), total), op, oc, lanes)
    if coefficients > 8:
        last = _lane_sums(builder, [builder.fmul(vec, _load(builder, bp, _offset(
            builder, oi_v.type(0), B8 + 8 * v), 8, True)) for v, vec in enumerate(vectors)], w)
        for c in range(3):
            at = builder.gep(op, [_offset(builder, oi_v, c * coefficients + 8)])
            builder.store(builder.fadd(builder.load(at), last[c]), at)


def _lane_sums(builder, vectors: list, w: int) -> list:
    """Per colour the sum of its w lanes of a cell given as vectors of 8."""
    ir, _ = _ir()
    zero = ir.Constant(ir.VectorType(ir.FloatType(), 8), [0.0] * 8)
    sums = []
    for c in range(3):
        acc = None
        for v, vec in enumerate(vectors):
            keep = [c * w <= 8 * v + i < (c + 1) * w for i in range(8)]
            if not any(keep):
                continue
            if not all(keep):
                vec = builder.select(ir.Constant(ir.VectorType(ir.IntType(1), 8), keep), vec,
                                     zero)
            acc = vec if acc is None else builder.fadd(acc, vec)
        sums.append(_hsum(builder, acc))
    return sums


def _hsum(builder, vec):
    """The sum of an 8-float vector's lanes (halves added, then quarters, then pairs)."""
    ir, _ = _ir()
    width_ = 8
    while width_ > 1:
        half = width_ // 2
        mask = ir.VectorType(ir.IntType(32), half)
        lo = builder.shuffle_vector(vec, vec, ir.Constant(mask, list(range(half))))
        hi = builder.shuffle_vector(vec, vec, ir.Constant(mask, list(range(half, width_))))
        vec = builder.fadd(lo, hi)
        width_ = half
    return builder.extract_element(vec, ir.Constant(ir.IntType(32), 0))


def _cell_intrinsic(open_space: bool, coefficients: int, w: int):
    """An intrinsic (ring, o, srcs, vis, factors, t, basis, out, oi) sweeping one cell of an
    octant of colour block w (``_sweep_ir``) and adding its fold to out[oi:]
    (``_fold_ir``)."""
    from numba.core import types

    def typer(typingctx, ring, o, srcs, vis, factors, t, basis, out, oi):
        def codegen(context, builder, sig, args):
            ring_v, o_v, srcs_v, vis_v, fac_v, t_v, basis_v, out_v, oi_v = args
            rp = _data(context, builder, sig.args[0], ring_v)
            fp = _data(context, builder, sig.args[4], fac_v)
            vectors = _sweep_ir(builder, rp, o_v, srcs_v, vis_v, fp, t_v, open_space, chunks(w))
            _fold_ir(builder, vectors, (rp, o_v), _data(context, builder, sig.args[6], basis_v),
                     _data(context, builder, sig.args[7], out_v), oi_v, coefficients, w)
            return context.get_dummy_value()

        return types.void(ring, o, srcs, vis, factors, t, basis, out, oi), codegen

    typer.__name__ = f"_cell{coefficients}_{w}{'_open' if open_space else ''}"
    return _intrinsic(typer)


def _fold4_intrinsic(w: int):
    """An intrinsic (ring, o, basis, out, oi): outflow[oi:oi+12] (3 colours x 4) += the band
    0-1 fold of the cell at ring[o] (a shell cell that receives nothing: its light is its
    source), colour block w."""
    from numba.core import types

    def typer(typingctx, ring, o, basis, out, oi):
        def codegen(context, builder, sig, args):
            ring_v, o_v, basis_v, out_v, oi_v = args
            rp = _data(context, builder, sig.args[0], ring_v)
            vectors = [_load(builder, rp, _offset(builder, o_v, 8 * v), 8)
                       for v in range(chunks(w))]
            _fold_ir(builder, vectors, (rp, o_v), _data(context, builder, sig.args[2], basis_v),
                     _data(context, builder, sig.args[3], out_v), oi_v, 4, w)
            return context.get_dummy_value()

        return types.void(ring, o, basis, out, oi), codegen

    typer.__name__ = f"_fold4_{w}"
    return _intrinsic(typer)


# per colour block: an interior cell (swept, folded into bands 0-2), a shell cell (bands
# 0-1), each also in open space (every transmittance 1), and a shell cell kept as it is
_cell9_w, _cell9_w_open = _cell_intrinsic(False, 9, WIDE), _cell_intrinsic(True, 9, WIDE)
_cell4_w, _cell4_w_open = _cell_intrinsic(False, 4, WIDE), _cell_intrinsic(True, 4, WIDE)
_cell9_n, _cell9_n_open = _cell_intrinsic(False, 9, NARROW), _cell_intrinsic(True, 9, NARROW)
_cell4_n, _cell4_n_open = _cell_intrinsic(False, 4, NARROW), _cell_intrinsic(True, 4, NARROW)
_fold4_w, _fold4_n = _fold4_intrinsic(WIDE), _fold4_intrinsic(NARROW)


@_intrinsic
def _prefetch(typingctx, array, index):
    """Ask for the cache line of array[index] ahead of its use (for writing; no fault if it
    lies outside the array)."""
    from numba.core import types

    def codegen(context, builder, sig, args):
        ir, cgutils = _ir()
        ptr = builder.gep(_data(context, builder, sig.args[0], args[0]), [args[1]])
        i8p, i32 = ir.IntType(8).as_pointer(), ir.IntType(32)
        fn = cgutils.get_or_insert_function(
            builder.module, ir.FunctionType(ir.VoidType(), [i8p, i32, i32, i32]),
            "llvm.prefetch.p0")
        builder.call(fn, [builder.bitcast(ptr, i8p), ir.Constant(i32, 1), ir.Constant(i32, 3),
                          ir.Constant(i32, 1)])
        return context.get_dummy_value()

    return types.void(array, index), codegen


@_intrinsic
def _add_clear(typingctx, dst, d, src, s):
    """dst[d:d+8] += src[s:s+8], then src[s:s+8] = 0 (8-float vectors: a scalar loop of this
    was not vectorized, the arrays may alias)."""
    from numba.core import types

    def codegen(context, builder, sig, args):
        ir, _ = _ir()
        dp = _data(context, builder, sig.args[0], args[0])
        sp = _data(context, builder, sig.args[2], args[2])
        part = _load(builder, sp, args[3], 8)
        _store(builder, builder.fadd(_load(builder, dp, args[1], 8), part), dp, args[1], 8)
        _store(builder, ir.Constant(part.type, [0.0] * 8), sp, args[3], 8)
        return context.get_dummy_value()

    return types.void(dst, d, src, s), codegen


def _launch_fractions(builder, d, m, signs):
    """launch_corners_kernel's float32 arithmetic (kernels/ordinates.py), one lane per
    direction (GEOMETRY lanes, the same operations in the same order): per axis the fraction
    towards the far corner, and where the corners are the octant's own (base 0 on its
    positive axes, -1 on its negative ones)."""
    ir, cgutils = _ir()
    n = GEOMETRY
    vt = ir.VectorType(ir.FloatType(), n)

    def const(x):
        return ir.Constant(vt, [x] * n)

    def vmax(a, b):  # numba's max(a, b): b if b > a else a
        return builder.select(builder.fcmp_ordered(">", b, a), b, a)

    def vmin(a, b):
        return builder.select(builder.fcmp_ordered("<", b, a), b, a)

    cos = builder.fadd(builder.fadd(builder.fmul(d[0], m[0]), builder.fmul(d[1], m[1])),
                       builder.fmul(d[2], m[2]))
    side = [builder.fsub(d[a], builder.fmul(cos, m[a])) for a in range(3)]
    sq = builder.fadd(builder.fadd(builder.fmul(side[0], side[0]), builder.fmul(side[1], side[1])),
                      builder.fmul(side[2], side[2]))
    sqrt = cgutils.get_or_insert_function(builder.module, ir.FunctionType(vt, [vt]),
                                          f"llvm.sqrt.v{n}f32")
    sin = builder.call(sqrt, [sq])
    t = builder.fdiv(const(LAUNCH_CELLS), vmax(vmax(cos, sin), const(1e-6)))
    scale = builder.select(builder.fcmp_ordered(">", cos, const(0.0)), t, const(0.0))
    fracs, own = [], None
    for a in range(3):
        mv = vmin(vmax(builder.fadd(d[a], builder.fmul(scale, side[a])), const(-1.0)), const(1.0))
        neg = builder.fcmp_ordered("<", mv, const(0.0))
        fracs.append(builder.select(neg, builder.fadd(mv, const(1.0)), mv))
        octant_neg = _splat(builder, builder.icmp_signed("<", signs[a],
                                                         ir.Constant(signs[a].type, 0)), n)
        same = builder.not_(builder.xor(neg, octant_neg))
        own = same if own is None else builder.and_(own, same)
    return fracs, own


def _lanes(builder, rows: list, chunk: int, w: int):
    """Cell lanes 8 chunk .. 8 chunk + 7 (colour c, direction d at w c + d) gathered from
    per-colour GEOMETRY-lane rows (``rows``: one per colour, or one for all); the lanes after
    the light read lane GEOMETRY - 1 (no direction there)."""
    ir, _ = _ir()
    picks = []
    for x in range(8 * chunk, 8 * chunk + 8):
        c, dd = divmod(x, w) if x < 3 * w else (2, GEOMETRY - 1)
        picks.append((min(c, len(rows) - 1), dd))
    used = sorted({c for c, _ in picks})
    mask = [dd + (GEOMETRY if c != used[0] else 0) for c, dd in picks]
    return builder.shuffle_vector(rows[used[0]], rows[used[-1]],
                                  ir.Constant(ir.VectorType(ir.IntType(32), 8), mask))


def _launch_intrinsic(w: int):
    """An intrinsic (ring, targets, corner_vis, flux, row, dirs, mx, my, mz, sx, sy, sz):
    one lit cell's launch along the directions of an octant of colour block w (``dirs``:
    their x, y, z rows and a row 1 for each, GEOMETRY lanes each), the geometry of all of
    them at once (``_launch_fractions``), the flux of those landing on the octant's own
    corners (flux[row + c GEOMETRY + d], colour c, direction d) added to the 8 cells at
    ``targets`` (ring offsets, corner (cx, cy, cz) at 4 cx + 2 cy + cz), each share times
    its ``corner_vis``: weight (fx or 1 - fx) (fy or 1 - fy) (fz or 1 - fz), all lanes at
    once. Returns the bit mask of the directions left out (other corners, some flux)."""
    from numba.core import types

    def typer(typingctx, ring, targets, corner_vis, flux, row, dirs, mx, my, mz, sx, sy, sz):
        def codegen(context, builder, sig, args):
            ir, _ = _ir()
            ring_v, tg_v, cv_v, flux_v, row_v, dirs_v, mx_v, my_v, mz_v = args[:9]
            rp = _data(context, builder, sig.args[0], ring_v)
            fp = _data(context, builder, sig.args[3], flux_v)
            dp = _data(context, builder, sig.args[5], dirs_v)
            n = GEOMETRY
            i64 = ir.IntType(64)
            zero = ir.Constant(ir.VectorType(ir.FloatType(), n), [0.0] * n)
            d = [_load(builder, dp, ir.Constant(i64, a * n), n) for a in range(4)]
            m = [_splat(builder, v, n) for v in (mx_v, my_v, mz_v)]
            fracs, own = _launch_fractions(builder, d[:3], m, args[9:])
            valid = builder.fcmp_ordered("!=", d[3], zero)
            keep = builder.and_(own, valid)
            left = builder.and_(builder.not_(own), valid)
            flux, out = [], None
            for c in range(3):
                f = _load(builder, fp, _offset(builder, row_v, c * n), n)
                flux.append(builder.select(keep, f, zero))
                lit = builder.and_(left, builder.fcmp_unordered("!=", f, zero))
                out = lit if out is None else builder.or_(out, lit)
            one = ir.Constant(ir.VectorType(ir.FloatType(), 8), [1.0] * 8)
            fma = _fma(builder, 8)
            cvis = [_splat(builder, builder.extract_value(cv_v, c), 8) for c in range(8)]
            for v in range(chunks(w)):
                share_x = [(builder.fsub(one, f), f) for f in
                           (_lanes(builder, [fr], v, w) for fr in fracs)]
                lanes = _lanes(builder, flux, v, w)
                for cx in range(2):
                    ax = builder.fmul(lanes, share_x[0][cx])
                    for cy in range(2):
                        axy = builder.fmul(ax, share_x[1][cy])
                        for cz in range(2):
                            c = 4 * cx + 2 * cy + cz
                            at = _offset(builder, builder.extract_value(tg_v, c), 8 * v)
                            share = builder.fmul(axy, share_x[2][cz])
                            old = _load(builder, rp, at, 8)
                            _store(builder, builder.call(fma, [share, cvis[c], old]), rp, at, 8)
            return builder.zext(builder.bitcast(out, ir.IntType(n)), i64)

        return types.int64(ring, targets, corner_vis, flux, row, dirs, mx, my, mz, sx, sy,
                           sz), codegen

    typer.__name__ = f"_launch_lanes_{w}"
    return _intrinsic(typer)


_launch_w, _launch_n = _launch_intrinsic(WIDE), _launch_intrinsic(NARROW)


# ---------------------------------------------------------------- the kernels


@jit.kernel
def _scatter_direction_kernel(flux, m, xyz, dirs, lvis, e, j, dd, w, ring, live, p, lo, hi,
                       sx, sy, sz):  # pragma: no cover - compiled
    """The launch of lit cell e along direction j (lane dd of its octant, colour block w;
    ``flux`` its rows (n, 3 GEOMETRY)) added corner by corner: the compiled ordinates.launch
    (kernels/ordinates.py) for one (cell, direction), for the few whose corners are not the
    octant's own (``_launch_lanes``). Targets in slabs outside lo..hi-1 (the shell, when it
    is not swept) are dropped; the rows reached are marked in ``live``."""
    has_vis = lvis.shape[1] > 0
    one = np.float32(1.0)
    pp = p * p
    n = hi - lo
    x, y, z = xyz[e, 0], xyz[e, 1], xyz[e, 2]
    f0, f1, f2 = flux[e, dd], flux[e, GEOMETRY + dd], flux[e, 2 * GEOMETRY + dd]
    bx, by, bz, fx, fy, fz = launch_corners_kernel(dirs[j, 0], dirs[j, 1], dirs[j, 2],
                                                   m[e, 0], m[e, 1], m[e, 2])
    for cx in range(2):
        u = x + bx + cx - lo if sx > 0 else hi - 1 - x - bx - cx
        if u < 0 or u >= n:
            continue
        slot = u % RING
        wx = fx if cx else one - fx
        for cy in range(2):
            wxy = wx * (fy if cy else one - fy)
            row = y + by + cy
            for cz in range(2):
                wt = wxy * (fz if cz else one - fz)
                if has_vis:
                    wt = wt * lvis[e, ((bx + cx + 1) * 3 + by + cy + 1) * 3 + bz + cz + 1]
                at = (slot * pp + row * p + z + bz + cz) * LANES + dd
                ring[at] += wt * f0
                ring[at + w] += wt * f1
                ring[at + 2 * w] += wt * f2
                kk = z + bz + cz - lo if sz > 0 else hi - 1 - z - bz - cz
                if lo <= row < hi and 0 <= kk < n:
                    live[slot, row] = min(live[slot, row], kk)


@jit.kernel
def _scatter_slab_kernel(flux, m, xyz, dirs, lvis, e0, e1, o, d0, wide, odirs, sign, ring, live, p,
                  lo, hi):  # pragma: no cover - compiled
    """The launch of lit cells e0..e1-1 (padded cells xyz[e]) along the octant's directions
    from d0 into the ring: those landing on the octant's own corners (base cell b = the
    cell, less 1 on the octant's negative axes, and b + {0, 1}^3) as lanes
    (``_launch_lanes``), any other (a tilted emitter turning its sideways shift against the
    octant) by ``_scatter_direction_kernel``. Corners in slabs outside lo..hi-1 go to the ring's
    spare slot (dropped); the rows reached are marked in ``live``. ``flux``: the lit cells'
    colour rows per octant (8, n, 3 GEOMETRY). One call per slab of lit cells, scalars only
    inside: a call or an array view per lit cell (reference counts) cost more than its
    launch."""
    sx, sy, sz = sign[o, 0], sign[o, 1], sign[o, 2]
    one = np.float32(1.0)
    pp = p * p
    n = hi - lo
    has_vis = lvis.shape[1] > 0
    rows, lanes = odirs[o], flux[o]
    w = WIDE if wide else NARROW
    for e in range(e0, e1):
        x, y, z = xyz[e, 0], xyz[e, 1], xyz[e, 2]
        bx, by, bz = (x - 1 if sx < 0 else x), (y - 1 if sy < 0 else y), (z - 1 if sz < 0 else z)
        u0 = bx - lo if sx > 0 else hi - 1 - bx  # the slabs of corners cx = 0 and 1
        u1 = u0 + 1 if sx > 0 else u0 - 1
        k0 = max(bz - lo if sz > 0 else hi - 2 - bz, 0)  # the first of the corners along z
        slots = (u0 % RING if 0 <= u0 < n else RING, u1 % RING if 0 <= u1 < n else RING)
        for slot in slots:
            for row in range(by, by + 2):
                if slot < RING and lo <= row < hi and k0 < n:
                    live[slot, row] = min(live[slot, row], k0)
        r00 = (by * p + bz) * LANES
        r01, r10, r11 = r00 + LANES, r00 + p * LANES, r00 + (p + 1) * LANES
        s0, s1 = slots[0] * pp * LANES, slots[1] * pp * LANES
        targets = (np.uintp(s0 + r00), np.uintp(s0 + r01), np.uintp(s0 + r10),
                   np.uintp(s0 + r11), np.uintp(s1 + r00), np.uintp(s1 + r01),
                   np.uintp(s1 + r10), np.uintp(s1 + r11))
        if has_vis:  # propagation.OFFSETS index of corner (cx, cy, cz): k + 9 cx + 3 cy + cz
            k = ((bx - x + 1) * 3 + by - y + 1) * 3 + bz - z + 1
            cvis = (lvis[e, k], lvis[e, k + 1], lvis[e, k + 3], lvis[e, k + 4],
                    lvis[e, k + 9], lvis[e, k + 10], lvis[e, k + 12], lvis[e, k + 13])
        else:
            cvis = (one, one, one, one, one, one, one, one)
        at = np.uintp(e * 3 * GEOMETRY)
        if wide:
            left = _launch_w(ring, targets, cvis, lanes, at, rows, m[e, 0], m[e, 1], m[e, 2],
                             sx, sy, sz)
        else:
            left = _launch_n(ring, targets, cvis, lanes, at, rows, m[e, 0], m[e, 1], m[e, 2],
                             sx, sy, sz)
        dd = 0
        while left:
            if left & 1:
                _scatter_direction_kernel(lanes, m, xyz, dirs, lvis, e, d0 + dd, dd, w, ring, live, p,
                                   lo, hi, sx, sy, sz)
            left >>= 1
            dd += 1


@jit.kernel
def _fill_slot_kernel(ring, live, slot, x, faces, face, p, n, vis):  # pragma: no cover - compiled
    """Ready ring slot ``slot`` for slab x: no light (the rows its last slab lit emptied; all
    its rows dark: ``live`` n), and in lanes vis.. of each interior cell the transmittances
    of its faces the octant's light leaves through (faces[face[a]], axis a: 1 without
    ``faces``; 0 for x outside the grid's interior; shell cells keep 0: they only receive).
    Emptying only the lit rows (light outside them lies in shell cells, which no cell reads
    but through a transmittance of 0) spares most of 40 MB of writes per cascade."""
    base = slot * p * p * LANES
    for j in range(p):
        if live[slot, j] < n:
            ring[base + j * p * LANES:base + (j + 1) * p * LANES] = 0.0
        live[slot, j] = n
    inner = 0 < x < p - 1
    one, zero = np.float32(1.0), np.float32(0.0)
    for j in range(1, p - 1):
        for k in range(1, p - 1):
            o = base + (j * p + k) * LANES + vis
            if not inner:
                ring[o] = ring[o + 1] = ring[o + 2] = zero
            elif faces.shape[0] == 0:
                ring[o] = ring[o + 1] = ring[o + 2] = one
            else:
                ring[o] = faces[face[0], x - 1, j - 1, k - 1]
                ring[o + 1] = faces[face[1], x - 1, j - 1, k - 1]
                ring[o + 2] = faces[face[2], x - 1, j - 1, k - 1]


@jit.kernel
def _sweep_slab_kernel(ring, live, sc, sp, i, first, sy, sz, p, shell, wide, factors, basis, values,
                outflow, row_values, row_outflow):  # pragma: no cover - compiled
    """Sweep and fold one slab x = i (ring slot ``sc``, the slab behind in slot ``sp``): row
    by row along y, cell by cell along z in upwind order, each cell one ``_cell*`` (the
    transmittance of each source towards the cell: the product of its faces' in its lanes
    VIS, in quadrature.offset_visibilities' order; all 1: ``_open``), then folded (interior:
    bands 0-2 into ``row_values``, shell: bands 0-1 into ``row_outflow``). A row starts at
    the first cell light can reach (``live``: of its source and of the rows it receives
    from; dark rows are skipped: 58% of the fine Cornell cascade's, 15% of the coarse
    one's). With the shell, cells on its upwind faces (and the whole ``first`` slab) receive
    nothing: their light is their source. A swept row's folds go to the sums in one
    streaming pass (``_add_row_kernel``), the sums' cache lines not fetched cell by cell."""
    r = p - 2
    lo, hi = (0, p) if shell else (1, p - 1)
    n = hi - lo
    slab = np.uintp(p * p * LANES)
    cur, prev = np.uintp(sc) * slab, np.uintp(sp) * slab
    inner_slab = 0 < i < p - 1
    back = sy * p
    size = np.uintp(LANES)
    shell_rows = np.uintp(8 * LANES)
    one = np.float32(1.0)
    vis = np.uintp(3 * (WIDE if wide else NARROW))
    fx, fy, fz = vis, vis + np.uintp(1), vis + np.uintp(2)
    for jj in range(n):
        j = lo + jj if sy > 0 else hi - 1 - jj
        start = live[sc, j]
        if not first:
            start = min(start, live[sp, j])
        if jj > 0:
            start = min(start, live[sc, j - sy])
            if not first:
                start = min(start, live[sp, j - sy])
        if start >= n:
            continue  # no light reaches this row
        live[sc, j] = start
        inner_row = inner_slab and 0 < j < p - 1
        ahead = ((i - 1) * r + j - 1 + sy) * r * 27  # the sums of the next row, as cells go
        for kk in range(start, n):
            k = lo + kk if sz > 0 else hi - 1 - kk
            c = np.uintp(j * p + k)
            o = cur + c * size
            inside = inner_row and 0 < k < p - 1
            if shell and (first or jj == 0 or kk == 0):  # receives nothing: its source stays
                if wide:
                    _fold4_w(ring, o, basis, row_outflow, np.uintp(k * 12))
                else:
                    _fold4_n(ring, o, basis, row_outflow, np.uintp(k * 12))
                continue
            a, b = np.uintp(c - sz), np.uintp(c - back)
            d = np.uintp(b - sz)
            srcs = (cur + a * size, cur + b * size, cur + d * size, prev + c * size,
                    prev + a * size, prev + b * size, prev + d * size)
            vs = (ring[srcs[0] + fz], ring[srcs[1] + fy], ring[srcs[2] + fy] * ring[srcs[2] + fz],
                  ring[srcs[3] + fx], ring[srcs[4] + fx] * ring[srcs[4] + fz],
                  ring[srcs[5] + fx] * ring[srcs[5] + fy],
                  ring[srcs[6] + fx] * ring[srcs[6] + fy] * ring[srcs[6] + fz])
            open_space = (vs[0] == one and vs[1] == one and vs[2] == one and vs[3] == one
                          and vs[4] == one and vs[5] == one and vs[6] == one)
            if inside:
                _prefetch(values, np.uintp(ahead + (k - 1) * 27))
                _prefetch(values, np.uintp(ahead + (k - 1) * 27 + 16))
                at, t, out = np.uintp((k - 1) * 27), np.uintp(0), row_values
            else:  # a shell cell (without the shell every swept cell is inside)
                at, t, out = np.uintp(k * 12), shell_rows, row_outflow
            if wide and inside:
                if open_space:
                    _cell9_w_open(ring, o, srcs, vs, factors, t, basis, out, at)
                else:
                    _cell9_w(ring, o, srcs, vs, factors, t, basis, out, at)
            elif wide:
                if open_space:
                    _cell4_w_open(ring, o, srcs, vs, factors, t, basis, out, at)
                else:
                    _cell4_w(ring, o, srcs, vs, factors, t, basis, out, at)
            elif inside:
                if open_space:
                    _cell9_n_open(ring, o, srcs, vs, factors, t, basis, out, at)
                else:
                    _cell9_n(ring, o, srcs, vs, factors, t, basis, out, at)
            elif open_space:
                _cell4_n_open(ring, o, srcs, vs, factors, t, basis, out, at)
            else:
                _cell4_n(ring, o, srcs, vs, factors, t, basis, out, at)
        if inner_row:  # the row's folds to the sums
            _add_row_kernel(values, ((i - 1) * r + j - 1) * r * 27, row_values, 0, r * 27)
        if shell and inner_row:  # its two shell cells
            at = (i * p + j) * p * 12
            _add_row_kernel(outflow, at, row_outflow, 0, 12)
            _add_row_kernel(outflow, at + (p - 1) * 12, row_outflow, (p - 1) * 12, 12)
        elif shell:
            _add_row_kernel(outflow, (i * p + j) * p * 12, row_outflow, 0, p * 12)


@jit.kernel
def _add_row_kernel(dst, d, src, s, count):  # pragma: no cover - compiled
    """dst[d:d+count] += src[s:s+count], emptying src there: 8 floats at a time
    (``_add_clear``), the rest one by one."""
    whole = count - count % 8
    for t in range(0, whole, 8):
        _add_clear(dst, np.uintp(d + t), src, np.uintp(s + t))
    for t in range(whole, count):
        dst[d + t] += src[s + t]
        src[s + t] = 0.0


@jit.kernel
def _octant_kernel(o, sign, span, factors, basis, odirs, flux, m, xyz, dirs, lvis, lit_first,
                   pcell, pcol, pflux, pass_first, faces, p, shell, ring, live, values,
                   outflow):  # pragma: no cover - compiled
    """Launch, sweep and fold octant o (module docstring): slabs in upwind order along x, each
    one's sources completed first (the launch of the lit cells one slab ahead, the handed-on
    light in it); per ring slot and row the first cell light may have reached (``live``:
    n, none) lets the sweep skip what stays dark. ``ring`` and ``live`` carry over from the
    worker's octant before: a slot is emptied where that left light (``_fill_slot_kernel``)."""
    sx, sy, sz = sign[o, 0], sign[o, 1], sign[o, 2]
    d0, count = span[o, 0], span[o, 1]
    wide = count > NARROW
    w = WIDE if wide else NARROW
    lo, hi = (0, p) if shell else (1, p - 1)
    n = hi - lo
    face = np.empty(3, np.int64)  # per axis the face the octant's light leaves a cell through
    for a in range(3):
        face[a] = 2 * a + (1 if sign[o, a] < 0 else 0)
    row_values, row_outflow = np.zeros(p * 27, np.float32), np.zeros(p * 12, np.float32)
    fac, bas = factors[o], basis[o]
    _fill_slot_kernel(ring, live, RING - 1, lo - 1 if sx > 0 else hi, faces, face, p, n, 3 * w)
    for ii in range(n):
        for u in range(ii + 2 if ii > 0 else 0, ii + 3):  # ready slots up to slab ii + 2
            _fill_slot_kernel(ring, live, u % RING, lo + u if sx > 0 else hi - 1 - u, faces, face, p,
                       n, 3 * w)
        for u in range(ii + 1 if ii > 0 else 0, ii + 2):  # lit cells of slab ii + 1 (and 0)
            x = lo + u if sx > 0 else hi - 1 - u
            if 0 <= x < p and lit_first[x] < lit_first[x + 1]:
                _scatter_slab_kernel(flux, m, xyz, dirs, lvis, lit_first[x], lit_first[x + 1], o, d0,
                              wide, odirs, sign, ring, live, p, lo, hi)
        i = lo + ii if sx > 0 else hi - 1 - ii
        sc = ii % RING
        cur = sc * p * p * LANES
        for e in range(pass_first[i], pass_first[i + 1]):
            cell = pcell[e] - i * p * p
            at = cur + cell * LANES + pcol[e] * w
            for dd in range(count):
                ring[at + dd] += pflux[o, e, dd]
            j, k = cell // p, cell % p
            live[sc, j] = min(live[sc, j], k - lo if sz > 0 else hi - 1 - k)
        _sweep_slab_kernel(ring, live, sc, (ii + RING - 1) % RING, i, shell and ii == 0, sy, sz, p,
                    shell, wide, fac, bas, values, outflow, row_values, row_outflow)


def launch_sweep_fold(injected: np.ndarray, visibility: np.ndarray | None,
                      passing: np.ndarray | None = None, shell: bool = True,
                      occlude_launch: bool = True) -> tuple:
    """sweep.launch_sweep_fold compiled: the propagation of sweep.launch_solve folded as
    sweep.fold_parts, in one pass per octant (call it when ``jit.enabled()``): ``injected``
    (R, R, R, 3, 4) launched from its surfaces, ``passing`` (the same, or None) handed on,
    both swept through the face transmittances ``visibility`` (6, R, R, R) or None; the
    launch occluded by them when ``occlude_launch``. Returns (values (R, R, R, 3, 9), outflow
    (R+2, R+2, R+2, 3, 4) with a zero interior, or None without ``shell``): the same as
    ``fold_parts(launch_solve(injected, offvis if occlude_launch else None, passing, offvis,
    shell), R, shell)`` with offvis = quadrature.offset_visibilities(visibility).
    The octants run on the thread pool (runtime/pool.py), a fixed share per worker, each worker adding to its
    own sums, added up in a fixed order: the same bits every run (a worker taking whichever
    octant came next added them in a varying order)."""
    work = _inputs(injected, visibility, passing, shell, occlude_launch)
    shares = _shares(pool.workers())
    sums = [None] * len(shares)

    def run(w: int) -> None:
        sums[w] = _zero_sums(work, w == 0)
        ring = _ring(work)
        with jit.flush_subnormals():  # light fading behind walls: 3x (jit.py)
            for o in shares[w]:
                _run_octant(work, o, ring, *sums[w])

    for _ in pool.executor().map(run, range(len(shares))):
        pass  # iterating re-raises a worker's exception here
    parts = max(2, len(shares))
    for _ in pool.executor().map(lambda w: _add_part(work, sums, w, parts), range(parts)):
        pass
    return _finish(work, *sums[0])


def _shares(workers: int) -> list:
    """The octants of each worker: for two, those with an even number of negative axes and
    those with an odd one, each 2 of either sign on every axis (light that mostly goes one
    way, down from a lit ceiling say, is split evenly)."""
    order = [0, 1, 3, 2, 5, 4, 6, 7]  # parity of the sign bits alternates
    workers = max(1, min(workers, len(order)))
    return [order[w::workers] for w in range(workers)]


def _add_part(work: dict, sums: list, w: int, parts: int) -> None:
    """Worker w's part (of ``parts``) of sums[0] += the other workers' sums, in order, less
    the fold of the handed-on light there (``_take_off_passing``): its share of the values'
    cells, and of the outflow's slabs only the shell (the rest is 0 in every sum)."""
    values = sums[0][0]
    cells = work["r"] ** 3
    c0, c1 = w * cells // parts, (w + 1) * cells // parts
    lo, hi = c0 * 3 * sh.BANDS2, c1 * 3 * sh.BANDS2
    for other in sums[1:]:
        values[lo:hi] += other[0][lo:hi]
    _take_off_passing(work, values, c0, c1)
    if work["shell"] and len(sums) > 1:
        p = work["p"]
        for other in sums[1:]:
            _add_shell_kernel(sums[0][1], other[1], p, w * p // parts, (w + 1) * p // parts)


def _take_off_passing(work: dict, values: np.ndarray, c0: int, c1: int) -> None:
    """values (flat R^3 3 9) -= the fold of the handed-on light (it is not an arrival) in the
    grid's flat cells c0..c1-1."""
    pcell, pcol, pflux, _ = work["passing"]
    if not pcell.size:
        return
    r, p = work["r"], work["p"]
    i, j, k = np.unravel_index(pcell, (p, p, p))
    cells = ((i - 1) * r + j - 1) * r + k - 1  # ascending, as pcell
    e0, e1 = np.searchsorted(cells, (c0, c1))
    if e0 == e1:
        return
    basis = tables()["basis"][:, :B8].reshape(8, WIDE, BASIS_STRIDE)
    folded = sum(pflux[o, e0:e1, :WIDE] @ basis[o, :, :sh.BANDS2] for o in range(8))
    values.reshape(-1, sh.BANDS2)[cells[e0:e1] * 3 + pcol[e0:e1]] -= folded


@jit.kernel
def _add_shell_kernel(dst, src, p, i0, i1):  # pragma: no cover - compiled
    """dst += src on the shell cells (12 floats each) of padded slabs i0..i1-1."""
    row = p * 12
    for i in range(i0, i1):
        for j in range(p):
            at = (i * p + j) * row
            if i == 0 or i == p - 1 or j == 0 or j == p - 1:
                for t in range(row):
                    dst[at + t] += src[at + t]
            else:
                for t in range(12):
                    dst[at + t] += src[at + t]
                    dst[at + row - 12 + t] += src[at + row - 12 + t]


@jit.kernel
def _zero_shell_kernel(out, p):  # pragma: no cover - compiled
    """out = 0 on the shell cells (12 floats each) of the padded grid; the rest as it is."""
    row = p * 12
    for i in range(p):
        for j in range(p):
            at = (i * p + j) * row
            if i == 0 or i == p - 1 or j == 0 or j == p - 1:
                out[at:at + row] = 0.0
            else:
                out[at:at + 12] = 0.0
                out[at + row - 12:at + row] = 0.0


def _inputs(injected: np.ndarray, visibility: np.ndarray | None, passing: np.ndarray | None,
            shell: bool, occlude_launch: bool) -> dict:
    """What ``_octant_kernel`` reads besides ``tables()``: the face transmittances (6, R, R, R)
    float32 (or (0, R, R, R): none), the lit cells' launch (``_launch_inputs``), the
    handed-on light (``_passing_inputs``)."""
    r = injected.shape[0]
    faces = np.zeros((0, r, r, r), np.float32)
    if visibility is not None:
        faces = np.ascontiguousarray(visibility, np.float32)
    launch = _launch_inputs(injected, visibility if occlude_launch else None)
    return {"r": r, "p": r + 2, "shell": shell, "faces": faces, **launch,
            "passing": _passing_inputs(passing, r)}


def _direction_lanes(octant_stride: int) -> np.ndarray:
    """Where direction j's value goes in a row of octant lanes: its octant's place (octant
    o at o ``octant_stride``) plus its place in the octant (q,)."""
    base = np.empty(DIRECTIONS, np.int64)
    for o, (d0, count) in enumerate(tables()["span"]):
        base[d0:d0 + count] = o * octant_stride + np.arange(count)
    return base


def _launch_inputs(injected: np.ndarray, visibility: np.ndarray | None) -> dict:
    """The lit cells' launch (kernels/ordinates.py's launch_inputs in the octants' layout):
    "launch" = (flux per octant, lit cell and colour in GEOMETRY lanes (8, n, 3 GEOMETRY), emission
    directions (n, 3), padded cells (n, 3), directions (q, 3), transmittances (n, 27) or
    (n, 0): the launch's occlusion, from ``visibility``), and "lit_first": the first lit
    cell of each slab ((R+3,), the lit cells in flat order)."""
    r = injected.shape[0]
    cells = np.ascontiguousarray(injected, np.float32).reshape(-1, 4)
    lit, rows, xyz, lit_first = _lit_cells_kernel(cells, r)
    # lanes past an octant's directions are left as they are: _launch_lanes never reads them
    flux = np.empty((8, lit.size, 3 * GEOMETRY), np.float32)
    dirs = ordinate_tables()[0]
    unfold_rows_at(cells, rows, np.arange(rows.size) * GEOMETRY, dirs, flux,
                   _direction_lanes(lit.size * 3 * GEOMETRY))
    m = emission_directions(cells, lit)
    lvis = np.zeros((lit.size, 0), np.float32)
    if visibility is not None:
        lvis = np.empty((lit.size, 27), np.float32)
        _offset_visibility_kernel(np.ascontiguousarray(visibility, np.float32), lit, lvis)
    return {"launch": (flux, m, xyz, dirs, lvis), "lit_first": lit_first}


@jit.kernel
def _lit_cells_kernel(cells, r):  # pragma: no cover - compiled
    """kernels/ordinates.py's lit_rows and launch_geometry's cells, compiled: (lit cells
    (n,), their 3 n (cell, colour) rows, padded cells (n, 3), the first lit cell of each
    padded slab (R+3,)); lit where the colours' band 0 sum (in order) is > 0."""
    p = r + 2
    total = r * r * r
    zero = np.float32(0.0)
    lit = np.empty(total, np.int64)
    n = 0
    for c in range(total):
        row = 3 * c
        if (cells[row, 0] + cells[row + 1, 0]) + cells[row + 2, 0] > zero:
            lit[n] = c
            n += 1
    lit = lit[:n].copy()
    rows = np.empty(3 * n, np.int64)
    xyz = np.empty((n, 3), np.int64)
    first = np.zeros(p + 1, np.int64)
    for e in range(n):
        c = lit[e]
        rows[3 * e], rows[3 * e + 1], rows[3 * e + 2] = 3 * c, 3 * c + 1, 3 * c + 2
        i, j, k = c // (r * r) + 1, (c // r) % r + 1, c % r + 1
        xyz[e, 0], xyz[e, 1], xyz[e, 2] = i, j, k
        first[i + 1] = e + 1  # the slabs after i start after e (filled forward below)
    for x in range(1, p + 1):
        first[x] = max(first[x], first[x - 1])
    return lit, rows, xyz, first


@jit.kernel
def _offset_visibility_kernel(faces, cells, out):  # pragma: no cover - compiled
    """quadrature.offset_visibilities(faces) (float32 (6, R, R, R)) at the flat ``cells``
    only, side by side into out (n, 27): the same products in the same order."""
    flat = faces.reshape(6, -1)
    one = np.float32(1.0)
    for e in range(cells.shape[0]):
        c = cells[e]
        f0 = (flat[1, c], one, flat[0, c])
        f1 = (flat[3, c], one, flat[2, c])
        f2 = (flat[5, c], one, flat[4, c])
        for a in range(3):
            for b in range(3):
                ab = f0[a] * f1[b]
                for d in range(3):
                    out[e, (a * 3 + b) * 3 + d] = ab * f2[d]


def _passing_inputs(passing: np.ndarray | None, r: int) -> tuple:
    """The handed-on light in the octants' layout: (padded flat cells (m,), colours (m,),
    flux per octant and (cell, colour) in GEOMETRY lanes (8, m, GEOMETRY), 0 past the
    octant's directions, the first of each slab (R+3,)) for the m (cell, colour) pairs
    holding light (ordinates.unfold_sparse's). Octant-major: an octant reads its own in
    order (cell-major, 1 ms of its kernel's 15 went to cache misses)."""
    if passing is None:
        passing = np.zeros((0, 3, 4), np.float32)
    cells = np.ascontiguousarray(passing, np.float32).reshape(-1, 4)
    rows, pcell, colour, first = _passing_cells_kernel(cells, r)
    flux = np.zeros((8, rows.size, GEOMETRY), np.float32)
    unfold_rows_at(cells, rows, np.arange(rows.size) * GEOMETRY, ordinate_tables()[0], flux,
                   _direction_lanes(rows.size * GEOMETRY))
    return pcell, colour, flux, first


@jit.kernel
def _passing_cells_kernel(cells, r):  # pragma: no cover - compiled
    """The (cell, colour) rows of ``cells`` ((R^3 3, 4)) whose band 0 is > 0, their padded
    flat cells and colours, and the first of each padded slab (R+3,): ``_passing_inputs``'
    index arithmetic, compiled."""
    p = r + 2
    zero = np.float32(0.0)
    rows = np.empty(cells.shape[0], np.int64)
    m = 0
    for t in range(cells.shape[0]):
        if cells[t, 0] > zero:
            rows[m] = t
            m += 1
    rows = rows[:m].copy()
    pcell = np.empty(m, np.int64)
    colour = np.empty(m, np.int64)
    first = np.zeros(p + 1, np.int64)
    for e in range(m):
        c = rows[e] // 3
        colour[e] = rows[e] - 3 * c
        i, j, k = c // (r * r) + 1, (c // r) % r + 1, c % r + 1
        pcell[e] = (i * p + j) * p + k
        first[i + 1] = e + 1
    for x in range(1, p + 1):
        first[x] = max(first[x], first[x - 1])
    return rows, pcell, colour, first


def _ring(work: dict) -> tuple:
    """A worker's slab ring (RING slabs and the spare slot, LANES floats per padded cell)
    and its rows' first lit cells (all 0: the first fill empties every slot)."""
    p = work["p"]
    return np.empty((RING + 1) * p * p * LANES, np.float32), np.zeros((RING + 1, p), np.int64)


def _zero_sums(work: dict, whole: bool = True) -> tuple:
    """Folded sums to add to: values (R^3 3 9) and outflow ((R+2)^3 3 4, empty without the
    shell), zero; not ``whole``: the outflow zero on the shell only (the sweep adds nothing
    elsewhere, and only its shell is added up)."""
    r, p = work["r"], work["p"]
    values = np.zeros(r**3 * 3 * sh.BANDS2, np.float32)
    if not work["shell"]:
        return values, np.zeros(0, np.float32)
    if whole:
        return values, np.zeros(p**3 * 3 * 4, np.float32)
    outflow = np.empty(p**3 * 3 * 4, np.float32)
    _zero_shell_kernel(outflow, p)
    return values, outflow


def _run_octant(work: dict, o: int, ring: tuple, values: np.ndarray,
                outflow: np.ndarray) -> None:
    """``_octant_kernel`` of octant o in a worker's ``_ring``, adding to ``values`` and
    ``outflow``."""
    tab = tables()
    _octant_kernel(o, tab["sign"], tab["span"], tab["factors"], tab["basis"], tab["dirs"],
                   *work["launch"], work["lit_first"], *work["passing"], work["faces"],
                   work["p"], work["shell"], *ring, values, outflow)


def _finish(work: dict, values: np.ndarray, outflow: np.ndarray) -> tuple:
    """The folded sums (added up, the handed-on light's fold taken off: ``_add_part``) in
    their shapes: (values (R, R, R, 3, 9), outflow (R+2, R+2, R+2, 3, 4) or None)."""
    r, p = work["r"], work["p"]
    values = values.reshape(r, r, r, 3, sh.BANDS2)
    return values, (outflow.reshape(p, p, p, 3, 4) if work["shell"] else None)
