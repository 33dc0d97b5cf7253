"""Mapper core: Bayesian (log-odds) occupancy grid built from 2-D laser scans (pure).

DESIGN.md §4 "Mapping"; paper §2.1 ("The occupancy probability for each cell is then updated
based on the Bayesian update formula"). No I/O, no clock, no zenoh: poses and scans come in as
arguments.

Model (inverse sensor model in log-odds form, Thrun et al. "Probabilistic Robotics" §9.2)::

    l(cell) <- clamp(l(cell) + l_occ, l_min, l_max)    at the cell hit by a beam
    l(cell) <- clamp(l(cell) + l_free, l_min, l_max)   at every other cell the beam crosses
    p(cell)  = 1 / (1 + exp(-l(cell)))

- Rays are traced with integer Bresenham from the laser's cell to the end point's cell.
- A reading >= range_max (or +inf, REP-117 "no return") marks free cells only, up to range_max.
- Readings < range_min are ignored.
- **One update per cell per scan.** Near the laser, neighbouring beams cross the same cells; with
  181 beams a cell next to the robot would otherwise get ~20x l_free from one scan, i.e. one scan
  would count as twenty independent observations. So within one scan each cell receives at most
  one update: hits are applied first and take precedence (a cell hit by one beam is not cleared by
  a grazing neighbour beam in the same scan), then every other crossed cell gets l_free once.
- **The surface a beam hit** (``surface_reach`` > 0): a thin ray that meets a wall at a
  grazing angle crosses, before its hit, cells that the wall's face passes through (a face in
  the middle of a cell). Clearing them is a model mismatch: with l_free on every crossed cell,
  the grazing beams of many scans clear the face cells of a wall seen from afar, the unknown
  inside the wall then borders free cells, and that false frontier along the wall only closes
  when the robot passes close by. So a beam does not clear a cell, within ``surface_reach`` of
  its hit, that the surface it hit passes through; the hit is applied as usual. A beam's
  surface is the straight line through its hit and two neighbouring hits when the three lie on
  one line (:func:`surface_normals`), and only over the stretch those hits span (half a cell
  more), so a beam through a doorway is not stopped by the wall line beside it. A beam also
  respects its neighbour beams' surfaces (one that grazes a face and just misses its end), but
  only where their hits lie at most ``surface_step`` apart: farther apart, a gap between them
  (a door no beam went through) cannot be told from wall. Without such a line (a lone hit,
  no-return neighbours) a beam clears every crossed cell as before.
- The int8 occupancy (ROS values: -1 never touched, else round(100 p)) is kept current for
  the cells a scan updates, so no whole-grid conversion ever happens per scan.
- numpy only (no numba kernel): all rays of a scan are traced at once in closed form
  (:func:`integrate_cells`). The mapper process then loads no numba and no LLVM: 213 -> 93 MB
  resident on office (docs/benchmarks.md, "Memory").

The grid starts as an ``initial_size`` square centred on the first pose (cell boundaries on
multiples of the resolution) and grows by ``grow_margin`` on a side a beam would leave, moving
the origin by whole cells so existing cells keep their world position; it refuses (ScanError) to
grow beyond ``max_size`` (protection against a bad pose).
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

from topoexplore.common.domain import GridMap, Pose, Scan
from topoexplore.common.grid import GridGeometry, ray_cells
from topoexplore.common.params import MapperParams

__all__ = [
    "ScanError",
    "MapLoadError",
    "MapperCore",
    "beam_endpoints",
    "grow_axis",
    "surface_normals",
    "logodds_to_int8",
    "prob_to_logodds",
]

class ScanError(ValueError):
    """A scan or pose is inconsistent (no beams, NaN, negative range, absurd pose, ...)."""


class MapLoadError(ValueError):
    """A saved grid cannot be loaded (shape, values or resolution do not fit)."""


# --- small pure helpers --------------------------------------------------------------------


def logodds_to_int8(logodds: np.ndarray) -> np.ndarray:
    """Log-odds -> ROS occupancy in percent, round(100 p) with p = 1/(1+exp(-l)); int8 0..100."""
    p = 1.0 / (1.0 + np.exp(-np.asarray(logodds, dtype=np.float64)))
    return np.floor(100.0 * p + 0.5).astype(np.int8)


def prob_to_logodds(p: np.ndarray, l_min: float, l_max: float) -> np.ndarray:
    """Probability -> log-odds log(p/(1-p)), clamped to [l_min, l_max] (p may be 0 or 1)."""
    p = np.clip(np.asarray(p, dtype=np.float64), 1e-9, 1.0 - 1e-9)
    return np.clip(np.log(p / (1.0 - p)), l_min, l_max)


def beam_endpoints(pose: Pose, scan: Scan, laser_offset: float = 0.0
                   ) -> tuple[float, float, np.ndarray, np.ndarray, np.ndarray]:
    """World end points of the usable beams of one scan.

    Beam i points at ``theta + angle_min + i * angle_increment`` from the laser, which sits
    ``laser_offset`` [m] ahead of the robot centre. Returns ``(lx, ly, ex, ey, hit)``: laser
    position [m], end points [m] of the beams with range >= range_min (no-return beams end at
    range_max), and ``hit`` (True where the beam ended on an obstacle).
    """
    x, y, th = pose
    r = scan.ranges
    lx = x + laser_offset * math.cos(th)
    ly = y + laser_offset * math.sin(th)
    idx = np.nonzero(r >= scan.range_min)[0]
    rr = r[idx]
    hit = rr < scan.range_max
    rr = np.minimum(rr, scan.range_max)
    ang = th + scan.angle_min + idx * scan.angle_increment
    ex = lx + rr * np.cos(ang)
    ey = ly + rr * np.sin(ang)
    return lx, ly, ex, ey, hit


def surface_normals(ex: np.ndarray, ey: np.ndarray, hit: np.ndarray, max_step: float,
                    straight: float = math.cos(math.radians(20.0))
                    ) -> tuple[np.ndarray, ...]:
    """The straight surface seen at each beam's end point: ``(ok, near, nx, ny, lo, hi)``.

    Known (ok) for a hit that lies on one straight line with two neighbouring hits: k-1 and
    k+1 (centred), else k-2 and k-1, else k+1 and k+2 (one-sided: the last beam before a
    corner, a depth jump or a gap). Three end points a, b, c are on one line when the steps
    b - a and c - b point the same way within acos(straight); near where both steps are at
    most max_step [m] long as well (at a grazing angle the hits of one wall lie far apart,
    and then an unseen gap between them, a door no beam went through, cannot be told from
    wall: only the beam's own hit is trusted then). (nx, ny) is the unit normal,
    perpendicular to c - a; lo <= 0 <= hi [m] bound the stretch of the line the three hits
    span, measured from the hit along the tangent (ny, -nx): the surface is known only there.
    """
    n = ex.shape[0]
    ok = np.zeros(n, bool)
    near = np.zeros(n, bool)
    nx, ny, lo, hi = np.zeros(n), np.zeros(n), np.zeros(n), np.zeros(n)
    if n < 3:
        return ok, near, nx, ny, lo, hi
    # for every run of three beams (i, i+1, i+2): on one line, and the chord c - a
    sx, sy = ex[1:] - ex[:-1], ey[1:] - ey[:-1]
    sn = np.hypot(sx, sy)
    line = hit[:-2] & hit[1:-1] & hit[2:] & (sn[:-1] > 1e-9) & (sn[1:] > 1e-9)
    short = (sn[:-1] <= max_step) & (sn[1:] <= max_step)
    line &= (sx[:-1] * sx[1:] + sy[:-1] * sy[1:]) >= straight * sn[:-1] * sn[1:]
    cx, cy = sx[:-1] + sx[1:], sy[:-1] + sy[1:]
    for first in (1, 2, 0):  # the run centred on k, then the one ending at k, then starting
        k = np.nonzero(line)[0] + first
        k = k[~ok[k]]
        i = k - first
        ok[k] = True
        near[k] = short[i]
        cn = np.maximum(np.hypot(cx[i], cy[i]), 1e-12)
        tx, ty = cx[i] / cn, cy[i] / cn
        nx[k], ny[k] = -ty, tx
        along = [(ex[i + m] - ex[k]) * tx + (ey[i + m] - ey[k]) * ty for m in range(3)]
        lo[k] = np.minimum(np.minimum(along[0], along[1]), along[2])
        hi[k] = np.maximum(np.maximum(along[0], along[1]), along[2])
    return ok, near, nx, ny, lo, hi


# --- one scan into the grid (numpy) -------------------------------------------------------

_CHUNK = 1 << 20  # [cells] ray cells traced at once: bounds the temporary arrays of a scan


def _apply(logodds: np.ndarray, occ: np.ndarray, flat: np.ndarray, delta: float,
           l_min: float, l_max: float) -> None:
    """Add ``delta`` to the log-odds of the cells ``flat`` (flat indices, each once), clamp,
    and keep their int8 occupancy current (the sum and the probability in float64)."""
    lo, oc = logodds.reshape(-1), occ.reshape(-1)
    v = np.clip(lo[flat].astype(np.float64) + delta, l_min, l_max)
    lo[flat] = v
    oc[flat] = np.floor(100.0 / (1.0 + np.exp(-v)) + 0.5).astype(np.int8)


def _on_surface(rows: np.ndarray, cols: np.ndarray, n_free: np.ndarray, k0: int, r0: int,
                c0: int, er: np.ndarray, ec: np.ndarray, surf: tuple) -> np.ndarray:
    """Mask (beam, step) of the ray cells of beams k0.. that a beam does not clear: within
    ``reach`` of its own hit, or of a neighbour's hit where near[j], and crossed by the known
    stretch of that hit's surface (the arguments of :meth:`MapperCore._surfaces`).

    Only a few steps of a ray can be within reach of a point: the major coordinate of step i
    is exact (major0 + sign * i), so |major0 + sign * i + 0.5 - p_major| <= reach bounds i to
    a window of floor(2 reach) + 1 steps; the exact test runs on that window only.
    """
    ok, near, hc, hr, nx, ny, lo, hi, reach = surf
    m, length = rows.shape
    n = ok.shape[0]
    on = np.zeros((m, length), bool)
    k = np.arange(k0, k0 + m)
    cmajor = np.abs(ec[k] - c0) >= np.abs(er[k] - r0)
    m0 = np.where(cmajor, c0, r0)
    s = np.where(cmajor, np.where(ec[k] > c0, 1, -1), np.where(er[k] > r0, 1, -1))
    steps = np.arange(int(math.floor(2.0 * reach)) + 4)[None, :]
    for o in (-1, 0, 1):
        j = np.clip(k + o, 0, n - 1)
        use = (k + o >= 0) & (k + o < n) & ok[j] & (near[j] | (o == 0))
        t = s * (np.where(cmajor, hc[j], hr[j]) - 0.5 - m0)
        i = (np.ceil(t - reach).astype(np.int64) - 1)[:, None] + steps
        inside = use[:, None] & (i >= 0) & (i < n_free[:, None])
        b, i = np.nonzero(inside)[0], i[inside]
        jb = j[b]
        ax = cols[b, i] + 0.5 - hc[jb]
        ay = rows[b, i] + 0.5 - hr[jb]
        u = ny[jb] * ax - nx[jb] * ay  # along the surface from the hit
        # the line crosses the cell: centre closer than the cell's half extent along the
        # normal (less 0.05 cell, so a face on a cell edge does not)
        hit = ((ax * ax + ay * ay <= reach * reach)
               & (np.abs(nx[jb] * ax + ny[jb] * ay)
                  < 0.5 * (np.abs(nx[jb]) + np.abs(ny[jb])) - 0.05)
               & (lo[jb] - 0.5 <= u) & (u <= hi[jb] + 0.5))
        on[b[hit], i[hit]] = True
    return on


def integrate_cells(logodds: np.ndarray, occ: np.ndarray, scratch: np.ndarray, r0: int,
                    c0: int, er: np.ndarray, ec: np.ndarray, hit: np.ndarray, l_free: float,
                    l_occ: float, l_min: float, l_max: float, surf: tuple
                    ) -> tuple[int, int, int, int]:
    """Apply one scan in place; return the touched window (row0, row1, col0, col1), half-open.

    Each beam k is the Bresenham line (:func:`topoexplore.common.grid.ray_cells`) from the
    laser's cell (r0, c0) to its end cell (er[k], ec[k]); every index must be inside the grid.
    The end cell of a hit gets ``l_occ``; every other cell of a line gets ``l_free``, except
    the cells :func:`_on_surface` keeps (when ``surf``'s reach > 0). Each cell is updated at
    most once per scan, and a cell hit in this scan is not cleared by another beam. ``scratch``
    is an int32 array of the grid's shape whose contents do not matter (it marks the cells
    seen in this scan: the last position in the list of free cells, -1 for a hit).
    """
    h, w = logodds.shape
    n = er.shape[0]
    n_free = np.maximum(np.maximum(np.abs(er - r0), np.abs(ec - c0)) + 1 - hit, 0)
    hits = er[hit] * w + ec[hit]
    free = []
    per = max(1, _CHUNK // max(1, int(n_free.max(initial=0)) + 1))
    for k0 in range(0, n, per):  # beams in chunks: rows x steps stays under _CHUNK cells
        k1 = min(n, k0 + per)
        rows, cols, _ = ray_cells(r0, c0, er[k0:k1], ec[k0:k1])
        keep = np.arange(rows.shape[1])[None, :] < n_free[k0:k1, None]
        if surf[-1] > 0.0:
            keep &= ~_on_surface(rows, cols, n_free[k0:k1], k0, r0, c0, er, ec, surf)
        free.append(rows[keep] * w + cols[keep])
    flat = np.concatenate(free) if free else np.zeros(0, np.int64)
    mark = scratch.reshape(-1)
    pos = np.arange(flat.size, dtype=np.int32)
    mark[flat] = pos  # the last occurrence of a cell wins ...
    mark[hits] = -1  # ... and a hit in this scan takes precedence over every free
    flat = flat[mark[flat] == pos]
    hits = np.unique(hits)
    _apply(logodds, occ, hits, l_occ, l_min, l_max)
    _apply(logodds, occ, flat, l_free, l_min, l_max)
    cells = np.concatenate((hits, flat))
    if cells.size == 0:
        return 0, 0, 0, 0
    r, c = np.divmod(cells, w)
    return int(r.min()), int(r.max()) + 1, int(c.min()), int(c.max()) + 1


def grow_axis(lo: int, hi: int, n: int, margin: int, limit: int) -> tuple[int, int]:
    """Cells to add below index 0 and above index n-1 so that lo..hi fit in an axis of n cells.

    A side that is exceeded gets the overflow plus ``margin`` cells; if that would make the axis
    longer than ``limit`` cells the margins are cut (shared between the sides); (-1, -1) if even
    the bare overflow does not fit.
    """
    need_lo = max(0, -lo)
    need_hi = max(0, hi - (n - 1))
    if n + need_lo + need_hi > limit:
        return -1, -1
    add_lo = need_lo + margin if need_lo else 0
    add_hi = need_hi + margin if need_hi else 0
    excess = n + add_lo + add_hi - limit
    if excess > 0:
        cut_lo = min(add_lo - need_lo, (excess + 1) // 2)
        cut_hi = min(add_hi - need_hi, excess - cut_lo)
        cut_lo = min(add_lo - need_lo, excess - cut_hi)
        add_lo -= cut_lo
        add_hi -= cut_hi
    return add_lo, add_hi


# --- the core ------------------------------------------------------------------------------


class MapperCore:
    """Log-odds occupancy grid that grows as needed (DESIGN.md §4 "Mapping").

    Cell (row i, col j) covers ``[origin + (j, i) * res, origin + (j+1, i+1) * res)``; row = y.
    """

    def __init__(self, params: MapperParams, laser_offset: float = 0.0):
        self.params = params
        self.laser_offset = float(laser_offset)  # [m] laser ahead of the robot centre
        self._res = float(params.resolution)  # [m/cell]
        # origin = base + offset cells * res: integer offsets keep growth exactly cell-aligned
        self._base_x = 0.0  # [m]
        self._base_y = 0.0  # [m]
        self._off_c = 0  # [cells]
        self._off_r = 0  # [cells]
        self._l = np.zeros((0, 0), np.float32)  # log-odds
        self._occ = np.zeros((0, 0), np.int8)  # ROS int8 cache, -1 = never touched
        self._scratch = np.zeros((0, 0), np.int32)  # integrate_cells' per-cell marks
        self.scans = 0  # scans integrated (including ones with no usable beam)
        self.grown = 0  # times the grid grew

    # -- state ---------------------------------------------------------------------------------

    @property
    def ready(self) -> bool:
        """True once a grid exists (after the first integrate, or from_grid)."""
        return self._l.size > 0

    @property
    def geometry(self) -> GridGeometry:
        self._need_grid()
        h, w = self._l.shape
        return GridGeometry(self._res, self._origin_x(), self._origin_y(), w, h)

    def occupancy(self, copy: bool = False) -> np.ndarray:
        """int8 (h, w): -1 unknown (never touched), else round(100 p).

        Without ``copy`` this is a read-only live view that the next integrate() changes.
        """
        self._need_grid()
        if copy:
            return self._occ.copy()
        v = self._occ.view()
        v.flags.writeable = False
        return v

    def log_odds(self) -> np.ndarray:
        """Read-only view of the float32 log-odds grid (for tests and diagnostics)."""
        self._need_grid()
        v = self._l.view()
        v.flags.writeable = False
        return v

    def grid(self, copy: bool = False) -> GridMap:
        """The occupancy grid with its geometry (a read-only live view without ``copy``)."""
        return GridMap(self.occupancy(copy), self.geometry)

    def _need_grid(self) -> None:
        if not self.ready:
            raise RuntimeError("mapper has no grid yet: integrate a scan or use from_grid")

    def _origin_x(self) -> float:
        return self._base_x + self._off_c * self._res

    def _origin_y(self) -> float:
        return self._base_y + self._off_r * self._res

    # -- loading -------------------------------------------------------------------------------

    @classmethod
    def from_grid(cls, grid: GridMap, params: MapperParams,
                  laser_offset: float = 0.0) -> MapperCore:
        """Continue mapping on a saved grid: log-odds = logit(value / 100), clamped; -1 unknown.

        Values 0 and 100 (e.g. from a map_server file) come back as the clamp values
        (round(100 p) at l_min / l_max, 2 / 98 with the defaults): classes are preserved.
        """
        g, geom = grid.data, grid.geom
        if g.min() < -1 or g.max() > 100:
            raise MapLoadError("grid values must be -1 (unknown) or 0..100")
        if not math.isclose(geom.resolution, params.resolution, rel_tol=1e-9):
            raise MapLoadError(
                f"map resolution {geom.resolution} m differs from mapper.resolution "
                f"{params.resolution} m"
            )
        if max(geom.width, geom.height) * geom.resolution > params.max_size + 1e-9:
            raise MapLoadError(f"map is larger than mapper.max_size={params.max_size} m")
        core = cls(params, laser_offset)
        core._base_x = float(geom.origin_x)
        core._base_y = float(geom.origin_y)
        known = g >= 0
        lo = np.zeros(g.shape, np.float32)
        lo[known] = prob_to_logodds(g[known] / 100.0, params.l_min, params.l_max)
        core._l = lo
        core._occ = np.full(g.shape, -1, np.int8)
        core._occ[known] = logodds_to_int8(lo[known])
        core._scratch = np.zeros(g.shape, np.int32)
        return core

    # -- checkpoints (issue 14: a restarted mapper keeps its map) -------------------------------

    def checkpoint(self) -> dict[str, np.ndarray]:
        """What a restarted mapper needs to go on exactly where this one is: the log-odds, the
        touched cells and the grid's placement, as arrays (the shell writes them)."""
        self._need_grid()
        return {"log_odds": self._l.copy(), "occupancy": self._occ.copy(),
                "placement": np.array([self._base_x, self._base_y, self._res], np.float64),
                "counts": np.array([self._off_c, self._off_r, self.scans, self.grown], np.int64)}

    @classmethod
    def from_checkpoint(cls, ck: Mapping[str, np.ndarray], params: MapperParams,
                        laser_offset: float = 0.0) -> MapperCore:
        """The mapper a :meth:`checkpoint` describes; MapLoadError if it is not one this
        mapper's parameters can continue (another resolution, a grid beyond max_size, bad
        values)."""
        try:
            lo = np.asarray(ck["log_odds"])
            occ = np.asarray(ck["occupancy"])
            place = np.asarray(ck["placement"], np.float64)
            counts = np.asarray(ck["counts"])
        except KeyError as exc:
            raise MapLoadError(f"checkpoint has no {exc.args[0]!r}") from None
        if lo.dtype != np.float32 or occ.dtype != np.int8 or lo.ndim != 2 \
                or occ.shape != lo.shape or place.shape != (3,) or counts.shape != (4,) \
                or counts.dtype.kind != "i":
            raise MapLoadError("checkpoint arrays have the wrong types or shapes")
        if not (np.isfinite(place).all() and np.isfinite(lo).all()):
            raise MapLoadError("checkpoint holds non-finite numbers")
        if lo.size and (lo.min() < params.l_min - 1e-6 or lo.max() > params.l_max + 1e-6
                        or occ.min() < -1 or occ.max() > 100):
            raise MapLoadError("checkpoint values are outside the log-odds clamp")
        if not math.isclose(place[2], params.resolution, rel_tol=1e-9):
            raise MapLoadError(f"checkpoint resolution {place[2]} m differs from "
                               f"mapper.resolution {params.resolution} m")
        if max(lo.shape) * params.resolution > params.max_size + 1e-9:
            raise MapLoadError(f"checkpoint grid is larger than mapper.max_size="
                               f"{params.max_size} m")
        core = cls(params, laser_offset)
        core._base_x, core._base_y = float(place[0]), float(place[1])
        core._off_c, core._off_r, core.scans, core.grown = (int(v) for v in counts)
        core._l = lo.copy()
        core._occ = occ.copy()
        core._scratch = np.zeros(lo.shape, np.int32)
        return core

    def adopt(self, newer: GridMap) -> int:
        """Take in a newer map of this mapper's own (its last published one, kept by a peer):
        every cell whose value there differs from ours takes that value (log-odds =
        logit(value / 100), clamped), growing the grid to cover it. Cells it does not know
        stay as they are. Returns how many cells changed. MapLoadError if the map cannot be
        this mapper's (another resolution, off the cell lattice, beyond max_size)."""
        g, geom = newer.data, newer.geom
        if g.size == 0:
            return 0
        if g.min() < -1 or g.max() > 100:
            raise MapLoadError("grid values must be -1 (unknown) or 0..100")
        if not math.isclose(geom.resolution, self._res, rel_tol=1e-9):
            raise MapLoadError(f"map resolution {geom.resolution} m differs from "
                               f"mapper.resolution {self._res} m")
        if not self.ready:
            other = MapperCore.from_grid(newer, self.params, self.laser_offset)
            self.__dict__.update(other.__dict__)
            return int((g >= 0).sum())
        fc = (geom.origin_x - self._origin_x()) / self._res  # its cell (0, 0) in ours
        fr = (geom.origin_y - self._origin_y()) / self._res
        c0, r0 = round(fc), round(fr)
        if abs(fc - c0) > 1e-3 or abs(fr - r0) > 1e-3:
            raise MapLoadError("map cells are not on this mapper's cell lattice")
        h, w = g.shape
        H, W = self._l.shape
        if r0 < 0 or c0 < 0 or r0 + h > H or c0 + w > W:
            try:
                dr, dc = self._grow(r0, r0 + h - 1, c0, c0 + w - 1)
            except ScanError as exc:
                raise MapLoadError(str(exc)) from None
            r0, c0 = r0 + dr, c0 + dc
        mine = self._occ[r0:r0 + h, c0:c0 + w]
        change = (g >= 0) & (g != mine)
        if change.any():
            lo = prob_to_logodds(g[change] / 100.0, self.params.l_min, self.params.l_max)
            self._l[r0:r0 + h, c0:c0 + w][change] = lo
            self._occ[r0:r0 + h, c0:c0 + w][change] = g[change]
        return int(change.sum())

    # -- the update ----------------------------------------------------------------------------

    def integrate(self, pose: Pose, scan: Scan) -> tuple[int, int, int, int]:
        """Fuse one scan taken at ``pose`` (robot centre, map frame; the laser sits
        ``laser_offset`` ahead).

        Returns the changed window ``(row0, row1, col0, col1)`` (half-open) in the current grid.
        If the grid was created or grew during this call, every index shifted, so the window is
        the whole grid. ``(0, 0, 0, 0)`` if no cell changed. Raises ScanError (state unchanged)
        if the scan's range or the grid would have to grow beyond ``max_size``.
        """
        if scan.range_max > self.params.max_size:
            raise ScanError(f"range_max={scan.range_max} exceeds mapper.max_size")
        lx, ly, ex, ey, hit = beam_endpoints(pose, scan, self.laser_offset)
        changed_shape = False
        if not self.ready:
            self._create(float(pose[0]), float(pose[1]))
            changed_shape = True
        res = self._res
        xs = np.append(ex, lx)
        ys = np.append(ey, ly)
        cols = np.floor((xs - self._origin_x()) / res).astype(np.int64)
        rows = np.floor((ys - self._origin_y()) / res).astype(np.int64)
        h, w = self._l.shape
        if rows.min() < 0 or cols.min() < 0 or rows.max() >= h or cols.max() >= w:
            try:
                dr, dc = self._grow(int(rows.min()), int(rows.max()), int(cols.min()),
                                    int(cols.max()))
            except ScanError:
                if changed_shape:  # created in this call: leave the core as it was
                    self._alloc((0, 0))
                raise
            rows += dr
            cols += dc
            changed_shape = True
        self.scans += 1
        window = integrate_cells(
            self._l, self._occ, self._scratch, int(rows[-1]), int(cols[-1]), rows[:-1],
            cols[:-1], np.asarray(hit, dtype=bool), float(self.params.l_free),
            float(self.params.l_occ), float(self.params.l_min), float(self.params.l_max),
            self._surfaces(ex, ey, hit),
        )
        if changed_shape:
            h, w = self._l.shape
            return 0, h, 0, w
        return tuple(int(v) for v in window)

    def _surfaces(self, ex: np.ndarray, ey: np.ndarray, hit: np.ndarray) -> tuple:
        """The surface arguments of :func:`integrate_cells` (surf, near, hc, hr, nx, ny, lo, hi,
        reach; lengths in cells) for the end points ex, ey [m] in the current grid
        (:func:`surface_normals`); empty when surface_reach is 0."""
        reach = float(self.params.surface_reach) / self._res
        if reach <= 0.0:  # none of them is read: empty arrays of the right types
            z, b = np.zeros(0), np.zeros(0, bool)
            return b, b, z, z, z, z, z, z, 0.0
        ok, near, nx, ny, lo, hi = surface_normals(ex, ey, hit, self.params.surface_step)
        hc = (ex - self._origin_x()) / self._res
        hr = (ey - self._origin_y()) / self._res
        return ok, near, hc, hr, nx, ny, lo / self._res, hi / self._res, reach

    def _create(self, x: float, y: float) -> None:
        """First grid: initial_size square centred on (x, y), cell edges on multiples of res."""
        n = max(1, int(math.ceil(self.params.initial_size / self._res - 1e-9)))
        self._base_x = 0.0
        self._base_y = 0.0
        self._off_c = int(math.floor(x / self._res)) - n // 2
        self._off_r = int(math.floor(y / self._res)) - n // 2
        self._alloc((n, n))

    def _alloc(self, shape: tuple[int, int]) -> None:
        self._l = np.zeros(shape, np.float32)
        self._occ = np.full(shape, -1, np.int8)
        self._scratch = np.zeros(shape, np.int32)

    def _grow(self, rmin: int, rmax: int, cmin: int, cmax: int) -> tuple[int, int]:
        """Grow so that rows rmin..rmax and cols cmin..cmax fit, plus grow_margin on each side
        that was exceeded. Returns the (row, col) index shift. ScanError beyond max_size."""
        h, w = self._l.shape
        m = int(math.ceil(self.params.grow_margin / self._res - 1e-9))
        limit = int(math.floor(self.params.max_size / self._res + 1e-9))
        add_r0, add_r1 = grow_axis(rmin, rmax, h, m, limit)  # r0 side = small y
        add_c0, add_c1 = grow_axis(cmin, cmax, w, m, limit)
        if add_r0 < 0 or add_c0 < 0:
            need_w = max(cmax, w - 1) - min(cmin, 0) + 1
            need_h = max(rmax, h - 1) - min(rmin, 0) + 1
            raise ScanError(
                f"grid would grow to {need_w * self._res:.1f} x {need_h * self._res:.1f} m, "
                f"beyond mapper.max_size={self.params.max_size} m (bad pose?)"
            )
        nh = h + add_r0 + add_r1
        nw = w + add_c0 + add_c1
        old_l, old_occ = self._l, self._occ
        self._alloc((nh, nw))
        self._l[add_r0:add_r0 + h, add_c0:add_c0 + w] = old_l
        self._occ[add_r0:add_r0 + h, add_c0:add_c0 + w] = old_occ
        self._off_r -= add_r0
        self._off_c -= add_c0
        self.grown += 1
        return add_r0, add_c0


WARM_MODULES: tuple[str, ...] = ()  # no numba kernels (common.warm)
