"""Reliability core: position probability of topological end nodes (pure, no I/O).

Kwon, Song, Lee, "Improved Exploration Algorithm Using Reliability Index of Thinning Based
Topological Nodes", §3.2, equations 1-10, with the interpretations of DESIGN.md §4:

- eqs. 1-2, distance index: D = (r_near + d_c) / (r + d_c) with r = the minimum robot-centre to
  node distance over all observations, clamped to [r_near, r_far] (defaults: D = 4 / (r + 3.5),
  1 at r <= 0.5 m, 0.5 at r >= 4.5 m).
- eq. 3, angle difference: the *circular* spread of the observation bearings (2 pi minus the
  largest gap between sorted bearings), which does not break at the +-pi seam.
- eq. 4, angle index: A = min(alpha_max / 90 deg, 1).
- eq. 5: R = max(D, A).
- eqs. 6-10, Bayes update with p(X | unrel) = 1 - R: P <- R P / (R P + (1 - R)(1 - P)),
  clamped to p_max so that a later reset still means something.
- "Movement resets belief": a node that moved more than move_tolerance from where its
  observation history began gets P = p_init and a fresh history at its new position.

Observation (the paper: "out of the scanning range (180 deg) or blocked by obstacles is
excluded"): inside the forward field of view of the laser, within range, and the straight line
from the laser to the node crosses no occupied cell (unknown cells do not block).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np
from numba import njit
from scipy.spatial import cKDTree

from topoexplore.common.grid import GridGeometry, open_unknown
from topoexplore.common.messages import NodeReliability
from topoexplore.common.params import ReliabilityParams

__all__ = [
    "ReliabilityError",
    "distance_index",
    "circular_spread",
    "angle_index",
    "reliability_index",
    "bayes_update",
    "line_cells",
    "line_of_sight",
    "is_observed",
    "ReliabilityCore",
]

TWO_PI = 2.0 * math.pi


class ReliabilityError(ValueError):
    """Bad input to a reliability function."""


# --- small helpers ------------------------------------------------------------------------


def _finite(name: str, value: float) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ReliabilityError(f"{name} must be a number (got {value!r})") from None
    if not math.isfinite(v):
        raise ReliabilityError(f"{name} must be finite (got {v})")
    return v


def _pose3(pose) -> tuple[float, float, float]:
    try:
        n = len(pose)
    except TypeError:
        raise ReliabilityError(f"pose must be (x, y, theta) (got {pose!r})") from None
    if n != 3:
        raise ReliabilityError(f"pose must have 3 values (x, y, theta), got {n}")
    return (_finite("pose.x", pose[0]), _finite("pose.y", pose[1]), _finite("pose.theta", pose[2]))


def _wrap(a: float) -> float:
    """Angle [rad] -> (-pi, pi]."""
    return math.atan2(math.sin(a), math.cos(a))


def _check_grid(grid_int8: np.ndarray, geom: GridGeometry) -> np.ndarray:
    if not isinstance(geom, GridGeometry):
        raise ReliabilityError(f"geom must be a GridGeometry (got {type(geom).__name__})")
    g = np.asarray(grid_int8)
    if g.ndim != 2 or g.shape != (geom.height, geom.width):
        raise ReliabilityError(
            f"grid shape {g.shape} does not match geometry (height, width) = "
            f"({geom.height}, {geom.width})"
        )
    if not (math.isfinite(geom.resolution) and geom.resolution > 0):
        raise ReliabilityError(f"grid resolution must be positive (got {geom.resolution})")
    return g


def _check_p_occ(p_occ: float) -> float:
    p = _finite("p_occ", p_occ)
    if not 0.0 < p < 1.0:
        raise ReliabilityError(f"p_occ must be in (0, 1) (got {p})")
    return p


# --- equations ----------------------------------------------------------------------------


def distance_index(r_min: float, params: ReliabilityParams) -> float:
    """Distance reliability index D, paper eqs. 1-2.

    r = r_min clamped to [r_near, r_far]; D = (r_near + d_c) / (r + d_c), which with the paper's
    constants (0.5, 4.5, 3.5) is D = 4 / (r + 3.5): 1 at r <= 0.5 m, 0.5 at r >= 4.5 m.
    r_min = inf (never observed) gives the far value; the core reports D = 0 before the first
    observation instead.
    """
    try:
        r = float(r_min)
    except (TypeError, ValueError):
        raise ReliabilityError(f"r_min must be a number (got {r_min!r})") from None
    if math.isnan(r) or r < 0.0:
        raise ReliabilityError(f"r_min must be >= 0 (got {r})")
    r = min(max(r, params.r_near), params.r_far)
    return (params.r_near + params.d_c) / (r + params.d_c)


def circular_spread(bearings: np.ndarray) -> float:
    """Angular spread alpha_max [rad] of a set of bearings, paper eq. 3 (DESIGN interpretation).

    2 pi minus the largest gap between the sorted bearings on the circle, so bearings of 170 and
    -170 deg give 20 deg (not 340). 0 for zero or one bearing. Result in [0, 2 pi).
    """
    b = np.asarray(bearings, dtype=np.float64).ravel()
    if b.size and not np.all(np.isfinite(b)):
        raise ReliabilityError("bearings must be finite")
    if b.size < 2:
        return 0.0
    b = np.sort(np.mod(b, TWO_PI))
    largest_gap = max(float(np.max(np.diff(b))), float(b[0] + TWO_PI - b[-1]))
    return float(min(max(TWO_PI - largest_gap, 0.0), TWO_PI))


def angle_index(alpha_max: float, params: ReliabilityParams) -> float:
    """Angle reliability index A, paper eq. 4: min(alpha_max / 90 deg, 1) (90 deg = alpha_full)."""
    a = _finite("alpha_max", alpha_max)
    if a < 0.0:
        raise ReliabilityError(f"alpha_max must be >= 0 (got {a})")
    return min(a / params.alpha_full, 1.0)


def reliability_index(d: float, a: float) -> float:
    """Overall reliability index R = max(D, A), paper eq. 5."""
    return max(_finite("D", d), _finite("A", a))


def bayes_update(p: float, r: float) -> float:
    """Position probability update, paper eqs. 6-10.

    With p(X | rel) = R (eq. 10), p(X | unrel) = 1 - R (eq. 8) and P(unrel) = 1 - P (eq. 9):
    P' = R P / (R P + (1 - R)(1 - P)); in odds form, odds' = odds * R / (1 - R).
    """
    p = _finite("p", p)
    r = _finite("r", r)
    if not 0.0 <= p <= 1.0:
        raise ReliabilityError(f"p must be in [0, 1] (got {p})")
    if not 0.0 <= r <= 1.0:
        raise ReliabilityError(f"r must be in [0, 1] (got {r})")
    num = r * p
    den = num + (1.0 - r) * (1.0 - p)
    if den <= 0.0:
        raise ReliabilityError(f"bayes_update undefined for p={p}, r={r} (certain prior, "
                               "certain opposite evidence)")
    return num / den


# --- visibility ---------------------------------------------------------------------------


def line_cells(x0: float, y0: float, x1: float, y1: float, geom: GridGeometry):
    """Every grid cell the segment (x0, y0)-(x1, y1) [m] passes through ("supercover").

    Exact traversal (Amanatides-Woo, vectorised): the segment is split at every crossing of a
    cell border and the cell of each piece's midpoint is taken, in order from the start. Where
    the segment passes exactly through a cell corner, the two cells that only touch it there are
    appended after the ordered cells, so a line cannot slip between two diagonal (8-connected)
    wall cells. Returns (rows, cols) int64 arrays; cells may lie outside the grid.
    """
    res = geom.resolution
    gx0, gy0 = (x0 - geom.origin_x) / res, (y0 - geom.origin_y) / res
    gx1, gy1 = (x1 - geom.origin_x) / res, (y1 - geom.origin_y) / res
    dx, dy = gx1 - gx0, gy1 - gy0
    tx = ty = np.empty(0)
    if dx != 0.0:
        ks = np.arange(math.floor(min(gx0, gx1)) + 1, math.ceil(max(gx0, gx1)), dtype=np.float64)
        tx = (ks - gx0) / dx
    if dy != 0.0:
        ks = np.arange(math.floor(min(gy0, gy1)) + 1, math.ceil(max(gy0, gy1)), dtype=np.float64)
        ty = np.sort((ks - gy0) / dy)
    t = np.unique(np.clip(np.concatenate([[0.0, 1.0], tx, ty]), 0.0, 1.0))
    keep = np.diff(t) > 1e-12
    mid = 0.5 * (t[:-1] + t[1:])[keep] if t.size > 1 else np.empty(0)
    if mid.size == 0:  # zero-length segment
        mid = np.array([0.0])
    cols = np.floor(gx0 + mid * dx).astype(np.int64)
    rows = np.floor(gy0 + mid * dy).astype(np.int64)
    if tx.size and ty.size:
        # corner crossings: an x-border and a y-border crossed at the same t
        j = np.searchsorted(ty, tx)
        lo = ty[np.clip(j - 1, 0, ty.size - 1)]
        hi = ty[np.clip(j, 0, ty.size - 1)]
        tc = tx[np.minimum(np.abs(lo - tx), np.abs(hi - tx)) < 1e-9]
        if tc.size:
            # just before the corner the segment is in one cell, just after in the diagonal one;
            # the two touch cells pair the "before" row with the "after" column and vice versa
            e = 1e-4 / max(abs(dx), abs(dy))  # a 1e-4 cell step either side
            cb = np.floor(gx0 + (tc - e) * dx).astype(np.int64)
            rb = np.floor(gy0 + (tc - e) * dy).astype(np.int64)
            ca = np.floor(gx0 + (tc + e) * dx).astype(np.int64)
            ra = np.floor(gy0 + (tc + e) * dy).astype(np.int64)
            rows = np.concatenate([rows, rb, ra])
            cols = np.concatenate([cols, ca, cb])
    return rows, cols


def _line_clear(ax: float, ay: float, bx: float, by: float, grid: np.ndarray,
                geom: GridGeometry, occ_threshold: float) -> bool:
    rows, cols = line_cells(ax, ay, bx, by, geom)
    ra, ca = geom.world_to_cell(ax, ay)
    rb, cb = geom.world_to_cell(bx, by)
    keep = ~(((rows == ra) & (cols == ca)) | ((rows == rb) & (cols == cb)))
    keep &= (rows >= 0) & (rows < geom.height) & (cols >= 0) & (cols < geom.width)
    if not np.any(keep):
        return True
    return not bool(np.any(grid[rows[keep], cols[keep]] > occ_threshold))


def line_of_sight(a_xy, b_xy, grid_int8: np.ndarray, geom: GridGeometry,
                  p_occ: float = 0.65) -> bool:
    """True if the segment a-b [m] crosses no occupied cell (value > p_occ * 100).

    The cells containing a and b themselves are excluded; unknown (-1) cells and cells outside
    the grid do not block.
    """
    g = _check_grid(grid_int8, geom)
    p = _check_p_occ(p_occ)
    ax, ay = _finite("a.x", a_xy[0]), _finite("a.y", a_xy[1])
    bx, by = _finite("b.x", b_xy[0]), _finite("b.y", b_xy[1])
    return _line_clear(ax, ay, bx, by, g, geom, p * 100.0)


def _laser_xy(pose: tuple[float, float, float], params: ReliabilityParams) -> tuple[float, float]:
    x, y, th = pose
    return x + params.laser_offset * math.cos(th), y + params.laser_offset * math.sin(th)


def _in_fov_range(nx: float, ny: float, lx: float, ly: float, theta: float,
                  params: ReliabilityParams) -> bool:
    dist = math.hypot(nx - lx, ny - ly)
    if dist > params.range_max:
        return False
    if dist < 1e-9:  # node at the laser: trivially seen
        return True
    rel = _wrap(math.atan2(ny - ly, nx - lx) - theta)
    return abs(rel) <= 0.5 * params.fov + 1e-12


def near_frontier(nx: float, ny: float, grid: np.ndarray, geom: GridGeometry, radius: float,
                  p_free: float = 0.35, unknown: np.ndarray | None = None) -> bool:
    """Is there a frontier cell (known free, 4-adjacent to unknown) within radius [m] of the node?

    Our interpretation of "the environment around the end node is examined" (paper §3.2): a
    node next to a frontier sits where the map simply stops, so an observation of it says
    nothing about whether it will stay (a wall hides the unknown behind it: occupied cells are
    never frontier). radius <= 0 disables the test. unknown: the unknown mask to use
    (:func:`open_unknown`; default: every never-observed cell).
    """
    if radius <= 0.0:
        return False
    r, c = geom.world_to_cell(nx, ny)
    k = int(math.ceil(radius / geom.resolution)) + 1
    r0, r1 = max(0, int(r) - k), min(geom.height, int(r) + k + 1)
    c0, c1 = max(0, int(c) - k), min(geom.width, int(c) + k + 1)
    if r0 >= r1 or c0 >= c1:
        return True  # node outside the map: nothing is known around it
    win = grid[r0:r1, c0:c1]
    free = (win >= 0) & (win < p_free * 100.0)
    unk = win < 0 if unknown is None else unknown[r0:r1, c0:c1]
    pad = np.pad(unk, 1, constant_values=False)
    touch = pad[:-2, 1:-1] | pad[2:, 1:-1] | pad[1:-1, :-2] | pad[1:-1, 2:]
    front = free & touch
    if not front.any():
        return False
    rr, cc = np.nonzero(front)
    x, y = geom.cell_to_world(rr + r0, cc + c0)
    return bool(np.min(np.hypot(x - nx, y - ny)) <= radius)


_CROSS = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))


def frontier_cells(grid: np.ndarray, p_free: float = 0.35, min_cells: int = 1,
                   unknown: np.ndarray | None = None) -> np.ndarray:
    """(n, 2) int (row, col) of the frontier cells (known free, 4-adjacent to unknown) that lie
    in 8-connected frontier groups of at least min_cells cells (single holes in a wall seen at a
    grazing angle are not a way into the unknown). unknown: the unknown mask to use
    (:func:`open_unknown`; default: every never-observed cell)."""
    g = np.asarray(grid)
    free = (g >= 0) & (g < p_free * 100.0)
    unknown = (g < 0 if unknown is None else np.asarray(unknown, bool)).view(np.uint8)
    # 4-neighbourhood "touches unknown" (cells outside the grid count as unknown)
    touch = cv2.dilate(unknown, _CROSS, borderType=cv2.BORDER_CONSTANT, borderValue=1)
    front = (free & touch.view(bool)).view(np.uint8)
    nz = cv2.findNonZero(front)  # (n, 1, 2) x, y; ~4 x faster than np.argwhere here
    if nz is None:
        return np.zeros((0, 2), np.int64)
    cells = nz.reshape(-1, 2)[:, ::-1].astype(np.int64)  # (row, col)
    if min_cells <= 1:
        return cells
    _mark_groups(front, cells, min_cells)
    return cells[front[cells[:, 0], cells[:, 1]] == 3]


@njit(cache=True)
def _mark_groups(front, cells, min_cells):  # pragma: no cover - compiled
    """In place on ``front`` (uint8, 1 = frontier): cells of 8-connected groups of at least
    min_cells become 3, the others 2. Visits only the listed frontier cells: they are few,
    and labelling the whole grid costs ~100 x more at 1000 x 1000."""
    h, w = front.shape
    n = cells.shape[0]
    stack = np.empty(n, np.int64)
    members = np.empty(n, np.int64)
    for k in range(n):
        r0, c0 = cells[k, 0], cells[k, 1]
        if front[r0, c0] != 1:
            continue
        front[r0, c0] = 2
        top = 1
        stack[0] = r0 * w + c0
        m = 0
        while top > 0:
            top -= 1
            q = stack[top]
            members[m] = q
            m += 1
            r = q // w
            c = q - r * w
            for dr in range(-1, 2):
                for dc in range(-1, 2):
                    a = r + dr
                    b = c + dc
                    if 0 <= a < h and 0 <= b < w and front[a, b] == 1:
                        front[a, b] = 2
                        stack[top] = a * w + b
                        top += 1
        if m >= min_cells:
            for i in range(m):
                q = members[i]
                front[q // w, q - (q // w) * w] = 3


def leaf_chains(end_ids, edges: list[tuple[int, int]]) -> dict[int, list[int]]:
    """Edge indices of each end node's leaf chain: from the end node along edges through
    nodes of degree 2 (corner nodes) up to the first node of another degree or another end
    node. The chain is the part of the skeleton (and so of free space) the end node stands for.
    """
    ends = set(end_ids)
    inc: dict[int, list[int]] = {}
    for k, (a, b) in enumerate(edges):
        inc.setdefault(a, []).append(k)
        if b != a:
            inc.setdefault(b, []).append(k)
    out: dict[int, list[int]] = {}
    for e in ends:
        chain: list[int] = []
        if len(inc.get(e, ())) == 1:
            cur, k = e, inc[e][0]
            while k not in chain:
                chain.append(k)
                a, b = edges[k]
                cur = b if a == cur else a
                nxt = inc.get(cur, ())
                if cur in ends or len(nxt) != 2:
                    break
                k = nxt[0] if nxt[1] == k else nxt[1]
        out[e] = chain
    return out


def frontier_owned(end_ids, edges: list[tuple[int, int, np.ndarray]], grid: np.ndarray,
                   geom: GridGeometry, p_free: float, min_cells: int, max_dist: float,
                   unknown: np.ndarray | None = None) -> dict[int, int]:
    """Frontier cells each end node "owns": cells of frontier groups >= min_cells whose nearest
    skeleton point (any edge polyline point, within max_dist [m]) is on the node's leaf chain;
    where a chain joins two end nodes (no branch between them), each owns its nearer half.

    Our interpretation of "the environment around the end node is examined" (paper §3.2) for
    frontiers beside an edge rather than at its tip (a room whose side opens into the unknown):
    the end node stands for its leaf chain's part of free space, and while unknown space opens
    from that part, an observation of the node does not say the map there is complete.
    edges: (node a, node b, (n, 2) polyline [m]). Returns {end id: cells}, only ids with cells.
    """
    if not edges or min_cells <= 0:
        return {}
    cells = frontier_cells(grid, p_free, min_cells, unknown)
    if len(cells) == 0:
        return {}
    pairs = [(a, b) for a, b, _ in edges]
    chains = leaf_chains(end_ids, pairs)
    pts, lab = _stack_edges(edges)
    if len(pts) == 0:
        return {}
    # per skeleton point: the owning end node, the one nearest along its chain (a chain that
    # joins two end nodes without a branch is split between them where they are equally far)
    step = np.hypot(*np.diff(pts, axis=0).T)
    step[lab[1:] != lab[:-1]] = 0.0
    cum = np.concatenate([[0.0], np.cumsum(step)])
    first = np.searchsorted(lab, np.arange(len(edges)))
    last = np.searchsorted(lab, np.arange(len(edges)), side="right")
    along = cum - cum[np.minimum(first, len(pts) - 1)][lab]  # arc length from the edge's a
    length = np.where(last > first, cum[np.maximum(last - 1, 0)] - cum[np.minimum(
        first, len(pts) - 1)], 0.0)
    owner = np.full(len(pts), -1, np.int64)
    best = np.full(len(pts), np.inf)
    ids = sorted(chains)
    for j, e in enumerate(ids):
        cur, off = e, 0.0
        for k in chains[e]:
            sl = slice(int(first[k]), int(last[k]))
            a, b = pairs[k]
            d = off + (along[sl] if a == cur else length[k] - along[sl])
            closer = d < best[sl]
            owner[sl] = np.where(closer, j, owner[sl])
            best[sl] = np.where(closer, d, best[sl])
            off += float(length[k])
            cur = b if a == cur else a
    x, y = geom.cell_to_world(cells[:, 0], cells[:, 1])
    d, i = cKDTree(pts).query(np.column_stack([x, y]), k=1, distance_upper_bound=max_dist)
    own = owner[i[np.isfinite(d)]]
    counts = np.bincount(own[own >= 0], minlength=len(ids))
    return {ids[j]: int(counts[j]) for j in np.flatnonzero(counts)}


def is_observed(node_xy, pose, grid_int8: np.ndarray, geom: GridGeometry,
                params: ReliabilityParams, p_occ: float = 0.65) -> bool:
    """Whether an end node counts as observed at this pose (paper §3.2, after eqs. 2 and 3).

    Observed = inside the forward field of view (params.fov centred on the heading, seen from
    the laser at params.laser_offset ahead of the robot centre), within params.range_max of the
    laser, and the line from the laser to the node crosses no occupied cell (excluding the
    node's and the laser's own cells; unknown cells do not block).
    """
    p = _pose3(pose)
    g = _check_grid(grid_int8, geom)
    occ = _check_p_occ(p_occ) * 100.0
    try:
        nx, ny = _finite("node.x", node_xy[0]), _finite("node.y", node_xy[1])
    except (TypeError, IndexError):
        raise ReliabilityError(f"node_xy must be (x, y) (got {node_xy!r})") from None
    lx, ly = _laser_xy(p, params)
    if not _in_fov_range(nx, ny, lx, ly, p[2], params):
        return False
    return _line_clear(lx, ly, nx, ny, g, geom, occ)


# --- the stateful core --------------------------------------------------------------------


def new_viewpoint(last: tuple[float, float, float] | None, rx: float, ry: float,
                  bearing: float, params: ReliabilityParams) -> bool:
    """Does an observation from (rx, ry) at ``bearing`` count as new evidence for eq. 6?

    The Bayes update (eqs. 6-10) treats observations as independent; repeated scans from the
    same viewpoint are not, and counting every scan would make any still node in view reliable
    within seconds. An observation counts when the robot moved ``view_distance`` [m] or the
    bearing to the node turned ``view_angle`` [rad] since the node's last counted observation
    (view_distance = 0: every scan counts, the paper's literal per-period update).
    """
    if last is None or params.view_distance <= 0.0:
        return True
    lx, ly, lb = last
    turned = abs(math.remainder(bearing - lb, 2 * math.pi))
    return math.hypot(rx - lx, ry - ly) >= params.view_distance or turned >= params.view_angle


def _stack_edges(edges) -> tuple[np.ndarray, np.ndarray]:
    """All edge polyline points as one (n, 2) array [m] and the edge index of each point
    (one conversion for all edges: per-edge arrays cost more than the rest of the update)."""
    flat: list = []
    lab: list[int] = []
    for k, (_, _, p) in enumerate(edges):
        if isinstance(p, np.ndarray):
            p = p.reshape(-1, 2).tolist()
        flat.extend(p)
        lab.extend([k] * len(p))
    try:
        pts = np.asarray(flat, dtype=np.float64).reshape(-1, 2)
    except (TypeError, ValueError):
        raise ReliabilityError("edge points must be [x, y] pairs of numbers") from None
    return pts, np.asarray(lab, dtype=np.int64)


def _check_edges(edges) -> list[tuple[int, int, list]]:
    out = []
    for item in edges:
        try:
            a, b, pts = item
            a, b = int(a), int(b)
        except (TypeError, ValueError):
            raise ReliabilityError(f"edge must be (a, b, (n, 2) points) (got {item!r:.80})"
                                   ) from None
        out.append((a, b, pts))
    pts, _ = _stack_edges(out)
    if not np.all(np.isfinite(pts)):
        raise ReliabilityError("an edge has a non-finite point")
    return out


@dataclass
class _Track:
    """Observation history of one end node since its anchor (where the history began)."""

    anchor_x: float  # [m]
    anchor_y: float  # [m]
    x: float  # [m] current position
    y: float  # [m]
    p: float  # position probability
    bins: np.ndarray  # float64 [nbins]: a representative bearing per occupied bin, NaN if empty
    r_min: float = math.inf  # [m]
    d: float = 0.0
    a: float = 0.0
    alpha_max: float = 0.0  # [rad]
    n_obs: int = 0
    n_bearings: int = 0
    visited: bool = False
    visible: bool = False
    resets: int = field(default=0)
    view: tuple[float, float, float] | None = None  # robot x, y [m], bearing [rad] last counted


class ReliabilityCore:
    """Per end node: history (anchor, bearings, r_min) and position probability P.

    Bearings are stored one per angular bin (params.bearing_bin wide, the first bearing that
    fell into the bin is kept exactly), so memory and cost per node stay bounded on long runs
    and alpha_max is exact up to one bin width.
    """

    def __init__(self, params: ReliabilityParams):
        if not isinstance(params, ReliabilityParams):
            raise ReliabilityError(
                f"params must be ReliabilityParams (got {type(params).__name__})")
        self.params = params
        self._nbins = max(1, int(math.ceil(TWO_PI / params.bearing_bin - 1e-9)))
        self._bin_width = TWO_PI / self._nbins  # [rad]
        self._tracks: dict[int, _Track] = {}
        self._places: list[tuple[float, float, float]] = []  # x, y [m], P of reliable nodes
        self._updates = 0
        self._resets = 0
        self._dropped = 0

    # -- internals --

    def _new_track(self, x: float, y: float) -> _Track:
        return _Track(anchor_x=x, anchor_y=y, x=x, y=y, p=self._recall(x, y),
                      bins=np.full(self._nbins, np.nan))

    def _recall(self, x: float, y: float) -> float:
        """Initial P at (x, y) [m]: p_init, or the P a node reached while it stood within
        recall_radius of here (the place was examined already: a skeleton end that flips
        between two corners of a room, or gets a new id, does not send the robot back).
        recall_radius < move_tolerance, so a node that moves away from where it was reliable
        is still reset (DESIGN §4)."""
        r = self.params.recall_radius
        if r <= 0.0 or not self._places:
            return self.params.p_init
        a = np.asarray(self._places)
        near = (a[:, 0] - x) ** 2 + (a[:, 1] - y) ** 2 <= r * r
        return float(max(self.params.p_init, a[near, 2].max())) if near.any() else \
            self.params.p_init

    def _remember(self, tr: _Track) -> None:
        """Keep the place of a reliable node (one entry per recall_radius)."""
        r = self.params.recall_radius
        if r <= 0.0 or tr.p < self.params.p_reliable:
            return
        for k, (px, py, pp) in enumerate(self._places):
            if (px - tr.x) ** 2 + (py - tr.y) ** 2 <= r * r:
                self._places[k] = (px, py, max(pp, tr.p))
                return
        self._places.append((tr.x, tr.y, tr.p))

    def _add_bearing(self, tr: _Track, bearing: float) -> None:
        b = bearing % TWO_PI
        k = int(b / self._bin_width) % self._nbins
        if math.isnan(tr.bins[k]):
            tr.bins[k] = b
            tr.n_bearings += 1
            tr.alpha_max = circular_spread(tr.bins[~np.isnan(tr.bins)])

    @staticmethod
    def _parse_nodes(end_nodes) -> dict[int, tuple[float, float]]:
        out: dict[int, tuple[float, float]] = {}
        for item in end_nodes:
            try:
                nid, x, y = item
            except (TypeError, ValueError):
                raise ReliabilityError(f"end node must be (id, x, y) (got {item!r})") from None
            if isinstance(nid, bool) or not isinstance(nid, (int, np.integer)):
                raise ReliabilityError(f"end node id must be an int (got {nid!r})")
            nid = int(nid)
            if nid in out:
                raise ReliabilityError(f"end node id {nid} appears twice")
            out[nid] = (_finite(f"node {nid} x", x), _finite(f"node {nid} y", y))
        return out

    # -- public --

    def update(self, end_nodes: list[tuple[int, float, float]], gone: list[int],
               pose: tuple[float, float, float], grid_int8: np.ndarray, geom: GridGeometry,
               p_occ: float = 0.65, edges: list[tuple[int, int, np.ndarray]] | None = None
               ) -> list[NodeReliability]:
        """One reliability step for the current end nodes seen from ``pose``.

        end_nodes: (id, x [m], y [m]) of every current end node; gone: ids that vanished;
        pose: robot centre (x [m], y [m], theta [rad]); grid_int8: the occupancy grid used for
        the line-of-sight test with its geometry; edges: the topological edges (node a, node b,
        (n, 2) polyline [m]) for the frontier ownership test (:func:`frontier_owned`; None
        skips it). Returns one NodeReliability per current end node, sorted by id.
        """
        pr = self.params
        pose = _pose3(pose)
        grid = _check_grid(grid_int8, geom)
        occ = _check_p_occ(p_occ) * 100.0
        nodes = self._parse_nodes(end_nodes)
        owned: dict[int, int] = {}
        unknown = None
        if pr.frontier_group > 0 or pr.frontier_radius > 0:
            unknown = open_unknown(grid, int(pr.pocket_area / geom.resolution ** 2), pr.p_free,
                                   p_occ)
        checked = _check_edges(edges) if edges else []  # validated even when unused
        if checked and pr.frontier_group > 0:
            min_cells = max(1, int(math.ceil(pr.frontier_group / geom.resolution - 1e-9)))
            owned = frontier_owned(list(nodes), checked, grid, geom, pr.p_free,
                                   min_cells, pr.range_max, unknown)
        for gid in gone:
            if self._tracks.pop(int(gid), None) is not None:
                self._dropped += 1
        for nid in [k for k in self._tracks if k not in nodes]:
            del self._tracks[nid]
            self._dropped += 1

        rx, ry, th = pose
        lx, ly = _laser_xy(pose, pr)
        out: list[NodeReliability] = []
        for nid in sorted(nodes):
            nx, ny = nodes[nid]
            tr = self._tracks.get(nid)
            if tr is None:
                tr = self._tracks[nid] = self._new_track(nx, ny)
            elif math.hypot(nx - tr.anchor_x, ny - tr.anchor_y) > pr.move_tolerance:
                resets = tr.resets + 1  # movement resets belief (DESIGN §4)
                tr = self._tracks[nid] = self._new_track(nx, ny)
                tr.resets = resets
                self._resets += 1
            tr.x, tr.y = nx, ny
            dist = math.hypot(nx - rx, ny - ry)  # [m] robot centre -> node (paper eq. 2)
            if dist <= pr.visit_radius:
                tr.visited = True
            tr.visible = _in_fov_range(nx, ny, lx, ly, th, pr) and _line_clear(
                lx, ly, nx, ny, grid, geom, occ)
            if tr.visible:
                tr.n_obs += 1
                tr.r_min = min(tr.r_min, dist)
                if dist > 1e-9:
                    self._add_bearing(tr, math.atan2(ny - ry, nx - rx))
                tr.d = distance_index(tr.r_min, pr)
                tr.a = angle_index(tr.alpha_max, pr)
                bearing = math.atan2(ny - ry, nx - rx)
                if (new_viewpoint(tr.view, rx, ry, bearing, pr) and nid not in owned
                        and not near_frontier(nx, ny, grid, geom, pr.frontier_radius,
                                              pr.p_free, unknown)):
                    tr.view = (rx, ry, bearing)
                    tr.p = min(bayes_update(tr.p, reliability_index(tr.d, tr.a)), pr.p_max)
                    self._remember(tr)
            out.append(NodeReliability(
                id=nid, x=nx, y=ny, p=tr.p, d=tr.d, a=tr.a, r_min=tr.r_min,
                alpha_max=tr.alpha_max, visible=tr.visible, n_obs=tr.n_obs, visited=tr.visited,
                frontier=owned.get(nid, 0)))
        self._updates += 1
        return out

    def snapshot(self) -> dict:
        """JSON-able state: counters and per-node history (r_min None when never observed)."""
        nodes = {}
        for nid in sorted(self._tracks):
            tr = self._tracks[nid]
            nodes[str(nid)] = {
                "x": tr.x, "y": tr.y, "anchor": [tr.anchor_x, tr.anchor_y], "p": tr.p,
                "d": tr.d, "a": tr.a,
                "r_min": tr.r_min if math.isfinite(tr.r_min) else None,
                "alpha_max_deg": math.degrees(tr.alpha_max), "n_obs": tr.n_obs,
                "n_bearings": tr.n_bearings, "visible": tr.visible, "visited": tr.visited,
                "resets": tr.resets,
                "reliable": tr.p >= self.params.p_reliable,
            }
        return {
            "updates": self._updates,
            "end_nodes": len(self._tracks),
            "reliable": sum(1 for t in self._tracks.values() if t.p >= self.params.p_reliable),
            "resets": self._resets,
            "examined_places": len(self._places),
            "dropped": self._dropped,
            "nodes": nodes,
        }
