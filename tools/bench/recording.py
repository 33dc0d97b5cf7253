"""``topoexplore bench record``: what recording costs, on the real stack in real time.

    topoexplore bench record [--world office] [--speed 4] [--sim-time 120] [--repeats 2]

Runs ``topoexplore run --world W --speed S --max-sim-time T`` (real-time mode, every service
a process) alternately without and with ``--record``, and prints per run:

- the CPU seconds of each service (report.json ``cpu_s``) and their sum: the recorder is
  one more subscriber, so this is the overhead *on the services* (the router's fan-out is
  shown apart);
- the CPU of the whole command (``run`` with its recorder and every child, from the
  operating system's accounting of the finished process tree);
- whether the recorder kept up: messages, messages lost by ``header.seq``, the writer's
  largest backlog, the file size; and whether the sim kept real time (its real-time factor).

The ratio with/without is printed per service and for the sum. Figures, not a timed test.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from topoexplore.tools.launch.supervisor import free_port

SERVICES = ("sim", "mapper", "topology", "reliability", "planner", "controller")


def one_run(world: str, speed: float, sim_time: float, record: bool, out: Path) -> dict:
    before = os.times()
    cmd = [sys.executable, "-m", "topoexplore.tools.cli", "run", "--world", world, "--speed",
           str(speed), "--max-sim-time", str(sim_time), "--quiet", "--out", str(out),
           "--connect", f"tcp/127.0.0.1:{free_port()}", "--namespace", f"benchrec{os.getpid()}"]
    if record:
        cmd.append("--record")
    subprocess.run(cmd, capture_output=True, text=True, timeout=sim_time / speed * 10 + 300)
    after = os.times()
    rep = json.loads((out / "report.json").read_text())
    cpu = {k: v["user_s"] + v["sys_s"] for k, v in (rep.get("cpu_s") or {}).items()}
    return {"record": record, "cpu": cpu, "services_s": sum(cpu.get(s, 0.0) for s in SERVICES),
            "router_s": cpu.get("router", 0.0),
            "command_s": (after.children_user - before.children_user)
            + (after.children_system - before.children_system),
            "sim_time_s": rep["sim_time_s"], "wall_s": rep["wall_time_s"],
            "recording": rep.get("recording"),
            "mcap_mb": (out / "run.mcap").stat().st_size / 1e6 if record else 0.0}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="topoexplore bench record", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--world", default="office")
    ap.add_argument("--speed", type=float, default=4.0, help="real-time factor (default 4)")
    ap.add_argument("--sim-time", type=float, default=120.0, help="[s] of sim time per run")
    ap.add_argument("--repeats", type=int, default=2, help="pairs of runs (default 2)")
    ap.add_argument("--json", default=None, help="write the runs here as JSON")
    a = ap.parse_args(argv)
    if not (a.speed > 0 and a.sim_time > 0 and a.repeats >= 1):
        print("topoexplore bench record: --speed, --sim-time and --repeats must be > 0",
              file=sys.stderr)
        return 2
    runs = []
    with tempfile.TemporaryDirectory(prefix="bench-record-") as tmp:
        for i in range(a.repeats):
            for record in (False, True):
                r = one_run(a.world, a.speed, a.sim_time, record, Path(tmp) / f"{i}-{record}")
                runs.append(r)
                rec = r["recording"] or {}
                print(f"{'record ' if record else 'plain  '} run {i}: services "
                      f"{r['services_s']:.1f} CPU s, router {r['router_s']:.1f}, whole command "
                      f"{r['command_s']:.1f}; sim {r['sim_time_s']:.0f} s in {r['wall_s']:.0f} s"
                      + (f"; {rec.get('messages')} messages, lost {rec.get('gaps')}, backlog "
                         f"max {rec.get('max_backlog')}, {r['mcap_mb']:.1f} MB" if record
                         else ""), flush=True)
    print(f"\n{a.world}, real time x{a.speed:g}, {a.sim_time:g} s of sim time, "
          f"{a.repeats} pair(s): median CPU s without / with --record (ratio)")
    for name in (*SERVICES, "router"):
        p = statistics.median(r["cpu"].get(name, 0.0) for r in runs if not r["record"])
        q = statistics.median(r["cpu"].get(name, 0.0) for r in runs if r["record"])
        print(f"  {name:12s} {p:7.2f} / {q:7.2f}  ({q / p if p else float('nan'):.3f})")
    for key, label in (("services_s", "all services"), ("command_s", "whole command")):
        p = statistics.median(r[key] for r in runs if not r["record"])
        q = statistics.median(r[key] for r in runs if r["record"])
        print(f"  {label:12s} {p:7.2f} / {q:7.2f}  ({q / p if p else float('nan'):.3f})")
    if a.json:
        Path(a.json).write_text(json.dumps(runs, indent=1))
    return 0
