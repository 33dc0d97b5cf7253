"""``topoexplore bench codec``: what each message costs on the wire (no bus).

    topoexplore bench codec [--repeats 2000] [--json]

For the messages the pipeline sends most (odometry, a scan of 181 and of 360 beams, a path
of 200 waypoints, a 605 x 550 map: the large-office grid), the payload size and the time of
each direction of the round trip every hop pays: domain type -> message -> MessagePack
(``convert.*_to_msg`` + ``messages.encode``), and MessagePack -> validated message -> domain
type (``messages.decode`` + ``convert.*_from_msg``). Median of ``--repeats`` calls (a tenth
of them for the map). Figures, not a timed test.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from topoexplore.common import convert
from topoexplore.common import messages as m
from topoexplore.common.domain import GridMap, Odom, Pose, Route, Scan
from topoexplore.common.grid import GridGeometry


def cases() -> dict[str, tuple[Any, Callable, Callable, type]]:
    """name -> (domain object, to_msg, from_msg, message type)."""
    rng = np.random.default_rng(0)
    path = np.cumsum(rng.normal(size=(200, 2)) * 0.1, axis=0)
    grid = rng.choice(np.array([-1, 0, 100], np.int8), size=(550, 605))
    return {
        "odometry": (Odom(Pose(1.0, 2.0, 0.3), 0.2, 0.1), convert.odom_to_msg,
                     convert.odom_from_msg, m.Odometry),
        "scan 181": (Scan(rng.uniform(0.1, 8.0, 181), -math.pi / 2, math.pi / 180, 0.02, 8.0),
                     convert.scan_to_msg, convert.scan_from_msg, m.LaserScan),
        "scan 360": (Scan(rng.uniform(0.1, 12.0, 360), -math.pi, math.pi / 180, 0.05, 12.0),
                     convert.scan_to_msg, convert.scan_from_msg, m.LaserScan),
        "path 200": (Route(path, 1, 3, (1.0, 1.0), "reliability", 0.5), convert.route_to_msg,
                     convert.route_from_msg, m.Path),
        "map 605x550": (GridMap(grid, GridGeometry(0.1, -1.0, -2.0, 605, 550)),
                        convert.grid_to_msg, convert.grid_from_msg, m.OccupancyGrid),
    }


def _median_us(fn: Callable[[], Any], n: int) -> float:
    times = []
    for _ in range(n):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times) * 1e6


def measure(repeats: int) -> list[dict[str, Any]]:
    header = m.header(3, 12.5, "map", 2)
    out = []
    for name, (obj, to_msg, from_msg, msg_type) in cases().items():
        n = max(1, repeats // 10) if name.startswith("map") else repeats
        raw = m.encode(to_msg(obj, header))

        def to_wire(obj=obj, to_msg=to_msg) -> bytes:
            return m.encode(to_msg(obj, header))

        def from_wire(raw=raw, from_msg=from_msg, msg_type=msg_type) -> Any:
            return from_msg(m.decode(raw, msg_type))

        out.append({"message": name, "type": msg_type.__name__, "bytes": len(raw),
                    "to_wire_us": round(_median_us(to_wire, n), 1),
                    "from_wire_us": round(_median_us(from_wire, n), 1)})
    return out


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # one line, exit 2, no usage dump
        print(f"topoexplore bench codec: {message}", file=sys.stderr)
        raise SystemExit(2)


def main(argv: list[str] | None = None) -> int:
    ap = _Parser(prog="topoexplore bench codec", description=__doc__,
                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=2000, help="calls per figure (default 2000)")
    ap.add_argument("--json", action="store_true", help="print the figures as JSON")
    a = ap.parse_args(argv)
    if not 1 <= a.repeats <= 10**7:
        ap.error("--repeats must be in 1..10000000")
    rows = measure(a.repeats)
    if a.json:
        print(json.dumps(rows, indent=1))
        return 0
    print(f"{'message':14s} {'type':14s} {'bytes':>9s} {'to wire':>10s} {'from wire':>10s}")
    for r in rows:
        print(f"{r['message']:14s} {r['type']:14s} {r['bytes']:9d} {r['to_wire_us']:8.1f} us "
              f"{r['from_wire_us']:8.1f} us")
    return 0
