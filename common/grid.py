"""Grid geometry and cell classification shared by every stage (pure, no I/O).

A grid is an int8 array of shape (height, width), row = y index, column = x index, ROS values:
-1 unknown, 0..100 occupancy probability in percent. Cell (row i, col j) covers the square with
lower-left corner ``origin + (j, i) * resolution``.
"""

from __future__ import annotations

from dataclasses import dataclass

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
