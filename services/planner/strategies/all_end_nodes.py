"""The ``all-end-nodes`` strategy (Choset-style, the paper's foil): the open end nodes are
those the robot has not yet come within ``visit_radius`` of, whatever their P; the visit
track is kept here from the poses of every update."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from topoexplore.services.planner.strategies.base import Config, Update
from topoexplore.services.planner.strategies.topological import Scene, Topological

TRACK_STEP = 0.05  # [m] robot positions are recorded every this much travel


class AllEndNodes(Topological):
    unresolved = "unvisited"

    def __init__(self, cfg: Config):
        super().__init__(cfg)
        self._track = np.zeros((256, 2))  # robot positions every TRACK_STEP [m]
        self._n = 0

    def observe(self, u: Update) -> None:
        """Remember where the robot has been."""
        n = self._n
        if n:
            lx, ly = self._track[n - 1]
            if math.hypot(u.x - lx, u.y - ly) < TRACK_STEP:
                return
        if n == len(self._track):  # amortised doubling: O(1) per point over a long run
            self._track = np.concatenate([self._track, np.zeros_like(self._track)])
        self._track[n] = (u.x, u.y)
        self._n = n + 1

    def _visited(self, x: float, y: float) -> bool:
        a = self._track[:self._n]
        if len(a) == 0:
            return False
        d2 = (a[:, 0] - x) ** 2 + (a[:, 1] - y) ** 2
        return bool(d2.min() <= self.cfg.params.visit_radius ** 2 + 1e-12)

    def is_open(self, i: int, s: Scene) -> bool:
        return not self._visited(*s.index.nodes[i][1:])

    def open_now(self, u: Update, i: int, x: float, y: float) -> bool:
        return not self._visited(x, y)

    def all_done(self, n: int) -> str:
        return (f"all {n} reachable end nodes visited (within "
                f"{self.cfg.params.visit_radius:g} m)")

    def resolved(self, i: int, s: Scene) -> str:
        return "visited"

    def snapshot(self) -> dict[str, Any]:
        return {**super().snapshot(), "visited_positions": self._n}
