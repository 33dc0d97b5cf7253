"""Controller core: pure pursuit path following with a laser safety stop (pure, no I/O).

DESIGN.md §4 "Controller": pure pursuit on the planned path with v <= v_max (paper §4: the
Pioneer 2DX moved at most 200 mm/s), rotate in place when the heading error is large, slow down
near obstacles, hard stop when the front sector of the latest scan is closer than a safety
distance, stop on an empty plan. The hard stop looks at the body's own path: the straight
corridor ahead (|y| <= radius) and the arc the command drives (the disc of the body swept
along it, arc_distance); returns within robot.body_margin beside that path only slow the
robot to slow_min_scale (a door as wide as the body plus twice the margin is passable).
Blocked, it creeps straight on when only the commanded arc was in the way, else turns on the
spot to the clear heading nearest its path's (:func:`clear_heading`). Additionally: progress
along the path is tracked so the lookahead point never goes back, and a stuck robot backs up
(only into space a recent scan saw free) and turns toward the path.

Modes: "idle" (no path), "done" (exploration over), "arrived" (end of path reached), "rotate"
(turning in place), "track" (pure pursuit), "slow" (pure pursuit, slowed by an obstacle ahead),
"blocked" (obstacle within the safety distance: v = 0, rotation allowed), "recovery" (backing
up, then turning toward the path).

Frames: pose (x [m], y [m], theta [rad]) in the map frame; scan angles in the robot frame with
the laser at the robot centre (x forward, y left, counter-clockwise).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from topoexplore.common.domain import Command, Pose, Route, Scan, wrap_angle
from topoexplore.common.params import ControllerParams, RobotParams

__all__ = [
    "ControllerError",
    "MODES",
    "wrap_angle",
    "clean_path",
    "path_arclength",
    "point_at",
    "project_on_path",
    "lookahead_point",
    "pure_pursuit",
    "front_distance",
    "arc_distance",
    "straight_distance",
    "clear_heading",
    "seen_free",
    "obstacle_scale",
    "ControllerCore",
]

BLOCKED_TURN = 0.25  # share of w_max a blocked robot turns at least toward a clear heading
#   (turn_w of a small turn would hardly move it)
WARM_MODULES: tuple[str, ...] = ()  # no numba kernels (common.warm)
MODES = ("idle", "done", "look", "rotate", "track", "slow", "blocked", "recovery", "face",
         "arrived")
_SAMPLE_STEP = 0.02  # [m] path sampling step of the lookahead search
REAR_EVERY = 0.5  # [s] one scan kept per this for the rear check (ControllerCore.rear_clear)


class ControllerError(ValueError):
    """Bad input to the controller."""


# --- path geometry --------------------------------------------------------------------------


def clean_path(waypoints) -> np.ndarray:
    """(n, 2) float array [m] without consecutive duplicates; raises on bad shape/values."""
    try:
        w = np.asarray(waypoints, dtype=np.float64)
    except (TypeError, ValueError):
        raise ControllerError("waypoints must be an (n, 2) array of numbers") from None
    if w.size == 0:
        return np.zeros((0, 2))
    if w.ndim != 2 or w.shape[1] != 2:
        raise ControllerError(f"waypoints must have shape (n, 2) (got {w.shape})")
    if not np.all(np.isfinite(w)):
        raise ControllerError("waypoints must be finite")
    if len(w) > 1:
        keep = np.ones(len(w), dtype=bool)
        keep[1:] = np.hypot(*(w[1:] - w[:-1]).T) > 1e-6
        w = w[keep]
    return w


def path_arclength(path: np.ndarray) -> np.ndarray:
    """Cumulative arc length [m] at each waypoint (0 at the first)."""
    if len(path) < 2:
        return np.zeros(len(path))
    return np.concatenate([[0.0], np.cumsum(np.hypot(*(path[1:] - path[:-1]).T))])


def point_at(path: np.ndarray, cum: np.ndarray, s) -> np.ndarray:
    """Point(s) [m] at arc length s [m] along the path (clamped to the ends); shape (..., 2)."""
    s = np.asarray(s, dtype=np.float64)
    if len(path) == 1:
        return np.broadcast_to(path[0], s.shape + (2,)).copy()
    i = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(path) - 2)
    seg = cum[i + 1] - cum[i]
    t = np.clip((s - cum[i]) / seg, 0.0, 1.0)[..., None]
    return path[i] + t * (path[i + 1] - path[i])


def project_on_path(path: np.ndarray, cum: np.ndarray, x: float, y: float, s_lo: float,
                    s_hi: float) -> tuple[float, float]:
    """Closest point of the path piece with arc length in [s_lo, s_hi] to (x, y).

    Returns (s [m], distance [m]); the earliest one on ties.
    """
    if len(path) == 1:
        return 0.0, float(math.hypot(path[0, 0] - x, path[0, 1] - y))
    total = float(cum[-1])
    s_lo = min(max(s_lo, 0.0), total)
    s_hi = min(max(s_hi, s_lo), total)
    i0 = min(max(int(np.searchsorted(cum, s_lo, side="right")) - 1, 0), len(path) - 2)
    i1 = min(int(np.searchsorted(cum, s_hi, side="left")), len(path) - 1)
    i1 = max(i1, i0 + 1)
    a, b = path[i0:i1], path[i0 + 1:i1 + 1]
    ab = b - a
    seg = cum[i0 + 1:i1 + 1] - cum[i0:i1]
    t = np.clip(((x - a[:, 0]) * ab[:, 0] + (y - a[:, 1]) * ab[:, 1]) / (seg * seg), 0.0, 1.0)
    s = np.clip(cum[i0:i1] + t * seg, s_lo, s_hi)
    pts = point_at(path, cum, s)
    d = np.hypot(pts[:, 0] - x, pts[:, 1] - y)
    k = int(np.argmin(d))
    return float(s[k]), float(d[k])


def lookahead_point(path: np.ndarray, cum: np.ndarray, x: float, y: float, s: float,
                    lookahead: float, window: float) -> tuple[np.ndarray, float]:
    """Pure pursuit goal point: the first path point from arc length s on that is at least
    ``lookahead`` [m] from the robot (searched up to s + window + lookahead); the end of the
    path when every point is closer. Returns (point, its arc length)."""
    total = float(cum[-1]) if len(cum) else 0.0
    hi = min(s + window + lookahead, total)
    ss = np.append(np.arange(s, hi, _SAMPLE_STEP), hi)
    pts = point_at(path, cum, ss)
    far = np.hypot(pts[:, 0] - x, pts[:, 1] - y) >= lookahead
    k = int(np.argmax(far)) if np.any(far) else len(ss) - 1
    return pts[k], float(ss[k])


def pure_pursuit(pose: tuple[float, float, float], target) -> tuple[float, float, float]:
    """Heading error alpha [rad], distance L [m] and curvature kappa = 2 sin(alpha) / L [1/m]
    of the circular arc from the pose to the target (Coulter 1992)."""
    x, y, th = pose
    dx, dy = float(target[0]) - x, float(target[1]) - y
    dist = math.hypot(dx, dy)
    if dist < 1e-9:
        return 0.0, 0.0, 0.0
    alpha = wrap_angle(math.atan2(dy, dx) - th)
    return alpha, dist, 2.0 * math.sin(alpha) / dist


# --- scan geometry --------------------------------------------------------------------------


def _scan_xy(scan: Scan) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Returns of a scan (REP-117, :meth:`Scan.returns`: an object too close to measure is
    one at range_min): (r, angle, x, y) in the robot frame."""
    r, a = scan.returns()
    return r, a, r * np.cos(a), r * np.sin(a)


def front_distance(scan: Scan | None, params: ControllerParams, half_width: float) -> float:
    """Range [m] of the nearest return in the front sector, inf if none.

    Front sector: |angle| <= front_half_angle and lateral offset |y| <= half_width [m]
    (robot.radius + robot.body_margin: a return beside the robot's swept corridor is not in
    the way).
    """
    if scan is None:
        return math.inf
    r, a, _, y = _scan_xy(scan)
    a = np.arctan2(np.sin(a), np.cos(a))
    m = (np.abs(a) <= params.front_half_angle) & (np.abs(y) <= half_width)
    return float(np.min(r[m])) if np.any(m) else math.inf


def arc_distance(scan: Scan | None, kappa: float, half_width: float) -> float:
    """Where the body meets the nearest return if it drives on along the arc of curvature
    kappa [1/m] (the command's w / v; 0 straight): the travel [m] until a disc of half_width
    [m] round the centre first touches a return, plus half_width, so that a return straight
    ahead at range r gives r, as front_distance does. inf if the arc meets none.

    front_distance looks along a straight corridor and within the front sector; a robot
    turning past a corner sweeps returns beside that corridor, and one beside its front
    (outside the sector) is in the way as soon as it moves (a held-back cluttered floor:
    turning right at 0.2 m/s into a return 0.19 m beside the body, seen at 74 deg). A return
    the disc already overlaps (a ragged wall it brushes) counts (travel 0) only while the arc
    leads nearer to it.

    Geometry (closed form): the centre moves on the circle of radius |1/kappa| round
    (0, 1/kappa); a return at distance D from that point is touched over the arc angles where
    the law of cosines gives a centre-to-return distance below half_width.
    """
    if scan is None:
        return math.inf
    _, _, px, py = _scan_xy(scan)
    rho = float(half_width)
    if px.size == 0 or rho <= 0.0:
        return math.inf
    if abs(kappa) < 1e-6:  # straight on: the corridor |y| < rho ahead of the centre
        m = (px > 0.0) & (np.abs(py) < rho)
        if not np.any(m):
            return math.inf
        ell = px[m] - np.sqrt(rho * rho - py[m] ** 2)
        return float(np.min(np.maximum(ell, 0.0))) + rho
    big_r = 1.0 / kappa  # [m] signed turning radius; the centre of the turn is (0, big_r)
    qx, qy = px, py - big_r
    dist = np.hypot(qx, qy)  # [m] return to the centre of the turn
    ar = abs(big_r)
    m = np.abs(dist - ar) < rho  # the body's annulus holds the return
    if not np.any(m):
        return math.inf
    qx, qy, dist = qx[m], qy[m], dist[m]
    psi = np.arctan2(qy, qx)
    # angle travelled round the turn to the return's own bearing, in [0, 2 pi)
    delta = np.mod(psi + math.pi / 2, 2 * math.pi) if kappa > 0 else np.mod(
        math.pi / 2 - psi, 2 * math.pi)
    with np.errstate(divide="ignore", invalid="ignore"):
        cphi = (ar * ar + dist * dist - rho * rho) / (2.0 * ar * dist)
    phi = np.arccos(np.clip(np.nan_to_num(cphi, nan=-1.0), -1.0, 1.0))  # contact half-angle
    ell = ar * (delta - phi)  # [m] travel to the first contact
    inside = (delta - phi <= 0.0) | (delta + phi >= 2 * math.pi)  # touched already ...
    ahead = (delta > 1e-9) & (delta < math.pi)  # ... and the arc leads nearer to it
    ell = np.where(inside, np.where(ahead, 0.0, np.inf), ell)
    best = float(np.min(ell))
    return best + rho if math.isfinite(best) else math.inf


def seen_free(px: np.ndarray, py: np.ndarray, pose: Pose, scan: Scan,
              margin: float = 0.05) -> np.ndarray:
    """Which points (px, py) [m] (the pose's frame) the scan taken at pose saw free (bool): a
    beam of the scan points at the point and ran at least ``margin`` [m] past it before its
    return (no return: to range_max). Points outside the beams' angles, or behind a beam
    that read nothing usable (NaN, too close), were not seen."""
    dx, dy = np.asarray(px, float) - pose[0], np.asarray(py, float) - pose[1]
    d = np.hypot(dx, dy)
    n, inc = scan.beams, scan.angle_increment
    k = np.rint(np.mod(np.arctan2(dy, dx) - pose[2] - scan.angle_min, 2 * math.pi) / inc
                ).astype(np.int64)  # the bearing's beam, counted from angle_min
    if n * abs(inc) >= 2 * math.pi - 1e-6:  # a full circle: the last gap closes on beam 0
        k = np.where(k >= n, k - n, k)
    ok = (k >= 0) & (k < n) & (inc > 0)
    r = np.asarray(scan.ranges, np.float64)
    reach = np.where(np.isnan(r) | np.isneginf(r) | (r < scan.range_min), 0.0,
                     np.minimum(r, scan.range_max))  # REP-117: +Inf, >= range_max: free to max
    out = np.zeros(d.shape, bool)
    out[ok] = d[ok] + margin <= reach[k[ok]]
    return out


def straight_distance(scan: Scan | None, params: ControllerParams, half_width: float,
                      turn: float = 0.0) -> float:
    """How far the way straight on is clear [m] after turning on the spot by turn [rad]
    (counter-clockwise): the nearer of :func:`front_distance` and :func:`arc_distance` with
    kappa 0, as :meth:`ControllerCore._pursue` judges the way ahead."""
    if scan is None:
        return math.inf
    turned = dataclasses.replace(scan, angle_min=scan.angle_min - turn)  # the robot's frame then
    return min(front_distance(turned, params, half_width), arc_distance(turned, 0.0, half_width))


def clear_heading(scan: Scan | None, params: ControllerParams, radius: float,
                  half_width: float, alpha: float, step: float = math.radians(2.5)
                  ) -> float | None:
    """The turn [rad] (counter-clockwise, from the robot's heading) to the heading nearest
    the path's (alpha [rad] off the heading) whose way straight on is clear beyond
    safety_distance (:func:`straight_distance`), tried in steps of step [rad] out to
    rotate_angle either side of the path's heading: first with the body margin (half_width
    [m]), then with the body alone (radius [m]); the path's own heading first. None: none.

    What a blocked robot turns to. Turning toward the path alone left one stuck for good when
    it already faced the path: on a held-back cluttered SLAM map (cluttered-s1-24x22-n2) the
    stair-step corner of a box lay at the body's edge, 0.2 m beside its heading, and the
    laser's noise put its returns inside the corridor every few scans; the robot stood
    "blocked" with nothing to turn, the planner learned a blockage there, twice, and called the
    map done with 6 % of it unseen."""
    n = int(params.rotate_angle / step)
    offsets = np.concatenate([[0.0], np.stack([np.arange(1, n + 1) * step,
                                               -np.arange(1, n + 1) * step], 1).ravel()])
    for hw in (half_width, radius):
        for off in offsets:
            if straight_distance(scan, params, hw, alpha + off) >= params.safety_distance:
                return float(alpha + off)
    return None


def obstacle_scale(d_front: float, params: ControllerParams) -> float:
    """Speed factor for the nearest front return d_front [m]: 1 beyond slow_distance, falling
    linearly to slow_min_scale at safety_distance (and 0 below it: hard stop)."""
    if d_front < params.safety_distance:
        return 0.0
    span = params.slow_distance - params.safety_distance
    if span <= 0.0 or d_front >= params.slow_distance:
        return 1.0
    f = (d_front - params.safety_distance) / span
    return params.slow_min_scale + (1.0 - params.slow_min_scale) * f


# --- the stateful core ----------------------------------------------------------------------


class ControllerCore:
    """Path follower state: current path and progress, rotate/recovery phases, stuck timer."""

    def __init__(self, params: ControllerParams, robot: RobotParams | None = None):
        self.params = params
        robot = RobotParams() if robot is None else robot
        self.radius = robot.radius  # [m]
        self.half_width = robot.radius + robot.body_margin  # [m] the swept corridor
        self.plan_id: int | None = None
        self.stale_plan_steps = 0  # steps stopped for want of a fresh plan (plan_timeout)
        self.path = np.zeros((0, 2))
        self._raw = np.zeros((0, 2))
        self.cum = np.zeros(0)
        self.s = 0.0  # [m] progress along the path (never decreases for one path)
        self.arrived = False
        self.mode = "idle"
        self.cmd = (0.0, 0.0)
        self._t_last = -math.inf
        self._rotating = False
        self._rot_dir = 0.0
        self._ref: tuple[float, float, float, float] | None = None  # t, x, y, theta of progress
        self._recovery: str | None = None  # None | "backup" | "turn"
        self._rec_start = 0.0  # [s]
        self.recoveries = 0
        self.backups_refused = 0  # recoveries that turned only: the rear not seen free
        self._seen: list[tuple[float, Pose, Scan]] = []  # (t, pose, scan): the rear check's
        self.front = math.inf  # [m] nearest return in the body's path ahead (stops) ...
        self.front_margin = math.inf  # [m] ... within body_margin beside it (slows)
        self.target: tuple[float, float] | None = None
        self.heading_error = 0.0  # [rad]
        self.goal_heading: float | None = None  # [rad] of the current path
        self._look_left = params.start_turn  # [rad] still to turn at the start (look around)
        self._look_th: float | None = None  # [rad] heading at the previous look step

    # -- helpers --

    def _set_path(self, plan_id: int, raw: np.ndarray) -> None:
        self.plan_id = plan_id
        self._raw = raw
        self.path = clean_path(raw)
        self.cum = path_arclength(self.path)
        self.s = 0.0
        self.arrived = False
        self._rotating = False
        self._ref = None

    def _out(self, v: float, w: float, mode: str, moving: bool, t: float, pose) -> Command:
        if not moving:
            self._ref = None
            self._recovery = None
            self._rotating = False
        elif self._ref is None:
            self._ref = (t, pose[0], pose[1], pose[2])
        self.mode = mode
        self.cmd = (float(v), float(w))
        return Command(float(v), float(w), mode)

    def _turn_w(self, alpha: float) -> float:
        p = self.params
        return float(np.clip(p.heading_gain * alpha, -p.w_max, p.w_max))

    def _take_route(self, route: Route | None) -> None:
        """A new path when the plan id, the waypoints or the goal heading changed."""
        raw = route.waypoints if route is not None else np.zeros((0, 2))
        plan_id = route.plan_id if route is not None else -1
        heading = route.goal_heading if route is not None else None
        if plan_id != self.plan_id or raw.shape != self._raw.shape or not np.array_equal(
                raw, self._raw) or heading != self.goal_heading:
            self._set_path(int(plan_id), raw)
            self.goal_heading = heading

    def _look(self, t: float, pose: Pose) -> Command | None:
        """Turn in place start_turn [rad] before the first path (a forward laser sees nothing
        behind); None once done."""
        if self._look_left <= 0.0:
            return None
        th = pose[2]
        if self._look_th is not None:
            self._look_left -= abs(wrap_angle(th - self._look_th))
        self._look_th = th
        if self._look_left > 1e-3:
            w_max = self.params.w_max
            w = w_max if self._look_left > 0.5 else max(0.5 * w_max, self._look_left)
            return self._out(0.0, w, "look", False, t, pose)
        self._look_left = 0.0
        return None

    def _at_end(self, t: float, pose: Pose) -> Command | None:
        """At the end of the path: face the goal heading, then report "arrived"."""
        p = self.params
        end = self.path[-1]
        if math.hypot(end[0] - pose[0], end[1] - pose[1]) > p.goal_tolerance or (
                float(self.cum[-1]) - self.s > p.search_window):
            return None
        err = 0.0 if self.goal_heading is None else wrap_angle(self.goal_heading - pose[2])
        self.heading_error = err
        if abs(err) > p.face_tolerance:
            w = math.copysign(max(abs(self._turn_w(err)), 0.5 * p.w_max), err)
            return self._out(0.0, w, "face", True, t, pose)
        self.arrived = True
        return self._out(0.0, 0.0, "arrived", False, t, pose)

    def _remember(self, t: float, pose: Pose, scan: Scan | None) -> None:
        """Keep a scan every REAR_EVERY s of the last recovery_memory s (the rear check's)."""
        keep = self.params.recovery_memory
        self._seen = [e for e in self._seen if 0.0 <= t - e[0] <= keep]
        if scan is not None and keep > 0.0 and (
                not self._seen or t - self._seen[-1][0] >= REAR_EVERY):
            self._seen.append((t, (float(pose[0]), float(pose[1]), float(pose[2])), scan))

    def rear_clear(self, pose: Pose, scan: Scan | None) -> bool:
        """May the robot back up? Only into space seen free: every sample point of the
        corridor it would sweep (behind the body, |y| <= half_width, up to the backing
        distance) lies where the current scan or one of the last recovery_memory s saw free
        space, and no return of those scans lies in the corridor. A robot with a forward 180°
        laser sees behind it only what it saw before it turned (or drove in), so it backs out
        the way it came and never into space it has not seen."""
        p = self.params
        hw = self.half_width
        reach = hw + p.recovery_speed * p.recovery_time  # [m] behind the centre
        xs = np.array([-(self.radius + 0.02), -0.5 * (self.radius + reach), -reach])
        ys = np.array([-hw, 0.0, hw])
        lx, ly = (v.ravel() for v in np.meshgrid(xs, ys))
        c, s_ = math.cos(pose[2]), math.sin(pose[2])
        wx, wy = pose[0] + c * lx - s_ * ly, pose[1] + s_ * lx + c * ly
        seen = np.zeros(lx.shape, bool)
        here = (float(pose[0]), float(pose[1]), float(pose[2]))
        for _t, at, sc in self._seen + ([(0.0, here, scan)] if scan is not None else []):
            seen |= seen_free(wx, wy, at, sc)
            r, a = sc.returns()
            hx = at[0] + r * np.cos(a + at[2]) - pose[0]
            hy = at[1] + r * np.sin(a + at[2]) - pose[1]
            bx, by = c * hx + s_ * hy, -s_ * hx + c * hy  # in the robot's frame now
            if np.any((bx < -1e-9) & (-bx <= reach) & (np.abs(by) <= hw)):
                return False
        return bool(seen.all())

    def _recover(self, t: float, pose: Pose, alpha: float, scan: Scan | None) -> Command | None:
        """Stuck detection (commanded motion, no progress for stuck_time) and the recovery:
        back up (if enabled and the rear was seen free: :meth:`rear_clear`), then turn to the
        path."""
        p = self.params
        x, y, th = pose
        if self._ref is not None and self._recovery is None:
            t0, x0, y0, th0 = self._ref
            if (math.hypot(x - x0, y - y0) > p.stuck_distance
                    or abs(wrap_angle(th - th0)) > p.stuck_angle):
                self._ref = (t, x, y, th)
            elif t - t0 >= p.stuck_time:
                self.recoveries += 1
                back = p.recovery_backup and self.rear_clear(pose, scan)
                self.backups_refused += p.recovery_backup and not back
                self._recovery = "backup" if back else "turn"
                self._rec_start = t
        if self._recovery == "backup":
            if t - self._rec_start < p.recovery_time:
                return self._out(-p.recovery_speed, 0.0, "recovery", True, t, pose)
            self._recovery = "turn"
            self._rec_start = t
        if self._recovery == "turn":
            if abs(alpha) > 0.5 * p.rotate_angle and t - self._rec_start < p.recovery_time:
                return self._out(0.0, self._turn_w(alpha), "recovery", True, t, pose)
            self._recovery = None
            self._ref = (t, x, y, th)
        return None

    def _rotate(self, t: float, pose: Pose, alpha: float) -> Command | None:
        """Rotate in place while the heading error is large (with hysteresis)."""
        p = self.params
        if abs(alpha) > p.rotate_angle or (self._rotating and abs(alpha) > 0.5 * p.rotate_angle):
            if not self._rotating or abs(alpha) < math.pi - 0.3:
                self._rot_dir = 1.0 if alpha >= 0.0 else -1.0
            self._rotating = True
            w = self._rot_dir * max(abs(self._turn_w(alpha)), 0.5 * p.w_max)
            return self._out(0.0, w, "rotate", True, t, pose)
        self._rotating = False
        return None

    def _pursue(self, t: float, pose: Pose, alpha: float, kappa: float,
                scan: Scan | None) -> Command:
        """Pure pursuit at v_max, slowed near obstacles ahead, stopped by the safety distance;
        ahead is the straight corridor and the arc the command drives (arc_distance)."""
        p = self.params
        self.front = min(self.front, arc_distance(scan, kappa, self.radius))
        self.front_margin = min(self.front_margin, arc_distance(scan, kappa, self.half_width))
        scale = obstacle_scale(self.front, p)
        if scale <= 0.0:
            return self._blocked(t, pose, alpha, scan)
        # a return beside the body's path (within body_margin of it) slows to a creep, never
        # stops: the body passes it, and a gap of the body's width plus the margins is a door
        scale = min(scale, max(p.slow_min_scale, obstacle_scale(self.front_margin, p)))
        v = p.v_max * scale
        if abs(kappa) * v > p.w_max:
            v = p.w_max / abs(kappa)
        w = float(np.clip(v * kappa, -p.w_max, p.w_max))
        return self._out(v, w, "slow" if scale < 1.0 else "track", True, t, pose)

    def _blocked(self, t: float, pose: Pose, alpha: float, scan: Scan | None) -> Command:
        """A return within safety_distance on the body's path. Straight on clear (only the
        arc the command drives was in the way): creep straight on. Else turn on the spot (a
        circle: safe) to :func:`clear_heading`, the heading nearest the path's whose straight
        corridor is clear, within rotate_angle of the path's; none: toward the path."""
        p = self.params
        if straight_distance(scan, p, self.radius) >= p.safety_distance:
            return self._out(p.v_max * p.slow_min_scale, 0.0, "slow", True, t, pose)
        turn = clear_heading(scan, p, self.radius, self.half_width, alpha)
        if turn is None:
            return self._out(0.0, self._turn_w(alpha), "blocked", True, t, pose)
        w = math.copysign(max(abs(self._turn_w(turn)), BLOCKED_TURN * p.w_max), turn)
        return self._out(0.0, w, "blocked", True, t, pose)

    # -- public --

    def update(self, t: float, pose: Pose, route: Route | None, done: bool,
               scan: Scan | None, plan_age: float | None = None,
               plan_limit: float | None = None) -> Command:
        """One control step at time t [s] for the robot at pose (map frame).

        route: the path to follow (None or no waypoints = stop); a new plan_id, changed
        waypoints or a changed goal heading start it anew; at its end the robot turns to the
        route's goal_heading (mode "face", within face_tolerance) before reporting "arrived".
        done: exploration over. scan: the latest scan (robot frame), or None. plan_age: robot
        time [s] since the last plan message arrived (None: none yet); beyond plan_limit
        (default params.plan_timeout) the planner is taken for stalled and the robot stops
        (mode "stale-plan") until one comes.
        """
        if t < self._t_last:  # clock went back (sim restart): forget timers, look again
            self._ref = None
            self._recovery = None
            self._look_left, self._look_th = self.params.start_turn, None
        self._t_last = t
        self._remember(t, pose, scan)
        self.front = front_distance(scan, self.params, self.radius)
        self.front_margin = front_distance(scan, self.params, self.half_width)
        self._take_route(route)
        if bool(done):
            return self._out(0.0, 0.0, "done", False, t, pose)
        limit = self.params.plan_timeout if plan_limit is None else plan_limit
        if plan_age is not None and plan_age > limit:
            self.stale_plan_steps += 1
            return self._out(0.0, 0.0, "stale-plan", False, t, pose)
        look = self._look(t, pose)
        if look is not None:
            return look
        if len(self.path) == 0:
            return self._out(0.0, 0.0, "idle", False, t, pose)
        if self.arrived:
            return self._out(0.0, 0.0, "arrived", False, t, pose)
        x, y, _ = pose
        s_proj, _ = project_on_path(self.path, self.cum, x, y, self.s,
                                    self.s + self.params.search_window)
        self.s = max(self.s, s_proj)
        end = self._at_end(t, pose)
        if end is not None:
            return end
        target, _ = lookahead_point(self.path, self.cum, x, y, self.s, self.params.lookahead,
                                    self.params.search_window)
        self.target = (float(target[0]), float(target[1]))
        alpha, _, kappa = pure_pursuit(pose, target)
        self.heading_error = alpha
        cmd = self._recover(t, pose, alpha, scan)
        if cmd is None:
            cmd = self._rotate(t, pose, alpha)
        return cmd if cmd is not None else self._pursue(t, pose, alpha, kappa, scan)

    def snapshot(self) -> dict:
        """JSON-able controller state."""
        total = float(self.cum[-1]) if len(self.cum) else 0.0
        return {
            "mode": self.mode,
            "v": self.cmd[0],
            "w": self.cmd[1],
            "plan_id": self.plan_id,
            "stale_plan_steps": self.stale_plan_steps,
            "waypoints": int(len(self.path)),
            "path_length": total,
            "progress": self.s,
            "arrived": self.arrived,
            "target": list(self.target) if self.target is not None else None,
            "heading_error": self.heading_error,
            "goal_heading": self.goal_heading,
            "front": self.front if math.isfinite(self.front) else None,
            "front_margin": self.front_margin if math.isfinite(self.front_margin) else None,
            "recovery": self._recovery,
            "recoveries": self.recoveries,
            "backups_refused": self.backups_refused,
        }
