"""Parameters: paper defaults, sections, TOML loading, command-line overrides, declared
constraints, one-line errors."""

from __future__ import annotations

import math

import msgspec
import pytest

from topoexplore.common.params import (
    MOVED,
    STRATEGIES,
    ParamError,
    Params,
    load_params,
    validated,
    with_changes,
)


def test_paper_defaults():
    p = load_params()
    assert p.laser.beams == 181 and math.isclose(p.laser.fov, math.pi)
    assert p.robot.radius == 0.2 and p.laser.scan_hz == 5.0
    assert p.mapper.resolution == 0.1
    assert p.reliability.p_init == 0.5 and p.reliability.p_reliable == 0.9
    assert p.reliability.r_near == 0.5 and p.reliability.r_far == 4.5
    assert p.controller.v_max == 0.2
    # the default strategy is the shorter one on the held-back half of the generated corpus
    # (issue 15's rule; docs/robustness.md): frontier since the surfaces rule; the paper's is
    # "reliability"
    assert p.planner.strategy == "frontier" and STRATEGIES == (
        "reliability", "all-end-nodes", "frontier")
    assert p.runtime.lockstep is False and p.mapper.occupancy == (0.35, 0.65)


def test_sections_are_robot_laser_runtime_bus_and_one_per_stage():
    assert list(msgspec.structs.fields(Params)[i].name for i in range(10)) == [
        "robot", "laser", "runtime", "bus", "sim", "mapper", "topology", "reliability",
        "planner", "controller"]
    # what every service shares is set once: no stage section repeats the robot or the laser
    shared = {"radius", "robot_radius", "beams", "fov", "range_max", "laser_offset",
              "lockstep"}
    for section in ("sim", "mapper", "topology", "reliability", "planner", "controller"):
        names = {f.name for f in msgspec.structs.fields(type(getattr(Params(), section)))}
        assert not names & shared, (section, names & shared)
    # one reliability threshold (the planner reads reliability.p_reliable), one p_free
    assert "p_reliable" not in {f.name for f in msgspec.structs.fields(type(Params().planner))}
    assert "p_free" not in {f.name for f in msgspec.structs.fields(type(Params().reliability))}


def test_toml_and_overrides(tmp_path):
    f = tmp_path / "p.toml"
    f.write_text("[laser]\nscan_hz = 10.0\n[planner]\nstrategy = 'frontier'\n")
    p = load_params(f, ["sim.seed=7", "controller.v_max=0.3", 'bus.robot="r2"',
                        "robot.radius=0.25"])
    assert p.laser.scan_hz == 10.0 and p.sim.seed == 7
    assert p.planner.strategy == "frontier" and p.controller.v_max == 0.3
    assert p.bus.robot == "r2" and p.robot.radius == 0.25


@pytest.mark.parametrize("content,overrides", [
    ("[laser]\nscan_hz = -1.0\n", []),
    ("[sim]\nbogus = 1\n", []),
    ("[nosuch]\nx = 1\n", []),
    ("[sim\n", []),
    ("", ["planner.strategy=random"]),
    ("", ["laser.beams=fast"]),
    ("", ["noequals"]),
    ("", ["reliability.p_reliable=1.5"]),
    ("", ["reliability.p_init=0.95"]),  # p_init < p_reliable < p_max
    ("", ['bus.namespace="a b"']),
    ("", ['bus.connect="tcp/127.0.0.1:99999"']),
    ("", ['bus.connect="localhost"']),
    ("", ['bus.connect="tcp/127.0.0.1:0"']),  # port 0 only for a peer's own listener
    ("", ['bus.listen="tcp/127.0.0.1"']),
    ("", ['bus.mode="router"']),
    ("", ["runtime.plan_lag=-1"]),
    ("", ["runtime.plan_lag=9"]),
    ("", ["mapper.initial_size=50.0", "mapper.max_size=40.0"]),
    ("", ["mapper.l_free=0.4"]),
    ("", ["mapper.l_max=nan"]),
    ("", ["mapper.resolution=0.0"]),
    ("", ["mapper.resolution=0.001"]),  # max_size / resolution > 50000 cells
    ("", ["mapper.grow_margin=-1.0"]),
    ("", ["mapper.map_every=true"]),
    ("", ["controller.slow_distance=0.1"]),  # below safety_distance
    ("", ["controller.start_turn=100.0"]),
    ("", ["laser.range_min=9.0"]),
    ("", ["laser.scan_hz=100.0"]),  # faster than sim.physics_hz
    ("", ["sim.seed=-1"]),
    ("", ["planner.clearance_margin=inf"]),
    ("", ["planner.switch_ratio=0.0"]),
    ("", ["topology.skeleton_method=magic"]),
])
def test_bad_parameters_give_one_line(tmp_path, content, overrides):
    f = tmp_path / "p.toml"
    f.write_text(content)
    with pytest.raises(ParamError) as exc:
        load_params(f, overrides)
    assert "\n" not in str(exc.value)


@pytest.mark.parametrize("old", sorted(MOVED))
def test_a_moved_parameter_names_its_new_place(old):
    section, name = old.split(".")
    with pytest.raises(ParamError, match=MOVED[old].replace(".", r"\.")):
        load_params(None, [f"{old}=1"])


def test_missing_file():
    with pytest.raises(ParamError, match="not found"):
        load_params("/nonexistent/params.toml")


def test_structs_built_in_code_are_checked_by_validated_and_with_changes():
    p = Params()
    assert validated(p) == p
    q = with_changes(p, "planner", strategy="reliability")
    assert q.planner.strategy == "reliability" and p.planner.strategy == "frontier"
    with pytest.raises(ParamError):
        with_changes(p, "planner", clearance_margin=-1.0)
    with pytest.raises(ParamError):
        with_changes(p, "controller", slow_distance=0.1)


def test_strategy_variants_are_strategies_with_parameters():
    from topoexplore.common.params import STRATEGIES, STRATEGY_NAMES, VARIANTS, strategy_overrides

    assert STRATEGY_NAMES[:len(STRATEGIES)] == STRATEGIES
    assert strategy_overrides("frontier") == ['planner.strategy="frontier"']
    p = load_params(None, strategy_overrides("reliability-paper"))
    assert p.planner.strategy == VARIANTS["reliability-paper"][0] == "reliability"
    r = p.reliability
    assert (r.view_distance, r.frontier_radius, r.frontier_group, r.examined_radius,
            r.recall_radius) == (0.0, 0.0, 0.0, 0.0, 0.0)
    assert not p.planner.frontier_completion and not p.planner.stop_when_mapped
    assert p.planner.surface_views == r.surface_views == 0  # the paper's map, as it is
    # the user's own overrides come after, and win
    p = load_params(None, [*strategy_overrides("reliability-paper"),
                           "reliability.view_distance=0.1"])
    assert p.reliability.view_distance == 0.1
    with pytest.raises(ParamError, match="unknown strategy 'greedy'"):
        strategy_overrides("greedy")


def test_params_to_dict_and_back_is_the_same_parameters():
    from topoexplore.common.params import ParamError, params_from_dict, params_to_dict

    p = load_params(None, ["laser.model=\"lidar-360\"", "localizer.sigma=0.07",
                           "planner.strategy=\"frontier\""])
    d = params_to_dict(p)
    assert params_from_dict(d) == p
    again = params_from_dict(d, ["localizer.sigma=0.05"])
    assert again.localizer.sigma == 0.05 and again.laser == p.laser
    with pytest.raises(ParamError):
        params_from_dict(d, ["localizer.sigma=-1"])
    with pytest.raises(ParamError):
        params_from_dict([1, 2])
