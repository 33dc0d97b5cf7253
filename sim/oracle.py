"""A short tour of viewpoints on the true map: how short an exploration path could be.

The reference the strategies' paths are divided by (``topoexplore bench oracle``). It knows
the map before it starts, so no strategy can match it; it is not a strategy. Pure: truth in,
figures out.

1. **Viewpoints**: the reachable robot centre positions (:func:`world.truth_robot_positions`)
   on a lattice, and the start; the whole plan is made on lattices of 0.1, 0.2, 0.3 and 0.5 m
   (each at most MAX_CANDIDATES points) and the shortest tour kept.
2. **What a viewpoint sees**: the cells of the coverage set (:func:`world.truth_mappable`)
   within ``laser_range`` [m] in Bresenham line of sight through free cells, all round: the
   robot turns in place at no path cost, so its 180 deg laser sees every bearing.
3. **Choosing viewpoints**, two ways, each until ``fraction`` of the coverage set is seen:
   greedy set cover (lazy gains: the start's view first, then the viewpoint that sees most of
   what is still unseen; within ln(n) + 1 of the fewest viewpoints in the worst case), and
   one after the other from where the robot is (most unseen cells per cell of path plus an
   overhead of 5, 20 or 100 cells, what the path sees counted: :meth:`_Plan.sequential`).
4. **Open tour** from the start through the chosen viewpoints: shortest paths between them
   over the reachable positions (8-connected, octile lengths: up to 8 % over the Euclidean
   length of a straight stretch at an angle), order by nearest neighbour, then 2-opt and
   or-opt moves until none shortens it (:func:`open_tour`; against every order on 200 small
   instances in ``tests/test_oracle.py``: 196 optimal, the worst 7 % longer).
5. **Seeing on the way** (:class:`_Plan`): the robot also sees from its paths (a sample every
   lattice step, all round: optimistic). Viewpoints the rest of the tour covers for are
   dropped (the least useful first); each one left moves to the candidate that alone sees
   what it alone sees at the least detour ("pull": greedy cover takes the viewpoint that sees
   most, often deep in a room or a corridor); the rest is toured again, and viewpoints of
   the cover are added back while the new order sees less than ``fraction``.

Of all these tours (4 lattices x 4 choices), the shortest is kept. No step is optimal, so it
is a *short* tour, not the shortest: against every set of up to 3 lattice viewpoints in every
order (:func:`exhaustive_tour`) it is equal on a three-room comb, junction and dead-end
(``tests/test_oracle.py``), and 1.34 x longer on small-house at a 1 m lattice (31.0 against
23.2 m). A strategy's path over it says how far the strategy is from what knowing the map
buys, an upper estimate of the gap to the true optimum. Seeing all round from every point of the path is optimistic, and viewpoints
and lines of sight are cells of 0.1 m, so on a tiny map (lse_arena: a 2.1 m tour) a strategy
can come out a few per cent under it.
"""

from __future__ import annotations

import heapq
import math
from dataclasses import dataclass

import numpy as np
from numba import njit
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

from topoexplore.sim.rays import ray_table, square_border
from topoexplore.sim.world import (
    LASER_RANGE,
    ROBOT_RADIUS,
    World,
    rasterize,
    truth_mappable,
    truth_robot_positions,
)

RESOLUTION = 0.1  # [m] the raster of the coverage figure
SPACINGS = (0.1, 0.2, 0.3, 0.5)  # [m] lattices of candidate viewpoints tried (the shortest
#   tour is kept: greedy cover is not monotone in the candidates); each made coarser where
#   it would exceed MAX_CANDIDATES
FRACTION = 0.99  # of the coverage set the tour sees
MAX_CANDIDATES = 4000  # the lattice is made coarser beyond this many candidate viewpoints
SEQUENTIAL_OVERHEADS = (5.0, 20.0, 100.0)  # [cells] the sequential choices tried (_Plan)
DIST_CHUNK = 32  # sources per shortest path search of _Plan.dist (each a row of the grid)
PRED_KEPT = 64  # shortest path trees _Plan.seg keeps (each an int32 per reachable cell)
_POP = np.array([bin(i).count("1") for i in range(256)], dtype=np.uint8)  # bits per byte


@dataclass(frozen=True)
class OracleTour:
    length_m: float  # [m] the open tour from the start
    points: np.ndarray  # (k, 2) [m] the start, then the viewpoints in tour order
    seen_fraction: float  # of the coverage set, seen from the tour's viewpoints
    candidates: int  # candidate viewpoints
    spacing_m: float  # [m] their lattice
    greedy_length_m: float  # [m] the nearest-neighbour order's length, before 2-opt / or-opt


@njit(cache=True, nogil=True)
def _views(solid, tidx, vr, vc, rays, r2, nbytes):  # pragma: no cover - compiled
    """uint8 (len(vr), nbytes): per viewpoint (vr[i], vc[i]) the bits (numpy packbits order)
    of the target cells (tidx >= 0) it sees: rays from it stop at the first solid cell, the
    raster's edge or squared distance r2 [cells^2]."""
    h, w = solid.shape
    out = np.zeros((vr.shape[0], nbytes), dtype=np.uint8)
    for v in range(vr.shape[0]):
        r0 = vr[v]
        c0 = vc[v]
        for k in range(rays.shape[0]):
            for i in range(rays.shape[1]):
                dr = rays[k, i, 0]
                dc = rays[k, i, 1]
                rr = r0 + dr
                cc = c0 + dc
                if dr * dr + dc * dc > r2 or rr < 0 or rr >= h or cc < 0 or cc >= w:
                    break
                if solid[rr, cc]:
                    break
                t = tidx[rr, cc]
                if t >= 0:
                    out[v, t >> 3] |= np.uint8(128 >> (t & 7))
    return out


def _bits(a: np.ndarray) -> int:
    """Set bits in a packed bit array."""
    return int(_POP[a].sum(dtype=np.int64))


def _row_bits(rows: np.ndarray, unseen: np.ndarray | None = None) -> np.ndarray:
    """int64 set bits per packed row (of rows & unseen with unseen), without temporaries: a
    large lattice's rows are hundreds of MB, and :meth:`_Plan.sequential` counts them on
    every step."""
    if len(rows) == 0:
        return np.zeros(0, dtype=np.int64)
    if unseen is None:
        unseen = np.full(rows.shape[1], 255, dtype=np.uint8)
    return _and_popcount(rows, unseen, _POP)


@njit(cache=True, nogil=True)
def _and_popcount(rows, mask, pop):  # pragma: no cover - compiled
    """Set bits of rows[i] & mask per row i (pop: the set bits of each byte value)."""
    out = np.zeros(rows.shape[0], dtype=np.int64)
    for i in range(rows.shape[0]):
        n = 0
        for j in range(rows.shape[1]):
            n += pop[rows[i, j] & mask[j]]
        out[i] = n
    return out


@njit(cache=True, nogil=True)
def _and_popcount_at(rows, mask, at, pop):  # pragma: no cover - compiled
    """_and_popcount over the bytes at (the only nonzero bytes of mask)."""
    out = np.zeros(rows.shape[0], dtype=np.int64)
    for i in range(rows.shape[0]):
        n = 0
        for j in at:
            n += pop[rows[i, j] & mask[j]]
        out[i] = n
    return out


@njit(cache=True, nogil=True)
def _covers(rows, mask, at):  # pragma: no cover - compiled
    """Per row: does it hold every bit of mask (whose nonzero bytes are at)?"""
    out = np.ones(rows.shape[0], dtype=np.bool_)
    for i in range(rows.shape[0]):
        for j in at:
            if rows[i, j] & mask[j] != mask[j]:
                out[i] = False
                break
    return out


@njit(cache=True, nogil=True)
def _walk(pred, source, target):  # pragma: no cover - compiled
    """The nodes of the shortest path from source to target (without source) in order, from a
    predecessor array (negative: none)."""
    n = 0
    v = target
    while v != source and v >= 0:
        n += 1
        v = pred[v]
    out = np.empty(n, dtype=np.int64)
    v = target
    for k in range(n - 1, -1, -1):
        out[k] = v
        v = pred[v]
    return out


def greedy_cover(views: np.ndarray, total: int, fraction: float) -> tuple[list[int], int]:
    """Greedy set cover of packed bit rows: row 0 (the start) first, then the row with the most
    unseen bits (lazy re-evaluation) until fraction of total bits are seen or nothing more
    is. Returns (chosen rows, bits seen)."""
    seen = views[0].copy()
    chosen = [0]
    count = _bits(seen)
    want = math.ceil(fraction * total - 1e-9)
    heap = [(-int(g), i) for i, g in enumerate(_row_bits(views)) if i != 0 and g > 0]
    heapq.heapify(heap)
    while count < want and heap:
        _, i = heapq.heappop(heap)
        g = _bits(views[i] & ~seen)
        if g <= 0:
            continue
        if heap and g < -heap[0][0]:
            heapq.heappush(heap, (-g, i))
            continue
        seen |= views[i]
        count += g
        chosen.append(i)
    return chosen, count


def open_tour(d: np.ndarray) -> tuple[list[int], float, float]:
    """A short open tour from node 0 through every node of the distance matrix d (k, k):
    nearest neighbour, then 2-opt and or-opt (segments of 1 to 3 moved, either way round)
    until no move shortens it. Returns (order starting with 0, its length, the nearest
    neighbour order's length). Unreachable pairs (inf) are never chosen while a finite one is
    left."""
    k = d.shape[0]
    if k <= 1:
        return list(range(k)), 0.0, 0.0
    left = set(range(1, k))
    order = [0]
    while left:
        row = d[order[-1]]
        nxt = min(left, key=lambda j: row[j])
        order.append(nxt)
        left.discard(nxt)
    greedy = _length(d, order)
    dd, arr = np.ascontiguousarray(d, dtype=np.float64), np.asarray(order, dtype=np.int64)
    improved = True
    while improved:  # arr is changed in place
        improved = bool(_two_opt(dd, arr) | _or_opt(dd, arr))
    order = arr.tolist()
    return order, _length(d, order), greedy


def _length(d: np.ndarray, order: list[int]) -> float:
    return float(sum(d[a, b] for a, b in zip(order[:-1], order[1:], strict=True)))


@njit(cache=True, nogil=True)
def _two_opt(d, order):  # pragma: no cover - compiled
    """Reverse order[i..j] (int64, in place) where that shortens the open tour (order[0]
    stays first); True if any move was made."""
    n = order.shape[0]
    any_ = False
    improved = True
    while improved:
        improved = False
        for i in range(1, n - 1):
            a = order[i - 1]
            b = order[i]
            for j in range(i + 1, n):
                c = order[j]
                delta = d[a, c] - d[a, b]
                if j + 1 < n:
                    e = order[j + 1]
                    delta += d[b, e] - d[c, e]
                if delta < -1e-9:
                    order[i:j + 1] = order[i:j + 1][::-1].copy()
                    improved = True
                    any_ = True
                    a = order[i - 1]
                    b = order[i]
    return any_


@njit(cache=True, nogil=True)
def _or_opt(d, order):  # pragma: no cover - compiled
    """Move a segment of 1 to 3 nodes (either way round) of order (int64, in place) to where
    it shortens the open tour (order[0] stays first); True if any move was made."""
    n = order.shape[0]
    any_ = False
    rest = np.empty(n, dtype=np.int64)
    for seg in range(1, 4):
        i = 1
        while i + seg <= n:
            p = order[i - 1]
            s0 = order[i]
            s1 = order[i + seg - 1]
            gain = d[p, s0]
            if i + seg < n:
                q = order[i + seg]
                gain = d[p, s0] - (d[p, q] - d[s1, q])
            m = 0  # rest = order without the segment
            for k in range(n):
                if k < i or k >= i + seg:
                    rest[m] = order[k]
                    m += 1
            best = 1e-9
            where = -1
            rev = False
            for j in range(1, m + 1):
                if j == i:
                    continue
                a = rest[j - 1]
                for way in range(2):
                    first = s0 if way == 0 else s1
                    last = s1 if way == 0 else s0
                    add = d[a, first]
                    if j < m:
                        b = rest[j]
                        add = d[a, first] + (d[last, b] - d[a, b])
                    if gain - add > best:
                        best = gain - add
                        where = j
                        rev = way == 1
            if where >= 0:
                piece = order[i:i + seg].copy()
                if rev:
                    piece = piece[::-1].copy()
                out = np.empty(n, dtype=np.int64)
                out[:where] = rest[:where]
                out[where:where + seg] = piece
                out[where + seg:] = rest[where:m]
                order[:] = out
                any_ = True
            else:
                i += 1
    return any_


def _grid_graph(pos: np.ndarray) -> tuple[csr_matrix, np.ndarray]:
    """The 8-connected graph of the True cells of pos (edge lengths 1 and sqrt 2 [cells]) and
    the node number of each cell (-1 off pos). Every edge is in it both ways, so it is
    searched as a directed graph: the same paths, without scipy building its transpose on
    every search."""
    h, w = pos.shape
    node = np.full((h, w), -1, dtype=np.int64)
    rr, cc = np.nonzero(pos)
    node[rr, cc] = np.arange(rr.size)
    src, dst, wt = [], [], []
    for dr, dc in ((0, 1), (1, -1), (1, 0), (1, 1)):
        r2, c2 = rr + dr, cc + dc
        ok = (r2 >= 0) & (r2 < h) & (c2 >= 0) & (c2 < w)
        ok[ok] &= pos[r2[ok], c2[ok]]
        src.append(node[rr[ok], cc[ok]])
        dst.append(node[r2[ok], c2[ok]])
        wt.append(np.full(int(ok.sum()), math.hypot(dr, dc)))
    s, t, x = np.concatenate(src), np.concatenate(dst), np.concatenate(wt)
    g = csr_matrix((np.concatenate([x, x]), (np.concatenate([s, t]), np.concatenate([t, s]))),
                   shape=(rr.size, rr.size))
    return g, node


def oracle_tour(world: World, laser_range: float = LASER_RANGE, radius: float = ROBOT_RADIUS,
                fraction: float = FRACTION, spacings: tuple[float, ...] = SPACINGS,
                resolution: float = RESOLUTION) -> OracleTour:
    """The short viewpoint tour of world (module docstring): the shortest over the candidate
    lattices of spacings [m] and the two ways of choosing viewpoints."""
    ctx = _Context(world, laser_range, radius, resolution)
    best: OracleTour | None = None
    steps: list[int] = []
    for spacing in spacings:
        step = max(1, round(spacing / resolution))
        while int(ctx.pos[::step, ::step].sum()) > MAX_CANDIDATES:
            step += 1
        if step in steps:
            continue
        steps.append(step)
        plan, vr, vc = ctx.plan(step, fraction)
        cover, _ = greedy_cover(plan.views, ctx.total, fraction)
        firsts = [plan.tour(cover)[0]] + [plan.sequential(o) for o in SEQUENTIAL_OVERHEADS]
        for first in firsts:
            order = plan.pull(plan.prune(first))
            order, length, greedy, seen = plan.repair(order, cover)
            t = ctx.result(order, vr, vc, length, greedy, seen, step)
            if best is None or t.length_m < best.length_m - 1e-9:
                best = t
    assert best is not None
    return best


def exhaustive_tour(world: World, spacing: float, max_viewpoints: int,
                    laser_range: float = LASER_RANGE, radius: float = ROBOT_RADIUS,
                    fraction: float = FRACTION, resolution: float = RESOLUTION
                    ) -> OracleTour | None:
    """The shortest tour, over every set of at most max_viewpoints candidates of the lattice of
    spacing [m] in every order, that sees fraction of the coverage set by the same model as
    :func:`oracle_tour` (paths seen from too); None if no such set covers. The check of the
    oracle on small worlds (``tests/test_oracle.py``): exponential, small lattices only."""
    import itertools

    ctx = _Context(world, laser_range, radius, resolution)
    step = max(1, round(spacing / resolution))
    plan, vr, vc = ctx.plan(step, fraction)
    k = len(vr)
    d = dijkstra(plan.graph, directed=False, indices=plan.cand_node)[:, plan.cand_node]
    best: tuple[float, list[int]] | None = None
    for m in range(max_viewpoints + 1):
        for subset in itertools.combinations(range(1, k), m):
            for perm in itertools.permutations(subset):
                order = [0, *perm]
                length = float(sum(d[a, b] for a, b in zip(order[:-1], order[1:], strict=True)))
                if best is not None and length >= best[0] - 1e-9:
                    continue
                if plan.count(plan.seen(order)) >= plan.want:
                    best = (length, order)
    if best is None:
        return None
    length, order = best
    seen = plan.count(plan.seen(order))
    return ctx.result(order, vr, vc, length, length, seen, step)


class _Context:
    """What every lattice shares: the rasters, the coverage set, the rays and the graph."""

    def __init__(self, world: World, laser_range: float, radius: float, resolution: float):
        self.res = resolution
        self.solid, self.ox, self.oy = rasterize(world, resolution)
        self.pos, _, _ = truth_robot_positions(world, resolution, radius)
        target, _, _ = truth_mappable(world, resolution, radius, laser_range)
        self.start = _start_cell(self.pos, world, self.ox, self.oy, resolution)
        self.tidx = np.full(self.solid.shape, -1, dtype=np.int64)
        tr, tc = np.nonzero(target)
        self.tidx[tr, tc] = np.arange(tr.size)
        self.total = int(tr.size)
        n = max(1, int(math.floor(laser_range / resolution + 1e-6)))
        self.rays = ray_table(square_border(n))
        self.r2 = float(n * n) + 1e-6
        self.graph, self.node = _grid_graph(self.pos)

    def plan(self, step: int, fraction: float) -> tuple[_Plan, np.ndarray, np.ndarray]:
        """The candidates of the lattice of step cells (the start first) and their plan."""
        lattice = np.zeros_like(self.pos)
        lattice[::step, ::step] = True
        lattice &= self.pos
        vr, vc = np.nonzero(lattice)
        vr = np.concatenate([[self.start[0]], vr]).astype(np.int64)
        vc = np.concatenate([[self.start[1]], vc]).astype(np.int64)
        nbytes = (self.total + 7) // 8
        views = _views(self.solid, self.tidx, vr, vc, self.rays, self.r2, nbytes)
        plan = _Plan(views, self.node[vr, vc], self.graph, np.nonzero(self.pos),
                     lambda r, c: _views(self.solid, self.tidx, r, c, self.rays, self.r2,
                                         nbytes),
                     math.ceil(fraction * self.total - 1e-9), step)
        return plan, vr, vc

    def result(self, order, vr, vc, length, greedy, seen, step) -> OracleTour:
        res = self.res
        pts = np.stack([self.ox + (vc[order] + 0.5) * res, self.oy + (vr[order] + 0.5) * res],
                       axis=1)
        return OracleTour(length * res, pts, seen / max(1, self.total), int(vr.size),
                          step * res, greedy * res)


class _Plan:
    """The tour's improvement steps over candidate viewpoints (indices into views; 0 is the
    start). The robot sees on the way too: all round, as at a viewpoint (optimistic), from a
    sample every ``step`` cells of each shortest path between consecutive viewpoints.
    Lengths in cells."""

    def __init__(self, views, cand_node, graph, cells, see, want, step):
        self.views, self.cand_node, self.graph = views, cand_node, graph
        self.rows, self.cols = cells
        self.see, self.want, self.step = see, want, step
        self._segs: dict[tuple[int, int], np.ndarray] = {}
        self._dist: dict[int, np.ndarray] = {}  # candidate -> path lengths to every candidate
        self._pred: dict[int, np.ndarray] = {}  # candidate -> shortest path tree (PRED_KEPT)
        self._gain0: np.ndarray | None = None  # unseen bits per candidate after the start's

    def dist(self, cands: list[int]) -> np.ndarray:
        """(len(cands), candidates) path lengths [cells] from each of cands to every
        candidate: each row is searched once (DIST_CHUNK sources at a time) and kept, since
        the tour is made again and again over mostly the same viewpoints."""
        missing = [c for c in dict.fromkeys(cands) if c not in self._dist]
        for i in range(0, len(missing), DIST_CHUNK):
            part = missing[i:i + DIST_CHUNK]
            d = dijkstra(self.graph, directed=True, indices=self.cand_node[part])
            for c, row in zip(part, d[:, self.cand_node], strict=True):
                self._dist[c] = row
        return np.stack([self._dist[c] for c in cands])

    def tour(self, cands: list[int]) -> tuple[list[int], float, float]:
        """open_tour over cands (cands[0] the start): (order, length, greedy length)."""
        order, length, greedy = open_tour(self.dist(cands)[:, cands])
        return [cands[o] for o in order], length, greedy

    def seg(self, a: int, b: int) -> np.ndarray:
        """Packed bits seen from the shortest path between candidates a and b (cached)."""
        key = (min(a, b), max(a, b))
        if key not in self._segs:
            na, nb = int(self.cand_node[key[0]]), int(self.cand_node[key[1]])
            pred = self._pred.get(key[0])
            row = self._dist.get(key[0])
            if pred is None and row is not None:  # the search stops at b's path length: the
                #   tree up to there is the whole search's (it settles nodes in the same order)
                _, pred = dijkstra(self.graph, directed=True, indices=na,
                                   return_predecessors=True,
                                   limit=float(row[key[1]]) * (1.0 + 1e-9) + 1e-9)
            elif pred is None:
                _, pred = dijkstra(self.graph, directed=True, indices=na,
                                   return_predecessors=True)
                if len(self._pred) >= PRED_KEPT:  # the oldest tree goes
                    del self._pred[next(iter(self._pred))]
                self._pred[key[0]] = pred
            cells = _walk(pred, na, nb)[self.step - 1::self.step]
            bits = np.zeros(self.views.shape[1], dtype=np.uint8)
            if cells.size:
                got = self.see(self.rows[cells].astype(np.int64),
                               self.cols[cells].astype(np.int64))
                bits = np.bitwise_or.reduce(got, axis=0)
            self._segs[key] = bits
        return self._segs[key]

    def seen(self, order: list[int], skip: int | None = None) -> np.ndarray:
        """Packed bits seen by the tour order, without the viewpoint at position skip (the tour
        then goes from the one before it straight to the one after)."""
        pts = [o for i, o in enumerate(order) if i != skip]
        parts = [self.views[o] for o in pts]
        parts += [self.seg(a, b) for a, b in zip(pts[:-1], pts[1:], strict=True)]
        return np.bitwise_or.reduce(np.stack(parts), axis=0)

    def count(self, bits: np.ndarray) -> int:
        return _bits(bits)

    def sequential(self, overhead: float) -> list[int]:
        """Viewpoints chosen one after the other from where the robot is: the one with the
        most unseen cells per cell of path to it (plus overhead cells, so that a speck next
        door does not beat a room; > 0), counting what the path there sees."""
        order = [0]
        seen = self.views[0].copy()
        if self._gain0 is None:  # each row's unseen bits: counted once, then only the bits
            self._gain0 = _row_bits(self.views, ~seen)  # each step newly sees are taken off
        gain = self._gain0.copy()
        while self.count(seen) < self.want:
            dist = self.dist([order[-1]])[0]
            score = np.where((gain > 0) & np.isfinite(dist), gain / (dist + overhead), -1.0)
            k = int(np.argmax(score))
            if score[k] <= 0:
                break
            new = seen | self.views[k] | self.seg(order[-1], k)
            fresh = new & ~seen
            at = np.flatnonzero(fresh)
            gain -= _and_popcount_at(self.views, fresh, at, _POP)
            seen = new
            order.append(k)
        return order

    def prune(self, order: list[int]) -> list[int]:
        """Drop, the least useful first, each viewpoint the rest of the tour covers for."""
        if self.count(self.seen(order)) < self.want:
            return order
        useful = []
        for p in range(1, len(order)):
            rest = self.seen(order, skip=p)
            useful.append((self.count(self.views[order[p]] & ~rest), order[p]))
        for _, k in sorted(useful):
            p = order.index(k)
            if self.count(self.seen(order, skip=p)) >= self.want:
                order = order[:p] + order[p + 1:]
        return order

    def pull(self, order: list[int]) -> list[int]:
        """Move each viewpoint (in tour order) to the candidate that sees all it alone sees
        (given the rest of the tour without its own paths) and is the cheapest detour between
        its neighbours: greedy cover takes the viewpoint that sees most, often deep in a room
        or a corridor, where a nearer one sees enough."""
        for p in range(1, len(order)):
            alone = self.views[order[p]] & ~self.seen(order, skip=p)
            fits = _covers(self.views, alone, np.flatnonzero(alone))
            fits[order] = False
            cand = np.nonzero(fits)[0]
            if cand.size == 0:
                continue
            ends = [order[p - 1]] + ([order[p + 1]] if p + 1 < len(order) else [])
            d = self.dist(ends)
            detour = d[:, cand].sum(axis=0)
            now = d[:, order[p]].sum()
            best = int(np.argmin(detour))
            if detour[best] < now - 1e-9:
                new = order[:p] + [int(cand[best])] + order[p + 1:]
                if self.count(self.seen(new)) >= self.want:
                    order = new
        return order

    def repair(self, order: list[int], pool: list[int]) -> tuple[list[int], float, float, int]:
        """Tour order's viewpoints again; while the new order sees less than wanted, add back
        the candidate of pool that sees most of the rest. Returns (order, length, greedy
        length, bits seen)."""
        keep = list(order)
        while True:
            order, length, greedy = self.tour(keep)
            bits = self.seen(order)
            seen = self.count(bits)
            extra = [k for k in pool if k not in keep]
            if seen >= self.want or not extra:
                return order, length, greedy, seen
            gain = [self.count(self.views[k] & ~bits) for k in extra]
            if max(gain) <= 0:
                return order, length, greedy, seen
            keep.append(extra[int(np.argmax(gain))])


def _start_cell(pos: np.ndarray, world: World, ox: float, oy: float, res: float
                ) -> tuple[int, int]:
    """The reachable position nearest to the robot's start."""
    rr, cc = np.nonzero(pos)
    x, y = world.robot_pose[0], world.robot_pose[1]
    k = int(np.argmin(np.hypot(ox + (cc + 0.5) * res - x, oy + (rr + 0.5) * res - y)))
    return int(rr[k]), int(cc[k])
