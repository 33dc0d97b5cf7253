"""``topoexplore bench faults``: explorations under injected faults (issue 14).

    topoexplore bench faults [--world office] [--speed 4] [--faults kill:mapper,stop:planner,...]
                             [--seed 0] [--json F] [--doc docs/reliability.md]

Runs ``topoexplore run`` in real time (every service a process under the supervisor), once
without a fault and once per fault, and injects the fault at a random moment (sim time drawn
in 15-45 % of the fault-free run's, from ``--seed``):

- ``kill:SERVICE``: SIGKILL; the supervisor restarts it. Recovery: wall time until the new
  process is up and has done work again (its state queryable's ``processed``, the sim's steps).
  Map cells lost: cells known just before the kill and unknown in the mapper's first map after
  it is working again.
- ``stop:SERVICE``: SIGSTOP for ``--stop-for`` s (wall), then SIGCONT. Stand-still: sim time
  from the SIGSTOP until the robot stays still, below 1 cm/s and 0.02 rad/s, for 0.5 s
  (None: it did not stop).
- ``router``: SIGKILL of the router; the supervisor restarts it. Recovery: wall time until
  every service is up again and the sim time moves on.
- ``drop:SERVICE:TOPIC:SHARE`` and ``delay:SERVICE:TOPIC:SECONDS``: for ``--chaos-for`` s
  (wall) SERVICE drops that share of its incoming TOPIC messages, or holds each back for that
  long (``runtime.chaos_*``, set live through its params queryable), then the chaos is
  switched off. The row says how many were dropped or delayed, and the run's messages lost
  by seq (report.json ``lost_messages_total``).

For each run: finished, coverage, collisions, restarts, recovery, stand-still, cells lost, the
path against the fault-free run's. ``--doc`` writes the table into a Markdown file.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import random
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any
from urllib.parse import quote

import msgspec
import numpy as np

from topoexplore.common import convert
from topoexplore.common import messages as m
from topoexplore.common.bus import Bus, BusError
from topoexplore.common.keys import TOPICS, Keys
from topoexplore.tools.launch.supervisor import free_port
from topoexplore.tools.livestate import StateError, fetch_state

SERVICES = ("sim", "mapper", "topology", "reliability", "planner", "controller")
DEFAULT_FAULTS = (*(f"kill:{s}" for s in SERVICES), "stop:controller", "stop:planner", "router",
                  "drop:mapper:scan:0.3", "delay:controller:plan:0.3")


def parse_fault(f: str) -> str | None:
    """None when f is a fault this bench knows, else what is wrong with it."""
    kind, _, rest = f.partition(":")
    if f == "router" or (kind in ("kill", "stop") and rest in SERVICES):
        return None
    if kind in ("drop", "delay"):
        svc, _, rest = rest.partition(":")
        topic, _, value = rest.rpartition(":")
        try:
            v = float(value)
        except ValueError:
            v = math.nan
        limit = 1.0 if kind == "drop" else 60.0
        if svc in SERVICES and topic in TOPICS and 0.0 < v <= limit:
            return None
        return f"{kind}:SERVICE:TOPIC:{'SHARE (0-1]' if kind == 'drop' else 'SECONDS (0-60]'}"
    return "kill:SERVICE, stop:SERVICE, router, drop:SERVICE:TOPIC:SHARE, delay:SERVICE:TOPIC:S"


def set_param(bus: Bus, keys: Keys, service: str, assignment: str) -> str | None:
    """Set a live parameter of a running service; None, or the error."""
    sel = f"{keys.params(service)}?set={quote(assignment, safe='')}"
    for _k, payload, err in bus.get(sel, timeout=3.0):
        if payload is None:
            return err or "no payload"
        ans = msgspec.msgpack.decode(payload)
        return ans.get("error") if isinstance(ans, dict) else "bad reply"
    return f"no reply from {service}"


class Watch:
    """The run as the bus shows it: sim time, the robot's true pose and speed."""

    def __init__(self, bus: Bus, keys: Keys):
        self.sim_time = 0.0  # [s]
        self.pose: tuple[float, float] | None = None
        self.moves: list[tuple[float, float, float]] = []  # (sim time [s], v [m/s], |w| [rad/s])
        self._last: tuple[float, float, float, float] | None = None
        self.lock = threading.Lock()
        bus.subscribe(keys.topic("sim/status"), m.SimStatus, self._on_status)
        bus.subscribe(keys.topic("truth"), m.PoseStamped, self._on_truth)

    def _on_status(self, msg: m.SimStatus, _k: str) -> None:
        self.sim_time = msg.sim_time

    def _on_truth(self, msg: m.PoseStamped, _k: str) -> None:
        p = convert.truth_from_msg(msg)
        t, x, y, th = msg.header.time, p.x, p.y, p.theta
        with self.lock:
            if self._last is not None and t > self._last[0]:
                dt = t - self._last[0]
                dth = math.remainder(th - self._last[3], 2 * math.pi)
                self.moves.append((t, math.hypot(x - self._last[1], y - self._last[2]) / dt,
                                   abs(dth) / dt))
            self._last = (t, x, y, th)
            self.sim_time = max(self.sim_time, t)

    def stood_still_after(self, t0: float, hold: float = 0.5) -> float | None:
        """Sim time [s] from t0 until the robot stayed still (below 1 cm/s and 0.02 rad/s:
        turning in place is moving) for ``hold`` s."""
        with self.lock:
            moves = [(t, v, w) for t, v, w in self.moves if t >= t0]
        still_since = None
        for t, v, w in moves:
            if v < 0.01 and w < 0.02:
                still_since = t if still_since is None else still_since
                if t - still_since >= hold:
                    return max(0.0, still_since - t0)
            else:
                still_since = None
        return None


def _state(bus: Bus, keys: Keys, service: str) -> dict | None:
    try:
        return fetch_state(bus, keys, service, timeout=1.0)
    except StateError:
        return None


def _known_grid(state: dict | None) -> tuple[np.ndarray, float, float, float] | None:
    grid = (state or {}).get("map")
    if not grid:
        return None
    data = np.frombuffer(grid["data"], np.int8).reshape(grid["height"], grid["width"])
    return data >= 0, grid["origin"]["x"], grid["origin"]["y"], grid["resolution"]


def cells_lost(before: tuple, after: tuple) -> int:
    """Cells known in ``before`` that ``after`` does not know (grids of one resolution, each
    placed by its origin)."""
    kb, xb, yb, res = before
    ka, xa, ya, _ = after
    rows, cols = np.nonzero(kb)
    dc, dr = round((xb - xa) / res), round((yb - ya) / res)
    r2, c2 = rows + dr, cols + dc
    inside = (r2 >= 0) & (r2 < ka.shape[0]) & (c2 >= 0) & (c2 < ka.shape[1])
    return int((~inside).sum() + (~ka[r2[inside], c2[inside]]).sum())


def _progress(state: dict | None) -> int:
    return int((state or {}).get("processed", 0)) + int((state or {}).get("steps", 0))


def _wait(cond, timeout: float, poll: float = 0.1) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if cond():
            return True
        time.sleep(poll)
    return False


def chaos(bus: Bus, keys: Keys, fault: str, chaos_for: float) -> dict[str, Any]:
    """drop:/delay: on one service's input for chaos_for s of wall time, then off."""
    kind, svc, rest = fault.split(":", 2)
    topic, _, value = rest.rpartition(":")
    sets = [f'runtime.chaos_topics=["{topic}"]',
            f"runtime.chaos_drop={value}" if kind == "drop" else f"runtime.chaos_delay={value}"]
    for a in sets:
        err = set_param(bus, keys, svc, a)
        if err:
            return {"error": f"{svc}: {err}"}
    time.sleep(chaos_for)
    st = _state(bus, keys, svc) or {}
    for a in ("runtime.chaos_topics=[]", "runtime.chaos_drop=0.0", "runtime.chaos_delay=0.0"):
        set_param(bus, keys, svc, a)
    c = st.get("chaos") or {}
    return {"chaos_dropped": sum((c.get("dropped") or {}).values()),
            "chaos_delayed": sum((c.get("delayed") or {}).values())}


def inject(fault: str, bus: Bus, keys: Keys, watch: Watch, stop_for: float,
           chaos_for: float = 60.0) -> dict[str, Any]:
    """Inject one fault into the running stack; what it cost (see the module doc)."""
    sup = _state(bus, keys, "supervisor") or {}
    out: dict[str, Any] = {"at_sim_s": round(watch.sim_time, 1)}
    kind, _, name = fault.partition(":")
    if kind == "router":
        pid = sup.get("router_pid")
        if not pid:
            return {**out, "error": "no router pid"}
        t0 = time.monotonic()
        os.kill(pid, signal.SIGKILL)
        t_sim = watch.sim_time
        ok = _wait(lambda: (_state(bus, keys, "supervisor") or {}).get("router_restarts", 0)
                   >= sup.get("router_restarts", 0) + 1, 60)
        ok = ok and _wait(lambda: watch.sim_time > t_sim + 1.0, 120)
        out["recovery_s"] = round(time.monotonic() - t0, 2) if ok else None
        return out
    if kind in ("drop", "delay"):
        return {**out, **chaos(bus, keys, fault, chaos_for)}
    proc = (sup.get("processes") or {}).get(name) or {}
    pid = proc.get("pid")
    if not pid:
        return {**out, "error": f"no pid for {name}"}
    if kind == "stop":
        t_sim = watch.sim_time
        os.kill(pid, signal.SIGSTOP)
        time.sleep(stop_for)
        os.kill(pid, signal.SIGCONT)
        out["stood_still_sim_s"] = watch.stood_still_after(t_sim)
        return out
    before = _known_grid(_state(bus, keys, "mapper"))
    t0 = time.monotonic()
    os.kill(pid, signal.SIGKILL)

    def working() -> bool:
        st = _state(bus, keys, name)
        return bool(st) and st.get("pid") != pid and _progress(st) > 0

    ok = _wait(working, 120)
    out["recovery_s"] = round(time.monotonic() - t0, 2) if ok else None
    if before is not None:
        after = None
        if _wait(lambda: _known_grid(_state(bus, keys, "mapper")) is not None, 30):
            after = _known_grid(_state(bus, keys, "mapper"))
        out["cells_known"] = int(before[0].sum())
        out["cells_lost"] = cells_lost(before, after) if after is not None else None
    return out


def one_run(world: str, speed: float, fault: str | None, fault_at: float, stop_for: float,
            out: Path, max_sim: float, chaos_for: float = 60.0) -> dict[str, Any]:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    ns = f"benchfault{os.getpid()}"
    keys = Keys(ns, "robot1")
    cmd = [sys.executable, "-m", "topoexplore.tools.cli", "run", "--world", world, "--speed",
           str(speed), "--quiet", "--out", str(out), "--connect", endpoint, "--namespace", ns,
           "--max-sim-time", str(max_sim)]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            start_new_session=True)
    row: dict[str, Any] = {"fault": fault or "none"}
    try:
        if fault is not None:
            try:
                with Bus.client(endpoint, name="bench-faults", wait_for_router=True) as bus:
                    watch = Watch(bus, keys)
                    if _wait(lambda: watch.sim_time >= fault_at or proc.poll() is not None,
                             max_sim / speed + 300, 0.05) and proc.poll() is None:
                        row.update(inject(fault, bus, keys, watch, stop_for, chaos_for))
                    else:
                        row["error"] = "the run ended before the fault"
            except BusError as exc:
                row["error"] = str(exc)
        log, _ = proc.communicate(timeout=max_sim / speed * 3 + 600)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(timeout=10)
    try:
        rep = json.loads((out / "report.json").read_text())
    except (OSError, ValueError):
        return {**row, "finished": False, "error": row.get("error") or "no report"}
    row.update(finished=rep["finished"], coverage=rep["coverage"],
               collisions=rep["collisions"], restarts=rep["restarts"],
               path_m=rep["path_length_m"], sim_s=rep["sim_time_s"],
               stale_cmds=rep.get("stale_cmds", 0), watchdog_stops=rep.get("watchdog_stops", 0),
               lost=rep.get("lost_messages_total"))
    return row


def table(rows: list[dict], world: str, speed: float) -> str:
    base = next((r for r in rows if r["fault"] == "none"), None)
    lines = [f"{world}, real time x{speed:g}; fault at a random sim time (15-45 % of the "
             f"fault-free run)", "",
             "| fault | at [sim s] | finished | coverage | collisions | restarts | recovery "
             "[wall s] | stood still after [sim s] | cells lost / known | messages lost | "
             "path [m] (x none) |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]

    def f(v: Any, fmt: str = "{}") -> str:
        return "–" if v is None else fmt.format(v)

    for r in rows:
        ratio = (f" ({r['path_m'] / base['path_m']:.2f})" if base and r.get("path_m")
                 and base.get("path_m") else "")
        lost = (f"{r['cells_lost']} / {r['cells_known']}" if r.get("cells_known") is not None
                else "–")
        lines.append(
            f"| {r['fault']} | {f(r.get('at_sim_s'))} | {'yes' if r.get('finished') else 'NO'} "
            f"| {f(r.get('coverage'), '{:.3f}')} | {f(r.get('collisions'))} "
            f"| {f(r.get('restarts'))} | {f(r.get('recovery_s'))} "
            f"| {f(r.get('stood_still_sim_s'), '{:.2f}')} | {lost} | {f(r.get('lost'))} "
            f"| {f(r.get('path_m'), '{:.1f}')}{ratio} |"
            + (f" chaos: {r.get('chaos_dropped', 0)} dropped, {r.get('chaos_delayed', 0)} "
               f"delayed" if "chaos_dropped" in r else "")
            + (f" {r['error']}" if r.get("error") else ""))
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="topoexplore bench faults", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--world", default="office")
    ap.add_argument("--speed", type=float, default=4.0, help="real-time factor (default 4)")
    ap.add_argument("--faults", default=",".join(DEFAULT_FAULTS),
                    help="comma separated: kill:SERVICE, stop:SERVICE, router, "
                    "drop:SERVICE:TOPIC:SHARE, delay:SERVICE:TOPIC:SECONDS")
    ap.add_argument("--stop-for", type=float, default=5.0, help="[wall s] of SIGSTOP")
    ap.add_argument("--chaos-for", type=float, default=60.0,
                    help="[wall s] of a drop: or delay: fault")
    ap.add_argument("--seed", type=int, default=0, help="draws the fault moments")
    ap.add_argument("--max-sim-time", type=float, default=3000.0)
    ap.add_argument("--json", default=None, help="write the rows here")
    ap.add_argument("--keep", default=None,
                    help="keep each run's output directory (report, logs) under this one")
    ap.add_argument("--doc", default=None, help="write the table into this Markdown file")
    a = ap.parse_args(argv)
    faults = [f.strip() for f in a.faults.split(",") if f.strip()]
    for f in faults:
        why = parse_fault(f)
        if why:
            print(f"topoexplore bench faults: unknown fault {f!r} (expected {why}; services "
                  f"{', '.join(SERVICES)})", file=sys.stderr)
            return 2
    if not (a.speed > 0 and a.stop_for > 0 and a.chaos_for > 0 and a.max_sim_time > 0):
        print("topoexplore bench faults: --speed, --stop-for, --chaos-for, --max-sim-time must "
              "be > 0", file=sys.stderr)
        return 2
    rng = random.Random(a.seed)
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench-faults-") as tmp:
        if a.keep:
            Path(a.keep).mkdir(parents=True, exist_ok=True)
            tmp = a.keep
        base = one_run(a.world, a.speed, None, 0.0, a.stop_for, Path(tmp) / "none",
                       a.max_sim_time)
        rows.append(base)
        print(json.dumps(base), flush=True)
        span = base.get("sim_s") or 300.0
        for i, fault in enumerate(faults):
            at = rng.uniform(0.15, 0.45) * span
            r = one_run(a.world, a.speed, fault, at, a.stop_for, Path(tmp) / str(i),
                        a.max_sim_time, a.chaos_for)
            rows.append(r)
            print(json.dumps(r), flush=True)
    text = table(rows, a.world, a.speed)
    print("\n" + text)
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1))
    if a.doc:
        Path(a.doc).write_text(text)
    return 0
