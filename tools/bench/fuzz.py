"""``topoexplore bench fuzz``: malformed traffic on every key a running stack subscribes.

    topoexplore bench fuzz [--per-key 10000] [--rate 2000] [--world paper-room] [--seed 0]

Starts the simulated stack (router and every service, real time, a free loopback port, a fresh
namespace), lets it explore, and publishes ``--per-key`` malformed messages (at most 10 000,
loopback only) on each key some service subscribes: ``cmd_vel``, ``scan``, ``odom``, ``map``,
``topo``, ``reliability``, ``plan``, ``explore/status``. Each payload is one of: random bytes,
MessagePack that is not a map, a valid message with a field missing, a float made NaN or
infinite, a value of the wrong type, a header out of range; each is checked against our
decoder before it is sent, so every one must be refused.

Afterwards it checks, and prints:
- every service is the same process as before (no crash, no restart);
- every bad message was counted by every subscriber of its key (the state queryables);
- each service logged a bad message at most once per kind of error and key (plus one
  summary line per key every 5 s), not once per message;
- no ``cmd_vel`` on the bus carried a NaN or an infinite number.
Exit 0 when all hold, 1 otherwise.
"""

from __future__ import annotations

import argparse
import math
import random
import re
import sys
import threading
import time
from collections import Counter
from typing import Any

import msgspec
import numpy as np

from topoexplore.common import convert
from topoexplore.common import messages as m
from topoexplore.common.bus import MAX_KINDS, Bus
from topoexplore.common.domain import Command, GridMap, Odom, Pose, Route
from topoexplore.common.grid import GridGeometry
from topoexplore.common.keys import SERVICE_IO, TOPICS, Keys

MAX_PER_KEY = 10_000
KINDS = ("bytes", "not-a-map", "missing", "nan", "wrong-type", "header")


def _h(frame: str = "map") -> m.Header:
    return m.header(3, 0.3, frame, 3)


# one valid message per type: the fuzzer breaks one thing in it
EXAMPLES: dict[type, Any] = {
    m.LaserScan: m.LaserScan(header=_h("laser"), angle_min=-1.5707963, angle_max=-1.5184364,
                             angle_increment=0.0174533, range_min=0.02, range_max=8.0,
                             ranges=[1.0, 2.0, 8.0, 0.5], intensities=[1.0, 1.0, 0.0, 3.0]),
    m.Odometry: convert.odom_to_msg(Odom(Pose(1.0, 2.0, 0.5), 0.2, 0.1), _h("odom")),
    m.PoseStamped: convert.truth_to_msg(Pose(1.0, 2.0, 0.5), _h()),
    m.TransformStamped: convert.correction_to_msg(Pose(0.1, -0.2, 0.05), _h()),
    m.Twist: convert.command_to_msg(Command(0.2, -0.1), _h("base_link")),
    m.OccupancyGrid: convert.grid_to_msg(GridMap(
        np.array([[-1, 0, 100], [50, -1, 0]], np.int8), GridGeometry(0.1, -1.0, -2.0, 3, 2)),
        _h()),
    m.TopoGraph: m.TopoGraph(header=_h(), nodes=[
        m.TopoNode(id=4, kind="end", x=0.0, y=0.0), m.TopoNode(id=7, kind="branch", x=1, y=0)],
        edges=[m.TopoEdge(a=4, b=7, points=[[0, 0], [1, 0]], length=1.0, clearance=0.5)]),
    m.Reliability: m.Reliability(header=_h(), nodes=[m.NodeReliability(
        id=4, x=0.0, y=0.0, p=0.5, d=0.5, a=0.5, r_min=1.0, alpha_max=0.1, visible=True)]),
    m.Path: convert.route_to_msg(Route(np.array([[0.0, 0.0], [1.0, 1.0]]), 1, 9, (1.0, 1.0)),
                                 _h()),
    m.ExploreStatus: m.ExploreStatus(header=_h(), state="exploring"),
    m.SimStatus: m.SimStatus(header=_h(), world="w", mode="lockstep", sim_time=0.3, steps=15,
                             collisions=0, path_length=0.1, real_time_factor=1.0),
}


def _paths(value: Any, path: tuple = ()) -> list[tuple]:
    """Paths to the leaves of a nested dict/list value."""
    if isinstance(value, dict):
        return [p for k, v in value.items() for p in _paths(v, (*path, k))]
    if isinstance(value, list) and value:
        return [p for i, v in enumerate(value) for p in _paths(v, (*path, i))]
    return [path]


def _set(value: Any, path: tuple, new: Any) -> Any:
    if not path:
        return new
    value = list(value) if isinstance(value, list) else dict(value)
    value[path[0]] = _set(value[path[0]], path[1:], new)
    return value


def malformed(msg_type: type, kind: str, rng: random.Random) -> bytes:
    """One payload of ``kind`` for a key of ``msg_type`` (not yet checked to be refused)."""
    base = msgspec.to_builtins(EXAMPLES[msg_type])
    if kind == "bytes":
        return bytes(rng.getrandbits(8) for _ in range(rng.randrange(0, 64)))
    if kind == "not-a-map":
        return msgspec.msgpack.encode(rng.choice([7, -1.5, "scan", [1, 2, 3], None, True]))
    if kind == "missing":
        base.pop(rng.choice(list(base)))
        return msgspec.msgpack.encode(base)
    leaves = _paths(base)
    if kind == "nan":
        floats = [p for p in leaves if isinstance(_get(base, p), float)] or leaves
        return msgspec.msgpack.encode(_set(base, rng.choice(floats),
                                           rng.choice([math.nan, math.inf, -math.inf])))
    if kind == "wrong-type":
        return msgspec.msgpack.encode(_set(base, rng.choice(leaves),
                                           rng.choice(["x", [1], {"a": 1}, b"\x00"])))
    return msgspec.msgpack.encode(_set(base, ("header", rng.choice(["seq", "src_seq"])),
                                       rng.choice([-5, 2**63 - 1])))


def _get(value: Any, path: tuple) -> Any:
    for p in path:
        value = value[p]
    return value


def refused(payload: bytes, msg_type: type) -> bool:
    try:
        m.decode(payload, msg_type)
    except m.MessageError:
        return True
    return False


def fuzz_payloads(msg_type: type, n: int, rng: random.Random) -> list[tuple[str, bytes]]:
    """``n`` (kind, payload) that our decoder refuses, kinds in turn."""
    out: list[tuple[str, bytes]] = []
    tries = 0
    while len(out) < n and tries < 20 * n + 100:
        kind = KINDS[tries % len(KINDS)]
        tries += 1
        p = malformed(msg_type, kind, rng)
        if refused(p, msg_type):
            out.append((kind, p))
    return out


_BAD_LINE = re.compile(r"\[(\w+)\].*bad message #")


def flood(bus: Bus, keys: Keys, topics: list[str], per_key: int, rate: float,
          rng: random.Random) -> dict[str, Counter]:
    """Publish ``per_key`` refused payloads on each topic at ``rate``; the kinds sent."""
    sent: dict[str, Counter] = {}
    for topic in topics:
        pub = bus.publisher(keys.topic(topic), reliable=True)
        payloads = fuzz_payloads(TOPICS[topic], per_key, rng)
        sent[topic] = Counter(k for k, _ in payloads)
        t_next = time.monotonic()
        for _kind, p in payloads:
            pub.put(p)
            t_next += 1.0 / rate
            delay = t_next - time.monotonic()
            if delay > 0:
                time.sleep(delay)
    return sent


def settle(bus: Bus, keys: Keys, before: dict[str, dict], expected: dict[str, int],
           timeout: float = 30.0) -> dict[str, dict]:
    """The services' states once each counted what it was sent (or after ``timeout``)."""
    from topoexplore.tools.livestate import StateError, fetch_state

    deadline = time.monotonic() + timeout
    after: dict[str, dict] = {}
    while time.monotonic() < deadline:
        try:
            after = {s: fetch_state(bus, keys, s) for s in SERVICE_IO}
        except StateError:
            time.sleep(0.5)
            continue
        if all(after[s]["bad_messages_total"] - before[s]["bad_messages_total"] >= expected[s]
               for s in SERVICE_IO):
            break
        time.sleep(0.5)
    return after


def verdict(before: dict, after: dict, expected: dict[str, int], processes: dict,
            logged: Counter, took: float) -> list[str]:
    """Print the table per service; the checks that failed."""
    failures = []
    print(f"{'service':12s} {'same pid':>8s} {'restarts':>8s} {'bad counted':>12s} "
          f"{'expected':>9s} {'log lines':>9s}")
    for s in SERVICE_IO:
        st, b = after.get(s) or {}, before[s]
        counted = st.get("bad_messages_total", 0) - b["bad_messages_total"]
        same = st.get("pid") == b["pid"]
        restarts = processes.get(s, {}).get("restarts", 0)
        print(f"{s:12s} {str(same):>8s} {restarts:>8d} {counted:>12d} {expected[s]:>9d} "
              f"{logged.get(s, 0):>9d}")
        if not same or restarts:
            failures.append(f"{s} restarted")
        if counted != expected[s]:
            failures.append(f"{s} counted {counted} of {expected[s]}")
        if st.get("callback_errors", 0):
            failures.append(f"{s}: {st['callback_errors']} callback errors")
        limit = len(SERVICE_IO[s][0]) * (MAX_KINDS + took / 5.0 + 2)
        if logged.get(s, 0) > limit:
            failures.append(f"{s} logged {logged[s]} bad-message lines (> {limit:.0f})")
    return failures


def main(argv: list[str] | None = None) -> int:
    from topoexplore.tools.launch.core import load_profile
    from topoexplore.tools.launch.supervisor import Supervisor, free_port, profile_path
    from topoexplore.tools.livestate import fetch_state

    ap = argparse.ArgumentParser(prog="topoexplore bench fuzz", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--per-key", type=int, default=MAX_PER_KEY,
                    help=f"malformed messages per key (at most {MAX_PER_KEY})")
    ap.add_argument("--rate", type=float, default=2000.0, help="messages per second per key")
    ap.add_argument("--world", default="paper-room")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args(argv)
    if not (1 <= a.per_key <= MAX_PER_KEY) or not (a.rate > 0):
        print(f"topoexplore bench fuzz: --per-key must be 1..{MAX_PER_KEY} and --rate > 0",
              file=sys.stderr)
        return 2
    rng = random.Random(a.seed)
    keys = Keys(f"fuzz{rng.getrandbits(32):08x}", "robot1")
    endpoint = f"tcp/127.0.0.1:{free_port()}"  # loopback only
    lines: list[str] = []
    lock = threading.Lock()

    def sink(line: str) -> None:
        with lock:
            lines.append(line)

    bad_cmds = Counter()

    def on_cmd(_key: str, payload: bytes, _enc: str) -> None:  # the controller's commands
        try:
            d = msgspec.msgpack.decode(payload)
        except msgspec.DecodeError:
            return
        vals = [d.get("v"), d.get("w")] if isinstance(d, dict) else []
        if any(isinstance(v, float) and not math.isfinite(v) for v in vals):
            bad_cmds["non-finite"] += 1

    topics = sorted({t for ins, _ in SERVICE_IO.values() for t in ins})
    sup = Supervisor(load_profile(profile_path("sim")), keys, endpoint, sink=sink,
                     overrides=[f'sim.world="{a.world}"', "localizer.enabled=true"])  # all 7
    try:
        if not sup.start(ready_timeout=120):
            print("topoexplore bench fuzz: the stack did not come up:\n" + "\n".join(lines[-20:]),
                  file=sys.stderr)
            return 1
        with Bus.client(endpoint, name="fuzz") as bus:
            before = {s: fetch_state(bus, keys, s) for s in SERVICE_IO}
            t0 = time.monotonic()
            sent = flood(bus, keys, topics, a.per_key, a.rate, rng)
            bus.subscribe_raw(keys.topic("cmd_vel"), on_cmd)  # after our own garbage
            time.sleep(3.0)
            expected = {s: sum(sum(sent[t].values()) for t in ins)
                        for s, (ins, _) in SERVICE_IO.items()}
            after = settle(bus, keys, before, expected)
            took = time.monotonic() - t0
        print(f"{sum(sum(c.values()) for c in sent.values())} malformed messages on "
              f"{len(topics)} keys in {took:.0f} s (kinds: "
              f"{', '.join(f'{k} {v}' for k, v in sum(sent.values(), Counter()).items())})")
        with lock:
            logged = Counter(mt.group(1) for ln in lines if (mt := _BAD_LINE.search(ln)))
        failures = verdict(before, after, expected, sup.table()["processes"], logged, took)
        if bad_cmds:
            failures.append(f"{bad_cmds['non-finite']} cmd_vel with NaN/Inf after the flood")
        print(f"cmd_vel with NaN or Inf from the stack: {bad_cmds['non-finite']}")
    finally:
        sup.stop()
    for f in failures:
        print(f"FAIL: {f}")
    print("all checks hold" if not failures else f"{len(failures)} check(s) failed")
    return 0 if not failures else 1
