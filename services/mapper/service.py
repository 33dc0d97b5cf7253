"""Mapper service: scan + odom -> log-odds occupancy grid -> ``map``.

Each scan is integrated at the odometry pose interpolated to the scan stamp. The map is
published for the first scan of every block of ``mapper.map_every`` scans (scan ``src_seq //
map_every`` changed), so in lockstep exactly the scans with ``src_seq % map_every == 0`` have a
map, and in real time a dropped scan only moves the map to the next one of its block.
Bad or inconsistent scans (wrong beam count, pose missing, rejected by the core) are counted
and skipped. The state queryable answers with a summary and the full current map.

With ``runtime.state_dir`` set, the mapper writes a checkpoint of its grid there every
``runtime.checkpoint_every`` seconds (``common.checkpoint``). A restarted mapper resumes from
it, then takes the cells that changed after it from its last published map, which planner
and reliability keep (:meth:`MapperService.resume`).
"""

from __future__ import annotations

import logging
import math
import time

import numpy as np

from topoexplore.common import convert
from topoexplore.common import messages as m
from topoexplore.common.checkpoint import Checkpointer
from topoexplore.common.node import Node, OdomBuffer, run_service
from topoexplore.services.mapper.core import WARM_MODULES, MapLoadError, MapperCore, ScanError

log = logging.getLogger("topoexplore.mapper")


class MapperService:
    def __init__(self, node: Node):
        self.node = node
        P = node.params
        self.core = MapperCore(P.mapper, P.laser.offset)
        rt = P.runtime
        self.ckpt = Checkpointer(rt.state_dir, "mapper", rt.checkpoint_every,
                                 rt.checkpoint_max_age, log)
        self.ckpt.stats.update(resumed_cells=0, resumed_from_peer=0)
        self.last_src = -1  # src_seq of the last scan in the map
        self.odom = OdomBuffer(corrected=node.params.localizer.enabled)
        self.pub_map = node.publisher("map")
        node.subscribe_odom(self.odom)
        node.subscribe("scan", queue=True)
        self.skipped: dict[str, int] = {}
        self.geometry_said: tuple = ()  # the scan geometry last warned about
        self.last_map: m.OccupancyGrid | None = None
        self.last_block = -1  # src_seq // map_every of the last published map
        node.add_state(self.state)
        self.resume()

    def resume(self) -> None:
        """A restarted mapper goes on with its map: the checkpoint in ``runtime.state_dir``
        (exact log-odds, up to ``checkpoint_every`` old) and then the last map it published,
        as a peer that subscribes to ``map`` keeps it (``Node.serve_latest``): the cells that
        changed after the checkpoint. A fresh start finds neither."""
        P = self.node.params
        ck_src = -1
        arrays = self.ckpt.load(time.time())
        if arrays is not None:
            try:
                self.core = MapperCore.from_checkpoint(arrays, P.mapper, P.laser.offset)
            except MapLoadError as exc:
                log.error("checkpoint not used: %s", exc)
                self.ckpt.stats["resumed_age_s"] = None
            else:
                src = arrays.get("src_seq")
                ck_src = int(src[0]) if src is not None and src.shape == (1,) else -1
        from_peer = 0
        if P.runtime.resume_from_peers:
            try:
                peer = self.node.latest_from_peers("map")
            except Exception as exc:  # noqa: BLE001 - a failed query: go on without it
                log.warning("could not ask the peers for the last map: %s", exc)
                peer = None
            if peer is not None and peer.header.src_seq > ck_src:
                try:
                    from_peer = self.core.adopt(convert.grid_from_msg(peer))
                except MapLoadError as exc:
                    log.error("the peers' last map not used: %s", exc)
                else:
                    self.last_src = peer.header.src_seq
        if not self.core.ready:
            return
        known = int((self.core.occupancy() >= 0).sum())
        self.ckpt.stats.update(resumed_cells=known, resumed_from_peer=from_peer)
        age = self.ckpt.stats["resumed_age_s"]
        log.info("resumed the map: %d known cells (checkpoint %s, %d cells from the peers' "
                 "last map)", known, "none" if age is None else f"{age:.1f} s old", from_peer)

    def save_checkpoint(self) -> None:
        t0 = time.monotonic()
        arrays = {**self.core.checkpoint(), "src_seq": np.array([self.last_src], np.int64)}
        self.ckpt.save(arrays, t0, time.time(), lambda: time.monotonic() - t0)

    def check_geometry(self, scan: m.LaserScan) -> None:
        """The mapper takes each scan's own beams, angles and range limits; say once when
        they differ from [laser], which reliability and the planner use for what the robot
        sees (field of view, range)."""
        lp = self.node.params.laser
        n = len(scan.ranges)
        span = abs(scan.angle_increment) * n if n > 1 else 0.0  # [rad] covered by the beams
        fov_ok = abs(span - lp.fov) <= 2.0 * abs(scan.angle_increment) + 1e-6
        geo = (n, round(span, 3), scan.range_max)
        if fov_ok and abs(scan.range_max - lp.range_max) <= 1e-6 or geo == self.geometry_said:
            return
        self.geometry_said = geo
        log.warning("scans of %d beams over %.0f deg to %.1f m, but [laser] says %d beams, "
                    "fov %.0f deg, range_max %.1f m: the map takes the scans as they are; "
                    "reliability and the planner model the laser by [laser] (set laser.model "
                    "or laser.fov / laser.range_max to match)", n, math.degrees(span),
                    scan.range_max, lp.beams, math.degrees(lp.fov), lp.range_max)

    def skip(self, reason: str, detail: str) -> None:
        self.skipped[reason] = self.skipped.get(reason, 0) + 1
        if self.skipped[reason] in (1, 10, 100) or self.skipped[reason] % 1000 == 0:
            log.warning("skipped scan (%s, %d so far): %s", reason, self.skipped[reason], detail)

    def step(self) -> None:
        got = self.node.take("scan", lambda s: self.odom.newest >= s.header.time - 1e-6)
        if got is None:
            return
        scan, ok = got
        pose = self.odom.pose_at(scan.header.time, tolerance=1e-6) if ok else None
        if pose is None:
            self.skip("pose_missing", f"no odometry at stamp {scan.header.time:.3f}")
            return
        self.check_geometry(scan)
        try:
            self.core.integrate(pose, convert.scan_from_msg(scan))
        except ScanError as exc:
            self.skip("rejected", str(exc))
            return
        self.node.processed += 1
        src = scan.header.src_seq
        if src < 0:  # a driver that fills only the ROS fields: number its scans here
            src = self.last_src + 1
        self.last_src = src
        block = src // self.node.params.mapper.map_every
        if block != self.last_block:  # else integrated; this block's map went out already
            self.last_block = block
            grid = self.make_map(scan.header.time, src)
            self.pub_map.put(grid)
            # the state shows a map only once it went out: a state query answered between
            # the two lines would otherwise show a map that no peer may ever get
            self.last_map = grid
        if self.ckpt.due(time.monotonic()):
            self.save_checkpoint()  # after the map went out: it does not wait for the disk

    def make_map(self, stamp: float, src_seq: int) -> m.OccupancyGrid:
        return convert.grid_to_msg(self.core.grid(), self.node.header("map", stamp, src_seq))

    def state(self) -> dict:
        out: dict = {"skipped_scans": dict(self.skipped), "map": self.last_map, "grid": None,
                     "checkpoint": dict(self.ckpt.stats)}
        if self.last_map is not None:
            g = self.last_map
            i = g.info
            out["grid"] = {"width": i.width, "height": i.height, "resolution": i.resolution,
                           "origin": [i.origin.position.x, i.origin.position.y]}
        return out


def main(argv: list[str] | None = None) -> int:
    return run_service("mapper", lambda node: MapperService(node).step, argv,
                       "log-odds occupancy grid mapper",
                       kernels=WARM_MODULES)


if __name__ == "__main__":
    raise SystemExit(main())
