"""The ``reliability`` strategy (the paper, §3.2): the open end nodes are those with position
probability P < p_reliable (eq. 6); done when none is left, or (``stop_when_mapped``, a
departure from the paper, docs/design.md) as soon as the completion rules find no frontier
left and no end node still below p_reliable has unexplored space beside it (``open_radius``)."""

from __future__ import annotations

import dataclasses

from topoexplore.services.planner.strategies.base import Evaluation, Update
from topoexplore.services.planner.strategies.topological import P_UNSEEN, Scene, Topological


class Reliability(Topological):
    needs_beliefs = True
    unresolved = "unreliable"

    def is_open(self, i: int, s: Scene) -> bool:
        return s.prob(i) < self.cfg.p_reliable

    def label(self, i: int, s: Scene) -> str:
        return f"end node {i} (P={s.prob(i):.2f})"

    def target_p(self, i: int, s: Scene) -> float:
        return s.prob(i)

    def all_done(self, n: int) -> str:
        return f"all {n} reachable end nodes reliable (P >= {self.cfg.p_reliable:g})"

    def resolved(self, i: int, s: Scene) -> str:
        return f"became reliable (P={s.prob(i):.2f})"

    def open_now(self, u: Update, i: int, x: float, y: float) -> bool:
        p = next((b.p for b in u.beliefs or () if b.id == i), P_UNSEEN)
        return float(p) < self.cfg.p_reliable

    def evaluate_all(self, u: Update) -> Evaluation:
        ev = self.evaluate_graph(u)
        if (self.cfg.params.stop_when_mapped and ev.cands and u.view is not None
                and self.completion.mapped(u)):
            r = self.cfg.params.open_radius
            beside = [c for c in ev.cands if self.beside_unknown(u, c.x, c.y, r)]
            if beside:  # the frontier rules miss it (fragmented by noise, short, narrow)
                return dataclasses.replace(ev, cands=beside)
            openings = self.completion.openings(ev)
            if openings is not None:  # a door seen only from afar: look before "done"
                return openings
            return Evaluation(end_nodes=ev.end_nodes, reliable=ev.reliable, done=(
                f"the map is complete ({self.completion.why}); {len(ev.cands)} end node(s) "
                f"below P {self.cfg.p_reliable:g} left unvisited, none beside unexplored "
                "space"))
        return self.complete(u, ev)
