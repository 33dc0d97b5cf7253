"""Mapper service: scan + odom -> log-odds occupancy grid -> ``map``.

Each scan is integrated at the odometry pose interpolated to the scan stamp. The map is
published for the first scan of every block of ``mapper.map_every`` scans (scan ``src_seq //
map_every`` changed), so in lockstep exactly the scans with ``src_seq % map_every == 0`` have a
map, and in real time a dropped scan only moves the map to the next one of its block.
Bad or inconsistent scans (wrong beam count, pose missing, rejected by the core) are counted
and skipped. The state queryable answers with a summary and the full current map.
"""

from __future__ import annotations

import logging

from topoexplore.common import convert
from topoexplore.common import messages as m
from topoexplore.common.node import Node, OdomBuffer, run_service
from topoexplore.services.mapper.core import WARM_MODULES, MapperCore, ScanError

log = logging.getLogger("topoexplore.mapper")


class MapperService:
    def __init__(self, node: Node):
        self.node = node
        self.core = MapperCore(node.params.mapper, node.params.laser.offset)
        self.odom = OdomBuffer()
        self.pub_map = node.publisher("map")
        node.subscribe_odom(self.odom)
        node.subscribe("scan", queue=True)
        self.skipped: dict[str, int] = {}
        self.last_map: m.OccupancyGrid | None = None
        self.last_block = -1  # src_seq // map_every of the last published map
        node.add_state(self.state)

    def skip(self, reason: str, detail: str) -> None:
        self.skipped[reason] = self.skipped.get(reason, 0) + 1
        if self.skipped[reason] in (1, 10, 100) or self.skipped[reason] % 1000 == 0:
            log.warning("skipped scan (%s, %d so far): %s", reason, self.skipped[reason], detail)

    def step(self) -> None:
        got = self.node.take("scan", lambda s: self.odom.newest >= s.header.stamp - 1e-6)
        if got is None:
            return
        scan, ok = got
        pose = self.odom.pose_at(scan.header.stamp, tolerance=1e-6) if ok else None
        if pose is None:
            self.skip("pose_missing", f"no odometry at stamp {scan.header.stamp:.3f}")
            return
        expected = self.node.params.laser.beams
        if len(scan.ranges) != expected:
            self.skip("beam_count", f"{len(scan.ranges)} beams, expected {expected}")
            return
        try:
            self.core.integrate(pose, convert.scan_from_msg(scan))
        except ScanError as exc:
            self.skip("rejected", str(exc))
            return
        self.node.processed += 1
        block = scan.header.src_seq // self.node.params.mapper.map_every
        if block == self.last_block:
            return  # integrated; this block's map went out already
        self.last_block = block
        self.last_map = self.make_map(scan.header.stamp, scan.header.src_seq)
        self.pub_map.put(self.last_map)

    def make_map(self, stamp: float, src_seq: int) -> m.OccupancyGrid:
        return convert.grid_to_msg(self.core.grid(), self.node.header("map", stamp, src_seq))

    def state(self) -> dict:
        out: dict = {"skipped_scans": dict(self.skipped), "map": self.last_map, "grid": None}
        if self.last_map is not None:
            g = self.last_map
            out["grid"] = {"width": g.width, "height": g.height, "resolution": g.resolution,
                           "origin": [g.origin.x, g.origin.y]}
        return out


def main(argv: list[str] | None = None) -> int:
    return run_service("mapper", lambda node: MapperService(node).step, argv,
                       "log-odds occupancy grid mapper",
                       kernels=WARM_MODULES)


if __name__ == "__main__":
    raise SystemExit(main())
