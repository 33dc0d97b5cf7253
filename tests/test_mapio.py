"""common.mapio: map_server reader/writer and PNG writer."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from topoexplore.common import mapio
from topoexplore.common.grid import FREE, OCCUPIED, UNKNOWN, GridGeometry, classify
from topoexplore.common.mapio import (
    PIX_FREE,
    PIX_OCCUPIED,
    PIX_UNKNOWN,
    MapIOError,
    parse_yaml,
    pixels_to_occupancy,
    read_map_server,
    unrotate,
    write_map_server,
    write_png,
)

MAPS = Path("/work/shared/maps")
needs_maps = pytest.mark.skipif(not MAPS.is_dir(), reason="shared maps not available")


def _yaml(tmp_path: Path, body: str, image: np.ndarray | None = None, name="m") -> Path:
    if image is not None:
        assert cv2.imwrite(str(tmp_path / f"{name}.pgm"), image)
    p = tmp_path / f"{name}.yaml"
    p.write_text(body)
    return p


GOOD = (
    "image: m.pgm\nresolution: 0.1\norigin: [1.0, -2.0, 0.0]\nnegate: 0\n"
    "occupied_thresh: 0.65\nfree_thresh: 0.196\n"
)


# --- round trips -----------------------------------------------------------------------------


@pytest.mark.parametrize("seed", range(5))
def test_round_trip_random_grids(tmp_path, seed):
    rng = np.random.default_rng(seed)
    h, w = rng.integers(1, 60, size=2)
    grid = rng.integers(-1, 101, size=(h, w)).astype(np.int8)
    geom = GridGeometry(0.1, float(rng.uniform(-50, 50)), float(rng.uniform(-50, 50)), w, h)
    y, pgm = write_map_server(tmp_path / "out" / "map.yaml", grid, geom)
    assert y.is_file() and pgm.is_file() and pgm.suffix == ".pgm"
    back, geom2 = read_map_server(y)
    assert geom2 == geom  # exact, even for origins that need more than 6 decimals
    assert back.dtype == np.int8 and back.shape == grid.shape
    assert np.array_equal(classify(back), classify(grid))
    assert set(np.unique(back)) <= {-1, 0, 100}


def test_round_trip_custom_thresholds(tmp_path):
    grid = np.array([[10, 30, 50, 70, -1]], np.int8)
    geom = GridGeometry(0.05, 0.0, 0.0, 5, 1)
    y, _ = write_map_server(tmp_path / "m.yaml", grid, geom, p_free=0.2, p_occ=0.6)
    back, _ = read_map_server(y)
    assert back.tolist() == [[0, -1, -1, 100, -1]]


def test_written_pgm_is_trinary_p5_top_row_is_max_y(tmp_path):
    grid = np.full((3, 4), -1, np.int8)
    grid[0, :] = 0  # bottom row (min y) free
    grid[2, 0] = 100  # top-left occupied
    y, pgm = write_map_server(tmp_path / "m.yaml", grid, GridGeometry(0.1, 0, 0, 4, 3))
    raw = pgm.read_bytes()
    assert raw.startswith(b"P5\n")
    img = cv2.imread(str(pgm), cv2.IMREAD_UNCHANGED)
    assert img.shape == (3, 4) and img.dtype == np.uint8
    assert img[0, 0] == PIX_OCCUPIED and (img[2, :] == PIX_FREE).all()
    assert img[1, 1] == PIX_UNKNOWN
    text = y.read_text()
    for key in ("image: m.pgm", "resolution:", "origin: [", "negate: 0", "occupied_thresh:",
                "free_thresh:", "mode: trinary"):
        assert key in text


# --- the shared real maps ----------------------------------------------------------------------


@needs_maps
@pytest.mark.parametrize(
    "name, shape, res, origin",
    [("lse_arena", (60, 80), 0.05, (0.0, 0.0)), ("small_house", (500, 500), 0.05, (-12.5, -12.5))],
)
def test_read_shared_maps(tmp_path, name, shape, res, origin):
    grid, geom = read_map_server(MAPS / f"{name}.yaml")
    assert grid.shape == shape and (geom.height, geom.width) == shape
    assert geom.resolution == res and (geom.origin_x, geom.origin_y) == origin
    raw = cv2.imread(str(MAPS / f"{name}.pgm"), cv2.IMREAD_UNCHANGED)
    # thresholds 0.65 / 0.196, negate 0: occ = (255 - v) / 255
    occ = (255.0 - raw) / 255.0
    n_occ, n_free = int((occ > 0.65).sum()), int((occ < 0.196).sum())
    assert int((grid == 100).sum()) == n_occ
    assert int((grid == 0).sum()) == n_free
    assert int((grid == -1).sum()) == raw.size - n_occ - n_free
    # image row 0 is the top: grid row 0 is the image's last row
    assert np.array_equal(grid[0] == 100, raw[-1] == 0)
    # write back and re-read identical
    y, _ = write_map_server(tmp_path / f"{name}.yaml", grid, geom)
    grid2, geom2 = read_map_server(y)
    assert geom2 == geom and np.array_equal(grid2, grid)


@needs_maps
def test_shared_map_counts():
    g, _ = read_map_server(MAPS / "lse_arena.yaml")  # 255 and 239 are both free there
    assert (g == -1).sum() == 0 and (g == 100).sum() == 345 and (g == 0).sum() == 4455
    g, _ = read_map_server(MAPS / "small_house.yaml")
    assert [(g == v).sum() for v in (0, 100, -1)] == [63021, 3442, 183537]


# --- nav2 semantics ----------------------------------------------------------------------------


def test_negate_and_thresholds():
    img = np.array([[0, 100, 200, 255]], np.uint8)
    # negate 0: occ = 1 - v/255 = 1.0, 0.61, 0.22, 0.0
    assert pixels_to_occupancy(img, False, 0.6, 0.25).tolist() == [[100, 100, 0, 0]]
    assert pixels_to_occupancy(img, False, 0.65, 0.2).tolist() == [[100, -1, -1, 0]]
    # negate 1: occ = v/255 = 0, 0.39, 0.78, 1
    assert pixels_to_occupancy(img, True, 0.65, 0.2).tolist() == [[0, -1, 100, 100]]


def test_scale_and_raw_modes():
    img = np.array([[255, 128, 0]], np.uint8)  # occ 0, 0.498, 1
    out = pixels_to_occupancy(img, False, 0.9, 0.1, "scale")
    assert out[0, 0] == 0 and out[0, 2] == 100
    assert out[0, 1] == int(np.rint((1 - 128 / 255 - 0.1) / 0.8 * 100))
    raw = pixels_to_occupancy(np.array([[0, 42, 100, 101, 255]], np.uint8), False, 0.65, 0.2,
                              "raw")
    assert raw.tolist() == [[0, 42, 100, -1, -1]]
    bgra = np.zeros((1, 2, 4), np.uint8)
    bgra[..., :3] = 128
    bgra[0, 0, 3] = 255
    bgra[0, 1, 3] = 0  # transparent -> unknown in scale mode
    out = pixels_to_occupancy(bgra, False, 0.9, 0.1, "scale")
    assert out[0, 1] == -1 and out[0, 0] >= 0


def test_color_png_map(tmp_path):
    img = np.zeros((2, 2, 3), np.uint8)
    img[0, 0] = 255
    img[1, 1] = (205, 205, 205)
    assert cv2.imwrite(str(tmp_path / "c.png"), img)
    y = _yaml(tmp_path, GOOD.replace("m.pgm", "c.png"), name="c")
    g, geom = read_map_server(y)
    assert (geom.origin_x, geom.origin_y, geom.width, geom.height) == (1.0, -2.0, 2, 2)
    # flipped: grid row 1 = image row 0
    assert g[1, 0] == 0 and g[0, 1] == -1 and g[1, 1] == 100 and g[0, 0] == 100


def test_yaml_parser():
    d = parse_yaml("# c\nimage: 'a b.pgm'  # x\nn: 3\nf: -1.5e-2\nl: [1, 2.5, 0]\nb: true\n"
                   "e: 1e-2\n")
    assert d == {"image": "a b.pgm", "n": 3, "f": -0.015, "l": [1, 2.5, 0], "b": True, "e": 0.01}
    assert parse_yaml("a:\n  b: 1\n") == {"a": {"b": 1}}  # nested YAML is YAML
    assert parse_yaml("") == {} and parse_yaml("# only a comment\n") == {}
    with pytest.raises(MapIOError, match="duplicate key 'a'"):
        parse_yaml("a: 1\na: 2\n")


BLOCK_ORIGIN = (
    "# saved by hand\nimage: m.pgm   # the picture\nresolution: 0.1\norigin:\n  - 1.0\n"
    "  - -2.0\n  - 0.0\nnegate: 0\noccupied_thresh: 0.65\nfree_thresh: 0.196\n"
)


@pytest.mark.parametrize("body", [
    BLOCK_ORIGIN,
    BLOCK_ORIGIN.replace("  - ", "- "),  # block list at the key's indentation
    "{image: m.pgm, resolution: 0.1, origin: [1.0, -2.0, 0.0], negate: 0,\n"
    " occupied_thresh: 0.65, free_thresh: 0.196}\n",  # flow style
    "---\n" + GOOD.replace("0.1", "1e-1", 1) + "...\n",  # markers, YAML 1.2 float
])
def test_valid_yaml_styles_read_the_same(tmp_path, body):
    want = read_map_server(_yaml(tmp_path, GOOD, np.full((2, 3), 254, np.uint8)))
    grid, geom = read_map_server(_yaml(tmp_path, body, name="other"))  # same m.pgm
    assert geom == want[1] and np.array_equal(grid, want[0])
    assert (geom.resolution, geom.origin_x, geom.origin_y) == (0.1, 1.0, -2.0)


def test_written_yaml_is_plain_map_server_yaml(tmp_path):
    geom = GridGeometry(0.05, -12.5, 1 / 3, 4, 3)
    y, _ = write_map_server(tmp_path / "m.yaml", np.zeros((3, 4), np.int8), geom)
    assert yaml.safe_load(y.read_text()) == {
        "image": "m.pgm", "resolution": 0.05, "origin": [-12.5, 1 / 3, 0.0], "negate": 0,
        "occupied_thresh": 0.65, "free_thresh": 0.196, "mode": "trinary"}
    assert list(yaml.safe_load(y.read_text()))[0] == "image"  # map_server's key order
    assert "origin: [-12.5, 0.3333333333333333, 0.0]\n" in y.read_text()


# --- strictness --------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "body, match",
    [
        (GOOD.replace("resolution: 0.1\n", ""), "missing key"),
        (GOOD.replace("negate: 0\n", ""), "missing key.*negate"),
        (GOOD.replace("0.1", "-0.1", 1), "resolution"),
        (GOOD.replace("resolution: 0.1", "resolution: abc"), "resolution"),
        (GOOD.replace("[1.0, -2.0, 0.0]", "[1.0, -2.0]"), "origin"),
        (GOOD.replace("negate: 0", "negate: 2"), "negate"),
        (GOOD.replace("free_thresh: 0.196", "free_thresh: 0.9"), "free_thresh"),
        (GOOD + "mode: fancy\n", "mode"),
        (GOOD.replace("m.pgm", "missing.pgm"), "not found"),
        ("just text\n", "expected 'key: value'"),
        ("- image: m.pgm\n- resolution: 0.1\n", "expected 'key: value'.*list"),
        (GOOD + "origin: [0, 0, 0]\n", "duplicate key 'origin'"),
        (GOOD.replace("[1.0, -2.0, 0.0]", "[1.0, -2.0, 0.0"), "not valid YAML.*line 4"),
        ("image: m.pgm\n  resolution: 0.1\n", "not valid YAML"),
        (GOOD + "\tmode: trinary\n", "not valid YAML"),
        (GOOD.replace("origin: [1.0, -2.0, 0.0]", "origin:\n  - 1.0\n  - .nan\n  - 0.0"),
         "origin"),
        (GOOD.replace("origin: [1.0, -2.0, 0.0]", "origin: {x: 1.0, y: -2.0, yaw: 0.0}"),
         "origin"),
    ],
)
def test_bad_yaml_is_one_line_error(tmp_path, body, match):
    y = _yaml(tmp_path, body, np.full((2, 2), 254, np.uint8))
    with pytest.raises(MapIOError, match=match) as exc:
        read_map_server(y)
    assert "\n" not in str(exc.value)


def test_missing_yaml_and_undecodable_image(tmp_path):
    with pytest.raises(MapIOError, match="not found"):
        read_map_server(tmp_path / "nope.yaml")
    (tmp_path / "m.pgm").write_bytes(b"not an image")
    with pytest.raises(MapIOError, match="cannot decode"):
        read_map_server(_yaml(tmp_path, GOOD))


def test_write_rejects_bad_input(tmp_path):
    geom = GridGeometry(0.1, 0, 0, 3, 2)
    with pytest.raises(MapIOError, match="shape"):
        write_map_server(tmp_path / "m.yaml", np.zeros((3, 3), np.int8), geom)
    with pytest.raises(MapIOError, match="integer"):
        write_map_server(tmp_path / "m.yaml", np.zeros((2, 3), np.float32), geom)
    with pytest.raises(MapIOError, match=".yaml"):
        write_map_server(tmp_path / "m.pgm", np.zeros((2, 3), np.int8), geom)


def test_write_png(tmp_path):
    img = np.zeros((5, 7, 3), np.uint8)
    img[1, 2] = (10, 20, 30)
    p = write_png(tmp_path / "sub" / "a.png", img)
    back = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    assert np.array_equal(back, img)
    with pytest.raises(MapIOError):
        write_png(tmp_path / "b.png", np.zeros((5, 7), np.float32))
    with pytest.raises(MapIOError):
        write_png(tmp_path / "b.jpg", img)


def test_classes_constant_names():
    assert (UNKNOWN, FREE, OCCUPIED) == (0, 1, 2)


# --- a turned origin (map_server's yaw) ----------------------------------------------------------


def test_a_quarter_turn_is_exact(tmp_path):
    """yaw = 90 deg: the map's x axis points along the world's y. The image's bottom-left
    pixel keeps its corner at the origin; each cell lands where its centre turns to."""
    img = np.full((2, 3), 254, np.uint8)  # 2 rows x 3 columns; row 0 is the top
    img[1, 0] = 0  # bottom-left: occupied
    img[0, 2] = 205  # top-right: unknown
    body = GOOD.replace("[1.0, -2.0, 0.0]", f"[1.0, -2.0, {np.pi / 2!r}]")
    grid, geom = read_map_server(_yaml(tmp_path, body, img))
    assert (geom.width, geom.height) == (2, 3)
    assert geom.origin_x == pytest.approx(0.8) and geom.origin_y == pytest.approx(-2.0)
    # the occupied cell: map-frame centre (0.05, 0.05) -> world (1 - 0.05, -2 + 0.05)
    r, c = geom.world_to_cell(0.95, -1.95)
    assert grid[int(r), int(c)] == 100
    # the unknown one: map-frame centre (0.25, 0.15) -> world (1 - 0.15, -2 + 0.25)
    r, c = geom.world_to_cell(0.85, -1.75)
    assert grid[int(r), int(c)] == -1
    assert int((grid == 0).sum()) == 4 and int((grid == -1).sum()) == 1


@pytest.mark.parametrize("yaw", [0.3, -1.0, 2.5])
def test_a_turned_map_keeps_every_place_where_it_was(yaw, monkeypatch):
    """Any yaw, a map of rooms and walls (blocks of 5 x 5 cells): the centre of every cell
    at least a cell away from a block edge, turned into the world, falls in an output cell
    with its value (nearest sampling moves an edge by up to a cell, nothing more), and the
    area of each class is kept within a few %."""
    rng = np.random.default_rng(7)
    blocks = rng.choice(np.array([0, 100, -1], np.int8), size=(8, 12), p=[0.6, 0.3, 0.1])
    src = np.kron(blocks, np.ones((5, 5), np.int8))
    res, x, y = 0.1, 3.0, -4.0
    out, geom = unrotate(src, res, x, y, yaw)
    monkeypatch.setattr(mapio, "UNROTATE_ROWS", 7)  # in blocks of rows: the same grid
    again, geom2 = unrotate(src, res, x, y, yaw)
    assert geom2 == geom and np.array_equal(again, out)
    r, c = np.mgrid[0:40, 0:60]
    inner = (r % 5 >= 1) & (r % 5 <= 3) & (c % 5 >= 1) & (c % 5 <= 3)
    u, v = (c[inner] + 0.5) * res, (r[inner] + 0.5) * res
    wx = x + np.cos(yaw) * u - np.sin(yaw) * v
    wy = y + np.sin(yaw) * u + np.cos(yaw) * v
    rr, cc = geom.world_to_cell(wx, wy)
    assert np.array_equal(out[rr.astype(int), cc.astype(int)], src[inner])
    for value in (0, 100):
        assert (out == value).sum() == pytest.approx((src == value).sum(), rel=0.05)
    assert geom.resolution == res and out.dtype == np.int8
