"""Driving by hand and live parameters (issue 13 items 4 and 5): the pure parts, then
`keys pub` driving the simulated robot, `keys set` on live services, teleop under a
pseudo-terminal."""

from __future__ import annotations

import os
import pty
import subprocess
import sys
import threading
import time

import pytest

from tests.conftest import REPO
from topoexplore.common import messages as m
from topoexplore.common.bus import Bus
from topoexplore.common.keys import Keys
from topoexplore.tools.keypub import PubError, build_message, parse_assignments
from topoexplore.tools.teleop import Teleop


def test_assignments_and_messages():
    assert parse_assignments(["v=0.2", "header.stamp=3", "blacklisted=[1, 2]"]) == {
        "v": 0.2, "header": {"stamp": 3}, "blacklisted": [1, 2]}
    tw = build_message(m.Twist, {"w": 0.5}, seq=7, frame="base_link", stamp=2.25)
    assert (tw.linear.x, tw.angular.z, tw.header.seq, tw.header.frame_id) == (
        0.0, 0.5, 7, "base_link")  # v=, w=: a planar base's linear.x, angular.z
    assert (tw.header.stamp.sec, tw.header.stamp.nanosec, tw.header.src_seq) == (2, 250000000, -1)
    tw = build_message(m.Twist, parse_assignments(["linear.x=0.2", "angular.z=-1",
                                                   "header.stamp=12.5"]), 1)
    assert (tw.linear.x, tw.angular.z, tw.header.time) == (0.2, -1.0, 12.5)
    for given, t in ((["header.stamp=1e6"], 1e6), (["header.stamp.sec=4"], 4.0),
                     (["header.stamp.sec=4", "header.stamp.nanosec=5"], 4.000000005),
                     (["header.stamp={sec: 1, nanosec: 2}"], 1.000000002)):
        assert build_message(m.Twist, parse_assignments(given), 1, stamp=9.0).header.time == t
    odom = build_message(m.Odometry, parse_assignments(["pose.pose.position.x=1.5"]), 1, "odom")
    assert odom.pose.pose.position.x == 1.5 and odom.pose.pose.orientation.w == 1.0
    assert odom.child_frame_id == "base_link" and len(odom.pose.covariance) == 36
    path = build_message(m.Path, parse_assignments(
        ["poses=[{pose: {position: {x: 1, y: 2}}}, {pose: {position: {x: 3}}}]",
         "target_id=3"]), 1)  # list items are filled in too (identity orientation)
    assert [(p.pose.position.x, p.pose.position.y, p.pose.orientation.w)
            for p in path.poses] == [(1.0, 2.0, 1.0), (3.0, 0.0, 1.0)] and path.target_id == 3
    for bad, why in ((["v"], "FIELD=VALUE"), (["x=1"], "no field 'x'"),
                     (["v=abc"], "Expected `float`"), (["v=.nan"], "finite"),
                     (["header=1", "header.seq=2"], "at once"),
                     (["v=1", "linear.x=1"], "same field"),
                     (["header.frame=base_link"], "no field 'header.frame'"),
                     (["header.stamp=-1"], "seconds >= 0"), (["header.stamp=abc"], "seconds"),
                     (["header.stamp.nanosec=1e9"], "not a time"),
                     (["header.stamp.usec=1"], "no field 'header.stamp.usec'")):
        with pytest.raises(PubError, match=why):
            build_message(m.Twist, parse_assignments(bad), 1)
    with pytest.raises(PubError, match="no field 'poses.0.pose.positon'"):
        build_message(m.Path, parse_assignments(["poses=[{pose: {positon: {x: 1}}}]"]), 1)


def test_teleop_keys_clamp_and_silence_stops():
    t = Teleop(v_step=0.05, w_step=0.2, v_max=0.2, w_max=1.0, hold=1.0)
    for i in range(10):
        t.key("w", 0.1 * i)
    assert t.command(1.0) == (0.2, 0.0)  # clamped to v_max
    t.key("a", 1.0)
    assert t.command(1.5) == (0.2, 0.2)
    assert t.command(2.6) == (0.0, 0.0)  # 1.6 s without a key: stopped, and reset
    t.key("w", 3.0)
    assert t.command(3.0) == (0.05, 0.0)
    t.key(" ", 3.1)
    assert t.command(3.1) == (0.0, 0.0)
    t.key("q", 3.2)
    assert t.quit and t.command(3.2) == (0.0, 0.0)


def _cli(*args: str, timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "topoexplore.tools.cli", *args], cwd=REPO,
                          capture_output=True, text=True, timeout=timeout)


def _wait_alive(endpoint: str, keys: Keys, services: tuple[str, ...]) -> None:
    with Bus.client(endpoint, wait_for_router=True) as bus:
        deadline = time.monotonic() + 60
        while not all(keys.alive(s) in bus.alive(keys.alive_all()) for s in services):
            assert time.monotonic() < deadline, f"{services} not up"
            time.sleep(0.1)


def _truth_x(endpoint: str, keys: Keys) -> float:
    got: list[float] = []
    with Bus.client(endpoint, wait_for_router=True) as bus:
        bus.subscribe(keys.truth, m.PoseStamped,
                      lambda msg, k: got.append(msg.pose.position.x))
        deadline = time.monotonic() + 10
        while not got and time.monotonic() < deadline:
            time.sleep(0.05)
    assert got
    return got[-1]


def test_keys_pub_drives_and_keys_set_changes_live(procs, endpoint, namespace):
    keys = Keys(namespace, "robot1")
    bus_args = ["--connect", endpoint, "--namespace", namespace]
    procs.python("-m", "topoexplore.tools.cli", "up", "--profile", "sim-only", *bus_args)
    _wait_alive(endpoint, keys, ("sim",))
    x0 = _truth_x(endpoint, keys)
    r = _cli("keys", "pub", "cmd_vel", "v=0.2", "--rate", "10", "--duration", "1.5", *bus_args)
    assert r.returncode == 0 and "published 15 Twist" in r.stdout, r.stdout + r.stderr
    time.sleep(0.7)  # the sim's watchdog stops the robot 0.5 s after the last command
    x1 = _truth_x(endpoint, keys)
    assert 0.2 < x1 - x0 < 0.6  # stamped with the robot's clock (its odometry), so applied
    # issue 14: a command stamped long ago (a replay) or ahead of the sim clock is dropped
    for stamp in ("header.stamp=0", "header.stamp.sec=1000000"):
        r = _cli("keys", "pub", "cmd_vel", "linear.x=0.2", stamp, "--rate", "10",
                 "--duration", "1", *bus_args)
        assert r.returncode == 0, r.stderr
    time.sleep(0.3)
    x2 = _truth_x(endpoint, keys)
    assert abs(x2 - x1) < 0.02, (x1, x2)
    r = _cli("keys", "get", "sim", "--field", "stale_cmds", *bus_args)
    assert r.returncode == 0 and int(r.stdout) >= 18, r.stdout + r.stderr
    # (the controller publishes cmd_vel too: it starts only now)
    procs.python("-m", "topoexplore.services.controller.service", *bus_args)
    _wait_alive(endpoint, keys, ("controller",))
    # live parameters: the list, a change (old and new), a refusal, a bad value
    r = _cli("keys", "set", "controller", *bus_args)
    assert r.returncode == 0 and "controller.v_max" in r.stdout, r.stderr
    r = _cli("keys", "set", "controller", "controller.v_max=0.3", *bus_args)
    assert r.returncode == 0 and "controller.v_max: 0.2 -> 0.3" in r.stdout, r.stderr
    deadline = time.monotonic() + 10
    while True:  # applied by the worker between two steps
        g = _cli("keys", "get", "controller", "--field", "params.controller.v_max", *bus_args)
        if g.stdout.strip() == "0.3" or time.monotonic() > deadline:
            break
        time.sleep(0.2)
    assert g.stdout.strip() == "0.3", g.stdout + g.stderr
    for bad, why in (("controller.start_turn=1", "cannot change while controller runs"),
                     ("controller.v_max=-1", "bad parameter"),
                     ("controller.nope=1", "unknown field")):
        r = _cli("keys", "set", "controller", bad, *bus_args)
        assert r.returncode == 1 and why in r.stderr, (bad, r.stderr)
        assert len(r.stderr.strip().splitlines()) == 1
    r = _cli("keys", "set", "sim", "sim.speed=2", *bus_args)
    assert r.returncode == 0 and "sim.speed: 1.0 -> 2.0" in r.stdout, r.stderr
    r = _cli("keys", "pub", "cmd_vel", "x=1", *bus_args)
    assert r.returncode == 2 and "no field 'x'" in r.stderr


def test_teleop_under_a_pty(procs, endpoint, namespace):
    keys = Keys(namespace, "robot1")
    procs.router(endpoint)
    cmds: list[tuple[float, float]] = []
    with Bus.client(endpoint, wait_for_router=True) as bus:
        bus.subscribe(keys.cmd_vel, m.Twist,
                      lambda msg, k: cmds.append((msg.linear.x, msg.angular.z)))
        master, slave = pty.openpty()
        p = subprocess.Popen([sys.executable, "-m", "topoexplore.tools.cli", "teleop",
                              "--connect", endpoint, "--namespace", namespace, "--hold", "0.5"],
                             stdin=slave, stdout=slave, stderr=slave, cwd=REPO,
                             start_new_session=True)
        os.close(slave)
        out = bytearray()

        def read() -> None:
            while True:
                try:
                    data = os.read(master, 1024)
                except OSError:
                    return
                if not data:
                    return
                out.extend(data)

        threading.Thread(target=read, daemon=True).start()
        deadline = time.monotonic() + 30
        while b"teleop on" not in out and time.monotonic() < deadline:
            time.sleep(0.05)
        for _ in range(3):
            os.write(master, b"w")
            time.sleep(0.05)
        os.write(master, b"a")
        deadline = time.monotonic() + 5
        while (0.15, 0.2) not in [(round(v, 2), round(w, 2)) for v, w in cmds] \
                and time.monotonic() < deadline:
            time.sleep(0.05)
        assert (0.15, 0.2) in [(round(v, 2), round(w, 2)) for v, w in cmds], cmds[-5:]
        time.sleep(1.0)  # silence: stopped
        assert cmds[-1] == (0.0, 0.0)
        os.write(master, b"w")
        time.sleep(0.3)
        os.write(master, b"q")
        assert p.wait(timeout=10) == 0
        time.sleep(0.3)
        os.close(master)
    assert cmds[-3:] == [(0.0, 0.0)] * 3  # safe on exit
    assert b"stopped the robot" in out
    r = subprocess.run([sys.executable, "-m", "topoexplore.tools.cli", "teleop"], cwd=REPO,
                       stdin=subprocess.DEVNULL, capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "needs a terminal" in r.stderr
