"""The decision machine's parts: the target being followed, what to do with it after an
update (:class:`Decision`), and the blacklist of given-up targets. Strategy-agnostic."""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

import numpy as np

from topoexplore.common.checkpoint import CheckpointError, checked
from topoexplore.services.planner.strategies.base import Candidate

REMAINING_WINDOW = 1.5  # [m] the robot is located on the path within this arc ahead of it
FACE_MIN_DISTANCE = 0.05  # [m] a point to face closer than this to the path end sets no heading


class Action(enum.Enum):
    """What happens to the current target in one update."""

    KEEP = "keep"  # follow the path on
    DROP = "drop"  # the target was blacklisted: choose another
    RETRY = "retry"  # a failure short of blacklisting: choose again, with a new path
    REPATH = "repath"  # a new path to the same target
    CROSS = "cross"  # a new path to the same target: the old one crosses a wall seen since
    SWITCH = "switch"  # another target is much cheaper


@dataclass(frozen=True)
class Decision:
    action: Action
    note: str = ""  # for the status reason ("" = nothing to say)
    progress_t: float | None = None  # REPATH / CROSS: the time of last progress to keep [s]
    switch_to: Candidate | None = None  # SWITCH: the new target

    @classmethod
    def keep(cls) -> Decision:
        return cls(Action.KEEP)

    @classmethod
    def repath(cls, progress_t: float, note: str, cross: bool = False) -> Decision:
        return cls(Action.CROSS if cross else Action.REPATH, note, progress_t)


@dataclass(eq=False)
class Target:
    """The candidate being followed and the path made to it."""

    cand: Candidate
    plan_x: float  # [m] target position when the path was made
    plan_y: float
    wps: np.ndarray  # (n, 2) waypoints [m]
    cum: np.ndarray  # (n,) arc length along wps [m]
    idx: int  # segment of wps the robot is on
    best_rem: float  # [m] least remaining path length seen since the last progress
    progress_t: float  # [s] time of the last progress
    arrived_t: float | None  # [s] since when the robot stands within goal_tolerance
    chosen_t: float  # [s]
    why: str
    partial: bool = False  # the path was cut at a narrow passage (Candidate.partial when made)
    crossings: int = 0  # new paths made because the path crossed an obstacle seen since
    unreachable_since: float | None = None  # [s] kept while its reachability flickers
    planned_clearance: np.ndarray | None = None  # (n,) [m] of wps on the map it was made on

    def moved(self) -> float:
        """[m] how far the target is from where it was when the path was made."""
        return math.hypot(self.cand.x - self.plan_x, self.cand.y - self.plan_y)

    def remaining(self, x: float, y: float) -> float:
        """Remaining path length [m] from the robot at (x, y); moves idx to the segment the
        robot is on (searched within REMAINING_WINDOW ahead)."""
        w, cum = self.wps, self.cum
        if len(w) < 2:
            return math.hypot(w[-1, 0] - x, w[-1, 1] - y)
        hi = int(np.searchsorted(cum, cum[self.idx] + REMAINING_WINDOW, side="right"))
        hi = min(len(w) - 1, max(hi, self.idx + 1))
        p0, p1 = w[self.idx:hi], w[self.idx + 1:hi + 1]
        d = p1 - p0
        dd = np.einsum("ij,ij->i", d, d)
        q = np.array([x, y])
        s = np.clip(np.einsum("ij,ij->i", q - p0, d) / np.where(dd > 0, dd, 1.0), 0.0, 1.0)
        near = p0 + s[:, None] * d
        lat = np.hypot(near[:, 0] - x, near[:, 1] - y)
        k = int(np.argmin(lat))
        self.idx += k
        j = self.idx
        arc = cum[j] + s[k] * (cum[j + 1] - cum[j])
        return float(lat[k] + cum[-1] - arc)

    def goal_heading(self) -> float | None:
        """[rad] the heading that faces the candidate's point to face from the path end."""
        face = self.cand.face
        if face is None:
            return None
        ex, ey = self.wps[-1]
        if math.hypot(face[0] - ex, face[1] - ey) <= FACE_MIN_DISTANCE:
            return None
        return math.atan2(face[1] - ey, face[0] - ex)


REASON_CHARS = 200  # a blacklist reason kept in a checkpoint is cut to this length
MAX_MARKS = 100_000  # a checkpoint with more blacklist marks is not ours


@dataclass
class Mark:
    """A blacklisted target or a failure count, by id and position."""

    id: int
    x: float
    y: float
    count: int = 0
    reason: str = ""
    t: float = 0.0


class Blacklist:
    """Targets given up (by id, and by position within radius: ids change as the map grows)
    and the failures counted toward that."""

    def __init__(self, radius: float):
        self.radius = radius
        self.marks: list[Mark] = []
        self.failures: list[Mark] = []

    def __bool__(self) -> bool:
        return bool(self.marks)

    def ids(self) -> tuple[int, ...]:
        return tuple(b.id for b in self.marks)

    def covers(self, c: Candidate) -> bool:
        r2 = self.radius ** 2
        for b in self.marks:
            if c.id >= 0 and b.id == c.id:
                return True
            if (b.x - c.x) ** 2 + (b.y - c.y) ** 2 <= r2:
                return True
        return False

    def add(self, c: Candidate, t: float, reason: str) -> str:
        """Blacklist c (a frontier goal gets the next free number as its id); the note."""
        bid = c.id if c.id >= 0 else len(self.marks)
        self.marks.append(Mark(bid, c.x, c.y, reason=reason, t=t))
        return f"blacklisted {c.label}: {reason}"

    def checkpoint(self) -> dict[str, np.ndarray]:
        out = {}
        for name, marks in (("blacklist", self.marks), ("failures", self.failures)):
            out[f"{name}_num"] = np.array([[b.x, b.y, b.t] for b in marks],
                                          np.float64).reshape(len(marks), 3)
            out[f"{name}_int"] = np.array([[b.id, b.count] for b in marks],
                                          np.int64).reshape(len(marks), 2)
            out[f"{name}_why"] = np.array([b.reason[:REASON_CHARS] for b in marks], f"<U{REASON_CHARS}")
        return out

    def restore(self, arrays: dict[str, np.ndarray]) -> None:
        for name in ("blacklist", "failures"):
            num = checked(arrays, f"{name}_num", "f", (None, 3))
            n = len(num)
            ints = checked(arrays, f"{name}_int", "i", (n, 2))
            why = checked(arrays, f"{name}_why", "U", (n,))
            if not np.isfinite(num).all() or n > MAX_MARKS:
                raise CheckpointError(f"planner checkpoint: {name} out of range")
            marks = [Mark(int(i[0]), float(v[0]), float(v[1]), count=int(i[1]), reason=str(r),
                          t=float(v[2])) for v, i, r in zip(num, ints, why, strict=True)]
            if name == "blacklist":
                self.marks = marks
            else:
                self.failures = marks

    def count_failure(self, c: Candidate) -> int:
        """One more failure of c; the number so far."""
        r2 = self.radius ** 2
        for a in self.failures:
            if (c.id >= 0 and a.id == c.id) or (a.x - c.x) ** 2 + (a.y - c.y) ** 2 <= r2:
                a.count += 1
                a.x, a.y = c.x, c.y
                return a.count
        self.failures.append(Mark(c.id, c.x, c.y, count=1))
        return 1
