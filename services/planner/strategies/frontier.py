"""The ``frontier`` strategy (Yamauchi / explore_lite, with grid path lengths): the frontier
groups of the map are the candidates, cost = potential_scale * path - gain_scale * size.

:func:`frontier_evaluation` is also what the completion rules (:mod:`.completion`) search with.
While the core follows a target, the search runs at most once per ``frontier_period`` (as
explore_lite's ``planner_frequency``); with no target, or when the map changed under the
path followed (:attr:`base.Update.fresh`), it runs on every update.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from typing import Any

import numpy as np

from topoexplore.common.grid import cells_for
from topoexplore.common.params import PlannerParams
from topoexplore.services.planner import gridsearch as gs
from topoexplore.services.planner.examined import line_of_sight
from topoexplore.services.planner.mapview import MapView
from topoexplore.services.planner.strategies.base import Candidate, Config, Evaluation, Update

SOFT_RADIUS_FACTOR = 2.0  # cells with clearance < this x (radius + margin) cost more ...
SOFT_PENALTY = 2.0  # ... up to (1 + this) x their length at the hard limit
NARROW_PENALTY = 4.0  # cells the robot's body fits but under the margin: this much more again


def frontier_evaluation(cfg: Config, u: Update, min_size: float | None = None,
                        pocket_area: float = 0.0, near: float = 0.0, reach_only: bool = False,
                        openings: bool = False) -> Evaluation:
    """Frontier groups on u.view as candidates: those at least min_size [m] long (default
    min_frontier_size), and the shorter ones (down to min_frontier_size) whose path is at
    most near [m], and with openings the shorter ones beside an opening not yet looked into
    (:meth:`MapView.openings`); with pocket_area > 0 [m^2], not those bordering a smaller
    enclosed unknown pocket. reach_only: no path costs, only which groups are reachable at all (see
    :func:`gridsearch.grid_search`), no look points, and (without near or openings) the
    search ends at the first group that counts: whether there is one, not how many.

    Paths keep the clearance margin (cells with clearance >= robot radius + margin); only
    when no group is reachable that way, the search goes again through narrow passages too
    (clearance down to the controller's corridor, robot.radius + robot.body_margin, at
    NARROW_PENALTY extra cost): a room behind a door as narrow as the robot's diameter plus
    twice the margin, or the gap the robot came in through, is reachable, never a reason to
    stop; only groups of completion_min_size or longer count there. reach_only asks that
    second question directly."""
    if reach_only:
        return _evaluate(cfg, u, min_size, pocket_area, near, True, True, openings)
    if u.target is not None and u.target.narrow:  # following a narrow-passage target: the
        return _narrow(cfg, u, min_size, pocket_area, near, openings)  # search that found it
    ev = _evaluate(cfg, u, min_size, pocket_area, near, False, False, openings)
    if ev.failed is None and not ev.cands and ev.unreachable:
        narrow = _narrow(cfg, u, min_size, pocket_area, near, openings)
        if narrow.cands:
            return narrow
    return ev


def _narrow(cfg: Config, u: Update, min_size: float | None, pocket_area: float, near: float,
            openings: bool = False) -> Evaluation:
    """The search through narrow passages too: only for groups of completion_min_size or
    longer, or openings (a real opening, worth the way through a tight spot; a sliver of
    unknown behind furniture is not)."""
    p = cfg.params
    size = max(p.min_frontier_size if min_size is None else min_size, p.completion_min_size)
    ev = _evaluate(cfg, u, size, pocket_area, 0.0, False, True, openings)
    for c in ev.cands:
        c.label += " through a narrow passage"
        c.narrow = True
    return ev


def nearest_frontier_evaluation(cfg: Config, u: Update) -> Evaluation:
    """The reachable frontier groups (through narrow passages too) with cost = path length:
    the nearest first (the watchdog's fallback). Only the groups the strategy's own "done"
    waits for: the frontier strategy's (min_frontier_size or longer), and for the
    topological strategies the completion rules' (completion_min_size or longer, shorter
    ones within completion_near, none beside an enclosed pocket under
    completion_pocket_area; :mod:`.completion`). A fallback that breaks a livelock never
    adds work that "done" would not wait for: with every group counted, a robot whose
    watchdog had fired toured 0.5 m specks across an office for 930 s (docs/design.md,
    "A global watchdog")."""
    if cfg.params.strategy == "frontier":
        ev = _evaluate(cfg, u, None, 0.0, 0.0, False, True)
    else:
        ev = _evaluate(cfg, u, *completion_rule(cfg.params), False, True)
    for c in ev.cands:
        c.cost, c.scale = c.dist, 1.0
        c.label += " (watchdog: nearest frontier)"
    return ev


def completion_rule(p: PlannerParams) -> tuple[float, float, float]:
    """(min_size [m], pocket_area [m^2], near [m]) of :func:`frontier_evaluation` for the
    groups the completion rules count (:mod:`.completion`; also the watchdog's fallback for
    the topological strategies)."""
    return (max(p.min_frontier_size, p.completion_min_size), p.completion_pocket_area,
            p.completion_near)


def _evaluate(cfg: Config, u: Update, min_size: float | None, pocket_area: float, near: float,
              reach_only: bool, narrow: bool, openings: bool = False) -> Evaluation:
    """frontier_evaluation with or without narrow passages."""
    p = cfg.params
    view = u.view
    min_size = p.min_frontier_size if min_size is None else min_size
    floor = min(min_size, p.min_frontier_size) if near > 0 or openings else min_size
    ev = Evaluation()
    search = (robot_reach(cfg, u) if narrow and reach_only
              else robot_search(cfg, u, narrow, reach_only))
    if search.start is None:
        ev.failed = "the robot is not near known free space (no start cell for the search)"
        ev.done = ev.failed
        return ev
    res = view.geom.resolution
    unknown = open_unknown(cfg, u, pocket_area) if pocket_area > 0 else view.unknown
    stop = None
    if reach_only and near <= 0 and not openings:  # only whether one group counts: the
        #   groups end with the first (all are min_size or longer: floor is min_size)
        def stop(g: gs.FrontierGroup) -> bool:
            return g.goal_xy is not None and not u.blacklisted(
                _candidate(g, search, res, p.potential_scale))
    groups, dropped = gs.find_frontiers(view.frontier_free, unknown, view.geom, search, floor,
                                        p.potential_scale, p.gain_scale, look=not reach_only,
                                        stop=stop)
    fit = cfg.fit(res)
    unreachable, black, doors = 0, 0, 0
    for g in groups:
        short = g.size * res < min_size - 1e-9 and not (
            g.goal_xy is not None and g.path_length <= near)
        mouth = (opening_mouth(view, fit, g) if short and openings and g.goal_xy is not None
                 else None)
        door = mouth is not None
        doors += door
        if short and not door:
            dropped += 1
        elif g.goal_xy is None:
            unreachable += 1
        else:
            c = _candidate(g, search, res, p.potential_scale)
            if mouth is not None:
                _look_from_afar(c, view, search, mouth, p)
            if u.blacklisted(c):
                black += 1
            else:
                ev.cands.append(c)
    done = "no frontier left"
    if dropped:
        done += f" ({dropped} group(s) shorter than {min_size:g} m ignored" + (
            f", unless within {near:g} m" if near > 0 and floor < min_size else "") + (
            ", or openings" if openings else "") + ")"
    if doors:
        done += f"; {doors} shorter opening(s) counted"
    if black:
        done += f"; {black} blacklisted"
    if unreachable:
        done += f"; {unreachable} frontier group(s) unreachable for the robot"
    ev.done = done
    ev.unreachable = unreachable
    ev.status_of = lambda c: "was cleared (no frontier group there any more)"
    # the search's clearance is the best clearance on the whole map when the search did
    # not need it (a reach-only one): made only if a path is checked
    ev.path_ok = path_fits(view, lambda: search.clearance, cfg.radius)
    return ev


def opening_mouth(view: MapView, fit: float, g: gs.FrontierGroup) -> tuple[int, int] | None:
    """May frontier group g be a door seen only from afar (:meth:`MapView.openings`, for the
    robot's body fit [m])? The cell (row, col) where it is judged one, or None: at the middle
    of its mouth (of its mouth cells, those with the greatest best clearance, within half a
    cell), a cell behind which the unknown widens."""
    mouth, wide = view.openings(fit)
    rows, cols = view.geom.world_to_cell(g.cells_xy[:, 0], g.cells_xy[:, 1])
    at = mouth[rows, cols]
    if not at.any():
        return None
    rows, cols = rows[at], cols[at]
    best = view.best_clearance[rows, cols]
    mid = best >= best.max() - 0.5 * view.geom.resolution
    hit = np.nonzero(wide[rows[mid], cols[mid]])[0]
    return None if len(hit) == 0 else (int(rows[mid][hit[0]]), int(cols[mid][hit[0]]))


def viewpoint(view: MapView, search: gs.GridSearch, cell: tuple[int, int], reach: float,
              angle: float) -> tuple[int, int] | None:
    """The reachable cell nearest by path from which the robot looks into the opening at
    cell (row, col) as the ``looked`` memory counts it (:mod:`..examined`): within reach
    [m], the line of sight within angle [rad] of the direction of one of the cell's unknown
    4-neighbours, and only free cells between. None if there is none."""
    res, (r0, c0) = view.geom.resolution, cell
    n = int(math.ceil(reach / res))
    h, w = view.free.shape
    a0, a1, b0, b1 = max(0, r0 - n), min(h, r0 + n + 1), max(0, c0 - n), min(w, c0 + n + 1)
    dist = search.dist[a0:a1, b0:b1]
    rr, cc = np.nonzero(np.isfinite(dist))
    if len(rr) == 0:
        return None
    dr, dc = (r0 - a0) - rr, (c0 - b0) - cc  # [cells] viewpoint -> the opening
    length = np.hypot(dr, dc)
    ok = (length <= reach / res) & (length > 0)
    square = np.zeros(len(rr), dtype=bool)
    cos_a = math.cos(angle)
    unknown = view.unknown
    with np.errstate(invalid="ignore", divide="ignore"):
        for d_r, d_c in ((1, 0), (-1, 0), (0, 1), (0, -1)):
            nr, nc = r0 + d_r, c0 + d_c
            if not (0 <= nr < h and 0 <= nc < w) or unknown[nr, nc]:
                square |= (dr * d_r + dc * d_c) / length >= cos_a
    ok &= square
    idx = np.nonzero(ok)[0]
    if len(idx) == 0:
        return None
    idx = idx[np.argsort(dist[rr[idx], cc[idx]], kind="stable")]
    free = view.free[a0:a1, b0:b1]
    for chunk in range(0, len(idx), 64):  # nearest first, a batch at a time
        part = idx[chunk:chunk + 64]
        seen = line_of_sight(free, (r0 - a0, c0 - b0), rr[part], cc[part])
        if seen.any():
            k = part[int(np.argmax(seen))]
            return int(rr[k] + a0), int(cc[k] + b0)
    return None


def open_unknown(cfg: Config, u: Update, pocket_area: float) -> np.ndarray:
    """Unexplored cells on u.view without the enclosed pockets under pocket_area [m^2], except
    those the robot can look into (:meth:`MapView.open_unknown`): completion_min_size of
    their edge reached from where it is (:func:`robot_reach`), completion_pocket_share of the
    known free cells or more."""
    cells, reach, share = _pocket_rule(cfg, u, pocket_area)
    return u.view.open_unknown(cells, robot_reach(cfg, u), reach, share)


def open_unknown_made(cfg: Config, u: Update, pocket_area: float) -> np.ndarray | None:
    """:func:`open_unknown` (cfg, u, pocket_area) if this update has made it, else None
    (nothing is computed)."""
    search = u.view.memo_made(_reach_key(u, True))
    if search is None:
        return None
    cells, reach, share = _pocket_rule(cfg, u, pocket_area)
    return u.view.open_unknown_made(cells, search, reach, share)


def _pocket_rule(cfg: Config, u: Update, pocket_area: float) -> tuple[int, int, float]:
    """(pocket cells, border cells reached to look in, share of the free cells) of
    :meth:`MapView.open_unknown` for pocket_area [m^2]."""
    p, res = cfg.params, u.view.geom.resolution
    return int(pocket_area / res ** 2), cells_for(p.completion_min_size, res), \
        p.completion_pocket_share


def robot_reach(cfg: Config, u: Update, narrow: bool = True) -> gs.GridSearch:
    """Where the robot can get at all (narrow passages too, or with narrow False only where
    :func:`robot_search` paths go; no path costs), once per map view and robot position."""
    return u.view.memo(_reach_key(u, narrow), lambda: robot_search(cfg, u, narrow, True))


def _reach_key(u: Update, narrow: bool) -> tuple:
    return "reach", narrow, u.x, u.y


def robot_search(cfg: Config, u: Update, narrow: bool = False, reach_only: bool = False
                 ) -> gs.GridSearch:
    """The grid search from the robot on u.view that frontier paths (and, with grid_paths,
    the topological strategies' paths to their end nodes) are made with: cells with clearance
    >= radius + margin (cfg.need), longer near walls (the soft penalty); narrow: through
    narrow passages too, at NARROW_PENALTY."""
    view, hard = u.view, cfg.need
    return view.search(u.x, u.y, hard, fit=cfg.fit(view.geom.resolution),
                       soft_radius=SOFT_RADIUS_FACTOR * hard, soft_penalty=SOFT_PENALTY,
                       narrow_penalty=NARROW_PENALTY if narrow else None, reach_only=reach_only)


def clearance_cap(cfg: Config) -> float:
    """[m] the greatest clearance a rule of the planner asks a cell for: the soft penalty's
    reach in :func:`robot_search`. The clearance the planner keeps between updates
    (:class:`.gridsearch.ClearanceKeeper`) is capped there."""
    return SOFT_RADIUS_FACTOR * cfg.need


def _look_from_afar(c: Candidate, view: MapView, search: gs.GridSearch,
                    mouth: tuple[int, int], p: PlannerParams) -> None:
    """Candidate c of an opening at cell mouth: its goal becomes the nearest place to look
    into it from (:func:`viewpoint`, within completion_openings), facing it."""
    c.opening = True
    c.label += " (an opening not yet looked into)"
    vp = viewpoint(view, search, mouth, p.completion_openings, p.examine_angle)
    if vp is None:
        return
    d = float(search.dist[vp])
    c.cost -= c.scale * (c.dist - d)
    c.x, c.y = (float(v) for v in view.geom.cell_to_world(*vp))
    c.dist = d
    c.path = lambda: search.path_to(*vp)
    c.face = tuple(float(v) for v in view.geom.cell_to_world(*mouth))
    c.label += f", looked into from ({c.x:.2f}, {c.y:.2f})"


def _candidate(g: gs.FrontierGroup, search: gs.GridSearch, res: float, scale: float
               ) -> Candidate:
    gx, gy = g.goal_xy
    return Candidate(-1, gx, gy, g.cost, g.path_length, scale, 0.0,
                     lambda: search.path_to(*g.goal_rc), g.cells_xy,
                     label=f"frontier at ({gx:.2f}, {gy:.2f}) size {g.size * res:.1f} m",
                     face=g.look_xy)


def path_fits(view: MapView, clearance: Callable[[], np.ndarray], radius: float):
    """path_ok of a grid path (a frontier's, or an end node's with grid_paths): every
    waypoint on the grid, on no occupied cell and with at least half the robot radius of
    clearance [m] (``clearance()``: the search's clearance map, asked for at each check, so
    an update that checks no path never makes a clearance the search left unmade)."""
    geom = view.geom

    def path_ok(wps: np.ndarray) -> bool:
        if len(wps) == 0:
            return True
        rows, cols = geom.world_to_cell(wps[:, 0], wps[:, 1])
        inside = geom.inside(rows, cols)
        if not np.all(inside):
            return False
        bad = view.occupied[rows, cols] | (clearance()[rows, cols] < 0.5 * radius)
        return not bool(np.any(bad))

    return path_ok


class Frontier:
    """Nearest-frontier exploration (explore_lite's cost form, grid path lengths)."""

    def __init__(self, cfg: Config):
        self.cfg = cfg
        self._ev: Evaluation | None = None  # the last search ...
        self._t = -math.inf  # ... and its time [s]

    def evaluate(self, u: Update) -> Evaluation:
        cached = self._ev
        if (cached is not None and cached.cands
                and u.may_reuse(self.cfg.params.frontier_period, self._t)):
            ev = cached  # following a target: keep the last search
        else:
            ev = (Evaluation(waiting="waiting for map") if u.view is None
                  else frontier_evaluation(self.cfg, u))
            self._ev, self._t = ev, u.t
        return self._with_end_nodes(u, ev)

    def kept(self, u: Update) -> Evaluation | None:
        return None  # evaluate keeps its search itself (frontier_period)

    def _with_end_nodes(self, u: Update, ev: Evaluation) -> Evaluation:
        """ev with this update's end node counts for the status (informational only)."""
        if u.graph is None or ev.waiting is not None:
            return ev
        ends = [n.id for n in u.graph.nodes if n.kind == "end"]
        reliable = 0
        if u.beliefs is not None:
            pm = {b.id: b.p for b in u.beliefs}
            reliable = sum(1 for i in ends if pm.get(i, 0.0) >= self.cfg.p_reliable)
        return dataclasses.replace(ev, end_nodes=len(ends), reliable=reliable)

    def snapshot(self) -> dict[str, Any]:
        return {"frontier_search_t": self._t if math.isfinite(self._t) else None}
