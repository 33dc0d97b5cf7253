"""``topoexplore bench``: benchmarks that print figures (not timed tests).

    topoexplore bench stages [--sizes 100,300,1000] [--json] [--bus] [--worlds paper-room,office]
    topoexplore bench explore [--worlds ...] [--strategies ...] [--seeds N] [--out DIR]
    topoexplore bench inproc [--worlds ...] [--strategies ...] [--seeds N] [--set k=v ...]

``stages`` measures the compute of each stage on synthetic office maps (mapper, topology, ...),
and with ``--bus`` the bus too, with real processes on loopback: one-way latency of a scan
and of a map through the router, lockstep sim throughput with an echo controller, per-hop and
scan → cmd_vel latency through all six processes in real-time mode, and the lockstep speed-up.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from topoexplore.common import messages as m
from topoexplore.common.bus import Bus
from topoexplore.common.keys import Keys


def _stats_ms(samples: list[float]) -> dict[str, float]:
    a = np.asarray(samples, dtype=np.float64) * 1000.0
    if a.size == 0:
        return {"median_ms": float("nan"), "p99_ms": float("nan"), "n": 0}
    return {"median_ms": round(float(np.median(a)), 3),
            "p99_ms": round(float(np.percentile(a, 99)), 3), "n": int(a.size)}


def _free_endpoint() -> str:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


class _Procs:
    def __init__(self) -> None:
        self.procs: list[subprocess.Popen] = []

    def python(self, *args: str) -> subprocess.Popen:
        p = subprocess.Popen([sys.executable, "-u", *args], stdout=subprocess.DEVNULL,
                             stderr=subprocess.DEVNULL, start_new_session=True)
        self.procs.append(p)
        return p

    def close(self) -> None:
        import signal

        for p in self.procs:
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGTERM)
        for p in self.procs:
            try:
                p.wait(timeout=5)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)


_PUBLISHER = r"""
import sys, time
from topoexplore.common import messages as m
from topoexplore.common.bus import Bus
ep, key, kind, n, rate = sys.argv[1], sys.argv[2], sys.argv[3], int(sys.argv[4]), float(sys.argv[5])
with Bus.client(ep, wait_for_router=True) as bus:
    pub = bus.publisher(key, reliable=True)
    while not pub.matched:
        time.sleep(0.01)
    time.sleep(0.2)
    grid = bytes(1000 * 1000)
    for i in range(n):
        h = m.header(i, time.monotonic(), "x", i)
        if kind == "scan":
            msg = m.LaserScan(header=h, angle_min=-1.57, angle_max=1.5713,
                              angle_increment=0.01745, range_min=0.02, range_max=8.0,
                              ranges=[3.0] * 181)
        else:
            msg = m.OccupancyGrid(header=h, info=m.MapMetaData(
                map_load_time=h.stamp, resolution=0.1, width=1000, height=1000,
                origin=m.GeoPose(position=m.Point(), orientation=m.Quaternion())), data=grid)
        pub.put(msg)
        time.sleep(1.0 / rate)
"""


def bench_hop(n: int = 200) -> dict[str, dict]:
    """One-way publish -> receipt latency through the router (two processes, same clock)."""
    out = {}
    for kind, t, rate in (("scan", m.LaserScan, 100.0), ("map_1000x1000", m.OccupancyGrid, 20.0)):
        ep = _free_endpoint()
        procs = _Procs()
        try:
            procs.python("-m", "topoexplore.tools.router", "--listen", ep)
            lat: list[float] = []
            done = threading.Event()
            with Bus.client(ep, wait_for_router=True) as bus:
                count = n if kind == "scan" else max(20, n // 4)

                def cb(msg, key, lat=lat, count=count, done=done):
                    lat.append(time.monotonic() - msg.header.time)
                    if len(lat) >= count:
                        done.set()

                bus.subscribe("bench/hop", t, cb)
                procs.python("-c", _PUBLISHER, ep, "bench/hop", kind.split("_")[0], str(count),
                             str(rate))
                done.wait(60)
            out[kind] = _stats_ms(lat)
        finally:
            procs.close()
    return out


def bench_lockstep_sim(world: str = "paper-room", scans: int = 400) -> dict:
    """Sim process in lockstep answered by an echo controller in this process: scans/s."""
    ep = _free_endpoint()
    keys = Keys("bench", "sim")
    procs = _Procs()
    try:
        procs.python("-m", "topoexplore.tools.router", "--listen", ep)
        procs.python("-m", "topoexplore.sim.service", "--connect", ep, "--namespace", "bench", "--robot",
                     "sim", "--set", "runtime.lockstep=true", "--set", "runtime.lockstep_wait_for=[]",
                     "--set", f'sim.world="{world}"')
        stamps: list[float] = []
        done = threading.Event()
        with Bus.client(ep, wait_for_router=True) as bus:
            pub = bus.publisher(keys.cmd_vel, m.Twist, reliable=True)

            def on_scan(msg: m.LaserScan, key: str) -> None:
                stamps.append(time.monotonic())
                if len(stamps) >= scans:
                    done.set()
                    return
                pub.put(m.Twist(header=m.header(msg.header.seq, msg.header.time, "base_link",
                                                msg.header.src_seq),
                                linear=m.Vector3(), angular=m.Vector3(z=0.3)))

            bus.subscribe(keys.scan, m.LaserScan, on_scan)
            done.wait(120)
        n = len(stamps) - 1
        dt = stamps[-1] - stamps[0] if n > 0 else float("nan")
        return {"world": world, "scans": n, "wall_s": round(dt, 3),
                "scans_per_s": round(n / dt, 1) if n > 0 else 0.0,
                "x_real_time_at_scan_hz": round(n / dt / 5.0, 1) if n > 0 else 0.0}
    finally:
        procs.close()


def bench_core_sim(world: str = "paper-room", scans: int = 500) -> dict:
    """SimCore compute only: one scan + physics steps per scan period."""
    from topoexplore.common.params import load_params
    from topoexplore.sim.core import SimCore
    from topoexplore.sim.world import load_world

    P = load_params()
    core = SimCore(load_world(world), P.sim, np.random.default_rng(0), P.robot, P.laser)
    steps = max(1, round(P.sim.physics_hz / P.laser.scan_hz))
    core.command(0.0, 0.3)
    t0 = time.perf_counter()
    for _ in range(scans):
        core.scan()
        for _ in range(steps):
            core.step()
        core.command(0.0, 0.3)
    dt = time.perf_counter() - t0
    return {"world": world, "scans_per_s": round(scans / dt, 1)}


def bench_pipeline_latency(world: str, duration: float = 20.0) -> dict:
    """Real-time stack (speed 1): per-hop and scan -> cmd_vel latency seen by one monitor."""
    from topoexplore.tools.launch.core import load_profile
    from topoexplore.tools.launch.supervisor import Supervisor, profile_path

    ep = _free_endpoint()
    keys = Keys("benchrt", "robot1")
    sup = Supervisor(load_profile(profile_path("sim")), keys, ep,
                     overrides=[f'sim.world="{world}"'], sink=lambda line: None)
    arrivals: dict[str, dict[int, float]] = {t: {} for t in
                                             ("scan", "map", "topo", "reliability", "plan",
                                              "cmd_vel")}
    lock = threading.Lock()
    try:
        sup.start_router()
        with Bus.client(ep, wait_for_router=True) as bus:
            for topic in arrivals:
                def cb(msg, key, topic=topic):
                    with lock:
                        arrivals[topic].setdefault(msg.header.src_seq, time.monotonic())
                bus.subscribe(keys.topic(topic), _TYPES[topic], cb)
            sup.start(ready_timeout=60)
            time.sleep(2.0)  # let the pipeline warm up (numba caches, first map)
            with lock:
                for d in arrivals.values():
                    d.clear()
            time.sleep(duration)
    finally:
        sup.stop()
    hops = {}
    order = list(arrivals)
    with lock:
        for a, b in zip(order, order[1:], strict=False):
            hops[f"{a}->{b}"] = _stats_ms([arrivals[b][k] - arrivals[a][k]
                                           for k in arrivals[b] if k in arrivals[a]])
        total = _stats_ms([arrivals["cmd_vel"][k] - arrivals["scan"][k]
                           for k in arrivals["cmd_vel"] if k in arrivals["scan"]])
        to_plan = _stats_ms([arrivals["plan"][k] - arrivals["scan"][k]
                             for k in arrivals["plan"] if k in arrivals["scan"]])
        answered = len(arrivals["cmd_vel"]) / max(1, len(arrivals["scan"]))
    return {"world": world, "scan_to_cmd_vel": total, "scan_to_plan": to_plan, "hops": hops,
            "scans": len(arrivals["scan"]), "answered_share": round(answered, 3)}


_TYPES = {"scan": m.LaserScan, "map": m.OccupancyGrid, "topo": m.TopoGraph,
          "reliability": m.Reliability, "plan": m.Path, "cmd_vel": m.Twist}


def bench_lockstep_explore(world: str = "paper-room") -> dict:
    with tempfile.TemporaryDirectory() as d:
        r = subprocess.run([sys.executable, "-m", "topoexplore.tools.cli", "run", "--world", world,
                            "--lockstep", "--quiet", "--out", d],
                           capture_output=True, text=True, timeout=1200)
        try:
            rep = json.loads((Path(d) / "report.json").read_text())
        except (OSError, ValueError):
            return {"world": world, "error": r.stderr.strip().splitlines()[-1:]}
    wall = rep["wall_time_s"]
    return {"world": world, "finished": rep["finished"], "sim_time_s": rep["sim_time_s"],
            "wall_time_s": wall, "speedup": round(rep["sim_time_s"] / wall, 1) if wall else 0.0}


def stages_main(argv: list[str]) -> int:
    from topoexplore.tools.bench import stages as benchstages

    ap = argparse.ArgumentParser(prog="topoexplore bench stages", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", default="100,300,1000", help="grid sizes (cells per side)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--json", action="store_true",
                    help="print {stage: {grid: {median_ms, p99_ms}}} (plus 'bus' with --bus)")
    ap.add_argument("--stages", default=",".join(benchstages.STAGES),
                    help="comma separated, from " + ", ".join(benchstages.STAGES))
    ap.add_argument("--bus", action="store_true", help="also measure the bus with real processes")
    ap.add_argument("--worlds", default="paper-room,office",
                    help="worlds for the real-time latency and lockstep figures")
    args = ap.parse_args(argv)
    stages = tuple(s for s in args.stages.split(",") if s)
    try:
        sizes = tuple(int(s) for s in args.sizes.split(","))
        if not sizes or min(sizes) < 20 or max(sizes) > 4000 or args.repeats < 1 \
                or not stages or set(stages) - set(benchstages.STAGES):
            raise ValueError
    except ValueError:
        print("topoexplore bench: --sizes must be integers in 20..4000, --repeats >= 1, "
              f"--stages from {', '.join(benchstages.STAGES)}", file=sys.stderr)
        return 2
    results = benchstages.bench_stages(sizes=sizes, repeats=args.repeats, stages=stages)
    if not args.json:
        print(benchstages.format_table(results), flush=True)
    if args.bus:
        worlds = [w for w in args.worlds.split(",") if w]
        bus = {"hop": bench_hop(), "sim_core": bench_core_sim(worlds[0]),
               "sim_lockstep_echo": bench_lockstep_sim(worlds[0]),
               "realtime_latency": [bench_pipeline_latency(w) for w in worlds],
               "lockstep_explore": [bench_lockstep_explore(w) for w in worlds]}
        results = dict(results, bus=bus)
        if not args.json:
            print(format_bus(bus))
    if args.json:
        print(json.dumps(results, indent=2))
    return 0


def format_bus(bus: dict) -> str:
    lines = ["", "bus (real processes on loopback, one router):"]
    for k, v in bus["hop"].items():
        lines.append(f"  one-way {k:<16} median {v['median_ms']:7.3f} ms  p99 {v['p99_ms']:7.3f} ms")
    c, e = bus["sim_core"], bus["sim_lockstep_echo"]
    lines.append(f"  sim core ({c['world']}): {c['scans_per_s']:.0f} scans/s of compute")
    lines.append(f"  sim lockstep + echo controller over the bus: {e['scans_per_s']:.0f} scans/s "
                 f"({e['x_real_time_at_scan_hz']:.0f}x real time at 5 Hz)")
    for r in bus["realtime_latency"]:
        s = r["scan_to_cmd_vel"]
        lines.append(f"  real time, {r['world']}: scan -> cmd_vel median {s['median_ms']:.1f} ms, "
                     f"p99 {s['p99_ms']:.1f} ms over {s['n']} scans "
                     f"(answered {r['answered_share']:.0%})")
        sp = r["scan_to_plan"]
        lines.append(f"      scan -> plan (mapper, topology, reliability, planner) median "
                     f"{sp['median_ms']:.1f} ms, p99 {sp['p99_ms']:.1f} ms; the controller answers "
                     f"each scan with the newest plan, so plan->cmd_vel can be negative")
        for hop, h in r["hops"].items():
            lines.append(f"      {hop:<20} median {h['median_ms']:6.1f} ms  p99 {h['p99_ms']:6.1f} ms")
    for r in bus["lockstep_explore"]:
        if "error" in r:
            lines.append(f"  lockstep explore {r['world']}: failed {r['error']}")
        else:
            lines.append(f"  lockstep explore {r['world']}: {r['sim_time_s']:.0f} sim s in "
                         f"{r['wall_time_s']:.1f} wall s = {r['speedup']:.1f}x real time "
                         f"({'finished' if r['finished'] else 'not finished'})")
    return "\n".join(lines)
