"""The `topoexplore` command: one-line errors, worlds listing, map save and render against a
running stack, render of a saved run directory."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import numpy as np
import pytest

from tests.conftest import REPO
from topoexplore.common.bus import Bus
from topoexplore.common.grid import classify
from topoexplore.common.keys import Keys
from topoexplore.common.mapio import read_map_server


def cli(*args: str, timeout: float = 120, env: dict | None = None
        ) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "topoexplore.tools.cli", *args], cwd=REPO,
                          capture_output=True, text=True, timeout=timeout,
                          env=env or dict(os.environ))


def one_line_error(r: subprocess.CompletedProcess) -> None:
    assert r.returncode != 0
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, r.stderr
    assert "Traceback" not in r.stderr


@pytest.mark.parametrize("args", [
    ["run", "--world", "corner", "--lockstep"],
    ["up", "--profile", "sim-only"],
])
def test_commands_that_need_the_simulator_say_which_extra(tmp_path, args):
    """A robot installs the core only: without the 'sim' extra, one line names it."""
    stub = tmp_path / "pymunk"
    stub.mkdir()
    (stub / "__init__.py").write_text("raise ImportError('pymunk is not installed here')\n")
    env = dict(os.environ, PYTHONPATH=str(tmp_path))
    r = cli(*args, env=env)
    one_line_error(r)
    assert "pip install 'topoexplore[sim]'" in r.stderr


def test_worlds_lists_builtins():
    r = cli("worlds")
    assert r.returncode == 0
    names = [ln.split()[0] for ln in r.stdout.splitlines()]
    for w in ("paper-room", "dead-end", "junction", "corner", "office", "maze"):
        assert w in names


def test_worlds_check_summarizes_a_map_world():
    r = cli("worlds", "--check", str(REPO.parent / "shared" / "maps" / "small_house.yaml"))
    if not (REPO.parent / "shared").exists():
        pytest.skip("../shared not present")
    assert r.returncode == 0 and "wall segments" in r.stdout


@pytest.mark.parametrize("content", [
    "name = 'x'\nsize = [-1, 5]\n",
    "name = 'x'\nsize = [5, 5]\n[robot]\npose = [50, 50, 0]\n",
    "name = 'x'\nsize = [5, 5]\n[[walls]]\npoints = 'no'\n",
    "this is not toml",
    "name = 'x'\nmap = 'missing.yaml'\n",
])
def test_bad_world_file_one_line(tmp_path, content):
    f = tmp_path / "w.toml"
    f.write_text(content)
    one_line_error(cli("worlds", "--check", str(f)))
    one_line_error(cli("run", "--world", str(f), "--lockstep", "--out", str(tmp_path / "o")))


@pytest.mark.parametrize("args", [
    ["run", "--world", "no-such-world"],
    ["run", "--set", "planner.strategy=random"],
    ["run", "--set", "laser.scan_hz=-5"],
    ["run", "--params", "/nonexistent.toml"],
    ["run", "--speed", "0"],
    ["up", "--profile", "/nonexistent.toml"],
    ["up", "--world", "/nonexistent.toml"],
    ["up", "--zenoh-config", "/nonexistent.json5"],
    ["run", "--world", "corner", "--zenoh-config", "/nonexistent.json5"],
    ["run", "--world", "corner", "--zenoh-config", "README.md"],
    ["bench", "stages", "--sizes", "abc"],
    ["bench", "inproc", "--worlds", "no-such-world"],
    ["bench", "inproc", "--set", "planner.clearance_margin=-1"],
    ["bench", "inproc", "--set", "sim.seed=3"],
    ["bench", "inproc", "--strategies", "random"],
    ["bench", "codec", "--repeats", "0"],
    ["bench", "posetrace", "/nonexistent.npz"],
    ["bench", "posetrace", "README.md"],
    ["bench", "codec", "--repeats", "many"],
    ["map", "save", "/tmp/x.yaml", "--connect", "tcp/127.0.0.1:1", "--timeout", "0.5"],
])
def test_bad_arguments_one_line(args, tmp_path):
    one_line_error(cli(*args))


def test_map_save_and_render_live_then_saved_dir(procs, endpoint, namespace, tmp_path):
    procs.python("-m", "topoexplore.tools.cli", "up", "--profile", "mapping", "--connect", endpoint,
                 "--namespace", namespace)
    keys = Keys(namespace, "robot1")
    with Bus.client(endpoint, wait_for_router=True) as bus:
        deadline = time.monotonic() + 60
        while keys.alive("topology") not in bus.alive(keys.alive_all()) \
                or keys.alive("sim") not in bus.alive(keys.alive_all()):
            assert time.monotonic() < deadline
            time.sleep(0.1)
    time.sleep(2.0)  # a few scans
    common = ["--connect", endpoint, "--namespace", namespace]
    r = cli("map", "save", str(tmp_path / "live" / "map.yaml"), *common)
    assert r.returncode == 0, r.stderr
    grid, geom = read_map_server(tmp_path / "live" / "map.yaml")
    cls = classify(grid)
    assert (cls == 1).sum() > 100 and (cls == 2).sum() > 10  # free and occupied seen
    assert geom.resolution == pytest.approx(0.1)
    r = cli("render", "--live", "-o", str(tmp_path / "live.png"), *common)
    assert r.returncode == 0, r.stderr
    assert "robot at (" in r.stdout  # drawn from its odometry (issue 13: it was left out)
    assert (tmp_path / "live.png").stat().st_size > 1000
    # a saved directory with only map files renders too
    r = cli("render", str(tmp_path / "live"))
    assert r.returncode == 0, r.stderr
    import cv2

    img = cv2.imread(str(tmp_path / "live" / "render.png"))
    assert img is not None and img.shape[2] == 3 and np.any(img != img[0, 0])


def test_render_bad_directory(tmp_path):
    one_line_error(cli("render", str(tmp_path)))
    one_line_error(cli("render"))


def test_run_takes_a_strategy_variant_and_the_user_overrides_win():
    import argparse

    from topoexplore.common.params import load_params
    from topoexplore.tools.run import add_arguments, run_overrides

    p = argparse.ArgumentParser()
    add_arguments(p)
    args = p.parse_args(["--strategy", "reliability-paper", "--connect", "tcp/127.0.0.1:7447",
                         "--set", "reliability.view_distance=0.1"])
    params = load_params(None, run_overrides(args))
    assert params.planner.strategy == "reliability" and not params.planner.frontier_completion
    assert params.reliability.examined_radius == 0.0 and params.reliability.view_distance == 0.1


def test_run_links_its_services_as_peers_unless_told_or_secured(tmp_path, monkeypatch):
    """bus.mode auto: `run` (its own router on this host) makes the services peers; a
    params file or --set that names a mode wins, and credentials keep them clients (a peer's
    own endpoint would not ask for them)."""
    import argparse

    from topoexplore.common.bus import CREDENTIALS_ENV
    from topoexplore.common.params import load_params
    from topoexplore.tools.run import add_arguments, run_overrides

    monkeypatch.delenv(CREDENTIALS_ENV, raising=False)
    ap = argparse.ArgumentParser()
    add_arguments(ap)
    f = tmp_path / "p.toml"
    f.write_text('[bus]\nmode = "client"\n')

    def mode(*argv: str) -> str:
        args = ap.parse_args(["--connect", "tcp/127.0.0.1:7447", *argv])
        return load_params(getattr(args, "params", None), run_overrides(args)).bus.mode

    assert load_params(None, []).bus.mode == "auto"
    assert mode() == "peer"
    assert mode("--set", 'bus.mode="client"') == "client"
    assert mode("--params", str(f)) == "client"
    monkeypatch.setenv(CREDENTIALS_ENV, str(tmp_path / "creds"))
    assert mode() == "auto"  # a Node opens auto as a client


def test_run_takes_world_seed_speed_and_strategy_from_the_params_file(tmp_path):
    """[sim] world/seed/speed and [planner] strategy of --params count unless the command
    line names them (they used to be overridden silently by the command line's defaults)."""
    import argparse

    from topoexplore.tools import run as runner

    ap = argparse.ArgumentParser()
    runner.add_arguments(ap)
    f = tmp_path / "p.toml"
    f.write_text('[sim]\nworld = "junction"\nseed = 3\nspeed = 2.0\n'
                 '[planner]\nstrategy = "all-end-nodes"\n')
    args = ap.parse_args(["--params", str(f)])
    runner._fill_from_params(args)
    assert (args.world, args.seed, args.speed) == ("junction", 3, 2.0)
    assert args.strategy == "all-end-nodes"
    assert 'sim.world="junction"' in runner.run_overrides(args)
    assert 'planner.strategy="all-end-nodes"' in runner.run_overrides(args)
    args = ap.parse_args(["--params", str(f), "--world", "maze", "--seed", "1",
                          "--strategy", "reliability-paper"])
    runner._fill_from_params(args)
    assert (args.world, args.seed, args.speed) == ("maze", 1, 2.0)
    assert args.strategy == "reliability-paper"
    args = ap.parse_args([])
    runner._fill_from_params(args)
    assert (args.world, args.seed, args.speed) == ("paper-room", 0, 1.0)
    assert args.strategy == "frontier"  # the default (docs/robustness.md)


def test_bench_codec_prints_every_message():
    r = cli("bench", "codec", "--repeats", "3", "--json")
    assert r.returncode == 0, r.stderr
    rows = json.loads(r.stdout)
    assert [x["type"] for x in rows] == ["Odometry", "LaserScan", "LaserScan", "Path",
                                         "OccupancyGrid"]
    assert all(x["bytes"] > 0 and x["to_wire_us"] > 0 and x["from_wire_us"] > 0 for x in rows)


def test_run_gives_a_world_time_to_finish_by_its_area(tmp_path):
    """Without --max-sim-time, `run` allows 6 s of sim time per m^2 of the world (at least
    2400 s), as `bench robust` does: a fixed 900 s stopped large-office a quarter through."""
    import argparse

    from topoexplore.sim.world import load_world, time_limit
    from topoexplore.tools import run as runner

    ap = argparse.ArgumentParser()
    runner.add_arguments(ap)
    args = ap.parse_args(["--world", "large-office", "--out", str(tmp_path / "a")])
    runner.check_input(args)
    assert args.max_sim_time == time_limit(load_world("large-office").area) > 3600.0
    args = ap.parse_args(["--world", "paper-room", "--out", str(tmp_path / "b")])
    runner.check_input(args)
    assert args.max_sim_time == 2400.0  # a small world: the floor
    args = ap.parse_args(["--world", "paper-room", "--max-sim-time", "30",
                          "--out", str(tmp_path / "c")])
    runner.check_input(args)
    assert args.max_sim_time == 30.0
    for bad in ("0", "-5", "nan"):
        args = ap.parse_args(["--world", "paper-room", "--max-sim-time", bad,
                              "--out", str(tmp_path / "d")])
        with pytest.raises(runner.InputError, match="--max-sim-time"):
            runner.check_input(args)
