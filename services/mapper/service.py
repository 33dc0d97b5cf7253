"""Mapper service: scan + odom -> log-odds occupancy grid -> ``map``.

Each scan is integrated at the odometry pose interpolated to the scan stamp. The map is
published for the first scan of every block of ``mapper.map_every`` scans (scan ``src_seq //
map_every`` changed), so in lockstep exactly the scans with ``src_seq % map_every == 0`` have a
map, and in real time a dropped scan only moves the map to the next one of its block.
Bad or inconsistent scans (wrong beam count, pose missing, rejected by the core) are counted
and skipped. The state queryable answers with a summary and the full current map.

With ``runtime.state_dir`` set, the mapper writes a checkpoint of its grid there every
``runtime.checkpoint_every`` seconds (``common.checkpoint``), and a restarted mapper resumes
from it: the map keeps every cell but those of the scans after the last checkpoint.
"""

from __future__ import annotations

import logging
import time

from topoexplore.common import convert
from topoexplore.common import messages as m
from topoexplore.common.checkpoint import (
    CheckpointError,
    checkpoint_path,
    read_checkpoint,
    write_checkpoint,
)
from topoexplore.common.node import Node, OdomBuffer, run_service
from topoexplore.services.mapper.core import WARM_MODULES, MapLoadError, MapperCore, ScanError

log = logging.getLogger("topoexplore.mapper")


class MapperService:
    def __init__(self, node: Node):
        self.node = node
        P = node.params
        self.core = MapperCore(P.mapper, P.laser.offset)
        self.ckpt_path = checkpoint_path(P.runtime.state_dir, "mapper")
        self.ckpt = {"written": 0, "failed": 0, "last_error": "", "bytes": 0, "ms": 0.0,
                     "resumed_cells": 0, "resumed_age_s": None}
        self.ckpt_due = 0.0  # [s] monotonic time of the next checkpoint
        if self.ckpt_path is not None:
            self.resume()
        self.odom = OdomBuffer()
        self.pub_map = node.publisher("map")
        node.subscribe_odom(self.odom)
        node.subscribe("scan", queue=True)
        self.skipped: dict[str, int] = {}
        self.last_map: m.OccupancyGrid | None = None
        self.last_block = -1  # src_seq // map_every of the last published map
        node.add_state(self.state)

    def resume(self) -> None:
        """Continue from this robot's checkpoint, if there is a recent one."""
        rt = self.node.params.runtime
        try:
            got = read_checkpoint(self.ckpt_path, time.time(), rt.checkpoint_max_age)
            if got is None:
                return
            arrays, age = got
            self.core = MapperCore.from_checkpoint(arrays, self.node.params.mapper,
                                                   self.node.params.laser.offset)
        except (CheckpointError, MapLoadError) as exc:
            log.error("checkpoint not used, starting with an empty map: %s", exc)
            return
        known = int((self.core.occupancy() >= 0).sum())
        self.ckpt.update(resumed_cells=known, resumed_age_s=round(age, 3))
        log.info("resumed from %s (written %.1f s ago): %d known cells, %d scans",
                 self.ckpt_path, age, known, self.core.scans)

    def save_checkpoint(self) -> None:
        t0 = time.monotonic()
        self.ckpt_due = t0 + self.node.params.runtime.checkpoint_every
        try:
            n = write_checkpoint(self.ckpt_path, self.core.checkpoint(), time.time())
        except OSError as exc:
            self.ckpt["failed"] += 1
            self.ckpt["last_error"] = f"{exc.strerror or exc}"
            if self.ckpt["failed"] in (1, 10, 100) or self.ckpt["failed"] % 1000 == 0:
                log.error("checkpoint %s not written (%d so far): %s", self.ckpt_path,
                          self.ckpt["failed"], exc.strerror or exc)
            return
        self.ckpt["written"] += 1
        self.ckpt["bytes"] = n
        self.ckpt["ms"] = round(1000.0 * (time.monotonic() - t0), 2)

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
        if block != self.last_block:  # else integrated; this block's map went out already
            self.last_block = block
            self.last_map = self.make_map(scan.header.stamp, scan.header.src_seq)
            self.pub_map.put(self.last_map)
        if self.ckpt_path is not None and time.monotonic() >= self.ckpt_due:
            self.save_checkpoint()  # after the map went out: it does not wait for the disk

    def make_map(self, stamp: float, src_seq: int) -> m.OccupancyGrid:
        return convert.grid_to_msg(self.core.grid(), self.node.header("map", stamp, src_seq))

    def state(self) -> dict:
        out: dict = {"skipped_scans": dict(self.skipped), "map": self.last_map, "grid": None,
                     "checkpoint": dict(self.ckpt, path=str(self.ckpt_path or ""))}
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
