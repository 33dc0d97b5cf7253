"""tools.draw: pure BGR rendering of grid, graph, reliabilities and trail."""

from __future__ import annotations

import math

import numpy as np
import pytest

from topoexplore.common.domain import Belief, Graph, Node
from topoexplore.common.grid import GridGeometry
from topoexplore.tools.draw import (
    COL_BRANCH,
    COL_CORNER,
    COL_EDGE,
    COL_END,
    COL_END_RELIABLE,
    COL_FREE,
    COL_OCCUPIED,
    COL_TARGET,
    COL_TRUTH,
    COL_UNCERTAIN,
    COL_UNKNOWN,
    TITLE_H,
    TRAIL_COLOURS,
    Overlays,
    RenderError,
    Style,
    choose_scale,
    crop_to_content,
    make_frame,
    render,
)


def grid_and_geom(w=60, h=40):
    g = np.full((h, w), -1, np.int8)
    g[5:35, 5:55] = 0  # free room
    g[5:35, 5] = 100  # a wall on its left side (x ~ 0.5 m)
    g[20, 30] = 50  # uncertain
    return g, GridGeometry(0.1, -1.0, 2.0, w, h)


def px(img, uv):
    u, v = uv
    return tuple(int(c) for c in img[int(round(float(v))), int(round(float(u)))])


def cell_centre(geom, r, c):
    return geom.cell_to_world(r, c)


def test_shape_dtype_and_default_scale():
    g, geom = grid_and_geom()
    img = render(g, geom)
    f = make_frame(g, geom)
    assert img.dtype == np.uint8 and img.ndim == 3 and img.shape[2] == 3
    assert f.scale == math.ceil(800 / 60)  # long side raised to >= 800 px
    assert img.shape[1] == max(f.map_w, 720) and img.shape[0] > TITLE_H + f.map_h
    assert f.map_w >= 800


def test_choose_scale():
    assert choose_scale(200, 100) == 6.0
    assert choose_scale(50, 50) == 16.0
    assert choose_scale(1000, 1000) == 2.0  # capped at 2400 px
    assert choose_scale(5000, 100) == pytest.approx(2400 / 5000)
    assert choose_scale(10, 10, px_per_cell=3) == 3.0
    with pytest.raises(RenderError):
        choose_scale(10, 10, px_per_cell=0)


def test_cell_colours_and_y_axis_up():
    g, geom = grid_and_geom()
    img = render(g, geom, style=Style(px_per_cell=5))
    f = make_frame(g, geom, style=Style(px_per_cell=5))
    for (r, c), colour in {(10, 20): COL_FREE, (10, 5): COL_OCCUPIED, (38, 58): COL_UNKNOWN,
                           (20, 30): COL_UNCERTAIN}.items():
        assert px(img, f.to_pixel(*cell_centre(geom, r, c))) == colour, (r, c)
    # row 0 (min y) is at the bottom of the map area, the last row right under the title bar
    u, v = f.to_pixel(*cell_centre(geom, 0, 0))
    assert v == pytest.approx(TITLE_H + (geom.height - 0.5) * 5)
    _, v_top = f.to_pixel(*cell_centre(geom, geom.height - 1, 0))
    assert v_top == pytest.approx(TITLE_H + 2.5)


def test_thresholds_are_respected():
    g = np.array([[10, 40, 80]], np.int8)
    geom = GridGeometry(0.1, 0, 0, 3, 1)
    f = make_frame(g, geom, style=Style(px_per_cell=10))
    img = render(g, geom, style=Style(px_per_cell=10, p_free=0.5, p_occ=0.7))
    cols = [px(img, f.to_pixel(*cell_centre(geom, 0, c))) for c in range(3)]
    assert cols == [COL_FREE, COL_FREE, COL_OCCUPIED]


def _topo() -> Graph:
    nodes = [Node(7, "end", 1.0, 3.0), Node(8, "branch", 2.0, 3.5), Node(9, "corner", 3.0, 4.0),
             Node(10, "end", 4.0, 4.5)]
    edges = [(7, 8, [[1.0, 3.0], [2.0, 3.5]], 1.1, 0.3), (8, 9, [[2.0, 3.5], [3.0, 4.0]], 1.1, 0.3),
             (9, 10, [[3.0, 4.0], [4.0, 4.5]], 1.1, 0.3)]
    return Graph.from_edges(nodes, edges)


def _rel(p7=0.95, p10=0.4) -> list[Belief]:
    def nr(i, x, y, p):
        return Belief(id=i, x=x, y=y, p=p, d=0.6, a=0.5, r_min=2.0, alpha_max=0.5, visible=True)
    return [nr(7, 1.0, 3.0, p7), nr(10, 4.0, 4.5, p10)]


def test_nodes_drawn_at_the_right_pixel_with_kind_colours():
    g, geom = grid_and_geom()
    topo = _topo()
    img = render(g, geom, Overlays(topo=topo), Style(px_per_cell=8))
    f = make_frame(g, geom, Overlays(topo=topo), Style(px_per_cell=8))
    assert px(img, f.to_pixel(1.0, 3.0)) == COL_END
    assert px(img, f.to_pixel(2.0, 3.5)) == COL_BRANCH
    assert px(img, f.to_pixel(3.0, 4.0)) == COL_CORNER
    # an edge pixel halfway between two nodes (away from the node shapes)
    assert px(img, f.to_pixel(1.5, 3.25)) == COL_EDGE


def test_reliable_end_nodes_look_different_and_target_ring():
    g, geom = grid_and_geom()
    topo, rel = _topo(), _rel()
    img = render(g, geom, Overlays(topo=topo, rel=rel, target_id=10), Style(px_per_cell=8))
    f = make_frame(g, geom, style=Style(px_per_cell=8))
    assert px(img, f.to_pixel(1.0, 3.0)) == COL_END_RELIABLE  # P = 0.95
    assert px(img, f.to_pixel(4.0, 4.5)) == COL_END  # P = 0.40
    u, v = f.to_pixel(4.0, 4.5)
    ring = [px(img, (u + d, v)) for d in range(10, 16)]
    assert COL_TARGET in ring
    no_rel = render(g, geom, Overlays(topo=topo), Style(px_per_cell=8))
    assert not np.array_equal(no_rel, img)  # labels id(P) and colours differ


def test_rel_nodes_without_topo_are_drawn():
    g, geom = grid_and_geom()
    img = render(g, geom, Overlays(rel=_rel()), Style(px_per_cell=8))
    f = make_frame(g, geom, style=Style(px_per_cell=8))
    assert px(img, f.to_pixel(1.0, 3.0)) == COL_END_RELIABLE


def test_robot_and_trail():
    g, geom = grid_and_geom()
    trail = [(0.8, 3.0, 0), (1.5, 3.0, 0), (2.5, 3.0, 0), (2.5, 4.0, 1), (2.5, 5.0, 1)]
    img = render(g, geom, Overlays(robot_pose=(3.5, 4.0, 0.0), trail=trail), Style(px_per_cell=8))
    f = make_frame(g, geom, style=Style(px_per_cell=8))
    assert px(img, f.to_pixel(2.0, 3.0)) == TRAIL_COLOURS[0]
    assert px(img, f.to_pixel(2.5, 4.5)) == TRAIL_COLOURS[1]
    u, v = f.to_pixel(3.5, 4.0)
    assert px(img, (u, v)) != COL_FREE  # robot body
    # heading tick points to +x (right in the image)
    assert px(img, (u + 19, v)) != COL_FREE and px(img, (u - 19, v)) == COL_FREE


def test_truth_overlay():
    g, geom = grid_and_geom()
    truth = np.zeros(g.shape, bool)
    truth[5:35, 5] = True  # mapped wall: stays black
    truth[5:35, 54] = True  # wall the map shows as free: tinted
    img = render(g, geom, Overlays(truth_occupied=truth), Style(px_per_cell=5))
    f = make_frame(g, geom, style=Style(px_per_cell=5))
    assert px(img, f.to_pixel(*cell_centre(geom, 10, 5))) == COL_OCCUPIED
    assert px(img, f.to_pixel(*cell_centre(geom, 10, 54))) == COL_TRUTH
    with pytest.raises(RenderError, match="truth"):
        render(g, geom, Overlays(truth_occupied=truth[:-1]))


def test_crop():
    g, geom = grid_and_geom()
    (rs, cs), sub = crop_to_content(g, geom, margin=0.5)
    assert (rs.start, rs.stop, cs.start, cs.stop) == (0, 40, 0, 60)  # clipped to the grid
    big = np.full((300, 300), -1, np.int8)
    big[100:110, 200:220] = 0
    bgeom = GridGeometry(0.1, 0.0, 0.0, 300, 300)
    (rs, cs), sub = crop_to_content(big, bgeom, margin=1.0)
    assert (rs.start, rs.stop, cs.start, cs.stop) == (90, 120, 190, 230)
    assert (sub.origin_x, sub.origin_y) == pytest.approx((19.0, 9.0))
    img = render(big, bgeom, style=Style(crop=True))
    f = make_frame(big, bgeom, style=Style(crop=True))
    assert f.geom == sub and img.shape[1] == max(f.map_w, 720)
    assert px(img, f.to_pixel(21.0, 10.5)) == COL_FREE


def test_large_grid_is_capped_and_fast_enough():
    g = np.full((1000, 1200), -1, np.int8)
    g[400:600, 400:600] = 0
    img = render(g, GridGeometry(0.1, 0, 0, 1200, 1000))
    assert max(img.shape[:2]) <= 2400 + 200  # map <= 2400 px plus title and legend


def test_bad_input():
    g, geom = grid_and_geom()
    with pytest.raises(RenderError, match="shape"):
        render(g[:, :-1], geom)
    with pytest.raises(RenderError, match="integer"):
        render(g.astype(float), geom)
    with pytest.raises(RenderError, match="robot_pose"):
        render(g, geom, Overlays(robot_pose=(0.0, float("nan"), 0.0)))
    with pytest.raises(RenderError, match="trail"):
        render(g, geom, Overlays(trail=[(0.0, 1.0)]))
    with pytest.raises(RenderError):
        render(g, geom, style=Style(p_free=0.8, p_occ=0.6))


def _house() -> tuple[np.ndarray, GridGeometry, np.ndarray]:
    """A 9 x 6 m floor of three rooms off a corridor at 0.05 m, half explored, in the mapper's
    margin of unknown; some undecided cells; a wall the map missed (truth has it)."""
    truth = np.zeros((120, 180), bool)
    truth[[0, -1], :] = True
    truth[:, [0, -1]] = True
    truth[70, :] = True  # corridor's north wall, doors below
    truth[40, :] = True  # corridor's south wall
    truth[70:, [60, 120]] = True  # room walls
    truth[:40, 90] = True
    for c in (25, 85, 145):
        truth[70, c:c + 18] = False  # doors
    truth[40, 40:58] = False
    truth[40, 130:148] = False
    truth[85:95, 20:35] = True  # a cupboard
    m = 30
    grid = np.full((120 + 2 * m, 180 + 2 * m), -1, np.int8)
    inner = np.where(truth, 100, 0).astype(np.int8)
    inner[:, 110:] = -1  # not seen yet
    inner[::7, ::11] = np.where(inner[::7, ::11] == 0, 50, inner[::7, ::11])  # undecided
    inner[70, 100:110] = 0  # a wall the map shows as free
    grid[m:-m, m:-m] = inner
    full = np.zeros(grid.shape, bool)
    full[m:-m, m:-m] = truth
    return grid, GridGeometry(0.05, -1.5, -1.5, 180 + 2 * m, 120 + 2 * m), full


def _house_overlays(truth: np.ndarray) -> Overlays:
    nodes = [Node(1, "end", 0.8, 2.75), Node(2, "branch", 2.0, 2.75), Node(3, "corner", 4.5, 2.75),
             Node(4, "end", 5.4, 2.75), Node(5, "end", 1.7, 4.8), Node(6, "end", 4.6, 1.0)]
    edges = [(1, 2, [[0.8, 2.75], [1.4, 2.8], [2.0, 2.75]], 1.2, 0.6),
             (2, 3, [[2.0, 2.75], [4.5, 2.75]], 2.5, 0.7),
             (3, 4, [[4.5, 2.75], [5.4, 2.75]], 0.9, 0.7),
             (2, 5, [[2.0, 2.75], [1.8, 3.6], [1.7, 4.8]], 2.1, 0.5),
             (3, 6, [[4.5, 2.75], [4.6, 1.0]], 1.8, 0.5)]

    def belief(i, x, y, p):
        return Belief(id=i, x=x, y=y, p=p, d=0.6, a=0.5, r_min=2.0, alpha_max=0.5, visible=True)
    rel = [belief(1, 0.8, 2.75, 0.97), belief(4, 5.4, 2.75, 0.41), belief(5, 1.7, 4.8, 0.85),
           belief(6, 4.6, 1.0, 0.1), belief(9, 7.5, 4.5, 0.6)]
    trail = [(0.5 + 5.0 * k / 143, 2.75 + math.sin(k / 20.0), k // 12) for k in range(144)]
    return Overlays(topo=Graph.from_edges(nodes, edges), rel=rel, robot_pose=(5.3, 3.2, 0.7),
                    trail=trail, target_id=4, truth_occupied=truth)


HOUSE_STYLE = Style(p_free=0.3, p_occ=0.7, p_reliable=0.85, robot_radius=0.25, crop=True,
                    title="house / reliability / seed 0: finished, 12.3 m, 456 s")
HOUSE_SHA256 = "17d2ac403eb45bd29ded1277e4eefe850b0be61382646a88e8d51356457e1169"
HOUSE_SHA256_OPENCV = "5.0.0"  # the OpenCV that drew HOUSE_SHA256's text
HOUSE_SHAPES_SHA256 = "8cc11a3e29954ddac6102ee01b7052d337794856e0db3cbda5c37b757c48f9fa"


def _house_picture() -> np.ndarray:
    grid, geom, truth = _house()
    return render(grid, geom, _house_overlays(truth), HOUSE_STYLE)


def _no_text(monkeypatch) -> None:
    """OpenCV's Hershey text moves by a pixel from one release to the next (5.0 -> 5.1 moved every
    glyph): draw no text and size it by a fixed rule, so what is left is our own geometry."""
    import cv2

    monkeypatch.setattr(cv2, "putText", lambda img, *a, **k: img)
    monkeypatch.setattr(cv2, "getTextSize",
                        lambda text, face, scale, thick: ((int(len(text) * 20 * scale), int(22 * scale)),
                                                          int(5 * scale)))


def test_realistic_picture_is_unchanged(monkeypatch):
    """Every overlay, crop and a custom style: pixel for pixel the picture the renderer drew
    before its options were grouped into Overlays / Style, text left out (SHA-256 of the pixels).
    Any change of this picture must be deliberate: look at it, then record the new hash."""
    import hashlib

    _no_text(monkeypatch)
    img = _house_picture()
    assert img.shape == (1105, 1146, 3)
    assert hashlib.sha256(img.tobytes()).hexdigest() == HOUSE_SHAPES_SHA256


def test_realistic_picture_with_text(monkeypatch):
    """With its text: the exact picture on the OpenCV that recorded it; on any other, the text
    is there (the title bar and legend differ from the text-free picture) and nothing else moved
    (at most the pixels near text differ)."""
    import hashlib

    import cv2

    img = _house_picture()
    assert img.shape == (1105, 1146, 3)
    if cv2.__version__ == HOUSE_SHA256_OPENCV:
        assert hashlib.sha256(img.tobytes()).hexdigest() == HOUSE_SHA256
    _no_text(monkeypatch)
    bare = _house_picture()
    differs = (img != bare).any(axis=2)
    assert differs[:TITLE_H].mean() > 0.01  # the title is drawn
    assert differs[-100:].mean() > 0.01  # so is the legend
    assert differs.mean() < 0.08  # text only


def test_an_older_runs_topology_json_still_loads():
    """topology.json written before the headers took the ROS shape ({seq, stamp: float, frame,
    src_seq}) is read with its header upgraded; today's shape is left as it is."""
    from topoexplore.tools.livestate import beliefs_from_state, graph_from_state, upgrade_header

    old_topo = {"header": {"seq": 4, "stamp": 12.25, "frame": "map", "src_seq": 8},
                "nodes": [{"id": 1, "kind": "end", "x": 0.0, "y": 0.0},
                          {"id": 2, "kind": "branch", "x": 1.0, "y": 0.0}],
                "edges": [{"a": 1, "b": 2, "points": [[0.0, 0.0], [1.0, 0.0]], "length": 1.0,
                           "clearance": 0.4}], "gone": []}
    g = graph_from_state(old_topo)
    assert [n.id for n in g.nodes] == [1, 2] and len(g.edges) == 1
    old_rel = {"header": {"seq": 0, "stamp": 3.0, "frame": "map", "src_seq": -1}, "nodes": [
        {"id": 1, "x": 0.0, "y": 0.0, "p": 0.5, "d": 0.0, "a": 0.0, "r_min": 1.0,
         "alpha_max": 0.0, "visible": True}]}
    assert beliefs_from_state(old_rel)[0].p == 0.5
    up = upgrade_header(old_topo)["header"]
    assert up == {"stamp": {"sec": 12, "nanosec": 250_000_000}, "frame_id": "map", "seq": 4,
                  "src_seq": 8}
    new = {"header": up, "nodes": []}
    assert upgrade_header(new) is new and upgrade_header(None) is None
