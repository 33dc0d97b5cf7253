"""What a strategy takes and returns: one update's inputs, the candidates it finds, and the
protocol every strategy follows (``evaluate(update) -> Evaluation``).

A strategy says *where* the robot could go (candidates with a cost and a path) and why there is
nowhere to go; the decision machine in :mod:`..core` decides which candidate to follow and when
to give it up, the same way for every strategy.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any, Protocol

import numpy as np

from topoexplore.common.domain import Belief, Graph
from topoexplore.common.params import PlannerParams
from topoexplore.services.planner.mapview import MapView


@dataclass(frozen=True)
class Config:
    """The settings every strategy reads."""

    params: PlannerParams
    radius: float  # [m] robot radius
    p_reliable: float  # an end node with P at or above this is reliable
    body_margin: float = 0.05  # [m] robot.body_margin (the controller's corridor)

    @property
    def need(self) -> float:
        """[m] least clearance of a place the robot may use (robot radius + margin)."""
        return self.radius + self.params.clearance_margin

    def fit(self, resolution: float) -> float:
        """[m] least clearance (of the best point in a cell, :func:`gridsearch
        .best_clearance_map`) of a narrow passage the robot may still drive through, on a
        grid of this resolution [m]: the controller's corridor (robot.radius +
        robot.body_margin) less half a cell. A gap of k free cells has k / 2 cells of best
        clearance, the least its real half width can be (the walls' surfaces lie somewhere in
        the occupied cells beside it), and up to a cell more: at 0.1 m the limit is 0.2 m, so
        a gap of 4 free cells passes (a 0.6 m door with a cell of blur on each side, as a SLAM
        map often draws it: the body fits for sure, the controller's corridor very likely)
        and one of 3 does not. Optimistic by design: where the controller still refuses, the
        planner's bounded effort and watchdog give up on it."""
        return max(self.radius, self.radius + min(self.body_margin, self.params.clearance_margin)
                   - 0.5 * resolution)


@dataclass(eq=False)
class Candidate:
    """A place the robot could go next."""

    id: int  # end node id, -1 for a frontier group
    x: float  # [m]
    y: float  # [m]
    cost: float  # selection cost (topological: path length [m]; frontier: explore_lite cost)
    dist: float  # [m] path length robot -> target
    scale: float  # cost per metre of path (1 for topological strategies, potential_scale)
    p: float  # position probability (reliability strategy), else 0
    path: Callable[[], np.ndarray]  # dense polyline from the entry / start cell to the target
    cells: np.ndarray | None = None  # frontier: the group's cell centres (identity matching)
    label: str = ""
    partial: bool = False  # the path stops at a narrow passage before the target
    face: tuple[float, float] | None = None  # [m] point to face at the end of the path
    narrow: bool = False  # the path goes through a narrow passage (the frontier fallback)
    opening: bool = False  # a frontier group that counts only as an opening not yet looked
    #   into (completion_openings)
    around: bool = False  # an end node whose skeleton path is narrow somewhere, reached on
    #   the grid search's path around that stretch (its path is the grid path already)

    def detached(self) -> Candidate:
        """This candidate without its lazy path: what an :class:`Update` carries as the target
        followed so far. The path closure holds the search of the update that made it, with
        its map view and its Update, whose target holds the update before, and so on: kept
        in the next Update, every map view since the robot last had no target stayed alive
        (hundreds of MB in the planner on a 600-update office run)."""
        return replace(self, path=_path_not_kept)


def _path_not_kept() -> np.ndarray:
    raise RuntimeError("the target of an earlier update keeps no path (Candidate.detached)")


def _no_longer(c: Candidate) -> str:
    return "is no longer a candidate"


def _always(wps: np.ndarray) -> bool:
    return True


def _never(c: Candidate) -> bool:
    return False


@dataclass
class Evaluation:
    """What one strategy sees in one update."""

    waiting: str | None = None  # an input is missing: stop and say what for
    failed: str | None = None  # the robot cannot plan at all (confirmed by the core)
    cands: list[Candidate] = field(default_factory=list)
    end_nodes: int = 0
    reliable: int = 0
    done: str = ""  # summary when no candidate is left
    unreachable: int = 0  # places (frontier groups) that would count but cannot be reached
    status_of: Callable[[Candidate], str] = _no_longer  # why a target is no candidate now
    path_ok: Callable[[np.ndarray], bool] = _always  # the rest of a path still fits the map
    path_clear: Callable[[np.ndarray], bool] = _always  # no segment crosses a wall
    flickered: Callable[[Candidate], bool] = _never  # still open, only not reachable now


@dataclass(frozen=True, eq=False)
class Update:
    """One planning update: the inputs, the shared map view, and what the core follows."""

    t: float  # [s]
    x: float  # [m] robot pose
    y: float  # [m]
    theta: float  # [rad]
    graph: Graph | None
    beliefs: Sequence[Belief] | None  # None: no reliability message yet
    view: MapView | None  # None: no map yet
    target: Candidate | None  # the target followed since the previous update
    blacklisted: Callable[[Candidate], bool]
    fresh: Callable[[], bool] = lambda: False  # the map changed under the followed path: no
    #   cached search (asked only when a search could be reused: it may cost a transform)

    def may_reuse(self, period: float, made_t: float) -> bool:
        """A search made at made_t [s] may serve this update: a target is followed, the search
        is younger than period [s], and the map has not changed under its path."""
        return self.target is not None and 0.0 <= self.t - made_t < period and not self.fresh()


class Strategy(Protocol):
    """An exploration strategy: built from a :class:`Config`, asked once per update."""

    def evaluate(self, u: Update) -> Evaluation: ...

    def snapshot(self) -> dict[str, Any]: ...


def id_list(ids: Sequence[int], limit: int = 8) -> str:
    """Ids for a status text: sorted, at most `limit` of them."""
    s = ", ".join(str(i) for i in sorted(ids)[:limit])
    return s + (", ..." if len(ids) > limit else "")
