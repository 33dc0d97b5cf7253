"""Tests of tools/keys.py (``topoexplore keys list|echo|hz|get``).

Pure helpers are unit-tested directly. The commands run as real processes against a real Zenoh
router process and a real publisher process on loopback (a free port and a namespace per test;
no mocks). Rate checks use loose bounds: they show the tool measures, not how fast the box is.
"""

from __future__ import annotations

import base64
import json
import math
import os
import select
import signal
import socket
import subprocess
import sys
import textwrap
import time
import uuid
from pathlib import Path

import pytest
import yaml

from topoexplore.common.keys import Keys
from topoexplore.tools.keys import (
    FieldError,
    KeyToolError,
    RateStats,
    Summary,
    format_rate_line,
    format_summary_line,
    format_table,
    format_yaml,
    parse_field_args,
    resolve_key,
    select_fields,
    state_selector,
    summarize,
    to_jsonable,
)

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONUNBUFFERED": "1"}
TOOL = "from topoexplore.tools.keys import main; raise SystemExit(main())"

# --- pure helpers --------------------------------------------------------------------------


def test_resolve_key_relative_and_full():
    k = Keys("ns1", "robot1")
    assert resolve_key("scan", k) == "ns1/robot1/scan"
    assert resolve_key("explore/status", k) == "ns1/robot1/explore/status"
    assert resolve_key("mapper/state", k) == "ns1/robot1/mapper/state"
    assert resolve_key("alive/*", k) == "ns1/robot1/alive/*"
    assert resolve_key("ns1/robot2/scan", k) == "ns1/robot2/scan"
    assert resolve_key("**/scan", k) == "**/scan"
    assert resolve_key("/scan", k) == "scan"  # leading '/' forces a full key
    for bad in ("", "a//b", "scan/", "a/b?x", "a/sc*n"):
        with pytest.raises(KeyToolError):
            resolve_key(bad, k)
    assert state_selector("mapper", k) == "ns1/robot1/mapper/state"
    assert state_selector("ns1/*/mapper/state", k) == "ns1/*/mapper/state"


def test_summarize_numbers_bytes_points_and_lists():
    assert summarize([1.0, 2.0]) == [1.0, 2.0]  # short lists unchanged
    s = summarize([float(i) for i in range(181)])
    assert isinstance(s, Summary) and s.startswith("<181 floats")
    assert "min 0" in s and "max 180" in s and "mean 90" in s
    assert "2 non-finite" in summarize([1.0] * 10 + [math.inf, math.nan])
    assert summarize(list(range(20))).startswith("<20 ints")
    grid = bytes([255] * 5 + [0] * 3 + [100] * 2 + [50])  # int8: -1 x5, 0 x3, 100 x2, 50
    g = summarize({"data": grid})["data"]
    assert g == "<11 bytes: unknown 5, free 3, occupied 2, uncertain 1>"
    assert summarize({"blob": b"\x00" * 1000}) == {"blob": "<1000 bytes>"}
    pts = summarize([[float(i), 2.0 * i] for i in range(50)])
    assert pts.startswith("<50 points") and "first [0, 0]" in pts and "last [49, 98]" in pts
    nodes = summarize([{"id": i, "r": list(range(100))} for i in range(20)])
    assert len(nodes) == 4 and nodes[0]["r"].startswith("<100 ints")
    assert nodes[-1] == "... 17 more (20 items)"
    assert summarize(["x"] * 30)[-1] == "... 22 more (30 items)"
    raw = {"a": list(range(100)), "b": b"xy"}
    assert summarize(raw, full=True) is raw
    with pytest.raises(KeyToolError):
        summarize([1], max_items=0)


def test_select_fields_and_errors():
    msg = {"header": {"seq": 3, "stamp": {"sec": 1, "nanosec": 5}},
           "waypoints": [[0.0, 1.0], [2.0, 3.0]], "m": {7: "x"}}
    assert select_fields(msg, ["header.stamp.nanosec"]) == {"header.stamp.nanosec": 5}
    assert select_fields(msg, ["header.stamp"]) == {"header.stamp": {"sec": 1, "nanosec": 5}}
    assert select_fields(msg, ["waypoints.1.0", "header.seq"]) == {"waypoints.1.0": 2.0,
                                                                   "header.seq": 3}
    assert select_fields(msg, ["waypoints.-1"]) == {"waypoints.-1": [2.0, 3.0]}
    assert select_fields(msg, ["m.7"]) == {"m.7": "x"}  # int map keys (state dicts)
    for bad in (["nope"], ["header.nope"], ["waypoints.5"], ["waypoints.x"], ["header.seq.a"]):
        with pytest.raises(FieldError):
            select_fields(msg, bad)
    with pytest.raises(FieldError):
        select_fields(msg, [])
    assert parse_field_args(["a.b,c", "d"]) == ["a.b", "c", "d"]
    with pytest.raises(FieldError):
        parse_field_args(["a..b"])


def test_format_yaml_and_json():
    obj = {"header": {"seq": 1, "frame_id": "map"}, "ranges": Summary("<3 floats: ...>"),
           "nodes": [{"id": 1, "kind": "end"}, {"id": 2, "kind": "branch"}],
           "pts": [[1.0, 2.0]], "empty": [], "s": "two words", "r": math.inf, "ok": True,
           "w": "yes", "u": "Zürich", "b": b"\x01\x02"}
    lines = format_yaml(obj).splitlines()
    assert lines[:3] == ["header:", "  seq: 1", "  frame_id: map"]  # block style, in order
    assert "ranges: <3 floats: ...>" in lines  # a summary is printed plainly
    assert lines[lines.index("nodes:") + 1:lines.index("nodes:") + 5] == [
        "- id: 1", "  kind: end", "- id: 2", "  kind: branch"]
    assert lines[lines.index("pts:") + 1] == "- [1.0, 2.0]"  # a list of scalars inline
    assert "empty: []" in lines and "s: two words" in lines and "u: Zürich" in lines
    assert "w: 'yes'" in lines  # a string that would read back as a bool is quoted
    assert "r: .inf" in lines and "ok: true" in lines
    assert lines[lines.index("b: !!binary |") + 1] == "  AQI="
    plain = {k: v for k, v in obj.items() if k != "ranges"}  # all but summaries read back
    assert yaml.safe_load(format_yaml(plain)) == plain
    assert format_yaml(3.5) == "3.5" and format_yaml(Summary("<x>")) == "<x>"
    assert format_yaml({"x": 9.350000000000001, "t": 1712345678.25, "e": 1e-12}) == (
        "x: 9.35\nt: 1712345678.25\ne: 1.0e-12")  # binary noise dropped, precision kept
    j = json.loads(json.dumps(to_jsonable({"r": math.inf, "b": b"\x01\x02", 1: Summary("<x>")})))
    assert j == {"r": "inf", "b": "AQI=", "1": "<x>"}
    table = format_table(["KEY", "HZ"], [["scan", 20.0], ["map", None]]).splitlines()
    assert table[0].split() == ["KEY", "HZ"] and table[2].split() == ["map", "-"]
    with pytest.raises(KeyToolError):
        format_table(["A"], [[1, 2]])


def test_rate_stats_explicit_timestamps():
    st = RateStats(window=5)
    assert st.window() is None and st.summary()["rate_hz"] is None
    st.add(0.0, 100)
    assert st.window() is None and st.summary()["count"] == 1
    for i, t in enumerate([0.1, 0.2, 0.3, 0.4, 0.7, 0.8]):  # 10 Hz with one late message
        st.add(t, 100 + 10 * (i + 1))
    w = st.window()  # last 5 arrivals: t = 0.2, 0.3, 0.4, 0.7, 0.8 -> periods .1 .1 .3 .1
    assert w["n"] == 5
    assert w["period_min"] == pytest.approx(0.1) and w["period_max"] == pytest.approx(0.3)
    assert w["rate_hz"] == pytest.approx(1.0 / 0.15)
    assert w["period_std"] == pytest.approx(math.sqrt(((0.05**2) * 3 + 0.15**2) / 4))
    assert w["bandwidth"] == pytest.approx((140 + 150 + 160) / 0.6 + 130 / 0.6)
    assert w["size_last"] == 160 and w["size_min"] == 120
    su = st.summary()  # all 7 messages over 0.8 s
    assert su["count"] == 7 and su["duration"] == pytest.approx(0.8)
    assert su["rate_hz"] == pytest.approx(6 / 0.8)
    assert su["period_min"] == pytest.approx(0.1) and su["period_max"] == pytest.approx(0.3)
    assert su["total_bytes"] == 100 + sum(100 + 10 * i for i in range(1, 7))
    assert su["bandwidth"] == pytest.approx((su["total_bytes"] - 100) / 0.8)
    assert "Hz" in format_rate_line(w) and "7 msgs" in format_summary_line(su)
    with pytest.raises(KeyToolError):
        st.add(0.5, 10)  # time went back
    with pytest.raises(KeyToolError):
        st.add(math.nan, 10)
    with pytest.raises(KeyToolError):
        RateStats(window=1)


# --- real processes --------------------------------------------------------------------------

PUBLISHER = textwrap.dedent('''
    import math, signal, sys, threading, time
    from topoexplore.common import messages as m
    from topoexplore.common.bus import Bus
    from topoexplore.common.keys import Keys
    endpoint, ns = sys.argv[1], sys.argv[2]
    keys = Keys(ns, "robot1")
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    bus = Bus.client(endpoint, name="fake")
    try:
        scan = bus.publisher(keys.scan, m.LaserScan)
        odom = bus.publisher(keys.odom, m.Odometry)
        grid = bus.publisher(keys.map, m.OccupancyGrid)
        bus.queryable(keys.state("fake"), lambda p: {
            "service": "fake", "processed": 7, "blob": b"\\x00" * 1000,
            "nested": {"a": [1, 2, 3]}})
        bus.declare_token(keys.alive("fake"))
        print("ready", flush=True)
        i = 0
        t0 = time.monotonic()
        while not stop.is_set():
            t = i * 0.05
            if i % 10 == 9:  # every 10th scan is garbage
                scan.put(b"\\x01garbage")
            else:
                scan.put(m.LaserScan(header=m.header(i, t, "laser", i), angle_min=-1.5,
                                     angle_max=-1.5 + 180 * 0.01, angle_increment=0.01,
                                     range_min=0.1, range_max=10.0,
                                     ranges=[1.0 + 0.01 * k for k in range(181)]))
            pose = m.GeoPose(position=m.Point(x=0.1 * i), orientation=m.quaternion(0.0))
            odom.put(m.Odometry(header=m.header(i, t, "odom"),
                                pose=m.PoseWithCovariance(pose=pose),
                                twist=m.TwistWithCovariance(twist=m.GeoTwist(
                                    linear=m.Vector3(x=0.5), angular=m.Vector3()))))
            if i % 10 == 0:
                info = m.MapMetaData(map_load_time=m.stamp(t), resolution=0.1, width=10,
                                     height=10, origin=m.GeoPose(position=m.Point(),
                                                                 orientation=m.Quaternion()))
                grid.put(m.OccupancyGrid(header=m.header(i, t, "map", i), info=info,
                                         data=bytes([255] * 50 + [0] * 30 + [100] * 20)))
            i += 1
            stop.wait(max(0.0, t0 + i * 0.05 - time.monotonic()))
    finally:
        bus.close()
''')


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait_line(p: subprocess.Popen, text: str, timeout: float = 10.0) -> None:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        r, _, _ = select.select([p.stdout], [], [], 0.1)
        if r:
            line = p.stdout.readline()
            if text in line:
                return
            if not line and p.poll() is not None:
                break
    raise AssertionError(f"process did not print {text!r} (rc={p.poll()})")


def _stop(procs: list[subprocess.Popen]) -> None:
    for p in procs:
        if p.poll() is None:
            p.terminate()
    for p in procs:
        try:
            p.wait(timeout=5)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait(timeout=5)
        for f in (p.stdout, p.stderr):
            if f is not None:
                f.close()


class Stack:
    """A router process + the fake publisher process; tools run as processes too."""

    def __init__(self, tmp_path: Path, with_publisher: bool = True):
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.ns = "kt" + uuid.uuid4().hex[:8]
        self.procs: list[subprocess.Popen] = []
        script = tmp_path / "fake_publisher.py"
        script.write_text(PUBLISHER)
        router = self._popen([sys.executable, "-m", "topoexplore.tools.router", "--listen",
                              self.endpoint])
        _wait_line(router, "router listening")
        if with_publisher:
            pub = self._popen([sys.executable, str(script), self.endpoint, self.ns])
            _wait_line(pub, "ready")

    def _popen(self, cmd: list[str]) -> subprocess.Popen:
        p = subprocess.Popen(cmd, cwd=ROOT, env=ENV, stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True)
        self.procs.append(p)
        return p

    def tool(self, *args: str) -> subprocess.Popen:
        return self._popen([sys.executable, "-c", TOOL, *args, "--connect", self.endpoint,
                            "--namespace", self.ns])

    def close(self) -> None:
        _stop(self.procs)


def finish(p: subprocess.Popen, timeout: float = 15.0) -> tuple[int, str, str]:
    out, err = p.communicate(timeout=timeout)
    assert "Traceback" not in err, err
    return p.returncode, out, err


@pytest.fixture
def stack(tmp_path):
    s = Stack(tmp_path)
    try:
        yield s
    finally:
        s.close()


def test_list_table_and_json(stack):
    table = stack.tool("list", "--duration", "1.5")
    js = stack.tool("list", "--duration", "1.5", "--json", "--all-robots")
    rc, out, err = finish(table)
    assert rc == 0, err
    rows = {ln.split()[0]: ln.split() for ln in out.splitlines() if ln.strip()}
    assert rows["scan"][1] == "LaserScan" and rows["odom"][1] == "Odometry"
    assert 10.0 < float(rows["scan"][3]) < 30.0  # ~20 Hz (loose)
    assert rows["scan"][-2] == "BAD" and rows["odom"][-1] == "ok"  # garbage counted, no crash
    assert rows["map"][1] == "OccupancyGrid"
    assert rows["fake"][:2] == ["fake", "robot1"]  # liveliness token
    assert rows["fake/state"][1] == "ok"  # state queryable answered
    assert "last error: LaserScan" in out
    rc, out, err = finish(js)
    assert rc == 0, err
    d = json.loads(out)
    keys = {k["key"]: k for k in d["keys"]}
    scan = keys[f"{stack.ns}/robot1/scan"]
    assert scan["type"] == "LaserScan" and 10.0 < scan["rate_hz"] < 30.0 and scan["bad"] >= 1
    assert scan["size"] > 1000 or scan["size"] < 20  # a scan or the garbage, whichever was last
    assert keys[f"{stack.ns}/robot1/odom"]["bad"] == 0
    assert d["services"] == [{"service": "fake", "robot": "robot1",
                              "token": f"{stack.ns}/robot1/alive/fake"}]
    assert d["states"][0]["ok"] and d["states"][0]["key"] == f"{stack.ns}/robot1/fake/state"


def test_echo(stack):
    once = stack.tool("echo", "scan", "--once")
    fields = stack.tool("echo", "scan", "--count", "12", "--field", "header.seq,ranges.0")
    js = stack.tool("echo", "odom", "--count", "2", "--json", "--field", "pose.pose.position")
    stamps = stack.tool("echo", "odom", "--once", "--field", "header.stamp,header.frame_id")
    scan_js = stack.tool("echo", "scan", "--once", "--json")
    grid = stack.tool("echo", f"{stack.ns}/robot1/map", "--once", "--timeout", "5")
    wild = stack.tool("echo", f"{stack.ns}/robot1/*", "--count", "3", "--json")
    quiet = stack.tool("echo", "explore/status", "--timeout", "0.5")
    rc, out, err = finish(once)
    assert rc == 0, err
    assert out.startswith("header:") and "ranges: <181 floats: min 1, max 2.8" in out
    assert out.rstrip().endswith("---") and out.count("---") == 1
    rc, out, err = finish(fields)
    assert rc == 0, err
    seqs = [int(ln.split()[1]) for ln in out.splitlines() if ln.startswith("header.seq:")]
    assert len(seqs) == 12 and seqs == sorted(seqs)
    assert out.count("ranges.0: 1.0") == 12
    assert "bad message on" in err and "LaserScan" in err  # 12 good of >= 13 include garbage
    rc, out, err = finish(js)
    assert rc == 0, err
    poses = [json.loads(ln) for ln in out.splitlines()]
    assert len(poses) == 2 and set(poses[0]) == {"x", "y", "z"}
    rc, out, err = finish(stamps)
    assert rc == 0, err
    d = yaml.safe_load(out.split("---")[0])  # a stamp is builtin_interfaces/Time
    assert set(d["header.stamp"]) == {"sec", "nanosec"} and d["header.frame_id"] == "odom"
    rc, out, err = finish(scan_js)
    assert rc == 0, err
    ranges = json.loads(out)["ranges"]  # a real array for scripts, not "<181 floats ...>"
    assert isinstance(ranges, list) and len(ranges) == 181 and min(ranges) == 1.0
    rc, out, err = finish(grid)
    assert rc == 0, err
    assert "data: <100 bytes: unknown 50, free 30, occupied 20>" in out
    rc, out, err = finish(wild)
    assert rc == 0, err
    lines = [json.loads(ln) for ln in out.splitlines()]
    assert len(lines) == 3 and all(ln["key"].startswith(f"{stack.ns}/robot1/") for ln in lines)
    rc, out, err = finish(quiet)
    assert rc == 1 and out == "" and len(err.strip().splitlines()) == 1
    assert "no message" in err


def test_hz(stack):
    rc, out, err = finish(stack.tool("hz", "scan", "--duration", "2.2", "--window", "50"))
    assert rc == 0, err
    lines = out.strip().splitlines()
    per_second = [ln for ln in lines if ln.startswith("rate ")]
    assert len(per_second) >= 1 and "bw " in per_second[0] and "std " in per_second[0]
    summary = lines[-1]
    assert summary.startswith(f"summary {stack.ns}/robot1/scan:")
    rate = float(summary.split("mean rate ")[1].split()[0])
    assert 10.0 < rate < 30.0


def test_get(stack):
    full = stack.tool("get", "fake")
    field = stack.tool("get", "fake", "--json", "--field", "nested.a")
    key = stack.tool("get", f"{stack.ns}/*/fake/state", "--json")
    missing = stack.tool("get", "nope", "--timeout", "0.5")
    rc, out, err = finish(full)
    assert rc == 0, err
    assert "service: fake" in out and "processed: 7" in out and "blob: <1000 bytes>" in out
    assert "nested:\n  a: [1, 2, 3]\n" in out
    rc, out, err = finish(field)
    assert rc == 0 and json.loads(out) == [1, 2, 3], err
    rc, out, err = finish(key)
    assert rc == 0, err
    d = json.loads(out)
    # --json is for scripts: whole values (bytes as base64), never a "<1000 bytes>" summary
    assert d["data"]["processed"] == 7 and base64.b64decode(d["data"]["blob"]) == bytes(1000)
    rc, out, err = finish(missing)
    assert rc == 1 and len(err.strip().splitlines()) == 1 and "no reply" in err


def test_ctrl_c_exits_cleanly(stack):
    echo = stack.tool("echo", "scan")
    lst = stack.tool("list", "--duration", "30")
    _wait_line(echo, "---")
    time.sleep(0.3)
    echo.send_signal(signal.SIGINT)
    lst.send_signal(signal.SIGINT)
    rc, _, err = finish(echo, timeout=10)
    assert rc == 0, err
    rc, _, err = finish(lst, timeout=10)
    assert rc == 130, err


def test_no_router_and_bad_arguments(tmp_path):
    port = free_port()  # nobody listens here
    base = [sys.executable, "-c", TOOL]
    cases = [
        ["list", "--connect", f"tcp/127.0.0.1:{port}"],
        ["echo", "scan", "--connect", f"tcp/127.0.0.1:{port}"],
        ["get", "mapper", "--connect", f"tcp/127.0.0.1:{port}"],
        ["echo", "a//b"],
        ["echo", "scan", "--count", "0"],
        ["hz", "scan", "--window", "x"],
        ["list", "--namespace", "bad ns"],
        ["echo", "scan", "--connect", "nonsense"],
        ["frobnicate"],
    ]
    procs = [subprocess.Popen(base + c, cwd=ROOT, env=ENV, stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True) for c in cases]
    try:
        for c, p in zip(cases, procs, strict=True):
            rc, out, err = finish(p)
            assert rc == 2, (c, rc, err)
            assert len(err.strip().splitlines()) == 1, (c, err)
            assert out == ""
    finally:
        _stop(procs)
