"""Codec round trip of every message, plain-msgpack readability, strict validation."""

from __future__ import annotations

import math

import msgpack
import msgspec
import numpy as np
import pytest

from topoexplore.common import messages as m


def hdr(**kw) -> m.Header:
    return m.header(kw.get("seq", 3), kw.get("stamp", 1.5), "map", kw.get("src_seq", 2))


POSE = m.GeoPose(position=m.Point(x=1.0, y=-2.0), orientation=m.quaternion(0.5))


def samples() -> list:
    grid = np.full((3, 4), -1, dtype=np.int8)
    grid[1, 2] = 100
    grid[0, 0] = 0
    return [
        m.LaserScan(header=hdr(), angle_min=-math.pi / 2, angle_max=math.pi / 2,
                    angle_increment=math.pi / 180, time_increment=1e-4, scan_time=0.2,
                    range_min=0.02, range_max=8.0, ranges=[1.0] * 181,
                    intensities=[100.0] * 181),
        m.Odometry(header=hdr(), child_frame_id="base_link", pose=m.PoseWithCovariance(
            pose=POSE, covariance=[0.01 * k for k in range(36)]),
            twist=m.TwistWithCovariance(twist=m.GeoTwist(linear=m.Vector3(x=0.2),
                                                         angular=m.Vector3(z=-0.1)))),
        m.PoseStamped(header=hdr(), pose=POSE),
        m.TransformStamped(header=hdr(), child_frame_id="odom", transform=m.Transform(
            translation=m.Vector3(x=0.1, y=-0.2), rotation=m.quaternion(0.05))),
        m.Twist(header=hdr(), linear=m.Vector3(x=0.2), angular=m.Vector3(z=0.3)),
        m.OccupancyGrid(header=hdr(), info=m.MapMetaData(
            map_load_time=m.Time(sec=1, nanosec=5), resolution=0.1, width=4, height=3,
            origin=m.GeoPose(position=m.Point(x=-1.0, y=-2.0), orientation=m.Quaternion())),
            data=grid.tobytes()),
        m.TopoGraph(header=hdr(), nodes=[m.TopoNode(id=1, kind="end", x=0.0, y=0.0),
                                         m.TopoNode(id=2, kind="branch", x=1.0, y=0.0)],
                    edges=[m.TopoEdge(a=1, b=2, points=[[0.0, 0.0], [1.0, 0.0]], length=1.0,
                                      clearance=0.4)], gone=[7]),
        m.Reliability(header=hdr(), nodes=[m.NodeReliability(
            id=1, x=0.0, y=0.0, p=0.6, d=0.8, a=0.1, r_min=1.5, alpha_max=0.2, visible=True,
            n_obs=3)]),
        m.Path(header=hdr(), poses=[m.PoseStamped(header=hdr(seq=-1, src_seq=-1), pose=POSE)] * 2,
               target_id=4, target_x=1.0, target_y=1.0, strategy="reliability", plan_id=2),
        m.ExploreStatus(header=hdr(), state="exploring", reason="target 4", target_id=4,
                        target_p=0.5, candidates=2, end_nodes=3, reliable=1, blacklisted=[9]),
        m.SimStatus(header=hdr(), world="paper-room", mode="lockstep", sim_time=1.0, steps=50,
                    collisions=0, path_length=0.2, real_time_factor=20.0),
    ]


@pytest.mark.parametrize("msg", samples(), ids=lambda s: type(s).__name__)
def test_round_trip(msg):
    raw = m.encode(msg)
    assert m.decode(raw, type(msg)) == msg


@pytest.mark.parametrize("msg", samples(), ids=lambda s: type(s).__name__)
def test_plain_msgpack_client_reads_every_message(msg):
    plain = msgpack.unpackb(m.encode(msg), raw=False)
    assert isinstance(plain, dict)
    assert plain == msgspec.to_builtins(msg, enc_hook=None) | {
        k: v for k, v in plain.items() if isinstance(v, bytes)}
    assert plain["header"]["seq"] == 3 and plain["header"]["src_seq"] == 2


def test_every_type_covered():
    assert {type(s) for s in samples()} == set(m.MESSAGE_TYPES.values())


def _mut(msg, **changes):
    return msgspec.structs.replace(msg, **changes)


S = {type(s).__name__: s for s in samples()}
NAN, INF = float("nan"), float("inf")

BAD = [
    ("not msgpack", b"\xc1\xc1garbage", m.LaserScan),
    ("empty payload", b"", m.Odometry),
    ("wrong root type", msgpack.packb([1, 2, 3]), m.Twist),
    ("missing header fields", msgpack.packb({"header": {}, "linear": {}, "angular": {}}),
     m.Twist),
    ("missing field", msgpack.packb({"header": {"stamp": {"sec": 0, "nanosec": 0},
                                                "frame_id": "map"}, "linear": {}}), m.Twist),
    ("float stamp", msgpack.packb({"header": {"stamp": 1.5, "frame_id": "map"}, "linear": {},
                                   "angular": {}}), m.Twist),
    ("string for float", msgpack.packb({"header": {"stamp": {"sec": 0, "nanosec": 0},
                                                   "frame_id": ""}, "linear": {"x": "fast"},
                                        "angular": {}}), m.Twist),
    ("nan velocity", m.encode(_mut(S["Twist"], linear=m.Vector3(x=NAN))), m.Twist),
    ("inf pose", m.encode(_mut(S["PoseStamped"], pose=m.GeoPose(
        position=m.Point(x=INF), orientation=m.Quaternion()))), m.PoseStamped),
    ("zero quaternion", m.encode(_mut(S["PoseStamped"], pose=m.GeoPose(
        position=m.Point(), orientation=m.Quaternion(w=0.0)))), m.PoseStamped),
    ("short covariance", m.encode(_mut(S["Odometry"], pose=m.PoseWithCovariance(
        pose=POSE, covariance=[0.0] * 9))), m.Odometry),
    ("nan covariance", m.encode(_mut(S["Odometry"], pose=m.PoseWithCovariance(
        pose=POSE, covariance=[NAN] * 36))), m.Odometry),
    ("nanosec overflow", m.encode(_mut(S["Twist"], header=m.Header(
        stamp=m.Time(sec=1, nanosec=10**9), frame_id="x"))), m.Twist),
    ("angle_max off", m.encode(_mut(S["LaserScan"], angle_max=2.0)), m.LaserScan),
    ("intensities count", m.encode(_mut(S["LaserScan"], intensities=[1.0] * 3)), m.LaserScan),
    ("unrotated bad origin", m.encode(_mut(S["OccupancyGrid"], info=msgspec.structs.replace(
        S["OccupancyGrid"].info, origin=m.GeoPose(position=m.Point(y=NAN),
                                                  orientation=m.Quaternion())))),
     m.OccupancyGrid),
    ("no ranges", m.encode(_mut(S["LaserScan"], ranges=[])), m.LaserScan),
    ("too many beams", m.encode(_mut(S["LaserScan"], ranges=[1.0] * 20000)), m.LaserScan),
    ("range_max < min", m.encode(_mut(S["LaserScan"], range_max=0.01)), m.LaserScan),
    ("zero increment", m.encode(_mut(S["LaserScan"], angle_increment=0.0)), m.LaserScan),
    ("more than a turn", m.encode(_mut(S["LaserScan"], angle_increment=0.1, angle_max=16.0)),
     m.LaserScan),
    ("nan angle_min", m.encode(_mut(S["LaserScan"], angle_min=NAN)), m.LaserScan),
    ("grid data short", m.encode(_mut(S["OccupancyGrid"], data=b"\x00" * 5)), m.OccupancyGrid),
    ("grid absurd size", m.encode(_mut(S["OccupancyGrid"], info=msgspec.structs.replace(
        S["OccupancyGrid"].info, width=100000, height=100000))), m.OccupancyGrid),
    ("grid bad value", m.encode(_mut(S["OccupancyGrid"], data=bytes([120] * 12))),
     m.OccupancyGrid),
    ("zero resolution", m.encode(_mut(S["OccupancyGrid"], info=msgspec.structs.replace(
        S["OccupancyGrid"].info, resolution=0.0))), m.OccupancyGrid),
    ("node kind", m.encode(_mut(S["TopoGraph"], nodes=[m.TopoNode(id=1, kind="x", x=0, y=0)],
                                edges=[])), m.TopoGraph),
    ("edge to unknown node", m.encode(_mut(S["TopoGraph"], edges=[m.TopoEdge(
        a=1, b=99, points=[], length=1.0, clearance=0.1)])), m.TopoGraph),
    ("duplicate node id", m.encode(_mut(S["TopoGraph"], nodes=[
        m.TopoNode(id=1, kind="end", x=0, y=0)] * 2, edges=[])), m.TopoGraph),
    ("3d point", m.encode(_mut(S["TopoGraph"], edges=[m.TopoEdge(
        a=1, b=2, points=[[0.0, 0.0, 1.0]], length=1.0, clearance=0.1)])), m.TopoGraph),
    ("ragged points", m.encode(_mut(S["TopoGraph"], edges=[m.TopoEdge(
        a=1, b=2, points=[[0.0, 0.0], [1.0]], length=1.0, clearance=0.1)])), m.TopoGraph),
    ("nan point", m.encode(_mut(S["TopoGraph"], edges=[m.TopoEdge(
        a=1, b=2, points=[[0.0, 0.0], [NAN, 1.0]], length=1.0, clearance=0.1)])), m.TopoGraph),
    ("absurd point", m.encode(_mut(S["TopoGraph"], edges=[m.TopoEdge(
        a=1, b=2, points=[[0.0, 1e12]], length=1.0, clearance=0.1)])), m.TopoGraph),
    ("negative edge length", m.encode(_mut(S["TopoGraph"], edges=[m.TopoEdge(
        a=1, b=2, points=[], length=-1.0, clearance=0.1)])), m.TopoGraph),
    ("nan clearance", m.encode(_mut(S["TopoGraph"], edges=[m.TopoEdge(
        a=1, b=2, points=[], length=1.0, clearance=NAN)])), m.TopoGraph),
    ("p above 1", m.encode(_mut(S["Reliability"], nodes=[msgspec.structs.replace(
        S["Reliability"].nodes[0], p=1.5)])), m.Reliability),
    ("nan waypoint", m.encode(_mut(S["Path"], poses=[m.PoseStamped(
        header=hdr(), pose=m.GeoPose(position=m.Point(y=NAN), orientation=m.Quaternion()))])),
     m.Path),
    ("bad state", m.encode(_mut(S["ExploreStatus"], state="lost")), m.ExploreStatus),
    ("negative stamp", m.encode(_mut(S["Twist"], header=m.Header(
        stamp=m.Time(sec=-1, nanosec=0), frame_id="x"))), m.Twist),
    ("bad mode", m.encode(_mut(S["SimStatus"], mode="fast")), m.SimStatus),
]


@pytest.mark.parametrize("name,raw,t", BAD, ids=[b[0] for b in BAD])
def test_validation_rejects_with_one_error_type(name, raw, t):
    with pytest.raises(m.MessageError) as exc:
        m.decode(raw, t)
    text = str(exc.value)
    assert "\n" not in text and t.__name__ in text


def test_a_bad_polyline_names_its_edge():
    good = m.TopoEdge(a=1, b=2, points=[[0.0, 0.0], [1.0, 0.0]], length=1.0, clearance=0.4)
    for points, text in [([[0.0, 0.0], [NAN, 1.0]], "edge 2-1 has a non-finite"),
                         ([[0.0, 0.0], [1.0]], "edge 2-1 has a point with 1 coordinates"),
                         ([[0.0, 0.0, 0.0]], "edge 2-1 has a point with 3 coordinates")]:
        bad = m.TopoEdge(a=2, b=1, points=points, length=1.0, clearance=0.4)
        raw = m.encode(_mut(S["TopoGraph"], edges=[good, bad, good]))
        with pytest.raises(m.MessageError, match=text):
            m.decode(raw, m.TopoGraph)


def test_seq_gaps_counts_jumps_restarts_and_not_the_first_message():
    g = m.SeqGaps()
    for seq in (7, 8, 9, 12, 13):  # joined at 7: not lost; 10 and 11 lost
        g.check("scan", seq)
    assert g.gaps == {"scan": 2} and g.first_seq == {"scan": 7} and g.total == 2
    assert g.check("scan", 0) == 0 and g.restarts == {"scan": 1}  # restarted publisher
    assert g.check("scan", 3) == 2 and g.total == 4
    g.check("scan", 1)  # another step back (a second publisher): the count starts again
    assert g.check("scan", 2) == 0 and g.total == 4
    g.check("odom", 0)
    assert g.gaps.get("odom") is None
