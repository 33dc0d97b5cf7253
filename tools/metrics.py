"""Truth metrics of a run (DESIGN §6): coverage and map accuracy. Pure, no I/O.

The truth comes from ``sim.world.rasterize`` / ``truth_mappable`` / ``truth_free_reachable``: a
bool raster with cell (0, 0)'s lower-left corner at ``truth_origin`` and cells of ``resolution``
metres. The map is a ROS-style int8 grid with its own :class:`~common.grid.GridGeometry` (origin,
size and even resolution may differ). The map is sampled at the centres of the truth cells;
truth cells outside the map count as unknown.
"""

from __future__ import annotations

import math

import numpy as np

from topoexplore.common.grid import (
    FREE,
    OCCUPIED,
    UNKNOWN,
    GridError,
    GridGeometry,
    check_grid,
    classify,
)

__all__ = ["MetricsError", "sample_classes", "coverage", "map_accuracy", "accuracy_counts"]


class MetricsError(ValueError):
    """Bad input to a metric (shapes, geometry, thresholds)."""


def _check_map(grid_int8, geom: GridGeometry) -> np.ndarray:
    """:func:`common.grid.check_grid`, as a MetricsError; a flat array of width x height cells
    (the wire layout, row by row) is taken as the grid."""
    g = np.asarray(grid_int8)
    if isinstance(geom, GridGeometry) and g.ndim == 1 and g.size == geom.width * geom.height:
        g = g.reshape(geom.height, geom.width)
    try:
        return check_grid(g, geom)
    except GridError as exc:
        raise MetricsError(str(exc)) from None


def _check_truth(truth, truth_origin, resolution, what: str) -> np.ndarray:
    t = np.asarray(truth)
    if t.ndim != 2 or t.dtype != bool:
        raise MetricsError(f"{what} must be a 2-D bool array (got {t.dtype} {t.shape})")
    if not (isinstance(resolution, (int, float)) and math.isfinite(resolution) and resolution > 0):
        raise MetricsError(f"resolution must be a positive number (got {resolution!r})")
    if len(truth_origin) != 2 or not all(math.isfinite(float(v)) for v in truth_origin):
        raise MetricsError(f"truth_origin must be (x, y) (got {truth_origin!r})")
    return t


def _check_thresholds(p_free: float, p_occ: float) -> None:
    if not 0.0 < p_free < 0.5 < p_occ < 1.0:
        raise MetricsError(f"need 0 < p_free < 0.5 < p_occ < 1 (got {p_free}, {p_occ})")


def sample_classes(grid_int8, geom: GridGeometry, shape: tuple[int, int],
                   truth_origin: tuple[float, float], resolution: float,
                   p_free: float = 0.35, p_occ: float = 0.65) -> np.ndarray:
    """Map classes (common.grid UNKNOWN / FREE / OCCUPIED) at the centres of the cells of a
    truth raster of ``shape`` (rows, cols); cells outside the map are UNKNOWN."""
    g = _check_map(grid_int8, geom)
    _check_thresholds(p_free, p_occ)
    cls = classify(g, p_free, p_occ)
    h, w = shape
    xs = truth_origin[0] + (np.arange(w) + 0.5) * resolution  # [m] truth cell centres
    ys = truth_origin[1] + (np.arange(h) + 0.5) * resolution
    rows, _ = geom.world_to_cell(0.0, ys)
    _, cols = geom.world_to_cell(xs, 0.0)
    rows = np.asarray(rows)
    cols = np.asarray(cols)
    rin = (rows >= 0) & (rows < geom.height)
    cin = (cols >= 0) & (cols < geom.width)
    out = np.full((h, w), UNKNOWN, dtype=np.uint8)
    if rin.any() and cin.any():
        out[np.ix_(rin, cin)] = cls[np.ix_(rows[rin], cols[cin])]
    return out


def coverage(grid_int8, geom: GridGeometry, truth_free, truth_origin, resolution: float,
             p_free: float = 0.35, p_occ: float = 0.65) -> float:
    """Share of the ``truth_free`` cells that the map classifies as known (free or occupied),
    DESIGN §6. In [0, 1]; 0 if the truth has no free cell. A run's ``coverage`` is measured on
    ``sim.world.truth_mappable`` (the free cells the robot can map), its ``coverage_free`` on
    ``truth_free_reachable`` (every free cell 8-connected to the start)."""
    t = _check_truth(truth_free, truth_origin, resolution, "truth_free")
    n = int(t.sum())
    if n == 0:
        return 0.0
    cls = sample_classes(grid_int8, geom, t.shape, truth_origin, resolution, p_free, p_occ)
    return float(np.count_nonzero(cls[t] != UNKNOWN)) / n


def _dilate8(mask: np.ndarray) -> np.ndarray:
    """3x3 dilation (within one cell, 8-neighbourhood)."""
    out = mask.copy()
    out[1:, :] |= mask[:-1, :]
    out[:-1, :] |= mask[1:, :]
    tmp = out.copy()
    out[:, 1:] |= tmp[:, :-1]
    out[:, :-1] |= tmp[:, 1:]
    return out


def accuracy_counts(grid_int8, geom: GridGeometry, truth_solid, truth_origin,
                    resolution: float, p_free: float = 0.35, p_occ: float = 0.65,
                    region=None) -> dict[str, int]:
    """Confusion counts over truth cells that the map classifies (see :func:`map_accuracy`):
    ``free_ok`` (map free, truth free), ``free_bad`` (map free, truth solid), ``occ_ok``
    (map occupied within one cell of truth solid), ``occ_bad`` (map occupied, no truth solid
    within one cell). ``region``: optional bool mask of the truth cells to evaluate."""
    solid = _check_truth(truth_solid, truth_origin, resolution, "truth_solid")
    cls = sample_classes(grid_int8, geom, solid.shape, truth_origin, resolution, p_free, p_occ)
    if region is not None:
        region = np.asarray(region)
        if region.shape != solid.shape or region.dtype != bool:
            raise MetricsError(f"region must be a bool array of shape {solid.shape}")
    near_solid = _dilate8(solid)
    mf = cls == FREE
    mo = cls == OCCUPIED
    if region is not None:
        mf &= region
        mo &= region
    return {
        "free_ok": int(np.count_nonzero(mf & ~solid)),
        "free_bad": int(np.count_nonzero(mf & solid)),
        "occ_ok": int(np.count_nonzero(mo & near_solid)),
        "occ_bad": int(np.count_nonzero(mo & ~near_solid)),
    }


def map_accuracy(grid_int8, geom: GridGeometry, truth_solid, truth_origin, resolution: float,
                 p_free: float = 0.35, p_occ: float = 0.65, region=None) -> float:
    """Among truth cells (free or solid, inside the world raster) that the map classifies, the
    share classified correctly, DESIGN §6: map free is correct on a truth free cell; map
    occupied is correct within one cell (8-neighbourhood) of a truth solid cell. In [0, 1];
    1.0 if the map classifies no truth cell (nothing claimed, nothing wrong)."""
    c = accuracy_counts(grid_int8, geom, truth_solid, truth_origin, resolution, p_free, p_occ,
                        region)
    n = c["free_ok"] + c["free_bad"] + c["occ_ok"] + c["occ_bad"]
    if n == 0:
        return 1.0
    return (c["free_ok"] + c["occ_ok"]) / n
