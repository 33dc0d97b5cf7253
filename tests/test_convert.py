"""The conversion layer: every wire <-> domain pair round-trips exactly, through the codec too
(what a service publishes is what the next one computes on)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from topoexplore.common import convert
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

H = m.header(4, 12.5, "map", 3)


def same_pose(a: Pose, b: Pose) -> bool:
    """Position exact; the yaw within 1e-15 rad (it travels as a quaternion)."""
    return (a.x, a.y) == (b.x, b.y) and abs(math.remainder(a.theta - b.theta, 2 * math.pi)) < 1e-15


def wire(msg, msg_type):
    return m.decode(m.encode(msg), msg_type)


def same_graph(a: Graph, b: Graph) -> None:
    assert a.nodes == b.nodes and a.gone == b.gone
    assert np.array_equal(a.points, b.points) and np.array_equal(a.offsets, b.offsets)
    assert len(a.edges) == len(b.edges)
    for ea, eb in zip(a.edges, b.edges, strict=True):
        assert (ea.a, ea.b, ea.length, ea.clearance) == (eb.a, eb.b, eb.length, eb.clearance)
        assert np.array_equal(ea.points, eb.points)


def graph() -> Graph:
    rng = np.random.default_rng(1)
    nodes = [Node(0, "end", 0.15, -2.05), Node(1, "branch", 1.0 / 3.0, 0.1),
             Node(2, "corner", 2.0, 0.1), Node(3, "end", 2.0, 2.0)]
    edges = [(0, 1, rng.normal(size=(7, 2)), 2.1, 0.35), (1, 2, rng.normal(size=(2, 2)), 1.7, 0.2),
             (2, 3, rng.normal(size=(30, 2)), 1.9, 0.41)]
    return Graph.from_edges(nodes, edges, gone=[5, 9])


def test_pose_odom_truth_command():
    p = Pose(1.0 / 3.0, -2.0e-7, math.pi - 1e-12)
    assert same_pose(convert.pose_from_msg(convert.pose_to_msg(p)), p)
    o = Odom(p, 0.2, -0.1)
    back = convert.odom_from_msg(wire(convert.odom_to_msg(o, H), m.Odometry))
    assert same_pose(back.pose, p) and (back.v, back.w) == (o.v, o.w)
    assert same_pose(convert.truth_from_msg(wire(convert.truth_to_msg(p, H), m.PoseStamped)), p)
    assert same_pose(convert.correction_from_msg(
        wire(convert.correction_to_msg(p, H), m.TransformStamped)), p)
    c = Command(0.123456789, -0.5)
    assert convert.command_from_msg(wire(convert.command_to_msg(c, H), m.Twist)) == c


def test_numpy_scalars_are_encoded_as_plain_floats():
    """Odometry with drift is made of numpy float64: it must still encode (it did not)."""
    o = Odom(Pose(np.float64(1.5), np.float64(2.5), np.float64(0.1)), np.float64(0.2), 0.0)
    back = convert.odom_from_msg(wire(convert.odom_to_msg(o, H), m.Odometry))
    assert same_pose(back.pose, o.pose) and back.v == o.v


def test_scan():
    s = Scan(np.random.default_rng(0).uniform(0.02, 8.0, 181), -math.pi / 2, math.pi / 180,
             0.02, 8.0)
    back = convert.scan_from_msg(wire(convert.scan_to_msg(s, H), m.LaserScan))
    assert np.array_equal(back.ranges, s.ranges) and back.ranges.dtype == np.float64
    assert (back.angle_min, back.angle_increment, back.range_min, back.range_max) == (
        s.angle_min, s.angle_increment, s.range_min, s.range_max)


def test_grid():
    a = np.arange(-1, 101, dtype=np.int8)[np.random.default_rng(2).integers(0, 102, (7, 9))]
    g = GridMap(a, GridGeometry(0.1, -3.3, 1.0 / 7.0, 9, 7))
    back = convert.grid_from_msg(wire(convert.grid_to_msg(g, H), m.OccupancyGrid))
    assert np.array_equal(back.data, g.data) and back.data.dtype == np.int8
    assert back.geom == g.geom


def test_graph():
    g = graph()
    same_graph(convert.graph_from_msg(wire(convert.graph_to_msg(g, H), m.TopoGraph)), g)
    empty = Graph.empty(gone=[1])
    same_graph(convert.graph_from_msg(wire(convert.graph_to_msg(empty, H), m.TopoGraph)), empty)


def test_graph_edges_are_views_of_the_flat_points():
    g = graph()
    assert all(np.shares_memory(e.points, g.points) for e in g.edges)
    assert g.edge_labels().tolist() == [0] * 7 + [1] * 2 + [2] * 30
    assert [n.id for n in g.end_nodes()] == [0, 3]


def test_beliefs():
    bs = [Belief(3, 1.0, 2.0, 0.93, 0.8, 0.4, 1.7, 0.6, True, 4, True, 0),
          Belief(8, -1.0, 0.5, 0.5, 0.0, 0.0, math.inf, 0.0, False)]
    assert convert.beliefs_from_msg(wire(convert.beliefs_to_msg(bs, H), m.Reliability)) == bs


@pytest.mark.parametrize("heading", [None, -2.5])
def test_route(heading):
    r = Route(np.array([[0.0, 0.0], [1.0 / 3.0, 2.0], [4.0, 5.5]]), 7, 12, (4.0, 5.5),
              "reliability", heading)
    back = convert.route_from_msg(wire(convert.route_to_msg(r, H), m.Path))
    assert np.array_equal(back.waypoints, r.waypoints)
    assert (back.plan_id, back.target_id, back.target_xy, back.strategy, back.goal_heading) == (
        r.plan_id, r.target_id, r.target_xy, r.strategy, r.goal_heading)
    stop = convert.route_from_msg(wire(convert.route_to_msg(Route(np.zeros((0, 2))), H), m.Path))
    assert stop.waypoints.shape == (0, 2)


def test_status():
    s = Status(ExploreState.DONE, "all 3 reachable end nodes reliable", "reliability", -1, 0.0,
               0, 5, 5, (2, 7), 3)
    back = convert.status_from_msg(wire(convert.status_to_msg(s, H), m.ExploreStatus))
    assert back == s and back.finished and isinstance(back.state, ExploreState)
