"""Every service receiving garbage on each key it subscribes keeps running and counts errors."""

from __future__ import annotations

import time

import msgpack
import pytest

from topoexplore.common import convert
from topoexplore.common import messages as m
from topoexplore.common.bus import Bus
from topoexplore.common.domain import Odom, Pose
from topoexplore.common.keys import Keys
from topoexplore.tools.livestate import fetch_state

SUBSCRIBED = {
    "sim": ["cmd_vel"],
    "mapper": ["scan", "odom"],
    "topology": ["map", "odom"],
    "reliability": ["topo", "map", "odom"],
    "planner": ["reliability", "topo", "map", "odom"],
    "controller": ["plan", "scan", "odom", "explore/status"],
    "localizer": ["scan", "odom", "map"],
}

GARBAGE = [
    b"\xc1not msgpack",
    msgpack.packb({"header": {"seq": 1}}),
    msgpack.packb([1, 2, 3]),
    msgpack.packb({"header": {"seq": 0, "stamp": float("nan"), "frame_id": "x", "src_seq": 0}}),
    msgpack.packb({"header": {"seq": 0, "stamp": {"sec": 1, "nanosec": -1}, "frame_id": "x"}}),
]


def wait_up(bus: Bus, keys: Keys, service: str, p) -> None:
    """Until the service's liveliness token is up (its process p still running)."""
    deadline = time.monotonic() + 60
    while keys.alive(service) not in bus.alive(keys.alive_all()):
        assert p.poll() is None, p.stdout.read()
        assert time.monotonic() < deadline, "service did not come up"
        time.sleep(0.05)


@pytest.mark.parametrize("service", list(SUBSCRIBED))
def test_garbage_on_every_key_is_counted_and_survived(procs, endpoint, namespace, service):
    procs.router(endpoint)
    module = "topoexplore.sim.service" if service == "sim" else f"topoexplore.services.{service}.service"
    p = procs.python("-m", module, "--connect", endpoint, "--namespace", namespace)
    keys = Keys(namespace, "robot1")
    with Bus.client(endpoint, wait_for_router=True) as bus:
        wait_up(bus, keys, service, p)
        before = fetch_state(bus, keys, service)
        for topic in SUBSCRIBED[service]:
            pub = bus.publisher(keys.topic(topic), reliable=True)
            for g in GARBAGE:
                pub.put(g)
        expected = len(SUBSCRIBED[service]) * len(GARBAGE)
        deadline = time.monotonic() + 10
        while True:
            state = fetch_state(bus, keys, service)
            if state["bad_messages_total"] >= expected or time.monotonic() > deadline:
                break
            time.sleep(0.1)
        assert state["bad_messages_total"] == expected, state["bad_messages"]
        for topic in SUBSCRIBED[service]:
            assert state["bad_messages"].get(keys.topic(topic)) == len(GARBAGE), state["bad_messages"]
        assert state["last_bad_message"]
        assert state["pid"] == before["pid"] and p.poll() is None  # still the same process
        assert state["callback_errors"] == 0


def test_messages_lost_on_the_way_are_counted_by_seq(procs, endpoint, namespace):
    """A service counts the messages that never reached it (header.seq jumps) per topic and
    reports them in its state; a restarted publisher (seq back to 0) is not a loss."""
    procs.router(endpoint)
    p = procs.python("-m", "topoexplore.services.mapper.service", "--connect", endpoint,
                     "--namespace", namespace)
    keys = Keys(namespace, "robot1")
    with Bus.client(endpoint, wait_for_router=True) as bus:
        wait_up(bus, keys, "mapper", p)
        pub = bus.publisher(keys.topic("odom"), reliable=True)
        for seq in (0, 1, 2, 6, 7, 0, 1):  # 3, 4, 5 lost; then the publisher restarted
            pub.put(convert.odom_to_msg(Odom(Pose(0.0, 0.0, 0.0), 0.0, 0.0),
                                        m.header(seq, 0.1 * seq, "odom", -1)))
        deadline = time.monotonic() + 10
        while True:
            state = fetch_state(bus, keys, "mapper")
            if state["received"].get("odom", 0) >= 7 or time.monotonic() > deadline:
                break
            time.sleep(0.1)
        assert state["lost"] == {"odom": 3} and state["lost_total"] == 3, state
        assert state["publisher_restarts"] == {"odom": 1}
        assert state["bad_messages_total"] == 0 and p.poll() is None


def test_chaos_set_live_drops_inputs_that_then_count_as_lost(procs, endpoint, namespace):
    """runtime.chaos_* set through the params queryable while the service runs (as bench
    faults does): the dropped messages are counted by the chaos and, by seq, as lost."""
    from topoexplore.tools.bench.faults import set_param

    procs.router(endpoint)
    p = procs.python("-m", "topoexplore.services.mapper.service", "--connect", endpoint,
                     "--namespace", namespace)
    keys = Keys(namespace, "robot1")

    def odom(seq: int) -> m.Odometry:
        return convert.odom_to_msg(Odom(Pose(0.0, 0.0, 0.0), 0.0, 0.0),
                                   m.header(seq, 0.1 * seq, "odom", -1))

    def wait_received(n: int) -> dict:
        deadline = time.monotonic() + 10
        while True:
            st = fetch_state(bus, keys, "mapper")
            if st["received"].get("odom", 0) >= n or time.monotonic() > deadline:
                return st
            time.sleep(0.1)

    with Bus.client(endpoint, wait_for_router=True) as bus:
        wait_up(bus, keys, "mapper", p)
        pub = bus.publisher(keys.topic("odom"), reliable=True)
        for seq in (0, 1):
            pub.put(odom(seq))
        wait_received(2)
        assert set_param(bus, keys, "mapper", 'runtime.chaos_topics=["odom"]') is None
        assert set_param(bus, keys, "mapper", "runtime.chaos_drop=1.0") is None
        assert "not a topic" in set_param(bus, keys, "mapper", 'runtime.chaos_topics=["x"]')
        deadline = time.monotonic() + 10  # applied by the worker between two steps
        while fetch_state(bus, keys, "mapper")["params"]["runtime"]["chaos_drop"] != 1.0:
            assert time.monotonic() < deadline
            time.sleep(0.05)
        for seq in (2, 3, 4):
            pub.put(odom(seq))
        deadline = time.monotonic() + 10
        while fetch_state(bus, keys, "mapper").get("chaos", {}).get("dropped") != {"odom": 3}:
            assert time.monotonic() < deadline
            time.sleep(0.05)
        assert set_param(bus, keys, "mapper", "runtime.chaos_topics=[]") is None
        deadline = time.monotonic() + 10
        while fetch_state(bus, keys, "mapper")["params"]["runtime"]["chaos_topics"]:
            assert time.monotonic() < deadline
            time.sleep(0.05)
        pub.put(odom(5))
        st = wait_received(3)
        assert st["received"]["odom"] == 3 and st["lost"] == {"odom": 3}, st
        assert p.poll() is None
