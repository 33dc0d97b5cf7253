"""The free space the robot can map (sim/world.py::truth_mappable) and the two coverage figures
the runners report (``coverage`` on it, ``coverage_free`` on every free cell connected to the
start): docs/design.md "Measuring a run"."""

from __future__ import annotations

import json

import numpy as np
import pytest

from topoexplore.common import convert
from topoexplore.common import messages as m
from topoexplore.common.domain import GridMap
from topoexplore.common.grid import GridGeometry
from topoexplore.common.params import LaserParams, RobotParams, load_params
from topoexplore.sim import rays as rk
from topoexplore.sim import world as W
from topoexplore.sim.world import (
    WorldError,
    parse_world,
    rasterize,
    truth_free_reachable,
    truth_mappable,
    truth_robot_positions,
)

RES = 0.1
FREE, OCC, UNK = 0, 100, -1


def two_rooms(gap: float, y0: float = 3.0, thick: float = 0.5) -> dict:
    """10 m x 6 m, robot in the left room; the wall between the rooms (``thick`` metres, centred
    on x = 5) has an opening of ``gap`` metres from y = y0."""
    top = 6.0 - (y0 + gap)
    return {"name": f"gap{gap}", "size": [10.0, 6.0], "robot": {"pose": [2.0, 3.0, 0.0]},
            "walls": [{"points": [[0, 0], [10, 0], [10, 6], [0, 6]], "closed": True}],
            "boxes": [{"center": [5.0, y0 / 2], "size": [thick, y0]},
                      {"center": [5.0, y0 + gap + top / 2], "size": [thick, top]}]}


def right_room(free: np.ndarray, thick: float = 0.5) -> np.ndarray:
    """The cells beyond the wall between the rooms."""
    out = np.zeros_like(free)
    out[:, int(round((5.0 + thick / 2) / RES)):] = True
    return out & free


def sets(data: dict, laser_range: float = 8.0):
    w = parse_world(data, "t")
    free, _, _ = truth_free_reachable(w, RES)
    pos, _, _ = truth_robot_positions(w, RES)
    target, _, _ = truth_mappable(w, RES, 0.2, laser_range)
    return free, pos, target


def test_defaults_are_the_robot_and_laser_parameters():
    assert W.ROBOT_RADIUS == RobotParams().radius and W.LASER_RANGE == LaserParams().range_max


def test_room_behind_a_narrow_gap_counts_only_where_seen_through_it():
    free, pos, target = sets(two_rooms(0.3))  # gap rows 30-32 through columns 48-52
    right = right_room(free)
    assert right.sum() > 2500  # 8-connected through the gap: the old set holds the room
    assert not (pos & right).any()  # the robot does not fit through
    seen = target & right
    assert seen[30:33, 53:99].all()  # the cells in sight through the gap count ...
    assert not seen[:25, 53:56].any() and not seen[38:, 53:56].any()  # ... not along the wall
    assert 0.3 * right.sum() < seen.sum() < 0.6 * right.sum()


def test_room_behind_a_door_counts():
    free, pos, target = sets(two_rooms(0.6, y0=3.03))  # 0.6 m, not on cell borders
    assert (pos & right_room(free)).any()
    assert np.array_equal(target, free)


@pytest.mark.parametrize("gap, y0, passes", [(0.4, 3.0, False), (0.5, 3.0, True),
                                             (0.5, 3.05, False), (0.6, 3.07, True)])
def test_gap_width_the_robot_passes(gap, y0, passes):
    w = parse_world(two_rooms(gap, y0, thick=0.1), "t")
    pos, _, _ = truth_robot_positions(w, RES)
    assert pos[:, 52:].any() == passes


def test_leak_slit_is_seen_through_but_not_passed():
    free, pos, target = sets(two_rooms(0.1))  # one row of free cells through the wall
    right = right_room(free)
    assert right.sum() > 2500  # 8-connected through the slit: the old set holds the room
    assert not (pos & right).any()
    seen = target & right
    assert seen[30, 53:99].all()  # along the slit
    assert not seen[:27, 53:56].any() and not seen[34:, 53:56].any()
    assert 0 < seen.sum() < 0.25 * right.sum()


def test_disc_covers_the_cells_along_walls():
    """With a laser range below one cell only the disc counts: every free cell along the walls
    of a room, but not the room's corner cells, which no disc of 0.2 m reaches."""
    data = {"size": [4.0, 3.0], "robot": {"pose": [2.0, 1.5, 0.0]},
            "walls": [{"points": [[0, 0], [4, 0], [4, 3], [0, 3]], "closed": True}]}
    free, pos, disc = sets(data, laser_range=0.05)
    rr, cc = np.nonzero(free)
    r0, r1, c0, c1 = rr.min(), rr.max(), cc.min(), cc.max()
    corners = [(r0, c0), (r0, c1), (r1, c0), (r1, c1)]
    assert all(not disc[rc] for rc in corners)
    edge = free.copy()
    edge[r0 + 1:r1, c0 + 1:c1] = False  # the ring of cells along the walls
    for rc in corners:
        edge[rc] = False
    assert disc[edge].all()
    _, _, target = sets(data)
    assert np.array_equal(target, free)  # the laser sees the corners


def test_robot_that_cannot_move_maps_from_where_it_stands():
    data = {"size": [1.0, 1.0], "robot": {"pose": [0.275, 0.275, 0.0]},
            "walls": [{"points": [[0, 0], [0.55, 0], [0.55, 0.55], [0, 0.55]], "closed": True}]}
    free, pos, target = sets(data)
    assert pos.sum() == 1 and free.sum() == 16
    assert np.array_equal(target, free)


def test_start_next_to_a_wall_finds_the_nearest_position():
    data = {"size": [4.0, 3.0], "robot": {"pose": [0.26, 1.5, 0.0]},  # clearance 0.21 m
            "walls": [{"points": [[0, 0], [4, 0], [4, 3], [0, 3]], "closed": True}]}
    pos, _, _ = truth_robot_positions(parse_world(data, "t"), RES)
    assert not pos[15, 2] and pos.sum() > 100 and pos[15, 3]


def test_bad_arguments():
    w = parse_world(two_rooms(0.6), "t")
    for kw in ({"radius": 0.0}, {"radius": float("nan")}, {"laser_range": -1.0}):
        with pytest.raises(WorldError):
            truth_mappable(w, RES, **kw)


@pytest.mark.parametrize("n", [1, 7, 80])
def test_rays_pass_every_cell_of_the_square(n):
    rays = rk.ray_table(rk.square_border(n))
    assert rays.shape == (8 * n, n + 1, 2)
    seen = np.zeros((2 * n + 1, 2 * n + 1), bool)
    seen[rays[:, :, 0] + n, rays[:, :, 1] + n] = True
    assert seen.all()


def _brute_force(w, laser_range: float) -> np.ndarray:
    """Disc cells, plus every ray of the table cast from every position and from every other
    cell (numpy, no pruning): what truth_mappable must give."""
    solid, _, _ = rasterize(w, RES)
    comp = W._free_component(w, solid, *w.origin, RES)
    pos, _, _ = truth_robot_positions(w, RES)
    disc = W._dilate(pos, W.disc_kernel(0.2, RES), outside=0) & comp
    n = int(laser_range / RES + 1e-6)
    rays = rk.ray_table(rk.square_border(n))
    h, wd = solid.shape
    out = disc.copy()
    for src, forward in ((np.argwhere(pos), True), (np.argwhere(comp & ~disc), False)):
        for k in range(rays.shape[0]):
            alive = np.ones(len(src), bool)
            for dr, dc in rays[k, 1:]:
                r, c = src[:, 0] + dr, src[:, 1] + dc
                inside = (r >= 0) & (r < h) & (c >= 0) & (c < wd)
                alive &= inside & (dr * dr + dc * dc <= (laser_range / RES) ** 2 + 1e-6)
                alive[alive] &= ~solid[r[alive], c[alive]]
                if forward:
                    out[r[alive], c[alive]] = True
                else:
                    hit = alive.copy()
                    hit[alive] = pos[r[alive], c[alive]]
                    out[src[hit, 0], src[hit, 1]] = True
                    alive &= ~hit
    return out & comp


@pytest.mark.parametrize("gap, thick", [(0.1, 0.5), (0.3, 0.1), (0.3, 0.5)])
def test_pruned_computation_equals_casting_every_ray(gap, thick):
    w = parse_world(two_rooms(gap, thick=thick), "t")
    target, _, _ = truth_mappable(w, RES, 0.2, 2.5)
    assert np.array_equal(target, _brute_force(w, 2.5))


# -- the runners report both figures ---------------------------------------------------------


def _grid_msg(known: np.ndarray, solid: np.ndarray) -> m.OccupancyGrid:
    data = np.where(known, np.where(solid, OCC, FREE), UNK).astype(np.int8)
    geom = GridGeometry(RES, 0.0, 0.0, known.shape[1], known.shape[0])
    return convert.grid_to_msg(GridMap(data, geom),
                               m.header(0, 0.0, "map", 0))


def test_run_truth_and_report_give_both_coverages(tmp_path):
    from topoexplore.tools.run import Monitor, Truth, make_report

    path = tmp_path / "gap.toml"
    data = two_rooms(0.3)
    text = 'name = "gap"\nsize = [10.0, 6.0]\n[robot]\npose = [2.0, 3.0, 0.0]\n'
    for kind in ("walls", "boxes"):
        for item in data[kind]:
            text += f"[[{kind}]]\n" + "".join(f"{k} = {json.dumps(v)}\n"
                                              for k, v in item.items())
    path.write_text(text)
    p = load_params(None, [])
    truth = Truth(str(path), p)
    assert truth.target.sum() < truth.free.sum() and not (truth.target & ~truth.free).any()
    msg = _grid_msg(truth.target, truth.occ)  # the map knows exactly the mappable cells
    assert truth.coverage(msg, p) == 1.0
    assert truth.coverage_free(msg, p) == pytest.approx(truth.target.sum() / truth.free.sum())
    report = make_report(world="gap", strategy="frontier", seed=0, finished=True,
                         stop_reason="done", mon=Monitor(), sim=None, wall=1.0, startup=1.0,
                         coverage=truth.coverage(msg, p),
                         coverage_free=truth.coverage_free(msg, p), accuracy=1.0, restarts=0,
                         bad_messages=0, p_reliable=0.9, lockstep=True)
    assert report["coverage"] == 1.0
    assert report["coverage_free"] == round(truth.target.sum() / truth.free.sum(), 4) < 0.95


def test_inproc_reports_both_coverages():
    from topoexplore.tools.bench import inproc

    r = inproc.run("dead-end", "frontier", 0, max_sim_time=20.0)
    assert 0.0 < r["coverage_free"] <= r["coverage"] <= 1.0
    stages = r["stage_s"]  # compute per core: every core ran, and within the run's wall time
    assert set(stages) == {"sim", "mapper", "topology", "reliability", "planner", "controller"}
    assert all(v > 0.0 for v in stages.values())
    assert sum(stages.values()) <= r["wall_s"] + 0.1
    line = inproc.stage_line([r, r])
    assert line.startswith("compute per stage, summed over the runs: sim ")
    assert f"planner {2 * stages['planner']:.1f} s" in line
    assert inproc.stage_line([{"stage_s": None}]) == "compute per stage: none measured"
    stub = inproc._one(("x", "no-such-world", "frontier", 0, (), 10.0, False))
    assert stub["state"] == "error" and stub["coverage"] is None and stub["coverage_free"] is None


def test_inproc_prints_each_run_as_it_finishes(capsys, tmp_path):
    """`bench inproc` prints a run's line as soon as the run is in (in the order asked), then
    the summary, and writes the same runs to --json."""
    from topoexplore.tools.bench import inproc

    out = tmp_path / "r.json"
    assert inproc.main(["--worlds", "dead-end,corner", "--strategies", "frontier", "--seeds",
                        "1", "--jobs", "1", "--max-sim-time", "5", "--json", str(out)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("dead-end ") and lines[1].startswith("corner ")
    assert all(" path " in ln and " wall " in ln for ln in lines[:2])
    assert lines[2].startswith("compute per stage")
    runs = json.loads(out.read_text())["runs"]
    assert [r["world_label"] for r in runs] == ["dead-end", "corner"]
    assert inproc.run_line(runs[0]) == lines[0]
