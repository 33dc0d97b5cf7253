"""Launch profiles and the restart policy (pure)."""

from __future__ import annotations

from pathlib import Path

import pytest

from topoexplore.tools.launch.core import (
    ProcSpec,
    ProcState,
    ProfileError,
    RestartPolicy,
    load_profile,
    parse_profile,
)

PROFILES = Path(__file__).resolve().parents[1] / "deploy" / "profiles"


def test_shipped_profiles_load():
    names = {p.stem for p in PROFILES.glob("*.toml")}
    assert {"sim", "robot", "sim-only", "mapping"} <= names
    sim = load_profile(PROFILES / "sim.toml")
    assert [p.name for p in sim.processes] == [
        "mapper", "topology", "reliability", "planner", "controller", "sim", "localizer"]
    robot = load_profile(PROFILES / "robot.toml")
    assert "sim" not in [p.name for p in robot.processes]


def test_a_process_under_a_parameter_runs_only_when_it_is_true():
    from topoexplore.common.params import load_params
    from topoexplore.tools.launch.core import select

    sim = load_profile(PROFILES / "sim.toml")
    off = [p.name for p in select(sim, load_params()).processes]
    on = [p.name for p in select(sim, load_params(None, ["localizer.enabled=true"])).processes]
    assert "localizer" not in off and on == off + ["localizer"]
    bad = parse_profile({"process": [{"name": "a", "module": "x", "when": "laser.beams"}]})
    with pytest.raises(ProfileError):
        select(bad, load_params())  # not a true/false parameter


@pytest.mark.parametrize("data", [
    {},
    {"process": [{"name": "a"}]},
    {"process": [{"name": "a", "module": "x", "cmd": ["y"]}]},
    {"process": [{"name": "a", "module": "x"}, {"name": "a", "module": "y"}]},
    {"process": [{"name": "a b", "module": "x"}]},
    {"process": [{"name": "a", "module": "x", "ready_timeout": -1}]},
    {"process": [{"name": "a", "module": "x", "bogus": 1}]},
    {"router": "yes", "process": [{"name": "a", "module": "x"}]},
    {"process": [{"name": "a", "module": "x", "when": "enabled"}]},
])
def test_bad_profiles(data):
    with pytest.raises(ProfileError):
        parse_profile(data)


def test_backoff_grows_and_caps():
    pol = RestartPolicy(base=0.5, cap=4.0)
    assert [pol.delay(n) for n in range(5)] == [0.5, 1.0, 2.0, 4.0, 4.0]


def test_restart_decisions():
    pol = RestartPolicy(base=1.0, cap=8.0, stable_after=30.0, max_restarts=3)
    st = ProcState(spec=ProcSpec(name="a", module="x"))
    st.on_start(0.0, 100)
    st.on_exit(1.0, -9, pol, stopping=False)
    assert st.restarts == 1 and st.next_start == 2.0
    st.on_start(2.0, 101)
    st.on_exit(3.0, 1, pol, stopping=False)
    assert st.restarts == 2 and st.next_start == 5.0  # backoff doubled
    st.on_start(5.0, 102)
    st.on_exit(100.0, 1, pol, stopping=False)  # ran long: backoff resets
    assert st.next_start == 101.0
    st.on_start(101.0, 103)
    text = st.on_exit(102.0, 1, pol, stopping=False)
    assert st.given_up and st.next_start is None and "gave up" in text


def test_no_restart_when_stopping_or_disabled():
    pol = RestartPolicy()
    st = ProcState(spec=ProcSpec(name="a", module="x"))
    st.on_start(0.0, 1)
    st.on_exit(1.0, 0, pol, stopping=True)
    assert st.next_start is None and st.restarts == 0
    st2 = ProcState(spec=ProcSpec(name="b", cmd=("true",), restart=False))
    st2.on_start(0.0, 2)
    st2.on_exit(1.0, 0, pol, stopping=False)
    assert st2.next_start is None


def test_process_memory_and_cpu_from_proc():
    import os

    from topoexplore.tools.launch.supervisor import proc_cpu, proc_memory

    mem, cpu = proc_memory(os.getpid()), proc_cpu(os.getpid())
    assert mem is not None and 0 < mem["rss_mb"] <= mem["peak_mb"]
    # the proportional and private shares (Linux >= 4.14) are parts of the resident set
    assert 0 < mem["private_mb"] <= mem["pss_mb"] <= mem["rss_mb"] + 0.1
    assert 0 <= mem["shmem_mb"] <= mem["rss_mb"]
    assert cpu is not None and cpu["user_s"] > 0 and cpu["sys_s"] >= 0
    assert proc_memory(2**22 + 12345) is None and proc_cpu(2**22 + 12345) is None


def test_exit_2_before_up_is_not_restarted_other_exits_are():
    spec = ProcSpec(name="mapper", module="topoexplore.services.mapper.service")
    policy = RestartPolicy()
    st = ProcState(spec=spec)
    st.on_start(0.0, 100)
    assert "not restarted" in st.on_exit(0.5, 2, policy, stopping=False)
    assert st.given_up and st.next_start is None and st.restarts == 0
    for code, was_up in ((1, False), (2, True), (-9, True)):
        st = ProcState(spec=spec)
        st.on_start(0.0, 100)
        st.was_up = was_up
        assert "restart #1" in st.on_exit(5.0, code, policy, stopping=False)
        assert not st.given_up and st.next_start is not None
    st.on_start(6.0, 101)
    assert not st.was_up  # a new start is judged on its own
    cmd = ProcState(spec=ProcSpec(name="laser", cmd=("/bin/false",), liveliness=False))
    cmd.on_start(0.0, 7)
    assert "restart #1" in cmd.on_exit(0.1, 2, policy, stopping=False)  # foreign: its codes


def test_module_command_passes_the_log_level_and_lines_are_stamped():
    import re

    from topoexplore.common.keys import Keys
    from topoexplore.tools.launch.core import ProcSpec, parse_profile
    from topoexplore.tools.launch.supervisor import Supervisor, stamped

    prof = parse_profile({"name": "p", "description": "", "router": False,
                          "process": [{"name": "mapper",
                                       "module": "topoexplore.services.mapper.service"}]})
    spec = ProcSpec(name="mapper", module="topoexplore.services.mapper.service")
    sup = Supervisor(prof, Keys(), "tcp/127.0.0.1:1", log_level="DEBUG", warm=False)
    cmd = sup.command(spec)
    assert cmd[cmd.index("--log-level") + 1] == "DEBUG"
    assert "--log-level" not in Supervisor(prof, Keys(), "tcp/127.0.0.1:1").command(spec)
    assert re.fullmatch(r"\[supervisor\] \d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3} mapper is up",
                        stamped("[supervisor] mapper is up"))
    assert stamped("[mapper] x") == "[mapper] x"
