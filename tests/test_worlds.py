"""World format, built-in worlds, map_server import, truth rasterization (sim/world.py)."""

from __future__ import annotations

import math
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from topoexplore.sim.world import (
    ROBOT_RADIUS,
    START_CLEARANCE,
    World,
    WorldError,
    builtin_worlds,
    clearance,
    load_world,
    parse_world,
    rasterize,
    truth_free_reachable,
    truth_mappable,
)

MAPS = Path("/work/shared/maps")
EXPECTED = {"paper-room", "dead-end", "junction", "corner", "office", "maze", "small-house",
            "large-office"}


def _explorable_fraction(world: World, res: float = 0.05, clr: float = 0.25) -> float:
    """Share of reachable free cells within reach (clr + 0.3 m) of where the robot fits."""
    solid, ox, oy = rasterize(world, res)
    reach, _, _ = truth_free_reachable(world, res)
    d = cv2.distanceTransform((~solid).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    _, lab = cv2.connectedComponents((d * res >= clr).astype(np.uint8), connectivity=8)
    x, y, _ = world.robot_pose
    area = lab == lab[int((y - oy) / res), int((x - ox) / res)]
    d_area = cv2.distanceTransform((~area).astype(np.uint8), cv2.DIST_L2,
                                   cv2.DIST_MASK_PRECISE) * res
    return float(((d_area <= clr + 0.3) & reach).sum() / reach.sum())


def test_builtin_list():
    names = builtin_worlds()
    assert EXPECTED <= set(names)
    assert all(desc and "\n" not in desc for desc in names.values())


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_builtin_loads_with_free_start(name):
    w = load_world(name)
    assert w.source == f"builtin:{name}"
    x, y, th = w.robot_pose
    xmin, xmax, ymin, ymax = w.extent
    assert xmin < x < xmax and ymin < y < ymax and math.isfinite(th)
    assert clearance(w, x, y) >= START_CLEARANCE
    solid, ox, oy = rasterize(w, 0.1)
    assert not solid[int((y - oy) / 0.1), int((x - ox) / 0.1)]
    reach, _, _ = truth_free_reachable(w, 0.1)
    assert reach.sum() > 100
    assert not (reach & solid).any()


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_builtin_mappable_is_the_free_space(name):
    """The built-in worlds have no gap the robot cannot pass: the free space it can map is
    (nearly) every free cell connected to the start, and never more."""
    w = load_world(name)
    target, ox, oy = truth_mappable(w, 0.1)
    reach, fx, fy = truth_free_reachable(w, 0.1)
    assert (ox, oy) == (fx, fy) and target.shape == reach.shape
    assert not (target & ~reach).any()
    assert target.sum() >= 0.999 * reach.sum()


@pytest.mark.parametrize("name", sorted(EXPECTED - {"large-office"}))
def test_builtin_explorable(name):
    assert _explorable_fraction(load_world(name)) > 0.98


def test_builtin_sizes():
    assert load_world("paper-room").size == (10.0, 10.0)
    w, h = load_world("office").size
    assert w >= 20 and h >= 15
    w, h = load_world("large-office").size
    assert w >= 40 and h >= 40
    assert load_world("large-office").shape_count > 100


def test_paper_room_has_thin_legs():
    w = load_world("paper-room")
    radii = [r for _, r in w.circles]
    assert len(radii) >= 8 and all(0.02 <= r <= 0.05 for r in radii)


@pytest.mark.parametrize("stem", ["small_house", "lse_arena"])
def test_map_server_import(stem):
    w = load_world(str(MAPS / f"{stem}.yaml"))
    img = cv2.imread(str(MAPS / f"{stem}.pgm"), cv2.IMREAD_UNCHANGED)
    res = 0.05
    assert w.size == pytest.approx((img.shape[1] * res, img.shape[0] * res))
    x, y, _ = w.robot_pose
    assert clearance(w, x, y) >= START_CLEARANCE
    assert load_world(str(MAPS / f"{stem}.yaml")).robot_pose == w.robot_pose  # deterministic
    # the shapes rasterize back to the image exactly (not free = solid; border made solid)
    solid, ox, oy = rasterize(w, res)
    assert (ox, oy) == pytest.approx(w.origin)
    expect = ~((255.0 - img) / 255.0 < 0.196)[::-1]  # not free = solid (205 is not free)
    expect[0, :] = expect[-1, :] = expect[:, 0] = expect[:, -1] = True
    assert np.array_equal(solid, expect)
    assert len(w.boxes) < solid.sum() / 10  # merged into a modest number of shapes


def test_small_house_builtin_matches_shared_map():
    a = load_world("small-house")
    b = load_world(str(MAPS / "small_house.yaml"))
    assert a.boxes == b.boxes and a.robot_pose == b.robot_pose and a.origin == (-12.5, -12.5)


def test_rasterize_box_and_wall_exact():
    w = parse_world({"size": [2.0, 1.0], "robot": {"pose": [0.5, 0.5, 0.0]},
                     "boxes": [{"center": [1.5, 0.5], "size": [0.2, 0.2]}],
                     "walls": [{"points": [[1.0, 0.0], [1.0, 1.0]]}], "wall_thickness": 0.05},
                    "t")
    solid, ox, oy = rasterize(w, 0.1)
    assert solid.shape == (10, 20) and (ox, oy) == (0.0, 0.0)
    # wall x in [0.95, 1.05] -> columns 9 and 10; box x, y in [1.4, 1.6] -> cols 14-15, rows 4-5
    expect = np.zeros((10, 20), bool)
    expect[:, 9:11] = True
    expect[4:6, 14:16] = True
    assert np.array_equal(solid, expect)


def test_rasterize_thin_leg_and_diagonal_wall_block_8_connectivity():
    w = parse_world({"size": [3.0, 3.0], "robot": {"pose": [0.5, 2.5, 0.0]},
                     "walls": [{"points": [[0.0, 0.0], [3.0, 3.0]]}],
                     "circles": [{"center": [2.03, 0.51], "radius": 0.02}]}, "t")
    solid, _, _ = rasterize(w, 0.1)
    assert solid[5, 20]  # the 2 cm leg is not lost
    reach, _, _ = truth_free_reachable(w, 0.1)
    assert reach[25, 5] and not reach[5, 25]  # the diagonal wall separates the halves


def test_rasterize_rotated_box():
    w = parse_world({"size": [4.0, 4.0], "robot": {"pose": [0.5, 0.5, 0.0]},
                     "boxes": [{"center": [2.0, 2.0], "size": [1.0, 1.0],
                                "angle": math.pi / 4}]}, "t")
    solid, _, _ = rasterize(w, 0.1)
    h = math.sqrt(0.5)  # the diamond reaches x = 2 +- 0.707
    assert solid[20, int((2.0 + h - 0.05) / 0.1)] and not solid[20, int((2.0 + h + 0.1) / 0.1)]
    assert not solid[int((2.0 + 0.45) / 0.1), int((2.0 + 0.45) / 0.1)]  # corner cut off
    assert 80 <= solid.sum() <= 160  # area 1 m^2 = 100 cells, plus boundary cells


def test_rasterize_bad_resolution():
    with pytest.raises(WorldError):
        rasterize(load_world("corner"), 0.0)


def _write(tmp: Path, name: str, text: str) -> str:
    p = tmp / name
    p.write_text(text)
    return str(p)


ROOM = """size = [4, 4]
[robot]
pose = [1, 1, 0]
[[walls]]
points = [[0, 0], [4, 0], [4, 4], [0, 4]]
closed = true
"""

BAD = {
    "bad_toml": ("size = [4, 4\n", "not valid TOML"),
    "no_size": ("[robot]\npose = [1, 1, 0]\n", "missing size"),
    "neg_size": (ROOM.replace("size = [4, 4]", "size = [-4, 4]"), "positive"),
    "str_size": (ROOM.replace("size = [4, 4]", 'size = ["a", 4]'), "finite number"),
    "no_pose": ("size = [4, 4]\n", "missing [robot] pose"),
    "short_pose": (ROOM.replace("pose = [1, 1, 0]", "pose = [1, 1]"), "list of 3"),
    "unknown_key": (ROOM + "colour = 3\n", "unknown key"),
    "unknown_wall_key": (ROOM.replace("closed = true", "closed = true\nheight = 2"),
                         "unknown key"),
    "robot_in_wall": (ROOM.replace("pose = [1, 1, 0]", "pose = [0.1, 2, 0]"), "wall"),
    "robot_outside": (ROOM.replace("pose = [1, 1, 0]", "pose = [9, 1, 0]"), "outside"),
    "robot_in_box": (ROOM + "[[boxes]]\ncenter = [1, 1]\nsize = [0.5, 0.5]\n", "wall"),
    "neg_radius": (ROOM + "[[circles]]\ncenter = [2, 2]\nradius = -0.1\n", "positive"),
    "wall_one_point": (ROOM + "[[walls]]\npoints = [[1, 1]]\n", ">= 2"),
    "wall_outside": (ROOM + "[[walls]]\npoints = [[1, 1], [7, 1]]\n", "outside"),
    "closed_not_bool": (ROOM.replace("closed = true", 'closed = "yes"'), "true or false"),
    "walls_not_tables": ("walls = 3\nsize = [4, 4]\n[robot]\npose = [1, 1, 0]\n",
                         "array of tables"),
    "missing_map": ('map = "nope.yaml"\n', "not found"),
    "map_and_size": ('map = "nope.yaml"\nsize = [1, 1]\n', "either size or map"),
    "neg_wall_thickness": ("wall_thickness = -1\n" + ROOM, "wall_thickness"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_world_files(tmp_path, case):
    text, needle = BAD[case]
    path = _write(tmp_path, f"{case}.toml", text)
    with pytest.raises(WorldError) as ei:
        load_world(path)
    msg = str(ei.value)
    assert "\n" not in msg and needle in msg and path in msg


def test_good_room_file_loads(tmp_path):
    w = load_world(_write(tmp_path, "room.toml", ROOM))
    assert w.name == "room" and len(w.segments) == 4 and w.robot_pose == (1.0, 1.0, 0.0)


def test_missing_file_and_unknown_name(tmp_path):
    with pytest.raises(WorldError, match="not found"):
        load_world(str(tmp_path / "none.toml"))
    with pytest.raises(WorldError, match="unknown world"):
        load_world("no-such-world")


def test_map_world_errors(tmp_path):
    shutil.copy(MAPS / "lse_arena.yaml", tmp_path / "a.yaml")
    with pytest.raises(WorldError, match="not found"):  # image missing next to the YAML
        load_world(str(tmp_path / "a.yaml"))
    (tmp_path / "b.yaml").write_text("image: x.pgm\nresolution: 0.05\n")
    with pytest.raises(WorldError, match="missing"):
        load_world(str(tmp_path / "b.yaml"))
    # a TOML on top of a map, with a given pose inside a wall
    shutil.copy(MAPS / "lse_arena.pgm", tmp_path / "lse_arena.pgm")
    shutil.copy(MAPS / "lse_arena.yaml", tmp_path / "lse_arena.yaml")
    p = _write(tmp_path, "m.toml", 'map = "lse_arena.yaml"\n[robot]\npose = [0.01, 0.01, 0]\n')
    with pytest.raises(WorldError, match="outside|wall"):
        load_world(p)
    p = _write(tmp_path, "ok.toml", 'map = "lse_arena.yaml"\n[[circles]]\n'
               'center = [1.0, 1.0]\nradius = 0.1\n')
    w = load_world(p)
    assert w.circles == [((1.0, 1.0), 0.1)] and w.origin == (0.0, 0.0)
    assert clearance(w, *w.robot_pose[:2]) >= ROBOT_RADIUS
