"""The run's monitor (tools/run.py): the report describes exactly the scan whose status ended
the run, fed by scripted messages (no bus)."""

from __future__ import annotations

import numpy as np

from topoexplore.common import convert
from topoexplore.common import messages as m
from topoexplore.common.domain import Route
from topoexplore.tools.run import Monitor


def plan(src: int, target: int) -> m.Path:
    route = Route(np.array([[0.0, 0.0], [1.0, 0.0]]), src, target, (1.0, float(target)))
    return convert.route_to_msg(route, m.header(src, 0.1 * src, "map", src))


def status(src: int, state: str) -> m.ExploreStatus:
    return m.ExploreStatus(header=m.header(src, 0.1 * src, "map", src), state=state)


def test_targets_after_the_end_are_not_counted():
    mon = Monitor()
    mon.on_plan(plan(1, 4))
    mon.on_status(status(1, "exploring"))
    mon.on_plan(plan(2, 7))
    mon.on_status(status(2, "done"))
    assert mon.event.is_set() and mon.end_seq == 2
    mon.on_plan(plan(3, 9))  # a later scan's plan, on its way when the run ended
    mon.on_status(status(3, "exploring"))
    assert mon.targets == [4, 7]
    assert mon.plan.target_id == 7 and mon.status.state == "done"
