"""Topology core: occupancy grid -> thinning-based topological map with stable node ids (pure).

DESIGN.md §4 "Thinning" and "Node identity"; paper §2 (Figs. 1-4) and §3.1 (Figs. 5-6).
No I/O, no clock, no zenoh: the grid, its geometry and the robot position come in as arguments.

Pipeline of :meth:`TopologyCore.update` (details and measured costs in docs/topology.md):

1. known free = ``common.grid.free_mask``; unknown and occupied are both "not free".
2. clean: small non-free islands -> free, opening, diagonal contacts broken (skeleton.py).
3. thin (numba Zhang-Suen + one-pixel-wide pass). Incrementally: only a window around the cells
   that changed is re-thinned, and the result is accepted only if it agrees with the previous
   skeleton on a band around the window (else the window grows; last resort: full thinning).
4. the skeleton component of the robot (entry = nearest skeleton pixel reachable through the
   free mask from the robot's cell, or from the nearest free cell within ``entry_radius``).
5. graph: end pixels (1 neighbour), branch clusters (>= 3 neighbours, one node per cluster),
   edges traced between them; a cycle with no node gets a corner node.
6. spur pruning on the graph (not end-pixel erosion): leaf edges shorter than
   clip(spur_clearance_factor * clearance at the branch, spur_length, spur_max_length) are cut
   and the graph is re-traced (a branch left with two edges becomes a plain edge pixel).
7. corner nodes (paper Fig. 3(c)/(d)), edge length and clearance (cv2 L2 distance transform).
8. stable ids: same-kind nearest neighbour within ``id_gate``; end nodes that moved further
   along their own skeleton branch are matched through that branch (Fig. 5).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.spatial import cKDTree

from topoexplore.common.checkpoint import CheckpointError, checked
from topoexplore.common.domain import Graph, GridMap, Node
from topoexplore.common.grid import (
    GridGeometry,
    Occupancy,
    cells_for,
    distance_transform,
    free_mask,
    occupied_mask,
    unknown_mask,
)
from topoexplore.common.params import TopologyParams
from topoexplore.services.topology import graph as g
from topoexplore.services.topology import skeleton as sk

__all__ = ["TopoResult", "TopologyCore", "associate_ids"]

# modules whose WARM kernels this core runs (common.warm)
WARM_MODULES = (g.__name__, sk.__name__)


@dataclass
class TopoResult:
    graph: Graph
    skeleton: np.ndarray  # bool (h, w): final pruned skeleton of the robot's component
    stats: dict = field(default_factory=dict)  # node and edge counts


# --- id association --------------------------------------------------------------------------


def _greedy(pairs: list[tuple[float, int, int]], used_old: set[int], used_new: set[int],
            out: dict[int, int]) -> None:
    """Greedy one-to-one matching of (cost, old, new) pairs in increasing cost."""
    pairs.sort()
    for _, o, n in pairs:
        if o in used_old or n in used_new:
            continue
        used_old.add(o)
        used_new.add(n)
        out[n] = o


def associate_ids(prev_kind: np.ndarray, prev_xy: np.ndarray, new_kind: np.ndarray,
                  new_xy: np.ndarray, chains: dict[int, np.ndarray], gate: float) -> dict[int, int]:
    """Match new nodes to previous nodes; returns {new index: previous index}.

    Tier 1 (DESIGN.md §4 "Node identity"): same kind, distance <= ``gate`` [m], greedy by
    distance, one-to-one.
    Tier 2 (paper Fig. 5, an end node moving outward along a hallway faster than the gate): a
    still unmatched previous end node is matched to an unmatched new end node whose leaf chain
    (``chains[new index]``: polyline [m] from the new end node to the node at the other end of
    its branch) passes within ``gate`` of it, provided the previous node is farther than ``gate``
    from that other node (otherwise it became the junction: Fig. 6). Cost = arc length from the
    new end node to the closest chain point; greedy, one-to-one.
    """
    out: dict[int, int] = {}
    used_old: set[int] = set()
    used_new: set[int] = set()
    if len(prev_xy) == 0 or len(new_xy) == 0:
        return out
    pairs: list[tuple[float, int, int]] = []
    sdm = cKDTree(new_xy).sparse_distance_matrix(cKDTree(prev_xy), gate, output_type="ndarray")
    for n, o, d in zip(sdm["i"].tolist(), sdm["j"].tolist(), sdm["v"].tolist(), strict=True):
        if new_kind[n] == prev_kind[o]:
            pairs.append((d, o, n))
    _greedy(pairs, used_old, used_new, out)
    old_ends = [o for o in range(len(prev_xy)) if prev_kind[o] == 0 and o not in used_old]
    new_ends = [n for n in chains if n not in used_new]
    if not old_ends or not new_ends:
        return out
    pairs = []
    for n in new_ends:
        ch = chains[n]
        if len(ch) < 2:
            continue
        seg = np.hypot(np.diff(ch[:, 0]), np.diff(ch[:, 1]))
        arc = np.concatenate(([0.0], np.cumsum(seg)))
        anchor = ch[-1]
        for o in old_ends:
            p = prev_xy[o]
            if math.hypot(p[0] - anchor[0], p[1] - anchor[1]) <= gate:
                continue
            dd = np.hypot(ch[:, 0] - p[0], ch[:, 1] - p[1])
            k = int(np.argmin(dd))
            if dd[k] <= gate:
                pairs.append((float(arc[k] + dd[k]), o, n))
    _greedy(pairs, used_old, used_new, out)
    return out


# --- the core --------------------------------------------------------------------------------


def _clip(a0: int, a1: int, b0: int, b1: int, h: int, w: int) -> tuple[int, int, int, int]:
    """Rows a0..a1 and cols b0..b1 (half-open) clipped to an h x w array."""
    return max(a0, 0), min(a1, h), max(b0, 0), min(b1, w)


class TopologyCore:
    """Thinning-based topological map with stable node ids (see module docstring)."""

    def __init__(self, params: TopologyParams, occ: Occupancy | None = None):
        self.p = params
        self.occ = occ or Occupancy()  # the map's classification thresholds
        self._next_id = 0
        self._prev_ids = np.zeros(0, np.int64)
        self._prev_kind = np.zeros(0, np.int8)
        self._prev_xy = np.zeros((0, 2))
        self._updates = 0
        self._full_thins = 0
        self._window_thins = 0
        self._reused = 0
        # incremental state (padded arrays, one-pixel zero border)
        self._geom: GridGeometry | None = None
        self._grid: np.ndarray | None = None
        self._mask: np.ndarray | None = None
        self._skel: np.ndarray | None = None
        self._dt: np.ndarray | None = None
        self._seen: np.ndarray | None = None
        self._nodeid: np.ndarray | None = None
        self._dt_full = 0
        self._dt_window = 0
        self._last_counts: dict[str, int] = {}

    # -- public ----------------------------------------------------------------------------

    def snapshot(self) -> dict:
        """Small JSON-able summary for the state queryable."""
        return {
            "updates": self._updates,
            "next_id": self._next_id,
            "nodes": int(len(self._prev_ids)),
            "counts": dict(self._last_counts),
            "full_thinnings": self._full_thins,
            "window_thinnings": self._window_thins,
            "unchanged_maps": self._reused,
            "full_distance_transforms": self._dt_full,
            "window_distance_transforms": self._dt_window,
            "grid": None if self._geom is None else [self._geom.width, self._geom.height,
                                                     self._geom.resolution],
        }

    def checkpoint(self) -> dict[str, np.ndarray]:
        """What a restarted topology needs to keep its node ids: the last nodes (id, kind,
        position) that the next update is associated with, and the next free id."""
        return {"next_id": np.array([self._next_id], np.int64), "ids": self._prev_ids.copy(),
                "kind": self._prev_kind.copy(), "xy": np.asarray(self._prev_xy, np.float64)}

    def restore(self, arrays: dict[str, np.ndarray]) -> None:
        """Take the node ids back from :meth:`checkpoint`; the next update's nodes are matched
        to them as to the previous update's. CheckpointError if they do not fit together."""
        ids = checked(arrays, "ids", "i", (None,)).astype(np.int64)
        n = len(ids)
        kind = checked(arrays, "kind", "i", (n,)).astype(np.int8)
        xy = checked(arrays, "xy", "f", (n, 2)).astype(np.float64)
        next_id = int(checked(arrays, "next_id", "i", (1,))[0])
        if not np.isfinite(xy).all() or len(np.unique(ids)) != n or (n and ids.min() < 0) \
                or next_id <= (int(ids.max()) if n else -1) or next_id >= 2**62 \
                or not np.isin(kind, (g.END, g.BRANCH, g.CORNER)).all():
            raise CheckpointError("topology checkpoint: ids, kinds or positions out of range")
        self._prev_ids, self._prev_kind, self._prev_xy = ids, kind, xy
        self._next_id = next_id

    def update(self, grid_map: GridMap, robot_xy: tuple[float, float]) -> TopoResult:
        """One topology update for the current grid (module docstring, steps 1-8); robot_xy
        [m] picks the skeleton component the robot is on."""
        grid, geom = grid_map.data, grid_map.geom
        p_free, p_occ = self.occ
        self._updates += 1
        res = geom.resolution
        mask, skel, dirty = self._mask_and_skeleton(grid, geom, p_free, p_occ)
        dt = self._distance(grid, mask, dirty, p_occ)
        entry, cell = self._entry(mask, skel, geom, robot_xy)
        if entry < 0 and cell < 0:
            return self._empty(geom)
        if entry < 0:  # thinning erased the robot's whole component: keep its centre cell
            skel = skel.copy()
            entry = int(g.component_peak(mask, dt, cell // mask.shape[1], cell % mask.shape[1]))
            skel.flat[entry] = 1
        n_cells = mask.size
        if self._nodeid is None or self._nodeid.size != n_cells:
            self._seen = np.zeros(n_cells, np.uint8)
            self._nodeid = np.full(n_cells, -1, np.int32)
            self._buf = np.empty(n_cells, np.int64)
        seen, nodeid, buf = self._seen, self._nodeid, self._buf
        p = self.p
        spur_px = p.spur_length / res
        spur_max_px = max(p.spur_length, p.spur_max_length) / res
        gr = g.build_graph(skel, entry, seen, nodeid, buf)
        front_cells = (cells_for(p.frontier_spur_length, res)
                       if p.frontier_spur_length > 0 else 0)
        grid8 = np.ascontiguousarray(grid, dtype=np.int8)
        if front_cells > 0:  # frontier spurs see the undecided band at the laser's reach as
            grid8 = grid8.copy()  # unexplored too (common.grid.unknown_mask, as the frontier
            grid8[unknown_mask(grid8, p_free, p_occ)] = -1  # baseline and reliability do)
        work = skel
        for _ in range(p.spur_rounds):
            node_pix, node_kind, ea, eb, off, pix, _nid, comp = gr
            if len(ea) == 0:
                break
            if work is skel:
                work = skel.copy()
            cut = g.prune_spurs(work, node_pix, node_kind, ea, eb, off, pix, nodeid, dt,
                                spur_px, p.spur_clearance_factor, spur_max_px, grid8,
                                mask, p.frontier_spur_margin / res, front_cells)
            if cut == 0:
                break
            g.reset_nodeid(nodeid, comp)
            if not work.flat[entry]:
                entry = self._surviving_pixel(work, off, pix)
            gr = g.build_graph(work, entry, seen, nodeid, buf)
        try:
            return self._finish(gr, mask, dt, geom)
        finally:
            g.reset_nodeid(nodeid, gr[7])

    # -- steps -----------------------------------------------------------------------------

    def _clean(self, free: np.ndarray, res: float) -> np.ndarray:
        hole_cells = int(round(self.p.fill_holes / (res * res)))
        return sk.clean_free_mask(free, hole_cells, int(self.p.open_cells))

    def _reach(self, res: float) -> int:
        """Cells within which the cleaning of one cell depends on its input."""
        hole_cells = int(round(self.p.fill_holes / (res * res)))
        return hole_cells + 2 * int(self.p.open_cells) + 2

    def _mask_and_skeleton(self, grid, geom, p_free, p_occ):
        """Cleaned free mask and skeleton (padded uint8), incrementally when possible.

        Returns (mask, skel, dirty): dirty = padded (r0, r1, c0, c1) outside which neither the
        mask nor the occupied cells changed, or None if everything must be treated as new.
        """
        prev = self._aligned_previous(grid, geom)
        dirty = None
        if prev is None:
            mask, skel = self._full_mask_and_skeleton(grid, geom.resolution, p_free)
        else:
            mask, skel = prev
            ok, dirty = self._window_update(grid, geom.resolution, p_free, mask, skel)
            if not ok:
                mask, skel = self._full_mask_and_skeleton(grid, geom.resolution, p_free)
                dirty = None
        self._geom = geom
        self._grid = grid.copy()
        self._mask = mask
        self._skel = skel
        return mask, skel, dirty

    def _distance(self, grid, mask, dirty, p_occ) -> np.ndarray:
        """Distance transform [cells] of (cleaned free and not occupied), kept between updates.

        A window update is exact: the crop's transform is used only where it cannot differ from
        the full one (every value in the crop below half the margin; see docs/topology.md).
        """
        H, W = mask.shape
        if dirty is not None and self._dt is not None and self._dt.shape == (H, W):
            r0, r1, c0, c1 = dirty
            if r1 <= r0 or c1 <= c0:
                return self._dt
            for margin in (40, 100):
                half = margin // 2
                x0, x1 = max(r0 - margin, 0), min(r1 + margin, H)
                y0, y1 = max(c0 - margin, 0), min(c1 + margin, W)
                if float(self._dt[x0:x1, y0:y1].max()) >= half - 1:
                    continue
                sub = self._dt_input(grid, mask, p_occ, x0, x1, y0, y1)
                d = distance_transform(sub)
                if float(d.max()) >= half - 1:
                    continue
                i0, i1 = max(r0 - half, 0), min(r1 + half, H)
                j0, j1 = max(c0 - half, 0), min(c1 + half, W)
                self._dt[i0:i1, j0:j1] = d[i0 - x0:i1 - x0, j0 - y0:j1 - y0]
                self._dt_window += 1
                return self._dt
        self._dt_full += 1
        self._dt = distance_transform(self._dt_input(grid, mask, p_occ, 0, H, 0, W))
        return self._dt

    @staticmethod
    def _dt_input(grid, mask, p_occ, r0, r1, c0, c1) -> np.ndarray:
        """(mask and not occupied) for padded rows r0..r1, cols c0..c1 (uint8 0/1)."""
        sub = mask[r0:r1, c0:c1].copy()
        h, w = grid.shape
        gr0, gr1, gc0, gc1 = max(r0 - 1, 0), min(r1 - 1, h), max(c0 - 1, 0), min(c1 - 1, w)
        if gr1 > gr0 and gc1 > gc0:
            occ = occupied_mask(grid[gr0:gr1, gc0:gc1], p_occ)
            sub[gr0 + 1 - r0:gr1 + 1 - r0, gc0 + 1 - c0:gc1 + 1 - c0][occ] = 0
        return sub

    def _full_mask_and_skeleton(self, grid, res, p_free):
        self._full_thins += 1
        free = np.zeros((grid.shape[0] + 2, grid.shape[1] + 2), bool)
        free[1:-1, 1:-1] = free_mask(grid, p_free)
        mask = self._clean(free, res)
        mask[0, :] = mask[-1, :] = 0
        mask[:, 0] = mask[:, -1] = 0
        return mask, sk.skeletonize(mask, self.p.skeleton_method)

    def _aligned_previous(self, grid, geom):
        """Previous (mask, skeleton) if the geometry is unchanged, else None.

        A grown or shifted grid (rare: the mapper grows by metres at a time) is recomputed fully.
        """
        if not self.p.incremental or self._geom is None:
            return None
        if self._geom != geom or self._grid.shape != grid.shape:
            return None
        return self._mask, self._skel

    def _window_update(self, grid, res, p_free, mask, skel) -> tuple[bool, tuple | None]:
        """Re-clean and re-thin the changed window in place.

        Returns (ok, dirty): ok False means a full pass is needed; dirty is the padded window
        (r0, r1, c0, c1) in which the mask or the occupied cells may have changed.
        """
        changed = self._changed_cells(grid)
        if changed is None:
            self._reused += 1
            return True, (0, 0, 0, 0)
        dirty, box = self._reclean(grid, res, p_free, mask, changed)
        if box is None:
            self._reused += 1
            return True, dirty
        if self._rethin(mask, skel, box):
            self._window_thins += 1
            return True, dirty
        return False, None

    def _changed_cells(self, grid) -> tuple[int, int, int, int] | None:
        """Padded bounding box (r0, r1, c0, c1) of the cells that differ from the previous
        grid, None if none does."""
        changed = grid != self._grid
        rows = np.flatnonzero(changed.any(axis=1))
        if rows.size == 0:
            return None
        cols = np.flatnonzero(changed.any(axis=0))
        return int(rows[0]) + 1, int(rows[-1]) + 2, int(cols[0]) + 1, int(cols[-1]) + 2

    def _reclean(self, grid, res, p_free, mask, box) -> tuple[tuple, tuple | None]:
        """Re-clean the changed box plus the cleaning reach (from a crop with context) into
        ``mask``. Returns (dirty, changed): the re-cleaned window and the padded bounding box of
        the mask cells that changed (None if none did)."""
        h, w = grid.shape
        H, W = mask.shape
        r0, r1, c0, c1 = box
        reach = self._reach(res)
        pr0, pr1, pc0, pc1 = _clip(r0 - reach, r1 + reach, c0 - reach, c1 + reach, H, W)
        cr0, cr1, cc0, cc1 = _clip(pr0 - reach, pr1 + reach, pc0 - reach, pc1 + reach, H, W)
        free = np.zeros((cr1 - cr0, cc1 - cc0), bool)
        gr0, gr1, gc0, gc1 = max(cr0 - 1, 0), min(cr1 - 1, h), max(cc0 - 1, 0), min(cc1 - 1, w)
        free[gr0 + 1 - cr0:gr1 + 1 - cr0, gc0 + 1 - cc0:gc1 + 1 - cc0] = free_mask(
            grid[gr0:gr1, gc0:gc1], p_free)
        cm = self._clean(free, res)
        new_m = cm[pr0 - cr0:pr1 - cr0, pc0 - cc0:pc1 - cc0].copy()
        # keep the array's zero border
        if pr0 == 0:
            new_m[0, :] = 0
        if pc0 == 0:
            new_m[:, 0] = 0
        if pr1 == H:
            new_m[-1, :] = 0
        if pc1 == W:
            new_m[:, -1] = 0
        diff = new_m != mask[pr0:pr1, pc0:pc1]
        dirty = (pr0, pr1, pc0, pc1)
        if not diff.any():
            return dirty, None
        mask[pr0:pr1, pc0:pc1] = new_m
        rr = np.flatnonzero(diff.any(axis=1))
        cc = np.flatnonzero(diff.any(axis=0))
        return dirty, (pr0 + rr[0], pr0 + rr[-1] + 1, pc0 + cc[0], pc0 + cc[-1] + 1)

    def _rethin(self, mask, skel, box) -> bool:
        """Re-thin a window around the mask change ``box`` and paste it into ``skel`` if the
        result agrees with the skeleton on a band around it; else grow the window (4 tries).
        False: a full pass is needed."""
        H, W = mask.shape
        r0, r1, c0, c1 = box
        for attempt in range(4):
            cr0, cr1, cc0, cc1 = _clip(r0 - 8, r1 + 8, c0 - 8, c1 + 8, H, W)
            dt = cv2.distanceTransform(mask[cr0:cr1, cc0:cc1], cv2.DIST_C, 3)
            dmax = float(dt.max()) if dt.size else 0.0
            if not dmax <= H + W:  # no non-free cell in the crop: cv2 returns ~FLT_MAX, and
                return False  # the thinning reach is unbounded -> full update
            rad = int(dmax) + 3
            win = _clip(r0 - rad, r1 + rad, c0 - rad, c1 + rad, H, W)
            ctx = int(rad * (2 + attempt)) + 6
            crop = _clip(win[0] - ctx, win[1] + ctx, win[2] - ctx, win[3] + ctx, H, W)
            if (crop[1] - crop[0]) * (crop[3] - crop[2]) > 0.6 * H * W:
                return False
            if self._paste_thinned(mask, skel, win, crop):
                return True
            r0, r1, c0, c1 = win
        return False

    def _paste_thinned(self, mask, skel, win, crop) -> bool:
        """Thin ``mask`` in ``crop`` and paste the result into ``skel`` in ``win`` if it agrees
        with ``skel`` on the 3-cell seam band around ``win`` (inside the crop)."""
        H, W = mask.shape
        wr0, wr1, wc0, wc1 = win
        xr0, xr1, xc0, xc1 = crop
        sub = np.zeros((xr1 - xr0 + 2, xc1 - xc0 + 2), np.uint8)
        sub[1:-1, 1:-1] = mask[xr0:xr1, xc0:xc1]
        thin = sk.skeletonize(sub, self.p.skeleton_method)[1:-1, 1:-1]
        band = 3
        br0, br1, bc0, bc1 = _clip(wr0 - band, wr1 + band, wc0 - band, wc1 + band, H, W)
        old_b = skel[br0:br1, bc0:bc1].copy()
        new_b = thin[br0 - xr0:br1 - xr0, bc0 - xc0:bc1 - xc0]
        inner = np.zeros(old_b.shape, bool)
        inner[wr0 - br0:wr1 - br0, wc0 - bc0:wc1 - bc0] = True
        if not np.array_equal(old_b[~inner], new_b[~inner]):
            return False
        skel[wr0:wr1, wc0:wc1] = thin[wr0 - xr0:wr1 - xr0, wc0 - xc0:wc1 - xc0]
        # the seam pixels may form staircases with the pasted window
        sk.one_pixel_wide(skel, br0, br1, bc0, bc1)
        return True

    def _entry(self, mask, skel, geom: GridGeometry, robot_xy) -> tuple[int, int]:
        """(skeleton pixel where the robot joins the skeleton or -1, the robot's free cell or -1);
        flat padded indices."""
        r, c = geom.world_to_cell(robot_xy[0], robot_xy[1])
        r, c = int(r) + 1, int(c) + 1
        H, W = mask.shape
        rad = int(math.ceil(self.p.entry_radius / geom.resolution))
        if not (0 < r < H - 1 and 0 < c < W - 1) or not mask[r, c]:
            r0, r1 = max(r - rad, 1), min(r + rad + 1, H - 1)
            c0, c1 = max(c - rad, 1), min(c + rad + 1, W - 1)
            if r0 >= r1 or c0 >= c1:
                return -1, -1
            win = mask[r0:r1, c0:c1]
            rr, cc = np.nonzero(win)
            if rr.size == 0:
                return -1, -1
            d2 = (rr + r0 - r) ** 2 + (cc + c0 - c) ** 2
            k = int(np.argmin(d2))
            if d2[k] > rad * rad:
                return -1, -1
            r, c = int(rr[k] + r0), int(cc[k] + c0)
        return int(g.find_entry(mask, skel, r, c, H * W)), r * W + c

    @staticmethod
    def _surviving_pixel(work, off, pix) -> int:
        for e in range(len(off) - 1):
            for k in range(off[e], off[e + 1]):
                if work.flat[pix[k]]:
                    return int(pix[k])
        return int(np.flatnonzero(work.ravel())[0])

    def _empty(self, geom: GridGeometry) -> TopoResult:
        gone = [int(i) for i in self._prev_ids]
        self._prev_ids = np.zeros(0, np.int64)
        self._prev_kind = np.zeros(0, np.int8)
        self._prev_xy = np.zeros((0, 2))
        self._last_counts = {"end": 0, "branch": 0, "corner": 0, "edges": 0}
        return TopoResult(Graph.empty(gone), np.zeros((geom.height, geom.width), bool))

    def _finish(self, gr, mask, dt, geom: GridGeometry) -> TopoResult:
        node_pix, node_kind, ea, eb, off, pix, _nodeid, comp = gr
        H, W = mask.shape
        res = geom.resolution
        p = self.p
        deg = np.bincount(np.concatenate((ea, eb)), minlength=len(node_pix))
        leaf = (node_kind == g.BRANCH) & (deg <= 1)
        if leaf.any():  # a blob of >= 3-neighbour pixels at a skeleton tip (left by pruning
            node_kind = node_kind.copy()  # or a staircase) is a leaf: an end node, not a
            node_kind[leaf] = g.END  # branch (docs/design.md, "A branch blob at a tip")
        splits = g.split_corners(mask, ea, eb, off, pix, W, p.corner_min_deviation / res,
                                 bool(p.corner_nodes))
        sa, sb, s0, s1, ln, cl = g.assemble(ea, eb, off, pix, splits, len(node_pix), dt, W)
        all_pix = np.concatenate((node_pix, pix[splits]))
        kinds = np.concatenate((node_kind, np.full(len(splits), g.CORNER, np.int8)))
        nr, nc = np.divmod(all_pix, W)
        nx, ny = geom.cell_to_world(nr - 1, nc - 1)
        nxy = np.column_stack((nx, ny))
        # leaf chains of end nodes (pre-corner edges), oriented from the end node
        pr, pc = np.divmod(pix, W)
        px, py = geom.cell_to_world(pr - 1, pc - 1)
        pts = np.column_stack((px, py))
        chains: dict[int, np.ndarray] = {}
        for e in range(len(ea)):
            a, b = int(ea[e]), int(eb[e])
            seg = pts[off[e]:off[e + 1]]
            if node_kind[a] == g.END and deg[a] == 1:
                chains[a] = seg
            if node_kind[b] == g.END and deg[b] == 1 and a != b:
                chains[b] = seg[::-1]
        match = associate_ids(self._prev_kind, self._prev_xy, kinds, nxy, chains, p.id_gate)
        ids = np.empty(len(kinds), np.int64)
        for n in range(len(kinds)):
            o = match.get(n)
            if o is None:
                ids[n] = self._next_id
                self._next_id += 1
            else:
                ids[n] = self._prev_ids[o]
        matched_old = set(match.values())
        gone = [int(self._prev_ids[o]) for o in range(len(self._prev_ids)) if o not in matched_old]
        self._prev_ids, self._prev_kind, self._prev_xy = ids, kinds, nxy
        nodes = [Node(int(i), g.KIND_NAMES[int(k)], x, y)
                 for i, k, x, y in zip(ids.tolist(), kinds.tolist(), nx.tolist(), ny.tolist(),
                                       strict=True)]
        keep, koff = g.decimate(pix, s0, s1, W)
        graph = Graph.build(nodes, np.column_stack((ids[sa], ids[sb])).tolist(), pts[keep], koff,
                            (ln * res).tolist(), (cl * res).tolist(), gone)
        out = np.zeros((H, W), bool)
        out.flat[pix] = True
        out.flat[node_pix] = True
        if len(comp) == 1:
            out.flat[comp] = True
        self._last_counts = {
            "end": int(np.sum(kinds == g.END)),
            "branch": int(np.sum(kinds == g.BRANCH)),
            "corner": int(np.sum(kinds == g.CORNER)),
            "edges": len(graph.edges),
        }
        return TopoResult(graph, out[1:-1, 1:-1], dict(self._last_counts))
