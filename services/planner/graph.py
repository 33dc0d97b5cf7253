"""Topological-graph search for the planner (pure: no I/O, no clock, no bus).

Paper §3.2: the next target end node is the one with the least A* path cost over the
topological map, and the robot travels along the topological edges to it. DESIGN.md §4
"Planner" adds: only edges with clearance >= robot radius + margin are traversable, and the
robot joins the skeleton at an *entry point* = the nearest point of any traversable edge
polyline that it can reach in a straight line through known free cells.

The search is A* with a zero heuristic (= Dijkstra) from the entry point to *every* node at
once: the target choice needs the exact path cost of every candidate, and one single-source
search returns exactly what one A* run per candidate would (A* with the Euclidean heuristic is
:func:`astar_cost`, kept for single-goal queries and for the tests that cross-check both).
"""

from __future__ import annotations

import heapq
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from topoexplore.common.domain import Graph
from topoexplore.common.grid import GridGeometry

ENTRY = -1  # pseudo node id of the entry point in predecessor chains
DENSE_STEP = 0.05  # [m] edge polylines are resampled at least this densely, so that the
#   clearance measured at their points sees an obstacle beside a long straight stretch


class GraphInputError(ValueError):
    """A topological graph or a query on it is unusable."""


@dataclass(eq=False, slots=True)
class Edge:
    """One topological edge of the search with its polyline oriented from node a to node b
    (made for every edge on every update: a plain slotted class, cheap to build)."""

    idx: int
    a: int
    b: int
    pts: np.ndarray  # (n, 2) polyline [m], n >= 2, pts[0] at node a, pts[-1] at node b
    cum: np.ndarray  # (n,) cumulative arc length along pts [m]
    clearance: float  # [m]

    @property
    def length(self) -> float:
        return float(self.cum[-1])


@dataclass
class TopoIndex:
    """Search structure built from one topological graph (:func:`build_index`)."""

    nodes: dict[int, tuple[str, float, float]]  # id -> (kind, x [m], y [m]); kind "cut" (id
    #   < 0): where build_index split a narrow edge into its wide ends and narrow middle
    edges: list[Edge]  # traversable edges (clearance high enough), indexed by Edge.idx
    narrow: list[Edge]  # edges too narrow for the robot (kept for reporting)
    adj: dict[int, list[tuple[int, float, int, bool]]] = field(default_factory=dict)
    # adj[u] = [(v, cost [m], edge idx, forward = traversed a->b), ...]
    narrow_adj: dict[int, list[tuple[int, float, int, bool]]] = field(default_factory=dict)
    # the same for narrow edges, with edge idx = -(narrow idx + 1)

    def edge(self, ei: int) -> Edge:
        """Edge by search index: ei >= 0 a traversable edge, ei < 0 narrow[-ei - 1]."""
        return self.edges[ei] if ei >= 0 else self.narrow[-ei - 1]

    def end_ids(self) -> list[int]:
        return [i for i, (k, _, _) in self.nodes.items() if k == "end"]

    def all_points(self) -> np.ndarray:
        """All polyline points (traversable and narrow edges) stacked, (n, 2) [m]."""
        if not self.edges and not self.narrow:
            return np.zeros((0, 2))
        return np.concatenate([e.pts for e in self.edges + self.narrow])


@dataclass(frozen=True)
class Entry:
    """Where the robot joins the skeleton: point on edge `edge` between pts[seg] and pts[seg+1]."""

    edge: Edge
    seg: int
    x: float  # [m]
    y: float  # [m]
    arc: float  # [m] arc length from node a to the entry point along the edge
    dist: float  # [m] straight-line robot -> entry
    line_of_sight: bool  # False: fallback to the nearest point (no free straight line found)
    lead: np.ndarray | None = None  # (n, 2) [m] grid path robot -> entry point, where no
    #   straight line fits the robot's body (then dist is its length)


def polyline_lengths(pts: np.ndarray) -> np.ndarray:
    """Cumulative arc length [m] of a (n, 2) polyline, starting at 0."""
    if len(pts) < 2:
        return np.zeros(len(pts))
    seg = np.hypot(np.diff(pts[:, 0]), np.diff(pts[:, 1]))
    return np.concatenate([[0.0], np.cumsum(seg)])


def _edge_polyline(pts: list[list[float]], pa: tuple[float, float], pb: tuple[float, float]
                   ) -> list[list[float]]:
    """Edge polyline (a list the caller owns) oriented a -> b and anchored at both node
    positions (plain lists: this runs for every edge on every update, numpy per edge would
    cost more than the search)."""
    ax, ay = pa
    bx, by = pb
    if len(pts) >= 2:
        # tolerate a polyline given b -> a (orientation is part of the contract, but cheap to fix)
        (x0, y0), (x1, y1) = pts[0], pts[-1]
        keep = math.hypot(x0 - ax, y0 - ay) + math.hypot(x1 - bx, y1 - by)
        flip = math.hypot(x0 - bx, y0 - by) + math.hypot(x1 - ax, y1 - ay)
        if flip < keep:
            pts.reverse()
    if not pts or math.hypot(pts[0][0] - ax, pts[0][1] - ay) > 1e-6:
        pts.insert(0, [ax, ay])
    if math.hypot(pts[-1][0] - bx, pts[-1][1] - by) > 1e-6 or len(pts) < 2:
        pts.append([bx, by])
    return pts


def densify(pts: np.ndarray, step: float) -> np.ndarray:
    """The polyline pts (n, 2) [m] with points inserted so that no two in a row are more than
    step [m] apart (a topology message may simplify a straight stretch to its two ends)."""
    n = len(pts)
    if n < 2:
        return pts
    d = pts[1:] - pts[:-1]
    reps = np.ones(n, np.int64)  # the points each one stands for: itself and those after it
    reps[:-1] = np.maximum(1, np.ceil(np.hypot(d[:, 0], d[:, 1]) / step)).astype(np.int64)
    src = np.repeat(np.arange(n), reps)
    first = np.repeat(np.cumsum(reps) - reps, reps)
    frac = (np.arange(len(src)) - first) / np.repeat(reps, reps)
    seg = np.vstack([d, np.zeros((1, 2))])[src]  # the last point starts no segment
    return pts[src] + frac[:, None] * seg


def build_index(graph: Graph, min_clearance: float,
                clearance_at: Callable[[np.ndarray], np.ndarray] | None = None,
                tip_length: float = 0.0, polylines: PolylineCache | None = None
                ) -> TopoIndex:
    """Graph -> TopoIndex. Edges with clearance < min_clearance [m] are not traversable.

    The clearance is the edge's own ``clearance`` field, or, when ``clearance_at(points)``
    (clearance [m] at each point) is given, its least value along the polyline leaving out the
    last ``tip_length`` [m] next to an end node. The planner passes the distance to the nearest
    *occupied* cell: a gap is narrow between obstacles (the graph's clearance also counts
    unknown cells, so every leaf edge ending at the edge of the known map would look narrow),
    and a skeleton tip in a dead-end corner is always close to the walls, yet the robot only
    needs to get near the end node (:func:`trim_narrow_tip` stops the path there).
    With ``clearance_at``, a narrow edge is split where it is narrow: its wide ends stay
    traversable up to "cut" nodes (negative ids) and only the stretch between them is narrow.
    Self-loops are dropped (never on a shortest path). Raises GraphInputError if an edge refers
    to a node that is not in the graph. ``polylines``: the edges' polylines kept from the last
    update (:class:`PolylineCache`; the same index either way).
    """
    cache = polylines or PolylineCache()
    if clearance_at is not None:
        same = cache.same_index(graph, (min_clearance, tip_length), clearance_at)
        if same is not None:
            return same
    nodes = {n.id: (n.kind, float(n.x), float(n.y)) for n in graph.nodes}
    kept, P, o, cum_all = cache.make(graph, nodes)
    b = _IndexBuilder(nodes)
    if not kept:
        return b.index()
    if clearance_at is None:
        for k, e in enumerate(kept):
            b.add(e.a, e.b, P[o[k]:o[k + 1]], cum_all[o[k]:o[k + 1]], float(e.clearance),
                  float(e.clearance) + 1e-9 >= min_clearance)
        return b.index()
    m = _PointClearance(P, o, cum_all, kept, nodes, clearance_at, min_clearance, tip_length)
    for k, e in enumerate(kept):
        sl = slice(o[k], o[k + 1])
        if m.clear[k] + 1e-9 >= min_clearance:
            b.add(e.a, e.b, P[sl], cum_all[sl], float(m.clear[k]), True)
        else:
            b.add_narrow(e.a, e.b, P[sl], cum_all[sl], m.inner[sl], m.c_all[sl],
                         np.flatnonzero(m.bad[sl]), float(m.clear[k]))
    index = b.index()
    cache.keep_index(graph, (min_clearance, tip_length), P, m.c_all, index)
    return index


class PolylineCache:
    """The dense polylines of a graph's edges (:func:`_edge_polyline`, then :func:`densify`)
    and their arc lengths, kept from one update to the next: the topology service sends the
    whole graph on every update, and almost every edge comes back as it was (97 % of them on
    the 60 x 60 m office), so only the new ones are made. An edge is the same when its end
    nodes (ids and positions) and its points are; the cache holds the last update's edges
    only."""

    def __init__(self) -> None:
        self._made: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}
        self._index: tuple | None = None  # the last index made with a clearance: (graph,
        #   its arguments, the flat polylines, the clearance at them, the index)
        self.reused = 0  # updates whose index was the one before (:meth:`same_index`)

    def same_index(self, graph: Graph, args: tuple, clearance_at: Callable[[np.ndarray],
                   np.ndarray]) -> TopoIndex | None:
        """The index kept by :meth:`keep_index` if it is the one ``build_index`` would make
        now: the same nodes, edges and polylines, the same arguments, and the same clearance
        at every polyline point. While the robot drives through mapped space the topology
        sends the same graph again and again (the index is read, never changed)."""
        if self._index is None:
            return None
        old, old_args, P, c_all, index = self._index
        if (old_args != args or len(old.edges) != len(graph.edges) or old.nodes != graph.nodes
                or not np.array_equal(old.offsets, graph.offsets)
                or not np.array_equal(old.points, graph.points)
                or any(e.a != f.a or e.b != f.b for e, f in zip(old.edges, graph.edges,
                                                                 strict=True))
                or not np.array_equal(np.asarray(clearance_at(P), np.float64), c_all)):
            return None
        self.reused += 1
        return index

    def keep_index(self, graph: Graph, args: tuple, P: np.ndarray, c_all: np.ndarray,
                   index: TopoIndex) -> None:
        """Keep the index just made from graph with args, and the clearance c_all [m] it
        read at the flat polyline points P, for :meth:`same_index`."""
        self._index = (graph, args, P, c_all, index)

    def make(self, graph: Graph, nodes: dict[int, tuple[str, float, float]]
             ) -> tuple[list, np.ndarray, np.ndarray, np.ndarray]:
        """(edges kept, P, o, cum): the edges that join two different nodes, their polylines
        in one flat (P, 2) array [m] with each edge's start offset in o (and the end), and
        each point's arc length [m] from its own edge's start."""
        pts, off = graph.points, graph.offsets.tolist()
        old, made = self._made, {}
        kept, parts, arcs = [], [], []
        for k, e in enumerate(graph.edges):
            if e.a not in nodes or e.b not in nodes:
                raise GraphInputError(f"edge {e.a}-{e.b} refers to a node that is not in the "
                                      "graph")
            if e.a == e.b:
                continue
            mine = pts[off[k]:off[k + 1]]
            key = (e.a, e.b, nodes[e.a][1:], nodes[e.b][1:], mine.tobytes())
            got = made.get(key) or old.get(key)
            if got is None:
                got = _dense_polyline(mine.tolist(), nodes[e.a][1:], nodes[e.b][1:])
            made[key] = got
            kept.append(e)
            parts.append(got[0])
            arcs.append(got[1])
        self._made = made
        if not kept:
            return kept, np.zeros((0, 2)), np.zeros(1, np.int64), np.zeros(0)
        o = np.concatenate([[0], np.cumsum([len(a) for a in arcs])])
        return kept, np.concatenate(parts), o, np.concatenate(arcs)


def _dense_polyline(pts: list[list[float]], pa: tuple[float, float], pb: tuple[float, float]
                    ) -> tuple[np.ndarray, np.ndarray]:
    """One edge's polyline (:func:`_edge_polyline`) resampled every DENSE_STEP at least
    (:func:`densify`), and its arc length [m] at each point."""
    line = np.asarray(_edge_polyline(pts, pa, pb), dtype=np.float64)
    P = densify(line, DENSE_STEP)
    P.flags.writeable = False  # shared by every update that keeps the edge
    cum = polyline_lengths(P)
    cum.flags.writeable = False
    return P, cum


class _PointClearance:
    """Clearance of the flat polylines per point and per edge (:func:`build_index`)."""

    def __init__(self, P: np.ndarray, o: np.ndarray, cum_all: np.ndarray, kept: list,
                 nodes: dict[int, tuple[str, float, float]],
                 clearance_at: Callable[[np.ndarray], np.ndarray], min_clearance: float,
                 tip_length: float):
        length = cum_all[o[1:] - 1]
        lo = np.array([tip_length if nodes[e.a][0] == "end" else 0.0 for e in kept])
        hi = length - np.array([tip_length if nodes[e.b][0] == "end" else 0.0 for e in kept])
        cnt = np.diff(o)
        # per point: not within tip_length of an end node / clearance [m] / inner and narrow
        self.inner = ((cum_all >= np.repeat(lo, cnt) - 1e-9)
                      & (cum_all <= np.repeat(hi, cnt) + 1e-9))
        self.c_all = np.asarray(clearance_at(P), dtype=np.float64)
        self.bad = self.inner & (self.c_all + 1e-9 < min_clearance)
        # per edge: least clearance of its inner points
        self.clear = np.minimum.reduceat(np.where(self.inner, self.c_all, np.inf), o[:-1])
        short = ~np.isfinite(self.clear) & (np.add.reduceat(self.inner, o[:-1]) == 0)
        for k in np.nonzero(short)[0]:
            seg = cum_all[o[k]:o[k + 1]]  # short edge: judge it by its middle point
            self.clear[k] = self.c_all[o[k] + int(np.argmin(np.abs(seg - 0.5 * seg[-1])))]


class _IndexBuilder:
    """Collects the traversable and narrow edges of a TopoIndex and their adjacency."""

    def __init__(self, nodes: dict[int, tuple[str, float, float]]):
        self.nodes = nodes
        self.adj: dict[int, list[tuple[int, float, int, bool]]] = {i: [] for i in nodes}
        self.nadj: dict[int, list[tuple[int, float, int, bool]]] = {}
        self.edges: list[Edge] = []
        self.narrow: list[Edge] = []
        self.cut_id = ENTRY - 1  # cut nodes: -2, -3, ... (topology ids are >= 0; ENTRY is -1)

    def index(self) -> TopoIndex:
        return TopoIndex(self.nodes, self.edges, self.narrow, self.adj, self.nadj)

    def add(self, a: int, b: int, pts: np.ndarray, cum: np.ndarray, c: float, ok: bool
            ) -> None:
        """Edge a -> b along pts (cum: arc length at each point, from 0), traversable if ok."""
        edges, adj = (self.edges, self.adj) if ok else (self.narrow, self.nadj)
        k = len(edges)
        edges.append(Edge(k, a, b, pts, cum, c))
        ei = k if ok else -k - 1
        length = float(cum[-1])
        adj.setdefault(a, []).append((b, length, ei, True))
        adj.setdefault(b, []).append((a, length, ei, False))

    def cut(self, x: float, y: float) -> int:
        """A new cut node at (x, y) [m]; its id."""
        i, self.cut_id = self.cut_id, self.cut_id - 1
        self.nodes[i] = ("cut", float(x), float(y))
        return i

    def add_narrow(self, a: int, b: int, pts: np.ndarray, cum: np.ndarray, inn: np.ndarray,
                   cc: np.ndarray, bad: np.ndarray, c: float) -> None:
        """A narrow edge: split at its narrow stretch (points `bad`, inner points `inn`,
        clearance `cc`) so that the wide parts on either side stay traversable (a long
        corridor edge with one narrow spot far away is still where the robot can drive); a
        side that is only an end node's tip (allowed narrow) is not split off."""
        if bad.size == 0:  # a short edge judged by its middle point
            self.add(a, b, pts, cum, c, False)
            return
        i0, i1 = int(bad[0]) - 1, int(bad[-1]) + 1
        before, after = bool(inn[:i0 + 1].any()), bool(inn[i1:].any())
        ca, cb = a, b
        if before:
            ca = self.cut(pts[i0, 0], pts[i0, 1])
            self.add(a, ca, pts[:i0 + 1], cum[:i0 + 1], float(cc[:i0 + 1][inn[:i0 + 1]].min()),
                     True)
        if after:
            cb = self.cut(pts[i1, 0], pts[i1, 1])
        lo_i, hi_i = (i0 if before else 0), (i1 if after else len(pts) - 1)
        self.add(ca, cb, pts[lo_i:hi_i + 1], cum[lo_i:hi_i + 1] - cum[lo_i], c, False)
        if after:
            self.add(cb, b, pts[i1:], cum[i1:] - cum[i1], float(cc[i1:][inn[i1:]].min()), True)


# --- line of sight on the grid ---------------------------------------------------------------


def line_of_sight(free: np.ndarray, geom: GridGeometry, x0: float, y0: float, x1: float,
                  y1: float, skip_radius: float = 0.0) -> bool:
    """True if every grid cell on the segment (x0,y0)-(x1,y1) [m] is known free.

    Samples every third of a cell. Samples within `skip_radius` [m] of (x0, y0) are ignored:
    the robot stands there, and its own cells may still be unknown or noisy. Cells outside the
    grid count as not free.
    """
    length = math.hypot(x1 - x0, y1 - y0)
    n = max(2, int(math.ceil(length / (geom.resolution / 3.0))) + 1)
    s = np.linspace(0.0, 1.0, n)
    xs = x0 + s * (x1 - x0)
    ys = y0 + s * (y1 - y0)
    keep = s * length > skip_radius
    if not np.any(keep):
        return True
    rows, cols = geom.world_to_cell(xs[keep], ys[keep])
    inside = geom.inside(rows, cols)
    if not np.all(inside):
        return False
    return bool(np.all(free[rows, cols]))


def crosses(blocked: np.ndarray, geom: GridGeometry, pts: np.ndarray) -> bool:
    """True if the polyline pts (n, 2) [m] passes through a cell set in `blocked`.

    Samples every third of a cell along each segment; samples outside the grid are ignored
    (the map may not have grown there yet).
    """
    pts = np.asarray(pts, dtype=np.float64).reshape(-1, 2)
    if len(pts) == 0:
        return False
    if len(pts) == 1:
        xs, ys = pts[:, 0], pts[:, 1]
    else:
        d = np.hypot(*np.diff(pts, axis=0).T)
        n = np.maximum(1, np.ceil(d / (geom.resolution / 3.0)).astype(np.int64))
        seg = np.repeat(np.arange(len(d)), n)
        start = np.repeat(np.cumsum(n) - n, n)
        s = (np.arange(len(seg)) - start) / n[seg]
        a, b = pts[seg], pts[seg + 1]
        xs = np.append(a[:, 0] + s * (b[:, 0] - a[:, 0]), pts[-1, 0])
        ys = np.append(a[:, 1] + s * (b[:, 1] - a[:, 1]), pts[-1, 1])
    rows, cols = geom.world_to_cell(xs, ys)
    inside = geom.inside(rows, cols)
    return bool(np.any(blocked[rows[inside], cols[inside]]))


# --- entry point -----------------------------------------------------------------------------


TIE_DECIMALS = 9  # [m] distances to the skeleton compared to 1 nm (find_entry)


def find_entry(index: TopoIndex, x: float, y: float,
               visible: Callable[[float, float, float, float], bool] | None = None,
               max_checks: int = 64) -> Entry | None:
    """Entry point for a robot at (x, y) [m]: the nearest point of any traversable edge with a
    free straight line from the robot (`visible(x0, y0, x1, y1)`); if none of the `max_checks`
    nearest segments is visible, the nearest point overall (line_of_sight=False).
    None if the index has no traversable edge.
    """
    if not index.edges:
        return None
    pts = np.concatenate([e.pts for e in index.edges])
    n = np.array([len(e.pts) for e in index.edges])
    first = np.cumsum(n) - n  # each edge's first point
    p0, p1 = pts[:-1], pts[1:]  # segment k joins p0[k] and p1[k] (views, no copies) ...
    inside = np.ones(len(p0), bool)
    inside[first[1:] - 1] = False  # ... unless point k is the last of its edge
    eid = np.repeat(np.arange(len(n)), n)[:-1]  # edge idx (= position in index.edges)
    seg = np.arange(len(p0)) - first[eid]  # segment in edge
    d = p1 - p0
    dd = np.einsum("ij,ij->i", d, d)
    q = np.array([x, y])
    t = np.where(dd > 0, np.einsum("ij,ij->i", q - p0, d) / np.where(dd > 0, dd, 1.0), 0.0)
    t = np.clip(t, 0.0, 1.0)
    near = p0 + t[:, None] * d
    dist = np.where(inside, np.hypot(near[:, 0] - x, near[:, 1] - y), np.inf)
    dist = np.round(dist, TIE_DECIMALS)  # a point two segments share is as near on both: a tie
    #   (to the earlier one), not whichever the rounding of p0 + t d favours
    order = nearest_first(dist, max(1, max_checks) if visible is not None else 1)
    order = order[inside[order]]  # (fewer than max_checks segments: no joins of two edges)

    def make(k: int, los: bool) -> Entry:
        e = index.edges[int(eid[k])]
        i = int(seg[k])
        arc = float(e.cum[i] + t[k] * (e.cum[i + 1] - e.cum[i]))
        return Entry(e, i, float(near[k, 0]), float(near[k, 1]), arc, float(dist[k]), los)

    if visible is None:
        return make(int(order[0]), True)
    for k in order[:max_checks]:
        if visible(x, y, float(near[k, 0]), float(near[k, 1])):
            return make(int(k), True)
    return make(int(order[0]), False)


def nearest_first(values: np.ndarray, k: int) -> np.ndarray:
    """The indices of the k least values, least first, equal values in index order: the first
    k of ``np.argsort(values, kind="stable")`` without sorting all of them (a partition, then
    a sort of the values up to the k-th: 0.1 ms instead of 0.6-0.9 for 10 700 distances,
    large-office's skeleton)."""
    v = np.asarray(values)
    if k >= len(v):
        return np.argsort(v, kind="stable")
    kth = np.partition(v, k - 1)[k - 1]
    if np.isnan(kth):  # NaNs sort last: among the k only when fewer values are numbers
        return np.argsort(v, kind="stable")[:k]
    cand = np.flatnonzero(v <= kth)  # all values tied with the k-th too, in index order
    return cand[np.argsort(v[cand], kind="stable")][:k]


# --- search ----------------------------------------------------------------------------------


def entry_at(index: TopoIndex, edge_pos: int, k: int, lead: np.ndarray) -> Entry:
    """The entry at point k of edge index.edges[edge_pos], reached over the polyline `lead`
    [m] (robot -> that point) instead of a straight line."""
    e = index.edges[edge_pos]
    k = int(min(max(k, 0), len(e.pts) - 1))
    seg = min(k, len(e.pts) - 2)
    x, y = float(e.pts[k, 0]), float(e.pts[k, 1])
    length = float(polyline_lengths(lead)[-1]) if len(lead) > 1 else 0.0
    return Entry(e, seg, x, y, float(e.cum[k]), length, False, lead)


def search_from_entry(index: TopoIndex, entry: Entry, through_narrow: bool = False
                      ) -> tuple[dict[int, float], dict[int, tuple[int, int, bool]]]:
    """Least path cost [m] from the robot (via the entry point) to every reachable node.

    Cost = straight line robot -> entry + arc lengths along traversable edges (A* with h = 0);
    with ``through_narrow`` the narrow edges count too (where the robot could get if the
    passages were wide enough: see :func:`cut_at_narrow`).
    Returns (cost by node id, predecessor by node id) with pred[v] = (u, edge idx, forward)
    (edge idx as in :meth:`TopoIndex.edge`); u == ENTRY for the two nodes of the entry edge
    reached directly from the entry point.
    """
    e = entry.edge
    dist: dict[int, float] = {}
    pred: dict[int, tuple[int, int, bool]] = {}
    heap: list[tuple[float, int, int, int, bool]] = []
    heapq.heappush(heap, (entry.dist + entry.arc, e.a, ENTRY, e.idx, False))
    heapq.heappush(heap, (entry.dist + e.length - entry.arc, e.b, ENTRY, e.idx, True))
    while heap:
        c, v, u, ei, fwd = heapq.heappop(heap)
        if v in dist:
            continue
        dist[v] = c
        pred[v] = (u, ei, fwd)
        for w, wc, wi, wf in index.adj.get(v, ()):
            if w not in dist:
                heapq.heappush(heap, (c + wc, w, v, wi, wf))
        if through_narrow:
            for w, wc, wi, wf in index.narrow_adj.get(v, ()):
                if w not in dist:
                    heapq.heappush(heap, (c + wc, w, v, wi, wf))
    return dist, pred


def astar_cost(index: TopoIndex, entry: Entry, goal: int) -> float:
    """Single-goal A* (Euclidean heuristic) from the entry point to `goal`; inf if unreachable.

    Same costs as :func:`search_from_entry` (the heuristic is admissible: no edge is shorter
    than the straight line between its nodes).
    """
    if goal not in index.nodes:
        raise GraphInputError(f"goal node {goal} is not in the graph")
    gx, gy = index.nodes[goal][1:]

    def h(v: int) -> float:
        return math.hypot(index.nodes[v][1] - gx, index.nodes[v][2] - gy)

    e = entry.edge
    best: dict[int, float] = {}
    heap = [(entry.dist + entry.arc + h(e.a), entry.dist + entry.arc, e.a),
            (entry.dist + e.length - entry.arc + h(e.b), entry.dist + e.length - entry.arc, e.b)]
    heapq.heapify(heap)
    done: set[int] = set()
    while heap:
        _, g, v = heapq.heappop(heap)
        if v in done:
            continue
        if v == goal:
            return g
        done.add(v)
        for w, wc, _, _ in index.adj.get(v, ()):
            ng = g + wc
            if w not in done and ng < best.get(w, math.inf):
                best[w] = ng
                heapq.heappush(heap, (ng + h(w), ng, w))
    return math.inf


def path_points(index: TopoIndex, entry: Entry, pred: dict[int, tuple[int, int, bool]],
                goal: int) -> np.ndarray:
    """Dense polyline [m] entry point -> along the edges -> goal node (not yet thinned)."""
    if goal not in pred:
        raise GraphInputError(f"node {goal} is not reachable from the entry point")
    chain: list[tuple[int, bool]] = []
    v = goal
    while True:
        u, ei, fwd = pred[v]
        chain.append((ei, fwd))
        if u == ENTRY:
            break
        v = u
        if len(chain) > len(index.edges) + len(index.narrow) + 1:  # defensive
            raise GraphInputError("predecessor chain does not end at the entry point")
    chain.reverse()
    e = entry.edge
    first_ei, first_fwd = chain[0]
    start = np.array([[entry.x, entry.y]])
    if entry.lead is not None and len(entry.lead):
        start = np.vstack([entry.lead, start])
    if first_fwd:  # entry -> b
        parts = [start, e.pts[entry.seg + 1:]]
    else:  # entry -> a
        parts = [start, e.pts[entry.seg::-1]]
    for ei, fwd in chain[1:]:
        pts = index.edge(ei).pts
        parts.append((pts if fwd else pts[::-1])[1:])
    return np.concatenate(parts)


def cut_at_narrow(pts: np.ndarray, clearance_at: Callable[[np.ndarray], np.ndarray],
                  min_clearance: float) -> np.ndarray:
    """The part of a path before its first point with clearance < min_clearance [m]: where
    the robot can get on the way to a node behind a narrow passage (all of pts if none is
    narrow; empty if the first point is)."""
    pts = np.asarray(pts, dtype=np.float64).reshape(-1, 2)
    if len(pts) == 0:
        return pts
    bad = np.flatnonzero(np.asarray(clearance_at(pts)) + 1e-9 < min_clearance)
    return pts if bad.size == 0 else pts[:int(bad[0])]


def thin_polyline(pts: np.ndarray, spacing: float, max_deviation: float = 0.05) -> np.ndarray:
    """Thin a dense polyline to about `spacing` [m] between kept points without cutting corners.

    Keeps the first and the last point; a point is kept when it is >= spacing from the previous
    kept one, or when skipping it would let the straight chord between kept points pass more
    than `max_deviation` [m] from a dropped point (corners survive). A kept point closer than
    spacing/2 to the last point is dropped, unless it is a corner.
    """
    if spacing <= 0 or max_deviation < 0:
        raise GraphInputError(f"need spacing > 0 and max_deviation >= 0 (got {spacing}, "
                              f"{max_deviation})")
    pts = np.asarray(pts, dtype=np.float64).reshape(-1, 2)
    n = len(pts)
    if n <= 2:
        return pts.copy()
    kept = [0]
    corner = [False]
    last = 0
    for i in range(1, n - 1):
        p0 = pts[last]
        if math.hypot(pts[i, 0] - p0[0], pts[i, 1] - p0[1]) >= spacing:
            kept.append(i)
            corner.append(False)
            last = i
            continue
        # would the chord last -> i+1 cut a corner at any point in (last, i]?
        q = pts[i + 1]
        d = q - p0
        dd = float(d @ d)
        mid = pts[last + 1:i + 1]
        if dd > 0:
            s = np.clip((mid - p0) @ d / dd, 0.0, 1.0)
            dev = np.hypot(*(p0 + s[:, None] * d - mid).T)
        else:
            dev = np.hypot(*(mid - p0).T)
        if dev.max() > max_deviation:
            kept.append(i)
            corner.append(True)
            last = i
    end = pts[-1]
    lp = pts[kept[-1]]
    if len(kept) > 1 and not corner[-1] and math.hypot(*(end - lp)) < 0.5 * spacing:
        kept.pop()
    kept.append(n - 1)
    return pts[kept]


def grid_clearance(clearance: np.ndarray, geom: GridGeometry
                   ) -> Callable[[np.ndarray], np.ndarray]:
    """clearance_at for :func:`build_index`: a clearance map [m] (distance to the nearest
    occupied cell) looked up at (n, 2) points [m]; points outside the grid get inf.
    """

    def clearance_at(pts: np.ndarray) -> np.ndarray:
        pts = np.asarray(pts, dtype=np.float64).reshape(-1, 2)
        rows, cols = geom.world_to_cell(pts[:, 0], pts[:, 1])
        inside = geom.inside(rows, cols)
        out = np.full(len(pts), np.inf)
        out[inside] = clearance[rows[inside], cols[inside]]
        return out

    return clearance_at


def trim_narrow_tip(pts: np.ndarray, clearance_at: Callable[[np.ndarray], np.ndarray],
                    min_clearance: float, tip_length: float) -> np.ndarray:
    """Cut the end of a path where it is narrower than min_clearance [m], at most the last
    tip_length [m] (the skeleton tip in a dead-end corner); at least the first point stays.
    """
    pts = np.asarray(pts, dtype=np.float64).reshape(-1, 2)
    if len(pts) < 2 or tip_length <= 0:
        return pts
    c = clearance_at(pts)
    cum = polyline_lengths(pts)
    from_end = cum[-1] - cum
    k = len(pts) - 1
    while k > 0 and c[k] + 1e-9 < min_clearance and from_end[k] <= tip_length + 1e-9:
        k -= 1
    return pts[:k + 1]
