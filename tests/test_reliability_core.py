"""Unit tests for the reliability core (paper eqs. 1-10, DESIGN.md §4 "Reliability")."""

from __future__ import annotations

import json
import math

import msgspec
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from topoexplore.common.domain import Belief, Graph, GridMap, Node, Pose
from topoexplore.common.grid import (
    GridGeometry,
    OpenUnknown,
    near_frontier,
    nearest_occupied,
    open_unknown,
)
from topoexplore.common.messages import Reliability, decode, encode, header
from topoexplore.common.params import LaserParams, ReliabilityParams
from topoexplore.services.reliability.core import (
    FrontierOwnership,
    ReliabilityCore,
    ReliabilityError,
    angle_index,
    bayes_update,
    circular_spread,
    distance_index,
    frontier_cells,
    frontier_owned,
    group_sizes,
    is_observed,
    leaf_chains,
    leaf_headings,
    line_cells,
    line_of_sight,
    new_viewpoint,
)

P = ReliabilityParams(examined_radius=0.0, frontier_group=0.0)  # the index by the equations
# (eqs. 1-10) and the frontier tests at the node (rules 1-2), not rules 3-4
LASER = LaserParams()
GEOM = GridGeometry(resolution=0.1, origin_x=-10.0, origin_y=-10.0, width=200, height=200)


def graph(ends, gone=(), edges=()) -> Graph:
    """End nodes (id, x, y), vanished ids, edges (a, b, polyline): the nodes of the edges
    that are not end nodes become branch nodes at their first point."""
    nodes = [Node(int(i), "end", float(x), float(y)) for i, x, y in ends]
    have = {n.id for n in nodes}
    for a, b, pts in edges:
        for nid, xy in ((a, pts[0]), (b, pts[-1])):
            if nid not in have:
                nodes.append(Node(nid, "branch", float(xy[0]), float(xy[1])))
                have.add(nid)
    return Graph.from_edges(nodes, [(a, b, pts, 1.0, 0.5) for a, b, pts in edges], gone)


def upd(core, ends, gone, pose, grid, geom=GEOM, edges=()):
    return core.update(graph(ends, gone, edges), Pose(*pose), GridMap(grid, geom))


def free_grid() -> np.ndarray:
    return np.zeros((GEOM.height, GEOM.width), dtype=np.int8)


def wall_grid(x: float) -> np.ndarray:
    """Free grid with a vertical occupied wall at world x = x (one cell thick)."""
    g = free_grid()
    _, col = GEOM.world_to_cell(x, 0.0)
    g[:, int(col)] = 100
    return g


# --- eqs. 1-2: distance index ---------------------------------------------------------------


@pytest.mark.parametrize("r", [0.0, 0.1, 0.3, 0.5])
def test_distance_index_is_one_at_and_below_half_metre(r):
    assert distance_index(r, P) == pytest.approx(1.0)


@pytest.mark.parametrize("r", [4.5, 5.0, 8.0, 100.0, math.inf])
def test_distance_index_is_half_at_and_beyond_far(r):
    assert distance_index(r, P) == pytest.approx(0.5)


@pytest.mark.parametrize("r", [0.6, 1.0, 2.0, 3.3, 4.4])
def test_distance_index_between_is_4_over_r_plus_3_5(r):
    assert distance_index(r, P) == pytest.approx(4.0 / (r + 3.5))


def test_distance_index_rejects_bad_input():
    with pytest.raises(ReliabilityError):
        distance_index(-0.1, P)
    with pytest.raises(ReliabilityError):
        distance_index(float("nan"), P)
    with pytest.raises(ValueError):  # ReliabilityError is a ValueError
        distance_index("far", P)


# --- eq. 3: circular spread -------------------------------------------------------------------


def deg(*a: float) -> np.ndarray:
    return np.radians(np.array(a, dtype=np.float64))


def test_spread_empty_and_single_is_zero():
    assert circular_spread(np.array([])) == 0.0
    assert circular_spread(deg(42.0)) == 0.0
    assert circular_spread(deg(42.0, 42.0, 42.0)) == pytest.approx(0.0)


def test_spread_across_the_seam_is_short_arc():
    assert math.degrees(circular_spread(deg(170.0, -170.0))) == pytest.approx(20.0)
    assert math.degrees(circular_spread(deg(-179.0, 179.0, 175.0))) == pytest.approx(6.0)


def test_spread_simple_and_paper_fig8():
    assert math.degrees(circular_spread(deg(10.0, 40.0, 70.0))) == pytest.approx(60.0)
    # order and multiples of 2 pi do not matter
    assert math.degrees(circular_spread(deg(70.0, 400.0, 10.0))) == pytest.approx(60.0)


def test_spread_uses_largest_gap_not_extremes():
    # 0, 170, 265 deg: gaps 170, 95, 95 -> spread 360 - 170 = 190
    assert math.degrees(circular_spread(deg(0.0, 170.0, 265.0))) == pytest.approx(190.0)
    # all around: spread close to 360
    assert math.degrees(circular_spread(deg(*range(0, 360, 10)))) == pytest.approx(350.0)


def test_spread_rejects_non_finite():
    with pytest.raises(ReliabilityError):
        circular_spread(np.array([0.0, np.nan]))


# --- eq. 4: angle index -----------------------------------------------------------------------


@pytest.mark.parametrize("a_deg,expected", [(0, 0.0), (45, 0.5), (90, 1.0), (170, 1.0)])
def test_angle_index(a_deg, expected):
    assert angle_index(math.radians(a_deg), P) == pytest.approx(expected)


def test_angle_index_rejects_negative():
    with pytest.raises(ReliabilityError):
        angle_index(-0.1, P)


# --- eqs. 6-10: Bayes update ------------------------------------------------------------------


@pytest.mark.parametrize("r", [0.5, 0.6, 0.727, 0.9, 1.0 - 1e-9])
def test_bayes_sequence_matches_closed_form(r):
    p = 0.5
    for k in range(1, 8):
        p = bayes_update(p, r)
        odds = (r / (1.0 - r)) ** k  # prior odds 1 multiplied by R / (1 - R) each step
        assert p == pytest.approx(odds / (1.0 + odds), rel=1e-9)


def test_bayes_half_is_neutral_and_one_is_certain():
    assert bayes_update(0.3, 0.5) == pytest.approx(0.3)
    assert bayes_update(0.3, 1.0) == pytest.approx(1.0)
    assert bayes_update(0.5, 0.8) == pytest.approx(0.8)


def test_bayes_rejects_bad_input():
    for p, r in [(1.2, 0.5), (0.5, -0.1), (float("nan"), 0.5), (0.0, 1.0), (1.0, 0.0)]:
        with pytest.raises(ReliabilityError):
            bayes_update(p, r)


# --- visibility -------------------------------------------------------------------------------


def test_line_cells_exact_traversal():
    rows, cols = line_cells(0.05, 0.05, 0.35, 0.25, GEOM)
    cells = list(zip(rows.tolist(), cols.tolist(), strict=True))
    r0, c0 = (int(v) for v in GEOM.world_to_cell(0.05, 0.05))
    r1, c1 = (int(v) for v in GEOM.world_to_cell(0.35, 0.25))
    assert cells[0] == (r0, c0) and cells[-1] == (r1, c1)
    # 4-connected chain: every step changes exactly one index by one
    for (ra, ca), (rb, cb) in zip(cells, cells[1:], strict=False):
        assert abs(ra - rb) + abs(ca - cb) == 1


def test_line_cells_through_a_corner_include_touching_cells():
    rows, cols = line_cells(-0.15, -0.15, 0.15, 0.15, GEOM)  # passes the corner at (0, 0)
    cells = set(zip(rows.tolist(), cols.tolist(), strict=True))
    assert {(99, 99), (100, 100), (99, 100), (100, 99)} <= cells


def test_line_of_sight_diagonal_wall_blocks():
    g = free_grid()
    for k in range(-20, 20):  # a diagonal (8-connected) wall x + y = 0
        r, c = GEOM.world_to_cell(0.1 * k + 0.05, -0.1 * k - 0.05)
        g[int(r), int(c)] = 100
    assert not line_of_sight((-1.0, -1.0), (1.0, 1.0), GridMap(g, GEOM))
    assert line_of_sight((-1.0, -1.0), (-0.5, -1.5), GridMap(g, GEOM))


def test_observed_in_front_within_range():
    assert is_observed((2.0, 0.0), Pose(0.0, 0.0, 0.0), GridMap(free_grid(), GEOM), LASER)
    assert is_observed((0.0, 2.0), Pose(0.0, 0.0, 0.0), GridMap(free_grid(), GEOM), LASER)  # 90 deg: FOV edge


def test_not_observed_behind_robot():
    assert not is_observed((-2.0, 0.0), Pose(0.0, 0.0, 0.0), GridMap(free_grid(), GEOM), LASER)
    assert not is_observed((-1.0, 1.0), Pose(0.0, 0.0, 0.0), GridMap(free_grid(), GEOM), LASER)
    # heading matters: facing -x the node at -2 is in front
    assert is_observed((-2.0, 0.0), Pose(0.0, 0.0, math.pi), GridMap(free_grid(), GEOM), LASER)


def test_not_observed_out_of_range():
    p = LaserParams(range_max=3.0)
    assert is_observed((2.9, 0.0), Pose(0.0, 0.0, 0.0), GridMap(free_grid(), GEOM), p)
    assert not is_observed((3.1, 0.0), Pose(0.0, 0.0, 0.0), GridMap(free_grid(), GEOM), p)


def test_range_measured_from_laser_offset():
    p = LaserParams(range_max=3.0, offset=0.2)
    assert is_observed((3.1, 0.0), Pose(0.0, 0.0, 0.0), GridMap(free_grid(), GEOM), p)
    # a node beside the centre is behind the offset laser's 180 deg field of view
    assert not is_observed((0.1, 1.0), Pose(0.0, 0.0, 0.0), GridMap(free_grid(), GEOM), p)


def test_not_observed_behind_wall_unknown_does_not_block():
    assert not is_observed((2.0, 0.0), Pose(0.0, 0.0, 0.0), GridMap(wall_grid(1.0), GEOM), LASER)
    g = free_grid()
    g[:, 105:115] = -1  # unknown band between robot and node
    assert is_observed((2.0, 0.0), Pose(0.0, 0.0, 0.0), GridMap(g, GEOM), LASER)
    g[:, 110] = 50  # uncertain (not above p_occ) does not block either
    assert is_observed((2.0, 0.0), Pose(0.0, 0.0, 0.0), GridMap(g, GEOM), LASER)


def test_own_cells_excluded():
    g = free_grid()
    r, c = GEOM.world_to_cell(2.0, 0.0)
    g[int(r), int(c)] = 100  # the node's own cell is occupied (noisy map)
    r, c = GEOM.world_to_cell(0.0, 0.0)
    g[int(r), int(c)] = 100  # and the laser's cell
    assert is_observed((2.0, 0.0), Pose(0.0, 0.0, 0.0), GridMap(g, GEOM), LASER)


# --- the stateful core ------------------------------------------------------------------------


def by_id(out: list[Belief]) -> dict[int, Belief]:
    return {n.id: n for n in out}


def test_first_observation_values():
    core = ReliabilityCore(P)
    out = upd(core, [(7, 2.0, 0.0)], [], (0.0, 0.0, 0.0), free_grid(), GEOM)
    n = out[0]
    assert n.visible and n.n_obs == 1
    assert n.r_min == pytest.approx(2.0)
    assert n.d == pytest.approx(4.0 / 5.5)
    assert n.a == 0.0 and n.alpha_max == 0.0
    assert n.p == pytest.approx(bayes_update(0.5, 4.0 / 5.5))


P_EVERY_SCAN = msgspec.structs.replace(P, view_distance=0.0)  # the paper's literal update


def test_repeated_observation_follows_closed_form():
    core = ReliabilityCore(P_EVERY_SCAN)
    r = 4.0 / 5.5
    for k in range(1, 6):
        n = upd(core, [(1, 2.0, 0.0)], [], (0.0, 0.0, 0.0), free_grid(), GEOM)[0]
        odds = (r / (1 - r)) ** k
        assert n.p == pytest.approx(min(odds / (1 + odds), P.p_max))


def test_never_observed_node_defaults():
    core = ReliabilityCore(P)
    n = upd(core, [(1, -2.0, 0.0)], [], (0.0, 0.0, 0.0), free_grid(), GEOM)[0]
    assert not n.visible and n.n_obs == 0
    assert n.p == P.p_init and n.d == 0.0 and n.a == 0.0 and math.isinf(n.r_min)
    # and it encodes into a valid Reliability message (inf r_min allowed)
    h = header(0, 0.0, "map", -1)
    msg = decode(encode(Reliability(header=h, nodes=[n])), Reliability)
    assert math.isinf(msg.nodes[0].r_min)


@pytest.mark.parametrize(
    "pose,grid",
    [
        ((0.0, 0.0, math.pi), free_grid()),  # behind the robot
        ((-9.0, 0.0, 0.0), free_grid()),  # 11 m away: out of range
        ((0.0, 0.0, 0.0), wall_grid(1.0)),  # behind a wall
    ],
)
def test_no_update_when_not_observed(pose, grid):
    core = ReliabilityCore(P)
    upd(core, [(1, 2.0, 0.0)], [], (0.0, 0.0, 0.0), free_grid(), GEOM)
    before = upd(core, [(1, 2.0, 0.0)], [], (0.0, 0.0, 0.0), free_grid(), GEOM)[0]
    after = upd(core, [(1, 2.0, 0.0)], [], pose, grid, GEOM)[0]
    assert not after.visible
    assert (after.p, after.d, after.a, after.r_min, after.n_obs) == (
        before.p, before.d, before.a, before.r_min, before.n_obs)


def test_angle_index_grows_with_viewpoints_and_p_is_clamped():
    core = ReliabilityCore(P)
    node = (1, 0.0, 4.0)
    # robot circles the node at 5 m (D = 0.5, neutral), facing it; bearings span 100 deg
    for bdeg in range(-140, -39, 10):
        b = math.radians(bdeg)
        rx, ry = node[1] - 5.0 * math.cos(b), node[2] - 5.0 * math.sin(b)
        n = upd(core, [node], [], (rx, ry, b), free_grid(), GEOM)[0]
        assert n.visible
    assert math.degrees(n.alpha_max) == pytest.approx(100.0, abs=0.6)
    assert n.a == pytest.approx(1.0)
    assert n.d == pytest.approx(0.5)
    # A = 1 makes P certain; the ceiling keeps it below 1
    assert n.p == pytest.approx(P.p_max)


def test_bearings_stay_bounded():
    core = ReliabilityCore(P)
    rng = np.random.default_rng(1)
    for _ in range(3000):
        b = float(rng.uniform(-math.pi, math.pi))
        upd(core, [(1, 0.0, 0.0)], [], (-3 * math.cos(b), -3 * math.sin(b), b), free_grid(), GEOM)
    s = core.snapshot()["nodes"]["1"]
    assert s["n_bearings"] <= 720
    assert s["alpha_max_deg"] > 355.0


def test_same_viewpoint_counts_once_new_viewpoints_count():
    core = ReliabilityCore(P)
    for _ in range(10):  # standing still: one piece of evidence, not ten
        n = upd(core, [(1, 2.0, 0.0)], [], (0.0, 0.0, 0.0), free_grid(), GEOM)[0]
    assert n.n_obs == 10
    assert n.p == pytest.approx(bayes_update(0.5, distance_index(2.0, P)))
    # moving view_distance counts again
    n = upd(core, [(1, 2.0, 0.0)], [], (-P.view_distance, 0.0, 0.0), free_grid(), GEOM)[0]
    assert n.p > bayes_update(0.5, distance_index(2.0, P))
    # so does a bearing change of view_angle without much travel
    core2 = ReliabilityCore(P)
    upd(core2, [(1, 2.0, 0.0)], [], (0.0, 0.0, 0.0), free_grid(), GEOM)
    y = 2.0 * math.tan(P.view_angle) + 1e-3
    n2 = upd(core2, [(1, 2.0, 0.0)], [], (0.0, y, 0.0), free_grid(), GEOM)[0]
    assert y < P.view_distance and n2.p > bayes_update(0.5, distance_index(2.0, P))


def test_new_viewpoint_rule():
    assert new_viewpoint(None, 0, 0, 0, P)
    assert not new_viewpoint((0.0, 0.0, 0.0), 0.1, 0.0, 0.01, P)
    assert new_viewpoint((0.0, 0.0, 0.0), P.view_distance, 0.0, 0.0, P)
    assert new_viewpoint((0.0, 0.0, math.pi - 0.01), 0.0, 0.0, -math.pi + 0.1, P)  # wraps
    assert new_viewpoint((0.0, 0.0, 0.0), 0.0, 0.0, 0.0, P_EVERY_SCAN)


def test_reset_on_movement():
    core = ReliabilityCore(P_EVERY_SCAN)
    for _ in range(5):
        n = upd(core, [(1, 2.0, 0.0)], [], (0.0, 0.0, 0.0), free_grid(), GEOM)[0]
    assert n.p > 0.9
    # small drift below the tolerance keeps the history
    n = upd(core, [(1, 2.0, 0.25)], [], (0.0, 0.0, math.pi), free_grid(), GEOM)[0]
    assert n.p > 0.9 and n.n_obs == 5
    # beyond the tolerance from the anchor (2, 0): belief resets, history restarts there
    n = upd(core, [(1, 2.0, 0.35)], [], (0.0, 0.0, math.pi), free_grid(), GEOM)[0]
    assert n.p == P.p_init and n.n_obs == 0 and math.isinf(n.r_min) and n.d == 0.0
    assert core.snapshot()["nodes"]["1"]["anchor"] == [2.0, 0.35]
    # observed in the same update as the reset: fresh history with one observation
    n = upd(core, [(1, 2.0, 1.0)], [], (0.0, 0.0, 0.0), free_grid(), GEOM)[0]
    assert n.n_obs == 1 and n.r_min == pytest.approx(math.hypot(2.0, 1.0))
    assert n.p == pytest.approx(bayes_update(0.5, distance_index(n.r_min, P)))


def test_a_new_node_where_a_node_was_reliable_starts_from_that_belief():
    """recall_radius: a skeleton end that gets a new id (or flips back) at a place already
    examined does not send the robot back there; farther away, or with recall off, p_init."""
    core = ReliabilityCore(P_EVERY_SCAN)
    for _ in range(5):
        n = upd(core, [(1, 2.0, 0.0)], [], (0.0, 0.0, 0.0), free_grid(), GEOM)[0]
    assert n.p > 0.9
    behind = (0.0, 0.0, math.pi)  # the robot looks away: no new observation below
    out = by_id(upd(core, [(2, 2.1, 0.05), (3, 2.0, 1.0)], [1], behind, free_grid(), GEOM))
    assert out[2].p == pytest.approx(n.p) and out[2].n_obs == 0
    assert out[3].p == P.p_init
    assert core.snapshot()["examined_places"] == 1
    # a node that moves beyond move_tolerance from its anchor is reset, recall or not
    out = by_id(upd(core, [(2, 2.1, 0.5), (3, 2.0, 1.0)], [], behind, free_grid(), GEOM))
    assert out[2].p == P.p_init
    off = ReliabilityCore(msgspec.structs.replace(P_EVERY_SCAN, recall_radius=0.0))
    for _ in range(5):
        upd(off, [(1, 2.0, 0.0)], [], (0.0, 0.0, 0.0), free_grid(), GEOM)
    out = by_id(upd(off, [(2, 2.1, 0.05)], [1], behind, free_grid(), GEOM))
    assert out[2].p == P.p_init


def test_gone_and_missing_ids_dropped():
    core = ReliabilityCore(P)
    nodes = [(1, 2.0, 0.0), (2, 2.0, 1.0), (3, 2.0, -1.0)]
    for _ in range(3):
        upd(core, nodes, [], (0.0, 0.0, 0.0), free_grid(), GEOM)
    out = upd(core, [(2, 2.0, 1.0)], [1], (0.0, 0.0, 0.0), free_grid(), GEOM)
    assert [n.id for n in out] == [2]
    assert set(core.snapshot()["nodes"]) == {"2"}
    # an id that comes back starts from scratch
    n = upd(core, [(1, 2.0, 0.0)], [], (0.0, 0.0, math.pi), free_grid(), GEOM)[0]
    assert n.p == P.p_init and n.n_obs == 0


def test_gone_id_also_present_restarts_history():
    core = ReliabilityCore(P)
    upd(core, [(1, 2.0, 0.0)], [], (0.0, 0.0, 0.0), free_grid(), GEOM)
    n = upd(core, [(1, 2.0, 0.0)], [1], (0.0, 0.0, math.pi), free_grid(), GEOM)[0]
    assert n.p == P.p_init and n.n_obs == 0


def test_output_sorted_and_complete():
    core = ReliabilityCore(P)
    out = upd(core, [(9, 1.0, 0.0), (3, 1.0, 1.0), (5, -1.0, 0.0)], [], (0.0, 0.0, 0.0),
                      free_grid(), GEOM)
    assert [n.id for n in out] == [3, 5, 9]
    assert by_id(out)[5].visible is False and by_id(out)[9].visible is True


def test_visited_flag():
    core = ReliabilityCore(P)
    n = upd(core, [(1, 2.0, 0.0)], [], (0.0, 0.0, 0.0), free_grid(), GEOM)[0]
    assert not n.visited
    n = upd(core, [(1, 2.0, 0.0)], [], (1.6, 0.0, 0.0), free_grid(), GEOM)[0]
    assert n.visited
    # stays visited while the robot leaves, even when not observed
    n = upd(core, [(1, 2.0, 0.0)], [], (-5.0, 0.0, math.pi), free_grid(), GEOM)[0]
    assert n.visited and not n.visible
    # reset with the history when the node moves
    n = upd(core, [(1, 3.0, 0.0)], [], (-5.0, 0.0, math.pi), free_grid(), GEOM)[0]
    assert not n.visited


def test_snapshot_is_json():
    core = ReliabilityCore(P)
    upd(core, [(1, 2.0, 0.0), (2, -2.0, 0.0)], [], (0.0, 0.0, 0.0), free_grid(), GEOM)
    snap = json.loads(json.dumps(core.snapshot(), allow_nan=False))
    assert snap["end_nodes"] == 2 and snap["nodes"]["2"]["r_min"] is None


# --- frontier rules (docs/design.md: observations of a node next to unknown space don't count)


def side_opening_grid(width_m: float = 1.0) -> np.ndarray:
    """Corridor x in [-5, 0), y in [-1, 1) with walls all round, except an opening of width_m
    in its upper wall at x in [-3, -3 + width_m): free cells up to y = 1.5, unknown beyond."""
    g = np.full((GEOM.height, GEOM.width), 100, dtype=np.int8)

    def cells(x0, x1, y0, y1):
        r0, c0 = GEOM.world_to_cell(x0 + 0.05, y0 + 0.05)
        r1, c1 = GEOM.world_to_cell(x1 - 0.05, y1 - 0.05)
        return slice(int(r0), int(r1) + 1), slice(int(c0), int(c1) + 1)

    g[cells(-5, 0, -1, 1)] = 0
    g[cells(-3, -3 + width_m, 1, 1.5)] = 0
    g[cells(-3, -3 + width_m, 1.5, 3)] = -1
    return g


def chain_edges():
    """end 1 - corner 2 - branch 3, and the branch's other leaves 4 and 5."""
    return [(1, 2, [(-4.5, 0.0), (-2.5, 0.0)]), (2, 3, [(-2.5, 0.0), (-0.5, 0.0)]),
            (3, 4, [(-0.5, 0.0), (-0.5, -0.8)]), (3, 5, [(-0.5, 0.0), (-0.1, 0.5)])]


def test_frontier_cells_groups_and_grid_edge():
    g = side_opening_grid()
    cells = frontier_cells(g, 0.35, 4)
    assert len(cells) == 10  # the row of free cells below the unknown, 1 m wide
    x, y = GEOM.cell_to_world(cells[:, 0], cells[:, 1])
    assert np.allclose(y, 1.45) and x.min() > -3.0 and x.max() < -2.0
    assert len(frontier_cells(side_opening_grid(0.3), 0.35, 4)) == 0  # 3 cells: a wall hole
    assert len(frontier_cells(side_opening_grid(0.3), 0.35, 1)) == 3
    # free cells on the border of the grid touch the unknown outside it
    assert len(frontier_cells(free_grid(), 0.35, 4)) == 4 * 200 - 4


@settings(max_examples=60, deadline=None)
@given(st.integers(1, 30), st.integers(1, 30), st.floats(0.05, 0.7), st.integers(0, 2 ** 31))
def test_group_sizes_are_the_8_connected_components_of_the_listed_cells(h, w, fill, seed):
    """Against an independent labelling of the whole grid (scipy.ndimage.label, 8-connected):
    groups never join across the grid's sides (a key one off wraps to the next row)."""
    from scipy import ndimage

    mask = np.random.default_rng(seed).random((h, w)) < fill
    cells = np.argwhere(mask).astype(np.int64)
    lab, _ = ndimage.label(mask, structure=np.ones((3, 3), int))
    want = np.bincount(lab.ravel())[lab[cells[:, 0], cells[:, 1]]]
    assert np.array_equal(group_sizes(cells, w), want)
    shuffled = np.random.default_rng(seed + 1).permutation(len(cells))  # any order of cells
    assert np.array_equal(group_sizes(cells[shuffled], w), want[shuffled])


def test_open_unknown_drops_small_enclosed_pockets_only():
    g = side_opening_grid()  # the 1 m x 1.5 m unknown room behind the opening: 150 cells
    assert open_unknown(g, 50).sum() == (g < 0).sum() == 150  # big enough: kept
    assert open_unknown(g, 200).sum() == 0  # a pocket below 200 cells: dropped
    u = open_unknown(g, 200)
    assert len(frontier_cells(g, 0.35, 4, u)) == 0 and len(frontier_cells(g, 0.35, 4)) == 10
    g2 = free_grid()
    g2[:, :3] = -1  # unknown touching the grid border: real unexplored space, whatever its size
    assert open_unknown(g2, 10 ** 6).sum() == (g2 < 0).sum()
    assert open_unknown(g, 0).sum() == 150  # 0 disables


def test_leaf_chains_stop_at_branches_and_other_ends():
    edges = [(a, b) for a, b, _ in chain_edges()]
    ch = leaf_chains([1, 4, 5], edges)
    assert ch == {1: [0, 1], 4: [2], 5: [3]}
    # a corridor with two ends: the same edges for both; an end node of degree 0 owns nothing
    assert leaf_chains([7, 8, 9], [(7, 6), (6, 8)]) == {7: [0, 1], 8: [1, 0], 9: []}


def test_frontier_owned_by_the_leaf_chain_nearest_to_it():
    g = side_opening_grid()
    edges = graph([], (), chain_edges())
    own = frontier_owned([1, 4, 5], edges, g, GEOM, 0.35, 4, 8.0)
    assert own == {1: 10}
    assert frontier_owned([1, 4, 5], edges, g, GEOM, 0.35, 4, 1.0) == {}  # 1.45 m away
    assert frontier_owned([1, 4, 5], edges, side_opening_grid(0.3), GEOM, 0.35, 4, 8.0) == {}


def test_a_chain_between_two_end_nodes_is_split_between_them():
    """The corridor's two ends 1 (x = -4.5) and 9 (x = -0.1) are joined by a chain with no
    branch: the opening at x in [-3, -2) is nearer to end 1 along the chain, so only end 1
    owns it (the far end of a lone chain used to own the frontier behind the robot too)."""
    g = side_opening_grid()
    edges = graph([], (), [(1, 2, [(-4.5, 0.0), (-2.5, 0.0)]), (2, 9, [(-2.5, 0.0), (-0.1, 0.0)])])
    assert frontier_owned([1, 9], edges, g, GEOM, 0.35, 4, 8.0) == {1: 10}
    edges2 = graph([], (), [(1, 9, [(-2.8, 0.0), (-1.0, 0.0), (4.0, 0.0)])])  # opening near 1
    assert frontier_owned([1, 9], edges2, g, GEOM, 0.35, 4, 8.0) == {1: 10}
    edges3 = graph([], (), [(9, 1, [(4.0, 0.0), (-1.0, 0.0), (-2.8, 0.0)])])  # same, reversed
    assert frontier_owned([1, 9], edges3, g, GEOM, 0.35, 4, 8.0) == {1: 10}


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2 ** 31 - 1), st.integers(1, 6), st.sampled_from(["never", "open", "lazy"]))
def test_ownership_read_from_a_window_is_the_whole_grids(seed, min_cells, unknown):
    """FrontierOwnership.cells from the window round a node's chain equals the same count on
    the whole grid: random trees of straight edges (with chains of corner nodes, a chain
    joining two end nodes, edges both ways), on grids of free, occupied, undecided and
    never-observed blocks with speckle, the unknown mask absent, an array or an
    OpenUnknown."""
    rng = np.random.default_rng(seed)
    geom = GridGeometry(resolution=0.1, origin_x=0.0, origin_y=0.0, width=90, height=70)
    g = rng.choice(np.array([-1, 0, 0, 0, 50, 100], np.int8), size=(7, 9)).repeat(10, 0).repeat(
        10, 1)
    speck = rng.random(g.shape) < 0.05
    g[speck] = rng.choice(np.array([-1, 0, 100, 40], np.int8), size=int(speck.sum()))
    n = int(rng.integers(2, 12))
    xy = rng.uniform((0.2, 0.2), (8.8, 6.8), size=(n, 2))
    pairs = [(i, int(rng.integers(0, i))) for i in range(1, n)] + [(n, n + 1)]
    xy = np.vstack([xy, rng.uniform((0.2, 0.2), (8.8, 6.8), size=(2, 2))])
    edges = []
    for a, b in pairs:
        mid = (xy[a] + xy[b]) / 2 + rng.normal(0.0, 0.3, 2)
        pts = [tuple(xy[a]), tuple(mid), tuple(xy[b])]
        edges.append((a, b, pts) if rng.random() < 0.7 else (b, a, pts[::-1]))
    deg = np.bincount(np.array(pairs).ravel(), minlength=n + 2)
    ends = [int(i) for i in np.flatnonzero(deg == 1)]
    gr = graph([], (), edges)
    mask = {"never": None, "open": open_unknown(g, 30), "lazy": OpenUnknown(g, 30)}[unknown]
    for max_dist in (0.6, 1.5):
        win = FrontierOwnership(ends, gr, g, geom, 0.35, min_cells, max_dist, mask)
        whole = FrontierOwnership(ends, gr, g, geom, 0.35, min_cells, max_dist, mask, whole=True)
        assert [win.cells(e) for e in ends] == [whole.cells(e) for e in ends]


def test_observations_of_a_node_owning_a_frontier_do_not_count():
    """Rule 3 (reliability.frontier_group > 0; 1 m by default, docs/design.md)."""
    g = side_opening_grid()
    edges = chain_edges()
    core = ReliabilityCore(msgspec.structs.replace(P, frontier_group=0.4))
    ends = [(1, -4.5, 0.0), (4, -0.5, -0.8)]
    out = None
    for k in range(8):  # the robot drives along the corridor looking at both nodes
        pose = (-2.0 + 0.1 * k, 0.3 - 0.1 * k, -math.pi / 2 if k % 2 else math.pi)
        out = upd(core, ends, [], pose, g, GEOM, edges=edges)
    p = {n.id: n for n in out}
    assert p[1].frontier == 10 and p[1].p == P.p_init and p[1].n_obs > 0
    assert p[4].frontier == 0 and p[4].p > P.p_init
    # the frontier is resolved (a wall there now): node 1's observations count again
    g2 = g.copy()
    g2[g2 == -1] = 100
    for k in range(4):
        out = upd(core, ends, [], (-2.0 - 0.3 * k, 0.0, math.pi), g2, GEOM, edges=edges)
    p = {n.id: n for n in out}
    assert p[1].frontier == 0 and p[1].p > P.p_init
    # no edges given / frontier_group = 0: the rule is off
    core = ReliabilityCore(msgspec.structs.replace(P, frontier_group=0.0))
    for k in range(4):
        out = upd(core, ends, [], (-2.0 - 0.3 * k, 0.0, math.pi), g, GEOM, edges=edges)
    assert {n.id: n.p for n in out}[1] > P.p_init


def test_frontier_ownership_is_worked_out_only_when_an_observation_can_count(monkeypatch):
    """Rule 3's test runs once on an update with a node in sight from a new viewpoint (for
    that node alone), and not at all on one without (the robot looking away); Beliefs keep
    the count as last worked out."""
    import topoexplore.services.reliability.core as rc

    calls = []
    real = rc.FrontierOwnership.cells
    monkeypatch.setattr(rc.FrontierOwnership, "cells",
                        lambda *a, **k: calls.append(1) or real(*a, **k))
    g, edges = side_opening_grid(), chain_edges()
    core = ReliabilityCore(msgspec.structs.replace(P, frontier_group=0.4))
    ends = [(1, -4.5, 0.0), (4, -0.5, -0.8)]
    p = {n.id: n for n in upd(core, ends, [], (-2.0, 0.3, math.pi), g, GEOM, edges=edges)}
    assert len(calls) == 1 and p[1].visible and p[1].frontier == 10
    p = {n.id: n for n in upd(core, ends, [], (-2.0, 0.3, math.pi / 2), g, GEOM, edges=edges)}
    assert not p[1].visible and not p[4].visible  # looking away from both
    assert len(calls) == 1 and p[1].frontier == 10
    upd(core, ends, [], (-2.0, 0.3, math.pi), g, GEOM, edges=edges)
    assert len(calls) == 2  # node 1's view did not count (it owned the frontier): still new


# --- examined surroundings (docs/design.md, "Reliability") ---------------------------------

P_EXAMINED = msgspec.structs.replace(P, examined_radius=1.0)


def unknown_beyond(x: float) -> np.ndarray:
    """Free grid, unknown from world x = x on (the map stops there)."""
    g = free_grid()
    _, col = GEOM.world_to_cell(x, 0.0)
    g[:, int(col):] = -1
    return g


def test_a_node_whose_surroundings_are_mapped_is_reliable_from_afar():
    """Seen from 4 m (D = 0.5 by eq. 2: no evidence) with nothing unknown within 1 m: the
    place is examined, the observation counts as from close by."""
    core = ReliabilityCore(P_EXAMINED)
    n = upd(core, [(1, 4.0, 0.0)], [], (0.0, 0.0, 0.0), free_grid(), GEOM)[0]
    assert n.visible and n.d == 1.0 and n.p >= P.p_reliable
    assert core.snapshot()["nodes"]["1"]["examined"]
    paper = ReliabilityCore(P)
    n = upd(paper, [(1, 4.0, 0.0)], [], (0.0, 0.0, 0.0), free_grid(), GEOM)[0]
    assert n.d == pytest.approx(4.0 / 7.5) and n.p < P.p_reliable


def test_a_node_with_unknown_space_near_is_not_examined():
    """Unknown 0.8 m beyond the node (a frontier within examined_radius, outside
    frontier_radius): eq. 2 decides, as without the rule."""
    core = ReliabilityCore(P_EXAMINED)
    n = upd(core, [(1, 4.0, 0.0)], [], (0.0, 0.0, 0.0), unknown_beyond(4.8), GEOM)[0]
    assert n.visible and n.d == pytest.approx(4.0 / 7.5) and n.p < P.p_reliable
    assert not core.snapshot()["nodes"]["1"]["examined"]


def test_unknown_behind_a_wall_does_not_hold_a_node_open():
    """A wall between the node and the unknown space: no frontier, so examined."""
    g = unknown_beyond(4.6)
    _, col = GEOM.world_to_cell(4.5, 0.0)
    g[:, int(col)] = 100
    core = ReliabilityCore(P_EXAMINED)
    n = upd(core, [(1, 4.0, 0.0)], [], (0.0, 0.0, 0.0), g, GEOM)[0]
    assert n.d == 1.0 and n.p >= P.p_reliable


@pytest.mark.parametrize("views", [0, 3])
def test_a_wall_face_cleared_by_grazing_beams_holds_a_node_open_only_without_surfaces(views):
    """The wall 0.3 m beyond the node, seen occupied on three updates, then 0.8 m of its face
    cleared (grazing beams; its inside never seen): with the surface memory the cleared cells
    are no frontier and the next observation counts; without it they are a frontier within
    frontier_radius and it does not."""
    whole = unknown_beyond(4.4)
    _, col = GEOM.world_to_cell(4.3, 0.0)  # the face cells' centres 0.35 m from the node
    row, _ = GEOM.world_to_cell(0.0, 0.0)
    whole[:, int(col)] = 100
    cleared = whole.copy()
    cleared[int(row) - 4:int(row) + 4, int(col)] = 0
    core = ReliabilityCore(msgspec.structs.replace(P, surface_views=views))
    for k in range(3):
        n = upd(core, [(1, 4.0, 0.0)], [], (0.0, 0.6 * (k - 1), 0.0), whole, GEOM)[0]
    before = n.p
    n = upd(core, [(1, 4.0, 0.0)], [], (0.0, -1.5, 0.3), cleared, GEOM)[0]
    assert n.visible and before > P.p_init
    assert (n.p > before) is (views > 0), (before, n.p)
    arrays = core.checkpoint()
    again = ReliabilityCore(msgspec.structs.replace(P, surface_views=views))
    again.restore(arrays)
    assert again.snapshot()["nodes"] == core.snapshot()["nodes"]


@pytest.mark.parametrize("gap_cells,examined", [(2, True), (4, True), (8, False)])
def test_a_few_cells_of_frontier_are_speckle_a_door_is_a_frontier(gap_cells, examined):
    """A wall 0.5 m beyond the node with a gap in it: a gap of fewer than min_frontier (0.5 m,
    5 cells) of frontier cells is a hole in a ragged SLAM wall, as the planner's frontier
    rules see it, and the node is examined; an 0.8 m gap is a door to unknown space."""
    g = unknown_beyond(4.6)
    _, col = GEOM.world_to_cell(4.5, 0.0)
    row, _ = GEOM.world_to_cell(0.0, 0.0)
    g[:, int(col)] = 100
    lo = int(row) - gap_cells // 2
    g[lo:lo + gap_cells, int(col)] = 0
    core = ReliabilityCore(P_EXAMINED)
    n = upd(core, [(1, 4.0, 0.0)], [], (0.0, 0.0, 0.0), g, GEOM)[0]
    assert core.snapshot()["nodes"]["1"]["examined"] is examined
    assert (n.p >= P.p_reliable) is examined
    one = ReliabilityCore(msgspec.structs.replace(P_EXAMINED, min_frontier=0.0))
    upd(one, [(1, 4.0, 0.0)], [], (0.0, 0.0, 0.0), g, GEOM)
    assert not one.snapshot()["nodes"]["1"]["examined"]  # 0: any single cell counts


def test_examined_stays_with_the_node_until_it_moves():
    core = ReliabilityCore(P_EXAMINED)
    upd(core, [(1, 4.0, 0.0)], [], (0.0, 0.0, 0.0), free_grid(), GEOM)
    n = upd(core, [(1, 4.0, 0.0)], [], (0.0, 0.0, math.pi), free_grid(), GEOM)[0]
    assert not n.visible and n.d == 1.0
    n = upd(core, [(1, 5.0, 0.0)], [], (0.0, 0.0, math.pi), free_grid(), GEOM)[0]
    assert n.d == 0.0 and n.p == P.p_init  # moved beyond move_tolerance: a new history


def aisle_grid(open_end: bool) -> np.ndarray:
    """An aisle 2.5 m wide along x (shelves at y = +-1.3 m), its far end at x = 5.25 m open
    to unknown space (open_end) or closed by a wall."""
    g = free_grid()
    for y in (-1.3, 1.3):
        row, _ = GEOM.world_to_cell(0.0, y)
        g[int(row), :] = 100
    _, col = GEOM.world_to_cell(5.25, 0.0)
    g[:, int(col):] = -1 if open_end else 100
    return g


@pytest.mark.parametrize("examined", [0.0, 1.0])
def test_a_node_at_the_end_of_a_wide_aisle_into_unknown_space_is_not_reliable(examined):
    """The skeleton of an aisle 2.5 m wide that runs into unknown space ends about half its
    width short of the unknown: 1.25 m, beyond frontier_radius (0.5 m) and examined_radius
    (1 m). Driving past its mouth, the robot saw the node from many bearings, and it was
    accepted (a warehouse: the band behind four aisles left for the end of the run). With
    frontier_clearance (off by default: it lost on the tuning half) the frontier test's
    radius grows by the node's distance to the nearest occupied cell, so it holds; a closed
    aisle's node is still accepted from afar."""
    prm = msgspec.structs.replace(P, examined_radius=examined)
    poses = [(0.0, 0.8 - 0.4 * k, 0.3 * (k - 2)) for k in range(5)]
    for open_end, rule, held in [(True, True, True), (True, False, False),
                                 (False, True, False)]:
        core = ReliabilityCore(msgspec.structs.replace(prm, frontier_clearance=rule))
        for pose in poses:
            n = upd(core, [(1, 4.0, 0.0)], [], pose, aisle_grid(open_end), GEOM)[0]
        assert n.visible and n.n_obs == len(poses)
        assert (n.p == P.p_init) is held, (open_end, rule, n.p)
        assert (n.p >= P.p_reliable) is not held or examined == 0.0, (open_end, rule, n.p)


def test_nearest_occupied_is_capped():
    g = aisle_grid(False)
    assert nearest_occupied(4.0, 0.0, g, GEOM, 4.5) == pytest.approx(1.25, abs=0.06)
    assert nearest_occupied(4.0, 0.0, g, GEOM, 0.8) == 0.8
    assert nearest_occupied(0.0, 0.0, free_grid(), GEOM, 2.0) == 2.0
    assert nearest_occupied(0.0, 0.0, g, GEOM, 0.0) == 0.0


AISLE_EDGE = (7, 1, np.array([[0.0, 0.0], [2.0, 0.0], [4.0, 0.0]]))  # branch 7 -> end node 1


def test_leaf_headings_point_where_the_skeleton_ran_out():
    g = graph([(1, 4.0, 0.0), (2, 0.0, -3.0)], edges=[
        AISLE_EDGE, (2, 7, np.array([[0.0, -3.0], [0.0, -1.0], [0.0, 0.0]]))])
    h = leaf_headings(g)
    assert h[1] == pytest.approx(0.0) and h[2] == pytest.approx(-math.pi / 2)
    assert leaf_headings(graph([(1, 4.0, 0.0)])) == {}  # no edge: no heading
    short = graph([(1, 0.1, 0.0)], edges=[(7, 1, np.array([[0.0, 0.0], [0.1, 0.0]]))])
    assert leaf_headings(short)[1] == pytest.approx(0.0)  # shorter than back: the far end


def test_near_frontier_in_a_cone_and_the_free_disc():
    g = aisle_grid(True)
    unk = g < 0
    assert not near_frontier(4.0, 0.0, g, GEOM, 0.5, unknown=unk, min_cells=5)
    assert near_frontier(4.0, 0.0, g, GEOM, 1.75, unknown=unk, min_cells=5, heading=0.0,
                         half_angle=math.pi / 4)
    assert not near_frontier(4.0, 0.0, g, GEOM, 1.75, unknown=unk, min_cells=5,
                             heading=math.pi, half_angle=math.pi / 4)  # behind the node
    # the free disc: up to the nearest occupied or unknown cell
    assert nearest_occupied(4.6, 0.0, g, GEOM, 4.5) == pytest.approx(1.3, abs=0.06)
    assert nearest_occupied(4.6, 0.0, g, GEOM, 4.5, unknown=unk) == pytest.approx(0.7, abs=0.06)


@pytest.mark.parametrize("examined", [0.0, 1.0])
def test_frontier_ahead_holds_an_aisle_into_unknown_space_open(examined):
    """frontier_ahead (off by default until measured): the node at the end of an aisle 2.5 m
    wide whose skeleton ran out where the unknown begins (1.25 m beyond) is a frontier, its
    observations from the aisle's mouth do not count; a closed aisle's node is accepted, and
    so is a node whose unknown lies beside it, outside the cone (a ragged wall)."""
    prm = msgspec.structs.replace(P, examined_radius=examined)
    poses = [(0.0, 0.8 - 0.4 * k, 0.3 * (k - 2)) for k in range(5)]

    def final(grid, rule, heading_edge=AISLE_EDGE):
        core = ReliabilityCore(msgspec.structs.replace(
            prm, frontier_ahead=math.pi / 4 if rule else 0.0))
        for pose in poses:
            n = upd(core, [(1, 4.0, 0.0)], [], pose, grid, GEOM, edges=[heading_edge])[0]
        assert n.visible and n.n_obs == len(poses)
        return n.p

    assert final(aisle_grid(True), True) == P.p_init
    assert final(aisle_grid(True), False) > P.p_init
    closed = final(aisle_grid(False), True)
    assert closed > P.p_init and (closed >= P.p_reliable or examined == 0.0)
    # the same aisle, its skeleton running across it (heading +y): the unknown is beside it
    across = (7, 1, np.array([[4.0, -1.0], [4.0, -0.5], [4.0, 0.0]]))
    assert final(aisle_grid(True), True, across) > P.p_init
