"""The package: layers checked by import-linter, every import declared, a wheel that works
outside the checkout, and no long functions."""

from __future__ import annotations

import ast
import importlib.metadata as md
import os
import re
import signal
import subprocess
import sys
import time
import tomllib
from pathlib import Path

import pytest

from tests.conftest import REPO, free_port

PYPROJECT = tomllib.loads((REPO / "pyproject.toml").read_text())
FOLDERS = {"common": "topoexplore.common", "services": "topoexplore.services",
           "sim": "topoexplore.sim", "tools": "topoexplore.tools"}
MAX_FUNCTION_LINES = 80  # the "about 80"; most are far shorter


def sources() -> list[Path]:
    return sorted(p for folder in FOLDERS for p in (REPO / folder).rglob("*.py"))


def test_layers_hold():
    """tools -> services | sim -> common; services independent; zenoh only in common.bus;
    cores pure (pyproject.toml [tool.importlinter])."""
    exe = Path(sys.executable).parent / "lint-imports"
    r = subprocess.run([str(exe), "--no-cache"], cwd=REPO, capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-2000:]
    assert "broken" in r.stdout and " 0 broken" in r.stdout


def test_every_package_folder_is_in_the_wheel():
    listed = set(PYPROJECT["tool"]["setuptools"]["packages"])
    found = {"topoexplore.deploy"}
    for folder, pkg in FOLDERS.items():
        for init in (REPO / folder).rglob("__init__.py"):
            rel = init.parent.relative_to(REPO / folder)
            found.add(".".join([pkg, *rel.parts]))
    assert found == listed


def _imports(path: Path) -> list[tuple[str, bool]]:
    """(top-level module name, imported at module level) of every import in a file."""
    tree = ast.parse(path.read_text())
    top = {id(n) for n in tree.body}
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(a.name.split(".")[0], id(node) in top) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            out.append((node.module.split(".")[0], id(node) in top))
    return out


def _requirements(reqs: list[str]) -> set[str]:
    names = set()
    for r in reqs:
        name = re.split(r"[\s\[<>=!~;]", r, maxsplit=1)[0]
        if name != "topoexplore":
            names.add(md.metadata(name)["Name"].lower())
    return names


def test_every_imported_package_is_declared():
    """Third-party imports of the package are declared: a service module's top-level imports
    in the core dependencies (a robot installs only those), everything else in an extra."""
    core = _requirements(PYPROJECT["project"]["dependencies"])
    extras = set().union(*(_requirements(v) for k, v in
                           PYPROJECT["project"]["optional-dependencies"].items() if k != "test"))
    dists = md.packages_distributions()
    problems = []
    for path in sources():
        rel = path.relative_to(REPO)
        for name, toplevel in _imports(path):
            if name in sys.stdlib_module_names or name in ("topoexplore", "__future__"):
                continue
            owners = {d.lower() for d in dists.get(name, [])}
            if not owners:
                problems.append(f"{rel}: {name} is not installed")
            elif toplevel and rel.parts[0] in ("common", "services") and not owners & core:
                problems.append(f"{rel}: {name} ({', '.join(owners)}) is not a core dependency")
            elif not owners & (core | extras):
                problems.append(f"{rel}: {name} ({', '.join(owners)}) is not declared")
    assert not problems, "\n".join(problems)


def test_no_function_is_long():
    long = []
    for path in sources():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                n = node.end_lineno - node.lineno + 1
                if n > MAX_FUNCTION_LINES:
                    long.append(f"{path.relative_to(REPO)}:{node.lineno} {node.name} ({n} lines)")
    assert not long, "\n".join(long)


# --- the wheel, installed outside the checkout ------------------------------------------------


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> dict:
    """The package built as a wheel and installed into a fresh virtualenv. Its dependencies
    come from this environment (a .pth line, so no package index is needed); nothing of the
    checkout is on its path, and it runs from a directory outside the checkout."""
    d = tmp_path_factory.mktemp("wheel")
    r = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--quiet", "-w",
                        str(d / "dist"), str(REPO)], capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr[-3000:]
    (wheel,) = (d / "dist").glob("topoexplore-*.whl")
    venv = d / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=300)
    py, exe = venv / "bin" / "python", venv / "bin" / "topoexplore"
    r = subprocess.run([str(py), "-m", "pip", "install", "--no-deps", "--no-index", "--quiet",
                        str(wheel)], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    site = subprocess.run([str(py), "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"],
                          capture_output=True, text=True, check=True).stdout.strip()
    outer = [p for p in sys.path if p.endswith("site-packages")]
    Path(site, "outer-deps.pth").write_text("\n".join(outer) + "\n")
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    env["PATH"] = f"{venv / 'bin'}{os.pathsep}{env.get('PATH', '')}"
    cwd = d / "work"
    cwd.mkdir()
    return {"py": str(py), "exe": str(exe), "env": env, "cwd": cwd, "site": site,
            "wheel": wheel}


def test_wheel_holds_the_package_data(installed):
    import zipfile

    names = zipfile.ZipFile(installed["wheel"]).namelist()
    for must in ("topoexplore/deploy/profiles/sim.toml", "topoexplore/deploy/profiles/robot.toml",
                 "topoexplore/sim/worlds/paper-room.toml", "topoexplore/sim/worlds/small_house.pgm",
                 "topoexplore/common/bus.py", "topoexplore/tools/cli.py"):
        assert must in names, must
    assert not any(n.startswith(("common/", "services/", "sim/", "tools/")) for n in names)
    r = subprocess.run([installed["py"], "-c", "import topoexplore.common.bus as b; "
                        "print(b.__file__)"], cwd=installed["cwd"], env=installed["env"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and r.stdout.startswith(installed["site"]), r.stdout + r.stderr


def test_wheel_runs_an_exploration(installed):
    out = installed["cwd"] / "run-corner"
    r = subprocess.run([installed["exe"], "run", "--world", "corner", "--lockstep", "--quiet",
                        "--max-sim-time", "120", "--connect", f"tcp/127.0.0.1:{free_port()}",
                        "--out", str(out)], cwd=installed["cwd"], env=installed["env"],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    assert (out / "report.json").stat().st_size > 0 and (out / "final.png").stat().st_size > 0


def test_wheel_brings_up_a_launch_profile(installed):
    ep = f"tcp/127.0.0.1:{free_port()}"
    up = subprocess.Popen([installed["exe"], "up", "--profile", "sim-only", "--connect", ep,
                           "--namespace", "wheeltest"], cwd=installed["cwd"],
                          env=installed["env"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                          text=True, start_new_session=True)
    try:
        deadline = time.monotonic() + 120
        while True:
            r = subprocess.run([installed["exe"], "keys", "get", "sim", "--connect", ep,
                                "--namespace", "wheeltest", "--field", "world", "--timeout", "1"],
                               cwd=installed["cwd"], env=installed["env"], capture_output=True,
                               text=True, timeout=60)
            if r.returncode == 0 and "paper-room" in r.stdout:
                break
            assert up.poll() is None, up.stdout.read()
            assert time.monotonic() < deadline, r.stderr
            time.sleep(0.5)
    finally:
        if up.poll() is None:
            os.killpg(up.pid, signal.SIGINT)
        try:
            up.wait(timeout=30)
        except subprocess.TimeoutExpired:
            os.killpg(up.pid, signal.SIGKILL)
            up.wait(timeout=10)
        up.stdout.close()
    assert up.returncode == 0


def test_systemd_units_start_what_exists():
    """The unit templates name importable modules and real subcommands: each robot-profile
    service for ``topoexplore@.service``, and ``topoexplore warmup`` / ``router`` / ``up``."""
    import importlib.util

    from topoexplore.tools.cli import FORWARD, build_parser
    from topoexplore.tools.launch.core import load_profile
    from topoexplore.tools.launch.supervisor import profile_path

    names = [s.name for s in load_profile(profile_path("robot")).processes]
    subcommands = set(FORWARD) | set(build_parser()._subparsers._group_actions[0].choices)
    for unit in sorted((REPO / "deploy" / "systemd").glob("*.service")):
        for line in unit.read_text().splitlines():
            if not line.startswith(("ExecStart=", "ExecStartPre=")):
                continue
            argv = line.split("=", 1)[1].split()
            if "-m" in argv:
                module = argv[argv.index("-m") + 1]
                for name in names if "%i" in module else [""]:
                    mod = module.replace("%i", name)
                    # the installed package, not a folder that happens to be the cwd
                    assert mod.startswith("topoexplore."), (unit.name, mod)
                    assert importlib.util.find_spec(mod) is not None, (unit.name, mod)
            else:
                assert argv[0].endswith("/topoexplore"), (unit.name, line)
                assert argv[1] in subcommands, (unit.name, line)
