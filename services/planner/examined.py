"""Frontier cells that are surfaces, not openings (pure): the cells the map showed occupied
(:class:`common.surfaces.Surfaces`, on) and the cells looked at that stayed frontier
(:class:`Examined`).

A frontier cell is a known free cell with an unknown 4-neighbour. Where an obstacle's face
lies inside a cell (a wall 0.15 m thick on a 0.1 m grid, a shelf's side, a ragged SLAM wall),
beams that graze the face mark that cell free, beams that meet the face end in that very cell,
and no beam ever reaches the cell behind it: the pair "free cell, unknown neighbour" never
resolves, however long the robot looks. A frontier search that counts such a pair chases a
row of them along every wall. Those cells flip: the robot passing close marks them
occupied, grazing beams from afar clear them again. :class:`common.surfaces.Surfaces`
remembers them (docs/design.md "Surfaces"); :class:`Examined`, off by default
(``planner.examine_range`` 0), judges the ones that never flip (docs/design.md
"Experimental, off by default" says what was measured).

The examined rule: a frontier cell counts as examined once the robot has looked at it
squarely from close by ``views`` times, and examined cells are no frontier:

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
from topoexplore.common.grid import FREE, UNKNOWN, GridGeometry

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
