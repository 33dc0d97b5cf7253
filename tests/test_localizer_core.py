"""The localizer core (services/localizer/core.py) on synthetic scans with known offsets."""

from __future__ import annotations

import math

import cv2
import msgspec
import numpy as np
import pytest

from topoexplore.common.domain import GridMap, Pose, Scan
from topoexplore.common.grid import GridGeometry
from topoexplore.common.params import LocalizerParams
from topoexplore.services.localizer.core import (
    NORTH,
    SOUTH,
    WEST,
    LocalizerCore,
    direction_histogram,
    heading_offset,
    scan_conditioning,
    surface_directions,
    surface_sides,
)

RES = 0.05  # [m]
N = 120
# walls one cell thick with their faces... at cell centres: x, y = 10.5 and 110.5 cells, and a
# box; the rays below end exactly there
LO, HI = 10.5 * RES, 110.5 * RES
BOX = (30.5 * RES, 60.5 * RES, 50.5 * RES, 62.5 * RES)  # x0, y0, x1, y1 [m]


def room() -> GridMap:
    g = np.zeros((N, N), np.int8)
    g[10, 10:111] = g[110, 10:111] = 100
    g[10:111, 10] = g[10:111, 110] = 100
    g[60:63, 30:51] = 100
    g[61, 31:50] = 0  # the box's inside is not a face
    return GridMap(g, GridGeometry(RES, 0.0, 0.0, N, N))


def _ray_segs(x: float, y: float, a: float, segs: list) -> float:
    """[m] from (x, y) along heading ``a`` to the nearest of the line segments (inf: none)."""
    c, s = math.cos(a), math.sin(a)
    best = math.inf
    for (ax, ay), (bx, by) in segs:
        ex, ey = bx - ax, by - ay
        den = c * ey - s * ex
        if abs(den) < 1e-12:
            continue
        t = ((ax - x) * ey - (ay - y) * ex) / den
        u = ((ax - x) * s - (ay - y) * c) / den
        if t > 0 and 0 <= u <= 1:
            best = min(best, t)
    return best


def _ray(x: float, y: float, a: float) -> float:
    segs = [((LO, LO), (HI, LO)), ((HI, LO), (HI, HI)), ((HI, HI), (LO, HI)), ((LO, HI), (LO, LO))]
    x0, y0, x1, y1 = BOX
    segs += [((x0, y0), (x1, y0)), ((x1, y0), (x1, y1)), ((x1, y1), (x0, y1)), ((x0, y1), (x0, y0))]
    return _ray_segs(x, y, a, segs)


def scan_at(x: float, y: float, th: float, beams: int = 181, fov: float = math.pi,
            rmax: float = 8.0) -> Scan:
    inc = fov / beams if fov >= 2 * math.pi - 1e-9 else fov / (beams - 1)
    amin = -math.pi if fov >= 2 * math.pi - 1e-9 else -fov / 2
    r = np.array([_ray(x, y, th + amin + i * inc) for i in range(beams)])
    return Scan(np.where(r < rmax, r, np.inf), amin, inc, 0.02, rmax)


def core(**kw) -> LocalizerCore:
    c = LocalizerCore(msgspec.structs.replace(LocalizerParams(), **kw))
    c.set_map(room())
    return c


@pytest.mark.parametrize("beams,fov", [(181, math.pi), (360, 2 * math.pi)])
def test_known_offsets_are_taken_back(beams, fov):
    """Without the motion prior the best fit is the true pose (the prior trades a little of
    that for odometry's guess where a scan constrains the pose weakly: see the corridor)."""
    rng = np.random.default_rng(3)
    c = core(prior=0.0)
    for _ in range(20):
        x, y, th = rng.uniform(1.2, 5.0), rng.uniform(0.9, 2.6), rng.uniform(-math.pi, math.pi)
        off = (rng.uniform(-0.25, 0.25), rng.uniform(-0.25, 0.25), rng.uniform(-0.12, 0.12))
        m = c.match(scan_at(x, y, th, beams, fov), Pose(x + off[0], y + off[1], th + off[2]))
        assert m.ok and m.score > 0.9, m
        assert math.hypot(m.pose.x - x, m.pose.y - y) < RES, (m.pose, (x, y, th), off)
        assert abs(math.remainder(m.pose.theta - th, 2 * math.pi)) < 0.01


def test_branch_and_bound_finds_what_the_full_search_finds():
    """coarse = 1 is the plain search over every cell (each block one cell, its bound its
    score); blocks of 4 and 8 cells find the same poses, scoring fewer."""
    rng = np.random.default_rng(5)
    full, bb = core(coarse=1), core(coarse=4)  # with the prior: its bounds are checked too
    fewer = 0
    for _ in range(10):
        x, y, th = rng.uniform(1.2, 5.0), rng.uniform(0.9, 2.6), rng.uniform(-math.pi, math.pi)
        s = scan_at(x, y, th)
        g = Pose(x + 0.2, y - 0.15, th + 0.05)
        a, b = full.match(s, g), bb.match(s, g)
        assert (a.pose.x, a.pose.y, a.pose.theta) == pytest.approx((b.pose.x, b.pose.y,
                                                                    b.pose.theta), abs=1e-9)
        fewer += b.evaluated < a.evaluated
    assert fewer >= 8


def test_no_map_or_too_few_points_keeps_the_guess():
    c = LocalizerCore(LocalizerParams())
    g = Pose(1.0, 2.0, 0.3)
    m = c.match(scan_at(2.0, 2.0, 0.0), g)
    assert not m.ok and m.pose == g  # no map yet
    c.set_map(GridMap(np.zeros((N, N), np.int8), GridGeometry(RES, 0.0, 0.0, N, N)))
    assert not c.ready and not c.match(scan_at(2.0, 2.0, 0.0), g).ok  # a map without walls
    c = core()
    empty = Scan(np.full(181, np.inf), -math.pi / 2, math.pi / 180, 0.02, 8.0)
    assert not c.match(empty, g).ok  # no returns


def test_a_scan_that_fits_nowhere_is_no_match():
    c = core()
    rng = np.random.default_rng(0)
    s = Scan(rng.uniform(0.3, 0.6, 181), -math.pi / 2, math.pi / 180, 0.02, 8.0)  # clutter
    g = Pose(3.0, 1.5, 0.0)
    m = c.match(s, g)
    assert not m.ok and m.pose == g and m.score < 0.3


def test_along_a_featureless_corridor_the_guess_stands():
    """A scan that sees two parallel walls only fixes the pose across them: the motion prior
    keeps the guess along the corridor, and the match still corrects the rest."""
    g = np.zeros((N, N), np.int8)
    g[40, :] = g[60, :] = 100  # walls at y = 40.5 and 60.5 cells
    c = LocalizerCore(LocalizerParams())
    c.set_map(GridMap(g, GridGeometry(RES, 0.0, 0.0, N, N)))
    x, y, th = 3.0, 50.5 * RES, 0.0
    ang = th - math.pi + 2 * math.pi / 360 * np.arange(360)
    r = np.array([(40.5 * RES - y) / math.sin(a) if math.sin(a) < -1e-9 else
                  (60.5 * RES - y) / math.sin(a) if math.sin(a) > 1e-9 else math.inf
                  for a in ang])
    s = Scan(np.where(r < 2.0, r, np.inf), -math.pi, 2 * math.pi / 360, 0.02, 2.0)
    m = c.match(s, Pose(x + 0.17, y - 0.12, th + 0.03))
    assert m.ok
    assert abs(m.pose.y - y) < RES and abs(m.pose.theta - th) < 0.01  # across: corrected
    assert abs(m.pose.x - (x + 0.17)) < RES  # along: odometry's guess


def corridor_scan(x: float, y: float, walls: tuple[float, float], rmax: float = 8.0) -> Scan:
    """A forward 180° scan between two walls along x at y = walls[0], walls[1] [m]."""
    ang = -math.pi / 2 + math.pi / 180 * np.arange(181)
    r = np.array([(walls[0] - y) / math.sin(a) if math.sin(a) < -1e-9 else
                  (walls[1] - y) / math.sin(a) if math.sin(a) > 1e-9 else math.inf
                  for a in ang])
    return Scan(np.where(r < rmax, r, np.inf), -math.pi / 2, math.pi / 180, 0.02, rmax)


def test_scan_conditioning_finds_the_corridor_direction():
    """Two parallel walls pin the position across them only (ratio about 0, the weak
    direction along them); a room's scans pin it both ways."""
    c = core()
    walls = (40.5 * RES, 60.5 * RES)
    ratio, weak = scan_conditioning(c._points(corridor_scan(3.0, 2.5, walls))[0])
    assert ratio < 0.01 and abs(weak[0]) > 0.99  # along x, in the robot frame
    rng = np.random.default_rng(3)
    for _ in range(20):
        x, y, th = rng.uniform(1.2, 5.0), rng.uniform(0.9, 2.6), rng.uniform(-math.pi, math.pi)
        assert scan_conditioning(c._points(scan_at(x, y, th))[0])[0] > 0.2
    assert scan_conditioning(np.zeros((2, 2)))[0] == 0.0  # too few points: no information


@pytest.mark.parametrize("mapped_to", [64, 70, 80])  # [cells] 0.2, 0.5, 1.0 m ahead
def test_the_map_edge_does_not_pull_the_pose_back_along_a_corridor(mapped_to):
    """The map of the scans before this one ends a little ahead of the robot: end points
    beyond its edge score nothing, and moving the pose back puts them on mapped wall. The
    plain search takes that pull (the bias that lost metres on large-office); with the
    degenerate-direction rule odometry's guess stands along the corridor, and the match
    still corrects across it."""
    n = 200
    g = np.full((n, n), -1, np.int8)
    g[41:60, :mapped_to] = 0
    g[40, :mapped_to] = g[60, :mapped_to] = 100  # faces at y = 40.5 and 60.5 cells
    grid = GridMap(g, GridGeometry(RES, 0.0, 0.0, n, n))
    x, y = 3.0, 50.5 * RES
    scan = corridor_scan(x, y, (40.5 * RES, 60.5 * RES))
    plain = LocalizerCore(msgspec.structs.replace(LocalizerParams(), degenerate_ratio=0.0,
                                                  known_only=False))
    plain.set_map(grid)
    assert plain.match(scan, Pose(x, y, 0.0)).pose.x < x - 0.1  # pulled back
    # step 0b alone leaves the points beyond the edge out, and with them the pull
    known = LocalizerCore(msgspec.structs.replace(LocalizerParams(), degenerate_ratio=0.0))
    known.set_map(grid)
    assert abs(known.match(scan, Pose(x, y, 0.0)).pose.x - x) < RES
    c = LocalizerCore(LocalizerParams())
    c.set_map(grid)
    m = c.match(scan, Pose(x, y + 0.08, 0.0))
    assert m.ok and m.conditioning < 0.01
    assert abs(m.pose.x - x) < 0.01  # along: odometry's guess (the weak direction turns with
    #   the matched heading)
    assert abs(m.pose.y - y) < RES  # across: corrected


def test_the_in_process_runner_runs_the_localizer():
    """`bench inproc --set localizer.enabled=true`: the localizer between the simulator and
    the rest, as in lockstep on the bus; with drifting odometry it keeps the pose close."""
    from topoexplore.tools.bench.inproc import run

    drift = ("sim.odom_drift=0.05", "sim.odom_drift_heading=0.05")
    on = run("paper-room", "reliability", 0, (*drift, "localizer.enabled=true"), 300.0)
    off = run("paper-room", "reliability", 0, drift, 300.0)
    assert on["finished"] and on["collisions"] == 0
    assert on["pose_rms_m"] < 0.15 and off["pose_rms_m"] > 3 * on["pose_rms_m"], (on, off)


def _cast(x: float, y: float, th: float, segs: list, beams: int = 181, rmax: float = 8.0
          ) -> Scan:
    """A forward 180° scan from (x, y, th) of the line segments ``segs``."""
    ang = -math.pi / 2 + math.pi / (beams - 1) * np.arange(beams)
    r = np.array([_ray_segs(x, y, a, segs) for a in th + ang])
    return Scan(np.where(r < rmax, r, np.inf), -math.pi / 2, math.pi / (beams - 1), 0.02, rmax)


def thin_wall_seen_from_the_north() -> tuple[GridMap, list]:
    """A room 0.1 m cells, its north wall 0.1 m thick, faces at y = 5.05 and 5.15 m: in the map
    only the north face's row (5.1-5.2 m) is a wall, as when it was mapped from the corridor
    beyond it, and the row of the south face was cleared (beams through a door); the west
    and east walls (x = 1.05, 8.95 m) as seen from inside."""
    n = 100
    g = np.full((n, n), -1, np.int8)
    g[20:51, 11:89] = 0  # the room (rows 20..50, y 2.0-5.1 m), the south face's row free
    g[51, 5:95] = 100  # the north face's row
    g[52:60, 5:95] = 0  # the corridor beyond it
    g[20:51, 10] = g[20:51, 89] = 100  # west and east walls' faces (x 1.0-1.1, 8.9-9.0)
    segs = [((0.5, 5.05), (9.5, 5.05)), ((1.05, 2.0), (1.05, 5.05)), ((8.95, 2.0), (8.95, 5.05))]
    return GridMap(g, GridGeometry(0.1, 0.0, 0.0, n, n)), segs


def test_a_thin_wall_mapped_from_the_other_side_does_not_pull_the_scan_onto_its_far_face():
    """Step 0: the scan from the room ends on the wall's south face, a cell short of the only
    face in the map. Faces scored from every side pull the pose a cell north (the whole-cell
    errors on office); with the sides recorded (beams travelling south ended on that row),
    the room's scan does not score on it and the pose stays."""
    grid, segs = thin_wall_seen_from_the_north()
    x, y, th = 5.0, 3.5, math.pi / 2  # facing the wall
    scan = _cast(x, y, th, segs)
    plain = LocalizerCore(msgspec.structs.replace(LocalizerParams(), directional=False))
    plain.set_map(grid)
    assert plain.match(scan, Pose(x, y, th)).pose.y > y + 0.07  # pulled onto the far face
    #   (its end points on the south face lie in cells the map knows, free: step 0b keeps them)
    c = LocalizerCore(LocalizerParams())
    c.set_map(grid)
    assert c.match(scan, Pose(x, y, th)).pose.y > y + 0.07  # no record yet: every side counts
    # the corridor's scans, facing south, ended on the wall's row: its side is recorded
    north = [((0.5, 5.15), (9.5, 5.15))]
    for cx in (2.0, 4.0, 6.0, 8.0):
        c.observe(_cast(cx, 5.8, -math.pi / 2, north), Pose(cx, 5.8, -math.pi / 2))
    c.set_map(grid)
    m = c.match(scan, Pose(x, y, th))
    assert not m.ok and m.pose == Pose(x, y, th)  # what is left (the side walls) is too little
    # (without step 0b: the guess 0.1 m east puts the east wall's end points in the
    # never-seen cells behind it, and 0b would leave them out)
    c = LocalizerCore(msgspec.structs.replace(LocalizerParams(), min_score=0.2,
                                              known_only=False))
    c.set_map(grid)
    for cx in (2.0, 4.0, 6.0, 8.0):
        c.observe(_cast(cx, 5.8, -math.pi / 2, north), Pose(cx, 5.8, -math.pi / 2))
    c.set_map(grid)
    m = c.match(scan, Pose(x + 0.1, y, th + 0.03))  # the side walls correct x and heading
    assert m.ok and abs(m.pose.y - y) < 0.02 and abs(m.pose.x - x) < 0.03, m
    assert abs(m.pose.theta - th) < 0.01


def test_the_sides_follow_a_growing_map_and_go_where_it_is_cleared():
    """The record is kept in the map's geometry: a map grown by whole cells keeps it where it
    was (in world coordinates); a cell the map has since seen free loses it."""
    grid, _ = thin_wall_seen_from_the_north()
    c = LocalizerCore(LocalizerParams())
    c.set_map(grid)
    north = [((0.5, 5.15), (9.5, 5.15))]
    c.observe(_cast(5.0, 5.8, -math.pi / 2, north), Pose(5.0, 5.8, -math.pi / 2))
    before = c._hits.copy()
    assert (before[51, 35:65] == NORTH).all()  # seen from above
    assert set(np.unique(before[51])) == {0, NORTH}  # far away the hits are too sparse
    assert before.sum() == before[51].sum()  # only the wall's row
    big = np.full((140, 120), -1, np.int8)
    big[20:120, 10:110] = grid.data  # grown by 2 m west and south
    c.set_map(GridMap(big, GridGeometry(0.1, -1.0, -2.0, 120, 140)))
    assert np.array_equal(c._hits[20:120, 10:110], before)
    big[71, 40:60] = 0  # part of the wall seen free since
    c.set_map(GridMap(big, GridGeometry(0.1, -1.0, -2.0, 120, 140)))
    assert not c._hits[71, 40:60].any() and c._hits[71, 60:75].all()


def test_surface_sides_are_the_normals_turned_to_the_laser():
    """End points along a wall on y = 4 seen from below: its south side, however flat the
    beams; along a wall at 45°, two sides; a lone point: none."""
    x = np.array([1.0, 2.0, 3.0, 4.0]) * 0.1
    ox, oy = 0.2, 1.0  # the laser, below the wall
    for y, lo in ((np.full(4, 4.0), SOUTH), (np.full(4, -2.0), NORTH)):
        dx, dy = x - ox, y - oy
        got = surface_sides(x, y, dx / np.hypot(dx, dy), dy / np.hypot(dx, dy))
        assert list(got) == [0, lo, lo, 0]  # the ends have one neighbour only
    d = np.array([0.0, 0.1, 0.2]) / math.sqrt(2)
    x, y = 2.0 + d, 2.0 - d  # a wall running south-east, seen from the origin
    assert surface_sides(x, y, x / np.hypot(x, y), y / np.hypot(x, y))[1] == WEST | SOUTH
    far = np.array([0.0, 1.0, 2.0])
    assert not surface_sides(far, far, np.ones(3), np.zeros(3)).any()


@pytest.mark.parametrize("res,sigma", [(0.1, 0.05), (0.05, 0.05), (0.1, 0.2), (0.01, 0.5)])
def test_the_likelihood_field_is_that_of_the_distance_to_the_faces(res, sigma):
    """Rings of dilations give exp(-d^2 / 2 sigma^2) of d = the distance to the nearest face
    cell less half a cell, as a Euclidean distance transform does (a wide spread takes the
    transform itself), 0 below the floor."""
    from topoexplore.common.grid import distance_transform
    from topoexplore.services.localizer.core import FIELD_FLOOR, likelihood_field

    rng = np.random.default_rng(1)
    face = np.zeros((90, 110), bool)
    face[rng.integers(0, 90, 40), rng.integers(0, 110, 40)] = True
    face[30, 10:80] = face[10:70, 55] = True
    d = np.maximum(distance_transform((~face).astype(np.uint8)) * res - 0.5 * res, 0.0)
    want = np.exp(-0.5 * (d / sigma) ** 2)
    want[want < FIELD_FLOOR] = 0.0
    got = likelihood_field(face, res, sigma)
    assert got.dtype == np.float32 and got.shape == face.shape
    assert np.abs(got - want).max() < 1e-6


def test_known_only_matches_the_end_points_on_observed_cells_alone():
    """``known_only``: a scan matched on a map that ends at x = 3.1 m (the east part never
    observed) is matched as if the beams ending beyond it had no return: they score nothing
    at the guess, and a pose that moved them onto a known wall would gain from them."""
    g = room()
    data = g.data.copy()
    data[:, 62:] = -1  # x >= 3.1 m unknown; the wall faces up to x = 3.05 m stay
    half = GridMap(data, g.geom)
    x, y, th = 1.2, 2.0, 1.3  # facing north-north-east: the west wall, the north wall and
    scan = scan_at(x, y, th)  # the box in view, the north wall's east half beyond the map
    guess = Pose(x + 0.08, y - 0.06, th + 0.03)
    on = LocalizerCore(msgspec.structs.replace(LocalizerParams(), known_only=True,
                                               max_points=1000))
    on.set_map(half)
    r, a = scan.returns()
    ex = guess.x + r * np.cos(guess.theta + a)
    cut = np.where(np.isfinite(scan.ranges), scan.ranges, 0.0)
    beyond = np.zeros(len(scan.ranges), bool)
    beyond[np.flatnonzero(np.isfinite(scan.ranges) & (scan.ranges < scan.range_max))] = \
        ex >= 62 * RES  # past the last known column
    assert 10 < beyond.sum() < 150
    kept = Scan(np.where(beyond, np.inf, cut), scan.angle_min, scan.angle_increment,
                scan.range_min, scan.range_max)
    off = LocalizerCore(msgspec.structs.replace(LocalizerParams(), known_only=False,
                                                max_points=1000))
    off.set_map(half)
    a1, a2 = on.match(scan, guess), off.match(kept, guess)
    assert a1.points == a2.points == int((~beyond & np.isfinite(scan.ranges)).sum())
    assert a1.pose == a2.pose and a1.ok
    assert math.hypot(a1.pose.x - x, a1.pose.y - y) < RES


def test_surface_directions_are_those_of_the_straight_stretches():
    """Walls and a box seen from inside the room: the straight stretches run along x or y
    (a window round a corner with one point on the other face may pass as straight, a little
    turned: the histogram's correlation outweighs a few); a scatter of points gives none."""
    s = scan_at(2.0, 4.0, 0.3)
    r, a = s.returns()
    pts = np.column_stack((r * np.cos(a + 0.3), r * np.sin(a + 0.3)))  # map-frame axes
    phi = surface_directions(pts)
    assert len(phi) > 100
    off = np.abs(((phi + math.pi / 4) % (math.pi / 2)) - math.pi / 4)
    assert np.mean(off < 1e-6) > 0.95 and np.all(off < 0.03)
    rng = np.random.default_rng(0)
    assert len(surface_directions(rng.uniform(0.0, 0.3, (60, 2)))) == 0
    assert len(surface_directions(pts[:5])) == 0


@pytest.mark.parametrize("turn", [0.012, -0.031])
def test_heading_offset_lines_a_turned_histogram_up_with_the_reference(turn):
    rng = np.random.default_rng(1)
    walls = np.concatenate((rng.normal(0.2, 0.003, 300), rng.normal(0.2 + math.pi / 2, 0.003, 200)))
    ref = direction_histogram(walls)
    seen = direction_histogram(rng.choice(walls, 80) + turn)
    assert heading_offset(seen, ref, 0.05) == pytest.approx(-turn, abs=0.003)
    # the best turn beyond the window: no offset; nothing to line up: none
    assert heading_offset(direction_histogram(walls[:50] + 0.08), ref, 0.05) is None
    assert heading_offset(np.zeros_like(ref), ref, 0.05) is None


def _turned_room(d: float, c: tuple[float, float]) -> GridMap:
    """The room of :func:`room` turned by ``d`` [rad] round ``c`` (the map a run whose
    heading walked off by ``d`` draws)."""
    cs, sn = math.cos(d), math.sin(d)
    x0, y0, x1, y1 = BOX
    rings = [[(LO, LO), (HI, LO), (HI, HI), (LO, HI)], [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]]
    g = np.zeros((N, N), np.uint8)
    for ring in rings:
        cells = [((c[0] + cs * (x - c[0]) - sn * (y - c[1])) / RES - 0.5,
                  (c[1] + sn * (x - c[0]) + cs * (y - c[1])) / RES - 0.5) for x, y in ring]
        poly = np.round(np.array(cells) * 16).astype(np.int32)
        cv2.polylines(g, [poly], True, 100, 1, cv2.LINE_8, shift=4)
    return GridMap(g.astype(np.int8), GridGeometry(RES, 0.0, 0.0, N, N))


@pytest.mark.parametrize("gain", [0.0, 0.5, 1.0])
def test_the_heading_comes_back_to_the_directions_seen_since_the_start(gain):
    """Step 6: a map drawn while the heading walked off by 0.03 rad agrees with a scan at the
    turned pose, so steps 1-5 keep the turn; the histogram of the scans before the walk
    does not, and the match turns back by ``gain`` of it."""
    d, c = 0.03, (3.0, 3.0)
    loc = LocalizerCore(msgspec.structs.replace(LocalizerParams(), heading_gain=gain))
    loc.set_map(room())
    for x, y, th in [(2.0, 2.0, 0.2), (4.0, 3.0, 1.7), (3.0, 4.5, -2.0), (2.5, 3.0, 3.0)]:
        loc.observe(scan_at(x, y, th), Pose(x, y, th))  # the run so far, at the true poses
    loc.set_map(_turned_room(d, c))
    x, y, th = 2.4, 3.2, 0.4
    guess = Pose(c[0] + math.cos(d) * (x - c[0]) - math.sin(d) * (y - c[1]),
                 c[1] + math.sin(d) * (x - c[0]) + math.cos(d) * (y - c[1]), th + d)
    got = loc.match(scan_at(x, y, th), guess)
    assert got.ok
    assert got.pose.theta == pytest.approx(th + (1.0 - gain) * d, abs=0.006)


def test_a_checkpoint_gives_a_new_core_what_the_scans_taught_this_one():
    """Step 0's sides per cell (with their grid's placement) and step 6's histogram come back
    in a fresh core; the likelihood fields it makes from the next map are then the same."""
    from topoexplore.common.checkpoint import decode_checkpoint, encode_checkpoint

    old = core()
    for x, y, th in ((1.5, 1.2, 0.3), (4.0, 2.4, -2.0), (2.5, 2.0, 1.6)):
        old.observe(scan_at(x, y, th), Pose(x, y, th))
    old.set_map(room())
    arrays, _ = decode_checkpoint(encode_checkpoint(old.checkpoint(), 0.0))  # through a file
    new = LocalizerCore(LocalizerParams())
    new.restore(arrays)
    new.set_map(room())
    assert new._ref.sum() > 0 and np.array_equal(new._ref, old._ref)
    assert new._hits.any() and np.array_equal(new._hits, old._hits)
    assert new._hits_geom == old._hits_geom
    assert np.array_equal(new._field, old._field)
    scan, guess = scan_at(3.0, 1.5, 0.5), Pose(3.1, 1.45, 0.55)
    assert new.match(scan, guess) == old.match(scan, guess)
    fresh = LocalizerCore(LocalizerParams())  # before any map: the histogram alone
    fresh.restore(LocalizerCore(LocalizerParams()).checkpoint())
    assert fresh._hits is None and not fresh._ref.any()


@pytest.mark.parametrize("change", [
    lambda a: a.pop("ref"), lambda a: a.update(ref=np.full(720, np.nan)),
    lambda a: a.update(ref=-a["ref"] - 1.0), lambda a: a.update(ref=np.zeros(10)),
    lambda a: a.update(hits=a["hits"] * 0 + 16), lambda a: a.pop("hits_geom"),
    lambda a: a.update(hits_geom=np.array([0.0, 0.0, 0.0])),
    lambda a: a.update(hits_geom=np.array([0.05, np.inf, 0.0])),
    lambda a: a.update(hits=np.zeros((0, 5), np.uint8)),
])
def test_a_localizer_checkpoint_it_cannot_use_is_refused_and_nothing_taken(change):
    from topoexplore.common.checkpoint import CheckpointError

    old = core()
    old.observe(scan_at(2.0, 1.5, 0.0), Pose(2.0, 1.5, 0.0))
    arrays = old.checkpoint()
    change(arrays)
    new = core()
    before = new.checkpoint()
    with pytest.raises(CheckpointError):
        new.restore(arrays)
    after = new.checkpoint()
    assert all(np.array_equal(after[k], before[k]) for k in before)
