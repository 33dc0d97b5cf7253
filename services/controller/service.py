"""Controller service: plan + odom + scan -> ``cmd_vel`` (pure pursuit with a safety stop).

Runs once per scan; in lockstep it waits for the plan derived from the latest scan that has a
map (the mapper publishes for ``src_seq % mapper.map_every == 0``), or with
``runtime.plan_lag`` = L from the map L map periods before that, and follows exactly that plan,
so the answer the simulator waits for is deterministic.
"""

from __future__ import annotations

import logging
import math
import threading

from topoexplore.common import convert
from topoexplore.common import messages as m
from topoexplore.common.domain import Command, Route
from topoexplore.common.node import Node, OdomBuffer, run_service
from topoexplore.common.params import ControllerParams, Params
from topoexplore.services.controller.core import WARM_MODULES, ControllerCore

log = logging.getLogger("topoexplore.controller")


# read by the core on every update, so they can change while it runs (``keys set``);
# start_turn is spent at the start, the robot's size shapes the core when it is made
LIVE = tuple(f"controller.{f}" for f in ControllerParams.__struct_fields__ if f != "start_turn")


class ControllerService:
    def __init__(self, node: Node):
        self.node = node
        self.core = ControllerCore(node.params.controller, node.params.robot)
        self.odom = OdomBuffer(corrected=node.params.localizer.enabled)
        self.pub = node.publisher("cmd_vel")
        self.pub_lock = threading.Lock()  # cmd_vel from the worker and from the odom thread
        self.plan_came: tuple[int, float] | None = None  # (plan seq, robot time it came)
        self.early_stops = 0  # stale-plan stops sent on odometry, before the next scan
        node.subscribe_odom(self.odom, then=self.on_odom)
        node.subscribe("plan", on_msg=self.on_plan)
        node.subscribe("explore/status")
        node.subscribe("scan", queue=True)
        self.last_cmd = Command(0.0, 0.0, "idle")
        self.last_src = -1  # src_seq of the last scan answered
        self._route: tuple[m.Path | None, Route | None] = (None, None)  # plan message, as
        self._done: tuple[m.ExploreStatus | None, bool] = (None, False)  # converted once
        node.add_state(self.state)
        node.add_live(LIVE, self.apply_params)

    def plan_source(self, src_seq: int) -> int:
        """Lockstep: the scan whose map's plan scan src_seq follows (negative: none yet)."""
        P = self.node.params
        every = P.mapper.map_every
        return src_seq - src_seq % every - P.runtime.plan_lag * every

    def ready(self, scan: m.LaserScan) -> bool:
        ok = self.odom.newest >= scan.header.time - 1e-6
        if self.node.lockstep:  # the plan and status of that map
            k = self.plan_source(scan.header.src_seq)
            inbox = self.node.inbox
            ok = ok and (k < 0 or (inbox.src_seq("plan") >= k
                                   and inbox.src_seq("explore/status") >= k))
        return ok

    def step(self) -> None:
        got = self.node.take("scan", self.ready)
        if got is None:
            return
        scan, _ = got
        inbox = self.node.inbox
        plan, status = inbox.latest.get("plan"), inbox.latest.get("explore/status")
        if self.node.lockstep:
            k = self.plan_source(scan.header.src_seq)
            plan, status = ((inbox.at("plan", k), inbox.at("explore/status", k)) if k >= 0
                            else (None, None))  # no plan to follow yet
        pose = self.odom.pose_near(scan.header.time)
        if pose is None:
            cmd = Command(0.0, 0.0, "no-pose")
        else:
            cmd = self.core.update(scan.header.time, pose, self.route(plan),
                                   self.finished(status), convert.scan_from_msg(scan),
                                   self.plan_age(scan.header.time), self.plan_limit())
        v, w, mode = cmd
        if mode != self.last_cmd.mode and mode == "stale-plan":
            log.warning("t=%.1f s: no new plan for %.1f s: the robot stops until one comes "
                        "(%d stopped steps so far)", scan.header.time,
                        self.plan_age(scan.header.time) or 0.0, self.core.stale_plan_steps)
        if mode != self.last_cmd.mode and mode in ("blocked", "recovery") and pose is not None:
            c = self.core  # the safety stop or a stuck recovery took over: say where and why
            log.info("t=%.1f s %s at (%.2f, %.2f, %.2f rad): front %.2f m, heading error "
                     "%.2f rad, lookahead (%.2f, %.2f), recoveries %d", scan.header.time, mode,
                     pose[0], pose[1], pose[2], c.front, c.heading_error, *(c.target or (math.nan, math.nan)),
                     c.recoveries)
        with self.pub_lock:
            self.last_cmd = cmd
            self.last_src = scan.header.src_seq
            self.pub.put(convert.command_to_msg(cmd, self.node.header(
                "cmd_vel", scan.header.time, scan.header.src_seq)))
        self.node.processed += 1

    def route(self, plan: m.Path | None) -> Route | None:
        """The plan message as a Route, converted once per message (a plan stays the
        newest for several scans; the core compares routes by value)."""
        if plan is not self._route[0]:
            self._route = (plan, convert.route_from_msg(plan) if plan is not None else None)
        return self._route[1]

    def finished(self, status: m.ExploreStatus | None) -> bool:
        """Has the planner said the exploration is over? (once per status message)"""
        if status is not self._done[0]:
            self._done = (status, status is not None and convert.status_from_msg(
                status).finished)
        return self._done[1]

    def on_plan(self, plan: m.Path) -> None:
        """Receive thread: the robot time (newest odometry) a new plan message came."""
        came = self.plan_came
        if came is None or plan.header.seq != came[0]:
            self.plan_came = (plan.header.seq, self.odom.newest)

    def on_odom(self, o: m.Odometry) -> None:
        """Receive thread, after the buffer took the pose: in real time, stop a moving robot
        as soon as the plan is stale by odometry time (20 Hz) instead of at the next scan
        (5 Hz): a frozen planner's robot stands still sooner."""
        t = o.header.time
        if self.node.lockstep:
            return
        age = self.plan_age(t)
        cmd = self.last_cmd
        if age is None or age <= self.plan_limit() or (cmd.v == 0.0 and cmd.w == 0.0):
            return
        with self.pub_lock:
            if self.last_cmd is not cmd:  # the worker answered a scan meanwhile
                return
            self.last_cmd = Command(0.0, 0.0, "stale-plan")
            self.early_stops += 1
            self.pub.put(convert.command_to_msg(self.last_cmd, self.node.header(
                "cmd_vel", t, self.last_src)))
        log.warning("t=%.1f s: no new plan for %.2f s: the robot stops until one comes", t, age)

    def plan_limit(self) -> float:
        """[s] robot time without a new plan message before the robot stops: plan_timeout; in
        lockstep, where plans come once per map and only when they are ready, at least two
        map periods and the plan lag."""
        P = self.node.params
        limit = P.controller.plan_timeout
        if self.node.lockstep:
            limit = max(limit, (2.0 + P.runtime.plan_lag) * P.mapper.map_every
                        / P.laser.scan_hz)
        return limit

    def plan_age(self, t: float) -> float | None:
        """Robot time [s] at t since a new plan message (another seq) last came; None before
        the first."""
        came = self.plan_came
        if came is None:
            return None
        if not math.isfinite(came[1]) or t < came[1] - 1.0:  # no odometry yet when it
            self.plan_came = came = (came[0], t)  # came, or the clock went back (sim restart)
        return max(0.0, t - came[1])

    def apply_params(self, P: Params) -> None:
        self.core.params = P.controller

    def state(self) -> dict:
        v, w, mode = self.last_cmd
        return {"cmd": {"v": v, "w": w, "mode": mode}, "core": self.core.snapshot(),
                "early_stops": self.early_stops}


def main(argv: list[str] | None = None) -> int:
    return run_service("controller", lambda node: ControllerService(node).step, argv,
                       "pure pursuit path follower with obstacle safety stop",
                       kernels=WARM_MODULES)


if __name__ == "__main__":
    raise SystemExit(main())
