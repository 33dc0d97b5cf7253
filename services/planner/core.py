"""Planner core: choose the next target and the path to it (pure: no bus, no clock, no I/O).

Three strategies share one decision machine (target choice, re-plan rules, bounded effort):

- ``reliability`` (the paper, §3.2; DESIGN.md §4 "Planner"): candidates are end nodes with
  position probability P < p_reliable (eq. 6) reachable along edges wide enough for the robot;
  the target is the candidate with the least path cost over the topological graph from the
  robot's entry point on the skeleton (ties: the one ahead of the robot, paper Fig. 10a); the
  path runs robot -> entry point -> edge polylines -> target. Done when no candidate is left.
- ``all-end-nodes`` (Choset-style foil): same, but the candidates are the end nodes the robot
  has not yet come within visit_radius of (tracked here from the poses), whatever their P.
- ``frontier`` (Yamauchi / explore_lite with grid path lengths, see frontier.py).

Re-plan rules (all strategies): the target is resolved (reliable / visited / vanished /
cleared) -> choose again; the target moved >= target_move from where the path was built, or the
remaining path left the current skeleton (or crosses an occupied cell, frontier) -> new path to
the same target; at most every replan_period s, switch to another target only if its cost <
switch_ratio * the current target's remaining cost (the hysteresis that keeps the robot from
oscillating between two targets); a shorter path to the same target by that ratio also replaces
the path. Bounded effort: no progress_distance of progress along the path for progress_timeout s
(a target that moves counts as progress: it is revealing new space) is one failure; after
max_attempts failures, or when the robot stands at the target for arrival_timeout s and it is
still unresolved, the target is blacklisted by id and by position (blacklist_radius) and
reported in ``blacklisted`` and ``reason``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from topoexplore.common import messages as m
from topoexplore.common.grid import (
    OCCUPIED,
    GridGeometry,
    classify,
    crop_known,
    free_mask,
    open_unknown,
)
from topoexplore.common.params import PlannerParams
from topoexplore.services.planner import frontier as fr
from topoexplore.services.planner import graph as gr

STRATEGIES = ("reliability", "all-end-nodes", "frontier")
P_UNSEEN = 0.5  # P of an end node the reliability message does not list yet (paper: initial P)
ENTRY_SKIP = 0.05  # [m] an entry point this close to the robot is not a separate waypoint
TRACK_STEP = 0.05  # [m] robot positions are recorded (visit tracking) every this much travel
REMAINING_WINDOW = 1.5  # [m] the robot is located on the path within this arc ahead of it
SOFT_RADIUS_FACTOR = 2.0  # frontier: cells with clearance < this x (radius + margin) cost more
SOFT_PENALTY = 2.0  # ... up to (1 + this) x their length at the hard limit
MAX_CROSSING_REPLANS = 2  # new paths per target when its path crosses a wall seen later
FACE_MIN_DISTANCE = 0.05  # [m] a point to face closer than this to the path end sets no heading


class PlannerInputError(ValueError):
    """Bad parameters or inputs given to the planner core."""


@dataclass
class PlanOutput:
    waypoints: list[tuple[float, float]]  # robot -> entry -> edges -> target [m]; [] = stop
    target_id: int  # end node id, or -1 (none / frontier strategy: use target_xy)
    target_xy: tuple[float, float]  # [m]
    state: str  # "exploring" | "done" | "failed"
    reason: str  # why this target / why stopped
    candidates: int
    end_nodes: int
    reliable: int
    blacklisted: list[int]
    replans: int
    target_p: float  # P of the target (reliability strategy), else 0
    plan_id: int  # increments whenever the path is replaced (new target / re-plan / stop)
    goal_heading: float | None = None  # [rad] heading to take at the end of the path


@dataclass
class _Cand:
    id: int  # end node id, -1 for a frontier group
    x: float  # [m]
    y: float  # [m]
    cost: float  # selection cost (topo: path length [m]; frontier: explore_lite cost)
    dist: float  # [m] path length robot -> target
    scale: float  # cost per metre of path (1 for topo strategies, potential_scale for frontier)
    p: float  # position probability (reliability strategy), else 0
    path: Callable[[], np.ndarray]  # dense polyline from the entry / start cell to the target
    cells: np.ndarray | None = None  # frontier: the group's cell centres (identity matching)
    label: str = ""
    partial: bool = False  # the path stops at a narrow passage before the target
    face: tuple[float, float] | None = None  # [m] point to face at the end of the path


@dataclass
class _Eval:
    """What one strategy sees in one update."""

    waiting: str | None = None
    failed: str | None = None
    cands: list[_Cand] = field(default_factory=list)
    end_nodes: int = 0
    reliable: int = 0
    done: str = ""  # summary when no candidate is left
    status_of: Callable[[_Cand], str] = lambda c: "is no longer a candidate"
    path_ok: Callable[[np.ndarray], bool] = lambda wps: True
    path_clear: Callable[[np.ndarray], bool] = lambda wps: True  # no segment crosses a wall


@dataclass
class _Target:
    cand: _Cand
    plan_x: float  # [m] target position when the path was built
    plan_y: float
    wps: np.ndarray  # (n, 2) waypoints [m]
    cum: np.ndarray  # (n,) arc length along wps [m]
    idx: int  # segment of wps the robot is on
    best_rem: float  # [m] least remaining path length seen since the last progress
    progress_t: float  # [s] time of the last progress
    arrived_t: float | None  # [s] since when the robot stands within goal_tolerance
    chosen_t: float  # [s]
    why: str
    partial: bool = False  # the path was cut at a narrow passage (_Cand.partial when made)
    crossings: int = 0  # new paths made because the path crossed an obstacle seen since


@dataclass
class _Mark:
    """A blacklisted target or a failure count, by id and position."""

    id: int
    x: float
    y: float
    count: int = 0
    reason: str = ""
    t: float = 0.0


def check_params(p: PlannerParams) -> None:
    """Raise PlannerInputError on parameters the core cannot work with."""
    if p.strategy not in STRATEGIES:
        raise PlannerInputError(f"unknown strategy {p.strategy!r} (use {', '.join(STRATEGIES)})")
    for name in ("robot_radius", "visit_radius", "goal_tolerance", "progress_timeout",
                 "progress_distance", "blacklist_radius", "replan_period", "target_move",
                 "arrival_timeout", "waypoint_spacing", "path_tolerance",
                 "frontier_match_radius", "potential_scale"):
        v = getattr(p, name)
        if not (math.isfinite(v) and v > 0):
            raise PlannerInputError(f"planner.{name} must be > 0 (got {v!r})")
    for name in ("clearance_margin", "tie_tolerance", "min_frontier_size", "gain_scale",
                 "tip_length"):
        v = getattr(p, name)
        if not (math.isfinite(v) and v >= 0):
            raise PlannerInputError(f"planner.{name} must be >= 0 (got {v!r})")
    if not 0 < p.p_reliable < 1:
        raise PlannerInputError(f"planner.p_reliable must be in (0, 1) (got {p.p_reliable})")
    if not 0 < p.switch_ratio <= 1:
        raise PlannerInputError(f"planner.switch_ratio must be in (0, 1] (got {p.switch_ratio})")
    if p.max_attempts < 1:
        raise PlannerInputError(f"planner.max_attempts must be >= 1 (got {p.max_attempts})")
    if p.done_confirm < 1:
        raise PlannerInputError(f"planner.done_confirm must be >= 1 (got {p.done_confirm})")


def angle_diff(a: float, b: float) -> float:
    """|a - b| wrapped to [0, pi] [rad]."""
    return abs((a - b + math.pi) % (2 * math.pi) - math.pi)


def _ids(ids: list[int], limit: int = 8) -> str:
    s = ", ".join(str(i) for i in sorted(ids)[:limit])
    return s + (", ..." if len(ids) > limit else "")


class PlannerCore:
    """Exploration planner; call :meth:`update` once per reliability / topo / map update."""

    def __init__(self, params: PlannerParams):
        check_params(params)
        self.p = params
        self._target: _Target | None = None
        self._plan_id = 0
        self._replans = 0
        self._blacklist: list[_Mark] = []
        self._attempts: list[_Mark] = []
        self._looked: list[_Mark] = []  # narrow points the robot has stood at (approach_narrow)
        self._track_buf = np.zeros((256, 2))  # robot positions every TRACK_STEP [m]
        self._track_n = 0
        self._rel_updates = 0  # updates that came with a reliability message
        self._rel_before = 0  # ... counted before the current update
        self._no_cand = 0  # consecutive updates without a candidate
        self._fail_since: float | None = None  # [s] since when the robot cannot plan at all
        self._last_t: float | None = None
        self._last_eval_t = -math.inf
        self._had_path = False
        self._last: PlanOutput | None = None
        self._updates = 0
        self._frontier_ev: _Eval | None = None  # frontier strategy: last search ...
        self._frontier_t = -math.inf  # ... and its time [s]
        self._mapped_t = -math.inf  # stop_when_mapped: time [s] of the last frontier check
        self._mapped_ok = False  # ... its answer
        self._mapped_why = ""
        self._clear: tuple[GridGeometry, np.ndarray] | None = None  # this update's (crop
        #   geometry, clearance map); the grid is the same throughout one update

    # --- public ------------------------------------------------------------------------------

    def update(self, t: float, pose: tuple[float, float, float], topo: m.TopoGraph | None,
               rel: m.Reliability | None, grid_int8: np.ndarray | None,
               geom: GridGeometry | None, p_free: float = 0.35, p_occ: float = 0.65
               ) -> PlanOutput:
        """One planning step at time t [s] for the robot at pose (x [m], y [m], theta [rad])."""
        x, y, th = self._check_inputs(t, pose, topo, rel, grid_int8, geom, p_free, p_occ)
        self._updates += 1
        if self._last_t is not None and t < self._last_t:  # clock reset: restart the timers
            self._last_eval_t = -math.inf
            if self._target is not None:
                self._target.progress_t = t
                self._target.arrived_t = None
        self._last_t = t
        self._rel_before = self._rel_updates
        self._clear = None  # valid for one update only
        if rel is not None:
            self._rel_updates += 1
        self._record(x, y)
        if self.p.strategy == "frontier":
            cached = self._frontier_ev
            if (cached is not None and self._target is not None and cached.cands
                    and 0.0 <= t - self._frontier_t < self.p.frontier_period):
                ev = cached  # following a target: keep the last frontier search
            else:
                ev = self._eval_frontier(x, y, topo, rel, grid_int8, geom, p_free, p_occ)
                self._frontier_ev, self._frontier_t = ev, t
        else:
            ev = self._eval_topo(x, y, topo, rel, grid_int8, geom, p_free, p_occ)
            if (self.p.stop_when_mapped and self.p.strategy == "reliability" and ev.cands
                    and grid_int8 is not None
                    and self._mapped(t, x, y, topo, rel, grid_int8, geom, p_free, p_occ)):
                ev = _Eval(end_nodes=ev.end_nodes, reliable=ev.reliable, done=(
                    f"the map is complete ({self._mapped_why}); {len(ev.cands)} end node(s) "
                    f"below P {self.p.p_reliable:g} left unvisited"))
            elif (self.p.frontier_completion and not ev.cands and ev.waiting is None
                    and ev.failed is None and grid_int8 is not None):
                ev = self._completion(t, x, y, ev, topo, rel, grid_int8, geom, p_free, p_occ)
        if ev.waiting is not None:
            self._target = None
            self._no_cand = 0
            return self._emit(t, "exploring", ev.waiting, ev, 0)
        out = self._decide(t, x, y, th, ev)
        return out

    def snapshot(self) -> dict[str, Any]:
        """JSON-friendly state for the service's state queryable."""
        tg = self._target
        last = self._last
        return {
            "strategy": self.p.strategy,
            "updates": self._updates,
            "t": self._last_t,
            "state": last.state if last else "idle",
            "reason": last.reason if last else "",
            "plan_id": self._plan_id,
            "replans": self._replans,
            "target": None if tg is None else {
                "id": tg.cand.id, "x": tg.cand.x, "y": tg.cand.y, "p": tg.cand.p,
                "cost": tg.cand.cost, "path_length": tg.cand.dist,
                "waypoints": len(tg.wps), "segment": tg.idx,
                "best_remaining": tg.best_rem, "progress_t": tg.progress_t,
                "arrived_t": tg.arrived_t, "chosen_t": tg.chosen_t, "why": tg.why},
            "blacklist": [{"id": b.id, "x": b.x, "y": b.y, "reason": b.reason, "t": b.t}
                          for b in self._blacklist],
            "failures": [{"id": a.id, "x": a.x, "y": a.y, "count": a.count}
                         for a in self._attempts],
            "looked": [{"id": b.id, "x": b.x, "y": b.y, "t": b.t} for b in self._looked],
            "visited_positions": self._track_n,
            "candidates": last.candidates if last else 0,
            "end_nodes": last.end_nodes if last else 0,
            "reliable": last.reliable if last else 0,
        }

    # --- inputs ------------------------------------------------------------------------------

    def _check_inputs(self, t, pose, topo, rel, grid, geom, p_free, p_occ):
        if not isinstance(t, (int, float)) or not math.isfinite(t):
            raise PlannerInputError(f"time must be a finite number (got {t!r})")
        try:
            x, y, th = (float(v) for v in pose)
        except (TypeError, ValueError):
            raise PlannerInputError(f"pose must be (x, y, theta) (got {pose!r})") from None
        if not all(math.isfinite(v) for v in (x, y, th)):
            raise PlannerInputError(f"pose must be finite (got {pose!r})")
        if topo is not None and not isinstance(topo, m.TopoGraph):
            raise PlannerInputError(f"topo must be a TopoGraph (got {type(topo).__name__})")
        if rel is not None and not isinstance(rel, m.Reliability):
            raise PlannerInputError(f"rel must be a Reliability (got {type(rel).__name__})")
        if (grid is None) != (geom is None):
            raise PlannerInputError("grid_int8 and geom must be given together")
        if grid is not None:
            try:
                fr.check_grid(grid, geom)
            except fr.FrontierInputError as exc:
                raise PlannerInputError(str(exc)) from None
        if not 0 < p_free <= p_occ < 1:
            raise PlannerInputError(f"need 0 < p_free <= p_occ < 1 (got {p_free}, {p_occ})")
        return x, y, th

    def _record(self, x: float, y: float) -> None:
        """Remember where the robot has been (all-end-nodes visit tracking)."""
        n = self._track_n
        if n:
            lx, ly = self._track_buf[n - 1]
            if math.hypot(x - lx, y - ly) < TRACK_STEP:
                return
        if n == len(self._track_buf):  # amortised doubling: O(1) per point over a long run
            self._track_buf = np.concatenate([self._track_buf, np.zeros_like(self._track_buf)])
        self._track_buf[n] = (x, y)
        self._track_n = n + 1

    def _visited(self, x: float, y: float) -> bool:
        a = self._track_buf[:self._track_n]
        if len(a) == 0:
            return False
        d2 = (a[:, 0] - x) ** 2 + (a[:, 1] - y) ** 2
        return bool(d2.min() <= self.p.visit_radius ** 2 + 1e-12)

    # --- strategies --------------------------------------------------------------------------

    def _eval_topo(self, x, y, topo, rel, grid, geom, p_free, p_occ) -> _Eval:
        p = self.p
        reliability = p.strategy == "reliability"
        if topo is None:
            return _Eval(waiting="waiting for topo")
        if reliability and rel is None:
            return _Eval(waiting="waiting for reliability")
        need = p.robot_radius + p.clearance_margin
        clearance_at = None
        if grid is not None:
            grid, geom = crop_known(grid, geom)  # the same answers on a smaller array
            occ = classify(grid, p_free, p_occ) == OCCUPIED
            clearance_at = gr.grid_clearance(
                self._clearance_of(grid, geom, p_free, p_occ, occ), geom)
        try:
            index = gr.build_index(topo, need, clearance_at, p.tip_length)
        except gr.GraphInputError as exc:
            raise PlannerInputError(str(exc)) from None
        ends = index.end_ids()
        if not index.nodes:
            return _Eval(waiting="waiting: the topological map is empty")
        if not ends and self._rel_before == 0:
            return _Eval(waiting="waiting: the topo has no end nodes yet and no earlier "
                                 "reliability update")
        pmap = {n.id: float(n.p) for n in rel.nodes} if rel is not None else {}

        def prob(i: int) -> float:
            return pmap.get(i, P_UNSEEN)

        thr = p.p_reliable
        reliable = [i for i in ends if prob(i) >= thr]
        if reliability:
            open_ids = [i for i in ends if prob(i) < thr]
        else:
            open_ids = [i for i in ends if not self._visited(*index.nodes[i][1:])]

        visible = None
        if grid is not None:
            free = free_mask(grid, p_free)

            def visible(x0, y0, x1, y1):
                return gr.line_of_sight(free, geom, x0, y0, x1, y1, p.robot_radius)

        entry = gr.find_entry(index, x, y, visible)
        dist, pred = gr.search_from_entry(index, entry) if entry is not None else ({}, {})
        ev = _Eval(end_nodes=len(ends), reliable=len(reliable))
        unreachable, black = [], []
        wide = None  # search through narrow edges too, made when first needed
        for i in open_ids:
            _, nx, ny = index.nodes[i]
            label = f"end node {i} (P={prob(i):.2f})" if reliability else f"end node {i}"
            if i not in dist:
                c = None
                if p.approach_narrow and entry is not None and clearance_at is not None:
                    if wide is None:
                        wide = gr.search_from_entry(index, entry, through_narrow=True)
                    c = self._approach(i, nx, ny, label, prob(i) if reliability else 0.0,
                                       index, entry, wide, clearance_at, need, x, y)
                if c is None:
                    unreachable.append(i)
                elif self._blacklisted(c):
                    black.append(i)
                else:
                    ev.cands.append(c)
                continue

            def path(i=i):
                pts = gr.path_points(index, entry, pred, i)
                if clearance_at is None:
                    return pts
                return gr.trim_narrow_tip(pts, clearance_at, need, p.tip_length)

            c = _Cand(i, nx, ny, dist[i], dist[i], 1.0, prob(i) if reliability else 0.0, path,
                      label=label)
            if self._blacklisted(c):
                black.append(i)
                continue
            ev.cands.append(c)
        if entry is None and open_ids:
            ev.failed = (f"cannot join the skeleton: no edge with clearance >= "
                         f"{p.robot_radius + p.clearance_margin:.2f} m (of {len(index.narrow)} "
                         f"narrow); {len(open_ids)} end node(s) still open "
                         f"(ids {_ids(open_ids)})")
        reach = [i for i in ends if i in dist]
        if reliability:
            ok = [i for i in reach if prob(i) >= thr]
            done = f"all {len(ok)} reachable end nodes reliable (P >= {thr:g})"
        else:
            ok = [i for i in reach if i not in open_ids]
            done = f"all {len(ok)} reachable end nodes visited (within {p.visit_radius:g} m)"
        if not ends:
            done = "the topological map has no end nodes"
        if black:
            done += f"; {len(black)} blacklisted (ids {_ids(black)})"
        if unreachable:
            what = "unreliable" if reliability else "unvisited"
            done += (f"; {len(unreachable)} {what} end node(s) unreachable for the robot "
                     f"(ids {_ids(unreachable)})")
        ev.done = done

        def status_of(c: _Cand) -> str:
            if c.id not in index.nodes or index.nodes[c.id][0] != "end":
                return "vanished"
            if reliability and prob(c.id) >= thr:
                return f"became reliable (P={prob(c.id):.2f})"
            if not reliability and c.id not in open_ids:
                return "visited"
            if c.id not in dist:
                return "became unreachable"
            return "was blacklisted"

        ev.status_of = status_of
        pts = index.all_points()
        tree = cKDTree(pts) if len(pts) else None

        def path_ok(wps: np.ndarray) -> bool:
            if len(wps) == 0:
                return True
            if tree is None:
                return False
            d, _ = tree.query(wps, k=1, distance_upper_bound=p.path_tolerance + 1e-9)
            return bool(np.all(np.isfinite(d)))

        ev.path_ok = path_ok
        if grid is not None:
            ev.path_clear = lambda wps: not gr.crosses(occ, geom, wps)
        return ev

    def _completion(self, t, x, y, ev: _Eval, topo, rel, grid, geom, p_free, p_occ) -> _Eval:
        """No end node is left to visit: the frontier groups still on the map are the
        candidates (as for the frontier strategy), so that "done" means the map is complete
        and not only that every end node is reliable. An opening seen at the side of a room
        or corridor may give no end node at all (a corridor that bends away as the maze's).
        The frontier search is repeated at most every frontier_period s while following."""
        cached = self._frontier_ev
        if (cached is not None and self._target is not None and self._target.cand.id < 0
                and cached.cands and 0.0 <= t - self._frontier_t < self.p.frontier_period):
            fe = cached
        else:
            fe = self._eval_completion(x, y, topo, rel, grid, geom, p_free, p_occ)
            self._frontier_ev, self._frontier_t = fe, t
        if fe.failed is not None:
            return ev
        for c in fe.cands:
            c.label = f"{c.label} (completion: no end node left)"
        fe.end_nodes, fe.reliable = ev.end_nodes, ev.reliable
        fe.done = f"{ev.done}; {fe.done}"
        return fe

    def _mapped(self, t, x, y, topo, rel, grid, geom, p_free, p_occ) -> bool:
        """stop_when_mapped: is no frontier left by the completion rules (so that the
        completion phase would find nothing either)? Checked at most every frontier_period s.
        First a cheap pass: a reachable group of completion_min_size or more (connected
        components, no path costs) means no; only without one is the full search run (path
        lengths for the shorter groups within completion_near). On large-office the full
        search every second was 40 % of the planner's time."""
        if 0.0 <= t - self._mapped_t < self.p.frontier_period:
            return self._mapped_ok
        self._mapped_t = t
        quick = self._eval_completion(x, y, topo, rel, grid, geom, p_free, p_occ, quick=True)
        if quick.failed is None and quick.cands:
            self._mapped_ok = False
            return False
        fe = self._eval_completion(x, y, topo, rel, grid, geom, p_free, p_occ)
        self._mapped_ok = fe.failed is None and not fe.cands
        self._mapped_why = fe.done
        return self._mapped_ok

    def _eval_completion(self, x, y, topo, rel, grid, geom, p_free, p_occ,
                         quick: bool = False) -> _Eval:
        """The frontier groups the completion rules count (completion_min_size, or shorter
        within completion_near, no enclosed pockets below completion_pocket_area). quick:
        only the long groups, and only whether they are reachable (no path costs)."""
        p = self.p
        return self._eval_frontier(x, y, topo, rel, grid, geom, p_free, p_occ,
                                   max(p.min_frontier_size, p.completion_min_size),
                                   p.completion_pocket_area, 0.0 if quick else p.completion_near,
                                   reach_only=quick)

    def _clearance_of(self, grid, geom, p_free, p_occ, occ=None) -> np.ndarray:
        """Distance [m] to the nearest occupied cell on the cropped grid of this update,
        computed once (the topological and frontier evaluations of one update share it)."""
        if self._clear is None or self._clear[0] != geom:
            if occ is None:
                occ = classify(grid, p_free, p_occ) == OCCUPIED
            self._clear = (geom, fr.clearance_map(occ, geom.resolution))
        return self._clear[1]

    def _approach(self, i, nx, ny, label, prob, index, entry, wide, clearance_at, need, x, y
                  ) -> _Cand | None:
        """Candidate for open end node i behind a narrow edge: the path up to the narrow point.

        Where the map is only half seen (a corridor glimpsed at an angle), its skeleton hugs the
        seen wall and looks narrow although the corridor is wide; from the narrow point the
        robot sees it. Cost = the whole path length (as if the passage were wide); None if no
        path leads there even through narrow edges, or once the robot has stood within
        goal_tolerance of the narrow point: it has looked from there, and the node counts as
        unreachable from then on unless the way becomes wide (a full, not partial, path) or its
        narrow point lies more than blacklist_radius from every point looked from (by position:
        node ids change as the skeleton is rebuilt). (Forgetting the look as soon as the
        robot leaves made it shuttle between the narrow point and the next target.)
        """
        dist, pred = wide
        if i not in dist:
            return None
        full = gr.path_points(index, entry, pred, i)
        pts = gr.cut_at_narrow(full, clearance_at, need)
        if len(pts) < 2 or len(pts) == len(full):
            return None
        reach = float(gr.polyline_lengths(pts)[-1])
        px, py = float(pts[-1, 0]), float(pts[-1, 1])
        if math.hypot(px - x, py - y) <= self.p.goal_tolerance:
            if not self._has_looked(i, px, py):
                self._looked.append(_Mark(i, px, py, reason="looked", t=self._last_t or 0.0))
            return None
        if self._has_looked(i, px, py):
            return None
        to_entry = math.hypot(pts[0, 0] - x, pts[0, 1] - y)
        return _Cand(i, nx, ny, dist[i], to_entry + reach, 1.0, prob, lambda: pts,
                     label=f"{label} up to a narrow passage", partial=True)

    def _eval_frontier(self, x, y, topo, rel, grid, geom, p_free, p_occ,
                       min_size: float | None = None, pocket_area: float = 0.0,
                       near: float = 0.0, reach_only: bool = False) -> _Eval:
        """Frontier groups as candidates: those at least min_size [m] long (default
        min_frontier_size), and the shorter ones (down to min_frontier_size) whose path is at
        most near [m]; with pocket_area > 0 [m^2], not those bordering a smaller enclosed
        unknown pocket."""
        p = self.p
        min_size = p.min_frontier_size if min_size is None else min_size
        floor = min(min_size, p.min_frontier_size) if near > 0 else min_size
        if grid is None:
            return _Eval(waiting="waiting for map")
        grid, geom = crop_known(grid, geom)  # the same answers on a smaller array
        ev = _Eval()
        if topo is not None:  # informational only
            ends = [n.id for n in topo.nodes if n.kind == "end"]
            ev.end_nodes = len(ends)
            if rel is not None:
                pm = {n.id: n.p for n in rel.nodes}
                ev.reliable = sum(1 for i in ends if pm.get(i, 0.0) >= p.p_reliable)
        hard = p.robot_radius + p.clearance_margin
        search = fr.grid_search(grid, geom, x, y, hard, p_free, p_occ,
                                soft_radius=SOFT_RADIUS_FACTOR * hard, soft_penalty=SOFT_PENALTY,
                                reach_only=reach_only,
                                clearance=self._clearance_of(grid, geom, p_free, p_occ))
        if search.start is None:
            ev.failed = "the robot is not near known free space (no start cell for the search)"
            ev.done = ev.failed
            return ev
        unknown = (open_unknown(grid, int(pocket_area / geom.resolution ** 2), p_free, p_occ)
                   if pocket_area > 0 else None)
        groups, dropped = fr.find_frontiers(grid, geom, search, floor,
                                            p.potential_scale, p.gain_scale, p_free, p_occ,
                                            unknown)
        unreachable, black = 0, 0
        for g in groups:
            if g.size * geom.resolution < min_size - 1e-9 and not (
                    g.goal_xy is not None and g.path_length <= near):
                dropped += 1
                continue
            if g.goal_xy is None:
                unreachable += 1
                continue
            c = _Cand(-1, g.goal_xy[0], g.goal_xy[1], g.cost, g.path_length, p.potential_scale,
                      0.0, (lambda g=g: search.path_to(*g.goal_rc)), g.cells_xy,
                      label=f"frontier at ({g.goal_xy[0]:.2f}, {g.goal_xy[1]:.2f}) "
                            f"size {g.size * geom.resolution:.1f} m", face=g.look_xy)
            if self._blacklisted(c):
                black += 1
                continue
            ev.cands.append(c)
        done = "no frontier left"
        if dropped:
            done += f" ({dropped} group(s) shorter than {min_size:g} m ignored" + (
                f", unless within {near:g} m)" if near > 0 and floor < min_size else ")")
        if black:
            done += f"; {black} blacklisted"
        if unreachable:
            done += f"; {unreachable} frontier group(s) unreachable for the robot"
        ev.done = done
        ev.status_of = lambda c: "was cleared (no frontier group there any more)"
        cls = classify(grid, p_free, p_occ)

        def path_ok(wps: np.ndarray) -> bool:
            if len(wps) == 0:
                return True
            rows, cols = geom.world_to_cell(wps[:, 0], wps[:, 1])
            inside = geom.inside(rows, cols)
            if not np.all(inside):
                return False
            bad = (cls[rows, cols] == OCCUPIED) | (
                search.clearance[rows, cols] < 0.5 * p.robot_radius)
            return not bool(np.any(bad))

        ev.path_ok = path_ok
        return ev

    # --- decision machine --------------------------------------------------------------------

    def _has_looked(self, i: int, px: float, py: float) -> bool:
        r2 = self.p.blacklist_radius ** 2
        return any((b.x - px) ** 2 + (b.y - py) ** 2 <= r2 for b in self._looked)

    def _blacklisted(self, c: _Cand) -> bool:
        r2 = self.p.blacklist_radius ** 2
        for b in self._blacklist:
            if c.id >= 0 and b.id == c.id:
                return True
            if (b.x - c.x) ** 2 + (b.y - c.y) ** 2 <= r2:
                return True
        return False

    def _add_blacklist(self, c: _Cand, t: float, reason: str) -> str:
        bid = c.id if c.id >= 0 else len(self._blacklist)
        self._blacklist.append(_Mark(bid, c.x, c.y, reason=reason, t=t))
        return f"blacklisted {c.label}: {reason}"

    def _count_failure(self, c: _Cand) -> int:
        r2 = self.p.blacklist_radius ** 2
        for a in self._attempts:
            if (c.id >= 0 and a.id == c.id) or (a.x - c.x) ** 2 + (a.y - c.y) ** 2 <= r2:
                a.count += 1
                a.x, a.y = c.x, c.y
                return a.count
        self._attempts.append(_Mark(c.id, c.x, c.y, count=1))
        return 1

    def _same(self, a: _Cand, b: _Cand) -> bool:
        if a.id >= 0 or b.id >= 0:
            return a.id == b.id
        return a is b or (a.x == b.x and a.y == b.y)

    def _match(self, cur: _Cand, cands: list[_Cand]) -> _Cand | None:
        if cur.id >= 0:
            for c in cands:
                if c.id == cur.id:
                    return c
            return None
        best, best_d = None, self.p.frontier_match_radius
        for c in cands:
            cells = c.cells if c.cells is not None and len(c.cells) else np.array([[c.x, c.y]])
            d = float(np.sqrt(((cells[:, 0] - cur.x) ** 2 + (cells[:, 1] - cur.y) ** 2).min()))
            if d <= best_d:
                best, best_d = c, d
        return best

    def _choose(self, cands: list[_Cand], x: float, y: float, th: float) -> tuple[_Cand, str]:
        best = min(cands, key=lambda c: c.cost)
        band = [c for c in cands if c.cost <= best.cost + self.p.tie_tolerance * c.scale + 1e-9]
        if len(band) == 1:
            return best, "least path cost"

        def off(c: _Cand) -> float:
            return angle_diff(math.atan2(c.y - y, c.x - x), th)

        pick = min(band, key=lambda c: (off(c), c.cost))
        if self._same(pick, best):
            return best, "least path cost"
        return pick, (f"ahead of the robot (cost within {self.p.tie_tolerance:g} m of the "
                      f"least)")

    def _new_path(self, c: _Cand, x: float, y: float) -> np.ndarray:
        dense = np.asarray(c.path(), dtype=np.float64).reshape(-1, 2)
        if len(dense) and math.hypot(dense[0, 0] - x, dense[0, 1] - y) < ENTRY_SKIP:
            dense = dense[1:]
        if len(dense) == 0:
            dense = np.array([[c.x, c.y]])
        rest = gr.thin_polyline(dense, self.p.waypoint_spacing) if len(dense) > 1 else dense
        return np.vstack([[x, y], rest])

    def _set_target(self, c: _Cand, t: float, x: float, y: float, why: str,
                    progress_t: float | None = None) -> None:
        wps = self._new_path(c, x, y)
        cum = gr.polyline_lengths(wps)
        self._target = _Target(c, c.x, c.y, wps, cum, 0, float(cum[-1]),
                               t if progress_t is None else progress_t, None,
                               t if progress_t is None or self._target is None
                               else self._target.chosen_t, why, c.partial)
        self._plan_id += 1

    def _remaining(self, tg: _Target, x: float, y: float) -> float:
        """Remaining path length [m]; moves tg.idx to the segment the robot is on."""
        w, cum = tg.wps, tg.cum
        if len(w) < 2:
            return math.hypot(w[-1, 0] - x, w[-1, 1] - y)
        hi = int(np.searchsorted(cum, cum[tg.idx] + REMAINING_WINDOW, side="right"))
        hi = min(len(w) - 1, max(hi, tg.idx + 1))
        p0, p1 = w[tg.idx:hi], w[tg.idx + 1:hi + 1]
        d = p1 - p0
        dd = np.einsum("ij,ij->i", d, d)
        q = np.array([x, y])
        s = np.clip(np.einsum("ij,ij->i", q - p0, d) / np.where(dd > 0, dd, 1.0), 0.0, 1.0)
        near = p0 + s[:, None] * d
        lat = np.hypot(near[:, 0] - x, near[:, 1] - y)
        k = int(np.argmin(lat))
        tg.idx += k
        j = tg.idx
        arc = cum[j] + s[k] * (cum[j + 1] - cum[j])
        return float(lat[k] + cum[-1] - arc)

    def _decide(self, t: float, x: float, y: float, th: float, ev: _Eval) -> PlanOutput:
        p = self.p
        notes: list[str] = []
        cands = ev.cands
        tg = self._target
        replanned = False
        if tg is not None:
            c = self._match(tg.cand, cands)
            if c is None:
                notes.append(f"previous target {tg.cand.label} {ev.status_of(tg.cand)}")
                self._target = tg = None
            else:
                tg.cand = c
                action, new = self._step_target(t, x, y, th, tg, c, cands, ev, notes)
                if action == "drop":
                    cands = [k for k in cands if not self._blacklisted(k)]
                    self._target = tg = None
                    self._replans += 1
                    replanned = True
                elif action == "retry":
                    best, why = self._choose(cands, x, y, th)
                    self._set_target(best, t, x, y, why if not self._same(best, c) else tg.why)
                    self._replans += 1
                elif action in ("same", "cross"):
                    self._set_target(c, t, x, y, tg.why, progress_t=new)
                    self._target.crossings = tg.crossings + (action == "cross")
                    self._replans += 1
                elif action == "switch":
                    self._set_target(new, t, x, y, f"switched from {c.label}: cost "
                                     f"{new.cost:.1f} < {p.switch_ratio:g} x {c.cost:.1f}")
                    self._replans += 1
        if self._target is None and cands:
            best, why = self._choose(cands, x, y, th)
            if replanned:
                why = f"{why} (after dropping the previous target)"
            self._set_target(best, t, x, y, why)
            self._last_eval_t = t
        tg = self._target
        if tg is None:
            return self._no_target(t, ev, notes)
        self._no_cand = 0
        self._fail_since = None
        c = tg.cand
        head = f"target {c.label}: {tg.why}; path {c.dist:.1f} m; {len(cands)} candidate(s)"
        if self._blacklist:
            notes.append(f"blacklisted: {_ids([b.id for b in self._blacklist])}")
        return self._emit(t, "exploring", "; ".join([head] + notes), ev, len(cands))

    def _no_target(self, t: float, ev: _Eval, notes: list[str]) -> PlanOutput:
        """Stop; report done / failed only once the situation is confirmed.

        done needs done_confirm consecutive updates without a candidate (one odd topology
        update must not end the run); failed (the robot cannot join the skeleton / free space)
        needs to last progress_timeout s.
        """
        p = self.p
        if ev.failed is not None:
            self._no_cand = 0
            if self._fail_since is None:
                self._fail_since = t
            waited = t - self._fail_since
            if waited >= p.progress_timeout:
                return self._emit(t, "failed", "; ".join(notes + [ev.failed]), ev, 0)
            return self._emit(t, "exploring", "; ".join(notes + [
                f"{ev.failed} (for {waited:.1f} s; failed after {p.progress_timeout:g} s)"]),
                ev, 0)
        self._fail_since = None
        self._no_cand += 1
        if self._no_cand >= p.done_confirm:
            return self._emit(t, "done", "; ".join(notes + [ev.done]), ev, 0)
        return self._emit(t, "exploring", "; ".join(notes + [
            f"no candidate left, confirming ({self._no_cand}/{p.done_confirm}): {ev.done}"]),
            ev, 0)

    def _step_target(self, t, x, y, th, tg: _Target, c: _Cand, cands, ev: _Eval,
                     notes: list[str]):
        """Progress, arrival, failure and re-plan checks for the current target.

        Returns (action, arg): ("keep", None) | ("drop", None) | ("retry", None) |
        ("same", progress_t) | ("switch", new candidate).
        """
        p = self.p
        if c.partial != tg.partial:
            notes.append(f"{c.label}: " + ("a passage on the way became narrow: new path"
                                           if c.partial else "the way is wide now: new path"))
            return "same", t
        moved = math.hypot(c.x - tg.plan_x, c.y - tg.plan_y) >= p.target_move
        rem = self._remaining(tg, x, y)
        if moved:
            tg.progress_t = t
        elif rem < tg.best_rem - p.progress_distance:
            tg.best_rem = rem
            tg.progress_t = t
        if math.hypot(x - tg.wps[-1, 0], y - tg.wps[-1, 1]) <= p.goal_tolerance:
            if tg.arrived_t is None:
                tg.arrived_t = t
        else:
            tg.arrived_t = None
        if tg.arrived_t is not None and t - tg.arrived_t >= p.arrival_timeout:
            notes.append(self._add_blacklist(
                c, t, f"reached but still unresolved after {p.arrival_timeout:g} s"))
            return "drop", None
        if t - tg.progress_t >= p.progress_timeout:
            n = self._count_failure(c)
            if n >= p.max_attempts:
                notes.append(self._add_blacklist(
                    c, t, f"no progress for {p.progress_timeout:g} s, {n} attempt(s)"))
                return "drop", None
            notes.append(f"no progress toward {c.label} for {p.progress_timeout:g} s "
                         f"(attempt {n}/{p.max_attempts}): re-planning")
            return "retry", None
        if moved:
            notes.append(f"target moved {math.hypot(c.x - tg.plan_x, c.y - tg.plan_y):.2f} m: "
                         "new path")
            return "same", t
        if not ev.path_ok(tg.wps[tg.idx + 1:]):
            notes.append("the path left the current map: new path")
            return "same", tg.progress_t
        if tg.crossings < MAX_CROSSING_REPLANS and not ev.path_clear(tg.wps[tg.idx:]):
            # a wall seen after the path was made (a corridor side glimpsed through gaps): the
            # waypoints may still lie near the skeleton on its far side, so path_ok passes
            notes.append("the path crosses an obstacle seen since it was made: new path")
            return "cross", tg.progress_t
        if t - self._last_eval_t >= p.replan_period:
            self._last_eval_t = t
            best, _ = self._choose(cands, x, y, th)
            margin = (1 - p.switch_ratio) * c.scale * c.dist
            if not self._same(best, c) and best.cost < c.cost - margin:
                return "switch", best
            if c.dist < p.switch_ratio * rem - 1e-9:
                notes.append(f"shorter path to the target ({c.dist:.1f} m < "
                             f"{p.switch_ratio:g} x {rem:.1f} m)")
                return "same", tg.progress_t
        return "keep", None

    def _emit(self, t: float, state: str, reason: str, ev: _Eval, ncand: int) -> PlanOutput:
        tg = self._target
        if tg is None:
            if self._had_path:
                self._plan_id += 1  # the stop is a new plan
            self._had_path = False
            out = PlanOutput([], -1, (0.0, 0.0), state, reason, ncand, ev.end_nodes,
                             ev.reliable, [b.id for b in self._blacklist], self._replans, 0.0,
                             self._plan_id)
        else:
            self._had_path = True
            c = tg.cand
            heading = None
            if c.face is not None:
                ex, ey = tg.wps[-1]
                if math.hypot(c.face[0] - ex, c.face[1] - ey) > FACE_MIN_DISTANCE:
                    heading = math.atan2(c.face[1] - ey, c.face[0] - ex)
            out = PlanOutput([(float(a), float(b)) for a, b in tg.wps], c.id,
                             (float(c.x), float(c.y)), state, reason, ncand, ev.end_nodes,
                             ev.reliable, [b.id for b in self._blacklist], self._replans,
                             float(c.p), self._plan_id, heading)
        self._last = out
        return out
