"""Truth metrics (common/metrics.py) on hand-made truth / map pairs."""

from __future__ import annotations

import numpy as np
import pytest

from topoexplore.common.grid import GridGeometry
from topoexplore.sim.world import parse_world, rasterize, truth_free_reachable
from topoexplore.tools.metrics import (
    MetricsError,
    accuracy_counts,
    coverage,
    map_accuracy,
    sample_classes,
)

FREE, OCC, UNK = 0, 100, -1


def test_coverage_same_geometry():
    truth = np.zeros((4, 5), bool)
    truth[1:3, 1:4] = True  # 6 free cells
    grid = np.full((4, 5), UNK, np.int8)
    grid[1, 1:4] = FREE  # 3 known free
    grid[2, 1] = OCC  # 1 known occupied (still "known")
    grid[2, 2] = 50  # between thresholds: unknown
    geom = GridGeometry(0.1, 0.0, 0.0, 5, 4)
    assert coverage(grid, geom, truth, (0.0, 0.0), 0.1) == pytest.approx(4 / 6)
    assert coverage(grid.ravel(), geom, truth, (0.0, 0.0), 0.1) == pytest.approx(4 / 6)


def test_coverage_map_with_other_origin_and_size():
    truth = np.ones((10, 10), bool)  # 1 m x 1 m at origin (0, 0), 0.1 m cells
    # map covers x in [0.5, 1.5], y in [-0.5, 0.5]: overlaps the truth's lower-right quarter
    geom = GridGeometry(0.1, 0.5, -0.5, 10, 10)
    grid = np.zeros((10, 10), np.int8)
    assert coverage(grid, geom, truth, (0.0, 0.0), 0.1) == pytest.approx(0.25)
    # a map shifted by a quarter cell: sampled at truth centres, still a quarter
    geom = GridGeometry(0.1, 0.475, -0.525, 10, 10)
    assert coverage(grid, geom, truth, (0.0, 0.0), 0.1) == pytest.approx(0.25)
    # a coarser map (0.2 m) covering everything
    geom = GridGeometry(0.2, -1.0, -1.0, 20, 20)
    assert coverage(np.zeros((20, 20), np.int8), geom, truth, (0.0, 0.0), 0.1) == 1.0
    # a map far away
    geom = GridGeometry(0.1, 50.0, 50.0, 10, 10)
    assert coverage(grid, geom, truth, (0.0, 0.0), 0.1) == 0.0


def test_sample_classes_outside_is_unknown():
    geom = GridGeometry(0.1, 0.0, 0.0, 2, 2)
    grid = np.array([[FREE, OCC], [UNK, FREE]], np.int8)
    cls = sample_classes(grid, geom, (3, 3), (0.0, 0.0), 0.1)
    assert cls.tolist() == [[1, 2, 0], [0, 1, 0], [0, 0, 0]]


def test_map_accuracy_counts():
    solid = np.zeros((5, 6), bool)
    solid[:, 0] = True  # wall in column 0
    geom = GridGeometry(0.1, 0.0, 0.0, 6, 5)
    grid = np.full((5, 6), UNK, np.int8)
    grid[0, 0] = OCC  # on the wall: ok
    grid[1, 1] = OCC  # one cell off the wall: ok (tolerance)
    grid[2, 2] = OCC  # two cells off: wrong
    grid[3, 0] = FREE  # free on the wall: wrong
    grid[3, 3:6] = FREE  # 3 right
    c = accuracy_counts(grid, geom, solid, (0.0, 0.0), 0.1)
    assert c == {"free_ok": 3, "free_bad": 1, "occ_ok": 2, "occ_bad": 1}
    assert map_accuracy(grid, geom, solid, (0.0, 0.0), 0.1) == pytest.approx(5 / 7)
    region = np.zeros_like(solid)
    region[3, :] = True
    assert map_accuracy(grid, geom, solid, (0.0, 0.0), 0.1, region=region) == pytest.approx(3 / 4)


def test_map_accuracy_empty_map_and_perfect_map():
    solid = np.zeros((3, 3), bool)
    solid[1, 1] = True
    geom = GridGeometry(0.1, 0.0, 0.0, 3, 3)
    assert map_accuracy(np.full((3, 3), UNK, np.int8), geom, solid, (0, 0), 0.1) == 1.0
    perfect = np.where(solid, OCC, FREE).astype(np.int8)
    assert map_accuracy(perfect, geom, solid, (0, 0), 0.1) == 1.0
    inverted = np.where(solid, FREE, OCC).astype(np.int8)
    # every occupied claim is within one cell of the centre solid cell; the free claim is wrong
    assert map_accuracy(inverted, geom, solid, (0, 0), 0.1) == pytest.approx(8 / 9)


def test_metrics_on_a_rasterized_world():
    w = parse_world({"size": [2.0, 1.0], "robot": {"pose": [0.5, 0.5, 0.0]},
                     "walls": [{"points": [[0, 0], [2, 0], [2, 1], [0, 1]], "closed": True},
                               {"points": [[1.0, 0.0], [1.0, 1.0]]}]}, "two-rooms")
    solid, ox, oy = rasterize(w, 0.1)
    reach, _, _ = truth_free_reachable(w, 0.1)
    assert reach[:, :9].any() and not reach[:, 11:].any()  # the right room is not reachable
    # the truth itself as a map: full coverage, perfect accuracy
    grid = np.where(solid, OCC, FREE).astype(np.int8)
    geom = GridGeometry(0.1, ox, oy, solid.shape[1], solid.shape[0])
    assert coverage(grid, geom, reach, (ox, oy), 0.1) == 1.0
    assert map_accuracy(grid, geom, solid, (ox, oy), 0.1) == 1.0
    # only the left half known
    half = grid.copy()
    half[:, 10:] = UNK
    assert coverage(half, geom, reach, (ox, oy), 0.1) == 1.0
    assert map_accuracy(half, geom, solid, (ox, oy), 0.1) == 1.0


def test_bad_inputs():
    geom = GridGeometry(0.1, 0.0, 0.0, 3, 3)
    truth = np.ones((3, 3), bool)
    with pytest.raises(MetricsError):
        coverage(np.zeros((2, 3), np.int8), geom, truth, (0, 0), 0.1)
    with pytest.raises(MetricsError):
        coverage(np.zeros((3, 3), np.int8), geom, truth.astype(int), (0, 0), 0.1)
    with pytest.raises(MetricsError):
        coverage(np.zeros((3, 3), np.int8), geom, truth, (0, 0), 0.0)
    with pytest.raises(MetricsError):
        coverage(np.zeros((3, 3), np.int8), geom, truth, (0, 0), 0.1, p_free=0.7)
    with pytest.raises(MetricsError):
        map_accuracy(np.zeros((3, 3), np.int8), (0.1, 0, 0, 3, 3), truth, (0, 0), 0.1)
    assert coverage(np.zeros((3, 3), np.int8), geom, np.zeros((3, 3), bool), (0, 0), 0.1) == 0.0
    # the one grid check (common.grid.check_grid), as a MetricsError
    with pytest.raises(MetricsError, match="integer"):
        coverage(np.zeros((3, 3), np.float32), geom, truth, (0, 0), 0.1)
    with pytest.raises(MetricsError, match="geometry"):
        coverage(np.zeros((3, 3), np.int8), GridGeometry(0.0, 0.0, 0.0, 3, 3), truth, (0, 0), 0.1)
