"""common.grid: classification, unexplored space and the observed-cells crop."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from topoexplore.common.grid import (
    UNKNOWN,
    GridGeometry,
    OpenUnknown,
    cells_for,
    classify,
    crop_known,
    distance_transform,
    known_window,
    open_never_near,
    open_unknown,
    open_unknown_at,
    ray_cells,
    reframe,
    unknown_mask,
)
from topoexplore.common.kernels import bresenham


def ref_unknown(g: np.ndarray) -> np.ndarray:
    """The definition, on the whole grid: never observed, plus undecided cells in the same
    8-connected component of (never | undecided) as a never-observed cell."""
    never = g == -1
    both = never | (classify(g.astype(np.int16)) == UNKNOWN)
    _, labels = cv2.connectedComponents(both.view(np.uint8), connectivity=8)
    keep = np.zeros(labels.max() + 1, dtype=bool)
    keep[np.unique(labels[never])] = True
    keep[0] = False
    return keep[labels]


def ref_open(g: np.ndarray, pocket_cells: int, reach: np.ndarray | None = None,
             min_reach: int = 1, min_area: int = 0) -> np.ndarray:
    u = ref_unknown(g)
    n, labels, st, _ = cv2.connectedComponentsWithStats(u.view(np.uint8), connectivity=8)
    h, w = u.shape
    border = ((st[:, 0] == 0) | (st[:, 1] == 0) | (st[:, 0] + st[:, 2] == w)
              | (st[:, 1] + st[:, 3] == h))
    pocket = ~border & (st[:, 4] < pocket_cells)
    pocket[0] = False
    for k in range(1, n) if reach is not None else ():  # reachable cells beside it, one by one
        beside = sum(1 for r, c in zip(*np.nonzero(reach), strict=True) if any(
            0 <= r + dr < h and 0 <= c + dc < w and labels[r + dr, c + dc] == k
            for dr, dc in ((1, 0), (-1, 0), (0, 1), (0, -1))))
        pocket[k] &= (beside < min_reach) | (st[k, 4] < min_area)
    return u & ~pocket[labels]


def random_grids(n: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    values = np.array([-1, 0, 20, 50, 100], np.int8)
    for _ in range(n):
        h, w = rng.integers(3, 40, 2)
        g = np.full((h, w), -1, np.int8)  # an observed box somewhere, unknown around it
        r0, c0 = rng.integers(0, h), rng.integers(0, w)
        r1, c1 = rng.integers(r0, h + 1), rng.integers(c0, w + 1)
        g[r0:r1, c0:c1] = rng.choice(values, size=(r1 - r0, c1 - c0), p=rng.dirichlet([1] * 5))
        yield g


def test_classify_table_matches_the_thresholds_for_every_int8_value():
    v = np.arange(-128, 128).astype(np.int8)
    for pf, po in [(0.35, 0.65), (0.2, 0.8), (0.5, 0.5)]:
        assert np.array_equal(classify(v, pf, po), classify(v.astype(np.int16), pf, po))


def test_unknown_mask_and_open_unknown_match_their_definition_on_the_whole_grid():
    for g in random_grids(400):
        assert np.array_equal(unknown_mask(g), ref_unknown(g))
        for pocket in (0, 3, 20):
            assert np.array_equal(open_unknown(g, pocket), ref_open(g, pocket))


def test_a_pocket_is_kept_where_the_robot_can_reach_enough_of_its_border():
    rng = np.random.default_rng(1)
    for g in random_grids(150, seed=3):
        reach = (g >= 0) & (g < 35) & (rng.random(g.shape) < 0.7)
        for pocket, min_reach, min_area in ((20, 1, 0), (20, 3, 0), (40, 6, 0), (40, 2, 8)):
            assert np.array_equal(open_unknown(g, pocket, reach=reach, min_reach=min_reach,
                                               min_area=min_area),
                                  ref_open(g, pocket, reach, min_reach, min_area))
    g = np.zeros((30, 30), np.int8)  # a 6 x 6 pocket in a free room: 24 border cells
    g[[0, -1], :] = g[:, [0, -1]] = 100
    g[10:16, 10:16] = -1
    free = g == 0
    assert open_unknown(g, 100).sum() == 0  # without reach: dropped
    assert open_unknown(g, 100, reach=free, min_reach=10).sum() == 36  # beside it: kept
    few = np.zeros_like(free)
    few[9, 10:13] = True  # three reachable cells beside it: not a frontier's worth
    assert open_unknown(g, 100, reach=few, min_reach=10).sum() == 0
    assert open_unknown(g, 100, reach=few, min_reach=3).sum() == 36
    assert open_unknown(g, 100, reach=free, min_reach=10, min_area=37).sum() == 0  # too small


def test_open_never_near_is_a_subset_of_open_unknown_whatever_the_reach():
    """The planner's quick test (beside_unknown) may say yes only where the whole-map one
    would: its cells are open_unknown's for any reach, and it finds the big ones it should."""
    rng = np.random.default_rng(11)
    found = 0
    for g in random_grids(400, seed=7):
        geom = GridGeometry(0.1, 0.0, 0.0, g.shape[1], g.shape[0])
        reach = (g >= 0) & (g < 35) & (rng.random(g.shape) < 0.5)
        for pocket in (0, 3, 20, 60):
            x, y = rng.uniform(-0.5, 0.1 * g.shape[1] + 0.5), rng.uniform(-0.5, 0.1 * g.shape[0])
            half = float(rng.uniform(0.1, 2.0))
            quick = open_never_near(g, geom, x, y, half, pocket)
            assert quick.shape == g.shape and not (quick & (g != -1)).any()
            for r in (None, reach):
                assert not (quick & ~open_unknown(g, pocket, reach=r, min_reach=2)).any()
            found += int(quick.any())
    assert found > 200  # not vacuous
    g = np.zeros((40, 40), np.int8)  # a room with an open side: 10 x 40 never observed
    g[:, 30:] = -1
    geom = GridGeometry(0.1, 0.0, 0.0, 40, 40)
    # the square of half 0.5 m (and a cell) holds 13 x 7 of them: too few for 600
    assert open_never_near(g, geom, 3.0, 2.0, 0.5, 600).sum() == 0
    assert open_never_near(g, geom, 3.0, 2.0, 1.0, 50).sum() == 23 * 10  # clipped at 4 m


def test_reachable_border_counts_each_reachable_cell_once_per_label():
    from topoexplore.common.grid import _reachable_border

    rng = np.random.default_rng(5)
    for _ in range(60):
        h, w = rng.integers(1, 25, 2)
        labels = rng.integers(0, 6, (h, w)).astype(np.int32)
        reach = rng.random((h, w)) < 0.5
        want = np.zeros(6, np.int64)
        for r, c in zip(*np.nonzero(reach), strict=True):
            beside = {int(labels[r + dr, c + dc]) for dr, dc in ((1, 0), (-1, 0), (0, 1), (0, -1))
                      if 0 <= r + dr < h and 0 <= c + dc < w}
            for k in beside:
                want[k] += 1
        assert np.array_equal(_reachable_border(labels, reach, np.ones(6, bool)), want)
        wanted = rng.random(6) < 0.5  # only these labels' counts: the others 0
        assert np.array_equal(_reachable_border(labels, reach, wanted),
                              np.where(wanted, want, 0))


def test_best_clearance_is_the_greatest_of_the_four_sub_cells():
    from topoexplore.common.grid import distance_transform
    from topoexplore.services.planner.gridsearch import best_clearance_map

    rng = np.random.default_rng(6)
    for _ in range(40):
        occ = rng.random(tuple(rng.integers(1, 30, 2))) < rng.uniform(0.01, 0.3)
        h, w = occ.shape
        fine = np.repeat(np.repeat(occ, 2, axis=0), 2, axis=1)
        d = distance_transform(np.where(fine, 0, 255).astype(np.uint8)) * np.float32(0.05)
        want = d.reshape(h, 2, w, 2).max(axis=(1, 3)) if occ.any() else np.full((h, w), 1e6)
        assert np.array_equal(best_clearance_map(occ, 0.1), want.astype(np.float32))


def test_fit_mask_is_the_best_clearance_test_without_the_transform():
    from topoexplore.services.planner.gridsearch import best_clearance_map, fit_mask

    rng = np.random.default_rng(7)
    for _ in range(200):
        occ = rng.random(tuple(rng.integers(1, 40, 2))) < rng.choice([0.0, 0.02, 0.1, 0.4, 1.0])
        res = float(rng.choice([0.05, 0.07, 0.1]))
        fit = float(rng.choice([0.0, 0.1, 0.175, 0.225, rng.uniform(0.0, 0.7)]))
        want = best_clearance_map(occ, res) + 1e-6 >= fit
        assert np.array_equal(fit_mask(occ, res, fit), want), (occ.shape, res, fit)


def test_a_reach_only_narrow_search_leaves_the_best_clearance_until_asked():
    """The robot on a passable cell: the reach-only search through narrow passages takes
    its cells from fit_mask and makes the best clearance only when its clearance is read;
    a view that made the best clearance first reaches the same cells."""
    from topoexplore.common.domain import GridMap
    from topoexplore.common.grid import Occupancy
    from topoexplore.services.planner.mapview import MapView

    data = np.zeros((40, 60), np.int8)  # two rooms joined by a door 5 cells (0.5 m) wide
    data[[0, -1], :] = 100
    data[:, [0, 29, -1]] = 100
    data[18:23, 29] = 0
    geom = GridGeometry(0.1, 0.0, 0.0, 60, 40)
    kw = dict(fit=0.2, soft_radius=0.6, soft_penalty=1.0, narrow_penalty=2.0, reach_only=True)
    lazy = MapView(GridMap(data, geom), Occupancy())
    search = lazy.search(1.5, 2.0, 0.35, **kw)
    assert not lazy._best.made
    eager = MapView(GridMap(data, geom), Occupancy())
    assert eager.best_clearance is not None  # made first: fits() reads it
    again = eager.search(1.5, 2.0, 0.35, **kw)
    assert np.array_equal(search.dist, again.dist) and np.isfinite(search.dist[20, 45])
    assert np.array_equal(search.clearance, eager.best_clearance)  # made on asking
    assert lazy._best.made


def test_crop_known_keeps_a_ring_of_unknown_and_world_coordinates():
    geom = GridGeometry(0.1, -5.0, -2.0, 100, 60)
    g = np.full((60, 100), -1, np.int8)
    g[10:20, 30:45] = 0
    win = known_window(g)
    assert win == (slice(9, 21), slice(29, 46))
    sub, sg = crop_known(g, geom)
    assert sub.shape == (12, 17) and (sg.width, sg.height) == (17, 12)
    assert sg.cell_to_world(1, 1) == pytest.approx(geom.cell_to_world(10, 30))
    assert (sub[0] == -1).all() and (sub[:, -1] == -1).all()
    assert crop_known(np.full((5, 5), -1, np.int8), geom)[0].shape == (5, 5)  # nothing seen
    g[0, 0] = g[-1, -1] = 0  # observed cells at both corners: the whole grid
    assert known_window(g) is None and crop_known(g, geom)[1] is geom


def _walls_mask(seed: int = 1) -> np.ndarray:
    """A map-like mask (walls and specks as zero cells) on which cv2's distance transform
    depends on the output's alignment."""
    rng = np.random.default_rng(seed)
    h, w = (int(v) for v in rng.integers(60, 160, 2))
    m = np.ones((h, w), np.uint8)
    for _ in range(rng.integers(3, 12)):
        r0, c0 = rng.integers(0, h), rng.integers(0, w)
        if rng.random() < 0.5:
            m[r0, c0:c0 + rng.integers(5, 60)] = 0
        else:
            m[r0:r0 + rng.integers(5, 60), c0] = 0
    m[rng.integers(0, h, 20), rng.integers(0, w, 20)] = 0
    return m


def _at(a: np.ndarray, offset: int) -> np.ndarray:
    """A copy of a whose data starts offset bytes after a 64-byte boundary."""
    buf = np.empty(a.nbytes + 128, np.uint8)
    start = (-buf.ctypes.data) % 64 + offset
    out = buf[start:start + a.nbytes].view(a.dtype).reshape(a.shape)
    out[...] = a
    return out


def test_distance_transform_is_a_function_of_the_mask_alone():
    """cv2's last bit depends on where its output lies in memory; the one distance transform
    of common.grid does not (lockstep runs must repeat exactly)."""
    m = _walls_mask()
    raw = []
    for off in (0, 4, 8, 16, 32):
        dst = _at(np.zeros(m.shape, np.float32), off)
        cv2.distanceTransform(m, cv2.DIST_L2, cv2.DIST_MASK_PRECISE, dst=dst)
        raw.append(dst.copy())
    assert any(not np.array_equal(raw[0], r) for r in raw[1:])  # the problem is real here
    ours = [distance_transform(_at(m, off)) for off in (0, 1, 3, 8, 16)]
    assert all(np.array_equal(ours[0], o) for o in ours[1:])
    assert np.allclose(ours[0], raw[0], rtol=1e-6, atol=1e-6) and ours[0].dtype == np.float32


def test_cells_for_a_length():
    assert cells_for(0.5, 0.1) == 5
    assert cells_for(3 * 0.1, 0.1) == 3  # 3 * 0.1 / 0.1 is 3.0000000000000004 in floats
    assert cells_for(0.51, 0.1) == 6
    assert cells_for(0.3, 0.05) == 6
    assert cells_for(0.0, 0.1) == 0


def _kernel_line(r0: int, c0: int, r1: int, c1: int) -> tuple[np.ndarray, np.ndarray]:
    rows = np.empty(max(abs(r1 - r0), abs(c1 - c0)) + 1, np.int64)
    cols = np.empty_like(rows)
    n = bresenham(r0, c0, r1, c1, rows, cols)
    return rows[:n], cols[:n]


def _check_ray_cells(r0: int, c0: int, r1: np.ndarray, c1: np.ndarray) -> None:
    rows, cols, n = ray_cells(r0, c0, r1, c1)
    assert rows.dtype == cols.dtype == n.dtype == np.int64
    assert rows.shape == cols.shape == (len(r1), int(n.max()))
    for k in range(len(r1)):
        want_r, want_c = _kernel_line(r0, c0, int(r1[k]), int(c1[k]))
        assert n[k] == len(want_r)
        assert np.array_equal(rows[k, :n[k]], want_r), (r0, c0, r1[k], c1[k])
        assert np.array_equal(cols[k, :n[k]], want_c), (r0, c0, r1[k], c1[k])


def test_ray_cells_is_the_bresenham_kernel_on_every_short_line():
    """The closed form gives the numba kernel's cells, in order, for every end point within
    40 cells of the start (all octants, ties, one-cell lines)."""
    d = np.arange(-40, 41)
    r1, c1 = (a.ravel() for a in np.meshgrid(d, d, indexing="ij"))
    _check_ray_cells(0, 0, r1, c1)
    _check_ray_cells(17, -5, r1 + 17, c1 - 5)  # and not only from the origin


def test_ray_cells_is_the_bresenham_kernel_on_long_lines():
    rng = np.random.default_rng(3)
    for _ in range(5):
        r0, c0 = (int(v) for v in rng.integers(-3000, 3000, 2))
        _check_ray_cells(r0, c0, r0 + rng.integers(-2500, 2500, 200),
                         c0 + rng.integers(-2500, 2500, 200))


def test_ray_cells_of_no_line():
    rows, cols, n = ray_cells(4, 5, np.zeros(0, np.int64), np.zeros(0, np.int64))
    assert rows.shape == cols.shape == (0, 0) and n.shape == (0,)


def test_reframe_keeps_a_layer_in_place_as_the_map_grows():
    """A layer beside a map, moved into the map's grown geometry, keeps its cells where they
    were in world coordinates; shrinking crops it; a geometry off by a part of a cell or of
    another resolution cannot take it (all fill)."""
    old = GridGeometry(0.1, 0.0, 0.0, 4, 3)
    a = np.arange(12, dtype=np.uint8).reshape(3, 4) + 1
    grown = GridGeometry(0.1, -0.2, -0.1, 7, 5)  # 2 cells west, 1 south, wider and taller
    b = reframe(a, old, grown)
    assert b.shape == (5, 7) and b.dtype == np.uint8
    assert np.array_equal(b[1:4, 2:6], a) and b.sum() == a.sum()
    assert np.array_equal(reframe(b, grown, old), a)  # and back
    part = GridGeometry(0.1, 0.1, 0.1, 2, 2)  # inside the old one
    assert np.array_equal(reframe(a, old, part), a[1:3, 1:3])
    assert not reframe(a, old, GridGeometry(0.1, 0.05, 0.0, 4, 3)).any()
    assert not reframe(a, old, GridGeometry(0.05, 0.0, 0.0, 8, 6)).any()
    assert (reframe(a, old, GridGeometry(0.1, 5.0, 5.0, 2, 2), fill=7) == 7).all()  # apart


def test_open_unknown_at_answers_as_the_whole_map_or_not_at_all():
    """A window of open_unknown worked out from the cells around it is the whole-map mask's
    window, or None (unsettled); and it settles most windows."""
    rng = np.random.default_rng(5)
    settled = unsettled = 0
    for g in random_grids(300, seed=13):
        h, w = g.shape
        for pocket in (0, 1, 5, 20, 60):
            whole = open_unknown(g, pocket)
            for _ in range(3):
                r0, c0 = int(rng.integers(0, h)), int(rng.integers(0, w))
                r1, c1 = int(rng.integers(r0 + 1, h + 1)), int(rng.integers(c0 + 1, w + 1))
                out = open_unknown_at(g, slice(r0, r1), slice(c0, c1), pocket,
                                      margin=int(rng.integers(1, 9)))
                if out is None:
                    unsettled += 1
                    continue
                assert np.array_equal(out, whole[r0:r1, c0:c1])
                settled += 1
    assert settled > 2 * unsettled  # not vacuous


def test_open_unknown_at_settles_by_the_rules_it_states():
    """A room with a 3 x 3 pocket and an open side: the pocket is dropped (it lies in the
    square), the open side's unknown is kept (on the square's edge with enough cells), an
    undecided speck is dropped, and a window whose square cuts a small component without
    reaching its end is unsettled."""
    g = np.zeros((60, 60), np.int8)
    g[[0, -1], :] = g[:, [0, -1]] = 100
    g[:, 45:] = -1  # open side, reaching the grid's border
    g[20:23, 20:23] = -1  # a pocket of 9 cells
    g[30, 10] = 50  # an undecided speck among free cells
    out = open_unknown_at(g, slice(15, 35), slice(5, 50), 20)
    assert out is not None and np.array_equal(out, open_unknown(g, 20)[15:35, 5:50])
    assert not out[5:8, 15:18].any() and not out[15, 5] and out[:, 40:].all()
    g[40, 2:40] = -1  # a row of 38 unknown cells: a pocket for 50, seen only in part
    assert open_unknown_at(g, slice(38, 43), slice(30, 45), 50, margin=2) is None
    assert np.array_equal(open_unknown_at(g, slice(38, 43), slice(30, 45), 50, margin=40),
                          open_unknown(g, 50)[38:43, 30:45])


def test_open_unknown_mask_reads_windows_locally_and_the_whole_map_when_it_must():
    """OpenUnknown: a window as open_unknown's, counted as local or whole; the whole-map
    mask for np.asarray and for anything that is not a plain window."""
    g = np.zeros((60, 300), np.int8)
    g[:, 280:] = -1
    g[40, 2:200] = -1  # 198 cells: a pocket for 250, longer than the second try's square
    m = OpenUnknown(g, 250)
    whole = open_unknown(g, 250)
    assert np.array_equal(m[10:20, 270:290], whole[10:20, 270:290])
    assert (m.local, m.whole) == (1, 0)
    assert np.array_equal(m[39:42, 150:155], whole[39:42, 150:155]) and m.whole == 1
    assert not whole[40, 2:200].any()
    copy = np.array(m)
    copy[:] = True
    assert np.array_equal(np.asarray(m), whole)  # a copy asked for is a copy
    assert np.array_equal(np.asarray(m), whole) and np.array_equal(m[::2, 3], whole[::2, 3])
    assert m.shape == g.shape
