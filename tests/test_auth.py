"""The authenticated, confined deployment (issue 14, item 2): deploy/zenoh/secure-router.json5,
the stack as user "robot", and strangers, on three hosts: the router, the robot's services
and an operator's machine (this test), each in a Linux network namespace of its own joined
by virtual links (veth); where namespaces cannot be made (not root, no ``ip``), the router
gets a loopback address of its own instead.

- the exploration runs through the router (the sim's clock moves, the map grows);
- a client without credentials, or with a wrong password, cannot connect;
- a viewer reads the map and the state, but its cmd_vel and its "done" are dropped;
- a teleop client drives (cmd_vel arrives) but cannot read the map.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass, field

import pytest

from tests.conftest import REPO
from tests.test_supervisor import wait_for
from topoexplore.common import messages as m
from topoexplore.common.bus import CREDENTIALS_ENV, USERS_ENV, Bus, BusError
from topoexplore.common.keys import Keys
from topoexplore.tools.launch.supervisor import free_port, profile_path
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


@dataclass
class Hosts:
    """Where the router and the services run, and the endpoints each side uses."""

    router_prefix: list[str]  # command prefix that runs a program on the router's host
    services_prefix: list[str]
    listen: str  # the router's listen endpoint
    services_connect: str  # the endpoint the robot's services connect to
    client_connect: str  # the endpoint this test (the operator's machine) connects to
    netns: list[str] = field(default_factory=list)

    def close(self) -> None:
        for ns in self.netns:
            subprocess.run(["ip", "netns", "del", ns], capture_output=True, timeout=30)


def _run(*cmd: str) -> None:
    subprocess.run(cmd, check=True, capture_output=True, timeout=30)


def make_hosts(port: int) -> Hosts:
    """Three hosts in network namespaces (router R, services S, this test in the root
    namespace): S -- R over one veth pair, the test -- R over another. Loopback addresses
    where namespaces cannot be made."""
    tag = os.getpid() % 100_000
    net = 16 + tag % 200  # 10.231.<net>.0/24: R-S, 10.232.<net>.0/24: R-test
    r, s_ = f"te{tag}r", f"te{tag}s"
    if os.geteuid() == 0 and shutil.which("ip"):
        hosts = Hosts(["ip", "netns", "exec", r], ["ip", "netns", "exec", s_],
                      f"tcp/0.0.0.0:{port}", f"tcp/10.231.{net}.1:{port}",
                      f"tcp/10.232.{net}.1:{port}", [r, s_])
        try:
            _run("ip", "netns", "add", r)
            _run("ip", "netns", "add", s_)
            _run("ip", "link", "add", f"{r}1", "type", "veth", "peer", "name", f"{s_}1")
            _run("ip", "link", "set", f"{r}1", "netns", r)
            _run("ip", "link", "set", f"{s_}1", "netns", s_)
            _run("ip", "link", "add", f"{r}2", "type", "veth", "peer", "name", f"{r}h")
            _run("ip", "link", "set", f"{r}2", "netns", r)
            _run("ip", "-n", r, "addr", "add", f"10.231.{net}.1/24", "dev", f"{r}1")
            _run("ip", "-n", s_, "addr", "add", f"10.231.{net}.2/24", "dev", f"{s_}1")
            _run("ip", "-n", r, "addr", "add", f"10.232.{net}.1/24", "dev", f"{r}2")
            _run("ip", "addr", "add", f"10.232.{net}.2/24", "dev", f"{r}h")
            for ns, dev in ((r, f"{r}1"), (r, f"{r}2"), (r, "lo"), (s_, f"{s_}1"), (s_, "lo")):
                _run("ip", "-n", ns, "link", "set", dev, "up")
            _run("ip", "link", "set", f"{r}h", "up")
            return hosts
        except (subprocess.SubprocessError, OSError):
            hosts.close()
    ep = f"tcp/127.0.0.2:{port}"  # the router on a loopback address of its own
    return Hosts([], [], ep, ep, ep)


@pytest.fixture
def hosts():
    h = make_hosts(free_port())
    yield h
    h.close()


def test_secure_router_keeps_strangers_out(procs, hosts, tmp_path, namespace, monkeypatch):
    users = tmp_path / "users.txt"
    users.write_text("robot:robot-pw\nviewer:viewer-pw\nteleop:teleop-pw\n")
    users.chmod(0o600)
    robot = _creds(tmp_path, "robot", "robot-pw")
    endpoint = hosts.client_connect
    monkeypatch.setenv(USERS_ENV, str(users))
    procs.start([*hosts.router_prefix, sys.executable, "-u", "-m", "topoexplore.tools.router",
                 "--listen", hosts.listen, "--zenoh-config", str(CONFIG)],
                stdout=(tmp_path / "router.log").open("w"))
    monkeypatch.setenv(CREDENTIALS_ENV, robot)  # the supervisor and its children: "robot"
    keys = Keys(namespace, "robot1")
    assert wait_for(lambda: _port_open(endpoint), 30), (tmp_path / "router.log").read_text()
    profile = tmp_path / "sim-remote-router.toml"  # the sim profile, on a router elsewhere
    profile.write_text(profile_path("sim").read_text().replace("router = true",
                                                                "router = false"))
    up_log = tmp_path / "up.log"
    up = procs.start([*hosts.services_prefix, sys.executable, "-u", "-m",
                      "topoexplore.tools.cli", "up", "--profile", str(profile), "--world",
                      "paper-room", "--connect", hosts.services_connect, "--namespace",
                      namespace], stdout=up_log.open("w"))
    try:
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

            assert wait_for(lambda: mapped() > 20, 120), \
                f"the stack does not run through the router: {up_log.read_text()[-3000:]}"
            assert up.poll() is None

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
                spoof = m.Twist(header=m.header(987654321, 0.0, "base_link", -1),
                                linear=m.Vector3(x=100.0), angular=m.Vector3())
                pub = vw.publisher(keys.cmd_vel, m.Twist, reliable=True)
                done = vw.publisher(keys.topic("explore/status"), m.ExploreStatus,
                                    reliable=True)
                # it sees the subscribers, so its puts go out and the router drops them
                assert wait_for(lambda: pub.matched and done.matched, 5)
                for _ in range(5):
                    pub.put(spoof)
                    done.put(m.ExploreStatus(header=m.header(987654321, 0.0, "map", -1),
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
                    tpub.put(m.Twist(header=m.header(123456789 + i, 0.0, "base_link", -1),
                                     linear=m.Vector3(), angular=m.Vector3()))
                    time.sleep(0.1)
                assert wait_for(lambda: any(m.decode(c, m.Twist).header.seq >= 123456789
                                         for c in list(cmds)), 5), "teleop cannot drive"
                time.sleep(1.0)
                assert odoms and not tmaps
    finally:
        up.terminate()
        up.wait(timeout=30)


def _port_open(endpoint: str) -> bool:
    import socket

    host, port = endpoint.split("/", 1)[1].rsplit(":", 1)
    with socket.socket() as s:
        s.settimeout(0.5)
        return s.connect_ex((host, int(port))) == 0
