"""ROS 2 CDR <-> ours (tools/ros2.py) and `topoexplore bridge ros2` as a process.

Round trips start from payloads that rosbags itself serialized: CDR -> ours -> CDR gives the
same bytes back, for every field the mapping carries.
"""

from __future__ import annotations

import math
import signal
import time

import numpy as np
import pytest

from tests.test_supervisor import wait_for
from topoexplore.common import messages as m
from topoexplore.common.bus import Bus
from topoexplore.common.keys import Keys
from topoexplore.tools import ros2

pytest.importorskip("rosbags")
T = ros2.typestore().types
F32 = np.float32


def cdr(msg, typename: str) -> bytes:
    return bytes(ros2.typestore().serialize_cdr(msg, typename))


def header(sec=12, nanosec=345_000_000, frame="laser"):
    return T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=sec,
                                                                           nanosec=nanosec),
                                    frame_id=frame)


def quat(yaw: float):
    q = m.quaternion(yaw)
    return T["geometry_msgs/msg/Quaternion"](x=q.x, y=q.y, z=q.z, w=q.w)


def ros_scan(n=360, ranges=None, intensities=None):
    amin, inc = F32(-math.pi), F32(2 * math.pi / n)
    r = np.linspace(0.3, 9.0, n).astype(F32) if ranges is None else np.asarray(ranges, F32)
    i = np.zeros(0, F32) if intensities is None else np.asarray(intensities, F32)
    return T[ros2.SCAN](header=header(), angle_min=float(amin),
                        angle_max=float(F32(float(amin) + float(inc) * (n - 1))),
                        angle_increment=float(inc), time_increment=float(F32(1 / 360 / 10)),
                        scan_time=0.1, range_min=float(F32(0.1)), range_max=12.0, ranges=r,
                        intensities=i)


def test_laserscan_round_trip_keeps_rep117_values():
    r = np.linspace(0.3, 9.0, 360).astype(F32)
    r[3], r[4], r[5] = np.inf, -np.inf, np.nan
    data = cdr(ros_scan(ranges=r), ros2.SCAN)
    ours = ros2.scan_from_cdr(data, 7)
    assert ours.header.seq == ours.header.src_seq == 7 and ours.header.frame_id == "laser"
    assert (ours.header.stamp.sec, ours.header.stamp.nanosec) == (12, 345_000_000)
    assert ours.header.time == pytest.approx(12.345)
    assert math.isinf(ours.ranges[3]) and ours.ranges[4] == -math.inf
    assert math.isnan(ours.ranges[5])
    assert ours.angle_max == float(F32(float(F32(-math.pi)) + float(F32(2 * math.pi / 360))
                                       * 359))
    assert ours.scan_time == float(F32(0.1)) and ours.time_increment > 0.0
    assert ours.intensities == []
    assert ros2.scan_to_cdr(ours) == data  # the same bytes


def test_laserscan_round_trip_keeps_intensities():
    inten = np.linspace(0.0, 1000.0, 360).astype(F32)
    data = cdr(ros_scan(intensities=inten), ros2.SCAN)
    ours = ros2.scan_from_cdr(data, 0)
    assert ours.intensities == inten.astype(np.float64).tolist()
    assert ros2.scan_to_cdr(ours) == data


def ros_odom(yaw=0.7, pose_cov=None, twist_cov=None, child="base_footprint"):
    pose = T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=1.25, y=-3.5,
                                                                             z=0.125),
                                       orientation=quat(yaw))
    v3 = T["geometry_msgs/msg/Vector3"]
    return T[ros2.ODOM](
        header=header(frame="odom"), child_frame_id=child,
        pose=T["geometry_msgs/msg/PoseWithCovariance"](
            pose=pose, covariance=np.zeros(36) if pose_cov is None else pose_cov),
        twist=T["geometry_msgs/msg/TwistWithCovariance"](
            twist=T[ros2.TWIST](linear=v3(x=0.2, y=0.01, z=0.0),
                                angular=v3(x=0.0, y=0.0, z=-0.4)),
            covariance=np.zeros(36) if twist_cov is None else twist_cov))


def test_odometry_round_trip():
    yaw = 0.7
    data = cdr(ros_odom(yaw), ros2.ODOM)
    ours = ros2.odom_from_cdr(data, 3)
    p, t = ours.pose.pose, ours.twist.twist
    assert ours.header.seq == 3 and ours.header.src_seq == -1
    assert ours.header.frame_id == "odom" and ours.child_frame_id == "base_footprint"
    assert (p.position.x, p.position.y, p.position.z) == (1.25, -3.5, 0.125)
    assert (t.linear.x, t.linear.y, t.angular.z) == (0.2, 0.01, -0.4)
    assert m.yaw_of(p.orientation) == pytest.approx(yaw, abs=1e-12)
    assert ros2.odom_to_cdr(ours) == data


def test_odometry_keeps_covariance_and_child_frame():
    pose_cov = np.diag([0.01, 0.02, 1e6, 1e6, 1e6, 0.05]).ravel()
    twist_cov = np.arange(36, dtype=np.float64) * 1e-3
    data = cdr(ros_odom(pose_cov=pose_cov, twist_cov=twist_cov, child="base_link_2"),
               ros2.ODOM)
    ours = ros2.odom_from_cdr(data, 0)
    assert ours.child_frame_id == "base_link_2"
    assert ours.pose.covariance == pose_cov.tolist()
    assert ours.twist.covariance == twist_cov.tolist()
    back = ros2.typestore().deserialize_cdr(ros2.odom_to_cdr(ours), ros2.ODOM)
    assert back.child_frame_id == "base_link_2"
    assert np.array_equal(back.pose.covariance, pose_cov)
    assert np.array_equal(back.twist.covariance, twist_cov)
    assert ros2.odom_to_cdr(ours) == data


def test_twist_round_trip():
    v3 = T["geometry_msgs/msg/Vector3"]
    data = cdr(T[ros2.TWIST](linear=v3(x=0.35, y=-0.05, z=0.0),
                             angular=v3(x=0.0, y=0.0, z=1.1)), ros2.TWIST)
    ours = ros2.twist_from_cdr(data, 0, 5.25)
    assert (ours.linear.x, ours.linear.y, ours.angular.z) == (0.35, -0.05, 1.1)
    assert (ours.header.stamp.sec, ours.header.stamp.nanosec) == (5, 250_000_000)
    assert ours.header.frame_id == "base_link" and ours.header.src_seq == -1
    assert ros2.twist_to_cdr(ours) == data


def test_occupancy_grid_round_trip():
    data_cells = np.array([-1, 0, 100, 50, -1, 0], np.int8)
    stamp = T["builtin_interfaces/msg/Time"](sec=3, nanosec=500_000_001)
    loaded = T["builtin_interfaces/msg/Time"](sec=1, nanosec=7)
    origin = T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=-2.0, y=-1.5,
                                                                               z=0.0),
                                         orientation=quat(0.3))
    g = T[ros2.GRID](header=T["std_msgs/msg/Header"](stamp=stamp, frame_id="map"),
                     info=T["nav_msgs/msg/MapMetaData"](map_load_time=loaded, resolution=0.05,
                                                        width=3, height=2, origin=origin),
                     data=data_cells)
    data = cdr(g, ros2.GRID)
    ours = ros2.grid_from_cdr(data, 0)
    i = ours.info
    assert (i.width, i.height, i.origin.position.x, i.origin.position.y) == (3, 2, -2.0, -1.5)
    assert m.yaw_of(i.origin.orientation) == pytest.approx(0.3, abs=1e-12)
    assert (ours.header.stamp.sec, ours.header.stamp.nanosec) == (3, 500_000_001)
    assert (i.map_load_time.sec, i.map_load_time.nanosec) == (1, 7)
    assert ours.header.frame_id == "map"
    assert i.resolution == pytest.approx(0.05) and ours.data == data_cells.tobytes()
    assert ros2.grid_to_cdr(ours) == data


def test_bad_payloads_are_one_line_errors():
    for bad in (b"", b"\x00\x01\x00\x00garbage", cdr(ros_scan(), ros2.SCAN)[:20]):
        with pytest.raises(ros2.Ros2Error):
            ros2.scan_from_cdr(bad, 0)
    with pytest.raises(ros2.Ros2Error):  # a valid CDR scan that is not a valid scan of ours
        ros2.scan_from_cdr(cdr(ros_scan(ranges=np.zeros(0)), ros2.SCAN), 0)


def test_keys_of_both_flavors():
    assert ros2.RosKeys().sub("/scan") == "scan"
    assert ros2.RosKeys("ros2dds", "robot1").pub("cmd_vel", ros2.TWIST) == "robot1/cmd_vel"
    k = ros2.RosKeys("rmw_zenoh", domain=3)
    assert k.sub("/scan") == "3/scan/*/*"
    key = k.pub("/cmd_vel", ros2.TWIST)
    assert key.startswith("3/cmd_vel/geometry_msgs::msg::dds_::Twist_/RIHS01_")
    assert len(ros2.rmw_attachment(1, 2, bytes(16))) == 32
    for bad in ("", "a/*", "a//b"):
        with pytest.raises(ValueError):
            k.sub(bad)
    with pytest.raises(ValueError):
        ros2.RosKeys("ros1")


def test_rmw_attachment_is_what_zenohs_serializer_makes():
    """rmw_zenoh reads its attachment with Zenoh's deserializer: int64, int64, 16 bytes."""
    import zenoh.ext as ze

    gid = bytes(range(16))
    want = ze.z_serialize((ze.Int64(5), ze.Int64(-7), tuple(ze.UInt8(b) for b in gid)))
    assert ros2.rmw_attachment(5, -7, gid) == want.to_bytes()


@pytest.mark.parametrize("flavor", ["ros2dds", "rmw_zenoh"])
def test_the_bridge_process(procs, endpoint, namespace, flavor):
    """A ROS 2 robot's CDR scan and odom arrive as ours; our cmd_vel and map leave as CDR;
    garbage is counted and the bridge goes on."""
    procs.router(endpoint)
    bridge = procs.python("-m", "topoexplore.tools.cli", "bridge", "ros2", "--flavor", flavor,
                          "--connect", endpoint, "--namespace", namespace)
    keys = Keys(namespace, "robot1")
    ros = ros2.RosKeys(flavor)
    scans: list[m.LaserScan] = []
    twists: list[tuple[bytes, bytes | None]] = []
    grids: list[bytes] = []
    with Bus.client(endpoint, wait_for_router=True) as bus:
        bus.subscribe(keys.topic("scan"), m.LaserScan, lambda msg, k: scans.append(msg))
        bus.subscribe_raw(ros.sub("cmd_vel"), lambda k, p, e: twists.append((k, p)))
        bus.subscribe_raw(ros.sub("map"), lambda k, p, e: grids.append(p))
        scan_key = ("scan" if flavor == "ros2dds" else
                    f"0/scan/{ros2.dds_type_name(ros2.SCAN)}/{ros2.typestore().hash_rihs01(ros2.SCAN)}")
        robot_scan = bus.publisher(scan_key, reliable=True, encoding="application/cdr")
        cmd = bus.publisher(keys.cmd_vel, m.Twist, reliable=True)
        grid = bus.publisher(keys.topic("map"), m.OccupancyGrid, reliable=True)
        data = cdr(ros_scan(), ros2.SCAN)

        def send() -> bool:
            robot_scan.put(b"not cdr")
            robot_scan.put(data)
            cmd.put(m.Twist(header=m.header(0, 1.0, "base_link", src_seq=0),
                            linear=m.Vector3(x=0.3), angular=m.Vector3(z=-0.2)))
            grid.put(m.OccupancyGrid(
                header=m.header(0, 1.0, "map", src_seq=0),
                info=m.MapMetaData(map_load_time=m.stamp(1.0), resolution=0.05, width=2,
                                   height=1, origin=m.GeoPose(position=m.Point(),
                                                              orientation=m.Quaternion())),
                data=bytes([0, 100])))
            time.sleep(0.2)
            return bool(scans and twists and grids)

        assert wait_for(send, 30), (scans, twists, grids, bridge.poll())
        assert len(scans[0].ranges) == 360 and scans[0].header.time == pytest.approx(12.345)
        assert scans[0].header.frame_id == "laser" and scans[0].scan_time == float(F32(0.1))
        key, payload = twists[0]
        t = ros2.typestore().deserialize_cdr(payload, ros2.TWIST)
        assert (t.linear.x, t.angular.z) == (0.3, -0.2)
        if flavor == "rmw_zenoh":
            assert key.startswith("0/cmd_vel/geometry_msgs::msg::dds_::Twist_/RIHS01_")
        g = ros2.typestore().deserialize_cdr(grids[0], ros2.GRID)
        assert (g.info.width, list(g.data)) == (2, [0, 100])
    bridge.send_signal(signal.SIGTERM)
    out, _ = bridge.communicate(timeout=30)
    assert bridge.returncode == 0, out
    assert "bad message" in out and "stopped" in out and "scan in" in out, out
