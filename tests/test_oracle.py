"""The oracle tour (sim/oracle.py) and ``topoexplore bench oracle``."""

from __future__ import annotations

import itertools
import json
import math

import numpy as np
import pytest
from scipy.sparse.csgraph import dijkstra

from topoexplore.sim import oracle as sim_oracle
from topoexplore.sim.oracle import exhaustive_tour, greedy_cover, open_tour, oracle_tour
from topoexplore.sim.world import load_world, parse_world
from topoexplore.tools.bench import oracle as bench_oracle


def brute_force(d: np.ndarray) -> float:
    """The shortest open tour from node 0 through every node, over every order."""
    k = d.shape[0]
    return min(sum(d[a, b] for a, b in zip((0, *perm[:-1]), perm, strict=True))
               for perm in itertools.permutations(range(1, k)))


def test_open_tour_is_optimal_on_almost_every_small_instance():
    """2-opt + or-opt against every order on 200 random plane instances of 2 to 8 points
    (measured: 196 optimal, the worst 7.2 % longer)."""
    rng = np.random.default_rng(0)
    exact, worst = 0, 1.0
    for _ in range(200):
        k = int(rng.integers(2, 9))
        p = rng.uniform(0.0, 10.0, (k, 2))
        d = np.hypot(p[:, None, 0] - p[None, :, 0], p[:, None, 1] - p[None, :, 1])
        order, length, greedy = open_tour(d)
        assert order[0] == 0 and sorted(order) == list(range(k))
        assert length <= greedy + 1e-9
        assert length == pytest.approx(sum(d[a, b] for a, b in zip(order[:-1], order[1:], strict=True)))
        best = brute_force(d)
        exact += abs(length - best) < 1e-9
        worst = max(worst, length / best)
    assert exact >= 190 and worst < 1.10, (exact, worst)


def test_open_tour_of_points_on_a_line_goes_to_the_near_end_first():
    x = np.array([0.0, 1.0, -2.0, 3.0, -1.0])  # start at 0: -1, -2 then 1, 3 (7 m)
    d = np.abs(x[:, None] - x[None, :])
    order, length, _ = open_tour(d)
    assert length == pytest.approx(7.0) and [x[o] for o in order] == [0, -1, -2, 1, 3]


def test_greedy_cover_takes_the_start_then_the_largest_gain():
    rows = np.packbits(np.array([[1, 1, 0, 0, 0, 0, 0, 0],
                                 [1, 1, 1, 0, 0, 0, 0, 0],
                                 [0, 0, 1, 1, 1, 1, 0, 0],
                                 [0, 0, 0, 0, 0, 0, 1, 1]], dtype=np.uint8), axis=1)
    chosen, seen = greedy_cover(rows, 8, 1.0)
    assert chosen == [0, 2, 3] and seen == 8
    chosen, seen = greedy_cover(rows, 8, 0.75)  # 6 of 8 bits: the start and row 2
    assert chosen == [0, 2] and seen == 6


def test_row_bits_counts_the_bits_of_each_row_and_the_mask():
    rng = np.random.default_rng(1)
    rows = rng.integers(0, 256, (37, 11), dtype=np.uint8)
    mask = rng.integers(0, 256, 11, dtype=np.uint8)
    bits = np.unpackbits(rows, axis=1)
    assert sim_oracle._row_bits(rows).tolist() == bits.sum(axis=1).tolist()
    assert (sim_oracle._row_bits(rows, mask).tolist()
            == (bits & np.unpackbits(mask)).sum(axis=1).tolist())
    assert sim_oracle._row_bits(rows[:0]).shape == (0,)
    sparse = np.where(np.arange(11) % 4 == 1, mask, 0).astype(np.uint8)  # _Plan.sequential
    at = np.flatnonzero(sparse)  # counts only the bytes a step newly sees
    assert (sim_oracle._and_popcount_at(rows, sparse, at, sim_oracle._POP).tolist()
            == sim_oracle._row_bits(rows, sparse).tolist())


def test_the_plans_kept_path_lengths_and_trees_are_the_graphs():
    """_Plan.dist keeps each candidate's row of path lengths, and seg its shortest path tree
    (both searched once): the same numbers as a search of the graph each time, and _walk the
    path the predecessors give (a cell's predecessor walked back to the start)."""
    ctx = sim_oracle._Context(load_world("small-house"), sim_oracle.LASER_RANGE,
                              sim_oracle.ROBOT_RADIUS, sim_oracle.RESOLUTION)
    plan, _, _ = ctx.plan(8, 0.99)
    cands = [0, 5, 3, 5, 17]
    want = dijkstra(plan.graph, directed=False, indices=plan.cand_node[cands])
    assert np.array_equal(plan.dist(cands), want[:, plan.cand_node])
    assert np.array_equal(plan.dist([17, 0]), want[[4, 0]][:, plan.cand_node])
    _, pred = dijkstra(plan.graph, directed=False, indices=int(plan.cand_node[0]),
                       return_predecessors=True)
    src, dst = int(plan.cand_node[0]), int(plan.cand_node[17])
    path, v = [], dst
    while v != src:
        path.append(v)
        v = int(pred[v])
    assert sim_oracle._walk(pred, src, dst).tolist() == path[::-1]
    assert sim_oracle._walk(pred, src, src).tolist() == []
    assert plan.seg(0, 17).tobytes() == plan.seg(17, 0).tobytes()


CORRIDOR = {
    "name": "corridor", "size": [20.0, 3.0],
    "robot": {"pose": [1.0, 1.5, 0.0]},
    "walls": [{"points": [[0.2, 0.5], [19.8, 0.5], [19.8, 2.5], [0.2, 2.5]], "closed": True}],
}


def test_oracle_on_a_corridor_drives_only_until_the_far_end_is_in_range():
    """A 19.6 m corridor and an 8 m laser: the far wall is seen from about 19.8 - 8 m; the
    tour goes there and not further."""
    o = oracle_tour(parse_world(CORRIDOR, "test"))
    assert o.seen_fraction >= 0.99
    assert tuple(o.points[0]) == pytest.approx((1.05, 1.45), abs=0.11)  # the start's cell
    assert 10.0 <= o.length_m <= 11.5, o.length_m
    assert o.length_m <= o.greedy_length_m + 1e-9


def comb() -> dict:
    """A corridor with three rooms above it, each behind a 1 m door: three viewpoints."""
    walls = [{"points": [[0.2, 0.2], [12.2, 0.2], [12.2, 6.2], [0.2, 6.2]], "closed": True}]
    for a, b in ((0.2, 1.5), (2.5, 5.5), (6.5, 9.5), (10.5, 12.2)):
        walls.append({"points": [[a, 1.6], [b, 1.6]]})
    for x in (4.2, 8.2):
        walls.append({"points": [[x, 1.6], [x, 6.2]]})
    return {"name": "comb", "size": [12.5, 6.5], "robot": {"pose": [0.8, 0.9, 0.0]},
            "walls": walls}


@pytest.mark.parametrize("world,spacing,most", [(comb(), 1.0, 3), ("junction", 0.5, 2),
                                                ("dead-end", 0.5, 2)])
def test_oracle_equals_the_best_tour_over_every_viewpoint_set_on_small_worlds(world, spacing,
                                                                            most):
    """Against every set of up to `most` lattice viewpoints in every order, by the same model
    (measured: equal on these; on small-house at 1 m, 32 s, the oracle is 31.0 m against
    23.2 m, 1.34 x: docs/benchmarks.md)."""
    w = parse_world(world, "test") if isinstance(world, dict) else load_world(world)
    best = exhaustive_tour(w, spacing, most)
    o = oracle_tour(w, spacings=(spacing,))
    assert best is not None and best.seen_fraction >= 0.99
    assert o.length_m == pytest.approx(best.length_m, abs=1e-6)
    assert len(o.points) == len(best.points)


@pytest.mark.parametrize("name", ["maze", "small-house"])
def test_oracle_sees_the_coverage_set_on_built_in_worlds(name):
    o = oracle_tour(load_world(name))
    assert o.seen_fraction >= 0.99 and o.length_m > 0 and len(o.points) >= 2
    steps = np.hypot(*np.diff(o.points, axis=0).T)
    assert o.length_m >= steps.sum() - 1e-6  # paths go round walls: never under the chord


def test_bench_oracle_divides_paths_by_the_tour(tmp_path, capsys):
    runs = tmp_path / "runs.jsonl"
    rows = [{"world": "junction", "strategy": "frontier", "seed": 0, "outcome": "finished",
             "path_length_m": 16.48, "coverage": 1.0},
            {"world": "junction", "strategy": "reliability", "seed": 0, "outcome": "early-done",
             "path_length_m": 3.0, "coverage": 0.5}]
    runs.write_text("\n".join(json.dumps(r) for r in rows) + "\n")
    out = tmp_path / "oracle.json"
    assert bench_oracle.main(["--from-results", str(tmp_path), "--jobs", "1",
                              "--json", str(out)]) == 0
    got = json.loads(out.read_text())
    tour = got["oracles"][0]["oracle_m"]
    fr = got["analysis"]["strategies"]["frontier"]
    assert fr["n"] == 1 and fr["geomean"] == pytest.approx(16.48 / tour, rel=1e-3)
    assert "reliability" not in got["analysis"]["strategies"]  # not finished: left out
    assert got["analysis"]["left_out"] == ["junction/reliability"]
    assert "frontier: path / oracle" in capsys.readouterr().out
    assert math.isfinite(tour) and tour > 0


@pytest.mark.parametrize("argv", [["--worlds", "no-such-world"], ["--jobs", "0"],
                                  ["--from-results", "/no/such/dir"]])
def test_bench_oracle_bad_arguments_are_one_line_errors(argv, capsys):
    assert bench_oracle.main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("topoexplore bench oracle:") and "\n" not in err


def test_bench_oracle_finds_the_world_file_a_run_was_given(tmp_path, monkeypatch):
    """bench inproc run with a world file (a generated floor) records the file: bench oracle
    --from-results takes the tour of that file, with no --corpus, whether the file was given
    absolute or relative to where the results lie."""
    import shutil
    from pathlib import Path

    import topoexplore.sim as sim_pkg

    floor = tmp_path / "floors" / "my-floor.toml"
    floor.parent.mkdir()
    shutil.copy(Path(sim_pkg.__file__).parent / "worlds" / "junction.toml", floor)
    for world in (str(floor), "floors/my-floor.toml"):
        res = tmp_path / "res.json"
        res.write_text(json.dumps({"runs": [{
            "world": world, "strategy": "frontier", "seed": 0, "state": "done",
            "finished": True, "path_length_m": 16.48, "coverage": 1.0}]}))
        out = tmp_path / "oracle.json"
        monkeypatch.chdir("/")  # a relative path is found beside the results, not here
        assert bench_oracle.main(["--from-results", str(res), "--jobs", "1",
                                  "--json", str(out)]) == 0
        got = json.loads(out.read_text())
        assert [o["world"] for o in got["oracles"]] == ["my-floor"]
        assert got["oracles"][0]["oracle_m"] == pytest.approx(
            oracle_tour(load_world("junction")).length_m, rel=1e-6)
        assert got["analysis"]["strategies"]["frontier"]["n"] == 1


def test_a_tour_is_kept_on_disk_by_world_and_code(tmp_path, monkeypatch):
    """bench oracle's tours are kept in the cache directory: asked again (another process,
    another benchmark) the tour is read, not planned; another world has another key; an
    unwritable cache costs time, never the figure."""
    import topoexplore.sim.oracle as sim_oracle
    from topoexplore.tools.bench.explore import resolve_world

    monkeypatch.setenv(bench_oracle.CACHE_ENV, str(tmp_path / "c"))
    bench_oracle._tour.cache_clear()
    path = resolve_world("junction")[1]
    first = bench_oracle.tour_length(path)
    kept = list((tmp_path / "c" / "oracle").glob("*.json"))
    assert len(kept) == 1 and json.loads(kept[0].read_text())["oracle_m"] == first

    def boom(*a, **k):
        raise AssertionError("planned again")

    bench_oracle._tour.cache_clear()
    monkeypatch.setattr(sim_oracle, "oracle_tour", boom)
    assert bench_oracle.tour_length(path) == first
    assert bench_oracle.world_key(load_world("junction")) != bench_oracle.world_key(
        load_world("dead-end"))
    kept[0].write_text('{"oracle_m": "not a length"}')  # damaged: planned again
    monkeypatch.undo()
    monkeypatch.setenv(bench_oracle.CACHE_ENV, str(tmp_path / "c"))
    bench_oracle._tour.cache_clear()
    assert bench_oracle.tour_length(path) == first
    assert json.loads(kept[0].read_text())["oracle_m"] == first

    blocker = tmp_path / "file"
    blocker.write_text("")
    monkeypatch.setenv(bench_oracle.CACHE_ENV, str(blocker))  # .../file/oracle: no directory
    bench_oracle._tour.cache_clear()
    assert bench_oracle.tour_length(path) == first
    bench_oracle._tour.cache_clear()
