"""The completion rules of the topological strategies (DESIGN.md §4, docs/design.md
"Completion phase" and "Stop when the map is complete").

- Completion phase (``frontier_completion``): once no end node is left to visit, the frontier
  groups still on the map are the candidates, so that "done" means the map is complete and not
  only that every end node is reliable (an opening at the side of a room or a corridor that
  bends away may give no end node at all).
- Map complete (``stop_when_mapped``, reliability only): no frontier group is left by the same
  rules, so no trip can add to the map.

- Near the robot (``pickup_radius``, off by default): while end nodes are left, the groups
  these rules count within that path length join them as candidates (:meth:`Completion.nearby`),
  once a cell of the group has been a frontier cell for ``pickup_age``.

Only groups of at least ``completion_min_size`` count, or shorter ones (down to
``min_frontier_size``) whose path is at most ``completion_near``, and none next to an enclosed
unknown pocket smaller than ``completion_pocket_area``. With ``completion_openings`` > 0, a
shorter group farther away counts too when it may be a door seen only from afar (an opening,
:func:`.frontier.opening_mouth`, docs/design.md "Openings"): its goal is the nearest place to
look into it from, and it is the last trip (:func:`_openings_last`; for "the map is complete",
:meth:`Completion.openings`). Both searches run at most once per ``frontier_period``.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from topoexplore.services.planner.strategies.base import Config, Evaluation, Update
from topoexplore.services.planner.strategies.frontier import completion_rule, frontier_evaluation

COMPLETION_NOTE = " (completion: no end node left)"
NEAR_NOTE = " (near the robot: before it is left behind)"
OPENING_NOTE = " (the map is complete but for it)"


class Completion:
    """The completion phase and the map-complete check, with their caches."""

    def __init__(self, cfg: Config):
        self.cfg = cfg
        self._ev: Evaluation | None = None  # completion phase: the last search ...
        self._t = -math.inf  # ... and its time [s]
        self._mapped_t = -math.inf  # map-complete check: time [s] of the last check ...
        self._mapped_ok = False  # ... its answer ...
        self.why = ""  # ... and the frontier summary behind it
        self._openings: Evaluation | None = None  # ... and the openings it left
        self._near_ev: Evaluation | None = None  # frontier groups near the robot ...
        self._near_t = -math.inf  # ... searched at this time [s]
        self._first_seen: dict[tuple[int, int], float] = {}  # [s] by frontier cell (pickup)

    def phase(self, u: Update, ev: Evaluation) -> Evaluation:
        """The topological evaluation ev found no candidate: the frontier groups as
        candidates; if the robot cannot get to any traversable cell, that failure (stuck,
        never "done")."""
        cached = self._ev
        if (cached is not None and u.target is not None and u.target.id < 0 and cached.cands
                and u.may_reuse(self.cfg.params.frontier_period, self._t)):
            fe = cached  # following a completion target: keep the last search
        else:
            fe = _openings_last(self._search(u))
            for c in fe.cands:
                c.label = f"{c.label}{COMPLETION_NOTE}"
            self._ev, self._t = fe, u.t
        if fe.failed is not None:
            return dataclasses.replace(ev, failed=fe.failed)
        # this update's end node counts and summary, whether the search is new or kept; an
        # end node followed until now is worded by the end nodes' evaluation (it vanished or
        # was resolved: not "cleared", which is a frontier group's word)
        groups, nodes = fe.status_of, ev.status_of
        return dataclasses.replace(fe, end_nodes=ev.end_nodes, reliable=ev.reliable,
                                   done=f"{ev.done}; {fe.done}",
                                   status_of=lambda c: nodes(c) if c.id >= 0 else groups(c))

    def nearby(self, u: Update, radius: float) -> Evaluation | None:
        """The frontier groups the completion rules count whose path is at most radius [m]
        (cost = path length, as an end node's), or None without any. The search runs at most
        once per frontier_period while a target is followed."""
        if radius <= 0.0:
            return None
        if self._near_ev is None or not u.may_reuse(self.cfg.params.frontier_period,
                                                    self._near_t):
            fe = self._search(u)
            cands = []
            for c in self._aged(u, fe.cands):
                if c.dist <= radius and not c.narrow:
                    c.cost, c.scale = c.dist, 1.0
                    c.label += NEAR_NOTE
                    cands.append(c)
            self._near_ev, self._near_t = dataclasses.replace(fe, cands=cands), u.t
        return self._near_ev if self._near_ev.cands else None

    def _aged(self, u: Update, cands: list) -> list:
        """The groups with a cell that has been a frontier cell for pickup_age [s] or more
        (on the searches of :meth:`nearby`): the edge of the laser's reach of the moment is
        not a group left behind."""
        age = self.cfg.params.pickup_age
        res = u.view.geom.resolution
        seen: dict[tuple[int, int], float] = {}
        kept = []
        for c in cands:
            keys = [] if c.cells is None else [
                (int(a), int(b)) for a, b in np.round(np.asarray(c.cells) / res)]
            first = u.t
            for k in keys:
                seen[k] = self._first_seen.get(k, u.t)
                first = min(first, seen[k])
            if u.t - first >= age:
                kept.append(c)
        self._first_seen = seen
        return kept

    def mapped(self, u: Update) -> bool:
        """Is no frontier left by the completion rules, openings not yet looked into aside
        (:meth:`openings`)? First a cheap pass (a reachable group of completion_min_size or
        more, no path costs, means no); the full search (path lengths for the shorter groups
        within completion_near, the openings) only without one."""
        if 0.0 <= u.t - self._mapped_t < self.cfg.params.frontier_period:
            return self._mapped_ok
        self._mapped_t = u.t
        self._openings = None
        quick = self._search(u, quick=True)
        if quick.failed is None and quick.cands:
            self._mapped_ok = False
            return False
        fe = self._search(u)
        self._mapped_ok = fe.failed is None and all(c.opening for c in fe.cands)
        self.why = fe.done
        if self._mapped_ok and fe.cands:
            for c in fe.cands:
                c.label += OPENING_NOTE
            self._openings = fe
        return self._mapped_ok

    def openings(self, ev: Evaluation) -> Evaluation | None:
        """After :meth:`mapped` said yes: the openings not yet looked into that it left, as
        the candidates (as in the completion phase) instead of ev's end nodes, so
        that a door seen only from afar is looked into before "done" without a visit to
        every end node first; None without any."""
        fe = self._openings
        if fe is None or not fe.cands:
            return None
        groups, nodes = fe.status_of, ev.status_of
        return dataclasses.replace(fe, end_nodes=ev.end_nodes, reliable=ev.reliable,
                                   status_of=lambda c: nodes(c) if c.id >= 0 else groups(c))

    def _search(self, u: Update, quick: bool = False) -> Evaluation:
        """The frontier groups the completion rules count. quick: only the long groups, and
        only whether they are reachable."""
        p = self.cfg.params
        size, pocket, near = completion_rule(p)
        return frontier_evaluation(self.cfg, u, size, pocket, 0.0 if quick else near,
                                   reach_only=quick,
                                   openings=not quick and p.completion_openings > 0)


def _openings_last(fe: Evaluation) -> Evaluation:
    """fe without its openings (:attr:`Candidate.opening`) while it has other candidates: an
    opening seen only from afar is the last trip, since a robot passing by on the way to
    the others often looks into it (and then it is none)."""
    if any(c.opening for c in fe.cands) and not all(c.opening for c in fe.cands):
        fe.cands = [c for c in fe.cands if not c.opening]
    return fe
