"""Grid geometry and cell classification shared by every stage (pure, no I/O).

A grid is an int8 array of shape (height, width), row = y index, column = x index, ROS values:
-1 unknown, 0..100 occupancy probability in percent. Cell (row i, col j) covers the square with
lower-left corner ``origin + (j, i) * resolution``.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from common import messages as m

UNKNOWN = 0
FREE = 1
OCCUPIED = 2


@dataclass(frozen=True)
class GridGeometry:
    resolution: float  # [m/cell]
    origin_x: float  # [m] world x of the lower-left corner of cell (0, 0)
    origin_y: float  # [m]
    width: int  # cells along x
    height: int  # cells along y

    @staticmethod
    def of(msg: m.OccupancyGrid) -> GridGeometry:
        return GridGeometry(msg.resolution, msg.origin.x, msg.origin.y, msg.width, msg.height)

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


def classify(data: np.ndarray, p_free: float = 0.35, p_occ: float = 0.65) -> np.ndarray:
    """int8 occupancy -> uint8 classes UNKNOWN / FREE / OCCUPIED.

    Known free: 0 <= value < p_free*100; occupied: value > p_occ*100; everything else
    (including -1) is unknown.
    """
    d = np.asarray(data)
    out = np.zeros(d.shape, dtype=np.uint8)
    out[(d >= 0) & (d < p_free * 100.0)] = FREE
    out[d > p_occ * 100.0] = OCCUPIED
    return out


def free_mask(data: np.ndarray, p_free: float = 0.35) -> np.ndarray:
    d = np.asarray(data)
    return (d >= 0) & (d < p_free * 100.0)


def occupied_mask(data: np.ndarray, p_occ: float = 0.65) -> np.ndarray:
    return np.asarray(data) > p_occ * 100.0


def unknown_mask(grid: np.ndarray, p_free: float = 0.35, p_occ: float = 0.65) -> np.ndarray:
    """Unexplored cells (bool): never observed (-1), plus the undecided cells (between p_free
    and p_occ) 8-connected to never-observed space: the band of once-seen cells at the edge of
    the laser's reach is still unexplored, while undecided specks along walls (hit/miss noise,
    enclosed by known cells) are not."""
    g = np.asarray(grid)
    never = g == -1
    undecided = (classify(g, p_free, p_occ) == UNKNOWN) & ~never
    if not undecided.any() or not never.any():
        return never
    both = (never | undecided).astype(np.uint8)
    n, labels = cv2.connectedComponents(both, connectivity=8)
    keep = np.zeros(n, dtype=bool)
    keep[np.unique(labels[never])] = True
    keep[0] = False
    return keep[labels]


def open_unknown(grid: np.ndarray, pocket_cells: int = 0, p_free: float = 0.35,
                 p_occ: float = 0.65) -> np.ndarray:
    """Unexplored cells (bool, :func:`common.grid.unknown_mask`: never observed plus the
    undecided band connected to it, as the frontier baseline sees them), without the enclosed
    pockets smaller than pocket_cells.

    A pocket is an 8-connected unknown component that does not touch the grid border (the
    mapper keeps a margin of unknown around everything it has seen, so real unexplored space
    always does) and has fewer than pocket_cells cells: the inside of an obstacle glimpsed
    through a notch (lse_arena's stair-step block), which no viewpoint can ever reveal.
    pocket_cells <= 0 keeps every unknown cell.
    """
    unknown = unknown_mask(grid, p_free, p_occ)
    if pocket_cells <= 0 or not unknown.any():
        return unknown
    n, labels, stats, _ = cv2.connectedComponentsWithStats(unknown.view(np.uint8), connectivity=8)
    h, w = unknown.shape
    x, y = stats[:, cv2.CC_STAT_LEFT], stats[:, cv2.CC_STAT_TOP]
    bw, bh = stats[:, cv2.CC_STAT_WIDTH], stats[:, cv2.CC_STAT_HEIGHT]
    border = (x == 0) | (y == 0) | (x + bw == w) | (y + bh == h)
    pocket = ~border & (stats[:, cv2.CC_STAT_AREA] < pocket_cells)
    pocket[0] = False  # label 0: the known cells
    if not pocket.any():
        return unknown
    return unknown & ~pocket[labels]
