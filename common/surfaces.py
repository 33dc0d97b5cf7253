"""Surfaces: cells a map showed occupied, remembered so that grazing beams that clear them later
do not make them frontier cells (pure; docs/design.md "Surfaces")."""

from __future__ import annotations

import numpy as np

from topoexplore.common.checkpoint import CheckpointError, checked
from topoexplore.common.grid import OCCUPIED, GridGeometry

MAX_SURFACE_CELLS = 10_000 ** 2  # the memory's bound: 100 MB, a 1 km square at 0.1 m


class Surfaces:
    """Cells the map has shown occupied on ``views`` updates: surfaces, no frontier cells
    when later free; ``views`` 0 disables the rule.

    Where an obstacle's face lies inside a cell, the robot passing close marks the cell
    occupied (beams end in it), and later beams that graze the face from afar clear it again
    (the textbook inverse sensor model clears every cell a beam crosses). The cell behind it,
    inside the wall, is never observed, so the cleared face cell borders unknown space: a false
    frontier along the wall, which closes when the robot comes close again and opens when it
    leaves (a warehouse's tail: the robot goes from one such row to the next for 1200 s of its
    2770). A frontier cell exists to be looked through; a cell that something inside stopped
    beams on several updates cannot be. A door is never hit, so it stays a frontier. Counted
    on separate updates, so that one noisy hit in front of a face, cleared by the next scan,
    does not make a surface. A person who stood at the border of the known space for as many
    updates would leave surface cells there (a real robot's case; the simulator has nothing
    that moves).

    The counts are kept on the global cell index (cell centre // resolution), as the
    planner's examined cells (services/planner/examined.py), in one array that grows with the
    map. The planner (its frontier mask) and the reliability index (its frontier tests) each
    keep one."""

    def __init__(self, views: int):
        self.views = views
        self._count = np.zeros((0, 0), dtype=np.uint8)  # [global row, global col]
        self._row0 = self._col0 = 0  # global index of _count[0, 0]

    @property
    def enabled(self) -> bool:
        return self.views > 0

    @staticmethod
    def _offset(geom: GridGeometry) -> tuple[int, int]:
        """Global (row, col) index of geom's cell (0, 0)."""
        x, y = geom.cell_to_world(np.array([0]), np.array([0]))
        return (int(np.floor(y[0] / geom.resolution)), int(np.floor(x[0] / geom.resolution)))

    def _window(self, geom: GridGeometry) -> tuple[slice, slice] | None:
        """The slices of the memory that geom covers, grown to cover it; None when that would
        pass MAX_SURFACE_CELLS (the cells beyond are then not remembered: the rule is off
        there, the service goes on)."""
        r0, c0 = self._offset(geom)
        h, w = geom.height, geom.width
        mh, mw = self._count.shape
        if mh == 0:
            lo_r, lo_c, hi_r, hi_c = r0, c0, r0 + h, c0 + w
        else:
            lo_r, lo_c = min(r0, self._row0), min(c0, self._col0)
            hi_r, hi_c = max(r0 + h, self._row0 + mh), max(c0 + w, self._col0 + mw)
        if (lo_r, lo_c, hi_r - lo_r, hi_c - lo_c) != (self._row0, self._col0, mh, mw):
            if (hi_r - lo_r) * (hi_c - lo_c) > MAX_SURFACE_CELLS:
                return None
            big = np.zeros((hi_r - lo_r, hi_c - lo_c), dtype=np.uint8)
            big[self._row0 - lo_r:self._row0 - lo_r + mh,
                self._col0 - lo_c:self._col0 - lo_c + mw] = self._count
            self._count, self._row0, self._col0 = big, lo_r, lo_c
        return (slice(r0 - self._row0, r0 - self._row0 + h),
                slice(c0 - self._col0, c0 - self._col0 + w))

    def observe(self, classes: np.ndarray, geom: GridGeometry) -> None:
        """Count one more view of every cell that is OCCUPIED in classes (cells of geom)."""
        if not self.enabled:
            return
        occ = classes == OCCUPIED
        if not occ.any():
            return
        win = self._window(geom)
        if win is None:
            return
        view = self._count[win]
        view[occ & (view < self.views)] += 1

    def mask(self, geom: GridGeometry) -> np.ndarray | None:
        """bool (height, width): the surface cells of geom; None if there are none."""
        if not self.enabled or self._count.size == 0:
            return None
        r0, c0 = self._offset(geom)
        out = np.zeros((geom.height, geom.width), dtype=bool)
        mh, mw = self._count.shape
        a, b = max(r0, self._row0), min(r0 + geom.height, self._row0 + mh)
        c, d = max(c0, self._col0), min(c0 + geom.width, self._col0 + mw)
        if a < b and c < d:
            out[a - r0:b - r0, c - c0:d - c0] = (
                self._count[a - self._row0:b - self._row0, c - self._col0:d - self._col0]
                >= self.views)
        return out

    def checkpoint(self) -> dict[str, np.ndarray]:
        return {"surfaces_count": self._count.copy(),
                "surfaces_origin": np.array([self._row0, self._col0], np.int64)}

    def restore(self, arrays: dict[str, np.ndarray]) -> None:
        count = checked(arrays, "surfaces_count", "i", (None, None))
        origin = checked(arrays, "surfaces_origin", "i", (2,))
        if (count.size > MAX_SURFACE_CELLS or np.abs(origin).max() > 2 ** 40
                or (count.shape[0] == 0) != (count.shape[1] == 0)
                or (count.size and (count.min() < 0 or count.max() > 255))):
            raise CheckpointError("checkpoint: surface memory out of range")
        self._count = count.astype(np.uint8)
        self._row0, self._col0 = int(origin[0]), int(origin[1])

    def snapshot(self) -> dict[str, int]:
        return {"surfaces": int(np.count_nonzero(self._count >= max(1, self.views)))}
