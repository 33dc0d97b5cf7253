"""Grid geometry and cell classification shared by every stage (pure, no I/O).

A grid is an int8 array of shape (height, width), row = y index, column = x index, ROS values:
-1 unknown, 0..100 occupancy probability in percent. Cell (row i, col j) covers the square with
lower-left corner ``origin + (j, i) * resolution``.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import NamedTuple

import cv2
import numpy as np

UNKNOWN = 0
FREE = 1
OCCUPIED = 2


class GridError(ValueError):
    """A grid array does not fit its geometry (shape, type, resolution, origin)."""


class Occupancy(NamedTuple):
    """Classification thresholds of an occupancy grid: known free below p_free, occupied
    above p_occ, undecided in between (``[mapper] p_free / p_occ``)."""

    p_free: float = 0.35
    p_occ: float = 0.65


@dataclass(frozen=True)
class GridGeometry:
    resolution: float  # [m/cell]
    origin_x: float  # [m] world x of the lower-left corner of cell (0, 0)
    origin_y: float  # [m]
    width: int  # cells along x
    height: int  # cells along y

    def world_to_cell(self, x, y):
        """World [m] -> (row, col) integer indices (may be outside the grid)."""
        col = np.floor((np.asarray(x) - self.origin_x) / self.resolution).astype(np.int64)
        row = np.floor((np.asarray(y) - self.origin_y) / self.resolution).astype(np.int64)
        return row, col

    def cell_to_world(self, row, col):
        """(row, col) -> world coordinates [m] of the cell centre."""
        x = self.origin_x + (np.asarray(col, dtype=np.float64) + 0.5) * self.resolution
        y = self.origin_y + (np.asarray(row, dtype=np.float64) + 0.5) * self.resolution
        return x, y

    def inside(self, row, col):
        row = np.asarray(row)
        col = np.asarray(col)
        return (row >= 0) & (row < self.height) & (col >= 0) & (col < self.width)

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """(xmin, xmax, ymin, ymax) [m]."""
        return (
            self.origin_x,
            self.origin_x + self.width * self.resolution,
            self.origin_y,
            self.origin_y + self.height * self.resolution,
        )


def cells_for(length: float, resolution: float) -> int:
    """Whole cells [cells] that cover a length [m] (ceil, with a tolerance for lengths that
    are a multiple of the resolution up to float error): 0.5 m at 0.1 m is 5 cells."""
    return int(math.ceil(length / resolution - 1e-9))


def ray_cells(r0: int, c0: int, r1: np.ndarray, c1: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cells of the integer Bresenham lines from (r0, c0) to each (r1[k], c1[k]), all at once.

    The same cells in the same order as :func:`topoexplore.common.kernels.bresenham` (the
    numba kernel steps an error term; ``tests/test_grid.py`` checks both on every line within
    40 cells and on long random ones), in closed form. Along the major axis (the larger of
    |dr| and |dc|; columns on a tie) step i of n = max(|dr|, |dc|) + 1 moves one cell; the
    minor coordinate is ``minor0 + sign * floor((2 i b + a - 1) / (2 a))`` with a, b the
    major and minor extents (a half-way point rounds down).

    Returns ``(rows, cols, n)``: int64 arrays of shape (k, n.max()) and the cell count of
    each line. Entries at i >= n[k] continue the line past its end and are not its cells.
    """
    r1 = np.asarray(r1, np.int64)
    c1 = np.asarray(c1, np.int64)
    dr, dc = np.abs(r1 - r0), np.abs(c1 - c0)
    sr = np.where(r1 > r0, 1, -1)
    sc = np.where(c1 > c0, 1, -1)
    cmajor = dc >= dr
    a = np.maximum(np.maximum(dr, dc), 1)[:, None]  # major extent (1 for a one-cell line)
    b = np.minimum(dr, dc)[:, None]
    n = np.maximum(dr, dc) + 1
    i = np.arange(int(n.max()) if n.size else 0, dtype=np.int64)[None, :]
    minor = (2 * i * b + a - 1) // (2 * a)
    cm = cmajor[:, None]
    rows = r0 + sr[:, None] * np.where(cm, minor, i)
    cols = c0 + sc[:, None] * np.where(cm, i, minor)
    return rows, cols, n


def check_grid(data, geom: GridGeometry) -> np.ndarray:
    """The one grid check: a 2-D integer array of shape (geom.height, geom.width) and a geometry
    with a positive resolution and a finite origin. Returns the array; GridError otherwise."""
    if not isinstance(geom, GridGeometry):
        raise GridError(f"geometry must be a GridGeometry (got {type(geom).__name__})")
    g = np.asarray(data)
    if g.ndim != 2 or g.shape != (geom.height, geom.width) or g.size == 0:
        raise GridError(f"grid shape {g.shape} does not match geometry "
                        f"{geom.height}x{geom.width} (rows x cols)")
    if not np.issubdtype(g.dtype, np.integer):
        raise GridError(f"grid must be an integer array (got {g.dtype})")
    if not (math.isfinite(geom.resolution) and geom.resolution > 0
            and math.isfinite(geom.origin_x) and math.isfinite(geom.origin_y)):
        raise GridError(f"bad grid geometry {geom}")
    return g


_ALIGN = 64  # [bytes]


def _aligned(shape: tuple[int, ...], dtype) -> np.ndarray:
    """An empty C-contiguous array whose data starts on a 64-byte boundary."""
    n = int(np.prod(shape)) * np.dtype(dtype).itemsize
    buf = np.empty(n + _ALIGN, np.uint8)
    off = (-buf.ctypes.data) % _ALIGN
    return buf[off:off + n].view(dtype).reshape(shape)


def distance_transform(src: np.ndarray) -> np.ndarray:
    """Exact Euclidean distance [cells] from each cell to the nearest zero cell of the uint8
    mask ``src`` (``cv2.distanceTransform``, L2, precise mask), float32.

    OpenCV's result differs in the last bit with where its input and output arrays lie in
    memory (SIMD paths), so the same map gave different clearances from run to run and a
    lockstep run was not quite deterministic. Both arrays are placed on 64-byte boundaries here,
    which makes the result a function of the mask alone. A mask without any zero cell gives
    cv2's "infinitely far" (~FLT_MAX) everywhere."""
    s = _aligned(src.shape, np.uint8)
    s[...] = src
    dst = _aligned(src.shape, np.float32)
    cv2.distanceTransform(s, cv2.DIST_L2, cv2.DIST_MASK_PRECISE, dst=dst)
    return dst


def reframe(arr: np.ndarray, old: GridGeometry, new: GridGeometry, fill=0) -> np.ndarray:
    """A layer kept beside a growing map, moved into the map's new geometry: the cells the two
    share keep their values, new cells get ``fill``. Geometries of the same resolution whose
    origins differ by whole cells (as the mapper grows its grid); otherwise the layer cannot
    be carried over and comes back all ``fill``."""
    out = np.full((new.height, new.width), fill, dtype=arr.dtype)
    if old.resolution != new.resolution:
        return out
    fr, fc = ((old.origin_y - new.origin_y) / new.resolution,
              (old.origin_x - new.origin_x) / new.resolution)
    r0, c0 = round(fr), round(fc)
    if abs(fr - r0) > 1e-6 or abs(fc - c0) > 1e-6:
        return out
    # the overlap in the new grid's cells, and where it lies in the old one
    nr0, nc0 = max(r0, 0), max(c0, 0)
    nr1, nc1 = min(r0 + old.height, new.height), min(c0 + old.width, new.width)
    if nr1 > nr0 and nc1 > nc0:
        out[nr0:nr1, nc0:nc1] = arr[nr0 - r0:nr1 - r0, nc0 - c0:nc1 - c0]
    return out


def crop_known(grid: np.ndarray, geom: GridGeometry, margin: int = 1
               ) -> tuple[np.ndarray, GridGeometry]:
    """The part of the grid (a view) that holds every observed cell (value != -1), grown by
    margin cells (clipped at the grid's edge), and its geometry. Outside it everything is
    never observed, so with margin >= 1 a ring of unknown cells is kept: distances to occupied
    cells, frontiers, unknown connectivity and paths through known space come out the same as
    on the whole grid. Nothing observed: the grid itself. The mapper's grid keeps a wide
    margin of unknown around what it has seen (mapper.grow_margin), so this is often half of it.
    """
    g = np.asarray(grid)
    win = known_window(g, margin)
    if win is None:
        return g, geom
    rs, cs = win
    res = geom.resolution
    return g[win], GridGeometry(res, geom.origin_x + cs.start * res,
                                geom.origin_y + rs.start * res, cs.stop - cs.start,
                                rs.stop - rs.start)


def known_window(grid: np.ndarray, margin: int = 1) -> tuple[slice, slice] | None:
    """(rows, cols) slices of the bounding box of the observed cells grown by margin cells
    (clipped at the grid's edge); None when that is the whole grid or nothing is observed."""
    g = np.asarray(grid)
    known = g != -1
    rows = np.flatnonzero(known.any(axis=1))
    if len(rows) == 0:
        return None
    cols = np.flatnonzero(known[rows[0]:rows[-1] + 1].any(axis=0))
    r0, r1 = max(0, int(rows[0]) - margin), min(g.shape[0], int(rows[-1]) + 1 + margin)
    c0, c1 = max(0, int(cols[0]) - margin), min(g.shape[1], int(cols[-1]) + 1 + margin)
    if (r0, c0, r1, c1) == (0, 0, g.shape[0], g.shape[1]):
        return None
    return slice(r0, r1), slice(c0, c1)


def classify(data: np.ndarray, p_free: float = 0.35, p_occ: float = 0.65) -> np.ndarray:
    """int8 occupancy -> uint8 classes UNKNOWN / FREE / OCCUPIED.

    Known free: 0 <= value < p_free*100; occupied: value > p_occ*100; everything else
    (including -1) is unknown.
    """
    d = np.asarray(data)
    if d.dtype == np.int8:  # the wire type: one table lookup per cell
        return _lookup(d, _class_table(float(p_free), float(p_occ)))
    out = np.zeros(d.shape, dtype=np.uint8)
    out[(d >= 0) & (d < p_free * 100.0)] = FREE
    out[d > p_occ * 100.0] = OCCUPIED
    return out


def _lookup(d: np.ndarray, table: np.ndarray) -> np.ndarray:
    """table (256 uint8) at each int8 cell of d, indexed by its uint8 bit pattern: OpenCV's
    lookup for a 2-D grid (a few times faster than numpy's indexing), numpy's otherwise."""
    u = d.view(np.uint8)
    return cv2.LUT(u, table) if u.ndim == 2 and u.size else table[u]


@functools.lru_cache(maxsize=16)
def _class_table(p_free: float, p_occ: float) -> np.ndarray:
    """classify() for every int8 value, indexed by the value's uint8 bit pattern."""
    v = np.arange(256, dtype=np.uint8).view(np.int8).astype(np.float64)
    out = np.zeros(256, dtype=np.uint8)
    out[(v >= 0) & (v < p_free * 100.0)] = FREE
    out[v > p_occ * 100.0] = OCCUPIED
    return out


@functools.lru_cache(maxsize=16)
def _mask_table(cls: int, p_free: float, p_occ: float) -> np.ndarray:
    """1 for the int8 values of class cls under (p_free, p_occ), as uint8 by bit pattern."""
    return (_class_table(p_free, p_occ) == cls).astype(np.uint8)


@functools.lru_cache(maxsize=16)
def _undecided_table(p_free: float, p_occ: float) -> np.ndarray:
    """1 for the int8 values that are observed (not -1) and neither free nor occupied."""
    out = (_class_table(p_free, p_occ) == UNKNOWN).astype(np.uint8)
    out[np.uint8(255)] = 0  # -1
    return out


def free_mask(data: np.ndarray, p_free: float = 0.35) -> np.ndarray:
    d = np.asarray(data)
    if d.dtype == np.int8:
        return _lookup(d, _mask_table(FREE, float(p_free), 101.0)).view(bool)
    return (d >= 0) & (d < p_free * 100.0)


def occupied_mask(data: np.ndarray, p_occ: float = 0.65) -> np.ndarray:
    d = np.asarray(data)
    if d.dtype == np.int8:
        return _lookup(d, _mask_table(OCCUPIED, -1.0, float(p_occ))).view(bool)
    return d > p_occ * 100.0


_KERNEL3 = np.ones((3, 3), np.uint8)
CROSS = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))  # a cell and its 4-neighbours


def _undecided(g: np.ndarray, never: np.ndarray, p_free: float, p_occ: float) -> np.ndarray:
    """The observed cells of g (never: its never-observed ones) that are neither free nor
    occupied."""
    if g.dtype == np.int8:
        return _lookup(g, _undecided_table(float(p_free), float(p_occ))).view(bool)
    return (classify(g, p_free, p_occ) == UNKNOWN) & ~never


def _joined(never: np.ndarray, undecided: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(labels, keep): the 8-connected components of the undecided cells, and per label
    whether it is 8-adjacent to a never-observed cell (label 0, the other cells: False)."""
    n, labels = cv2.connectedComponents(undecided.view(np.uint8), connectivity=8)
    keep = np.zeros(n, dtype=bool)
    keep[labels[cv2.dilate(never.view(np.uint8), _KERNEL3).view(bool) & undecided]] = True
    keep[0] = False
    return labels, keep


def unknown_mask(grid: np.ndarray, p_free: float = 0.35, p_occ: float = 0.65) -> np.ndarray:
    """Unexplored cells (bool): never observed (-1), plus the undecided cells (between p_free
    and p_occ) 8-connected to never-observed space: the band of once-seen cells at the edge of
    the laser's reach is still unexplored, while undecided specks along walls (hit/miss noise,
    enclosed by known cells) are not."""
    g = np.asarray(grid)
    win = known_window(g)
    if win is not None:  # outside the observed cells' box (+ a ring) all is never observed
        out = np.ones(g.shape, dtype=bool)
        out[win] = unknown_mask(g[win], p_free, p_occ)
        return out
    never = g == -1
    undecided = _undecided(g, never, p_free, p_occ)
    if not undecided.any() or not never.any():
        return never
    # an undecided component joins never-observed space iff one of its cells is 8-adjacent to
    # a never-observed cell (two undecided components are never adjacent): label only the
    # undecided cells, which are few, instead of the whole unknown area
    labels, keep = _joined(never, undecided)
    if not keep.any():
        return never
    if keep[1:].all():
        return never | undecided
    return never | keep[labels]


def open_unknown(grid: np.ndarray, pocket_cells: int = 0, p_free: float = 0.35,
                 p_occ: float = 0.65, reach: np.ndarray | None = None,
                 min_reach: int = 1, min_area: int = 0) -> np.ndarray:
    """Unexplored cells (bool, :func:`common.grid.unknown_mask`: never observed plus the
    undecided band connected to it, as the frontier baseline sees them), without the enclosed
    pockets smaller than pocket_cells.

    A pocket is an 8-connected unknown component that does not touch the grid border (the
    mapper keeps a margin of unknown around everything it has seen, so real unexplored space
    always does) and has fewer than pocket_cells cells: meant for the inside of an obstacle
    glimpsed through a notch, which no viewpoint can ever reveal. Size alone does not tell such
    a pocket from a shadow that a viewpoint would reveal: lse_arena's stair-step wedge is the
    shadow of a wall corner in a 2.0 x 0.7 m bay that is free in the map, enclosed by the walls
    and its own shadow line (docs/design.md, "Enclosed pockets").

    reach: cells the robot can drive its centre to (bool, the grid's shape). A pocket of at
    least min_area cells with at least min_reach reachable cells 4-adjacent to it is kept: the
    robot can stand beside it along a frontier that long and look in, so a viewpoint can
    reveal it. The inside of an obstacle has no such border (a notch the robot's centre fits
    through is an opening, not a notch); a laser shadow in open space does, such as
    lse_arena's wedge. A speck of unseen floor, or a box whose outline is still undecided,
    borders the reachable space only along a few cells, so min_reach (a frontier group's
    minimum length in cells) keeps them out.
    pocket_cells <= 0 keeps every unknown cell.
    """
    g = np.asarray(grid)
    win = known_window(g) if pocket_cells > 0 else None
    if win is not None:  # a pocket lies inside the observed cells' box; the ring of unknown
        out = np.ones(g.shape, dtype=bool)  # kept around it joins everything outside
        out[win] = open_unknown(g[win], pocket_cells, p_free, p_occ,
                                None if reach is None else reach[win], min_reach, min_area)
        return out
    unknown = unknown_mask(g, p_free, p_occ)
    if pocket_cells <= 0 or not unknown.any():
        return unknown
    n, labels, stats, _ = cv2.connectedComponentsWithStats(unknown.view(np.uint8), connectivity=8)
    h, w = unknown.shape
    x, y = stats[:, cv2.CC_STAT_LEFT], stats[:, cv2.CC_STAT_TOP]
    bw, bh = stats[:, cv2.CC_STAT_WIDTH], stats[:, cv2.CC_STAT_HEIGHT]
    border = (x == 0) | (y == 0) | (x + bw == w) | (y + bh == h)
    pocket = ~border & (stats[:, cv2.CC_STAT_AREA] < pocket_cells)
    pocket[0] = False  # label 0: the known cells
    if reach is not None and pocket.any():  # a pocket the robot can look into is no pocket
        pocket &= ((_reachable_border(labels, np.asarray(reach, dtype=bool), pocket)
                    < min_reach) | (stats[:, cv2.CC_STAT_AREA] < min_area))
    if not pocket.any():
        return unknown
    out = unknown.copy()
    for k in np.flatnonzero(pocket):  # pockets are small: clear each in its bounding box
        sl = np.s_[y[k]:y[k] + bh[k], x[k]:x[k] + bw[k]]
        out[sl] &= labels[sl] != k
    return out


def open_unknown_at(grid: np.ndarray, rows: slice, cols: slice, pocket_cells: int = 0,
                    p_free: float = 0.35, p_occ: float = 0.65, margin: int | None = None
                    ) -> np.ndarray | None:
    """``open_unknown(grid, pocket_cells, p_free, p_occ)[rows, cols]`` (no reach rule) worked
    out from the cells within margin of the window alone, or None where they cannot settle it
    (then the whole-map mask is the answer: :class:`OpenUnknown`).

    The whole-map rules, read in the square S = the window grown by margin (clipped to the
    grid), whose sides inside the grid are its *open* edges:
    - an undecided component is unexplored iff it is 8-adjacent to a never-observed cell. One
      without a cell on an open edge has all its neighbours in S; one on an open edge that is
      not seen to touch never-observed cells in S may do so outside: unsettled.
    - an unknown component is a pocket iff it does not reach the grid's border and has fewer
      than pocket_cells cells (open_unknown's known window is only a shortcut: its border
      cells are unobserved, joined to everything outside). One with a cell on an open edge
      has at least its cells in S: with pocket_cells of them it is no pocket, with fewer it is
      unsettled. Only components with a cell in the window matter.
    rows, cols: slices with step 1 inside the grid. margin [cells]: default twice the side of
    a square pocket, at least 4."""
    g = np.asarray(grid)
    h_all, w_all = g.shape
    if margin is None:
        margin = max(4, 2 * int(math.ceil(math.sqrt(max(pocket_cells, 1)))))
    r0, r1, c0, c1 = rows.start, rows.stop, cols.start, cols.stop
    a0, a1 = max(0, r0 - margin), min(h_all, r1 + margin)
    b0, b1 = max(0, c0 - margin), min(w_all, c1 + margin)
    sub = g[a0:a1, b0:b1]
    h, w = sub.shape
    edge = np.zeros((h, w), dtype=bool)  # the open edges: neighbours outside S in the grid
    edge[0, :] |= a0 > 0
    edge[-1, :] |= a1 < h_all
    edge[:, 0] |= b0 > 0
    edge[:, -1] |= b1 < w_all
    never = sub == -1
    unknown = never
    undecided = _undecided(sub, never, p_free, p_occ)
    if undecided.any():
        labels, keep = _joined(never, undecided)
        cut = np.zeros(len(keep), dtype=bool)
        cut[labels[edge & undecided]] = True
        cut[0] = False
        if (cut & ~keep).any():
            return None
        unknown = never | keep[labels]
    win = np.s_[r0 - a0:r1 - a0, c0 - b0:c1 - b0]
    if pocket_cells <= 0 or not unknown[win].any():
        return unknown[win].copy()
    n, labels, stats, _ = cv2.connectedComponentsWithStats(unknown.view(np.uint8), connectivity=8)
    x, y = stats[:, cv2.CC_STAT_LEFT], stats[:, cv2.CC_STAT_TOP]
    bw, bh = stats[:, cv2.CC_STAT_WIDTH], stats[:, cv2.CC_STAT_HEIGHT]
    border = (((x == 0) & (b0 == 0)) | ((y == 0) & (a0 == 0))
              | ((x + bw == w) & (b1 == w_all)) | ((y + bh == h) & (a1 == h_all)))
    small = stats[:, cv2.CC_STAT_AREA] < pocket_cells
    cut = np.zeros(n, dtype=bool)
    cut[labels[edge & unknown]] = True
    inside = np.zeros(n, dtype=bool)
    inside[labels[win]] = True
    inside[0] = False  # label 0: the known cells
    if (inside & cut & small & ~border).any():
        return None
    pocket = inside & ~cut & small & ~border
    lab = labels[win]
    return unknown[win] & ~pocket[lab]


class OpenUnknown:
    """:func:`open_unknown` (grid, pocket_cells, p_free, p_occ), asked a window at a time:
    ``mask[r0:r1, c0:c1]`` is worked out from the cells around the window
    (:func:`open_unknown_at`; where its default margin leaves it unsettled, again with
    WIDER), and the whole-map mask is made (once) only where neither settles it, or for
    ``np.asarray(mask)``. For callers that read a few small windows of a
    large map (:func:`near_frontier`, :func:`nearest_occupied`). ``local`` and ``whole``
    count the windows answered each way."""

    WIDER = 64  # [cells] the margin of a second try, where the default one left it unsettled

    def __init__(self, grid: np.ndarray, pocket_cells: int = 0, p_free: float = 0.35,
                 p_occ: float = 0.65):
        self.grid = np.asarray(grid)
        self.shape = self.grid.shape
        self._args = (int(pocket_cells), float(p_free), float(p_occ))
        self._whole: np.ndarray | None = None
        self.local = 0
        self.whole = 0

    def full(self) -> np.ndarray:
        """The whole-map mask, made on the first call."""
        if self._whole is None:
            self._whole = open_unknown(self.grid, *self._args)
        return self._whole

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        m = self.full()  # kept for the later windows: a copy when one is asked for
        return m.astype(dtype) if dtype is not None else (m.copy() if copy else m)

    def __getitem__(self, key):
        if self._whole is None and isinstance(key, tuple) and len(key) == 2 and all(
                isinstance(k, slice) and k.step in (None, 1) for k in key):
            (r0, r1, _), (c0, c1, _) = (k.indices(n) for k, n in zip(key, self.shape, strict=True))
            if r0 < r1 and c0 < c1:
                for margin in (None, self.WIDER):
                    out = open_unknown_at(self.grid, slice(r0, r1), slice(c0, c1), *self._args,
                                          margin=margin)
                    if out is not None:
                        self.local += 1
                        return out
        self.whole += 1
        return self.full()[key]


def _reachable_border(labels: np.ndarray, reach: np.ndarray, wanted: np.ndarray
                      ) -> np.ndarray:
    """Per label 0..n-1 (n = len(wanted)): how many reach cells are 4-adjacent to a cell of
    that label (each cell counted once per label), for the labels marked in ``wanted`` (the
    others count 0): the four neighbours' labels of each reach cell beside a wanted label,
    the unwanted ones set to n, sorted, a label counted where it differs from the one
    before."""
    n = len(wanted)
    beside = cv2.dilate(wanted[labels].view(np.uint8), CROSS).view(bool) & reach
    rr, cc = np.nonzero(beside)  # the few reach cells that touch a wanted label
    h, w = labels.shape
    nb = np.full((4, rr.size), n, dtype=labels.dtype)  # n: outside the grid, not counted
    for k, (dr, dc) in enumerate(((1, 0), (-1, 0), (0, 1), (0, -1))):
        r, c = rr + dr, cc + dc
        ok = (r >= 0) & (r < h) & (c >= 0) & (c < w)
        nb[k, ok] = labels[r[ok], c[ok]]
    nb[~np.append(wanted, False)[nb]] = n
    nb.sort(axis=0)
    first = np.ones(nb.shape, dtype=bool)
    first[1:] = nb[1:] != nb[:-1]
    return np.bincount(nb[first], minlength=n + 1)[:n]


def _window(x: float, y: float, geom: GridGeometry, radius: float
            ) -> tuple[int, int, int, int] | None:
    """(r0, r1, c0, c1): the grid's cells within radius [m] (plus one) of (x, y) [m], clipped
    to the grid; None when that square lies outside it."""
    r, c = geom.world_to_cell(x, y)
    k = int(math.ceil(radius / geom.resolution)) + 1
    r0, r1 = max(0, int(r) - k), min(geom.height, int(r) + k + 1)
    c0, c1 = max(0, int(c) - k), min(geom.width, int(c) + k + 1)
    return None if r0 >= r1 or c0 >= c1 else (r0, r1, c0, c1)


def nearest_occupied(nx: float, ny: float, grid: np.ndarray, geom: GridGeometry, limit: float,
                     p_occ: float = 0.65, unknown: np.ndarray | None = None) -> float:
    """Distance [m] from (nx, ny) [m] to the nearest occupied cell centre (value >= p_occ *
    100), or with unknown (a mask of the grid's shape, :func:`open_unknown`) the nearest
    occupied or unknown one: the radius of the known free disc around the point. At most
    limit [m] (also without one within it). grid: int8 occupancy."""
    if limit <= 0.0:
        return 0.0
    win = _window(nx, ny, geom, limit)
    if win is None:
        return float(limit)
    r0, r1, c0, c1 = win
    blocked = grid[r0:r1, c0:c1] >= p_occ * 100.0
    if unknown is not None:
        blocked |= unknown[r0:r1, c0:c1]
    rr, cc = np.nonzero(blocked)
    if len(rr) == 0:
        return float(limit)
    x, y = geom.cell_to_world(rr + r0, cc + c0)
    return float(min(limit, np.hypot(x - nx, y - ny).min()))


def open_never_near(grid: np.ndarray, geom: GridGeometry, x: float, y: float, half: float,
                    pocket_cells: int) -> np.ndarray:
    """The never-observed cells within half [m] of (x, y) [m] whose 8-connected never-observed
    component, counted within that square alone, has pocket_cells cells or more (bool, the
    grid's shape; False elsewhere): a subset of :func:`open_unknown` (grid, pocket_cells, any
    reach) found without looking at the rest of the map.

    Why a subset: such a cell is unexplored (``unknown_mask`` holds every never-observed cell),
    and its component there is no pocket. Either the square's component lies inside the
    observed cells' window, and then its unknown component there is at least as large; or it
    leaves that window, and then its part inside reaches the window's edge (a pocket never
    does) or the cell lies outside (all unexplored there). Used as a sufficient test before the
    whole-map one (``near_frontier`` with this mask finds no more than with open_unknown's)."""
    out = np.zeros(np.shape(grid), dtype=bool)
    win = _window(x, y, geom, half)
    if win is None:
        return out
    r0, r1, c0, c1 = win
    never = (np.asarray(grid)[r0:r1, c0:c1] == -1).view(np.uint8)
    if not never.any():
        return out
    _n, labels, stats, _ = cv2.connectedComponentsWithStats(never, connectivity=8)
    big = stats[:, cv2.CC_STAT_AREA] >= max(1, pocket_cells)
    big[0] = False  # label 0: the observed cells
    out[r0:r1, c0:c1] = big[labels]
    return out


def near_frontier(nx: float, ny: float, grid: np.ndarray, geom: GridGeometry, radius: float,
                  p_free: float = 0.35, unknown: np.ndarray | None = None,
                  min_cells: int = 1, heading: float | None = None,
                  half_angle: float = math.pi) -> bool:
    """Is there a frontier cell (known free, 4-adjacent to unknown) within radius [m] of (nx, ny)
    (at least min_cells of them)? With heading [rad], only cells whose bearing from (nx, ny)
    lies within half_angle [rad] of it count (a cone ahead).

    A place next to a frontier is where the map simply stops; a wall hides the unknown behind
    it (occupied cells are never frontier). grid: int8 occupancy (-1 unknown, 0..100);
    radius <= 0: False. unknown: the unknown mask to use, the grid's shape
    (:func:`open_unknown`, or an :class:`OpenUnknown`: only the window around the point is
    read; default: every never-observed cell). Used by the reliability index
    (is an end node's surrounding examined?) and the planner (is a place still open?).
    """
    if radius <= 0.0:
        return False
    win = _window(nx, ny, geom, radius)
    if win is None:
        return True  # node outside the map: nothing is known around it
    r0, r1, c0, c1 = win
    win = grid[r0:r1, c0:c1]
    free = (win >= 0) & (win < p_free * 100.0)
    unk = win < 0 if unknown is None else unknown[r0:r1, c0:c1]
    pad = np.pad(unk, 1, constant_values=False)
    touch = pad[:-2, 1:-1] | pad[2:, 1:-1] | pad[1:-1, :-2] | pad[1:-1, 2:]
    front = free & touch
    if not front.any():
        return False
    rr, cc = np.nonzero(front)
    x, y = geom.cell_to_world(rr + r0, cc + c0)
    near = np.hypot(x - nx, y - ny) <= radius
    if heading is not None and half_angle < math.pi:
        off = np.arctan2(y - ny, x - nx) - heading
        near &= np.abs(np.arctan2(np.sin(off), np.cos(off))) <= half_angle
    return int(np.count_nonzero(near)) >= max(1, min_cells)
