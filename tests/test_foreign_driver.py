"""Issue 16's foreign-driver test: the stack's `robot` profile (no simulator) against drivers
that share none of its code (tests/foreign_driver.py: zenoh and msgpack only, the messages
written from the ROS definitions as plain dicts): a 360 deg lidar with its own beam count,
+Inf for no return and NaN readings, odometry at 50 Hz without our seq/src_seq. The stack
explores the flat to the end, without a collision, and maps it.

With drift, the localizer runs (localizer.enabled) and the map must still hold together.
"""

from __future__ import annotations

import json
import math
import signal
import sys

import numpy as np
import pytest

from tests.conftest import REPO
from tests.test_supervisor import wait_for
from topoexplore.common import messages as m
from topoexplore.common.bus import Bus
from topoexplore.common.keys import Keys
from topoexplore.tools.livestate import StateError, fetch_state

# the driver's lidar, told to the stack the way a robot owner would: [laser]
LASER = ["laser.beams=400", f"laser.fov={2 * math.pi!r}", "laser.range_min=0.1",
         "laser.range_max=10.0", "laser.scan_hz=10.0", "robot.v_limit=0.5"]


@pytest.mark.parametrize("drift", [0.0, 0.03])
def test_the_robot_profile_explores_with_foreign_drivers(procs, endpoint, namespace, tmp_path,
                                                         drift):
    """Without drift, and with odometry drifting 0.03 per metre and radian, the localizer on."""
    keys = Keys(namespace, "robot1")
    up_log = tmp_path / "up.log"
    sets = [*LASER, *(["localizer.enabled=true"] if drift else [])]
    up = procs.python("-m", "topoexplore.tools.cli", "up", "--profile", "robot", "--connect",
                      endpoint, "--namespace", namespace,
                      *(a for kv in sets for a in ("--set", kv)), stdout=up_log.open("w"))
    statuses: list[str] = []
    with Bus.client(endpoint, wait_for_router=True) as bus:
        bus.subscribe(keys.topic("explore/status"), m.ExploreStatus,
                      lambda msg, k: statuses.append(msg.state))
        want = {keys.alive(s) for s in ("mapper", "topology", "reliability", "planner",
                                        "controller")}
        assert wait_for(lambda: want <= set(bus.alive(keys.alive_all())), 120), \
            up_log.read_text()[-3000:]
        driver = procs.python(str(REPO / "tests" / "foreign_driver.py"), "--connect", endpoint,
                              "--prefix", keys.prefix, "--speed", "3", "--drift", str(drift))
        done = wait_for(lambda: "done" in statuses or driver.poll() is not None, 400)
        try:
            mapper = fetch_state(bus, keys, "mapper")
        except StateError:
            mapper = {}
        driver.send_signal(signal.SIGTERM)
        out, _ = driver.communicate(timeout=30)
    up.send_signal(signal.SIGTERM)
    assert up.wait(timeout=30) == 0
    assert done and "done" in statuses, (statuses[-5:], up_log.read_text()[-3000:], out)
    stats = json.loads(out.strip().splitlines()[-1])
    assert stats["collisions"] == 0 and stats["stale_cmds"] == 0, stats
    assert stats["path_m"] > 1.0, stats  # it drove (a 360 deg lidar sees most from the door)
    # the map: most of the flat's 70 m^2 known, and no scan was skipped for its shape
    grid = mapper["map"]
    known = (np.frombuffer(grid["data"], np.int8) >= 0).sum() * grid["info"]["resolution"] ** 2
    assert known >= 0.9 * 70.0, known
    assert not mapper["skipped_scans"], mapper["skipped_scans"]
    assert mapper["bad_messages_total"] == 0, mapper["last_bad_message"]
    assert "[laser] says" not in up_log.read_text()  # the stack was told the lidar it has
    print(stats, f"known {known:.1f} m^2", file=sys.stderr)
