"""The exploration pipeline in one process, for tuning: ``topoexplore bench inproc``.

    topoexplore bench inproc [--worlds a,b] [--strategies ...] [--seeds N] [--set k=v ...]
                             [--jobs 2] [--max-sim-time S] [--json OUT] [--wire]
                             [--pose-trace DIR]

The six cores (sim, mapper, topology, reliability, planner, controller) are called in one
loop in the order the services run them in lockstep (with ``--set localizer.enabled=true``
the localizer too: each scan matched against the map of the scans before it, and every core
then takes odometry composed with its correction): every scan is integrated; on the first
scan of every ``mapper.map_every`` block the map goes through topology, reliability and
planner; the controller answers every scan with the newest plan (with ``runtime.plan_lag`` =
L, the plan of the map L map periods before, as the controller does in lockstep). The cores
pass domain objects (``common.domain``) to each other, odometry through its message
conversion (the one that is not exact: a heading through a quaternion and back may differ
in its last bit, and the services read what comes back); with ``--wire`` every hop goes through
the same message conversions and codec as on the bus (``common.convert``). Each run also
reports ``stage_s``, the compute seconds of each core (the sim's scans and physics steps,
the mapper, topology, reliability, planner, controller), summed in one line over the runs.
No bus and no processes, so a parameter sweep over the suite costs the compute alone (about
1/3 of the CPU of the same runs on the bus). A run gives the same path, sim time and coverage
as the bus run of the same world, strategy, seed and parameters (``tests/test_explore_e2e.py``
checks it on dead-end, office and paper-room; a 60 x 60 m world to 1800 s was checked by
hand: docs/benchmarks.md). ``bench explore`` runs its suite through :func:`run` and checks a
sample of its runs on the real processes (:mod:`.explore_local`).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections import deque
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

from topoexplore.common import convert
from topoexplore.common import messages as m
from topoexplore.common.domain import Pose, Scan, compose, inverse
from topoexplore.common.params import (
    STRATEGIES,
    STRATEGY_NAMES,
    Params,
    load_params,
    params_to_dict,
    strategy_overrides,
)
from topoexplore.services.controller.core import ControllerCore
from topoexplore.services.localizer.core import LocalizerCore
from topoexplore.services.mapper.core import MapperCore
from topoexplore.services.planner.core import PlannerCore
from topoexplore.services.reliability.core import ReliabilityCore
from topoexplore.services.topology.core import TopologyCore
from topoexplore.sim.core import SimCore
from topoexplore.sim.world import World, load_world, truth_free_reachable, truth_mappable
from topoexplore.tools.bench.explore import (
    BenchArgError,
    check_overrides,
    default_worlds,
    pair_ratios,
    parse_strategies,
    resolve_world,
)
from topoexplore.tools.metrics import coverage


class Wire:
    """Send each domain object through the wire and back (convert, encode, decode, convert):
    the in-process run then sees exactly what the services see over the bus."""

    def __init__(self) -> None:
        self.k = 0

    def __call__(self, obj: Any, to_msg: Callable, from_msg: Callable, msg_type: type) -> Any:
        self.k += 1
        hdr = m.header(self.k, 0.0, "map", self.k)
        return from_msg(m.decode(m.encode(to_msg(obj, hdr)), msg_type))


def _direct(obj: Any, *_: Any) -> Any:
    return obj


def _converted(obj: Any, to_msg: Callable, from_msg: Callable, _msg_type: type) -> Any:
    """The message conversion alone, for the one hop whose conversion is not exact: odometry's
    heading goes through a quaternion and may come back a last bit off (0.5800000000000001 ->
    0.5800000000000002), and every service on the bus reads the converted heading. Encoding
    is exact and left out. Without it a frontier run on a generated warehouse drove 324.8 m in
    process and 305.7 m on the bus (docs/benchmarks.md)."""
    return from_msg(to_msg(obj, m.header(0, 0.0, "odom", 0)))


class _Localized:
    """The localizer as its service runs it in lockstep: each scan matched against the map
    published before it, from odometry composed with the correction in force; the pose every
    other core takes is odometry composed with the new correction. Without the localizer the
    pose is odometry's. ``errors``: [m] the estimate against the truth, once per scan;
    ``headings``: [rad] the same for the heading. With ``trace`` every scan's stamp, odometry,
    truth, estimate and match is kept for :meth:`trace_arrays` (``bench posetrace``)."""

    def __init__(self, P: Params, hop: Callable, trace: bool = False):
        self.core = LocalizerCore(P.localizer, P.laser.offset, P.mapper.occupancy) \
            if P.localizer.enabled else None
        self.hop = hop
        self.correction = Pose(0.0, 0.0, 0.0)
        self.grid = None  # the newest map, not yet handed to the matcher
        self.errors: list[float] = []
        self.headings: list[float] = []
        self.rows: list[tuple] | None = [] if trace else None
        self.ranges: list[np.ndarray] = []  # with trace: each scan's ranges [m]
        self.scan_geom: tuple[float, ...] = ()  # angle_min, angle_increment, range_min, max
        self.params = json.dumps(params_to_dict(P)) if trace else ""

    def pose(self, odom: Pose, scan: Any, truth: Pose, t: float = 0.0) -> Pose:
        match = None
        if self.core is not None:
            if self.grid is not None:
                self.core.set_map(self.grid)
                self.grid = None
            if self.core.ready:
                match = self.core.match(scan, compose(self.correction, odom))
                if match.ok:
                    self.correction = self.hop(compose(match.pose, inverse(odom)),
                                               convert.correction_to_msg,
                                               convert.correction_from_msg, m.TransformStamped)
            self.core.observe(scan, compose(self.correction, odom))
        pose = compose(self.correction, odom) if self.core is not None else odom
        self.errors.append(math.hypot(pose.x - truth.x, pose.y - truth.y))
        self.headings.append(math.remainder(pose.theta - truth.theta, 2 * math.pi))
        if self.rows is not None:
            self.ranges.append(np.array(scan.ranges, np.float64))
            self.scan_geom = (scan.angle_min, scan.angle_increment, scan.range_min,
                              scan.range_max)
            self.rows.append((t, *odom, *truth, *pose,
                              -1 if match is None else int(match.ok),
                              math.nan if match is None else match.score,
                              math.nan if match is None else match.conditioning))
        return pose

    def figures(self) -> dict[str, Any]:
        e, h = np.asarray(self.errors), np.abs(np.asarray(self.headings))
        return {"pose_rms_m": round(float(np.sqrt(np.mean(e ** 2))), 4) if e.size else None,
                "pose_median_m": round(float(np.median(e)), 4) if e.size else None,
                "pose_max_m": round(float(e.max()), 4) if e.size else None,
                "heading_rms_rad": round(float(np.sqrt(np.mean(h ** 2))), 5) if h.size else None,
                "heading_max_rad": round(float(h.max()), 5) if h.size else None}

    def trace_arrays(self) -> dict[str, np.ndarray]:
        """The per-scan trace (:mod:`topoexplore.tools.bench.posetrace` reads it)."""
        a = np.asarray(self.rows or [], np.float64).reshape(-1, 13)
        return {"t": a[:, 0], "odom": a[:, 1:4], "truth": a[:, 4:7], "estimate": a[:, 7:10],
                "matched": a[:, 10].astype(np.int8), "score": a[:, 11],
                "conditioning": a[:, 12],
                # what `bench posetrace --replay` needs to run the localizer again
                "ranges": np.stack(self.ranges) if self.ranges else np.zeros((0, 0)),
                "scan": np.asarray(self.scan_geom, np.float64), "params": np.array(self.params)}


def replay_localizer(P: Params, t: np.ndarray, odom: np.ndarray, truth: np.ndarray,
                     ranges: np.ndarray, scan_geom: Sequence[float]) -> dict[str, np.ndarray]:
    """The localizer and the mapper of :func:`run` again over a run's recorded scans and
    odometry (``bench posetrace --replay``): each scan matched against the map of the scans
    before it, then integrated at the estimate. The trajectory is the recorded one, so two
    localizer settings meet the same scans (a run with other settings would drive elsewhere).
    With the run's own parameters the estimates are the run's, bit for bit. Returns the new
    trace (:meth:`_Localized.trace_arrays`)."""
    loc = _Localized(P, _direct, trace=True)
    mapper = MapperCore(P.mapper, P.laser.offset)
    a0, inc, rmin, rmax = (float(v) for v in scan_geom)
    for k in range(len(t)):
        scan = Scan(ranges[k], a0, inc, rmin, rmax)
        pose = loc.pose(Pose(*odom[k]), scan, Pose(*truth[k]), float(t[k]))
        mapper.integrate(pose, scan)
        if k % P.mapper.map_every == 0:
            loc.grid = mapper.grid(copy=True)
    return loc.trace_arrays()


class _Stages:
    """Compute seconds per core over a run (``perf_counter`` round each call): where an
    exploration's time goes, with no bus in it. ``sim`` is its scans and physics steps,
    ``mapper`` its scan integration and map copies."""

    NAMES = ("sim", "mapper", "topology", "reliability", "planner", "controller")

    def __init__(self) -> None:
        self.s = dict.fromkeys(self.NAMES, 0.0)

    def __call__(self, name: str, fn: Callable, *args: Any, **kw: Any) -> Any:
        t = time.perf_counter()
        out = fn(*args, **kw)
        self.s[name] += time.perf_counter() - t
        return out

    def figures(self) -> dict[str, float]:
        return {k: round(v, 3) for k, v in self.s.items()}


def _pipeline(P: Params, world: World) -> SimpleNamespace:
    """The six cores, built as the services build them."""
    occ = P.mapper.occupancy
    return SimpleNamespace(
        sim=SimCore(world, P.sim, np.random.default_rng(P.sim.seed), P.robot, P.laser),
        mapper=MapperCore(P.mapper, P.laser.offset), topology=TopologyCore(P.topology, occ),
        reliability=ReliabilityCore(P.reliability, P.laser, occ),
        planner=PlannerCore(P.planner, P.robot, P.reliability.p_reliable, occ),
        controller=ControllerCore(P.controller, P.robot))


def run(world: str, strategy: str = "reliability", seed: int = 0, sets: Sequence[str] = (),
        max_sim_time: float = 1800.0, on_update: Callable[..., Any] | None = None,
        wire: bool = False, pose_trace: Path | None = None, params: str | None = None,
        on_sim: Callable[[SimCore], Any] | None = None) -> dict[str, Any]:
    """One exploration, in process. ``sets``: ``section.key=value`` overrides (TOML values),
    over the parameter file ``params`` if given. ``on_update(t, pose, graph, beliefs, plan,
    grid)`` is called after every plan, then ``on_sim(sim)`` with the simulator core (its
    truth, path length and clock; to read, not to change); either may raise to stop the run.
    ``wire``: every hop goes through the message round trip (:class:`Wire`).
    ``pose_trace``: write every scan's odometry, truth, estimate and match there (.npz, read
    by ``bench posetrace``). Returns the run's figures."""
    P = load_params(params, [f"sim.world={json.dumps(world)}", f"sim.seed={int(seed)}",
                           *strategy_overrides(strategy), "runtime.lockstep=true", *sets])
    w = load_world(P.sim.world)
    c = _pipeline(P, w)
    hop = Wire() if wire else _direct
    loc = _Localized(P, hop, trace=pose_trace is not None)
    steps = max(1, round(P.sim.physics_hz / P.laser.scan_hz))
    plan = grid = None
    lagged: deque = deque()  # (map scan, route) the controller has yet to follow
    lag, route = P.runtime.plan_lag * P.mapper.map_every, None
    state, k, t0 = "exploring", -1, time.monotonic()
    st = _Stages()
    while True:
        k += 1
        t = m.header(0, c.sim.time, "map").time  # as a stamp carries it, to the nanosecond
        odom = (hop if wire else _converted)(c.sim.odom(), convert.odom_to_msg,
                                             convert.odom_from_msg, m.Odometry).pose
        scan = hop(st("sim", c.sim.scan), convert.scan_to_msg, convert.scan_from_msg,
                   m.LaserScan)
        pose = loc.pose(odom, scan, c.sim.truth_pose(), t)
        st("mapper", c.mapper.integrate, pose, scan)
        if k % P.mapper.map_every == 0:
            grid = loc.grid = hop(st("mapper", c.mapper.grid, copy=True), convert.grid_to_msg,
                                  convert.grid_from_msg, m.OccupancyGrid)
            graph = hop(st("topology", c.topology.update, grid, (pose.x, pose.y)).graph,
                        convert.graph_to_msg, convert.graph_from_msg, m.TopoGraph)
            beliefs = hop(st("reliability", c.reliability.update, graph, pose, grid),
                          convert.beliefs_to_msg, convert.beliefs_from_msg, m.Reliability)
            plan = st("planner", c.planner.update, t, pose, graph, beliefs, grid)
            state = plan.status.state
            if on_update is not None:
                on_update(t, pose, graph, beliefs, plan, grid)
            if on_sim is not None:
                on_sim(c.sim)
            if plan.status.finished:
                break
            lagged.append((k, plan.route))
        while lagged and lagged[0][0] <= k - lag:  # the plan the controller follows now
            route = hop(lagged.popleft()[1], convert.route_to_msg, convert.route_from_msg,
                        m.Path)
        cmd = st("controller", c.controller.update, t, pose, route, False, scan)
        c.sim.command(cmd.v, cmd.w)
        for _ in range(steps):
            st("sim", c.sim.step)
        if c.sim.time >= max_sim_time:
            state = "timeout"
            break
    cov, cov_free = _coverages(P, w, grid)
    if pose_trace is not None:
        Path(pose_trace).parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(pose_trace, **loc.trace_arrays())
    snap = c.planner.snapshot()
    return {"world": world, "strategy": strategy, "seed": int(seed), "state": str(state),
            "finished": state == "done", "stop_reason": plan.status.reason if plan else "",
            "path_length_m": round(c.sim.path_length, 3), "sim_time_s": round(c.sim.time, 1),
            "coverage": round(cov, 4), "coverage_free": round(cov_free, 4),
            "collisions": int(c.sim.collisions), "wall_s": round(time.monotonic() - t0, 1),
            "escalations": snap["watchdog"]["counts"],
            "watchdog_approaches": snap["watchdog"]["approaches"],
            "blocked_marks": snap["blocked"]["made"],
            "blocked_forgotten": snap["blocked"]["forgotten"],
            "blocked_released": snap["blocked"]["released"],
            "recoveries": c.controller.recoveries,  # the controller's stuck recoveries ...
            "backups_refused": c.controller.backups_refused,  # ... that only turned
            "stage_s": st.figures(), **loc.figures()}


def _coverages(P: Params, w: World, grid: Any) -> tuple[float, float]:
    """``coverage`` (share of the free cells the robot can map that the map knows) and
    ``coverage_free`` (share of every free cell connected to the start), as ``run`` reports."""
    res = P.mapper.resolution
    target, ox, oy = truth_mappable(w, res, P.robot.radius, P.laser.range_max)
    free, _, _ = truth_free_reachable(w, res)
    return tuple(float(coverage(grid.data, grid.geom, t, (ox, oy), res, P.mapper.p_free,
                                P.mapper.p_occ)) for t in (target, free))


def _one(item: tuple) -> dict[str, Any]:
    label, world, strategy, seed, sets, tmax, wire, *rest = item
    trace = Path(rest[0]) / f"{label}-{strategy}-s{seed}.npz" if rest and rest[0] else None
    try:
        r = run(world, strategy, seed, sets, tmax, wire=wire, pose_trace=trace)
    except Exception as exc:  # noqa: BLE001 - one failed run must not end the sweep
        r = {"world": world, "strategy": strategy, "seed": seed, "state": "error",
             "finished": False, "stop_reason": f"{type(exc).__name__}: {exc}",
             "path_length_m": None, "sim_time_s": None, "coverage": None,
             "coverage_free": None, "collisions": None, "wall_s": None}
    r["world_label"] = label
    return r


def stage_line(runs: Sequence[dict[str, Any]]) -> str:
    """One line: each core's compute summed over the runs (``stage_s``), with its share."""
    tot = {k: sum((r.get("stage_s") or {}).get(k, 0.0) for r in runs) for k in _Stages.NAMES}
    whole = sum(tot.values())
    if whole <= 0.0:
        return "compute per stage: none measured"
    return "compute per stage, summed over the runs: " + ", ".join(
        f"{k} {v:.1f} s ({100.0 * v / whole:.0f} %)" for k, v in tot.items())


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # one line, exit 2, no usage dump
        print(f"topoexplore bench inproc: {message}", file=sys.stderr)
        raise SystemExit(2)


def build_parser() -> argparse.ArgumentParser:
    ap = _Parser(prog="topoexplore bench inproc", description=__doc__.split("\n\n")[0])
    ap.add_argument("--worlds", help="comma-separated names or map files (default: the "
                                     "bench explore suite without large-office)")
    ap.add_argument("--strategies", default=",".join(STRATEGIES))
    ap.add_argument("--seeds", type=int, default=2, help="seeds 0..N-1 (default 2)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="parameter override for every run (repeatable)")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--max-sim-time", type=float, default=1800.0, help="per run [s]")
    ap.add_argument("--json", type=Path, help="write the runs and ratios here")
    ap.add_argument("--wire", action="store_true",
                    help="send every hop through the message round trip (as over the bus)")
    ap.add_argument("--pose-trace", type=Path, metavar="DIR",
                    help="write each run's per-scan odometry, truth, estimate and match to "
                         "DIR/<world>-<strategy>-s<seed>.npz (read it with bench posetrace)")
    return ap


def parse(argv: Sequence[str]) -> tuple[list[tuple], argparse.Namespace]:
    a = build_parser().parse_args(list(argv))
    if a.worlds:
        names = [w.strip() for w in a.worlds.split(",") if w.strip()]
    else:
        names = [w for w in default_worlds()[0] if w != "large-office"]
    worlds = [resolve_world(w)[:2] for w in names]
    strategies = parse_strategies(a.strategies)
    if a.seeds < 1 or a.jobs < 1:
        raise BenchArgError("--seeds and --jobs must be >= 1")
    if not (math.isfinite(a.max_sim_time) and a.max_sim_time > 0):
        raise BenchArgError("--max-sim-time must be a positive number")
    check_overrides(None, a.set)
    items = [(label, world, st, seed, tuple(a.set), a.max_sim_time, a.wire,
              None if a.pose_trace is None else str(a.pose_trace))
             for label, world in worlds for st in strategies for seed in range(a.seeds)]
    return items, a


def run_line(r: dict) -> str:
    """One run's line of the report."""
    cov = "-" if r["coverage"] is None else f"{r['coverage']:.3f}"
    cov_free = "-" if r["coverage_free"] is None else f"{r['coverage_free']:.3f}"
    return (f"{r['world_label']:14s} {r['strategy']:14s} s{r['seed']} {r['state']:8s} "
            f"path {r['path_length_m']} m  sim {r['sim_time_s']} s  coverage {cov} "
            f"(free {cov_free})  collisions {r['collisions']}  wall {r['wall_s']} s"
            + (f"  pose RMS {r['pose_rms_m']} m (max {r['pose_max_m']})"
               if r.get("pose_max_m") else ""))


def main(argv: Sequence[str] | None = None) -> int:
    try:
        items, a = parse(sys.argv[1:] if argv is None else argv)
    except BenchArgError as exc:
        print(f"topoexplore bench inproc: {exc}", file=sys.stderr)
        return 2
    t0 = time.monotonic()
    runs = []
    with ProcessPoolExecutor(min(a.jobs, len(items))) as pool:
        for r in pool.map(_one, items):  # in order, each line as soon as its run is in
            print(run_line(r), flush=True)
            runs.append(r)
    print(stage_line(runs))
    strategies = sorted({r["strategy"] for r in runs}, key=STRATEGY_NAMES.index)
    ratios = {}
    for den in ("frontier", "all-end-nodes"):
        if "reliability" in strategies and den in strategies:
            rr = pair_ratios(runs, "reliability", den, "path_length_m")
            ratios[f"reliability/{den}"] = rr
            gm = "-" if rr["geomean"] is None else f"{rr['geomean']:.3f}"
            print(f"path reliability/{den}: geometric mean {gm} over {rr['n_included']} "
                  f"pair(s), {rr['n_excluded']} excluded")
    from topoexplore.tools.bench.oracle import suite_line, suite_ratios

    oracle = suite_ratios(runs)
    print(suite_line(oracle))
    low = [f"{r['world_label']}/{r['strategy']}/s{r['seed']} {r['coverage']}" for r in runs
           if r["coverage"] is not None and r["coverage"] < 0.95]
    print(f"coverage < 0.95: {', '.join(low) or 'none'}; "
          f"wall {time.monotonic() - t0:.0f} s for {len(runs)} run(s)")
    if a.json:
        a.json.write_text(json.dumps({"sets": list(a.set), "runs": runs, "ratios": ratios,
                                      "oracle": oracle}, indent=1))
    return 0 if all(r["state"] != "error" for r in runs) else 1


if __name__ == "__main__":
    raise SystemExit(main())
