"""Grid kernels of the planner: path search over known free cells and frontier groups (pure).

Used by the ``frontier`` strategy and the completion rules (``strategies/``). Yamauchi's
nearest-frontier exploration as explore_lite does it (DESIGN.md §4 "Baseline strategies"),
with the distance measured as a grid path length instead of a straight line:

- a *frontier cell* is a known free cell 4-adjacent to unknown space (cells outside the grid
  count as unknown: the mapper grows the grid when a beam leaves it);
- *unknown* = never observed (-1) plus the undecided cells (between p_free and p_occ) that are
  8-connected to never-observed space: the band of once-seen cells at the edge of the laser's
  reach is still unexplored, while undecided specks along walls (hit/miss noise, enclosed by
  known cells) are not frontiers;
- frontier cells are grouped 8-connected; groups with size_cells * resolution <
  min_frontier_size are dropped (explore_lite);
- traversable = known free cells whose distance to the nearest *occupied* cell is >= the robot
  radius + clearance margin (cv2.distanceTransform; unknown is not an obstacle, as in a ROS
  costmap, otherwise no frontier cell would ever be reachable);
- distance = Dijkstra path length over traversable cells, 8-neighbours (diagonal sqrt(2), no
  corner cutting), from the robot's cell or the nearest traversable cell to it; cells close to
  obstacles cost more (a costmap-like inflation, see grid_search), so this is a path *cost* in
  metres that equals the path length wherever the robot has room;
- goal of a group = its reachable cell nearest to the group centroid; cost (explore_lite's
  form, both terms in metres) = potential_scale * path_length_m - gain_scale * size_cells *
  resolution.
"""

from __future__ import annotations

import functools
import heapq
import math
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numba
import numpy as np

from topoexplore.common.grid import GridGeometry, distance_transform

SQRT2 = math.sqrt(2.0)
LOOK_RADIUS = 1.0  # [m] unknown cells this close to a frontier goal set the heading to face
ESCAPE_RADIUS = 1.0  # [m] how far the search looks for traversable cells the robot can get to
TIGHT_PENALTY = 1.0  # a cell below the clearance the search asks for costs up to this many
#   lengths more, the tighter it is (down to the body's fit): a path through a gap, or out of
#   a tight spot, keeps to the middle, where the controller's corridor fits


class GridSearchError(ValueError):
    """A search result is inconsistent (a parent map with a cycle)."""


@dataclass
class FrontierGroup:
    label: int
    size: int  # cells
    centroid: tuple[float, float]  # [m]
    cells_xy: np.ndarray  # (n, 2) world centres of the group's cells [m]
    goal_rc: tuple[int, int] | None  # reachable cell nearest the centroid (None: unreachable)
    goal_xy: tuple[float, float] | None  # [m]
    path_length: float  # [m] grid path length robot -> goal (inf if unreachable)
    cost: float  # potential_scale * path_length - gain_scale * size * resolution
    look_xy: tuple[float, float] | None = None  # [m] mean of the unknown cells within
    #   LOOK_RADIUS of the goal: where the robot should face on arrival (None: none there)


@dataclass
class Escape:
    """How the robot gets from where it stands to the traversable cells (the search's seeds):
    through cells where its body fits, at most ESCAPE_RADIUS away."""

    seeds: np.ndarray  # int64 flat indices of the passable cells reached
    cost: np.ndarray  # float64 [m] cost of the way robot cell -> each seed (its length
    #   times the search's per-cell multiplier; the plain length without one)
    parent: dict[int, int]  # flat index -> the previous cell on the way (-1: the robot's cell)
    robot: int  # flat index of the robot's cell (-1: outside the grid)

    @property
    def stuck(self) -> bool:
        """No traversable cell within reach: the robot cannot get anywhere from here."""
        return self.seeds.size == 0


@dataclass
class GridSearch:
    """Result of one Dijkstra over the traversable cells, seeded by the robot's escape."""

    geom: GridGeometry
    passable: np.ndarray  # bool (H, W)
    clear: np.ndarray | Callable[[], np.ndarray]  # :attr:`clearance`, or what makes it
    start: tuple[int, int] | None  # (row, col) the nearest seed (None: the robot is stuck)
    dist: np.ndarray  # float64 (H, W) path length [m] from the robot, inf where unreachable
    parent: np.ndarray  # int64 (H*W,) flat index of the predecessor, -1 at seeds/unreached
    escape: Escape | None = None

    @property
    def clearance(self) -> np.ndarray:
        """float32 (H, W) distance [m] to the nearest occupied cell that the search judged
        cells by; made when first asked for if the search itself did not need it (a
        reach-only search from a passable cell)."""
        if callable(self.clear):
            self.clear = self.clear()
        return self.clear

    def path_to(self, row: int, col: int) -> np.ndarray:
        """Cell-centre polyline [m] from the robot (its escape cells, then the seed) to
        (row, col) along the parents; (0, 2) if unreached."""
        w = self.geom.width
        k = row * w + col
        if not math.isfinite(self.dist[row, col]):
            return np.zeros((0, 2))
        idx = []
        while k >= 0:
            idx.append(k)
            k = int(self.parent[k])
            if len(idx) > self.parent.size:  # defensive against a corrupt parent map
                raise GridSearchError("grid parent map has a cycle")
        if self.escape is not None:  # back from the seed to the robot's cell (not included)
            k = self.escape.parent.get(idx[-1], -1)
            while k >= 0 and k != self.escape.robot:
                idx.append(k)
                k = self.escape.parent.get(k, -1)
        idx.reverse()
        idx_a = np.asarray(idx)
        x, y = self.geom.cell_to_world(idx_a // w, idx_a % w)
        return np.stack([x, y], axis=1)


def frontier_mask(free: np.ndarray, unknown: np.ndarray) -> np.ndarray:
    """Known free cells 4-adjacent to unknown; outside the grid counts as unknown."""
    u = np.pad(unknown, 1, constant_values=True)
    adj = u[:-2, 1:-1] | u[2:, 1:-1] | u[1:-1, :-2] | u[1:-1, 2:]
    return free & adj


def _cells_to_occupied(occupied: np.ndarray) -> np.ndarray:
    """float32 distance [cells] from each cell centre to the nearest occupied cell centre
    (exact L2; at least one cell must be occupied)."""
    return distance_transform(np.where(occupied, 0, 255).astype(np.uint8))


def clearance_map(occupied: np.ndarray, resolution: float) -> np.ndarray:
    """Distance [m] from each cell centre to the nearest occupied cell centre (exact L2)."""
    if not occupied.any():
        return np.full(occupied.shape, np.float32(1e6), dtype=np.float32)
    return _cells_to_occupied(occupied) * np.float32(resolution)


def capped_clearance_map(occupied: np.ndarray, resolution: float, cap_cells: int
                         ) -> np.ndarray:
    """:func:`clearance_map` capped at cap_cells cells, each value the square root of its
    integer squared distance in cells: a function of the occupied cells within cap_cells of a
    cell alone, so that a part of it computed on a window of the grid is the same bit for bit
    (OpenCV's transform differs in the last bit from one array to another: 0.6082763 on the
    whole map, 0.60827625 on a window of it, at sqrt(37) cells)."""
    cap2 = float(cap_cells * cap_cells)
    if not occupied.any():
        d2 = np.full(occupied.shape, cap2)
    else:
        d2 = np.minimum(np.rint(np.square(_cells_to_occupied(occupied), dtype=np.float64)),
                        cap2)
    return np.sqrt(d2).astype(np.float32) * np.float32(resolution)


class ClearanceKeeper:
    """The clearance of the map [m] (:func:`capped_clearance_map`, capped at cap [m]), kept
    from one update to the next: only the cells within cap of an occupied cell that changed
    are computed again (on the 60 x 60 m office a window of 7 % of the map on average, nothing
    on one update in ten). The result is what :func:`capped_clearance_map` gives on the whole
    grid, bit for bit. The grid's geometry changing (the mapper growing it) starts afresh.

    Every rule that reads the planner's clearance compares it with a clearance it needs (the
    robot's radius and margins, the soft penalty's reach), all below cap: there a capped value
    and the true one say the same."""

    def __init__(self, cap: float):
        self.cap = float(cap)  # [m]
        self._key: tuple | None = None  # the geometry of the map below
        self._occ: np.ndarray | None = None  # its occupied cells ...
        self._out: np.ndarray | None = None  # ... and their clearance [m]
        self.cells = 0  # cells computed (a full map or windows) ...
        self.kept = 0  # ... and cells kept from the update before: what the keeper saved

    def clearance(self, occupied: np.ndarray, geom: GridGeometry) -> np.ndarray:
        """Read-only float32 clearance [m] of the occupied cells (the grid's shape) on geom."""
        res = geom.resolution
        cap_cells = max(1, math.ceil(self.cap / res - 1e-9))
        key = (res, geom.origin_x, geom.origin_y, occupied.shape, cap_cells)
        if key != self._key or self._out is None:
            out = capped_clearance_map(occupied, res, cap_cells)
            self.cells += out.size
        else:
            out = self._update(occupied, res, cap_cells)
        out.flags.writeable = False
        self._key, self._occ, self._out = key, occupied, out
        return out

    def _update(self, occupied: np.ndarray, res: float, cap_cells: int) -> np.ndarray:
        """The kept clearance with the window round the changed cells made again."""
        old = self._out
        changed = occupied != self._occ
        rows = np.flatnonzero(changed.any(axis=1))
        if rows.size == 0:
            self.kept += old.size
            return old
        cols = np.flatnonzero(changed.any(axis=0))
        h, w = occupied.shape
        k = cap_cells + 1
        # the cells whose value may change (within cap of a changed cell) ...
        r0, r1 = max(0, int(rows[0]) - k), min(h, int(rows[-1]) + 1 + k)
        c0, c1 = max(0, int(cols[0]) - k), min(w, int(cols[-1]) + 1 + k)
        # ... computed on a window holding every occupied cell within cap of them
        s0, s1 = max(0, r0 - k), min(h, r1 + k)
        t0, t1 = max(0, c0 - k), min(w, c1 + k)
        part = capped_clearance_map(occupied[s0:s1, t0:t1], res, cap_cells)
        out = old.copy()  # the last update's view may still hold the old array
        out[r0:r1, c0:c1] = part[r0 - s0:r1 - s0, c0 - t0:c1 - t0]
        self.cells += part.size
        self.kept += out.size - (r1 - r0) * (c1 - c0)
        return out


def best_clearance_map(occupied: np.ndarray, resolution: float) -> np.ndarray:
    """Per cell, the largest clearance [m] of a point in it: the distance transform at half
    the resolution (each cell as 2 x 2 sub-cells; occupied sub-cells are those of occupied
    cells), the greatest of a cell's four. A gap of k free cells between occupied ones gets
    (k / 2 - 0.25) * resolution: it tells a gap of 4 free cells (0.225 m at 0.1 m) from one
    of 3 (0.175 m), which the centre-to-centre :func:`clearance_map` cannot (0.2 m both)."""
    if not occupied.any():
        return np.full(occupied.shape, np.float32(1e6), dtype=np.float32)
    h, w = occupied.shape
    src = np.where(occupied, np.uint8(0), np.uint8(255))
    fine = cv2.resize(src, (2 * w, 2 * h), interpolation=cv2.INTER_NEAREST)  # 2 x 2 each
    d = distance_transform(fine)
    rows = np.maximum(d[0::2], d[1::2])  # the four sub-cells' greatest, then to metres:
    return np.maximum(rows[:, 0::2], rows[:, 1::2]) * np.float32(0.5 * resolution)


def fit_mask(occupied: np.ndarray, resolution: float, fit: float) -> np.ndarray:
    """``best_clearance_map(occupied, resolution) + 1e-6 >= fit``, cell for cell, without the
    distance transform: a sub-cell passes unless an occupied sub-cell lies at an offset whose
    distance (as the transform gives it for one obstacle, in the same float32 arithmetic)
    fails the test, so the failing ones are the occupied sub-cells dilated by that digital
    disc; a cell passes if one of its four sub-cells does. The distance is monotone in the
    squared offset and the transform's value at a sub-cell is the least over the obstacles,
    so this is the same mask (a test compares the two on random grids), at a fifth of the
    transform's cost on a large map."""
    h, w = occupied.shape
    if not occupied.any():
        return np.full(occupied.shape, bool(np.float32(1e6) + 1e-6 >= fit))
    near = _too_close(float(resolution), float(fit))
    if not near.any():  # fit <= 0: every point passes, an obstacle's own too
        return np.ones(occupied.shape, dtype=bool)
    fine = cv2.resize(occupied.view(np.uint8), (2 * w, 2 * h), interpolation=cv2.INTER_NEAREST)
    ok = cv2.dilate(fine, near) == 0
    rows = ok[0::2] | ok[1::2]
    return rows[:, 0::2] | rows[:, 1::2]


@functools.lru_cache(maxsize=16)
def _too_close(resolution: float, fit: float) -> np.ndarray:
    """uint8 kernel of the half-resolution offsets from one occupied sub-cell whose best
    clearance (:func:`best_clearance_map`'s arithmetic) fails ``+ 1e-6 >= fit``."""
    k = int(math.ceil(max(fit, 0.0) / (0.5 * resolution))) + 2
    one = np.full((2 * k + 1, 2 * k + 1), 255, np.uint8)
    one[k, k] = 0
    d = distance_transform(one) * np.float32(0.5 * resolution)
    return (~(d + 1e-6 >= fit)).astype(np.uint8)


@numba.njit(cache=True, nogil=True)
def _dijkstra8(passable, mult, seeds, seed_cost, res):  # pragma: no cover - jitted
    """Exact 8-neighbour Dijkstra as Dial's bucket queue (bucket width = res), from several
    seed cells with their starting costs.

    A step between cells u and v costs its length (res or res*sqrt(2)) times
    (mult[u] + mult[v]) / 2 with mult >= 1, so every step costs >= the bucket width: cells in
    the same bucket cannot improve each other and each bucket is settled in FIFO order; a ring
    of ceil(max step / res) + 2 buckets (more when the seeds' costs spread wider) suffices.
    O(cells), no heap.
    """
    h, w = passable.shape
    n = h * w
    dist = np.full(n, np.inf)
    parent = np.full(n, -1, dtype=np.int64)
    settled = np.zeros(n, dtype=np.bool_)
    inv = 1.0 / res
    spread = int(seed_cost.max() * inv) + 1 if seed_cost.size else 0
    nslot = max(int(math.ceil(1.4142135623730951 * mult.max())), spread) + 2
    cap = max(1024, seeds.shape[0])
    slots = np.empty((nslot, cap), dtype=np.int64)
    count = np.zeros(nslot, dtype=np.int64)
    for j in range(seeds.shape[0]):
        v = seeds[j]
        if seed_cost[j] < dist[v]:
            dist[v] = seed_cost[j]
            t = int(seed_cost[j] * inv + 1e-9) % nslot
            slots[t, count[t]] = v
            count[t] += 1
    k = 0
    pending = seeds.shape[0]
    while pending > 0:
        s = k % nslot
        i = 0
        while i < count[s]:
            u = slots[s, i]
            i += 1
            pending -= 1
            if settled[u]:
                continue
            settled[u] = True
            d = dist[u]
            r = u // w
            c = u - r * w
            mu = mult[r, c]
            for dr, dc in ((-1, 0), (1, 0), (0, -1), (0, 1), (-1, -1), (-1, 1), (1, -1), (1, 1)):
                rr = r + dr
                cc = c + dc
                if rr < 0 or rr >= h or cc < 0 or cc >= w or not passable[rr, cc]:
                    continue
                if dr != 0 and dc != 0:  # diagonal: no corner cutting
                    if not passable[r, cc] or not passable[rr, c]:
                        continue
                    step = res * 1.4142135623730951
                else:
                    step = res
                nd = d + step * 0.5 * (mu + mult[rr, cc])
                v = rr * w + cc
                if settled[v] or nd >= dist[v]:
                    continue
                dist[v] = nd
                parent[v] = u
                b = int(nd * inv + 1e-9)
                if b < k:
                    b = k
                t = b % nslot
                if count[t] >= cap:  # grow the ring's slots
                    bigger = np.empty((nslot, 2 * cap), dtype=np.int64)
                    bigger[:, :cap] = slots
                    slots = bigger
                    cap = 2 * cap
                slots[t, count[t]] = v
                count[t] += 1
                pending += 1
        count[s] = 0
        k += 1
    return dist, parent


def _cells_near(mask: np.ndarray, row: int, col: int, rad: int
                ) -> tuple[np.ndarray, np.ndarray]:
    """(rows, cols) of the True cells of `mask` within the square of rad cells around (row,
    col), nearest first (ties in row-major order)."""
    h, w = mask.shape
    r0, r1 = max(0, row - rad), min(h, row + rad + 1)
    c0, c1 = max(0, col - rad), min(w, col + rad + 1)
    if r0 >= r1 or c0 >= c1:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    rr, cc = np.nonzero(mask[r0:r1, c0:c1])
    rr, cc = rr + r0, cc + c0
    order = np.argsort((rr - row) ** 2 + (cc - col) ** 2, kind="stable")
    return rr[order], cc[order]


def grid_search(free: np.ndarray, passable: np.ndarray,
                clearance: np.ndarray | Callable[[], np.ndarray], geom: GridGeometry,
                x: float, y: float, robot_radius: float,
                fit: float | None = None, soft_radius: float = 0.0, soft_penalty: float = 0.0,
                narrow_penalty: float = 0.0, reach_only: bool = False) -> GridSearch:
    """Dijkstra path costs [m] from the robot at (x, y) [m] over the `passable` cells.

    passable: known free cells with clearance >= robot_radius [m] (``MapView.passable``);
    clearance: distance [m] to the nearest occupied cell (or a callable that makes it, called
    only if the search needs it); free: known free cells. A cell with
    clearance below soft_radius [m] costs up to (1 + soft_penalty) times its length (linearly
    more the closer it is to the robot_radius limit), so paths keep away from walls where
    there is room; with soft_penalty = 0 the cost is the plain path length. `passable` may
    hold cells with less clearance than robot_radius (down to the robot's body, `fit`: a
    narrow passage it can still drive through, as a costmap's lethal limit is the inscribed
    radius); those cost (1 + soft_penalty + narrow_penalty) times their length, and up to
    TIGHT_PENALTY more the tighter they are (:func:`cost_multiplier`), so the search takes them
    only where there is no wide way worth the detour, and then along the middle.

    The search starts from where the robot really is (:func:`escape`): its own cell if that
    is passable, else every passable cell it can get to within ESCAPE_RADIUS through free
    cells with at least `fit` [m] of clearance (where its body fits; default robot_radius),
    each with the length of that way as its starting cost. A robot in a corner or a doorway
    (inside the clearance margin) thus searches from the traversable space it can really
    drive to, never from a nearest cell behind a wall; with none in reach it is stuck
    (``escape.stuck``, start None).

    reach_only: no path costs, only which cells the search reaches (dist 0 there, inf
    elsewhere), from connected components: the same set as the Dijkstra's, since a diagonal
    step needs both cells beside it passable (so 4-connectivity decides), at a fraction of
    the cost.
    """
    h, w = passable.shape
    row, col = (int(v) for v in geom.world_to_cell(x, y))
    fit = robot_radius if fit is None else fit
    on_passable = 0 <= row < h and 0 <= col < w and bool(passable[row, col])
    mult = None  # a reach-only search from a passable cell prices no step (nor does escape)
    if not (reach_only and on_passable):  # ... and needs no clearance: a callable waits
        clearance = clearance() if callable(clearance) else clearance
        mult = cost_multiplier(clearance, robot_radius, fit, soft_radius, soft_penalty,
                               narrow_penalty)
    esc = escape(free, passable, clearance, row, col, fit, geom.resolution, mult=mult)
    dist = np.full((h, w), np.inf)
    start = None
    if not esc.stuck:
        s = int(esc.seeds[int(np.argmin(esc.cost))])
        start = (s // w, s % w)
    if start is not None and not reach_only:
        d, parent = _dijkstra8(passable, mult, esc.seeds, esc.cost, float(geom.resolution))
        dist = d.reshape(h, w)
    else:  # no parents: a read-only view of -1, no memory per cell
        parent = np.broadcast_to(np.int64(-1), (h * w,))
        if start is not None:
            dist[_reached(passable, esc.seeds)] = 0.0
    return GridSearch(geom, passable, clearance, start, dist, parent, esc)


def cost_multiplier(clearance: np.ndarray, robot_radius: float, fit: float,
                    soft_radius: float = 0.0, soft_penalty: float = 0.0,
                    narrow_penalty: float = 0.0) -> np.ndarray:
    """Per-cell factor (>= 1) on the length of a step, from its clearance [m].

    - clearance from soft_radius down to robot_radius (the clearance the search asks for):
      1 rising linearly to 1 + soft_penalty;
    - below robot_radius (a narrow passage the body fits, or the way out of a tight spot):
      1 + soft_penalty + narrow_penalty, plus up to TIGHT_PENALTY the nearer the clearance is
      to fit [m] (the body's own). Without that last term every cell under the margin cost the
      same, and the way out of a doorway the robot stood in ran along the door's jamb, at fit,
      instead of its middle: the controller then stopped for the jamb, its learned blockage
      closed the door, and the planner said "done" with the house half seen (held-back
      house-s5-18x14-n2, coverage 0.92).
    """
    mult = np.ones(clearance.shape, dtype=np.float64)
    if soft_penalty > 0 and soft_radius > robot_radius:
        frac = (soft_radius - clearance) / (soft_radius - robot_radius)
        mult += soft_penalty * np.clip(frac, 0.0, 1.0)
    span = robot_radius - fit  # [m] the narrow band: from the body's fit up to the margin
    depth = np.clip((robot_radius - clearance) / span, 0.0, 1.0) if span > 0 else 1.0
    tight = clearance + 1e-6 < robot_radius
    return np.where(tight, mult + narrow_penalty + TIGHT_PENALTY * depth, mult)


_STEPS = ((-1, 0), (1, 0), (0, -1), (0, 1), (-1, -1), (-1, 1), (1, -1), (1, 1))


def escape(free: np.ndarray, passable: np.ndarray, clearance: np.ndarray, row: int, col: int,
           fit: float, res: float, radius: float | None = None,
           mult: np.ndarray | None = None) -> Escape:
    """The passable cells the robot at cell (row, col) can get to within `radius` [m]
    (ESCAPE_RADIUS) of way, with the cost of the way (8-neighbour steps, no corner cutting;
    each step's length times the mean `mult` of its two cells, as the search that goes on
    from the seeds prices it (:func:`cost_multiplier`); the plain length without `mult`).

    Its own cell counts whatever it is (it stands there); a passable own cell is the only
    seed, at cost 0. Otherwise the way goes through free cells with clearance >= fit [m]
    (where its body fits); if there is none, through any free cell (the map may be tighter
    than the world: the robot got there); if there is none either (the robot stands on
    cells still unknown), the nearest passable cell in the radius with no occupied cell on
    the straight line to it. Stuck (no seed) only when none of the three finds one."""
    h, w = passable.shape
    inside = 0 <= row < h and 0 <= col < w
    robot = row * w + col if inside else -1
    if inside and passable[row, col]:
        return Escape(np.array([robot], np.int64), np.zeros(1), {}, robot)
    n = max(1, int(math.ceil((ESCAPE_RADIUS if radius is None else radius) / res)))
    for ok in (free & (clearance + 1e-6 >= fit), free):
        seeds, cost, parent = _escape_search(ok, passable, row, col, n * res, res, mult)
        if seeds:
            return Escape(np.array(seeds, np.int64), np.array(cost), parent, robot)
    near = _nearest_in_sight(passable, clearance > 0, row, col, n)
    if near is None:
        return Escape(np.zeros(0, np.int64), np.zeros(0), {}, robot)
    d = math.hypot(near[0] - row, near[1] - col) * res
    return Escape(np.array([near[0] * w + near[1]], np.int64), np.array([d]), {}, robot)


def _nearest_in_sight(mask: np.ndarray, clear: np.ndarray, row: int, col: int, rad: int
                      ) -> tuple[int, int] | None:
    """The True cell of `mask` nearest to (row, col) within rad cells whose straight line
    from (row, col) stays on `clear` cells (no wall in between); None if there is none."""
    h, w = mask.shape
    rr, cc = _cells_near(mask, row, col, rad)
    for k in range(rr.size):
        n = int(max(abs(rr[k] - row), abs(cc[k] - col))) * 2 + 1
        lr = np.rint(np.linspace(row, rr[k], n)).astype(int)
        lc = np.rint(np.linspace(col, cc[k], n)).astype(int)
        inside = (lr >= 0) & (lr < h) & (lc >= 0) & (lc < w)
        if np.all(clear[lr[inside], lc[inside]]):
            return int(rr[k]), int(cc[k])
    return None


def _escape_search(ok: np.ndarray, passable: np.ndarray, row: int, col: int, limit: float,
                   res: float, mult: np.ndarray | None = None
                   ) -> tuple[list[int], list[float], dict[int, int]]:
    """Dijkstra from (row, col) through `ok` cells, by cost (length times the mean `mult` of a
    step's cells; length alone without it), over ways up to `limit` [m] long; stops at
    passable cells (the seeds, with their costs); parent maps each visited flat index to the
    previous one (-1: the start)."""
    h, w = passable.shape
    cost: dict[tuple[int, int], float] = {(row, col): 0.0}
    parent: dict[int, int] = {}
    heap = [(0.0, 0.0, row, col)]  # (cost, length [m], row, col)
    seeds: list[int] = []
    costs: list[float] = []
    while heap:
        d, ln, r, c = heapq.heappop(heap)
        if d > cost.get((r, c), math.inf) or ln > limit + 1e-9:
            continue
        if (r, c) != (row, col) and passable[r, c]:
            seeds.append(r * w + c)
            costs.append(d)
            continue  # the Dijkstra over the passable cells goes on from here
        for dr, dc in _STEPS:
            rr, cc = r + dr, c + dc
            if not (0 <= rr < h and 0 <= cc < w and ok[rr, cc]):
                continue
            if dr and dc and not (_fits(ok, r, cc) and _fits(ok, rr, c)):
                continue
            step = res * SQRT2 if dr and dc else res
            f = 1.0 if mult is None else 0.5 * (float(mult[r, c]) + float(mult[rr, cc]))
            nd = d + step * f
            if nd < cost.get((rr, cc), math.inf):
                cost[(rr, cc)] = nd
                parent[rr * w + cc] = r * w + c if (r, c) != (row, col) else -1
                heapq.heappush(heap, (nd, ln + step, rr, cc))
    return seeds, costs, parent


def _fits(ok: np.ndarray, r: int, c: int) -> bool:
    return 0 <= r < ok.shape[0] and 0 <= c < ok.shape[1] and bool(ok[r, c])


def _reached(passable: np.ndarray, seeds: np.ndarray) -> np.ndarray:
    """The cells a search from the seeds reaches (4-connected components of passable)."""
    n, labels = cv2.connectedComponents(passable.view(np.uint8), connectivity=4)
    keep = np.zeros(n, dtype=bool)  # per label: does a seed lie in it (0: not passable)
    keep[labels.ravel()[seeds]] = True
    keep[0] = False
    ks = np.flatnonzero(keep)
    if len(ks) > 4:
        return keep[labels]
    out = np.zeros(labels.shape, dtype=bool)  # the seeds' few labels: a comparison each is
    for k in ks:  # cheaper than a lookup per cell
        out |= labels == k
    return out


def look_point(unknown: np.ndarray, geom: GridGeometry, rc: tuple[int, int],
               radius: float) -> tuple[float, float] | None:
    """Mean world position [m] of the `unknown` cells within `radius` [m] of cell rc (cells
    outside the grid count as unknown, as in frontier_mask); None if there are none."""
    dr, dc = _disk(max(1, int(math.ceil(radius / geom.resolution))))
    rr, cc = rc[0] + dr, rc[1] + dc
    h, w = unknown.shape
    inside = (rr >= 0) & (rr < h) & (cc >= 0) & (cc < w)
    unk = np.ones(rr.shape, dtype=bool)
    unk[inside] = unknown[rr[inside], cc[inside]]
    if not unk.any():
        return None
    x, y = geom.cell_to_world(rr[unk].astype(np.float64), cc[unk].astype(np.float64))
    return float(np.mean(x)), float(np.mean(y))


@functools.lru_cache(maxsize=8)
def _disk(n: int) -> tuple[np.ndarray, np.ndarray]:
    """(row, col) offsets of the cells within n cells of a centre, in row-major order."""
    dr, dc = np.mgrid[-n:n + 1, -n:n + 1]
    disk = dr ** 2 + dc ** 2 <= n * n
    dr, dc = dr[disk], dc[disk]
    dr.setflags(write=False)  # shared by every call
    dc.setflags(write=False)
    return dr, dc


def find_frontiers(free: np.ndarray, unknown: np.ndarray, geom: GridGeometry,
                   search: GridSearch, min_frontier_size: float, potential_scale: float,
                   gain_scale: float, look: bool = True,
                   stop: Callable[[FrontierGroup], bool] | None = None
                   ) -> tuple[list[FrontierGroup], int]:
    """Frontier groups (size >= min_frontier_size [m]) with goal, path length and cost.

    free: known free cells; unknown: the cells that count as unexplored
    (``MapView.unknown`` / ``MapView.open_unknown``). Returns (groups, number of groups
    dropped as too small). Unreachable groups are returned with goal None and cost inf.
    look False: no look points (look_xy None); stop: the groups end with the first one it
    says yes to (the count of dropped groups then only counts those before it).
    """
    fmask = frontier_mask(free, unknown)
    if not fmask.any():
        return [], 0
    n, labels, stats, cents = cv2.connectedComponentsWithStats(
        fmask.astype(np.uint8), connectivity=8)
    res = geom.resolution
    rows, cols = np.nonzero(fmask)
    lab = labels[rows, cols]
    order = np.argsort(lab, kind="stable")
    rows, cols, lab = rows[order], cols[order], lab[order]
    bounds = np.searchsorted(lab, np.arange(1, n + 1))
    groups: list[FrontierGroup] = []
    dropped = 0
    for k in range(1, n):
        size = int(stats[k, cv2.CC_STAT_AREA])
        if size * res < min_frontier_size - 1e-9:
            dropped += 1
            continue
        cx, cy = geom.cell_to_world(cents[k, 1], cents[k, 0])  # centroid is (x=col, y=row)
        groups.append(_group(k, size, (float(cx), float(cy)), rows[bounds[k - 1]:bounds[k]],
                             cols[bounds[k - 1]:bounds[k]], unknown, geom, search,
                             potential_scale, gain_scale, look))
        if stop is not None and stop(groups[-1]):
            break
    return groups, dropped


def _group(k: int, size: int, centroid: tuple[float, float], r: np.ndarray, c: np.ndarray,
           unknown: np.ndarray, geom: GridGeometry, search: GridSearch,
           potential_scale: float, gain_scale: float, look: bool = True) -> FrontierGroup:
    """Frontier group k of cells (r, c): its goal (the reachable cell nearest the centroid),
    path length and explore_lite cost; with look, its look point."""
    cx, cy = centroid
    wx, wy = geom.cell_to_world(r, c)
    d = search.dist[r, c]
    reach = np.isfinite(d)
    if reach.any():
        d2 = np.where(reach, (wx - cx) ** 2 + (wy - cy) ** 2, np.inf)
        j = int(np.argmin(d2))
        goal_rc = (int(r[j]), int(c[j]))
        goal_xy = (float(wx[j]), float(wy[j]))
        plen = float(d[j])
        cost = potential_scale * plen - gain_scale * size * geom.resolution
        look = look_point(unknown, geom, goal_rc, LOOK_RADIUS) if look else None
    else:
        goal_rc, goal_xy, plen, cost, look = None, None, math.inf, math.inf, None
    return FrontierGroup(k, size, centroid, np.stack([wx, wy], axis=1), goal_rc, goal_xy,
                         plen, cost, look)


# Entry kernels and the argument types the planner calls them with (common.warm).
WARM = {
    "_dijkstra8": ("(boolean[:, ::1], float64[:, ::1], int64[::1], float64[::1], float64)",),
}
