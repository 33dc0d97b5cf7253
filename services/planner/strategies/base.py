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


class Later:
    """A candidate judged only when it is first asked for: judge() -> Candidate or None (not
    a candidate after all), run once. id: the end node it is about."""

    __slots__ = ("id", "_judge", "_result", "_judged")

    def __init__(self, i: int, judge: Callable[[], Candidate | None]):
        self.id = i
        self._judge = judge
        self._result: Candidate | None = None
        self._judged = False

    def value(self) -> Candidate | None:
        if not self._judged:
            self._result, self._judged = self._judge(), True
            self._judge = None  # its closure holds the update's map view
        return self._result


class Candidates(Sequence):
    """One update's candidates, some of which (:class:`Later`) are judged only when the list
    is read as a whole: between two re-evaluations the planner core follows one target and
    needs no other (docs/design.md, "Candidates judged when needed"). Iterating, len(),
    indexing and + judge every member, in its place and once, so the list reads as if all had
    been judged at once; bool() and find() judge none while a judged member answers.
    summary() -> the strategy's "done" text, every member judged."""

    def __init__(self, items: Sequence[Candidate | Later],
                 summary: Callable[[], str] | None = None):
        self._items = list(items)
        self._summary = summary

    def _all(self) -> list[Candidate]:
        if not self.settled():
            self._items = [c for c in (x.value() if isinstance(x, Later) else x
                                       for x in self._items) if c is not None]
        return self._items

    def settled(self) -> bool:
        """Is every member judged?"""
        return not any(isinstance(x, Later) for x in self._items)

    def judged(self) -> list[Candidate]:
        """The members judged so far (none is judged by asking)."""
        return [x for x in self._items if not isinstance(x, Later)]

    def find(self, i: int) -> Candidate | None:
        """The candidate for end node i (i >= 0), judging only a member about i."""
        for x in self._items:
            if x.id == i:
                c = x.value() if isinstance(x, Later) else x
                if c is not None:
                    return c
        return None

    def summary(self) -> str:
        self._all()
        return "" if self._summary is None else self._summary()

    def __bool__(self) -> bool:
        return any(not isinstance(x, Later) for x in self._items) or bool(self._all())

    def __len__(self) -> int:
        return len(self._all())

    def __getitem__(self, k):
        return self._all()[k]

    def __iter__(self):
        return iter(self._all())

    def __add__(self, other: Sequence[Candidate]) -> Candidates:
        """These members (judged later as well) followed by other's."""
        return Candidates(self._items + list(other), self._summary)

    def __repr__(self) -> str:
        return f"Candidates({self._items!r})"


def find(cands: Sequence[Candidate], i: int) -> Candidate | None:
    """The candidate for end node i (i >= 0) in cands; a :class:`Candidates` list judges
    nothing else."""
    if isinstance(cands, Candidates):
        return cands.find(i)
    return next((c for c in cands if c.id == i), None)


@dataclass
class Evaluation:
    """What one strategy sees in one update."""

    waiting: str | None = None  # an input is missing: stop and say what for
    failed: str | None = None  # the robot cannot plan at all (confirmed by the core)
    cands: list[Candidate] | Candidates = field(default_factory=list)  # Candidates: some
    #   judged when first read (:meth:`settled` before reading done)
    end_nodes: int = 0
    reliable: int = 0
    done: str = ""  # summary when no candidate is left
    unreachable: int = 0  # places (frontier groups) that would count but cannot be reached
    status_of: Callable[[Candidate], str] = _no_longer  # why a target is no candidate now
    path_ok: Callable[[np.ndarray], bool] = _always  # the rest of a path still fits the map
    path_clear: Callable[[np.ndarray], bool] = _always  # no segment crosses a wall
    flickered: Callable[[Candidate], bool] = _never  # still open, only not reachable now

    def settled(self) -> Evaluation:
        """This evaluation with every candidate judged, and its done text with them: self if
        they were judged when made (a plain list)."""
        if not isinstance(self.cands, Candidates):
            return self
        return replace(self, cands=list(self.cands), done=self.cands.summary())


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
    planned_at: tuple[float, float] | None = None  # [m] where the target was when its path
    #   was made (the core makes a new path once it has moved target_move from there)

    def may_reuse(self, period: float, made_t: float) -> bool:
        """A search made at made_t [s] may serve this update: a target is followed, the search
        is younger than period [s], and the map has not changed under its path."""
        return self.target is not None and 0.0 <= self.t - made_t < period and not self.fresh()


class Strategy(Protocol):
    """An exploration strategy: built from a :class:`Config`, asked once per update."""

    def evaluate(self, u: Update) -> Evaluation: ...

    def kept(self, u: Update) -> Evaluation | None:
        """The last evaluation, if it may serve u as well (the core asks only when none of
        its rules that read other candidates or make a path is due); None: evaluate."""
        ...

    def snapshot(self) -> dict[str, Any]: ...


def id_list(ids: Sequence[int], limit: int = 8) -> str:
    """Ids for a status text: sorted, at most `limit` of them."""
    s = ", ".join(str(i) for i in sorted(ids)[:limit])
    return s + (", ..." if len(ids) > limit else "")
