"""Kernel warm-up (common/warm.py, tools/warm.py): every kernel a run needs is listed, compiled
once, counted right; ``topoexplore warmup`` and the supervisor's warm-up step."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
import types

import pytest
from numba.core.registry import CPUDispatcher

from tests.conftest import REPO
from topoexplore.common.warm import WarmError, compile_kernels, kernel_table
from topoexplore.tools.warm import clear_cache, core_of, profile_cores, warm_modules

SIM_CORES = ["topoexplore.services.mapper.core", "topoexplore.services.topology.core",
             "topoexplore.services.reliability.core", "topoexplore.services.planner.core",
             "topoexplore.services.controller.core", "topoexplore.sim.core",
             "topoexplore.services.localizer.core"]


TOOL_KERNELS = ["topoexplore.sim.rays"]  # the truth masks of run and bench (not the sim's)


def _all_kernel_modules() -> list[str]:
    return list(dict.fromkeys([*(m for c in SIM_CORES for m in warm_modules(c)),
                               *TOOL_KERNELS]))


def _signatures() -> dict[str, set[str]]:
    """Compiled signatures of every numba kernel of the package loaded in this process."""
    out: dict[str, set[str]] = {}
    for name, mod in list(sys.modules.items()):
        if not name.startswith("topoexplore.") or mod is None:
            continue
        for k, v in vars(mod).items():
            if isinstance(v, CPUDispatcher) and v.__module__ == name:
                out[f"{name}.{k}"] = {str(s) for s in v.signatures}
    return out


def test_the_sim_profile_maps_to_every_core():
    cores = dict(profile_cores("sim"))
    assert sorted(cores.values()) == sorted(SIM_CORES)
    assert core_of("topoexplore.services.topology.service") == "topoexplore.services.topology.core"
    assert core_of("no_such_package.service") is None and core_of("") is None


def test_every_listed_kernel_is_a_kernel_with_valid_signatures():
    mods = _all_kernel_modules()
    assert "topoexplore.services.topology.graph" in mods
    for mname in mods:
        table = kernel_table(mname)
        assert table, mname
        for name, disp, sigs in table:
            assert isinstance(disp, CPUDispatcher), (mname, name)
            assert all(s.startswith("(") for s in sigs), (mname, name)


def test_an_exploration_compiles_nothing_beyond_the_lists():
    """After the warm-up, runs of every strategy (including a SLAM-like map world) add no
    signature to any kernel: what a service compiles before it is up is all it needs."""
    from topoexplore.tools.bench import inproc

    compile_kernels(_all_kernel_modules())
    before = _signatures()
    for world, strategy, limit, sets in [
            ("paper-room", "reliability", 60.0, ()),
            ("junction", "frontier", 40.0, ()),
            ("small-house", "all-end-nodes", 20.0, ()),
            ("dead-end", "reliability", 30.0, ("reliability.frontier_group=0.5",))]:
        inproc.run(world, strategy=strategy, max_sim_time=limit, sets=sets)
    after = _signatures()
    new = {k: v - before.get(k, set()) for k, v in after.items() if v - before.get(k, set())}
    assert not new, f"compiled during the run, missing from a WARM list: {new}"


def test_a_second_warm_up_in_the_same_process_costs_nothing():
    mods = _all_kernel_modules()
    compile_kernels(mods)
    res = compile_kernels(mods)
    assert res.compiled == 0 and res.loaded == 0
    assert res.present == sum(len(s) for m in mods for _, _, s in kernel_table(m))
    assert "loaded from the cache" in res.line()
    assert compile_kernels([]).line() == "no numba kernels"


def _fake_module(name: str, **attrs) -> types.ModuleType:
    mod = types.ModuleType(name)
    mod.__dict__.update(attrs)
    sys.modules[name] = mod
    return mod


@pytest.mark.parametrize("attrs, text", [
    ({}, "no WARM dict"),
    ({"WARM": {"f": ("(int64,)",)}, "f": 3}, "not a numba kernel"),
    ({"WARM": {"g": ("(int64,)",)}}, "not a numba kernel"),
    ({"WARM": {"f": "(int64,)"}, "f": None}, "not a numba kernel"),
])
def test_a_bad_warm_list_is_named(attrs, text):
    name = "topoexplore_test_fake_warm"
    _fake_module(name, **attrs)
    try:
        with pytest.raises(WarmError, match=text):
            compile_kernels([name])
    finally:
        sys.modules.pop(name, None)


KERNEL_SRC = textwrap.dedent("""
    from numba import njit

    @njit(cache=True)
    def twice(a):
        return 2 * a

    WARM = {"twice": ("(int64,)", "(float64,)")}
""")


def _warm_in_new_process(tmp_path) -> dict:
    code = ("import json, sys; sys.path.insert(0, sys.argv[1]); "
            "from topoexplore.common.warm import compile_kernels; "
            "r = compile_kernels(['warmkernels']); "
            "print(json.dumps({'loaded': r.loaded, 'compiled': r.compiled, 'line': r.line()}))")
    r = subprocess.run([sys.executable, "-c", code, str(tmp_path)], capture_output=True,
                       text=True, timeout=120, cwd=REPO, env=dict(os.environ))
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout)


def test_compiled_once_then_loaded_from_the_disk_cache_then_cleared(tmp_path):
    (tmp_path / "warmkernels.py").write_text(KERNEL_SRC)
    first = _warm_in_new_process(tmp_path)
    assert (first["compiled"], first["loaded"]) == (2, 0), first
    assert "compiled" in first["line"] and str(tmp_path) in first["line"]
    second = _warm_in_new_process(tmp_path)
    assert (second["compiled"], second["loaded"]) == (0, 2), second
    sys.path.insert(0, str(tmp_path))
    try:
        assert clear_cache(["warmkernels"], package=False) >= 2
    finally:
        sys.path.remove(str(tmp_path))
        sys.modules.pop("warmkernels", None)
    assert not list((tmp_path / "__pycache__").glob("warmkernels.*.nb*"))
    third = _warm_in_new_process(tmp_path)
    assert (third["compiled"], third["loaded"]) == (2, 0), third


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "topoexplore.tools.cli", *args], cwd=REPO,
                          capture_output=True, text=True, timeout=300, env=dict(os.environ))


def test_warmup_command_reports_every_core():
    r = _cli("warmup", "--profile", "sim", "--jobs", "2")
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    for name in ("topology", "planner"):
        assert any(ln.startswith(f"[warmup] {name}: ") for ln in lines), r.stdout
    for name in ("mapper", "controller", "sim", "reliability"):  # no kernels
        assert not any(ln.startswith(f"[warmup] {name}:") for ln in lines), r.stdout
    assert lines[-1].startswith("[warmup] ") and " in " in lines[-1]


@pytest.mark.parametrize("args", [["--profile", "/nonexistent.toml"], ["--jobs", "0"],
                                  ["--cores", "nonsense"], ["--bogus"]])
def test_warmup_bad_arguments_one_line(args):
    r = _cli("warmup", *args)
    assert r.returncode == 2
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "Traceback" not in r.stderr, r.stderr


def test_the_stamp_holds_while_nothing_changes(tmp_path, monkeypatch):
    from topoexplore.common.warm import WarmResult
    from topoexplore.tools import warm

    stamp = tmp_path / "cache" / "warmup-stamp.json"
    monkeypatch.setattr(warm, "stamp_paths", lambda: [tmp_path / "ro" / "x" / "s.json", stamp])
    (tmp_path / "ro").write_text("a file, so no folder can be made under it")
    src, nbi = tmp_path / "k.py", tmp_path / "k.f-1.py311.nbi"
    src.write_text("kernel source")
    nbi.write_text("index")
    cores = [("topology", "topoexplore.services.topology.core")]
    results = {"topology": WarmResult(loaded=1, files=[str(src), str(nbi)])}
    assert warm.write_stamp(cores, results) == stamp
    assert warm.stamp_valid(cores) and warm.stamp_valid([])
    assert not warm.stamp_valid([*cores, ("planner", "topoexplore.services.planner.core")])
    env = warm._environment()
    monkeypatch.setattr(warm, "_environment", lambda: {**env, "numba": "0.0"})
    assert not warm.stamp_valid(cores)  # another numba: its cache does not hold
    monkeypatch.setattr(warm, "_environment", lambda: env)
    nbi.write_text("index, rewritten by numba for a new signature")
    assert not warm.stamp_valid(cores)
    warm.write_stamp(cores, results)
    assert warm.stamp_valid(cores)
    nbi.unlink()  # someone deleted __pycache__
    assert not warm.stamp_valid(cores)
    warm.write_stamp(cores, {"topology": WarmResult(loaded=1, files=[str(src)])})
    stamp.write_text("{not json")
    assert not warm.stamp_valid(cores)
    warm.remove_stamp()
    assert not stamp.exists()


def test_a_service_loads_only_the_kernels_its_core_runs():
    assert warm_modules("topoexplore.services.reliability.core") == ()  # whatever its params
    assert warm_modules("topoexplore.sim.core") == ()  # the truth masks are the tools' job
    assert warm_modules("topoexplore.services.planner.core") == (
        "topoexplore.services.planner.gridsearch",)


def test_services_that_run_no_kernel_do_not_import_numba():
    """numba alone costs a process about 60 MB resident: the simulator, the controller and
    reliability do without it, reliability also when its frontier-group test runs."""
    code = ("import sys; import topoexplore.sim.service, topoexplore.services.controller.service,"
            " topoexplore.services.reliability.service; "
            "import numpy as np; from topoexplore.services.reliability.core import frontier_cells;"
            " g = np.full((40, 40), -1, np.int8); g[5:30, 5:30] = 0;"
            " assert len(frontier_cells(g, 0.35, 4)) > 0; "
            "print(sorted(m for m in ('numba', 'llvmlite') if m in sys.modules))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       timeout=120, cwd=REPO, env=dict(os.environ))
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "[]", r.stdout
