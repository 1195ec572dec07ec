"""moderngl compute shaders (GLSL 4.30) for the two stages a GPU can take from the CPU: the
discrete-ordinates propagation (``angular="dom"``) and its lookup (9 coefficients, bands 0-2).
Everything else runs the CPU code: the injection (the engine injects on the CPU and hands the
numpy grid over), KD10's "sh" model and 4-coefficient grids (counted in ``GLBackend.fallbacks``).

The shaders are the ``.glsl`` files in ``shaders/``; each program is ``#version 430``, the
``#define`` lines generated here from the numpy modules' constants (sh's SH factors, the slot
count of the flux layout), then its files in order. Tables (per octant the trilinear weights
of its directions, the SH basis of each direction) are storage buffers made from
``ordinates.tables()``, so a change there carries over; a change of the algorithm must be ported.

Propagation: the first step (light launched from its surfaces, ordinates.launch, plus the plain
first step of light handed on from a finer cascade: ``propagation.first_arrivals``) runs on the
host; the shaders then step (shaders/dom_step.glsl, one dispatch per octant) until a step moves
less than ``min_fraction`` of the injected flux and fold the accumulated flux per direction into
bands 0-2 (shaders/dom_fold.glsl); the host adds the injected grid extended to band 2
(ordinates.add_emission_band2). The CPU solves the same transport for infinitely many steps (a
sweep per octant, sweep.py). What the early stop leaves out is the tail of that series: light
that is never negative, each later step carrying at most what the last one did (a step never
gains flux), so the GL grid is the CPU's less some non-negative light, bounded in
tests/test_gl_backend.py from the stopping rule.

Memory: the flux per direction, q x 3 x 4 bytes per cell (q = 64, packed per octant into 52 vec4
= 832 B), in each of three rgba32f 3-D textures (current, next, accumulated; a fourth for the
outflow with ``capture_outflow``, on the grid padded by one cell): 82 MB at 32^3, 650 MB at
64^3, 5.2 GB at 128^3. Images rather than storage buffers: a GPU caches them as textures.

Backend "auto" (``auto_backend``): on a software renderer (``SOFTWARE_RENDERERS``, e.g. Mesa's
llvmpipe) GL compute runs on the CPU it would relieve and loses to the compiled CPU kernels, so
every stage takes the CPU path and nothing is timed. On a hardware renderer ``measure`` times
both on a small grid once (a few seconds, with the shader compilation) and the choice is kept on
disk, in ``auto_backend.json`` under ``$LPV_GI_CACHE_DIR``, else ``$XDG_CACHE_HOME/lpv_gi``,
else ``~/.cache/lpv_gi``, keyed by everything it depends on (GL vendor, renderer and version,
the angular model, numpy's version, ``os.cpu_count()``, AUTO_MARGIN, the CPU kernels and a hash
of the timed sources, ``code_fingerprint``). ``LPV_GI_NO_CACHE=1`` turns the file off; an
unreadable or unwritable cache is ignored, and a failed GL context is not stored.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from .. import injection, lookup, propagation, sh
from ..grid import Grid
from ..propagation import ordinates
from ..runtime import jit

SHADERS = Path(__file__).resolve().parent / "shaders"
LOCAL = 64  # invocations per work group (1-D)
MAX_GROUPS = 65535  # GL's guaranteed GL_MAX_COMPUTE_WORK_GROUP_COUNT per dimension
# GL_RENDERER names (any case) of renderers that run shaders on the CPU: "auto" never picks
# or times GL there.
SOFTWARE_RENDERERS = ("llvmpipe", "softpipe", "SwiftShader", "Software")

# program -> its .glsl files, in order
PROGRAMS = {
    "dom_step": ("common.glsl", "flux_layout.glsl", "dom_step.glsl"),
    "dom_fold": ("common.glsl", "flux_layout.glsl", "dom_fold.glsl"),
    "lookup": ("common.glsl", "lookup.glsl"),
}


def _lit(x) -> str:
    """A GLSL literal that parses back to exactly this float32 value."""
    return repr(float(np.float32(x)))


def _defines() -> dict:
    """The generated constants every program gets as #define lines."""
    k0, k1, k2 = sh.IRRADIANCE_KERNEL
    return {"LOCAL": LOCAL, "SLOTS": _dom_layout()[1],
            # sh.irradiance_weights: A_l Y_lm, A_l the clamped cosine's band-l factor
            "W0": _lit(k0 * sh.Y0), "W1": _lit(k1 * sh.Y1), "W2": _lit(k2),
            "Y2A": _lit(sh.Y2A), "Y2B": _lit(sh.Y2B), "Y2C": _lit(sh.Y2C),
            # lookup.front_corners' plane and lookup.lookup_visibility's limit, in cells
            "LOOKUP_PLANE": _lit(lookup.OFFSET_CELLS + lookup.PLANE_TOLERANCE),
            "LOOKUP_OPEN": _lit(lookup.OPEN_FOR_LOOKUP)}


def source(name: str) -> str:
    """The GLSL source of program ``name`` (PROGRAMS)."""
    head = ["#version 430"] + [f"#define {k} {v}" for k, v in _defines().items()]
    files = [(SHADERS / f).read_text(encoding="utf-8") for f in PROGRAMS[name]]
    return "\n".join(head + files)


def software_renderer(renderer: str) -> bool:
    """Whether a GL_RENDERER string names a renderer that runs shaders on the CPU."""
    low = renderer.lower()
    return any(name.lower() in low for name in SOFTWARE_RENDERERS)


# -- the flux layout ----------------------------------------------------------------------------
def _dom_layout():
    """Packing of the flux per cell into vec4 slots: per octant (first direction, directions,
    first slot, slots); its 3 x n (direction, colour) values fill ceil(3 n / 4) vec4s, value
    k = 3 i + colour of direction j0 + i at component k % 4 of slot first + k // 4 (the rest
    of the last slot is zero). Returns (octants, total slots)."""
    _, _, groups = ordinates.tables()
    out, slot = [], 0
    for sl, _pairs in groups:
        n = sl.stop - sl.start
        m = -(-3 * n // 4)
        out.append((sl.start, n, slot, m))
        slot += m
    return out, slot


def _dom_tables():
    """(step weights (slots x 8, 4), fold table, per octant (sign, first slot, slots)).

    Step weights [slot x 8 + k]: for each packed value of the slot, the trilinear weight of its
    direction towards offset k = (bits of k) x the octant's sign (ordinates.tables' pairs).
    Fold table: [value x 9 + l] Y_l (bands 0-2, sh.evaluate_basis2) of each packed value's
    direction, then [slots x 36 + value] its colour; zero for the unused ends of slots."""
    dirs, _basis, groups = ordinates.tables()
    layout, slots = _dom_layout()
    basis2 = sh.evaluate_basis2(dirs).astype(np.float32)
    weights = np.zeros((slots, 8, 4), np.float32)
    basis = np.zeros((4 * slots, sh.BANDS2), np.float32)
    colour = np.zeros(4 * slots, np.float32)
    octants = []
    for (j0, n, s0, m), (_sl, pairs) in zip(layout, groups):
        sign = tuple(int(s) for s in np.where(dirs[j0] < 0, -1, 1))
        by_offset = {tuple(int(a) for a in off): np.asarray(w).reshape(-1)
                     for _i, off, w in pairs}
        for k in range(8):
            w = by_offset[tuple(((k >> (2 - a)) & 1) * sign[a] for a in range(3))]
            for v in range(3 * n):
                weights[s0 + v // 4, k, v % 4] = w[v // 3]
        for v in range(3 * n):
            basis[4 * s0 + v] = basis2[j0 + v // 3]
            colour[4 * s0 + v] = v % 3
        octants.append((sign, s0, m))
    return weights.reshape(-1, 4), np.concatenate([basis.ravel(), colour]), octants


def _dom_pack(flux: np.ndarray, tiles_per_row: int) -> bytes:
    """(q, 3, RF, RF, RF) flux per direction -> the bytes of the used region of a flux texture
    (shaders/flux_layout.glsl: slot t's cell (x, y, z) at texel (z + RF (t % A), y,
    x + RF (t // A)), A = ``tiles_per_row``)."""
    octants, slots = _dom_layout()
    rf = flux.shape[-1]
    a = tiles_per_row
    b = -(-slots // a)
    texels = np.zeros((rf * b, rf, rf * a, 4), np.float32)  # (depth, height, width, rgba)
    for j0, n, s0, m in octants:
        values = np.zeros((4 * m, rf, rf, rf), np.float32)
        values[:3 * n] = flux[j0:j0 + n].reshape(3 * n, rf, rf, rf)  # k = 3 i + colour
        values = values.reshape(m, 4, rf, rf, rf).transpose(0, 2, 3, 4, 1)
        for i in range(m):
            t = s0 + i
            texels[rf * (t // a):rf * (t // a + 1), :, rf * (t % a):rf * (t % a + 1)] = values[i]
    return texels.tobytes()


def _dom_tiling(rf: int, slots: int, max_size: int) -> int | None:
    """Tiles per row A: the flux of an RF^3 grid is one 3-D texture (RF A, RF, RF B), B rows
    of tiles, as square as the size limit allows; None if it exceeds ``max_size``."""
    b = -(-slots // max(1, min(slots, max_size // rf)))  # fewest rows of tiles
    a = -(-slots // b)  # then the fewest tiles per row
    return a if rf * a <= max_size and rf * b <= max_size else None


def _not_power_of_two(n: int) -> int:
    """The smallest m >= n that is not a power of two (llvmpipe compiles a shader variant per
    power-of-two-ness of the bound images: one variant instead of several)."""
    while n & (n - 1) == 0:
        n += 1
    return n


class GLBackend:
    """Compute shaders on one moderngl context (the process's shared one by default); the
    engine's backend interface (inject, propagate, irradiance, discard)."""

    name = "gl"
    fresh_results = True  # propagate returns new arrays, never kept: no copy needed

    def __init__(self, ctx=None):
        if ctx is None:
            from ..render.raster import gl_context

            ctx = gl_context()
        self.ctx = ctx
        self._programs: dict = {}
        self._scratch: dict = {}
        self._textures: dict = {}
        self._tables = None  # (step weights, fold table) buffers and the octants
        self.fallbacks = 0  # calls answered by the CPU code

    @property
    def renderer(self) -> str:
        return str(self.ctx.info.get("GL_RENDERER", ""))

    # -- plumbing -------------------------------------------------------------------------------
    def _program(self, name: str):
        prog = self._programs.get(name)
        if prog is None:
            prog = self._programs[name] = self.ctx.compute_shader(source(name))
        return prog

    def _buffer(self, name: str, nbytes: int):
        """A scratch buffer of at least ``nbytes`` (kept and reused between calls)."""
        nbytes = max(int(nbytes), 4)
        buf = self._scratch.get(name)
        if buf is None or buf.size < nbytes:
            if buf is not None:
                buf.release()
            buf = self._scratch[name] = self.ctx.buffer(reserve=nbytes)
        return buf

    def _upload(self, name: str, array, dtype) -> object:
        a = np.ascontiguousarray(array, dtype)
        buf = self._buffer(name, a.nbytes)
        buf.write(a.tobytes())
        return buf

    def _texture3d(self, name: str, size: tuple):
        """A scratch rgba32f 3-D texture of at least ``size`` (kept and reused between calls)."""
        size = tuple(_not_power_of_two(int(d)) for d in size)
        tex = self._textures.get(name)
        if tex is None or tex.size != size:
            if tex is not None:
                tex.release()
            tex = self._textures[name] = self.ctx.texture3d(size, 4, dtype="f4")
        return tex

    def _run(self, prog, count: int, buffers, **uniforms) -> None:
        """Set ``uniforms`` (those the program uses), bind ``buffers`` to storage bindings 0..
        and run ``count`` invocations in chunks of at most MAX_GROUPS work groups."""
        for key, value in dict(uniforms, count=int(count)).items():
            u = prog.get(key, None)
            if u is not None:
                u.value = value
        for i, buf in enumerate(buffers):
            buf.bind_to_storage_buffer(i)
        groups = -(-int(count) // LOCAL)
        done = 0
        while done < groups:
            g = min(groups - done, MAX_GROUPS)
            prog["base"].value = done * LOCAL
            prog.run(g, 1, 1)
            done += g
        self.ctx.memory_barrier()

    def _dom_buffers(self):
        if self._tables is None:
            weights, fold, octants = _dom_tables()
            self._tables = (self.ctx.buffer(weights.tobytes()), self.ctx.buffer(fold.tobytes()),
                            octants)
        return self._tables

    def check(self) -> None:
        """Compile and run a compute shader (raises where this context cannot)."""
        self.irradiance(Grid((0.0, 0.0, 0.0), 1.0, 1), np.zeros((1, 1, 1, 3, sh.BANDS2)),
                        np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]))

    # -- the engine's interface -----------------------------------------------------------------
    @staticmethod
    def inject(*args, **kwargs):
        """The CPU injection (injection.inject): propagation takes the injected numpy grid."""
        return injection.inject(*args, **kwargs)

    @staticmethod
    def discard(obj) -> None:
        pass

    _DOM_OPTIONS = frozenset({"visibility", "angular", "occlude_first_step", "capture_outflow",
                              "launch", "passing"})  # the keywords of propagation.propagate

    def propagate(self, injected: np.ndarray, iterations: int, min_fraction: float = 1e-3,
                  **options) -> propagation.PropagationResult:
        """``propagation.propagate`` (keywords as there): angular="dom" with ``launch`` (light
        just emitted by surfaces, what the engine propagates) steps on the GPU until a step
        moves less than ``min_fraction`` of the injected flux, at most ``iterations`` steps;
        anything else, or a flux texture larger than GL_MAX_3D_TEXTURE_SIZE, runs the CPU
        code (counted in ``fallbacks``)."""
        res = None
        if (options.get("angular", "dom") == "dom" and options.get("launch")
                and set(options) <= self._DOM_OPTIONS):
            res = self._propagate_dom(np.asarray(injected, np.float32), int(iterations),
                                      float(min_fraction), options.get("visibility"),
                                      bool(options.get("occlude_first_step")),
                                      bool(options.get("capture_outflow")),
                                      options.get("passing"))
        if res is None:
            self.fallbacks += 1
            res = propagation.propagate(injected, iterations, min_fraction, **options)
        return res

    def irradiance(self, grid: Grid, values: np.ndarray, positions: np.ndarray,
                   normals: np.ndarray, offset_cells: float = lookup.OFFSET_CELLS,
                   angular: str = "dom", visibility: np.ndarray | None = None,
                   **extra) -> np.ndarray:
        """``lookup.irradiance``: indirect irradiance (M, 3) float64 in W/m^2. A 9-coefficient
        grid (bands 0-2, a "dom" propagation's) is read on the GPU (shaders/lookup.glsl); any
        other grid or keyword runs the CPU code (counted in ``fallbacks``)."""
        if np.shape(values)[-1:] != (sh.BANDS2,) or extra:
            self.fallbacks += 1
            return lookup.irradiance(grid, values, positions, normals, offset_cells,
                                     angular=angular, visibility=visibility, **extra)
        r = grid.resolution
        values = np.ascontiguousarray(values, np.float32)
        if values.shape != (r, r, r, 3, sh.BANDS2):
            raise ValueError(f"grid values must be {(r, r, r, 3, sh.BANDS2)}, not {values.shape}")
        positions = np.asarray(positions, np.float64)
        m = positions.shape[0]
        if m == 0:
            return np.zeros((0, 3), np.float64)
        vis = None
        if visibility is not None:
            vis = np.ascontiguousarray(visibility, np.float32)
            if vis.shape != (6, r, r, r):
                raise ValueError(f"visibility must be (6, {r}, {r}, {r}), not {vis.shape}")
        buffers = [self._upload("lookup_values", values, np.float32),
                   self._upload("lookup_pos", positions, np.float64),
                   self._upload("lookup_nrm", normals, np.float64),
                   self._buffer("lookup_out", m * 12),
                   self._upload("lookup_vis", vis, np.float32) if vis is not None
                   else self._buffer("no_vis", 4)]
        self._run(self._program("lookup"), m, buffers, R=r,
                  origin=tuple(float(v) for v in grid.origin),
                  inv_cell=1.0 / float(grid.cell_size), offset_cells=float(offset_cells),
                  k_irr=float(1.0 / grid.cell_size**2), use_vis=int(vis is not None))
        out = np.frombuffer(buffers[3].read(size=m * 12), np.float32).reshape(m, 3)
        return out.astype(np.float64)

    # -- dom propagation ------------------------------------------------------------------------
    def _propagate_dom(self, injected, iterations, min_fraction, visibility, occlude_first_step,
                       capture_outflow, passing) -> propagation.PropagationResult | None:
        """The launched dom propagation (see the module notes): values (R, R, R, 3, 9) and,
        with ``capture_outflow``, the outflow's 4 moments on the padded grid. None if the flux
        textures would exceed GL_MAX_3D_TEXTURE_SIZE (the caller runs the CPU code)."""
        r = injected.shape[0]
        pad = int(capture_outflow)
        rf = r + 2 * pad
        _, slots = _dom_layout()
        per_row = _dom_tiling(rf, slots, int(self.ctx.info.get("GL_MAX_3D_TEXTURE_SIZE", 2048)))
        if per_row is None:
            return None
        total = injected if passing is None else injected + passing
        # the flux the unfolded light holds (ordinates.unfold keeps each lit cell's exactly)
        total0 = float(np.maximum(total[..., 0], 0.0).sum(dtype=np.float64)) * sh.SQRT_4PI
        values = np.zeros((r, r, r, 3, sh.BANDS2), np.float32)
        outflow = np.zeros((r + 2, r + 2, r + 2, 3, 4), np.float32) if pad else None
        done, fraction, early = 0, (1.0 if total0 > 0 else 0.0), not total0 > 0
        if not early and iterations > 0:
            start, _ = propagation.first_arrivals(injected, visibility, occlude_first_step,
                                                  passing)
            arrived = start.reshape(start.shape[0], 3, r + 2, r + 2, r + 2)
            inner = (Ellipsis, slice(1, -1), slice(1, -1), slice(1, -1))
            interior = np.zeros_like(arrived)
            interior[inner] = arrived[inner]  # what goes on stepping (and is accumulated)
            shell = arrived - interior  # what left the grid in the first step
            done = 1
            fraction = float(interior.sum(dtype=np.float64)) / total0
            early = fraction < min_fraction
            size = (rf * per_row, rf, rf * -(-slots // per_row))
            cur, nxt, acc = (self._texture3d(n, size) for n in ("dom_a", "dom_b", "dom_acc"))
            none = self._texture3d("dom_none", (1, 1, 1))
            out_tex = self._texture3d("dom_outflow", size) if pad else none
            packed = _dom_pack(interior if pad else interior[inner], per_row)
            for tex in (cur, acc):
                tex.write(packed, viewport=(0, 0, 0) + size)
            if pad:
                out_tex.write(_dom_pack(shell, per_row), viewport=(0, 0, 0) + size)
            vis_tex = none if visibility is None else self._visibility_texture(visibility, r)
            weights, fold_table, octants = self._dom_buffers()
            cells = rf**3
            groups = -(-cells // LOCAL)
            partial = self._buffer("dom_partial", 8 * groups * len(octants))
            step = self._program("dom_step")
            for _ in range(0 if early else iterations - 1):
                cur.bind_to_image(0, read=True, write=False)
                nxt.bind_to_image(1, read=False, write=True)
                acc.bind_to_image(2, read=True, write=True)
                out_tex.bind_to_image(3, read=True, write=True)
                vis_tex.bind_to_image(4, read=True, write=False)
                for o, (sign, first, m) in enumerate(octants):
                    self._run(step, cells, [weights, partial], RF=rf, tiles_per_row=per_row,
                              RV=r, pad=pad, use_vis=int(visibility is not None), sign=sign,
                              first_slot=first, slots=m, part_base=o * groups)
                moved = float(np.frombuffer(partial.read(size=8 * groups * len(octants)),
                                            np.float64).sum())
                cur, nxt = nxt, cur
                done += 1
                fraction = moved / total0
                if fraction < min_fraction:
                    early = True
                    break
            values = self._fold(acc, r, pad, rf, per_row, sh.BANDS2, fold_table)
            if pad:
                outflow = self._fold(out_tex, rf, 0, rf, per_row, 4, fold_table)
        ordinates.add_emission_band2(values, total)
        return propagation.PropagationResult(values, done, propagation.flux(total), fraction,
                                             early, outflow)

    def _fold(self, tex, r: int, pad: int, rf: int, per_row: int, k: int, table) -> np.ndarray:
        """(R, R, R, 3, K) SH of the flux texture ``tex`` (cells offset by ``pad``)."""
        nbytes = r**3 * 12 * k
        dst = self._buffer("dom_folded", nbytes)
        tex.bind_to_image(0, read=True, write=False)
        self._run(self._program("dom_fold"), r**3, [table, dst], R=r, pad=pad, K=k, RF=rf,
                  tiles_per_row=per_row)
        return np.frombuffer(dst.read(size=nbytes), np.float32).reshape(r, r, r, 3, k).copy()

    def _visibility_texture(self, visibility, r: int):
        """The (6, R, R, R) face transmittances as a 3-D texture of two texels per cell: faces
        (+x, -x, +y, -y) at (z, y, x), (+z, -z) at (z, y, x + R)."""
        vis = np.asarray(visibility, np.float32)
        if vis.shape != (6, r, r, r):
            raise ValueError(f"visibility must be (6, {r}, {r}, {r}), not {vis.shape}")
        texels = np.ones((2 * r, r, r, 4), np.float32)  # (depth, height, width, rgba)
        texels[:r] = np.moveaxis(vis[:4], 0, -1)
        texels[r:, ..., :2] = np.moveaxis(vis[4:], 0, -1)
        tex = self._texture3d("dom_vis", (r, r, 2 * r))
        tex.write(texels.tobytes(), viewport=(0, 0, 0, r, r, 2 * r))
        return tex

    def release(self) -> None:
        """Free the backend's programs, tables and scratch buffers."""
        tables = list(self._tables[:2]) if self._tables is not None else []
        for obj in (list(self._scratch.values()) + list(self._textures.values())
                    + list(self._programs.values()) + tables):
            obj.release()
        self._scratch.clear()
        self._textures.clear()
        self._programs.clear()
        self._tables = None


_BACKEND: GLBackend | None = None


def backend() -> GLBackend:
    """The process's GLBackend on ``raster.gl_context()``."""
    global _BACKEND
    if _BACKEND is None:
        _BACKEND = GLBackend()
    return _BACKEND


# -- backend "auto" -------------------------------------------------------------------------------
STAGES = ("propagate", "lookup")  # the stages GL can take (the injection is always the CPU's)
_AUTO: dict = {}  # angular model -> auto_backend record


def measure(resolution: int = 16, vpls: int = 16384, receivers: int = 65536, repeat: int = 3,
            gl: GLBackend | None = None) -> dict:
    """{stage: {backend: ms}}: the fastest of ``repeat`` interleaved runs of each stage as the
    engine runs it (dom light launched from its surfaces: the CPU's sweep against GL's steps
    to the early stop; the lookup of the result) on a small random grid. The minimum is the
    figure least disturbed by other load; the GL figures include the transfers."""
    if gl is None:
        gl = backend()
    rng = np.random.default_rng(0)
    g = Grid((0.0, 0.0, 0.0), 1.0, resolution)
    pos = rng.uniform(1.0, resolution - 1.0, (vpls, 3))
    nrm = rng.normal(size=(vpls, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    flux = rng.uniform(0.0, 1.0, (vpls, 3))
    rpos = rng.uniform(1.0, resolution - 1.0, (receivers, 3))
    rnrm = rng.normal(size=(receivers, 3))
    rnrm /= np.linalg.norm(rnrm, axis=1, keepdims=True)
    injected = injection.inject(g, pos, nrm, flux)
    its = 3 * resolution  # the engine's cap for "dom" (engine.auto_iterations)
    kw = {"angular": "dom", "launch": True}
    values = propagation.propagate(injected, its, **kw).values
    runs = {
        ("propagate", "numpy"): lambda: propagation.propagate(injected, its, **kw),
        ("propagate", "gl"): lambda: gl.propagate(injected, its, **kw),
        ("lookup", "numpy"): lambda: lookup.irradiance(g, values, rpos, rnrm, angular="dom"),
        ("lookup", "gl"): lambda: gl.irradiance(g, values, rpos, rnrm, angular="dom"),
    }
    times = {key: [] for key in runs}
    for fn in runs.values():
        fn()  # warm-up: shader compilation, scratch buffers, kernels
    for _ in range(repeat):
        for key, fn in runs.items():
            t0 = time.perf_counter()
            fn()
            times[key].append((time.perf_counter() - t0) * 1000.0)
    out: dict = {stage: {} for stage in STAGES}
    for (stage, name), t in times.items():
        out[stage][name] = round(float(min(t)), 3)
    return out


# GL must beat the CPU by this factor to be picked: the measurement is a few runs on a small
# grid of a shared machine, and the CPU path is the reference. A GPU that is worth it wins by
# much more.
AUTO_MARGIN = 1.5


def choose(ms: dict) -> dict:
    """{stage: backend} from measure()'s {stage: {backend: ms}}: gl only where it is
    AUTO_MARGIN times faster than numpy."""
    return {stage: "gl" if ms[stage].get("gl", np.inf) * AUTO_MARGIN < ms[stage]["numpy"]
            else "numpy" for stage in STAGES}


CACHE_FILE = "auto_backend.json"
# What measure() times, relative to lpv_core (folders: their .py and .glsl files): a change to
# any of them measures again.
TIMED_SOURCES = ("gl", "propagation", "kernels", "injection.py", "lookup.py", "sh.py",
                 "grid.py", "runtime")
_FINGERPRINT: str | None = None


def code_fingerprint() -> str:
    """sha256 (16 hex digits) of the sources of the code measure() times."""
    global _FINGERPRINT
    if _FINGERPRINT is None:
        h = hashlib.sha256()
        root = Path(__file__).resolve().parents[1]
        for name in TIMED_SOURCES:
            path = root / name
            files = sorted(f for f in path.rglob("*") if f.suffix in (".py", ".glsl")) \
                if path.is_dir() else [path]
            for f in files:
                h.update(f.relative_to(root).as_posix().encode())
                try:
                    h.update(f.read_bytes())
                except OSError:
                    h.update(b"?")
        _FINGERPRINT = h.hexdigest()[:16]
    return _FINGERPRINT


def cache_dir() -> Path:
    """Where the auto choice is kept: $LPV_GI_CACHE_DIR, else $XDG_CACHE_HOME/lpv_gi, else
    ~/.cache/lpv_gi."""
    if os.environ.get("LPV_GI_CACHE_DIR"):
        return Path(os.environ["LPV_GI_CACHE_DIR"])
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "lpv_gi"


def _cache_enabled() -> bool:
    return os.environ.get("LPV_GI_NO_CACHE", "").strip().lower() in ("", "0", "false", "no")


def cache_key(gl: GLBackend, angular: str) -> str:
    """Everything the auto choice depends on, as one string."""
    info = gl.ctx.info
    parts = {"vendor": info.get("GL_VENDOR", ""), "renderer": info.get("GL_RENDERER", ""),
             "version": info.get("GL_VERSION", ""), "angular": angular,
             "numpy": np.__version__, "cpus": os.cpu_count(), "margin": AUTO_MARGIN,
             "code": code_fingerprint(), "cpu_kernels": jit.name()}
    return json.dumps(parts, sort_keys=True)


def _cache_read() -> dict:
    """The cache file's {key: record}; {} when missing, unreadable or not a JSON object."""
    try:
        with open(cache_dir() / CACHE_FILE, encoding="utf-8") as f:
            data = json.load(f)
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def _cache_write(key: str, record: dict) -> None:
    """Add ``record`` under ``key`` (atomically: temp file + os.replace); errors are ignored
    (a cache that cannot be written is no cache)."""
    tmp = None
    with contextlib.suppress(Exception):
        folder = cache_dir()
        folder.mkdir(parents=True, exist_ok=True)
        data = _cache_read()
        data[key] = record
        fd, tmp = tempfile.mkstemp(prefix=".auto_backend.", suffix=".tmp", dir=folder)
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            json.dump(data, f, indent=1)
        os.replace(tmp, folder / CACHE_FILE)
        tmp = None
    if tmp is not None:  # written but not moved into place
        with contextlib.suppress(OSError):
            os.unlink(tmp)


def _valid(record) -> bool:
    return (isinstance(record, dict) and isinstance(record.get("stages"), dict)
            and set(record["stages"]) == set(STAGES)
            and all(v in ("numpy", "gl") for v in record["stages"].values())
            and record.get("backend") in ("numpy", "gl", "mixed"))


def _cpu(angular: str, reason: str) -> dict:
    return {"backend": "numpy", "stages": dict.fromkeys(STAGES, "numpy"), "ms": {},
            "angular": angular, "reason": reason}


def auto_backend(gl: GLBackend | None = None, angular: str = "dom") -> dict:
    """Where each stage runs for backend "auto" and this angular model, remembered per process:
    {"backend": "numpy" | "gl" | "mixed", "stages": {stage: backend}, "ms": measure()'s
    figures, "angular", and "reason" where the CPU was taken without timing anything (a
    software renderer, a model GL does not run, no usable GL) or "cached" (whether the choice
    was read from the disk cache, see the module notes)."""
    if angular not in _AUTO:
        _AUTO[angular] = _auto_choice(gl, angular)
    return _AUTO[angular]


def _auto_choice(gl: GLBackend | None, angular: str) -> dict:
    try:
        gl = gl if gl is not None else backend()
        renderer = gl.renderer
    except Exception as exc:  # noqa: BLE001 - no usable GL context: the CPU it is
        return _cpu(angular, f"gl unavailable: {exc}")
    if angular != "dom":
        return _cpu(angular, f'GL runs angular="dom" only, not {angular!r}: nothing to time')
    if software_renderer(renderer):
        return _cpu(angular, f"software renderer ({renderer}): GL compute runs on the CPU "
                             "there and loses to the CPU kernels, not timed")
    try:
        key = None
        if _cache_enabled():
            try:
                key = cache_key(gl, angular)
                hit = _cache_read().get(key)
            except Exception:  # noqa: BLE001 - the cache never stops a render
                key, hit = None, None
            if _valid(hit):
                stages = {stage: hit["stages"][stage] for stage in STAGES}
                return dict(hit, stages=stages, cached=True)
        ms = measure(gl=gl)
        stages = choose(ms)
        names = set(stages.values())
        record = {"backend": names.pop() if len(names) == 1 else "mixed",
                  "stages": stages, "ms": ms, "angular": angular}
        if key is not None:
            _cache_write(key, record)
        return dict(record, cached=False)
    except Exception as exc:  # noqa: BLE001 - GL failed while measuring: the CPU it is
        return _cpu(angular, f"gl unavailable: {exc}")


class MixedBackend:
    """Each stage on the backend that measured fastest for it (``auto_backend``); the
    injection on the CPU. Grids cross as numpy arrays."""

    fresh_results = True  # both backends' propagate return new arrays

    def __init__(self, stages: dict, backends: dict):
        self.stages = dict(stages)
        self._backends = backends
        self.name = "mixed(" + ", ".join(f"{k}={v}" for k, v in self.stages.items()) + ")"

    inject = staticmethod(injection.inject)

    @staticmethod
    def discard(obj) -> None:
        pass

    def propagate(self, *args, **kwargs):
        return self._backends[self.stages["propagate"]].propagate(*args, **kwargs)

    def irradiance(self, *args, **kwargs):
        return self._backends[self.stages["lookup"]].irradiance(*args, **kwargs)


def auto_select(gl: GLBackend | None, numpy_backend, angular: str = "dom"):
    """(backend object for settings.backend = "auto", the auto_backend record)."""
    choice = auto_backend(gl, angular) if gl is not None else _cpu(angular, "gl unavailable")
    backends = {"numpy": numpy_backend, "gl": gl}
    if choice["backend"] == "mixed":
        return MixedBackend(choice["stages"], backends), choice
    return backends[choice["backend"]], choice
