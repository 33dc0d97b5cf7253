"""``topoexplore bench record``: what recording costs, on the real stack in real time.

    topoexplore bench record [--world office] [--speed 4] [--sim-time 120] [--repeats 2]
                             [--modes plain,record,raw]

Runs ``topoexplore run --world W --speed S --max-sim-time T`` (real-time mode, every service
a process) in turn without recording (``plain``), with ``--record`` and with ``--record-raw``
(``raw``: the raw channels only; the Foxglove channels are then added after the run, timed
apart), and prints per run:

- the CPU seconds of each service (report.json ``cpu_s``) and their sum: the recorder is
  one more subscriber, so this is the overhead *on the services* (the router's fan-out is
  shown apart);
- the CPU of the whole command (``run`` with its recorder and every child, from the
  operating system's accounting of the finished process tree);
- whether the recorder kept up: messages, messages lost by ``header.seq``, the writer's
  largest backlog, the file size; and whether the sim kept real time (its real-time factor).

The ratio of each recording mode to ``plain`` is printed per service and for the sums.
Figures, not a timed test.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from topoexplore.tools.launch.supervisor import free_port

SERVICES = ("sim", "mapper", "topology", "reliability", "planner", "controller")


MODES = {"plain": [], "record": ["--record"], "raw": ["--record-raw"]}


def one_run(world: str, speed: float, sim_time: float, mode: str, out: Path) -> dict:
    before = os.times()
    cmd = [sys.executable, "-m", "topoexplore.tools.cli", "run", "--world", world, "--speed",
           str(speed), "--max-sim-time", str(sim_time), "--quiet", "--out", str(out),
           "--connect", f"tcp/127.0.0.1:{free_port()}", "--namespace", f"benchrec{os.getpid()}",
           *MODES[mode]]
    subprocess.run(cmd, capture_output=True, text=True, timeout=sim_time / speed * 10 + 300)
    after = os.times()
    rep = json.loads((out / "report.json").read_text())
    cpu = {k: v["user_s"] + v["sys_s"] for k, v in (rep.get("cpu_s") or {}).items()}
    mcap = out / "run.mcap"
    convert_s = 0.0
    if mode == "raw":  # the Foxglove channels added after the run: what that costs
        from topoexplore.tools.record import add_foxglove

        t0 = time.process_time()
        add_foxglove(mcap, out / "view.mcap")
        convert_s = time.process_time() - t0
    return {"mode": mode, "cpu": cpu, "services_s": sum(cpu.get(s, 0.0) for s in SERVICES),
            "router_s": cpu.get("router", 0.0),
            "command_s": (after.children_user - before.children_user)
            + (after.children_system - before.children_system),
            "convert_s": convert_s,
            "sim_time_s": rep["sim_time_s"], "wall_s": rep["wall_time_s"],
            "recording": rep.get("recording"),
            "mcap_mb": mcap.stat().st_size / 1e6 if mcap.is_file() else 0.0}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="topoexplore bench record", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--world", default="office")
    ap.add_argument("--speed", type=float, default=4.0, help="real-time factor (default 4)")
    ap.add_argument("--sim-time", type=float, default=120.0, help="[s] of sim time per run")
    ap.add_argument("--repeats", type=int, default=2, help="rounds of runs (default 2)")
    ap.add_argument("--modes", default="plain,record,raw",
                    help="comma-separated, in the order run each round (plain first: the "
                    "ratios are to it)")
    ap.add_argument("--json", default=None, help="write the runs here as JSON")
    a = ap.parse_args(argv)
    modes = [x.strip() for x in a.modes.split(",") if x.strip()]
    if not (a.speed > 0 and a.sim_time > 0 and a.repeats >= 1) or not modes \
            or modes[0] != "plain" or any(x not in MODES for x in modes):
        print("topoexplore bench record: --speed, --sim-time and --repeats must be > 0, and "
              f"--modes a list of {', '.join(MODES)} starting with plain", file=sys.stderr)
        return 2
    runs = []
    with tempfile.TemporaryDirectory(prefix="bench-record-") as tmp:
        for i in range(a.repeats):
            for mode in modes:
                r = one_run(a.world, a.speed, a.sim_time, mode, Path(tmp) / f"{i}-{mode}")
                runs.append(r)
                rec = r["recording"] or {}
                print(f"{mode:6s} run {i}: services {r['services_s']:.1f} CPU s, router "
                      f"{r['router_s']:.1f}, whole command {r['command_s']:.1f}; sim "
                      f"{r['sim_time_s']:.0f} s in {r['wall_s']:.0f} s"
                      + (f"; {rec.get('messages')} messages, lost {rec.get('gaps')}, backlog "
                         f"max {rec.get('max_backlog')}, {r['mcap_mb']:.1f} MB" if rec else "")
                      + (f"; Foxglove channels added after: {r['convert_s']:.1f} CPU s"
                         if mode == "raw" else ""), flush=True)
    print(f"\n{a.world}, real time x{a.speed:g}, {a.sim_time:g} s of sim time, {a.repeats} "
          f"round(s): median CPU s {' / '.join(modes)} (ratio to plain)")

    def med(mode: str, get) -> float:
        return statistics.median(get(r) for r in runs if r["mode"] == mode)

    rows = [(name, lambda r, n=name: r["cpu"].get(n, 0.0)) for name in (*SERVICES, "router")]
    rows += [("all services", lambda r: r["services_s"]),
             ("whole command", lambda r: r["command_s"])]
    for label, get in rows:
        vals = [med(x, get) for x in modes]
        ratios = [v / vals[0] if vals[0] else float("nan") for v in vals[1:]]
        print(f"  {label:13s} " + " / ".join(f"{v:7.2f}" for v in vals)
              + "  (" + ", ".join(f"{q:.3f}" for q in ratios) + ")")
    if "raw" in modes:
        print(f"  Foxglove channels added after a raw run: {med('raw', lambda r: r['convert_s']):.2f} "
              "CPU s (not during the run)")
    if a.json:
        Path(a.json).write_text(json.dumps(runs, indent=1))
    return 0
