"""Learned obstacles: where the robot could not drive although the map let the planner route
it (pure: time comes in as an argument).

The map is a belief; a table leg seen from a few angles may stay below the occupied
threshold, a door may be mapped a cell wider than it is. The controller then stops ("blocked":
something in its corridor) on a path the planner finds fine, and every new target sends it the
same way. So the planner watches the robot: following a path (not yet arrived) yet neither
moving ``STILL_DISTANCE`` nor turning ``STILL_ANGLE`` for ``blocked_time`` s means the way ahead
is blocked. It then marks a disc of ``blocked_radius`` just ahead of the robot (at its radius
plus that, where the controller's front sector saw the obstacle) as occupied in every grid the
planner derives for ``blocked_memory`` s: searches and clearances route around it, paths
through it are re-planned, and the robot, facing it, turns to a way out.

The disc is as wide as the controller's corridor (robot.radius + robot.body_margin by
default): a smaller one left free cells beside it in a gap just wider than the body, and the
escape from a tight spot, which may use any free cell, routed the robot through the gap it had
just refused (a cluttered floor: 43 marks in one place, then "stuck", coverage 0.83).

A mark is a belief about a moment, not the map: "done" is not said while unconfirmed marks are
remembered (the planner forgets them and searches again, :meth:`forget`); a mark made again
where one was forgotten is confirmed and stays.

Confirmed marks can still be wrong in one way the robot can prove: they wall it in. It drove
to where it stands, so marks that cut it off from a point of its own trail (:meth:`way_back`)
contradict its motion (a box corner beside its heading, refused twice: reach 23 cells, "done"
at coverage 0.94 on a cluttered floor). The planner then drops every mark (:meth:`release`)
instead of saying "done".
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from topoexplore.common.checkpoint import CheckpointError, checked

STILL_DISTANCE = 0.05  # [m] moving less than this ...
STILL_ANGLE = 0.3  # [rad] ... and turning less than this counts as standing still
MARK_LIMIT = 200  # marks kept (the oldest go first)
TRAIL_STEP = 0.25  # [m] the trail keeps a point each time the robot has moved this far
TRAIL_POINTS = 64  # trail points kept (the oldest go first)
WAY_BACK = 1.0  # [m] the trail point the marks must not cut the robot off from is this far
RELEASE_LIMIT = 3  # times a run every mark is dropped; walled in again after that: stuck


@dataclass
class Mark:
    x: float  # [m]
    y: float  # [m]
    r: float  # [m]
    t: float  # [s] when it was made


@dataclass
class Blockages:
    """The marks and the motion watch. wait [s] = blocked_time, radius [m] = blocked_radius,
    ahead [m] = robot radius + blocked_radius, memory [s] = blocked_memory."""

    wait: float
    radius: float
    ahead: float
    memory: float
    marks: list[Mark] = field(default_factory=list)
    made: int = 0  # marks made so far
    forgotten: int = 0  # marks dropped before their time (:meth:`forget`, :meth:`release`)
    released: int = 0  # times every mark was dropped (:meth:`release`)
    trail: list[tuple[float, float]] = field(default_factory=list)  # (x, y) [m], oldest first
    _dropped: list[tuple[float, float, float]] = field(default_factory=list)  # where (x, y, r)
    _anchor: tuple[float, float, float, float] | None = None  # (t, x, y, theta)

    def observe(self, t: float, x: float, y: float, th: float, following: bool
                ) -> Mark | None:
        """One update of the robot at (x, y, th) at t [s]; following: it has a path to a
        target it has not reached. Returns the new mark, if one is made now."""
        tr = self.trail
        if not tr or math.hypot(x - tr[-1][0], y - tr[-1][1]) >= TRAIL_STEP:
            tr.append((x, y))
            del tr[:-TRAIL_POINTS]
        a = self._anchor
        if (not following or a is None or t < a[0]
                or math.hypot(x - a[1], y - a[2]) >= STILL_DISTANCE
                or abs((th - a[3] + math.pi) % (2 * math.pi) - math.pi) >= STILL_ANGLE):
            self._anchor = (t, x, y, th) if following else None
            return None
        if t - a[0] < self.wait:
            return None
        m = Mark(x + self.ahead * math.cos(th), y + self.ahead * math.sin(th), self.radius, t)
        self.marks.append(m)
        del self.marks[:-MARK_LIMIT]
        self.made += 1
        self._anchor = (t, x, y, th)  # another mark only after another wait
        return m

    def active(self, t: float) -> list[tuple[float, float, float]]:
        """(x, y, r) [m] of the marks still remembered at t [s]."""
        return [(m.x, m.y, m.r) for m in self.marks if 0.0 <= t - m.t < self.memory]

    def forget(self, t: float) -> int:
        """Drop the marks still remembered at t [s], except those confirmed: made again where
        a mark had been forgotten (within its radius), the controller refusing the same place
        twice. Returns the number dropped (0: every mark left is confirmed)."""
        keep, n = [], 0
        for m in self.marks:
            if 0.0 <= t - m.t < self.memory and not self._confirmed(m):
                self._dropped.append((m.x, m.y, m.r))
                n += 1
            else:
                keep.append(m)
        self.marks = keep
        del self._dropped[:-MARK_LIMIT]
        self.forgotten += n
        return n

    def release(self, t: float) -> int:
        """Drop every mark remembered at t [s], confirmed or not (they wall the robot in).
        Their places are remembered as forgotten, so a mark made there again is confirmed at
        once. Returns the number dropped."""
        now = [m for m in self.marks if 0.0 <= t - m.t < self.memory]
        self.marks = [m for m in self.marks if m not in now]
        self._dropped.extend((m.x, m.y, m.r) for m in now)
        del self._dropped[:-MARK_LIMIT]
        self.forgotten += len(now)
        self.released += 1
        return len(now)

    def way_back(self, t: float, x: float, y: float, back: float, clear: float
                 ) -> tuple[float, float] | None:
        """The latest point of the trail at least back [m] from the robot at (x, y) and more
        than clear [m] outside every mark remembered at t [s]: a place it came from, which
        the marks must not cut it off from. None: no such point (a short trail)."""
        marks = self.active(t)
        for px, py in reversed(self.trail):
            if math.hypot(px - x, py - y) >= back and all(
                    math.hypot(px - mx, py - my) > r + clear for mx, my, r in marks):
                return px, py
        return None

    def _confirmed(self, m: Mark) -> bool:
        return any(math.hypot(m.x - x, m.y - y) <= max(m.r, r) for x, y, r in self._dropped)

    def checkpoint(self) -> dict[str, np.ndarray]:
        return {"blocked_marks": np.array([[m.x, m.y, m.r, m.t] for m in self.marks],
                                          np.float64).reshape(len(self.marks), 4),
                "blocked_dropped": np.array(self._dropped, np.float64).reshape(
                    len(self._dropped), 3),
                "blocked_counts": np.array([self.made, self.forgotten, self.released],
                                           np.int64)}

    def restore(self, arrays: dict[str, np.ndarray]) -> None:
        marks = checked(arrays, "blocked_marks", "f", (None, 4))
        dropped = checked(arrays, "blocked_dropped", "f", (None, 3))
        counts = checked(arrays, "blocked_counts", "i", (None,))  # 2: before release()
        if not (np.isfinite(marks).all() and np.isfinite(dropped).all()) \
                or len(marks) > MARK_LIMIT or len(dropped) > MARK_LIMIT or (counts < 0).any() \
                or len(counts) not in (2, 3):
            raise CheckpointError("planner checkpoint: blockage marks out of range")
        self.marks = [Mark(*(float(v) for v in row)) for row in marks]
        self._dropped = [tuple(float(v) for v in row) for row in dropped]
        self.made, self.forgotten, self.released = (int(v) for v in [*counts, 0][:3])
        self._anchor = None
        self.trail = []

    def snapshot(self) -> dict:
        return {"made": self.made, "forgotten": self.forgotten, "released": self.released,
                "marks": [{"x": m.x, "y": m.y, "r": m.r, "t": m.t} for m in self.marks[-20:]]}
