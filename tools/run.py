"""``topoexplore run``: the main job — explore a world with every service as its own process.

Starts the ``sim`` launch profile under the supervisor (router + six services), watches the
run over the bus (status, sim clock, ground truth, map, topo, reliability, plan) with a
progress bar, and at the end writes to ``--out``:

- ``report.json`` — metrics of DESIGN §6 (see :func:`make_report`);
- ``final.png`` — grid, skeleton, nodes with ``id(P)``, the path coloured by target segment;
- ``map.pgm`` + ``map.yaml`` (ROS map_server) and ``topology.json``; ``trail.csv``; ``logs.txt``.

Exit code 0 when exploration finished, 1 with a one-line reason otherwise, 2 on bad input.
"""

from __future__ import annotations

import argparse
import json
import math
import signal
import socket
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgspec

from topoexplore.common import messages as m
from topoexplore.common.bus import Bus, BusError
from topoexplore.common.grid import GridGeometry
from topoexplore.common.keys import Keys
from topoexplore.common.node import add_bus_args, add_param_args, params_from_args
from topoexplore.common.params import STRATEGIES, ParamError, Params


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--world", default="paper-room", help="built-in world name or world file")
    p.add_argument("--strategy", default="reliability", choices=STRATEGIES)
    p.add_argument("--lockstep", action="store_true",
                   help="deterministic lockstep simulation (faster than real time)")
    p.add_argument("--speed", type=float, default=1.0, help="real-time factor (real-time mode)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--max-sim-time", type=float, default=900.0,
                   help="give up after this much simulated time [s]")
    p.add_argument("--max-wall-time", type=float, default=0.0,
                   help="give up after this much wall time [s] (0: no limit)")
    p.add_argument("--out", default="runs/latest", help="output directory")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--quiet", "-q", action="store_true", help="print only the final summary")
    add_bus_args(p)
    add_param_args(p)


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def port_in_use(endpoint: str) -> bool:
    try:
        host, port = endpoint.split("/", 1)[1].rsplit(":", 1)
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            s.settimeout(0.2)
            return s.connect_ex((host, int(port))) == 0
    except (ValueError, OSError, IndexError):
        return False


@dataclass
class Monitor:
    """Collects what the report needs from the bus (callbacks on zenoh threads)."""

    lock: threading.Lock = field(default_factory=threading.Lock)
    status: m.ExploreStatus | None = None
    sim: m.SimStatus | None = None
    sim_by_seq: dict[int, m.SimStatus] = field(default_factory=dict)
    grid: m.OccupancyGrid | None = None
    topo: m.TopoGraph | None = None
    rel: m.Reliability | None = None
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
    sample_every: float = 0.25  # [m] of travel (and at least every 5 s of sim time)

    def on_status(self, msg: m.ExploreStatus) -> None:
        with self.lock:
            if self.end_seq is not None:
                return  # keep the status that ended the run (later scans repeat it)
            self.status = msg
            if msg.state in ("done", "failed"):
                self.end_seq = msg.header.src_seq
        if msg.state in ("done", "failed"):
            self.event.set()

    def on_sim(self, msg: m.SimStatus) -> None:
        with self.lock:
            self.sim = msg
            self.sim_by_seq[msg.header.src_seq] = msg
            if len(self.sim_by_seq) > 200:
                for k in sorted(self.sim_by_seq)[:-100]:
                    del self.sim_by_seq[k]

    def on_truth(self, msg: m.Pose) -> None:
        with self.lock:
            p = msg.pose
            self.pose = (p.x, p.y, p.theta)
            if not self.trail or math.hypot(p.x - self.trail[-1][0], p.y - self.trail[-1][1]) > 0.02:
                self.trail.append((p.x, p.y, self.segment))

    def on_plan(self, msg: m.Path) -> None:
        with self.lock:
            self.plan = msg
            if not msg.waypoints:
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
            for n in msg.nodes:
                self.seen_end_ids.add(n.id)
                if n.visited:
                    self.visited_ids.add(n.id)

    def on_topo(self, msg: m.TopoGraph) -> None:
        with self.lock:
            if self._late(msg):
                return
            self.topo = msg

    def on_map(self, msg: m.OccupancyGrid) -> None:
        with self.lock:
            if self._late(msg):
                return
            self.grid = msg
            sim = self.sim
            last = self.timeline[-1] if self.timeline else None
        if self.coverage_fn is None or sim is None:
            return
        if last is None or sim.path_length - last[1] >= self.sample_every \
                or sim.sim_time - last[0] >= 5.0:
            cov = self.coverage_fn(msg)
            with self.lock:
                self.timeline.append((sim.sim_time, sim.path_length, cov))


class Truth:
    """Ground-truth rasters of the world for coverage / accuracy."""

    def __init__(self, world_name: str, resolution: float):
        from topoexplore.sim.world import load_world, rasterize, truth_free_reachable

        self.world = load_world(world_name)
        self.resolution = resolution
        self.occ, ox, oy = rasterize(self.world, resolution)
        self.free, fx, fy = truth_free_reachable(self.world, resolution)
        self.origin = (ox, oy)
        self.free_origin = (fx, fy)

    def coverage(self, grid: m.OccupancyGrid | None, p: Params) -> float:
        from topoexplore.tools.metrics import coverage

        if grid is None:
            return 0.0
        return float(coverage(m.grid_to_array(grid), GridGeometry.of(grid), self.free,
                              self.free_origin, self.resolution, p.mapper.p_free, p.mapper.p_occ))

    def accuracy(self, grid: m.OccupancyGrid | None, p: Params) -> float:
        from topoexplore.tools.metrics import map_accuracy

        if grid is None:
            return 0.0
        return float(map_accuracy(m.grid_to_array(grid), GridGeometry.of(grid), self.occ,
                                  self.origin, self.resolution, p.mapper.p_free, p.mapper.p_occ))


def make_report(*, world: str, strategy: str, seed: int, finished: bool, stop_reason: str,
                mon: Monitor, sim: m.SimStatus | None, wall: float, startup: float,
                coverage: float, accuracy: float, restarts: int, bad_messages: int,
                p_reliable: float, lockstep: bool) -> dict[str, Any]:
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
        "path_length_m": round(sim.path_length, 3) if sim else 0.0,
        "coverage": round(coverage, 4),
        "map_accuracy": round(accuracy, 4),
        "collisions": sim.collisions if sim else 0,
        "end_nodes_seen": len(mon.seen_end_ids),
        "end_nodes_visited": len(mon.visited_ids),
        "end_nodes_accepted_remote": accepted_remote,
        "end_nodes_final": len(final_nodes),
        "targets": len(mon.targets),
        "restarts": restarts,
        "bad_messages": bad_messages,
        "lockstep_timeouts": sim.lockstep_timeouts if sim else 0,
        "watchdog_stops": sim.watchdog_stops if sim else 0,
        "scans": sim.header.src_seq + 1 if sim else 0,
    }


def _bad_message_total(bus: Bus, keys: Keys) -> int:
    from topoexplore.common.keys import SERVICES
    from topoexplore.tools.livestate import StateError, fetch_state

    total = 0
    for s in SERVICES:
        try:
            st = fetch_state(bus, keys, s, timeout=1.0)
            total += int(st.get("bad_messages_total", 0))
        except StateError:
            pass
    return total


def write_outputs(out: Path, report: dict, mon: Monitor, truth: Truth, p: Params,
                  title: str) -> None:
    from topoexplore.common.mapio import write_map_server, write_png
    from topoexplore.tools.draw import render

    out.mkdir(parents=True, exist_ok=True)
    (out / "report.json").write_text(json.dumps(report, indent=2) + "\n")
    with (out / "timeline.csv").open("w") as f:
        f.write("sim_time_s,path_length_m,coverage\n")
        for t, d, c in mon.timeline:
            f.write(f"{t:.2f},{d:.3f},{c:.4f}\n")
    with (out / "trail.csv").open("w") as f:
        f.write("x,y,segment\n")
        for x, y, s in mon.trail:
            f.write(f"{x:.3f},{y:.3f},{s}\n")
    topo_doc = {
        "topo": msgspec.to_builtins(mon.topo) if mon.topo else None,
        "reliability": msgspec.to_builtins(mon.rel) if mon.rel else None,
    }
    (out / "topology.json").write_text(json.dumps(topo_doc, indent=1) + "\n")
    if mon.grid is None:
        return
    grid = m.grid_to_array(mon.grid)
    geom = GridGeometry.of(mon.grid)
    write_map_server(out / "map.yaml", grid, geom, p.mapper.p_free, p.mapper.p_occ)
    img = render(grid, geom, topo=mon.topo, rel=mon.rel, robot_pose=mon.pose, trail=mon.trail,
                 target_id=mon.plan.target_id if mon.plan else -1, title=title,
                 p_free=p.mapper.p_free, p_occ=p.mapper.p_occ, p_reliable=p.planner.p_reliable,
                 robot_radius=p.sim.robot_radius, crop=True)
    write_png(out / "final.png", img)


def run(args: argparse.Namespace) -> int:
    from topoexplore.sim.world import WorldError, load_world
    from topoexplore.tools.launch.core import load_profile
    from topoexplore.tools.launch.supervisor import Supervisor, profile_path

    # -- validate everything before starting anything -------------------------------------
    if not (args.speed > 0 and math.isfinite(args.speed)):
        return _fail("--speed must be a positive number", 2)
    if not (args.max_sim_time > 0):
        return _fail("--max-sim-time must be positive", 2)
    try:
        load_world(args.world)
    except WorldError as exc:
        return _fail(str(exc), 2)
    overrides = [f"sim.world={json.dumps(args.world)}", f"sim.seed={args.seed}",
                 f"sim.lockstep={'true' if args.lockstep else 'false'}",
                 f"sim.speed={args.speed}", f'planner.strategy="{args.strategy}"'] + list(args.set)
    if args.connect is None:
        endpoint = "tcp/127.0.0.1:7447"
        if port_in_use(endpoint):
            endpoint = f"tcp/127.0.0.1:{free_port()}"
        overrides.append(f'bus.connect="{endpoint}"')
    saved_set = args.set
    args.set = overrides
    try:
        params = params_from_args(args)
    except ParamError as exc:
        return _fail(str(exc), 2)
    finally:
        args.set = saved_set
    keys = Keys(params.bus.namespace, params.bus.robot)
    endpoint = params.bus.connect
    out = Path(args.out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        return _fail(f"cannot create output directory {out}: {exc}", 2)
    truth = Truth(args.world, params.mapper.resolution)

    logf = (out / "logs.txt").open("w")
    log_lock = threading.Lock()
    quiet = args.quiet

    def sink(line: str) -> None:
        with log_lock:
            logf.write(line + "\n")
            logf.flush()
        if not quiet and ("WARNING" in line or "ERROR" in line or "Traceback" in line
                          or "[supervisor]" in line and "exited" in line):
            _echo(line)

    bar = None
    if not (args.no_progress or quiet):
        from tqdm import tqdm

        bar = tqdm(total=round(args.max_sim_time), unit="s", desc=f"{args.world}",
                   dynamic_ncols=True, mininterval=0.3, file=sys.stderr,
                   bar_format="{desc}: {percentage:3.0f}%|{bar}| {n:.0f}/{total:.0f} sim s "
                              "[{elapsed}{postfix}]")
        global _BAR
        _BAR = bar

    profile = load_profile(profile_path("sim"))
    sup = Supervisor(profile, keys, endpoint, params_file=args.params, overrides=overrides,
                     zenoh_config=args.zenoh_config, sink=sink)
    stop = threading.Event()
    interrupted = []

    def on_signal(signum: int, frame: Any) -> None:
        interrupted.append(signum)
        stop.set()

    old_int = signal.signal(signal.SIGINT, on_signal)
    old_term = signal.signal(signal.SIGTERM, on_signal)
    mon = Monitor()
    mon.coverage_fn = lambda g: truth.coverage(g, params)
    bus: Bus | None = None
    t0 = time.monotonic()
    finished, reason = False, ""
    startup = 0.0
    restarts = bad = 0
    try:
        if not quiet:
            _echo(f"exploring {args.world} with strategy {args.strategy} "
                  f"({'lockstep' if args.lockstep else f'real time x{args.speed:g}'}, seed "
                  f"{args.seed}) on {endpoint} as {keys.prefix}; logs in {out / 'logs.txt'}")
        sup.start_router()  # first, so the monitor below sees the run from its first message
        bus = Bus.client(endpoint, name="run", config_file=args.zenoh_config, wait_for_router=True)
        bus.subscribe(keys.explore_status, m.ExploreStatus, lambda msg, k: mon.on_status(msg))
        bus.subscribe(keys.sim_status, m.SimStatus, lambda msg, k: mon.on_sim(msg))
        bus.subscribe(keys.truth, m.Pose, lambda msg, k: mon.on_truth(msg))
        bus.subscribe(keys.plan, m.Path, lambda msg, k: mon.on_plan(msg))
        bus.subscribe(keys.reliability, m.Reliability, lambda msg, k: mon.on_rel(msg))
        bus.subscribe(keys.topo, m.TopoGraph, lambda msg, k: mon.on_topo(msg))
        bus.subscribe(keys.map, m.OccupancyGrid, lambda msg, k: mon.on_map(msg))
        if not sup.start():
            reason = "stack did not come up (see logs.txt)"
        startup = time.monotonic() - t0
        t_run = time.monotonic()
        last_cov_wall = 0.0
        cov = 0.0
        while not reason and not stop.is_set():
            sup.poll()
            mon.event.wait(0.1)
            with mon.lock:
                st, sim, grid = mon.status, mon.sim, mon.grid
            sim_t = sim.sim_time if sim else 0.0
            now = time.monotonic()
            if bar is not None and now - last_cov_wall > 1.0:
                last_cov_wall = now
                cov = truth.coverage(grid, params)
                tgt = ""
                if st is not None and st.target_id >= 0:
                    tgt = f" target {st.target_id} (P={st.target_p:.2f})"
                elif st is not None:
                    tgt = f" {st.state}"
                bar.set_postfix_str(f"coverage {cov:.2f}{tgt}", refresh=False)
                bar.n = min(bar.total, sim_t)
                bar.refresh()
            if st is not None and st.state in ("done", "failed"):
                finished = st.state == "done"
                reason = f"{st.state}: {st.reason}"
                break
            if sim_t >= args.max_sim_time:
                reason = f"max sim time {args.max_sim_time:g} s reached"
                break
            if args.max_wall_time and now - t_run > args.max_wall_time:
                reason = f"max wall time {args.max_wall_time:g} s reached"
                break
            if any(s.given_up for s in sup.states.values()):
                reason = "a service kept crashing (see logs.txt)"
                break
        if stop.is_set() and not reason:
            reason = "interrupted"
        wall = time.monotonic() - t_run if startup else 0.0
        with mon.lock:
            st = mon.status
            sim = mon.sim
            if finished and st is not None and st.header.src_seq in mon.sim_by_seq:
                sim = mon.sim_by_seq[st.header.src_seq]  # deterministic: the scan of 'done'
        restarts = sup.restarts
        bad = _bad_message_total(bus, keys) if startup else 0
    except BusError as exc:
        reason = f"bus error: {exc}"
        wall = 0.0
        sim = None
    finally:
        if bar is not None:
            bar.close()
        sup.stop()
        if bus is not None:
            bus.close()
        signal.signal(signal.SIGINT, old_int)
        signal.signal(signal.SIGTERM, old_term)
        logf.close()
    with mon.lock:
        coverage = truth.coverage(mon.grid, params)
        if sim is not None:
            mon.timeline.append((sim.sim_time, sim.path_length, coverage))
        accuracy = truth.accuracy(mon.grid, params)
        report = make_report(world=args.world, strategy=args.strategy, seed=args.seed,
                             finished=finished, stop_reason=reason, mon=mon, sim=sim, wall=wall,
                             startup=startup, coverage=coverage, accuracy=accuracy,
                             restarts=restarts, bad_messages=bad,
                             p_reliable=params.planner.p_reliable, lockstep=args.lockstep)
        title = (f"{args.world} / {args.strategy} / seed {args.seed}: "
                 f"{'finished' if finished else 'not finished'}, {report['path_length_m']:.1f} m, "
                 f"{report['sim_time_s']:.0f} s, coverage {coverage:.2f}")
        write_outputs(out, report, mon, truth, params, title)
    _echo(summary_line(report, out))
    if not finished:
        print(f"topoexplore: exploration did not finish: {reason}", file=sys.stderr)
        return 1
    return 0


def summary_line(r: dict, out: Path) -> str:
    return (f"{'finished' if r['finished'] else 'NOT finished'} ({r['stop_reason']}): "
            f"path {r['path_length_m']:.1f} m, sim {r['sim_time_s']:.0f} s, wall "
            f"{r['wall_time_s']:.1f} s, coverage {r['coverage']:.3f}, accuracy "
            f"{r['map_accuracy']:.3f}, collisions {r['collisions']}, end nodes seen "
            f"{r['end_nodes_seen']} / visited {r['end_nodes_visited']} / accepted remotely "
            f"{r['end_nodes_accepted_remote']} -> {out}/report.json, {out}/final.png")


_BAR = None


def _echo(line: str) -> None:
    if _BAR is not None:
        _BAR.write(line, file=sys.stderr)
    else:
        print(line, file=sys.stderr, flush=True)


def _fail(text: str, code: int) -> int:
    print(f"topoexplore: {text}", file=sys.stderr)
    return code
