"""Generated worlds (sim/generate.py): deterministic by seed, valid, essentially all reachable,
doors in range, sizes respected, SLAM noise present and harmless, the corpus helper and the
`topoexplore worlds generate` command."""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest

from tests.conftest import REPO
from topoexplore.common.mapio import read_map_server
from topoexplore.sim.generate import (
    DEFAULT_SIZES,
    DOOR_WIDTHS,
    MAP_MARGIN,
    MAX_NOISE,
    STYLES,
    GenerateError,
    check_arguments,
    generate,
    generate_corpus,
    reachability,
    slam_map,
    world_reachability,
    world_toml,
    write_generated,
)
from topoexplore.sim.world import START_CLEARANCE, World, clearance, load_world, rasterize
from topoexplore.tools import cli

RES = 0.05
SMALL = {"office": (16.0, 12.0), "house": (14.0, 11.0), "warehouse": (20.0, 14.0),
         "cluttered": (14.0, 12.0)}


@pytest.fixture(scope="module")
def gens():
    return {s: generate(s, 1, SMALL[s]) for s in STYLES}


@pytest.fixture(scope="module")
def office_maps(gens):
    return [slam_map(gens["office"], level) for level in range(MAX_NOISE + 1)]


def _files(d):
    return {p.name: p.read_bytes() for p in sorted(d.iterdir())}


# --- determinism --------------------------------------------------------------------------


def test_same_arguments_give_identical_files(tmp_path):
    for d in ("a", "b"):
        for level in (None, 2):
            write_generated(generate("office", 7, (16, 12)), tmp_path / d, level)
    a, b = _files(tmp_path / "a"), _files(tmp_path / "b")
    assert set(a) == {"office-s7-16x12.toml", "office-s7-16x12-n2.toml",
                      "office-s7-16x12-n2.yaml", "office-s7-16x12-n2.pgm"}
    assert a == b


def test_different_seeds_and_levels_differ(gens, office_maps):
    other = generate("house", 2, SMALL["house"])
    assert world_toml(other.world) != world_toml(gens["house"].world)
    assert other.world.segments != gens["house"].world.segments
    grids = [m.grid for m in office_maps]
    assert all(not np.array_equal(grids[i], grids[j]) for i in range(4) for j in range(i))


# --- validity and reachability ------------------------------------------------------------


@pytest.mark.parametrize("style", STYLES)
def test_world_file_loads_same_shapes_and_is_reachable(style, gens, tmp_path):
    g = gens[style]
    path = write_generated(g, tmp_path)
    w = load_world(str(path))
    assert (w.size, w.robot_pose, w.wall_thickness) == (g.world.size, g.world.robot_pose,
                                                        g.world.wall_thickness)
    assert (w.segments, w.boxes, w.circles) == (g.world.segments, g.world.boxes,
                                                g.world.circles)
    assert clearance(w, *w.robot_pose[:2]) >= START_CLEARANCE
    r = world_reachability(w)
    assert r.ok and r.fraction >= 0.99 and r.largest_pocket <= 0.5, r.summary()
    assert r.free_area > 0.6 * g.size[0] * g.size[1]


@pytest.mark.parametrize("level", range(MAX_NOISE + 1))
def test_slam_maps_load_and_stay_reachable(level, gens, tmp_path):
    for style in STYLES:
        g = gens[style]
        path = write_generated(g, tmp_path, level)
        assert path.suffix == ".toml" and path.with_suffix(".pgm").is_file()
        w = load_world(str(path))
        assert w.robot_pose == g.world.robot_pose
        assert w.origin == (-MAP_MARGIN, -MAP_MARGIN)
        assert clearance(w, *w.robot_pose[:2]) >= START_CLEARANCE
        r = world_reachability(w)
        assert r.ok, (style, level, r.summary())
        yaml_only = load_world(str(path.with_suffix(".yaml")))  # start picked automatically
        assert yaml_only.size == w.size


def test_checker_refuses_sealed_and_too_narrow_rooms():
    """Two 4 x 4 m rooms side by side; the door between them decides."""
    def two_rooms(door: float | None) -> World:
        walls = [((0.1, 0.1), (8.1, 0.1)), ((8.1, 0.1), (8.1, 4.1)), ((8.1, 4.1), (0.1, 4.1)),
                 ((0.1, 4.1), (0.1, 0.1))]
        if door is None:
            walls.append(((4.1, 0.1), (4.1, 4.1)))
        else:  # clear opening `door` wide between the wall ends' caps
            walls += [((4.1, 0.1), (4.1, 2.0 - 0.05)), ((4.1, 2.0 + door + 0.05), (4.1, 4.1))]
        return World("two", (8.2, 4.2), (2.0, 2.0, 0.0), segments=walls)

    assert world_reachability(two_rooms(0.7)).ok
    assert world_reachability(two_rooms(0.6)).ok
    for door in (None, 0.45):
        r = world_reachability(two_rooms(door))
        assert not r.ok and r.largest_pocket > 10 and r.fraction < 0.6
    solid = np.zeros((40, 40), bool)
    solid[:, 20:23] = True  # a wall with a one-cell slit (a leak ray) is still closed
    solid[10, 20:23] = False
    assert reachability(solid, RES, start=(0.5, 0.5)).fraction < 0.6


# --- what was placed ----------------------------------------------------------------------


@pytest.mark.parametrize("style", STYLES)
def test_door_widths_in_range_and_open(style):
    for seed in range(3):
        g = generate(style, seed, SMALL[style])
        solid, _, _ = rasterize(g.world, RES)
        doors = g.meta["doors"]
        assert doors or style == "cluttered"
        for d in doors:
            lo, hi, _mode = DOOR_WIDTHS[style][d["kind"]]
            assert lo - 1e-9 <= d["width"] <= hi + 1e-9, d
            x, y = d["center"]
            assert not solid[int(y / RES), int(x / RES)], d  # an opening, not a wall
        if style == "office":
            assert all(d["width"] >= 0.6 - 1e-9 for d in doors)


def test_styles_contain_what_they_promise(gens):
    m = {s: g.meta for s, g in gens.items()}
    office_kinds = {r["kind"] for r in m["office"]["rooms"]}
    assert {"corridor", "room"} <= office_kinds
    assert {"desk", "cabinet"} <= set(m["office"]["items"])
    corridors = [r["rect"] for r in m["office"]["rooms"] if r["kind"] == "corridor"]
    assert all(1.4 - 1e-9 <= min(x1 - x0, y1 - y0) - 0.15 <= 2.5 + 1e-9
               for x0, y0, x1, y1 in corridors)
    legs = [r for _c, r in gens["office"].world.circles if r < 0.1]
    assert legs and all(0.03 - 1e-9 <= r <= 0.05 + 1e-9 for r in legs)
    labels = {r["label"] for r in m["house"]["rooms"]}
    assert {"living", "kitchen"} <= labels and labels & {"bedroom", "study"}
    assert {"bed", "wardrobe"} <= set(m["house"]["items"])
    assert {"shelf", "pallet"} <= set(m["warehouse"]["items"])
    assert [z["kind"] for z in m["warehouse"]["zones"]] == ["loading"]
    assert any(r["label"] == "office" for r in m["warehouse"]["rooms"])
    assert m["warehouse"]["aisles"] and all(1.0 <= a <= 3.0 for a in m["warehouse"]["aisles"])
    assert m["cluttered"]["passages"]
    assert all(0.6 <= p["width"] <= 1.0 for p in m["cluttered"]["passages"])
    angles = [a for _c, _s, a in gens["cluttered"].world.boxes]
    assert sum(1 for a in angles if a != 0.0) > 10 and len(gens["cluttered"].world.circles) > 10


def test_size_respected_and_checked():
    g = generate("warehouse", 0, (60, 8.04))
    assert g.world.size == (60.0, 8.0)
    xs = [p[0] for seg in g.world.segments for p in seg]
    ys = [p[1] for seg in g.world.segments for p in seg]
    assert min(xs) >= 0 and max(xs) <= 60 and min(ys) >= 0 and max(ys) <= 8
    assert generate("house", 0).world.size == DEFAULT_SIZES["house"]
    for bad in ((7.9, 10), (10, 60.5), (10, math.nan), (10,), ("a", 10)):
        with pytest.raises(GenerateError):
            generate("office", 0, bad)
    for args in (("tower", 0), ("office", -1), ("office", 1.5), ("office", True)):
        with pytest.raises(GenerateError):
            check_arguments(*args)
    for level in (-1, MAX_NOISE + 1, 1.0):
        with pytest.raises(GenerateError):
            check_arguments("office", 0, None, level)


# --- SLAM noise ---------------------------------------------------------------------------


def _artefacts(grid: np.ndarray, clean: np.ndarray, size) -> dict[str, int]:
    m = int(round(MAP_MARGIN / RES))
    h, w = int(round(size[1] / RES)), int(round(size[0] / RES))
    outside = np.ones(grid.shape, bool)
    outside[m:m + h, m:m + w] = False
    occ, free = grid == 100, grid == 0
    pad = np.pad(free, 1, constant_values=False)
    free_neighbours = sum(pad[1 + dr:1 + dr + grid.shape[0], 1 + dc:1 + dc + grid.shape[1]]
                          for dr in (-1, 0, 1) for dc in (-1, 0, 1) if dr or dc)
    return {
        "specks": int((occ & (clean == 0) & (free_neighbours >= 7)).sum()),
        "leaks": int((free & outside).sum()),
        "missing": int(((grid == -1) & (clean == 100)).sum()),
        "ragged": int((occ & (clean == 0)).sum()),
    }


def test_noise_artefacts_present_from_level_1_absent_at_0(gens, office_maps):
    g = gens["office"]
    clean = office_maps[0]
    solid, _, _ = rasterize(g.world, RES)
    m = int(round(MAP_MARGIN / RES))
    assert np.array_equal(clean.grid != 0, np.pad(solid, m, constant_values=True))
    assert set(np.unique(clean.grid).tolist()) == {-1, 0, 100}
    assert not any(clean.stats.values())
    seen = [_artefacts(sm.grid, clean.grid, g.size) for sm in office_maps]
    assert not any(seen[0].values())
    for level in range(1, MAX_NOISE + 1):
        assert all(v > 0 for v in seen[level].values()), (level, seen[level])
        assert office_maps[level].stats["leak_rays"] > 0 and office_maps[level].stats["specks"] > 0
    for key in ("specks", "ragged", "missing"):
        assert seen[3][key] > seen[1][key]


def test_noise_keeps_every_door_open(gens, office_maps):
    m = int(round(MAP_MARGIN / RES))
    for sm in office_maps:
        for d in gens["office"].doors:
            x, y = d.center
            r, c = int(y / RES) + m, int(x / RES) + m
            across = sm.grid[r - 3:r + 4, c] if d.horizontal else sm.grid[r, c - 3:c + 4]
            assert (across == 0).all(), (sm.level, d)


def test_map_files_are_trinary_map_server(gens, tmp_path):
    path = write_generated(gens["house"], tmp_path, 2)
    pgm = path.with_suffix(".pgm").read_bytes()
    assert pgm.startswith(b"P5")
    grid, geom = read_map_server(path.with_suffix(".yaml"))
    assert geom.resolution == RES and (geom.origin_x, geom.origin_y) == (-2.0, -2.0)
    assert set(np.unique(grid).tolist()) == {-1, 0, 100}
    assert "map = \"house-s1-14x11-n2.yaml\"" in path.read_text()


# --- corpus and command line --------------------------------------------------------------


def test_corpus_lists_every_combination_in_order(tmp_path):
    entries = generate_corpus(tmp_path, seeds=[0, 1], styles=["house", "cluttered"],
                              noise_levels=[None, 1], sizes=[(10, 9)])
    names = [n for n, _p in entries]
    assert names == ["house-s0-10x9", "house-s0-10x9-n1", "house-s1-10x9", "house-s1-10x9-n1",
                     "cluttered-s0-10x9", "cluttered-s0-10x9-n1", "cluttered-s1-10x9",
                     "cluttered-s1-10x9-n1"]
    assert all(p.is_file() and p.suffix == ".toml" for _n, p in entries)
    assert load_world(str(entries[1][1])).robot_pose == load_world(str(entries[0][1])).robot_pose
    with pytest.raises(GenerateError):
        generate_corpus(tmp_path / "bad", seeds=[0], sizes=[(100, 10)])
    assert not (tmp_path / "bad").exists()


def test_cli_generate_writes_files(tmp_path, capsys):
    assert cli.main(["worlds", "generate", "--style", "cluttered", "--seed", "3", "--size", "10",
                     "9", "--out", str(tmp_path)]) == 0
    assert "cluttered-s3-10x9.toml" in capsys.readouterr().out
    assert cli.main(["worlds", "generate", "--style", "house", "--seed", "3", "--size", "10",
                     "9", "--slam-noise", "1", "--out", str(tmp_path / "maps")]) == 0
    assert sorted(p.name for p in (tmp_path / "maps").iterdir()) == [
        "house-s3-10x9-n1.pgm", "house-s3-10x9-n1.toml", "house-s3-10x9-n1.yaml"]
    load_world(str(tmp_path / "cluttered-s3-10x9.toml"))


@pytest.mark.parametrize("args", [
    ["--style", "tower", "--seed", "1"],
    ["--style", "office", "--seed", "-1"],
    ["--style", "office", "--seed", "x"],
    ["--style", "office", "--seed", "1", "--size", "5", "10"],
    ["--style", "office", "--seed", "1", "--size", "10"],
    ["--style", "office", "--seed", "1", "--size", "inf", "10"],
    ["--style", "office", "--seed", "1", "--slam-noise", "9"],
    ["--style", "office", "--seed", "1", "--slam-noise", "1.5"],
    ["--style", "office", "--seed", "1", "--bogus"],
    ["--seed", "1"],
])
def test_cli_generate_bad_arguments_one_line(args, tmp_path, capsys):
    out = tmp_path / "out"
    assert cli.main(["worlds", "generate", *args, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and err.startswith("topoexplore: worlds")
    assert not out.exists()


def test_cli_generate_refuses_a_file_as_output_and_bad_actions(tmp_path, capsys):
    (tmp_path / "f").write_text("")
    for argv in (["worlds", "generate", "--style", "house", "--seed", "0", "--out",
                  str(tmp_path / "f")], ["worlds", "frobnicate"],
                 ["worlds", "--check", "office", "generate"]):
        assert cli.main(argv) == 2
        assert len(capsys.readouterr().err.strip().splitlines()) == 1


def test_cli_bad_argument_in_a_real_process_has_no_traceback():
    r = subprocess.run([sys.executable, "-m", "topoexplore.tools.cli", "worlds", "generate",
                        "--style", "office", "--seed", "1", "--size", "1", "1", "--out", "x"],
                       cwd=REPO, capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
