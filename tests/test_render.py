"""common.render: pure BGR rendering of grid, graph, reliabilities and trail."""

from __future__ import annotations

import math

import numpy as np
import pytest

from topoexplore.common import messages as m
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
    RenderError,
    choose_scale,
    crop_to_content,
    make_frame,
    render,
)

H = m.Header(seq=0, stamp=0.0, frame="map", src_seq=-1)


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
    img = render(g, geom, px_per_cell=5)
    f = make_frame(g, geom, px_per_cell=5)
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
    f = make_frame(g, geom, px_per_cell=10)
    img = render(g, geom, px_per_cell=10, p_free=0.5, p_occ=0.7)
    cols = [px(img, f.to_pixel(*cell_centre(geom, 0, c))) for c in range(3)]
    assert cols == [COL_FREE, COL_FREE, COL_OCCUPIED]


def _topo():
    nodes = [m.TopoNode(id=7, kind="end", x=1.0, y=3.0), m.TopoNode(id=8, kind="branch", x=2.0,
                                                                     y=3.5),
             m.TopoNode(id=9, kind="corner", x=3.0, y=4.0),
             m.TopoNode(id=10, kind="end", x=4.0, y=4.5)]
    edges = [m.TopoEdge(a=7, b=8, points=[[1.0, 3.0], [2.0, 3.5]], length=1.1, clearance=0.3),
             m.TopoEdge(a=8, b=9, points=[[2.0, 3.5], [3.0, 4.0]], length=1.1, clearance=0.3),
             m.TopoEdge(a=9, b=10, points=[[3.0, 4.0], [4.0, 4.5]], length=1.1, clearance=0.3)]
    return m.TopoGraph(header=H, nodes=nodes, edges=edges)


def _rel(p7=0.95, p10=0.4):
    def nr(i, x, y, p):
        return m.NodeReliability(id=i, x=x, y=y, p=p, d=0.6, a=0.5, r_min=2.0, alpha_max=0.5,
                                 visible=True)
    return m.Reliability(header=H, nodes=[nr(7, 1.0, 3.0, p7), nr(10, 4.0, 4.5, p10)])


def test_nodes_drawn_at_the_right_pixel_with_kind_colours():
    g, geom = grid_and_geom()
    topo = _topo()
    img = render(g, geom, topo=topo, px_per_cell=8)
    f = make_frame(g, geom, topo=topo, px_per_cell=8)
    assert px(img, f.to_pixel(1.0, 3.0)) == COL_END
    assert px(img, f.to_pixel(2.0, 3.5)) == COL_BRANCH
    assert px(img, f.to_pixel(3.0, 4.0)) == COL_CORNER
    # an edge pixel halfway between two nodes (away from the node shapes)
    assert px(img, f.to_pixel(1.5, 3.25)) == COL_EDGE


def test_reliable_end_nodes_look_different_and_target_ring():
    g, geom = grid_and_geom()
    topo, rel = _topo(), _rel()
    img = render(g, geom, topo=topo, rel=rel, target_id=10, px_per_cell=8)
    f = make_frame(g, geom, px_per_cell=8)
    assert px(img, f.to_pixel(1.0, 3.0)) == COL_END_RELIABLE  # P = 0.95
    assert px(img, f.to_pixel(4.0, 4.5)) == COL_END  # P = 0.40
    u, v = f.to_pixel(4.0, 4.5)
    ring = [px(img, (u + d, v)) for d in range(10, 16)]
    assert COL_TARGET in ring
    no_rel = render(g, geom, topo=topo, px_per_cell=8)
    assert not np.array_equal(no_rel, img)  # labels id(P) and colours differ


def test_rel_nodes_without_topo_are_drawn():
    g, geom = grid_and_geom()
    img = render(g, geom, rel=_rel(), px_per_cell=8)
    f = make_frame(g, geom, px_per_cell=8)
    assert px(img, f.to_pixel(1.0, 3.0)) == COL_END_RELIABLE


def test_robot_and_trail():
    g, geom = grid_and_geom()
    trail = [(0.8, 3.0, 0), (1.5, 3.0, 0), (2.5, 3.0, 0), (2.5, 4.0, 1), (2.5, 5.0, 1)]
    img = render(g, geom, robot_pose=(3.5, 4.0, 0.0), trail=trail, px_per_cell=8)
    f = make_frame(g, geom, px_per_cell=8)
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
    img = render(g, geom, truth_occupied=truth, px_per_cell=5)
    f = make_frame(g, geom, px_per_cell=5)
    assert px(img, f.to_pixel(*cell_centre(geom, 10, 5))) == COL_OCCUPIED
    assert px(img, f.to_pixel(*cell_centre(geom, 10, 54))) == COL_TRUTH
    with pytest.raises(RenderError, match="truth"):
        render(g, geom, truth_occupied=truth[:-1])


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
    img = render(big, bgeom, crop=True)
    f = make_frame(big, bgeom, crop=True)
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
        render(g, geom, robot_pose=(0.0, float("nan"), 0.0))
    with pytest.raises(RenderError, match="trail"):
        render(g, geom, trail=[(0.0, 1.0)])
    with pytest.raises(RenderError):
        render(g, geom, p_free=0.8, p_occ=0.6)
