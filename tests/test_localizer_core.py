"""The localizer core (services/localizer/core.py) on synthetic scans with known offsets."""

from __future__ import annotations

import math

import msgspec
import numpy as np
import pytest

from topoexplore.common.domain import GridMap, Pose, Scan
from topoexplore.common.grid import GridGeometry
from topoexplore.common.params import LocalizerParams
from topoexplore.services.localizer.core import LocalizerCore, scan_conditioning

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


def _ray(x: float, y: float, a: float) -> float:
    c, s = math.cos(a), math.sin(a)
    best = math.inf
    segs = [((LO, LO), (HI, LO)), ((HI, LO), (HI, HI)), ((HI, HI), (LO, HI)), ((LO, HI), (LO, LO))]
    x0, y0, x1, y1 = BOX
    segs += [((x0, y0), (x1, y0)), ((x1, y0), (x1, y1)), ((x1, y1), (x0, y1)), ((x0, y1), (x0, y0))]
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
    ratio, weak = scan_conditioning(c._points(corridor_scan(3.0, 2.5, walls)))
    assert ratio < 0.01 and abs(weak[0]) > 0.99  # along x, in the robot frame
    rng = np.random.default_rng(3)
    for _ in range(20):
        x, y, th = rng.uniform(1.2, 5.0), rng.uniform(0.9, 2.6), rng.uniform(-math.pi, math.pi)
        assert scan_conditioning(c._points(scan_at(x, y, th)))[0] > 0.2
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
    plain = LocalizerCore(msgspec.structs.replace(LocalizerParams(), degenerate_ratio=0.0))
    plain.set_map(grid)
    assert plain.match(scan, Pose(x, y, 0.0)).pose.x < x - 0.2  # pulled back
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
