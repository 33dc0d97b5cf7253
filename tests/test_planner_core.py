"""Planner core on hand-made topological graphs and grids (DESIGN.md §4 "Planner")."""

from __future__ import annotations

import json
import math

import msgspec
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from topoexplore.common.domain import Belief, ExploreState, Graph, GridMap, Node, Plan
from topoexplore.common.grid import GridGeometry, Occupancy, classify, unknown_mask
from topoexplore.common.params import STRATEGIES, PlannerParams, RobotParams
from topoexplore.services.planner import graph as gr
from topoexplore.services.planner import gridsearch as gs
from topoexplore.services.planner import mapview, strategies
from topoexplore.services.planner.core import PlannerCore
from topoexplore.services.planner.decision import Action, Decision
from topoexplore.services.planner.mapview import MapView
from topoexplore.services.planner.strategies.base import Config
from topoexplore.services.planner.strategies.frontier import opening_mouth

RADIUS = RobotParams().radius

# --- builders --------------------------------------------------------------------------------


def node(i, kind, x, y):
    return Node(i, kind, float(x), float(y))


def edge(a, b, pts, clearance=0.5, step=0.1):
    """Edge a->b along the corner points `pts`, densified to ~step spacing like a skeleton:
    (a, b, points, length, clearance) for Graph.from_edges."""
    pts = np.asarray(pts, dtype=float)
    dense = [pts[0]]
    for p0, p1 in zip(pts[:-1], pts[1:], strict=True):
        n = max(1, int(math.ceil(np.hypot(*(p1 - p0)) / step)))
        for k in range(1, n + 1):
            dense.append(p0 + (p1 - p0) * k / n)
    dense = np.asarray(dense)
    length = float(np.sum(np.hypot(*np.diff(dense, axis=0).T)))
    return (a, b, dense, length, clearance)


def topo(nodes, edges):
    return Graph.from_edges(nodes, edges)


def rel(pmap):
    return [Belief(id=i, x=0.0, y=0.0, p=p, d=0.5, a=0.0, r_min=math.inf, alpha_max=0.0,
                   visible=False) for i, p in pmap.items()]


def grid(g, geom):
    return GridMap(g, geom)


def params(**kw):
    """Planner params of the reliability strategy unless a test says otherwise (these tests
    are mostly about the topological strategies; the default is frontier); done is reported
    at once (done_confirm=1) and the reliability strategy
    does not stop on a complete map (stop_when_mapped: the hand-made grids here are complete
    maps) unless a test says otherwise; paths run along the skeleton (grid_paths off: these
    tests are about the topological path itself, which grid_paths keeps where the grid
    search does not reach, and which the paper's variant drives)."""
    return msgspec.structs.replace(PlannerParams(), **{"strategy": "reliability",
                                                       "done_confirm": 1,
                                                       "stop_when_mapped": False,
                                                       "grid_paths": False, **kw})


def wps(out: Plan) -> list[tuple[float, float]]:
    return [tuple(map(float, w)) for w in out.route.waypoints]


def u_parts(narrow_to_4=False):
    """Robot at the branch node 0 (0, 0).

    End node 3 at (2, 0.5) is the nearest in a straight line (2.06 m) but 9.5 m away along the
    U (up the left arm, across, down the right arm). End node 4 at (-3, 0): 3 m by path.
    End node 5 at (0, -5): 5 m by path.
    """
    nodes = [node(0, "branch", 0, 0), node(1, "corner", 0, 4), node(2, "corner", 2, 4),
             node(3, "end", 2, 0.5), node(4, "end", -3, 0), node(5, "end", 0, -5)]
    edges = [edge(0, 1, [(0, 0), (0, 4)]), edge(1, 2, [(0, 4), (2, 4)]),
             edge(2, 3, [(2, 4), (2, 0.5)]),
             edge(0, 4, [(0, 0), (-3, 0)], clearance=0.15 if narrow_to_4 else 0.5),
             edge(0, 5, [(0, 0), (0, -5)])]
    return nodes, edges


def u_graph(narrow_to_4=False):
    return topo(*u_parts(narrow_to_4))


def dist_to_polylines(pt, tp):
    best = math.inf
    for e in tp.edges:
        p = np.asarray(e.points)
        for a, b in zip(p[:-1], p[1:], strict=True):
            d = b - a
            s = np.clip(np.dot(pt - a, d) / max(np.dot(d, d), 1e-12), 0, 1)
            best = min(best, float(np.hypot(*(a + s * d - pt))))
    return best


POSE = (0.0, 0.0, 0.0)
OPEN = {3: 0.5, 4: 0.5, 5: 0.5}


# --- reliability strategy --------------------------------------------------------------------


def test_waits_for_topo_and_reliability():
    core = PlannerCore(params())
    out = core.update(0.0, POSE, None, None, None)
    assert out.state == "exploring" and wps(out) == [] and "waiting for topo" in out.status.reason
    out = core.update(0.1, POSE, u_graph(), None, None)
    assert out.state == "exploring" and wps(out) == [] and "waiting" in out.status.reason


def test_no_end_nodes_is_done_only_after_a_reliability_update():
    loop = topo([node(0, "branch", 0, 0), node(1, "branch", 2, 0)],
                [edge(0, 1, [(0, 0), (2, 0)]), edge(0, 1, [(0, 0), (1, 1), (2, 0)])])
    core = PlannerCore(params(strategy="all-end-nodes"))
    out = core.update(0.0, POSE, loop, None, None)
    assert out.state == "exploring" and "waiting" in out.status.reason
    out = core.update(0.2, POSE, loop, rel({}), None)
    assert out.state == "exploring" and "waiting" in out.status.reason  # no *earlier* one
    out = core.update(0.4, POSE, loop, rel({}), None)
    assert out.state == "done" and "no end nodes" in out.status.reason


def test_empty_topo_waits_and_done_needs_confirmation():
    core = PlannerCore(params(done_confirm=2))
    empty = topo([], [])
    for k in range(3):
        out = core.update(0.2 * k, POSE, empty, rel({}), None)
        assert out.state == "exploring" and "empty" in out.status.reason
    allrel = {3: 0.95, 4: 0.95, 5: 0.95}
    out = core.update(1.0, POSE, u_graph(), rel(allrel), None)
    assert out.state == "exploring" and wps(out) == []
    assert "confirming (1/2)" in out.status.reason
    out = core.update(1.2, POSE, u_graph(), rel(OPEN), None)
    assert out.state == "exploring" and out.route.target_id == 4  # a candidate resets the count
    out = core.update(1.4, POSE, u_graph(), rel(allrel), None)
    assert out.state == "exploring" and wps(out) == []
    out = core.update(1.6, POSE, u_graph(), rel(allrel), None)
    assert out.state == "done" and out.status.finished


def test_stuck_then_failed_when_the_robot_cannot_join_the_skeleton():
    core = PlannerCore(params(stuck_timeout=10.0))
    nodes, edges = u_parts()
    narrow = topo(nodes, [(a, b, p, ln, 0.1) for a, b, p, ln, _ in edges])
    out = core.update(0.0, POSE, narrow, rel(OPEN), None)
    # stuck, never done: the route turns the robot on the spot to look the other way
    assert out.state == "stuck" and not out.status.finished and "cannot join" in out.status.reason
    assert wps(out) == [(POSE[0], POSE[1])]
    assert out.route.goal_heading == pytest.approx(POSE[2] + math.pi)
    first = out.route.plan_id
    out = core.update(5.0, POSE, narrow, rel(OPEN), None)
    assert out.state == "stuck" and out.route.plan_id == first  # the same recovery
    out = core.update(10.0, POSE, narrow, rel(OPEN), None)
    assert out.state == "failed" and "clearance" in out.status.reason and wps(out) == []
    assert "stuck for 10 s" in out.status.reason


def test_picks_nearest_by_path_cost_not_straight_line():
    core = PlannerCore(params())
    out = core.update(0.0, POSE, u_graph(), rel(OPEN), None)
    assert out.state == "exploring"
    r, s = out.route, out.status
    assert r.target_id == 4, s.reason  # 3 m by path; node 3 is nearer in a straight line
    assert r.target_xy == (-3.0, 0.0) and r.strategy == "reliability"
    assert s.candidates == 3 and s.end_nodes == 3 and s.reliable == 0
    assert s.target_id == 4 and s.target_p == pytest.approx(0.5)


def test_ignores_reliable_nodes_and_reports_done():
    core = PlannerCore(params())
    out = core.update(0.0, POSE, u_graph(), rel({3: 0.5, 4: 0.95, 5: 0.5}), None)
    assert out.route.target_id == 5 and out.status.reliable == 1
    out = core.update(0.2, POSE, u_graph(), rel({3: 0.91, 4: 0.95, 5: 0.99}), None)
    assert out.state == "done" and wps(out) == [] and out.route.target_id == -1
    assert out.route.target_xy == (0.0, 0.0)
    assert "all 3 reachable end nodes reliable (P >= 0.9)" in out.status.reason


def test_never_targets_a_node_behind_a_narrow_gap():
    core = PlannerCore(params())
    out = core.update(0.0, POSE, u_graph(narrow_to_4=True), rel(OPEN), None)
    assert out.route.target_id == 5  # 4 is nearer but behind a 0.15 m clearance edge
    out = core.update(0.2, POSE, u_graph(narrow_to_4=True), rel({3: 0.95, 4: 0.5, 5: 0.95}),
                      None)
    assert out.state == "done" and out.route.target_id == -1
    assert "unreachable" in out.status.reason and "4" in out.status.reason


def test_path_starts_at_robot_follows_edges_and_ends_at_target():
    tp = u_graph()
    core = PlannerCore(params())
    pose = (0.15, 2.2, math.pi / 2)  # slightly off the left arm of the U
    out = core.update(0.0, pose, tp, rel({3: 0.5, 4: 0.95, 5: 0.95}), None)
    assert out.route.target_id == 3
    w = out.route.waypoints
    assert tuple(w[0]) == pytest.approx(pose[:2])
    assert tuple(w[-1]) == pytest.approx((2.0, 0.5))
    assert tuple(w[1]) == pytest.approx((0.0, 2.2), abs=1e-6)  # entry point on the arm
    for p in w[1:]:
        assert dist_to_polylines(p, tp) < 1e-6
    steps = np.hypot(*np.diff(w[1:], axis=0).T)
    assert steps.max() <= 0.35 and steps.min() >= 0.1  # thinned to ~0.25 m
    # corners kept (to the polylines' resampling step, graph.DENSE_STEP)
    assert any(tuple(p) == pytest.approx((0.0, 4.0), abs=gr.DENSE_STEP) for p in w)
    assert any(tuple(p) == pytest.approx((2.0, 4.0), abs=gr.DENSE_STEP) for p in w)
    length = float(np.sum(np.hypot(*np.diff(w, axis=0).T)))
    assert length == pytest.approx(0.15 + 1.8 + 2.0 + 3.5, abs=0.05)  # up, across, down


def test_replans_when_target_becomes_reliable():
    core = PlannerCore(params())
    out1 = core.update(0.0, POSE, u_graph(), rel(OPEN), None)
    assert out1.route.target_id == 4
    out2 = core.update(0.2, POSE, u_graph(), rel(OPEN), None)
    assert out2.route.plan_id == out1.route.plan_id  # nothing changed: same plan
    out3 = core.update(0.4, POSE, u_graph(), rel({3: 0.5, 4: 0.93, 5: 0.5}), None)
    assert out3.route.target_id == 5 and out3.route.plan_id > out1.route.plan_id
    assert "became reliable" in out3.status.reason


def test_replans_when_target_moves_and_when_it_vanishes():
    core = PlannerCore(params())
    out1 = core.update(0.0, POSE, u_graph(), rel(OPEN), None)
    nodes, edges = u_parts()
    nodes[4] = node(4, "end", -3.6, 0)
    edges[3] = edge(0, 4, [(0, 0), (-3.6, 0)])
    out2 = core.update(0.2, POSE, topo(nodes, edges), rel(OPEN), None)
    assert out2.route.target_id == 4 and out2.route.plan_id == out1.route.plan_id + 1
    assert wps(out2)[-1] == pytest.approx((-3.6, 0.0))
    nodes, edges = u_parts()
    del nodes[4]
    del edges[3]
    out3 = core.update(0.4, POSE, topo(nodes, edges), rel(OPEN), None)
    assert out3.route.target_id == 5 and "vanished" in out3.status.reason


def test_ties_prefer_the_node_ahead():
    tp = topo([node(1, "end", -3, 0), node(2, "end", 3.2, 0)],
              [edge(1, 2, [(-3, 0), (3.2, 0)])])
    out = PlannerCore(params()).update(0.0, (0, 0, 0.0), tp, rel({1: 0.5, 2: 0.5}), None)
    assert out.route.target_id == 2  # 3.2 m ahead beats 3.0 m behind (within the tie tolerance)
    out = PlannerCore(params()).update(0.0, (0, 0, math.pi), tp, rel({1: 0.5, 2: 0.5}), None)
    assert out.route.target_id == 1


def with_node_6(x):
    nodes, edges = u_parts()
    return topo(nodes + [node(6, "end", x, 0)], edges + [edge(0, 6, [(0, 0), (x, 0)])])


def test_switches_only_to_a_much_cheaper_target():
    core = PlannerCore(params())
    assert core.update(0.0, POSE, u_graph(), rel(OPEN), None).route.target_id == 4
    out = core.update(2.5, POSE, with_node_6(2.3), rel({**OPEN, 6: 0.5}), None)
    assert out.route.target_id == 4  # 2.3 m: not < 0.7 * 3 m
    out = core.update(3.0, POSE, with_node_6(1.5), rel({**OPEN, 6: 0.5}), None)
    assert out.route.target_id == 4  # re-evaluated at most every replan_period (2 s)
    out = core.update(5.0, POSE, with_node_6(1.5), rel({**OPEN, 6: 0.5}), None)
    assert out.route.target_id == 6 and "switched from end node 4" in out.status.reason
    assert out.status.replans == 1


def test_blacklists_after_no_progress_by_id_and_position():
    core = PlannerCore(params(progress_timeout=20.0, max_attempts=2))
    out = core.update(0.0, POSE, u_graph(), rel(OPEN), None)
    assert out.route.target_id == 4
    t = 0.0
    for _ in range(30):  # the robot never moves
        t += 1.0
        out = core.update(t, POSE, u_graph(), rel(OPEN), None)
    assert out.route.target_id == 4 and out.status.blacklisted == ()
    assert out.status.replans == 1  # the first failure
    reasons = []
    for _ in range(15):
        t += 1.0
        out = core.update(t, POSE, u_graph(), rel(OPEN), None)
        reasons.append(out.status.reason)
    assert out.status.blacklisted == (4,) and out.route.target_id == 5
    assert any("blacklisted end node 4" in r and "no progress" in r for r in reasons)
    assert "blacklisted: 4" in out.status.reason  # stays visible while exploring goes on
    # the same place under a new id stays blacklisted
    nodes, edges = u_parts()
    nodes[4] = node(9, "end", -3.1, 0)
    edges[3] = edge(0, 9, [(0, 0), (-3.1, 0)])
    renamed = topo(nodes, edges)
    out = core.update(t + 1, POSE, renamed, rel({3: 0.5, 9: 0.5, 5: 0.5}), None)
    assert out.route.target_id == 5
    out = core.update(t + 2, POSE, renamed, rel({3: 0.95, 9: 0.5, 5: 0.95}), None)
    # the robot stood still while following: the learned blockages go first (done withheld)
    assert "done withheld" in out.status.reason
    out = core.update(t + 3, POSE, renamed, rel({3: 0.95, 9: 0.5, 5: 0.95}), None)
    assert out.state == "done" and "1 blacklisted" in out.status.reason
    snap = core.snapshot()
    assert snap["blacklist"][0]["id"] == 4 and "no progress" in snap["blacklist"][0]["reason"]
    assert snap["state"] == "done" and snap["failures"][0]["count"] == 2


def test_progress_along_the_path_prevents_blacklisting():
    core = PlannerCore(params(progress_timeout=5.0, max_attempts=1))
    out = core.update(0.0, POSE, u_graph(), rel(OPEN), None)
    assert out.route.target_id == 4
    for k in range(1, 20):  # 0.1 m/s toward node 4 along the edge
        out = core.update(float(k), (-0.1 * k, 0.0, math.pi), u_graph(), rel(OPEN), None)
    assert out.route.target_id == 4 and out.status.blacklisted == ()


def test_entry_point_needs_line_of_sight_on_the_grid():
    # two parallel corridors' skeletons; a wall hides the nearer one from the robot
    tp = topo([node(1, "end", -2, 1.0), node(2, "end", 2, 1.0), node(3, "end", -2, -1.5),
               node(4, "end", 2, -1.5), node(5, "branch", -2.5, -0.25)],
              [edge(1, 5, [(-2, 1.0), (-2.5, -0.25)]), edge(5, 3, [(-2.5, -0.25), (-2, -1.5)]),
               edge(1, 2, [(-2, 1.0), (2, 1.0)]), edge(3, 4, [(-2, -1.5), (2, -1.5)])])
    geom = GridGeometry(0.1, -4.0, -4.0, 80, 80)
    g = np.zeros((80, 80), dtype=np.int8)
    g[44:46, 20:70] = 100  # wall at y in [0.4, 0.6], x in [-2, 3]
    pr = {1: 0.95, 2: 0.95, 3: 0.95, 4: 0.5}
    out = PlannerCore(params()).update(0.0, (0.0, 0.0, 0.0), tp, rel(pr), grid(g, geom))
    assert out.route.target_id == 4
    assert wps(out)[1] == pytest.approx((0.0, -1.5), abs=1e-6)  # joins the visible edge
    out = PlannerCore(params()).update(0.0, (0.0, 0.0, 0.0), tp, rel(pr), None)
    assert wps(out)[1] == pytest.approx((0.0, 1.0), abs=1e-6)  # no grid: nearest point


@given(st.lists(st.sampled_from([0.0, 0.5, 1.0, 1.5, 2.0, math.inf, math.nan]), max_size=40),
       st.integers(1, 45))
@settings(max_examples=300, deadline=None)
def test_nearest_first_is_the_head_of_a_stable_argsort(values, k):
    """find_entry's partial sort: the same indices in the same order as a whole stable sort
    (ties in index order, NaN last), so the entry chosen does not change."""
    v = np.array(values, dtype=float)
    assert gr.nearest_first(v, k).tolist() == np.argsort(v, kind="stable")[:k].tolist()


def _entry_by_loops(index, x, y, visible, max_checks=64):
    """find_entry the long way: every segment of every edge in order, the nearest first
    (ties, to gr.TIE_DECIMALS: the earlier segment), the first visible among the max_checks
    nearest."""
    segs = []
    for pos, e in enumerate(index.edges):
        for i in range(len(e.pts) - 1):
            p0, d = e.pts[i], e.pts[i + 1] - e.pts[i]
            dd = float(d @ d)
            t = min(max(float((np.array([x, y]) - p0) @ d) / dd, 0.0), 1.0) if dd > 0 else 0.0
            nx, ny = p0 + t * d
            segs.append((round(math.hypot(nx - x, ny - y), gr.TIE_DECIMALS), len(segs), pos, i,
                         nx, ny))
    segs.sort(key=lambda s: (s[0], s[1]))
    for s in segs[:max_checks]:
        if visible(x, y, s[4], s[5]):
            return s, True
    return segs[0], False


@given(st.lists(st.lists(st.tuples(st.integers(-6, 6), st.integers(-6, 6)), min_size=2,
                         max_size=5), min_size=1, max_size=6),
       st.floats(-7, 7), st.floats(-7, 7), st.integers(0, 8))
@settings(max_examples=100, deadline=None)
def test_find_entry_is_the_nearest_visible_segment(lines, x, y, checks):
    """find_entry's vectorised search over all edges' segments at once (the joins between
    one edge's last point and the next edge's first are no segment) picks the segment a
    plain loop picks: ties to the earlier one, the first visible of the max_checks nearest."""
    nodes, edges = [], []
    for k, pts in enumerate(lines):
        a, b = 2 * k, 2 * k + 1
        nodes += [node(a, "end", *pts[0]), node(b, "end", *pts[-1])]
        edges.append((a, b, [list(map(float, p)) for p in pts], 0.0, 1.0))
    index = gr.build_index(topo(nodes, edges), 0.25)

    def visible(x0, y0, x1, y1):
        return x1 + y1 > 0.5

    for vis in (None, visible):
        got = gr.find_entry(index, x, y, vis, checks)
        want, los = _entry_by_loops(index, x, y, vis or (lambda *a: True), max(checks, 1))
        if vis is not None and checks == 0:
            want, los = _entry_by_loops(index, x, y, lambda *a: False)
        assert (got.edge.idx, got.seg, got.line_of_sight) == (index.edges[want[2]].idx,
                                                               want[3], los)
        assert (got.x, got.y, got.dist) == pytest.approx((want[4], want[5], want[0]))


def test_astar_matches_single_source_search():
    index = gr.build_index(u_graph(), 0.25)
    entry = gr.find_entry(index, 0.3, 1.0)
    dist, _ = gr.search_from_entry(index, entry)
    for i in (3, 4, 5):
        assert gr.astar_cost(index, entry, i) == pytest.approx(dist[i])
    assert dist[3] == pytest.approx(0.3 + 3.0 + 2.0 + 3.5)


# --- all-end-nodes ---------------------------------------------------------------------------


def test_all_end_nodes_visits_reliable_nodes_and_marks_visited():
    core = PlannerCore(params(strategy="all-end-nodes"))
    allrel = {3: 0.99, 4: 0.99, 5: 0.99}
    out = core.update(0.0, POSE, u_graph(), rel(allrel), None)
    assert out.state == "exploring" and out.route.target_id == 4 and out.status.target_p == 0.0
    out = core.update(1.0, (-2.6, 0.0, math.pi), u_graph(), rel(allrel), None)
    assert out.route.target_id == 5 and "visited" in out.status.reason  # within 0.5 m of 4
    # node 4 moves a little but stays within visit_radius of where the robot was: still visited
    nodes, edges = u_parts()
    nodes[4] = node(4, "end", -3.05, 0)
    edges[3] = edge(0, 4, [(0, 0), (-3.05, 0)])
    tp = topo(nodes, edges)
    out = core.update(2.0, (0.0, -4.8, -math.pi / 2), tp, rel(allrel), None)
    assert out.route.target_id == 3
    out = core.update(3.0, (2.0, 0.6, -math.pi / 2), tp, rel(allrel), None)
    assert out.state == "done" and "all 3 reachable end nodes visited" in out.status.reason
    assert core.snapshot()["visited_positions"] == 4


# --- frontier --------------------------------------------------------------------------------


def half_known_room():
    """6 m x 6 m room with walls; the left half is known free, the right half unknown."""
    geom = GridGeometry(0.1, 0.0, 0.0, 60, 60)
    g = np.full((60, 60), -1, dtype=np.int8)
    g[:, :30] = 0
    g[0, :30] = 100
    g[-1, :30] = 100
    g[:, 0] = 100
    return g, geom


def frontier_core(**kw):
    return PlannerCore(params(strategy="frontier", **kw))


def test_frontier_goal_at_the_frontier_with_grid_path_length():
    g, geom = half_known_room()
    out = frontier_core().update(0.0, (1.05, 3.05, 0.0), None, None, grid(g, geom))
    assert out.state == "exploring" and out.route.target_id == -1
    gx, gy = out.route.target_xy
    assert gx == pytest.approx(2.95)  # the last known free column, next to unknown
    assert 2.5 < gy < 3.5  # the reachable cell nearest the centroid of the frontier group
    w = out.route.waypoints
    assert tuple(w[0]) == pytest.approx((1.05, 3.05)) and tuple(w[-1]) == pytest.approx((gx, gy))
    length = float(np.sum(np.hypot(*np.diff(w, axis=0).T)))
    assert length == pytest.approx(math.hypot(gx - 1.05, gy - 3.05), abs=0.15)
    assert "frontier" in out.status.reason and out.route.strategy == "frontier"


def test_frontier_goal_faces_the_unknown_it_is_meant_to_reveal():
    g, geom = half_known_room()
    out = frontier_core().update(0.0, (1.05, 3.05, 0.0), None, None, grid(g, geom))
    heading = out.route.goal_heading
    assert heading is not None and abs(heading) < 0.3  # unknown is at +x
    # the frontier right behind a robot that has only seen ahead: turn around at the goal
    g2 = np.full((60, 60), -1, dtype=np.int8)
    g2[:, 20:] = 0
    g2[0, 20:] = g2[-1, 20:] = g2[:, -1] = 100
    out = frontier_core().update(0.0, (2.15, 3.05, 0.0), None, None, grid(g2, geom))
    heading = out.route.goal_heading
    assert heading is not None and abs(abs(heading) - math.pi) < 0.3
    look = gs.look_point(np.zeros((60, 60), bool), geom, (30, 30), 1.0)
    assert look is None  # nothing unknown near the goal: no heading
    assert PlannerCore(params()).update(0.0, POSE, u_graph(), rel(OPEN),
                                        None).route.goal_heading is None  # topological: none


def test_frontier_path_goes_around_a_wall():
    g, geom = half_known_room()
    g[1:50, 15] = 100  # wall with a gap at the top (rows 50..58)
    view = MapView(grid(g, geom), Occupancy())
    search = view.search(0.55, 1.05, 0.2)
    groups, _ = gs.find_frontiers(view.free, view.unknown, view.geom, search, 0.5, 3.0, 1.0)
    assert len(groups) == 1
    out = frontier_core().update(0.0, (0.55, 1.05, 0.0), None, None, grid(g, geom))
    w = out.route.waypoints
    length = float(np.sum(np.hypot(*np.diff(w, axis=0).T)))
    assert groups[0].path_length > 6.0  # around the wall, not the 2.4 m straight line
    assert length == pytest.approx(groups[0].path_length, rel=0.1)
    assert w[:, 1].max() > 5.0  # through the gap


def test_frontier_start_cell_unknown_and_done_when_no_frontier():
    g, geom = half_known_room()
    g[29:32, 9:12] = -1  # the robot's own cells are still unknown (enclosed: a tiny hole)
    out = frontier_core().update(0.0, (1.05, 3.05, 0.0), None, None, grid(g, geom))
    assert out.state == "exploring" and wps(out)
    full = np.zeros((60, 60), dtype=np.int8)
    full[0, :] = full[-1, :] = full[:, 0] = full[:, -1] = 100
    core = frontier_core()
    out = core.update(0.0, (1.05, 3.05, 0.0), None, None, grid(full, geom))
    assert out.state == "done" and wps(out) == [] and "no frontier" in out.status.reason
    out = core.update(0.0, (1.05, 3.05, 0.0), None, None, None)
    assert out.state == "exploring" and "waiting for map" in out.status.reason


@pytest.mark.parametrize("strategy", ["frontier", "reliability"])
def test_a_wall_face_cleared_by_grazing_beams_is_no_frontier(strategy):
    """A room mapped whole, then 1.5 m of its right wall cleared (grazing beams from afar, the
    wall's inside never seen): with the surface memory (on by default) the robot that saw the
    wall occupied on surface_views updates is done; without it the cleared face is a
    frontier to drive to."""
    geom = GridGeometry(0.1, 0.0, 0.0, 60, 60)
    whole = np.zeros((60, 60), dtype=np.int8)
    whole[0, :] = whole[-1, :] = whole[:, 0] = whole[:, -1] = 100
    cleared = whole.copy()
    cleared[20:35, -1] = 0
    pose = (1.05, 3.05, 0.0)
    loop = topo([node(0, "branch", 1, 3), node(1, "branch", 4, 3)],  # no end node: the
                [edge(0, 1, [(1, 3), (4, 3)]), edge(0, 1, [(1, 3), (2.5, 4), (4, 3)])])
    #   reliability strategy goes on with its completion rules

    def update(core, t, g):
        return core.update(t, pose, loop, rel({}), grid(g, geom))

    kw = {"strategy": strategy, "stop_when_mapped": True}
    for views, state in ((PlannerParams().surface_views, "done"), (0, "exploring")):
        assert views > 0 or state == "exploring"
        core = PlannerCore(params(surface_views=views, **kw))
        for t in range(max(views, 1)):
            update(core, 0.4 * t, whole)
        out = update(core, 2.0, cleared)
        assert out.state == state, out.status.reason
        if state == "exploring":
            assert out.route.target_xy[0] > 5.5  # to the cleared face
    core = PlannerCore(params(surface_views=3, **kw))  # seen occupied twice: not yet a surface
    for t in range(2):
        update(core, 0.4 * t, whole)
    assert update(core, 2.0, cleared).state == "exploring"


def test_frontier_drops_small_groups_and_blacklists_a_stuck_goal():
    g, geom = half_known_room()
    g[1:59, 29] = 100  # wall the right side off ...
    g[30:33, 29] = 0  # ... except a 0.3 m hole: a frontier of 3 cells < 0.5 m
    out = frontier_core().update(0.0, (1.05, 3.05, 0.0), None, None, grid(g, geom))
    assert out.state == "done" and "shorter than 0.5 m" in out.status.reason
    g, geom = half_known_room()
    core = frontier_core(progress_timeout=5.0, max_attempts=1)
    out = core.update(0.0, (1.05, 3.05, 0.0), None, None, grid(g, geom))
    for k in range(1, 8):
        out = core.update(float(k), (1.05, 3.05, 0.0), None, None, grid(g, geom))
    assert out.status.blacklisted == (0,) and out.state == "done"
    assert "blacklisted" in out.status.reason


def test_frontier_undecided_band_counts_as_unknown_but_wall_specks_do_not():
    g, geom = half_known_room()
    g[:, 30:33] = 50  # once-seen band between free and never-seen space
    g[20, 5] = 50  # an undecided speck enclosed by free cells
    free = (g >= 0) & (g < 35)
    unk = unknown_mask(g)
    assert unk[:, 30:33].all() and not unk[20, 5]
    fm = gs.frontier_mask(free, unk)
    assert fm[5:55, 29].all() and not fm[19:22, 4:7].any()


def corridor_grid():
    """Corridor x in [0, 6], y in [0, 1] (walls one cell thick around it), all known."""
    geom = GridGeometry(0.1, -1.0, -1.0, 90, 40)
    g = np.full((40, 90), -1, dtype=np.int8)
    g[9:21, 9:71] = 100
    g[10:20, 10:70] = 0  # free: x in [0, 6), y in [0, 1)
    return g, geom


def door_parts(b=2, wide=False):
    """End node 1 and branch node 0 at the corridor's left end, end node b at its right end;
    the edge to b bends through the door at x = 2 (or runs straight when wide)."""
    nodes = [node(1, "end", 0.5, 0.5), node(0, "branch", 1.0, 0.5), node(b, "end", 5.5, 0.5)]
    to_b = (edge(0, b, [(1.0, 0.5), (5.5, 0.5)], clearance=0.2) if wide else
            edge(0, b, [(1.0, 0.5), (1.9, 0.5), (2.05, 0.85), (2.2, 0.5), (5.5, 0.5)]))
    return nodes, [edge(1, 0, [(0.5, 0.5), (1.0, 0.5)]), to_b]


def test_grid_clearance_lets_the_robot_into_a_dead_end_but_not_through_a_gap():
    g, geom = corridor_grid()
    # leaf edge to a dead-end corner: the graph says 0.2 m (its tip), the grid agrees only
    # at the tip; the path stops where the corridor narrows, within tip_length of the node
    tp = topo([node(1, "end", 0.5, 0.5), node(2, "end", 5.85, 0.85)],
              [edge(1, 2, [(0.5, 0.5), (5.5, 0.5), (5.85, 0.85)], clearance=0.2)])
    core = PlannerCore(params())
    out = core.update(0.0, (0.5, 0.5, 0.0), tp, rel({1: 0.95, 2: 0.5}), grid(g, geom))
    assert out.route.target_id == 2, out.status.reason
    end = out.route.waypoints[-1]
    assert 0.0 < np.hypot(*(end - (5.85, 0.85))) <= 0.3 + 1e-6
    # without a grid the graph's clearance (0.2 m < 0.25 m) rules: no way onto the skeleton
    out = PlannerCore(params()).update(0.0, (0.5, 0.5, 0.0), tp, rel({1: 0.95, 2: 0.5}), None)
    assert out.route.target_id == -1 and out.state == "stuck"
    assert "cannot join" in out.status.reason
    # a 0.3 m wide door in the middle of the corridor: not passable whatever the graph says
    g[10:17, 30] = 100  # wall at x in [2.0, 2.1] except y in [0.7, 1.0]
    core = PlannerCore(params(approach_narrow=False))
    out = core.update(0.0, (0.6, 0.5, 0.0), topo(*door_parts()), rel({1: 0.95, 2: 0.5}),
                      grid(g, geom))
    assert out.state == "done" and "unreachable" in out.status.reason
    assert "2" in out.status.reason
    g[10:17, 30] = 0  # door gone, the skeleton runs down the middle: reachable
    out = core.update(0.2, (0.6, 0.5, 0.0), topo(*door_parts(wide=True)),
                      rel({1: 0.95, 2: 0.5}), grid(g, geom))
    assert out.route.target_id == 2


def test_trim_narrow_tip_keeps_the_wide_part():
    pts = np.array([[0.0, 0.0], [1.0, 0.0], [1.1, 0.0], [1.2, 0.0], [1.3, 0.0]])
    clear = lambda p: np.where(p[:, 0] > 1.05, 0.1, 0.5)  # noqa: E731
    out = gr.trim_narrow_tip(pts, clear, 0.25, 0.3)
    assert out.tolist() == [[0.0, 0.0], [1.0, 0.0]]
    out = gr.trim_narrow_tip(pts, clear, 0.25, 0.15)  # narrow for longer than the tip: keep
    assert len(out) == len(pts) - 2 or len(out) == len(pts)


def test_a_node_behind_a_narrow_passage_in_mapped_surroundings_is_not_approached():
    """Everything within approach_radius of the node is mapped: looking through the gap
    would show nothing new, so the node is unreachable at once (clutter: most such nodes lie
    between furniture in mapped rooms); with approach_radius 0 it is approached."""
    g, geom = corridor_grid()
    g[10:17, 30] = 100
    tp = topo(*door_parts())
    out = PlannerCore(params()).update(0.0, (0.6, 0.5, 0.0), tp, rel({1: 0.95, 2: 0.5}),
                                       grid(g, geom))
    assert out.state == "done" and "(ids 2)" in out.status.reason, out.status.reason
    out = PlannerCore(params(approach_radius=0.0)).update(
        0.0, (0.6, 0.5, 0.0), tp, rel({1: 0.95, 2: 0.5}), grid(g, geom))
    assert out.state == "exploring" and "narrow passage" in out.status.reason


def test_approaches_a_node_behind_a_narrow_passage_once():
    """An open end node behind a narrow point: the robot goes up to the narrow point (where it
    can look through), never beyond; standing there the node counts as unreachable, and the
    way becoming wide gives the whole path."""
    g, geom = corridor_grid()
    g[10:17, 30] = 100  # 0.3 m door at x in [2.0, 2.1]
    g[10:20, 60:71] = -1  # unexplored beyond x = 5 m: something to look at through the door
    tp = topo(*door_parts())
    p = params()
    core = PlannerCore(p)
    out = core.update(0.0, (0.6, 0.5, 0.0), tp, rel({1: 0.95, 2: 0.5}), grid(g, geom))
    assert out.state == "exploring" and out.route.target_id == 2, out.status.reason
    assert "narrow passage" in out.status.reason
    w = out.route.waypoints
    clear = gr.grid_clearance(gs.clearance_map(g > 65, geom.resolution), geom)(w)
    assert np.all(clear >= RADIUS + p.clearance_margin - 1e-9)
    stop = w[-1]
    assert 1.3 < stop[0] < 2.0, stop  # up to the door, not through it
    # standing at the narrow point the robot has looked: the node is unreachable, done
    pose = (float(stop[0]) - 0.2, float(stop[1]), 0.0)
    out = core.update(1.0, pose, tp, rel({1: 0.95, 2: 0.5}), grid(g, geom))
    assert out.state == "done" and "unreachable" in out.status.reason
    assert "(ids 2)" in out.status.reason
    # ... and stays so once the robot has left (it used to shuttle back and forth), also when
    # the node got a new id
    for k, tpk in enumerate((tp, topo(*door_parts(b=7)))):
        out = core.update(2.0 + k, (0.6, 0.5, 0.0), tpk, rel({1: 0.95, 2: 0.5, 7: 0.5}),
                          grid(g, geom))
        assert out.state == "done" and "unreachable" in out.status.reason, out.status.reason
    assert [b["id"] for b in core.snapshot()["looked"]] == [2]
    # the door opens while the robot approaches: a new path to the node itself
    core3 = PlannerCore(p)
    out = core3.update(0.0, (0.6, 0.5, 0.0), tp, rel({1: 0.95, 2: 0.5}), grid(g, geom))
    assert "narrow passage" in out.status.reason
    g[10:17, 30] = 0
    out = core3.update(0.2, (0.8, 0.5, 0.0), topo(*door_parts(wide=True)),
                       rel({1: 0.95, 2: 0.5}), grid(g, geom))
    assert out.route.target_id == 2 and "wide now" in out.status.reason
    assert np.hypot(*(out.route.waypoints[-1] - (5.5, 0.5))) < 0.35


def test_a_narrow_stretch_of_the_skeleton_in_an_open_room_is_driven_around():
    """The skeleton is one line through a room: where it passes a table leg it is narrow, but
    the room is wide. With grid_paths the grid search (the body and clearance the controller
    drives with) decides: the node is a whole candidate on the way around the leg (a large
    office: a room's node stayed "up to a narrow passage", was given up, and the room behind
    it never seen). A door narrower than the body stays narrow."""
    geom = GridGeometry(0.1, -1.0, -1.0, 60, 50)
    g = np.full((50, 60), 100, dtype=np.int8)
    g[10:40, 10:50] = 0  # free: x in [0, 4), y in [0, 3)
    g[26, 30] = 100  # a table leg at x in [2.0, 2.1], y in [1.6, 1.7]
    g[20:30, 50:60] = -1  # a door out of the room at x = 4 m, unexplored beyond
    tp = topo([node(1, "end", 0.5, 1.5), node(2, "end", 3.5, 1.5)],
              [edge(1, 2, [(0.5, 1.5), (3.5, 1.5)], clearance=0.1)])
    beliefs = rel({1: 0.95, 2: 0.5})
    p = params(grid_paths=True)
    out = PlannerCore(p).update(0.0, (0.6, 1.5, 0.0), tp, beliefs, grid(g, geom))
    assert out.state == "exploring" and out.route.target_id == 2, out.status.reason
    assert "around a narrow stretch" in out.status.reason
    w = out.route.waypoints
    clear = gr.grid_clearance(gs.clearance_map(g > 65, geom.resolution), geom)(w)
    assert np.all(clear >= RADIUS + p.clearance_margin - 1e-9)
    assert np.hypot(*(w[-1] - (3.5, 1.5))) <= p.tip_length + 0.1
    # without grid_paths (the skeleton path alone) only up to the leg
    out = PlannerCore(params()).update(0.0, (0.6, 1.5, 0.0), tp, beliefs, grid(g, geom))
    assert "up to a narrow passage" in out.status.reason, out.status.reason
    assert out.route.waypoints[-1][0] < 2.0
    # which nodes are targets does not change: with everything around it mapped, a node
    # behind a narrow stretch is still not one (approach_radius: nothing to look at)
    closed = np.where(g < 0, 100, g).astype(np.int8)
    out = PlannerCore(p).update(0.0, (0.6, 1.5, 0.0), tp, beliefs, grid(closed, geom))
    assert out.state == "done" and "(ids 2)" in out.status.reason, out.status.reason
    # a wall across the room with a 0.3 m door: the grid search does not get through either
    g[10:40, 30] = 100
    g[24:27, 30] = 0  # the door: y in [1.4, 1.7]
    p = params(grid_paths=True, approach_radius=0.0)  # approached whatever lies beyond
    out = PlannerCore(p).update(0.0, (0.6, 1.5, 0.0), tp, beliefs, grid(g, geom))
    assert "around" not in out.status.reason
    assert out.state == "exploring" and "narrow passage" in out.status.reason


def test_build_index_splits_an_edge_at_its_narrow_stretch():
    """A long edge narrow only in its middle keeps its wide ends traversable up to "cut"
    nodes (negative ids); only the middle is narrow."""
    tp = topo([node(1, "end", 0.0, 0.5), node(2, "end", 6.0, 0.5)],
              [edge(1, 2, [(0.0, 0.5), (6.0, 0.5)])])
    clear = lambda p: np.where(np.abs(p[:, 0] - 3.0) < 0.3, 0.1, 0.5)  # noqa: E731
    index = gr.build_index(tp, 0.25, clear, 0.3)
    cuts = [i for i, n in index.nodes.items() if n[0] == "cut"]
    assert len(cuts) == 2 and all(i < -1 for i in cuts)
    assert len(index.edges) == 2 and len(index.narrow) == 1
    mid = index.narrow[0]
    assert {mid.a, mid.b} == set(cuts)
    assert np.all(np.abs(mid.pts[1:-1, 0] - 3.0) < 0.3)
    wide = {(e.a, e.b) for e in index.edges}
    assert any(1 in ab for ab in wide) and any(2 in ab for ab in wide)
    for e in index.edges + index.narrow:
        assert e.cum[0] == 0.0 and e.length == pytest.approx(e.cum[-1])
    for e in index.edges:
        assert e.clearance >= 0.25
    # narrow over its whole length: one narrow edge, nothing cut
    index = gr.build_index(tp, 0.25, lambda p: np.full(len(p), 0.1), 0.3)
    assert len(index.narrow) == 1 and not index.edges
    assert not [i for i, n in index.nodes.items() if n[0] == "cut"]


def test_build_index_orients_and_anchors_polylines_and_drops_self_loops():
    tp = topo([node(1, "end", 0.0, 0.0), node(2, "branch", 2.0, 0.0)],
              [(1, 2, [[2.0, 0.0], [1.0, 0.0]], 2.0, 0.5),  # given b -> a, not at node a
               (2, 2, [[2.0, 0.0], [2.5, 0.5], [2.0, 0.0]], 1.4, 0.5)])
    index = gr.build_index(tp, 0.25)
    assert len(index.edges) == 1
    pts = index.edges[0].pts  # oriented a -> b, anchored, resampled every DENSE_STEP at most
    assert pts[0].tolist() == [0.0, 0.0] and pts[-1].tolist() == [2.0, 0.0]
    assert [1.0, 0.0] in pts.tolist() and np.all(pts[:, 1] == 0.0)
    assert np.all(np.diff(pts[:, 0]) > 0) and np.diff(pts[:, 0]).max() <= gr.DENSE_STEP + 1e-9
    assert index.adj[1] == [(2, 2.0, 0, True)] and index.adj[2] == [(1, 2.0, 0, False)]
    with pytest.raises(gr.GraphInputError):
        gr.build_index(topo([node(1, "end", 0.0, 0.0)], [edge(1, 3, [(0, 0), (1, 0)])]), 0.25)


def _index_figures(index):
    """What a TopoIndex holds, as plain values to compare."""
    edges = [(e.idx, e.a, e.b, e.pts.tolist(), e.cum.tolist(), e.clearance)
             for e in index.edges + index.narrow]
    return index.nodes, edges, index.adj, index.narrow_adj


def test_polyline_cache_gives_the_index_a_fresh_build_gives():
    """The polylines kept from the last update (PolylineCache) make the same index as a build
    from scratch, whatever changed between the two graphs: an edge's points, a node that
    moved, an edge given the other way round, a new edge, one gone."""
    clear = lambda p: np.where(np.abs(p[:, 0] - 3.0) < 0.3, 0.1, 0.5)  # noqa: E731
    n1, n2, n3 = node(1, "end", 0.0, 0.5), node(2, "branch", 6.0, 0.5), node(3, "end", 6.0, 3.0)
    graphs = [
        topo([n1, n2, n3], [edge(1, 2, [(0.0, 0.5), (6.0, 0.5)]),
                            edge(2, 3, [(6.0, 0.5), (6.0, 3.0)])]),
        topo([n1, n2, n3], [edge(1, 2, [(0.0, 0.5), (6.0, 0.5)]),  # 2-3 bends now
                            edge(2, 3, [(6.0, 0.5), (6.5, 2.0), (6.0, 3.0)])]),
        topo([n1, n2, node(3, "end", 6.0, 3.4)],  # node 3 moved: the same points, new anchor
             [edge(1, 2, [(0.0, 0.5), (6.0, 0.5)]),
              edge(2, 3, [(6.0, 0.5), (6.5, 2.0), (6.0, 3.0)])]),
        topo([n1, n2, n3], [edge(2, 1, [(6.0, 0.5), (0.0, 0.5)]),  # the other way round
                            edge(2, 3, [(6.0, 0.5), (6.0, 3.0)]),
                            edge(3, 3, [(6.0, 3.0), (7.0, 3.5), (6.0, 3.0)])]),
        topo([n1, n2], [edge(1, 2, [(0.0, 0.5), (6.0, 0.5)])]),
        topo([n1, n2], []),
        topo([n1, n2, n3], [edge(1, 2, [(0.0, 0.5), (6.0, 0.5)]),
                            edge(2, 3, [(6.0, 0.5), (6.0, 3.0)])]),
    ]
    cache = gr.PolylineCache()
    for g in graphs + graphs[::-1]:
        kept = gr.build_index(g, 0.25, clear, 0.3, cache)
        assert _index_figures(kept) == _index_figures(gr.build_index(g, 0.25, clear, 0.3))


def test_the_index_is_kept_while_graph_and_clearance_stay_the_same():
    """The same graph sent again (a new object, equal in every node, edge and point) with the
    same clearance along it gives the index made before; a moved point, another node kind,
    a clearance changed at one polyline point or another argument make it afresh, as a
    build without the cache would."""
    narrow_at = [3.0]
    clear = lambda p: np.where(np.abs(p[:, 0] - narrow_at[0]) < 0.3, 0.1, 0.5)  # noqa: E731

    def make(kind="end", y3=3.0):
        return topo([node(1, "end", 0.0, 0.5), node(2, "branch", 6.0, 0.5),
                     node(3, kind, 6.0, y3)],
                    [edge(1, 2, [(0.0, 0.5), (6.0, 0.5)]), edge(2, 3, [(6.0, 0.5), (6.0, y3)])])

    cache = gr.PolylineCache()
    first = gr.build_index(make(), 0.25, clear, 0.3, cache)
    assert gr.build_index(make(), 0.25, clear, 0.3, cache) is first and cache.reused == 1
    for g, args in ((make(y3=3.2), (0.25, 0.3)), (make(kind="branch"), (0.25, 0.3)),
                    (make(), (0.3, 0.3)), (make(), (0.25, 0.0))):
        got = gr.build_index(g, *args[:1], clear, args[1], cache)
        assert got is not first
        assert _index_figures(got) == _index_figures(gr.build_index(g, args[0], clear, args[1]))
        first = got
    narrow_at[0] = 2.0  # the clearance changed along edge 1-2
    got = gr.build_index(make(), 0.25, clear, 0.0, cache)
    assert got is not first and cache.reused == 1
    assert _index_figures(got) == _index_figures(gr.build_index(make(), 0.25, clear, 0.0))


def test_clearance_keeper_gives_the_whole_maps_capped_clearance_bit_for_bit():
    """Update after update (a few cells changed, none, a wall drawn, one erased, the grid
    grown), the kept clearance is exactly the capped clearance of the whole map made afresh,
    read-only, and below the cap the same as the uncapped clearance."""
    rng = np.random.default_rng(3)
    res, cap = 0.1, 0.7
    keeper = gs.ClearanceKeeper(cap)
    occ = rng.random((90, 120)) < 0.01
    geom = GridGeometry(res, 0.0, 0.0, 120, 90)
    for k in range(40):
        occ = occ.copy()
        if k % 10 == 9:  # the grid grown (new geometry): made afresh
            occ = np.pad(occ, ((0, 10), (5, 0)))
            geom = GridGeometry(res, geom.origin_x - 5 * res, 0.0, occ.shape[1], occ.shape[0])
        elif k % 5 == 2:
            pass  # nothing changed
        elif k % 5 == 3:  # a wall drawn, or erased where one stood
            r, c = rng.integers(0, occ.shape[0] - 12), rng.integers(0, occ.shape[1] - 30)
            occ[r, c:c + 30] = not occ[r, c]
        else:  # a few cells round one place (one scan's hits), the last one anywhere
            r, c = rng.integers(0, occ.shape[0] - 10), rng.integers(0, occ.shape[1] - 10)
            rows, cols = r + rng.integers(0, 10, 6), c + rng.integers(0, 10, 6)
            occ[rows, cols] = ~occ[rows, cols]
            if k == 39:
                occ[-1, -1] = ~occ[-1, -1]
        got = keeper.clearance(occ, geom)
        want = gs.capped_clearance_map(occ, res, 7)
        assert got.dtype == np.float32 and not got.flags.writeable
        assert np.array_equal(got, want), k
        true = gs.clearance_map(occ, res)
        below = true < cap - 1e-6
        assert np.allclose(got[below], true[below], rtol=0, atol=1e-6)
        assert np.all(got[~below] >= cap - 1e-6)
    assert 0 < keeper.cells and keeper.kept > keeper.cells  # most of it was kept
    with pytest.raises(ValueError, match="beyond"):  # asked above the cap: an error
        g, geom = half_known_room()
        MapView(grid(g, geom), Occupancy(), keeper=keeper).passable(cap + 0.1)


def test_crosses_an_occupied_cell():
    g, geom = corridor_grid()
    occ = g == 100
    assert not gr.crosses(occ, geom, np.array([[0.5, 0.5], [5.5, 0.5]]))
    assert gr.crosses(occ, geom, np.array([[0.5, 0.5], [0.5, 1.5]]))  # through the wall
    assert not gr.crosses(occ, geom, np.array([[0.5, 0.5]]))
    assert not gr.crosses(occ, geom, np.zeros((0, 2)))
    assert not gr.crosses(occ, geom, np.array([[20.0, 20.0], [30.0, 20.0]]))  # off the grid


def test_new_path_when_the_path_crosses_a_wall_seen_later():
    geom = GridGeometry(0.1, -1.0, -1.0, 90, 40)
    g = np.full((40, 90), 100, dtype=np.int8)
    g[10:26, 10:70] = 0  # free: x in [0, 6), y in [0, 1.6)
    nodes = [node(1, "end", 0.5, 0.5), node(2, "end", 5.5, 0.5)]
    tp = topo(nodes, [edge(1, 2, [(0.5, 0.5), (5.5, 0.5)])])
    # a path tolerance wide enough that the old path still "follows" the new skeleton: only
    # the crossing test can notice the wall
    core = PlannerCore(params(path_tolerance=0.8))
    out = core.update(0.0, (0.6, 0.5, 0.0), tp, rel({1: 0.95, 2: 0.5}), grid(g, geom))
    assert out.route.target_id == 2
    first = out.route.plan_id
    g[10:17, 39:41] = 100  # a wall piece across the old path: x in [2.9, 3.1), y < 0.7
    tp2 = topo(nodes, [edge(1, 2, [(0.5, 0.5), (2.5, 0.5), (2.7, 1.1), (3.3, 1.1), (3.5, 0.5),
                                   (5.5, 0.5)])])
    out = core.update(0.2, (0.7, 0.5, 0.0), tp2, rel({1: 0.95, 2: 0.5}), grid(g, geom))
    assert out.route.target_id == 2 and out.route.plan_id != first
    assert "crosses an obstacle" in out.status.reason
    assert not gr.crosses(g == 100, geom, out.route.waypoints)


def test_cut_at_narrow():
    pts = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [3.0, 0.0]])
    clear = lambda p: np.where(np.abs(p[:, 0] - 2.0) < 0.1, 0.1, 0.5)  # noqa: E731
    assert gr.cut_at_narrow(pts, clear, 0.25).tolist() == [[0.0, 0.0], [1.0, 0.0]]
    assert len(gr.cut_at_narrow(pts, clear, 0.05)) == 4
    assert len(gr.cut_at_narrow(pts[2:], clear, 0.25)) == 0


def test_frontier_search_runs_at_most_once_per_frontier_period_while_following():
    g, geom = half_known_room()
    core = frontier_core(frontier_period=1.0)
    out = core.update(0.0, (1.05, 3.05, 0.0), None, None, grid(g, geom))
    assert out.state == "exploring"
    full = g.copy()
    full[:, 30:] = 0  # the room is now known: no frontier left
    full[0, :] = full[-1, :] = full[:, -1] = 100
    out = core.update(0.4, (1.10, 3.05, 0.0), None, None, grid(full, geom))
    assert out.state == "exploring" and wps(out)  # still the search made at t = 0
    out = core.update(1.0, (1.15, 3.05, 0.0), None, None, grid(full, geom))
    assert out.state == "done" and "no frontier" in out.status.reason  # a new search at 1 s


# --- frontier completion (reliability / all-end-nodes) ----------------------------------------


def known_left_half_topo():
    """Two end nodes in the known left half of half_known_room, joined by one edge."""
    return topo([node(1, "end", 0.6, 3.05), node(2, "end", 2.5, 3.05)],
                [edge(1, 2, [(0.6, 3.05), (2.5, 3.05)])])


@pytest.mark.parametrize("strategy", ["reliability", "all-end-nodes"])
def test_completion_goes_to_the_frontier_left_once_no_end_node_is_left(strategy):
    g, geom = half_known_room()
    done = {1: 0.95, 2: 0.95}
    core = PlannerCore(params(strategy=strategy))
    if strategy == "all-end-nodes":  # visit both first
        for k, pose in enumerate([(0.6, 3.05, 0.0), (2.5, 3.05, 0.0)]):
            core.update(0.2 * k, pose, known_left_half_topo(), rel(done), grid(g, geom))
    out = core.update(1.0, (1.05, 3.05, 0.0), known_left_half_topo(), rel(done), grid(g, geom))
    assert out.state == "exploring" and out.route.target_id == -1, out.status.reason
    assert "completion" in out.status.reason and out.route.target_xy[0] == pytest.approx(2.95)
    off = PlannerCore(params(strategy="reliability", frontier_completion=False))
    out = off.update(1.0, (1.05, 3.05, 0.0), known_left_half_topo(), rel(done), grid(g, geom))
    assert out.state == "done" and "reliable" in out.status.reason


def test_a_kept_completion_search_is_described_once_with_this_updates_counts():
    """Reusing the completion search within frontier_period neither repeats its note in the
    target's label nor keeps the end node counts of the update it was made in."""
    g, geom = half_known_room()
    core = PlannerCore(params(frontier_period=5.0))
    done = {1: 0.95, 2: 0.95}
    out = None
    for k in range(4):
        out = core.update(0.2 * k, (1.05, 3.05, 0.0), known_left_half_topo(), rel(done),
                          grid(g, geom))
    assert out.status.reason.count("(completion: no end node left)") == 1, out.status.reason
    assert (out.status.end_nodes, out.status.reliable) == (2, 2)
    out = core.update(1.0, (1.05, 3.05, 0.0), known_left_half_topo(), rel({1: 0.95, 2: 0.5}),
                      grid(g, geom))  # node 2 open again: the topological target, not the frontier
    assert out.status.end_nodes == 2


def test_a_kept_frontier_search_reports_this_updates_end_node_counts():
    g, geom = half_known_room()
    core = frontier_core(frontier_period=5.0)
    out = core.update(0.0, (1.05, 3.05, 0.0), known_left_half_topo(), rel({1: 0.5, 2: 0.5}),
                      grid(g, geom))
    assert (out.status.end_nodes, out.status.reliable) == (2, 0)
    out = core.update(0.4, (1.05, 3.05, 0.0), known_left_half_topo(), rel({1: 0.95, 2: 0.95}),
                      grid(g, geom))  # within the period: the search is kept, the counts not
    assert (out.status.end_nodes, out.status.reliable) == (2, 2) and wps(out)


def test_completion_ignores_short_groups_unless_near():
    g, geom = half_known_room()
    g[1:59, 29] = 100  # wall the right side off ...
    g[28:35, 29] = 0  # ... except a 0.7 m gap: a group >= min_frontier_size, < 1 m
    done = {1: 0.95, 2: 0.95}
    near = PlannerCore(params())
    out = near.update(0.0, (1.05, 3.05, 0.0), known_left_half_topo(), rel(done), grid(g, geom))
    assert out.state == "exploring" and "completion" in out.status.reason, out.status.reason
    far = PlannerCore(params(completion_near=0.5))
    out = far.update(0.0, (1.05, 3.05, 0.0), known_left_half_topo(), rel(done), grid(g, geom))
    assert out.state == "done"
    assert "shorter than 1 m ignored, unless within 0.5 m" in out.status.reason
    tiny = PlannerCore(params())  # below min_frontier_size: never, near or not
    g[28:35, 29] = 100
    g[30:33, 29] = 0
    out = tiny.update(0.0, (1.05, 3.05, 0.0), known_left_half_topo(), rel(done), grid(g, geom))
    assert out.state == "done", out.status.reason


def gap_room(lo: int, hi: int):
    """half_known_room walled off at column 29 but for the free rows lo..hi-1 of the wall."""
    g, geom = half_known_room()
    g[1:59, 29] = 100
    g[lo:hi, 29] = 0
    return g, geom


def test_completion_counts_a_short_opening_until_the_robot_has_looked_into_it():
    """completion_openings: a 0.7 m gap (a group under completion_min_size) that the robot's
    body fits through counts however far away, until the robot has looked into it squarely
    from within that range; then it is a short group like any other."""
    g, geom = gap_room(28, 35)
    done = {1: 0.95, 2: 0.95}
    pose = (1.05, 3.05, 0.0)  # 1.85 m from the gap, facing it
    off = PlannerCore(params(completion_near=0.5))
    assert off.update(0.0, pose, known_left_half_topo(), rel(done), grid(g, geom)).state == "done"
    far = PlannerCore(params(completion_near=0.5, completion_openings=1.5))
    out = far.update(0.0, pose, known_left_half_topo(), rel(done), grid(g, geom))
    assert out.state == "exploring" and "completion" in out.status.reason, out.status.reason
    assert far.snapshot()["looked_into"] == 0
    # the goal: the nearest place to look into it from, not the gap itself: facing a cell
    # in the middle of the gap (rows 30-32) from within 1.5 m, at most 45 degrees off its
    # unknown side (+x)
    gx, gy = out.route.target_xy
    th = out.route.goal_heading
    assert th is not None and abs(th) <= math.pi / 4 + 1e-9
    dist = (2.95 - gx) / math.cos(th)
    assert dist <= 1.5 + 1e-9 and 3.0 <= gy + dist * math.sin(th) <= 3.3, (gx, gy, th)
    assert gx < 1.6, (gx, gy)  # on the robot's side of that cone (it stands at x 1.05)
    assert "looked into from" in out.status.reason
    close = PlannerCore(params(completion_near=0.5, completion_openings=2.5))
    out = close.update(0.0, pose, known_left_half_topo(), rel(done), grid(g, geom))
    assert out.state == "done", out.status.reason
    assert "or openings" in out.status.reason
    assert close.snapshot()["looked_into"] == 7
    away = PlannerCore(params(completion_near=0.5, completion_openings=2.5))
    out = away.update(0.0, (1.05, 3.05, math.pi), known_left_half_topo(), rel(done),
                      grid(g, geom))  # the same place, its back to the gap: not looked into
    assert out.state == "exploring", out.status.reason


def gap_group(view: MapView, lo: int, hi: int) -> tuple[np.ndarray, gs.FrontierGroup]:
    """The frontier cells of gap_room's gap (a mask on the view's cropped grid) and the
    group they make."""
    gap = np.zeros(view.free.shape, dtype=bool)
    ys = np.arange(lo, hi) * 0.1 + 0.05
    gap[view.geom.world_to_cell(np.full(hi - lo, 2.95), ys)] = True
    cells = np.stack([np.full(hi - lo, 2.95), ys], axis=1)
    return gap, gs.FrontierGroup(1, hi - lo, (2.95, float(ys.mean())), cells, None, None,
                                 math.inf, math.inf)


@pytest.mark.parametrize("lo, hi, fits", [(28, 35, True), (29, 33, True), (29, 32, False),
                                          (30, 31, False)])
def test_an_opening_is_a_gap_the_body_fits_through(lo, hi, fits):
    """MapView.openings at 0.1 m: fit 0.2 m (robot.radius 0.2 + body_margin 0.05 less half a
    cell) lets a gap of 4 free cells through, not one of 3 (the narrow passages' rule)."""
    g, geom = gap_room(lo, hi)
    view = MapView(grid(g, geom), Occupancy())
    fit = Config(PlannerParams(), 0.2, 0.9).fit(0.1)
    mouth, wide = view.openings(fit)
    gap, group = gap_group(view, lo, hi)
    assert not (mouth & ~gap).any()  # the room's open edges beside the gap are walled
    assert not (wide & ~mouth).any()
    assert (opening_mouth(view, fit, group) is not None) == fits
    if fits:
        mid = view.geom.world_to_cell(2.95, (lo + hi) / 2 * 0.1)
        assert wide[mid]  # the middle of the gap (its ends are too near the jambs)
        looked = MapView(grid(g, geom), Occupancy(), looked=lambda gm: gap)
        assert not looked.openings(fit)[0].any()
        assert opening_mouth(looked, fit, group) is None


@pytest.mark.parametrize("flanks, door", [((), True), ((27,), True), ((27, 35), False)])
def test_an_opening_widens_behind_a_channel_does_not(flanks, door):
    """A 0.7 m gap in a wall is a door when the unknown widens behind it, on one side at
    least (a door in a room's corner has the room's side wall flush with one jamb); with a
    wall seen along both sides of the way in (a recess beside furniture whose face was never
    hit, a channel), the way stays as narrow as its mouth: no opening."""
    g, geom = gap_room(28, 35)
    for row in flanks:
        g[row, 29:45] = 100
    view = MapView(grid(g, geom), Occupancy())
    fit = Config(PlannerParams(), 0.2, 0.9).fit(0.1)
    assert (opening_mouth(view, fit, gap_group(view, 28, 35)[1]) is not None) == door


@pytest.mark.parametrize("strategy", ["reliability", "all-end-nodes"])
def test_a_frontier_group_near_the_robot_is_picked_up_before_a_farther_end_node(strategy):
    """pickup_radius: while end nodes are left, a frontier group the completion rules count
    within that path length of the robot is a candidate beside them (cost: path length), so
    the robot does not leave it for a trip back at the end; farther, or with the rule off,
    the end node is the target. pickup_age: only once a cell of the group has been a
    frontier cell that long (the edge of the laser's reach of the moment is not left
    behind)."""
    g, geom = half_known_room()  # the frontier: column 29, x = 2.95 m
    open_1 = {1: 0.5, 2: 0.95}  # end node 1 at (0.6, 3.05) open, 1.9 m from the robot

    def core_for(pickup: float, age: float = 0.0) -> PlannerCore:
        core = PlannerCore(params(strategy=strategy, pickup_radius=pickup, pickup_age=age,
                                  blocked_time=100.0))  # it stands still: no blockage
        if strategy == "all-end-nodes":  # node 2 visited (the robot stands on it)
            core.update(0.0, (2.5, 3.05, 0.0), known_left_half_topo(), rel(open_1),
                        grid(g, geom))
        return core

    def at(core: PlannerCore, t: float):
        return core.update(t, (2.5, 3.05, 0.0), known_left_half_topo(), rel(open_1),
                           grid(g, geom))

    out = at(core_for(3.0), 0.2)
    assert out.state == "exploring" and out.route.target_id == -1, out.status.reason
    assert "near the robot" in out.status.reason
    assert out.route.target_xy[0] == pytest.approx(2.95)
    assert at(core_for(0.0), 0.2).route.target_id == 1
    out = at(core_for(0.3), 0.2)  # the group is 0.45 m away by path: beyond this radius
    assert out.route.target_id == 1, out.status.reason
    aged = core_for(3.0, age=10.0)
    out = at(aged, 0.2)  # a frontier since this update only: the end node
    assert out.route.target_id == 1, out.status.reason
    out = at(aged, 10.4)  # a frontier for 10.2 s: picked up (a switch: 0.45 < 0.7 x 1.9 m)
    assert out.route.target_id == -1 and "near the robot" in out.status.reason, out.status.reason


def test_stop_when_mapped_ends_with_open_end_nodes_once_no_frontier_is_left():
    g, geom = corridor_grid()  # all known: no frontier anywhere
    tp = topo([node(1, "end", 0.5, 0.5), node(2, "end", 5.5, 0.5)],
              [edge(1, 2, [(0.5, 0.5), (5.5, 0.5)])])
    core = PlannerCore(params(stop_when_mapped=True))
    out = core.update(0.0, (0.5, 0.5, 0.0), tp, rel({1: 0.95, 2: 0.5}), grid(g, geom))
    assert out.state == "done" and out.route.target_id == -1
    reason = out.status.reason
    assert "the map is complete" in reason and "1 end node(s) below P 0.9" in reason
    g2, _ = corridor_grid()
    g2[9:21, 60:71] = -1  # the far end not seen yet (walls included): a frontier, so go on
    core = PlannerCore(params(stop_when_mapped=True))
    out = core.update(0.0, (0.5, 0.5, 0.0), tp, rel({1: 0.95, 2: 0.5}), grid(g2, geom))
    assert out.state == "exploring" and out.route.target_id == 2, out.status.reason
    allend = PlannerCore(params(strategy="all-end-nodes", stop_when_mapped=True))
    out = allend.update(0.0, (0.5, 0.5, 0.0), tp, rel({1: 0.95, 2: 0.5}), grid(g, geom))
    assert out.state == "exploring" and out.route.target_id == 2  # baselines are unchanged


def test_reach_only_search_reaches_the_same_cells_as_the_dijkstra():
    rng = np.random.default_rng(3)
    geom = GridGeometry(0.1, 0.0, 0.0, 40, 30)
    for _ in range(60):
        g = rng.choice(np.array([-1, 0, 0, 0, 100], np.int8), size=(30, 40))
        x, y = rng.uniform(0.0, 4.0), rng.uniform(0.0, 3.0)
        view = MapView(grid(g, geom), Occupancy())
        full = view.search(x, y, 0.1, soft_radius=0.3, soft_penalty=2.0)
        quick = view.search(x, y, 0.1, soft_radius=0.3, soft_penalty=2.0, reach_only=True)
        assert quick.start == full.start
        assert np.array_equal(np.isfinite(quick.dist), np.isfinite(full.dist))


# --- structure: strategy registry, decisions, map view ---------------------------------------


def test_the_registry_has_exactly_the_strategies_of_the_params():
    assert set(strategies.REGISTRY) == set(STRATEGIES)
    for name in STRATEGIES:
        s = strategies.make(Config(params(strategy=name), RADIUS, 0.9))
        assert isinstance(s, strategies.REGISTRY[name])
        assert callable(s.evaluate) and isinstance(s.snapshot(), dict)
        assert PlannerCore(params(strategy=name)).update(0.0, POSE, None, None, None).state \
            == ExploreState.EXPLORING  # every strategy waits for its inputs


@pytest.mark.parametrize("strategy", STRATEGIES)
def test_snapshot_is_json(strategy):
    g, geom = half_known_room()
    core = PlannerCore(params(strategy=strategy))
    core.update(0.0, (1.05, 3.05, 0.0), known_left_half_topo(), rel({1: 0.5, 2: 0.5}),
                grid(g, geom))
    snap = json.loads(json.dumps(core.snapshot()))
    assert snap["strategy"] == strategy and snap["state"] == "exploring"
    assert snap["target"] is not None and snap["updates"] == 1


def test_decisions_are_typed():
    d = Decision.repath(1.5, "new path", cross=True)
    assert d.action is Action.CROSS and d.progress_t == 1.5 and d.note == "new path"
    assert Decision.repath(2.0, "x").action is Action.REPATH
    assert Decision.keep() == Decision(Action.KEEP) and Decision.keep().note == ""


def test_the_decision_machine_returns_decisions(monkeypatch):
    """The switch scenario seen through _step_target: a KEEP, then a SWITCH to node 6."""
    seen = []
    step = PlannerCore._step_target

    def spy(self, *a):
        d = step(self, *a)
        seen.append(d)
        return d

    monkeypatch.setattr(PlannerCore, "_step_target", spy)
    core = PlannerCore(params())
    core.update(0.0, POSE, u_graph(), rel(OPEN), None)
    core.update(2.5, POSE, with_node_6(2.3), rel({**OPEN, 6: 0.5}), None)
    core.update(5.0, POSE, with_node_6(1.5), rel({**OPEN, 6: 0.5}), None)
    assert all(isinstance(d, Decision) for d in seen)
    assert [d.action for d in seen] == [Action.KEEP, Action.SWITCH]
    assert seen[1].switch_to.id == 6


def test_map_view_derives_each_grid_from_the_observed_part():
    g, geom = half_known_room()
    big = np.full((100, 100), -1, dtype=np.int8)
    big[20:80, 20:80] = g  # the room inside a wide unknown margin
    view = MapView(grid(big, GridGeometry(0.1, -2.0, -2.0, 100, 100)), Occupancy())
    assert view.data.shape == (62, 32) and view.geom.origin_x == pytest.approx(-0.1)
    cls = classify(view.data, 0.35, 0.65)
    assert np.array_equal(view.classes, cls)
    assert np.array_equal(view.free, cls == 1) and np.array_equal(view.occupied, cls == 2)
    assert np.array_equal(view.clearance, gs.clearance_map(cls == 2, 0.1))
    assert np.array_equal(view.unknown, unknown_mask(view.data))
    assert view.open_unknown(0) is view.unknown
    assert view.passable(0.3) is view.passable(0.3)
    assert view.clearance_at(np.array([[100.0, 100.0]]))[0] == np.inf


@pytest.mark.parametrize("strategy", STRATEGIES)
def test_each_derived_grid_is_computed_once_per_update(strategy, monkeypatch):
    """The topological evaluation, the map-complete check (a quick and a full frontier search)
    and the completion phase of one update share one map view."""
    calls: dict[str, int] = {}

    def counted(name, fn):
        def f(*a, **kw):
            calls[name] = calls.get(name, 0) + 1
            return fn(*a, **kw)
        return f

    for name in ("crop_known", "classify", "unknown_mask", "open_unknown"):
        monkeypatch.setattr(mapview, name, counted(name, getattr(mapview, name)))
    # the clearance of the map: asked of the planner's keeper (kept between updates)
    monkeypatch.setattr(mapview.gs.ClearanceKeeper, "clearance",
                        counted("clearance_map", gs.ClearanceKeeper.clearance))
    searches: list[bool] = []
    grid_search = gs.grid_search

    def search(*a, reach_only=False, **kw):
        searches.append(reach_only)
        return grid_search(*a, reach_only=reach_only, **kw)

    monkeypatch.setattr(mapview.gs, "grid_search", search)
    g, geom = half_known_room()
    g[1:59, 29] = 100  # wall the right side off except a 0.7 m gap: a short completion group
    g[28:35, 29] = 0
    core = PlannerCore(params(strategy=strategy, stop_when_mapped=True, frontier_period=0.0))
    tp = topo([node(1, "end", 0.6, 3.05), node(2, "end", 2.5, 3.05), node(3, "end", 1.5, 5.0),
               node(0, "branch", 1.5, 3.05)],
              [edge(1, 0, [(0.6, 3.05), (1.5, 3.05)]), edge(0, 2, [(1.5, 3.05), (2.5, 3.05)]),
               edge(0, 3, [(1.5, 3.05), (1.5, 5.0)])])
    expected = {"reliability": [[True, False], [False, True]], "all-end-nodes": [[], []],
                "frontier": [[False], [False]]}[strategy]  # reach_only of each grid search
    # (reliability: the map-complete check's quick pass is where the robot can get at all,
    # which the pocket rule of the full search then shares; the completion phase needs it
    # for the pocket rule after its own search)
    for k, beliefs in enumerate(({1: 0.95, 2: 0.95, 3: 0.5}, {1: 0.95, 2: 0.95, 3: 0.95})):
        calls.clear()
        searches.clear()
        out = core.update(float(k), (1.05, 3.05, 0.0), tp, rel(beliefs), grid(g, geom))
        assert out.state == "exploring", out.status.reason
        assert searches == expected[k]  # reliability: map-complete check, then completion
        assert calls and max(calls.values()) == 1, calls
        assert calls["classify"] == calls["crop_known"] == calls["clearance_map"] == 1


def test_the_planner_keeps_no_chain_of_old_map_views():
    """Each Update used to carry the followed target with its lazy path, which held the
    update before it, and so on: every MapView since the robot last had no target stayed
    alive (674 at 460 s on office, 498 MB). Now a few at most."""
    import gc

    from topoexplore.services.planner.mapview import MapView
    from topoexplore.tools.bench import inproc

    updates: list[int] = []
    alive: list[int] = []

    def count(*_args) -> None:  # every 5th update: a scan of every object costs ~40 ms
        updates.append(1)
        if len(updates) % 5 == 0:
            alive.append(sum(isinstance(o, MapView) for o in gc.get_objects()))

    gc.collect()  # earlier tests' garbage cycles (cores, their closures) are not this run's
    inproc.run("office", strategy="reliability", max_sim_time=120.0, on_update=count)
    assert len(updates) > 200 and max(alive[20:]) <= 5, max(alive)


def test_narrower_than_answers_as_the_whole_maps_clearance():
    """A view asked whether points are narrower than a limit before it has the whole map's
    clearance answers from the box around the points alone: the same as the whole map's."""
    rng = np.random.default_rng(4)
    for _ in range(120):
        h, w = (int(v) for v in rng.integers(5, 70, 2))
        g = np.full((h, w), -1, np.int8)
        g[rng.random((h, w)) < 0.6] = 0
        g[rng.random((h, w)) < rng.uniform(0.0, 0.05)] = 100
        geom = GridGeometry(0.05, -1.0, 0.5, w, h)
        pts = np.column_stack([rng.uniform(-1.2, -1.0 + 0.05 * w + 0.2, 12),
                               rng.uniform(0.3, 0.5 + 0.05 * h + 0.2, 12)])
        for limit in (0.05, 0.17, 0.4):
            local = MapView(grid(g, geom), Occupancy())
            got = local.narrower_than(pts, limit)
            assert "clearance" not in local.__dict__  # no whole-map transform was made
            whole = MapView(grid(g, geom), Occupancy())
            assert np.array_equal(got, whole.clearance_at(pts) < limit)
            assert np.array_equal(whole.narrower_than(pts, limit), got)  # made: used as is


def test_open_unknown_made_only_reports_what_the_update_made():
    """beside_unknown's shortcut: the whole-map mask of this update if made, never made by
    asking."""
    from topoexplore.services.planner.strategies.base import Update
    from topoexplore.services.planner.strategies.frontier import open_unknown, open_unknown_made

    g, geom = half_known_room()
    g[20:23, 10:13] = -1  # a small enclosed pocket
    cfg = Config(params(), RADIUS, 0.9)
    view = MapView(grid(g, geom), Occupancy())
    u = Update(0.0, 1.05, 3.05, 0.0, None, None, view, None, lambda c: False)
    assert open_unknown_made(cfg, u, 1.5) is None
    assert view.memo_made(("reach", True, u.x, u.y)) is None  # nothing was made by asking
    whole = open_unknown(cfg, u, 1.5)
    assert open_unknown_made(cfg, u, 1.5) is whole
    assert open_unknown_made(cfg, u, 0.5) is None  # other arguments: not made
    assert view.open_unknown_made(0) is None and view.open_unknown_made(0) is None
    assert view.open_unknown(0) is view.open_unknown_made(0)


def test_find_frontiers_without_look_points_and_ending_at_the_first_group_it_is_told():
    """The map-complete check's quick pass: the same groups without look points, and with
    ``stop`` the list ends at the first group stop says yes to."""
    g, geom = half_known_room()
    g[1:50, 15] = 100  # a wall with a gap at the top, and a second unknown area behind it
    g[20:40, 3:6] = -1
    view = MapView(grid(g, geom), Occupancy())
    search = view.search(0.55, 1.05, 0.2)
    args = (view.free, view.unknown, view.geom, search, 0.5, 3.0, 1.0)
    full, dropped = gs.find_frontiers(*args)
    assert len(full) >= 2 and all(f.look_xy is not None for f in full if f.goal_xy)
    bare, dropped2 = gs.find_frontiers(*args, look=False)
    assert dropped2 == dropped and all(b.look_xy is None for b in bare)
    assert [(b.label, b.size, b.goal_rc, b.path_length) for b in bare] == [
        (f.label, f.size, f.goal_rc, f.path_length) for f in full]
    first, _ = gs.find_frontiers(*args, look=False, stop=lambda grp: grp.goal_xy is not None)
    k = next(i for i, f in enumerate(full) if f.goal_xy is not None)
    assert [f.label for f in first] == [f.label for f in full[:k + 1]]
    none, _ = gs.find_frontiers(*args, look=False, stop=lambda grp: False)
    assert len(none) == len(full)


def test_topological_path_check_matches_a_search_over_every_skeleton_point():
    """_near_skeleton's path_ok, which searches only the points in the waypoints' box, gives
    the answer of a check against every skeleton and lead-in point."""
    from topoexplore.services.planner.strategies.topological import _near_skeleton

    rng = np.random.default_rng(3)
    for _ in range(200):
        pts = rng.uniform(0.0, 20.0, size=(int(rng.integers(0, 60)), 2))
        lead = rng.uniform(0.0, 20.0, size=(int(rng.integers(0, 4)), 2))
        edges = [gr.Edge(0, 0, 1, pts, np.zeros(len(pts)), 1.0)] if len(pts) else []
        index = gr.TopoIndex({}, edges, [], {}, {})
        tol = float(rng.uniform(0.05, 3.0))
        ok = _near_skeleton(index, tol, lead)
        every = np.vstack([pts.reshape(-1, 2), lead])
        for _ in range(3):
            wps = rng.uniform(0.0, 20.0, size=(int(rng.integers(1, 8)), 2))
            if len(every):
                d = np.hypot(*(wps[:, None, :] - every[None, :, :]).transpose(2, 0, 1))
                want = bool(np.all(d.min(axis=1) <= tol))
            else:
                want = False
            assert ok(wps) == want
        assert ok(np.zeros((0, 2)))


def test_candidates_judge_a_later_member_only_when_the_list_is_read():
    """Between two re-evaluations the core asks only for the target it follows: a
    :class:`Later` member is judged when the list is read as a whole (in its place, once),
    or when asked for by its id; a judged member answers bool() without judging any."""
    from topoexplore.services.planner.strategies.base import Candidate, Candidates, Later, find

    calls = []

    def cand(i):
        return Candidate(i, float(i), 0.0, 1.0, 1.0, 1.0, 0.5, lambda: np.zeros((0, 2)))

    def later(i, keep=True):
        def judge():
            calls.append(i)
            return cand(i) if keep else None
        return Later(i, judge)

    cs = Candidates([cand(1), later(2), later(3, keep=False), cand(4)],
                    summary=lambda: f"judged {sorted(calls)}")
    assert cs and find(cs, 4).id == 4 and not calls
    assert find(cs, 2).id == 2 and calls == [2] and not cs.settled()
    joined = cs + [cand(-1)]
    assert [c.id for c in joined] == [1, 2, 4, -1] and calls == [2, 3]
    assert [c.id for c in cs] == [1, 2, 4] and calls == [2, 3]  # shared: judged once
    assert cs.settled() and len(cs) == 3 and cs[1].id == 2 and cs.summary() == "judged [2, 3]"
    empty = Candidates([later(5, keep=False)], summary=lambda: "none")
    assert not empty and calls[-1] == 5 and empty.summary() == "none"
    assert find([cand(7)], 7).id == 7 and find([cand(7)], 8) is None


@pytest.mark.parametrize("beyond", [True, False])
def test_a_node_behind_a_narrow_passage_is_judged_when_asked_as_if_judged_at_once(beyond):
    """While the robot follows end node 1, end node 2 behind a door is judged only when the
    candidates are read: then they (and the done text) are those of an evaluation that
    judged everything at once. beyond: unexplored space behind the door (2 is a candidate
    up to the door), else mapped (2 is unreachable)."""
    from topoexplore.services.planner.strategies.base import Candidates, Update, find

    g, geom = corridor_grid()
    g[10:17, 30] = 100  # 0.3 m door at x in [2.0, 2.1]
    if beyond:
        g[10:20, 60:71] = -1
    tp, beliefs = topo(*door_parts()), rel({1: 0.5, 2: 0.5})
    cfg = Config(params(), RADIUS, 0.9)

    def evaluate(target):
        view = MapView(grid(g, geom), Occupancy())
        s = strategies.make(cfg)
        return s.evaluate(Update(0.0, 1.2, 0.5, math.pi, tp, beliefs, view, target,
                                 lambda c: False))

    at_once = evaluate(None)
    assert isinstance(at_once.cands, list)
    follow = find(at_once.cands, 1).detached()
    lazy = evaluate(follow)
    assert isinstance(lazy.cands, Candidates) and not lazy.cands.settled()
    assert find(lazy.cands, 1).cost == follow.cost and not lazy.cands.settled()
    got = lazy.settled()
    assert [(c.id, c.cost, c.label, c.partial) for c in got.cands] == \
        [(c.id, c.cost, c.label, c.partial) for c in at_once.cands]
    assert [c.id for c in got.cands] == ([1, 2] if beyond else [1])
    assert got.done == at_once.done
    assert ("(ids 2)" in got.done) != beyond


def _kept_script(keep_period):
    """A scripted following of end node 2 along the corridor (updates every 0.2 s): the robot
    drives, the node moves 0.4 m at t = 0.6 s, the robot stalls from t = 1.4 to 2.6 s (the
    effort rule, progress_timeout 1 s: a retry), the node becomes reliable at t = 3.8 s.
    Returns the plans (state, target, plan id, waypoints, reason), the times of the whole
    evaluations and the number of kept ones."""
    g, geom = corridor_grid()
    core = PlannerCore(params(keep_period=keep_period, progress_timeout=1.0, max_attempts=3))
    calls = []
    evaluate = core.strategy.evaluate
    core.strategy.evaluate = lambda u: calls.append(u.t) or evaluate(u)
    out, x = [], 0.6
    for k in range(24):
        t = round(0.2 * k, 1)
        if not 1.4 <= t < 2.6:
            x += 0.1
        nodes, edges = door_parts(wide=True)
        if t >= 0.6:  # node 2 moved: (5.5, 0.5) -> (5.9, 0.5)
            nodes[2] = node(2, "end", 5.9, 0.5)
            edges[1] = edge(0, 2, [(1.0, 0.5), (5.9, 0.5)], clearance=0.2)
        p2 = 0.95 if t >= 3.8 else 0.5
        plan = core.update(t, (x, 0.5, 0.0), topo(nodes, edges), rel({1: 0.95, 2: p2}),
                           grid(g, geom))
        out.append((plan.state, plan.route.target_id, plan.route.plan_id,
                    np.round(plan.route.waypoints, 6).tolist(), plan.status.reason))
    return out, calls, core.snapshot()["kept_updates"]


def test_a_kept_evaluation_decides_as_a_whole_one_and_evaluates_less():
    """keep_period: while the target followed stays open where it was and its path stays
    valid, the last evaluation serves the update (docs/design.md, "A kept evaluation"). On a
    script with a moving target, a stall (bounded effort: a retry) and the target becoming
    reliable, every plan is the one a whole evaluation per update gives, and the updates
    where the target moved or became reliable were evaluated whole."""
    whole, calls0, kept0 = _kept_script(0.0)
    kept, calls1, kept1 = _kept_script(1.0)
    assert kept0 == 0 and len(calls0) == len(whole) == 24
    assert [w[:4] for w in kept] == [w[:4] for w in whole]
    reasons = [w[4] for w in whole]
    assert "target moved" in reasons[3] and "no progress" in " ".join(reasons[10:15])
    assert whole[19][0] == "done" and "reliable" in whole[19][4]
    assert 0.6 in calls1 and 3.8 in calls1  # the move and the resolution: seen at once
    assert kept1 > 0 and len(calls1) + kept1 == 24 and len(calls1) <= 14


def test_a_target_up_to_a_narrow_passage_is_evaluated_on_every_update():
    """Whether the way to a target is narrow is judged anew on every update (a way that
    becomes wide, or narrow again, makes a new path), so a target up to a narrow passage (or
    around one) is never followed on a kept evaluation."""
    g, geom = corridor_grid()
    g[10:17, 30] = 100  # 0.3 m door at x in [2.0, 2.1]
    g[10:20, 60:71] = -1  # unexplored beyond x = 5 m
    core = PlannerCore(params(keep_period=1.0))
    calls = []
    evaluate = core.strategy.evaluate
    core.strategy.evaluate = lambda u: calls.append(u.t) or evaluate(u)
    for k in range(4):
        out = core.update(0.2 * k, (0.6 + 0.05 * k, 0.5, 0.0), topo(*door_parts()),
                          rel({1: 0.95, 2: 0.5}), grid(g, geom))
        assert out.route.target_id == 2 and "narrow passage" in out.status.reason
    assert len(calls) == 4 and core.snapshot()["kept_updates"] == 0
