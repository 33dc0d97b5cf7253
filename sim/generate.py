"""Generated worlds: office floors, houses, warehouses and cluttered halls, deterministic by seed.

:func:`generate` lays a building out on a 0.05 m lattice (wall centrelines half a step off it,
so every wall surface, door jamb and axis-aligned piece of furniture lies on pixel edges of a
0.05 m raster), furnishes it, checks with :func:`reachability` that the robot can reach
essentially all of its free space and picks a start pose. The result is an ordinary
:class:`sim.world.World` (walls as segments, furniture as boxes, legs as small circles) plus a
description of what was placed (:attr:`Generated.meta`: rooms, doors with their widths,
aisles, passages). :func:`slam_map` turns a generated world into a ROS map_server grid degraded
like a map a real robot made; :func:`write_generated` writes either, :func:`generate_corpus`
writes many.

Everything random comes from one ``numpy.random.Generator`` seeded from the arguments (style,
seed, size, and the noise level for a map); nothing uses global random state, so the same
arguments give byte-identical files.

The reachability check (:func:`reachability`) works on a raster: the robot's centre may be
where the clearance is at least ``ROBOT_RADIUS + MARGIN`` (less half a cell for the
rasterization), those cells are connected from the start, and a free cell counts as reached
when it lies within ``REACH_SEE`` more of them along free space (the band along walls and into
corners the body and laser sweep). Free space thinner than a slit (5 cells, 0.25 m at 0.05 m)
is not counted as part of the building: it is what leak rays and gaps behind furniture leave.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from statistics import NormalDist

import cv2
import numpy as np

from topoexplore.common.grid import GridGeometry, distance_transform
from topoexplore.common.mapio import MapIOError, atomic_write, write_map_server
from topoexplore.sim.world import (
    ROBOT_RADIUS,
    START_CLEARANCE,
    World,
    clearance,
    rasterize,
)

__all__ = [
    "STYLES",
    "DEFAULT_SIZES",
    "SIZE_RANGE",
    "MAX_NOISE",
    "DOOR_WIDTHS",
    "GenerateError",
    "Generated",
    "Space",
    "Door",
    "Item",
    "Reach",
    "SlamMap",
    "check_arguments",
    "generate",
    "reachability",
    "world_reachability",
    "slam_map",
    "world_toml",
    "write_generated",
    "generate_corpus",
    "world_name",
]

STYLES = ("office", "house", "warehouse", "cluttered")
DEFAULT_SIZES = {"office": (32.0, 24.0), "house": (18.0, 14.0), "warehouse": (34.0, 26.0),
                 "cluttered": (24.0, 22.0)}
SIZE_RANGE = (8.0, 60.0)  # [m] allowed width and height
MAX_NOISE = 3
RES = 0.05  # [m] lattice step and raster resolution
WALL_R = 0.075  # [m] wall segment radius: walls 0.15 m thick, 3 pixels
JAMB = 0.15  # [m] least wall between a door and a corner
MARGIN = 0.1  # [m] clearance wanted on top of the robot radius
REACH_CLEARANCE = ROBOT_RADIUS + MARGIN  # [m] where the robot's centre may be
REACH_SEE = 0.15  # [m] a free cell within REACH_CLEARANCE + this of a centre cell is reached
MIN_REACHED = 0.99  # share of the free space that must be reached
MAX_POCKET = 0.5  # [m^2] largest unreached piece allowed (under a chair, behind a table)
BUILD_POCKET = 0.3  # [m^2] what generation aims for (noise may add a little)
OPEN_MIN = 0.9  # [m] least clear width where two spaces of one group meet without a wall
MAP_MARGIN = 2.0  # [m] unknown border around a SLAM map (room for leak rays)
# style -> {door kind: (narrowest, widest, most common) clear width [m]}
DOOR_WIDTHS = {
    "office": {"door": (0.6, 1.2, 0.9)},
    "house": {"door": (0.7, 1.0, 0.85)},
    "warehouse": {"door": (0.8, 1.2, 1.0), "opening": (2.5, 4.0, 3.2)},
    "cluttered": {"opening": (1.0, 2.5, 1.6)},
}

Point = tuple[float, float]
Rect = tuple[float, float, float, float]  # x0, y0, x1, y1 [m]
Box = tuple[Point, Point, float]
Circle = tuple[Point, float]
Segment = tuple[Point, Point]

_K3 = np.ones((3, 3), np.uint8)
_K5 = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5))
_NORMALS = ((0.0, 1.0), (0.0, -1.0), (1.0, 0.0), (-1.0, 0.0))  # into the room from S, N, W, E


class GenerateError(ValueError):
    """A bad argument (one line), or a world the generator could not make valid (a bug)."""


# --------------------------------------------------------------------------------------------
# arguments, names, random streams


def check_arguments(style: str, seed: int, size: Sequence[float] | None = None,
                    slam_noise: int | None = None) -> tuple[float, float]:
    """Validate the arguments of :func:`generate` / :func:`slam_map`; returns the world size
    [m] (the style's default, or ``size`` rounded to 0.1 m). Raises :class:`GenerateError`."""
    if style not in STYLES:
        raise GenerateError(f"unknown style {style!r} (expected one of {', '.join(STYLES)})")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise GenerateError(f"seed must be an integer >= 0 (got {seed!r})")
    if slam_noise is not None and (isinstance(slam_noise, bool)
                                   or not isinstance(slam_noise, (int, np.integer))
                                   or not 0 <= slam_noise <= MAX_NOISE):
        raise GenerateError(f"slam noise level must be an integer 0..{MAX_NOISE} "
                            f"(got {slam_noise!r})")
    if size is None:
        return DEFAULT_SIZES[style]
    if len(size) != 2:
        raise GenerateError(f"size must be two numbers W H (got {list(size)!r})")
    lo, hi = SIZE_RANGE
    out = []
    for v in size:
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) \
                or not lo <= v <= hi:
            raise GenerateError(f"size must be between {lo:g} and {hi:g} m per side "
                                f"(got {v!r})")
        out.append(round(float(v), 1))
    return out[0], out[1]


def world_name(style: str, seed: int, size: Sequence[float], slam_noise: int | None = None
               ) -> str:
    """File stem of a generated world, e.g. ``office-s3-32x24`` or ``house-s0-20x15-n2``."""
    name = f"{style}-s{seed}-{size[0]:g}x{size[1]:g}"
    return name if slam_noise is None else f"{name}-n{slam_noise}"


def _rng(style: str, seed: int, size: Sequence[float], stream: int) -> np.random.Generator:
    """The one random stream of a world (stream 0) or of its SLAM map at a level (1 + level)."""
    key = [int(seed), STYLES.index(style), int(round(size[0] * 10)), int(round(size[1] * 10)),
           int(stream)]
    return np.random.default_rng(key)


# --------------------------------------------------------------------------------------------
# lattice


def _q(v: float) -> float:
    """Round to 0.1 mm (what the files hold), never a negative zero."""
    return round(float(v), 4) + 0.0


def _between(rng: np.random.Generator, lo: float, hi: float) -> float:
    """rng.uniform(lo, hi) that takes hi a hair below lo (float rounding) as hi = lo."""
    return float(rng.uniform(lo, max(lo, hi)))


def _lat(v: float) -> float:
    """The nearest lattice point (wall surfaces, furniture edges, sizes)."""
    return _q(round(v / RES) * RES)


def _lat_floor(v: float) -> float:
    return _q(math.floor(v / RES + 1e-6) * RES)


def _line(v: float) -> float:
    """The wall centreline at or below ``v`` (half a step off the lattice)."""
    return _q((math.floor(v / RES - 0.5 + 1e-6) + 0.5) * RES)


def _inner(rect: Rect) -> Rect:
    """Clear interior of a space whose rect runs along wall centrelines."""
    x0, y0, x1, y1 = rect
    return _q(x0 + WALL_R), _q(y0 + WALL_R), _q(x1 - WALL_R), _q(y1 - WALL_R)


def _grow(rect: Rect, d: float) -> Rect:
    return rect[0] - d, rect[1] - d, rect[2] + d, rect[3] + d


def _area(rect: Rect) -> float:
    return (rect[2] - rect[0]) * (rect[3] - rect[1])


def _transpose(rect: Rect) -> Rect:
    return rect[1], rect[0], rect[3], rect[2]


def _cuts(rng: np.random.Generator, a: float, b: float, lo: float, hi: float
          ) -> list[tuple[float, float]]:
    """Split [a, b] (wall centrelines) into pieces between ``lo`` and about ``hi`` long."""
    length = b - a
    if length <= hi + 1e-9 or length < 2 * lo:
        return [(a, b)]
    n_lo = math.ceil(length / hi)
    n = int(rng.integers(n_lo, max(n_lo, math.floor(length / lo)) + 1))
    for _ in range(20):
        edges = [a] + [_line(p) for p in np.sort(rng.uniform(a, b, n - 1))] + [b]
        d = np.diff(edges)
        if d.min() >= lo - 1e-9 and d.max() <= hi * 1.25:
            break
    else:
        edges = [a] + [_line(a + length * i / n) for i in range(1, n)] + [b]
    return list(zip(edges[:-1], edges[1:], strict=True))


def _union(ivs: Iterable[tuple[float, float]]) -> list[tuple[float, float]]:
    out: list[list[float]] = []
    for a, b in sorted(ivs):
        if out and a <= out[-1][1] + 1e-9:
            out[-1][1] = max(out[-1][1], b)
        else:
            out.append([a, b])
    return [(a, b) for a, b in out]


def _subtract(ivs: list[tuple[float, float]], cuts: Iterable[tuple[float, float]]
              ) -> list[tuple[float, float]]:
    out = list(ivs)
    for c0, c1 in cuts:
        nxt = []
        for a, b in out:
            if c1 <= a or c0 >= b:
                nxt.append((a, b))
                continue
            if c0 > a:
                nxt.append((a, c0))
            if c1 < b:
                nxt.append((c1, b))
        out = nxt
    return [(a, b) for a, b in out if b - a > 1e-6]


# --------------------------------------------------------------------------------------------
# the reachability checker


@dataclass(frozen=True)
class Reach:
    """What the robot can reach of a world's free space (see the module docstring)."""

    free_area: float  # [m^2] free space wider than a slit
    reached_area: float  # [m^2] of it reached by the robot
    largest_pocket: float  # [m^2] largest connected piece not reached
    pockets: int  # unreached pieces larger than one cell
    start_clearance: float  # [m] on the raster at the start (nan without a start)
    unreached: np.ndarray = field(repr=False, compare=False)

    @property
    def fraction(self) -> float:
        return self.reached_area / self.free_area if self.free_area > 0 else 0.0

    @property
    def ok(self) -> bool:
        """Essentially all reachable: >= MIN_REACHED of the area, no pocket > MAX_POCKET."""
        return self.fraction >= MIN_REACHED and self.largest_pocket <= MAX_POCKET

    def summary(self) -> dict:
        return {"free_area": round(self.free_area, 2), "reached_area": round(self.reached_area, 2),
                "fraction": round(self.fraction, 5), "largest_pocket": round(self.largest_pocket, 3),
                "pockets": self.pockets}


def _geodesic(seed: np.ndarray, free_u8: np.ndarray, steps: int) -> np.ndarray:
    """Cells reachable from ``seed`` in ``steps`` 8-connected moves through free cells."""
    cur = seed.astype(np.uint8) & free_u8
    for _ in range(steps):
        cur = cv2.dilate(cur, _K3) & free_u8
    return cur.astype(bool)


def _coverage(solid: np.ndarray, res: float, clr: float, comp_of: Callable | None = None
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(clearance [m] per cell, centre cells used, reached cells, free body) of a solid mask.

    ``comp_of(centres, dt)`` picks the centre cells to start from (default: all of them)."""
    free_u8 = (~solid).astype(np.uint8)
    dt = distance_transform(free_u8) * res - res / 2
    centres = dt >= clr - res
    if comp_of is not None:
        centres = comp_of(centres, dt)
    covered = _geodesic(centres, free_u8, max(1, round((clr + REACH_SEE) / res)))
    body = cv2.morphologyEx(free_u8, cv2.MORPH_OPEN, _K5).astype(bool)
    return dt, centres, covered, body


def _component_at(rc: tuple[int, int] | None) -> Callable:
    """comp_of for :func:`_coverage`: the centre component holding cell ``rc`` (None: the
    largest); a start a cell or two off the centre cells snaps to the nearest one."""

    def pick(centres: np.ndarray, dt: np.ndarray) -> np.ndarray:
        n, lab = cv2.connectedComponents(centres.astype(np.uint8), connectivity=8)
        if n <= 1:
            return np.zeros_like(centres)
        if rc is None:
            return lab == int(np.argmax(np.bincount(lab[lab > 0])))
        r, c = rc
        win = lab[max(r - 2, 0):r + 3, max(c - 2, 0):c + 3]
        if not 0 <= r < lab.shape[0] or not 0 <= c < lab.shape[1] or not (win > 0).any():
            return np.zeros_like(centres)
        label = lab[r, c] if lab[r, c] > 0 else int(win[win > 0].min())
        return lab == label

    return pick


def reachability(solid: np.ndarray, res: float = RES, origin: Point = (0.0, 0.0),
                 start: Point | None = None, clearance_m: float = REACH_CLEARANCE) -> Reach:
    """Check a solid mask (row 0 = min y): how much of its free space the robot reaches from
    ``start`` [m] (None: from the largest connected region of allowed centre cells)."""
    rc = None
    if start is not None:
        rc = (int(math.floor((start[1] - origin[1]) / res)),
              int(math.floor((start[0] - origin[0]) / res)))
    dt, _centres, covered, body = _coverage(np.asarray(solid, bool), res, clearance_m,
                                            _component_at(rc))
    unreached = body & ~covered
    n, _lab, stats, _ = cv2.connectedComponentsWithStats(unreached.astype(np.uint8),
                                                         connectivity=8)
    areas = stats[1:, cv2.CC_STAT_AREA] * res * res if n > 1 else np.zeros(0)
    start_clr = float("nan")
    if rc is not None and 0 <= rc[0] < dt.shape[0] and 0 <= rc[1] < dt.shape[1]:
        start_clr = float(dt[rc])
    return Reach(free_area=float(body.sum() * res * res),
                 reached_area=float((body & covered).sum() * res * res),
                 largest_pocket=float(areas.max()) if areas.size else 0.0,
                 pockets=int((areas > res * res + 1e-12).sum()),
                 start_clearance=start_clr, unreached=unreached)


def world_reachability(world: World, res: float = RES) -> Reach:
    """:func:`reachability` of a world (any world: generated, built-in or a map) from its
    start pose."""
    solid, ox, oy = rasterize(world, res)
    return reachability(solid, res, (ox, oy), world.robot_pose[:2])


# --------------------------------------------------------------------------------------------
# floor plans: rectangles tiling the building, walls where they meet, doors to connect them


@dataclass
class Space:
    """A room, corridor, hallway, hall or zone: a rectangle along wall centrelines."""

    kind: str  # room | corridor | hallway | hall | zone
    rect: Rect
    label: str = ""  # office, meeting, bedroom, kitchen, storage, ...
    group: str = ""  # spaces of one non-empty group that touch are one open space (no wall)


@dataclass(frozen=True)
class Door:
    """An opening of ``lo .. hi`` [m] (clear) in the wall between spaces ``a`` and ``b``."""

    a: int
    b: int
    horizontal: bool  # the wall runs along x
    line: float  # [m] y of a horizontal wall's centreline, x of a vertical one
    lo: float
    hi: float
    kind: str = "door"  # door | opening (warehouse hall openings, cluttered zone openings)

    @property
    def width(self) -> float:
        return _q(self.hi - self.lo)

    @property
    def center(self) -> Point:
        mid = _q((self.lo + self.hi) / 2)
        return (mid, self.line) if self.horizontal else (self.line, mid)

    def keepout(self, depth: float = 0.9, side: float = 0.3) -> Rect:
        """Where no furniture may stand: the opening and a square-ish approach either side."""
        if self.horizontal:
            return self.lo - side, self.line - depth, self.hi + side, self.line + depth
        return self.line - depth, self.lo - side, self.line + depth, self.hi + side


@dataclass
class _Plan:
    style: str
    size: tuple[float, float]
    spaces: list[Space]
    zones: list[tuple[str, Rect]] = field(default_factory=list)  # loading areas
    doors: list[Door] = field(default_factory=list)
    open_pairs: set[tuple[int, int]] = field(default_factory=set)
    walls: list[Segment] = field(default_factory=list)
    root: int = 0

    def transpose(self) -> None:
        for s in self.spaces:
            s.rect = _transpose(s.rect)
        self.zones = [(n, _transpose(r)) for n, r in self.zones]


def _edges(spaces: list[Space]):
    """({(i, j): (horizontal, line, s0, s1)} for spaces touching along a piece of wall, and
    {(horizontal, line): [(s0, s1), ...]} every space edge on each wall line)."""
    lines: dict[tuple[bool, float], list[tuple[float, float, int, int]]] = {}
    for i, s in enumerate(spaces):
        x0, y0, x1, y1 = s.rect
        for horiz, line, a, b, high in ((True, y0, x0, x1, 0), (True, y1, x0, x1, 1),
                                        (False, x0, y0, y1, 0), (False, x1, y0, y1, 1)):
            lines.setdefault((horiz, _q(line)), []).append((a, b, i, high))
    pairs: dict[tuple[int, int], tuple[bool, float, float, float]] = {}
    for (horiz, line), items in lines.items():
        for a0, b0, i, hi_i in items:
            for a1, b1, j, hi_j in items:
                s0, s1 = max(a0, a1), min(b0, b1)
                if hi_i == 1 and hi_j == 0 and s1 - s0 > 1e-6:
                    pairs[(min(i, j), max(i, j))] = (horiz, line, s0, s1)
    return pairs, {k: [(a, b) for a, b, _i, _h in v] for k, v in lines.items()}


def _door_on(rng: np.random.Generator, edge, widths: tuple[float, float, float]
             ) -> tuple[float, float] | None:
    """A door's (lo, hi) on a shared wall piece, or None when the piece is too short."""
    _horiz, _line_, s0, s1 = edge
    lo_lim, hi_lim = _q(s0 + WALL_R + JAMB), _q(s1 - WALL_R - JAMB)
    wmin, wmax, mode = widths
    avail = hi_lim - lo_lim
    if avail < wmin - 1e-9:
        return None
    w = min(_lat(rng.triangular(wmin, mode, wmax)), _lat_floor(avail + 1e-9))
    w = min(max(w, wmin), wmax)
    lo = _q(lo_lim + _lat_floor(rng.uniform(0.0, max(avail - w, 0.0))))
    return lo, _q(lo + w)


def _door_kind(plan: _Plan, i: int, j: int) -> str:
    kinds = DOOR_WIDTHS[plan.style]
    a, b = plan.spaces[i], plan.spaces[j]
    if "opening" in kinds and ("door" not in kinds or (a.kind == b.kind == "hall")):
        return "opening"
    return "door"


def _add_door(rng, plan: _Plan, edges, i: int, j: int) -> bool:
    key = (min(i, j), max(i, j))
    kind = _door_kind(plan, i, j)
    span = _door_on(rng, edges[key], DOOR_WIDTHS[plan.style][kind])
    if span is None:
        return False
    horiz, line, _s0, _s1 = edges[key]
    plan.doors.append(Door(key[0], key[1], horiz, line, span[0], span[1], kind))
    return True


def _connect(rng: np.random.Generator, plan: _Plan, edges, extra: float) -> None:
    """Open junctions within groups, then doors along a breadth-first tree from the root's
    open space (so rooms next to a corridor get their door to it), then extra doors (loops,
    rooms with two doors) with probability ``extra`` per touching pair."""
    n = len(plan.spaces)
    nbrs: dict[int, list[int]] = {i: [] for i in range(n)}
    parent = list(range(n))

    def find(k: int) -> int:
        while parent[k] != k:
            parent[k] = parent[parent[k]]
            k = parent[k]
        return k

    for (i, j) in sorted(edges):
        nbrs[i].append(j)
        nbrs[j].append(i)
        gi, gj = plan.spaces[i].group, plan.spaces[j].group
        _h, _l, s0, s1 = edges[(i, j)]
        if gi and gi == gj and s1 - s0 >= 2 * WALL_R + OPEN_MIN:
            plan.open_pairs.add((i, j))
            parent[find(i)] = find(j)
    members: dict[int, list[int]] = {}
    for k in range(n):
        members.setdefault(find(k), []).append(k)
    queue = list(members[find(plan.root)])
    connected = set(queue)
    for i in queue:  # grows while iterating: breadth first
        for j in rng.permutation(nbrs[i]).tolist():
            if j not in connected and _add_door(rng, plan, edges, i, j):
                new = members[find(j)]
                connected.update(new)
                queue.extend(new)
    if len(connected) < n:
        missing = sorted(set(range(n)) - connected)
        raise GenerateError(f"internal: {plan.style} plan has unreachable spaces {missing}")
    doored = {(d.a, d.b) for d in plan.doors}
    count = Counter(k for d in plan.doors for k in (d.a, d.b))
    for key in sorted(edges):
        if key in plan.open_pairs or key in doored or rng.random() >= extra:
            continue
        if max(count[key[0]], count[key[1]]) < 3 and _add_door(rng, plan, edges, *key):
            count.update(key)


def _build_walls(plan: _Plan, edges, lines) -> None:
    """Wall segments along every space edge, less open junctions and door openings."""
    cuts: dict[tuple[bool, float], list[tuple[float, float]]] = {}
    for key in plan.open_pairs:
        horiz, line, s0, s1 = edges[key]
        cuts.setdefault((horiz, line), []).append((s0, s1))
    for d in plan.doors:
        cuts.setdefault((d.horizontal, d.line), []).append((d.lo - WALL_R, d.hi + WALL_R))
    segs: list[Segment] = []
    for (horiz, line) in sorted(lines):
        for a, b in _subtract(_union(lines[(horiz, line)]), sorted(cuts.get((horiz, line), []))):
            a, b = _q(a), _q(b)
            segs.append(((a, line), (b, line)) if horiz else ((line, a), (line, b)))
    plan.walls = segs


def _finish_plan(rng: np.random.Generator, plan: _Plan, extra: float) -> None:
    edges, lines = _edges(plan.spaces)
    _connect(rng, plan, edges, extra)
    _build_walls(plan, edges, lines)


# --------------------------------------------------------------------------------------------
# office: rooms off corridors (bands of rooms between horizontal corridors, vertical connectors)


def _office_bands(rng: np.random.Generator, h: float):
    """Rows along y: room bands [(y0, y1, inner)] and corridors [(y0, y1)] between them."""
    bottom, top = WALL_R, _line(h - WALL_R + 1e-6)
    total = top - bottom
    k = max(1, int(round(total / 12.5)))
    widths = [_q(_lat(rng.uniform(1.4, 2.5)) + 2 * WALL_R) for _ in range(k)]
    weights = np.array([1.0] + [2.0] * (k - 1) + [1.0])
    depths = (total - sum(widths)) * weights * rng.uniform(0.8, 1.2, k + 1)
    depths = depths * (total - sum(widths)) / depths.sum()
    if depths.min() < 2.5:
        depths = (total - sum(widths)) * weights / weights.sum()
    bands, corridors, y = [], [], bottom
    for i in range(k + 1):
        y1 = top if i == k else _line(y + depths[i] + 1e-6)
        bands.append((y, y1, 0 < i < k))
        if i < k:
            corridors.append((y1, _q(y1 + widths[i])))
            y = corridors[-1][1]
    return bands, corridors


def _office_connectors(rng: np.random.Generator, w: float, k: int):
    """Vertical corridors: [(x0, x1, {band indices they cross})]."""
    if k >= 2:
        n = 1 + int(rng.random() < 0.75) + int(w > 45 and rng.random() < 0.6)
    else:
        n = int(rng.integers(0, 3 if w >= 16 else 2))
    lo, hi = 4.5, w - 4.5
    centres: list[float] = []
    for m in range(n, 0, -1):
        if hi <= lo:
            break
        for _ in range(30):
            c = np.sort(rng.uniform(lo, hi, m))
            if m == 1 or np.diff(c).min() >= 7.5:
                centres = c.tolist()
                break
        if centres:
            break
    out = []
    for c in centres:
        clear = _lat(rng.uniform(1.4, 2.5))
        x0 = _line(c - clear / 2)
        if k >= 2:
            crossed = set(range(1, k)) | {b for b in (0, k) if rng.random() < 0.3}
        else:
            crossed = {int(rng.integers(0, 2))}
        out.append((x0, _q(x0 + clear + 2 * WALL_R), crossed))
    return out


def _office_corridors(rng, w: float, corridors, conns) -> list[Space]:
    """Horizontal corridors (some stop short: a storage room behind their dead end)."""
    right = _line(w - WALL_R + 1e-6)
    left_lim = min((c[0] for c in conns), default=_line(w * 0.4))
    right_lim = max((c[1] for c in conns), default=_line(w * 0.6))
    out = []
    for y0, y1 in corridors:
        xa, xb = WALL_R, right
        if left_lim - WALL_R >= 4.0 and rng.random() < 0.45:
            xa = _line(rng.uniform(WALL_R + 3.0, left_lim) + 1e-6)
        if right - right_lim >= 4.0 and rng.random() < 0.45:
            xb = max(_line(rng.uniform(right_lim, right - 3.0) + 1e-6), right_lim)
        out.append(Space("corridor", (xa, y0, xb, y1), "corridor", "corridor"))
        for a, b in ((WALL_R, xa), (xb, right)):
            if b - a > 1e-6:
                out += [Space("room", (p, y0, q, y1), "storage") for p, q in _cuts(rng, a, b, 3, 7)]
    return out


def _office_row(rng, x0: float, y0: float, x1: float, y1: float) -> list[Space]:
    """Rooms side by side along x; now and then two merge into a bigger one."""
    pieces = _cuts(rng, x0, x1, 2.6, 6.0)
    merged: list[tuple[float, float]] = []
    for a, b in pieces:
        if merged and rng.random() < 0.12 and b - merged[-1][0] <= 14:
            merged[-1] = (merged[-1][0], b)
        else:
            merged.append((a, b))
    out = []
    for a, b in merged:
        area = _area(_inner((a, y0, b, y1)))
        label = ("open-plan" if area >= 30 else "meeting" if area >= 12 and rng.random() < 0.25
                 else "office")
        out.append(Space("room", (a, y0, b, y1), label))
    return out


def _office_layout(rng: np.random.Generator, size: tuple[float, float]) -> _Plan:
    W, H = size
    swap = (W < H) != (rng.random() < 0.2)  # corridors mostly along the long side
    w, h = (H, W) if swap else (W, H)
    bands, corridors = _office_bands(rng, h)
    conns = _office_connectors(rng, w, len(corridors))
    spaces = _office_corridors(rng, w, corridors, conns)
    right = _line(w - WALL_R + 1e-6)
    for bi, (y0, y1, inner) in enumerate(bands):
        crossing = sorted((x0, x1) for x0, x1, crossed in conns if bi in crossed)
        spaces += [Space("corridor", (x0, y0, x1, y1), "corridor", "corridor")
                   for x0, x1 in crossing]
        rows = [(y0, y1)]
        if inner and y1 - y0 >= 7.0:
            ym = _line(y0 + (y1 - y0) * rng.uniform(0.42, 0.58))
            rows = [(y0, ym), (ym, y1)]
        for ya, yb in rows:
            for xa, xb in _subtract([(WALL_R, right)], crossing):
                spaces += _office_row(rng, xa, ya, xb, yb)
    plan = _Plan("office", size, spaces)
    if swap:
        plan.transpose()
    return plan


# --------------------------------------------------------------------------------------------
# house: binary space partition with short hallways branching off each other

_SIDE_MAP = {  # touch side -> canonical side (u along the hallway, v across) -> real side
    "x0": {"u0": "x0", "u1": "x1", "v0": "y0", "v1": "y1"},
    "x1": {"u0": "x1", "u1": "x0", "v0": "y0", "v1": "y1"},
    "y0": {"u0": "y0", "u1": "y1", "v0": "x0", "v1": "x1"},
    "y1": {"u0": "y1", "u1": "y0", "v0": "x0", "v1": "x1"},
}


def _from_uv(rect: Rect, touch: str, u0: float, v0: float, u1: float, v1: float) -> Rect:
    """A rect given in a frame with u from the ``touch`` side into ``rect``, v across it."""
    x0, y0, x1, y1 = rect
    if touch == "x0":
        r = (x0 + u0, y0 + v0, x0 + u1, y0 + v1)
    elif touch == "x1":
        r = (x1 - u1, y0 + v0, x1 - u0, y0 + v1)
    elif touch == "y0":
        r = (x0 + v0, y0 + u0, x0 + v1, y0 + u1)
    else:
        r = (x0 + v0, y1 - u1, x0 + v1, y1 - u0)
    return _q(r[0]), _q(r[1]), _q(r[2]), _q(r[3])


def _try_hallway(rng, rect: Rect, touch: str | None, depth: int, out: list[Space]) -> bool:
    """Carve a hallway from the ``touch`` side (an outer wall at the top level) into ``rect``
    and split what is left around it. False when the block is too small for one."""
    x0, y0, x1, y1 = rect
    if touch is None:
        if depth > 0:
            return False
        touch = str(rng.choice(["x0", "x1"] if x1 - x0 >= y1 - y0 else ["y0", "y1"]))
    elif rng.random() < 0.3:
        return False
    along, across = (x1 - x0, y1 - y0) if touch[0] == "x" else (y1 - y0, x1 - x0)
    hw = _q(_lat(rng.uniform(1.0, 1.4)) + 2 * WALL_R)
    if along < 8.0 or across < 2 * 2.8 + hw or along * across < 50:
        return False
    length = _lat(along * rng.uniform(0.55, 0.85))
    if along - length < 3.0:
        length = along
    c0 = _lat(min(max(across * rng.uniform(0.35, 0.65) - hw / 2, 2.8), across - hw - 2.8))
    sides = _SIDE_MAP[touch]
    out.append(Space("hallway", _from_uv(rect, touch, 0, c0, length, c0 + hw), "hallway", "hall"))
    parts = [((0, 0, length, c0), sides["v1"]), ((0, c0 + hw, length, across), sides["v0"])]
    if along - length >= 6.0 and across >= 8.0 and rng.random() < 0.7:  # a T: cross hallway
        out.append(Space("hallway", _from_uv(rect, touch, length, 0, length + hw, across),
                         "hallway", "hall"))
        parts.append(((length + hw, 0, along, across), sides["u0"]))
    elif length < along:  # the end block touches the hallway's end only: rooms, no branch
        parts.append(((length, 0, along, across), None))
    for (u0, v0, u1, v1), side in parts:
        _house_split(rng, _from_uv(rect, touch, u0, v0, u1, v1), side, depth + 1, out)
    return True


def _house_split(rng, rect: Rect, touch: str | None, depth: int, out: list[Space]) -> None:
    """Split ``rect`` into rooms; ``touch`` is its side along a hallway, if any."""
    if depth < 4 and _try_hallway(rng, rect, touch, depth, out):
        return
    x0, y0, x1, y1 = rect
    lx, ly = x1 - x0, y1 - y0
    long_side = max(lx, ly)
    if long_side < 2 * 2.6 or (long_side <= 8.0 and lx * ly <= rng.uniform(18, 44)):
        out += _house_leaf(rng, rect)
        return
    if lx >= ly:
        c = min(max(_line(x0 + lx * rng.uniform(0.35, 0.65)), _q(x0 + 2.6)), _q(x1 - 2.6))
        halves = (((x0, y0, c, y1), "x1"), ((c, y0, x1, y1), "x0"))
    else:
        c = min(max(_line(y0 + ly * rng.uniform(0.35, 0.65)), _q(y0 + 2.6)), _q(y1 - 2.6))
        halves = (((x0, y0, x1, c), "y1"), ((x0, c, x1, y1), "y0"))
    for part, lost in halves:  # the half that lost the touching side no longer touches
        _house_split(rng, part, None if touch == lost else touch, depth + 1, out)


def _house_leaf(rng, rect: Rect) -> list[Space]:
    """A room; now and then with a strip off one end for a bathroom, wc or closet."""
    x0, y0, x1, y1 = rect
    along_x = x1 - x0 >= y1 - y0
    long_side = max(x1 - x0, y1 - y0)
    sw = _lat(rng.uniform(1.9, 2.5))
    if long_side - sw < 2.6 or rng.random() >= 0.3:
        return [Space("room", rect)]
    low = bool(rng.random() < 0.5)
    if along_x:
        c = _q(x0 + sw) if low else _q(x1 - sw)
        parts = ((x0, y0, c, y1), (c, y0, x1, y1))
    else:
        c = _q(y0 + sw) if low else _q(y1 - sw)
        parts = ((x0, y0, x1, c), (x0, c, x1, y1))
    strip, rest = parts if low else parts[::-1]
    return [Space("room", rest), Space("room", strip, "small")]


def _merge_living(rng, spaces: list[Space]) -> None:
    """Join two rooms side by side (same extent along their shared wall) into one living
    room of 22-48 m^2 when there is such a pair: houses have one big room."""
    rooms = [i for i, s in enumerate(spaces) if s.kind == "room" and not s.label]
    pairs = []
    for n, i in enumerate(rooms):
        for j in rooms[n + 1:]:
            a, b = spaces[i].rect, spaces[j].rect
            side_x = a[1] == b[1] and a[3] == b[3] and (a[2] == b[0] or b[2] == a[0])
            side_y = a[0] == b[0] and a[2] == b[2] and (a[3] == b[1] or b[3] == a[1])
            u = (min(a[0], b[0]), min(a[1], b[1]), max(a[2], b[2]), max(a[3], b[3]))
            lx, ly = u[2] - u[0], u[3] - u[1]
            if (side_x or side_y) and 22 <= _area(_inner(u)) <= 48 \
                    and max(lx, ly) <= 2.3 * min(lx, ly):
                pairs.append((i, j, u))
    if pairs:
        i, j, u = pairs[int(rng.integers(len(pairs)))]
        spaces[i].rect = u
        del spaces[j]


def _label_house(rng, spaces: list[Space]) -> None:
    rooms = sorted((i for i, s in enumerate(spaces) if s.kind == "room" and not s.label),
                   key=lambda i: (-_area(spaces[i].rect), i))
    for rank, i in enumerate(rooms):
        area = _area(_inner(spaces[i].rect))
        if rank == 0:
            label = "living"
        elif rank == 1:
            label = "kitchen"
        elif rank == 2 and len(rooms) >= 6 and rng.random() < 0.6:
            label = "dining"
        elif area < 7.0:
            label = "small"
        else:
            label = "study" if rng.random() < 0.2 else "bedroom"
        spaces[i].label = label
    small = ["bathroom", "wc", "closet", "laundry"]
    for k, s in enumerate(x for x in spaces if x.label == "small"):
        s.label = small[k] if k < len(small) else "closet" if k % 2 else "bathroom"


def _house_layout(rng: np.random.Generator, size: tuple[float, float]) -> _Plan:
    W, H = size
    spaces: list[Space] = []
    _house_split(rng, (WALL_R, WALL_R, _line(W - WALL_R + 1e-6), _line(H - WALL_R + 1e-6)),
                 None, 0, spaces)
    _merge_living(rng, spaces)
    _label_house(rng, spaces)
    plan = _Plan("house", size, spaces)
    halls = [i for i, s in enumerate(spaces) if s.kind == "hallway"]
    plan.root = halls[0] if halls else next(i for i, s in enumerate(spaces)
                                            if s.label == "living")
    return plan


# --------------------------------------------------------------------------------------------
# warehouse: one to three halls in a row, an office corner, a loading area


def _warehouse_layout(rng: np.random.Generator, size: tuple[float, float]) -> _Plan:
    W, H = size
    swap = W < H
    w, h = (H, W) if swap else (W, H)
    right, top = _line(w - WALL_R + 1e-6), _line(h - WALL_R + 1e-6)
    n = 1 if w < 30 else int(rng.integers(1, 3)) if w < 46 else int(rng.integers(2, 4))
    xs = ([WALL_R] + [_line(WALL_R + (right - WALL_R) * (i + rng.uniform(-0.1, 0.1)) / n)
                      for i in range(1, n)] + [right])
    a, b = xs[0], xs[1]
    ow = max(_lat(min(rng.uniform(5.0, 9.0), (b - a) * 0.45)), 2.6)
    oh = max(_lat(min(rng.uniform(4.0, 6.0), (top - WALL_R) * 0.4)), 2.6)
    at_top = bool(rng.random() < 0.5)
    ob0, ob1 = (_q(top - oh), top) if at_top else (WALL_R, _q(WALL_R + oh))
    rest = (a, WALL_R, _q(a + ow), ob0) if at_top else (a, ob1, _q(a + ow), top)
    spaces = [Space("hall", (_q(a + ow), WALL_R, b, top), "hall", "hall0"),
              Space("hall", rest, "hall", "hall0")]
    spaces += [Space("room", (p, ob0, q, ob1), "office") for p, q in _cuts(rng, a, _q(a + ow),
                                                                           2.6, 4.5)]
    spaces += [Space("hall", (xs[k], WALL_R, xs[k + 1], top), "hall", f"hall{k}")
               for k in range(1, n)]
    la = xs[-2] if n > 1 else _q(a + ow)
    depth = _lat(rng.uniform(4.0, 7.0))
    inner_lo, inner_hi = _q(WALL_R * 2), _q(top - WALL_R)
    zone = ((_q(la + WALL_R), inner_lo, _q(right - WALL_R), _q(inner_lo + depth)) if at_top
            else (_q(la + WALL_R), _q(inner_hi - depth), _q(right - WALL_R), inner_hi))
    plan = _Plan("warehouse", size, spaces, zones=[("loading", zone)])
    if swap:
        plan.transpose()
    return plan


# --------------------------------------------------------------------------------------------
# cluttered: one to four open zones with wide openings between them


def _cluttered_layout(rng: np.random.Generator, size: tuple[float, float]) -> _Plan:
    W, H = size
    rects: list[Rect] = [(WALL_R, WALL_R, _line(W - WALL_R + 1e-6), _line(H - WALL_R + 1e-6))]
    for _ in range(2):
        nxt = []
        for r in rects:
            x0, y0, x1, y1 = r
            lx, ly = x1 - x0, y1 - y0
            if max(lx, ly) < 16 or rng.random() >= 0.7:
                nxt.append(r)
            elif lx >= ly:
                c = _line(x0 + lx * rng.uniform(0.35, 0.65))
                nxt += [(x0, y0, c, y1), (c, y0, x1, y1)]
            else:
                c = _line(y0 + ly * rng.uniform(0.35, 0.65))
                nxt += [(x0, y0, x1, c), (x0, c, x1, y1)]
        rects = nxt
    return _Plan("cluttered", size, [Space("zone", r, "zone") for r in rects])


# --------------------------------------------------------------------------------------------
# furniture: items placed one by one on a raster, each refused if it would leave free space
# the robot cannot reach nearby (a slot behind a desk, a corner closed by a wardrobe)


@dataclass
class Item:
    """A piece of furniture (or a shelf row, a pallet stack, an obstacle): boxes and circles
    placed together; ``tol`` [m^2] is how much unreachable free space it may leave (the
    space under a chair)."""

    kind: str
    boxes: list[Box] = field(default_factory=list)
    circles: list[Circle] = field(default_factory=list)
    tol: float = 0.05
    gap: float = 0.0  # [m] a gate's passage width
    window: tuple[int, int, int, int] = (0, 0, 0, 0)  # raster rows r0:r1, cols c0:c1

    @property
    def area(self) -> float:
        return (sum(s[0] * s[1] for _c, s, _a in self.boxes)
                + sum(math.pi * r * r for _c, r in self.circles))


def _box(rect: Rect) -> Box:
    x0, y0, x1, y1 = rect
    return (_q((x0 + x1) / 2), _q((y0 + y1) / 2)), (_q(x1 - x0), _q(y1 - y0)), 0.0


def _rbox(cx: float, cy: float, sx: float, sy: float, angle: float) -> Box:
    return (_q(cx), _q(cy)), (_q(sx), _q(sy)), _q(angle)


def _corners(cx: float, cy: float, hx: float, hy: float, angle: float) -> np.ndarray:
    ca, sa = math.cos(angle), math.sin(angle)
    local = np.array([[-hx, -hy], [hx, -hy], [hx, hy], [-hx, hy]])
    return local @ np.array([[ca, sa], [-sa, ca]]) + [cx, cy]


def _legs(cx: float, cy: float, sx: float, sy: float, angle: float, r: float,
          inset: float = 0.04) -> list[Circle]:
    """Legs (circles of radius r) at the corners of a table or chair top."""
    pts = _corners(cx, cy, sx / 2 - inset - r, sy / 2 - inset - r, angle)
    return [((_q(x), _q(y)), _q(r)) for x, y in pts]


def _stamp(item: Item, shape: tuple[int, int]):
    """Raster cells ``item`` touches (cells it overlaps, as sim.world.rasterize, near enough
    for placement): (r0, r1, c0, c1, bool mask) or None when it leaves the world."""
    polys = [_corners(c[0], c[1], s[0] / 2 + RES / 2 - 1e-3, s[1] / 2 + RES / 2 - 1e-3, a)
             for c, s, a in item.boxes]
    pts = [p for poly in polys for p in poly]
    pts += [(c[0] + sx * r, c[1] + sy * r) for c, r in item.circles for sx in (-1, 1)
            for sy in (-1, 1)]
    arr = np.asarray(pts) / RES
    c0, r0 = np.floor(arr.min(axis=0)).astype(int) - 1
    c1, r1 = np.ceil(arr.max(axis=0)).astype(int) + 1
    if c0 < 0 or r0 < 0 or c1 > shape[1] or r1 > shape[0]:
        return None
    m = np.zeros((r1 - r0, c1 - c0), np.uint8)
    off = np.array([c0 + 0.5, r0 + 0.5])
    for poly in polys:
        p = np.round((poly / RES - off) * 16).astype(np.int32)
        cv2.fillConvexPoly(m, p, 1, cv2.LINE_8, 4)
    for (cx, cy), r in item.circles:
        x, y = np.round((np.array([cx, cy]) / RES - off) * 16).astype(int)
        cv2.circle(m, (int(x), int(y)), int(round((r / RES + 0.5) * 16)), 1, -1, cv2.LINE_8, 4)
    return r0, r1, c0, c1, m.astype(bool)


class _BorderComponents:
    """comp_of for :func:`_coverage` in a raster window: the centre cells connected to the
    window's border (so, as far as the window can tell, to the rest of the building). Counts
    the sizeable ones in ``big``: a piece of furniture that raises the count has cut a place
    in two inside the window, which may have sealed it off."""

    MIN_CELLS = 40  # [cells] 0.1 m^2 at 0.05 m: smaller bits of centre space do not count

    def __init__(self) -> None:
        self.big = 0

    def __call__(self, centres: np.ndarray, _dt: np.ndarray) -> np.ndarray:
        n, lab, stats, _ = cv2.connectedComponentsWithStats(centres.astype(np.uint8),
                                                            connectivity=8)
        if n <= 1:
            self.big = 0
            return centres
        edge = np.unique(np.concatenate((lab[0], lab[-1], lab[:, 0], lab[:, -1])))
        edge = edge[edge > 0]
        self.big = int((stats[edge, cv2.CC_STAT_AREA] >= self.MIN_CELLS).sum())
        return np.isin(lab, edge)


def _window_check(solid: np.ndarray) -> tuple[int, int]:
    """(free cells the border-connected centre cells miss, sizeable border components)."""
    comps = _BorderComponents()
    _dt, _c, covered, body = _coverage(solid, RES, REACH_CLEARANCE, comps)
    return int((body & ~covered).sum()), comps.big


class _Placer:
    """Walls rasterized once; items stamped on top as they are accepted."""

    def __init__(self, plan: _Plan):
        walls = World(name="walls", size=plan.size, robot_pose=(0.0, 0.0, 0.0),
                      segments=plan.walls, wall_thickness=WALL_R)
        self.walls, _, _ = rasterize(walls, RES)
        self.solid = self.walls.copy()
        self.taken = np.zeros_like(self.walls)  # cells of accepted items
        self.keep = np.zeros_like(self.walls)  # door approaches: nothing stands there
        for d in plan.doors:
            x0, y0, x1, y1 = d.keepout()
            self.keep[max(int(y0 / RES), 0):max(int(math.ceil(y1 / RES)), 0),
                      max(int(x0 / RES), 0):max(int(math.ceil(x1 / RES)), 0)] = True
        self.items: list[Item] = []

    def place(self, item: Item | None) -> bool:
        if item is None:
            return False
        st = _stamp(item, self.walls.shape)
        if st is None:
            return False
        r0, r1, c0, c1, m = st
        core = cv2.erode(m.astype(np.uint8), _K3).astype(bool)
        if (m & self.keep[r0:r1, c0:c1]).any() \
                or (core & (self.taken[r0:r1, c0:c1] | self.walls[r0:r1, c0:c1])).any():
            return False
        pad = int(round(1.0 / RES))
        h, w = self.solid.shape
        R0, R1, C0, C1 = max(r0 - pad, 0), min(r1 + pad, h), max(c0 - pad, 0), min(c1 + pad, w)
        before = self.solid[R0:R1, C0:C1]
        after = before.copy()
        after[r0 - R0:r1 - R0, c0 - C0:c1 - C0] |= m
        lost0, parts0 = _window_check(before)
        lost1, parts1 = _window_check(after)
        if (lost1 - lost0) * RES * RES > item.tol or parts1 > parts0:
            return False
        self.solid[r0:r1, c0:c1] |= m
        self.taken[r0:r1, c0:c1] |= m
        item.window = (r0, r1, c0, c1)
        self.items.append(item)
        return True

    def attempt(self, make: Callable[[], Item | None], tries: int = 6) -> bool:
        """Place the first of up to ``tries`` candidates ``make()`` offers that fits."""
        return any(self.place(make()) for _ in range(tries))


# --- pieces of furniture: each maker returns one candidate Item (or None) for a room interior


def _wall_rect(rng, inner: Rect, length: float, depth: float, side: int,
               corner_p: float = 0.4) -> Rect | None:
    """A ``length`` x ``depth`` rect with its back on wall ``side`` (0 S, 1 N, 2 W, 3 E)."""
    x0, y0, x1, y1 = inner
    along, room = ((x1 - x0), (y1 - y0)) if side < 2 else ((y1 - y0), (x1 - x0))
    if length > along + 1e-9 or depth > room - 0.9:
        return None
    u, spare = rng.random(), max(along - length, 0.0)
    t = 0.0 if u < corner_p / 2 else spare if u < corner_p else _between(rng, 0.0, spare)
    a0 = (x0 if side < 2 else y0) + _lat_floor(t + 1e-9)
    a1 = a0 + length
    r = ((a0, y0, a1, y0 + depth), (a0, y1 - depth, a1, y1), (x0, a0, x0 + depth, a1),
         (x1 - depth, a0, x1, a1))[side]
    return _q(r[0]), _q(r[1]), _q(r[2]), _q(r[3])


def _front(rect: Rect, side: int, dist: float) -> Point:
    """The point ``dist`` in front of the middle of a wall rect's front edge."""
    nx, ny = _NORMALS[side]
    x0, y0, x1, y1 = rect
    return ((x0 + x1) / 2 + nx * ((x1 - x0) / 2 + dist),
            (y0 + y1) / 2 + ny * ((y1 - y0) / 2 + dist))


def _chair(x: float, y: float, angle: float) -> list[Circle]:
    return _legs(x, y, 0.44, 0.44, angle, 0.03, 0.02)


def _against(kind: str, length: tuple[float, float], depth: tuple[float, float],
             corner_p: float = 0.5) -> Callable:
    """Maker of a plain box against a wall (cabinet, wardrobe, counter, bed...)."""

    def make(rng, inner: Rect) -> Item | None:
        rect = _wall_rect(rng, inner, _lat(rng.uniform(*length)), _lat(rng.uniform(*depth)),
                          int(rng.integers(4)), corner_p)
        return None if rect is None else Item(kind, [_box(rect)])

    return make


def _desk(rng, inner: Rect) -> Item | None:
    side = int(rng.integers(4))
    rect = _wall_rect(rng, inner, _lat(rng.uniform(1.2, 1.8)), _lat(rng.uniform(0.6, 0.8)),
                      side, 0.3)
    if rect is None:
        return None
    x, y = _front(rect, side, 0.3)
    return Item("desk", [_box(rect)], _chair(x, y, rng.uniform(-0.5, 0.5)), tol=0.2)


def _table(rng, inner: Rect, length: tuple[float, float], width: tuple[float, float],
           kind: str) -> Item | None:
    """A free-standing table (legs only) with chairs along its long sides, mostly."""
    x0, y0, x1, y1 = inner
    along_x = (x1 - x0) >= (y1 - y0)
    room_long, room_short = max(x1 - x0, y1 - y0), min(x1 - x0, y1 - y0)
    tl = min(_lat(rng.uniform(*length)), _lat_floor(room_long - 2.2))
    tw = min(_lat(rng.uniform(*width)), _lat_floor(room_short - 2.2))
    if tl < length[0] - 0.4 or tw < 0.7:
        return None
    cx = (x0 + x1) / 2 + rng.uniform(-0.3, 0.3)
    cy = (y0 + y1) / 2 + rng.uniform(-0.3, 0.3)
    sx, sy = (tl, tw) if along_x else (tw, tl)
    circles = _legs(cx, cy, sx, sy, 0.0, _q(rng.uniform(0.035, 0.05)), 0.05)
    if rng.random() < 0.75:
        n = max(1, int((tl - 0.2) / 0.65))
        for k in range(n):
            t = -tl / 2 + tl * (k + 0.5) / n
            for s in (-1, 1):
                d = s * (tw / 2 + 0.12)
                px, py = (cx + t, cy + d) if along_x else (cx + d, cy + t)
                circles += _chair(px, py, rng.uniform(-0.3, 0.3))
    return Item(kind, [], circles, tol=0.3)


def _meeting_table(rng, inner: Rect) -> Item | None:
    return _table(rng, inner, (1.6, 3.2), (0.9, 1.2), "table")


def _dining_table(rng, inner: Rect) -> Item | None:
    return _table(rng, inner, (1.2, 1.8), (0.8, 1.0), "table")


def _desk_island(rng, inner: Rect) -> Item | None:
    """Two desks back to back in an open-plan office, chairs on both sides."""
    x0, y0, x1, y1 = inner
    length, depth = _lat(rng.uniform(2.4, 3.2)), 1.4
    sx, sy = (length, depth) if rng.random() < 0.5 else (depth, length)
    if x1 - x0 < sx + 2.6 or y1 - y0 < sy + 2.6:
        return None
    cx = _lat(_between(rng, x0 + 1.3 + sx / 2, x1 - 1.3 - sx / 2))
    cy = _lat(_between(rng, y0 + 1.3 + sy / 2, y1 - 1.3 - sy / 2))
    chairs: list[Circle] = []
    n = max(1, int(length / 1.2))
    for k in range(n):
        t = -length / 2 + length * (k + 0.5) / n
        for s in (-1, 1):
            d = s * (depth / 2 + 0.3)
            px, py = (cx + t, cy + d) if sx > sy else (cx + d, cy + t)
            chairs += _chair(px, py, rng.uniform(-0.5, 0.5))
    return Item("desk", [_rbox(cx, cy, sx, sy, 0.0)], chairs, tol=0.3)


def _plant(rng, inner: Rect) -> Item:
    x0, y0, x1, y1 = inner
    r = _q(rng.uniform(0.15, 0.25))
    cx = x0 + r + 0.05 if rng.random() < 0.5 else x1 - r - 0.05
    cy = y0 + r + 0.05 if rng.random() < 0.5 else y1 - r - 0.05
    return Item("plant", [], [((_q(cx), _q(cy)), r)])


def _bed(rng, inner: Rect) -> Item | None:
    """A bed, head against a wall, with a nightstand on each side where there is room."""
    side = int(rng.integers(4))
    width = float(rng.choice([0.9, 1.4, 1.6, 1.8]))
    rect = _wall_rect(rng, inner, width, 2.0, side, 0.3)
    if rect is None:
        return None
    boxes = [_box(rect)]
    x0, y0, x1, y1 = rect
    stands = ([(x0 - 0.45, y0, x0, y0 + 0.4), (x1, y0, x1 + 0.45, y0 + 0.4)] if side == 0 else
              [(x0 - 0.45, y1 - 0.4, x0, y1), (x1, y1 - 0.4, x1 + 0.45, y1)] if side == 1 else
              [(x0, y0 - 0.45, x0 + 0.4, y0), (x0, y1, x0 + 0.4, y1 + 0.45)] if side == 2 else
              [(x1 - 0.4, y0 - 0.45, x1, y0), (x1 - 0.4, y1, x1, y1 + 0.45)])
    ix0, iy0, ix1, iy1 = inner
    for s in stands:
        if s[0] >= ix0 - 1e-9 and s[1] >= iy0 - 1e-9 and s[2] <= ix1 + 1e-9 \
                and s[3] <= iy1 + 1e-9:
            boxes.append(_box(s))
    return Item("bed", boxes)


def _sofa(rng, inner: Rect) -> Item | None:
    """A sofa against a wall and a coffee table (legs) in front of it."""
    side = int(rng.integers(4))
    rect = _wall_rect(rng, inner, _lat(rng.uniform(1.8, 2.4)), 0.9, side, 0.2)
    if rect is None:
        return None
    x, y = _front(rect, side, 0.75 + 0.3)
    sx, sy = (1.0, 0.6) if side < 2 else (0.6, 1.0)
    return Item("sofa", [_box(rect)], _legs(x, y, sx, sy, 0.0, 0.03), tol=0.15)


def _armchair(rng, inner: Rect) -> Item | None:
    x0, y0, x1, y1 = inner
    if x1 - x0 < 2.6 or y1 - y0 < 2.6:
        return None
    cx, cy = rng.uniform(x0 + 0.9, x1 - 0.9), rng.uniform(y0 + 0.9, y1 - 0.9)
    return Item("armchair", [_rbox(cx, cy, 0.8, 0.8, rng.uniform(-0.6, 0.6))])


def _counter(rng, inner: Rect) -> Item | None:
    """Kitchen counters along two walls from a corner (an L)."""
    x0, y0, x1, y1 = inner
    corner = int(rng.integers(4))
    cx, sxn = (x0, 1) if corner in (0, 2) else (x1, -1)
    cy, syn = (y0, 1) if corner in (0, 1) else (y1, -1)
    la = min(_lat(rng.uniform(1.8, 4.0)), _lat_floor(x1 - x0 - 1.0))
    lb = min(_lat(rng.uniform(1.2, 3.0)), _lat_floor(y1 - y0 - 1.6))
    if la < 1.2 or lb < 0.6:
        return None
    a = (cx, cy, cx + sxn * la, cy + syn * 0.6)
    b = (cx, cy + syn * 0.6, cx + sxn * 0.6, cy + syn * (0.6 + lb))
    norm = [(min(r[0], r[2]), min(r[1], r[3]), max(r[0], r[2]), max(r[1], r[3])) for r in (a, b)]
    return Item("counter", [_box(r) for r in norm])


_cabinet = _against("cabinet", (0.8, 1.2), (0.4, 0.5), 0.6)
_shelf_unit = _against("shelf", (0.8, 2.0), (0.35, 0.5), 0.5)
_wardrobe = _against("wardrobe", (1.0, 2.4), (0.6, 0.6), 0.7)
_tv_unit = _against("cabinet", (1.2, 1.8), (0.45, 0.45), 0.3)
_fridge = _against("fridge", (0.7, 0.7), (0.7, 0.7), 0.7)
_washer = _against("washer", (0.6, 0.6), (0.6, 0.6), 0.7)
_bathtub = _against("bathtub", (1.7, 1.7), (0.75, 0.75), 1.0)
_sink = _against("sink", (0.5, 0.6), (0.45, 0.45), 0.3)
_toilet = _against("toilet", (0.4, 0.4), (0.65, 0.65), 0.3)


def _room_recipe(rng, label: str, area: float) -> list[tuple[Callable, int]]:
    """(maker, how many) for a room of ``label`` and interior ``area`` [m^2]."""
    coin = lambda p: int(rng.random() < p)  # noqa: E731
    recipes = {
        "office": [(_desk, min(max(int(area / 7), 1), 4)), (_cabinet, int(rng.integers(0, 3))),
                   (_plant, coin(0.3))],
        "meeting": [(_meeting_table, 1), (_cabinet, coin(0.5)), (_plant, 1)],
        "open-plan": [(_desk_island, int(area / 10)), (_desk, int(area / 20)), (_cabinet, 2),
                      (_plant, 1)],
        "storage": [(_shelf_unit, int(area / 3) + 1)],
        "bedroom": [(_bed, 1), (_wardrobe, 1), (_desk, coin(0.3)), (_shelf_unit, coin(0.4))],
        "living": [(_sofa, 1), (_armchair, int(rng.integers(1, 3))), (_tv_unit, 1),
                   (_shelf_unit, 1), (_plant, 1), (_dining_table, int(area > 25))],
        "kitchen": [(_counter, 1), (_fridge, 1), (_dining_table, int(area >= 9))],
        "dining": [(_dining_table, 1), (_cabinet, 1)],
        "bathroom": [(_bathtub, 1), (_sink, 1), (_toilet, 1)],
        "wc": [(_toilet, 1), (_sink, 1)],
        "closet": [(_shelf_unit, 2)],
        "laundry": [(_washer, 1), (_shelf_unit, 1)],
        "study": [(_desk, 1), (_shelf_unit, 2), (_armchair, 1)],
    }
    return recipes.get(label, [])


def _furnish_rooms(rng, plan: _Plan, placer: _Placer) -> None:
    for s in plan.spaces:
        inner = _inner(s.rect)
        if s.kind == "room":
            for make, count in _room_recipe(rng, s.label, _area(inner)):
                for _ in range(count):
                    placer.attempt(lambda m=make, inner=inner: m(rng, inner))
        elif s.kind == "corridor" and min(inner[2] - inner[0], inner[3] - inner[1]) >= 1.9 \
                and rng.random() < 0.4:  # a cabinet or printer against a corridor wall
            long_x = inner[2] - inner[0] >= inner[3] - inner[1]
            sides = (0, 1) if long_x else (2, 3)
            placer.attempt(lambda inner=inner, sides=sides: _corridor_cabinet(rng, inner, sides))


def _corridor_cabinet(rng, inner: Rect, sides: tuple[int, int]) -> Item | None:
    rect = _wall_rect(rng, inner, _lat(rng.uniform(0.6, 1.2)), _lat(rng.uniform(0.4, 0.5)),
                      int(rng.choice(sides)), 0.0)
    return None if rect is None else Item("cabinet", [_box(rect)])


# --- warehouse shelving and pallets, cluttered obstacles


def _shelf_rows(rng, placer: _Placer, region: Rect, blocked: list[Rect]) -> list[float]:
    """Rows of shelving (one box per stretch between cross aisles) across ``region``;
    returns the aisle widths between rows."""
    x0, y0, x1, y1 = region
    along_x = (x1 - x0 >= y1 - y0) == bool(rng.random() < 0.75)
    if not along_x:  # work with rows along x, turn back at the end
        x0, y0, x1, y1 = _transpose(region)
        blocked = [_transpose(r) for r in blocked]
    depth = _lat(rng.uniform(0.9, 1.1)) if rng.random() < 0.4 else _lat(rng.uniform(1.8, 2.2))
    aisle0 = rng.uniform(1.0, 3.0)
    seg, cross = _lat(rng.uniform(6.0, 16.0)), _lat(rng.uniform(1.5, 3.0))
    spans, u = [], x0
    while u < x1 - 1.5:
        spans.append((u, min(u + seg, x1)))
        u = _q(u + seg + cross)
    widths: list[float] = []
    v = y0
    while v + depth <= y1 + 1e-9:
        cut = [(r[0], r[2]) for r in blocked if r[1] < v + depth and r[3] > v]
        for p, q in _subtract(spans, cut):
            p, q = _lat(p), _lat(q)
            if q - p >= 1.5:
                rect = (p, v, q, _q(v + depth))
                placer.place(Item("shelf", [_box(rect if along_x else _transpose(rect))]))
        aisle = min(max(_lat(aisle0 + rng.uniform(-0.2, 0.2)), 1.0), 3.0)
        if v + 2 * depth + aisle <= y1 + 1e-9:
            widths.append(aisle)
        v = _q(v + depth + aisle)
    return widths


def _pallet_stack(rng, zone: Rect) -> Item | None:
    """One to three pallets in a row, now and then a little askew."""
    k = int(rng.integers(1, 4))
    pw, pl = (1.2, 0.8) if rng.random() < 0.5 else (0.8, 1.2)
    total = k * pw + (k - 1) * 0.1
    angle = (0.0 if rng.random() < 0.7 else rng.uniform(-0.25, 0.25)) \
        + (0.0 if rng.random() < 0.5 else math.pi / 2)
    ext = math.hypot(total, pl) / 2 + 0.05
    x0, y0, x1, y1 = zone
    if x1 - x0 < 2 * ext or y1 - y0 < 2 * ext:
        return None
    cx, cy = _between(rng, x0 + ext, x1 - ext), _between(rng, y0 + ext, y1 - ext)
    dx, dy = math.cos(angle), math.sin(angle)
    boxes = [_rbox(cx + dx * t, cy + dy * t, pw, pl, angle)
             for t in (-total / 2 + pw / 2 + i * (pw + 0.1) for i in range(k))]
    return Item("pallet", boxes, tol=0.1)


def _furnish_warehouse(rng, plan: _Plan, placer: _Placer) -> list[float]:
    """Shelving rows in every hall (away from the office corner and the loading area),
    pallets in the loading area. Returns the aisle widths."""
    blocked = [_grow(s.rect, 1.5) for s in plan.spaces if s.kind == "room"]
    blocked += [_grow(z, 0.3) for _n, z in plan.zones]
    aisles: list[float] = []
    for g in sorted({s.group for s in plan.spaces if s.kind == "hall"}):
        rects = [s.rect for s in plan.spaces if s.group == g]
        hall = (min(r[0] for r in rects), min(r[1] for r in rects), max(r[2] for r in rects),
                max(r[3] for r in rects))
        aisles += _shelf_rows(rng, placer, _grow(_inner(hall), -_lat(rng.uniform(1.2, 2.0))),
                              blocked)
    for _n, zone in plan.zones:
        for _ in range(int(_area(zone) / 8) + 1):
            placer.attempt(lambda zone=zone: _pallet_stack(rng, zone), 4)
    return aisles


def _obstacle(rng, inner: Rect) -> Item | None:
    """A post, barrel, crate or bigger block, boxes mostly at a random angle."""
    if rng.random() < 0.3:
        r = rng.uniform(0.05, 0.15) if rng.random() < 0.5 else rng.uniform(0.2, 0.6)
        ext, box = r, None
    else:
        lo, hi = ((0.2, 0.5), (0.5, 1.2), (1.2, 2.5))[int(rng.choice(3, p=[0.4, 0.4, 0.2]))]
        sx, sy = rng.uniform(lo, hi), rng.uniform(lo, min(hi, 1.5))
        angle = 0.0 if rng.random() < 0.3 else rng.uniform(0.0, math.pi)
        ext, box = math.hypot(sx, sy) / 2, (sx, sy, angle)
    x0, y0, x1, y1 = inner
    if x1 - x0 < 2 * ext + 0.1 or y1 - y0 < 2 * ext + 0.1:
        return None
    cx, cy = _between(rng, x0 + ext, x1 - ext), _between(rng, y0 + ext, y1 - ext)
    if box is None:
        return Item("post" if r < 0.16 else "barrel", [], [((_q(cx), _q(cy)), _q(r))])
    return Item("block", [_rbox(cx, cy, *box)])


def _gate(rng, inner: Rect) -> Item | None:
    """Two blocks in line with a narrow passage (0.65-1.0 m) between them."""
    theta = rng.uniform(0.0, math.pi)
    g = _q(rng.uniform(0.65, 1.0))
    l1, l2 = rng.uniform(0.8, 2.0, 2)
    t = rng.uniform(0.2, 0.5)
    ext = g / 2 + max(l1, l2) + 0.3
    x0, y0, x1, y1 = inner
    if x1 - x0 < 2 * ext or y1 - y0 < 2 * ext:
        return None
    cx, cy = _between(rng, x0 + ext, x1 - ext), _between(rng, y0 + ext, y1 - ext)
    dx, dy = math.cos(theta), math.sin(theta)
    a, b = g / 2 + l1 / 2, g / 2 + l2 / 2
    return Item("gate", [_rbox(cx - dx * a, cy - dy * a, l1, t, theta),
                         _rbox(cx + dx * b, cy + dy * b, l2, t, theta)], gap=g)


def _furnish_cluttered(rng, plan: _Plan, placer: _Placer) -> None:
    for s in plan.spaces:
        inner = _inner(s.rect)
        area = _area(inner)
        for _ in range(max(1, int(area / 45))):
            placer.attempt(lambda inner=inner: _gate(rng, inner), 8)
        target, placed = area * rng.uniform(0.12, 0.22), 0.0
        for _ in range(int(area * 1.2)):
            if placed >= target:
                break
            item = _obstacle(rng, inner)
            if placer.place(item):
                placed += item.area


# --------------------------------------------------------------------------------------------
# generation


_LAYOUTS = {"office": _office_layout, "house": _house_layout, "warehouse": _warehouse_layout,
            "cluttered": _cluttered_layout}
_EXTRA_DOORS = {"office": 0.12, "house": 0.08, "warehouse": 0.3, "cluttered": 0.6}
_START_IN = {"office": ("corridor",), "house": ("hallway", "living"), "warehouse": ("loading",),
             "cluttered": ("zone",)}


@dataclass
class Generated:
    """A generated world and what the generator put in it."""

    style: str
    seed: int
    size: tuple[float, float]
    world: World
    spaces: list[Space]
    doors: list[Door]
    items: list[Item]
    zones: list[tuple[str, Rect]]
    aisles: list[float]
    reach: Reach

    @property
    def name(self) -> str:
        return world_name(self.style, self.seed, self.size)

    @property
    def meta(self) -> dict:
        """What was placed, as plain data (JSON-able): rooms, doors and their clear widths,
        aisles, narrow passages, zones, furniture counts, shape counts, the reach check."""
        sp = self.spaces
        label = lambda k: sp[k].label or sp[k].kind  # noqa: E731
        return {
            "name": self.name, "style": self.style, "seed": self.seed, "size": list(self.size),
            "start": list(self.world.robot_pose),
            "rooms": [{"kind": s.kind, "label": s.label, "rect": list(s.rect)} for s in sp],
            "doors": [{"center": list(d.center), "width": d.width, "kind": d.kind,
                       "between": [label(d.a), label(d.b)]} for d in self.doors],
            "aisles": list(self.aisles),
            "passages": [{"center": [_q((it.boxes[0][0][0] + it.boxes[1][0][0]) / 2),
                                     _q((it.boxes[0][0][1] + it.boxes[1][0][1]) / 2)],
                          "width": it.gap} for it in self.items if it.kind == "gate"],
            "zones": [{"kind": n, "rect": list(r)} for n, r in self.zones],
            "items": dict(sorted(Counter(it.kind for it in self.items).items())),
            "shapes": {"walls": len(self.world.segments), "boxes": len(self.world.boxes),
                       "circles": len(self.world.circles)},
            "reach": self.reach.summary(),
        }


def _assemble(plan: _Plan, items: list[Item], pose, name: str = "", description: str = ""
              ) -> World:
    return World(name=name or plan.style, size=plan.size, robot_pose=tuple(pose),
                 segments=list(plan.walls), wall_thickness=WALL_R, description=description,
                 boxes=[b for it in items for b in it.boxes],
                 circles=[c for it in items for c in it.circles])


def _repair(plan: _Plan, items: list[Item]) -> tuple[list[Item], np.ndarray]:
    """Drop the items around any unreached pocket until the world passes the check (the
    placer's local test misses a room cut in two by several pieces together)."""
    reach = None
    for _ in range(8):
        solid, _, _ = rasterize(_assemble(plan, items, (0.0, 0.0, 0.0)), RES)
        reach = reachability(solid, RES)
        if reach.fraction >= MIN_REACHED and reach.largest_pocket <= BUILD_POCKET:
            return items, solid
        n, lab, stats, _ = cv2.connectedComponentsWithStats(reach.unreached.astype(np.uint8),
                                                            connectivity=8)
        area = stats[:, cv2.CC_STAT_AREA] * RES * RES
        limit = BUILD_POCKET if area[1:].max() > BUILD_POCKET else 0.05
        big = np.isin(lab, np.flatnonzero(area > limit)) & (lab > 0)
        near = distance_transform((~big).astype(np.uint8)) * RES <= 0.4
        keep = [it for it in items
                if not near[it.window[0]:it.window[1], it.window[2]:it.window[3]].any()]
        if len(keep) == len(items):
            break
        items = keep
    raise GenerateError(f"internal: {plan.style} world leaves {reach.largest_pocket:.2f} m^2 "
                        f"unreachable ({reach.fraction:.3f} reached)")


def _pick_start(rng, plan: _Plan, world: World, solid: np.ndarray) -> tuple[float, float, float]:
    """A start in the reachable space, in a corridor / hallway / hall where the style has
    one, with at least START_CLEARANCE (+5 cm) to every solid."""
    dt, comp, _cov, _body = _coverage(solid, RES, REACH_CLEARANCE, _component_at(None))
    good = comp & (dt >= START_CLEARANCE + 0.15)
    pref = np.zeros_like(good)
    rects = [s.rect for s in plan.spaces if {s.kind, s.label} & set(_START_IN[plan.style])]
    rects += [_grow(z, WALL_R) for n, z in plan.zones if n in _START_IN[plan.style]]
    for x0, y0, x1, y1 in rects:
        pref[int(y0 / RES):int(math.ceil(y1 / RES)), int(x0 / RES):int(math.ceil(x1 / RES))] = True
    for mask in (good & pref, good):
        cand = np.flatnonzero(mask)
        for k in (rng.integers(0, len(cand), 40) if len(cand) else []):
            row, col = divmod(int(cand[k]), solid.shape[1])
            x, y = (col + 0.5) * RES, (row + 0.5) * RES
            if clearance(world, x, y) >= START_CLEARANCE + 0.05:
                return _q(x), _q(y), _q(round(rng.uniform(-math.pi, math.pi), 3))
    row, col = divmod(int(np.argmax(np.where(comp, dt, -1.0))), solid.shape[1])
    return _q((col + 0.5) * RES), _q((row + 0.5) * RES), 0.0


def generate(style: str, seed: int, size: Sequence[float] | None = None) -> Generated:
    """Generate a world of ``style`` (see STYLES) from ``seed`` at ``size`` [m] (W, H; default
    DEFAULT_SIZES[style]). Deterministic: the same arguments give the same world."""
    size = check_arguments(style, seed, size)
    rng = _rng(style, seed, size, 0)
    plan = _LAYOUTS[style](rng, size)
    _finish_plan(rng, plan, _EXTRA_DOORS[style])
    placer = _Placer(plan)
    _furnish_rooms(rng, plan, placer)
    aisles: list[float] = []
    if style == "warehouse":
        aisles = _furnish_warehouse(rng, plan, placer)
    elif style == "cluttered":
        _furnish_cluttered(rng, plan, placer)
    items, solid = _repair(plan, placer.items)
    pose = _pick_start(rng, plan, _assemble(plan, items, (0.0, 0.0, 0.0)), solid)
    reach = reachability(solid, RES, (0.0, 0.0), pose[:2])
    if not reach.ok or reach.start_clearance < START_CLEARANCE:
        raise GenerateError(f"internal: {style} seed {seed} start {pose} reaches only "
                            f"{reach.fraction:.3f} of the free space")
    gen = Generated(style, int(seed), size, World("", size, pose), plan.spaces, plan.doors,
                    items, plan.zones, aisles, reach)
    gen.world = _assemble(plan, items, pose, gen.name, _describe(gen))
    return gen


def _describe(gen: Generated) -> str:
    rooms = sum(1 for s in gen.spaces if s.kind == "room")
    widths = [d.width for d in gen.doors if d.kind == "door"] or [d.width for d in gen.doors]
    doors = f"{len(gen.doors)} doors {min(widths):.2f}-{max(widths):.2f} m" if widths else "no doors"
    return (f"generated {gen.style} {gen.size[0]:g} x {gen.size[1]:g} m, seed {gen.seed}: "
            f"{rooms} rooms, {doors}, {len(gen.items)} furniture pieces")


# --------------------------------------------------------------------------------------------
# SLAM maps: the clean world rasterized, then degraded like a map a robot made

_FREE, _OCC, _UNK = 0, 100, -1  # int8 map values (common.grid / map_server semantics)
_NOISE_KEYS = ("ragged_added", "ragged_removed", "specks", "free_specks", "missing",
               "leak_rays", "leak_pixels", "reverted")


@dataclass
class SlamMap:
    """An int8 occupancy grid (row 0 = min y: 0 free, 100 occupied, -1 unknown) covering the
    world and a MAP_MARGIN border, its geometry, and counts of what the noise did."""

    grid: np.ndarray
    geom: GridGeometry
    level: int
    stats: dict[str, int]

    @property
    def margin(self) -> int:
        """[cells] border around the world."""
        return int(round(MAP_MARGIN / RES))


def _clean_grid(solid: np.ndarray) -> np.ndarray:
    """Free where free; solid the laser can see (within 3 cells of free space) occupied; the
    rest (outside the building, inside furniture) unknown, as in any SLAM map."""
    free = ~solid
    seen = cv2.dilate(free.astype(np.uint8), np.ones((7, 7), np.uint8)).astype(bool)
    return np.where(free, _FREE, np.where(seen, _OCC, _UNK)).astype(np.int8)


def _protection(solid: np.ndarray, start_rc: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Where noise may not add solid cells: around narrow places of the reachable space
    (doors, gaps between furniture; for wall noise where the clear width is under 0.9 m, for
    specks under 1.5 m) and around the start."""
    dt, comp, _cov, _body = _coverage(solid, RES, REACH_CLEARANCE, _component_at(start_rc))
    ridge = comp & (dt >= cv2.dilate(dt, _K3) - 1e-4)  # the middle of a passage
    masks = []
    for width, reach in ((0.45, 0.55), (0.75, 0.85)):
        narrow = ridge & (dt < width)
        near = distance_transform((~narrow).astype(np.uint8)) * RES <= reach
        masks.append(near)
    rows, cols = np.ogrid[:solid.shape[0], :solid.shape[1]]
    around = (rows - start_rc[0]) ** 2 + (cols - start_rc[1]) ** 2 <= (0.8 / RES) ** 2
    return masks[0] | around, masks[1] | around


def _ragged(rng, grid: np.ndarray, protect: np.ndarray, level: int, stats: dict) -> None:
    """Wall surfaces wobble by a pixel or two: a smooth random field pushes them out (into
    free space, not where protected) or in (only where the solid behind is thick)."""
    field_ = cv2.GaussianBlur(rng.standard_normal(grid.shape).astype(np.float32), (0, 0), 1.2)
    field_ /= max(float(field_.std()), 1e-6)
    t = NormalDist().inv_cdf(1.0 - 0.07 * level)
    free = grid == _FREE
    solid_u8 = (~free).astype(np.uint8)
    edge1 = free & cv2.dilate(solid_u8, _K3).astype(bool)
    add1 = edge1 & (field_ > t) & ~protect
    edge2 = free & ~edge1 & cv2.dilate(add1.astype(np.uint8), _K3).astype(bool)
    add2 = edge2 & (field_ > t + 0.5) & ~protect
    thick = cv2.dilate(cv2.erode(solid_u8, _K3), _K3).astype(bool)
    remove = (grid == _OCC) & cv2.dilate(free.astype(np.uint8), _K3).astype(bool) & thick \
        & (field_ < -t)
    grid[add1 | add2] = _OCC
    grid[remove] = _FREE
    stats["ragged_added"] += int((add1 | add2).sum())
    stats["ragged_removed"] += int(remove.sum())


def _pick(rng, mask: np.ndarray, n: int) -> np.ndarray:
    """Up to ``n`` random flat indices of True cells (repeats possible)."""
    cand = np.flatnonzero(mask)
    return cand[rng.integers(0, len(cand), n)] if len(cand) and n > 0 else cand[:0]


def _speckle(rng, grid: np.ndarray, protect: np.ndarray, level: int, stats: dict) -> None:
    """Occupied specks in free space (people walking by, sensor noise), a few two cells
    big, and free specks inside walls."""
    free = grid == _FREE
    specks = _pick(rng, free & ~protect, int(rng.poisson(0.05 * level * free.sum() * RES * RES)))
    grid.flat[specks] = _OCC
    w = grid.shape[1]
    pairs = specks[rng.random(len(specks)) < 0.3]
    pairs = pairs + np.where(rng.random(len(pairs)) < 0.5, 1, w)
    pairs = pairs[(pairs < grid.size) & free.flat[np.minimum(pairs, grid.size - 1)]
                  & ~protect.flat[np.minimum(pairs, grid.size - 1)]]
    grid.flat[pairs] = _OCC
    stats["specks"] += len(np.unique(specks))
    inside = (grid == _OCC) & ~cv2.dilate((grid == _FREE).astype(np.uint8), _K3).astype(bool)
    holes = _pick(rng, inside, int(rng.poisson(0.002 * level * inside.sum())))
    grid.flat[holes] = _FREE
    stats["free_specks"] += len(np.unique(holes))


def _missing_walls(rng, grid: np.ndarray, level: int, stats: dict) -> None:
    """Bits of wall the laser never hit: occupied cells along a surface turned unknown."""
    surface = (grid == _OCC) & cv2.dilate((grid == _FREE).astype(np.uint8), _K3).astype(bool)
    n = int(rng.poisson(0.03 * level * surface.sum() * RES))
    h, w = grid.shape
    for k in _pick(rng, surface, n).tolist():
        r, c = divmod(k, w)
        d = int(rng.integers(1, 4))
        win = grid[max(r - d, 0):r + d + 1, max(c - d, 0):c + d + 1]
        win[win == _OCC] = _UNK
    stats["missing"] += n


def _ray_cells(x0: float, y0: float, x1: float, y1: float, shape: tuple[int, int]) -> np.ndarray:
    """Grid cells (rows, cols) along a straight line [m, world frame], in order, no repeats."""
    n = max(2, int(math.hypot(x1 - x0, y1 - y0) / (RES / 3)))
    t = np.linspace(0.0, 1.0, n)
    cols = np.floor((x0 + (x1 - x0) * t + MAP_MARGIN) / RES).astype(int)
    rows = np.floor((y0 + (y1 - y0) * t + MAP_MARGIN) / RES).astype(int)
    keep = np.ones(n, bool)
    keep[1:] = (np.diff(rows) != 0) | (np.diff(cols) != 0)
    cells = np.stack((rows[keep], cols[keep]), axis=1)
    inside = ((cells[:, 0] > 0) & (cells[:, 0] < shape[0] - 1) & (cells[:, 1] > 0)
              & (cells[:, 1] < shape[1] - 1))
    return cells[inside]


def _leak_ray(rng, grid: np.ndarray, size: tuple[float, float]) -> int:
    """One ray from inside a room through the outer wall into the unknown outside, cleared
    to free (1-2 cells wide), sometimes ending on an occupied cell. 0 if the first thing the
    ray meets from its start is not the outer wall (furniture, an inner wall)."""
    W, H = size
    side = int(rng.choice(4, p=np.array([W, W, H, H]) / (2 * (W + H))))
    t = rng.uniform(0.5, (W if side < 2 else H) - 0.5)
    nx, ny = ((0.0, -1.0), (0.0, 1.0), (-1.0, 0.0), (1.0, 0.0))[side]
    qx, qy = ((t, 0.0), (t, H), (0.0, t), (W, t))[side]
    a = rng.uniform(-0.9, 0.9)
    dx, dy = nx * math.cos(a) - ny * math.sin(a), nx * math.sin(a) + ny * math.cos(a)
    d_in, d_out = rng.uniform(0.5, 4.0), rng.uniform(0.5, MAP_MARGIN - 0.2) / math.cos(a)
    cells = _ray_cells(qx - dx * d_in, qy - dy * d_in, qx + dx * d_out, qy + dy * d_out,
                       grid.shape)
    vals = grid[cells[:, 0], cells[:, 1]]
    if len(cells) < 4 or vals[0] != _FREE or (vals == _FREE).all():
        return 0
    k = int(np.argmax(vals != _FREE))
    hx, hy = (cells[k, 1] + 0.5) * RES - MAP_MARGIN, (cells[k, 0] + 0.5) * RES - MAP_MARGIN
    if min(hx, W - hx, hy, H - hy) > 0.4:  # not the outer wall
        return 0
    ray = cells[k:]
    if rng.random() < 0.35:  # two cells wide
        step = (1, 0) if abs(dx) > abs(dy) else (0, 1)
        wide = ray + step
        wide = wide[(wide[:, 0] < grid.shape[0] - 1) & (wide[:, 1] < grid.shape[1] - 1)]
        ray = np.concatenate((ray, wide))
    changed = int((grid[ray[:, 0], ray[:, 1]] != _FREE).sum())
    grid[ray[:, 0], ray[:, 1]] = _FREE
    if rng.random() < 0.5:  # the ray hit something out there
        r, c = cells[-1]
        grid[r, c] = _OCC
    return changed


def _leak_rays(rng, grid: np.ndarray, size: tuple[float, float], level: int,
               stats: dict) -> None:
    n = int(rng.poisson(level * 2 * (size[0] + size[1]) / 12.0)) + level
    for _ in range(n):
        for _try in range(6):
            changed = _leak_ray(rng, grid, size)
            if changed:
                stats["leak_rays"] += 1
                stats["leak_pixels"] += changed
                break


def _noise_repair(grid: np.ndarray, clean_solid: np.ndarray, start: Point, stats: dict
                  ) -> Reach:
    """Undo noise that cut the robot off from anything: solid cells the noise added near an
    unreached pocket become free again (all of them, as a last resort)."""
    added = (grid != _FREE) & ~clean_solid
    origin = (-MAP_MARGIN, -MAP_MARGIN)
    for _ in range(4):
        reach = reachability(grid != _FREE, RES, origin, start)
        if reach.ok:
            return reach
        n, lab, st, _ = cv2.connectedComponentsWithStats(reach.unreached.astype(np.uint8),
                                                         connectivity=8)
        big = np.isin(lab, np.flatnonzero(st[:, cv2.CC_STAT_AREA] * RES * RES > 0.05)) & (lab > 0)
        fix = added & (distance_transform((~big).astype(np.uint8)) * RES <= 0.6)
        if not fix.any():
            break
        grid[fix] = _FREE
        added &= ~fix
        stats["reverted"] += int(fix.sum())
    grid[added] = _FREE
    stats["reverted"] += int(added.sum())
    return reachability(grid != _FREE, RES, origin, start)


def slam_map(gen: Generated, level: int) -> SlamMap:
    """The world as a SLAM map at noise ``level`` (0: clean raster, up to MAX_NOISE): ragged
    walls, specks, missing wall cells and leak rays, never cutting off reachable space."""
    check_arguments(gen.style, gen.seed, gen.size, level)
    solid, _, _ = rasterize(gen.world, RES)
    m = int(round(MAP_MARGIN / RES))
    solid = np.pad(solid, m, constant_values=True)
    grid = _clean_grid(solid)
    stats = dict.fromkeys(_NOISE_KEYS, 0)
    x, y, _th = gen.world.robot_pose
    if level > 0:
        rng = _rng(gen.style, gen.seed, gen.size, 1 + level)
        start_rc = (int((y + MAP_MARGIN) / RES), int((x + MAP_MARGIN) / RES))
        protect_walls, protect_specks = _protection(solid, start_rc)
        _ragged(rng, grid, protect_walls, level, stats)
        _speckle(rng, grid, protect_specks, level, stats)
        _missing_walls(rng, grid, level, stats)
        _leak_rays(rng, grid, gen.size, level, stats)
        reach = _noise_repair(grid, solid, (x, y), stats)
        if not reach.ok or reach.start_clearance < START_CLEARANCE:
            raise GenerateError(f"internal: {gen.name} noise {level} reaches only "
                                f"{reach.fraction:.3f} of the free space")
    h, w = grid.shape
    return SlamMap(grid, GridGeometry(RES, -MAP_MARGIN, -MAP_MARGIN, w, h), level, stats)


# --------------------------------------------------------------------------------------------
# files


def _num(v: float) -> str:
    return repr(_q(v))


def _pt(p: Sequence[float]) -> str:
    return "[" + ", ".join(_num(v) for v in p) + "]"


def _toml_str(text: str) -> str:
    return '"' + text.replace("\\", "\\\\").replace('"', '\\"') + '"'


def world_toml(world: World, comment: str = "") -> str:
    """A world as TOML text (sim/world.py's format, shapes as inline tables, one a line)."""
    out = [f"# {line}" for line in comment.splitlines()]
    out += [f"name = {_toml_str(world.name)}", f"description = {_toml_str(world.description)}",
            f"size = {_pt(world.size)}", f"wall_thickness = {_num(world.wall_thickness)}", "",
            "walls = ["]
    out += [f"  {{points = [{_pt(a)}, {_pt(b)}]}}," for a, b in world.segments]
    out += ["]", "boxes = ["]
    out += [f"  {{center = {_pt(c)}, size = {_pt(s)}, angle = {_num(a)}}},"
            for c, s, a in world.boxes]
    out += ["]", "circles = ["]
    out += [f"  {{center = {_pt(c)}, radius = {_num(r)}}}," for c, r in world.circles]
    out += ["]", "", "[robot]", f"pose = {_pt(world.robot_pose)}", ""]
    return "\n".join(out)


def _command(gen: Generated, slam_noise: int | None) -> str:
    cmd = (f"topoexplore worlds generate --style {gen.style} --seed {gen.seed} "
           f"--size {gen.size[0]:g} {gen.size[1]:g}")
    return cmd if slam_noise is None else f"{cmd} --slam-noise {slam_noise}"


def write_generated(gen: Generated, out_dir: str | Path, slam_noise: int | None = None) -> Path:
    """Write ``gen`` into ``out_dir`` (created) and return the world file to load.

    Without ``slam_noise``: ``<name>.toml``, an ordinary world. With a level (0..MAX_NOISE):
    the SLAM-like map ``<name>-n<level>.yaml`` + ``.pgm`` (ROS map_server, trinary, 0.05 m
    per pixel, origin at (-MAP_MARGIN, -MAP_MARGIN) so the world frame is unchanged) and a
    ``<name>-n<level>.toml`` wrapper (``map = ...`` and the generated start pose), which is
    the file returned. Problems raise :class:`GenerateError` (one line)."""
    check_arguments(gen.style, gen.seed, gen.size, slam_noise)
    out = Path(out_dir)
    name = world_name(gen.style, gen.seed, gen.size, slam_noise)
    path = out / f"{name}.toml"
    try:
        if out.exists() and not out.is_dir():
            raise GenerateError(f"output {out} exists and is not a directory")
        out.mkdir(parents=True, exist_ok=True)
        if slam_noise is None:
            text = world_toml(gen.world, f"generated by: {_command(gen, None)}")
        else:
            sm = slam_map(gen, slam_noise)
            yaml_path, _pgm = write_map_server(out / f"{name}.yaml", sm.grid, sm.geom)
            text = _map_toml(gen, sm, name, yaml_path.name)
        atomic_write(path, text.encode("utf-8"))  # a bench reading it meanwhile sees old or new
    except MapIOError as exc:
        raise GenerateError(str(exc)) from None
    except OSError as exc:
        raise GenerateError(f"cannot write {path}: {exc.strerror or exc}") from None
    return path


def _map_toml(gen: Generated, sm: SlamMap, name: str, yaml_name: str) -> str:
    noise = ", ".join(f"{k} {v}" for k, v in sm.stats.items())
    lines = [f"# generated by: {_command(gen, sm.level)}",
             f"# SLAM-like map {yaml_name} (+ .pgm), 0.05 m/pixel; noise: {noise}",
             f"name = {_toml_str(name)}",
             f"description = {_toml_str(f'{gen.world.description}; SLAM noise {sm.level}')}",
             f"map = {_toml_str(yaml_name)}", "", "[robot]",
             f"pose = {_pt(gen.world.robot_pose)}", ""]
    return "\n".join(lines)


def generate_corpus(out_dir: str | Path, seeds: Iterable[int] = (0, 1, 2),
                    styles: Iterable[str] = STYLES,
                    noise_levels: Iterable[int | None] = (None, 1, 3),
                    sizes: Iterable[Sequence[float] | None] = (None, (60.0, 60.0)),
                    ) -> list[tuple[str, Path]]:
    """Write every combination into ``out_dir`` and return [(name, world file)], ordered by
    style, size, seed, noise level (None: the TOML world; a level: the SLAM map's TOML
    wrapper). Each (style, size, seed) is generated once and written at every level."""
    seeds, styles, levels, sizes = list(seeds), list(styles), list(noise_levels), list(sizes)
    for style in styles:  # every argument checked before anything is written
        for size in sizes:
            for level in levels:
                for seed in seeds:
                    check_arguments(style, seed, size, level)
    out: list[tuple[str, Path]] = []
    for style in styles:
        for size in sizes:
            for seed in seeds:
                gen = generate(style, seed, size)
                for level in levels:
                    path = write_generated(gen, out_dir, level)
                    out.append((path.stem, path))
    return out
