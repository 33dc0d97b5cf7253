"""Localizer core: where is the robot on the map, given a scan and odometry's guess (pure).

A correlative scan matcher (Olson, "Real-time correlative scan matching", ICRA 2009): the
map's occupied cells become a likelihood field, ``exp(-d^2 / (2 sigma^2))`` of the distance
d [m] to the nearest one; a pose scores the mean likelihood at the scan's end points. The
search covers ``search_xy`` [m] and ``search_theta`` [rad] round the guess:

1. angles: steps small enough that the farthest end point moves by less than a cell;
2. for each angle, every translation on a coarse grid (``coarse`` cells a step) scored on a
   max-pooled field, so a coarse score bounds every fine score of its block from above;
3. the blocks in order of their bound, each searched cell by cell on the fine field, until the
   best fine score beats every remaining bound: the result is the exact best of the fine
   search (branch and bound), found at a fraction of its cost;
4. a match counts when enough end points scored and their mean likelihood reaches
   ``min_score``; else the guess stands (``ok`` False);
5. degenerate scans (Zhang, Kaess & Singh, "On degeneracy of optimization-based state
   estimation problems", ICRA 2016: the solution is kept only in the directions the data
   constrain): when the scan's own surfaces leave a direction nearly unconstrained
   (:func:`scan_conditioning` below ``degenerate_ratio``: two parallel walls, a corridor or an
   aisle), the match keeps odometry's guess along that direction. Scan-to-map matching is
   biased there: the map of the scans before this one ends a little ahead of the robot, the
   end points beyond its edge score nothing, and moving the pose back puts them on mapped
   wall, so every scan pulled the estimate back along the corridor (large-office and the
   generated warehouses lost metres this way; docs/benchmarks.md).

Poses are the robot centre's (map frame); the laser sits ``laser_offset`` [m] ahead.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from topoexplore.common.domain import GridMap, Pose, Scan
from topoexplore.common.params import LocalizerParams


@dataclass(frozen=True)
class Match:
    pose: Pose  # the best pose (the guess when not ok)
    score: float  # mean likelihood of the end points at it (0..1)
    ok: bool  # the match is trusted (enough points, score >= min_score)
    points: int  # end points used
    evaluated: int  # poses scored, coarse blocks and fine cells (the search's cost)
    conditioning: float = 1.0  # weakest / strongest translation information (0..1)


def scan_conditioning(pts: np.ndarray, gap: float = 0.25) -> tuple[float, np.ndarray]:
    """How well a scan's surfaces pin a position (point-to-line information): each end
    point with neighbours on both sides within ``gap`` [m] has a surface normal n (across the
    line through its neighbours); the information is the sum of n n^T. Returns the ratio of its
    eigenvalues, smallest over largest (0: two parallel walls, a corridor), and the unit
    direction of the smallest, in the frame of ``pts``."""
    if len(pts) < 3:
        return 0.0, np.array([1.0, 0.0])
    t = pts[2:] - pts[:-2]
    near = (np.hypot(*(pts[1:-1] - pts[:-2]).T) < gap) & (np.hypot(*(pts[2:] - pts[1:-1]).T) < gap)
    t = t[near]
    ln = np.hypot(t[:, 0], t[:, 1])
    t = t[ln > 1e-9] / ln[ln > 1e-9, None]
    if len(t) < 2:
        return 0.0, np.array([1.0, 0.0])
    nx, ny = -t[:, 1], t[:, 0]
    info = np.array([[nx @ nx, nx @ ny], [nx @ ny, ny @ ny]])
    lam, vec = np.linalg.eigh(info)  # ascending
    return float(max(lam[0], 0.0) / lam[1]), vec[:, 0]


class LocalizerCore:
    def __init__(self, params: LocalizerParams, laser_offset: float = 0.0,
                 p_occ: float = 0.65):
        self.p = params
        self.laser_offset = laser_offset  # [m]
        self.p_occ = p_occ  # a cell at or above this occupancy (0..1) is a wall
        self._field: np.ndarray | None = None  # float32 (H, W) fine likelihood field
        self._coarse: np.ndarray | None = None  # max over each coarse block's reach
        self._geom = None

    @property
    def ready(self) -> bool:
        return self._field is not None

    def set_map(self, grid: GridMap) -> None:
        """Build the likelihood fields of a map (call when the map changed)."""
        occ = grid.data >= round(100 * self.p_occ)
        g = grid.geom
        if not occ.any():
            self._field = self._coarse = None
            return
        # the faces of the walls: occupied cells beside a cell that is not (a beam ends on a
        # face; deep inside a thick wall or a filled block no beam ends, and scoring it as a
        # wall would pull a scan into it)
        face = occ & cv2.dilate((~occ).astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
        # [m] to the nearest face cell's edge (half a cell from the centre of the cell hit)
        d = cv2.distanceTransform((~face).astype(np.uint8), cv2.DIST_L2, 5) * g.resolution
        d = np.maximum(d - 0.5 * g.resolution, 0.0)
        field = np.exp(-0.5 * (d / self.p.sigma) ** 2).astype(np.float32)
        c = self.p.coarse
        # the coarse field at cell (r, c) holds the max of the fine field over the block of
        # translations [r, r + c) x [c, c + c) (a grey dilation with an anchor at the corner)
        k = np.ones((c, c), np.uint8)
        coarse = cv2.dilate(field, k, anchor=(0, 0), borderType=cv2.BORDER_CONSTANT,
                            borderValue=0.0)
        self._field, self._coarse, self._geom = field, coarse, g

    def _points(self, scan: Scan) -> np.ndarray:
        """End points (x, y) [m] in the robot frame, at most max_points, evenly taken."""
        r, a = scan.returns()
        keep = r > 0.0
        r, a = r[keep], a[keep]
        if len(r) > self.p.max_points:
            idx = np.linspace(0, len(r) - 1, self.p.max_points).round().astype(int)
            r, a = r[idx], a[idx]
        return np.column_stack((self.laser_offset + r * np.cos(a), r * np.sin(a)))

    def match(self, scan: Scan, guess: Pose) -> Match:
        """The best pose within the search window round ``guess`` (module docstring)."""
        pts = self._points(scan)
        if self._field is None or len(pts) < self.p.min_points:
            return Match(guess, 0.0, False, len(pts), 0)
        g, p = self._geom, self.p
        res, c = g.resolution, p.coarse
        reach = float(np.max(np.hypot(pts[:, 0], pts[:, 1])))
        dth = max(res / max(reach, res), 1e-3)  # [rad] the farthest point moves < 1 cell
        n_th = int(math.ceil(p.search_theta / dth))
        thetas = guess.theta + dth * np.arange(-n_th, n_th + 1)
        n_xy = int(math.ceil(p.search_xy / res))  # fine cells each way
        n_blocks = int(math.ceil((2 * n_xy + 1) / c))
        H, W = self._field.shape
        n = len(pts)
        # every angle: world end points at the window's corner translation, as cell indices
        base = []
        for th in thetas:
            cs, sn = math.cos(th), math.sin(th)
            wx = guess.x + cs * pts[:, 0] - sn * pts[:, 1] - n_xy * res
            wy = guess.y + sn * pts[:, 0] + cs * pts[:, 1] - n_xy * res
            base.append((np.floor((wy - g.origin_y) / res).astype(np.int64),
                         np.floor((wx - g.origin_x) / res).astype(np.int64)))
        off = np.arange(n_blocks) * c
        bounds = self._bounds(base, off)  # (angle, block row, block col)
        # the motion prior: a penalty growing with the distance from the guess (ties, as
        # along a corridor, go to odometry); a block's bound takes its nearest translation's
        w = p.prior * n
        dth_pen = w * ((thetas - guess.theta) / p.search_theta) ** 2  # (angles,)
        lo = off - n_xy  # the block's nearest offset from the window's centre [cells]
        near = np.where(lo > 0, lo, np.where(lo + c - 1 < 0, lo + c - 1, 0)) * res
        pen_xy = w * (near[:, None] ** 2 + near[None, :] ** 2) / p.search_xy ** 2
        bounds -= dth_pen[:, None, None] + pen_xy[None, :, :]
        order = np.argsort(bounds, axis=None)[::-1]
        best, best_raw, cell, evaluated = -np.inf, 0.0, (0, n_xy, n_xy), bounds.size
        fine = np.arange(c)
        for flat in order:
            t, by, bx = np.unravel_index(flat, bounds.shape)
            if bounds[t, by, bx] <= best:
                break  # no block left can beat the best: it is the fine search's best
            r0, c0 = base[t]
            rr = r0[None, :] + by * c + fine[:, None]  # (c, n)
            cc = c0[None, :] + bx * c + fine[:, None]
            vr = (rr >= 0) & (rr < H)
            vc = (cc >= 0) & (cc < W)
            rr, cc = np.clip(rr, 0, H - 1), np.clip(cc, 0, W - 1)
            vals = self._field[rr[:, None, :], cc[None, :, :]]
            vals = np.where(vr[:, None, :] & vc[None, :, :], vals, 0.0)
            raw = vals.sum(axis=2)  # (c rows, c cols)
            iy = by * c + fine
            ix = bx * c + fine
            s = raw - dth_pen[t] - w * (((iy - n_xy) * res)[:, None] ** 2
                                        + ((ix - n_xy) * res)[None, :] ** 2) / p.search_xy ** 2
            # translations beyond the window (the last block's overhang) do not count
            s[iy > 2 * n_xy, :] = -np.inf
            s[:, ix > 2 * n_xy] = -np.inf
            evaluated += c * c
            k = int(np.argmax(s))
            if s.flat[k] > best:
                best, best_raw = float(s.flat[k]), float(raw.flat[k])
                dy, dx = divmod(k, c)
                cell = (t, by * c + dy, bx * c + dx)
        score = best_raw / n
        if score < p.min_score:
            return Match(guess, score, False, n, evaluated)
        t, iy, ix = cell
        pose = Pose(guess.x + (ix - n_xy) * res, guess.y + (iy - n_xy) * res,
                    float(thetas[t]))
        pose = self._refine(pts, pose, max_step=2.0 * res)
        pose, ratio = self._hold_weak(pts, pose, guess)
        return Match(Pose(pose.x, pose.y, math.remainder(pose.theta, 2 * math.pi)), score, True,
                     n, evaluated, ratio)

    def _hold_weak(self, pts: np.ndarray, pose: Pose, guess: Pose) -> tuple[Pose, float]:
        """Step 5: where the scan's surfaces leave a direction nearly unconstrained (a
        corridor), what pulled the match along it was no surface but the map's edge, so
        odometry's guess stands there; across it and in heading the match is refined with that
        direction held. Returns the pose and the scan's conditioning."""
        ratio, weak = scan_conditioning(pts)
        if ratio >= self.p.degenerate_ratio:
            return pose, ratio
        cs, sn = math.cos(pose.theta), math.sin(pose.theta)
        ux, uy = cs * weak[0] - sn * weak[1], sn * weak[0] + cs * weak[1]  # map frame
        along = (pose.x - guess.x) * ux + (pose.y - guess.y) * uy
        held = Pose(pose.x - along * ux, pose.y - along * uy, pose.theta)
        return self._refine(pts, held, max_step=2.0 * self._geom.resolution,
                            frozen=(ux, uy)), ratio

    def _bounds(self, base: list[tuple[np.ndarray, np.ndarray]], off: np.ndarray
                ) -> np.ndarray:
        """Coarse bounds (angle, block row, block col): each block's score on the max-pooled
        field, at least every fine score of the block."""
        H, W = self._coarse.shape
        c = self.p.coarse
        bounds = np.empty((len(base), len(off), len(off)))
        for t, (r0, c0) in enumerate(base):
            rr = r0[None, :] + off[:, None]  # (blocks, n)
            cc = c0[None, :] + off[:, None]
            vr = (rr > -c) & (rr < H)  # a block whose corner lies just off the map still
            vc = (cc > -c) & (cc < W)  # reaches into it: its bound is the edge block's
            rr, cc = np.clip(rr, 0, H - 1), np.clip(cc, 0, W - 1)
            vals = self._coarse[rr[:, None, :], cc[None, :, :]]  # (by, bx, n)
            vals = np.where(vr[:, None, :] & vc[None, :, :], vals, 0.0)
            bounds[t] = vals.sum(axis=2)
        return bounds

    def _sample(self, wx: np.ndarray, wy: np.ndarray) -> tuple[np.ndarray, ...]:
        """Bilinear field values and their gradients [1/m] at world points (0 off the map)."""
        g = self._geom
        res = g.resolution
        fx = (wx - g.origin_x) / res - 0.5  # cell-centre coordinates
        fy = (wy - g.origin_y) / res - 0.5
        c0, r0 = np.floor(fx).astype(np.int64), np.floor(fy).astype(np.int64)
        ax, ay = fx - c0, fy - r0
        H, W = self._field.shape
        ok = (r0 >= 0) & (r0 < H - 1) & (c0 >= 0) & (c0 < W - 1)
        r0, c0 = np.where(ok, r0, 0), np.where(ok, c0, 0)
        f = self._field
        v00, v01 = f[r0, c0], f[r0, c0 + 1]
        v10, v11 = f[r0 + 1, c0], f[r0 + 1, c0 + 1]
        val = (1 - ay) * ((1 - ax) * v00 + ax * v01) + ay * ((1 - ax) * v10 + ax * v11)
        gx = ((1 - ay) * (v01 - v00) + ay * (v11 - v10)) / res
        gy = ((1 - ax) * (v10 - v00) + ax * (v11 - v01)) / res
        return np.where(ok, val, 0.0), np.where(ok, gx, 0.0), np.where(ok, gy, 0.0)

    def _refine(self, pts: np.ndarray, pose: Pose, max_step: float, iters: int = 10,
                frozen: tuple[float, float] | None = None) -> Pose:
        """Gauss-Newton on the bilinear field from the best pose of the search: the residual
        of each end point is 1 - its likelihood; steps stay within ``max_step`` [m] of where
        it started, and a step that scores worse ends it."""
        x, y, th = pose
        px, py = pts[:, 0], pts[:, 1]

        def score(x: float, y: float, th: float) -> tuple[float, tuple[np.ndarray, ...]]:
            cs, sn = math.cos(th), math.sin(th)
            wx, wy = x + cs * px - sn * py, y + sn * px + cs * py
            v, gx, gy = self._sample(wx, wy)
            return float(v.sum()), (v, gx, gy, -sn * px - cs * py, cs * px - sn * py)

        best, parts = score(x, y, th)
        for _ in range(iters):
            v, gx, gy, dxt, dyt = parts
            J = np.column_stack((gx, gy, gx * dxt + gy * dyt))
            r = 1.0 - v
            A = J.T @ J + 1e-6 * np.eye(3)
            step = np.linalg.solve(A, J.T @ r)
            if frozen is not None:  # no step along this direction
                a = step[0] * frozen[0] + step[1] * frozen[1]
                step[0] -= a * frozen[0]
                step[1] -= a * frozen[1]
            nx, ny, nth = x + step[0], y + step[1], th + step[2]
            if math.hypot(nx - pose.x, ny - pose.y) > max_step:
                break
            s, p2 = score(nx, ny, nth)
            if s <= best:
                break
            best, parts, x, y, th = s, p2, nx, ny, nth
            if abs(step[0]) + abs(step[1]) < 1e-4 and abs(step[2]) < 1e-5:
                break
        return Pose(x, y, th)


# this core runs no numba kernel (common.warm)
WARM_MODULES: tuple[str, ...] = ()
