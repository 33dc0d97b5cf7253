"""The run's monitor (tools/run.py): the report describes exactly the scan whose status ended
the run, fed by scripted messages (no bus)."""

from __future__ import annotations

import numpy as np

from topoexplore.common import convert
from topoexplore.common import messages as m
from topoexplore.common.domain import GridMap, Route
from topoexplore.common.grid import GridGeometry
from topoexplore.tools.run import GRIDS_KEPT, Monitor


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


def sim_status(src: int) -> m.SimStatus:
    return m.SimStatus(header=m.header(src, 0.2 * src, "sim/status", src), world="w",
                       mode="lockstep", sim_time=0.2 * src, steps=src, collisions=0,
                       path_length=0.1 * src, real_time_factor=1.0)


def grid(src: int) -> m.OccupancyGrid:
    g = GridMap(np.zeros((4, 4), np.int8), GridGeometry(0.1, 0.0, 0.0, 4, 4))
    return convert.grid_to_msg(g, m.header(src, 0.2 * src, "map", src))


def test_the_report_waits_for_the_sim_status_and_map_of_the_ending_scan():
    """They come from other processes than the planner's status: read while still on their
    way, the report took the scan before the one that ended the run."""
    import threading

    mon = Monitor()
    mon.on_sim(sim_status(203))
    mon.on_map(grid(203))
    mon.on_status(status(204, "done"))
    assert not mon.settle(204, timeout=0.05)
    late = [threading.Timer(0.2, mon.on_sim, args=(sim_status(204),)),
            threading.Timer(0.3, mon.on_map, args=(grid(204),))]
    for t in late:
        t.start()
    try:
        assert mon.settle(204, timeout=5.0)
    finally:
        for t in late:
            t.join()
    assert mon.sim_by_seq[204].sim_time == 0.2 * 204 and mon.grid.header.src_seq == 204


def test_a_later_scans_map_that_came_before_the_ending_status_is_not_the_reports():
    """The map of the next map scan can overtake the planner's status that ended the run
    (other processes, other hops): same seed, coverage 0.9978 and 0.9979 on the bus. The
    report takes the ending scan's map."""
    mon = Monitor()
    for k in (200, 202, 204):
        mon.on_map(grid(k))
    mon.on_map(grid(206))  # the next one, before the status of 204 came
    mon.on_status(status(204, "done"))
    assert mon.settle(204, timeout=0.05) is False  # (no sim status of 204 here)
    mon.on_sim(sim_status(204))
    assert mon.settle(204, timeout=0.05)  # its own map came, and its sim status
    with mon.lock:
        assert mon.ending_grid(204).header.src_seq == 204
        assert mon.ending_grid(205).header.src_seq == 204  # not a map scan: the one before
        assert mon.ending_grid(100).header.src_seq == 206  # none kept: the latest
    fresh = Monitor()
    for k in range(0, 80, 2):
        fresh.on_map(grid(k))
        fresh.on_status(status(k - 7, "exploring"))  # the planner 3.5 maps behind
    # when map 78 came, the newest status was of scan 69: map 68 and the later ones
    assert sorted(fresh.grid_by_seq) == [68, 70, 72, 74, 76, 78]
    silent = Monitor()  # no status ever: the GRIDS_KEPT latest
    for k in range(0, 200, 2):
        silent.on_map(grid(k))
    assert sorted(silent.grid_by_seq) == list(range(200 - 2 * GRIDS_KEPT, 200, 2))


def test_the_ending_scans_map_stays_when_many_later_maps_overtake_its_status():
    """In lockstep the mapper runs plan_lag map periods ahead of the planner, and further
    while the monitor is busy: eight later maps before the ending status still leave the
    ending scan's map to the report (a fixed count of four once did not: same seed, coverage
    0.998 and 0.9979 on the bus)."""
    mon = Monitor()
    for k in range(190, 204, 2):
        mon.on_map(grid(k))
        mon.on_status(status(k - 1, "exploring"))
    for k in range(204, 222, 2):
        mon.on_map(grid(k))
    mon.on_sim(sim_status(204))
    mon.on_status(status(204, "done"))
    assert mon.settle(204, timeout=0.05)
    with mon.lock:
        mon.use_ending(204)
    assert mon.grid.header.src_seq == 204


def topo_msg(src: int) -> m.TopoGraph:
    return m.TopoGraph(header=m.header(src, 0.2 * src, "map", src), nodes=[], edges=[])


def rel_msg(src: int, ids: list[int], visited: list[int]) -> m.Reliability:
    nodes = [m.NodeReliability(id=i, x=0.0, y=0.0, p=0.5, d=0.5, a=0.0, r_min=1.0,
                               alpha_max=0.0, visible=False, visited=i in visited)
             for i in ids]
    return m.Reliability(header=m.header(src, 0.2 * src, "map", src), nodes=nodes)


def test_a_later_scans_topology_and_reliability_are_not_the_reports():
    """As the map: the topology and reliability messages of the next scan can overtake the
    status that ended the run; the report (topology.json, the picture, end nodes seen and
    visited) takes the ending scan's, and forgets the ids only the later one added."""
    mon = Monitor()
    for k in (200, 202, 204):
        mon.on_map(grid(k))
        mon.on_topo(topo_msg(k))
        mon.on_rel(rel_msg(k, [1, 2], [1]))
    mon.on_topo(topo_msg(206))  # the next scan's, before the status of 204 came
    mon.on_rel(rel_msg(206, [1, 2, 7], [1, 2]))
    mon.on_status(status(204, "done"))
    assert mon.seen_end_ids == {1, 2, 7} and mon.visited_ids == {1, 2}
    with mon.lock:
        mon.use_ending(204)
    assert mon.topo.header.src_seq == mon.rel.header.src_seq == mon.grid.header.src_seq == 204
    assert mon.seen_end_ids == {1, 2} and mon.visited_ids == {1}
    fresh = Monitor()
    for k in range(0, 40, 2):
        fresh.on_topo(topo_msg(k))
        fresh.on_rel(rel_msg(k, [k], []))
        fresh.on_status(status(k - 6, "exploring"))
    # when those of 38 came, the newest status was of scan 30
    assert sorted(fresh.topo_by_seq) == sorted(fresh.rel_by_seq) == [30, 32, 34, 36, 38]
    assert fresh.seen_end_ids == set(range(0, 40, 2))  # pruning the record keeps the ids


def test_the_reports_counters_are_read_from_each_services_state_once_fetched():
    """The end of a run fetches every service's state once (run.final_states) and reads the
    report's counters from those states; a service that did not answer is simply absent."""
    from topoexplore.tools import run

    states = {
        "mapper": {"bad_messages_total": 2, "lost": {"scan": 3, "odom": 0},
                   "checkpoint": {"path": "/s/mapper", "written": 5}},
        "planner": {"bad_messages_total": 1, "lost": {},
                    "core": {"watchdog": {"counts": {"blacklist": 1}, "log": ["x"],
                                          "approaches": 4},
                             "blocked": {"made": 2}, "replans": 7}},
        "reliability": {"nodes": {"updates": 9, "resets": 3, "dropped": 1,
                                  "nodes": {"1": {"resets": 2}, "2": {"resets": 0},
                                            "3": "not a node"}},
                        "checkpoint": {"path": ""}},
        "localizer": {"matched": 10, "kept": 2},
    }
    assert run.message_counts(states) == (3, {"mapper": {"scan": 3}})
    assert run.checkpoint_counts(states) == {"mapper": {"path": "/s/mapper", "written": 5}}
    assert run.reliability_counts(states["reliability"]) == {
        "updates": 9, "resets": 3, "nodes_reset": 1, "dropped": 1}
    assert run.reliability_counts({"nodes": None}) is None
    assert run.localizer_counts(states["localizer"]) == {
        "matched": 10, "kept": 2, "no_map": 0, "degenerate": 0}
    p = run.planner_robustness(states["planner"])
    assert p["watchdog_escalations"] == {"blacklist": 1} and p["watchdog_approaches"] == 4
    assert p["blocked_marks"] == 2 and p["blocked_forgotten"] == 0 and p["replans"] == 7
    assert run.message_counts({}) == (0, {}) and run.checkpoint_counts({}) == {}


def test_the_timeline_pairs_each_map_with_its_own_scans_travel():
    """A map is sampled with the sim status of its own scan, whichever came first: the newest
    status read may be a scan or more off (the bus delivers the two from different
    processes). A run in process pairs them the same way (tests/test_explore_e2e.py)."""
    mon = Monitor()
    mon.coverage_fn = lambda msg: float(msg.header.src_seq)  # which map was sampled
    mon.sample_every = 0.0  # every map
    mon.on_sim(sim_status(1))
    mon.on_sim(sim_status(2))
    mon.on_map(grid(1))  # its status came first, and a later one after it
    mon.on_map(grid(3))  # before its status
    mon.on_map(grid(5))  # both wait (their coverage taken now, the point made later)
    assert len(mon.timeline) == 1 and mon.sample_waiting == {3: 3.0, 5: 5.0}
    mon.on_sim(sim_status(3))
    mon.on_sim(sim_status(4))
    mon.on_sim(sim_status(5))
    assert mon.sample_waiting == {}
    assert mon.timeline == [(0.2 * k, 0.1 * k, float(k)) for k in (1, 3, 5)]
    mon.on_map(grid(4))  # an older map than the last sample's: not sampled
    assert len(mon.timeline) == 3
