"""Every message that crosses the bus, defined once.

Wire format: MessagePack maps with field names (msgspec structs, not array-like), so any plain
msgpack client (``msgpack.unpackb(raw)``) reads every message as nested dicts and lists. Bulk
grid data travels as a msgpack ``bin`` (bytes).

The shapes are the ROS 2 message definitions, field for field (``std_msgs/Header``,
``sensor_msgs/LaserScan``, ``nav_msgs/Odometry``, ``geometry_msgs/PoseStamped``,
``geometry_msgs/TransformStamped``, ``nav_msgs/OccupancyGrid``, ``nav_msgs/Path``; a velocity
command is ``geometry_msgs/Twist``'s ``linear``/``angular`` with a header beside them), so a
driver written from the ROS message docs is right. Our own fields live beside the ROS ones:
``header.seq`` (per publisher and key) and ``header.src_seq`` (the sequence number of the laser
scan the message derives from, so a stage can tell how fresh its input is and lockstep mode
can wait for it), the path's target fields, and the topology, reliability and status messages.

Conventions (REP-103/105): SI units, x forward, y left, angles counter-clockwise in radians,
planar poses as a quaternion about z (:func:`quaternion`, :func:`yaw_of`); frames ``map`` ->
``odom`` -> ``base_link`` -> ``laser``. Stamps are ``Time{sec, nanosec}`` (sim or wall time);
``header.time`` gives seconds as a float.

:func:`decode` validates strictly (types, lengths, finite numbers, sane sizes); every problem
raises the one error type :class:`MessageError`.
"""

from __future__ import annotations

import math
from typing import Any

import msgspec
import numpy as np

__all__ = [
    "MessageError",
    "Time",
    "Header",
    "stamp",
    "header",
    "Vector3",
    "Point",
    "Quaternion",
    "quaternion",
    "yaw_of",
    "GeoPose",
    "GeoTwist",
    "PoseWithCovariance",
    "TwistWithCovariance",
    "LaserScan",
    "Odometry",
    "PoseStamped",
    "Transform",
    "TransformStamped",
    "Twist",
    "MapMetaData",
    "OccupancyGrid",
    "TopoNode",
    "TopoEdge",
    "TopoGraph",
    "NodeReliability",
    "Reliability",
    "Path",
    "ExploreStatus",
    "SimStatus",
    "MESSAGE_TYPES",
    "encode",
    "decode",
]

# Sanity limits for decoded messages.
MAX_BEAMS = 10_000
MAX_GRID_CELLS = 25_000_000  # 5000 x 5000 cells (500 m x 500 m at 0.1 m)
MAX_NODES = 100_000
MAX_EDGES = 200_000
MAX_POINTS = 2_000_000  # all polyline points in one graph
MAX_WAYPOINTS = 100_000
MAX_STR = 256
MAX_COORD = 1.0e6  # [m]

NODE_KINDS = ("end", "branch", "corner")
EXPLORE_STATES = ("idle", "exploring", "done", "failed", "stuck")


class MessageError(ValueError):
    """A message could not be decoded or failed validation."""


class Time(msgspec.Struct, kw_only=True):
    """builtin_interfaces/Time."""

    sec: int  # [s]
    nanosec: int  # [ns], 0 <= nanosec < 1e9


class Header(msgspec.Struct, kw_only=True):
    """std_msgs/Header (``stamp``, ``frame_id``) and ours beside it: ``seq`` (per publisher
    and key, from 0; -1 = not counted) and ``src_seq`` (the scan this message derives from;
    -1 = none). A driver that fills only the ROS fields is read as seq -1, src_seq -1."""

    stamp: Time
    frame_id: str
    seq: int = -1
    src_seq: int = -1

    @property
    def time(self) -> float:
        """The stamp [s] as a float."""
        return self.stamp.sec + self.stamp.nanosec / 1e9


def stamp(t: float) -> Time:
    """[s] -> Time, to the nearest nanosecond (a negative time is clamped to 0)."""
    ns = max(0, round(t * 1e9))
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def header(seq: int, t: float, frame_id: str, src_seq: int = -1) -> Header:
    """A Header stamped ``t`` [s]."""
    return Header(stamp=stamp(t), frame_id=frame_id, seq=seq, src_seq=src_seq)


class Vector3(msgspec.Struct, kw_only=True):
    """geometry_msgs/Vector3."""

    x: float = 0.0
    y: float = 0.0
    z: float = 0.0


class Point(msgspec.Struct, kw_only=True):
    """geometry_msgs/Point [m]."""

    x: float = 0.0
    y: float = 0.0
    z: float = 0.0


class Quaternion(msgspec.Struct, kw_only=True):
    """geometry_msgs/Quaternion (x, y, z, w); identity by default."""

    x: float = 0.0
    y: float = 0.0
    z: float = 0.0
    w: float = 1.0


def quaternion(yaw: float) -> Quaternion:
    """A rotation of ``yaw`` [rad] about z (REP-103)."""
    return Quaternion(z=math.sin(yaw / 2.0), w=math.cos(yaw / 2.0))


def yaw_of(q: Quaternion) -> float:
    """The yaw [rad] of a quaternion, about z (REP-103; roll and pitch ignored)."""
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))


class GeoPose(msgspec.Struct, kw_only=True):
    """geometry_msgs/Pose."""

    position: Point
    orientation: Quaternion


class GeoTwist(msgspec.Struct, kw_only=True):
    """geometry_msgs/Twist: linear [m/s], angular [rad/s]."""

    linear: Vector3
    angular: Vector3


def _zeros36() -> list[float]:
    return [0.0] * 36


class PoseWithCovariance(msgspec.Struct, kw_only=True):
    """geometry_msgs/PoseWithCovariance (row-major 6x6: x, y, z, roll, pitch, yaw)."""

    pose: GeoPose
    covariance: list[float] = msgspec.field(default_factory=_zeros36)


class TwistWithCovariance(msgspec.Struct, kw_only=True):
    """geometry_msgs/TwistWithCovariance."""

    twist: GeoTwist
    covariance: list[float] = msgspec.field(default_factory=_zeros36)


class LaserScan(msgspec.Struct, kw_only=True):
    """sensor_msgs/LaserScan."""

    header: Header  # frame_id: the laser's frame
    angle_min: float  # [rad]
    angle_max: float  # [rad]
    angle_increment: float  # [rad]
    time_increment: float = 0.0  # [s] between measurements
    scan_time: float = 0.0  # [s] between scans
    range_min: float  # [m]
    range_max: float  # [m]
    ranges: list[float]  # [m]; REP-117: NaN invalid, +Inf or >= range_max no return, -Inf
    #   too close, < range_min invalid
    intensities: list[float] = []  # device-specific units; empty or one per range


class Odometry(msgspec.Struct, kw_only=True):
    """nav_msgs/Odometry: the pose in ``header.frame_id`` (odom), the twist in
    ``child_frame_id`` (base_link)."""

    header: Header
    child_frame_id: str = "base_link"
    pose: PoseWithCovariance
    twist: TwistWithCovariance


class PoseStamped(msgspec.Struct, kw_only=True):
    """geometry_msgs/PoseStamped (ground truth, the localizer's pose, a path's poses)."""

    header: Header
    pose: GeoPose


class Transform(msgspec.Struct, kw_only=True):
    """geometry_msgs/Transform."""

    translation: Vector3
    rotation: Quaternion


class TransformStamped(msgspec.Struct, kw_only=True):
    """geometry_msgs/TransformStamped: ``child_frame_id``'s pose in ``header.frame_id``
    (the localizer's map -> odom correction, REP-105)."""

    header: Header
    child_frame_id: str
    transform: Transform


class Twist(msgspec.Struct, kw_only=True):
    """geometry_msgs/Twist's fields (linear.x = v [m/s], angular.z = w [rad/s] for a planar
    base) with our header beside them: a velocity command carries its stamp."""

    header: Header
    linear: Vector3
    angular: Vector3


class MapMetaData(msgspec.Struct, kw_only=True):
    """nav_msgs/MapMetaData."""

    map_load_time: Time
    resolution: float  # [m/cell]
    width: int  # cells along x
    height: int  # cells along y
    origin: GeoPose  # world pose of cell (0, 0)'s corner


class OccupancyGrid(msgspec.Struct, kw_only=True):
    """nav_msgs/OccupancyGrid: int8 row-major, x fastest, -1 unknown, 0..100 occupancy
    (``data`` travels as one msgpack bin, not a list of ints)."""

    header: Header
    info: MapMetaData
    data: bytes  # width*height int8


class TopoNode(msgspec.Struct, kw_only=True):
    id: int
    kind: str  # "end" | "branch" | "corner"
    x: float  # [m]
    y: float  # [m]


class TopoEdge(msgspec.Struct, kw_only=True):
    a: int  # node id
    b: int  # node id
    points: list[list[float]]  # polyline [[x, y], ...] from a to b [m]
    length: float  # [m]
    clearance: float  # minimum distance to a non-free cell along the edge [m]


class TopoGraph(msgspec.Struct, kw_only=True):
    header: Header
    nodes: list[TopoNode]
    edges: list[TopoEdge]
    gone: list[int] = []  # ids that vanished since the previous update


class NodeReliability(msgspec.Struct, kw_only=True):
    id: int
    x: float  # [m]
    y: float  # [m]
    p: float  # position probability P (eq. 6)
    d: float  # distance index D (eq. 1)
    a: float  # angle index A (eq. 4)
    r_min: float  # [m] minimum observed distance (eq. 2), inf if never observed
    alpha_max: float  # [rad] circular spread of observation bearings (eq. 3)
    visible: bool  # observed in this update
    n_obs: int = 0  # observations since the history (re)started
    visited: bool = False  # robot came within the visit radius
    frontier: int = 0  # frontier cells the node's leaf chain owns (observations don't count;
    # as last worked out: only on updates where an observation could count)


class Reliability(msgspec.Struct, kw_only=True):
    header: Header
    nodes: list[NodeReliability]


class Path(msgspec.Struct, kw_only=True):
    """nav_msgs/Path (``poses``: the waypoints in the map frame, each facing the next; the
    last faces ``goal_heading`` if given) and ours beside it."""

    header: Header
    poses: list[PoseStamped]  # empty = stop
    target_id: int = -1
    target_x: float = 0.0  # [m]
    target_y: float = 0.0  # [m]
    strategy: str = ""
    plan_id: int = 0  # changes only when the path is replaced (new target or re-plan)
    goal_heading: float | None = None  # [rad] face this way at the end of the path (None:
    #   any heading); the frontier goal faces the unknown space it is meant to reveal


class ExploreStatus(msgspec.Struct, kw_only=True):
    header: Header
    state: str  # "idle" | "exploring" | "done" | "failed" | "stuck" (recovering, not finished)
    reason: str = ""
    strategy: str = ""
    target_id: int = -1
    target_p: float = 0.0
    candidates: int = 0  # at the last update that judged them all (every update without a
    #   target, every planner.replan_period while one is followed: docs/design.md)
    end_nodes: int = 0
    reliable: int = 0
    blacklisted: list[int] = []
    replans: int = 0


class SimStatus(msgspec.Struct, kw_only=True):
    header: Header
    world: str
    mode: str  # "lockstep" | "realtime"
    sim_time: float  # [s]
    steps: int
    collisions: int
    path_length: float  # [m] integrated ground-truth travel
    real_time_factor: float
    watchdog_stops: int = 0
    lockstep_timeouts: int = 0
    stale_cmds: int = 0  # cmd_vel dropped as stale by stamp (sim.cmd_max_age)
    clipped_cmds: int = 0  # cmd_vel beyond robot.v_limit / w_limit, clipped


MESSAGE_TYPES: dict[str, type] = {
    t.__name__: t
    for t in (
        LaserScan,
        Odometry,
        PoseStamped,
        TransformStamped,
        Twist,
        OccupancyGrid,
        TopoGraph,
        Reliability,
        Path,
        ExploreStatus,
        SimStatus,
    )
}

_encoder = msgspec.msgpack.Encoder()
_decoders = {t: msgspec.msgpack.Decoder(t) for t in MESSAGE_TYPES.values()}


def encode(msg: msgspec.Struct) -> bytes:
    """Encode a message struct to MessagePack bytes."""
    return _encoder.encode(msg)


def decode(raw: bytes | bytearray | memoryview, msg_type: type) -> Any:
    """Decode and validate; raise MessageError on any problem."""
    try:
        dec = _decoders[msg_type]
    except KeyError:
        raise MessageError(f"unknown message type {msg_type!r}") from None
    if len(raw) > 64 * 1024 * 1024:
        raise MessageError(f"{msg_type.__name__}: payload of {len(raw)} bytes is too large")
    try:
        msg = dec.decode(raw)
    except (msgspec.DecodeError, msgspec.ValidationError) as exc:
        raise MessageError(f"{msg_type.__name__}: {exc}") from None
    _VALIDATORS[msg_type](msg)
    return msg


# --- validation ----------------------------------------------------------------------------


def _fail(msg: Any, text: str) -> None:
    raise MessageError(f"{type(msg).__name__}: {text}")


def _finite(msg: Any, name: str, value: float, lo: float = -MAX_COORD, hi: float = MAX_COORD):
    if not math.isfinite(value):
        _fail(msg, f"{name} is not finite ({value})")
    if not lo <= value <= hi:
        _fail(msg, f"{name}={value} outside [{lo}, {hi}]")


def _header(msg: Any, h: Header | None = None, name: str = "header") -> None:
    h = msg.header if h is None else h
    if h.seq < -1 or h.seq > 2**62:
        _fail(msg, f"{name}.seq={h.seq} out of range")
    if h.src_seq < -1 or h.src_seq > 2**62:
        _fail(msg, f"{name}.src_seq={h.src_seq} out of range")
    _time(msg, f"{name}.stamp", h.stamp)
    if len(h.frame_id) > MAX_STR:
        _fail(msg, f"{name}.frame_id too long")


def _time(msg: Any, name: str, t: Time) -> None:
    if not 0 <= t.sec <= 10**12 or not 0 <= t.nanosec < 1_000_000_000:
        _fail(msg, f"{name}=({t.sec}, {t.nanosec}) not a time (sec 0..1e12, nanosec 0..1e9)")


def _vec(msg: Any, name: str, v: Vector3 | Point, lim: float = MAX_COORD) -> None:
    _finite(msg, f"{name}.x", v.x, -lim, lim)
    _finite(msg, f"{name}.y", v.y, -lim, lim)
    _finite(msg, f"{name}.z", v.z, -lim, lim)


def _quat(msg: Any, name: str, q: Quaternion) -> None:
    for k in ("x", "y", "z", "w"):
        _finite(msg, f"{name}.{k}", getattr(q, k), -1.01, 1.01)
    norm = math.sqrt(q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w)
    if abs(norm - 1.0) > 1e-3:
        _fail(msg, f"{name} is not a unit quaternion (norm {norm:.6g})")


def _pose(msg: Any, name: str, p: GeoPose) -> None:
    _vec(msg, f"{name}.position", p.position)
    _quat(msg, f"{name}.orientation", p.orientation)


def _cov(msg: Any, name: str, c: list[float]) -> None:
    if len(c) != 36:
        _fail(msg, f"{name} has {len(c)} values, expected 36 (6x6)")
    if not all(math.isfinite(v) for v in c):
        _fail(msg, f"{name} is not finite")


def _v_scan(m: LaserScan) -> None:
    _header(m)
    n = len(m.ranges)
    if not 1 <= n <= MAX_BEAMS:
        _fail(m, f"{n} ranges (expected 1..{MAX_BEAMS})")
    _finite(m, "angle_min", m.angle_min, -2 * math.pi, 2 * math.pi)
    _finite(m, "angle_max", m.angle_max, -2 * math.pi, 2 * math.pi)
    _finite(m, "angle_increment", m.angle_increment, -math.pi, math.pi)
    if m.angle_increment == 0.0 and n > 1:
        _fail(m, "angle_increment is zero")
    if abs(m.angle_increment) * (n - 1) > 2 * math.pi + 1e-6:
        _fail(m, f"{n} beams at {m.angle_increment} rad span more than a turn")
    # angle_max is angle_min + (n - 1) * angle_increment; drivers that count n increments (or
    # round in float32) are read as well: the beam angles come from angle_min and the increment
    end = m.angle_min + (n - 1) * m.angle_increment
    if abs(m.angle_max - end) > abs(m.angle_increment) + 1e-3:
        _fail(m, f"angle_max={m.angle_max:.6g} disagrees with angle_min + (n - 1) * "
                 f"angle_increment = {end:.6g}")
    _finite(m, "time_increment", m.time_increment, -1.0, 1.0)
    _finite(m, "scan_time", m.scan_time, 0.0, 100.0)
    _finite(m, "range_min", m.range_min, 0.0, 1000.0)
    _finite(m, "range_max", m.range_max, 0.0, 1000.0)
    if m.range_max <= m.range_min:
        _fail(m, "range_max must exceed range_min")
    if m.intensities and len(m.intensities) != n:
        _fail(m, f"{len(m.intensities)} intensities for {n} ranges (expected none or one each)")
    # ranges as REP-117 reads them, any float goes: NaN (no valid reading), +Inf (no return
    # within range_max), -Inf (an object closer than range_min), finite values outside
    # [range_min, range_max] (invalid: discarded); range_max itself is no return too (what
    # many drivers and our simulator send). common.domain.Scan says what each use makes of them.


def _v_odom(m: Odometry) -> None:
    _header(m)
    if len(m.child_frame_id) > MAX_STR:
        _fail(m, "child_frame_id too long")
    _pose(m, "pose.pose", m.pose.pose)
    _cov(m, "pose.covariance", m.pose.covariance)
    _vec(m, "twist.twist.linear", m.twist.twist.linear, 100.0)
    _vec(m, "twist.twist.angular", m.twist.twist.angular, 100.0)
    _cov(m, "twist.covariance", m.twist.covariance)


def _v_pose(m: PoseStamped) -> None:
    _header(m)
    _pose(m, "pose", m.pose)


def _v_transform(m: TransformStamped) -> None:
    _header(m)
    if len(m.child_frame_id) > MAX_STR:
        _fail(m, "child_frame_id too long")
    _vec(m, "transform.translation", m.transform.translation)
    _quat(m, "transform.rotation", m.transform.rotation)


def _v_twist(m: Twist) -> None:
    _header(m)
    _vec(m, "linear", m.linear, 100.0)
    _vec(m, "angular", m.angular, 100.0)


def _v_grid(m: OccupancyGrid) -> None:
    _header(m)
    i = m.info
    _time(m, "info.map_load_time", i.map_load_time)
    _finite(m, "info.resolution", i.resolution, 1e-4, 100.0)
    if i.width < 1 or i.height < 1 or i.width * i.height > MAX_GRID_CELLS:
        _fail(m, f"grid size {i.width}x{i.height} not in 1..{MAX_GRID_CELLS} cells")
    _pose(m, "info.origin", i.origin)  # its yaw is ignored, as map_server does
    if len(m.data) != i.width * i.height:
        _fail(m, f"data has {len(m.data)} bytes, expected width*height={i.width * i.height}")
    a = np.frombuffer(m.data, dtype=np.int8)
    if a.size and (a.min() < -1 or a.max() > 100):
        _fail(m, "cell values must be -1 (unknown) or 0..100")


def _v_topo(m: TopoGraph) -> None:
    _header(m)
    if len(m.nodes) > MAX_NODES or len(m.edges) > MAX_EDGES:
        _fail(m, f"too many nodes/edges ({len(m.nodes)}/{len(m.edges)})")
    ids = set()
    for n in m.nodes:
        if n.kind not in NODE_KINDS:
            _fail(m, f"node {n.id} has unknown kind {n.kind!r}")
        if n.id < 0 or n.id in ids:
            _fail(m, f"node id {n.id} negative or duplicated")
        ids.add(n.id)
        _finite(m, f"node {n.id} x", n.x)
        _finite(m, f"node {n.id} y", n.y)
    edges = m.edges
    for e in edges:
        if e.a not in ids or e.b not in ids:
            _fail(m, f"edge {e.a}-{e.b} refers to an unknown node")
    counts = [len(e.points) for e in edges]
    if sum(counts) > MAX_POINTS:
        _fail(m, "too many polyline points")
    _v_polylines(m, edges, counts)
    for name in ("length", "clearance"):  # one vectorised check per field
        v = np.fromiter((getattr(e, name) for e in edges), np.float64, len(edges))
        bad = ~(np.isfinite(v) & (v >= 0.0) & (v <= MAX_COORD))
        if bad.any():
            e = edges[int(np.argmax(bad))]
            _finite(m, f"edge {e.a}-{e.b} {name}", getattr(e, name), 0.0, MAX_COORD)
    if len(m.gone) > MAX_NODES:
        _fail(m, "too many gone ids")


def _v_polylines(m: TopoGraph, edges: list[TopoEdge], counts: list[int]) -> None:
    """Every polyline point [x, y], finite and sane: one array for all edges (a topo message
    is decoded by three services on every map update; per-point loops cost 0.25 ms each)."""
    if not sum(counts):
        return
    try:
        pts = np.array([p for e in edges for p in e.points], dtype=np.float64)
        ok_shape = pts.ndim == 2 and pts.shape[1] == 2
    except ValueError:  # ragged: some point has another length
        ok_shape = False
    if not ok_shape:
        for e in edges:
            for p in e.points:
                if len(p) != 2:
                    _fail(m, f"edge {e.a}-{e.b} has a point with {len(p)} coordinates")
        _fail(m, "polyline points are not [x, y] pairs")
    bad = ~np.isfinite(pts).all(axis=1) | (np.abs(pts) > MAX_COORD).any(axis=1)
    if bad.any():
        k = int(np.searchsorted(np.cumsum(counts), int(np.argmax(bad)), side="right"))
        _fail(m, f"edge {edges[k].a}-{edges[k].b} has a non-finite or absurd point")


def _v_rel(m: Reliability) -> None:
    _header(m)
    if len(m.nodes) > MAX_NODES:
        _fail(m, "too many nodes")
    for n in m.nodes:
        _finite(m, f"node {n.id} x", n.x)
        _finite(m, f"node {n.id} y", n.y)
        for name in ("p", "d", "a"):
            _finite(m, f"node {n.id} {name}", getattr(n, name), 0.0, 1.0)
        if not (n.r_min >= 0.0):  # inf allowed: never observed
            _fail(m, f"node {n.id} r_min={n.r_min} invalid")
        _finite(m, f"node {n.id} alpha_max", n.alpha_max, 0.0, 2 * math.pi + 1e-9)
        if n.n_obs < 0:
            _fail(m, f"node {n.id} n_obs negative")


def _v_path(m: Path) -> None:
    _header(m)
    if len(m.poses) > MAX_WAYPOINTS:
        _fail(m, "too many poses")
    if m.poses:  # one array for all poses (a path can hold hundreds)
        v = np.array([(p.pose.position.x, p.pose.position.y, p.pose.position.z,
                       p.pose.orientation.x, p.pose.orientation.y, p.pose.orientation.z,
                       p.pose.orientation.w) for p in m.poses], dtype=np.float64)
        if not np.all(np.isfinite(v)) or np.any(np.abs(v[:, :3]) > MAX_COORD):
            _fail(m, "non-finite or absurd pose position")
        with np.errstate(over="ignore"):  # an absurd component: an inf norm, refused below
            norm = np.linalg.norm(v[:, 3:], axis=1)
        if np.any(np.abs(norm - 1.0) > 1e-3):
            _fail(m, "a pose orientation is not a unit quaternion")
        for k, p in enumerate(m.poses):
            if len(p.header.frame_id) > MAX_STR:
                _fail(m, f"poses[{k}].header.frame_id too long")
    _finite(m, "target_x", m.target_x)
    _finite(m, "target_y", m.target_y)
    if m.goal_heading is not None:
        _finite(m, "goal_heading", m.goal_heading, -1000.0, 1000.0)
    if len(m.strategy) > MAX_STR:
        _fail(m, "strategy too long")


def _v_status(m: ExploreStatus) -> None:
    _header(m)
    if m.state not in EXPLORE_STATES:
        _fail(m, f"unknown state {m.state!r}")
    _finite(m, "target_p", m.target_p, 0.0, 1.0)
    if len(m.reason) > 4096 or len(m.strategy) > MAX_STR or len(m.blacklisted) > MAX_NODES:
        _fail(m, "field too long")
    for name in ("candidates", "end_nodes", "reliable", "replans"):
        if getattr(m, name) < 0:
            _fail(m, f"{name} negative")


def _v_sim(m: SimStatus) -> None:
    _header(m)
    if m.mode not in ("lockstep", "realtime"):
        _fail(m, f"unknown mode {m.mode!r}")
    if len(m.world) > MAX_STR:
        _fail(m, "world name too long")
    _finite(m, "sim_time", m.sim_time, 0.0, 1.0e12)
    _finite(m, "path_length", m.path_length, 0.0, 1.0e12)
    _finite(m, "real_time_factor", m.real_time_factor, 0.0, 1.0e9)
    for name in ("steps", "collisions", "watchdog_stops", "lockstep_timeouts", "stale_cmds",
                 "clipped_cmds"):
        if getattr(m, name) < 0:
            _fail(m, f"{name} negative")


_VALIDATORS = {
    LaserScan: _v_scan,
    Odometry: _v_odom,
    PoseStamped: _v_pose,
    TransformStamped: _v_transform,
    Twist: _v_twist,
    OccupancyGrid: _v_grid,
    TopoGraph: _v_topo,
    Reliability: _v_rel,
    Path: _v_path,
    ExploreStatus: _v_status,
    SimStatus: _v_sim,
}


class SeqGaps:
    """Messages lost on the way, by ``header.seq`` (each publisher counts from 0 per key).

    A jump forward counts the messages skipped (``gaps``): dropped under congestion, too big
    for the transport, or lost while a link was down. A seq back to 0 is a restarted publisher
    (``restarts``); any other step back (a second publisher on the key, a resumed one) starts
    the count again. The first message of a key is not a gap: what came before it was sent
    before this reader listened (``first_seq``).
    """

    def __init__(self) -> None:
        self._next: dict[str, int] = {}
        self.gaps: dict[str, int] = {}
        self.restarts: dict[str, int] = {}
        self.first_seq: dict[str, int] = {}

    def check(self, key: str, seq: int) -> int:
        """Record one message; returns how many it shows lost just before it."""
        want = self._next.get(key)
        self._next[key] = seq + 1
        if want is None:
            self.first_seq[key] = seq
        elif seq > want:
            self.gaps[key] = self.gaps.get(key, 0) + seq - want
            return seq - want
        elif seq == 0 and want > 0:
            self.restarts[key] = self.restarts.get(key, 0) + 1
        return 0

    @property
    def total(self) -> int:
        return sum(self.gaps.values())
