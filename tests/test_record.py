"""Recording and playing back (issue 13): the Foxglove conversions (pure), the MCAP recorder on
scripted samples, and `topoexplore run --record` + `topoexplore play` with real processes."""

from __future__ import annotations

import json
import math
import os
import re
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import msgspec
import numpy as np
import pytest

from tests.conftest import REPO, free_port
from topoexplore.common import convert
from topoexplore.common import messages as m
from topoexplore.common.bus import Bus
from topoexplore.common.domain import Pose, Route, Scan
from topoexplore.common.keys import Keys
from topoexplore.tools import fox
from topoexplore.tools.record import Recorder, header_of, raw_messages, read_summary

pytest.importorskip("mcap")
pytest.importorskip("foxglove")
pytest.importorskip("mcap_protobuf")


def dec(fmsg):
    """A Foxglove message decoded as Foxglove would: protobuf, from its own schema."""
    from mcap.records import Schema
    from mcap_protobuf.decoder import DecoderFactory

    sc = fmsg.get_schema()
    schema = Schema(id=1, name=sc.name, encoding=sc.encoding, data=bytes(sc.data))
    return DecoderFactory().decoder_for("protobuf", schema)(fmsg.encode())


def hdr(seq: int, stamp: float, src: int = -1, frame: str = "map") -> m.Header:
    return m.header(seq, stamp, frame, src)


def grid_msg(seq: int = 0) -> m.OccupancyGrid:
    data = bytes([0xFF, 0, 100, 50, 0xFF, 0])  # unknown, free, occupied, half, unknown, free
    h = hdr(seq, 1.0, seq)
    return m.OccupancyGrid(header=h, info=m.MapMetaData(
        map_load_time=h.stamp, resolution=0.1, width=3, height=2,
        origin=m.GeoPose(position=m.Point(x=-1.0, y=-2.0), orientation=m.Quaternion())),
        data=data)


def scan_msg(seq: int, stamp: float, ranges: list[float]) -> m.LaserScan:
    return convert.scan_to_msg(Scan(np.asarray(ranges), -math.pi / 2, math.pi / 180, 0.02, 8.0),
                               hdr(seq, stamp, seq, "laser"))


def pose_msg(seq: int, stamp: float, x: float, frame: str = "map") -> m.PoseStamped:
    return convert.truth_to_msg(Pose(x, 0.0, 0.0), hdr(seq, stamp, seq, frame))


def path_msg(seq: int, stamp: float, waypoints: list) -> m.Path:
    return convert.route_to_msg(Route(np.asarray(waypoints, float), 1, 9, (1.0, 1.0)),
                                hdr(seq, stamp, seq))


def topo_msg(src: int) -> m.TopoGraph:
    nodes = [m.TopoNode(id=4, kind="end", x=0.0, y=0.0), m.TopoNode(id=7, kind="branch", x=1, y=0),
             m.TopoNode(id=9, kind="end", x=2.0, y=0.0)]
    edges = [m.TopoEdge(a=4, b=7, points=[[0, 0], [1, 0]], length=1.0, clearance=0.5),
             m.TopoEdge(a=7, b=9, points=[[1, 0], [2, 0]], length=1.0, clearance=0.5)]
    return m.TopoGraph(header=hdr(src, 0.2 * src, src), nodes=nodes, edges=edges)


def rel_msg(src: int) -> m.Reliability:
    def node(i: int, p: float) -> m.NodeReliability:
        return m.NodeReliability(id=i, x=0.0, y=0.0, p=p, d=0.5, a=0.5, r_min=1.0,
                                 alpha_max=0.1, visible=True)

    return m.Reliability(header=hdr(src, 0.2 * src, src), nodes=[node(4, 0.5), node(9, 0.95)])


# --- Foxglove conversions (pure) -------------------------------------------------------------


def test_grid_colours_and_geometry():
    g = dec(fox.grid_to_fox(grid_msg()))
    rgba = g.data
    assert len(rgba) == 6 * 4 and g.column_count == 3 and g.row_stride == 12
    assert rgba[0:4] == bytes([128, 128, 128, 255])  # unknown grey
    assert rgba[4:8] == bytes([255, 255, 255, 255])  # free white
    assert rgba[8:12] == bytes([0, 0, 0, 255])  # occupied black
    assert g.pose.position.x == -1.0 and g.pose.position.y == -2.0 and g.frame_id == "map"


def test_graph_waits_for_its_reliability_and_labels_id_p():
    sc = fox.FoxScene(p_reliable=0.9)
    assert sc.convert("topo", topo_msg(3)) != []  # no reliability seen yet: graph alone
    sc.convert("reliability", rel_msg(3))
    assert sc.convert("topo", topo_msg(4)) == []  # waits for reliability 4
    [(topic, upd)] = sc.convert("reliability", rel_msg(4))
    assert topic == "/viz/graph"
    upd = dec(upd)
    ent = upd.entities[0]
    assert sorted(t.text for t in ent.texts) == ["4(0.50)", "9(0.95)"]
    colours = {t.text: (t.color.r, t.color.g) for t in ent.texts}
    assert colours["4(0.50)"][0] > colours["4(0.50)"][1]  # unreliable: red
    assert colours["9(0.95)"][1] > colours["9(0.95)"][0]  # reliable: green
    assert len(ent.spheres) == 3 and len(ent.lines) == 2


def test_scan_tf_trail_and_plan():
    sc = fox.FoxScene(laser_offset=0.15)
    scan = scan_msg(0, 0.2, [1.0] * 180 + [8.0])
    out = sc.convert("scan", scan)
    assert [t for t, _ in out] == ["/tf", "/viz/scan"]  # the static mount once, then the scan
    assert dec(out[0][1]).transforms[0].translation.x == 0.15
    s = dec(out[1][1])
    assert math.isclose(s.end_angle, math.pi / 2) and math.isinf(s.ranges[-1])
    assert [t for t, _ in sc.convert("scan", scan)] == ["/viz/scan"]
    trail = []
    for i in range(11):
        p = pose_msg(i, 0.1 * i, 0.1 * i)
        trail += [u for t, u in sc.convert("truth", p) if t == "/viz/trail"]
    assert len(trail) == 2  # one entity per 0.5 m
    path = path_msg(0, 1.0, [[0, 0], [1, 1]])
    ent = dec(sc.convert("plan", path)[0][1]).entities[0]
    assert len(ent.lines) == 1 and len(ent.spheres) == 1
    stop = path_msg(1, 1.2, [])
    ent = dec(sc.convert("plan", stop)[0][1]).entities[0]
    assert len(ent.lines) == 0 and len(ent.spheres) == 0
    assert sc.convert("cmd_vel", object()) == []  # nothing to draw
    st = sc.convert("explore/status", m.ExploreStatus(header=hdr(0, 1.0), state="done"))
    assert st == [("/status/explore", {"header": {"stamp": {"sec": 1, "nanosec": 0},
                                                  "frame_id": "map", "seq": 0, "src_seq": -1},
                                       "state": "done",
                                       "reason": "", "strategy": "", "target_id": -1,
                                       "target_p": 0.0, "candidates": 0, "end_nodes": 0,
                                       "reliable": 0, "blacklisted": [], "replans": 0})]


# --- the recorder on scripted samples ----------------------------------------------------------


def test_recorder_file_channels_schemas_counts_and_gaps(tmp_path):
    keys = Keys("ns", "r1")
    path = tmp_path / "x.mcap"
    rec = Recorder(path, keys.prefix, metadata={"world": "w"})
    for seq in (0, 1, 2, 4):  # seq 3 lost
        rec.put(keys.topic("map"), m.encode(grid_msg(seq)), 1_000 + seq)
    rec.put(keys.topic("topo"), m.encode(topo_msg(0)), 2_000)
    rec.put(keys.topic("reliability"), m.encode(rel_msg(0)), 2_001)
    rec.put(keys.topic("odom"), b"\x93garbage", 2_002)  # kept raw, counted bad
    rec.put("ns/r1/custom", b"\x01", 2_003)  # not ours: raw channel without schema
    rec.put(keys.topic("plan"), m.encode(path_msg(7, 1.0, [])), 2_004)
    st = rec.close()
    assert st["first_seq"]["ns/r1/plan"] == 7 and st["first_seq"]["ns/r1/map"] == 0
    # (a recorder that joins a running stack: what came before it is not lost)
    assert st["messages"] == 9 and st["gaps"] == 1 and st["gaps_per_key"] == {"ns/r1/map": 1}
    assert st["bad"] == {"ns/r1/odom": 1} and st["errors"] == 0
    su = read_summary(path)
    ch = su["channels"]
    assert ch["ns/r1/map"] == {"encoding": "msgpack", "schema": "topoexplore.OccupancyGrid",
                               "schema_encoding": "jsonschema", "count": 4}
    assert ch["ns/r1/custom"]["schema"] == "" and ch["ns/r1/odom"]["count"] == 1
    assert ch["/viz/map"]["encoding"] == "protobuf" and ch["/viz/map"]["count"] == 4
    assert ch["/viz/graph"]["schema"] == "foxglove.SceneUpdate"
    assert su["metadata"]["topoexplore"] == {"prefix": "ns/r1", "world": "w"}
    # the exact bytes, in log-time order, publish time from header.stamp
    got = list(raw_messages(path, {"ns/r1/map"}))
    assert [b for _, b, _ in got] == [m.encode(grid_msg(s)) for s in (0, 1, 2, 4)]
    assert [t for _, _, t in got] == [1000, 1001, 1002, 1004]
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        pubs = [msg.publish_time for _s, c, msg in make_reader(f).iter_messages(
            topics=["ns/r1/topo"])]
    assert pubs == [0]  # stamp 0.0 s
    schema = json.loads(make_reader(open(path, "rb")).get_summary().schemas[1].data)
    assert "$defs" in schema or "properties" in schema


def test_a_raw_recording_gets_its_foxglove_channels_afterwards(tmp_path, capsys):
    """run --record-raw / record --no-foxglove, then add_foxglove (record --from): the file
    a recorder with Foxglove channels writes, the same raw bytes, times and metadata; the
    pictures use the recording's own parameters (the laser mount of its overrides)."""
    from topoexplore.tools.record import add_foxglove, main_record, recorded_params

    keys = Keys("ns", "r1")
    meta = {"command": "run", "overrides": json.dumps(["laser.offset=0.3"]), "params_toml": ""}
    samples = [(keys.topic("map"), m.encode(grid_msg(s)), 1_000 + s) for s in range(3)]
    samples += [(keys.topic("scan"), m.encode(scan_msg(0, 0.5, [1.0] * 181)), 1_500),
                (keys.topic("plan"), m.encode(path_msg(0, 0.5, [])), 1_600),
                (keys.topic("topo"), m.encode(topo_msg(0)), 2_000)]
    files = {}
    for name, foxglove in (("raw", False), ("live", True)):
        rec = Recorder(tmp_path / f"{name}.mcap", keys.prefix, foxglove=foxglove,
                       laser_offset=0.3, metadata=meta)
        for k, b, t in samples:
            rec.put(k, b, t)
        rec.close()
        files[name] = tmp_path / f"{name}.mcap"
    assert recorded_params(meta).laser.offset == 0.3 and recorded_params({}) is None
    raw = read_summary(files["raw"])
    assert all(c["encoding"] == "msgpack" for c in raw["channels"].values())
    st = add_foxglove(files["raw"], tmp_path / "after.mcap")
    assert st["messages"] == len(samples) and st["errors"] == 0 and st["bad"] == {}
    live, after = read_summary(files["live"]), read_summary(tmp_path / "after.mcap")
    assert after["channels"] == live["channels"] and after["metadata"] == live["metadata"]
    assert list(raw_messages(tmp_path / "after.mcap")) == list(raw_messages(files["live"]))
    from mcap.reader import make_reader

    def fox_data(path):
        with open(path, "rb") as f:
            return [(c.topic, msg.log_time, msg.data) for _s, c, msg in
                    make_reader(f).iter_messages(log_time_order=True)
                    if c.message_encoding != "msgpack"]

    assert fox_data(tmp_path / "after.mcap") == fox_data(files["live"])  # laser at 0.3 m
    # the command line: one line and exit 2 on a bad call, the counts on a good one
    out = tmp_path / "cli.mcap"
    assert main_record(["--from", str(files["raw"]), "--out", str(out)]) == 0
    assert read_summary(out)["channels"] == live["channels"]
    assert "Foxglove messages" in capsys.readouterr().out
    with open(files["raw"], "rb") as f:  # a chunk damaged, the summary intact
        ci = make_reader(f).get_summary().chunk_indexes[0]
    broken = bytearray(files["raw"].read_bytes())
    mid = ci.chunk_start_offset + ci.chunk_length // 2
    broken[mid - 32:mid + 32] = bytes(64)
    (tmp_path / "broken.mcap").write_bytes(bytes(broken))
    for argv in (["--from", str(files["raw"]), "--out", str(files["raw"])],
                 ["--from", str(tmp_path / "broken.mcap"), "--out", str(tmp_path / "b.mcap")],
                 ["--from", str(tmp_path / "none.mcap"), "--out", str(out)],
                 ["--from", str(files["raw"]), "--out", str(out), "--keys", "map"],
                 ["--from", str(tmp_path / "nodir" / "x.mcap"), "--out",
                  str(tmp_path / "nodir" / "y.mcap")]):
        assert main_record(argv) == 2, argv
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert not (tmp_path / "b.mcap").exists()  # nothing half written


def test_header_of_reads_only_the_header():
    raw = m.encode(topo_msg(5))
    assert header_of(raw).seq == 5 and header_of(b"\x01") is None
    assert header_of(msgspec.msgpack.encode({"x": 1})) is None


# --- real processes: run --record, then play -------------------------------------------------


def _mcap_seqs(path: Path) -> dict[str, list[int]]:
    out: dict[str, list[int]] = {}
    for key, data, _t in raw_messages(path):
        h = header_of(data)
        out.setdefault(key, []).append(h.seq if h else -1)
    return out


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    out = tmp_path_factory.mktemp("rec") / "run"
    ns = f"rec{os.getpid()}"
    cmd = [sys.executable, "-m", "topoexplore.tools.cli", "run", "--world", "paper-room",
           "--lockstep", "--quiet", "--record", "--out", str(out), "--connect",
           f"tcp/127.0.0.1:{free_port()}", "--namespace", ns, "--max-sim-time", "300"]
    r = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    return out, ns, json.loads((out / "report.json").read_text())


def test_run_record_loses_no_message(recorded):
    out, ns, report = recorded
    rec = report["recording"]
    su = read_summary(out / "run.mcap")
    prefix = f"{ns}/robot1"
    for topic in ("scan", "odom", "truth", "map", "topo", "reliability", "plan", "cmd_vel",
                  "explore/status", "sim/status"):
        assert su["channels"][f"{prefix}/{topic}"]["count"] > 0, topic
    assert rec["gaps"] == 0 and rec["errors"] == 0 and not rec["bad"]
    assert rec["per_key"] == {k: c["count"] for k, c in su["channels"].items()
                              if c["encoding"] == "msgpack"}
    # every publisher's messages, each exactly once: seq 0..n-1 per key (the publisher counter)
    for key, seqs in _mcap_seqs(out / "run.mcap").items():
        assert seqs == list(range(len(seqs))), key
    scans = su["channels"][f"{prefix}/scan"]["count"]
    assert scans == report["scans"] or scans >= report["scans"]  # the sim may step on after done
    odoms = su["channels"][f"{prefix}/odom"]["count"]
    assert abs(odoms - 4 * scans) <= 4  # 20 Hz odometry, 5 Hz scans
    for topic in fox.TOPICS:
        assert su["channels"][topic]["count"] > 0, topic
    assert su["metadata"]["topoexplore"]["world"] == "paper-room"
    # the Foxglove channels decode with their embedded schemas (as Foxglove reads them)
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    last = {}
    with open(out / "run.mcap", "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _s, ch, _msg, dm in reader.iter_decoded_messages(
                topics=[t for t in fox.TOPICS if t not in fox.JSON_TYPES]):
            last[ch.topic] = dm
        for _s, ch, msg in reader.iter_messages(topics=list(fox.JSON_TYPES)):
            last[ch.topic] = json.loads(msg.data)
    assert last["/status/explore"]["state"] == "done"
    assert last["/status/sim"]["world"] == "paper-room"
    labels = [t.text for t in last["/viz/graph"].entities[0].texts]
    assert labels and all(re.fullmatch(r"\d+\(\d\.\d\d\)", t) for t in labels), labels
    assert last["/viz/map"].column_count > 0 and len(last["/viz/scan"].ranges) == 181


def test_play_publishes_the_recording(recorded, procs, endpoint, namespace):
    out, ns, _report = recorded
    procs.router(endpoint)
    got: list[m.LaserScan] = []
    odoms = threading.Event()
    n_scans = read_summary(out / "run.mcap")["channels"][f"{ns}/robot1/scan"]["count"]
    with Bus.client(endpoint, wait_for_router=True) as bus:
        keys = Keys(namespace, "robot2")
        bus.subscribe(keys.scan, m.LaserScan, lambda msg, k: got.append(msg))
        bus.subscribe(keys.odom, m.Odometry, lambda msg, k: odoms.set())
        time.sleep(0.3)
        t0 = time.monotonic()
        r = subprocess.run([sys.executable, "-m", "topoexplore.tools.cli", "play",
                            str(out / "run.mcap"), "--keys", "scan", "--rate", "1000",
                            "--connect", endpoint, "--namespace", namespace, "--robot", "robot2"],
                           cwd=REPO, capture_output=True, text=True, timeout=120)
        assert r.returncode == 0, r.stderr
        deadline = time.monotonic() + 10
        while len(got) < n_scans and time.monotonic() < deadline:
            time.sleep(0.05)
    assert [s.header.seq for s in got] == list(range(n_scans))
    assert not odoms.is_set()  # --keys scan: nothing else
    assert f"played {n_scans} messages onto {namespace}/robot2" in r.stdout
    assert time.monotonic() - t0 < 60
    # bad input: one line, exit 2
    bad = subprocess.run([sys.executable, "-m", "topoexplore.tools.cli", "play",
                          str(out / "report.json")], cwd=REPO, capture_output=True, text=True)
    assert bad.returncode == 2 and len(bad.stderr.strip().splitlines()) == 1
    bad = subprocess.run([sys.executable, "-m", "topoexplore.tools.cli", "play",
                          str(out / "run.mcap"), "--keys", "nope"], cwd=REPO,
                         capture_output=True, text=True)
    assert bad.returncode == 2 and "unknown topic" in bad.stderr


# --- replay: pure parts, then the recorded run through real services --------------------------


def test_service_io_table_matches_the_services():
    """common.keys.SERVICE_IO (what replay feeds and compares) against each service module."""
    from topoexplore.common.keys import SERVICE_IO

    for svc, (ins, outs) in SERVICE_IO.items():
        path = REPO / ("sim" if svc == "sim" else f"services/{svc}") / "service.py"
        src = path.read_text()
        subs = set(re.findall(r'subscribe\("([a-z_/]+)"', src))
        if "subscribe_odom(" in src:
            subs.add("odom")
        pubs = set(re.findall(r'publisher\("([a-z_/]+)"', src))
        assert subs == set(ins), (svc, subs)
        assert pubs == set(outs), (svc, pubs)


def test_first_difference_and_expectation():
    from topoexplore.tools.replay import Expectation, chain_io, first_difference, parse_through

    assert first_difference({"a": [1, {"b": 2}]}, {"a": [1, {"b": 3}]}) == ("a[1].b", 2, 3)
    assert first_difference({"a": [1]}, {"a": [1, 2]}) == ("a (length)", 1, 2)
    assert first_difference({"a": 1}, {"a": 1, "c": 0}) == ("c", "<missing>", 0)
    assert first_difference({"x": math.nan}, {"x": math.nan}) is None
    ins, outs = chain_io(["topology", "reliability"])
    assert ins == ["map", "odom"] and outs == ["topo", "reliability"]
    with pytest.raises(ValueError, match="unknown service"):
        parse_through("mapper,sim")
    e = Expectation()
    e.got("topo", m.encode(topo_msg(1)))  # the replay may be ahead of the reading
    e.expect("topo", m.encode(topo_msg(1)))
    assert e.compared == 1 and e.divergence is None and e.caught_up()
    e.expect("topo", m.encode(topo_msg(2)))
    assert not e.caught_up() and e.missing() == ("topo", 1, 2)
    other = topo_msg(2)
    other.nodes[1].x = 1.5
    e.got("topo", m.encode(other))
    d = e.divergence
    assert d.scan == 2 and d.index == 1 and d.what == "nodes[1].x: recorded 1.0, replayed 1.5"
    # below: only the outputs of earlier scans are waited for (a pipelined lockstep logs a
    # scan's map before the scan itself at times)
    e3 = Expectation()
    e3.expect("topo", m.encode(topo_msg(5)))
    assert not e3.caught_up() and e3.caught_up(below=5) and not e3.caught_up(below=6)
    # outputs of one scan arrive in any order: the first in the recording's order is reported
    e2 = Expectation()
    e2.expect("topo", m.encode(topo_msg(3)))
    e2.expect("reliability", m.encode(rel_msg(3)))
    e2.got("reliability", m.encode(rel_msg(4)))  # differs, arrives first
    e2.got("topo", m.encode(topo_msg(4)))  # differs too, recorded first
    assert e2.divergence.topic == "topo" and len(e2.divergences) == 2
    # logged in the other order (the recorder hears each service over its own route): the
    # upstream topic of the chain is still the one reported, and an earlier scan before both
    e4 = Expectation(["topo", "reliability"])
    e4.expect("reliability", m.encode(rel_msg(3)))
    e4.expect("topo", m.encode(topo_msg(3)))
    e4.got("reliability", m.encode(rel_msg(4)))
    e4.got("topo", m.encode(topo_msg(4)))
    assert e4.divergence.topic == "topo" and e4.divergence.index == 0
    e4.expect("reliability", m.encode(rel_msg(2)))
    e4.got("reliability", m.encode(rel_msg(5)))
    assert e4.divergence.topic == "reliability" and e4.divergence.scan == 2


def test_a_divergence_reads_on_for_the_rest_of_its_scan():
    """The drive stops at the input after a divergence; outputs of the same scan logged after
    that input (an upstream one, logged late) are still expected, and later scans' are not."""
    import threading

    from topoexplore.tools.replay import Expectation, _expect_rest_of_scan

    e = Expectation(["topo", "reliability"])
    e.expect("reliability", m.encode(rel_msg(3)))
    e.got("reliability", m.encode(rel_msg(4)))
    e.got("topo", m.encode(topo_msg(4)))  # the replayed topology, already in
    log = iter([("p/odom", m.encode(pose_msg(3, 0.6, 0.0)), 0), ("p/topo", m.encode(topo_msg(3)), 1),
                ("p/odom", m.encode(pose_msg(4, 0.8, 0.0)), 2), ("p/topo", m.encode(topo_msg(4)), 3),
                ("p/reliability", m.encode(rel_msg(4)), 4)])
    _expect_rest_of_scan(log, "p", ["topo", "reliability"], e, threading.Condition(),
                         threading.Event(), 30.0)  # caught up at once: no wait
    assert e.divergence.topic == "topo" and e.divergence.scan == 3
    assert len(e.recorded["topo"]) == 1 and len(e.recorded["reliability"]) == 1
    assert next(log)[0] == "p/reliability"  # stopped at the first output of a later scan


def _replay(path: Path, *extra: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "topoexplore.tools.cli", "replay", str(path),
                           *extra], cwd=REPO, capture_output=True, text=True, timeout=600)


def test_replay_reproduces_the_recorded_outputs(recorded):
    out, _ns, _report = recorded
    with ThreadPoolExecutor(3) as pool:  # three processes, each replaying alone: at once
        r, changed, bad = pool.map(lambda extra: _replay(out / "run.mcap", *extra), [
            ("--through", "mapper,topology,reliability,planner"),
            ("--through", "topology,reliability", "--scans", "150",  # keeps the short
             "--set", "topology.spur_length=0.3"),  # leaves the default prunes: a new skeleton
            #   at once (0.7 pruned nothing more in the first 150 scans of some runs)
            ("--through", "planner", "--set", "planner.nope=1")])
    assert r.returncode == 0, r.stdout + r.stderr[-2000:]
    assert "identical" in r.stdout and "map " in r.stdout and "plan " in r.stdout
    # a changed parameter: the first divergence, named by scan, topic and field
    assert changed.returncode == 1, changed.stdout + changed.stderr[-2000:]
    assert re.search(r"FIRST DIVERGENCE at scan \d+, topo message #\d+: .+: recorded",
                     changed.stdout), changed.stdout
    assert bad.returncode == 2 and len(bad.stderr.strip().splitlines()) == 1


def _old_layout_recording(path: Path, keys: Keys) -> None:
    """A recording as one made before the ROS-shaped messages (odometry as x, y, theta and a
    float stamp), with the scans and maps of today."""
    rec = Recorder(path, keys.prefix, foxglove=False)
    for seq in range(3):
        rec.put(keys.topic("odom"), msgspec.msgpack.encode(
            {"seq": seq, "stamp": 0.2 * seq, "x": 0.1 * seq, "y": 0.0, "theta": 0.0}),
            1_000 + 3 * seq)
        rec.put(keys.topic("scan"), m.encode(scan_msg(seq, 0.2 * seq, [1.0] * 5)), 1_001 + 3 * seq)
        rec.put(keys.topic("map"), m.encode(grid_msg(seq)), 1_002 + 3 * seq)
    rec.close()


def test_an_old_wire_layout_is_named_before_anything_is_played(tmp_path):
    from topoexplore.tools.record import layout_error, unreadable_channels

    keys = Keys("ns", "r1")
    path = tmp_path / "old.mcap"
    _old_layout_recording(path, keys)
    every = {keys.topic(t) for t in ("odom", "scan", "map")}
    bad = unreadable_channels(path, every)
    assert list(bad) == [keys.topic("odom")] and "Odometry" in bad[keys.topic("odom")]
    assert unreadable_channels(path, every - {keys.topic("odom")}) == {}
    why = layout_error(path, every, keys.prefix)
    assert "on odom (first" in why and "\n" not in why
    assert layout_error(path, every - {keys.topic("odom")}, keys.prefix) is None
    # play and replay refuse it in one line, exit 2, before they open the bus (no router)
    for cmd in (["play", str(path)], ["replay", str(path), "--through", "mapper"]):
        r = subprocess.run([sys.executable, "-m", "topoexplore.tools.cli", *cmd], cwd=REPO,
                           capture_output=True, text=True, timeout=120)
        err = r.stderr.strip()
        assert r.returncode == 2 and len(err.splitlines()) == 1, (cmd, r.stderr)
        assert "another wire layout" in err and "on odom (first" in err, err
