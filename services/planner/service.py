"""Planner service: reliability + topo + map + odom -> ``plan`` and ``explore/status``.

One plan per reliability update (so lockstep can wait for it by ``src_seq``); the status is
published with every plan in lockstep and at ``planner.status_hz`` or on change in real time.
With ``runtime.state_dir`` set, the planner's memory (blacklists, learned blockages, examined
cells) is checkpointed and a restarted planner takes it back.
"""

from __future__ import annotations

import logging
import math
import threading
import time

import msgspec

from topoexplore.common import convert
from topoexplore.common import messages as m
from topoexplore.common.checkpoint import Checkpointer
from topoexplore.common.node import Node, OdomBuffer, run_service
from topoexplore.services.planner.core import WARM_MODULES, PlannerCore

log = logging.getLogger("topoexplore.planner")


class PlannerService:
    def __init__(self, node: Node):
        self.node = node
        P = node.params
        self.p = P.planner
        self.core = PlannerCore(P.planner, P.robot, P.reliability.p_reliable, P.mapper.occupancy)
        self.odom = OdomBuffer(corrected=node.params.localizer.enabled)
        self.pub_plan = node.publisher("plan")
        self.pub_status = node.publisher("explore/status", reliable=True)
        self.pub_lock = threading.Lock()  # plan and its seq: the worker and the heartbeat
        self.last_plan: m.Path | None = None
        self.worker_beat = time.monotonic()  # [wall s] the worker loop's last turn
        self.beat_stamp = -math.inf  # [s] robot time of the last plan sent
        self.heartbeats = 0
        node.subscribe_odom(self.odom, then=self.on_odom)
        node.subscribe("map")
        node.serve_latest("map")  # a restarted mapper takes its last map back
        node.subscribe("topo")
        node.subscribe("reliability", queue=True)
        self.last_status: m.ExploreStatus | None = None
        self.last_status_wall = 0.0
        self.last_key: tuple = ()
        self.last_decision: tuple = ()
        self.plan = None
        rt = P.runtime  # blacklists, blockages, examined cells survive a restart
        self.ckpt = Checkpointer(rt.state_dir, "planner", rt.checkpoint_every,
                                 rt.checkpoint_max_age, log)
        if self.ckpt.resume(self.core.restore, time.time()):
            snap = self.core.snapshot()
            log.info("resumed from the checkpoint: %d blacklisted, %d blockage marks, %d "
                     "examined cells", len(snap["blacklist"]), snap["blocked"]["made"],
                     snap["examined"]["examined"])
        node.add_state(self.state)

    def ready(self, rel: m.Reliability) -> bool:
        k = rel.header.src_seq
        inbox = self.node.inbox
        return (inbox.src_seq("topo") >= k and inbox.src_seq("map") >= k
                and self.odom.newest >= rel.header.time - 1e-6)

    def on_odom(self, o: m.Odometry) -> None:
        """Receive thread, after the buffer took the pose: in real time, send the last plan
        again every planner.heartbeat of robot time while the worker loop is alive (it turns
        at least every 0.2 s; a worker stuck for 2 s gets no heartbeat). A frozen or dead process
        sends nothing, and the controller stops the robot (controller.plan_timeout)."""
        beat = self.p.heartbeat
        if beat <= 0.0 or self.node.lockstep or self.last_plan is None \
                or time.monotonic() - self.worker_beat > 2.0:
            return
        with self.pub_lock:
            last = self.last_plan
            t = o.header.time
            if t - self.beat_stamp < beat and t >= self.beat_stamp:
                return
            h = last.header
            self.last_plan = msgspec.structs.replace(last, header=self.node.header(
                "plan", h.time, h.src_seq))
            self.pub_plan.put(self.last_plan)
            self.beat_stamp = t
            self.heartbeats += 1

    def step(self) -> None:
        self.worker_beat = time.monotonic()
        got = self.node.take("reliability", self.ready)
        if got is None:
            self.maybe_status(force=False)
            return
        rel, _ = got
        inbox = self.node.inbox
        k = rel.header.src_seq  # lockstep: that scan's topology and map
        topo, grid = inbox.at("topo", k), inbox.at("map", k)
        pose = self.odom.pose_near(rel.header.time)
        if pose is None:
            log.warning("reliability %d skipped: no pose", rel.header.src_seq)
            return
        plan = self.core.update(
            rel.header.time, pose, convert.graph_from_msg(topo) if topo is not None else None,
            convert.beliefs_from_msg(rel),
            convert.grid_from_msg(grid) if grid is not None else None)
        self.plan = plan
        stamp, k = rel.header.time, rel.header.src_seq
        with self.pub_lock:
            self.last_plan = convert.route_to_msg(plan.route, self.node.header("plan", stamp, k))
            self.pub_plan.put(self.last_plan)
            self.beat_stamp = self.odom.newest
        self.last_status = convert.status_to_msg(  # its seq is given when it goes out
            plan.status, m.header(0, stamp, "map", k))
        self.node.processed += 1
        st = plan.status
        key = (st.state, st.target_id, st.reason, st.blacklisted)
        decision = (st.state, st.target_id, st.blacklisted)
        if decision != self.last_decision:  # a new target, a blacklisting or the end: say why
            log.info("t=%.1f s %s: %s", stamp, st.state.value, st.reason)
            self.last_decision = decision
        self.maybe_status(force=self.node.lockstep or key != self.last_key)
        self.last_key = key
        self.ckpt.save_if_due(self.core.checkpoint)  # after the plan and status went out

    def maybe_status(self, force: bool) -> None:
        now = time.monotonic()
        if self.last_status is None:
            return
        if force or now - self.last_status_wall >= 1.0 / self.p.status_hz:
            self.last_status_wall = now
            h = self.last_status.header  # one seq per message sent: a gap is a loss
            self.last_status = msgspec.structs.replace(self.last_status, header=self.node.header(
                "explore/status", h.time, h.src_seq))
            self.pub_status.put(self.last_status)

    def state(self) -> dict:
        return {"status": self.last_status, "core": self.core.snapshot(),
                "heartbeats": self.heartbeats,
                "checkpoint": dict(self.ckpt.stats)}


def main(argv: list[str] | None = None) -> int:
    return run_service("planner", lambda node: PlannerService(node).step, argv,
                       "exploration planner (reliability | all-end-nodes | frontier)",
                       kernels=WARM_MODULES)


if __name__ == "__main__":
    raise SystemExit(main())
