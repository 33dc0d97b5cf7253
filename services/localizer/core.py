"""Localizer core: where is the robot on the map, given a scan and odometry's guess (pure).

A correlative scan matcher (Olson, "Real-time correlative scan matching", ICRA 2009): the
map's occupied cells become a likelihood field, ``exp(-d^2 / (2 sigma^2))`` of the distance
d [m] to the nearest one; a pose scores the mean likelihood at the scan's end points. The
search covers ``search_xy`` [m] and ``search_theta`` [rad] round the guess:

0. the sides of the faces (``directional``): a beam ends on a surface that faces it. Each
   wall cell keeps the sides it has been seen from (east, north, west, south: the axes of the
   surface normals the scans found there, from each end point's neighbours, turned towards
   the laser), and an end point scores only on cells seen from a side its beam can reach: a
   beam travelling north-east meets faces whose normal points west or south. Cells with no
   record (the map's before this localizer saw them) count from every side. A thin wall
   (0.1 m: its two faces in neighbouring cells) mapped from one side pulled every scan from
   the other side onto the far face, a whole cell off, and the map took that error in:
   office with perfect odometry, pose RMS 0.11 m in whole cells, 0.044 m with the rule
   (docs/benchmarks.md). The core keeps the record itself (:meth:`observe`, each scan at the
   pose it is mapped at) as a bit mask per cell beside the map, so the field is one per
   quadrant of the beam's heading;
0b. the observed part of the map (``known_only``): the end points that fall, at the guess,
   on a cell the map has never observed are left out. Such a point scores nothing where it
   is, and a pose turned a little so that it lands on a known wall gains from it: with 8 m
   of range a few milliradians move far points by a cell, and in new territory every scan
   has such points on the same side, so every scan pulled the heading the same way and the
   map kept it (large-office: 0.06 rad in 13 m while odometry's own heading moved by 0.007;
   docs/benchmarks.md). It is the turning twin of the corridor pull of step 5. What it
   costs: a guess a cell off towards a wall whose far side the map never saw puts that
   wall's end points behind it, and they are left out (counting the never-seen cells
   beside a wall as known, or a cell round every observed one, measured worse);
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
   generated warehouses lost metres this way; docs/benchmarks.md);
6. heading from the run's own surface directions (``heading_gain``; the angle histogram of
   Weiss, Wetzler & von Puttkamer, "Keeping track of position and orientation of moving
   indoor systems by correlation of range-finder scans", IROS 1994): the directions of the
   straight stretches of every scan, at the heading it is mapped at, add up to a histogram
   (mod 180°) whose peaks are the building's wall directions. Each match's heading moves by
   ``heading_gain`` of the offset that best lines the scan's directions up with it, within
   ``heading_window``, turning about the centroid of the points it matched. Steps 1-5
   match against the map, which the scans of the last few metres drew: along a wall in new
   territory it turns with them, and the heading walked off with odometry's (a generated
   warehouse, 0.1 rad in 15 m). The histogram holds every scan since the start.

Poses are the robot centre's (map frame); the laser sits ``laser_offset`` [m] ahead.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from topoexplore.common.checkpoint import CheckpointError, checked
from topoexplore.common.domain import GridMap, Pose, Scan
from topoexplore.common.grid import (
    GridGeometry,
    Occupancy,
    distance_transform,
    free_mask,
    reframe,
)
from topoexplore.common.params import LocalizerParams

# the sides a wall cell has been seen from, by the normal of the face seen (bits)
EAST, NORTH, WEST, SOUTH = 1, 2, 4, 8
# the sides a beam can meet, by the quadrant of its heading (map frame): quadrant q holds
# headings in [q x 90°, (q + 1) x 90°); heading north-east (q = 0) it meets faces seen from
# the west or the south
REACHES = (WEST | SOUTH, EAST | SOUTH, EAST | NORTH, WEST | NORTH)


def beam_bins(directions: np.ndarray) -> np.ndarray:
    """The quadrant (0..3) of beams travelling at ``directions`` [rad] (map frame)."""
    return np.floor(np.asarray(directions) / (math.pi / 2)).astype(np.int64) % 4


DIAGONAL = math.sin(math.radians(22.5))  # a normal within 67.5° of an axis counts for it


def surface_sides(x: np.ndarray, y: np.ndarray, dx: np.ndarray, dy: np.ndarray,
                  gap: float = 0.25) -> np.ndarray:
    """The sides (bits of EAST ... SOUTH) of the surfaces a scan's end points (x, y) [m] lie
    on, seen by beams heading (dx, dy), in scan order: the normal across the line through
    each point's two neighbours (both within ``gap`` [m]), turned towards the laser; a side
    for each axis it is within 67.5° of (a diagonal wall has two). 0: no neighbours, no
    normal."""
    out = np.zeros(len(x), np.uint8)
    if len(x) < 3:
        return out
    tx, ty = x[2:] - x[:-2], y[2:] - y[:-2]
    near = ((np.hypot(x[1:-1] - x[:-2], y[1:-1] - y[:-2]) < gap)
            & (np.hypot(x[2:] - x[1:-1], y[2:] - y[1:-1]) < gap))
    ln = np.hypot(tx, ty)
    near &= ln > 1e-9
    nx, ny = -ty / np.where(near, ln, 1.0), tx / np.where(near, ln, 1.0)
    flip = nx * dx[1:-1] + ny * dy[1:-1] > 0  # the normal faces the laser
    nx, ny = np.where(flip, -nx, nx), np.where(flip, -ny, ny)
    bits = (np.where(nx > DIAGONAL, EAST, 0) | np.where(nx < -DIAGONAL, WEST, 0)
            | np.where(ny > DIAGONAL, NORTH, 0) | np.where(ny < -DIAGONAL, SOUTH, 0))
    out[1:-1] = np.where(near, bits, 0)
    return out


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


MAX_CELLS = 100_000_000  # a checkpoint's grid of sides may not be larger (a 500 m square at 5 cm)
HEADING_BINS = 720  # the direction histogram (step 6): 180° in bins of 0.25°
HEADING_SPREAD = 0.004  # [rad] a direction's spread in it: about a 7-point fit's noise
HEADING_MIN_SCAN = 20  # directions a scan needs for step 6
HEADING_MIN_REF = 200  # directions the histogram needs before step 6 acts


def surface_directions(pts: np.ndarray, half: int = 3, gap: float = 0.25,
                       straight: float = 0.01, spread: float = 0.05) -> np.ndarray:
    """Directions [rad] in [0, π) of the straight stretches of a scan (step 6): round each
    end point (x, y) [m] whose ``half`` neighbours each side, in scan order, follow one
    another within ``gap`` [m], the principal axis of those 2 half + 1 points, kept when they
    lie within ``straight`` [m] (rms) of it and spread ``spread`` [m] (rms) along it."""
    k = 2 * half + 1
    if len(pts) < k:
        return np.zeros(0)
    X = sliding_window_view(np.asarray(pts[:, 0], np.float64), k)
    Y = sliding_window_view(np.asarray(pts[:, 1], np.float64), k)
    ok = np.all(np.hypot(np.diff(X, axis=1), np.diff(Y, axis=1)) < gap, axis=1)
    X, Y = X - X.mean(axis=1, keepdims=True), Y - Y.mean(axis=1, keepdims=True)
    sxx, syy, sxy = (X * X).mean(axis=1), (Y * Y).mean(axis=1), (X * Y).mean(axis=1)
    tr, det = sxx + syy, sxx * syy - sxy * sxy
    across = tr / 2 - np.sqrt(np.maximum(tr * tr / 4 - det, 0.0))  # the smaller variance
    ok &= (across < straight ** 2) & (tr - across > spread ** 2)
    return (0.5 * np.arctan2(2 * sxy[ok], (sxx - syy)[ok])) % math.pi


def direction_histogram(phi: np.ndarray) -> np.ndarray:
    """Counts of directions ``phi`` [rad] (mod π) in HEADING_BINS bins."""
    b = np.floor((np.asarray(phi) % math.pi) / (math.pi / HEADING_BINS)).astype(np.int64)
    return np.bincount(b % HEADING_BINS, minlength=HEADING_BINS).astype(np.float64)


@functools.lru_cache(maxsize=1)
def _spread_kernel() -> np.ndarray:
    bw = math.pi / HEADING_BINS
    half = int(math.ceil(3 * HEADING_SPREAD / bw))
    return np.exp(-0.5 * (np.arange(-half, half + 1) * bw / HEADING_SPREAD) ** 2)


def heading_offset(scan_hist: np.ndarray, ref: np.ndarray, window: float) -> float | None:
    """The turn [rad] that lines a scan's direction histogram up best with the reference
    (step 6): the peak of their correlation within ``window`` each way, interpolated between
    bins. None when nothing correlates, or the peak lies at the window's edge (the best turn
    may lie beyond it)."""
    ker = _spread_kernel()
    h = len(ker) // 2
    s = np.convolve(np.concatenate((scan_hist[-h:], scan_hist, scan_hist[:h])), ker, "valid")
    bw = math.pi / HEADING_BINS
    ks = np.arange(-int(math.ceil(window / bw)), int(math.ceil(window / bw)) + 1)
    c = np.array([s @ np.roll(ref, -k) for k in ks])
    j = int(np.argmax(c))
    if c[j] <= 0.0 or j == 0 or j == len(c) - 1:
        return None
    a, b, d = c[j - 1], c[j], c[j + 1]
    curv = a - 2 * b + d
    frac = 0.5 * (a - d) / curv if curv < 0 else 0.0
    return float((ks[j] + frac) * bw)


FIELD_FLOOR = 1e-6  # a likelihood below this is 0: the field reaches no farther from a face
MAX_RINGS = 250  # a spread over more distances on the grid than this: a distance transform


@functools.lru_cache(maxsize=8)
def _rings(resolution: float, sigma: float) -> tuple[tuple[np.ndarray, float], ...]:
    """The likelihood field's rings round a face cell, nearest first: for each distance on the
    grid (the root of a sum of two squares [cells]) whose likelihood stays above FIELD_FLOOR,
    the disc kernel reaching that far and the likelihood there; none when there are more than
    MAX_RINGS."""
    reach = 0.5 * resolution + sigma * math.sqrt(-2.0 * math.log(FIELD_FLOOR))  # [m]
    n = int(reach / resolution) + 1
    i, j = np.mgrid[-n:n + 1, -n:n + 1]
    s2 = i * i + j * j
    sq = np.unique(s2)
    w = np.exp(-0.5 * (np.maximum(np.sqrt(sq) * resolution - 0.5 * resolution, 0.0) / sigma) ** 2)
    keep = w >= FIELD_FLOOR
    if keep.sum() > MAX_RINGS:
        return ()
    return tuple(((s2 <= q).astype(np.uint8), float(v))
                 for q, v in zip(sq[keep], w[keep], strict=True))


def likelihood_field(face: np.ndarray, resolution: float, sigma: float) -> np.ndarray:
    """float32 exp(-d^2 / 2 sigma^2) of d [m], the distance to the nearest ``face`` cell's
    edge (half a cell from its centre, where a hit lies in the cell it marks); 0 where it is
    below FIELD_FLOOR: ``lut[level]`` of :func:`likelihood_levels`, or for a spread over more
    than MAX_RINGS distances, from a Euclidean distance transform."""
    if not _rings(float(resolution), float(sigma)):
        d = distance_transform((~face).astype(np.uint8)) * resolution
        d = np.maximum(d - 0.5 * resolution, 0.0)
        f = np.exp(-0.5 * (d / sigma) ** 2).astype(np.float32)
        return np.where(f >= FIELD_FLOOR, f, 0.0).astype(np.float32)
    level, lut = likelihood_levels(face, resolution, sigma)
    return lut[level]


def likelihood_levels(face: np.ndarray, resolution: float, sigma: float
                      ) -> tuple[np.ndarray, np.ndarray]:
    """The likelihood field as uint8 levels and the float32 table of their values: one binary
    dilation per ring round the faces (a distance transform's values at about a quarter of
    its cost on a 1000² map, a quarter of the memory). Levels rise with the likelihood, so a
    max over levels is a max over likelihoods (the coarse fields are dilations of levels).
    Beyond MAX_RINGS, the transform's values in 255 steps."""
    rings = _rings(float(resolution), float(sigma))
    if not rings:
        f = likelihood_field(face, resolution, sigma)
        return (np.round(f * 255.0).astype(np.uint8),
                (np.arange(256) / 255.0).astype(np.float32))
    src = face.astype(np.uint8)
    level = np.zeros_like(src)  # len(rings) - the nearest ring reaching the cell, 0: none
    m = len(rings)
    for k, (kernel, _) in enumerate(rings):
        np.maximum(level, cv2.dilate(src, kernel) * np.uint8(m - k), out=level)
    return level, np.array([0.0] + [w for _, w in reversed(rings)], np.float32)


class LocalizerCore:
    def __init__(self, params: LocalizerParams, laser_offset: float = 0.0,
                 occ: Occupancy | None = None):
        self.p = params
        self.laser_offset = laser_offset  # [m]
        # a cell at or above p_occ is a wall; below p_free known free (a face recorded there
        # is gone)
        self.occ = occ or Occupancy()
        # uint8 (fields, H, W) fine likelihood fields as levels (likelihood_levels), one per
        # quadrant of the beam's heading (one when not directional); the coarse ones: the max
        # over each coarse block's reach; _lut: the likelihood of each level
        self._field: np.ndarray | None = None
        self._coarse: np.ndarray | None = None
        self._lut: np.ndarray | None = None
        self._geom = None
        self._hits: np.ndarray | None = None  # uint8 (H, W): the sides each cell was seen from
        self._hits_geom = None
        self._known: np.ndarray | None = None  # bool (H, W): observed cells (known_only)
        self._known_geom = None
        self._ref = np.zeros(HEADING_BINS)  # the run's direction histogram (step 6)
        self._dirs: tuple[Scan, np.ndarray] | None = None  # the last matched scan's directions

    @property
    def ready(self) -> bool:
        return self._field is not None

    def set_map(self, grid: GridMap) -> None:
        """Build the likelihood fields of a map (call when the map changed)."""
        occ = grid.data >= round(100 * self.occ.p_occ)
        g = grid.geom
        if self.p.known_only:
            self._known, self._known_geom = grid.data >= 0, g
        if self.p.directional:
            hits = (np.zeros((g.height, g.width), np.uint8) if self._hits is None
                    else reframe(self._hits, self._hits_geom, g))
            hits[free_mask(grid.data, self.occ.p_free)] = 0  # cleared since: no surface there now
            self._hits, self._hits_geom = hits, g
        if not occ.any():
            self._field = self._coarse = None
            return
        # the faces of the walls: occupied cells beside a cell that is not (a beam ends on a
        # face; deep inside a thick wall or a filled block no beam ends, and scoring it as a
        # wall would pull a scan into it)
        face = occ & cv2.dilate((~occ).astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
        if self.p.directional:  # step 0: per quadrant, the faces its beams can reach
            seen = self._hits
            sides = [face & (((seen & r) != 0) | (seen == 0)) for r in REACHES]
        else:
            sides = [face]
        c = self.p.coarse
        k = np.ones((c, c), np.uint8)
        fields, coarse = [], []
        for i, side in enumerate(sides):
            same = next((j for j in range(i) if np.array_equal(side, sides[j])), None)
            if same is not None:  # no record tells this quadrant's faces apart
                fields.append(fields[same])
                coarse.append(coarse[same])
                continue
            f, self._lut = likelihood_levels(side, g.resolution, self.p.sigma)
            fields.append(f)
            # the coarse field at cell (r, c) holds the max of the fine field over the block
            # of translations [r, r + c) x [c, c + c) (a grey dilation, anchor at the corner)
            coarse.append(cv2.dilate(f, k, anchor=(0, 0), borderType=cv2.BORDER_CONSTANT,
                                     borderValue=0.0))
        self._field, self._coarse, self._geom = np.stack(fields), np.stack(coarse), g

    def observe(self, scan: Scan, pose: Pose) -> None:
        """Record the sides from which the cells the end points of ``scan``, placed at
        ``pose`` (the pose it is mapped at), lie in were seen (step 0), in the geometry of the
        last map. Before the first map, and for end points beyond its edge, nothing is
        recorded: those faces count from every side. The scan's directions, at that pose,
        join the histogram of step 6."""
        if self.p.heading_gain > 0.0:
            phi = self._directions(scan)
            self._ref += direction_histogram(phi + pose.theta)
        if not self.p.directional or self._hits is None:
            return
        r, a = scan.returns()
        keep = r > 0.0
        r, d = r[keep], a[keep] + pose.theta
        cs, sn = math.cos(pose.theta), math.sin(pose.theta)
        wx = pose.x + self.laser_offset * cs + r * np.cos(d)
        wy = pose.y + self.laser_offset * sn + r * np.sin(d)
        g = self._hits_geom
        side = surface_sides(wx, wy, np.cos(d), np.sin(d))
        row, col = g.world_to_cell(wx, wy)
        ok = g.inside(row, col) & (side != 0)
        np.bitwise_or.at(self._hits, (row[ok], col[ok]), side[ok])

    # -- checkpoints (a restarted localizer keeps what it learned of the run) ---------------

    def checkpoint(self) -> dict[str, np.ndarray]:
        """What the scans taught that the map does not hold: step 6's direction histogram and
        step 0's sides each cell was seen from, with their grid's placement (the likelihood
        fields are made again from the next map)."""
        out = {"ref": self._ref.copy()}
        if self._hits is not None:
            g = self._hits_geom
            out["hits"] = self._hits.copy()
            out["hits_geom"] = np.array([g.resolution, g.origin_x, g.origin_y], np.float64)
        return out

    def restore(self, arrays: dict[str, np.ndarray]) -> None:
        """Take back what :meth:`checkpoint` wrote; CheckpointError (nothing taken) if the
        arrays are not such a checkpoint."""
        ref = checked(arrays, "ref", "f", (HEADING_BINS,)).astype(np.float64)
        if not np.isfinite(ref).all() or (ref < 0.0).any():
            raise CheckpointError("localizer checkpoint: direction histogram out of range")
        hits = geom = None
        if "hits" in arrays:
            hits = checked(arrays, "hits", "i", (None, None))
            place = checked(arrays, "hits_geom", "f", (3,)).astype(np.float64)
            h, w = hits.shape
            if not np.isfinite(place).all() or place[0] <= 0.0 or not 0 < h * w <= MAX_CELLS \
                    or hits.min() < 0 or hits.max() > (NORTH | SOUTH | EAST | WEST):
                raise CheckpointError("localizer checkpoint: surface sides out of range")
            hits = hits.astype(np.uint8)
            geom = GridGeometry(float(place[0]), float(place[1]), float(place[2]), w, h)
        self._ref = ref
        if hits is not None:
            self._hits, self._hits_geom = hits, geom

    def _bins(self, theta: float, ang: np.ndarray) -> np.ndarray:
        """Which field each end point scores on with the robot at heading ``theta`` (its
        beam's quadrant; the one field when not directional)."""
        if self._field.shape[0] == 1:
            return np.zeros(len(ang), np.int64)
        return beam_bins(theta + ang)

    def _points(self, scan: Scan) -> tuple[np.ndarray, np.ndarray]:
        """End points (x, y) [m] in the robot frame, at most max_points, evenly taken, and
        their beams' angles [rad] in the robot frame."""
        r, a = scan.returns()
        keep = r > 0.0
        r, a = r[keep], a[keep]
        if len(r) > self.p.max_points:
            idx = np.linspace(0, len(r) - 1, self.p.max_points).round().astype(int)
            r, a = r[idx], a[idx]
        return np.column_stack((self.laser_offset + r * np.cos(a), r * np.sin(a))), a

    def match(self, scan: Scan, guess: Pose) -> Match:
        """The best pose within the search window round ``guess`` (module docstring)."""
        pts, ang = self._points(scan)
        if self.p.known_only and self._known is not None and len(pts):
            pts, ang = self._on_known(pts, ang, guess)
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
        H, W = self._field.shape[1:]
        n = len(pts)
        # every angle: world end points at the window's corner translation, as cell indices
        base = []
        for th in thetas:
            cs, sn = math.cos(th), math.sin(th)
            wx = guess.x + cs * pts[:, 0] - sn * pts[:, 1] - n_xy * res
            wy = guess.y + sn * pts[:, 0] + cs * pts[:, 1] - n_xy * res
            base.append((np.floor((wy - g.origin_y) / res).astype(np.int64),
                         np.floor((wx - g.origin_x) / res).astype(np.int64),
                         self._bins(th, ang)))
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
            r0, c0, b0 = base[t]
            rr = r0[None, :] + by * c + fine[:, None]  # (c, n)
            cc = c0[None, :] + bx * c + fine[:, None]
            vr = (rr >= 0) & (rr < H)
            vc = (cc >= 0) & (cc < W)
            rr, cc = np.clip(rr, 0, H - 1), np.clip(cc, 0, W - 1)
            vals = self._lut[self._field[b0[None, None, :], rr[:, None, :], cc[None, :, :]]]
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
        pose = self._refine(pts, ang, pose, max_step=2.0 * res)
        pose, ratio = self._hold_weak(pts, ang, pose, guess)
        if p.heading_gain > 0.0:
            pose = self._hold_heading(scan, pts, pose)
        return Match(Pose(pose.x, pose.y, math.remainder(pose.theta, 2 * math.pi)), score, True,
                     n, evaluated, ratio)

    def _on_known(self, pts: np.ndarray, ang: np.ndarray, guess: Pose
                  ) -> tuple[np.ndarray, np.ndarray]:
        """The end points that fall on a known cell of the map at ``guess`` (``known_only``)."""
        g = self._known_geom
        cs, sn = math.cos(guess.theta), math.sin(guess.theta)
        wx = guess.x + cs * pts[:, 0] - sn * pts[:, 1]
        wy = guess.y + sn * pts[:, 0] + cs * pts[:, 1]
        row, col = g.world_to_cell(wx, wy)
        ok = g.inside(row, col)
        ok[ok] = self._known[row[ok], col[ok]]
        return pts[ok], ang[ok]

    def _hold_weak(self, pts: np.ndarray, ang: np.ndarray, pose: Pose, guess: Pose
                   ) -> tuple[Pose, float]:
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
        return self._refine(pts, ang, held, max_step=2.0 * self._geom.resolution,
                            frozen=(ux, uy)), ratio

    def _directions(self, scan: Scan) -> np.ndarray:
        """The directions of the straight stretches of ``scan`` (robot frame; step 6), once
        per scan: :meth:`match` and then :meth:`observe` ask for them."""
        if self._dirs is None or self._dirs[0] is not scan:
            self._dirs = (scan, surface_directions(self._points(scan)[0]))
        return self._dirs[1]

    def _hold_heading(self, scan: Scan, pts: np.ndarray, pose: Pose) -> Pose:
        """Step 6: turn the match by ``heading_gain`` of the offset between the directions
        of the scan's stretches (every end point) and the run's histogram of them, about
        the centroid of the end points it matched (``pts``), so that their place on the map,
        and the translation steps 1-5 found (along a corridor odometry's), stay."""
        phi = self._directions(scan)
        if len(phi) < HEADING_MIN_SCAN or self._ref.sum() < HEADING_MIN_REF:
            return pose
        off = heading_offset(direction_histogram(phi + pose.theta), self._ref,
                             self.p.heading_window)
        if off is None:
            return pose
        cx, cy = pts.mean(axis=0)
        cs, sn = math.cos(pose.theta), math.sin(pose.theta)
        wx, wy = pose.x + cs * cx - sn * cy, pose.y + sn * cx + cs * cy  # the centroid
        th = pose.theta + self.p.heading_gain * off
        cs, sn = math.cos(th), math.sin(th)
        return Pose(wx - cs * cx + sn * cy, wy - sn * cx - cs * cy, th)

    def _bounds(self, base: list[tuple[np.ndarray, ...]], off: np.ndarray) -> np.ndarray:
        """Coarse bounds (angle, block row, block col): each block's score on the max-pooled
        field, at least every fine score of the block."""
        H, W = self._coarse.shape[1:]
        c = self.p.coarse
        bounds = np.empty((len(base), len(off), len(off)))
        for t, (r0, c0, b0) in enumerate(base):
            rr = r0[None, :] + off[:, None]  # (blocks, n)
            cc = c0[None, :] + off[:, None]
            vr = (rr > -c) & (rr < H)  # a block whose corner lies just off the map still
            vc = (cc > -c) & (cc < W)  # reaches into it: its bound is the edge block's
            rr, cc = np.clip(rr, 0, H - 1), np.clip(cc, 0, W - 1)
            vals = self._lut[self._coarse[b0[None, None, :], rr[:, None, :],
                                          cc[None, :, :]]]  # (by, bx, n)
            vals = np.where(vr[:, None, :] & vc[None, :, :], vals, 0.0)
            bounds[t] = vals.sum(axis=2)
        return bounds

    def _sample(self, wx: np.ndarray, wy: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, ...]:
        """Bilinear field values and their gradients [1/m] at world points, each on the field
        of its bin ``b`` (0 off the map)."""
        g = self._geom
        res = g.resolution
        fx = (wx - g.origin_x) / res - 0.5  # cell-centre coordinates
        fy = (wy - g.origin_y) / res - 0.5
        c0, r0 = np.floor(fx).astype(np.int64), np.floor(fy).astype(np.int64)
        ax, ay = fx - c0, fy - r0
        H, W = self._field.shape[1:]
        ok = (r0 >= 0) & (r0 < H - 1) & (c0 >= 0) & (c0 < W - 1)
        r0, c0 = np.where(ok, r0, 0), np.where(ok, c0, 0)
        f, lut = self._field, self._lut
        v00, v01 = lut[f[b, r0, c0]], lut[f[b, r0, c0 + 1]]
        v10, v11 = lut[f[b, r0 + 1, c0]], lut[f[b, r0 + 1, c0 + 1]]
        val = (1 - ay) * ((1 - ax) * v00 + ax * v01) + ay * ((1 - ax) * v10 + ax * v11)
        gx = ((1 - ay) * (v01 - v00) + ay * (v11 - v10)) / res
        gy = ((1 - ax) * (v10 - v00) + ax * (v11 - v01)) / res
        return np.where(ok, val, 0.0), np.where(ok, gx, 0.0), np.where(ok, gy, 0.0)

    def _refine(self, pts: np.ndarray, ang: np.ndarray, pose: Pose, max_step: float,
                iters: int = 10, frozen: tuple[float, float] | None = None) -> Pose:
        """Gauss-Newton on the bilinear field from the best pose of the search: the residual
        of each end point is 1 - its likelihood; steps stay within ``max_step`` [m] of where
        it started, and a step that scores worse ends it."""
        x, y, th = pose
        px, py = pts[:, 0], pts[:, 1]
        b = self._bins(th, ang)  # the bins at the start (a step turns by far less than one)

        def score(x: float, y: float, th: float) -> tuple[float, tuple[np.ndarray, ...]]:
            cs, sn = math.cos(th), math.sin(th)
            wx, wy = x + cs * px - sn * py, y + sn * px + cs * py
            v, gx, gy = self._sample(wx, wy, b)
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
