"""``topoexplore run``: the main job — explore a world with every service as its own process.

Starts the ``sim`` launch profile under the supervisor (router + six services), watches the
run over the bus (status, sim clock, ground truth, map, topo, reliability, plan) with a
progress bar, and at the end writes to ``--out``:

- ``report.json`` — metrics of DESIGN §6 (see :func:`make_report`): ``coverage`` is the share
  of the free space the robot can map that is known, ``coverage_free`` the share of every free
  cell connected to the start (docs/design.md "Measuring a run");
- ``timeline.csv`` — ``coverage`` over sim time and distance travelled;
- ``final.png`` — grid, skeleton, nodes with ``id(P)``, the path coloured by target segment;
- ``map.pgm`` + ``map.yaml`` (ROS map_server) and ``topology.json``; ``trail.csv``; ``logs.txt``.

Exit code 0 when exploration finished, 1 with a one-line reason otherwise, 2 on bad input.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgspec

from topoexplore.common import convert
from topoexplore.common import messages as m
from topoexplore.common.bus import CREDENTIALS_ENV, Bus, BusError, check_config_file
from topoexplore.common.checkpoint import clear_state_dir
from topoexplore.common.domain import GridMap
from topoexplore.common.keys import DEFAULT_ENDPOINT, Keys
from topoexplore.common.node import (
    LOG_LEVELS,
    OdomBuffer,
    add_bus_args,
    add_param_args,
    params_from_args,
    stop_on_signals,
)
from topoexplore.common.params import (
    STRATEGY_NAMES,
    ParamError,
    Params,
    load_params,
    strategy_overrides,
)
from topoexplore.tools.extras import ExtraMissing, require
from topoexplore.tools.launch.supervisor import free_port, port_open

# [s] how long the report waits for the sim status and map of the scan that ended a run
END_WAIT = 2.0
# at most this many maps, topologies and reliability messages kept by scan; fewer once the
# planner's statuses show which are too old to be the report's (Monitor.status_seq)
GRIDS_KEPT = 24


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--world", default=None,
                   help="built-in world name or world file (default: [sim] world of --params, "
                   "else paper-room)")
    p.add_argument("--strategy", default=None, choices=STRATEGY_NAMES,
                   help="default: [planner] strategy of --params, else frontier (the shorter "
                   "on buildings never tuned on: docs/robustness.md); reliability is the "
                   "paper's method")
    p.add_argument("--lockstep", action="store_true",
                   help="deterministic lockstep simulation (faster than real time)")
    p.add_argument("--speed", type=float, default=None,
                   help="real-time factor (real-time mode; default: [sim] speed of --params, "
                   "else 1)")
    p.add_argument("--seed", type=int, default=None,
                   help="default: [sim] seed of --params, else 0")
    p.add_argument("--max-sim-time", type=float, default=None,
                   help="give up after this much simulated time [s] (default: 6 s per m^2 of "
                   "the world's area, at least 2400 s)")
    p.add_argument("--max-wall-time", type=float, default=0.0,
                   help="give up after this much wall time [s] (0: no limit)")
    p.add_argument("--out", default="runs/latest", help="output directory")
    p.add_argument("--log-level", default=None, choices=LOG_LEVELS,
                   help="log level of every service in logs.txt (default INFO)")
    p.add_argument("--record", action="store_true",
                   help="record every key into OUT/run.mcap (raw + Foxglove channels; "
                   "topoexplore play / Foxglove read it)")
    p.add_argument("--record-raw", action="store_true",
                   help="record, the raw channels only: cheaper during the run; add the "
                   "Foxglove channels later with topoexplore record --from OUT/run.mcap --out F")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--quiet", "-q", action="store_true", help="print only the final summary")
    add_bus_args(p)
    add_param_args(p)


SAMPLE_EVERY_M = 0.25  # [m] of travel between two points of the coverage timeline ...
SAMPLE_EVERY_S = 5.0  # [s] ... and of sim time at most
TRAIL_STEP_M = 0.02  # [m] a trail point when the robot moved further than this
WAITING_POINTS = 10_000  # map coverages the monitor keeps while their scans' sim status is
#   on its way


def timeline_due(last: tuple[float, float, float] | None, sim_time: float, path_length: float,
                 every: float = SAMPLE_EVERY_M) -> bool:
    """A coverage-timeline point is due at (sim_time [s], path_length [m]): ``every`` of
    travel or SAMPLE_EVERY_S of sim time after the ``last`` point (None: the first), and not
    before it. A bus run's monitor and a run in process (``bench explore``) sample alike."""
    return last is None or sim_time >= last[0] and (
        path_length - last[1] >= every or sim_time - last[0] >= SAMPLE_EVERY_S)


@dataclass
class Monitor:
    """Collects what the report needs from the bus (callbacks on zenoh threads)."""

    lock: threading.Lock = field(default_factory=threading.Lock)
    status: m.ExploreStatus | None = None
    sim: m.SimStatus | None = None
    sim_by_seq: dict[int, m.SimStatus] = field(default_factory=dict)
    grid: m.OccupancyGrid | None = None
    # the last few maps by the scan they describe: a map of a later scan can arrive before the
    # status that ended the run, and the report must describe exactly the ending scan's map
    grid_by_seq: dict[int, m.OccupancyGrid] = field(default_factory=dict)
    topo: m.TopoGraph | None = None
    rel: m.Reliability | None = None
    # the same for the topology and reliability messages, and the end node ids each
    # reliability message added to seen_end_ids / visited_ids
    topo_by_seq: dict[int, m.TopoGraph] = field(default_factory=dict)
    rel_by_seq: dict[int, m.Reliability] = field(default_factory=dict)
    ids_by_seq: dict[int, tuple[set[int], set[int]]] = field(default_factory=dict)
    plan: m.Path | None = None
    trail: list[tuple[float, float, int]] = field(default_factory=list)
    pose: tuple[float, float, float] | None = None
    segment: int = 0
    seg_target: tuple[int, float, float] | None = None
    seen_end_ids: set[int] = field(default_factory=set)
    visited_ids: set[int] = field(default_factory=set)
    ever_reliable: dict[int, bool] = field(default_factory=dict)
    targets: list[int] = field(default_factory=list)
    event: threading.Event = field(default_factory=threading.Event)
    # src_seq of the scan whose status ended the run: later outputs are ignored, so the
    # report, map and picture describe exactly that scan (deterministic in lockstep)
    end_seq: int | None = None
    # coverage over distance: (sim_time, path_length, coverage), sampled on map updates
    timeline: list[tuple[float, float, float]] = field(default_factory=list)
    coverage_fn: Any = None
    # the coverage of maps read before the sim status of their own scan, by scan: a timeline
    # point when that status comes
    sample_waiting: dict[int, float] = field(default_factory=dict)
    sample_every: float = SAMPLE_EVERY_M  # [m] of travel (and every SAMPLE_EVERY_S)
    first_motion: float | None = None  # [monotonic s] when the sim first reported travel
    # the robot's own estimate of its pose (odometry, corrected when the localizer runs),
    # compared with the truth at each truth stamp it covers: [m] sum of squares, max, count
    est: OdomBuffer | None = None
    pending: list[tuple[float, float, float]] = field(default_factory=list)
    pose_err: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])

    def on_status(self, msg: m.ExploreStatus) -> None:
        with self.lock:
            if self.end_seq is not None:
                return  # keep the status that ended the run (later scans repeat it)
            self.status = msg
            if msg.state in ("done", "failed"):
                self.end_seq = msg.header.src_seq
        if msg.state in ("done", "failed"):
            self.event.set()

    @property
    def status_seq(self) -> int:
        """The scan of the newest status read (-1 before any): the planner reports its scans
        in order, so the run ends on this scan or a later one, and what was kept for scans
        before the newest one at or before it can go (in lockstep the mapper runs plan_lag map
        periods ahead, and further while this monitor is busy: a fixed count of 4 maps once
        let the ending scan's map go, same seed, coverage 0.998 and 0.9979 on the bus)."""
        return self.status.header.src_seq if self.status is not None else -1

    def on_sim(self, msg: m.SimStatus) -> None:
        with self.lock:
            if self.first_motion is None and msg.path_length > 0.0:
                self.first_motion = time.monotonic()
            self.sim = msg
            self.sim_by_seq[msg.header.src_seq] = msg
            if len(self.sim_by_seq) > 200:
                for k in sorted(self.sim_by_seq)[:-100]:
                    del self.sim_by_seq[k]
            for k in sorted(k for k in self.sample_waiting if k <= msg.header.src_seq):
                self._add_point(self.sim_by_seq.get(k, msg), self.sample_waiting.pop(k))

    def ending_grid(self, seq: int) -> m.OccupancyGrid | None:
        """The map of scan ``seq``, else the latest of an earlier scan, else the latest (call
        with the lock held)."""
        return _at_scan(self.grid_by_seq, seq, self.grid)

    def use_ending(self, seq: int) -> None:
        """Map, topology and reliability of scan ``seq`` (the one that ended the run) for the
        report, and the end node ids seen or visited only in later scans' messages forgotten
        (call with the lock held)."""
        self.grid = self.ending_grid(seq)
        self.topo = _at_scan(self.topo_by_seq, seq, self.topo)
        self.rel = _at_scan(self.rel_by_seq, seq, self.rel)
        for k, (seen, visited) in self.ids_by_seq.items():
            if k > seq:
                self.seen_end_ids -= seen
                self.visited_ids -= visited

    def settle(self, seq: int, timeout: float) -> bool:
        """Wait up to ``timeout`` [s] until the sim status and the map of scan ``seq`` (the
        one whose status ended the run) are here. They come from other processes than that
        status, so they may still be on their way when it has been read. False if they never
        came (the report then describes the latest ones)."""
        deadline = time.monotonic() + timeout
        while True:
            with self.lock:
                if seq in self.sim_by_seq and seq in self.grid_by_seq:
                    return True
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.01)

    def on_estimate(self) -> None:
        """Odometry or a correction came: score the truth stamps the estimate now covers."""
        with self.lock:
            est = self.est
            if est is None:
                return
            newest = est.newest
            while self.pending and self.pending[0][0] <= newest:
                t, x, y = self.pending.pop(0)
                p = est.pose_at(t)
                if p is not None:
                    e = math.hypot(p[0] - x, p[1] - y)
                    self.pose_err[0] += e * e
                    self.pose_err[1] = max(self.pose_err[1], e)
                    self.pose_err[2] += 1

    def on_truth(self, msg: m.PoseStamped) -> None:
        with self.lock:
            p = convert.truth_from_msg(msg)
            self.pose = (p.x, p.y, p.theta)
            if self.est is not None and len(self.pending) < 1000:
                self.pending.append((msg.header.time, p.x, p.y))
            last = self.trail[-1] if self.trail else None
            if last is None or math.hypot(p.x - last[0], p.y - last[1]) > TRAIL_STEP_M:
                self.trail.append((p.x, p.y, self.segment))

    def on_plan(self, msg: m.Path) -> None:
        with self.lock:
            if self._late(msg):
                return  # a plan for a scan after the one that ended the run
            self.plan = msg
            if not msg.poses:
                return
            cur = (msg.target_id, msg.target_x, msg.target_y)
            prev = self.seg_target
            changed = prev is None or cur[0] != prev[0] or (
                cur[0] < 0 and math.hypot(cur[1] - prev[1], cur[2] - prev[2]) > 1.0)
            if changed:
                if prev is not None:
                    self.segment += 1
                self.seg_target = cur
                self.targets.append(msg.target_id)

    def _late(self, msg: Any) -> bool:
        return self.end_seq is not None and msg.header.src_seq > self.end_seq

    def on_rel(self, msg: m.Reliability) -> None:
        with self.lock:
            if self._late(msg):
                return
            self.rel = msg
            seen = {n.id for n in msg.nodes} - self.seen_end_ids
            visited = {n.id for n in msg.nodes if n.visited} - self.visited_ids
            self.seen_end_ids |= seen
            self.visited_ids |= visited
            seq = msg.header.src_seq
            _keep(self.rel_by_seq, seq, msg, self.status_seq)
            _keep(self.ids_by_seq, seq, (seen, visited), self.status_seq)

    def on_topo(self, msg: m.TopoGraph) -> None:
        with self.lock:
            if self._late(msg):
                return
            self.topo = msg
            _keep(self.topo_by_seq, msg.header.src_seq, msg, self.status_seq)

    def on_map(self, msg: m.OccupancyGrid) -> None:
        with self.lock:
            if self._late(msg):
                return
            self.grid = msg
            _keep(self.grid_by_seq, msg.header.src_seq, msg, self.status_seq)
            # the timeline pairs the map with the travel up to its own scan (the newest
            # status read may be a scan or more off it), as a run in process does
            seq = msg.header.src_seq
            sim = self.sim_by_seq.get(seq)
            if self.coverage_fn is None or sim is not None and not self._due(sim):
                return
        cov = self.coverage_fn(msg)  # outside the lock: the other inputs go on meanwhile
        with self.lock:
            sim = self.sim_by_seq.get(seq)
            if sim is not None:
                self._add_point(sim, cov)
                return
            # its status is still on its way: on_sim makes the point when it comes (only a
            # number is kept, so a monitor that falls behind keeps every map's point)
            self.sample_waiting[seq] = cov
            for k in sorted(self.sample_waiting)[:-WAITING_POINTS]:
                del self.sample_waiting[k]

    def _due(self, sim: m.SimStatus) -> bool:
        """A timeline point is due at ``sim`` (call with the lock held)."""
        return timeline_due(self.timeline[-1] if self.timeline else None, sim.sim_time,
                            sim.path_length, self.sample_every)

    def _add_point(self, sim: m.SimStatus, cov: float) -> None:
        """The timeline point of a map at ``sim`` (its scan's status), if due (call with the
        lock held)."""
        if self._due(sim):
            self.timeline.append((sim.sim_time, sim.path_length, cov))


def _keep(by_seq: dict[int, Any], seq: int, value: Any, status_seq: int) -> None:
    """by_seq[seq] = value, forgetting the scans before the newest one at or before
    ``status_seq`` (the run cannot end on them), and all but the GRIDS_KEPT latest."""
    by_seq[seq] = value
    keys = sorted(by_seq)
    floor = max((k for k in keys if k <= status_seq), default=keys[0])
    keys = [k for k in keys if k >= floor]
    for k in set(by_seq).difference(keys[-GRIDS_KEPT:]):
        del by_seq[k]


def _at_scan(by_seq: dict[int, Any], seq: int, latest: Any) -> Any:
    """The value of scan ``seq``, else of the latest earlier scan kept, else ``latest``."""
    done = [k for k in by_seq if k <= seq]
    return by_seq[max(done)] if done else latest


class Truth:
    """Ground-truth rasters of the world for coverage / accuracy: the solid cells, the free cells
    the robot can map (``target``, for ``coverage``) and every free cell connected to the start
    (``free``, for ``coverage_free``), at the map resolution (docs/design.md "Measuring a run").
    A map is given as the wire's OccupancyGrid (the monitor) or as a GridMap (a run in
    process, ``bench explore``)."""

    def __init__(self, world_name: str, p: Params):
        from topoexplore.sim.world import (
            load_world,
            rasterize,
            truth_free_reachable,
            truth_mappable,
        )

        self.world = load_world(world_name)
        self.resolution = resolution = p.mapper.resolution
        self.occ, ox, oy = rasterize(self.world, resolution)
        self.free, fx, fy = truth_free_reachable(self.world, resolution)
        self.target, _, _ = truth_mappable(self.world, resolution, p.robot.radius,
                                           p.laser.range_max)
        self.origin = (ox, oy)
        self.free_origin = (fx, fy)  # of both free and target

    def coverage(self, grid: m.OccupancyGrid | GridMap | None, p: Params) -> float:
        """Share of the free cells the robot can map that the map knows (``coverage``)."""
        return self._share(grid, p, self.target)

    def coverage_free(self, grid: m.OccupancyGrid | GridMap | None, p: Params) -> float:
        """Share of every free cell connected to the start that the map knows (the older
        figure, ``coverage_free``)."""
        return self._share(grid, p, self.free)

    def _share(self, grid: m.OccupancyGrid | GridMap | None, p: Params, truth) -> float:
        from topoexplore.tools.metrics import coverage

        if grid is None:
            return 0.0
        g = _domain(grid)
        return float(coverage(g.data, g.geom, truth, self.free_origin, self.resolution,
                              p.mapper.p_free, p.mapper.p_occ))

    def accuracy(self, grid: m.OccupancyGrid | GridMap | None, p: Params) -> float:
        from topoexplore.tools.metrics import map_accuracy

        if grid is None:
            return 0.0
        g = _domain(grid)
        return float(map_accuracy(g.data, g.geom, self.occ, self.origin, self.resolution,
                                  p.mapper.p_free, p.mapper.p_occ))


def _domain(grid: m.OccupancyGrid | GridMap) -> GridMap:
    return grid if isinstance(grid, GridMap) else convert.grid_from_msg(grid)


def _pose_error(mon: Monitor) -> dict[str, float | int]:
    sq, worst, n = mon.pose_err
    return {"rms": round(math.sqrt(sq / n), 4) if n else 0.0, "max": round(worst, 4),
            "samples": int(n)}


def make_report(*, world: str, strategy: str, seed: int, finished: bool, stop_reason: str,
                mon: Monitor, sim: m.SimStatus | None, wall: float, startup: float,
                coverage: float, coverage_free: float, accuracy: float, restarts: int,
                bad_messages: int, p_reliable: float, lockstep: bool,
                lost_messages: dict | None = None,
                planner: dict | None = None, warmup: float | None = None,
                first_motion: float | None = None,
                memory: dict | None = None, cpu: dict | None = None,
                recording: dict | None = None,
                checkpoints: dict | None = None,
                localizer: dict | None = None,
                reliability: dict | None = None) -> dict[str, Any]:
    """The report.json document. ``coverage``: share of the free cells the robot can map that
    the final map knows; ``coverage_free``: share of every free cell connected to the start."""
    rel = mon.rel
    final_nodes = rel.nodes if rel is not None else []
    accepted_remote = sum(1 for n in final_nodes
                          if n.p >= p_reliable and n.id not in mon.visited_ids)
    return {
        "world": world,
        "strategy": strategy,
        "seed": seed,
        "mode": "lockstep" if lockstep else "realtime",
        "finished": finished,
        "stop_reason": stop_reason,
        "sim_time_s": round(sim.sim_time, 3) if sim else 0.0,
        "wall_time_s": round(wall, 3),
        "startup_s": round(startup, 3),
        # [s] of startup spent compiling / loading the numba kernels (topoexplore warmup)
        "warmup_s": round(warmup, 3) if warmup is not None else None,
        # [s] from the command's start (parameters checked, truth mask built, stack started)
        # to the robot's first motion
        "first_motion_s": round(first_motion, 3) if first_motion is not None else None,
        "path_length_m": round(sim.path_length, 3) if sim else 0.0,
        "coverage": round(coverage, 4),
        "coverage_free": round(coverage_free, 4),
        "map_accuracy": round(accuracy, 4),
        "collisions": sim.collisions if sim else 0,
        # [m] the robot's own pose estimate (odometry, corrected by the localizer when it
        # runs) against the truth, at the truth's stamps
        "pose_error_m": _pose_error(mon),
        "end_nodes_seen": len(mon.seen_end_ids),
        "end_nodes_visited": len(mon.visited_ids),
        "end_nodes_accepted_remote": accepted_remote,
        "end_nodes_final": len(final_nodes),
        "targets": len(mon.targets),
        "restarts": restarts,
        "bad_messages": bad_messages,
        # messages that never reached a service, by header.seq ({service: {topic: n}}):
        # dropped under congestion (real time only: lockstep publishers block instead), lost
        # while a link or the router was down, refused by the transport
        "lost_messages": lost_messages or {},
        "lost_messages_total": sum(sum(v.values()) for v in (lost_messages or {}).values()),
        "lockstep_timeouts": sim.lockstep_timeouts if sim else 0,
        "watchdog_stops": sim.watchdog_stops if sim else 0,
        # cmd_vel the sim dropped as stale by stamp / clipped to the robot's limits
        "stale_cmds": sim.stale_cmds if sim else 0,
        "clipped_cmds": sim.clipped_cmds if sim else 0,
        "scans": sim.header.src_seq + 1 if sim else 0,
        "planner": planner,  # watchdog escalations and their log, learned obstacles
        # per process at the end of the run: resident now and its high-water mark [MB]
        "memory_mb": memory,
        # per process: CPU time used up to the end of the run (user, system) [s]
        "cpu_s": cpu,
        # with --record: messages per key in run.mcap, lost by header.seq, bad, file size
        "recording": _recording_summary(recording),
        # per service keeping a checkpoint (runtime.state_dir): written, failed, size, time per
        # write [ms], and what a restart resumed (known cells, age of the checkpoint)
        "checkpoints": checkpoints or {},
        # with the localizer: scans matched, kept (no trusted match: the guess stood), with
        # no map yet, and matched with odometry's guess kept along a corridor (degenerate)
        "localizer": localizer,
        # reliability core over the run: updates, movement resets of belief (an end node's
        # tip moved beyond move_tolerance: its P starts again at the prior) and the histories
        # dropped with vanished end nodes; nodes_reset: the end nodes still tracked at the end
        # that had a reset
        "reliability": reliability,
    }


def recording_metadata(args: argparse.Namespace, setup: Setup) -> dict[str, str]:
    """What ``replay`` needs to run the services as they ran: the overrides every service got
    (without the router endpoint) and the text of the --params file."""
    overrides = [o for o in setup.overrides
                 if not o.startswith(("bus.connect=", "runtime.state_dir="))]
    text = ""
    if args.params:
        try:
            text = Path(args.params).read_text()
        except OSError:
            text = ""
    return {"command": "run", "world": str(args.world), "strategy": args.strategy,
            "seed": str(args.seed), "lockstep": str(bool(args.lockstep)).lower(),
            "overrides": json.dumps(overrides), "params_toml": text}


def _recording_summary(st: dict | None) -> dict | None:
    if st is None:
        return None
    keep = ("path", "messages", "per_key", "foxglove", "gaps", "gaps_per_key", "first_seq",
            "restarts", "bad", "errors",
            "last_error", "bytes", "max_backlog")
    return {k: st[k] for k in keep if k in st}


def final_states(bus: Bus, keys: Keys, names: tuple[str, ...]) -> dict[str, dict]:
    """The state of each service in names, fetched once from its state queryable at the end
    of a run (one round trip each; a service that does not answer is left out)."""
    from topoexplore.tools.livestate import StateError, fetch_state

    out = {}
    for s in names:
        try:
            out[s] = fetch_state(bus, keys, s, timeout=1.0)
        except StateError:
            continue
    return out


def planner_robustness(state: dict) -> dict:
    """The report's ``planner`` entry from the planner's state (its core's snapshot)."""
    core = state.get("core") or {}
    wd, bl = core.get("watchdog") or {}, core.get("blocked") or {}
    return {"watchdog_escalations": wd.get("counts", {}), "watchdog_log": wd.get("log", []),
            "watchdog_approaches": wd.get("approaches", 0),
            "blocked_marks": bl.get("made", 0), "blocked_forgotten": bl.get("forgotten", 0),
            "blocked_released": bl.get("released", 0),
            "replans": core.get("replans", 0)}


def localizer_counts(state: dict) -> dict:
    """The report's ``localizer`` entry: the localizer's counters from its state."""
    return {k: state.get(k, 0) for k in ("matched", "kept", "no_map", "degenerate")}


def reliability_counts(state: dict) -> dict | None:
    """The report's ``reliability`` entry from the reliability service's state (its core's
    snapshot): updates, the movement resets of belief (an end node moved beyond
    move_tolerance, DESIGN §4), how many of the end nodes tracked at the end had one, and the
    histories dropped with vanished nodes; None without a snapshot."""
    snap = state.get("nodes")
    if not isinstance(snap, dict):
        return None
    nodes = snap.get("nodes") if isinstance(snap.get("nodes"), dict) else {}
    return {"updates": snap.get("updates", 0), "resets": snap.get("resets", 0),
            "nodes_reset": sum(1 for n in nodes.values()
                               if isinstance(n, dict) and n.get("resets", 0) > 0),
            "dropped": snap.get("dropped", 0)}


def checkpoint_counts(states: dict[str, dict]) -> dict:
    """The checkpoint counters of the services that keep one, from their states."""
    out = {}
    for s in ("sim", "mapper", "topology", "reliability", "planner", "localizer"):
        ck = states.get(s, {}).get("checkpoint")
        if isinstance(ck, dict) and ck.get("path"):
            out[s] = ck
    return out


def message_counts(states: dict[str, dict]) -> tuple[int, dict[str, dict[str, int]]]:
    """The services' bad messages (total) and messages lost on the way to each service, by
    header.seq ({service: {topic: n}}, only where some were lost), from their states."""
    total, lost = 0, {}
    for s, st in states.items():
        total += int(st.get("bad_messages_total", 0))
        per = {k: int(v) for k, v in (st.get("lost") or {}).items() if v}
        if per:
            lost[s] = per
    return total, lost


def write_timeline(path: Path, rows: Sequence[tuple[float, float, float]]) -> None:
    """``timeline.csv``: (sim time [s], path length [m], coverage) per sample."""
    with path.open("w") as f:
        f.write("sim_time_s,path_length_m,coverage\n")
        for t, d, c in rows:
            f.write(f"{t:.2f},{d:.3f},{c:.4f}\n")


def write_trail(path: Path, rows: Sequence[tuple[float, float, int]]) -> None:
    """``trail.csv``: the robot's true positions [m] and the target segment of each."""
    with path.open("w") as f:
        f.write("x,y,segment\n")
        for x, y, s in rows:
            f.write(f"{x:.3f},{y:.3f},{s}\n")


def write_outputs(out: Path, report: dict, mon: Monitor, truth: Truth, p: Params,
                  title: str) -> None:
    from topoexplore.common.mapio import write_map_server, write_png
    from topoexplore.tools.draw import Overlays, Style, render

    out.mkdir(parents=True, exist_ok=True)
    (out / "report.json").write_text(json.dumps(report, indent=2) + "\n")
    write_timeline(out / "timeline.csv", mon.timeline)
    write_trail(out / "trail.csv", mon.trail)
    topo_doc = {
        "topo": msgspec.to_builtins(mon.topo) if mon.topo else None,
        "reliability": msgspec.to_builtins(mon.rel) if mon.rel else None,
    }
    (out / "topology.json").write_text(json.dumps(topo_doc, indent=1) + "\n")
    if mon.grid is None:
        return
    g = convert.grid_from_msg(mon.grid)
    grid, geom = g.data, g.geom
    write_map_server(out / "map.yaml", grid, geom, p.mapper.p_free, p.mapper.p_occ)
    topo = convert.graph_from_msg(mon.topo) if mon.topo is not None else None
    rel = convert.beliefs_from_msg(mon.rel) if mon.rel is not None else None
    overlays = Overlays(topo=topo, rel=rel, robot_pose=mon.pose, trail=mon.trail,
                        target_id=mon.plan.target_id if mon.plan else -1)
    style = Style(p_free=p.mapper.p_free, p_occ=p.mapper.p_occ,
                  p_reliable=p.reliability.p_reliable, robot_radius=p.robot.radius, crop=True,
                  title=title)
    img = render(grid, geom, overlays, style)
    write_png(out / "final.png", img)


def run(args: argparse.Namespace) -> int:
    """``topoexplore run``: check the input, run the stack until exploration ends, write the
    outputs. Returns the exit code (0 finished, 1 not finished, 2 bad input)."""
    t_cmd = time.monotonic()
    try:
        setup = check_input(args)
    except InputError as exc:
        return _fail(str(exc), 2)
    truth = Truth(args.world, setup.params)
    console = Console.for_args(args)
    session = StackRun(args, setup, truth, console)
    outcome = session.execute()
    if session.mon.first_motion is not None:
        outcome.first_motion = session.mon.first_motion - t_cmd
    from topoexplore.common.mapio import MapIOError

    try:
        report = write_results(args, setup, truth, session.mon, outcome)
    except (OSError, MapIOError) as exc:  # a full disk or a vanished --out: the stack is
        return _fail(f"cannot write the results to {setup.out}: {exc}", 1)  # stopped already
    console.echo(summary_line(report, setup.out))
    if not outcome.finished:
        print(f"topoexplore: exploration did not finish: {outcome.reason}", file=sys.stderr)
        return 1
    return 0


# --- step 1: arguments and parameters ---------------------------------------------------------


class InputError(ValueError):
    """A bad argument or parameter: ``run`` exits 2 with this line before starting anything."""


@dataclass(frozen=True)
class Setup:
    """What the checked input gives a run: parameters (with the run's overrides), key space,
    the overrides the services get, and the output directory (created)."""

    params: Params
    keys: Keys
    overrides: list[str]
    out: Path

    @property
    def endpoint(self) -> str:
        return self.params.bus.connect


def check_input(args: argparse.Namespace) -> Setup:
    """Check every argument and parameter before anything starts; InputError otherwise."""
    from topoexplore.sim.world import WorldError, load_world, time_limit

    _fill_from_params(args)
    try:
        require("pymunk", "tqdm", what="topoexplore run")
        if getattr(args, "record_raw", False):
            require("mcap", what="topoexplore run --record-raw")
        elif getattr(args, "record", False):
            require("mcap", "foxglove", what="topoexplore run --record")
    except ExtraMissing as exc:
        raise InputError(str(exc)) from None
    if not (args.speed > 0 and math.isfinite(args.speed)):
        raise InputError("--speed must be a positive number")
    if args.max_sim_time is not None and not (args.max_sim_time > 0):
        raise InputError("--max-sim-time must be positive")
    try:
        world = load_world(args.world)
    except WorldError as exc:
        raise InputError(str(exc)) from None
    if args.max_sim_time is None:  # room to finish: a user's building is no fixed size
        args.max_sim_time = time_limit(world.area)
    if args.zenoh_config:
        try:
            check_config_file(args.zenoh_config)
        except BusError as exc:
            raise InputError(str(exc)) from None
    if args.connect and port_open(args.connect):
        raise InputError(f"--connect {args.connect}: the port is in use (another router or "
                         f"program listens there); run starts its own router, give it a free "
                         f"port or leave --connect out")
    overrides = run_overrides(args)
    params = _params_with(args, overrides)
    keys = Keys(params.bus.namespace, params.bus.robot)
    out = Path(args.out)
    try:
        out.mkdir(parents=True, exist_ok=True)
        if not params.runtime.state_dir:  # checkpoints: a restarted service resumes
            overrides.append(f"runtime.state_dir={json.dumps(str(out / 'state'))}")
            params = _params_with(args, overrides)
        clear_state_dir(params.runtime.state_dir)  # a new run: no earlier run's state
    except OSError as exc:
        raise InputError(f"cannot create output directory {out}: {exc}") from None
    return Setup(params, keys, overrides, out)


def _fill_from_params(args: argparse.Namespace) -> None:
    """--world, --seed, --speed and --strategy not given: the --params file's [sim] and
    [planner] values (they used to be overridden by the command line's defaults without a
    word), else the defaults."""
    if None not in (args.world, args.seed, args.speed, args.strategy):
        return
    try:
        base = load_params(getattr(args, "params", None), [])
    except ParamError as exc:
        raise InputError(str(exc)) from None
    if args.world is None:
        args.world = base.sim.world
    if args.seed is None:
        args.seed = base.sim.seed
    if args.speed is None:
        args.speed = base.sim.speed
    if args.strategy is None:
        args.strategy = base.planner.strategy


def run_overrides(args: argparse.Namespace) -> list[str]:
    """The ``--set`` overrides every service gets: world, seed, mode, speed and strategy of the
    run, the user's own ``--set``, a free router port unless ``--connect`` names one, and
    ``bus.mode`` peer where it is auto (the run's own router on this host: the services link
    to each other) unless the bus takes credentials (a peer's own endpoint would not ask)."""
    _fill_from_params(args)
    overrides = [f"sim.world={json.dumps(args.world)}", f"sim.seed={args.seed}",
                 f"runtime.lockstep={'true' if args.lockstep else 'false'}",
                 f"sim.speed={args.speed}", *strategy_overrides(args.strategy)] + list(args.set)
    if args.connect is None:
        endpoint = DEFAULT_ENDPOINT
        if port_open(endpoint):
            endpoint = f"tcp/127.0.0.1:{free_port()}"
        overrides.append(f'bus.connect="{endpoint}"')
    if _params_with(args, overrides).bus.mode == "auto" and not os.environ.get(CREDENTIALS_ENV):
        overrides.append('bus.mode="peer"')
    return overrides


def _params_with(args: argparse.Namespace, overrides: list[str]) -> Params:
    """The parameters as the services will see them (``args.set`` is left as it was)."""
    saved_set = args.set
    args.set = overrides
    try:
        return params_from_args(args)
    except ParamError as exc:
        raise InputError(str(exc)) from None
    finally:
        args.set = saved_set


# --- the console: progress bar and messages ------------------------------------------------


class Console:
    """Where ``run`` talks: stderr, through the progress bar when there is one (so a message
    does not tear the bar)."""

    def __init__(self, bar: Any = None):
        self.bar = bar

    @classmethod
    def for_args(cls, args: argparse.Namespace) -> Console:
        """With a tqdm bar over the sim time, unless ``--no-progress`` or ``--quiet``."""
        if args.no_progress or args.quiet:
            return cls()
        from tqdm import tqdm

        return cls(tqdm(total=round(args.max_sim_time), unit="s", desc=f"{args.world}",
                        dynamic_ncols=True, mininterval=0.3, file=sys.stderr,
                        bar_format="{desc}: {percentage:3.0f}%|{bar}| {n:.0f}/{total:.0f} sim s "
                                   "[{elapsed}{postfix}]"))

    def echo(self, line: str) -> None:
        if self.bar is not None:
            self.bar.write(line, file=sys.stderr)
        else:
            print(line, file=sys.stderr, flush=True)

    def progress(self, sim_t: float, coverage: float, st: m.ExploreStatus | None) -> None:
        """Show the sim time, coverage and the current target or state (only with a bar)."""
        tgt = ""
        if st is not None and st.target_id >= 0:
            tgt = f" target {st.target_id} (P={st.target_p:.2f})"
        elif st is not None:
            tgt = f" {st.state}"
        self.bar.set_postfix_str(f"coverage {coverage:.2f}{tgt}", refresh=False)
        self.bar.n = min(self.bar.total, sim_t)
        self.bar.refresh()

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


# --- steps 2-4: start the stack, watch the run, stop -------------------------------------------


@dataclass
class Outcome:
    """How the run went, for the report."""

    finished: bool = False
    reason: str = ""
    startup: float = 0.0  # [s] wall time until every service was up
    wall: float = 0.0  # [s] wall time of the run after startup
    sim: m.SimStatus | None = None  # the last sim status (the one of the final scan if done)
    restarts: int = 0
    bad: int = 0  # bad messages counted by the services
    lost: dict | None = None  # messages lost on the way to each service, by header.seq
    planner: dict | None = None  # the planner's robustness counters (planner_robustness)
    warmup: float | None = None  # [s] wall time of the kernel warm-up step (topoexplore warmup)
    first_motion: float | None = None  # [s] wall time from the command's start to first motion
    memory: dict | None = None  # resident memory per process [MB] (Supervisor.memory)
    cpu: dict | None = None  # CPU seconds per process (Supervisor.cpu)
    recording: dict | None = None  # the recorder's counts (tools.record.Recorder.stats)
    checkpoints: dict | None = None  # per service: its checkpoint counters (checkpoint_counts)
    localizer: dict | None = None  # the localizer's counters (localizer_counts), when it runs
    reliability: dict | None = None  # the reliability core's counters (reliability_counts)


class StackRun:
    """One run of the ``sim`` profile under the supervisor: :meth:`execute` starts router and
    services, watches the run until it ends (with the progress bar) and stops everything."""

    def __init__(self, args: argparse.Namespace, setup: Setup, truth: Truth, console: Console):
        from topoexplore.tools.launch.core import load_profile
        from topoexplore.tools.launch.supervisor import Supervisor, profile_path

        self.args, self.setup, self.truth, self.console = args, setup, truth, console
        self.mon = Monitor()
        self.mon.coverage_fn = lambda g: truth.coverage(g, setup.params)
        self.log: Any = (setup.out / "logs.txt").open("w")  # None once a write failed
        self.log_lock = threading.Lock()
        self.sup = Supervisor(load_profile(profile_path("sim")), setup.keys, setup.endpoint,
                              params_file=args.params, overrides=setup.overrides,
                              zenoh_config=args.zenoh_config, sink=self.sink,
                              log_level=args.log_level)
        self.stop = threading.Event()  # set by SIGINT / SIGTERM
        self.bus: Bus | None = None
        self.recorder: Any = None  # tools.record.Recorder with --record
        self.outcome = Outcome()

    def sink(self, line: str) -> None:
        """A log line of the stack: into logs.txt; warnings, errors and exits also shown."""
        with self.log_lock:
            if self.log is not None:
                try:
                    self.log.write(line + "\n")
                    self.log.flush()
                except OSError as exc:  # a full disk: say it once, keep the run (and the
                    self.log = None  # children's pipes) going
                    self.console.echo(f"topoexplore: cannot write logs.txt ({exc}); the stack's "
                                      f"log lines are not kept from here on")
        if not self.args.quiet and ("WARNING" in line or "ERROR" in line or "Traceback" in line
                                    or "[supervisor]" in line and "exited" in line
                                    or line.startswith("[warmup]") and "compil" in line):
            self.console.echo(line)

    def execute(self) -> Outcome:
        """Start, watch, collect; always stop the stack and restore the signal handlers."""
        restore = stop_on_signals(self.stop.set, self.sup.interrupted.set)
        out = self.outcome
        try:
            t_run = self._start()
            self._watch(t_run)
            self._collect()
        except BusError as exc:
            out.reason = f"bus error: {exc}"
            out.wall = 0.0
            out.sim = None
        finally:
            self.console.close()
            self.sup.stop()
            if self.bus is not None:
                self.bus.close()
            if self.recorder is not None:  # after the bus: no sample arrives any more
                out.recording = self.recorder.close()
            restore()
            with self.log_lock:
                if self.log is not None:
                    try:
                        self.log.close()
                    except OSError:
                        pass
                    self.log = None
        return out

    def _start(self) -> float:
        """Router first (so the monitor sees the run from its first message), the monitor's
        subscriptions, then the services. Returns the wall time [monotonic s] the run began."""
        args, keys, mon = self.args, self.setup.keys, self.mon
        t0 = time.monotonic()
        if not args.quiet:
            mode = "lockstep" if args.lockstep else f"real time x{args.speed:g}"
            self.console.echo(f"exploring {args.world} with strategy {args.strategy} ({mode}, "
                              f"seed {args.seed}) on {self.setup.endpoint} as {keys.prefix}; "
                              f"logs in {self.setup.out / 'logs.txt'}")
        self.sup.start_router()
        self.bus = bus = Bus.client(self.setup.endpoint, name="run",
                                    config_file=args.zenoh_config, wait_for_router=True,
                                    shared_memory=self.setup.params.bus.shared_memory)
        bus.subscribe(keys.explore_status, m.ExploreStatus, lambda msg, k: mon.on_status(msg))
        bus.subscribe(keys.sim_status, m.SimStatus, lambda msg, k: mon.on_sim(msg))
        bus.subscribe(keys.truth, m.PoseStamped, lambda msg, k: mon.on_truth(msg))
        est = mon.est = OdomBuffer(corrected=self.setup.params.localizer.enabled)

        def on_odom(msg: m.Odometry, _k: str) -> None:
            est.add(msg.header.time, convert.pose_from_msg(msg.pose.pose), msg.header.seq)
            mon.on_estimate()

        def on_correction(msg: m.TransformStamped, _k: str) -> None:
            est.add_correction(msg.header.time, convert.correction_from_msg(msg))
            mon.on_estimate()

        bus.subscribe(keys.topic("odom"), m.Odometry, on_odom)
        if est.corrected:
            bus.subscribe(keys.topic("map_odom"), m.TransformStamped, on_correction)
        bus.subscribe(keys.plan, m.Path, lambda msg, k: mon.on_plan(msg))
        bus.subscribe(keys.reliability, m.Reliability, lambda msg, k: mon.on_rel(msg))
        bus.subscribe(keys.topo, m.TopoGraph, lambda msg, k: mon.on_topo(msg))
        bus.subscribe(keys.map, m.OccupancyGrid, lambda msg, k: mon.on_map(msg))
        raw = getattr(args, "record_raw", False)
        if args.record or raw:
            self._record(bus, foxglove=not raw)
        if not self.sup.start():
            self.outcome.reason = "stack did not come up (see logs.txt)"
        self.outcome.startup = time.monotonic() - t0
        return time.monotonic()

    def _record(self, bus: Bus, foxglove: bool) -> None:
        """Every key of the robot into OUT/run.mcap, subscribed before any service starts so
        that the file holds the run from its first message (foxglove False: the raw channels
        only, --record-raw)."""
        from topoexplore.tools.record import Recorder

        p = self.setup.params
        rec = self.recorder = Recorder(
            self.setup.out / "run.mcap", self.setup.keys.prefix, foxglove=foxglove,
            laser_offset=p.laser.offset,
            p_reliable=p.reliability.p_reliable,
            metadata=recording_metadata(self.args, self.setup))
        bus.subscribe_raw(f"{self.setup.keys.prefix}/**", lambda k, b, _e: rec.put(k, b))

    def _watch(self, t_run: float) -> None:
        """Until the run ends: keep the services running, show progress, check the limits."""
        out, mon = self.outcome, self.mon
        last_cov_wall = 0.0
        while not out.reason and not self.stop.is_set():
            self.sup.poll()
            mon.event.wait(0.1)
            with mon.lock:
                st, sim, grid = mon.status, mon.sim, mon.grid
            sim_t = sim.sim_time if sim else 0.0
            now = time.monotonic()
            if self.console.bar is not None and now - last_cov_wall > 1.0:
                last_cov_wall = now
                self.console.progress(sim_t, self.truth.coverage(grid, self.setup.params), st)
            if st is not None and st.state in ("done", "failed"):
                out.finished = st.state == "done"
                out.reason = f"{st.state}: {st.reason}"
            else:
                out.reason = self._limit_reached(sim_t, now - t_run)
        if self.stop.is_set() and not out.reason:
            out.reason = "interrupted"
        out.wall = time.monotonic() - t_run if out.startup else 0.0

    def _limit_reached(self, sim_t: float, wall: float) -> str:
        """Why the run must stop although exploration has not ended ("" while it may go on)."""
        args = self.args
        if sim_t >= args.max_sim_time:
            return f"max sim time {args.max_sim_time:g} s reached"
        if args.max_wall_time and wall > args.max_wall_time:
            return f"max wall time {args.max_wall_time:g} s reached"
        if any(s.given_up for s in self.sup.states.values()):
            return "a service kept crashing (see logs.txt)"
        return ""

    def _collect(self) -> None:
        """The final sim status (of the very scan that ended a finished run: deterministic in
        lockstep), the restarts and the services' bad-message counts."""
        out, mon = self.outcome, self.mon
        if out.finished and mon.end_seq is not None and self.args.lockstep:
            mon.settle(mon.end_seq, END_WAIT)  # (in real time the sim reports at status_hz,
            #   not on every scan: the latest status is the report's)
        with mon.lock:
            st = mon.status
            out.sim = mon.sim
            if out.finished and st is not None and st.header.src_seq in mon.sim_by_seq:
                out.sim = mon.sim_by_seq[st.header.src_seq]
            if out.finished and mon.end_seq is not None:
                mon.use_ending(mon.end_seq)
        out.restarts = self.sup.restarts
        out.warmup = self.sup.warm_s
        out.memory = self.sup.memory() or None
        out.cpu = self.sup.cpu() or None
        if out.startup:
            self._final_counts(out)

    def _final_counts(self, out: Outcome) -> None:
        """The report's counters from the services' states, each fetched once."""
        from topoexplore.common.keys import SERVICES

        loc = ("localizer",) if self.setup.params.localizer.enabled else ()
        states = final_states(self.bus, self.setup.keys, SERVICES + loc)

        def read(name: str, fn):  # None where the service did not answer (or does not run)
            return fn(states[name]) if name in states else None

        out.bad, out.lost = message_counts({s: states[s] for s in SERVICES if s in states})
        out.planner = read("planner", planner_robustness)
        out.checkpoints = checkpoint_counts(states)
        out.localizer = read("localizer", localizer_counts)
        out.reliability = read("reliability", reliability_counts)


# --- step 5: the report and the files ------------------------------------------------------


def write_results(args: argparse.Namespace, setup: Setup, truth: Truth, mon: Monitor,
                  outcome: Outcome) -> dict[str, Any]:
    """Final coverage and accuracy, the report, and every output file. Returns the report."""
    params, sim = setup.params, outcome.sim
    with mon.lock:
        coverage = truth.coverage(mon.grid, params)
        coverage_free = truth.coverage_free(mon.grid, params)
        if sim is not None:  # the maps of scans after the ending one are not the run's
            mon.timeline[:] = [p for p in mon.timeline if p[0] < sim.sim_time]
            mon.timeline.append((sim.sim_time, sim.path_length, coverage))
        accuracy = truth.accuracy(mon.grid, params)
        report = make_report(world=args.world, strategy=args.strategy, seed=args.seed,
                             finished=outcome.finished, stop_reason=outcome.reason, mon=mon,
                             sim=sim, wall=outcome.wall, startup=outcome.startup,
                             coverage=coverage, coverage_free=coverage_free, accuracy=accuracy,
                             restarts=outcome.restarts, bad_messages=outcome.bad,
                             lost_messages=outcome.lost,
                             p_reliable=params.reliability.p_reliable, lockstep=args.lockstep,
                             planner=outcome.planner, warmup=outcome.warmup,
                             first_motion=outcome.first_motion, memory=outcome.memory,
                             cpu=outcome.cpu, recording=outcome.recording,
                             checkpoints=outcome.checkpoints, localizer=outcome.localizer,
                             reliability=outcome.reliability)
        title = (f"{args.world} / {args.strategy} / seed {args.seed}: "
                 f"{'finished' if outcome.finished else 'not finished'}, "
                 f"{report['path_length_m']:.1f} m, {report['sim_time_s']:.0f} s, "
                 f"coverage {coverage:.2f}")
        write_outputs(setup.out, report, mon, truth, params, title)
    return report


def summary_line(r: dict, out: Path) -> str:
    return (f"{'finished' if r['finished'] else 'NOT finished'} ({r['stop_reason']}): "
            f"path {r['path_length_m']:.1f} m, sim {r['sim_time_s']:.0f} s, wall "
            f"{r['wall_time_s']:.1f} s, coverage {r['coverage']:.3f} (of all free "
            f"{r['coverage_free']:.3f}), accuracy "
            f"{r['map_accuracy']:.3f}, collisions {r['collisions']}, end nodes seen "
            f"{r['end_nodes_seen']} / visited {r['end_nodes_visited']} / accepted remotely "
            f"{r['end_nodes_accepted_remote']} -> {out}/report.json, {out}/final.png")


def _fail(text: str, code: int) -> int:
    print(f"topoexplore: {text}", file=sys.stderr)
    return code
