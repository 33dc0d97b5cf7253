"""Reliability service: topo + map + odom -> per end node position probability -> ``reliability``.

For each topo update k, waits until the map it was derived from (``src_seq >= k``) is here,
takes the robot pose at the topo stamp, and runs the Bayes update of paper eqs. 1-10. With
``runtime.state_dir`` set, every end node's history and P are checkpointed: a restarted
reliability does not send the robot back to places already reliable.
"""

from __future__ import annotations

import logging
import time

from topoexplore.common import convert
from topoexplore.common import messages as m
from topoexplore.common.checkpoint import Checkpointer
from topoexplore.common.node import Node, OdomBuffer, run_service
from topoexplore.services.reliability.core import WARM_MODULES, ReliabilityCore

log = logging.getLogger("topoexplore.reliability")


class ReliabilityService:
    def __init__(self, node: Node):
        self.node = node
        P = node.params
        self.core = ReliabilityCore(P.reliability, P.laser, P.mapper.occupancy)
        self.odom = OdomBuffer(corrected=node.params.localizer.enabled)
        self.pub = node.publisher("reliability")
        node.subscribe_odom(self.odom)
        node.subscribe("map")
        node.serve_latest("map")  # a restarted mapper takes its last map back
        node.subscribe("topo", queue=True)
        self.skipped = 0
        self.last: m.Reliability | None = None
        rt = P.runtime  # P of every end node survives a restart (runtime.state_dir)
        self.ckpt = Checkpointer(rt.state_dir, "reliability", rt.checkpoint_every,
                                 rt.checkpoint_max_age, log)
        if self.ckpt.resume(self.core.restore, time.time()):
            snap = self.core.snapshot()
            log.info("resumed %d end node histories (%d reliable) from the checkpoint",
                     snap["end_nodes"], snap["reliable"])
        node.add_state(self.state)

    def ready(self, topo: m.TopoGraph) -> bool:
        return (self.node.inbox.src_seq("map") >= topo.header.src_seq
                and self.odom.newest >= topo.header.time - 1e-6)

    def step(self) -> None:
        got = self.node.take("topo", self.ready)
        if got is None:
            return
        topo, _ = got
        grid = self.node.inbox.at("map", topo.header.src_seq)  # lockstep: that scan's map
        pose = self.odom.pose_near(topo.header.time)
        if grid is None or pose is None:
            self.skipped += 1
            log.warning("topo %d skipped: %s missing", topo.header.src_seq,
                        "map" if grid is None else "pose")
            return
        beliefs = self.core.update(convert.graph_from_msg(topo), pose,
                                   convert.grid_from_msg(grid))
        self.last = convert.beliefs_to_msg(beliefs, self.node.header(
            "reliability", topo.header.time, topo.header.src_seq))
        self.pub.put(self.last)
        self.node.processed += 1
        self.ckpt.save_if_due(self.core.checkpoint)  # after the beliefs went out

    def state(self) -> dict:
        return {"skipped": self.skipped, "nodes": self.core.snapshot(), "last": self.last,
                "checkpoint": dict(self.ckpt.stats)}


def main(argv: list[str] | None = None) -> int:
    return run_service("reliability", lambda node: ReliabilityService(node).step, argv,
                       "end node position probability (Bayes update, paper eqs. 1-10)",
                       kernels=WARM_MODULES)


if __name__ == "__main__":
    raise SystemExit(main())
