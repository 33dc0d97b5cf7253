"""Where things are on the bus: every key expression, built in one place from namespace +
robot, and the default router endpoint.

Layout: ``<ns>/<robot>/<topic>``, e.g. ``topoexplore/robot1/scan``. Liveliness tokens live at
``<ns>/<robot>/alive/<service>`` and state queryables at ``<ns>/<robot>/<service>/state``.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from topoexplore.common import messages as m

DEFAULT_NAMESPACE = "topoexplore"
DEFAULT_ROBOT = "robot1"
DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"  # the router every process connects to by default

# topic -> message type: the one table of what travels on which key
TOPICS: dict[str, type] = {
    "scan": m.LaserScan,
    "odom": m.Odometry,
    "truth": m.PoseStamped,
    "cmd_vel": m.Twist,
    "map": m.OccupancyGrid,
    "topo": m.TopoGraph,
    "reliability": m.Reliability,
    "plan": m.Path,
    "explore/status": m.ExploreStatus,
    "sim/status": m.SimStatus,
    "map_odom": m.TransformStamped,  # the localizer's map -> odom correction (REP-105), per scan
}

SERVICES = ("sim", "mapper", "topology", "reliability", "planner", "controller")

# service -> (topics it subscribes to, topics it publishes): who feeds whom (``replay`` plays
# the inputs of a chain of services and compares its outputs; tests/test_record.py checks the
# table against every service module)
SERVICE_IO: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    "sim": (("cmd_vel",), ("scan", "odom", "truth", "sim/status")),
    "mapper": (("scan", "odom"), ("map",)),
    "topology": (("map", "odom"), ("topo",)),
    "reliability": (("map", "topo", "odom"), ("reliability",)),
    "planner": (("map", "topo", "reliability", "odom"), ("plan", "explore/status")),
    "controller": (("plan", "explore/status", "scan", "odom"), ("cmd_vel",)),
    "localizer": (("scan", "odom", "map"), ("map_odom",)),
}

_SEGMENT = re.compile(r"^[A-Za-z0-9_\-]+(/[A-Za-z0-9_\-]+)*$")


def check_segment(value: str, what: str) -> str:
    """Validate a namespace or robot name (one or more plain key segments)."""
    if not _SEGMENT.match(value or ""):
        raise ValueError(f"bad {what} {value!r}: use letters, digits, '_', '-' and '/' separators")
    return value


def check_endpoint(ep: str, any_port: bool = False) -> str:
    """A Zenoh locator like tcp/127.0.0.1:7447 (tcp/udp/tls/quic need host:port, port
    1..65535, or 0 with any_port: a listener on any free port); ValueError otherwise."""
    proto, sep, addr = ep.partition("/")
    if not sep or not proto or not addr:
        raise ValueError(f"bad endpoint {ep!r}: expected PROTOCOL/HOST:PORT, e.g. "
                         f"{DEFAULT_ENDPOINT}")
    if proto in ("tcp", "udp", "tls", "quic"):
        host, colon, port = addr.rpartition(":")
        low = 0 if any_port else 1
        if not colon or not host or not port.isdigit() or not low <= int(port) <= 65535:
            raise ValueError(f"bad endpoint {ep!r}: port must be {low}..65535")
    return ep


@dataclass(frozen=True)
class Keys:
    namespace: str = DEFAULT_NAMESPACE
    robot: str = DEFAULT_ROBOT

    def __post_init__(self) -> None:
        check_segment(self.namespace, "namespace")
        check_segment(self.robot, "robot name")

    @property
    def prefix(self) -> str:
        return f"{self.namespace}/{self.robot}"

    def topic(self, name: str) -> str:
        if name not in TOPICS:
            raise KeyError(f"unknown topic {name!r}")
        return f"{self.prefix}/{name}"

    def alive(self, service: str) -> str:
        return f"{self.prefix}/alive/{service}"

    def alive_all(self) -> str:
        return f"{self.prefix}/alive/*"

    def state(self, service: str) -> str:
        return f"{self.prefix}/{service}/state"

    def latest(self, service: str, topic: str) -> str:
        """The queryable answering with the last message of ``topic`` a service received: a
        restarted publisher gets its last output back from any peer (``Node.serve_latest``)."""
        return f"{self.prefix}/{service}/latest/{topic}"

    def params(self, service: str) -> str:
        """The queryable that reads and changes a service's live parameters (keys set)."""
        return f"{self.prefix}/{service}/params"

    def all(self) -> str:
        return f"{self.prefix}/**"

    # convenience attributes
    @property
    def scan(self) -> str:
        return self.topic("scan")

    @property
    def odom(self) -> str:
        return self.topic("odom")

    @property
    def truth(self) -> str:
        return self.topic("truth")

    @property
    def cmd_vel(self) -> str:
        return self.topic("cmd_vel")

    @property
    def map(self) -> str:
        return self.topic("map")

    @property
    def topo(self) -> str:
        return self.topic("topo")

    @property
    def reliability(self) -> str:
        return self.topic("reliability")

    @property
    def plan(self) -> str:
        return self.topic("plan")

    @property
    def explore_status(self) -> str:
        return self.topic("explore/status")

    @property
    def sim_status(self) -> str:
        return self.topic("sim/status")

    def topic_of(self, key: str) -> str | None:
        """Inverse of :meth:`topic`: the topic name for a full key, or None."""
        pre = self.prefix + "/"
        if not key.startswith(pre):
            return None
        rest = key[len(pre) :]
        return rest if rest in TOPICS else None


def type_for_key(key: str) -> type | None:
    """Message type for any full key ``<ns>/<robot>/<topic>`` (namespace-agnostic)."""
    for topic, t in TOPICS.items():
        if key.endswith("/" + topic):
            return t
    return None
