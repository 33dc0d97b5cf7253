"""Localizer service: scan + odom + map -> the ``map`` -> ``odom`` correction, ``map_odom``.

For each scan: odometry's pose at its stamp, composed with the correction in force, is the
guess; the core matches the scan against the mapper's latest map around it; a trusted match
sets the correction to ``match ∘ odom⁻¹`` (REP-105: map -> odom). One ``map_odom`` message per
scan, stamped as the scan, trusted or not, so the services that wait for it (every service's
odometry is corrected when ``localizer.enabled``: ``common.node.OdomBuffer``) never wait in
vain. In lockstep it matches against the map of the scans before this one (the mapper waits
for this scan's correction before it integrates the scan). With ``runtime.state_dir`` set,
the correction and what the scans taught the core (the sides each wall was seen from, the
direction histogram) are checkpointed, so a restarted localizer goes on from where it was
instead of from raw odometry.
"""

from __future__ import annotations

import logging
import time

import numpy as np

from topoexplore.common import convert
from topoexplore.common import messages as m
from topoexplore.common.checkpoint import Checkpointer, CheckpointError, checked
from topoexplore.common.domain import Pose, compose, inverse
from topoexplore.common.node import Node, OdomBuffer, run_service
from topoexplore.services.localizer.core import LocalizerCore

log = logging.getLogger("topoexplore.localizer")


class LocalizerService:
    def __init__(self, node: Node):
        self.node = node
        P = node.params
        self.core = LocalizerCore(P.localizer, P.laser.offset, P.mapper.occupancy)
        self.odom = OdomBuffer()  # odometry as it is: the correction is made here
        self.pub = node.publisher("map_odom")
        node.subscribe_odom(self.odom)
        node.subscribe("map")
        node.subscribe("scan", queue=True)
        self.correction = Pose(0.0, 0.0, 0.0)
        self.map_seq = -1
        # kept: no trusted match (the guess stands); degenerate: matched, but along a corridor
        #   odometry's guess stands (core step 5)
        self.counts = {"matched": 0, "kept": 0, "no_map": 0, "degenerate": 0}
        self.last_score = 0.0
        rt = node.params.runtime  # the correction survives a restart (runtime.state_dir)
        self.ckpt = Checkpointer(rt.state_dir, "localizer", rt.checkpoint_every,
                                 rt.checkpoint_max_age, log)
        if self.ckpt.resume(self.restore, time.time()):
            log.info("resumed the correction (%.3f m, %.3f m, %.4f rad) from the checkpoint",
                     *self.correction)
        if node.params.runtime.resume_from_peers:
            self.map_from_peers()
        node.add_state(self.state)

    def map_from_peers(self) -> None:
        """A restarted localizer matches against the last map its peers hold (planner and
        reliability keep it, ``Node.serve_latest``) until the mapper publishes the next: the
        maps that went out while it was down never come again. A fresh start finds none."""
        try:
            grid = self.node.latest_from_peers("map")
        except Exception as exc:  # noqa: BLE001 - a failed query: go on without it
            log.warning("could not ask the peers for the last map: %s", exc)
            return
        if grid is not None and "map" not in self.node.inbox.latest:
            self.node.inbox.put("map", grid)
            log.info("took the peers' last map (scan %d)", grid.header.src_seq)

    def checkpoint(self) -> dict[str, np.ndarray]:
        return {**self.core.checkpoint(),
                "correction": np.array(tuple(self.correction), np.float64)}

    def restore(self, arrays: dict[str, np.ndarray]) -> None:
        """The correction and the core's state from :meth:`checkpoint`'s arrays, or
        CheckpointError with nothing taken."""
        c = checked(arrays, "correction", "f", (3,)).astype(np.float64)
        if not np.isfinite(c).all():
            raise CheckpointError("localizer checkpoint: correction not finite")
        self.core.restore(arrays)
        self.correction = Pose(float(c[0]), float(c[1]), float(c[2]))

    def ready(self, scan: m.LaserScan) -> bool:
        ok = self.odom.newest >= scan.header.time - 1e-6
        if self.node.lockstep:  # the map of the scans before this one (none before scan 0)
            k = scan.header.src_seq - 1
            k -= k % self.node.params.mapper.map_every
            ok = ok and (k < 0 or self.node.inbox.src_seq("map") >= k)
        return ok

    def step(self) -> None:
        # in lockstep the mapper waits for this scan's correction as long as this waits for
        # the map before it: waiting half as long, a map that will not come (the mapper
        # skipped that scan while this localizer was down) delays one scan, not every scan
        got = self.node.take("scan", self.ready, share=0.5)
        if got is None:
            return
        scan, _ = got
        odom = self.odom.pose_near(scan.header.time)
        if odom is None:
            return
        grid = self.node.inbox.latest.get("map")
        if grid is not None and grid.header.seq != self.map_seq:
            self.core.set_map(convert.grid_from_msg(grid))
            self.map_seq = grid.header.seq
        scan_d = convert.scan_from_msg(scan)
        if self.core.ready:
            match = self.core.match(scan_d, compose(self.correction, odom))
            self.last_score = match.score
            if match.ok:
                self.correction = compose(match.pose, inverse(odom))
                self.counts["matched"] += 1
                if match.conditioning < self.core.p.degenerate_ratio:
                    self.counts["degenerate"] += 1
            else:
                self.counts["kept"] += 1
        else:
            self.counts["no_map"] += 1
        # the sides of the faces this scan met, at the pose it is mapped at (core step 0)
        self.core.observe(scan_d, compose(self.correction, odom))
        self.pub.put(convert.correction_to_msg(self.correction, self.node.header(
            "map_odom", scan.header.time, scan.header.src_seq, frame="map")))
        self.node.processed += 1
        self.ckpt.save_if_due(self.checkpoint)  # after the correction went out

    def state(self) -> dict:
        x, y, th = self.correction
        return {"correction": {"x": float(x), "y": float(y), "theta": float(th)},
                "score": float(self.last_score), "checkpoint": dict(self.ckpt.stats),
                **self.counts}


def main(argv: list[str] | None = None) -> int:
    return run_service("localizer", lambda node: LocalizerService(node).step, argv,
                       "scan matcher: the map -> odom correction")


if __name__ == "__main__":
    raise SystemExit(main())
