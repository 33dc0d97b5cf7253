"""Planner core: choose the next target and the path to it (pure: no bus, no clock, no I/O).

A strategy (``strategies/``, chosen by ``planner.strategy``) evaluates each update: the
candidates, each with a cost and a path, or why there is none. The decision machine here is
the same for every strategy:

- target choice: the least cost; costs within ``tie_tolerance`` tie, and then the candidate
  ahead of the robot wins (paper Fig. 10a);
- re-plan rules: the target is resolved (reliable / visited / vanished / cleared) -> choose
  again; the target moved >= target_move from where the path was made, or the rest of the path
  left the map (``Evaluation.path_ok``) or crosses a wall seen since (``path_clear``) -> a new
  path to the same target; at most every replan_period s, switch to another target only if its
  cost < switch_ratio * the current target's (hysteresis against oscillating between two
  targets), and a path shorter by that ratio replaces the current one;
- bounded effort: no progress_distance of progress along the path for progress_timeout s (a
  target that moves counts as progress: it is revealing new space) is one failure; after
  max_attempts failures, or when the robot stands at the target for arrival_timeout s and it is
  still unresolved, the target is blacklisted by id and by position (blacklist_radius) and
  reported in ``blacklisted`` and ``reason``;
- "done" needs done_confirm updates in a row without a candidate, and is withheld while
  learned blockages (:mod:`.blockage`) could be what leaves nothing reachable: unconfirmed
  ones are forgotten; confirmed ones that cut the robot off from its own trail are all
  dropped (at most RELEASE_LIMIT times a run; then the robot is "stuck", never "done");
- stuck: the robot cannot get to any traversable cell (or the watchdog's last step): the
  state is "stuck" (never "done"), the route asks the controller to turn on the spot to look
  around, and only stuck_timeout s later the state becomes "failed";
- the global progress watchdog (:mod:`.watchdog`): no new map information for watchdog_time
  s of driving escalates: nearest frontier -> blacklist what was tried -> stuck (or, if the
  robot still drives, blacklist again);
- a kept evaluation (keep_period > 0, off by default): on an update where none of the rules
  above that read other candidates or make a path is due, the strategy's last evaluation
  may serve (:meth:`PlannerCore._kept`, docs/design.md "A kept evaluation").
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from topoexplore.common.checkpoint import CheckpointError, checked
from topoexplore.common.domain import (
    Belief,
    ExploreState,
    Graph,
    GridMap,
    Plan,
    Pose,
    Route,
    Status,
)
from topoexplore.common.grid import GridGeometry, Occupancy
from topoexplore.common.params import PlannerParams, ReliabilityParams, RobotParams
from topoexplore.common.surfaces import Surfaces
from topoexplore.services.planner import graph as gr
from topoexplore.services.planner import gridsearch as gs
from topoexplore.services.planner import strategies
from topoexplore.services.planner.blockage import RELEASE_LIMIT, WAY_BACK, Blockages
from topoexplore.services.planner.decision import Action, Blacklist, Decision, Target
from topoexplore.services.planner.examined import Examined
from topoexplore.services.planner.mapview import MapView
from topoexplore.services.planner.strategies.base import (
    Candidate,
    Candidates,
    Config,
    Evaluation,
    Update,
    find,
    id_list,
)
from topoexplore.services.planner.strategies.frontier import (
    clearance_cap,
    nearest_frontier_evaluation,
    robot_reach,
    robot_search,
)
from topoexplore.services.planner.watchdog import Watchdog

# modules whose WARM kernels this core runs (common.warm)
WARM_MODULES = ("topoexplore.services.planner.gridsearch",)
ENTRY_SKIP = 0.05  # [m] an entry point this close to the robot is not a separate waypoint
MAX_CROSSING_REPLANS = 2  # new paths per target when its path crosses a wall seen later
NARROWED_TOLERANCE = 0.5  # [cells] a waypoint planned with the clearance the planner needs
#   may lose this much of it before the path is re-made


def angle_diff(a: float, b: float) -> float:
    """|a - b| wrapped to [0, pi] [rad]."""
    return abs((a - b + math.pi) % (2 * math.pi) - math.pi)


class PlannerCore:
    """Exploration planner; call :meth:`update` once per reliability / topo / map update."""

    def __init__(self, params: PlannerParams, robot: RobotParams | None = None,
                 p_reliable: float | None = None, occ: Occupancy | None = None):
        self.p = params
        self.occ = occ or Occupancy()
        robot = robot or RobotParams()
        self._cfg = Config(params, robot.radius,
                           ReliabilityParams().p_reliable if p_reliable is None else p_reliable,
                           robot.body_margin)  # shared with the watchdog's frontier search
        self.strategy = strategies.make(self._cfg)
        self._target: Target | None = None
        self._blacklist = Blacklist(params.blacklist_radius)
        self._plan_id = 0
        self._replans = 0
        self._no_cand = 0  # consecutive updates without a candidate
        self._stuck_n = 0  # consecutive updates in which the robot cannot get anywhere
        self._fail_since: float | None = None  # [s] since when the robot is stuck
        self._look: tuple[float, float, float] | None = None  # stuck: turn on the spot
        #   (x [m], y [m]) to the heading [rad]
        self._watchdog = Watchdog(params.watchdog_time, params.watchdog_area,
                                  params.watchdog_travel)
        mark_r = params.blocked_radius or robot.radius + robot.body_margin  # [m]
        self._blockages = Blockages(params.blocked_time, mark_r, robot.radius + mark_r,
                                    params.blocked_memory)
        self._examined = Examined(params.examine_range, params.examine_bearing,
                                  params.examine_angle, params.examine_views)
        self._looked = Examined(params.completion_openings, params.examine_bearing,
                                params.examine_angle, 1, name="looked")  # frontier cells
        #   looked into squarely from close: no opening for the completion rules
        self._surfaces = Surfaces(params.surface_views)
        self._clearance_keeper = gs.ClearanceKeeper(clearance_cap(self._cfg))
        self._last_t: float | None = None
        self._last_eval_t = -math.inf
        self._had_path = False
        self._last: Plan | None = None
        self._updates = 0
        self._kept_n = 0  # updates served by a kept evaluation (:meth:`_kept`)
        self._ncand = 0  # candidates at the last update that judged them all
        self._view: MapView | None = None  # this update's map view
        self._u: Update | None = None  # ... and the update the strategy evaluated
        self._walled: str | None = None  # walled in by marks after RELEASE_LIMIT releases
        self._narrowed_now = lambda: False  # ... under which the followed path narrowed
        self._near: tuple[Evaluation | None, float] = (None, -math.inf)  # the watchdog's
        #   nearest-frontier search and its time [s]

    # --- public ------------------------------------------------------------------------------

    def update(self, t: float, pose: Pose, graph: Graph | None,
               beliefs: Sequence[Belief] | None, grid: GridMap | None) -> Plan:
        """One planning step at time t [s] for the robot at pose (x [m], y [m], theta [rad]);
        beliefs None: no reliability message yet."""
        x, y, th = (float(v) for v in pose)
        self._updates += 1
        if self._last_t is not None and t < self._last_t:  # clock reset: restart the timers
            self._last_eval_t = -math.inf
            if self._target is not None:
                self._target.progress_t = t
                self._target.arrived_t = None
        self._last_t = t
        tg = self._target
        self._blockages.observe(t, x, y, th, tg is not None and tg.arrived_t is None)
        self._view = None if grid is None else MapView(grid, self.occ,
                                                        self._blockages.active(t),
                                                        self._closed,
                                                        self._looked.mask,
                                                        self._clearance_keeper)
        if self._view is not None:
            self._surfaces.observe(self._view.map_classes, self._view.geom)
            self._examined.observe(x, y, th, self._view.classes, self._view.geom)
            self._looked.observe(x, y, th, self._view.classes, self._view.geom)
        rem = None if tg is None else tg.remaining(x, y)  # [m] the robot located on its
        #   path: _narrowed judges what is ahead, the watchdog how near the target is
        self._narrowed_now = self._narrowed(tg)  # asked late: by then the evaluation may
        #   have made the whole map's clearance
        u = Update(t, x, y, th, graph, beliefs, self._view,
                   None if self._target is None else self._target.cand.detached(),
                   self._blacklist.covers,
                   fresh=self._narrowed_now,
                   planned_at=None if tg is None else (tg.plan_x, tg.plan_y))
        self._u = u
        ev = self._kept(u, tg)
        kept = ev is not None
        if kept:
            self._kept_n += 1
        else:
            ev = self.strategy.evaluate(u)
        if ev.waiting is not None:
            self._target = None
            self._no_cand = 0
            return self._emit(ExploreState.EXPLORING, ev.waiting, ev, 0)
        notes: list[str] = []
        ev = self._watch(u, ev, grid, notes, rem, kept)
        return self._decide(t, x, y, th, ev, notes)

    def _kept(self, u: Update, tg: Target | None) -> Evaluation | None:
        """The strategy's last evaluation for this update (:meth:`Strategy.kept`), when the
        decision can only be to follow the target on: no rule that reads the other
        candidates or makes a path is due. The replan timer, bounded effort and arrival
        rules, a target kept through a flicker and the watchdog's modes are judged here; the
        target moving, its path leaving the map or crossing a wall, and a narrowed path make
        the strategy or this check say no (a watchdog step on such an update evaluates
        again: :meth:`_watch`). docs/design.md, "A kept evaluation"."""
        p, t = self.p, u.t
        if (tg is None or p.keep_period <= 0 or self._watchdog.mode is not None
                or tg.unreachable_since is not None
                or not 0.0 <= t - self._last_eval_t < p.replan_period
                or t - tg.progress_t >= p.progress_timeout
                or (tg.arrived_t is not None and t - tg.arrived_t >= p.arrival_timeout)):
            return None
        ev = self.strategy.kept(u)
        if ev is None or not (ev.path_ok(tg.wps[tg.idx + 1:]) and ev.path_clear(tg.wps[tg.idx:])):
            return None
        return ev

    def _watch(self, u: Update, ev: Evaluation, grid: GridMap | None, notes: list[str],
               rem: float | None, kept: bool = False) -> Evaluation:
        """The global progress watchdog: act on an escalation step; in the nearest-frontier
        step the candidates are the nearest frontier groups (until new information). rem [m]:
        the remaining path to the target followed (None without one); kept: ev is a kept
        evaluation (:meth:`_kept`)."""
        area = 0.0
        if grid is not None:
            area = float(np.count_nonzero(grid.data != -1)) * grid.geom.resolution ** 2
        cur = None if self._target is None else self._target.cand
        step = self._watchdog.observe(u.t, area, ev.reliable, cur is not None, (u.x, u.y), cur,
                                      rem)
        if step is not None and kept:  # a step reads every candidate: evaluate them now
            ev = self.strategy.evaluate(u)
        if step is not None:
            what = self._watchdog.log[-1].why
            self._replans += 1
            if step == "blacklist":
                # every target tried since the last new information, the current one first
                tried = ([cur] if cur is not None else []) + self._watchdog.window
                given = []
                for c in tried:
                    if not self._blacklist.covers(c):
                        self._blacklist.add(c, u.t, f"watchdog: {what}")
                        given.append(c.label)
                self._watchdog.window.clear()
                if given:
                    notes.append(f"watchdog: {what}: blacklisted {len(given)} target(s) tried "
                                 f"meanwhile ({'; '.join(given[:3])}"
                                 + (", ..." if len(given) > 3 else "") + ")")
                self._target = None
                ev = ev.settled()
                ev.cands = [c for c in ev.cands if not self._blacklist.covers(c)]
            elif step == "nearest_frontier":
                notes.append(f"watchdog: {what}: to the nearest frontier")
                self._target = None
            elif step == "stuck":
                self._target = None
        mode = self._watchdog.mode
        if mode == "nearest_frontier" and u.view is not None:
            near = self._nearest(u)
            if near.cands:
                return dataclasses.replace(near, end_nodes=ev.end_nodes, reliable=ev.reliable)
        if mode == "stuck":
            why = (f"watchdog: nothing helped ({self._watchdog.log[-1].why})"
                   if self._watchdog.log else "watchdog: nothing helped")
            return dataclasses.replace(ev, cands=[], failed=why)
        return ev

    def _nearest(self, u: Update) -> Evaluation:
        """The watchdog's nearest-frontier search: kept while a target is followed, for
        frontier_period at most and while the map does not change under its path, as every
        other frontier search (a new escalation step clears the target, and with it the
        search)."""
        ev, made = self._near
        if (ev is None or u.target is None or u.target.id >= 0 or not ev.cands
                or not u.may_reuse(self.p.frontier_period, made)):
            ev = nearest_frontier_evaluation(self._cfg, u)
            self._near = (ev, u.t)
        return ev

    def checkpoint(self) -> dict[str, np.ndarray]:
        """The planner's memory of the exploration: the targets it gave up on (blacklist and
        failure counts), the learned blockages, the examined frontier cells, its counters and
        the watchdog's (escalations and their log, for report.json).
        The target, its path and the timers are not kept: a restarted planner chooses again
        from the next update."""
        return {**self._blacklist.checkpoint(), **self._blockages.checkpoint(),
                **self._examined.checkpoint(), **self._looked.checkpoint(),
                **self._surfaces.checkpoint(),
                **self._watchdog.checkpoint(),
                "planner_counts": np.array([self._plan_id, self._replans, self._updates],
                                           np.int64)}

    def restore(self, arrays: dict[str, np.ndarray]) -> None:
        """Take back :meth:`checkpoint`'s memory (CheckpointError if it does not fit)."""
        counts = checked(arrays, "planner_counts", "i", (3,))
        if (counts < 0).any():
            raise CheckpointError("planner checkpoint: counters out of range")
        self._blacklist.restore(arrays)
        self._blockages.restore(arrays)
        self._examined.restore(arrays)
        self._looked.restore(arrays)
        self._surfaces.restore(arrays)
        self._watchdog.restore(arrays)
        self._plan_id, self._replans, self._updates = (int(v) for v in counts)

    def snapshot(self) -> dict[str, Any]:
        """JSON-friendly state for the service's state queryable."""
        tg, st = self._target, (self._last.status if self._last else None)
        return {
            "strategy": self.p.strategy,
            "updates": self._updates,
            "kept_updates": self._kept_n,
            "t": self._last_t,
            "state": st.state.value if st else ExploreState.IDLE.value,
            "reason": st.reason if st else "",
            "plan_id": self._plan_id,
            "replans": self._replans,
            "target": None if tg is None else {
                "id": tg.cand.id, "x": tg.cand.x, "y": tg.cand.y, "p": tg.cand.p,
                "cost": tg.cand.cost, "path_length": tg.cand.dist,
                "waypoints": len(tg.wps), "segment": tg.idx,
                "best_remaining": tg.best_rem, "progress_t": tg.progress_t,
                "arrived_t": tg.arrived_t, "chosen_t": tg.chosen_t, "why": tg.why},
            "blacklist": [{"id": b.id, "x": b.x, "y": b.y, "reason": b.reason, "t": b.t}
                          for b in self._blacklist.marks],
            "failures": [{"id": a.id, "x": a.x, "y": a.y, "count": a.count}
                         for a in self._blacklist.failures],
            **self.strategy.snapshot(),
            "watchdog": self._watchdog.snapshot(),
            "blocked": self._blockages.snapshot(),
            "examined": self._examined.snapshot(),
            "looked_into": self._looked.snapshot()["examined"],
            **self._surfaces.snapshot(),
            "candidates": st.candidates if st else 0,
            "end_nodes": st.end_nodes if st else 0,
            "reliable": st.reliable if st else 0,
        }

    # --- target choice -----------------------------------------------------------------------

    def _same(self, a: Candidate, b: Candidate) -> bool:
        if a.id >= 0 or b.id >= 0:
            return a.id == b.id
        return a is b or (a.x == b.x and a.y == b.y)

    def _match(self, cur: Candidate, cands: list[Candidate]) -> Candidate | None:
        """The candidate that is the current target now: the same end node id, or for a
        frontier goal the group with a cell nearest to it (within frontier_match_radius)."""
        if cur.id >= 0:
            return find(cands, cur.id)
        best, best_d = None, self.p.frontier_match_radius
        for c in cands:
            cells = c.cells if c.cells is not None and len(c.cells) else np.array([[c.x, c.y]])
            d = float(np.sqrt(((cells[:, 0] - cur.x) ** 2 + (cells[:, 1] - cur.y) ** 2).min()))
            if d <= best_d:
                best, best_d = c, d
        return best

    def _choose(self, cands: list[Candidate], x: float, y: float, th: float
                ) -> tuple[Candidate, str]:
        best = min(cands, key=lambda c: c.cost)
        band = [c for c in cands if c.cost <= best.cost + self.p.tie_tolerance * c.scale + 1e-9]
        if len(band) == 1:
            return best, "least path cost"

        def off(c: Candidate) -> float:
            return angle_diff(math.atan2(c.y - y, c.x - x), th)

        pick = min(band, key=lambda c: (off(c), c.cost))
        if self._same(pick, best):
            return best, "least path cost"
        return pick, (f"ahead of the robot (cost within {self.p.tie_tolerance:g} m of the "
                      f"least)")

    def _new_path(self, c: Candidate, x: float, y: float) -> np.ndarray:
        dense = np.asarray(c.path(), dtype=np.float64).reshape(-1, 2)
        if len(dense) and math.hypot(dense[0, 0] - x, dense[0, 1] - y) < ENTRY_SKIP:
            dense = dense[1:]
        if len(dense) == 0:
            dense = np.array([[c.x, c.y]])
        rest = gr.thin_polyline(dense, self.p.waypoint_spacing) if len(dense) > 1 else dense
        return np.vstack([[x, y], rest])

    def _set_target(self, c: Candidate, t: float, x: float, y: float, why: str,
                    progress_t: float | None = None) -> None:
        """Follow c on a new path (a new plan id); progress_t given: the same target with its
        time of last progress and time chosen kept."""
        wps = self._new_path(c, x, y)
        wps.setflags(write=False)  # the route of every plan until the next path shares it
        cum = gr.polyline_lengths(wps)
        self._target = Target(c, c.x, c.y, wps, cum, 0, float(cum[-1]),
                              t if progress_t is None else progress_t, None,
                              t if progress_t is None or self._target is None
                              else self._target.chosen_t, why, c.partial,
                              planned_clearance=self._clearance(wps))
        self._plan_id += 1

    def _closed(self, geom: GridGeometry) -> np.ndarray | None:
        """The cells of geom that are no frontier cells whatever their neighbours: examined
        (:class:`.examined.Examined`) or surfaces (:class:`common.surfaces.Surfaces`); None:
        none."""
        a, b = self._examined.mask(geom), self._surfaces.mask(geom)
        return b if a is None else a if b is None else a | b

    def _clearance(self, wps: np.ndarray) -> np.ndarray | None:
        """Clearance [m] of the waypoints on this update's map (None: no map)."""
        return None if self._view is None else self._view.clearance_at(wps)

    def _narrowed(self, tg: Target | None) -> Callable[[], bool]:
        """Does the rest of the path now pass closer to an obstacle than it was planned to (a
        question asked when needed, once per update)? That is, has a waypoint planned with
        the clearance the planner needs (robot radius + clearance_margin) now more than
        NARROWED_TOLERANCE cells less? (A waypoint planned
        through a narrow passage is not judged: there a cell more or less of a ragged wall is
        the passage, and a new path would be no wider.)

        A path is made on the map of its moment; a wall seen later beside it (one side of a
        corridor first glimpsed from its end) can leave the path along that wall at the
        body's limit, while path_ok, which only asks for the skeleton or a free cell, keeps it.
        The controller then stops for the wall it grazes, and the mark it earns there closes
        the corridor (a house floor: "done" at coverage 0.40)."""
        view = self._view
        if tg is None or tg.planned_clearance is None or view is None \
                or tg.idx + 1 >= len(tg.wps):
            return lambda: False
        need = self._cfg.need
        wide = tg.planned_clearance[tg.idx + 1:] + 1e-6 >= need
        if not np.any(wide):
            return lambda: False
        pts, limit = tg.wps[tg.idx + 1:][wide], need - NARROWED_TOLERANCE * view.geom.resolution
        # the question, not its answer: asked only if needed, once; it holds the points and
        # this update's view, never the target (whose path would hold older updates)
        return functools.cache(lambda: bool(np.any(view.narrower_than(pts, limit))))

    # --- decision machine --------------------------------------------------------------------

    def _decide(self, t: float, x: float, y: float, th: float, ev: Evaluation,
                notes: list[str]) -> Plan:
        cands = ev.cands
        replanned = False
        if self._target is not None:
            cands, replanned = self._follow(t, x, y, th, ev, notes)
        if self._target is None and cands:
            best, why = self._choose(cands, x, y, th)
            if replanned:
                why = f"{why} (after dropping the previous target)"
            self._set_target(best, t, x, y, why)
            self._last_eval_t = t
        tg = self._target
        if tg is None:
            return self._no_target(t, x, y, th, ev, notes)
        self._no_cand = 0
        self._stuck_n = 0
        self._fail_since = None
        self._look = None
        self._walled = None
        c = tg.cand
        if not isinstance(cands, Candidates) or cands.settled():
            self._ncand = len(cands)  # else: the count when they were last all judged
        head = f"target {c.label}: {tg.why}; path {c.dist:.1f} m; {self._ncand} candidate(s)"
        if self._blacklist:
            notes.append(f"blacklisted: {id_list(self._blacklist.ids())}")
        return self._emit(ExploreState.EXPLORING, "; ".join([head] + notes), ev, self._ncand)

    def _follow(self, t: float, x: float, y: float, th: float, ev: Evaluation,
                notes: list[str]) -> tuple[list[Candidate], bool]:
        """Check the current target against this update's candidates and act on the decision.
        Returns the candidates left and whether the target was dropped."""
        tg = self._target
        cands = ev.cands
        c = self._match(tg.cand, cands)
        grace = c is None and self._grace(t, tg, ev)
        if grace:
            c = tg.cand
            notes.append(f"kept {c.label}: not reachable on this update's map but still open "
                         f"and its path still clear (for {t - tg.unreachable_since:.1f} s)")
        elif c is None:
            notes.append(f"previous target {tg.cand.label} {ev.status_of(tg.cand)}")
            self._target = None
            return cands, False
        else:
            tg.unreachable_since = None
        tg.cand = c
        d = self._step_target(t, x, y, th, tg, c, cands, ev)
        if d.note:
            notes.append(d.note)
        if d.action is Action.KEEP:
            return cands, False
        self._replans += 1
        if d.action is Action.RETRY and grace:  # no new path to it now: choose again
            self._target = None
            return cands, True
        if d.action is Action.DROP:
            self._target = None
            return [k for k in cands if not self._blacklist.covers(k)], True
        if d.action is Action.RETRY:
            best, why = self._choose(cands, x, y, th)
            self._set_target(best, t, x, y, why if not self._same(best, c) else tg.why)
        elif d.action is Action.SWITCH:
            new = d.switch_to
            self._set_target(new, t, x, y, f"switched from {c.label}: cost {new.cost:.1f} < "
                             f"{self.p.switch_ratio:g} x {c.cost:.1f}")
        else:  # REPATH / CROSS
            self._set_target(c, t, x, y, tg.why, progress_t=d.progress_t)
            self._target.crossings = tg.crossings + (d.action is Action.CROSS)
        return cands, False

    def _grace(self, t: float, tg: Target, ev: Evaluation) -> bool:
        """Commitment against flickering reachability: a target that is still open but not
        reachable on this update (a skeleton edge dipping under the clearance limit for a
        moment) is kept, on its old path, while that path still fits the map and crosses no
        wall, for at most progress_timeout s in a row."""
        if not ev.flickered(tg.cand):
            return False
        if tg.unreachable_since is None:
            tg.unreachable_since = t
        rest = tg.wps[tg.idx:]
        return (t - tg.unreachable_since < self.p.progress_timeout
                and ev.path_ok(rest[1:]) and ev.path_clear(rest))

    def _step_target(self, t: float, x: float, y: float, th: float, tg: Target, c: Candidate,
                     cands: list[Candidate], ev: Evaluation) -> Decision:
        """Progress, arrival, failure and re-plan checks for the current target c."""
        p = self.p
        moved = tg.moved() >= p.target_move
        rem = tg.remaining(x, y)
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
        failed = self._effort(t, tg, c)
        if failed is not None:
            return failed
        if c.partial != tg.partial:  # a new path is no progress: a passage whose width
            #   flickers about the limit must not hold off the effort rule
            return Decision.repath(tg.progress_t, f"{c.label}: " + (
                "a passage on the way became narrow: new path" if c.partial
                else "the way is wide now: new path"))
        if moved:
            return Decision.repath(t, f"target moved {tg.moved():.2f} m: new path")
        if not ev.path_ok(tg.wps[tg.idx + 1:]):
            return Decision.repath(tg.progress_t, "the path left the current map: new path")
        if tg.crossings < MAX_CROSSING_REPLANS and not ev.path_clear(tg.wps[tg.idx:]):
            # a wall seen after the path was made (a corridor side glimpsed through gaps): the
            # waypoints may still lie near the skeleton on its far side, so path_ok passes
            return Decision.repath(tg.progress_t, "the path crosses an obstacle seen since it "
                                   "was made: new path", cross=True)
        if self._narrowed_now():
            return Decision.repath(tg.progress_t, "the path passes closer to an obstacle seen "
                                   "since it was made: new path")
        if t - self._last_eval_t >= p.replan_period:
            self._last_eval_t = t
            return self._reconsider(tg, c, cands, rem, x, y, th)
        return Decision.keep()

    def _effort(self, t: float, tg: Target, c: Candidate) -> Decision | None:
        """Bounded effort: DROP (blacklisted) or RETRY once the target took too long."""
        p = self.p
        if tg.arrived_t is not None and t - tg.arrived_t >= p.arrival_timeout:
            return Decision(Action.DROP, self._blacklist.add(
                c, t, f"reached but still unresolved after {p.arrival_timeout:g} s"))
        if t - tg.progress_t >= p.progress_timeout:
            n = self._blacklist.count_failure(c)
            if n >= p.max_attempts:
                return Decision(Action.DROP, self._blacklist.add(
                    c, t, f"no progress for {p.progress_timeout:g} s, {n} attempt(s)"))
            return Decision(Action.RETRY, f"no progress toward {c.label} for "
                            f"{p.progress_timeout:g} s (attempt {n}/{p.max_attempts}): "
                            "re-planning")
        return None

    def _reconsider(self, tg: Target, c: Candidate, cands: list[Candidate], rem: float,
                    x: float, y: float, th: float) -> Decision:
        """The periodic re-evaluation: switch to a much cheaper target, or take a much
        shorter path to the same one."""
        p = self.p
        if not cands:  # kept through a flicker (_grace): nothing to compare it with
            return Decision.keep()
        best, _ = self._choose(cands, x, y, th)
        margin = (1 - p.switch_ratio) * c.scale * c.dist
        if not self._same(best, c) and best.cost < c.cost - margin:
            return Decision(Action.SWITCH, switch_to=best)
        if c.dist < p.switch_ratio * rem - 1e-9:
            return Decision.repath(tg.progress_t, f"shorter path to the target ({c.dist:.1f} m "
                                   f"< {p.switch_ratio:g} x {rem:.1f} m)")
        return Decision.keep()

    def _no_target(self, t: float, x: float, y: float, th: float, ev: Evaluation,
                   notes: list[str]) -> Plan:
        """Stop; report done only once the situation is confirmed (one odd topology update
        must not end the run); stuck (turning on the spot to look around) when the robot
        cannot get anywhere, failed only after stuck_timeout."""
        p = self.p
        ev = ev.settled()
        if ev.failed is None and self._walled is not None:
            ev = dataclasses.replace(ev, failed=self._walled)
        if ev.failed is not None:
            self._no_cand = 0
            self._stuck_n += 1
            if self._stuck_n < p.done_confirm and self._fail_since is None:
                return self._emit(ExploreState.EXPLORING, "; ".join(notes + [
                    f"confirming ({self._stuck_n}/{p.done_confirm}): {ev.failed}"]), ev, 0)
            if self._fail_since is None and self._walled is None:
                out = self._release(t, x, y, th, ev, notes, "stuck")
                if out is not None:
                    return out
            if self._fail_since is None:
                self._fail_since = t
                self._look = (x, y, th + math.pi)  # recovery: look the other way
                self._plan_id += 1
            waited = t - self._fail_since
            if waited >= p.stuck_timeout:
                self._look = None
                return self._emit(ExploreState.FAILED, "; ".join(notes + [
                    f"{ev.failed} (stuck for {waited:.0f} s)"]), ev, 0)
            return self._emit(ExploreState.STUCK, "; ".join(notes + [
                f"{ev.failed} (stuck for {waited:.1f} s: turning to look around; failed "
                f"after {p.stuck_timeout:g} s)"]), ev, 0)
        self._fail_since = None
        self._look = None
        self._stuck_n = 0
        self._no_cand += 1
        if self._no_cand >= p.done_confirm:
            n = self._blockages.forget(t)
            if n:  # nothing reachable only with the learned marks: without them, look again
                self._no_cand = 0
                return self._emit(ExploreState.EXPLORING, "; ".join(notes + [
                    f"done withheld: {n} learned blockage(s) forgotten, searching again "
                    f"({ev.done})"]), ev, 0)
            out = self._release(t, x, y, th, ev, notes, "done")
            if out is not None:
                return out
            return self._emit(ExploreState.DONE, "; ".join(notes + [ev.done]), ev, 0)
        return self._emit(ExploreState.EXPLORING, "; ".join(notes + [
            f"no candidate left, confirming ({self._no_cand}/{p.done_confirm}): {ev.done}"]),
            ev, 0)

    def _release(self, t: float, x: float, y: float, th: float, ev: Evaluation,
                 notes: list[str], what: str) -> Plan | None:
        """Before saying `what` ("done", "stuck"): when the learned blockages wall the robot
        in (:meth:`_walled_in`), drop them all and search again; after RELEASE_LIMIT times,
        the robot is stuck. None: they do not wall it in."""
        walled = self._walled_in(t, x, y)
        if walled is None:
            return None
        self._no_cand = self._stuck_n = 0
        if self._blockages.released >= RELEASE_LIMIT:
            self._walled = f"{walled}, after dropping every blockage {RELEASE_LIMIT} times"
            return self._no_target(t, x, y, th, ev, notes)
        n = self._blockages.release(t)
        return self._emit(ExploreState.EXPLORING, "; ".join(notes + [
            f"{what} withheld: {walled}; all {n} dropped "
            f"({self._blockages.released}/{RELEASE_LIMIT}), searching again"]), ev, 0)

    def _walled_in(self, t: float, x: float, y: float) -> str | None:
        """Why the learned blockages remembered at t [s] wall the robot at (x, y) [m] in:
        a point of its trail WAY_BACK away that it cannot reach with them and can without
        (the map alone does not cut it off). None: they do not (or no marks, no trail)."""
        u, bl = self._u, self._blockages
        if u is None or u.view is None or not u.view.blocked:
            return None
        back = bl.way_back(t, x, y, WAY_BACK, self._cfg.need)
        if back is None:
            return None
        row, col = u.view.geom.world_to_cell(*back)
        if not u.view.geom.inside(row, col):
            return None

        def reached(search) -> bool:
            return bool(np.isfinite(search.dist[row, col]))

        if reached(robot_reach(self._cfg, u)):
            return None
        if not reached(robot_search(self._cfg, dataclasses.replace(
                u, view=u.view.without_blocked()), True, True)):
            return None
        return (f"{len(u.view.blocked)} learned blockage(s) cut the robot off from where it "
                f"came from ({back[0]:.1f}, {back[1]:.1f})")

    def _emit(self, state: ExploreState, reason: str, ev: Evaluation, ncand: int) -> Plan:
        """The plan of this update: the path to the target, or a stop (a new plan id)."""
        tg = self._target
        if tg is None and self._look is not None:  # stuck: turn on the spot
            self._had_path = True
            lx, ly, heading = self._look
            route = Route(np.array([[lx, ly]]), self._plan_id, -1, (lx, ly), self.p.strategy,
                          heading)
            target_p = 0.0
        elif tg is None:
            if self._had_path:
                self._plan_id += 1  # the stop is a new plan
            self._had_path = False
            route = Route(np.zeros((0, 2)), self._plan_id, -1, (0.0, 0.0), self.p.strategy)
            target_p = 0.0
        else:
            self._had_path = True
            c = tg.cand
            route = Route(tg.wps, self._plan_id, c.id, (float(c.x), float(c.y)), self.p.strategy,
                          tg.goal_heading())
            target_p = float(c.p)
        status = Status(state, reason, self.p.strategy, route.target_id, target_p, ncand,
                        ev.end_nodes, ev.reliable, self._blacklist.ids(), self._replans)
        self._last = Plan(route, status)
        return self._last
