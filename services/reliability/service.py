"""Reliability service: topo + map + odom -> per end node position probability -> ``reliability``.

For each topo update k, waits until the map it was derived from (``src_seq >= k``) is here,
takes the robot pose at the topo stamp, and runs the Bayes update of paper eqs. 1-10.
"""

from __future__ import annotations

import logging

from topoexplore.common import convert
from topoexplore.common import messages as m
from topoexplore.common.node import Node, OdomBuffer, run_service
from topoexplore.common.params import Params
from topoexplore.services.reliability.core import WARM_MODULES, ReliabilityCore

log = logging.getLogger("topoexplore.reliability")


class ReliabilityService:
    def __init__(self, node: Node):
        self.node = node
        P = node.params
        self.core = ReliabilityCore(P.reliability, P.laser, P.mapper.occupancy)
        self.odom = OdomBuffer()
        self.pub = node.publisher("reliability")
        node.subscribe_odom(self.odom)
        node.subscribe("map")
        node.serve_latest("map")  # a restarted mapper takes its last map back
        node.subscribe("topo", queue=True)
        self.skipped = 0
        self.last: m.Reliability | None = None
        node.add_state(self.state)

    def ready(self, topo: m.TopoGraph) -> bool:
        return (self.node.inbox.src_seq("map") >= topo.header.src_seq
                and self.odom.newest >= topo.header.stamp - 1e-6)

    def step(self) -> None:
        got = self.node.take("topo", self.ready)
        if got is None:
            return
        topo, _ = got
        grid = self.node.inbox.latest.get("map")
        pose = self.odom.pose_near(topo.header.stamp)
        if grid is None or pose is None:
            self.skipped += 1
            log.warning("topo %d skipped: %s missing", topo.header.src_seq,
                        "map" if grid is None else "pose")
            return
        beliefs = self.core.update(convert.graph_from_msg(topo), pose,
                                   convert.grid_from_msg(grid))
        self.last = convert.beliefs_to_msg(beliefs, self.node.header(
            "reliability", topo.header.stamp, topo.header.src_seq))
        self.pub.put(self.last)
        self.node.processed += 1

    def state(self) -> dict:
        return {"skipped": self.skipped, "nodes": self.core.snapshot(), "last": self.last}


def main(argv: list[str] | None = None) -> int:
    return run_service("reliability", lambda node: ReliabilityService(node).step, argv,
                       "end node position probability (Bayes update, paper eqs. 1-10)",
                       kernels=_kernels)


def _kernels(params: Params) -> tuple[str, ...]:
    """The core's one kernel runs only in the frontier-group test (reliability.frontier_group
    > 0, off by default)."""
    return WARM_MODULES if params.reliability.frontier_group > 0 else ()


if __name__ == "__main__":
    raise SystemExit(main())
