"""Line-of-sight rays on a raster (numba): the ray table and the casts that the truth masks
(:func:`topoexplore.sim.world.truth_mappable`) and the oracle (``sim/oracle.py``) use.

A module of its own so that the simulator process, which never casts these rays, does not
import numba (about 60 MB resident): ``sim.world`` imports it when a truth mask is made.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from topoexplore.common.kernels import bresenham

__all__ = ["square_border", "ray_table", "blocked", "sees_goal", "rays_through", "rays_to"]


def square_border(n: int) -> np.ndarray:
    """int64 (8n, 2) offsets (dr, dc) of the cells on the border of the square of half side n."""
    t = np.arange(-n, n)
    sides = [np.stack([np.full_like(t, -n), t], 1), np.stack([t, np.full_like(t, n)], 1),
             np.stack([np.full_like(t, n), -t], 1), np.stack([-t, np.full_like(t, -n)], 1)]
    return np.concatenate(sides).astype(np.int64)


@njit(cache=True, nogil=True)
def ray_table(border):  # pragma: no cover - compiled
    """int64 (k, n + 1, 2): the Bresenham line from (0, 0) to each of the k ``border`` offsets
    (Chebyshev length n). Bresenham lines are translation invariant, so a ray from any cell is
    this table shifted by the cell."""
    k = border.shape[0]
    n = abs(border[0, 0])
    out = np.empty((k, n + 1, 2), dtype=np.int64)
    rows = np.empty(n + 1, dtype=np.int64)
    cols = np.empty(n + 1, dtype=np.int64)
    for j in range(k):
        bresenham(0, 0, border[j, 0], border[j, 1], rows, cols)
        out[j, :, 0] = rows
        out[j, :, 1] = cols
    return out


@njit(cache=True, nogil=True)
def blocked(solid, r, c, dr, dc, r2):  # pragma: no cover - compiled
    """Whether the cell (r + dr, c + dc) stops a ray from (r, c): out of range, outside the
    raster or solid."""
    h, w = solid.shape
    rr = r + dr
    cc = c + dc
    return (dr * dr + dc * dc > r2 or rr < 0 or rr >= h or cc < 0 or cc >= w
            or solid[rr, cc])


@njit(cache=True, nogil=True)
def sees_goal(solid, src, goal, rays, r2):  # pragma: no cover - compiled
    """bool mask of the ``src`` cells from which a ray (:func:`ray_table`) meets a ``goal``
    cell through free cells within squared distance ``r2`` [cells^2]."""
    h, w = solid.shape
    out = np.zeros((h, w), dtype=np.bool_)
    for r in range(h):
        for c in range(w):
            if not src[r, c]:
                continue
            for k in range(rays.shape[0]):
                for i in range(1, rays.shape[1]):
                    dr = rays[k, i, 0]
                    dc = rays[k, i, 1]
                    if blocked(solid, r, c, dr, dc, r2):
                        break
                    if goal[r + dr, c + dc]:
                        out[r, c] = True
                        break
                if out[r, c]:
                    break
    return out


@njit(cache=True, nogil=True)
def rays_through(rays):  # pragma: no cover - compiled
    """The rays (:func:`ray_table`, half side n) through each offset (dr, dc) of the square:
    ``ids[start[q]:start[q + 1]]`` for q = (dr + n) * (2n + 1) + dc + n. A ray reaches its
    offset at step max(|dr|, |dc|)."""
    k, m = rays.shape[0], rays.shape[1]
    n = m - 1
    side = 2 * n + 1
    start = np.zeros(side * side + 1, dtype=np.int64)
    for j in range(k):
        for i in range(1, m):
            start[(rays[j, i, 0] + n) * side + rays[j, i, 1] + n + 1] += 1
    start = np.cumsum(start)
    ids = np.empty(start[-1], dtype=np.int64)
    fill = start[:-1].copy()
    for j in range(k):
        for i in range(1, m):
            q = (rays[j, i, 0] + n) * side + rays[j, i, 1] + n
            ids[fill[q]] = j
            fill[q] += 1
    return start, ids


@njit(cache=True, nogil=True)
def rays_to(solid, viewpoints, tr, tc, rays, start, ids, r2):  # pragma: no cover - compiled
    """Cells passed by the rays (:func:`ray_table`) from the ``viewpoints`` cells that can
    reach one of the target cells (tr, tc) (only those rays, only as far as the farthest
    target on them): the same targets as casting every ray, for a fraction of the work."""
    h, w = solid.shape
    k, m = rays.shape[0], rays.shape[1]
    n = m - 1
    side = 2 * n + 1
    need = np.zeros(k, dtype=np.int64)  # per ray: the step of its farthest target
    out = np.zeros((h, w), dtype=np.bool_)
    for r in range(h):
        for c in range(w):
            if not viewpoints[r, c]:
                continue
            for t in range(tr.size):
                dr = tr[t] - r
                dc = tc[t] - c
                if abs(dr) > n or abs(dc) > n or dr * dr + dc * dc > r2:
                    continue
                q = (dr + n) * side + dc + n
                for j in range(start[q], start[q + 1]):
                    need[ids[j]] = max(need[ids[j]], max(abs(dr), abs(dc)))
            for j in range(k):
                for i in range(1, need[j] + 1):
                    if blocked(solid, r, c, rays[j, i, 0], rays[j, i, 1], r2):
                        break
                    out[r + rays[j, i, 0], c + rays[j, i, 1]] = True
                need[j] = 0
    return out


# Entry kernels and the argument types the truth masks and the oracle call them with
# (common.warm).
WARM = {
    "ray_table": ("(int64[:, ::1],)",),
    "sees_goal": (
        "(boolean[:, ::1], boolean[:, ::1], boolean[:, ::1], int64[:, :, ::1], float64)",),
    "rays_through": ("(int64[:, :, ::1],)",),
    "rays_to": (
        "(boolean[:, ::1], boolean[:, ::1], int64[:], int64[:], int64[:, :, ::1], int64[::1],"
        " int64[::1], float64)",),
}
