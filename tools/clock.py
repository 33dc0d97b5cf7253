"""The robot's clock as the bus shows it, for tools that command the robot.

The simulator (and a driver, by the same contract) drops a ``cmd_vel`` stamped more than
``sim.cmd_max_age`` before its clock or after it (``sim.core.SimCore.command``). The controller
stamps each command with the scan it answers; ``keys pub`` and ``teleop`` stamp theirs with the
latest odometry stamp, which is the robot's time at most one odometry period ago.
"""

from __future__ import annotations

import threading

from topoexplore.common import messages as m
from topoexplore.common.bus import Bus
from topoexplore.common.keys import Keys


class RobotClock:
    """The stamp [s] of the robot's latest odometry (sim time in simulation), or None."""

    def __init__(self, bus: Bus, keys: Keys):
        self._stamp: float | None = None
        self._seen = threading.Event()
        bus.subscribe(keys.topic("odom"), m.Odometry, self._on_odom)

    def _on_odom(self, msg: m.Odometry, _key: str) -> None:
        self._stamp = msg.header.time
        self._seen.set()

    def now(self) -> float | None:
        return self._stamp

    def wait(self, timeout: float) -> float | None:
        """The clock, waiting up to ``timeout`` [s] for the first odometry."""
        self._seen.wait(timeout)
        return self._stamp
