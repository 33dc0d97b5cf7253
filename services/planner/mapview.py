"""One update's map and the grids derived from it, shared by every strategy of the update.

The planner searches only the observed part of the map (:meth:`GridMap.crop_known`: the same
distances, frontiers and paths on a smaller array). Each derived grid (cell classes, free and
occupied masks, clearance map, unknown masks, passable cells) is computed at most once, when
first asked for: the topological evaluation, the frontier search and the completion rules of
one update all read the same arrays.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from topoexplore.common.domain import GridMap
from topoexplore.common.grid import (
    FREE,
    OCCUPIED,
    GridGeometry,
    Occupancy,
    classify,
    crop_known,
    open_unknown,
    unknown_mask,
)
from topoexplore.services.planner import graph as gr
from topoexplore.services.planner import gridsearch as gs

NEAR_MARGIN = 0.5  # [m] obstacles this far outside a window still count (:meth:`MapView.near`)
OPENING_DEPTH = 1.0  # how far behind an opening its widening is judged, in robot widths
#   (2 x fit, :meth:`MapView.openings`)


class _once:
    """A property computed on first access and then stored on the instance (as
    functools.cached_property, without its lock: a view belongs to one update)."""

    def __init__(self, fn: Callable[[Any], Any]):
        self.fn = fn
        self.__doc__ = fn.__doc__

    def __set_name__(self, owner: type, name: str) -> None:
        self.name = name

    def __get__(self, obj: Any, owner: type | None = None) -> Any:
        if obj is None:
            return self
        value = obj.__dict__[self.name] = self.fn(obj)
        return value


class _Lazy:
    """A value made on the first call and then kept. A view hands it to its searches (a
    reach-only search may never need it) instead of a closure over the view: a search kept in
    the view's memo would otherwise close a reference cycle, and every view with its grids
    would stay alive until the cyclic collector ran."""

    def __init__(self, make: Callable[[], Any]):
        self._make: Callable[[], Any] | None = make
        self._value: Any = None

    def __call__(self) -> Any:
        if self._make is not None:
            self._value, self._make = self._make(), None
        return self._value

    @property
    def made(self) -> bool:
        return self._make is None


class MapView:
    """Lazily derived grids of one map (on its observed part) for one planning update."""

    def __init__(self, grid: GridMap, occ: Occupancy,
                 blocked: Sequence[tuple[float, float, float]] = (),
                 examined: Callable[[GridGeometry], np.ndarray | None] | None = None,
                 looked: Callable[[GridGeometry], np.ndarray | None] | None = None,
                 keeper: gs.ClearanceKeeper | None = None):
        self._grid = grid
        self._keeper = keeper  # the clearance kept from the last update's view, if given
        self.occ = occ
        self.blocked = tuple(blocked)  # (x, y, r) [m]: discs learned to be impassable
        self._examined = examined  # geom -> the examined frontier cells (:mod:`.examined`)
        self._looked = looked  # geom -> the frontier cells looked into from close
        self._open: dict[tuple[int, int | None, int, int], tuple[Any, np.ndarray]] = {}
        self._passable: dict[float, np.ndarray] = {}
        self._fits: dict[float, np.ndarray] = {}
        self._memo: dict[Any, Any] = {}

    def without_blocked(self) -> MapView:
        """The same map without the learned blockages (a new view: nothing shared)."""
        return MapView(self._grid, self.occ, (), self._examined, self._looked)

    def memo(self, key: Any, make: Callable[[], Any]) -> Any:
        """make() once per view and key: what several rules of one update share."""
        if key not in self._memo:
            self._memo[key] = make()
        return self._memo[key]

    def _made(self, name: str) -> bool:
        """Has this view computed its :class:`_once` property ``name``?"""
        return name in self.__dict__

    def memo_made(self, key: Any) -> Any:
        """What :meth:`memo` holds for key, or None if it was not made (nothing is made)."""
        return self._memo.get(key)

    @_once
    def _crop(self) -> tuple[np.ndarray, GridGeometry]:
        return crop_known(self._grid.data, self._grid.geom)

    @_once
    def data(self) -> np.ndarray:
        """int8 cells of the observed part plus a ring of unknown (a view of the map's)."""
        return self._crop[0]

    @_once
    def geom(self) -> GridGeometry:
        return self._crop[1]

    @_once
    def map_classes(self) -> np.ndarray:
        """UNKNOWN / FREE / OCCUPIED per cell of the map alone (:func:`common.grid.classify`):
        what the surface memory counts (a learned blockage is a belief that can be dropped,
        not something the beams hit)."""
        return classify(self.data, self.occ.p_free, self.occ.p_occ)

    @_once
    def classes(self) -> np.ndarray:
        """:attr:`map_classes` with the learned obstacles (``blocked`` discs,
        :mod:`.blockage`) OCCUPIED."""
        if not self.blocked:
            return self.map_classes
        cls = self.map_classes.copy()
        geom = self.geom
        for bx, by, br in self.blocked:  # each disc on its own bounding box of cells
            (r0, r1), (c0, c1) = (geom.world_to_cell(np.array([bx - br, bx + br]),
                                                     np.array([by - br, by + br])))
            r0, r1 = max(0, int(r0)), min(geom.height, int(r1) + 1)
            c0, c1 = max(0, int(c0)), min(geom.width, int(c1) + 1)
            if r0 >= r1 or c0 >= c1:
                continue
            rows, cols = np.mgrid[r0:r1, c0:c1]
            xs, ys = geom.cell_to_world(rows, cols)
            box = cls[r0:r1, c0:c1]
            box[(xs - bx) ** 2 + (ys - by) ** 2 <= br * br] = OCCUPIED
        return cls

    @_once
    def free(self) -> np.ndarray:
        return self.classes == FREE

    @_once
    def frontier_free(self) -> np.ndarray:
        """Free cells that may be frontier cells: :attr:`free` without the examined frontier
        cells (:mod:`.examined`: looked at squarely and still beside unknown space)."""
        closed = None if self._examined is None else self._examined(self.geom)
        return self.free if closed is None else self.free & ~closed

    @_once
    def occupied(self) -> np.ndarray:
        return self.classes == OCCUPIED

    @_once
    def clearance(self) -> np.ndarray:
        """float32 distance [m] to the nearest occupied cell (unknown is no obstacle); with a
        :class:`gridsearch.ClearanceKeeper`, capped at its cap and made from the last
        update's clearance where the occupied cells did not change (the keeper works on the
        whole grid, whose geometry changes far less often than the observed part's)."""
        if self._keeper is None:
            return gs.clearance_map(self.occupied, self.geom.resolution)
        full, geom = self._grid.geom, self.geom
        r0 = round((geom.origin_y - full.origin_y) / geom.resolution)
        c0 = round((geom.origin_x - full.origin_x) / geom.resolution)
        win = slice(r0, r0 + geom.height), slice(c0, c0 + geom.width)
        occ = np.zeros((full.height, full.width), dtype=bool)
        occ[win] = self.occupied  # outside the observed part: never observed, no obstacle
        return self._keeper.clearance(occ, full)[win]

    @property
    def best_clearance(self) -> np.ndarray:
        """float32 largest clearance [m] of a point in each cell (:func:`gridsearch
        .best_clearance_map`): what narrow passages are judged by."""
        return self._best()

    @_once
    def _best(self) -> _Lazy:
        """:attr:`best_clearance` as a value made on first call, which the searches of this
        view share without holding the view."""
        return _Lazy(functools.partial(gs.best_clearance_map, self.occupied,
                                       self.geom.resolution))

    @_once
    def unknown(self) -> np.ndarray:
        """Unexplored cells as the frontier baseline sees them (:func:`common.grid
        .unknown_mask`)."""
        return unknown_mask(self.data, self.occ.p_free, self.occ.p_occ)

    def open_unknown(self, pocket_cells: int, search: gs.GridSearch | None = None,
                     min_reach: int = 1, share: float = 0.0) -> np.ndarray:
        """Unexplored cells without the enclosed pockets smaller than pocket_cells
        (:func:`common.grid.open_unknown`), except those the robot can look into: a pocket
        with min_reach cells of its border reached by search, holding at least share of the
        known free cells; pocket_cells <= 0: :attr:`unknown`."""
        if pocket_cells <= 0:
            return self.unknown
        key = self._open_key(pocket_cells, search, min_reach, share)
        min_area = key[3]
        hit = self._open.get(key)
        if hit is None or hit[0] is not search:  # the search is kept: its id stays its own
            reach = None if search is None else np.isfinite(search.dist)
            hit = self._open[key] = (search, open_unknown(
                self.data, pocket_cells, self.occ.p_free, self.occ.p_occ, reach, min_reach,
                min_area))
        return hit[1]

    def open_unknown_made(self, pocket_cells: int, search: gs.GridSearch | None = None,
                          min_reach: int = 1, share: float = 0.0) -> np.ndarray | None:
        """:meth:`open_unknown` with these arguments if this view has made it, else None
        (nothing is computed)."""
        if pocket_cells <= 0:
            return self.unknown if self._made("unknown") else None
        hit = self._open.get(self._open_key(pocket_cells, search, min_reach, share))
        return None if hit is None or hit[0] is not search else hit[1]

    def _open_key(self, pocket_cells: int, search: gs.GridSearch | None, min_reach: int,
                  share: float) -> tuple[int, int | None, int, int]:
        min_area = math.ceil(share * self.free_cells) if search is not None else 0
        return pocket_cells, None if search is None else id(search), min_reach, min_area

    def openings(self, fit: float) -> tuple[np.ndarray, np.ndarray]:
        """(mouth, wide): where the frontier may be a door seen only from afar
        (docs/design.md, "Openings"), less the cells the robot has looked into squarely from
        close (the ``looked`` memory); :func:`strategies.frontier.opening_mouth` judges a
        group by them.

        - mouth: frontier cells (:attr:`frontier_free` beside :attr:`unknown`) where the
          body fits into the unknown: the cell and an unknown 4-neighbour n each have a
          point at least fit [m] from every occupied cell (:attr:`best_clearance`, as
          narrow passages are judged), so a speck in a wall (a gap of k cells has about
          k / 2 cells of best clearance) has none;
        - wide: mouth cells where, through such an n in direction d, the way on along d
          for OPENING_DEPTH x 2 fit [m] (about the robot's diameter) is unknown with no
          occupied cell, and the best clearance there is at least a quarter of that depth
          more than at n (beyond the grid counts as open). Behind a door the nearest
          obstacles are its jambs, so from its middle the clearance grows as
          sqrt(c^2 + depth^2) (doors up to 1.9 m wide pass); in a channel with a wall seen
          along both sides (a recess between a wall and a piece of furniture whose face was
          never hit) it stays as narrow as at the middle of its mouth."""
        return self.memo(("openings", fit), lambda: self._openings(fit))

    def _openings(self, fit: float) -> tuple[np.ndarray, np.ndarray]:
        res = self.geom.resolution
        depth = OPENING_DEPTH * 2.0 * fit  # [m]
        k = max(1, int(round(depth / res)))
        best = self.best_clearance
        roomy = best + 1e-6 >= fit
        h, w = roomy.shape
        m = k + 1  # padding: beyond the grid is unknown, free of obstacles, roomy
        unk = np.pad(self.unknown, m, constant_values=True)
        occ = np.pad(self.occupied, m, constant_values=False)
        clear = np.pad(best, m, constant_values=np.inf)
        front = gs.frontier_mask(self.frontier_free, self.unknown) & roomy
        looked = None if self._looked is None else self._looked(self.geom)
        if looked is not None:
            front &= ~looked
        mouth, wide = np.zeros_like(front), np.zeros_like(front)
        for dr, dc in ((1, 0), (-1, 0), (0, 1), (0, -1)):
            def at(a: np.ndarray, i: int, dr: int = dr, dc: int = dc) -> np.ndarray:
                return a[m + i * dr:m + i * dr + h, m + i * dc:m + i * dc + w]
            into = front & at(unk, 1) & (at(clear, 1) + 1e-6 >= fit)
            mouth |= into
            for i in range(2, k + 2):
                into &= ~at(occ, i)
            wide |= into & (at(clear, k + 1) >= at(clear, 1) + depth / 4.0)
        return mouth, wide

    @_once
    def free_cells(self) -> int:
        """How many cells are known free."""
        return int(np.count_nonzero(self.free))

    def fits(self, fit: float) -> np.ndarray:
        """Known free cells with a point at least fit [m] from every occupied cell (the test
        of :attr:`best_clearance` + 1e-6 >= fit), from :attr:`best_clearance` once it is
        made, else without it (:func:`gridsearch.fit_mask`: the same cells)."""
        if fit not in self._fits:
            ok = (self.best_clearance + 1e-6 >= fit if self._best.made
                  else gs.fit_mask(self.occupied, self.geom.resolution, fit))
            self._fits[fit] = self.free & ok
        return self._fits[fit]

    def _capped(self, *limits: float) -> None:
        """A clearance asked of the map beyond the keeper's cap would read the cap: an error
        in the caller, not an answer."""
        if self._keeper is not None and max(limits) > self._keeper.cap + 1e-9:
            raise ValueError(f"clearance {max(limits):g} m asked beyond the kept clearance's "
                             f"cap {self._keeper.cap:g} m")

    def passable(self, radius: float) -> np.ndarray:
        """Known free cells at least radius [m] from every occupied cell."""
        if radius not in self._passable:
            self._capped(radius)
            self._passable[radius] = self.free & (self.clearance + 1e-6 >= radius)
        return self._passable[radius]

    def clearance_at(self, pts: np.ndarray) -> np.ndarray:
        """Clearance [m] at (n, 2) points [m]; inf outside the grid."""
        return self._clearance_lookup(pts)

    def narrower_than(self, pts: np.ndarray, limit: float) -> np.ndarray:
        """clearance_at(pts) < limit [m], per (n, 2) point [m] (False outside the grid): from
        the whole map's clearance when this view has it, else from the distance transform of
        the box of cells around the points alone. Every occupied cell nearer than limit to a
        point lies in that box, so the answer is the same, without the whole map's transform
        on an update that needs nothing else of it (a target followed between searches)."""
        pts = np.asarray(pts, dtype=np.float64).reshape(-1, 2)
        if self._made("clearance") or len(pts) == 0:
            return self.clearance_at(pts) < limit
        geom, out = self.geom, np.zeros(len(pts), dtype=bool)
        rows, cols = geom.world_to_cell(pts[:, 0], pts[:, 1])
        inside = geom.inside(rows, cols)
        if not inside.any():
            return out
        rows, cols, k = rows[inside], cols[inside], int(math.ceil(limit / geom.resolution)) + 1
        r0, c0 = max(0, int(rows.min()) - k), max(0, int(cols.min()) - k)
        r1 = min(geom.height, int(rows.max()) + k + 1)
        c1 = min(geom.width, int(cols.max()) + k + 1)
        near = gs.clearance_map(self.occupied[r0:r1, c0:c1], geom.resolution)
        out[inside] = near[rows - r0, cols - c0] < limit
        return out

    @_once
    def _clearance_lookup(self):
        return gr.grid_clearance(self.clearance, self.geom)

    def near(self, x: float, y: float, half: float
             ) -> tuple[np.ndarray, np.ndarray, GridGeometry]:
        """The square of cells within half [m] of (x, y): (free, best clearance, its
        geometry). The best clearance is computed from the occupied cells of the square
        and NEAR_MARGIN around it, so it is exact up to that value (farther obstacles cannot
        make a cell narrower than that): what a body-fit test near the robot needs, at a
        fraction of :attr:`best_clearance`'s cost on a large map."""
        geom = self.geom
        res = geom.resolution
        row, col = (int(v) for v in geom.world_to_cell(x, y))
        k = int(math.ceil(half / res))
        m = k + int(math.ceil(NEAR_MARGIN / res))
        a0, a1 = max(0, row - m), min(geom.height, row + m + 1)  # computed on ...
        b0, b1 = max(0, col - m), min(geom.width, col + m + 1)
        r0, r1 = max(0, row - k), min(geom.height, row + k + 1)  # ... returned
        c0, c1 = max(0, col - k), min(geom.width, col + k + 1)
        if r0 >= r1 or c0 >= c1:  # the robot is far outside the observed part
            a0, a1, b0, b1 = r0, r1, c0, c1 = 0, geom.height, 0, geom.width
        best = gs.best_clearance_map(self.occupied[a0:a1, b0:b1], res)
        best = best[r0 - a0:r1 - a0, c0 - b0:c1 - b0]
        sub = GridGeometry(res, geom.origin_x + c0 * res, geom.origin_y + r0 * res, c1 - c0,
                           r1 - r0)
        return self.free[r0:r1, c0:c1], best, sub

    def search(self, x: float, y: float, radius: float, fit: float | None = None,
               soft_radius: float = 0.0, soft_penalty: float = 0.0,
               narrow_penalty: float | None = None, reach_only: bool = False
               ) -> gs.GridSearch:
        """Grid path search from (x, y) [m] over the cells passable for radius [m], the robot
        getting to them through cells with clearance >= fit [m] (its body). With
        narrow_penalty, the cells whose best point (:attr:`best_clearance`) has fit count
        too, at that extra cost (:func:`gridsearch.grid_search`)."""
        self._capped(radius, soft_radius, fit or 0.0)
        narrow = narrow_penalty is not None and fit is not None and fit < radius
        if narrow:  # narrow passages are judged by the best point of each cell; a reach-only
            #   search may need none of its values (:func:`gridsearch.grid_search`)
            clear = self._best if reach_only else self.best_clearance
            return gs.grid_search(self.free, self.fits(fit), clear, self.geom, x, y, radius,
                                  fit=fit, soft_radius=soft_radius, soft_penalty=soft_penalty,
                                  narrow_penalty=narrow_penalty, reach_only=reach_only)
        return gs.grid_search(self.free, self.passable(radius), self.clearance, self.geom,
                              x, y, radius, fit=fit, soft_radius=soft_radius,
                              soft_penalty=soft_penalty, reach_only=reach_only)
