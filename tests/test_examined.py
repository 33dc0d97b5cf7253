"""Examined frontier cells (services/planner/examined.py): a frontier cell looked at squarely
from close by on several updates, and still beside unknown space, is a surface."""

from __future__ import annotations

import math

import numpy as np
import pytest

from topoexplore.common.domain import GridMap
from topoexplore.common.grid import FREE, OCCUPIED, UNKNOWN, GridGeometry, Occupancy
from topoexplore.common.surfaces import Surfaces
from topoexplore.services.planner.examined import Examined
from topoexplore.services.planner.mapview import MapView

RES = 0.1  # [m]


def wall_room(origin=(0.0, 0.0)) -> tuple[np.ndarray, GridGeometry]:
    """80 x 80 cells: free above row 10; row 10 is a wall face with two free cells
    (cols 20, 21: grazing beams cleared them) and unknown below (the wall's inside)."""
    cls = np.full((80, 80), FREE, dtype=np.int8)
    cls[:10] = UNKNOWN
    cls[10] = OCCUPIED
    cls[10, 20:22] = FREE
    return cls, GridGeometry(RES, origin[0], origin[1], 80, 80)


def examined(views: int = 3) -> Examined:
    return Examined(2.0, 1.4, math.pi / 4, views)


def test_a_face_cell_looked_at_squarely_three_times_is_examined():
    cls, geom = wall_room()
    ex = examined()
    x, y = 2.05, 2.05  # 1 m above cell (10, 20), facing down
    assert ex.observe(x, y, -math.pi / 2, cls, geom) == 0
    assert ex.observe(x, y, -math.pi / 2, cls, geom) == 0
    assert ex.observe(x, y, -math.pi / 2, cls, geom) == 2
    m = ex.mask(geom)
    assert m is not None and m[10, 20] and m[10, 21] and m.sum() == 2
    assert ex.snapshot() == {"examined": 2, "viewed": 0}


@pytest.mark.parametrize("pose, why", [
    ((4.05, 1.35, math.pi), "grazing: the line of sight runs along the wall"),
    ((2.05, 4.05, -math.pi / 2), "too far (2.9 m)"),
    ((2.05, 2.05, math.pi / 2), "behind the robot"),
])
def test_views_that_could_not_map_the_neighbour_do_not_count(pose, why):
    cls, geom = wall_room()
    ex = examined(views=1)
    assert ex.observe(*pose, cls, geom) == 0, why
    assert ex.mask(geom) is None


def test_a_cell_behind_an_obstacle_is_not_in_view():
    cls, geom = wall_room()
    cls[15, 19:23] = OCCUPIED  # a box between the robot and the face cells
    ex = examined(views=1)
    assert ex.observe(2.05, 2.05, -math.pi / 2, cls, geom) == 0
    cls[15, 19:23] = FREE
    assert ex.observe(2.05, 2.05, -math.pi / 2, cls, geom) == 2


def test_examined_cells_keep_their_place_when_the_map_grows():
    cls, geom = wall_room()
    ex = examined(views=1)
    ex.observe(2.05, 2.05, -math.pi / 2, cls, geom)
    grown = GridGeometry(RES, -1.0, -0.5, 100, 90)  # 10 more columns left, 5 rows below
    m = ex.mask(grown)
    assert list(zip(*np.nonzero(m), strict=True)) == [(15, 30), (15, 31)]


def test_examined_cells_are_no_frontier_for_the_map_view():
    cls, geom = wall_room()
    data = np.where(cls == FREE, 0, np.where(cls == OCCUPIED, 100, -1)).astype(np.int8)
    grid = GridMap(data, geom)
    ex = examined(views=1)
    view = MapView(grid, Occupancy(), (), ex.mask)
    face = view.geom.world_to_cell(np.array([2.05, 2.15]), np.array([1.05, 1.05]))
    assert view.frontier_free[face].all()
    ex.observe(2.05, 2.05, -math.pi / 2, view.classes, view.geom)
    again = MapView(grid, Occupancy(), (), ex.mask)
    assert not again.frontier_free[face].any()
    assert again.free[face].all()  # still free for paths


def test_two_memories_keep_their_own_checkpoint_arrays():
    """The planner keeps two: the examined cells and the cells looked into
    (completion_openings); a checkpoint without the second is refused, as any that does not
    fit (the service then starts afresh)."""
    from topoexplore.common.checkpoint import CheckpointError
    from topoexplore.common.params import PlannerParams, RobotParams
    from topoexplore.services.planner.core import PlannerCore

    cls, geom = wall_room()
    ex, looked = examined(views=1), Examined(2.0, 1.4, math.pi / 4, 1, name="looked")
    ex.observe(2.05, 2.05, -math.pi / 2, cls, geom)
    arrays = {**ex.checkpoint(), **looked.checkpoint()}
    assert set(arrays) == {"examined_closed", "examined_count", "looked_closed", "looked_count"}
    again = Examined(2.0, 1.4, math.pi / 4, 1, name="looked")
    again.restore(arrays)
    assert again.mask(geom) is None
    core = PlannerCore(PlannerParams(completion_openings=2.0), RobotParams(), 0.9, Occupancy())
    old = {k: v for k, v in core.checkpoint().items() if not k.startswith("looked")}
    with pytest.raises(CheckpointError, match="looked_closed"):
        core.restore(old)


def test_off_means_nothing_is_examined():
    cls, geom = wall_room()
    ex = Examined(0.0, 1.4, math.pi / 4, 1)
    assert not ex.enabled
    assert ex.observe(2.05, 2.05, -math.pi / 2, cls, geom) == 0
    assert ex.mask(geom) is None


def test_near_frontier_groups_join_the_end_nodes_with_their_own_path_checks():
    from topoexplore.services.planner.strategies.base import Candidate, Evaluation
    from topoexplore.services.planner.strategies.topological import _joined

    def cand(i):
        return Candidate(i, 0.0, 0.0, 1.0, 1.0, 1.0, 0.0, lambda: np.zeros((0, 2)))

    def topo_ok(wps):
        return False

    def frontier_ok(wps):
        return True

    ev = Evaluation(cands=[cand(3)], path_ok=topo_ok)
    near = Evaluation(cands=[cand(-1)], path_ok=frontier_ok)
    on_node = _joined(ev, near, on_frontier=False)
    assert [c.id for c in on_node.cands] == [3, -1] and on_node.path_ok is topo_ok
    assert _joined(ev, near, on_frontier=True).path_ok is frontier_ok


# --- surfaces: cells the map showed occupied, no frontier when cleared later ----------------


def wall_whole(origin=(0.0, 0.0)) -> tuple[np.ndarray, GridGeometry]:
    """wall_room's map before the grazing beams: the face row all occupied."""
    cls, geom = wall_room(origin)
    cls[10] = OCCUPIED
    return cls, geom


def test_a_face_cell_shown_occupied_on_three_updates_is_a_surface_when_cleared_later():
    whole, geom = wall_whole()
    cleared, _ = wall_room()
    s = Surfaces(3)
    s.observe(whole, geom)
    s.observe(whole, geom)
    m = s.mask(geom)
    assert m is not None and not m.any()  # two views: not yet
    s.observe(whole, geom)
    s.observe(cleared, geom)  # the grazing beams cleared two face cells: still surfaces
    m = s.mask(geom)
    assert m[10, 20] and m[10, 21] and m.sum() == 80
    assert s.snapshot() == {"surfaces": 80}
    grid = GridMap(np.where(cleared == FREE, 0, np.where(cleared == OCCUPIED, 100, -1))
                   .astype(np.int8), geom)
    view = MapView(grid, Occupancy(), (), s.mask)  # a view of the observed part
    face = view.geom.world_to_cell(np.array([2.05, 2.15]), np.array([1.05, 1.05]))
    assert not view.frontier_free[face].any() and view.free[face].all()


def test_a_door_never_hit_stays_a_frontier():
    """A door in the wall (cols 20-27) that no beam ever ended in: no surface."""
    cls, geom = wall_whole()
    cls[10, 20:28] = FREE
    s = Surfaces(1)
    for _ in range(5):
        s.observe(cls, geom)
    grid = GridMap(np.where(cls == FREE, 0, np.where(cls == OCCUPIED, 100, -1))
                   .astype(np.int8), geom)
    view = MapView(grid, Occupancy(), (), s.mask)
    door = view.geom.world_to_cell(np.arange(20, 28) * RES + 0.05, np.full(8, 1.05))
    assert view.frontier_free[door].all()


def test_surfaces_keep_their_place_when_the_map_grows_and_moves():
    cls, geom = wall_whole()
    s = Surfaces(1)
    s.observe(cls, geom)
    grown = GridGeometry(RES, -1.0, -0.5, 100, 90)  # 10 more columns left, 5 rows below
    big = np.full((90, 100), FREE, dtype=np.int8)
    big[5:85, 10:90] = cls
    big[40, 95] = OCCUPIED  # a new hit beyond the old map: the memory grows
    s.observe(big, grown)
    m = s.mask(grown)
    assert m[15, 10:90].all() and m[40, 95] and m.sum() == 81
    small = GridGeometry(RES, 1.0, 0.5, 20, 20)  # a window inside: cols 10-29 rows 5-24
    assert s.mask(small)[5].all() and s.mask(small).sum() == 20


def test_surfaces_checkpoint_round_trip_and_bad_arrays():
    from topoexplore.common.checkpoint import CheckpointError

    cls, geom = wall_whole((-3.0, 2.0))
    s = Surfaces(2)
    s.observe(cls, geom)
    arrays = s.checkpoint()
    again = Surfaces(2)
    again.restore(arrays)
    assert again.mask(geom).sum() == 0
    again.observe(cls, geom)
    assert again.mask(geom).sum() == 80
    with pytest.raises(CheckpointError):
        again.restore({**arrays, "surfaces_count": np.full((2, 2), -1, np.int64)})
    with pytest.raises(CheckpointError):
        again.restore({**arrays, "surfaces_origin": np.zeros(3, np.int64)})


def test_surfaces_off():
    cls, geom = wall_whole()
    s = Surfaces(0)
    s.observe(cls, geom)
    assert not s.enabled and s.mask(geom) is None


def test_the_surface_memory_stops_growing_at_its_bound(monkeypatch):
    """A map beyond MAX_SURFACE_CELLS (a pose far off): its cells are not remembered, and the
    service goes on with what it had."""
    import topoexplore.common.surfaces as surfaces

    cls, geom = wall_whole()
    s = Surfaces(1)
    s.observe(cls, geom)
    monkeypatch.setattr(surfaces, "MAX_SURFACE_CELLS", 100 * 100)
    far = GridGeometry(RES, 50.0, 50.0, 80, 80)  # the union would be 580 x 580 cells
    s.observe(cls, far)
    assert s.mask(far).sum() == 0 and s.mask(geom).sum() == 80


def test_learned_blockages_are_not_surfaces():
    """The planner counts the map's own classes: a blockage disc it learned (a belief it may
    drop) is occupied for its paths, never a surface."""
    from topoexplore.common.params import PlannerParams
    from topoexplore.services.planner.core import PlannerCore

    cls, geom = wall_whole()
    data = np.where(cls == FREE, 0, np.where(cls == OCCUPIED, 100, -1)).astype(np.int8)
    view = MapView(GridMap(data, geom), Occupancy(), [(4.0, 5.0, 0.3)])
    at = view.geom.world_to_cell(np.array([4.0]), np.array([5.0]))
    assert view.classes[at] == OCCUPIED and view.map_classes[at] == FREE
    core = PlannerCore(PlannerParams(strategy="frontier", surface_views=1))
    core._blockages.active = lambda t: [(4.0, 5.0, 0.3)]  # a blockage held on every update
    core.update(0.0, (2.05, 2.05, 0.0), None, None, GridMap(data, geom))
    mask = core._surfaces.mask(geom)
    assert mask[10].all() and mask.sum() == 80  # the wall, not the disc
