"""``topoexplore bench robust``: outcome classes, tables and ratios per half, arguments, and one
small real run (one generated house, one strategy, in process)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from topoexplore.tools.bench import robust as rb


def run(world, strategy, outcome_state="done", coverage=1.0, path=10.0, half="tune",
        style="office", stagnant=0.0, esc=None, marks=0):
    r = {"world": world, "strategy": strategy, "state": outcome_state, "coverage": coverage,
         "path_length_m": path, "half": half, "style": style, "stagnant_s": stagnant,
         "collisions": 0, "escalations": esc if esc is not None else {"blacklist": 0},
         "blocked_marks": marks, "stop_reason": "x", "picture": None}
    r["outcome"] = rb.classify(r)
    return r


def test_classify_every_outcome():
    assert rb.classify({"state": "done", "coverage": 0.96}) == "finished"
    assert rb.classify({"state": "done", "coverage": 0.5}) == "early-done"
    assert rb.classify({"state": "done", "coverage": None}) == "early-done"
    assert rb.classify({"state": "timeout", "stagnant_s": rb.STAGNANT_S}) == "livelock"
    assert rb.classify({"state": "timeout", "stagnant_s": 10.0}) == "timeout"
    assert rb.classify({"state": "failed"}) == "failed"
    assert rb.classify({"state": "error"}) == "error"


def test_time_limit_scales_with_area_without_a_cap():
    assert rb.time_limit(10.0) == 2400.0
    assert rb.time_limit(1000.0) == 6000.0
    assert rb.time_limit(3600.0) == 21600.0  # a 60 x 60 m world (was capped at 12000 s)


RUNS = [
    run("a", "reliability", path=8.0), run("a", "frontier", path=10.0),
    run("a", "all-end-nodes", path=20.0),
    run("b", "reliability", path=30.0, style="house"), run("b", "frontier", path=10.0,
                                                           style="house"),
    run("b", "all-end-nodes", "timeout", 0.9, 50.0, style="house", stagnant=700.0,
        esc={"blacklist": 2, "stuck": 1}, marks=3),
    run("c", "reliability", "done", 0.3, 2.0, half="held"),
    run("c", "frontier", "failed", 0.2, 1.0, half="held"),
]


def test_tables_ratios_and_worst_per_half():
    a = rb.analyse(RUNS, ["reliability", "all-end-nodes", "frontier"])
    assert set(a) == {"tune", "held"}
    t = a["tune"]["strategies"]
    assert t["reliability"]["finished"] == 2 and t["reliability"]["finished_rate"] == 1.0
    assert t["all-end-nodes"]["livelock"] == 1 and t["all-end-nodes"]["escalations"] == 3
    assert t["all-end-nodes"]["blocked_marks"] == 3
    assert t["all-end-nodes"]["coverage_min"] == 0.9
    rf = a["tune"]["ratios"]["reliability/frontier"]
    assert rf["n"] == 2 and rf["geomean"] == pytest.approx((0.8 * 3.0) ** 0.5)
    assert a["tune"]["ratios"]["reliability/all-end-nodes"]["n"] == 1  # b's did not finish
    assert a["tune"]["ratios_by_style"]["house"]["worlds"] == {"b": 3.0}
    assert a["tune"]["over_2x_shortest"] == [
        {"world": "a", "strategy": "all-end-nodes", "ratio": 2.5},
        {"world": "b", "strategy": "reliability", "ratio": 3.0}]
    assert a["tune"]["worst"][0]["outcome"] == "livelock"
    held = a["held"]
    assert [w["outcome"] for w in held["worst"]] == ["failed", "early-done"]
    assert held["ratios"]["reliability/frontier"]["n"] == 0
    assert held["ratios"]["reliability/frontier"]["geomean"] is None


def test_path_over_the_oracle_tour_counts_finished_runs_only():
    runs = [dict(run("a", "reliability", path=20.0), oracle_m=10.0),
            dict(run("b", "reliability", path=40.0), oracle_m=5.0),
            dict(run("c", "reliability", coverage=0.5, path=1.0), oracle_m=10.0),  # early done
            dict(run("a", "frontier", path=30.0), oracle_m=10.0),
            dict(run("b", "frontier", path=30.0), oracle_m=None)]  # no tour for b: left out
    o = rb.analyse(runs, ["reliability", "frontier"])["tune"]["oracle"]
    assert o["reliability"]["geomean"] == pytest.approx(4.0) and o["reliability"]["n"] == 2
    assert o["frontier"]["geomean"] == pytest.approx(3.0) and o["frontier"]["n"] == 1
    assert "reliability **4.00** (2)" in rb.summary(
        {"created": "x", "command": "c", "jobs": 1, "wall_s": 1.0, "runs": runs,
         "analysis": rb.analyse(runs, ["reliability", "frontier"])})


def test_the_papers_rule_is_compared_but_not_the_yardstick_nor_among_the_worst():
    runs = RUNS + [run("a", "reliability-paper", path=3.0),
                   run("a", "reliability-distance", path=17.0),
                   run("c", "reliability-paper", "done", 0.1, 1.0, half="held")]
    a = rb.analyse(runs, list(rb.DEFAULT_STRATEGIES) + ["reliability-distance"])
    over = a["tune"]["over_2x_shortest"]  # against the three strategies' best (8 m), not 3 m
    assert {"world": "a", "strategy": "reliability-distance", "ratio": 2.12} in over
    assert not any(o["strategy"] == "reliability" for o in over if o["world"] == "a")
    assert a["tune"]["ratios"]["reliability/reliability-paper"]["worlds"] == {"a": 2.667}
    assert a["tune"]["ratios"]["reliability/reliability-distance"]["n"] == 1
    assert all(w["strategy"] != "reliability-paper" for h in a.values() for w in h["worst"])
    assert a["held"]["strategies"]["reliability-paper"]["early-done"] == 1


def test_simulator_seeds_pair_runs_per_world_and_seed_and_show_the_spread():
    def sim(r, k):
        return dict(r, sim_seed=k)

    runs = [sim(run("a", "reliability", path=8.0), 0), sim(run("a", "frontier", path=10.0), 0),
            sim(run("a", "reliability", path=12.0), 1), sim(run("a", "frontier", path=10.0), 1),
            sim(run("b", "reliability", path=30.0, style="house"), 0),
            sim(run("b", "frontier", path=10.0, style="house"), 0),
            sim(run("b", "frontier", path=5.0, style="house"), 1),  # no reliability pair
            sim(run("c", "reliability", path=6.0), 1), sim(run("c", "frontier", path=8.0), 1)]
    a = rb.analyse(runs, ["reliability", "frontier"])["tune"]
    rf = a["ratios"]["reliability/frontier"]
    # a: (0.8 * 1.2) ** 0.5 over its two seeds, b: 3.0, c: 0.75; then over the three worlds
    ra = (0.8 * 1.2) ** 0.5
    assert rf["n"] == 3 and rf["pairs"] == 4
    assert rf["worlds"]["a"] == round(ra, 3)
    assert rf["geomean"] == pytest.approx((ra * 3.0 * 0.75) ** (1 / 3))
    assert rf["low"] < rf["geomean"] < rf["high"]
    logs = np.log([ra, 3.0, 0.75])  # Student's t with 2 degrees of freedom
    half = 4.302653 * np.std(logs, ddof=1) / np.sqrt(3)  # t(0.975, 2)
    assert rf["high"] == pytest.approx(np.exp(np.mean(logs) + half))
    sp = a["sim_spread"]
    assert sp["reliability"] == {"n": 1, "median": 1.5, "max": 1.5}
    assert sp["frontier"]["n"] == 2 and sp["frontier"]["max"] == 2.0
    over = a["over_2x_shortest"]
    assert {"world": "b", "strategy": "reliability", "ratio": 3.0} in over
    md = rb.summary({"created": "x", "command": "c", "jobs": 1, "wall_s": 1.0, "runs": runs,
                     "analysis": {"tune": a}})
    assert "over 3 world(s) where both finished, 4 run pairs" in md
    assert "95 % interval" in md and "reliability 1.50, 1.50 (1)" in md
    assert "| c/sim1 | reliability | finished |" in md  # the seed when it is not 0
    assert rb.run_label(runs[2]) == "a/sim1" and rb.run_label(runs[0]) == "a"
    one = rb.path_ratio(runs[:2], "reliability", "frontier")  # one world: no interval
    assert one["low"] is None and one["high"] is None and one["pairs"] == 1
    two = rb.path_ratio(runs[:6], "reliability", "frontier")  # two worlds: none either
    assert two["n"] == 2 and two["low"] is None


def test_a_plan_runs_every_world_and_strategy_once_per_simulator_seed(tmp_path):
    a = rb.build_parser().parse_args(["--half", "held", "--seeds", "1", "--max-area", "300",
                                      "--strategies", "reliability,frontier",
                                      "--sim-seeds", "2,0,2", "--corpus", str(tmp_path)])
    plan, strategies = rb._plan(a)
    assert strategies == ["reliability", "frontier"]
    assert sorted((i.name, s, k) for i, s, k in plan) == sorted(
        (w, s, k) for w in ("house-s1-18x14", "house-s1-18x14-n2")
        for s in strategies for k in (0, 2))


def test_summary_names_every_half_and_the_command():
    doc = {"created": "now", "command": "topoexplore bench robust", "jobs": 2, "runs": RUNS,
           "wall_s": 1.0, "analysis": rb.analyse(RUNS, ["reliability", "frontier",
                                                        "all-end-nodes"])}
    md = rb.summary(doc)
    assert "Tuning half" in md and "Held-back half" in md and "    topoexplore bench robust\n" in md
    assert "| all-end-nodes | 2 | 1 | 0 | 0 | 1 | 0 | 0 | 3 | 3 |" in md


@pytest.mark.parametrize("argv", [
    ["--strategies", "greedy"], ["--jobs", "0"], ["--bus", "-1"], ["--half", "odd"],
    ["--set", "planner.no_such=1"], ["--quick", "--worlds", "no-such-world"], ["--bogus"],
    ["--seeds", "8"], ["--seeds", "x"], ["--max-area", "0"], ["--max-area", "nan"],
    ["--sim-seeds", "-1"], ["--sim-seeds", "x"], ["--sim-seeds", ","], ["--sim-seeds", "1000"],
])
def test_bad_arguments_one_line_exit_2(argv, tmp_path, capsys):
    out = tmp_path / "out"
    assert rb.main([*argv, "--out", str(out), "--corpus", str(tmp_path / "c")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("topoexplore bench robust: ") and "\n" not in err
    assert not out.exists()


def test_corpus_halves_sizes_and_filters(tmp_path):
    assert {s for s in rb.SEEDS if rb.half_of(s) == "tune"} == {0, 2, 4, 6}
    assert {s for s in rb.SEEDS if rb.half_of(s) == "held"} == {1, 3, 5, 7}
    sizes = {(st, sd, lv): rb.size_of(st, sd, lv) for st in rb.STYLES for sd in rb.SEEDS
             for lv in (None, rb.NOISE)}
    assert len(sizes) >= 60  # the corpus size
    assert sizes[("office", 7, None)] == (60.0, 60.0) and sizes[("house", 3, None)] is None
    assert sizes[("cluttered", 6, rb.NOISE)] == (36.0, 33.0)
    items = rb.build_corpus(tmp_path, "held", seeds=[1], max_area=300.0)  # default sizes
    assert [(i.name, i.half, i.noise) for i in items] == [("house-s1-18x14", "held", None),
                                                          ("house-s1-18x14-n2", "held", 2)]
    assert all((tmp_path / (i.name + ".toml")).is_file() or (tmp_path / (i.name + ".yaml"))
               .is_file() for i in items)


@pytest.mark.timeout(600)
def test_smoke_corpus_every_strategy_writes_results_summary_and_pictures(tmp_path):
    """The --quick corpus (three generated 12 x 10 m worlds: a house, the same style with SLAM
    noise, a cluttered floor) x all three strategies and the paper's rule, in process, two at
    a time (~60 s): no run errs, fails or livelocks, and the files hold what the tables say.
    The paper's rule (no completion phase) may stop early; it is the reference, not held to
    the coverage."""
    out = tmp_path / "out"
    rc = rb.main(["--quick", "--jobs", "2", "--no-progress", "--corpus", str(tmp_path / "c"),
                  "--out", str(out)])
    assert rc == 0
    doc = json.loads((out / "results.json").read_text())
    runs = doc["runs"]
    assert len(runs) == 12 and {r["strategy"] for r in runs} == set(rb.DEFAULT_STRATEGIES)
    assert {r["world"] for r in runs} == {"house-s0-12x10", "house-s1-12x10-n2",
                                          "cluttered-s1-12x10"}
    for r in runs:
        assert r["outcome"] in ("finished", "early-done", "timeout"), (r["world"], r["outcome"])
        assert r["collisions"] == 0 and (out / r["picture"]).is_file()
        assert r["coverage"] >= 0.9 or r["strategy"] == "reliability-paper"
    tables = doc["analysis"]
    assert set(tables) == {"tune", "held"}
    assert sum(t["runs"] for h in tables.values() for t in h["strategies"].values()) == 12
    assert sum(t["finished"] for h in tables.values() for t in h["strategies"].values()) == \
        sum(r["outcome"] == "finished" for r in runs)
    assert all(r["oracle_m"] > 0 for r in runs)  # one short tour on the true map per world
    assert len({(r["world"], r["oracle_m"]) for r in runs}) == 3
    md = (out / "summary.md").read_text()
    assert "house-s1-12x10-n2" in md and "Held-back half" in md
    assert "path / oracle tour" in md
    assert len((out / "runs.jsonl").read_text().splitlines()) == 12


def _results_dir(path, runs, command):
    import cv2
    import numpy as np

    (path / "pics").mkdir(parents=True)
    for r in runs:
        r["picture"] = f"pics/{r['world']}-{r['strategy']}.png"
        cv2.imwrite(str(path / r["picture"]), np.full((40, 1000, 3), 200, np.uint8))
    (path / "results.json").write_text(json.dumps(
        {"created": "2026-01-01 00:00", "command": command, "jobs": 2, "runs": runs,
         "wall_s": 10.0, "analysis": {}}))
    return path


def test_from_results_merges_halves_into_one_doc_with_small_pictures(tmp_path, capsys):
    a = _results_dir(tmp_path / "a", [dict(r) for r in RUNS[:6]], "topoexplore bench robust --half tune")
    b = _results_dir(tmp_path / "b", [dict(r) for r in RUNS[6:]]
                     + [run("a", "frontier", path=9.0)], "topoexplore bench robust --half held")
    out, doc = tmp_path / "out", tmp_path / "docs" / "robustness.md"
    assert rb.main(["--from-results", str(a), str(b), "--out", str(out), "--doc", str(doc)]) == 0
    merged = json.loads((out / "results.json").read_text())
    assert len(merged["runs"]) == 8  # a/frontier of b replaced a's
    assert [r["path_length_m"] for r in merged["runs"] if r["world"] == "a"
            and r["strategy"] == "frontier"] == [9.0]
    md = doc.read_text()
    assert "--half tune" in md and "--half held" in md and "Held-back half" in md
    pics = sorted((doc.parent / "img" / "robust").iterdir())
    assert len(pics) == rb.DOC_PICTURES - 2 and all(p.suffix == ".jpg" for p in pics)  # 8 runs
    import cv2
    assert cv2.imread(str(pics[0])).shape[1] == rb.DOC_WIDTH
    assert "](img/robust/c-frontier.jpg)" in md
    assert (out / "pics" / "c-frontier.png").is_file()
    # a second simulator seed of a run is another run, not a replacement
    c = _results_dir(tmp_path / "c", [dict(run("a", "frontier", path=11.0), sim_seed=1)],
                     "topoexplore bench robust --half tune --sim-seeds 1")
    assert rb.main(["--from-results", str(a), str(b), str(c), "--out", str(out)]) == 0
    merged = json.loads((out / "results.json").read_text())
    assert sorted(r["path_length_m"] for r in merged["runs"] if r["world"] == "a"
                  and r["strategy"] == "frontier") == [9.0, 11.0]
    capsys.readouterr()
    assert rb.main(["--from-results", str(tmp_path / "none")]) == 2
    assert "cannot read" in capsys.readouterr().err


def test_real_maps_missing_is_said_not_skipped_silently(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(rb, "shared_maps_dir", lambda: None)
    out = tmp_path / "out"
    assert rb.main(["--half", "real", "--out", str(out), "--corpus", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert "no ../shared/maps" in err and "\n" not in err and not out.exists()
    a = rb.build_parser().parse_args(["--half", "all", "--seeds", "1", "--max-area", "300",
                                      "--corpus", str(tmp_path)])
    plan, _ = rb._plan(a)
    assert "real maps are left out" in capsys.readouterr().err
    assert {i.half for i, _s, _k in plan} == {"held"}


def test_compare_pairs_worlds_and_says_how_sure_it_is(tmp_path, capsys):
    """--compare: per world the geometric mean path of each side's finished runs (its
    simulator seeds), new / base over the worlds with an interval and a sign test; a run
    that stops finishing is listed, not averaged in; runs.jsonl stands in for a missing
    results.json (a run cut short)."""
    from topoexplore.tools.bench import compare as cp

    base = [run(f"w{k}", "reliability", path=100.0) for k in range(6)]
    base += [run("w0", "frontier", path=50.0), run("w5", "reliability", path=400.0)]
    base[-1]["sim_seed"] = 1  # w5: two seeds, 100 and 400 m -> 200 m
    new = [run(f"w{k}", "reliability", path=80.0) for k in range(5)]
    new.append(run("w5", "reliability", "timeout", path=50.0))
    c = cp.compare(base, new, "reliability")
    assert c["n"] == 5 and c["shorter"] == 5 and c["longer"] == 0
    assert c["geomean"] == pytest.approx(0.8) and c["low"] == pytest.approx(0.8)
    assert c["p"] == pytest.approx(0.0625)
    assert c["total"] == pytest.approx((500.0, 400.0))
    assert c["outcome_changes"] == [{"world": "w5", "base": "2/2 finished",
                                     "new": "0/1 finished"}]
    w5 = next(r for r in c["worlds"] if r["world"] == "w5")
    assert w5["base"] == pytest.approx(200.0) and w5["new"] is None and w5["ratio"] is None
    # a change that does nothing on average: an interval across 1, an even split
    noop = [run(f"w{k}", "reliability", path=100.0 * (1.3 if k % 2 else 1 / 1.3))
            for k in range(6)]
    c = cp.compare(base[:6], noop, "reliability")
    assert c["low"] < 1.0 < c["high"] and c["shorter"] == c["longer"] == 3 and c["p"] == 1.0
    # the CLI: one report per strategy on both sides
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    (tmp_path / "a" / "results.json").write_text(json.dumps({"runs": base}))
    (tmp_path / "b" / "runs.jsonl").write_text("".join(json.dumps(r) + "\n" for r in new))
    assert rb.main(["--compare", str(tmp_path / "a"), str(tmp_path / "b")]) == 0
    out = capsys.readouterr().out
    assert "### reliability:" in out and "**0.800**" in out and "outcome changed on w5" in out
    assert "### frontier" not in out  # no frontier runs on the new side
    assert rb.main(["--compare", str(tmp_path / "a"), str(tmp_path / "nope")]) == 2
    assert rb.main(["--compare", str(tmp_path / "a"), str(tmp_path / "b"),
                    "--strategies", "frontier"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and all(e.startswith("topoexplore bench robust: --compare") for e in err)


def test_the_path_driven_toward_completion_targets_is_counted_and_reported():
    """A run's completion_m: the path between updates whose plan (as of the earlier update)
    followed a completion-phase target; the report gives its share per strategy."""
    from types import SimpleNamespace as NS

    from topoexplore.services.planner.strategies.completion import COMPLETION_NOTE

    track = rb._Track()
    grid = NS(data=np.zeros((2, 2), np.int8))
    route = NS(target_id=-1, target_xy=(0.0, 0.0), waypoints=np.zeros((2, 2)))
    for x, reason in ((0.0, "target end node 3"), (1.0, f"target frontier{COMPLETION_NOTE}"),
                      (3.0, f"target frontier{COMPLETION_NOTE}"), (6.0, "target end node 4"),
                      (10.0, "done")):
        plan = NS(route=route, status=NS(reason=reason))
        track(0.0, NS(x=x, y=0.0), None, None, plan, grid)
    assert track.completion_m == pytest.approx(5.0)  # 1 -> 3 -> 6 m
    runs = [run("w1", "reliability", path=20.0), run("w2", "reliability", path=10.0),
            run("w3", "reliability", "timeout", path=10.0), run("w4", "frontier", path=9.0)]
    runs[0]["completion_m"], runs[1]["completion_m"], runs[2]["completion_m"] = 5.0, 4.0, 9.0
    share = rb.completion_share(runs, "reliability")
    assert share == {"n": 2, "median": pytest.approx(0.325), "max": pytest.approx(0.4)}
    assert rb.completion_share(runs, "frontier")["n"] == 0  # made before the count
    doc = {"command": "x", "created": "now", "wall_s": 1.0, "jobs": 1, "runs": runs,
           "analysis": rb.analyse(runs, ["reliability", "frontier"])}
    assert "completion phase" in rb.summary(doc) and "reliability 0.33, 0.40 (2)" in \
        rb.summary(doc)
