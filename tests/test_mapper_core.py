"""services.mapper.core: log-odds occupancy grid (DESIGN.md §4 "Mapping").

Run ``python tests/test_mapper_core.py`` for the per-scan timing benchmark (prints figures).
"""

from __future__ import annotations

import math

import msgspec
import numpy as np
import pytest

from topoexplore.common.domain import GridMap, Pose, Scan
from topoexplore.common.grid import FREE, OCCUPIED, GridError, GridGeometry, classify
from topoexplore.common.kernels import bresenham
from topoexplore.common.params import MapperParams
from topoexplore.services.mapper.core import (
    MapLoadError,
    MapperCore,
    ScanError,
    beam_endpoints,
    grow_axis,
    integrate_cells,
    logodds_to_int8,
    surface_normals,
)

INC = math.pi / 180.0  # [rad] 1 deg, 181 beams
AMIN = -math.pi / 2


def params(**kw) -> MapperParams:
    return msgspec.structs.replace(MapperParams(), **kw)


def room_ranges(pose, half_x=3.0, half_y=2.0, n=181, amin=AMIN, inc=INC, offset=0.0):
    """Exact ranges from the laser to the walls of an axis-aligned room centred on (0, 0)."""
    x, y, th = pose
    lx, ly = x + offset * math.cos(th), y + offset * math.sin(th)
    out = np.empty(n)
    for i in range(n):
        a = th + amin + i * inc
        c, s = math.cos(a), math.sin(a)
        tx = ((half_x if c > 0 else -half_x) - lx) / c if abs(c) > 1e-12 else math.inf
        ty = ((half_y if s > 0 else -half_y) - ly) / s if abs(s) > 1e-12 else math.inf
        out[i] = min(tx, ty)
    return out


def mk(ranges, amin=AMIN, inc=INC, rmin=0.02, rmax=8.0) -> Scan:
    return Scan(np.asarray(ranges, float), amin, inc, rmin, rmax)


def scan(core, pose, ranges, rmin=0.02, rmax=8.0):
    return core.integrate(Pose(*pose), mk(ranges, rmin=rmin, rmax=rmax))


# --- basics ---------------------------------------------------------------------------------


def test_first_scan_centres_aligned_grid():
    core = MapperCore(MapperParams())
    assert not core.ready
    with pytest.raises(RuntimeError):
        _ = core.geometry
    win = scan(core, (1.23, -4.56, 0.3), np.full(181, 3.0))
    g = core.geometry
    assert (g.width, g.height) == (200, 200) and g.resolution == 0.1
    assert win == (0, 200, 0, 200)  # created in this call: the whole grid
    # cell edges on multiples of the resolution, pose near the centre
    assert abs(g.origin_x / 0.1 - round(g.origin_x / 0.1)) < 1e-9
    assert abs(g.origin_y / 0.1 - round(g.origin_y / 0.1)) < 1e-9
    r, c = g.world_to_cell(1.23, -4.56)
    assert abs(int(r) - 100) <= 1 and abs(int(c) - 100) <= 1
    occ = core.occupancy()
    assert occ.dtype == np.int8 and occ.shape == (200, 200)
    assert not occ.flags.writeable
    assert core.occupancy(copy=True).flags.writeable


def test_single_beam_free_then_hit():
    p = MapperParams()
    core = MapperCore(p)
    pose = (0.05, 0.05, 0.0)  # centre of cell (100, 100) of the first grid
    core.integrate(Pose(*pose), mk(np.array([1.0]), 0.0, 0.0, 0.02, 8.0))
    g = core.geometry
    r0, c0 = (int(v) for v in g.world_to_cell(0.05, 0.05))
    lo = core.log_odds()
    row = lo[r0, c0:c0 + 12]
    assert np.allclose(row[:10], p.l_free)  # robot cell .. 0.95 m: free
    assert row[10] == pytest.approx(p.l_occ)  # 1.05 m: the hit cell
    assert row[11] == 0.0  # beyond the hit: untouched
    occ = core.occupancy()
    assert occ[r0, c0 + 11] == -1 and occ[r0 + 1, c0] == -1
    assert occ[r0, c0 + 10] == round(100 / (1 + math.exp(-p.l_occ)))


@pytest.mark.parametrize("bearing", [0.3, 1.2, 2.5, -0.7, -2.0, math.pi / 4])
def test_a_beam_updates_the_bresenham_cells_of_its_ray(bearing):
    """Free along common.kernels.bresenham from the laser's cell to the end cell, hit at the end
    cell, nothing else."""
    p = MapperParams()
    core = MapperCore(p)
    core.integrate(Pose(0.05, 0.05, bearing), mk(np.array([2.37]), 0.0, 0.0, 0.02, 8.0))
    g = core.geometry
    r0, c0 = (int(v) for v in g.world_to_cell(0.05, 0.05))
    r1, c1 = (int(v) for v in g.world_to_cell(0.05 + 2.37 * math.cos(bearing),
                                               0.05 + 2.37 * math.sin(bearing)))
    rows, cols = np.empty(64, np.int64), np.empty(64, np.int64)
    n = bresenham(r0, c0, r1, c1, rows, cols)
    want = np.zeros(core.log_odds().shape, np.float32)
    want[rows[:n - 1], cols[:n - 1]] = p.l_free
    want[r1, c1] = p.l_occ
    assert np.array_equal(core.log_odds(), want)


def loop_integrate(lo, occ, r0, c0, er, ec, hit, p: MapperParams, surf):
    """The mapper's update written as the plain loop it once was (a numba kernel): hits
    first, then each beam's Bresenham cells (common.kernels) in order, each cell once per
    scan, skipping the cells on a surface a hit of this beam or a near neighbour lies on."""
    ok, near, hc, hr, nx, ny, slo, shi, reach = surf
    done = np.zeros(lo.shape, bool)
    touched = []

    def apply(r, c, delta):
        v = min(max(float(lo[r, c]) + delta, p.l_min), p.l_max)
        lo[r, c] = v
        occ[r, c] = math.floor(100.0 / (1.0 + math.exp(-v)) + 0.5)
        done[r, c] = True
        touched.append((r, c))

    for k in np.nonzero(hit)[0]:
        if not done[er[k], ec[k]]:
            apply(er[k], ec[k], p.l_occ)
    n = len(er)
    rows, cols = np.empty(4096, np.int64), np.empty(4096, np.int64)
    for k in range(n):
        m = bresenham(r0, c0, er[k], ec[k], rows, cols) - int(hit[k])
        for r, c in zip(rows[:m].tolist(), cols[:m].tolist(), strict=True):
            on = False
            for j in range(max(k - 1, 0), min(k + 2, n) if reach > 0 else 0):
                if ok[j] and (j == k or near[j]):
                    ax, ay = c + 0.5 - hc[j], r + 0.5 - hr[j]
                    u = ny[j] * ax - nx[j] * ay
                    on = on or bool(ax * ax + ay * ay <= reach * reach
                                    and abs(nx[j] * ax + ny[j] * ay)
                                    < 0.5 * (abs(nx[j]) + abs(ny[j])) - 0.05
                                    and slo[j] - 0.5 <= u <= shi[j] + 0.5)
            if not on and not done[r, c]:
                apply(r, c, p.l_free)
    if not touched:
        return 0, 0, 0, 0
    t = np.array(touched)
    return t[:, 0].min(), t[:, 0].max() + 1, t[:, 1].min(), t[:, 1].max() + 1


@pytest.mark.parametrize("reach", [0.0, 0.3, 1.0])
def test_integrate_cells_is_the_plain_loop(reach):
    """The vectorised update gives exactly (bit for bit) the loop's log-odds, occupancy and
    window, scan after scan: cluttered ranges, no-returns, grazing walls, surfaces on."""
    p = params(surface_reach=reach, initial_size=24.0)  # nothing grows below
    core = MapperCore(p, laser_offset=0.1)
    rng = np.random.default_rng(5)
    scan(core, (0.0, 0.0, 0.0), np.full(181, 9.0))
    for _ in range(12):
        # near a wall half the time: its far part is seen at a grazing angle
        pose = Pose(rng.uniform(-2.7, 2.7), rng.choice([-1, 1]) * rng.uniform(0.5, 2.3),
                    rng.uniform(-math.pi, math.pi))
        ranges = room_ranges(pose, 3.0, 2.5, offset=0.1) * rng.uniform(0.7, 1.0)
        ranges[rng.random(181) < 0.1] = math.inf
        ranges[rng.random(181) < 0.05] *= rng.uniform(0.2, 0.9)  # clutter
        lx, ly, ex, ey, hit = beam_endpoints(pose, mk(ranges), 0.1)
        g = core.geometry
        er, ec = (np.floor((v - o) / g.resolution).astype(np.int64)
                  for v, o in ((ey, g.origin_y), (ex, g.origin_x)))
        r0, c0 = (int(math.floor((v - o) / g.resolution))
                  for v, o in ((ly, g.origin_y), (lx, g.origin_x)))
        surf = core._surfaces(ex, ey, hit)
        want_lo, want_occ = core.log_odds().copy(), core.occupancy(copy=True)
        want = loop_integrate(want_lo, want_occ, r0, c0, er, ec, hit, p, surf)
        lo, occ = core.log_odds().copy(), core.occupancy(copy=True)
        got = integrate_cells(lo, occ, np.zeros(lo.shape, np.int32), r0, c0, er, ec, hit,
                              p.l_free, p.l_occ, p.l_min, p.l_max, surf)
        assert got == tuple(int(v) for v in want)
        assert np.array_equal(lo, want_lo) and np.array_equal(occ, want_occ)
        assert core.integrate(pose, mk(ranges)) == got  # the core calls it the same way
        assert np.array_equal(core.log_odds(), want_lo)


def test_max_range_marks_free_only_and_inf_is_no_return():
    p = MapperParams()
    for value in (8.0, 9.5, math.inf):
        core = MapperCore(p)
        core.integrate(Pose(0.05, 0.05, 0.0), mk(np.array([value]), 0.0, 0.0, 0.02, 8.0))
        lo = core.log_odds()
        assert (lo > 0).sum() == 0
        n_free = int((lo < 0).sum())
        assert n_free == 81  # 0.05 .. 8.05 m: cells 0..80 along +x


def test_short_readings_ignored():
    core = MapperCore(MapperParams())
    scan(core, (0, 0, 0), np.full(181, 2.0))
    before = core.occupancy(copy=True)
    win = scan(core, (0, 0, 0), np.full(181, 0.01), rmin=0.05)
    assert win == (0, 0, 0, 0)
    assert np.array_equal(before, core.occupancy())


def test_each_cell_updated_at_most_once_per_scan():
    p = MapperParams()
    core = MapperCore(p)
    scan(core, (0.0, 0.0, 0.0), room_ranges((0.0, 0.0, 0.0)))
    values = np.unique(core.log_odds().astype(np.float64))
    allowed = np.array([0.0, p.l_free, p.l_occ])
    assert np.isclose(values[:, None], allowed[None, :], atol=1e-6).any(axis=1).all(), values
    assert np.isclose(values, p.l_occ, atol=1e-6).any()


def test_hits_take_precedence_over_crossing_beams_in_one_scan():
    p = MapperParams()
    core = MapperCore(p)
    # two beams in (nearly) the same direction: one hits at 1.0 m, one passes to 3.0 m
    core.integrate(Pose(0.05, 0.05, 0.0), mk(np.array([1.0, 3.0]), 0.0, 1e-6, 0.02, 8.0))
    g = core.geometry
    r0, c0 = (int(v) for v in g.world_to_cell(0.05, 0.05))
    lo = core.log_odds()
    assert lo[r0, c0 + 10] == pytest.approx(p.l_occ)
    assert lo[r0, c0 + 30] == pytest.approx(p.l_occ)
    assert lo[r0, c0 + 20] == pytest.approx(p.l_free)


def test_clamp_and_cells_change_back():
    p = MapperParams()
    core = MapperCore(p)
    pose = (0.05, 0.05, 0.0)
    for _ in range(20):
        core.integrate(Pose(*pose), mk(np.array([1.0]), 0.0, 0.0, 0.02, 8.0))
    lo = core.log_odds()
    assert lo.max() == pytest.approx(p.l_max) and lo.min() == pytest.approx(p.l_min)
    r0, c0 = (int(v) for v in core.geometry.world_to_cell(*pose[:2]))
    assert classify(core.occupancy())[r0, c0 + 10] == OCCUPIED
    # the obstacle goes away: the same cell is crossed by longer beams and becomes free
    n = 0
    while classify(core.occupancy())[r0, c0 + 10] != FREE:
        core.integrate(Pose(*pose), mk(np.array([3.0]), 0.0, 0.0, 0.02, 8.0))
        n += 1
        assert n < 50
    assert n == math.ceil((p.l_max - math.log(p.p_free / (1 - p.p_free))) / -p.l_free + 1e-9)


@pytest.mark.parametrize("reach", [0.0, 2.0])
def test_room_map_is_right(reach):
    core = MapperCore(params(surface_reach=reach))
    for k in range(12):
        th = k * math.pi / 6
        pose = (0.3 * math.cos(th), 0.2 * math.sin(th), th)
        scan(core, pose, room_ranges(pose))
    g = core.geometry
    cls = classify(core.occupancy())
    rows, cols = np.nonzero(cls == OCCUPIED)
    x, y = g.cell_to_world(rows, cols)
    # every occupied cell within one cell of a wall (x = +-3 or y = +-2)
    dist = np.minimum(np.abs(np.abs(x) - 3.0), np.abs(np.abs(y) - 2.0))
    assert len(rows) > 150 and dist.max() <= 0.1 + 1e-9
    # the interior (0.3 m away from the walls) is known free
    rr, cc = np.nonzero(np.ones_like(cls, bool))
    xx, yy = g.cell_to_world(rr, cc)
    inner = (np.abs(xx) < 2.7) & (np.abs(yy) < 1.7)
    assert (cls[rr[inner], cc[inner]] == FREE).mean() > 0.99


def test_surface_normals():
    # 0..3 on y = 1, 3..5 on x = 3 (3 is the corner), 6 off both lines
    ex = np.array([0.0, 1.0, 2.0, 3.0, 3.0, 3.0, 5.0])
    ey = np.array([1.0, 1.0, 1.0, 1.0, 2.0, 3.0, 3.0])
    hit = np.ones(7, bool)
    ok, near, nx, ny, lo, hi = surface_normals(ex, ey, hit, 5.0)
    assert (near == ok).all()  # every step within 5 m
    assert not surface_normals(ex, ey, hit, 0.5)[1].any()  # steps of 1 m: none near
    # 1, 2 and 4 centred; 0 from the run it starts, 3 and 5 from the run they end
    assert ok.tolist() == [True] * 6 + [False]
    assert np.allclose(np.abs(ny[:4]), 1.0) and np.allclose(np.abs(nx[4:6]), 1.0)
    # the stretch each line is known over: the span of its three hits, from the hit
    assert np.allclose(np.abs(hi - lo)[:6], 2.0) and (lo <= 0).all() and (hi >= 0).all()
    assert np.allclose(sorted(np.abs([lo[0], hi[0]])), [0.0, 2.0])  # 0 is an end of its run
    assert np.allclose(sorted(np.abs([lo[1], hi[1]])), [1.0, 1.0])  # 1 is the middle
    hit[2] = False  # no return: no run through beam 2
    ok, _, nx, ny, _, _ = surface_normals(ex, ey, hit, 5.0)
    assert ok.tolist() == [False, False, False, True, True, True, False]
    assert np.allclose(np.abs(nx[3:6]), 1.0)


def wall_ranges(lx, ly, th, face_x, n=181, amin=AMIN, inc=INC):
    """Exact ranges from the laser at (lx, ly) to a wall x >= face_x (no return elsewhere)."""
    a = th + amin + np.arange(n) * inc
    c = np.cos(a)
    with np.errstate(divide="ignore"):
        return np.where(c > 1e-9, (face_x - lx) / np.where(c > 1e-9, c, 1.0), np.inf)


@pytest.mark.parametrize("reach", [0.0, 2.0])
def test_grazing_beams_and_a_wall_face_inside_a_cell(reach):
    """A robot drives along a wall whose face (x = 1.65 m) lies in the middle of a cell
    column, 0.55 m away, looking along it: the far face cells are only seen at grazing angles.
    Without the surface rule those beams clear them (free cells beside the unknown inside the
    wall: a false frontier); with it, none is cleared, the cells in front are."""
    core = MapperCore(params(surface_reach=reach))
    for k in range(30):
        y = 0.05 * k
        scan(core, (1.1, y, math.pi / 2), wall_ranges(1.1, y, math.pi / 2, 1.65))
    g = core.geometry
    cls = classify(core.occupancy())
    rows = np.arange(g.height)
    _, ys = g.cell_to_world(rows, np.zeros_like(rows))
    far = rows[(ys > 3.0) & (ys < 6.0)]  # 1.5 m ahead of the last pose and beyond
    face = int(g.world_to_cell(1.65, 3.0)[1])
    front = int(g.world_to_cell(1.45, 3.0)[1])
    face_free = (cls[far, face] == FREE).mean()
    assert (cls[far, front] == FREE).mean() > 0.9
    if reach == 0.0:
        assert face_free > 0.5  # the mismatch the rule is for
    else:
        assert face_free == 0.0


def test_a_beam_through_a_doorway_clears_it():
    """A wall along y = 2.05 (face inside a cell row) with a 0.8 m doorway, seen obliquely:
    the beams through the door cross the wall's line there, and the doorway's cells are
    cleared with the surface rule on, as without it."""
    lx, ly = 0.0, 0.0
    a = math.pi / 2 + AMIN + np.arange(181) * INC  # looking along +y
    s, c = np.sin(a), np.cos(a)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(s > 1e-9, (2.05 - ly) / np.where(s > 1e-9, s, 1.0), np.inf)
        x = lx + t * c
        door = (x > 1.0) & (x < 1.8)
        t = np.where(door, np.where(s > 1e-9, (4.0 - ly) / np.where(s > 1e-9, s, 1.0), np.inf), t)
    free = {}
    for reach in (0.0, 2.0):
        core = MapperCore(params(surface_reach=reach))
        for _ in range(5):
            core.integrate(Pose(lx, ly, math.pi / 2), mk(t))
        g = core.geometry
        cls = classify(core.occupancy())
        r = int(g.world_to_cell(1.4, 2.05)[0])
        cols = [int(g.world_to_cell(x, 2.05)[1]) for x in np.arange(1.15, 1.7, 0.1)]
        free[reach] = (cls[r, cols] == FREE).tolist()
    assert all(free[0.0]) and free[2.0] == free[0.0]


def test_a_beam_past_a_jamb_is_not_stopped_by_the_wall_line_beyond_the_hits():
    """Five beams 7.5 deg apart from (0, 0): three hit a wall along y = 2.05 (face inside a
    cell row) at x = 0.2, 0.48, 0.77; the next ones pass a doorway (x > 0.95) to y = 4. The
    wall's line, extended past its last hit, runs through the cell where the first beam past
    the jamb crosses y = 2.05 (x = 1.09), the only beam that crosses it: the surface is known
    only over the stretch its hits span, so that doorway cell is cleared as without the rule
    (with the line extended, it stays unknown)."""
    amin, inc = math.radians(54.4), math.radians(7.5)
    a = amin + np.arange(5) * inc
    x = 2.05 / np.tan(a)
    t = np.where(x > 0.95, 4.0 / np.sin(a), 2.05 / np.sin(a))
    cell = {}
    for reach in (0.0, 2.0):
        core = MapperCore(params(surface_reach=reach))
        for _ in range(5):
            core.integrate(Pose(0.0, 0.0, 0.0), mk(t, amin=amin, inc=inc))
        g = core.geometry
        r, c = (int(v) for v in g.world_to_cell(2.03 / math.tan(a[1]), 2.03))
        cell[reach] = int(classify(core.occupancy())[r, c])
    assert cell[0.0] == FREE and cell[2.0] == FREE


def test_laser_offset():
    p = MapperParams()
    core = MapperCore(p, laser_offset=0.5)
    core.integrate(Pose(0.05, 0.05, math.pi / 2), mk(np.array([1.0]), 0.0, 0.0, 0.02, 8.0))
    lo = core.log_odds()
    r, c = (int(v) for v in core.geometry.world_to_cell(0.05, 1.55))
    assert lo[r, c] == pytest.approx(p.l_occ)
    r0, c0 = (int(v) for v in core.geometry.world_to_cell(0.05, 0.05))
    assert lo[r0, c0] == 0.0  # the robot centre is behind the laser: not on the beam


# --- the int8 cache and the changed window ----------------------------------------------------


def test_int8_cache_and_window_match_full_conversion():
    rng = np.random.default_rng(3)
    core = MapperCore(params(initial_size=6.0, grow_margin=2.0))
    prev_occ, prev_geom = None, None
    for _ in range(60):
        pose = (rng.uniform(-6, 6), rng.uniform(-6, 6), rng.uniform(-3.2, 3.2))
        r = np.where(rng.random(181) < 0.2, 8.0, rng.uniform(0.0, 7.0, 181))
        win = scan(core, pose, r, rmin=0.1)
        occ = core.occupancy()
        lo = core.log_odds()
        touched = occ >= 0
        assert np.array_equal(occ[touched], logodds_to_int8(lo[touched]))
        assert (lo[~touched] == 0).all()
        if core.geometry == prev_geom:
            r0, r1, c0, c1 = win
            diff = occ != prev_occ
            outside = diff.copy()
            outside[r0:r1, c0:c1] = False
            assert not outside.any()
            assert diff.any()
        else:
            assert win == (0, occ.shape[0], 0, occ.shape[1])
        prev_occ, prev_geom = occ.copy(), core.geometry
    assert core.grown > 0


def test_growth_keeps_cells_in_place_and_aligned():
    p = params(initial_size=4.0, grow_margin=1.0)
    core = MapperCore(p)
    scan(core, (0.0, 0.0, 0.0), np.full(181, 1.5))
    g0 = core.geometry
    occ0 = core.occupancy(copy=True)
    # facing -x, 5 m beams: must grow on the low-x side only
    win = scan(core, (0.0, 0.0, math.pi), np.full(181, 5.0), rmax=6.0)
    g1 = core.geometry
    assert win == (0, g1.height, 0, g1.width)
    shift_c = (g0.origin_x - g1.origin_x) / p.resolution
    shift_r = (g0.origin_y - g1.origin_y) / p.resolution
    assert abs(shift_c - round(shift_c)) < 1e-9 and abs(shift_r - round(shift_r)) < 1e-9
    shift_c, shift_r = round(shift_c), round(shift_r)
    assert shift_c >= 10 + 10 and g1.origin_x <= -5.0 - 1.0 + 1e-9  # beam end + margin
    assert g1.width == g0.width + shift_c  # nothing added on the high-x side
    # an old cell that the new scan did not touch keeps its value at the same world place
    sub = core.occupancy()[shift_r:shift_r + g0.height, shift_c:shift_c + g0.width]
    right = np.s_[:, g0.width // 2 + 2:]  # x > 0.2 m: behind the robot in the second scan
    assert np.array_equal(sub[right], occ0[right])


def test_grow_axis():
    assert grow_axis(0, 9, 10, 5, 100) == (0, 0)
    assert grow_axis(-3, 9, 10, 5, 100) == (8, 0)
    assert grow_axis(0, 12, 10, 5, 100) == (0, 8)
    assert grow_axis(-3, 12, 10, 5, 100) == (8, 8)
    assert grow_axis(-3, 12, 10, 5, 20) == (5, 5)  # margins cut to fit the limit
    assert grow_axis(-3, 12, 10, 5, 16) == (3, 3)
    assert grow_axis(-3, 12, 10, 5, 15) == (-1, -1)  # the overflow alone does not fit


def test_refuses_to_grow_beyond_max_size_state_unchanged():
    core = MapperCore(params(initial_size=20.0, max_size=40.0))
    scan(core, (0, 0, 0), np.full(181, 3.0))
    g, occ = core.geometry, core.occupancy(copy=True)
    with pytest.raises(ScanError, match="max_size"):
        scan(core, (1000.0, 0.0, 0.0), np.full(181, 3.0))  # bad pose
    assert core.geometry == g and np.array_equal(core.occupancy(), occ)
    # a first scan that does not fit leaves the core empty
    core = MapperCore(params(initial_size=10.0, max_size=12.0))
    with pytest.raises(ScanError):
        scan(core, (0, 0, 0), np.full(181, 8.0), rmax=9.0)
    assert not core.ready


# --- bad input ----------------------------------------------------------------------------------
# A scan that crossed the bus was validated when it was decoded (tests/test_messages.py); the
# core checks only what depends on its own parameters.


def test_scan_beyond_max_size_is_refused():
    core = MapperCore(params(max_size=40.0))
    with pytest.raises(ScanError, match="max_size") as exc:
        core.integrate(Pose(0.0, 0.0, 0.0), mk(np.full(181, 2.0), rmax=50.0))
    assert isinstance(exc.value, ValueError) and "\n" not in str(exc.value)
    assert not core.ready


def test_beam_endpoints():
    lx, ly, ex, ey, hit = beam_endpoints(Pose(1.0, 2.0, math.pi / 2),
                                         mk(np.array([0.01, 1.0, 9.0]), -0.5, 0.5, 0.05, 8.0),
                                         laser_offset=0.2)
    assert (lx, ly) == pytest.approx((1.0, 2.2))
    assert hit.tolist() == [True, False]  # first beam dropped (< range_min)
    assert (ex[0], ey[0]) == pytest.approx((1.0, 3.2))
    assert math.hypot(ex[1] - lx, ey[1] - ly) == pytest.approx(8.0)


# --- reload ---------------------------------------------------------------------------------------


def test_from_occupancy_round_trip():
    p = MapperParams()
    core = MapperCore(p)
    for k in range(6):
        pose = (0.1 * k, 0.0, k * 1.0)
        scan(core, pose, room_ranges(pose))
    occ, geom = core.occupancy(copy=True), core.geometry
    again = MapperCore.from_grid(core.grid(copy=True), p)
    assert again.geometry == geom
    assert np.array_equal(again.occupancy(), occ)  # values stay in 2..98 with the defaults
    # continue mapping on the reloaded core: same result as the original
    scan(core, (0, 0, 0), room_ranges((0, 0, 0)))
    scan(again, (0, 0, 0), room_ranges((0, 0, 0)))
    assert np.array_equal(again.occupancy(), core.occupancy())
    # a map_server style grid (0 / 100 / -1) keeps its classes
    ms = np.array([[0, 100, -1, 50]], np.int8)
    c2 = MapperCore.from_grid(GridMap(ms, GridGeometry(0.1, 0.0, 0.0, 4, 1)), p)
    assert np.array_equal(classify(c2.occupancy()), classify(ms))
    assert c2.occupancy()[0, 2] == -1 and c2.log_odds()[0, 2] == 0.0


@pytest.mark.parametrize(
    "grid, geom, match",
    [
        (np.full((2, 2), 101, np.int8), GridGeometry(0.1, 0, 0, 2, 2), "values"),
        (np.zeros((2, 2), np.int8), GridGeometry(0.05, 0, 0, 2, 2), "resolution"),
        (np.zeros((5000, 1), np.int8), GridGeometry(0.1, 0, 0, 1, 5000), "max_size"),
    ],
)
def test_from_grid_rejects_a_grid_it_cannot_continue(grid, geom, match):
    with pytest.raises(MapLoadError, match=match):
        MapperCore.from_grid(GridMap(grid, geom), MapperParams())


@pytest.mark.parametrize(
    "grid, geom, match",
    [
        (np.zeros((2, 3), np.int8), GridGeometry(0.1, 0, 0, 2, 3), "shape"),
        (np.zeros((2, 2), np.float32), GridGeometry(0.1, 0, 0, 2, 2), "integer"),
        (np.zeros((2, 2), np.int16), GridGeometry(0.1, 0, 0, 2, 2), "int8"),
        (np.zeros((2, 2), np.int8), GridGeometry(0.1, float("nan"), 0, 2, 2), "geometry"),
    ],
)
def test_a_grid_map_checks_its_array_against_its_geometry(grid, geom, match):
    with pytest.raises(GridError, match=match):
        GridMap(grid, geom)


# --- benchmark (not a test) ---------------------------------------------------------------------


def benchmark(n: int = 500) -> None:
    """Median time per 181-beam scan on a 1000x1000 grid, including the int8 cache, with the
    surface rule off (surface_reach 0) and on (2 m), the two interleaved scan by scan."""
    import time

    cores = {}
    for reach in (0.0, 2.0):
        t0 = time.perf_counter()
        cores[reach] = MapperCore.from_grid(
            GridMap(np.full((1000, 1000), -1, np.int8), GridGeometry(0.1, -50.0, -50.0, 1000,
                                                                        1000)),
            params(surface_reach=reach))
        print(f"construct 1000x1000 (incl. numba warm-up) {1e3 * (time.perf_counter() - t0):.0f}"
              f" ms (surface_reach {reach})")
    rng = np.random.default_rng(0)
    kinds = {
        "office 0.5-4 m": lambda pose: rng.uniform(0.5, 4.0, 181),
        "mixed, 30% no return": lambda pose: np.where(rng.random(181) < 0.3, 8.0,
                                                      rng.uniform(0.5, 7.9, 181)),
        "all max range 8 m": lambda pose: np.full(181, 8.0),
        "room walls 12x8 m": lambda pose: np.minimum(
            room_ranges((pose[0] % 5 - 2.5, pose[1] % 3 - 1.5, pose[2]), 6.0, 4.0)
            + rng.normal(0, 0.01, 181), 7.99),
    }
    for name, gen in kinds.items():
        ts = {0.0: [], 2.0: []}
        for _ in range(n):
            pose = (rng.uniform(-30, 30), rng.uniform(-30, 30), rng.uniform(-3, 3))
            r = gen(pose)
            for reach, core in cores.items():
                t = time.perf_counter()
                core.integrate(Pose(*pose), mk(r))
                core.occupancy()
                ts[reach].append(time.perf_counter() - t)
        for reach in ts:
            v = np.array(ts[reach]) * 1e3
            print(f"{name:22s} reach {reach:.0f} m  median {np.median(v):.3f} ms"
                  f"  p95 {np.percentile(v, 95):.3f} ms  max {v.max():.3f} ms  (n={n})")


if __name__ == "__main__":
    benchmark()


def test_rep117_readings():
    """NaN (no valid reading), -Inf (too close) and values below range_min change nothing;
    +Inf is no return, like range_max: free space out to range_max."""
    pose = (0.0, 0.0, 0.0)
    base = room_ranges(pose)
    ref = MapperCore(params())
    scan(ref, pose, base)
    for bad in (np.nan, -np.inf, 0.01):
        r = base.copy()
        r[80:100] = bad  # the beams straight ahead
        core = MapperCore(params())
        scan(core, pose, r)
        wall = core.occupancy()
        assert (wall != ref.occupancy()).any()  # the beam's ray and its wall are not there
        assert ((wall >= 0) <= (ref.occupancy() >= 0)).all()  # and nothing else appears
    inf, at_max = base.copy(), base.copy()
    inf[80:100], at_max[80:100] = np.inf, 8.0
    a, b = MapperCore(params()), MapperCore(params())
    scan(a, pose, inf)
    scan(b, pose, at_max)
    assert np.array_equal(a.occupancy(), b.occupancy())


def test_any_beam_count_and_a_full_turn():
    """A 360-beam lidar's scan (another beam count and a full turn) maps a room all round."""
    n, inc = 360, 2 * math.pi / 360
    pose = (0.0, 0.0, 0.0)
    core = MapperCore(params())
    core.integrate(Pose(*pose), Scan(room_ranges(pose, n=n, amin=-math.pi, inc=inc), -math.pi,
                                     inc, 0.1, 12.0))
    occ = core.occupancy()
    assert (occ >= 0).sum() * params().resolution ** 2 > 0.9 * 6.0 * 4.0  # [m^2] the room
