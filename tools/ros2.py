"""ROS 2 CDR <-> our messages, and the Zenoh keys ROS 2 uses (pure: no bus, no clock).

The CDR side is ``rosbags``' typestore (the ROS 2 standard message definitions, pure Python,
no ROS installation): payloads are CDR with the 4-byte encapsulation header, as DDS and
rmw_zenoh carry them. Our messages are the ROS 2 definitions field for field
(:mod:`topoexplore.common.messages`), so each conversion is a copy: stamps as ``sec`` and
``nanosec`` (no float in between), frame ids, quaternions, covariances, every scan field.
Conversions come in symmetric pairs; tests/test_ros2.py round-trips each against payloads
that rosbags itself serialized and gets the same bytes back.

| ROS 2 | ours | what maps |
|---|---|---|
| sensor_msgs/msg/LaserScan | LaserScan | every field; ranges and intensities are float32 there, float64 here (exact both ways; REP-117's inf and nan kept) |
| nav_msgs/msg/Odometry | Odometry | every field (header, child_frame_id, pose and twist with their covariances) |
| geometry_msgs/msg/Twist | Twist | linear, angular; a ROS Twist has no header: ours is dropped on the way out, and one coming in is stamped with the time the caller gives (the robot's clock), frame ``base_link`` |
| nav_msgs/msg/OccupancyGrid | OccupancyGrid | every field (header, info with map_load_time and the origin pose, data) |

Ours only: ``header.seq`` (the bridge's count of that topic) and ``header.src_seq`` (a scan's
own count; -1 for the others); they are dropped on the way out.

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


# --- the common pieces, field for field ---------------------------------------------------


def _time_from(t: Any) -> m.Time:
    return m.Time(sec=int(t.sec), nanosec=int(t.nanosec))


def _time_to(t: m.Time) -> Any:
    return _types()["builtin_interfaces/msg/Time"](sec=t.sec, nanosec=t.nanosec)


def _header_from(h: Any, seq: int, src_seq: int = -1) -> m.Header:
    return m.Header(stamp=_time_from(h.stamp), frame_id=str(h.frame_id), seq=seq,
                    src_seq=src_seq)


def _header_to(h: m.Header) -> Any:
    return _types()["std_msgs/msg/Header"](stamp=_time_to(h.stamp), frame_id=h.frame_id)


def _xyz_from(v: Any, cls: type) -> Any:
    """A ROS Vector3 or Point -> ours (``cls``)."""
    return cls(x=float(v.x), y=float(v.y), z=float(v.z))


def _xyz_to(v: m.Vector3 | m.Point, typename: str) -> Any:
    return _types()[typename](x=v.x, y=v.y, z=v.z)


def _pose_from(p: Any) -> m.GeoPose:
    q = p.orientation
    return m.GeoPose(position=_xyz_from(p.position, m.Point),
                     orientation=m.Quaternion(x=float(q.x), y=float(q.y), z=float(q.z),
                                              w=float(q.w)))


def _pose_to(p: m.GeoPose) -> Any:
    T, q = _types(), p.orientation
    return T["geometry_msgs/msg/Pose"](
        position=_xyz_to(p.position, "geometry_msgs/msg/Point"),
        orientation=T["geometry_msgs/msg/Quaternion"](x=q.x, y=q.y, z=q.z, w=q.w))


def _floats(a: Any) -> list[float]:
    """A ROS float array (float32 or float64) -> a float64 list (exact)."""
    return np.asarray(a, np.float64).tolist()


def _serialize(msg: Any, typename: str) -> bytes:
    return bytes(typestore().serialize_cdr(msg, typename))


# --- LaserScan ---------------------------------------------------------------------------


def scan_from_cdr(data: bytes, seq: int) -> m.LaserScan:
    """A CDR sensor_msgs/LaserScan -> ours (seq and src_seq: the bridge's count)."""
    s = _decode(data, SCAN)
    return _checked(m.LaserScan(
        header=_header_from(s.header, seq, src_seq=seq),
        angle_min=float(s.angle_min), angle_max=float(s.angle_max),
        angle_increment=float(s.angle_increment), time_increment=float(s.time_increment),
        scan_time=float(s.scan_time), range_min=float(s.range_min),
        range_max=float(s.range_max), ranges=_floats(s.ranges),
        intensities=_floats(s.intensities)), m.LaserScan)


def scan_to_cdr(msg: m.LaserScan) -> bytes:
    s = _types()[SCAN](header=_header_to(msg.header), angle_min=msg.angle_min,
                       angle_max=msg.angle_max, angle_increment=msg.angle_increment,
                       time_increment=msg.time_increment, scan_time=msg.scan_time,
                       range_min=msg.range_min, range_max=msg.range_max,
                       ranges=np.asarray(msg.ranges, np.float32),
                       intensities=np.asarray(msg.intensities, np.float32))
    return _serialize(s, SCAN)


# --- Odometry ----------------------------------------------------------------------------


def odom_from_cdr(data: bytes, seq: int) -> m.Odometry:
    o = _decode(data, ODOM)
    t = o.twist.twist
    return _checked(m.Odometry(
        header=_header_from(o.header, seq), child_frame_id=str(o.child_frame_id),
        pose=m.PoseWithCovariance(pose=_pose_from(o.pose.pose),
                                  covariance=_floats(o.pose.covariance)),
        twist=m.TwistWithCovariance(
            twist=m.GeoTwist(linear=_xyz_from(t.linear, m.Vector3),
                             angular=_xyz_from(t.angular, m.Vector3)),
            covariance=_floats(o.twist.covariance))), m.Odometry)


def odom_to_cdr(msg: m.Odometry) -> bytes:
    T, t = _types(), msg.twist.twist
    v3 = "geometry_msgs/msg/Vector3"
    o = T[ODOM](header=_header_to(msg.header), child_frame_id=msg.child_frame_id,
                pose=T["geometry_msgs/msg/PoseWithCovariance"](
                    pose=_pose_to(msg.pose.pose),
                    covariance=np.asarray(msg.pose.covariance, np.float64)),
                twist=T["geometry_msgs/msg/TwistWithCovariance"](
                    twist=T[TWIST](linear=_xyz_to(t.linear, v3),
                                   angular=_xyz_to(t.angular, v3)),
                    covariance=np.asarray(msg.twist.covariance, np.float64)))
    return _serialize(o, ODOM)


# --- Twist -------------------------------------------------------------------------------


def twist_to_cdr(msg: m.Twist) -> bytes:
    """Ours -> a CDR geometry_msgs/Twist (linear, angular; our header has no place there)."""
    v3 = "geometry_msgs/msg/Vector3"
    t = _types()[TWIST](linear=_xyz_to(msg.linear, v3), angular=_xyz_to(msg.angular, v3))
    return _serialize(t, TWIST)


def twist_from_cdr(data: bytes, seq: int, stamp: float) -> m.Twist:
    """A CDR Twist -> ours, stamped ``stamp`` [s] (a Twist has none: the robot's clock; to
    the nearest nanosecond), frame base_link."""
    t = _decode(data, TWIST)
    return _checked(m.Twist(header=m.header(seq, stamp, "base_link"),
                            linear=_xyz_from(t.linear, m.Vector3),
                            angular=_xyz_from(t.angular, m.Vector3)), m.Twist)


# --- OccupancyGrid -----------------------------------------------------------------------


def grid_to_cdr(msg: m.OccupancyGrid) -> bytes:
    T, i = _types(), msg.info
    info = T["nav_msgs/msg/MapMetaData"](map_load_time=_time_to(i.map_load_time),
                                         resolution=i.resolution, width=i.width,
                                         height=i.height, origin=_pose_to(i.origin))
    g = T[GRID](header=_header_to(msg.header), info=info,
                data=np.frombuffer(msg.data, np.int8))
    return _serialize(g, GRID)


def grid_from_cdr(data: bytes, seq: int) -> m.OccupancyGrid:
    g = _decode(data, GRID)
    i = g.info
    return _checked(m.OccupancyGrid(
        header=_header_from(g.header, seq),
        info=m.MapMetaData(map_load_time=_time_from(i.map_load_time),
                           resolution=float(i.resolution), width=int(i.width),
                           height=int(i.height), origin=_pose_from(i.origin)),
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
