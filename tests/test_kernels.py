"""common.kernels: the one Bresenham line and the one 8-connected flood fill."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from topoexplore.common.kernels import bresenham, flood_fill, line_length


def line(r0: int, c0: int, r1: int, c1: int) -> list[tuple[int, int]]:
    n = line_length(r0, c0, r1, c1)
    rows = np.full(n + 3, -99, np.int64)  # spare cells: nothing is written past n
    cols = np.full(n + 3, -99, np.int64)
    assert bresenham(r0, c0, r1, c1, rows, cols) == n
    assert (rows[n:] == -99).all() and (cols[n:] == -99).all()
    return list(zip(rows[:n].tolist(), cols[:n].tolist(), strict=True))


def classic(r0: int, c0: int, r1: int, c1: int) -> list[tuple[int, int]]:
    """The error-term loop the mapper and the corner test used to carry inline."""
    dr, dc = abs(r1 - r0), abs(c1 - c0)
    sr, sc = (1 if r1 > r0 else -1), (1 if c1 > c0 else -1)
    err, r, c, out = dc - dr, r0, c0, []
    while True:
        out.append((r, c))
        if r == r1 and c == c1:
            return out
        e2 = 2 * err
        if e2 > -dr:
            err -= dr
            c += sc
        if e2 < dc:
            err += dc
            r += sr


# --- bresenham ---------------------------------------------------------------------------


def test_line_cells_in_order_shallow():
    assert line(0, 0, 3, 7) == [(0, 0), (0, 1), (1, 2), (1, 3), (2, 4), (2, 5), (3, 6), (3, 7)]


def test_line_cells_in_order_steep_and_backwards():
    assert line(7, 3, 0, 0) == [(7, 3), (6, 3), (5, 2), (4, 2), (3, 1), (2, 1), (1, 0), (0, 0)]


def test_axis_aligned_and_diagonal_lines():
    assert line(2, 1, 2, 5) == [(2, 1), (2, 2), (2, 3), (2, 4), (2, 5)]
    assert line(4, 0, 1, 0) == [(4, 0), (3, 0), (2, 0), (1, 0)]
    assert line(0, 0, 3, 3) == [(0, 0), (1, 1), (2, 2), (3, 3)]
    assert line(0, 3, 3, 0) == [(0, 3), (1, 2), (2, 1), (3, 0)]
    assert line(-2, -2, -5, 1) == [(-2, -2), (-3, -1), (-4, 0), (-5, 1)]  # any integers


def test_a_point_is_one_cell():
    assert line(4, 9, 4, 9) == [(4, 9)]


@pytest.mark.parametrize("seed", range(3))
def test_random_lines(seed):
    """Every octant: both ends included, one cell per step along the major axis, each cell the
    ideal line's rounding on the minor axis (within half a cell), reversed lines differ only in
    how they round exact halves, and the cells equal those of the classic loop."""
    rng = np.random.default_rng(seed)
    for _ in range(500):
        r0, c0, r1, c1 = (int(v) for v in rng.integers(-40, 40, 4))
        cells = line(r0, c0, r1, c1)
        assert cells == classic(r0, c0, r1, c1)
        assert cells[0] == (r0, c0) and cells[-1] == (r1, c1)
        assert len(cells) == max(abs(r1 - r0), abs(c1 - c0)) + 1
        steps = np.diff(np.array(cells), axis=0)
        assert (np.abs(steps).reshape(-1, 2).max(axis=1) == 1).all()  # 8-adjacent, no repeats
        back = line(r1, c1, r0, c0)
        assert len(back) == len(cells) and back[0] == (r1, c1) and back[-1] == (r0, c0)
        for path in (cells, back[::-1]):
            for r, c in path:
                if abs(c1 - c0) >= abs(r1 - r0) and c1 != c0:
                    assert abs(r - (r0 + (r1 - r0) * (c - c0) / (c1 - c0))) <= 0.5
                elif r1 != r0:
                    assert abs(c - (c0 + (c1 - c0) * (r - r0) / (r1 - r0))) <= 0.5


# --- flood_fill ---------------------------------------------------------------------------


def fill(img: np.ndarray, r: int, c: int, old: int = 1, new: int = 2) -> list[int]:
    out = np.full(img.size + 1, -1, np.int64)
    n = flood_fill(img, r, c, old, new, out)
    assert (out[n:] == -1).all()
    return out[:n].tolist()


def test_diagonal_contacts_join():
    img = np.array([[1, 0, 0, 0],
                    [0, 1, 0, 1],
                    [0, 0, 1, 0],
                    [0, 1, 0, 0]], np.uint8)
    assert sorted(fill(img, 0, 0)) == [0, 5, 7, 10, 13]
    assert (img == np.where(img > 0, 2, 0)).all()


def test_a_gap_separates():
    img = np.array([[1, 1, 0, 1],
                    [1, 1, 0, 1]], np.uint8)
    assert sorted(fill(img, 1, 0)) == [0, 1, 4, 5]
    assert img.tolist() == [[2, 2, 0, 1], [2, 2, 0, 1]]


def test_breadth_first_from_the_seed_in_raster_order():
    img = np.ones((5, 5), np.uint8)  # no zero border: cells on the edges are filled too
    order = fill(img, 2, 2)
    assert order[:9] == [12, 6, 7, 8, 11, 13, 16, 17, 18]
    assert sorted(order) == list(range(25))
    ring = [max(abs(p // 5 - 2), abs(p % 5 - 2)) for p in order]
    assert ring == sorted(ring)
    assert fill(np.ones((3, 3), np.uint8), 0, 0) == [0, 1, 3, 4, 2, 5, 6, 7, 8]


def test_seed_not_old_or_outside_fills_nothing():
    img = np.array([[0, 1], [1, 1]], np.uint8)
    for r, c in ((0, 0), (-1, 0), (0, 2), (2, 1)):
        assert fill(img, r, c) == []
    assert img.tolist() == [[0, 1], [1, 1]]


def test_other_values_and_types():
    img = np.array([[-1, -1, 5], [7, -1, -1], [-1, 0, 3]], np.int8)
    assert sorted(fill(img, 0, 0, old=-1, new=9)) == [0, 1, 4, 5, 6]
    assert img.tolist() == [[9, 9, 5], [7, 9, 9], [9, 0, 3]]


@pytest.mark.parametrize("seed", range(4))
def test_fill_is_the_seeds_cv2_component(seed):
    rng = np.random.default_rng(seed)
    for _ in range(40):
        h, w = (int(v) for v in rng.integers(1, 40, 2))
        mask = (rng.random((h, w)) < rng.uniform(0.3, 0.7)).astype(np.uint8)
        _, labels = cv2.connectedComponents(mask, connectivity=8)
        r, c = int(rng.integers(0, h)), int(rng.integers(0, w))
        img = mask.copy()
        got = fill(img, r, c)
        if not mask[r, c]:
            assert got == [] and (img == mask).all()
            continue
        comp = labels == labels[r, c]
        assert sorted(got) == np.flatnonzero(comp).tolist()
        assert got[0] == r * w + c
        assert (img == np.where(comp, 2, mask)).all()
