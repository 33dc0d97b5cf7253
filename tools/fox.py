"""Our messages as Foxglove messages: what ``record`` writes beside the raw channels and what
``view`` serves live, so that Foxglove shows a run the way the paper's figures do.

Pure: messages in, Foxglove messages out; no bus, no clock, no file. :class:`FoxScene` keeps the
little state the pictures need (the last graph for the reliability colours, the trail's last
point) and turns one decoded bus message into zero or more ``(topic, foxglove message)`` pairs.

Channels (frames after REP-105; our odometry is in ``map``, so ``map`` -> ``base_link`` is one
transform, and ``base_link`` -> ``laser`` is the ``[laser] offset``):

- ``/viz/map``: ``foxglove.Grid``, RGBA cells: free white, occupied black, unknown grey.
- ``/viz/scan``: ``foxglove.LaserScan`` in ``laser``.
- ``/tf``: ``foxglove.FrameTransforms``: ``map`` -> ``base_link`` from odometry, ``map`` ->
  ``truth`` from the simulator's ground truth, ``base_link`` -> ``laser``.
- ``/viz/trail``: ``foxglove.SceneUpdate``, one line entity per stretch of ground-truth travel.
- ``/viz/graph``: ``foxglove.SceneUpdate``: edges as lines, nodes as spheres (end nodes red
  below P = ``p_reliable``, green at or above it; branch purple; corner orange), end nodes
  labelled ``id(P)`` as in the paper's Fig. 10.
- ``/viz/plan``: ``foxglove.SceneUpdate``: the planned path and its target.
- ``/status/explore``, ``/status/sim``: the planner's and the simulator's status as JSON
  (the message's own fields; for the Raw Messages and Plot panels).

A converted message is a Foxglove message object (protobuf: ``encode()``, ``get_schema()``)
or, for the JSON channels, a plain dict; :data:`JSON_TYPES` names the message type of each
JSON channel (its JSON Schema).
"""

from __future__ import annotations

import functools
import json
import math
from typing import Any

import msgspec
import numpy as np

from topoexplore.common import convert
from topoexplore.common import messages as m

TOPICS = ("/viz/map", "/viz/scan", "/tf", "/viz/trail", "/viz/graph", "/viz/plan",
          "/status/explore", "/status/sim")
JSON_TYPES: dict[str, type] = {"/status/explore": m.ExploreStatus, "/status/sim": m.SimStatus}
PROTO_TYPES = {"/viz/map": "Grid", "/viz/scan": "LaserScan", "/tf": "FrameTransforms",
               "/viz/trail": "SceneUpdate", "/viz/graph": "SceneUpdate", "/viz/plan": "SceneUpdate"}
TRAIL_STEP = 0.5  # [m] ground-truth travel per trail entity
_KIND_RGBA = {"branch": (0.55, 0.25, 0.75, 1.0), "corner": (1.0, 0.6, 0.1, 1.0)}
_UNRELIABLE = (0.85, 0.1, 0.1, 1.0)
_RELIABLE = (0.1, 0.65, 0.2, 1.0)
# occupancy [-1, 0..100] -> RGBA: unknown grey, free white fading to black with occupancy
_LUT = np.empty((256, 4), dtype=np.uint8)
for _v in range(256):
    _s = _v - 256 if _v > 127 else _v  # the int8 value
    if _s < 0 or _s > 100:
        _LUT[_v] = (128, 128, 128, 255)
    else:
        g = round(255 * (1.0 - _s / 100.0))
        _LUT[_v] = (g, g, g, 255)


@functools.cache
def _fm() -> Any:
    import warnings

    with warnings.catch_warnings():  # foxglove.schemas (deprecated) is imported by the package
        warnings.simplefilter("ignore", DeprecationWarning)
        import foxglove.messages as fm
    return fm


@functools.cache
def json_schema(msg_type: type) -> bytes:
    """The JSON Schema of one of our message types (a raw channel's or a JSON channel's)."""
    return json.dumps(msgspec.json.schema(msg_type), sort_keys=True).encode()


def channel_schema(topic: str) -> tuple[str, str, str, bytes]:
    """(message encoding, schema name, schema encoding, schema data) of a Foxglove channel of
    :data:`TOPICS`, known before any message: a view creates its channels up front."""
    if topic in JSON_TYPES:
        t = JSON_TYPES[topic]
        return "json", f"topoexplore.{t.__name__}", "jsonschema", json_schema(t)
    sc = getattr(_fm(), PROTO_TYPES[topic]).get_schema()
    return "protobuf", sc.name, sc.encoding, bytes(sc.data)


def stamp(t: float) -> Any:
    """Seconds -> foxglove.Timestamp (negative or non-finite times become 0)."""
    fm = _fm()
    t = t if math.isfinite(t) and t > 0 else 0.0
    sec = int(t)
    return fm.Timestamp(sec=sec, nsec=min(999_999_999, int(round((t - sec) * 1e9))))


def header_stamp(h: m.Header) -> Any:
    """A message's stamp -> foxglove.Timestamp, copied (no float in between)."""
    return _fm().Timestamp(sec=h.stamp.sec, nsec=h.stamp.nanosec)


def _quat_z(theta: float) -> Any:
    return _fm().Quaternion(x=0.0, y=0.0, z=math.sin(theta / 2.0), w=math.cos(theta / 2.0))


def _pose(x: float, y: float, theta: float = 0.0, z: float = 0.0) -> Any:
    fm = _fm()
    return fm.Pose(position=fm.Vector3(x=x, y=y, z=z), orientation=_quat_z(theta))


def _color(rgba: tuple[float, float, float, float]) -> Any:
    return _fm().Color(r=rgba[0], g=rgba[1], b=rgba[2], a=rgba[3])


def grid_rgba(data: bytes, width: int, height: int) -> bytes:
    """int8 occupancy cells (row-major, x fastest) -> RGBA bytes of the same layout."""
    cells = np.frombuffer(data, dtype=np.uint8, count=width * height)
    return _LUT[cells].tobytes()


def grid_to_fox(g: m.OccupancyGrid) -> Any:
    fm = _fm()
    u8 = fm.PackedElementFieldNumericType.Uint8
    fields = [fm.PackedElementField(name=n, offset=i, type=u8)
              for i, n in enumerate(("red", "green", "blue", "alpha"))]
    i = g.info
    return fm.Grid(timestamp=header_stamp(g.header), frame_id="map",
                   pose=_pose(i.origin.position.x, i.origin.position.y,
                              m.yaw_of(i.origin.orientation)),
                   column_count=i.width,
                   cell_size=fm.Vector2(x=i.resolution, y=i.resolution),
                   row_stride=4 * i.width, cell_stride=4, fields=fields,
                   data=grid_rgba(g.data, i.width, i.height))


def scan_to_fox(s: m.LaserScan) -> Any:
    fm = _fm()
    n = len(s.ranges)
    ranges = [r if math.isfinite(r) and r < s.range_max else math.inf for r in s.ranges]
    return fm.LaserScan(timestamp=header_stamp(s.header), frame_id="laser", pose=_pose(0, 0),
                        start_angle=s.angle_min,
                        end_angle=s.angle_min + s.angle_increment * max(0, n - 1),  # not
                        #   angle_max: a driver that counts n increments would skew the beams
                        ranges=ranges, intensities=[])


def transform(t: float, parent: str, child: str, x: float, y: float, theta: float) -> Any:
    fm = _fm()
    return fm.FrameTransform(timestamp=stamp(t), parent_frame_id=parent, child_frame_id=child,
                             translation=fm.Vector3(x=x, y=y, z=0.0), rotation=_quat_z(theta))


def graph_scene(topo: m.TopoGraph, rel: m.Reliability | None, p_reliable: float) -> Any:
    """The topological map as one scene entity: edges, nodes coloured by kind and P, labels
    ``id(P)`` at the end nodes (those without a P yet are labelled with the id only)."""
    fm = _fm()
    ts = header_stamp(topo.header)
    p_of = {n.id: n.p for n in rel.nodes} if rel is not None else {}
    lines = [fm.LinePrimitive(type=fm.LinePrimitiveLineType.LineStrip, pose=_pose(0, 0),
                              thickness=2.0, scale_invariant=True,
                              points=[fm.Point3(x=p[0], y=p[1], z=0.01) for p in e.points],
                              color=_color((0.1, 0.45, 0.9, 1.0)))
             for e in topo.edges if len(e.points) >= 2]
    spheres, texts = [], []
    for n in topo.nodes:
        if n.kind == "end":
            p = p_of.get(n.id)
            rgba = _RELIABLE if p is not None and p >= p_reliable else _UNRELIABLE
            label = f"{n.id}({p:.2f})" if p is not None else str(n.id)
            texts.append(fm.TextPrimitive(pose=_pose(n.x, n.y + 0.3, z=0.05), billboard=True,
                                          font_size=12.0, scale_invariant=True,
                                          color=_color(rgba), text=label))
        else:
            rgba = _KIND_RGBA.get(n.kind, (0.5, 0.5, 0.5, 1.0))
        spheres.append(fm.SpherePrimitive(pose=_pose(n.x, n.y, z=0.02),
                                          size=fm.Vector3(x=0.25, y=0.25, z=0.25),
                                          color=_color(rgba)))
    ent = fm.SceneEntity(timestamp=ts, frame_id="map", id="graph", lines=lines,
                         spheres=spheres, texts=texts)
    return fm.SceneUpdate(entities=[ent])


def plan_scene(p: m.Path) -> Any:
    """The path the controller follows and its target (an empty path deletes the line)."""
    fm = _fm()
    ts = header_stamp(p.header)
    pts = [fm.Point3(x=q.pose.position.x, y=q.pose.position.y, z=0.03) for q in p.poses]
    lines, spheres = [], []
    if len(pts) >= 2:
        lines.append(fm.LinePrimitive(type=fm.LinePrimitiveLineType.LineStrip, pose=_pose(0, 0),
                                      thickness=3.0, scale_invariant=True, points=pts,
                                      color=_color((1.0, 0.0, 0.8, 1.0))))
    if pts:
        spheres.append(fm.SpherePrimitive(pose=_pose(p.target_x, p.target_y, z=0.04),
                                          size=fm.Vector3(x=0.4, y=0.4, z=0.4),
                                          color=_color((1.0, 0.0, 0.8, 0.6))))
    meta = [fm.KeyValuePair(key="target_id", value=str(p.target_id)),
            fm.KeyValuePair(key="strategy", value=p.strategy)]
    return fm.SceneUpdate(entities=[fm.SceneEntity(timestamp=ts, frame_id="map", id="plan",
                                                   lines=lines, spheres=spheres,
                                                   metadata=meta)])


class FoxScene:
    """Decoded bus messages -> Foxglove messages, keyed by our topic names (``scan``, ``odom``,
    ``truth``, ``map``, ``topo``, ``reliability``, ``plan``; the others give nothing)."""

    def __init__(self, laser_offset: float = 0.0, p_reliable: float = 0.9):
        self.laser_offset = laser_offset  # [m] laser ahead of base_link
        self.p_reliable = p_reliable
        self._graph: m.TopoGraph | None = None
        self._beliefs: m.Reliability | None = None
        self._trail: tuple[float, float] | None = None
        self._trail_n = 0
        self._laser_sent = False

    def convert(self, topic: str, msg: Any) -> list[tuple[str, Any]]:
        fn = getattr(self, "_" + topic.replace("/", "_"), None)
        return fn(msg) if fn is not None else []

    def _scan(self, s: m.LaserScan) -> list[tuple[str, Any]]:
        out = [("/viz/scan", scan_to_fox(s))]
        if not self._laser_sent:  # the mount is static: once is enough for Foxglove's buffer
            self._laser_sent = True
            out.insert(0, ("/tf", _fm().FrameTransforms(transforms=[transform(
                0.0, "base_link", "laser", self.laser_offset, 0.0, 0.0)])))
        return out

    def _odom(self, o: m.Odometry) -> list[tuple[str, Any]]:
        p = convert.pose_from_msg(o.pose.pose)
        return [("/tf", _fm().FrameTransforms(transforms=[transform(
            o.header.time, "map", "base_link", p.x, p.y, p.theta)]))]

    def _truth(self, t: m.PoseStamped) -> list[tuple[str, Any]]:
        fm = _fm()
        p = convert.truth_from_msg(t)
        out = [("/tf", fm.FrameTransforms(transforms=[transform(
            t.header.time, "map", "truth", p.x, p.y, p.theta)]))]
        if self._trail is None:
            self._trail = (p.x, p.y)
        elif math.hypot(p.x - self._trail[0], p.y - self._trail[1]) >= TRAIL_STEP:
            a, self._trail = self._trail, (p.x, p.y)
            self._trail_n += 1
            line = fm.LinePrimitive(type=fm.LinePrimitiveLineType.LineStrip, pose=_pose(0, 0),
                                    thickness=2.0, scale_invariant=True,
                                    points=[fm.Point3(x=a[0], y=a[1], z=0.02),
                                            fm.Point3(x=p.x, y=p.y, z=0.02)],
                                    color=_color((0.95, 0.55, 0.0, 1.0)))
            out.append(("/viz/trail", fm.SceneUpdate(entities=[fm.SceneEntity(
                timestamp=header_stamp(t.header), frame_id="map", id=f"trail-{self._trail_n}",
                lines=[line])])))
        return out

    def _map(self, g: m.OccupancyGrid) -> list[tuple[str, Any]]:
        return [("/viz/map", grid_to_fox(g))]

    def _topo(self, t: m.TopoGraph) -> list[tuple[str, Any]]:
        self._graph = t
        if self._beliefs is None:  # no reliability service: the graph alone
            return [("/viz/graph", graph_scene(t, None, self.p_reliable))]
        if self._beliefs.header.src_seq >= t.header.src_seq:
            return [("/viz/graph", graph_scene(t, self._beliefs, self.p_reliable))]
        return []  # its P values come with the next reliability message

    def _reliability(self, r: m.Reliability) -> list[tuple[str, Any]]:
        self._beliefs = r
        if self._graph is None:
            return []
        return [("/viz/graph", graph_scene(self._graph, r, self.p_reliable))]

    def _plan(self, p: m.Path) -> list[tuple[str, Any]]:
        return [("/viz/plan", plan_scene(p))]

    def _explore_status(self, s: m.ExploreStatus) -> list[tuple[str, Any]]:
        return [("/status/explore", msgspec.to_builtins(s))]

    def _sim_status(self, s: m.SimStatus) -> list[tuple[str, Any]]:
        return [("/status/sim", msgspec.to_builtins(s))]
