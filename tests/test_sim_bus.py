"""Two processes: the simulator as a real process; the test answers scans with cmd_vel over
the bus (lockstep) and reads scan/odom back."""

from __future__ import annotations

import math
import threading

from topoexplore.common import convert
from topoexplore.common import messages as m
from topoexplore.common.bus import Bus
from topoexplore.common.domain import Command
from topoexplore.common.keys import Keys


def test_sim_process_driven_over_the_bus(procs, endpoint, namespace):
    procs.router(endpoint)
    sim = procs.python("-m", "topoexplore.sim.service", "--connect", endpoint, "--namespace", namespace,
                       "--set", "runtime.lockstep=true", "--set", "runtime.lockstep_wait_for=[]",
                       "--set", 'sim.world="dead-end"', "--set", "sim.range_noise=0.0")
    keys = Keys(namespace, "robot1")
    scans: list[m.LaserScan] = []
    odoms: list[m.Odometry] = []
    done = threading.Event()
    with Bus.client(endpoint, wait_for_router=True) as bus:
        pub = bus.publisher(keys.cmd_vel, m.Twist, reliable=True)

        def on_scan(msg: m.LaserScan, key: str) -> None:
            scans.append(msg)
            if len(scans) >= 26:
                done.set()
                return
            pub.put(convert.command_to_msg(Command(0.2, 0.0), m.header(
                len(scans), msg.header.time, "base_link", msg.header.src_seq)))

        bus.subscribe(keys.odom, m.Odometry, lambda msg, k: odoms.append(msg))
        bus.subscribe(keys.scan, m.LaserScan, on_scan)
        assert done.wait(60), f"only {len(scans)} scans; sim output: {sim.poll()}"
    assert len(scans[0].ranges) == 181
    assert math.isclose(scans[0].angle_min, -math.pi / 2, abs_tol=1e-9)
    assert [s.header.src_seq for s in scans[:26]] == list(range(26))
    # 25 scan periods at 5 Hz = 5 s at 0.2 m/s -> about 1 m along the heading
    first = next(o for o in odoms if o.header.time == scans[0].header.time)
    last = next(o for o in odoms if o.header.time == scans[25].header.time)
    a, b = first.pose.pose.position, last.pose.pose.position
    dist = math.hypot(b.x - a.x, b.y - a.y)
    assert 0.9 < dist < 1.05, dist
    assert scans[25].header.time > scans[0].header.time
    # odometry at sim.odom_hz (20 Hz) exactly, whatever physics_hz (50 Hz: not a multiple), and
    # no extra message at a scan when an odometry tick falls on it (issue 13 item 6: 30 Hz seen)
    span = [o for o in odoms if scans[0].header.time < o.header.time <= scans[25].header.time]
    assert len(span) == 100, len(span)  # 5 s x 20 Hz
    stamps = [o.header.time for o in odoms]
    assert len(stamps) == len(set(stamps))
