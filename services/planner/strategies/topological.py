"""What the two topological strategies share (the paper, §3.2; DESIGN.md §4 "Planner").

Candidates are the *open* end nodes (the strategy says which are open) reachable along edges
wide enough for the robot; cost = path length over the topological graph from the robot's
entry point on the skeleton. The path runs robot -> entry point -> edge polylines -> target;
with ``grid_paths`` (the default, docs/design.md) the robot drives the grid search's path to
that path's last point instead, where the search reaches it.

Approach through a narrow passage (``approach_narrow``): an open end node reachable only over
an edge too narrow for the robot is a candidate whose path stops at the first narrow point,
with the whole path length as its cost (a corridor seen at an angle has a skeleton hugging one
wall that looks narrow; from the narrow point the robot sees the corridor). Once the robot has
stood within goal_tolerance of that point, the node counts as unreachable unless the way
becomes wide or its narrow point lies more than blacklist_radius from every point looked from
(by position: node ids change as the skeleton is rebuilt).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import partial
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from topoexplore.common.grid import GridGeometry, cells_for, near_frontier, open_never_near
from topoexplore.services.planner import graph as gr
from topoexplore.services.planner import gridsearch as gs
from topoexplore.services.planner.mapview import MapView
from topoexplore.services.planner.strategies.base import (
    Candidate,
    Candidates,
    Config,
    Evaluation,
    Later,
    Update,
    id_list,
)
from topoexplore.services.planner.strategies.completion import Completion
from topoexplore.services.planner.strategies.frontier import (
    NARROW_PENALTY,
    open_unknown,
    open_unknown_made,
    path_fits,
    robot_reach,
    robot_search,
)

P_UNSEEN = 0.5  # P of an end node the reliability message does not list yet (paper: initial P)
LOCAL_SIDE = 2.0  # beside_unknown's quick test looks this many pocket sides (the side of a
#   square of completion_pocket_area) beyond its radius: room for a component to show its size
ENTRY_WINDOW = 4.0  # [m] the way onto the skeleton is checked for the body's fit this far
#   from the robot (farther, the nearest edge point is taken as before)


@dataclass
class Scene:
    """One update's topological search: the index, the end nodes and the search from the
    robot's entry point."""

    u: Update
    index: gr.TopoIndex
    pmap: dict[int, float]  # P by end node id (from the beliefs)
    ends: list[int]
    clearance_at: Callable[[np.ndarray], np.ndarray] | None  # None: no map
    open_ids: list[int] = field(default_factory=list)
    entry: gr.Entry | None = None
    dist: dict[int, float] = field(default_factory=dict)
    pred: dict[int, tuple[int, int, bool]] = field(default_factory=dict)
    wide: tuple | None = None  # the search through narrow edges too, made when first needed
    search: gs.GridSearch | None = None  # the grid search from the robot, once made

    def grid(self, cfg: Config) -> gs.GridSearch:
        """The grid search from the robot (:func:`robot_search`), made when first needed."""
        if self.search is None:
            self.search = robot_search(cfg, self.u)
        return self.search

    def prob(self, i: int) -> float:
        return self.pmap.get(i, P_UNSEEN)


@dataclass
class _Look:
    """A narrow point the robot has stood at (approach_narrow)."""

    id: int
    x: float
    y: float
    t: float


class Topological:
    """Base of the reliability and all-end-nodes strategies; subclasses say which end nodes
    are open and how to word it."""

    needs_beliefs = False  # wait for the first reliability message
    unresolved = "unvisited"  # what an open end node is, in the status

    def __init__(self, cfg: Config):
        self.cfg = cfg
        self.completion = Completion(cfg)
        self._rel_updates = 0  # updates that came with a reliability message
        self._looked: list[_Look] = []
        self._polylines = gr.PolylineCache()  # the edges' polylines, kept between updates
        self._last: Evaluation | None = None  # the last whole evaluation ...
        self._last_t = -math.inf  # ... and its time [s] (:meth:`kept`)

    # --- what a subclass says ----------------------------------------------------------------

    def observe(self, u: Update) -> None:
        """Called first on every update."""

    def is_open(self, i: int, s: Scene) -> bool:
        raise NotImplementedError

    def label(self, i: int, s: Scene) -> str:
        return f"end node {i}"

    def target_p(self, i: int, s: Scene) -> float:
        return 0.0

    def open_now(self, u: Update, i: int, x: float, y: float) -> bool:
        """Is end node i at (x, y) [m] still open on update u? (:meth:`kept`'s question, from
        u alone: no index, no search)"""
        raise NotImplementedError

    def all_done(self, n: int) -> str:
        """Done text for n reachable end nodes, none of them open."""
        raise NotImplementedError

    def resolved(self, i: int, s: Scene) -> str:
        """Why end node i is no longer open."""
        raise NotImplementedError

    # --- evaluation --------------------------------------------------------------------------

    def evaluate(self, u: Update) -> Evaluation:
        """The whole evaluation of update u (kept for :meth:`kept` when keep_period > 0: it
        holds the update's map view, so it is not kept for nothing)."""
        ev = self.evaluate_all(u)
        if self.cfg.params.keep_period > 0:
            self._last, self._last_t = ev, u.t
        return ev

    def evaluate_all(self, u: Update) -> Evaluation:
        return self.complete(u, self.evaluate_graph(u))

    def kept(self, u: Update) -> Evaluation | None:
        """The last whole evaluation again, for an update on which only the target followed
        matters (the core asks only when none of its rules that read other candidates or
        make a path is due: docs/design.md, "A kept evaluation"). None, and the core
        evaluates, unless the evaluation is younger than keep_period, the map has not changed
        under the path (:meth:`Update.may_reuse`), the target is not one up to a narrow
        passage or around one (whether its way is narrow is judged anew on each update),
        and an end node followed is still an end node, still open, and within
        target_move of where its path was made to (``Update.planned_at``: the core's "target
        moved" rule). The walls the path is checked against are this update's."""
        self.observe(u)
        ev, tg = self._last, u.target
        if (ev is None or tg is None or tg.partial or tg.around  # the way up to a narrow
                #   passage becoming wide, or the way around one narrow again, is the
                #   evaluation's to see (a new path)
                or ev.waiting is not None or ev.failed is not None
                or u.graph is None or u.view is None
                or (self.needs_beliefs and u.beliefs is None)
                or not u.may_reuse(self.cfg.params.keep_period, self._last_t)):
            return None
        if tg.id >= 0:
            node = next((n for n in u.graph.nodes if n.id == tg.id), None)
            px, py = u.planned_at if u.planned_at is not None else (tg.x, tg.y)
            if (node is None or node.kind != "end"
                    or math.hypot(node.x - px, node.y - py) >= self.cfg.params.target_move
                    or not self.open_now(u, tg.id, node.x, node.y)):
                return None
        return replace(ev, path_clear=_clear_of(u.view))

    def complete(self, u: Update, ev: Evaluation) -> Evaluation:
        """The completion phase once no end node is left (frontier_completion); while end
        nodes are left, the frontier groups within pickup_radius join them."""
        p = self.cfg.params
        if not p.frontier_completion or ev.waiting is not None or ev.failed is not None \
                or u.view is None:
            return ev
        if not ev.cands:
            return self.completion.phase(u, ev.settled())
        near = self.completion.nearby(u, p.pickup_radius)
        if near is None:
            return ev
        return _joined(ev, near, u.target is not None and u.target.id < 0)

    def evaluate_graph(self, u: Update) -> Evaluation:
        """The open end nodes as candidates."""
        rel_before = self._rel_updates
        if u.beliefs is not None:
            self._rel_updates += 1
        self.observe(u)
        if u.graph is None:
            return Evaluation(waiting="waiting for topo")
        if self.needs_beliefs and u.beliefs is None:
            return Evaluation(waiting="waiting for reliability")
        s = self._scene(u)
        if not s.index.nodes:
            return Evaluation(waiting="waiting: the topological map is empty")
        if not s.ends and rel_before == 0:
            return Evaluation(waiting="waiting: the topo has no end nodes yet and no earlier "
                                      "reliability update")
        self._search(s)
        return self._evaluation(s)

    def _scene(self, u: Update) -> Scene:
        clearance_at = u.view.clearance_at if u.view is not None else None
        index = gr.build_index(u.graph, self.cfg.need, clearance_at, self.cfg.params.tip_length,
                               self._polylines)
        pmap = {b.id: float(b.p) for b in u.beliefs} if u.beliefs is not None else {}
        return Scene(u, index, pmap, index.end_ids(), clearance_at)

    def _search(self, s: Scene) -> None:
        """Open end nodes, entry point (in line of sight on the map) and path costs."""
        s.open_ids = [i for i in s.ends if self.is_open(i, s)]
        u, visible, near = s.u, None, None
        if u.view is not None:
            radius = self.cfg.radius
            free, best, geom = near = u.view.near(u.x, u.y, ENTRY_WINDOW)
            fits = free & (best + 1e-6 >= self.cfg.fit(geom.resolution))

            def visible(x0: float, y0: float, x1: float, y1: float) -> bool:
                # the straight way to the skeleton must fit the body, as the controller's
                # corridor needs (the robot's own cells, within its radius, may be tight)
                return gr.line_of_sight(fits, geom, x0, y0, x1, y1, radius)

        s.entry = gr.find_entry(s.index, u.x, u.y, visible)
        if s.entry is not None and not s.entry.line_of_sight and near is not None:
            s.entry = self._grid_entry(s, near) or s.entry
        if s.entry is not None:
            s.dist, s.pred = gr.search_from_entry(s.index, s.entry)

    def _grid_entry(self, s: Scene, near: tuple) -> gr.Entry | None:
        """No straight line from the robot to the skeleton fits its body (an obstacle beside
        it, a learned blockage ahead): join the skeleton over a grid path instead, the
        frontier strategy's narrow search (escape from a tight spot, narrow cells at a
        penalty) within ENTRY_WINDOW of the robot, at the skeleton point it reaches first.
        None if it reaches none."""
        u, cfg = s.u, self.cfg
        free, best_c, geom = near
        fit = cfg.fit(geom.resolution)
        gsr = gs.grid_search(free, free & (best_c + 1e-6 >= fit), best_c, geom, u.x, u.y,
                             cfg.need, fit=fit, narrow_penalty=NARROW_PENALTY)
        if gsr.start is None:
            return None
        best: tuple[float, int, int, int, int] | None = None
        for pos, e in enumerate(s.index.edges):
            rows, cols = geom.world_to_cell(e.pts[:, 0], e.pts[:, 1])
            ok = geom.inside(rows, cols)
            if not np.any(ok):
                continue
            d = np.full(len(e.pts), np.inf)
            d[ok] = gsr.dist[rows[ok], cols[ok]]
            k = int(np.argmin(d))
            if math.isfinite(d[k]) and (best is None or d[k] < best[0]):
                best = (float(d[k]), pos, k, int(rows[k]), int(cols[k]))
        if best is None:
            return None
        lead = gsr.path_to(best[3], best[4])
        lead = np.vstack([[u.x, u.y], lead]) if len(lead) else np.array([[u.x, u.y]])
        return gr.entry_at(s.index, best[1], best[2], lead)

    def _evaluation(self, s: Scene) -> Evaluation:
        ev = Evaluation(end_nodes=len(s.ends),
                        reliable=sum(1 for i in s.ends if s.prob(i) >= self.cfg.p_reliable))
        outcome: dict[int, str] = {}  # end node id -> "unreachable" | "blacklisted"
        items: list[Candidate | Later] = []

        def judged(i: int, c: Candidate | Later | None) -> Candidate | None:
            """c, or None when it is no candidate (the outcome for the done text noted)."""
            if isinstance(c, Later):
                c = c.value()
            if c is None:
                outcome[i] = "unreachable"
            elif s.u.blacklisted(c):
                outcome[i] = "blacklisted"
            else:
                return c
            return None

        for i in s.open_ids:
            c = self._candidate(s, i)
            if isinstance(c, Later):  # judged when the list is read: the outcome then too
                items.append(Later(i, partial(judged, i, c)))
            elif judged(i, c) is not None:
                items.append(c)
        if s.entry is None and s.open_ids:
            ev.failed = (f"cannot join the skeleton: no edge with clearance >= "
                         f"{self.cfg.need:.2f} m (of {len(s.index.narrow)} narrow); "
                         f"{len(s.open_ids)} end node(s) still open (ids {id_list(s.open_ids)})")

        def done() -> str:
            return self._done(s, [i for i in s.open_ids if outcome.get(i) == "unreachable"],
                              [i for i in s.open_ids if outcome.get(i) == "blacklisted"])

        if any(isinstance(x, Later) for x in items):
            ev.cands = Candidates(items, done)
        else:
            ev.cands, ev.done = items, done()
        ev.status_of = lambda c: self._status_of(s, c)
        ev.flickered = lambda c: (not c.partial and c.id in s.index.nodes
                                  and c.id in s.open_ids and c.id not in s.dist)
        ev.path_ok = _near_skeleton(s.index, self.cfg.params.path_tolerance,
                                    None if s.entry is None else s.entry.lead)
        if s.u.view is not None:
            ev.path_clear = _clear_of(s.u.view)
            if self.cfg.params.grid_paths:
                self._grid_paths(s, ev)
        return ev

    def _grid_paths(self, s: Scene, ev: Evaluation) -> None:
        """grid_paths: the way to each end node on the grid, as a frontier strategy's, where
        the grid search reaches the skeleton path's last point; the skeleton path elsewhere.
        The search runs only when a path is made. (A candidate judged later is one behind a
        narrow passage, partial or around: it has its path already.)"""
        view, cfg = s.u.view, self.cfg
        search = partial(s.grid, cfg)
        for c in ev.cands.judged() if isinstance(ev.cands, Candidates) else ev.cands:
            if not c.partial and not c.around:
                c.path = _grid_or(c.path, search, view.geom)
        on_skeleton, fits = ev.path_ok, path_fits(view, lambda: view.clearance, cfg.radius)
        ev.path_ok = lambda wps: on_skeleton(wps) or fits(wps)

    def _candidate(self, s: Scene, i: int) -> Candidate | Later | None:
        """Open end node i as a candidate; None if it is unreachable; a :class:`Later` to
        judge when asked for when it lies behind a narrow passage (:meth:`_approach`)."""
        _, nx, ny = s.index.nodes[i]
        if i not in s.dist:
            return self._approach(s, i, nx, ny)
        need, tip, clearance_at = self.cfg.need, self.cfg.params.tip_length, s.clearance_at

        def path() -> np.ndarray:
            pts = gr.path_points(s.index, s.entry, s.pred, i)
            if clearance_at is None:
                return pts
            return gr.trim_narrow_tip(pts, clearance_at, need, tip)

        return Candidate(i, nx, ny, s.dist[i], s.dist[i], 1.0, self.target_p(i, s), path,
                         label=self.label(i, s))

    def _approach(self, s: Scene, i: int, nx: float, ny: float) -> Candidate | Later | None:
        """Candidate for open end node i behind a narrow edge: the path up to the narrow point
        (approach_narrow); None if there is none or the robot has looked from there.

        The path and its narrow point are found now. While the robot follows another end
        node, the rest (is there unexplored space around the node, can the robot go around
        the narrow stretch, has it looked from that point) is judged when the candidate is
        asked for (a :class:`Later`), unless the robot stands at the narrow point (where the
        rest records that it looked: judged now, in order). Judged later, it sees the looks
        recorded before it, as it would have now."""
        if not (self.cfg.params.approach_narrow and s.entry is not None
                and s.clearance_at is not None):
            return None
        if s.wide is None:
            s.wide = gr.search_from_entry(s.index, s.entry, through_narrow=True)
        dist, pred = s.wide
        if i not in dist:
            return None
        full = gr.path_points(s.index, s.entry, pred, i)
        nlead = 0 if s.entry.lead is None else len(s.entry.lead)  # the lead-in is not cut
        pts = np.vstack([full[:nlead], gr.cut_at_narrow(full[nlead:], s.clearance_at,
                                                         self.cfg.need)])
        if len(pts) - nlead < 2 or len(pts) == len(full):
            return None
        u, px, py = s.u, float(pts[-1, 0]), float(pts[-1, 1])
        rest = partial(self._approach_rest, s, i, nx, ny, full, dist[i], pts, len(self._looked))
        if (u.target is None or u.target.id == i or u.target.id < 0
                or math.hypot(px - u.x, py - u.y) <= self.cfg.params.goal_tolerance):
            return rest()
        return Later(i, rest)

    def _approach_rest(self, s: Scene, i: int, nx: float, ny: float, full: np.ndarray,
                       cost: float, pts: np.ndarray, looks: int) -> Candidate | None:
        """:meth:`_approach` for end node i at (nx, ny) [m], from its skeleton path ``full``
        (``cost`` [m] long) cut at the narrow point (``pts``): the first ``looks`` recorded
        looks count."""
        r = self.cfg.params.approach_radius
        if r > 0 and not self.beside_unknown(s.u, nx, ny, r):
            return None  # its surroundings are mapped: nothing to look at through the gap
        around = self._around(s, i, nx, ny, full, cost)
        if around is not None:
            return around
        reach = float(gr.polyline_lengths(pts)[-1])
        px, py = float(pts[-1, 0]), float(pts[-1, 1])
        u = s.u
        if math.hypot(px - u.x, py - u.y) <= self.cfg.params.goal_tolerance:
            if not self._has_looked(px, py, looks):
                self._looked.append(_Look(i, px, py, u.t))
            return None
        if self._has_looked(px, py, looks):
            return None
        to_entry = math.hypot(pts[0, 0] - u.x, pts[0, 1] - u.y)
        return Candidate(i, nx, ny, cost, to_entry + reach, 1.0, self.target_p(i, s),
                         lambda: pts, label=f"{self.label(i, s)} up to a narrow passage",
                         partial=True)

    def _around(self, s: Scene, i: int, nx: float, ny: float, full: np.ndarray,
                cost: float) -> Candidate | None:
        """Open end node i that would be approached up to the narrow stretch of its skeleton
        path ``full`` (``cost`` [m] long), as a whole candidate instead when the grid search
        (the body and clearance the controller drives with: :func:`robot_search`) gets to
        where that path ends, its narrow tip trimmed as for any end node: the skeleton is one
        line through a room, and a narrow stretch of it (between table legs) is not a narrow
        way. Its path is the grid search's, made only when it is followed. None without
        grid_paths, or when the search does not get there (judged on a reach-only search, once
        per update: a cheap flood of the same cells)."""
        u, cfg = s.u, self.cfg
        if not cfg.params.grid_paths or u.view is None:
            return None
        geom = u.view.geom
        trimmed = gr.trim_narrow_tip(full, s.clearance_at, cfg.need, cfg.params.tip_length)
        r, c = (int(v) for v in geom.world_to_cell(*(float(v) for v in trimmed[-1])))
        reach = robot_reach(cfg, u, narrow=False)
        if reach.start is None or not geom.inside(r, c) or not math.isfinite(reach.dist[r, c]):
            return None
        return Candidate(i, nx, ny, cost, cost, 1.0, self.target_p(i, s),
                         _grid_or(lambda: trimmed, partial(s.grid, cfg), geom),
                         label=f"{self.label(i, s)} (around a narrow stretch of its edge)",
                         around=True)

    def beside_unknown(self, u: Update, x: float, y: float, radius: float) -> bool:
        """Is there at least min_frontier_size of frontier (in cells, however fragmented)
        within radius [m] of (x, y) [m]? Enclosed pockets smaller than
        completion_pocket_area (the inside of a box) do not count, unless the robot can get
        beside them (the completion rules' search), nor do specks."""
        p, v = self.cfg.params, u.view
        if v is None:
            return True
        res, area = v.geom.resolution, p.completion_pocket_area
        n = cells_for(p.min_frontier_size, res)
        whole = open_unknown_made(self.cfg, u, area)
        # unless this update has the whole-map mask already: first the never-observed space
        # around the point alone (a subset of the cells the whole-map test counts, so a yes
        # is its yes), as a rule enough where the map stops
        if whole is None and near_frontier(
                x, y, v.data, v.geom, radius, v.occ.p_free,
                open_never_near(v.data, v.geom, x, y, radius + LOCAL_SIDE * math.sqrt(area),
                                int(area / res ** 2)), min_cells=n):
            return True
        if whole is None:
            whole = open_unknown(self.cfg, u, area)
        return near_frontier(x, y, v.data, v.geom, radius, v.occ.p_free, whole, min_cells=n)

    def _has_looked(self, px: float, py: float, looks: int) -> bool:
        """Has the robot looked from within blacklist_radius of (px, py) [m], by the first
        ``looks`` looks recorded?"""
        r2 = self.cfg.params.blacklist_radius ** 2
        return any((b.x - px) ** 2 + (b.y - py) ** 2 <= r2 for b in self._looked[:looks])

    def _done(self, s: Scene, unreachable: list[int], black: list[int]) -> str:
        """Why there is no candidate (if there is none)."""
        open_set = set(s.open_ids)
        done = self.all_done(sum(1 for i in s.ends if i in s.dist and i not in open_set))
        if not s.ends:
            done = "the topological map has no end nodes"
        if black:
            done += f"; {len(black)} blacklisted (ids {id_list(black)})"
        if unreachable:
            done += (f"; {len(unreachable)} {self.unresolved} end node(s) unreachable for the "
                     f"robot (ids {id_list(unreachable)})")
        return done

    def _status_of(self, s: Scene, c: Candidate) -> str:
        if c.id not in s.index.nodes or s.index.nodes[c.id][0] != "end":
            return "vanished"
        if c.id not in s.open_ids:
            return self.resolved(c.id, s)
        if c.id not in s.dist:
            return "became unreachable"
        return "was blacklisted"

    def snapshot(self) -> dict[str, Any]:
        return {"looked": [{"id": b.id, "x": b.x, "y": b.y, "t": b.t} for b in self._looked]}


def _clear_of(view: MapView) -> Callable[[np.ndarray], bool]:
    """path_clear on the map view: no segment of the waypoints crosses an occupied cell."""
    return lambda wps: not gr.crosses(view.occupied, view.geom, wps)


def _near_skeleton(index: gr.TopoIndex, tolerance: float, lead: np.ndarray | None = None
                   ) -> Callable[[np.ndarray], bool]:
    """path_ok of a topological path: every waypoint within tolerance [m] of the skeleton or of
    this update's grid lead-in to it (the points are gathered on the first call; each call
    searches only those in the waypoints' box grown by the tolerance, which no other point
    can be within)."""
    every: list = []

    def path_ok(wps: np.ndarray) -> bool:
        if len(wps) == 0:
            return True
        if not every:
            pts = index.all_points()
            if lead is not None and len(lead):
                pts = np.vstack([pts.reshape(-1, 2), lead]) if len(pts) else lead
            every.append(np.asarray(pts, dtype=np.float64).reshape(-1, 2))
        pts = every[0]
        bound = tolerance + 1e-9
        lo, hi = wps.min(axis=0) - 2.0 * bound, wps.max(axis=0) + 2.0 * bound
        pts = pts[np.all((pts >= lo) & (pts <= hi), axis=1)]
        if len(pts) == 0:
            return False
        d, _ = cKDTree(pts).query(wps, k=1, distance_upper_bound=bound)
        return bool(np.all(np.isfinite(d)))

    return path_ok


def _joined(ev: Evaluation, near: Evaluation, on_frontier: bool) -> Evaluation:
    """ev's end nodes and near's frontier groups as one evaluation; the path checks of the
    kind of target followed (on_frontier: a frontier group's)."""
    src = near if on_frontier else ev
    return replace(ev, cands=ev.cands + near.cands, path_ok=src.path_ok,
                               path_clear=src.path_clear, status_of=src.status_of)


def _grid_or(path: Callable[[], np.ndarray], search: Callable[[], gs.GridSearch],
             geom: GridGeometry) -> Callable[[], np.ndarray]:
    """The grid path (of search()) to path()'s last point where the search reaches it, else
    path()."""

    def grid_path() -> np.ndarray:
        pts = path()
        sr = search()
        r, c = geom.world_to_cell(float(pts[-1, 0]), float(pts[-1, 1]))
        if sr.start is not None and geom.inside(r, c) and math.isfinite(sr.dist[int(r), int(c)]):
            g = sr.path_to(int(r), int(c))
            if len(g):
                return g
        return pts

    return grid_path
