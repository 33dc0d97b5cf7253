"""Topology service: map -> thinning-based topological graph -> ``topo``.

The robot position (needed to keep only its connected component) is the odometry pose at the
map's stamp. Node ids are stable across updates; vanished ids are reported in ``gone``. With
``runtime.state_dir`` set, the last nodes and the next free id are checkpointed, so a
restarted topology gives the same places the same ids.
"""

from __future__ import annotations

import logging
import time

from topoexplore.common import convert
from topoexplore.common import messages as m
from topoexplore.common.checkpoint import Checkpointer
from topoexplore.common.node import Node, OdomBuffer, run_service
from topoexplore.services.topology.core import WARM_MODULES, TopologyCore

log = logging.getLogger("topoexplore.topology")


class TopologyService:
    def __init__(self, node: Node):
        self.node = node
        self.core = TopologyCore(node.params.topology, node.params.mapper.occupancy)
        self.odom = OdomBuffer(corrected=node.params.localizer.enabled)
        self.pub = node.publisher("topo")
        node.subscribe_odom(self.odom)
        node.subscribe("map", queue=True)
        self.skipped = 0
        self.last: m.TopoGraph | None = None
        rt = node.params.runtime  # node ids survive a restart (runtime.state_dir)
        self.ckpt = Checkpointer(rt.state_dir, "topology", rt.checkpoint_every,
                                 rt.checkpoint_max_age, log)
        if self.ckpt.resume(self.core.restore, time.time()):
            log.info("resumed %d node ids (next id %d) from the checkpoint",
                     len(self.core.checkpoint()["ids"]), self.core.snapshot()["next_id"])
        node.add_state(self.state)

    def step(self) -> None:
        got = self.node.take("map", lambda g: self.odom.newest >= g.header.time - 1e-6)
        if got is None:
            return
        grid, _ = got
        pose = self.odom.pose_near(grid.header.time)
        if pose is None:
            self.skipped += 1
            log.warning("no odometry for map at %.3f: skipped", grid.header.time)
            return
        res = self.core.update(convert.grid_from_msg(grid), (pose.x, pose.y))
        self.last = convert.graph_to_msg(res.graph, self.node.header(
            "topo", grid.header.time, grid.header.src_seq))
        self.pub.put(self.last)
        self.node.processed += 1
        self.ckpt.save_if_due(self.core.checkpoint)  # after the graph went out

    def state(self) -> dict:
        out = {"skipped_maps": self.skipped, "core": self.core.snapshot(),
               "checkpoint": dict(self.ckpt.stats)}
        if self.last is not None:
            kinds: dict[str, int] = {}
            for n in self.last.nodes:
                kinds[n.kind] = kinds.get(n.kind, 0) + 1
            out.update(nodes=kinds, edges=len(self.last.edges), topo=self.last)
        return out


def main(argv: list[str] | None = None) -> int:
    return run_service("topology", lambda node: TopologyService(node).step, argv,
                       "thinning-based topological map",
                       kernels=WARM_MODULES)


if __name__ == "__main__":
    raise SystemExit(main())
