"""The domain types that the cores take and return (pure data, no I/O, no wire format).

Cores never see a wire message: :mod:`topoexplore.common.convert` turns each message into one
of these types and back (symmetric pairs, each round-trip tested), and the in-process runner
passes them from core to core directly. Arrays are numpy, lengths in metres, angles in radians
(REP-103: x forward, y left, counter-clockwise).

Everything that crosses the bus was validated when it was decoded
(:func:`topoexplore.common.messages.decode`), so these types check only what is cheap and
structural: a :class:`GridMap` checks its array against its geometry (the one grid check,
:func:`topoexplore.common.grid.check_grid`).
"""

from __future__ import annotations

import enum
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from topoexplore.common.grid import GridError, GridGeometry, check_grid, crop_known

__all__ = [
    "Pose",
    "Odom",
    "Command",
    "Scan",
    "GridMap",
    "NODE_KINDS",
    "Node",
    "Edge",
    "Graph",
    "Belief",
    "ExploreState",
    "Route",
    "Status",
    "Plan",
]


class Pose(NamedTuple):
    """Robot pose in the map frame (a tuple (x, y, theta) wherever one is expected)."""

    x: float  # [m]
    y: float  # [m]
    theta: float  # [rad]


class Odom(NamedTuple):
    """Odometry: the pose and the measured velocity along the heading."""

    pose: Pose
    v: float = 0.0  # [m/s]
    w: float = 0.0  # [rad/s]


class Command(NamedTuple):
    """A velocity command (cmd_vel) and the controller mode that produced it."""

    v: float  # [m/s]
    w: float  # [rad/s]
    mode: str = ""


@dataclass(frozen=True, eq=False)
class Scan:
    """One 2-D laser scan in the laser frame: beam i points at angle_min + i * angle_increment.

    Ranges as REP-117 reads them: a value in [range_min, range_max) is a return; +Inf, or a
    value >= range_max, is no return within range_max (free space to range_max: our
    simulator and many drivers send range_max); -Inf is an object closer than range_min
    (the mapper cannot place it, the controller's safety stop takes it as an obstacle at the
    laser); NaN, and a finite value below range_min, is no valid reading (discarded)."""

    ranges: np.ndarray  # float64 (n,) [m]
    angle_min: float  # [rad]
    angle_increment: float  # [rad]
    range_min: float  # [m]
    range_max: float  # [m]

    @property
    def beams(self) -> int:
        return int(self.ranges.shape[0])

    def angles(self) -> np.ndarray:
        """Beam angles [rad] in the laser frame."""
        return self.angle_min + self.angle_increment * np.arange(self.beams)

    def returns(self) -> tuple[np.ndarray, np.ndarray]:
        """(ranges [m], angles [rad]) of the beams that saw something: the returns in
        [range_min, range_max), and the too-close readings (-Inf) at range_min."""
        r = np.asarray(self.ranges, dtype=np.float64)
        a = self.angles()
        close = np.isneginf(r)
        ok = ((r >= self.range_min) & (r < self.range_max)) | close
        return np.where(close, self.range_min, r)[ok], a[ok]


def wrap_angle(a: float) -> float:
    """Angle [rad] -> (-pi, pi]."""
    return math.atan2(math.sin(a), math.cos(a))


def compose(a: Pose, b: Pose) -> Pose:
    """a ∘ b: the pose b given in a's frame, in the frame a is given in (e.g. the map ->
    odom correction composed with an odometry pose gives the pose on the map)."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return Pose(a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1],
                math.remainder(a[2] + b[2], 2 * math.pi))


def inverse(a: Pose) -> Pose:
    """The pose ``a⁻¹`` with ``compose(a, inverse(a))`` the identity."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return Pose(-c * a[0] - s * a[1], s * a[0] - c * a[1], math.remainder(-a[2], 2 * math.pi))


@dataclass(frozen=True, eq=False)
class GridMap:
    """An occupancy grid: int8 (height, width), row = y, ROS values (-1 unknown, 0..100)."""

    data: np.ndarray
    geom: GridGeometry

    def __post_init__(self) -> None:
        if check_grid(self.data, self.geom).dtype != np.int8:
            raise GridError(f"a GridMap holds int8 cells (got {np.asarray(self.data).dtype})")

    def crop_known(self, margin: int = 1) -> GridMap:
        """The part holding every observed cell plus a ring of unknown (a view; same answers
        for distances, frontiers and paths: :func:`topoexplore.common.grid.crop_known`)."""
        data, geom = crop_known(self.data, self.geom, margin)
        return self if data is self.data else GridMap(data, geom)


NODE_KINDS = ("end", "branch", "corner")


class Node(NamedTuple):
    id: int
    kind: str  # "end" | "branch" | "corner"
    x: float  # [m]
    y: float  # [m]


class Edge(NamedTuple):
    a: int  # node id
    b: int  # node id
    points: np.ndarray  # (n, 2) polyline [m] from a to b (a view into Graph.points)
    length: float  # [m]
    clearance: float  # [m] least distance to a non-free cell along the edge


@dataclass(frozen=True, eq=False)
class Graph:
    """A thinning-based topological map: nodes, edges with their polylines, and the ids that
    vanished since the previous update. Every polyline point is also in one flat array
    (``points``; edge k is ``points[offsets[k]:offsets[k + 1]]``) for vectorised use."""

    nodes: tuple[Node, ...]
    edges: tuple[Edge, ...]
    points: np.ndarray  # float64 (P, 2) [m]
    offsets: np.ndarray  # int64 (len(edges) + 1,)
    gone: tuple[int, ...] = ()

    @classmethod
    def build(cls, nodes: Iterable[Node], ab: Sequence[tuple[int, int]], points: np.ndarray,
              offsets: Sequence[int], lengths: Sequence[float], clearances: Sequence[float],
              gone: Iterable[int] = ()) -> Graph:
        """A graph from flat edge arrays: edge k joins ab[k] along points[offsets[k]:
        offsets[k + 1]]."""
        pts = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 2)
        off = np.asarray(offsets, dtype=np.int64)
        o = off.tolist()
        edges = tuple(Edge(int(a), int(b), pts[o[k]:o[k + 1]], float(ln), float(cl))
                      for k, ((a, b), ln, cl) in enumerate(zip(ab, lengths, clearances,
                                                                strict=True)))
        return cls(tuple(nodes), edges, pts, off, tuple(int(i) for i in gone))

    @classmethod
    def from_edges(cls, nodes: Iterable[Node], edges: Iterable[tuple], gone: Iterable[int] = ()
                   ) -> Graph:
        """A graph from (a, b, points, length, clearance) tuples (tests, hand-made graphs)."""
        edges = list(edges)
        pts = [np.asarray(e[2], dtype=np.float64).reshape(-1, 2) for e in edges]
        off = np.concatenate([[0], np.cumsum([len(p) for p in pts])]).astype(np.int64)
        flat = np.concatenate(pts) if pts else np.zeros((0, 2))
        return cls.build(nodes, [(e[0], e[1]) for e in edges], flat, off,
                         [e[3] for e in edges], [e[4] for e in edges], gone)

    @classmethod
    def empty(cls, gone: Iterable[int] = ()) -> Graph:
        return cls((), (), np.zeros((0, 2)), np.zeros(1, np.int64), tuple(gone))

    def end_nodes(self) -> list[Node]:
        return [n for n in self.nodes if n.kind == "end"]

    def edge_labels(self) -> np.ndarray:
        """The edge index of every point of ``points``."""
        return np.repeat(np.arange(len(self.edges)), np.diff(self.offsets))


@dataclass(frozen=True)
class Belief:
    """What the reliability core knows of one end node (paper eqs. 1-10)."""

    id: int
    x: float  # [m]
    y: float  # [m]
    p: float  # position probability P (eq. 6)
    d: float  # distance index D (eq. 1)
    a: float  # angle index A (eq. 4)
    r_min: float  # [m] minimum observed distance (eq. 2), inf if never observed
    alpha_max: float  # [rad] circular spread of observation bearings (eq. 3)
    visible: bool  # observed in this update
    n_obs: int = 0  # observations since the history (re)started
    visited: bool = False  # the robot came within the visit radius
    frontier: int = 0  # frontier cells the node's leaf chain owns (observations don't count;
    # as last worked out: only on updates where an observation could count)


class ExploreState(enum.StrEnum):
    IDLE = "idle"
    EXPLORING = "exploring"
    DONE = "done"
    FAILED = "failed"
    STUCK = "stuck"  # the robot cannot get anywhere from here: recovering (not finished)


@dataclass(frozen=True, eq=False)
class Route:
    """The path the controller follows (empty = stop) and what it leads to."""

    waypoints: np.ndarray  # float64 (n, 2) [m]
    plan_id: int = 0  # changes only when the path is replaced
    target_id: int = -1  # end node id, -1 for none or a frontier goal
    target_xy: tuple[float, float] = (0.0, 0.0)  # [m]
    strategy: str = ""
    goal_heading: float | None = None  # [rad] face this way at the end of the path

    def __post_init__(self) -> None:
        w = np.asarray(self.waypoints, dtype=np.float64).reshape(-1, 2)
        object.__setattr__(self, "waypoints", w)


@dataclass(frozen=True)
class Status:
    """What the planner says about the exploration (explore/status)."""

    state: ExploreState
    reason: str = ""
    strategy: str = ""
    target_id: int = -1
    target_p: float = 0.0
    candidates: int = 0
    end_nodes: int = 0
    reliable: int = 0
    blacklisted: tuple[int, ...] = ()
    replans: int = 0

    @property
    def finished(self) -> bool:
        return self.state in (ExploreState.DONE, ExploreState.FAILED)


@dataclass(frozen=True, eq=False)
class Plan:
    """One planning step's result: the route to follow and the status to report."""

    route: Route
    status: Status

    @property
    def state(self) -> ExploreState:
        return self.status.state
