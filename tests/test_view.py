"""`topoexplore view` (issue 13 item 3): a real view process on a real bus, a WebSocket client
speaking Foxglove's protocol receives every advertised channel and messages on each."""

from __future__ import annotations

import json
import struct
import sys
import threading
import time

import pytest

from tests.test_record import grid_msg, hdr, path_msg, pose_msg, rel_msg, scan_msg, topo_msg
from topoexplore.common import convert
from topoexplore.common import messages as m
from topoexplore.common.bus import Bus
from topoexplore.common.domain import Odom, Pose
from topoexplore.common.keys import Keys
from topoexplore.tools import fox

pytest.importorskip("foxglove")
pytest.importorskip("websockets")


def _publish_forever(endpoint: str, keys: Keys, stop: threading.Event) -> None:
    with Bus.client(endpoint, wait_for_router=True) as bus:
        pub = {t: bus.publisher(keys.topic(t)) for t in
               ("scan", "odom", "truth", "map", "topo", "reliability", "plan", "explore/status",
                "sim/status")}
        k = 0
        while not stop.is_set():
            k += 1
            t = 0.2 * k
            pub["scan"].put(scan_msg(k, t, [1.0] * 181))
            pub["odom"].put(convert.odom_to_msg(Odom(Pose(0.1 * k, 0.0, 0.0), 0.0, 0.0),
                                                hdr(k, t, k, "odom")))
            pub["truth"].put(pose_msg(k, t, 0.1 * k))
            pub["map"].put(grid_msg(k))
            pub["topo"].put(topo_msg(k))
            pub["reliability"].put(rel_msg(k))
            pub["plan"].put(path_msg(k, t, [[0, 0], [1, 1]]))
            pub["explore/status"].put(m.ExploreStatus(header=hdr(k, t, k), state="exploring"))
            pub["sim/status"].put(m.SimStatus(header=hdr(k, t, k), world="w", mode="lockstep",
                                              sim_time=t, steps=k, collisions=0,
                                              path_length=0.1 * k, real_time_factor=1.0))
            time.sleep(0.1)


def test_view_serves_every_channel(procs, endpoint, namespace):
    from websockets.sync.client import connect

    procs.router(endpoint)
    view = procs.python("-m", "topoexplore.tools.cli", "view", "--port", "0", "--connect",
                        endpoint, "--namespace", namespace, "--duration", "30")
    line = view.stdout.readline()
    assert "ws://127.0.0.1:" in line, line
    port = int(line.split("ws://127.0.0.1:")[1].split()[0])
    stop = threading.Event()
    pub = threading.Thread(target=_publish_forever, args=(endpoint, Keys(namespace, "robot1"),
                                                         stop), daemon=True)
    pub.start()
    got: dict[str, int] = {}
    topics: dict[int, str] = {}
    errors: list[str] = []
    try:
        with connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1"],
                     open_timeout=10) as ws:
            deadline = time.monotonic() + 20
            while len(got) < len(fox.TOPICS) and time.monotonic() < deadline:
                try:
                    msg = ws.recv(timeout=1.0)
                except TimeoutError:
                    continue
                if isinstance(msg, str):
                    d = json.loads(msg)
                    if d.get("op") == "advertise":
                        new = [c for c in d["channels"] if c["id"] not in topics]
                        topics.update({c["id"]: c["topic"] for c in new})
                        ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                            {"id": c["id"], "channelId": c["id"]} for c in new]}))
                    elif d.get("op") == "status" and d.get("level", 0) >= 1:
                        errors.append(d.get("message", ""))  # e.g. "Unknown channel ID: 4"
                elif msg[0] == 1:  # message data: opcode, subscription id, log time, payload
                    sid = struct.unpack_from("<I", msg, 1)[0]
                    got[topics[sid]] = got.get(topics[sid], 0) + 1
    finally:
        stop.set()
        pub.join(timeout=10)
    assert not errors, errors
    assert set(topics.values()) == set(fox.TOPICS)
    assert set(got) == set(fox.TOPICS), got


def test_view_bad_input_and_layout(tmp_path):
    import subprocess

    from tests.conftest import REPO

    def view(*a: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "topoexplore.tools.cli", "view", *a],
                              cwd=REPO, capture_output=True, text=True, timeout=60)

    r = view("--port", "70000")
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1
    r = view("--write-layout", str(tmp_path / "layout.json"))
    assert r.returncode == 0, r.stderr
    layout = json.loads((tmp_path / "layout.json").read_text())
    shipped = json.loads((REPO / "docs" / "foxglove-layout.json").read_text())
    assert layout == shipped  # docs/foxglove-layout.json is what the code writes
    text = json.dumps(layout)
    assert all(t in text for t in ("/viz/map", "/viz/graph", "/status/explore"))
