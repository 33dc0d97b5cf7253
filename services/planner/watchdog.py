"""The global progress watchdog of the planner (pure: time comes in as an argument).

Per-target bounded effort (``progress_timeout``, ``max_attempts``) cannot see a livelock in
which every single target makes some progress yet the exploration as a whole learns nothing:
two targets taking turns as their reachability flickers, a frontier goal that keeps moving
along a wall the robot cannot pass, a narrow passage the controller refuses again and again.
The watchdog measures what exploration is for, new information: the known area of the map
grows by ``watchdog_area`` or an end node turns reliable. With neither for ``watchdog_time``
of driving (a target followed), it escalates, one step per further ``watchdog_time``:

1. ``nearest_frontier``: the targets from now on are the nearest reachable frontier groups
   (the explore_lite rule, path lengths over the grid through narrow passages too), whatever
   the strategy, and the robot commits to one: the least risky way to new information, and
   one that strategy-level flicker cannot defeat (an end node that is visited, then not, as
   the skeleton changes, while a frontier appears and vanishes with it: the robot turned
   between the two on the spot);
2. ``blacklist``: still nothing: every target followed since the last new information is
   blacklisted (by position, as a target given up after ``max_attempts``): targets taken in
   turn while nothing was learnt are all unproductive (a row of frontier specks at the holes
   of a shelf a SLAM map left ragged), and the nearest-frontier mode goes on without them;
3. ``stuck``: nothing helped and the robot hardly moved (less than ``min_travel`` in the
   last period): it cannot get anywhere. The planner reports the robot as stuck (never "done")
   and asks the controller to turn on the spot to look around; ``stuck_timeout`` later it
   fails. If it did move, this step is another blacklist step instead (and so on): the targets
   run out and the strategy's own rules end the run ("done", with the blacklist in the
   reason), or new information resets the level.

New information resets the level. Every step is counted and logged (:attr:`counts`,
:attr:`log`); the planner's state and ``report.json`` carry them.

A long trip is not a livelock. The first target taken after new information (or after an
escalation step) earns time while the robot gets nearer to it: each time its remaining path
is ``min_travel`` shorter than ever before, the period starts again (the level stays). Only
the first: a row of targets taken in turn, each approached and none informative, is what
the watchdog is for, and two targets taken in turn as their reachability flickers get no
nearer than before. Without this, a trip across a large floor to the last frontier (34 m at
the narrow-passage pace) ran out the period on the way, and the nearest-frontier step then
toured the floor's specks: 133 m of a 236 m run on a held-back house.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from topoexplore.common.checkpoint import CheckpointError, checked

LEVELS = ("nearest_frontier", "blacklist", "stuck")
LOG_LIMIT = 50  # escalation events kept in the log (the counts keep the totals)
WINDOW_LIMIT = 200  # targets remembered since the last new information
SAME_RADIUS = 0.25  # [m] a target this close to a remembered one is that one


def _same(a: Any, b: Any) -> bool:
    """The same target (a candidate: id, x [m], y [m]) seen in two updates."""
    return (a.id >= 0 and a.id == b.id) or math.hypot(a.x - b.x, a.y - b.y) <= SAME_RADIUS


@dataclass
class Event:
    t: float  # [s]
    level: str  # one of LEVELS
    why: str


@dataclass
class Watchdog:
    """Escalation state. ``period`` [s] = watchdog_time, ``min_area`` [m^2] = watchdog_area,
    ``min_travel`` [m] = watchdog_travel."""

    period: float
    min_area: float
    min_travel: float = 1.0
    level: int = 0  # 0: fine, k: LEVELS[k - 1] is in force
    info_t: float | None = None  # [s] time of the last new information
    area: float = 0.0  # [m^2] known area at that time
    reliable: int = 0  # reliable end nodes at that time
    counts: dict[str, int] = field(default_factory=lambda: {k: 0 for k in LEVELS})
    log: list[Event] = field(default_factory=list)
    travel: float = 0.0  # [m] driven since the last step or new information
    window: list[Any] = field(default_factory=list)  # targets followed since then
    approaches: int = 0  # periods started again by the first target's approach
    _xy: tuple[float, float] | None = None
    _first: Any = None  # the first target taken since new information or the last step ...
    _first_best: float = math.inf  # ... and its least remaining path so far [m]

    def observe(self, t: float, area: float, reliable: int, driving: bool,
                xy: tuple[float, float] | None = None, target: Any = None,
                remaining: float | None = None) -> str | None:
        """One planning update at t [s] with the map's known area [m^2] and the number of
        reliable end nodes; driving: a target is being followed; xy [m]: the robot's position;
        target: the one followed (remembered in :attr:`window` until new information);
        remaining [m]: its remaining path length. Returns the step to act on now, or None."""
        if xy is not None:
            if self._xy is not None:
                self.travel += math.hypot(xy[0] - self._xy[0], xy[1] - self._xy[1])
            self._xy = (float(xy[0]), float(xy[1]))
        if target is not None and not any(_same(target, w) for w in self.window):
            self.window.append(target)
            del self.window[:-WINDOW_LIMIT]
        if self.info_t is None or t < self.info_t:  # first update, or the clock was reset
            self._reset(t, area, reliable)
            return None
        if area >= self.area + self.min_area or reliable > self.reliable:
            self._reset(t, area, reliable)
            return None
        if not driving:  # standing still to confirm "done" or waiting: not a livelock
            self.info_t = t if self.level == 0 else self.info_t
            return None
        if self._approached(target, remaining):  # on a long trip to the first target
            self.info_t = t
            self.travel = 0.0
            return None
        if t - self.info_t < self.period or self.level >= len(LEVELS):
            return None
        why = (f"no new map information for {t - self.info_t:.0f} s of driving (known area "
               f"{area:.1f} m^2, {self.travel:.1f} m driven)")
        if LEVELS[self.level] == "stuck" and self.travel >= self.min_travel:
            name = "blacklist"  # it drives but learns nothing: give up what it tried, again
        else:
            self.level += 1
            name = LEVELS[self.level - 1]
        self.counts[name] += 1
        self.log.append(Event(t, name, why))
        del self.log[:-LOG_LIMIT]
        self.info_t = t  # the next step only after another period without information
        self.travel = 0.0
        self._first, self._first_best = None, math.inf
        return name

    def _approached(self, target: Any, remaining: float | None) -> bool:
        """Is the robot min_travel nearer than ever before to the first target taken since
        new information or the last step (remembering it if there is none yet)?"""
        if target is None or remaining is None or not math.isfinite(remaining):
            return False
        if self._first is None:
            self._first, self._first_best = target, remaining
            return False
        if not _same(target, self._first) or remaining > self._first_best - self.min_travel:
            return False
        self._first_best = remaining
        self.approaches += 1
        return True

    @property
    def mode(self) -> str | None:
        """The mode in force: "nearest_frontier" after the first step and the blacklist
        step, "stuck" after the last, None before the first."""
        if not self.level:
            return None
        return "stuck" if LEVELS[self.level - 1] == "stuck" else "nearest_frontier"

    def _reset(self, t: float, area: float, reliable: int) -> None:
        self.level = 0
        self.info_t, self.area, self.reliable = t, area, reliable
        self.travel = 0.0
        self.window.clear()
        self._first, self._first_best = None, math.inf

    def checkpoint(self) -> dict[str, np.ndarray]:
        """What report.json counts (escalations per level, approaches, the log), kept across
        a planner restart; the level in force and the timers start again."""
        return {"watchdog_counts": np.array([self.counts.get(k, 0) for k in LEVELS]
                                            + [self.approaches], np.int64),
                "watchdog_log_t": np.array([e.t for e in self.log], np.float64),
                "watchdog_log_level": np.array([e.level for e in self.log], "<U32"),
                "watchdog_log_why": np.array([e.why[:200] for e in self.log], "<U200")}

    def restore(self, arrays: dict[str, np.ndarray]) -> None:
        counts = checked(arrays, "watchdog_counts", "i", (len(LEVELS) + 1,))
        t = checked(arrays, "watchdog_log_t", "f", (None,))
        level = checked(arrays, "watchdog_log_level", "U", (len(t),))
        why = checked(arrays, "watchdog_log_why", "U", (len(t),))
        if (counts < 0).any() or not np.isfinite(t).all() \
                or not set(level.tolist()) <= set(LEVELS):
            raise CheckpointError("planner checkpoint: watchdog counts or log out of range")
        self.counts = {k: int(v) for k, v in zip(LEVELS, counts[:-1], strict=True)}
        self.approaches = int(counts[-1])
        self.log = [Event(float(a), str(b), str(c)) for a, b, c in zip(t, level, why, strict=True)]

    def snapshot(self) -> dict:
        return {"level": self.mode, "last_information_t": self.info_t,
                "counts": dict(self.counts), "approaches": self.approaches,
                "log": [{"t": e.t, "level": e.level, "why": e.why} for e in self.log]}
