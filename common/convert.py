"""The conversion layer: wire messages <-> domain types, in symmetric pairs.

Every ``<thing>_to_msg`` has its ``<thing>_from_msg``, and ``from_msg(to_msg(x))`` gives back
``x`` (tests/test_convert.py): float64 arrays travel as msgpack doubles, grids as int8 bytes,
so a run over the bus and a run in one process see the same inputs. Two things are not
bit-exact, by the ROS shapes: a yaw travels as a quaternion (back within 1e-15 rad) and a
stamp as whole nanoseconds (``header.time`` within 0.5 ns of the float it was made from).
The service shells and the in-process runner (``topoexplore bench inproc --wire``) use these
functions and no others. Messages are validated when they are decoded
(:func:`topoexplore.common.messages.decode`), so nothing is checked again here.
"""

from __future__ import annotations

import numpy as np

from topoexplore.common import messages as m
from topoexplore.common.domain import (
    Belief,
    Command,
    ExploreState,
    Graph,
    GridMap,
    Node,
    Odom,
    Pose,
    Route,
    Scan,
    Status,
)
from topoexplore.common.grid import GridGeometry

__all__ = [
    "pose_to_msg", "pose_from_msg", "odom_to_msg", "odom_from_msg", "truth_to_msg",
    "truth_from_msg", "correction_to_msg", "correction_from_msg", "command_to_msg",
    "command_from_msg", "scan_to_msg", "scan_from_msg", "grid_to_msg", "grid_from_msg",
    "graph_to_msg", "graph_from_msg", "beliefs_to_msg", "beliefs_from_msg", "route_to_msg",
    "route_from_msg", "status_to_msg", "status_from_msg",
]


def pose_to_msg(p: Pose) -> m.GeoPose:
    """A planar pose -> geometry_msgs/Pose (z = 0, a quaternion about z)."""
    return m.GeoPose(position=m.Point(x=float(p.x), y=float(p.y)),
                     orientation=m.quaternion(float(p.theta)))


def pose_from_msg(msg: m.GeoPose) -> Pose:
    """The yaw comes back within an ulp or two (a quaternion is not an angle)."""
    return Pose(msg.position.x, msg.position.y, m.yaw_of(msg.orientation))


def odom_to_msg(o: Odom, header: m.Header, child_frame_id: str = "base_link",
                pose_covariance: list[float] | None = None) -> m.Odometry:
    """Pose in ``header.frame_id`` (odom), velocity in the body frame ``child_frame_id``."""
    pose = m.PoseWithCovariance(pose=pose_to_msg(o.pose))
    if pose_covariance is not None:
        pose.covariance = list(pose_covariance)
    return m.Odometry(header=header, child_frame_id=child_frame_id, pose=pose,
                      twist=m.TwistWithCovariance(twist=m.GeoTwist(
                          linear=m.Vector3(x=float(o.v)), angular=m.Vector3(z=float(o.w)))))


def odom_from_msg(msg: m.Odometry) -> Odom:
    t = msg.twist.twist
    return Odom(pose_from_msg(msg.pose.pose), t.linear.x, t.angular.z)


def truth_to_msg(p: Pose, header: m.Header) -> m.PoseStamped:
    return m.PoseStamped(header=header, pose=pose_to_msg(p))


def truth_from_msg(msg: m.PoseStamped) -> Pose:
    return pose_from_msg(msg.pose)


def correction_to_msg(c: Pose, header: m.Header, child_frame_id: str = "odom"
                      ) -> m.TransformStamped:
    """The map -> odom correction (odom's pose in ``header.frame_id``, map; REP-105)."""
    return m.TransformStamped(header=header, child_frame_id=child_frame_id,
                              transform=m.Transform(
                                  translation=m.Vector3(x=float(c.x), y=float(c.y)),
                                  rotation=m.quaternion(float(c.theta))))


def correction_from_msg(msg: m.TransformStamped) -> Pose:
    t = msg.transform
    return Pose(t.translation.x, t.translation.y, m.yaw_of(t.rotation))


def command_to_msg(c: Command, header: m.Header) -> m.Twist:
    """(v, w) -> linear.x [m/s], angular.z [rad/s]."""
    return m.Twist(header=header, linear=m.Vector3(x=float(c.v)),
                   angular=m.Vector3(z=float(c.w)))


def command_from_msg(msg: m.Twist) -> Command:
    """A planar base takes linear.x and angular.z; the other components are not drivable."""
    return Command(msg.linear.x, msg.angular.z)


def scan_to_msg(s: Scan, header: m.Header, scan_time: float = 0.0) -> m.LaserScan:
    """``scan_time`` [s]: the period of the scans (0: unknown); the beams are taken at once
    (time_increment 0), as the simulator takes them."""
    n = s.beams
    return m.LaserScan(header=header, angle_min=float(s.angle_min),
                       angle_max=float(s.angle_min + (n - 1) * s.angle_increment),
                       angle_increment=float(s.angle_increment), scan_time=float(scan_time),
                       range_min=float(s.range_min), range_max=float(s.range_max),
                       ranges=np.asarray(s.ranges, dtype=np.float64).tolist())


def scan_from_msg(msg: m.LaserScan) -> Scan:
    return Scan(np.asarray(msg.ranges, dtype=np.float64), msg.angle_min, msg.angle_increment,
                msg.range_min, msg.range_max)


def grid_to_msg(g: GridMap, header: m.Header) -> m.OccupancyGrid:
    geom = g.geom
    info = m.MapMetaData(map_load_time=header.stamp, resolution=geom.resolution,
                         width=geom.width, height=geom.height,
                         origin=m.GeoPose(position=m.Point(x=geom.origin_x, y=geom.origin_y),
                                          orientation=m.Quaternion()))
    return m.OccupancyGrid(header=header, info=info,
                           data=np.ascontiguousarray(g.data, dtype=np.int8).tobytes())


def grid_from_msg(msg: m.OccupancyGrid) -> GridMap:
    """A read-only view of the message's bytes (no copy)."""
    i = msg.info
    data = np.frombuffer(msg.data, dtype=np.int8).reshape(i.height, i.width)
    return GridMap(data, GridGeometry(i.resolution, i.origin.position.x, i.origin.position.y,
                                      i.width, i.height))


def graph_to_msg(g: Graph, header: m.Header) -> m.TopoGraph:
    pts = g.points.tolist()  # one conversion for every edge
    off = g.offsets.tolist()
    nodes = [m.TopoNode(id=int(n.id), kind=n.kind, x=float(n.x), y=float(n.y)) for n in g.nodes]
    edges = [m.TopoEdge(a=int(e.a), b=int(e.b), points=pts[off[k]:off[k + 1]],
                        length=float(e.length), clearance=float(e.clearance))
             for k, e in enumerate(g.edges)]
    return m.TopoGraph(header=header, nodes=nodes, edges=edges, gone=[int(i) for i in g.gone])


def graph_from_msg(msg: m.TopoGraph) -> Graph:
    counts = [len(e.points) for e in msg.edges]
    flat = [p for e in msg.edges for p in e.points]
    pts = np.asarray(flat, dtype=np.float64).reshape(-1, 2)
    off = np.concatenate([[0], np.cumsum(counts, dtype=np.int64)]).astype(np.int64)
    return Graph.build((Node(n.id, n.kind, n.x, n.y) for n in msg.nodes),
                       [(e.a, e.b) for e in msg.edges], pts, off,
                       [e.length for e in msg.edges], [e.clearance for e in msg.edges], msg.gone)


def beliefs_to_msg(beliefs, header: m.Header) -> m.Reliability:
    return m.Reliability(header=header, nodes=[m.NodeReliability(
        id=int(b.id), x=float(b.x), y=float(b.y), p=float(b.p), d=float(b.d), a=float(b.a),
        r_min=float(b.r_min), alpha_max=float(b.alpha_max), visible=bool(b.visible),
        n_obs=int(b.n_obs), visited=bool(b.visited), frontier=int(b.frontier))
        for b in beliefs])


def beliefs_from_msg(msg: m.Reliability) -> list[Belief]:
    return [Belief(id=n.id, x=n.x, y=n.y, p=n.p, d=n.d, a=n.a, r_min=n.r_min,
                   alpha_max=n.alpha_max, visible=n.visible, n_obs=n.n_obs, visited=n.visited,
                   frontier=n.frontier) for n in msg.nodes]


def _headings(w: np.ndarray, goal_heading: float | None) -> np.ndarray:
    """Each waypoint faces the next; the last faces the goal heading (else its leg's)."""
    h = np.zeros(len(w))
    if len(w) > 1:
        d = np.diff(w, axis=0)
        h[:-1] = np.arctan2(d[:, 1], d[:, 0])
        h[-1] = h[-2]
    if goal_heading is not None and len(w):
        h[-1] = goal_heading
    return h


def route_to_msg(r: Route, header: m.Header) -> m.Path:
    w = np.asarray(r.waypoints, dtype=np.float64).reshape(-1, 2)
    h = _headings(w, r.goal_heading) / 2.0
    ph = m.Header(stamp=header.stamp, frame_id=header.frame_id)
    poses = [m.PoseStamped(header=ph, pose=m.GeoPose(position=m.Point(x=x, y=y),
                                                     orientation=m.Quaternion(z=qz, w=qw)))
             for (x, y), qz, qw in zip(w.tolist(), np.sin(h).tolist(), np.cos(h).tolist(),
                                       strict=True)]
    return m.Path(header=header, poses=poses, target_id=int(r.target_id),
                  target_x=float(r.target_xy[0]), target_y=float(r.target_xy[1]),
                  strategy=r.strategy, plan_id=int(r.plan_id),
                  goal_heading=None if r.goal_heading is None else float(r.goal_heading))


def route_from_msg(msg: m.Path) -> Route:
    w = np.array([(p.pose.position.x, p.pose.position.y) for p in msg.poses],
                 dtype=np.float64).reshape(-1, 2)
    return Route(w, msg.plan_id, msg.target_id, (msg.target_x, msg.target_y), msg.strategy,
                 msg.goal_heading)


def status_to_msg(s: Status, header: m.Header) -> m.ExploreStatus:
    return m.ExploreStatus(
        header=header, state=ExploreState(s.state).value, reason=s.reason, strategy=s.strategy,
        target_id=int(s.target_id), target_p=min(1.0, max(0.0, float(s.target_p))),
        candidates=int(s.candidates), end_nodes=int(s.end_nodes), reliable=int(s.reliable),
        blacklisted=[int(i) for i in s.blacklisted], replans=int(s.replans))


def status_from_msg(msg: m.ExploreStatus) -> Status:
    return Status(ExploreState(msg.state), msg.reason, msg.strategy, msg.target_id,
                  msg.target_p, msg.candidates, msg.end_nodes, msg.reliable,
                  tuple(msg.blacklisted), msg.replans)
