"""geometry_volume's compiled twins (kernels/geometry_volume.py) against its numpy reference:
the same bits.

Coverage is a count of samples and the kernels repeat the numpy arithmetic operation for
operation (same edge tolerances, plane rule and sample window), so every output must match
exactly, not just to within a sample."""


import numpy as np
import pytest

pytest.importorskip("numba")

from lpv_core import geometry_volume
from lpv_core.grid import Grid, fit_grid
from lpv_core.kernels import geometry_volume as compiled
from lpv_core.runtime import jit
from lpv_core.scene import GISettings
from tools import core_scenes as demo

pytestmark = pytest.mark.skipif(not jit.enabled(), reason="kernels turned off (LPV_JIT=0)")


TWINS = ("_subdivide", "face_coverage", "face_offsets", "occluder_volume")


def _both(name, *args):
    """(numpy reference's result, compiled twin's result) of the stage function ``name`` on
    args: the stage with the kernels off, then on (it then prepares the inputs and runs the
    twin: test_the_stage_runs_its_twins)."""
    with jit.disabled():
        ref = getattr(geometry_volume, name)(*args)
    return ref, getattr(geometry_volume, name)(*args)


def _same(ref, new):
    ref = ref if isinstance(ref, tuple) else (ref,)
    new = new if isinstance(new, tuple) else (new,)
    assert len(ref) == len(new)
    for a, b in zip(ref, new):
        assert a.shape == b.shape and a.dtype == b.dtype
        np.testing.assert_array_equal(a, b)


def _check(grid: Grid, triangles: np.ndarray):
    """Every geometry_volume step, numpy vs compiled, on ``triangles`` in ``grid``."""
    spacing = geometry_volume.SURFEL_SPACING * grid.cell_size
    _same(*_both("_subdivide", triangles, spacing))
    with jit.disabled():
        sub, _, normal, area = geometry_volume._subdivide(triangles, spacing)
    ref, new = _both("face_coverage", grid, sub)
    _same(ref, new)
    _same(*_both("face_offsets", grid, sub, normal, area))
    _same(*_both("occluder_volume", grid, triangles))
    return ref


def test_the_stage_runs_its_twins(monkeypatch):
    # With the kernels on, each function with a twin calls it (on the inputs it prepared).
    grid = Grid((0.0, 0.0, 0.0), 1.0, 4)
    args = {"_subdivide": (np.zeros((1, 3, 3)), 0.5), "face_coverage": (grid, np.zeros((1, 3, 3))),
            "face_offsets": (grid, np.zeros((1, 3, 3)), np.zeros((1, 3)), np.zeros(1)),
            "occluder_volume": (grid, np.zeros((1, 3, 3)))}
    for name in TWINS:
        monkeypatch.setattr(compiled, name, lambda *a, name=name: name)
        assert getattr(geometry_volume, name)(*args[name]) == name


def _cornell(resolution: int):
    sc = demo.cornell_box("SPOT", (16, 16), GISettings(grid_resolution=resolution))
    lo, hi = sc.bounds()
    return fit_grid(lo, hi, resolution), sc.positions[sc.flag("occluder")]


def _random_triangles(rng, r: int, n: int) -> np.ndarray:
    """Triangles in a grid of cell 1 at the origin: sizes from 1e-3 to 3 R cells, centres
    reaching past the grid on every side, a quarter degenerate (collinear or a point) and a
    quarter edge-on or nearly edge-on to a grid axis, some of them flat on a grid plane."""
    centre = rng.uniform(-0.3 * r, 1.3 * r, (n, 1, 3))
    size = np.exp(rng.uniform(np.log(1e-3), np.log(3.0 * r), (n, 1, 1)))
    tri = centre + size * rng.uniform(-0.5, 0.5, (n, 3, 3))
    kind = rng.integers(0, 8, n)
    t = rng.uniform(-1.0, 2.0, n)
    collinear = kind == 0
    tri[collinear, 2] = tri[collinear, 0] + t[collinear, None] * (tri[collinear, 1]
                                                                 - tri[collinear, 0])
    tri[kind == 1] = tri[kind == 1, :1]  # all three corners in one point
    axis = rng.integers(0, 3, n)
    for i in np.nonzero(kind == 2)[0]:  # edge-on: flat in one coordinate's *direction*
        d = tri[i, 1] - tri[i, 0]
        d[axis[i]] += 1.0
        tri[i, 2] = tri[i, 0] + rng.uniform(-2, 2) * d
    for i in np.nonzero(kind == 3)[0]:  # nearly edge-on to axis: a tilt of 1e-10 .. 1e-6
        tri[i, :, axis[i]] = tri[i, 0, axis[i]] + rng.uniform(-1, 1, 3) * 10 ** rng.uniform(
            -10, -6)
        tri[i, :, (axis[i] + 1) % 3] = tri[i, 0, (axis[i] + 1) % 3]
        tri[i, 1, (axis[i] + 1) % 3] += 1e-9
    for i in np.nonzero(kind == 4)[0]:  # flat on a cell or half-cell plane
        tri[i, :, axis[i]] = np.round(tri[i, 0, axis[i]] * 2.0) / 2.0
    return tri


@pytest.mark.parametrize("resolution", [5, 16])
def test_cornell_box_matches_numpy(resolution):
    grid, tris = _cornell(resolution)
    cover = _check(grid, tris)
    assert cover.max() == 1.0  # (the walls do cover faces)


@pytest.mark.parametrize("resolution", [5, 16])
def test_random_triangles_match_numpy(resolution):
    rng = np.random.default_rng(7 + resolution)
    grid = Grid((0.0, 0.0, 0.0), 1.0, resolution)
    tris = _random_triangles(rng, resolution, 60)
    # (moved and scaled, so that no coordinate is a round number)
    moved = Grid((-3.25, 1.5, 1e3), 0.37, resolution)
    cover = _check(grid, tris)
    assert 0.0 < cover.mean() < 1.0
    _check(moved, tris * 0.37 + moved.origin_array)


@pytest.mark.parametrize("resolution", [5, 16])
def test_unsubdivided_triangles_and_slivers_match_numpy(resolution):
    # face_coverage on triangles as they come (up to 1.5 cells: the numpy path scans the
    # largest one's window for each), slivers just above and below its edge-on threshold
    # included, whose tolerance-grown tips reach past their own bounding boxes.
    rng = np.random.default_rng(resolution)
    grid = Grid((0.0, 0.0, 0.0), 1.0, resolution)
    tris = rng.uniform(-1.0, resolution + 1.0, (400, 1, 3)) + rng.uniform(-0.75, 0.75,
                                                                          (400, 3, 3))
    for i in range(0, 400, 4):
        axis = i % 3
        tris[i, 2] = 0.5 * (tris[i, 0] + tris[i, 1])
        tris[i, 2, (axis + 1) % 3] += 10.0 ** rng.uniform(-13, -7)
    _same(*_both("face_coverage", grid, tris))
    normal = rng.normal(size=(400, 3))
    area = rng.uniform(0.0, 1.0, 400)
    _same(*_both("face_offsets", grid, tris, normal, area))


@pytest.mark.parametrize("resolution", [5, 16])
@pytest.mark.parametrize("at", [2.5, 2.0])
def test_axis_aligned_wall_on_a_plane_matches_numpy(resolution, at):
    # A wall exactly half-way between two face planes (x = 2.5 cells: the tie rule puts it on
    # the lower one) or on one (x = 2), edges on face boundaries, as two triangles.
    grid = Grid((0.0, 0.0, 0.0), 1.0, resolution)
    y0, y1, z0, z1 = 1.0, resolution - 1.0, 0.5, resolution - 2.0
    wall = np.array([[[at, y0, z0], [at, y1, z0], [at, y1, z1]],
                     [[at, y0, z0], [at, y1, z1], [at, y0, z1]]])
    cover = _check(grid, wall)
    assert cover[0, 2, 1:resolution - 1, 1:resolution - 2].min() == 1.0
    vis, gaps = geometry_volume.occluder_volume(grid, wall)
    assert vis.min() == 0.0 and (gaps.max() > 0) == (at == 2.5)


def _on_samples(grid: Grid, axis: int, plane: float, su, sv) -> np.ndarray:
    """World points at sample coordinates (su, sv) (sample j at (j + 0.5) / M cells) on the
    plane ``plane`` (cells) across ``axis``."""
    m = geometry_volume.COVERAGE_SAMPLES
    u, v = [a for a in range(3) if a != axis]
    rel = np.empty(np.broadcast(su, sv).shape + (3,))
    rel[..., axis] = plane
    rel[..., u] = (np.asarray(su) + 0.5) / m
    rel[..., v] = (np.asarray(sv) + 0.5) / m
    return grid.origin_array + grid.cell_size * rel


@pytest.mark.parametrize("resolution", [5, 16])
@pytest.mark.parametrize("origin, cell", [((0.0, 0.0, 0.0), 1.0), ((-3.25, 1.5, 7.1), 0.37)])
def test_edges_through_samples_and_slivers_match_numpy(resolution, origin, cell):
    # Where the tolerances decide: (1) triangles with corners on sample points, their edges
    # (diagonals too) running through samples, which rounding puts a hair inside or outside,
    # or moved off them by about the tolerance;
    # (2) slivers along a row of samples, as thin as 1e-10 .. 1e-8 of their length (around
    # the edge-on threshold, 1e-9), whose tolerance-grown tips reach a sample past their
    # bounding boxes (counted only inside the largest window any triangle needs: see
    # _cover_part_kernel).
    rng = np.random.default_rng(resolution)
    grid = Grid(origin, cell, resolution)
    rm = resolution * geometry_volume.COVERAGE_SAMPLES
    tris = []
    for _ in range(300):
        axis = int(rng.integers(0, 3))
        plane = rng.integers(0, resolution + 1) + rng.uniform(-0.4, 0.4)
        base = rng.integers(-2, rm + 2, 2)
        su, sv = (base[:, None] + rng.integers(-4, 5, (2, 3))).astype(float)
        if rng.random() < 0.5:  # moved off the samples by about the tolerance
            su += rng.choice([-1.0, 1.0]) * 10 ** rng.uniform(-10, -8)
        tris.append(_on_samples(grid, axis, plane, su, sv))
    for _ in range(300):
        axis = int(rng.integers(0, 3))
        plane = rng.integers(0, resolution + 1) + rng.uniform(-0.4, 0.4)
        length = rng.uniform(0.5, 5.0)
        thin = length * 10 ** rng.uniform(-10, -8)
        j, row = rng.uniform(-2, rm + 2), float(rng.integers(-1, rm + 1))
        tip, far = (j + length, j) if rng.random() < 0.5 else (j, j + length)
        su = np.array([tip, far, far])
        sv = np.array([row, row, row + thin])
        if rng.random() < 0.5:
            su, sv = sv, su
        tris.append(_on_samples(grid, axis, plane, su, sv))
    tris = np.array(tris)
    _same(*_both("face_coverage", grid, tris))
    _check(grid, tris)


@pytest.mark.parametrize("samples", [1, 3, 12])
def test_other_sample_counts_match_numpy(samples):
    # (12 x 12 samples: more than one 64-bit word of hit bits per face)
    grid, tris = _cornell(5)
    with jit.disabled():
        sub = geometry_volume._subdivide(tris, 0.5 * grid.cell_size)[0]
    _same(*_both("face_coverage", grid, sub, samples))


def test_empty_matches_numpy():
    grid = Grid((0.0, 0.0, 0.0), 1.0, 4)
    _check(grid, np.zeros((0, 3, 3)))


def test_occluder_volume_runs_match_numpy():
    # occluder_volume's first pass runs over the triangles in runs, on the pool threads; the
    # face_offsets sums of faces that several runs reach must still add in sub-triangle order:
    # a wall, the same wall again, a tilted copy and a moved one (split two and two), all on
    # the same faces.
    grid = Grid((0.0, 0.0, 0.0), 1.0, 6)
    wall = np.array([[[2.3, 0.5, 0.5], [2.3, 5.5, 0.5], [2.3, 5.5, 5.5]]])
    tilt = wall.copy()
    tilt[0, 2, 0] += 0.3
    moved = wall + np.array([0.1, 0.0, 0.0])
    _same(*_both("occluder_volume", grid, np.concatenate([wall, wall, tilt, moved])))
    _check(grid, np.concatenate([wall, moved, tilt, wall]))


# occluder_volume's shortcuts (see kernels/geometry_volume.py): a triangle whose
# sub-triangles all surely go to one plane has its interior filled and only the sub-triangles
# along edges with samples near them scanned; a triangle surely edge-on to an axis adds no
# records there; records are scanned over their own window where no sample past it can count;
# the triangles are cut in chunks shared by two threads. Each must leave the bits as numpy's.


def _boxes(rng, grid: Grid, count: int, snap: float) -> np.ndarray:
    """``count`` axis-aligned boxes (walls: filled planes) in ``grid``, corners snapped to
    multiples of ``snap`` cells (cell lines 1, half cells 0.5, sample lines 1/8, or 0: none),
    some moved off them by about the fill's margin."""
    tris = []
    r = grid.resolution
    for _ in range(count):
        lo = rng.uniform(-0.3 * r, 1.1 * r, 3)
        hi = lo + rng.uniform(0.3, 1.2 * r, 3)
        if snap > 0:
            lo, hi = np.round(lo / snap) * snap, np.round(hi / snap) * snap
            lo = lo + rng.choice([0.0, 1e-9, 1e-5, -1e-5, 3e-4]) / 8
        hi = np.maximum(hi, lo + 0.1)
        tris.append(demo.box_triangles(grid.origin_array + lo * grid.cell_size,
                                       grid.origin_array + hi * grid.cell_size))
    return np.concatenate(tris)


@pytest.mark.parametrize("snap", [1.0, 0.5, 1 / 8, 1 / 16, 0.0])
@pytest.mark.parametrize("origin, cell", [((0.0, 0.0, 0.0), 1.0), ((-3.25, 1.5, 1e3), 0.37),
                                          ((1e4, -2e4, 5e3), 0.1)])
def test_filled_walls_match_numpy(snap, origin, cell):
    # Walls on cell lines, half cells (between samples: no scanned edges), sample lines (every
    # edge within reach of samples), off them by the margin or not at all; near the origin or
    # far from it (the edge-on test's rounding).
    rng = np.random.default_rng(int(snap * 16) + int(cell * 100))
    grid = Grid(origin, cell, 12)
    tris = _boxes(rng, grid, 4, snap)
    cover = _check(grid, tris)
    assert cover.max() == 1.0


@pytest.mark.parametrize("tilt", [0.0, 1e-13, 1e-10, 1e-8, 1e-7, 1e-4, 0.3])
def test_nearly_aligned_walls_match_numpy(tilt):
    # A wall tilted by ``tilt`` cells across its 10 cells: edge-on to two axes' planes or just
    # not (offset terms without records, or records: slivers on a row of samples, x = 34.5 / 8
    # cells), and its plane one or several.
    grid = Grid((0.0, 0.0, 0.0), 1.0, 12)
    x = 34.5 / geometry_volume.COVERAGE_SAMPLES
    wall = np.array([[[x, 1.0, 1.0], [x, 11.0, 1.0], [x + tilt, 11.0, 11.0]],
                     [[x, 1.0, 1.0], [x + tilt, 11.0, 11.0], [x + tilt, 1.0, 11.0]]])
    _check(grid, wall)
    _check(grid, wall + np.array([0.2 - tilt / 2, 0.0, 0.0]))  # (about the tie at 4.5)


def test_fill_window_with_slivers_matches_numpy():
    # Slivers whose tolerance-grown tips reach samples past their own windows count those
    # samples only inside the largest window any sub-triangle needs: here a filled wall's
    # interior sub-triangles (no records of their own) set it.
    rng = np.random.default_rng(3)
    grid = Grid((0.0, 0.0, 0.0), 1.0, 10)
    rm = 10 * geometry_volume.COVERAGE_SAMPLES
    slivers = []
    for _ in range(300):
        axis = int(rng.integers(0, 3))
        plane = rng.integers(0, 11) + rng.uniform(-0.4, 0.4)
        length = rng.uniform(0.5, 3.0)
        thin = length * 10 ** rng.uniform(-10, -8)
        j, row = rng.uniform(-2, rm + 2), float(rng.integers(-1, rm + 1))
        tip, far = (j + length, j) if rng.random() < 0.5 else (j, j + length)
        su, sv = np.array([tip, far, far]), np.array([row, row, row + thin])
        if rng.random() < 0.5:
            su, sv = sv, su
        slivers.append(_on_samples(grid, axis, plane, su, sv))
    # walls 300 cells wide, edges far outside the grid (no records): sub-triangles 4.7 cells
    # (k = 64), windows of about 37 samples
    walls = np.concatenate([demo.quad((-150.3, -150.2, 0.4 + z), (150.5, -150.2, 0.4 + z),
                                      (150.5, 150.6, 0.4 + z), (-150.3, 150.6, 0.4 + z))
                            for z in (2.0, 6.0)])
    for tris in (np.array(slivers), np.concatenate([np.array(slivers), walls])):
        _same(*_both("occluder_volume", grid, tris))


@pytest.mark.parametrize("split", [0, 1, 3, "all"])
def test_chunks_from_both_ends_match_numpy(monkeypatch, split):
    # The chunks taken from the back (another thread's) log their offset terms, added after
    # the front's: every split of the chunks, many triangles on the same faces (the same
    # walls again, moved a little, in other sizes: other k, other chunks).
    grid = Grid((0.0, 0.0, 0.0), 1.0, 8)
    rng = np.random.default_rng(5)
    base = _boxes(rng, grid, 2, 0.5)
    tris = np.concatenate([base, base + 0.01, base[::-1] * 1.02, _boxes(rng, grid, 3, 0.0)])

    def split_at(pool, front, back, count):
        cut = count if split == "all" else min(split, count)
        for i in range(cut):
            front(i)
        for j in range(count - 1, cut - 1, -1):
            back(j)
        return list(range(cut, count))

    with jit.disabled():
        ref = geometry_volume.occluder_volume(grid, tris)
    monkeypatch.setattr(compiled, "_front_back", split_at)
    _same(ref, compiled.occluder_volume(grid, tris))


def test_scratch_reuse_matches_numpy(monkeypatch):
    # The working arrays kept between calls: scenes and resolutions one after another, and
    # a call broken off midway (its planes not cleared) before the next.
    grid5, cornell5 = _cornell(5)
    grid16, cornell16 = _cornell(16)
    rng = np.random.default_rng(11)
    walls = _boxes(rng, Grid((0.0, 0.0, 0.0), 1.0, 16), 3, 0.5)
    for grid, tris in [(grid16, cornell16), (grid5, cornell5), (grid16, walls),
                       (grid16, cornell16)]:
        _same(*_both("occluder_volume", grid, tris))

    def broken(*args):
        raise RuntimeError("midway")

    monkeypatch.setattr(compiled, "_finish_volume_kernel", broken)
    with pytest.raises(RuntimeError):
        compiled.occluder_volume(grid16, walls)
    monkeypatch.undo()
    _same(*_both("occluder_volume", grid16, cornell16))


@pytest.mark.parametrize("seed", range(8))
def test_random_scenes_match_numpy(seed):
    # Boxes, large tilted and nearly aligned triangles and slivers, in grids of other sizes,
    # cells and origins.
    rng = np.random.default_rng(100 + seed)
    r = int(rng.choice([4, 7, 12]))
    cell = float(rng.choice([1.0, 0.37, 1 / 3]))
    grid = Grid(tuple(rng.choice([0.0, -3.25, 1e3]) * np.array([1.0, 0.5, -1.0])), cell, r)
    tris = [_boxes(rng, grid, 2, float(rng.choice([1.0, 0.5, 1 / 8, 0.0])))]
    for _ in range(3):
        t = rng.uniform(0, r, 3) + rng.uniform(-0.6 * r, 0.6 * r, (3, 3))
        if rng.random() < 0.5:
            axis = rng.integers(0, 3)
            t[:, axis] = t[0, axis] + rng.choice([0.0, 1e-12, 1e-6]) * rng.uniform(-1, 1, 3)
        tris.append((grid.origin_array + t * cell)[None])
    tris.append(_random_triangles(rng, r, 20) * cell + grid.origin_array)
    _check(grid, np.concatenate(tris))


@pytest.mark.parametrize("ulps", [-2, -1, 0, 1, 2])
def test_wall_on_the_plane_rule_matches_numpy(ulps):
    # An aligned wall where the plane rule (nearest plane, ties down: floor(x + 0.5 - 1e-6))
    # flips: its sub-triangles' centroids, a few ulps apart, go to either plane; not filled.
    grid = Grid((0.0, 0.0, 0.0), 1.0, 8)
    x = np.nextafter(4.5 + 1e-6, 5.0 if ulps > 0 else 4.0) if ulps else 4.5 + 1e-6
    for _ in range(abs(ulps) - 1):
        x = np.nextafter(x, 5.0 if ulps > 0 else 4.0)
    wall = demo.quad((x, 0.7, 0.3), (x, 7.1, 0.3), (x, 7.1, 7.9), (x, 0.7, 7.9))
    _check(grid, wall)
    _check(grid, np.ascontiguousarray(wall[:, :, [1, 0, 2]]))  # (across y)
