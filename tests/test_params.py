"""Parameters: paper defaults, TOML loading, command-line overrides, one-line errors."""

from __future__ import annotations

import math

import pytest

from topoexplore.common.params import ParamError, load_params


def test_paper_defaults():
    p = load_params()
    assert p.sim.beams == 181 and math.isclose(p.sim.fov, math.pi)
    assert p.mapper.resolution == 0.1
    assert p.reliability.p_init == 0.5 and p.reliability.p_reliable == 0.9
    assert p.reliability.r_near == 0.5 and p.reliability.r_far == 4.5
    assert p.controller.v_max == 0.2
    assert p.planner.strategy == "reliability"


def test_toml_and_overrides(tmp_path):
    f = tmp_path / "p.toml"
    f.write_text("[sim]\nscan_hz = 10.0\n[planner]\nstrategy = 'frontier'\n")
    p = load_params(f, ["sim.seed=7", "controller.v_max=0.3", 'bus.robot="r2"'])
    assert p.sim.scan_hz == 10.0 and p.sim.seed == 7
    assert p.planner.strategy == "frontier" and p.controller.v_max == 0.3
    assert p.bus.robot == "r2"


@pytest.mark.parametrize("content,overrides", [
    ("[sim]\nscan_hz = -1.0\n", []),
    ("[sim]\nbogus = 1\n", []),
    ("[nosuch]\nx = 1\n", []),
    ("[sim\n", []),
    ("", ["planner.strategy=random"]),
    ("", ["sim.beams=fast"]),
    ("", ["noequals"]),
    ("", ["reliability.p_reliable=1.5"]),
    ("", ['bus.namespace="a b"']),
    ("", ['bus.connect="tcp/127.0.0.1:99999"']),
    ("", ['bus.connect="localhost"']),
])
def test_bad_parameters_give_one_line(tmp_path, content, overrides):
    f = tmp_path / "p.toml"
    f.write_text(content)
    with pytest.raises(ParamError) as exc:
        load_params(f, overrides)
    assert "\n" not in str(exc.value)


def test_missing_file():
    with pytest.raises(ParamError, match="not found"):
        load_params("/nonexistent/params.toml")
