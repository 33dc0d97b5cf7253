"""Frontier cells that are surfaces, not openings (pure): the cells the map showed occupied
(:class:`Surfaces`, on) and the cells looked at that stayed frontier (:class:`Examined`).

A frontier cell is a known free cell with an unknown 4-neighbour. Where an obstacle's face
lies inside a cell (a wall 0.15 m thick on a 0.1 m grid, a shelf's side, a ragged SLAM wall),
beams that graze the face mark that cell free, beams that meet the face end in that very cell,
and no beam ever reaches the cell behind it: the pair "free cell, unknown neighbour" never
resolves, however long the robot looks. A frontier search that counts such a pair chases a
row of them along every wall. Those cells flip: the robot passing close marks them occupied,
grazing beams from afar clear them again. :class:`Surfaces` remembers them (docs/design.md
"Surfaces"); :class:`Examined`, off by default (``planner.examine_range`` 0), judges the ones
that never flip (docs/design.md "Experimental, off by default" says what was measured).

The examined rule: a frontier cell counts as examined once the robot has looked at it squarely from
close by ``views`` times, and examined cells are no frontier:

- close: the cell centre is within ``reach`` [m] of the robot (at 1 deg between beams, beams
  pass at most 3.5 cm apart at 2 m, so beams cross every cell of 0.1 m there);
- in the laser's view: its bearing from the robot's heading is at most ``bearing`` [rad];
- in line of sight: every cell on the segment from the robot to it is known free on the map;
- squarely: the line of sight points into one of its unknown neighbours, within ``angle``
  [rad], so that beams through the cell would go on into that neighbour and map it.

If the cell were open, the beams of such a view would have mapped the neighbour and the cell
would have stopped being a frontier cell; since it did not, something inside the cell stops
them. Views are counted on separate updates, so a map that lags the pose by a scan or two
cannot examine a cell alone. Cells are remembered by their global index (cell centre // res),
which survives the map growing or being cropped differently.
"""

from __future__ import annotations

import math

import numpy as np

from topoexplore.common.checkpoint import CheckpointError, checked
from topoexplore.common.grid import FREE, OCCUPIED, UNKNOWN, GridGeometry

_DIRS = ((1, 0), (-1, 0), (0, 1), (0, -1))  # (d_row, d_col) of the 4-neighbours


def _keys(geom: GridGeometry, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """Global cell index of (rows, cols): (floor(centre_x / res), floor(centre_y / res))
    packed into one int64."""
    x, y = geom.cell_to_world(rows, cols)
    ix = np.floor(x / geom.resolution).astype(np.int64)
    iy = np.floor(y / geom.resolution).astype(np.int64)
    return (ix << 32) ^ (iy & 0xFFFFFFFF)


class Examined:
    """The examined frontier cells of one exploration; ``reach`` <= 0 disables the rule."""

    def __init__(self, reach: float, bearing: float, angle: float, views: int,
                 name: str = "examined"):
        self.reach = reach  # [m]
        self.name = name  # of its checkpoint arrays (two trackers share a planner's)
        self.bearing = bearing  # [rad]
        self.cos_angle = math.cos(angle)
        self.views = views
        self._count: dict[int, int] = {}
        self._closed: set[int] = set()
        self._closed_arr = np.zeros(0, dtype=np.int64)

    @property
    def enabled(self) -> bool:
        return self.reach > 0.0

    def observe(self, x: float, y: float, th: float, classes: np.ndarray,
                geom: GridGeometry) -> int:
        """Count this update's square views of frontier cells from the robot at (x [m],
        y [m], th [rad]) on the cell classes (UNKNOWN / FREE / OCCUPIED) of geom; returns
        how many cells became examined."""
        if not self.enabled:
            return 0
        res = geom.resolution
        n = int(math.ceil(self.reach / res)) + 1
        (rr,), (cc,) = geom.world_to_cell(np.array([x]), np.array([y]))
        r0, r1 = max(0, rr - n), min(geom.height, rr + n + 1)
        c0, c1 = max(0, cc - n), min(geom.width, cc + n + 1)
        if r0 >= r1 or c0 >= c1:
            return 0
        win = np.pad(classes[r0:r1, c0:c1], 1, constant_values=UNKNOWN)
        free = win[1:-1, 1:-1] == FREE
        unk = win == UNKNOWN
        rows, cols = np.nonzero(free & (unk[:-2, 1:-1] | unk[2:, 1:-1] | unk[1:-1, :-2]
                                        | unk[1:-1, 2:]))
        if len(rows) == 0:
            return 0
        cx, cy = geom.cell_to_world(rows + r0, cols + c0)
        dx, dy = cx - x, cy - y
        dist = np.hypot(dx, dy)
        bearing = np.abs((np.arctan2(dy, dx) - th + math.pi) % (2 * math.pi) - math.pi)
        ok = (dist <= self.reach) & (dist > 1e-9) & (bearing <= self.bearing)
        square = np.zeros(len(rows), dtype=bool)
        with np.errstate(invalid="ignore", divide="ignore"):
            ux, uy = dx / dist, dy / dist
        for d_r, d_c in _DIRS:  # an unknown neighbour the line of sight points into
            nb = unk[rows + 1 + d_r, cols + 1 + d_c]
            square |= nb & (ux * d_c + uy * d_r >= self.cos_angle)
        ok &= square
        if not ok.any():
            return 0
        idx = np.nonzero(ok)[0]
        seen = line_of_sight(win[1:-1, 1:-1] == FREE, (rr - r0, cc - c0), rows[idx], cols[idx])
        idx = idx[seen]
        if len(idx) == 0:
            return 0
        new = 0
        for k in _keys(geom, rows[idx] + r0, cols[idx] + c0).tolist():
            if k in self._closed:
                continue
            v = self._count.get(k, 0) + 1
            self._count[k] = v
            if v >= self.views:
                self._closed.add(k)
                del self._count[k]
                new += 1
        if new:
            self._closed_arr = np.fromiter(self._closed, dtype=np.int64, count=len(self._closed))
        return new

    def mask(self, geom: GridGeometry) -> np.ndarray | None:
        """bool (height, width): the examined cells of geom; None if there are none."""
        keys = self._closed_arr
        if len(keys) == 0:
            return None
        res = geom.resolution
        ix, iy = keys >> 32, (keys & 0xFFFFFFFF).astype(np.int32).astype(np.int64)
        cols = np.rint(((ix + 0.5) * res - geom.origin_x) / res - 0.5).astype(np.int64)
        rows = np.rint(((iy + 0.5) * res - geom.origin_y) / res - 0.5).astype(np.int64)
        inside = geom.inside(rows, cols)
        out = np.zeros((geom.height, geom.width), dtype=bool)
        out[rows[inside], cols[inside]] = True
        return out

    def checkpoint(self) -> dict[str, np.ndarray]:
        return {f"{self.name}_closed": self._closed_arr.copy(),
                f"{self.name}_count": np.array(sorted(self._count.items()), np.int64).reshape(
                    len(self._count), 2)}

    def restore(self, arrays: dict[str, np.ndarray]) -> None:
        closed = checked(arrays, f"{self.name}_closed", "i", (None,)).astype(np.int64)
        count = checked(arrays, f"{self.name}_count", "i", (None, 2)).astype(np.int64)
        if (count[:, 1] < 0).any():
            raise CheckpointError("planner checkpoint: examined counts out of range")
        self._closed = set(closed.tolist())
        self._closed_arr = np.fromiter(self._closed, dtype=np.int64, count=len(self._closed))
        self._count = {int(k): int(v) for k, v in count}

    def snapshot(self) -> dict[str, int]:
        return {"examined": len(self._closed), "viewed": len(self._count)}


MAX_SURFACE_CELLS = 50_000 ** 2 // 4  # the memory's bound (a 400 m square at 0.1 m: 16e6)


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
    does not make a surface. A person who stood at the border of the known space would (a
    real robot's case; the simulator has nothing that moves).

    The counts are kept on the global cell index (cell centre // resolution), as
    :class:`Examined`'s keys, in one array that grows with the map."""

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

    def _window(self, geom: GridGeometry, grow: bool) -> tuple[slice, slice] | None:
        """The slices of the memory that geom covers (grown to cover it with grow; None
        without, when geom reaches outside it)."""
        r0, c0 = self._offset(geom)
        h, w = geom.height, geom.width
        mh, mw = self._count.shape
        lo_r, lo_c = min(r0, self._row0) if mh else r0, min(c0, self._col0) if mw else c0
        hi_r = max(r0 + h, self._row0 + mh) if mh else r0 + h
        hi_c = max(c0 + w, self._col0 + mw) if mw else c0 + w
        if (lo_r, lo_c, hi_r, hi_c) != (self._row0, self._col0, self._row0 + mh,
                                         self._col0 + mw):
            if not grow:
                return None
            if (hi_r - lo_r) * (hi_c - lo_c) > MAX_SURFACE_CELLS:
                raise ValueError("planner: the surface memory would exceed its bound")
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
        rows, cols = self._window(geom, True)
        view = self._count[rows, cols]
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
            raise CheckpointError("planner checkpoint: surface memory out of range")
        self._count = count.astype(np.uint8)
        self._row0, self._col0 = int(origin[0]), int(origin[1])

    def snapshot(self) -> dict[str, int]:
        return {"surfaces": int(np.count_nonzero(self._count >= max(1, self.views)))}


def line_of_sight(free: np.ndarray, start: tuple[int, int], rows: np.ndarray,
                   cols: np.ndarray) -> np.ndarray:
    """For each target cell (rows[k], cols[k]) of the window: is every cell the segment from
    the start cell's centre to the target's centre passes (sampled every quarter cell, the
    target itself and the start excluded) free?"""
    sr, sc = start
    dr, dc = rows - sr, cols - sc
    steps = int(4 * max(1, int(np.max(np.maximum(np.abs(dr), np.abs(dc))))))
    s = (np.arange(1, steps) / steps)[None, :]
    pr = np.floor(sr + 0.5 + dr[:, None] * s).astype(np.int64)
    pc = np.floor(sc + 0.5 + dc[:, None] * s).astype(np.int64)
    inside = (pr >= 0) & (pr < free.shape[0]) & (pc >= 0) & (pc < free.shape[1])
    prc, pcc = np.clip(pr, 0, free.shape[0] - 1), np.clip(pc, 0, free.shape[1] - 1)
    own = ((pr == rows[:, None]) & (pc == cols[:, None])) | ((pr == sr) & (pc == sc))
    good = (inside & free[prc, pcc]) | own
    return good.all(axis=1)
