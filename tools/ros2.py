"""ROS 2 CDR <-> our messages, and the Zenoh keys ROS 2 uses (pure: no bus, no clock).

The CDR side is ``rosbags``' typestore (the ROS 2 standard message definitions, pure Python,
no ROS installation): payloads are CDR with the 4-byte encapsulation header, as DDS and
rmw_zenoh carry them. Conversions come in symmetric pairs (tests/test_ros2.py round-trips
each against payloads that rosbags itself serialized):

| ROS 2 | ours | what maps |
|---|---|---|
| sensor_msgs/msg/LaserScan | LaserScan | stamp, frame_id, angle_min, angle_increment, range_min, range_max, ranges (float32, REP-117 values kept) |
| nav_msgs/msg/Odometry | Odometry | stamp; pose position x, y and the yaw of its quaternion; twist linear.x, angular.z |
| geometry_msgs/msg/Twist | Twist | linear.x = v, angular.z = w (a Twist has no stamp: ours gets the robot's latest odometry stamp) |
| nav_msgs/msg/OccupancyGrid | OccupancyGrid | stamp, resolution, width, height, origin x, y, yaw, data |

Keys (``RosKeys``):

- ``ros2dds`` (zenoh-bridge-ros2dds): the ROS topic name without its leading slash, under the
  bridge's own namespace if it has one (``--ros-prefix``): ``/scan`` -> ``scan``.
- ``rmw_zenoh`` (ROS 2 Jazzy and later with ``RMW_IMPLEMENTATION=rmw_zenoh_cpp``):
  ``<domain>/<topic>/<DDS type name>/<type hash>``, e.g.
  ``0/cmd_vel/geometry_msgs::msg::dds_::Twist_/RIHS01_...``; subscriptions take any type
  hash (``0/scan/*/*``); publications carry rmw_zenoh's attachment (sequence number, source
  timestamp [ns], a 16-byte source gid).
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from functools import cache
from typing import Any

import numpy as np

from topoexplore.common import messages as m
from topoexplore.tools.extras import require

SCAN, ODOM = "sensor_msgs/msg/LaserScan", "nav_msgs/msg/Odometry"
TWIST, GRID = "geometry_msgs/msg/Twist", "nav_msgs/msg/OccupancyGrid"
FLAVORS = ("ros2dds", "rmw_zenoh")


class Ros2Error(ValueError):
    """A payload that is not the CDR message it should be (one line)."""


@cache
def typestore() -> Any:
    require("rosbags", what="the ROS 2 bridge")
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


def _types() -> Any:
    return typestore().types


def _decode(data: bytes, typename: str) -> Any:
    try:
        return typestore().deserialize_cdr(bytes(data), typename)
    except Exception as exc:  # noqa: BLE001 - rosbags raises several kinds on bad bytes
        raise Ros2Error(f"not a CDR {typename}: {type(exc).__name__}: {exc}"[:300]) from None


def _checked(msg: Any, msg_type: type) -> Any:
    """Our message, validated as the bus validates it (a decode of its encoding)."""
    try:
        return m.decode(m.encode(msg), msg_type)
    except m.MessageError as exc:
        raise Ros2Error(str(exc)) from None


def to_stamp(t: Any) -> float:
    """builtin_interfaces/Time -> [s]."""
    return float(t.sec) + 1e-9 * float(t.nanosec)


def from_stamp(s: float) -> Any:
    """[s] -> builtin_interfaces/Time (sec, nanosec; a negative time is clamped to 0)."""
    ns = max(0, round(s * 1e9))
    return _types()["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)


def _header(stamp: float, frame: str) -> Any:
    return _types()["std_msgs/msg/Header"](stamp=from_stamp(stamp), frame_id=frame)


def yaw_of(q: Any) -> float:
    """The yaw [rad] of a quaternion (x, y, z, w) (REP-103: about z)."""
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))


def quaternion(yaw: float) -> Any:
    return _types()["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(yaw / 2.0),
                                                    w=math.cos(yaw / 2.0))


# --- LaserScan ---------------------------------------------------------------------------


def scan_from_cdr(data: bytes, seq: int) -> m.LaserScan:
    """A CDR sensor_msgs/LaserScan -> ours (seq and src_seq: the bridge's count)."""
    s = _decode(data, SCAN)
    return _checked(m.LaserScan(
        header=m.Header(seq=seq, stamp=to_stamp(s.header.stamp), frame=s.header.frame_id,
                        src_seq=seq),
        angle_min=float(s.angle_min), angle_increment=float(s.angle_increment),
        range_min=float(s.range_min), range_max=float(s.range_max),
        ranges=np.asarray(s.ranges, np.float64).tolist()), m.LaserScan)


def scan_to_cdr(msg: m.LaserScan, scan_time: float = 0.0) -> bytes:
    n = len(msg.ranges)
    T = _types()
    s = T[SCAN](header=_header(msg.header.stamp, msg.header.frame),
                angle_min=msg.angle_min,
                angle_max=msg.angle_min + msg.angle_increment * max(0, n - 1),
                angle_increment=msg.angle_increment, time_increment=0.0, scan_time=scan_time,
                range_min=msg.range_min, range_max=msg.range_max,
                ranges=np.asarray(msg.ranges, np.float32),
                intensities=np.zeros(0, np.float32))
    return bytes(typestore().serialize_cdr(s, SCAN))


# --- Odometry ----------------------------------------------------------------------------


def odom_from_cdr(data: bytes, seq: int) -> m.Odometry:
    o = _decode(data, ODOM)
    p, q = o.pose.pose.position, o.pose.pose.orientation
    return _checked(m.Odometry(
        header=m.Header(seq=seq, stamp=to_stamp(o.header.stamp), frame=o.header.frame_id,
                        src_seq=-1),
        pose=m.Pose2D(x=float(p.x), y=float(p.y), theta=yaw_of(q)),
        v=float(o.twist.twist.linear.x), w=float(o.twist.twist.angular.z)), m.Odometry)


def odom_to_cdr(msg: m.Odometry, child_frame: str = "base_link") -> bytes:
    T = _types()
    v3 = T["geometry_msgs/msg/Vector3"]
    pose = T["geometry_msgs/msg/Pose"](
        position=T["geometry_msgs/msg/Point"](x=msg.pose.x, y=msg.pose.y, z=0.0),
        orientation=quaternion(msg.pose.theta))
    o = T[ODOM](header=_header(msg.header.stamp, msg.header.frame), child_frame_id=child_frame,
                pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose,
                                                                covariance=np.zeros(36)),
                twist=T["geometry_msgs/msg/TwistWithCovariance"](
                    twist=T[TWIST](linear=v3(x=msg.v, y=0.0, z=0.0),
                                   angular=v3(x=0.0, y=0.0, z=msg.w)),
                    covariance=np.zeros(36)))
    return bytes(typestore().serialize_cdr(o, ODOM))


# --- Twist -------------------------------------------------------------------------------


def twist_to_cdr(msg: m.Twist) -> bytes:
    v3 = _types()["geometry_msgs/msg/Vector3"]
    t = _types()[TWIST](linear=v3(x=msg.v, y=0.0, z=0.0), angular=v3(x=0.0, y=0.0, z=msg.w))
    return bytes(typestore().serialize_cdr(t, TWIST))


def twist_from_cdr(data: bytes, seq: int, stamp: float) -> m.Twist:
    """A CDR Twist -> ours, stamped ``stamp`` (a Twist has none: the robot's clock)."""
    t = _decode(data, TWIST)
    return _checked(m.Twist(header=m.Header(seq=seq, stamp=stamp, frame="base_link",
                                            src_seq=-1),
                            v=float(t.linear.x), w=float(t.angular.z)), m.Twist)


# --- OccupancyGrid -----------------------------------------------------------------------


def grid_to_cdr(msg: m.OccupancyGrid) -> bytes:
    T = _types()
    origin = T["geometry_msgs/msg/Pose"](
        position=T["geometry_msgs/msg/Point"](x=msg.origin.x, y=msg.origin.y, z=0.0),
        orientation=quaternion(msg.origin.theta))
    info = T["nav_msgs/msg/MapMetaData"](map_load_time=from_stamp(msg.header.stamp),
                                         resolution=msg.resolution, width=msg.width,
                                         height=msg.height, origin=origin)
    g = T[GRID](header=_header(msg.header.stamp, msg.header.frame), info=info,
                data=np.frombuffer(msg.data, np.int8))
    return bytes(typestore().serialize_cdr(g, GRID))


def grid_from_cdr(data: bytes, seq: int) -> m.OccupancyGrid:
    g = _decode(data, GRID)
    i = g.info
    return _checked(m.OccupancyGrid(
        header=m.Header(seq=seq, stamp=to_stamp(g.header.stamp), frame=g.header.frame_id,
                        src_seq=-1),
        resolution=float(i.resolution), width=int(i.width), height=int(i.height),
        origin=m.Pose2D(x=float(i.origin.position.x), y=float(i.origin.position.y),
                        theta=yaw_of(i.origin.orientation)),
        data=np.asarray(g.data, np.int8).tobytes()), m.OccupancyGrid)


# --- keys --------------------------------------------------------------------------------


def dds_type_name(typename: str) -> str:
    """sensor_msgs/msg/LaserScan -> sensor_msgs::msg::dds_::LaserScan_"""
    pkg, kind, name = typename.split("/")
    return f"{pkg}::{kind}::dds_::{name}_"


@dataclass(frozen=True)
class RosKeys:
    """The Zenoh keys of ROS 2 topics for one bridge flavor (see the module doc)."""

    flavor: str = "ros2dds"
    prefix: str = ""  # ros2dds: the bridge's namespace ("" or "robot1", no slashes around)
    domain: int = 0  # rmw_zenoh: ROS_DOMAIN_ID

    def __post_init__(self) -> None:
        if self.flavor not in FLAVORS:
            raise ValueError(f"unknown flavor {self.flavor!r} (expected {', '.join(FLAVORS)})")
        if not 0 <= self.domain <= 232:
            raise ValueError(f"ROS domain id {self.domain} out of 0..232")

    def _name(self, topic: str) -> str:
        t = topic.strip("/")
        if not t or any(c in t for c in "*$?#") or "//" in t:
            raise ValueError(f"bad ROS topic name {topic!r}")
        return t

    def sub(self, topic: str) -> str:
        """The key expression to subscribe to a ROS topic (any type hash for rmw_zenoh)."""
        t = self._name(topic)
        if self.flavor == "ros2dds":
            return f"{self.prefix.strip('/')}/{t}" if self.prefix.strip("/") else t
        return f"{self.domain}/{t}/*/*"

    def pub(self, topic: str, typename: str) -> str:
        """The key to publish a ROS topic of ``typename`` on."""
        t = self._name(topic)
        if self.flavor == "ros2dds":
            return self.sub(topic)
        return f"{self.domain}/{t}/{dds_type_name(typename)}/{typestore().hash_rihs01(typename)}"


def rmw_attachment(seq: int, stamp_ns: int, gid: bytes) -> bytes:
    """rmw_zenoh's attachment of a publication: sequence number (int64), source timestamp
    [ns] (int64), source gid (16 bytes), as Zenoh's serializer lays them out (little endian,
    the fixed-size gid without a length)."""
    if len(gid) != 16:
        raise ValueError("a gid is 16 bytes")
    return struct.pack("<qq16s", seq, stamp_ns, gid)
