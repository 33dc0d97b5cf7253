"""Unit tests for the controller core (DESIGN.md §4 "Controller")."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from topoexplore.common.domain import Pose, Route, Scan
from topoexplore.common.params import ControllerParams, load_params
from topoexplore.services.controller.core import (
    MODES,
    ControllerCore,
    arc_distance,
    clean_path,
    clear_heading,
    front_distance,
    lookahead_point,
    obstacle_scale,
    path_arclength,
    point_at,
    project_on_path,
    seen_free,
    straight_distance,
)

P = ControllerParams(start_turn=0.0)  # path following from the first step (look: own test)
P_BACKUP = ControllerParams(recovery_backup=True, start_turn=0.0)
STRAIGHT = np.array([[0.0, 0.0], [5.0, 0.0]])
L_PATH = np.array([[0.0, 0.0], [2.0, 0.0], [2.0, 2.0]])


R = 0.2  # [m] robot radius


def free_scan(rng: float = 8.0) -> Scan:
    """181 beams, -90..90 deg, all returning rng [m]."""
    return Scan(np.full(181, rng), -math.pi / 2, math.radians(1.0), 0.02, 8.0)


def scan_with(points_xy: list[tuple[float, float]], rng: float = 8.0) -> Scan:
    """Free scan with returns at the given robot-frame points (nearest beam per point)."""
    s = free_scan(rng)
    for x, y in points_xy:
        k = int(round((math.atan2(y, x) - s.angle_min) / s.angle_increment))
        s.ranges[k] = min(s.ranges[k], math.hypot(x, y))
    return s


def step(core, t, pose, path, plan_id, done, scan, goal_heading=None):
    """One update with the path given as waypoints and a plan id."""
    route = Route(np.asarray(path, dtype=np.float64).reshape(-1, 2), plan_id,
                  goal_heading=goal_heading)
    return core.update(t, Pose(*pose), route, done, scan)


def unicycle(x: float, y: float, th: float, v: float, w: float, dt: float
             ) -> tuple[float, float, float]:
    """An ideal unicycle driven at (v, w) for dt [s] (exact arc integration)."""
    if abs(w) < 1e-9:
        return x + v * dt * math.cos(th), y + v * dt * math.sin(th), th
    return (x + v / w * (math.sin(th + w * dt) - math.sin(th)),
            y - v / w * (math.cos(th + w * dt) - math.cos(th)), th + w * dt)


def simulate(core: ControllerCore, path, pose, steps: int, dt: float = 0.2, scan=None,
             plan_id: int = 1, t0: float = 0.0):
    """Closed loop with an ideal unicycle (exact arc integration); returns poses, modes."""
    x, y, th = pose
    poses, modes = [], []
    for k in range(steps):
        v, w, mode = step(core, t0 + k * dt, (x, y, th), path, plan_id, False,
                                 scan if scan is not None else free_scan())
        assert abs(v) <= P.v_max + 1e-12 and abs(w) <= P.w_max + 1e-12
        assert mode in MODES
        modes.append(mode)
        x, y, th = unicycle(x, y, th, v, w, dt)
        poses.append((x, y, th))
        if mode == "arrived":
            break
    return poses, modes


# --- geometry helpers -------------------------------------------------------------------------


def test_path_helpers():
    path = clean_path([[0, 0], [0, 0], [1, 0], [1, 1]])
    assert path.shape == (3, 2)
    cum = path_arclength(path)
    assert cum.tolist() == [0.0, 1.0, 2.0]
    assert point_at(path, cum, 1.5).tolist() == [1.0, 0.5]
    assert point_at(path, cum, 9.0).tolist() == [1.0, 1.0]
    s, d = project_on_path(path, cum, 0.4, -0.3, 0.0, 10.0)
    assert s == pytest.approx(0.4) and d == pytest.approx(0.3)
    assert project_on_path(path, cum, 1.0, 1.0, 2.0, 2.0) == (2.0, 0.0)  # from the very end
    # never goes back: projection limited to s >= s_lo
    s, _ = project_on_path(path, cum, 0.2, 0.0, 0.5, 10.0)
    assert s == pytest.approx(0.5)


def test_projection_window_ignores_later_parts_of_a_loop():
    # U-shaped path whose end comes back close to the start
    path = clean_path([[0, 0], [3, 0], [3, 1], [0, 1]])
    cum = path_arclength(path)
    s, _ = project_on_path(path, cum, 0.1, 0.6, 0.0, 1.5)  # nearer to the last leg
    assert s < 1.5


def test_lookahead_point_off_path_goes_back_to_path():
    path = STRAIGHT
    cum = path_arclength(path)
    pt, _ = lookahead_point(path, cum, 1.0, 0.2, 1.0, 0.4, 1.5)
    assert pt[0] == pytest.approx(1.0 + math.sqrt(0.4**2 - 0.2**2), abs=0.03)
    pt, _ = lookahead_point(path, cum, 1.0, 2.0, 1.0, 0.4, 1.5)  # far off: nearest path point
    assert pt.tolist() == [1.0, 0.0]


def test_front_distance_sector_and_lateral_offset():
    assert front_distance(None, P, R) == math.inf
    assert front_distance(free_scan(), P, R) == math.inf  # range_max everywhere: no return
    assert front_distance(scan_with([(0.5, 0.0)]), P, R) == pytest.approx(0.5)
    # inside the angular sector but beside the robot's corridor (lateral 0.3 > 0.25): ignored
    assert front_distance(scan_with([(0.6, 0.3)]), P, R) == math.inf
    # ahead-left at 45 deg and inside the corridor: in the way (a sofa corner, say)
    assert front_distance(scan_with([(0.2, 0.2)]), P, R) == pytest.approx(math.hypot(0.2, 0.2))
    # outside the angular sector (about 76 deg): beside the robot, not ahead
    assert front_distance(scan_with([(0.05, 0.2)]), P, R) == math.inf
    # REP-117: below range_min, NaN and +Inf are no returns; -Inf is an object too close
    s = free_scan()
    s.ranges[90] = 0.0
    s.ranges[91] = np.nan
    s.ranges[89] = np.inf
    assert front_distance(s, P, R) == math.inf
    s.ranges[90] = -np.inf
    assert front_distance(s, P, R) == pytest.approx(s.range_min)


def only(points_xy: list[tuple[float, float]]) -> Scan:
    """A scan with returns at the given robot-frame points only (no return elsewhere)."""
    return scan_with(points_xy, math.inf)


def _arc_brute(x: float, y: float, kappa: float, rho: float) -> float:
    """arc_distance for one return, by walking the centre along the arc in 0.1 mm steps."""
    length = 2 * math.pi / abs(kappa) if kappa else 3.0
    s = np.arange(0.0, length, 1e-4)
    cx, cy = ((np.sin(kappa * s) / kappa, (1 - np.cos(kappa * s)) / kappa) if kappa
              else (s, 0.0 * s))
    d = np.hypot(x - cx, y - cy)
    if d[0] < rho:
        return rho if d[1] < d[0] else math.inf
    hit = np.nonzero(d < rho)[0]
    return float(s[hit[0]]) + rho if len(hit) else math.inf


def test_arc_distance_is_the_swept_disc_of_the_body():
    rng = np.random.default_rng(7)
    for _ in range(400):
        x, y = rng.uniform(0.0, 1.0), rng.uniform(-0.8, 0.8)
        kappa = 0.0 if rng.random() < 0.2 else rng.uniform(-4.0, 4.0)
        if math.hypot(x, y) < 0.05:  # below range_min: no valid reading (REP-117)
            continue
        s = only([(x, y)])
        k = int(np.nonzero(np.isfinite(s.ranges))[0][0])
        a = s.angle_min + k * s.angle_increment  # the beam's own point
        px, py = s.ranges[k] * math.cos(a), s.ranges[k] * math.sin(a)
        got, want = arc_distance(s, kappa, R), _arc_brute(px, py, kappa, R)
        assert (math.isinf(got) and math.isinf(want)) or got == pytest.approx(want, abs=2e-3)
    # straight ahead it is the range, as front_distance measures it
    assert arc_distance(only([(0.45, 0.0)]), 0.0, R) == pytest.approx(0.45)
    assert arc_distance(only([]), 1.0, R) == math.inf
    assert arc_distance(None, 1.0, R) == math.inf


def test_turning_into_a_return_beside_the_body_stops():
    """A held-back cluttered floor: turning right at 0.2 m/s past a return 0.19 m to the right
    of the body's front, at 74 deg (outside the front sector): the straight corridor sees
    nothing, the arc the command drives meets it at once."""
    wall = [(0.044, -0.191), (0.04, -0.203), (0.08, -0.23), (0.12, -0.27), (0.2, -0.37)]
    scan = only(wall)
    assert front_distance(scan, P, R) == math.inf  # outside the sector: not looked at
    bend = np.array([[0.0, 0.0], [0.3, -0.05], [0.4, -0.4]])  # the path bends to the right
    core = ControllerCore(P)
    v, w, mode = step(core, 0.0, (0.0, 0.0, 0.0), bend, 1, False, scan)
    assert mode == "blocked" and v == 0.0 and w < 0.0  # turns on the spot (a circle: safe)
    # turning left, away from it, after the body has passed it, is not in the way
    assert arc_distance(only([(-0.01, -0.2)]), 2.0, R) == math.inf
    # straight on past a wall 0.21 m to the side: the body clears it (a door's jamb)
    assert arc_distance(only([(0.3, 0.21), (0.6, 0.21)]), 0.0, R) == math.inf


def _world_scan(pose, points) -> Scan:
    """The free scan with returns at world points (x, y) [m] seen from pose."""
    x, y, th = pose
    c, s_ = math.cos(th), math.sin(th)
    return scan_with([(c * (px - x) + s_ * (py - y), -s_ * (px - x) + c * (py - y))
                      for px, py in points])


def test_a_robot_blocked_while_facing_its_path_turns_to_a_clear_heading_and_goes_on():
    """Held-back cluttered-s1-24x22-n2 (SLAM noise): the stair-step corner of a box 0.19 m
    to the right of the robot's heading, just ahead of its centre, inside the body's
    corridor by a centimetre. The path runs straight on, so turning toward the path turned
    nothing: the robot stood "blocked" for good. Now it turns left until its way straight on
    is clear, creeps on past the corner and goes back to its path, never touching it."""
    corner = [(0.12, -0.19), (0.12, -0.25), (0.16, -0.19), (0.2, -0.19)]  # the box's corner
    core = ControllerCore(P)
    x, y, th = 0.0, 0.0, 0.0
    v, w, mode = step(core, 0.0, (x, y, th), STRAIGHT, 1, False, _world_scan((x, y, th), corner))
    assert mode == "blocked" and v == 0.0 and w > 0.0  # away from the corner, to the left
    dt, gap = 0.2, math.inf
    for k in range(1, 60):
        x, y, th = unicycle(x, y, th, v, w, dt)
        gap = min(gap, min(math.hypot(px - x, py - y) for px, py in corner))
        v, w, mode = step(core, k * dt, (x, y, th), STRAIGHT, 1, False,
                          _world_scan((x, y, th), corner))
    assert gap > R  # never touched it
    assert x > 0.5 and abs(y) < 0.1 and v > 0.0 and mode in ("track", "slow")  # past it


def test_blocked_only_on_the_commanded_arc_creeps_straight_on():
    """A return 0.205 m right of the heading, beside the body's front: the arc of a right turn
    meets it at once, the way straight on does not (the body passes it): creep straight on
    instead of standing still."""
    scan = only([(0.05, -0.205)])
    assert straight_distance(scan, P, R) >= P.safety_distance
    bend = np.array([[0.0, 0.0], [0.3, -0.05], [0.4, -0.4]])  # the path bends to the right
    v, w, mode = step(ControllerCore(P), 0.0, (0.0, 0.0, 0.0), bend, 1, False, scan)
    assert mode == "slow" and w == 0.0 and v == pytest.approx(P.v_max * P.slow_min_scale)


def test_clear_heading():
    free = free_scan()
    assert clear_heading(free, P, R, R + 0.05, 0.3) == pytest.approx(0.3)  # the path's own
    post = scan_with([(0.27, 0.1)])  # a post 0.29 m ahead, 0.1 m left of the heading
    turn = clear_heading(post, P, R, R + 0.05, 0.0)
    assert turn is not None and -P.rotate_angle <= turn < 0.0  # to the right, away from it
    assert straight_distance(post, P, R + 0.05, turn) >= P.safety_distance
    assert straight_distance(post, P, R + 0.05, 0.0) < P.safety_distance
    # the nearest to the path's heading: every heading between is blocked
    assert all(straight_distance(post, P, R + 0.05, a) < P.safety_distance
               for a in np.linspace(turn + 0.05, 0.0, 10))
    walled = scan_with([(0.25 * math.cos(a), 0.25 * math.sin(a))
                        for a in np.linspace(-math.pi / 2, math.pi / 2, 181)])
    assert clear_heading(walled, P, R, R + 0.05, 0.0) is None
    assert clear_heading(None, P, R, R + 0.05, 0.2) == pytest.approx(0.2)


def test_obstacle_scale():
    assert obstacle_scale(math.inf, P) == 1.0
    assert obstacle_scale(P.slow_distance, P) == 1.0
    assert obstacle_scale(P.safety_distance, P) == pytest.approx(P.slow_min_scale)
    mid = 0.5 * (P.safety_distance + P.slow_distance)
    assert obstacle_scale(mid, P) == pytest.approx(0.5 * (1 + P.slow_min_scale))
    assert obstacle_scale(P.safety_distance - 0.01, P) == 0.0


def test_seen_free_follows_each_beam_to_its_return():
    s = scan_with([(1.0, 0.0)])  # a return 1 m straight ahead, 8 m elsewhere
    px = np.array([0.5, 0.97, 1.5, 3.0, -1.0, 0.0])
    py = np.array([0.0, 0.0, 0.0, 1.0, 0.0, 2.0])
    got = seen_free(px, py, (0.0, 0.0, 0.0), s)
    # before the return; too near it (margin); behind it; beside it; behind the laser; at 90°
    assert got.tolist() == [True, False, False, True, False, True]
    # the same scan taken facing back (theta = pi) sees the point behind, not the one ahead
    assert seen_free(np.array([-0.5, 0.5]), np.zeros(2), (0.0, 0.0, math.pi), s).tolist() == \
        [True, False]
    # REP-117: +Inf is free to range_max, NaN and -Inf are not seen
    r = np.full(181, np.inf)
    r[90], r[0] = np.nan, -np.inf
    odd = Scan(r, -math.pi / 2, math.radians(1.0), 0.02, 8.0)
    assert seen_free(np.array([2.0, 0.0, 7.9, 9.0]), np.array([0.0, -2.0, 0.5, 0.0]),
                     (0.0, 0.0, 0.0), odd).tolist() == [False, False, True, False]


def test_backing_up_only_into_space_a_recent_scan_saw_free():
    core = ControllerCore(P_BACKUP)
    # facing +x, a forward laser: nothing seen behind yet
    assert not core.rear_clear((0.0, 0.0, 0.0), free_scan())
    # it had faced back (-x) a moment ago and saw free space there: backing up is allowed
    step(core, 0.0, (0.0, 0.0, math.pi), STRAIGHT, 1, False, free_scan())
    assert core.rear_clear((0.0, 0.0, 0.0), free_scan())
    # ... unless that scan had a return within the corridor the body would sweep
    core = ControllerCore(P_BACKUP)
    step(core, 0.0, (0.0, 0.0, math.pi), STRAIGHT, 1, False, scan_with([(0.35, 0.0)]))
    assert not core.rear_clear((0.0, 0.0, 0.0), free_scan())
    # ... or it was seen longer ago than recovery_memory
    core = ControllerCore(P_BACKUP)
    step(core, 0.0, (0.0, 0.0, math.pi), STRAIGHT, 1, False, free_scan())
    step(core, P_BACKUP.recovery_memory + 1.0, (0.0, 0.0, 0.0), STRAIGHT, 1, False,
         free_scan())
    assert not core.rear_clear((0.0, 0.0, 0.0), free_scan())
    # a 360° lidar sees behind now: its return 0.3 m behind blocks, its free rear allows
    wide = Scan(np.array([0.3, 8.0, 8.0]), math.pi, -math.pi / 2, 0.02, 8.0)
    assert not ControllerCore(P_BACKUP).rear_clear((0.0, 0.0, 0.0), wide)
    around = Scan(np.full(360, 8.0), -math.pi, math.radians(1.0), 0.02, 8.0)
    assert ControllerCore(P_BACKUP).rear_clear((0.0, 0.0, 0.0), around)


# --- behaviour --------------------------------------------------------------------------------


def test_straight_path_full_speed():
    core = ControllerCore(P)
    v, w, mode = step(core, 0.0, (0.0, 0.0, 0.0), STRAIGHT, 1, False, free_scan())
    assert mode == "track"
    assert v == pytest.approx(P.v_max)
    assert abs(w) < 1e-9


def test_path_behind_rotates_in_place():
    core = ControllerCore(P)
    v, w, mode = step(core, 0.0, (0.0, 0.0, math.pi), STRAIGHT, 1, False, free_scan())
    assert mode == "rotate" and v == 0.0 and abs(w) > 0.0
    # path to the left: turn counter-clockwise
    core = ControllerCore(P)
    v, w, mode = step(core, 0.0, (0.0, 0.0, 0.0), [[0, 0], [0, 3]], 1, False, free_scan())
    assert mode == "rotate" and v == 0.0 and w > 0.0


def test_rotation_direction_does_not_chatter_at_pi():
    core = ControllerCore(P)
    path = [[0.0, 0.0], [-3.0, 0.0]]
    _, w1, _ = step(core, 0.0, (0.0, 0.0, 0.01), path, 1, False, free_scan())
    _, w2, m2 = step(core, 0.2, (0.0, 0.0, -0.01), path, 1, False, free_scan())
    assert m2 == "rotate" and math.copysign(1, w1) == math.copysign(1, w2)


def test_obstacle_in_front_blocks():
    core = ControllerCore(P)
    v, w, mode = step(core, 0.0, (0.0, 0.0, 0.0), STRAIGHT, 1, False, scan_with([(0.25, 0.0)]))
    assert mode == "blocked" and v == 0.0


def test_obstacle_near_slows_down():
    core = ControllerCore(P)
    v, _, mode = step(core, 0.0, (0.0, 0.0, 0.0), STRAIGHT, 1, False, scan_with([(0.45, 0.0)]))
    assert mode == "slow"
    assert 0.0 < v < P.v_max
    assert v == pytest.approx(P.v_max * obstacle_scale(0.45, P))


def test_obstacle_beside_corridor_does_not_slow():
    core = ControllerCore(P)
    v, _, mode = step(core, 0.0, (0.0, 0.0, 0.0), STRAIGHT, 1, False,
                             scan_with([(0.4, 0.35), (0.4, -0.35)]))
    assert mode == "track" and v == pytest.approx(P.v_max)


def test_a_door_of_the_body_width_plus_the_margins_is_passed_at_a_creep():
    """Door posts 0.24 m either side of the path (a 0.48 m door for a 0.4 m body; the
    margin band is 0.2..0.25 m), right beside the robot: no stop, the slowest speed. The same
    post in the body's own path stops it."""
    core = ControllerCore(P)
    posts = [(0.1, 0.24), (0.1, -0.24), (0.2, 0.24), (0.2, -0.24)]
    v, _, mode = step(core, 0.0, (0.0, 0.0, 0.0), STRAIGHT, 1, False, scan_with(posts))
    assert mode == "slow" and v == pytest.approx(P.v_max * P.slow_min_scale)
    core = ControllerCore(P)
    v, _, mode = step(core, 0.0, (0.0, 0.0, 0.0), STRAIGHT, 1, False,
                      scan_with([(0.2, 0.15)]))
    assert mode == "blocked" and v == 0.0


def test_a_stale_plan_stops_the_robot_until_a_new_one_comes():
    """Issue 14: a planner frozen (SIGSTOP) or dead leaves its last plan on the bus; beyond
    plan_timeout of robot time without a new plan message the controller stops."""
    core = ControllerCore(P)
    route = Route(np.asarray(STRAIGHT, float).reshape(-1, 2), 1)
    assert core.update(0.0, Pose(0.0, 0.0, 0.0), route, False, free_scan(), None).mode == "track"
    assert core.update(0.1, Pose(0.0, 0.0, 0.0), route, False, free_scan(),
                       P.plan_timeout).mode == "track"
    cmd = core.update(0.2, Pose(0.0, 0.0, 0.0), route, False, free_scan(), P.plan_timeout + 0.1)
    assert cmd == (0.0, 0.0, "stale-plan") and core.stale_plan_steps == 1
    assert core.update(0.3, Pose(0.0, 0.0, 0.0), route, False, free_scan(), 0.0).mode == "track"
    # a caller's own limit (the service's, in lockstep: two map periods) replaces the default
    assert core.update(0.4, Pose(0.0, 0.0, 0.0), route, False, free_scan(), P.plan_timeout + 0.1,
                       plan_limit=0.8).mode == "track"
    assert core.update(0.5, Pose(0.0, 0.0, 0.0), route, False, free_scan(), 0.81,
                       plan_limit=0.8).mode == "stale-plan"


def test_empty_path_and_done_stop():
    core = ControllerCore(P)
    assert step(core, 0.0, (0.0, 0.0, 0.0), np.zeros((0, 2)), 1, False, free_scan()) == (
        0.0, 0.0, "idle")
    assert step(core, 0.2, (0.0, 0.0, 0.0), [], 2, False, None) == (0.0, 0.0, "idle")
    assert step(core, 0.4, (0.0, 0.0, 0.0), STRAIGHT, 3, True, free_scan()) == (
        0.0, 0.0, "done")


def test_follows_l_shaped_path_to_the_end():
    core = ControllerCore(P)
    poses, modes = simulate(core, L_PATH, (0.0, 0.0, 0.0), steps=600)
    assert modes[-1] == "arrived"
    x, y, _ = poses[-1]
    assert math.hypot(x - 2.0, y - 2.0) <= P.goal_tolerance
    # stays near the path: every pose within 0.25 m of one of the two legs
    for px, py, _ in poses:
        d = min(math.hypot(px - min(max(px, 0.0), 2.0), py),
                math.hypot(px - 2.0, py - min(max(py, 0.0), 2.0)))
        assert d < 0.25
    assert "track" in modes
    # latched: keeps reporting arrived with zero command
    assert step(core, 999.0, poses[-1], L_PATH, 1, False, free_scan()) == (0.0, 0.0, "arrived")
    # speed limit respected: at least the straight-line distance at v_max; and no dawdling
    assert len(modes) * 0.2 >= (math.hypot(2.0, 2.0) - P.goal_tolerance) / P.v_max
    assert len(modes) * 0.2 <= 1.5 * 4.0 / P.v_max


def test_starting_sideways_turns_then_follows():
    core = ControllerCore(P)
    poses, modes = simulate(core, L_PATH, (0.0, 0.0, -math.pi / 2), steps=600)
    assert modes[0] == "rotate" and modes[-1] == "arrived"


def test_looks_around_once_at_the_start_then_follows():
    core = ControllerCore(ControllerParams())  # default: one full turn first
    th, t, turned, modes = 0.0, 0.0, 0.0, []
    for _ in range(200):
        v, w, mode = step(core, t, (0.0, 0.0, th), STRAIGHT, 1, False, free_scan())
        modes.append(mode)
        if mode != "look":
            break
        assert v == 0.0 and w > 0.0
        th, t, turned = th + w * 0.2, t + 0.2, turned + w * 0.2
    assert modes[0] == "look" and modes[-1] == "track"
    assert 2 * math.pi - 0.05 <= turned <= 2 * math.pi + 0.25
    # done once: a new plan does not look again; a clock reset (sim restart) does
    assert step(core, t + 0.2, (0.0, 0.0, th), STRAIGHT, 2, False, free_scan())[2] == "track"
    assert step(core, 0.0, (0.0, 0.0, th), STRAIGHT, 2, False, free_scan())[2] == "look"
    assert step(ControllerCore(P), 0.0, (0.0, 0.0, 0.0), STRAIGHT, 1, False,
                                    free_scan())[2] == "track"  # start_turn = 0: no look


def test_faces_the_goal_heading_before_arriving():
    core = ControllerCore(P)
    path = np.array([[0.0, 0.0], [1.0, 0.0]])
    pose = (1.0, 0.0, 0.0)  # at the end, facing +x; the plan wants the robot to face -y
    v, w, mode = step(core, 0.0, pose, path, 1, False, free_scan(), goal_heading=-math.pi / 2)
    assert mode == "face" and v == 0.0 and w < 0.0
    th, t = 0.0, 0.0
    for _ in range(50):
        t += 0.2
        th += w * 0.2
        v, w, mode = step(core, t, (1.0, 0.0, th), path, 1, False, free_scan(),
                                 goal_heading=-math.pi / 2)
        if mode == "arrived":
            break
    assert mode == "arrived" and abs(th + math.pi / 2) <= P.face_tolerance + 0.2
    # without a heading the same pose is arrived at once; a new heading re-opens the goal
    core2 = ControllerCore(P)
    assert step(core2, 0.0, pose, path, 1, False, free_scan())[2] == "arrived"
    assert step(core2, 0.2, pose, path, 1, False, free_scan(), goal_heading=math.pi)[2] == "face"


def test_new_plan_resets_progress_and_arrival():
    core = ControllerCore(P)
    poses, modes = simulate(core, STRAIGHT[:, :] * [0.4, 1.0], (0.0, 0.0, 0.0), steps=200)
    assert modes[-1] == "arrived"
    v, _, mode = step(core, 100.0, poses[-1], [[2.0, 0.0], [5.0, 0.0]], 2, False, free_scan())
    assert mode == "track" and v > 0.0
    assert core.snapshot()["plan_id"] == 2


def test_progress_never_goes_back():
    core = ControllerCore(P)
    step(core, 0.0, (3.0, 0.0, 0.0), STRAIGHT, 1, False, free_scan())
    s1 = core.snapshot()["progress"]
    step(core, 0.2, (1.0, 0.0, 0.0), STRAIGHT, 1, False, free_scan())  # pushed back
    assert core.snapshot()["progress"] >= s1


def test_recovery_never_backs_up_into_space_it_has_not_seen():
    core = ControllerCore(P)
    assert P.recovery_backup  # the default
    cmds = [step(core, k * 0.2, (0.0, 0.0, 0.0), STRAIGHT, 1, False,
                        scan_with([(0.25, 0.0)])) for k in range(int(P.stuck_time / 0.2) + 8)]
    assert all(v >= 0.0 for v, _, _ in cmds)  # never drives blind backwards
    assert core.backups_refused == 1 and cmds[-1][2] in ("recovery", "blocked")
    off = ControllerCore(ControllerParams(recovery_backup=False, start_turn=0.0))
    step(off, 0.0, (0.0, 0.0, math.pi), STRAIGHT, 1, False, free_scan())  # rear seen free
    cmds = [step(off, 0.2 + k * 0.2, (0.0, 0.0, 0.0), STRAIGHT, 1, False,
                 scan_with([(0.25, 0.0)])) for k in range(int(P.stuck_time / 0.2) + 8)]
    assert all(v >= 0.0 for v, _, _ in cmds) and off.backups_refused == 0  # off: turns only


def test_stuck_triggers_recovery_backup_then_turn():
    core = ControllerCore(P_BACKUP)
    step(core, -1.0, (0.0, 0.0, math.pi), STRAIGHT, 1, False, free_scan())  # saw behind
    pose = (0.0, 0.0, 0.0)
    t, dt = 0.0, 0.2
    mode = ""
    while t < P.stuck_time - 1e-9:  # commanding forward, but the robot does not move
        v, w, mode = step(core, t, pose, STRAIGHT, 1, False, free_scan())
        assert mode == "track"
        t += dt
    v, w, mode = step(core, t, pose, STRAIGHT, 1, False, free_scan())
    assert mode == "recovery" and v == pytest.approx(-P.recovery_speed) and w == 0.0
    # backs up for recovery_time, then resumes (heading already toward the path)
    t_end = t + P.recovery_time
    while t < t_end - 1e-9:
        v, _, mode = step(core, t, pose, STRAIGHT, 1, False, free_scan())
        assert mode == "recovery" and v < 0.0
        t += dt
    v, _, mode = step(core, t + dt, pose, STRAIGHT, 1, False, free_scan())
    assert mode == "track" and v > 0.0
    assert core.snapshot()["recoveries"] == 1


def test_blocked_for_long_triggers_recovery():
    core = ControllerCore(P_BACKUP)
    step(core, -1.0, (0.0, 0.0, math.pi), STRAIGHT, 1, False, free_scan())  # saw behind
    scan = scan_with([(0.25, 0.0)])
    modes = [step(core, k * 0.2, (0.0, 0.0, 0.0), STRAIGHT, 1, False, scan)[2]
             for k in range(int(P.stuck_time / 0.2) + 2)]
    assert modes[0] == "blocked" and modes[-1] == "recovery"


def test_recovery_skips_backup_when_rear_is_blocked():
    core = ControllerCore(P)
    r = np.full(361, 8.0)
    r[0] = 0.3  # return straight behind
    blocked_rear = Scan(r, -math.pi, math.radians(1.0), 0.02, 8.0)
    path = [[0.0, 0.0], [0.0, 3.0]]  # to the left: needs turning
    pose = (0.0, 0.0, 0.0)
    # stand still while "rotating" (wedged): no progress -> recovery, which may not back up
    out = [step(core, k * 0.2, pose, path, 1, False, blocked_rear)
           for k in range(int(P.stuck_time / 0.2) + 2)]
    assert out[-1][2] == "recovery"
    assert out[-1][0] == 0.0 and out[-1][1] > 0.0


def test_moving_robot_is_not_stuck():
    core = ControllerCore(P)
    _, modes = simulate(core, [[0.0, 0.0], [20.0, 0.0]], (0.0, 0.0, 0.0), steps=150)
    assert "recovery" not in modes


def test_clock_going_back_resets_timers():
    core = ControllerCore(P)
    for k in range(10):
        step(core, 100.0 + k * 0.2, (0.0, 0.0, 0.0), STRAIGHT, 1, False, free_scan())
    _, _, mode = step(core, 0.0, (0.0, 0.0, 0.0), STRAIGHT, 1, False, free_scan())
    assert mode == "track"


def test_deterministic():
    a, b = ControllerCore(P), ControllerCore(P)
    pa, ma = simulate(a, L_PATH, (0.1, -0.1, 0.3), steps=400)
    pb, mb = simulate(b, L_PATH, (0.1, -0.1, 0.3), steps=400)
    assert pa == pb and ma == mb


def test_single_waypoint_path():
    core = ControllerCore(P)
    poses, modes = simulate(core, [[1.0, 0.5]], (0.0, 0.0, 0.0), steps=200)
    assert modes[-1] == "arrived"


def test_snapshot_is_json():
    core = ControllerCore(P)
    step(core, 0.0, (0.0, 0.0, 0.0), L_PATH, 1, False, free_scan())
    snap = json.loads(json.dumps(core.snapshot(), allow_nan=False))
    assert snap["mode"] == "track" and snap["plan_id"] == 1


def test_params_validation():
    with pytest.raises(ValueError):
        load_params(overrides=["controller.slow_distance=0.1"])
    with pytest.raises(ValueError):
        load_params(overrides=["controller.slow_min_scale=0"])
    assert load_params().controller == ControllerParams()
