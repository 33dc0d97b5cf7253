"""``topoexplore bench explore``: ratio arithmetic, coverage distances, files, arguments, and
one small smoke run of the real suite (2 worlds x 3 strategies x 1 seed, capped sim time)."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys

import numpy as np
import pytest

from tests.conftest import REPO, SHARED
from topoexplore.tools.bench import explore as be


def rep(world, strategy, seed, path, sim, finished=True, coverage=1.0, timeline=None):
    return {"world": world, "world_label": world, "strategy": strategy, "seed": seed,
            "finished": finished, "stop_reason": "done: x" if finished else "max sim time",
            "path_length_m": path, "sim_time_s": sim, "wall_time_s": 2.0, "coverage": coverage,
            "map_accuracy": 0.99, "collisions": 0, "end_nodes_visited": 1,
            "end_nodes_accepted_remote": 1, "timeline": timeline or []}


RUNS = [
    rep("a", "reliability", 0, 10.0, 100.0), rep("a", "frontier", 0, 20.0, 150.0),
    rep("a", "all-end-nodes", 0, 12.5, 110.0),
    rep("a", "reliability", 1, 8.0, 90.0), rep("a", "frontier", 1, 32.0, 180.0),
    rep("a", "all-end-nodes", 1, 16.0, 100.0, finished=False),
    rep("b", "reliability", 0, 5.0, 60.0), rep("b", "frontier", 0, 4.0, 200.0, finished=False),
    rep("b", "all-end-nodes", 0, 0.0, 40.0),
]


# -- ratios --------------------------------------------------------------------------------


def test_pair_ratios_per_pair_and_geometric_mean():
    rr = be.pair_ratios(RUNS, "reliability", "frontier", "path_length_m")
    by = {(p["world"], p["seed"]): p for p in rr["pairs"]}
    assert set(by) == {("a", 0), ("a", 1), ("b", 0)}
    assert by[("a", 0)]["ratio"] == pytest.approx(0.5) and by[("a", 0)]["included"]
    assert by[("a", 1)]["ratio"] == pytest.approx(0.25) and by[("a", 1)]["included"]
    # unfinished pair: ratio shown, not counted, reason given
    assert by[("b", 0)]["ratio"] == pytest.approx(1.25) and not by[("b", 0)]["included"]
    assert "frontier not finished" in by[("b", 0)]["excluded_reason"]
    assert rr["geomean"] == pytest.approx(math.sqrt(0.5 * 0.25))
    assert (rr["n_included"], rr["n_excluded"]) == (2, 1)
    assert rr["by_world"]["a"]["geomean"] == pytest.approx(math.sqrt(0.125))
    assert rr["by_world"]["b"] == {"geomean": None, "n_included": 0, "n_pairs": 1}
    assert rr["geomean_covered"] == rr["geomean"] and rr["n_covered"] == 2


def test_pair_ratios_covered_figure_leaves_out_incomplete_maps():
    runs = [rep("a", "reliability", 0, 10.0, 1.0), rep("a", "frontier", 0, 20.0, 1.0),
            rep("a", "reliability", 1, 10.0, 1.0), rep("a", "frontier", 1, 1.0, 1.0,
                                                         coverage=0.9)]
    rr = be.pair_ratios(runs, "reliability", "frontier", "path_length_m")
    assert rr["geomean"] == pytest.approx(math.sqrt(0.5 * 10.0)) and rr["n_included"] == 2
    assert rr["geomean_covered"] == pytest.approx(0.5) and rr["n_covered"] == 1


def test_pair_ratios_exclude_unfinished_and_zero_denominator():
    rr = be.pair_ratios(RUNS, "reliability", "all-end-nodes", "path_length_m")
    by = {(p["world"], p["seed"]): p for p in rr["pairs"]}
    assert by[("a", 0)]["included"] and by[("a", 0)]["ratio"] == pytest.approx(0.8)
    assert "all-end-nodes not finished" in by[("a", 1)]["excluded_reason"]
    assert by[("b", 0)]["ratio"] is None and "zero" in by[("b", 0)]["excluded_reason"]
    assert rr["geomean"] == pytest.approx(0.8) and rr["n_excluded"] == 2
    st = be.pair_ratios(RUNS, "reliability", "all-end-nodes", "sim_time_s")
    assert st["geomean"] == pytest.approx(math.sqrt(100.0 / 110.0 * 60.0 / 40.0))  # b counts


def test_all_ratios_only_for_strategies_that_ran_and_none_without_pairs():
    assert set(be.all_ratios(RUNS, ["reliability", "frontier"])) == {
        "path_length_m:reliability/frontier", "sim_time_s:reliability/frontier"}
    assert be.all_ratios(RUNS, ["reliability"]) == {}
    only_unfinished = [rep("a", "reliability", 0, 1.0, 1.0, finished=False),
                       rep("a", "frontier", 0, 2.0, 1.0)]
    rr = be.pair_ratios(only_unfinished, "reliability", "frontier", "path_length_m")
    assert rr["geomean"] is None and rr["n_excluded"] == 1


def test_geometric_mean():
    assert be.geometric_mean([2.0, 8.0]) == pytest.approx(4.0)
    assert be.geometric_mean([]) is None
    with pytest.raises(be.BenchDataError):
        be.geometric_mean([1.0, 0.0])


def test_aggregate_means_over_all_seeds():
    agg = be.aggregate(RUNS)
    a = agg["a"]["all-end-nodes"]
    assert (a["runs"], a["finished"], a["finished_rate"]) == (2, 1, 0.5)
    assert a["path_length_m"] == {"mean": 14.25, "min": 12.5, "max": 16.0, "n": 2}


# -- coverage over distance ----------------------------------------------------------------


TL_D = [0.0, 0.3, 1.0, 2.0, 1.9, 3.0]  # a stale, smaller distance at index 4
TL_C = [0.0, 0.5, 0.85, 0.89, 0.92, 0.94]


def test_distance_to_coverage():
    assert be.distance_to_coverage(TL_D, TL_C, 0.9) == pytest.approx(2.0)  # running max
    assert be.distance_to_coverage(TL_D, TL_C, 0.95) is None
    assert be.distance_to_coverage(TL_D, TL_C, 0.5) == pytest.approx(0.3)
    assert be.distance_to_coverage([], [], 0.9) is None
    for args in (([0.0, 1.0], [0.1], 0.9), (TL_D, TL_C, 0.0), (TL_D, TL_C, 1.5),
                 ([0.0, float("nan")], [0.1, 0.2], 0.9)):
        with pytest.raises(be.BenchDataError):
            be.distance_to_coverage(*args)


def test_derive_and_table():
    runs = [be.derive(rep("a", "reliability", s, 3.0, 10.0,
                          timeline=[[0.0, d, c] for d, c in zip(TL_D, TL_C, strict=True)]))
            for s in (0, 1)]
    runs[1]["timeline"][-1][2] = 0.96
    runs[1] = be.derive(runs[1])
    assert runs[0]["d90_m"] == pytest.approx(2.0) and runs[0]["d95_m"] is None
    assert runs[1]["d95_m"] == pytest.approx(3.0)
    row = be.coverage_distance_table(runs)["a"]["reliability"]
    assert row["d90"] == [2.0, 2.0] and row["d90_mean"] == pytest.approx(2.0)
    assert row["d95"] == [None, 3.0] and row["d95_mean"] == pytest.approx(3.0)
    assert row["d95_reached"] == "1/2"


def test_mean_curve_holds_final_coverage():
    grid, mean = be.mean_curve([([0.0, 1.0, 2.0], [0.2, 0.6, 1.0]), ([0.0, 1.0], [0.4, 0.8])],
                               points=5)
    np.testing.assert_allclose(grid, [0.0, 0.5, 1.0, 1.5, 2.0])
    np.testing.assert_allclose(mean, [0.3, 0.3, 0.7, 0.7, 0.9])
    g, m = be.mean_curve([([], [])])
    assert g.size == 0 and m.size == 0


# -- files (--from-results) ----------------------------------------------------------------


def _doc(runs):
    return {"version": 1, "created": "2026-01-01T00:00:00+00:00",
            "command": "topoexplore bench explore --worlds a,b", "argv": [],
            "machine": be.machine_info(),
            "config": {"worlds": ["a", "b"], "world_labels": ["a", "b"],
                       "strategies": list(be.STRATEGIES), "seeds": 2, "max_sim_time": 900.0,
                       "max_wall_time": 600.0, "jobs": 1, "planned_runs": 12},
            "notes": ["map x not found: skipped"], "interrupted": False, "runs": runs}


def test_from_results_writes_summary_csv_json_and_curves(tmp_path, capsys):
    runs = []
    for r in RUNS:
        r = dict(r)
        k = {"reliability": 1.0, "all-end-nodes": 0.8, "frontier": 0.6}[r["strategy"]]
        r["timeline"] = [[t, t * k, min(1.0, 0.1 * t)] for t in range(11)]
        runs.append(r)
    src = tmp_path / "src"
    src.mkdir()
    (src / "results.json").write_text(json.dumps(_doc(runs)))
    out = tmp_path / "out"
    assert be.main(["--from-results", str(src), "--out", str(out)]) == 0
    doc = json.loads((out / "results.json").read_text())
    rr = doc["ratios"]["path_length_m:reliability/frontier"]
    assert rr["geomean"] == pytest.approx(math.sqrt(0.125)) and rr["n_excluded"] == 1
    assert doc["runs"][0]["d90_m"] == pytest.approx(9.0)  # coverage 0.9 at t=9, k=1
    assert doc["coverage_distance"]["a"]["frontier"]["d90_mean"] == pytest.approx(5.4)
    rows = (out / "results.csv").read_text().splitlines()
    assert len(rows) == 1 + len(RUNS) and "timeline" not in rows[0]
    assert rows[0].startswith("world_label,strategy,seed,finished,")
    summary = (out / "summary.md").read_text()
    for text in ("geometric mean **0.354** over 2 pair(s)", "1 pair(s) excluded",
                 "b seed 0, reliability vs frontier (path_length_m, sim_time_s): frontier not finished",
                 "| a | frontier | 5.4 (2/2) |", "Note: map x not found",
                 "2 CPUs" if os.cpu_count() == 2 else "CPUs", "curves/a.png"):
        assert text in summary, text
    for w in ("a", "b"):
        png = (out / "curves" / f"{w}.png").read_bytes()
        assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 5000
    assert "re-made" in capsys.readouterr().err


def test_from_results_shows_both_coverages_and_reads_old_files(tmp_path):
    """Runs with ``coverage_free`` get it in the per-world table beside ``coverage``; results
    made before it existed are still read, with a note that their coverage is the older one."""
    new_runs = [dict(r, coverage=0.97, coverage_free=0.91) for r in RUNS]
    for name, runs in (("new", new_runs), ("old", [dict(r) for r in RUNS])):
        src = tmp_path / name
        src.mkdir()
        (src / "results.json").write_text(json.dumps(_doc(runs)))
        assert be.main(["--from-results", str(src)]) == 0
        summary = (src / "summary.md").read_text()
        doc = json.loads((src / "results.json").read_text())
        assert "| coverage | coverage of all free |" in summary
        agg = doc["aggregate"]["a"]["reliability"]
        assert agg["coverage"]["mean"] == pytest.approx(0.97 if name == "new" else 1.0)
        if name == "new":
            assert agg["coverage_free"]["mean"] == pytest.approx(0.91)
            assert "| 0.970 | 0.910 |" in summary and be.OLD_COVERAGE_NOTE not in summary
            assert "coverage_free" in (src / "results.csv").read_text().splitlines()[0]
        else:
            assert agg["coverage_free"]["n"] == 0 and "| 1.000 | – |" in summary
            assert summary.count(be.OLD_COVERAGE_NOTE) == 1
            assert be.main(["--from-results", str(src)]) == 0  # again: the note once
            assert (src / "summary.md").read_text().count(be.OLD_COVERAGE_NOTE) == 1


# -- arguments -----------------------------------------------------------------------------


@pytest.mark.parametrize("argv", [
    ["--worlds", "no-such-world"], ["--strategies", "reliability,greedy"], ["--seeds", "0"],
    ["--jobs", "0"], ["--max-sim-time", "-5"], ["--worlds", "maps/none.yaml"], ["--bogus"],
    ["--worlds", "dead-end,dead-end"], ["--from-results", "/nonexistent-dir"],
    ["--from-results", ".", "--seeds", "2"], ["--set", "planner.no_such=1"],
    ["--set", "controller.v_max=-1"], ["--set", "planner.strategy=frontier"],
    ["--params", "/nonexistent.toml"],
])
def test_bad_arguments_one_line_exit_2_before_anything(argv, tmp_path, capsys):
    out = tmp_path / "bench"
    assert be.main([*argv, "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("topoexplore bench explore: ") and "\n" not in err
    assert not out.exists()


def test_defaults_and_quick():
    cfg, _ = be.parse_config(["--quick"])
    assert cfg.inproc and cfg.bus_check == be.DEFAULT_BUS_CHECK and cfg.record == "none"
    assert [w[0] for w in cfg.worlds] == list(be.QUICK_WORLDS) and cfg.seeds == 1
    assert cfg.strategies == list(be.STRATEGIES) and cfg.jobs == be.DEFAULT_JOBS
    cfg, _ = be.parse_config([])
    labels = [w[0] for w in cfg.worlds]
    assert {"paper-room", "dead-end", "junction", "corner", "office", "maze", "small-house",
            "large-office"} <= set(labels) and cfg.seeds == 2
    if (SHARED / "maps" / "lse_arena.yaml").is_file():
        assert "lse_arena" in labels and not cfg.notes
        assert "../shared/maps/lse_arena.yaml" in cfg.command
    else:
        assert any("lse_arena" in n for n in cfg.notes)


def test_parameter_overrides_reach_every_run_and_the_command(tmp_path):
    toml = tmp_path / "p.toml"
    toml.write_text("[controller]\nv_max = 0.25\n")
    cfg, _ = be.parse_config(["--quick", "--params", str(toml), "--set", "mapper.map_every=3"])
    assert cfg.params == str(toml.resolve()) and cfg.overrides == ["mapper.map_every=3"]
    assert "--params" in cfg.command and "--set mapper.map_every=3" in cfg.command


# -- smoke run of the real suite -----------------------------------------------------------


@pytest.mark.timeout(420)
def test_smoke_suite_files_and_ratio_arithmetic(tmp_path):
    """2 worlds x 3 strategies x 1 seed, lockstep, capped at 50 sim s / 12 wall s per run, two
    runs at a time (~45 s): whatever the outcomes, the files exist and every ratio in
    results.json equals the one recomputed from the runs' own report.json files."""
    out = tmp_path / "bench"
    worlds = ["dead-end", "corner"]
    r = subprocess.run([sys.executable, "-m", "topoexplore.tools.cli", "bench", "explore", "--bus",
                        "--worlds", ",".join(worlds), "--seeds", "1", "--max-sim-time", "50",
                        "--max-wall-time", "12", "--jobs", "2", "--no-progress", "--out", str(out)],
                       cwd=REPO, capture_output=True, text=True, timeout=400,
                       env=dict(os.environ))
    assert r.returncode == 0, r.stderr[-2000:]
    for name in ("results.json", "results.csv", "summary.md"):
        assert (out / name).stat().st_size > 0, name
    doc = json.loads((out / "results.json").read_text())
    assert len(doc["runs"]) == 6 and len((out / "results.csv").read_text().splitlines()) == 7
    reports = {}
    for run in doc["runs"]:
        run_dir = out / run["run_dir"]
        assert run_dir.name == f"{run['world_label']}-{run['strategy']}-{run['seed']}"
        report = json.loads((run_dir / "report.json").read_text())
        reports[(run["world_label"], run["strategy"])] = report
        assert {k: run[k] for k in report} == report  # the report, unchanged, plus fields
        # every run was recorded; only the recordings of runs that did not finish are kept
        assert report["recording"]["gaps"] == 0
        kept = run_dir / "run.mcap"
        assert kept.is_file() == (not run["finished"])
        assert run["recording_file"] == (run["run_dir"] + "/run.mcap" if kept.is_file() else None)
        if kept.is_file():  # recorded raw, its Foxglove channels added after the run
            from topoexplore.tools.record import read_summary

            assert run["recording_note"].startswith("Foxglove channels added"), run
            assert "/viz/map" in read_summary(kept)["channels"]
    for w in worlds:
        if any(doc["runs"][i]["timeline"] for i in range(6) if doc["runs"][i]["world_label"] == w):
            assert (out / "curves" / f"{w}.png").stat().st_size > 0
    assert set(doc["ratios"]) == {f"{m}:reliability/{d}" for m in be.RATIO_METRICS
                                  for d in ("frontier", "all-end-nodes")}
    for key, rr in doc["ratios"].items():
        metric, pair = key.split(":")
        num, den = pair.split("/")
        assert len(rr["pairs"]) == 2
        included = []
        for p in rr["pairs"]:
            a, b = reports[(p["world"], num)], reports[(p["world"], den)]
            want = a[metric] / b[metric] if b[metric] > 0 else None
            assert p["ratio"] == pytest.approx(want) if want is not None else p["ratio"] is None
            both = a["finished"] and b["finished"] and a[metric] > 0 and b[metric] > 0
            assert p["included"] == both, p
            if both:
                included.append(want)
        assert rr["n_included"] == len(included) and rr["n_excluded"] == 2 - len(included)
        if included:
            assert rr["geomean"] == pytest.approx(math.exp(np.mean(np.log(included))))
        else:
            assert rr["geomean"] is None
    summary = (out / "summary.md").read_text()
    assert "--worlds dead-end,corner" in summary and "## Ratios" in summary
    assert "path / oracle tour" in summary  # the runs over a tour planned on the true map
    for w, tour in doc["oracle"]["tours"].items():
        assert w in worlds and tour is not None and tour >= 0.0


def test_bench_stages_times_every_core():
    """`bench stages` (compute part) on the smallest map: a figure for every service core."""
    from topoexplore.tools.bench import stages as benchstages

    res = benchstages.bench_stages(sizes=(100,), repeats=1)
    for stage in benchstages.STAGES:
        v = res[stage]["100x100"]
        assert v["median_ms"] >= 0 and v["p99_ms"] >= v["median_ms"], stage
        assert v["scans"] > 0
    assert res["reliability"]["100x100"]["end_nodes"] > 0
    table = benchstages.format_table(res)
    assert all(f"{s}:" in table for s in benchstages.STAGES)
    with pytest.raises(ValueError):
        benchstages.bench_stages(sizes=(100,), stages=("nope",))


@pytest.mark.parametrize("jobs", ["1", "2"])
def test_sigterm_stops_the_suite_and_its_running_stacks(tmp_path, jobs):
    """SIGTERM (a CI timeout, systemd) ends the suite like Ctrl-C: exit 130, partial results
    written, and no process of the runs in flight is left (with --jobs 2 as well: the pool
    must not wait for them)."""
    import signal
    import time

    out = tmp_path / "b"
    p = subprocess.Popen([sys.executable, "-m", "topoexplore.tools.cli", "bench", "explore", "--bus",
                          "--worlds", "office", "--strategies", "reliability", "--seeds", "1", "--out",
                          str(out), "--no-progress", "--jobs", jobs], cwd=REPO,
                         stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    tag = f"bench{p.pid}"

    def stack() -> list[str]:
        r = subprocess.run(["pgrep", "-f", tag], capture_output=True, text=True)
        return r.stdout.split()

    try:
        deadline = time.monotonic() + 60
        while len(stack()) < 7 and time.monotonic() < deadline:  # runner + router + 6 services
            time.sleep(0.5)
        assert len(stack()) >= 7, "the run's stack did not start"
        p.send_signal(signal.SIGTERM)
        _, err = p.communicate(timeout=60)
        assert p.returncode == 130, err
        deadline = time.monotonic() + 10
        while stack() and time.monotonic() < deadline:
            time.sleep(0.2)
        assert stack() == []
        assert json.loads((out / "results.json").read_text())["interrupted"] is True
    finally:
        if p.poll() is None:
            p.kill()
        for pid in stack():
            os.kill(int(pid), 9)


# -- in process (the default), checked on the bus -----------------------------------------


def test_in_process_or_on_the_bus_arguments(capsys):
    cfg, _ = be.parse_config(["--quick"])
    assert cfg.inproc and "--bus-check 3" in cfg.command and "--bus " not in cfg.command
    cfg, _ = be.parse_config(["--quick", "--bus-check", "0"])
    assert cfg.bus_check == 0 and "--bus-check 0" in cfg.command
    cfg, _ = be.parse_config(["--quick", "--bus"])
    assert not cfg.inproc and cfg.bus_check == 0 and "--bus-check" not in cfg.command
    assert cfg.record == "failed" and "--bus" in cfg.command and "--record" not in cfg.command
    cfg, _ = be.parse_config(["--quick", "--bus", "--record", "all"])
    assert cfg.record == "all" and "--bus --record all" in cfg.command
    for bad in (["--bus", "--bus-check", "2"], ["--bus-check", "-1"], ["--record", "all"],
                ["--record", "none"]):
        with pytest.raises(be.BenchArgError):
            be.parse_config(["--quick", *bad])
    assert be.main(["--quick", "--record", "failed"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == ("topoexplore bench explore: --record needs --bus: a run in process has no "
                   "traffic to record")


def test_bus_check_picks_every_strategy_on_short_runs_of_different_worlds_and_a_median_one():
    from topoexplore.tools.bench.explore_local import pick_bus_runs

    runs = [rep("a", "reliability", 0, 10.0, 50.0), rep("a", "frontier", 0, 9.0, 45.0),
            rep("a", "all-end-nodes", 0, 12.0, 60.0), rep("b", "reliability", 0, 20.0, 80.0),
            rep("b", "frontier", 0, 18.0, 70.0), rep("b", "all-end-nodes", 0, 25.0, 90.0),
            rep("c", "frontier", 0, 2.0, 10.0),  # drove too little to tell anything
            rep("d", "reliability", 0, 8.0, 20.0, finished=False)]  # not finished
    got = [(r["world_label"], r["strategy"]) for r in pick_bus_runs(runs, 3)]
    assert got == [("a", "frontier"), ("b", "reliability"), ("a", "all-end-nodes")]
    assert len(pick_bus_runs(runs, 6)) == 6 and len(pick_bus_runs(runs, 10)) == 6
    assert pick_bus_runs(runs, 0) == [] and pick_bus_runs([], 3) == []
    # the last pick is the run of median sim time among its strategy's (fresh worlds first)
    runs = [rep("p", "frontier", 0, 9.0, 30.0)] + [
        rep(w, "reliability", 0, 10.0, t) for w, t in (("q", 40.0), ("r", 100.0),
                                                       ("s", 200.0), ("t", 300.0),
                                                       ("u", 400.0))]
    got = [(r["world_label"], r["strategy"]) for r in pick_bus_runs(runs, 2)]
    assert got == [("p", "frontier"), ("s", "reliability")]
    assert [r["world_label"] for r in pick_bus_runs(runs, 1)] == ["p"]


def test_bus_check_compares_outcome_and_path():
    from topoexplore.tools.bench.explore_local import check_line, compare

    local = rep("a", "frontier", 0, 10.0, 50.0)
    c = compare(local, dict(local, path_length_m=10.1))
    assert c["agree"] and c["path_difference"] == pytest.approx(0.01)
    assert "DISAGREE" not in check_line(c) and "1.00 % apart" in check_line(c)
    assert not compare(local, dict(local, path_length_m=10.5))["agree"]  # 5 % apart
    c = compare(local, dict(local, finished=False))
    assert not c["agree"] and "DISAGREE" in check_line(c) and "on the bus False" in check_line(c)
    c = compare(local, dict(local, path_length_m=None))  # the bus run left no report
    assert not c["agree"] and c["path_difference"] is None


@pytest.mark.timeout(300)
def test_inproc_suite_writes_what_the_bus_suite_writes_and_checks_a_run_on_the_bus(tmp_path):
    """dead-end x frontier and reliability x 1 seed in process, one of them again on the real
    processes: the run directories hold what `topoexplore run` writes, the suite's files are
    there, and the bus run agrees with the in-process one."""
    out = tmp_path / "bench"
    r = subprocess.run([sys.executable, "-m", "topoexplore.tools.cli", "bench", "explore",
                        "--worlds", "dead-end", "--strategies", "reliability,frontier",
                        "--seeds", "1", "--bus-check", "1", "--no-progress",
                        "--out", str(out)],
                       cwd=REPO, capture_output=True, text=True, timeout=280,
                       env=dict(os.environ))
    assert r.returncode == 0, r.stderr[-2000:]
    assert "checked on the bus: 1 of 1 agree" in r.stderr
    doc = json.loads((out / "results.json").read_text())
    assert doc["config"]["inproc"] and len(doc["runs"]) == 2
    # the suite's own wall time and CPU, the workers' and the bus run's included
    assert 0 < doc["suite_wall_s"] and doc["suite_cpu_s"] > sum(
        r["wall_time_s"] for r in doc["runs"]) * 0.5, (doc["suite_wall_s"], doc["suite_cpu_s"])
    assert "suite: " in r.stderr and "The suite took" in (out / "summary.md").read_text()
    for run in doc["runs"]:
        assert run["finished"] and run["pipeline"] == "inproc" and run["collisions"] == 0
        run_dir = out / run["run_dir"]
        for name in ("report.json", "timeline.csv", "trail.csv", "map.yaml", "final.png"):
            assert (run_dir / name).stat().st_size > 0, name
        report = json.loads((run_dir / "report.json").read_text())
        assert {k: run[k] for k in report} == report
        assert run["timeline"][-1][1:] == [run["path_length_m"], run["coverage"]]
        assert run["d90_m"] is not None and run["end_nodes_seen"] >= 1
        assert 0.9 < run["map_accuracy"] <= 1.0
    (check,) = doc["bus_check"]
    assert check["agree"] and check["bus_finished"] and check["path_difference"] < 0.02
    bus_report = json.loads((out / "bus" / "runs" / f"dead-end-{check['strategy']}-0"
                             / "report.json").read_text())
    assert bus_report["path_length_m"] == check["bus_path_m"]
    summary = (out / "summary.md").read_text()
    assert "Each exploration ran in one process" in summary and "1 of 1 agree" in summary
    assert (out / "curves" / "dead-end.png").stat().st_size > 0


@pytest.mark.timeout(120)
def test_sigterm_stops_the_suite_and_its_worker_processes(tmp_path):
    """In process with --jobs 2 the runs are in worker processes: SIGTERM ends the suite with
    exit 130 and partial results, and no worker is left."""
    import signal
    import time

    out = tmp_path / "b"
    p = subprocess.Popen([sys.executable, "-m", "topoexplore.tools.cli", "bench", "explore",
                          "--worlds", "office", "--strategies", "reliability,frontier",
                          "--seeds", "1", "--out", str(out), "--no-progress", "--jobs", "2"],
                         cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)

    def workers() -> list[str]:
        r = subprocess.run(["pgrep", "-P", str(p.pid)], capture_output=True, text=True)
        return r.stdout.split()

    try:
        deadline = time.monotonic() + 60
        while len(workers()) < 2 and time.monotonic() < deadline:
            time.sleep(0.2)
        seen = workers()
        assert len(seen) >= 2, "the workers did not start"
        time.sleep(2.0)  # the runs are under way
        p.send_signal(signal.SIGTERM)
        _, err = p.communicate(timeout=60)
        assert p.returncode == 130, err
        assert json.loads((out / "results.json").read_text())["interrupted"] is True
        deadline = time.monotonic() + 10
        while any(os.path.exists(f"/proc/{w}") for w in seen) and time.monotonic() < deadline:
            time.sleep(0.2)
        assert not [w for w in seen if os.path.exists(f"/proc/{w}")]
    finally:
        if p.poll() is None:
            p.kill()


def test_a_run_in_process_stops_at_its_wall_time_limit_with_a_report(tmp_path):
    from topoexplore.tools.bench.explore_local import run_local

    run = run_local("paper-room", "paper-room", "frontier", 0, tmp_path, 600.0,
                    max_wall_time=1e-6)
    assert not run["finished"] and run["path_length_m"] is None
    assert run["stop_reason"] == "WallLimit: stopped after 1e-06 wall s"
    report = json.loads((tmp_path / run["run_dir"] / "report.json").read_text())
    assert report["stop_reason"] == run["stop_reason"] and report["pipeline"] == "inproc"
