"""``topoexplore bridge ros2``: a robot that runs ROS 2 drives the stack, with no ROS installed
here.

    topoexplore bridge ros2 [--flavor ros2dds|rmw_zenoh] [--ros-prefix NS] [--domain 0]
                            [--scan scan] [--odom odom] [--cmd-vel cmd_vel] [--map map]
                            [--connect ...] [--namespace ...] [--robot ...]

The robot's ROS 2 side publishes ``sensor_msgs/LaserScan`` and ``nav_msgs/Odometry`` as CDR
on its own Zenoh keys: through zenoh-bridge-ros2dds (``--flavor ros2dds``, the default; keys
are the topic names) or natively with rmw_zenoh (``--flavor rmw_zenoh``; keys
``<domain>/<topic>/<type>/<hash>``). The bridge republishes them as ours (``scan``, ``odom``
under ``<namespace>/<robot>/``) and sends our ``cmd_vel`` (``geometry_msgs/Twist``) and
``map`` (``nav_msgs/OccupancyGrid``) back as CDR. Key mapping and field mapping:
:mod:`topoexplore.tools.ros2` and the README. A payload that is not the message it should be
is counted and logged once per kind of error; the bridge goes on. SIGINT / SIGTERM stop it,
with one line of counts.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import threading
import time
from collections import Counter
from typing import Any

from topoexplore.common import messages as m
from topoexplore.common.bus import Bus, BusError, check_config_file, init_logging
from topoexplore.common.keys import DEFAULT_ENDPOINT, DEFAULT_NAMESPACE, DEFAULT_ROBOT, Keys
from topoexplore.common.node import LOG_DATEFMT, LOG_FORMAT, add_bus_args, stop_on_signals
from topoexplore.tools import ros2
from topoexplore.tools.extras import ExtraMissing

log = logging.getLogger("topoexplore.bridge")
CDR = "application/cdr"


class Ros2Bridge:
    """Our keys <-> a ROS 2 robot's (one flavor of keys, see :class:`ros2.RosKeys`)."""

    def __init__(self, bus: Bus, keys: Keys, ros: ros2.RosKeys, topics: dict[str, str]):
        self.bus, self.keys, self.ros = bus, keys, ros
        self.counts: Counter[str] = Counter()
        self._lock = threading.Lock()
        self._seq: Counter[str] = Counter()
        self._gid = os.urandom(16)  # rmw_zenoh: this publisher's identity
        self.scan = bus.publisher(keys.topic("scan"), m.LaserScan)
        self.odom = bus.publisher(keys.topic("odom"), m.Odometry)
        bus.subscribe_raw(ros.sub(topics["scan"]), self._inbound("scan", ros2.scan_from_cdr,
                                                                   self.scan))
        bus.subscribe_raw(ros.sub(topics["odom"]), self._inbound("odom", ros2.odom_from_cdr,
                                                                   self.odom))
        self.out: dict[str, Any] = {}
        for ours, typename, to_cdr in (("cmd_vel", ros2.TWIST, ros2.twist_to_cdr),
                                       ("map", ros2.GRID, ros2.grid_to_cdr)):
            if not topics.get(ours):
                continue
            pub = bus.publisher(ros.pub(topics[ours], typename), encoding=CDR)
            bus.subscribe(keys.topic(ours), _TYPES[ours], self._outbound(ours, to_cdr, pub))

    def _next(self, name: str) -> int:
        with self._lock:
            k = self._seq[name]
            self._seq[name] += 1
            return k

    def _inbound(self, name: str, from_cdr, pub):
        def on(key: str, payload: bytes, _enc: str) -> None:
            try:
                msg = from_cdr(payload, self._seq[name])
            except ros2.Ros2Error as exc:
                self.bus.bad.add(key, str(exc))
                return
            self._next(name)
            pub.put(msg)
            self.counts[f"{name} in"] += 1

        return on

    def _outbound(self, name: str, to_cdr, pub):
        def on(msg: Any, _key: str) -> None:
            data = to_cdr(msg)
            att = None
            if self.ros.flavor == "rmw_zenoh":
                att = ros2.rmw_attachment(self._next(name), time.time_ns(), self._gid)
            pub.put(data, attachment=att)
            self.counts[f"{name} out"] += 1

        return on


_TYPES = {"cmd_vel": m.Twist, "map": m.OccupancyGrid}


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="topoexplore bridge", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("kind", choices=["ros2"], help="the other side (ROS 2)")
    p.add_argument("--flavor", choices=ros2.FLAVORS, default="ros2dds",
                   help="zenoh-bridge-ros2dds keys (default) or rmw_zenoh's")
    p.add_argument("--ros-prefix", default="", help="ros2dds: the bridge's namespace, if any")
    p.add_argument("--domain", type=int, default=0, help="rmw_zenoh: ROS_DOMAIN_ID (default 0)")
    for name, default in (("scan", "scan"), ("odom", "odom"), ("cmd-vel", "cmd_vel"),
                          ("map", "map")):
        p.add_argument(f"--{name}", default=default,
                       help=f"ROS topic (default {default}" + ("; '' : not sent)" if name in
                                                                ("cmd-vel", "map") else ")"))
    p.add_argument("--log-level", default="INFO", choices=("DEBUG", "INFO", "WARNING", "ERROR"))
    add_bus_args(p)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=getattr(logging, args.log_level), stream=sys.stderr,
                        format=LOG_FORMAT, datefmt=LOG_DATEFMT, force=True)
    init_logging()
    topics = {"scan": args.scan, "odom": args.odom, "cmd_vel": args.cmd_vel, "map": args.map}
    try:
        ros = ros2.RosKeys(args.flavor, args.ros_prefix, args.domain)
        for t in ("scan", "odom"):
            ros.sub(topics[t])
        ros2.typestore()
        keys = Keys(args.namespace or DEFAULT_NAMESPACE, args.robot or DEFAULT_ROBOT)
        connect = args.connect or DEFAULT_ENDPOINT
        if args.zenoh_config:
            check_config_file(args.zenoh_config)
    except (ValueError, ExtraMissing, BusError) as exc:
        print(f"topoexplore bridge: {exc}", file=sys.stderr)
        return 2
    stop = threading.Event()
    restore = stop_on_signals(stop.set)
    try:
        with Bus.client(connect, name="bridge", config_file=args.zenoh_config,
                        wait_for_router=True) as bus:
            bridge = Ros2Bridge(bus, keys, ros, topics)
            log.info("bridge ros2 (%s) up: %s <-> %s", args.flavor, keys.prefix,
                     ros.sub(topics["scan"]).rsplit("/", 1)[0] if args.flavor == "ros2dds"
                     else f"domain {args.domain}")
            while not stop.wait(0.5):
                pass
            counts, bad = dict(bridge.counts), bus.bad.total
    except BusError as exc:
        print(f"topoexplore bridge: {exc}", file=sys.stderr)
        return 2
    finally:
        restore()
    print(f"topoexplore bridge: stopped; {', '.join(f'{k} {v}' for k, v in sorted(counts.items())) or 'no messages'}; "
          f"{bad} bad", flush=True)
    return 0
