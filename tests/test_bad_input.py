"""Every service receiving garbage on each key it subscribes keeps running and counts errors."""

from __future__ import annotations

import time

import msgpack
import pytest

from topoexplore.common.bus import Bus
from topoexplore.common.keys import Keys
from topoexplore.tools.livestate import fetch_state

SUBSCRIBED = {
    "sim": ["cmd_vel"],
    "mapper": ["scan", "odom"],
    "topology": ["map", "odom"],
    "reliability": ["topo", "map", "odom"],
    "planner": ["reliability", "topo", "map", "odom"],
    "controller": ["plan", "scan", "odom", "explore/status"],
}

GARBAGE = [
    b"\xc1not msgpack",
    msgpack.packb({"header": {"seq": 1}}),
    msgpack.packb([1, 2, 3]),
    msgpack.packb({"header": {"seq": 0, "stamp": float("nan"), "frame": "x", "src_seq": 0}}),
]


@pytest.mark.parametrize("service", list(SUBSCRIBED))
def test_garbage_on_every_key_is_counted_and_survived(procs, endpoint, namespace, service):
    procs.router(endpoint)
    module = "topoexplore.sim.service" if service == "sim" else f"topoexplore.services.{service}.service"
    p = procs.python("-m", module, "--connect", endpoint, "--namespace", namespace)
    keys = Keys(namespace, "robot1")
    with Bus.client(endpoint, wait_for_router=True) as bus:
        deadline = time.monotonic() + 60
        while keys.alive(service) not in bus.alive(keys.alive_all()):
            assert p.poll() is None, p.stdout.read()
            assert time.monotonic() < deadline, "service did not come up"
            time.sleep(0.05)
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
