"""Simulator service: runs :class:`sim.core.SimCore` and publishes scan, odom, truth, sim/status.

Modes (DESIGN §5):
- real-time: physics at ``physics_hz`` paced by the wall clock times ``speed``;
- lockstep: after publishing scan k, wait for the cmd_vel answering it (``src_seq >= k``), then
  advance one scan period. Runs are deterministic and faster than real time.

Run: ``python -m sim.service --set sim.world=paper-room``.
"""

from __future__ import annotations

import logging
import math
import time

import numpy as np

from topoexplore.common import convert
from topoexplore.common import messages as m
from topoexplore.common.checkpoint import Checkpointer
from topoexplore.common.node import Node, run_service
from topoexplore.common.params import Params
from topoexplore.sim.core import WARM_MODULES, SimCore, SimError
from topoexplore.sim.world import WorldError, load_world

log = logging.getLogger("topoexplore.sim")


class SimService:
    def __init__(self, node: Node):
        self.node = node
        P = node.params
        p = P.sim
        self.p = p
        self.runtime = P.runtime
        try:
            self.world = load_world(p.world)
        except WorldError as exc:
            raise SystemExit(f"topoexplore-sim: {exc}") from None
        self.core = SimCore(self.world, p, np.random.default_rng(p.seed), P.robot, P.laser)
        self.steps_per_scan = max(1, round(p.physics_hz / P.laser.scan_hz))
        self.scan_period = self.steps_per_scan / p.physics_hz  # [s]
        self.odom_tick = 1  # the next odometry tick (tick 0 goes out with the first scan)
        self.odom_stamp: float | None = None  # [s] sim time of the last odometry published
        self.pub_scan = node.publisher("scan")
        self.pub_odom = node.publisher("odom")
        self.pub_truth = node.publisher("truth")
        self.pub_status = node.publisher("sim/status")
        node.subscribe("cmd_vel")
        self.scan_seq = -1
        self.step_count = 0
        self.lockstep_timeouts = 0
        self.wall_start = time.monotonic()
        self.last_status_wall = 0.0
        self.started = False
        self.applied_cmd: m.Twist | None = None  # the last command applied (by identity:
        #   a foreign controller need not count its header.seq)
        rt = P.runtime
        self.ckpt = Checkpointer(rt.state_dir, "sim", rt.checkpoint_every,
                                 rt.checkpoint_max_age, log)
        self.resume()
        node.add_state(self.state)
        node.add_live(("sim.speed",), self.apply_params)  # the pace of real-time mode

    # -- checkpoints: a restarted simulator goes on with the same robot and clock ----------
    def resume(self) -> None:
        arrays = self.ckpt.load(time.time())
        if arrays is None:
            return
        try:
            self.core.resume(arrays)
            seq = arrays.get("sim_scan_seq")
            if seq is None or seq.shape != (1,) or seq.dtype.kind != "i":
                raise SimError("checkpoint has no scan count")
        except SimError as exc:
            log.error("checkpoint not used, starting over: %s", exc)
            self.core = SimCore(self.world, self.p, np.random.default_rng(self.p.seed),
                                self.node.params.robot, self.node.params.laser)
            self.ckpt.stats["resumed_age_s"] = None
            return
        self.scan_seq = int(seq[0])
        self.step_count = self.core.steps
        p = self.p  # the next odometry tick after this step (see odom_due)
        self.odom_tick = int(math.floor(self.step_count * p.odom_hz / p.physics_hz + 1e-9)) + 1
        x, y, th = self.core.truth_pose()
        log.info("resumed at sim time %.2f s (checkpoint %.1f s old): robot at (%.2f, %.2f, "
                 "%.2f rad), path %.1f m, scan %d", self.core.time,
                 self.ckpt.stats["resumed_age_s"], x, y, th, self.core.path_length,
                 self.scan_seq)

    def maybe_checkpoint(self) -> None:
        """Every ``checkpoint_every`` of sim time (the robot's motion a restart can lose, in
        lockstep as in real time)."""
        if self.ckpt.due(self.core.time):
            t0 = time.monotonic()
            arrays = {**self.core.checkpoint(),
                      "sim_scan_seq": np.array([self.scan_seq], np.int64)}
            self.ckpt.save(arrays, self.core.time, time.time(), lambda: time.monotonic() - t0)

    # -- publishing -----------------------------------------------------------------------
    def publish_odom(self) -> None:
        t = self.odom_stamp = self.core.time
        self.pub_odom.put(convert.odom_to_msg(
            self.core.odom(), self.node.header("odom", t, self.scan_seq, frame="odom"),
            pose_covariance=self.core.odom_covariance()))
        self.pub_truth.put(convert.truth_to_msg(self.core.truth_pose(),
                                                self.node.header("truth", t, self.scan_seq)))

    def publish_scan(self) -> None:
        self.scan_seq += 1
        if self.odom_stamp != self.core.time:  # the mapper needs the pose at the scan stamp:
            self.publish_odom()  # an extra message only when no odometry tick fell on it
        hdr = m.header(self.scan_seq, self.core.time, "laser", self.scan_seq)
        self.pub_scan.put(convert.scan_to_msg(self.core.scan(), hdr, self.scan_period))

    def publish_status(self) -> None:
        wall = time.monotonic() - self.wall_start
        self.pub_status.put(m.SimStatus(
            header=self.node.header("sim/status", self.core.time, self.scan_seq),
            world=self.world.name, mode="lockstep" if self.node.lockstep else "realtime",
            sim_time=self.core.time, steps=self.step_count, collisions=self.core.collisions,
            path_length=self.core.path_length,
            real_time_factor=self.core.time / wall if wall > 0 else 0.0,
            watchdog_stops=self.core.watchdog_stops, lockstep_timeouts=self.lockstep_timeouts,
            stale_cmds=self.core.stale_cmds, clipped_cmds=self.core.clipped_cmds))

    def apply_latest_cmd(self) -> None:
        cmd = self.node.inbox.latest.get("cmd_vel")
        if cmd is not None and cmd is not self.applied_cmd:
            self.applied_cmd = cmd
            c = convert.command_from_msg(cmd)
            n = self.core.stale_cmds
            if not self.core.command(c.v, c.w, cmd.header.time) \
                    and (n + 1 in (1, 10, 100) or (n + 1) % 1000 == 0):  # counted, not echoed
                log.warning("stale cmd_vel #%d dropped: stamp %.3f s, sim time %.3f s "
                            "(%d so far)", cmd.header.seq, cmd.header.time, self.core.time,
                            self.core.stale_cmds)

    def physics_step(self) -> None:
        before = self.core.collisions
        self.core.step()
        self.step_count += 1
        if self.core.collisions != before:
            x, y, th = self.core.truth_pose()
            log.warning("collision #%d at x=%.2f y=%.2f heading=%.0f deg, sim time %.1f s",
                        self.core.collisions, x, y, math.degrees(th), self.core.time)
        if self.odom_due():
            self.publish_odom()

    def odom_due(self) -> bool:
        """Odometry at ``odom_hz`` on average, whatever ``physics_hz``: tick k goes out at the
        first physics step at or after k / odom_hz (50 Hz physics, 20 Hz odometry: steps 0, 3,
        5, 8, 10, ...; a rounded step of 2 would give 25 Hz). With the default rates every scan
        falls on a tick, so the scan needs no odometry of its own."""
        due = False
        p = self.p
        while self.step_count * p.odom_hz >= self.odom_tick * p.physics_hz * (1.0 - 1e-9):
            self.odom_tick += 1
            due = True
        return due

    # -- modes ----------------------------------------------------------------------------
    def wait_for_pipeline(self) -> None:
        """Lockstep: before scan 0, wait for the listed services and for a scan subscriber
        (a scan nobody receives would cost a whole lockstep timeout)."""
        want = set(self.runtime.lockstep_wait_for)
        if self.node.params.localizer.enabled:
            want.add("localizer")
        deadline = time.monotonic() + self.runtime.lockstep_wait
        alive: set[str] = set()
        while not self.node.stop.is_set() and time.monotonic() < deadline:
            if want:
                alive = {k.rsplit("/", 1)[-1]
                         for k in self.node.bus.alive(self.node.keys.alive_all())}
            if want <= alive and self.pub_scan.matched:
                return
            time.sleep(0.05)
        log.warning("lockstep: starting without %s", sorted(want - alive) or "a scan subscriber")

    def step_lockstep(self) -> None:
        if not self.started:
            self.wait_for_pipeline()
            self.started = True
            self.wall_start = time.monotonic()
        self.publish_scan()
        self.publish_status()
        k = self.scan_seq
        ok = self.node.inbox.wait(
            lambda: self.node.stop.is_set() or self.node.inbox.src_seq("cmd_vel") >= k,
            self.runtime.lockstep_timeout)
        if self.node.stop.is_set():
            return
        if not ok:
            self.lockstep_timeouts += 1
            log.warning("lockstep: no cmd_vel for scan %d within %.1f s; stepping on", k,
                        self.runtime.lockstep_timeout)
        self.apply_latest_cmd()
        for _ in range(self.steps_per_scan):
            self.physics_step()
        self.node.processed += 1
        self.maybe_checkpoint()

    def step_realtime(self) -> None:
        if not self.started:
            self.started = True
            self.wall_start = time.monotonic() - self.core.time / self.p.speed  # 0 unless resumed
            self.publish_scan()
        self.apply_latest_cmd()
        self.physics_step()
        if self.step_count % self.steps_per_scan == 0:
            self.publish_scan()
            self.node.processed += 1
            self.maybe_checkpoint()
        now = time.monotonic()
        if now - self.last_status_wall >= 1.0 / self.p.status_hz:
            self.last_status_wall = now
            self.publish_status()
        # pace: sim time runs at `speed` x wall time
        target = self.wall_start + self.core.time / self.p.speed
        delay = target - time.monotonic()
        if delay > 0:
            self.node.stop.wait(delay)

    def step(self) -> None:
        if self.node.lockstep:
            self.step_lockstep()
        else:
            self.step_realtime()

    def apply_params(self, P: Params) -> None:
        """A new real-time factor: the pacing restarts from now, so sim time does not jump."""
        if P.sim.speed != self.p.speed and self.started:
            self.wall_start = time.monotonic() - self.core.time / P.sim.speed
        self.p = P.sim

    def state(self) -> dict:
        x, y, th = self.core.truth_pose()
        return {
            "world": self.world.name,
            "world_source": self.world.source,
            "sim_time": self.core.time,
            "scan_seq": self.scan_seq,
            "steps": self.step_count,
            "collisions": self.core.collisions,
            "path_length": self.core.path_length,
            "watchdog_stops": self.core.watchdog_stops,
            "lockstep_timeouts": self.lockstep_timeouts,
            "stale_cmds": self.core.stale_cmds,
            "clipped_cmds": self.core.clipped_cmds,
            "checkpoint": dict(self.ckpt.stats),
            "truth_pose": [x, y, th],
            "heading_deg": math.degrees(th),
        }


def main(argv: list[str] | None = None) -> int:
    return run_service("sim", lambda node: SimService(node).step, argv,
                       "pymunk differential-drive robot with a 181-beam laser",
                       kernels=WARM_MODULES)


if __name__ == "__main__":
    raise SystemExit(main())
