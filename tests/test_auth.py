"""The authenticated, confined deployment (issue 14, item 2): deploy/zenoh/secure-router.json5
on a loopback address of its own, the stack as user "robot", and strangers.

- the exploration runs through the router (the sim's clock moves, the map grows);
- a client without credentials, or with a wrong password, cannot connect;
- a viewer reads the map and the state, but its cmd_vel and its "done" are dropped;
- a teleop client drives (cmd_vel arrives) but cannot read the map.
"""

from __future__ import annotations

import dataclasses
import time

import pytest

from tests.conftest import REPO
from tests.test_supervisor import wait_for
from topoexplore.common import messages as m
from topoexplore.common.bus import CREDENTIALS_ENV, USERS_ENV, Bus, BusError
from topoexplore.common.keys import Keys
from topoexplore.tools.launch.core import load_profile
from topoexplore.tools.launch.supervisor import Supervisor, free_port, profile_path
from topoexplore.tools.livestate import StateError, fetch_state

CONFIG = REPO / "deploy" / "zenoh" / "secure-router.json5"


def _creds(tmp_path, user: str, password: str) -> str:
    p = tmp_path / f"{user}.cred"
    p.write_text(f"{user}:{password}\n")
    p.chmod(0o600)
    return str(p)


def _client(monkeypatch, endpoint: str, cred: str | None) -> Bus:
    if cred is None:
        monkeypatch.delenv(CREDENTIALS_ENV, raising=False)
    else:
        monkeypatch.setenv(CREDENTIALS_ENV, cred)
    return Bus.client(endpoint, name="auth-test")


def test_secure_router_keeps_strangers_out(procs, tmp_path, namespace, monkeypatch):
    users = tmp_path / "users.txt"
    users.write_text("robot:robot-pw\nviewer:viewer-pw\nteleop:teleop-pw\n")
    users.chmod(0o600)
    robot = _creds(tmp_path, "robot", "robot-pw")
    endpoint = f"tcp/127.0.0.2:{free_port()}"  # the router on a loopback address of its own
    monkeypatch.setenv(USERS_ENV, str(users))
    procs.python("-m", "topoexplore.tools.router", "--listen", endpoint, "--zenoh-config",
                 str(CONFIG))
    monkeypatch.setenv(CREDENTIALS_ENV, robot)  # the supervisor and its children: "robot"
    keys = Keys(namespace, "robot1")
    wait_for(lambda: _port_open(endpoint), 30)
    profile = dataclasses.replace(load_profile(profile_path("sim")), router=False)
    sup = Supervisor(profile, keys, endpoint, overrides=['sim.world="paper-room"'])
    try:
        assert sup.start(ready_timeout=120)
        with _client(monkeypatch, endpoint, robot) as rb:
            cmds: list[bytes] = []
            statuses: list[str] = []
            rb.subscribe_raw(keys.cmd_vel, lambda k, payload, e: cmds.append(payload))
            rb.subscribe(keys.topic("explore/status"), m.ExploreStatus,
                         lambda msg, k: statuses.append(msg.state))

            def mapped() -> int:
                try:
                    st = fetch_state(rb, keys, "mapper", timeout=1.0)
                except StateError:
                    return 0
                return st["processed"]

            assert wait_for(lambda: mapped() > 20, 60), "the stack does not run through the router"

            # strangers: no credentials, a wrong password
            for cred in (None, _creds(tmp_path, "viewer", "not-the-password")):
                with pytest.raises(BusError):
                    _client(monkeypatch, endpoint, cred).close()

            # a viewer reads, and nothing it puts gets through
            with _client(monkeypatch, endpoint, _creds(tmp_path, "viewer", "viewer-pw")) as vw:
                maps: list[int] = []
                vw.subscribe(keys.topic("map"), m.OccupancyGrid,
                             lambda msg, k: maps.append(msg.header.seq))
                assert wait_for(lambda: bool(maps), 10), "the viewer cannot read the map"
                assert fetch_state(vw, keys, "sim", timeout=2.0)["service"] == "sim"
                spoof = m.Twist(header=m.Header(seq=987654321, stamp=0.0, frame="base_link",
                                                src_seq=-1), v=100.0, w=0.0)
                pub = vw.publisher(keys.cmd_vel, m.Twist, reliable=True)
                done = vw.publisher(keys.topic("explore/status"), m.ExploreStatus,
                                    reliable=True)
                # it sees the subscribers, so its puts go out and the router drops them
                assert wait_for(lambda: pub.matched and done.matched, 5)
                for _ in range(5):
                    pub.put(spoof)
                    done.put(m.ExploreStatus(header=m.Header(seq=987654321, stamp=0.0,
                                                             frame="map", src_seq=-1),
                                             state="done", reason="spoofed"))
                    time.sleep(0.1)
                time.sleep(1.0)
                assert not any(c for c in cmds if m.decode(c, m.Twist).header.seq == 987654321)
                assert "done" not in statuses

            # teleop drives, and reads nothing but odometry
            with _client(monkeypatch, endpoint, _creds(tmp_path, "teleop", "teleop-pw")) as tp:
                tmaps: list[int] = []
                tp.subscribe(keys.topic("map"), m.OccupancyGrid,
                             lambda msg, k: tmaps.append(1))
                odoms: list[int] = []
                tp.subscribe(keys.topic("odom"), m.Odometry, lambda msg, k: odoms.append(1))
                tpub = tp.publisher(keys.cmd_vel, m.Twist, reliable=True)
                time.sleep(0.5)
                for i in range(5):
                    tpub.put(m.Twist(header=m.Header(seq=123456789 + i, stamp=0.0,
                                                     frame="base_link", src_seq=-1),
                                     v=0.0, w=0.0))
                    time.sleep(0.1)
                assert wait_for(lambda: any(m.decode(c, m.Twist).header.seq >= 123456789
                                         for c in list(cmds)), 5), "teleop cannot drive"
                time.sleep(1.0)
                assert odoms and not tmaps
    finally:
        sup.stop()


def _port_open(endpoint: str) -> bool:
    import socket

    host, port = endpoint.split("/", 1)[1].rsplit(":", 1)
    with socket.socket() as s:
        s.settimeout(0.5)
        return s.connect_ex((host, int(port))) == 0
