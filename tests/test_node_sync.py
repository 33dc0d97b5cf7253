"""Pure helpers of the service runtime: odometry buffer and inbox (no bus)."""

from __future__ import annotations

import math
import threading
from types import SimpleNamespace

import pytest

from topoexplore.common.node import Inbox, OdomBuffer


def test_odom_exact_and_interpolated():
    b = OdomBuffer()
    b.add(0.0, (0.0, 0.0, 0.0))
    b.add(1.0, (1.0, 2.0, math.pi / 2))
    assert b.pose_at(0.0) == (0.0, 0.0, 0.0)
    x, y, th = b.pose_at(0.5)
    assert math.isclose(x, 0.5) and math.isclose(y, 1.0) and math.isclose(th, math.pi / 4)
    assert b.pose_at(1.5) is None  # not covered yet: the caller waits
    assert b.newest == 1.0


def test_odom_angle_wraps():
    b = OdomBuffer()
    b.add(0.0, (0, 0, math.pi - 0.1))
    b.add(1.0, (0, 0, -math.pi + 0.1))
    th = b.pose_at(0.5)[2]
    assert math.isclose(abs(math.remainder(th, 2 * math.pi)), math.pi, abs_tol=1e-9)


def test_odom_horizon_and_restart():
    b = OdomBuffer(horizon=1.0)
    for i in range(100):
        b.add(i * 0.1, (i, 0, 0))
    assert b.pose_at(0.0) is None
    b.add(0.0, (5, 5, 0))  # sim restarted: clock went back
    assert b.pose_at(0.0) == (5, 5, 0)


def test_inbox_queue_lockstep_keeps_all_and_realtime_conflates():
    ib = Inbox()
    ib.make_queue("scan", 10_000)
    for i in range(5):
        ib.put("scan", i)
    assert [ib.pop("scan") for _ in range(5)] == [0, 1, 2, 3, 4]
    rt = Inbox()
    rt.make_queue("scan", 1)
    for i in range(5):
        rt.put("scan", i)
    assert rt.pop("scan") == 4 and rt.dropped["scan"] == 4


def test_inbox_history_gives_the_message_of_a_given_scan():
    """Lockstep with a plan lag: a stage works on the map of scan k while newer maps arrive;
    it takes that scan's message, not the newest (``Inbox.at``)."""
    from topoexplore.common import messages as m

    ib = Inbox()
    ib.keep_history("map", 3)
    assert ib.at("map", 10) is None
    for k in (0, 2, 4, 6):
        ib.put("map", SimpleNamespace(header=m.header(k // 2, 0.1 * k, "map", k)))
    assert ib.at("map", 4).header.src_seq == 4
    assert ib.at("map", 5).header.src_seq == 4  # the newest at or before scan 5
    assert ib.at("map", 100).header.src_seq == 6
    assert ib.at("map", 1).header.src_seq == 6  # scan 0's was dropped (3 kept): the latest
    assert ib.latest["map"].header.src_seq == 6
    ib.put("plan", SimpleNamespace(header=m.header(0, 0.0, "map", 8)))
    assert ib.at("plan", 0).header.src_seq == 8  # no history kept: the latest


def test_inbox_wait_wakes_on_put():
    ib = Inbox()
    ib.make_queue("x", 1)
    t = threading.Timer(0.05, lambda: ib.put("x", 1))
    t.start()
    assert ib.wait(lambda: ib.pending("x") > 0, 5.0)
    t.join()


def test_pose_near_falls_back_to_newest():
    b = OdomBuffer()
    assert b.pose_near(1.0) is None
    b.add(0.0, (0.0, 0.0, 0.0))
    b.add(1.0, (1.0, 0.0, 0.0))
    assert b.pose_near(0.5) == (0.5, 0.0, 0.0)
    assert b.pose_near(5.0) == (1.0, 0.0, 0.0)  # not covered yet: newest


def test_a_restarted_publisher_replaces_the_history():
    """A simulator resumed from its checkpoint: its seq starts again and its clock went back
    0.6 s. The poses of the one before are dropped, not mixed with the new ones."""
    b = OdomBuffer()
    for k in range(10):
        b.add(0.1 * k, (0.1 * k, 0.0, 0.0), seq=100 + k)
    b.add(0.3, (5.0, 5.0, 0.0), seq=0)  # the resumed one, elsewhere
    b.add(0.4, (5.0, 5.1, 0.0), seq=1)
    assert b.newest == 0.4 and b.pose_at(0.35) == pytest.approx((5.0, 5.05, 0.0))


def _rt(**kw):
    from topoexplore.common.params import RuntimeParams

    return RuntimeParams(**kw)


def test_chaos_drops_a_seeded_share_of_chosen_topics_only():
    from topoexplore.common.node import Chaos

    c = Chaos(_rt(chaos_topics=["scan"], chaos_drop=0.3, chaos_seed=4))
    got = []
    for i in range(1000):
        c.admit("scan", lambda i=i: got.append(("scan", i)))
        c.admit("odom", lambda i=i: got.append(("odom", i)))
    scans = [i for t, i in got if t == "scan"]
    assert sum(1 for t, _ in got if t == "odom") == 1000  # other topics untouched
    assert 250 <= c.dropped["scan"] == 1000 - len(scans) <= 350
    assert scans == sorted(scans)
    again = Chaos(_rt(chaos_topics=["scan"], chaos_drop=0.3, chaos_seed=4))
    kept = []
    for i in range(1000):
        again.admit("scan", lambda i=i: kept.append(i))
    assert kept == scans  # the same seed drops the same messages
    c.configure(_rt())  # off
    c.admit("scan", lambda: got.append(("scan", -1)))
    assert got[-1] == ("scan", -1)


def test_chaos_delays_in_order():
    import time

    from topoexplore.common.node import Chaos

    c = Chaos(_rt(chaos_topics=["plan"], chaos_delay=0.2))
    got, t0 = [], time.monotonic()
    done = threading.Event()
    for i in range(20):
        c.admit("plan", lambda i=i: (got.append((i, time.monotonic() - t0)),
                                      i == 19 and done.set()))
    assert got == [] and c.delayed["plan"] == 20
    assert done.wait(5.0)
    assert [i for i, _ in got] == list(range(20)) and all(dt >= 0.2 for _, dt in got)
    c.close()


def test_a_corrected_buffer_composes_odometry_with_the_correction_in_force():
    from topoexplore.common.domain import Pose, compose, inverse

    a = Pose(1.0, -2.0, 0.7)
    assert compose(a, inverse(a)) == pytest.approx((0.0, 0.0, 0.0), abs=1e-12)
    b = OdomBuffer(corrected=True)
    b.add(0.0, (0.0, 0.0, 0.0))
    b.add(1.0, (1.0, 0.0, 0.0))
    assert b.newest == -math.inf  # odometry, but no correction yet: a scan at 1.0 waits
    b.add_correction(0.5, Pose(0.0, 1.0, math.pi / 2))  # map -> odom from 0.5 on
    assert b.newest == 0.5
    assert b.pose_at(0.0) == pytest.approx((0.0, 1.0, math.pi / 2))  # before: the first one
    b.add_correction(1.0, Pose(0.0, 0.0, 0.0))
    assert b.pose_at(1.0) == pytest.approx((1.0, 0.0, 0.0)) and b.newest == 1.0
    x, y, th = b.pose_at(0.75)  # odometry (0.75, 0, 0) under the correction of 0.5
    assert (x, y, th) == pytest.approx((0.0, 1.75, math.pi / 2))
    plain = OdomBuffer()
    plain.add(0.0, (0.0, 0.0, 0.0))
    plain.add_correction(0.0, Pose(5.0, 5.0, 0.0))  # applied, but not waited for
    assert plain.newest == 0.0 and plain.pose_at(0.0) == pytest.approx((5.0, 5.0, 0.0))
