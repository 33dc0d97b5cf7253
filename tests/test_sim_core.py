"""Simulator core: laser geometry, differential drive, walls, collisions, watchdog, seeds."""

from __future__ import annotations

import math

import numpy as np
import pytest

from topoexplore.common.params import LaserParams, RobotParams, SimParams
from topoexplore.sim.core import SimCore, SimError, beam_angles
from topoexplore.sim.world import World, clearance, load_world, parse_world

DT = 1.0 / 50.0  # [s] default physics step


def box_world(pose=(3.0, 3.0, 0.0), extra=None) -> World:
    """10 x 6 m room; walls of radius 0.05 centred on the boundary -> inner faces at
    x = 0.05, 9.95 and y = 0.05, 5.95."""
    data = {"size": [10.0, 6.0], "robot": {"pose": list(pose)}, "wall_thickness": 0.05,
            "walls": [{"points": [[0, 0], [10, 0], [10, 6], [0, 6]], "closed": True}]}
    data.update(extra or {})
    return parse_world(data, "test-box")


ROBOT = {"v_limit", "w_limit", "radius"}
LASER = {"offset", "range_min", "range_max", "beams", "fov", "scan_hz"}


def make(world=None, seed=0, **kw) -> SimCore:
    """A SimCore in the box world; keyword parameters go to their section (sim/robot/laser)."""
    kw.setdefault("range_noise", 0.0)
    robot = RobotParams(**{k: v for k, v in kw.items() if k in ROBOT})
    laser = LaserParams(**{k: v for k, v in kw.items() if k in LASER})
    sim = SimParams(**{k: v for k, v in kw.items() if k not in ROBOT | LASER})
    return SimCore(world or box_world(), sim, np.random.default_rng(seed), robot, laser)


def drive(sim: SimCore, v: float, w: float, seconds: float) -> None:
    for _ in range(round(seconds / DT)):
        sim.command(v, w)
        sim.step()


# ------------------------------------------------------------------------------ laser


def test_beam_layout():
    sim = make()
    assert sim.angle_min == pytest.approx(-math.pi / 2)
    assert sim.angle_increment == pytest.approx(math.pi / 180)
    assert beam_angles(181, math.pi) == (sim.angle_min, sim.angle_increment)
    r = sim.scan().ranges
    assert r.dtype == np.float64 and r.shape == (181,)


def test_laser_ranges_match_geometry():
    r = make().scan().ranges  # robot at (3, 3) heading +x
    assert r[90] == pytest.approx(9.95 - 3.0, abs=1e-6)  # 0 deg -> right wall
    assert r[0] == pytest.approx(3.0 - 0.05, abs=1e-6)  # -90 deg -> bottom wall
    assert r[180] == pytest.approx(5.95 - 3.0, abs=1e-6)  # +90 deg -> top wall
    assert r[45] == pytest.approx(2.95 * math.sqrt(2), abs=1e-6)  # -45 deg, bottom wall
    # +30 deg: top wall at distance 2.95 / sin(30 deg)
    assert r[120] == pytest.approx(2.95 / math.sin(math.radians(30)), abs=1e-6)


def test_laser_follows_heading_and_offset():
    r = make(box_world(pose=(3.0, 3.0, math.pi / 2))).scan().ranges
    assert r[90] == pytest.approx(2.95, abs=1e-6)  # now facing the top wall
    assert r[0] == pytest.approx(6.95, abs=1e-6)  # -90 deg points to +x
    r = make(offset=0.1).scan().ranges
    assert r[90] == pytest.approx(6.85, abs=1e-6)
    assert r[0] == pytest.approx(2.95, abs=1e-6)  # sideways beams unchanged


def test_laser_sees_thin_leg_and_box():
    w = box_world(extra={"circles": [{"center": [5.0, 3.0], "radius": 0.03}],
                         "boxes": [{"center": [3.0, 4.5], "size": [1.0, 1.0]}]})
    r = make(w).scan().ranges
    assert r[90] == pytest.approx(2.0 - 0.03, abs=1e-6)
    assert r[180] == pytest.approx(1.0, abs=1e-6)


def test_no_return_is_range_max_exactly_and_noise_is_clipped():
    w = parse_world({"size": [40.0, 40.0], "robot": {"pose": [20.0, 20.0, 0.0]}}, "open")
    r = make(w, range_noise=0.05).scan().ranges
    assert np.all(r == 8.0)
    sim = make(box_world(pose=(9.0, 3.0, 0.0)), range_noise=2.0, range_min=0.5)
    r = sim.scan().ranges
    assert r.min() >= 0.5 and r.max() <= 8.0


def test_noise_statistics():
    sim = make(range_noise=0.01)
    d = np.array([sim.scan().ranges[90] for _ in range(400)]) - 6.95
    assert abs(d.mean()) < 0.003 and 0.008 < d.std() < 0.012


def test_same_seed_same_scans_different_seed_differs():
    a, b, c = make(seed=5, range_noise=0.01), make(seed=5, range_noise=0.01), make(
        seed=6, range_noise=0.01)
    for sim in (a, b, c):
        drive(sim, 0.3, 0.2, 1.0)
    sa, sb, sc = a.scan().ranges, b.scan().ranges, c.scan().ranges
    assert np.array_equal(sa, sb) and not np.array_equal(sa, sc)
    assert a.truth_pose() == b.truth_pose()


# ------------------------------------------------------------------------------ motion


def test_straight_drive_distance_and_time():
    sim = make()
    drive(sim, 0.2, 0.0, 1.0)
    x, y, th = sim.truth_pose()
    # one physics step of actuation lag (see SimCore): 0.2 m minus at most one step
    assert 0.2 - 0.2 * DT - 1e-9 <= x - 3.0 <= 0.2 + 1e-9
    assert y == pytest.approx(3.0) and th == pytest.approx(0.0)
    assert sim.time == pytest.approx(1.0)
    assert sim.velocity() == pytest.approx((0.2, 0.0))
    assert sim.path_length == pytest.approx(x - 3.0)
    assert sim.collisions == 0


def test_drive_along_heading():
    sim = make(box_world(pose=(3.0, 2.0, math.pi / 2)))
    drive(sim, 0.5, 0.0, 2.0)
    x, y, _ = sim.truth_pose()
    assert x == pytest.approx(3.0, abs=1e-9) and y == pytest.approx(3.0, abs=0.5 * DT + 1e-9)


def test_rotate_in_place():
    sim = make()
    drive(sim, 0.0, 1.0, 1.0)
    x, y, th = sim.truth_pose()
    assert (x, y) == pytest.approx((3.0, 3.0))
    assert 1.0 - DT - 1e-9 <= th <= 1.0 + 1e-9
    assert sim.path_length == pytest.approx(0.0)
    drive(sim, 0.0, -2.0, 2.0)  # wraps through -pi
    assert -math.pi < sim.truth_pose()[2] <= math.pi


def test_arc_matches_unicycle():
    sim = make()
    drive(sim, 0.5, 0.5, 2.0)
    x, y, th = sim.truth_pose()
    t = 2.0 - DT  # lag
    assert th == pytest.approx(0.5 * t, abs=1e-6)
    assert x == pytest.approx(3.0 + math.sin(0.5 * t) / 0.5 * 0.5, abs=0.01)
    assert y == pytest.approx(3.0 + (1 - math.cos(0.5 * t)) / 0.5 * 0.5, abs=0.01)


def test_commands_are_clipped_and_checked():
    sim = make(v_limit=0.5, w_limit=1.0)
    drive(sim, 5.0, 0.0, 0.2)
    assert sim.velocity()[0] == pytest.approx(0.5)
    drive(sim, 0.0, -9.0, 0.2)
    assert sim.velocity()[1] == pytest.approx(-1.0)
    for bad in ((math.nan, 0.0), (0.0, math.inf), ("a", 0.0)):
        with pytest.raises(SimError):
            sim.command(*bad)


def test_bad_constructor_arguments():
    with pytest.raises(SimError):
        SimCore("paper-room", SimParams(), np.random.default_rng(0))
    with pytest.raises(SimError):
        SimCore(box_world(), SimParams(), 42)


# ------------------------------------------------------------------------------ walls


def test_wall_stops_robot_and_counts_one_collision():
    sim = make(box_world(pose=(8.5, 3.0, 0.0)))
    drive(sim, 1.0, 0.0, 3.0)
    x, _, _ = sim.truth_pose()
    assert 9.95 - 0.2 - 0.01 <= x <= 9.95 - 0.2 + 0.01  # stopped at the wall
    assert sim.collisions == 1 and sim.in_contact
    assert abs(sim.velocity()[0]) < 1e-6
    assert sim.path_length == pytest.approx(x - 8.5, abs=0.02)
    drive(sim, -0.5, 0.0, 1.0)  # back off and hit again: a second collision
    assert not sim.in_contact
    drive(sim, 0.5, 0.0, 2.0)
    assert sim.collisions == 2


def test_no_tunnelling_through_a_thin_leg_at_full_speed():
    w = box_world(pose=(2.0, 3.0, 0.0),
                  extra={"circles": [{"center": [5.0, 3.0], "radius": 0.03}]})
    sim = make(w)
    drive(sim, 1.0, 0.0, 5.0)
    x, y, _ = sim.truth_pose()
    assert x < 5.0 - 0.23 + 0.02 and sim.collisions >= 1


def test_oblique_contact_never_penetrates():
    w = box_world(pose=(8.0, 4.0, 0.4))
    sim = make(w)
    worst = math.inf
    for _ in range(300):
        sim.command(1.0, 0.0)
        sim.step()
        x, y, _ = sim.truth_pose()
        worst = min(worst, clearance(w, x, y))
    assert worst > 0.2 - 0.025  # at most one step (2 cm) of overlap at impact
    assert sim.collisions >= 1


def test_built_in_world_runs():
    sim = SimCore(load_world("paper-room"), SimParams(), np.random.default_rng(1))
    for _ in range(20):
        sim.scan()
        for _ in range(10):
            sim.command(0.4, 0.3)
            sim.step()
    assert sim.path_length > 0.5 and np.isfinite(sim.scan().ranges).all()


# ------------------------------------------------------------------------------ watchdog, odom


def test_watchdog_stops_after_half_a_second():
    sim = make()
    sim.command(0.5, 0.0)
    for _ in range(20):  # 0.4 s: still moving
        sim.step()
    assert sim.velocity()[0] == pytest.approx(0.5) and sim.watchdog_stops == 0
    for _ in range(6):  # 0.52 s: stopped
        sim.step()
    assert sim.velocity() == (0.0, 0.0) and sim.watchdog_stops == 1
    x = sim.truth_pose()[0]
    assert x - 3.0 == pytest.approx(0.25, abs=0.5 * DT + 1e-9)
    for _ in range(100):
        sim.step()
    assert sim.truth_pose()[0] == pytest.approx(x) and sim.watchdog_stops == 1  # one event
    drive(sim, 0.5, 0.0, 1.0)  # commands keep it alive
    assert sim.watchdog_stops == 1 and sim.velocity()[0] == pytest.approx(0.5)
    for _ in range(30):
        sim.step()
    assert sim.watchdog_stops == 2


def test_stale_commands_are_dropped_and_over_limit_ones_clipped():
    """Issue 14: a cmd_vel stamped more than cmd_max_age before the sim clock, or after it (a
    replay, another clock), has no effect; one beyond robot.v_limit / w_limit is clipped."""
    sim = make()
    for _ in range(100):  # 2 s of sim time
        sim.step()
    now = sim.time
    assert not sim.command(0.5, 0.0, now - 1.5) and sim.stale_cmds == 1
    assert not sim.command(0.5, 0.0, now + 0.1) and sim.stale_cmds == 2
    assert not sim.command(0.5, 0.0, 0.0) and sim.stale_cmds == 3
    sim.step()
    assert sim.velocity() == (0.0, 0.0)
    assert sim.command(0.5, 0.0, sim.time - 0.5) and sim.stale_cmds == 3  # fresh enough
    assert sim.clipped_cmds == 0
    assert sim.command(100.0, -50.0, sim.time) and sim.clipped_cmds == 1
    sim.step()
    v, w = sim.velocity()
    assert v == pytest.approx(sim.robot.v_limit) and w == pytest.approx(-sim.robot.w_limit)


def test_a_resumed_sim_goes_on_with_the_same_robot_and_clock():
    sim = make()
    drive(sim, 0.3, 0.2, 2.0)
    ck = sim.checkpoint()
    again = make()
    again.resume(ck)
    assert again.time == sim.time and again.steps == sim.steps
    assert again.truth_pose() == pytest.approx(sim.truth_pose())
    assert again.path_length == sim.path_length and again.collisions == sim.collisions
    assert again.velocity() == (0.0, 0.0)  # at rest until a command comes
    drive(again, 0.3, 0.0, 1.0)
    assert again.path_length > sim.path_length
    bad = dict(ck, sim_world=np.array("elsewhere"))
    with pytest.raises(SimError, match="world"):
        make().resume(bad)
    with pytest.raises(SimError, match="non-finite"):
        make().resume(dict(ck, sim_pose=np.array([np.nan, 0.0, 0.0])))
    with pytest.raises(SimError, match="no 'sim_path'"):
        make().resume({k: v for k, v in ck.items() if k != "sim_path"})


def test_no_watchdog_event_when_idle():
    sim = make()
    for _ in range(100):
        sim.step()
    assert sim.watchdog_stops == 0 and sim.truth_pose() == (3.0, 3.0, 0.0)


def test_odometry_exact_by_default_and_drifts_when_asked():
    sim = make()
    drive(sim, 0.5, 0.3, 2.0)
    assert sim.odom_pose() == sim.truth_pose()
    a = make(odom_drift=0.05, seed=3)
    b = make(odom_drift=0.05, seed=3)
    for s in (a, b):
        drive(s, 0.5, 0.3, 4.0)
    assert a.odom_pose() == b.odom_pose()
    err = math.dist(a.odom_pose()[:2], a.truth_pose()[:2])
    assert 0.0 < err < 0.5


def test_heading_drift_is_its_own_random_walk_per_metre():
    """odom_drift_heading [rad/sqrt(m)] alone: the heading error after d metres has sigma
    odom_drift_heading * sqrt(d), and straight driving gets no translation noise of its own;
    odom_drift alone with odom_drift_heading = 0 leaves the heading exact."""
    errs = []
    for seed in range(60):
        s = make(world=box_world((1.0, 3.0, 0.0)), odom_drift_heading=0.05, seed=seed)
        drive(s, 0.5, 0.0, 4.0)  # 2 m
        errs.append(s.odom_pose().theta - s.truth_pose().theta)
    sigma = float(np.std(errs))
    assert 0.05 * math.sqrt(2.0) * 0.7 < sigma < 0.05 * math.sqrt(2.0) * 1.3
    s = make(world=box_world((1.0, 3.0, 0.0)), odom_drift=0.05, odom_drift_heading=0.0, seed=1)
    drive(s, 0.5, 0.2, 4.0)
    assert s.odom_pose().theta == pytest.approx(s.truth_pose().theta, abs=1e-9)
    assert s.odom_pose()[:2] != pytest.approx(s.truth_pose()[:2], abs=1e-4)


@pytest.mark.parametrize("slip", [0.0, 0.5, 1.0])
def test_wheel_slip_counts_motion_the_body_did_not_make_against_a_wall(slip):
    """Pushing into the wall at 0.4 m/s for 2 s after touching it: the body stays, the
    odometry counts slip x the commanded 0.8 m; free driving before the wall is exact."""
    s = make(world=box_world((9.0, 3.0, 0.0)), odom_slip=slip, seed=0)
    while not s.in_contact:
        s.command(0.4, 0.0)
        s.step()
    assert s.odom_pose()[:2] == pytest.approx(s.truth_pose()[:2], abs=1e-6)
    x0, odo0 = s.truth_pose().x, s.odom_pose().x
    drive(s, 0.4, 0.0, 2.0)
    assert s.in_contact and s.truth_pose().x == pytest.approx(x0, abs=0.02)
    assert s.odom_pose().x - odo0 == pytest.approx(slip * 0.8, abs=0.03)


def test_beam_angles_edge_to_edge_or_evenly_round_a_full_turn():
    from topoexplore.sim.core import beam_angles

    amin, inc = beam_angles(181, math.pi)  # the SICK: -90 .. +90 deg at 1 deg
    assert amin == pytest.approx(-math.pi / 2) and inc == pytest.approx(math.radians(1.0))
    amin, inc = beam_angles(360, 2 * math.pi)  # a 360 deg lidar: no beam twice
    assert amin == pytest.approx(-math.pi) and inc == pytest.approx(math.radians(1.0))


def test_odometry_covariance_follows_the_drift_model():
    """Variance odom_drift^2 x travel in x and y, odom_drift_heading^2 x travel in yaw (the
    Odometry message carries it); zero with perfect odometry; kept across a checkpoint."""
    perfect = make()
    drive(perfect, 0.3, 0.0, 2.0)
    assert perfect.odom_covariance() == [0.0] * 36
    sim = make(odom_drift=0.03, odom_drift_heading=0.02)
    drive(sim, 0.3, 0.0, 2.0)
    cov = sim.odom_covariance()
    travel = cov[0] / 0.03 ** 2
    assert travel == pytest.approx(sim.path_length, rel=0.05)  # straight: travel is the path
    assert cov[7] == cov[0] and cov[35] == pytest.approx(0.02 ** 2 * travel)
    assert sum(1 for v in cov if v) == 3
    again = make(odom_drift=0.03, odom_drift_heading=0.02)
    again.resume(sim.checkpoint())
    assert again.odom_covariance() == cov
    older = {k: v for k, v in sim.checkpoint().items() if k != "sim_odom_travel"}
    again.resume(older)  # a checkpoint written before the covariance: it starts from 0
    assert again.odom_covariance() == [0.0] * 36
