"""A stand-in for a real robot's drivers, written the way a driver author would write one:
zenoh and msgpack only, none of topoexplore's modules (issue 16, the foreign-driver test).

It is a differential-drive base with a 360 deg lidar in a two-room flat (walls as line
segments). On ``<prefix>/scan`` it publishes 400 beams all round at 10 Hz, +Inf where a beam
returns nothing within range_max (REP-117) and a few NaN readings; on ``<prefix>/odom``
odometry at 50 Hz, with drift if asked; from ``<prefix>/cmd_vel`` it takes commands, clipped
to its limits, dropped when stamped more than 1 s before its clock, and it stops when none
came for 0.5 s. It never drives into a wall: a step that would bring the body within its
radius of one is refused and counted as a collision. Its clock runs ``--speed`` times
faster than the wall clock. On SIGTERM or SIGINT it prints one JSON line (collisions, path
length, true pose, messages) and exits 0.

The messages are plain dicts written from the ROS 2 message docs (``sensor_msgs/LaserScan``,
``nav_msgs/Odometry``, ``geometry_msgs/Twist`` with a ``std_msgs/Header``), frames per
REP-105 (``laser``, ``odom`` -> ``base_link``). Of the stack's own header fields only the
scans carry ``seq`` (so the stack counts scans lost on the way); the rest is left out (read
as -1: the mapper numbers the scans itself).

    python tests/foreign_driver.py --connect tcp/127.0.0.1:7447 --prefix topoexplore/robot1
"""

from __future__ import annotations

import argparse
import json
import math
import random
import signal
import threading
import time

import msgpack
import zenoh

# the flat: 10 m x 7 m, a wall at x = 6 with a 1 m door, a box in the big room [m]
WALLS = [
    ((0.0, 0.0), (10.0, 0.0)), ((10.0, 0.0), (10.0, 7.0)), ((10.0, 7.0), (0.0, 7.0)),
    ((0.0, 7.0), (0.0, 0.0)),
    ((6.0, 0.0), (6.0, 3.0)), ((6.0, 4.0), (6.0, 7.0)),
    ((2.5, 4.5), (3.5, 4.5)), ((3.5, 4.5), (3.5, 5.5)), ((3.5, 5.5), (2.5, 5.5)),
    ((2.5, 5.5), (2.5, 4.5)),
]
START = (1.5, 1.5, 0.0)  # x, y [m], heading [rad]
BEAMS, RANGE_MIN, RANGE_MAX = 400, 0.1, 10.0  # the lidar: its own beam count, [m]
RADIUS, V_LIMIT, W_LIMIT = 0.2, 0.5, 1.5  # the base [m], [m/s], [rad/s]
ODOM_HZ, SCAN_HZ = 50.0, 10.0


def ray(x: float, y: float, a: float) -> float:
    """Distance [m] from (x, y) along heading a to the nearest wall, inf if none."""
    dx, dy = math.cos(a), math.sin(a)
    best = math.inf
    for (x1, y1), (x2, y2) in WALLS:
        ex, ey = x2 - x1, y2 - y1
        den = dx * ey - dy * ex
        if abs(den) < 1e-12:
            continue
        t = ((x1 - x) * ey - (y1 - y) * ex) / den  # along the ray
        u = ((x1 - x) * dy - (y1 - y) * dx) / den  # along the wall
        if t > 0.0 and 0.0 <= u <= 1.0:
            best = min(best, t)
    return best


def clearance(x: float, y: float) -> float:
    """Distance [m] from (x, y) to the nearest wall."""
    best = math.inf
    for (x1, y1), (x2, y2) in WALLS:
        ex, ey = x2 - x1, y2 - y1
        s = max(0.0, min(1.0, ((x - x1) * ex + (y - y1) * ey) / (ex * ex + ey * ey)))
        best = min(best, math.hypot(x - x1 - s * ex, y - y1 - s * ey))
    return best


def stamp(t: float) -> dict:
    """builtin_interfaces/Time from seconds."""
    ns = round(t * 1e9)
    return {"sec": ns // 1_000_000_000, "nanosec": ns % 1_000_000_000}


def header(t: float, frame_id: str, **ours: int) -> dict:
    """std_msgs/Header; ``ours``: the stack's seq / src_seq beside it (optional: -1 if left out)."""
    return {"stamp": stamp(t), "frame_id": frame_id, **ours}


def quaternion(yaw: float) -> dict:
    return {"x": 0.0, "y": 0.0, "z": math.sin(yaw / 2.0), "w": math.cos(yaw / 2.0)}


def vector3(x: float = 0.0, y: float = 0.0, z: float = 0.0) -> dict:
    return {"x": x, "y": y, "z": z}


class Robot:
    def __init__(self, drift: float, seed: int):
        self.x, self.y, self.th = START  # the truth
        self.ox, self.oy, self.oth = START  # what odometry says
        self.v = self.w = 0.0
        self.cmd = (0.0, 0.0, -math.inf)  # v, w, robot time it came
        self.t = 0.0  # [s] robot clock
        self.drift = drift  # relative error of odometry per metre and per radian
        self.rng = random.Random(seed)
        self.collisions = self.path = 0.0
        self.stale = self.clipped = self.cmds = 0
        self.lock = threading.Lock()

    def on_cmd(self, sample: zenoh.Sample) -> None:
        try:
            msg = msgpack.unpackb(sample.payload.to_bytes())  # geometry_msgs/Twist + header
            v, w = float(msg["linear"]["x"]), float(msg["angular"]["z"])
            st = msg["header"]["stamp"]
            stamp = int(st["sec"]) + int(st["nanosec"]) / 1e9
        except (ValueError, KeyError, TypeError):
            return
        if not (math.isfinite(v) and math.isfinite(w)):
            return
        with self.lock:
            self.cmds += 1
            if stamp < self.t - 1.0 or stamp > self.t + 1e-6:  # stale, or another clock
                self.stale += 1
                return
            cv, cw = max(-V_LIMIT, min(V_LIMIT, v)), max(-W_LIMIT, min(W_LIMIT, w))
            self.clipped += (cv, cw) != (v, w)
            self.cmd = (cv, cw, self.t)

    def step(self, dt: float) -> None:
        with self.lock:
            v, w, came = self.cmd
            if self.t - came > 0.5:  # the base's own watchdog
                v = w = 0.0
            self.t += dt
        nx = self.x + v * dt * math.cos(self.th)
        ny = self.y + v * dt * math.sin(self.th)
        if v != 0.0 and clearance(nx, ny) < RADIUS:
            self.collisions += 1  # refused: the bumper
            v = 0.0
            nx, ny = self.x, self.y
        self.path += math.hypot(nx - self.x, ny - self.y)
        self.x, self.y = nx, ny
        self.th = math.remainder(self.th + w * dt, 2 * math.pi)
        # odometry: the same motion with a relative error per metre / radian
        e = self.drift
        d, dth = abs(v) * dt, w * dt
        ov = v * (1.0 + self.rng.gauss(0.0, e)) if e else v
        odth = dth + (self.rng.gauss(0.0, e) * (abs(dth) + d) if e else 0.0)
        self.ox += ov * dt * math.cos(self.oth)
        self.oy += ov * dt * math.sin(self.oth)
        self.oth = math.remainder(self.oth + odth, 2 * math.pi)
        self.v, self.w = v, w

    def scan(self) -> list[float]:
        out = []
        for i in range(BEAMS):
            a = self.th - math.pi + i * 2 * math.pi / BEAMS
            r = ray(self.x, self.y, a)
            if self.rng.random() < 0.01:
                out.append(math.nan)  # a reading the lidar could not make
            elif r > RANGE_MAX:
                out.append(math.inf)  # REP-117: no return within range_max
            else:
                out.append(r + self.rng.gauss(0.0, 0.01))
        return out


def odometry(robot: Robot) -> dict:
    """nav_msgs/Odometry: the pose in odom, the twist in base_link. The ROS fields only: the
    stack's header.seq / src_seq are left out (read as -1)."""
    zeros = [0.0] * 36
    return {"header": header(robot.t, "odom"), "child_frame_id": "base_link",
            "pose": {"pose": {"position": vector3(robot.ox, robot.oy),
                              "orientation": quaternion(robot.oth)}, "covariance": zeros},
            "twist": {"twist": {"linear": vector3(robot.v), "angular": vector3(z=robot.w)},
                      "covariance": zeros}}


def laser_scan(robot: Robot, k: int) -> dict:
    """sensor_msgs/LaserScan, scan ``k``. Of the stack's own fields only header.seq is set
    (scans lost on the way are counted); src_seq is left out: the mapper numbers the scans."""
    inc = 2 * math.pi / BEAMS
    return {"header": header(robot.t, "laser", seq=k), "angle_min": -math.pi,
            "angle_max": -math.pi + (BEAMS - 1) * inc, "angle_increment": inc,
            "time_increment": 0.0, "scan_time": 1.0 / SCAN_HZ, "range_min": RANGE_MIN,
            "range_max": RANGE_MAX, "ranges": robot.scan(), "intensities": []}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--connect", required=True)
    ap.add_argument("--prefix", required=True, help="key prefix, e.g. topoexplore/robot1")
    ap.add_argument("--speed", type=float, default=1.0, help="robot clock / wall clock")
    ap.add_argument("--drift", type=float, default=0.0)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps([a.connect]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    robot = Robot(a.drift, a.seed)
    sent = {"scan": 0, "odom": 0}
    with zenoh.open(conf) as session:
        pub_scan = session.declare_publisher(f"{a.prefix}/scan")
        pub_odom = session.declare_publisher(f"{a.prefix}/odom")
        sub = session.declare_subscriber(f"{a.prefix}/cmd_vel", robot.on_cmd)
        dt, per_scan = 1.0 / ODOM_HZ, round(ODOM_HZ / SCAN_HZ)
        tick, t0 = 0, time.monotonic()
        while not stop.is_set():
            robot.step(dt)
            tick += 1
            odom = odometry(robot)
            pub_odom.put(msgpack.packb(odom))
            sent["odom"] += 1
            if tick % per_scan == 0:
                k = sent["scan"]
                scan = laser_scan(robot, k)
                pub_scan.put(msgpack.packb(scan))
                sent["scan"] += 1
            wait = t0 + tick * dt / a.speed - time.monotonic()
            if wait > 0:
                stop.wait(wait)
        sub.undeclare()
    print(json.dumps({"collisions": robot.collisions, "path_m": round(robot.path, 3),
                      "pose": [robot.x, robot.y, robot.th], "robot_time_s": round(robot.t, 2),
                      "cmds": robot.cmds, "stale_cmds": robot.stale, "sent": sent}), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
