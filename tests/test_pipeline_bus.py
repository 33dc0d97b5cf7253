"""Over the bus: sim + mapper + topology processes on paper-room produce a topological map
whose end and branch nodes lie in free space."""

from __future__ import annotations

import threading
import time

from topoexplore.common import convert
from topoexplore.common import messages as m
from topoexplore.common.bus import Bus
from topoexplore.common.grid import OCCUPIED, classify
from topoexplore.common.keys import Keys
from topoexplore.sim.world import load_world, rasterize
from topoexplore.tools.launch.core import load_profile
from topoexplore.tools.launch.supervisor import Supervisor, profile_path


def test_sim_mapper_topology_over_the_bus(endpoint, namespace):
    keys = Keys(namespace, "robot1")
    sup = Supervisor(load_profile(profile_path("mapping")), keys, endpoint,
                     overrides=["sim.speed=4.0"], sink=lambda line: None)
    got: dict[str, object] = {}
    ready = threading.Event()

    def on_topo(msg: m.TopoGraph, key: str) -> None:
        kinds = {n.kind for n in msg.nodes}
        got["topo"] = msg
        got["map"] = got.get("map_latest")
        if "end" in kinds and "branch" in kinds and got["map"] is not None:
            ready.set()

    try:
        sup.start_router()
        with Bus.client(endpoint, wait_for_router=True) as bus:
            bus.subscribe(keys.map, m.OccupancyGrid, lambda msg, k: got.__setitem__("map_latest", msg))
            bus.subscribe(keys.topo, m.TopoGraph, on_topo)
            assert sup.start(ready_timeout=60)
            # the robot stands still (no controller): one view from the start pose suffices
            assert ready.wait(30), f"topo: {got.get('topo')}"
            time.sleep(0.2)
    finally:
        sup.stop()
    topo: m.TopoGraph = got["topo"]
    grid: m.OccupancyGrid = got["map"]
    g = convert.grid_from_msg(grid)
    geom, cls = g.geom, classify(g.data)
    solid, ox, oy = rasterize(load_world("paper-room"), 0.1)
    for n in topo.nodes:
        if n.kind in ("end", "branch"):
            r, c = geom.world_to_cell(n.x, n.y)
            assert geom.inside(r, c)
            # never on an occupied map cell (tiny unknown specks are filled by the cleaning)
            assert cls[int(r), int(c)] != OCCUPIED, n
            # and in truth free space
            tr, tc = int((n.y - oy) // 0.1), int((n.x - ox) // 0.1)
            assert not solid[tr, tc], n
    ids = [n.id for n in topo.nodes]
    assert len(ids) == len(set(ids))
    for e in topo.edges:
        assert e.points and e.length > 0 and e.clearance >= 0
