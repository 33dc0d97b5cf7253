"""Simulator core: pymunk differential-drive robot, 2D laser, odometry, watchdog (DESIGN §5).

Pure: no clock reads, no I/O. Time advances only by :meth:`SimCore.step` (one physics step of
``1 / params.physics_hz`` seconds); randomness comes from the ``rng`` passed in, so the same
world, parameters, seed and command sequence give identical scans and poses.
"""

from __future__ import annotations

import math

import numpy as np
import pymunk

from topoexplore.common.domain import Odom, Pose, Scan
from topoexplore.common.params import LaserParams, RobotParams, SimParams
from topoexplore.sim.world import World

__all__ = ["SimError", "SimCore", "box_vertices", "beam_angles"]

# modules whose WARM kernels the simulator runs (common.warm): none; sim.world's kernels make
# the truth masks, which the tools compute (run, bench), not the simulator
WARM_MODULES: tuple[str, ...] = ()

WALL_TYPE = 1  # pymunk collision types
ROBOT_TYPE = 2
ROBOT_CATEGORY = 0b10  # pymunk shape-filter category of the robot (the laser ignores it)
ROBOT_MASS = 10.0  # [kg] only matters against pushing; walls are static
COLLISION_SLOP = 0.002  # [m] allowed overlap before pymunk pushes shapes apart (default 0.1)


class SimError(ValueError):
    """Bad argument to the simulator core."""


def box_vertices(center, size, angle: float) -> list[tuple[float, float]]:
    """Corners [m] of a rectangle (centre, (w, h), angle [rad]), counter-clockwise."""
    cx, cy = center
    hx, hy = size[0] / 2, size[1] / 2
    ca, sa = math.cos(angle), math.sin(angle)
    return [(cx + ca * u - sa * v, cy + sa * u + ca * v)
            for u, v in ((-hx, -hy), (hx, -hy), (hx, hy), (-hx, hy))]


def beam_angles(beams: int, fov: float) -> tuple[float, float]:
    """(angle_min, angle_increment) [rad] of a scan of ``beams`` beams centred on the heading:
    the first and last beams at the edges of the field of view, or, for a full turn, evenly
    round it (the last beam one step short of the first, as a 360 deg lidar reports)."""
    if fov >= 2.0 * math.pi - 1e-9:
        return -math.pi, 2.0 * math.pi / beams
    return -fov / 2.0, fov / (beams - 1)


class SimCore:
    """One robot in one static world.

    Robot: pymunk dynamic circle (radius ``robot.radius``, infinite moment). Each step
    the body velocity is set from the latest command in the body frame (differential drive),
    so the contact solver really stops it at walls. Contacts with static shapes are counted:
    going from touching nothing to touching something is one collision.
    """

    def __init__(self, world: World, params: SimParams, rng: np.random.Generator,
                 robot: RobotParams | None = None, laser: LaserParams | None = None):
        if not isinstance(world, World):
            raise SimError(f"world must be a sim.world.World (got {type(world).__name__})")
        if not isinstance(rng, np.random.Generator):
            raise SimError(f"rng must be a numpy Generator (got {type(rng).__name__})")
        self.world = world
        self.params = params
        self.robot = robot or RobotParams()
        self.laser = laser or LaserParams()
        self._rng = rng
        self._odom_rng = np.random.default_rng(rng.integers(0, 2**63 - 1))
        self._dt = 1.0 / params.physics_hz  # [s]
        self._steps = 0

        space = pymunk.Space()
        space.gravity = (0.0, 0.0)
        sb = space.static_body
        shapes: list[pymunk.Shape] = []
        for a, b in world.segments:
            shapes.append(pymunk.Segment(sb, a, b, world.wall_thickness))
        for c, r in world.circles:
            shapes.append(pymunk.Circle(sb, r, offset=c))
        for c, s, ang in world.boxes:
            shapes.append(pymunk.Poly(sb, box_vertices(c, s, ang)))
        for sh in shapes:
            sh.collision_type = WALL_TYPE
            sh.friction = 0.5
            sh.elasticity = 0.0
        space.add(*shapes)

        x, y, th = world.robot_pose
        r = self.robot.radius
        body = pymunk.Body(ROBOT_MASS, math.inf)
        body.position = (x, y)
        body.angle = th
        robot = pymunk.Circle(body, r)
        robot.collision_type = ROBOT_TYPE
        robot.friction = 0.5
        robot.elasticity = 0.0
        robot.filter = pymunk.ShapeFilter(categories=ROBOT_CATEGORY)
        # Drive: pymunk integrates positions *before* it solves velocities, so setting
        # body.velocity before space.step() would move the robot into walls unchecked. Instead
        # the command is imposed in the velocity phase (velocity_func); the contact solver then
        # corrects it and the next position update uses the corrected velocity, so walls
        # really stop the robot. Consequence: one physics step of actuation lag.
        body.velocity_func = self._drive
        space.add(body, robot)
        space.collision_slop = COLLISION_SLOP
        space.on_collision(ROBOT_TYPE, WALL_TYPE, begin=self._on_begin, separate=self._on_separate)
        self._space = space
        self._body = body
        self._laser_filter = pymunk.ShapeFilter(
            mask=pymunk.ShapeFilter.ALL_MASKS() ^ ROBOT_CATEGORY)

        lp = self.laser
        self.angle_min, self.angle_increment = beam_angles(lp.beams, lp.fov)  # [rad]
        self._beam_rel = self.angle_min + self.angle_increment * np.arange(lp.beams)

        self._cmd = (0.0, 0.0)  # [m/s, rad/s] active command
        self._cmd_time = 0.0  # [s] sim time of the latest command()
        self._meas = (0.0, 0.0)  # [m/s, rad/s] measured velocity after the last step
        self._odom = (float(x), float(y), float(th))
        self._odom_travel = 0.0  # [m] travel odometry integrated with error (its variance)
        self._touching = 0
        self.collisions = 0
        self.path_length = 0.0  # [m]
        self.watchdog_stops = 0
        self.stale_cmds = 0  # commands dropped: stamped too long ago or ahead of the clock
        self.clipped_cmds = 0  # commands beyond the robot's v_limit / w_limit

    # ---------------------------------------------------------------- contacts
    def _drive(self, body, gravity, damping, dt) -> None:
        """pymunk velocity_func: differential drive, velocity along the current heading."""
        v, w = self._cmd
        th = body.angle
        body.velocity = (v * math.cos(th), v * math.sin(th))
        body.angular_velocity = w  # a circle turning in place cannot hit anything

    def _on_begin(self, arbiter, space, data) -> None:
        if self._touching == 0:
            self.collisions += 1
        self._touching += 1

    def _on_separate(self, arbiter, space, data) -> None:
        self._touching = max(self._touching - 1, 0)

    # ---------------------------------------------------------------- state
    @property
    def time(self) -> float:
        """[s] sim time."""
        return self._steps * self._dt

    @property
    def steps(self) -> int:
        """Physics steps since the start (of the first run, after a resume)."""
        return self._steps

    @property
    def in_contact(self) -> bool:
        """The robot touches a static shape now."""
        return self._touching > 0

    def truth_pose(self) -> Pose:
        """Ground-truth pose (x [m], y [m], theta [rad] in (-pi, pi])."""
        b = self._body
        return Pose(float(b.position.x), float(b.position.y), _wrap(float(b.angle)))

    def odom_pose(self) -> Pose:
        """Odometry pose in the map frame: the truth unless odometry error is on
        (``odom_drift``, ``odom_drift_heading``, ``odom_slip``)."""
        if not self._odom_error:
            return self.truth_pose()
        x, y, th = self._odom
        return Pose(x, y, _wrap(th))

    def odom(self) -> Odom:
        """Odometry: pose and measured velocity."""
        return Odom(self.odom_pose(), *self._meas)

    def _drift_rates(self) -> tuple[float, float]:
        """The odometry random walks: translation [m/sqrt(m)], heading [rad/sqrt(m)] (the
        heading one defaults to the translation one)."""
        k = self.params.odom_drift
        return k, k if self.params.odom_drift_heading is None else self.params.odom_drift_heading

    def odom_covariance(self) -> list[float]:
        """The covariance of :meth:`odom_pose` as the drift model has it (row-major 6 x 6 over
        x, y, z, roll, pitch, yaw, as nav_msgs/Odometry carries it): odom_drift^2 x travel
        [m^2] in x and in y, odom_drift_heading^2 x travel [rad^2] in yaw, travel counted as
        the drift counts it. Zero with perfect odometry. Not in it: wheel slip, and the
        position error a heading error grows into."""
        k, kh = self._drift_rates()
        cov = [0.0] * 36
        cov[0] = cov[7] = k * k * self._odom_travel
        cov[35] = kh * kh * self._odom_travel
        return cov

    def velocity(self) -> tuple[float, float]:
        """Measured (v [m/s] along the heading, w [rad/s]) after the last step."""
        return self._meas

    # ---------------------------------------------------------------- checkpoints
    def checkpoint(self) -> dict[str, np.ndarray]:
        """What a restarted simulator needs to go on with the same robot: the pose, the
        odometry, the clock and the counters (issue 14: one clock across restarts)."""
        x, y, th = self.truth_pose()
        return {"sim_world": np.array(self.world.name),
                "sim_pose": np.array([x, y, th], np.float64),
                "sim_odom": np.array(self._odom, np.float64),
                "sim_path": np.array([self.path_length], np.float64),
                "sim_odom_travel": np.array([self._odom_travel], np.float64),
                "sim_counts": np.array([self._steps, self.collisions, self.watchdog_stops,
                                        self.stale_cmds, self.clipped_cmds], np.int64)}

    def resume(self, ck: dict[str, np.ndarray]) -> None:
        """Go on from a :meth:`checkpoint` of this world: the robot stands at its pose,
        at rest, and the clock and counters continue. SimError if it is not one."""
        try:
            world = str(ck["sim_world"])
            pose = np.asarray(ck["sim_pose"], np.float64)
            odom = np.asarray(ck["sim_odom"], np.float64)
            path = np.asarray(ck["sim_path"], np.float64)
            counts = np.asarray(ck["sim_counts"])
        except KeyError as exc:
            raise SimError(f"checkpoint has no {exc.args[0]!r}") from None
        if world != self.world.name:
            raise SimError(f"checkpoint of world {world!r}, not {self.world.name!r}")
        if pose.shape != (3,) or odom.shape != (3,) or path.shape != (1,) \
                or counts.shape != (5,) or counts.dtype.kind != "i" or (counts < 0).any():
            raise SimError("checkpoint arrays have the wrong types or shapes")
        if not (np.isfinite(pose).all() and np.isfinite(odom).all() and np.isfinite(path).all()
                and path[0] >= 0.0):
            raise SimError("checkpoint holds non-finite numbers")
        self._body.position = (float(pose[0]), float(pose[1]))
        self._body.angle = float(pose[2])
        self._body.velocity = (0.0, 0.0)
        self._body.angular_velocity = 0.0
        self._space.reindex_shapes_for_body(self._body)
        self._odom = (float(odom[0]), float(odom[1]), float(odom[2]))
        self.path_length = float(path[0])
        travel = np.asarray(ck.get("sim_odom_travel", [0.0]), np.float64)  # older: none
        self._odom_travel = float(travel[0]) if travel.shape == (1,) and np.isfinite(
            travel[0]) and travel[0] >= 0.0 else 0.0
        (self._steps, self.collisions, self.watchdog_stops, self.stale_cmds,
         self.clipped_cmds) = (int(v) for v in counts)
        self._cmd, self._cmd_time, self._meas = (0.0, 0.0), self.time, (0.0, 0.0)

    # ---------------------------------------------------------------- control
    def command(self, v: float, w: float, stamp: float | None = None) -> bool:
        """Set the latest cmd_vel (clipped to v_limit / w_limit) and reset the watchdog.

        A command stamped (sim time [s]) more than ``cmd_max_age`` before now, or after now, is
        stale: dropped and counted, and False is returned. ``stamp=None``: not checked (the
        core's own callers)."""
        try:
            v, w = float(v), float(w)
        except (TypeError, ValueError):
            raise SimError(f"command needs two numbers (got {v!r}, {w!r})") from None
        if not (math.isfinite(v) and math.isfinite(w)):
            raise SimError(f"command must be finite (got v={v}, w={w})")
        if stamp is not None and not (self.time - self.params.cmd_max_age <= stamp
                                      <= self.time):
            self.stale_cmds += 1
            return False
        r = self.robot
        cmd = (min(max(v, -r.v_limit), r.v_limit), min(max(w, -r.w_limit), r.w_limit))
        if cmd != (v, w):
            self.clipped_cmds += 1
        self._cmd = cmd
        self._cmd_time = self.time
        return True

    def step(self) -> None:
        """Advance one physics step of 1 / physics_hz seconds."""
        if self.time - self._cmd_time >= self.params.watchdog - 1e-9 and self._cmd != (0.0, 0.0):
            self._cmd = (0.0, 0.0)
            self.watchdog_stops += 1
        b = self._body
        x0, y0 = b.position
        th0 = b.angle
        self._space.step(self._dt)
        self._steps += 1
        x1, y1 = b.position
        th1 = b.angle
        dx, dy = x1 - x0, y1 - y0
        ds = math.hypot(dx, dy)
        self.path_length += ds
        vel = b.velocity
        self._meas = (vel.x * math.cos(th1) + vel.y * math.sin(th1), float(b.angular_velocity))
        if self._odom_error:
            ds, dth = dx * math.cos(th0) + dy * math.sin(th0), th1 - th0
            slip = self.params.odom_slip
            if slip > 0.0 and self._touching > 0:  # held: the wheels turn on the spot
                ds += slip * (self._cmd[0] * self._dt - ds)
                dth += slip * (self._cmd[1] * self._dt - dth)
            self._integrate_odom(ds, dth)

    @property
    def _odom_error(self) -> bool:
        p = self.params
        return p.odom_drift > 0.0 or bool(p.odom_drift_heading) or p.odom_slip > 0.0

    def _integrate_odom(self, ds: float, dth: float) -> None:
        """Odometry with random-walk drift: per step, variance drift^2 * |travel| in
        translation [m] and heading_drift^2 * |travel| in heading [rad] (so the errors have
        sigma drift [m] and heading_drift [rad] after 1 m); travel counts a turn on the spot
        by the arc of the robot's rim."""
        k, kh = self._drift_rates()
        travel = abs(ds) + abs(dth) * self.robot.radius
        self._odom_travel += travel
        if travel > 0.0 and (k > 0.0 or kh > 0.0):
            root = math.sqrt(travel)
            e_s, e_t = self._odom_rng.normal(0.0, (k * root, kh * root))
            ds, dth = ds + float(e_s), dth + float(e_t)
        x, y, th = self._odom
        mid = th + dth / 2
        self._odom = (x + ds * math.cos(mid), y + ds * math.sin(mid), th + dth)

    # ---------------------------------------------------------------- laser
    def scan(self) -> Scan:
        """One laser scan: laser.beams ranges [m] from angle_min by angle_increment.

        Beams start at the laser (robot centre + laser.offset ahead), Gaussian noise of sigma
        range_noise on returns, no return -> range_max exactly, clipped to [range_min,
        range_max].
        """
        p = self.laser
        b = self._body
        x, y = b.position
        th = b.angle
        ox = x + p.offset * math.cos(th)
        oy = y + p.offset * math.sin(th)
        rmax = p.range_max
        ang = th + self._beam_rel
        ex = (ox + rmax * np.cos(ang)).tolist()
        ey = (oy + rmax * np.sin(ang)).tolist()
        query = self._space.segment_query_first
        flt = self._laser_filter
        origin = (ox, oy)
        alpha = np.ones(p.beams)
        for i in range(p.beams):
            info = query(origin, (ex[i], ey[i]), 0.0, flt)
            if info is not None:
                alpha[i] = info.alpha
        sigma = self.params.range_noise
        noise = self._rng.normal(0.0, sigma, p.beams) if sigma > 0 else 0.0
        hit = alpha < 1.0
        ranges = np.clip(np.where(hit, alpha * rmax + noise, rmax), p.range_min, rmax)
        return Scan(ranges, self.angle_min, self.angle_increment, p.range_min, rmax)


def _wrap(a: float) -> float:
    """Angle to (-pi, pi]."""
    a = math.fmod(a + math.pi, 2 * math.pi)
    if a <= 0:
        a += 2 * math.pi
    return a - math.pi
