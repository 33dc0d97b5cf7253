"""Simulator worlds: the TOML world format, ROS map_server import, truth rasterization and the
truth sets coverage is measured on (:func:`truth_mappable`, :func:`truth_free_reachable`).

Pure except for reading world files (TOML, map YAML, map image). DESIGN.md §5 describes the
format; a world is a set of static solid shapes in a rectangle ``origin .. origin + size``:

- ``segments``: wall pieces, pymunk segment shapes of radius ``wall_thickness`` (so a wall is
  ``2 * wall_thickness`` thick),
- ``circles``: (centre, radius) desk and chair legs,
- ``boxes``: (centre, size, angle) solid rectangles (furniture; map pixels are merged into
  axis-aligned boxes).

World TOML (all lengths in metres, angles in radians)::

    name = "my-world"
    description = "one line"            # optional
    size = [10.0, 8.0]                  # [m] world spans [0, w] x [0, h]
    wall_thickness = 0.05               # optional [m] segment *radius* (default 0.05)
    [robot]
    pose = [1.0, 1.0, 0.0]              # optional for map worlds (picked automatically)
    [[walls]]
    points = [[0, 0], [10, 0], [10, 8], [0, 8]]
    closed = true
    [[boxes]]
    center = [5, 4]
    size = [1.0, 0.5]
    angle = 0.3                         # optional
    [[circles]]
    center = [2, 2]
    radius = 0.04

or, instead of ``size``, ``map = "file.yaml"`` (relative to the TOML file): a ROS map_server
map (image + YAML with resolution, origin, negate, occupied_thresh, free_thresh); every pixel
that is not free is solid, the world frame is the map frame. Extra walls/boxes/circles may be
added on top of a map.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from topoexplore.common.grid import distance_transform
from topoexplore.common.mapio import MapIOError, read_map_server

__all__ = [
    "WorldError",
    "World",
    "ROBOT_RADIUS",
    "START_CLEARANCE",
    "WORLDS_DIR",
    "builtin_worlds",
    "load_world",
    "parse_world",
    "rasterize",
    "truth_free_reachable",
    "truth_robot_positions",
    "truth_mappable",
    "disc_kernel",
    "LASER_RANGE",
    "START_SEARCH",
    "clearance",
    "pick_start_pose",
    "solid_to_boxes",
    "map_grid_to_solid",
]

ROBOT_RADIUS = 0.2  # [m] robot size used to validate start poses (paper: Pioneer 2DX)
LASER_RANGE = 8.0  # [m] default laser range of the mappable truth (LaserParams.range_max)
START_SEARCH = 3  # [cells] how far from the start cell a reachable centre position is looked for
START_CLEARANCE = 0.5  # [m] wanted distance from an automatically picked start to any solid
DEFAULT_WALL_RADIUS = 0.05  # [m] segment radius -> walls 0.1 m thick
PICK_RESOLUTION = 0.05  # [m] raster used to pick start poses
WORLDS_DIR = Path(__file__).resolve().parent / "worlds"
_EPS = 1e-6  # [cells] tolerance for float cell boundaries

Point = tuple[float, float]


class WorldError(ValueError):
    """A world file or world definition is invalid (one-line message naming the file)."""


@dataclass
class World:
    name: str
    size: tuple[float, float]  # [m] (width along x, height along y)
    robot_pose: tuple[float, float, float]  # [m, m, rad]
    segments: list[tuple[Point, Point]] = field(default_factory=list)  # walls [m]
    circles: list[tuple[Point, float]] = field(default_factory=list)  # (centre, radius) [m]
    boxes: list[tuple[Point, Point, float]] = field(default_factory=list)  # (centre, size, angle)
    wall_thickness: float = DEFAULT_WALL_RADIUS  # [m] radius of segment shapes (half thickness)
    source: str = ""  # file path or "builtin:<name>"
    origin: Point = (0.0, 0.0)  # [m] lower-left corner of the world rectangle
    description: str = ""

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """(xmin, xmax, ymin, ymax) [m]."""
        ox, oy = self.origin
        return ox, ox + self.size[0], oy, oy + self.size[1]

    @property
    def shape_count(self) -> int:
        return len(self.segments) + len(self.circles) + len(self.boxes)

    @property
    def area(self) -> float:
        """[m^2] of the world rectangle (a map's whole extent, unknown cells included)."""
        return float(self.size[0] * self.size[1])


def time_limit(area: float) -> float:
    """[s] sim time an exploration of a world of this area [m^2] may take: 6 s per m^2, at
    least 2400 s (``topoexplore run``'s default, and ``bench robust``'s). Generous on purpose
    (a cluttered 24 x 22 m floor needs about 1700 s at the robot's slow speeds near obstacles,
    a 24 x 40 m office of 46 rooms 3600-4400 s): a run that stops making progress is told
    apart by its stagnant map (livelock), not by the limit. There is no upper cap: a cap of
    12000 s (until 2026-12-03) stopped every strategy on the 60 x 60 m office while it was
    still finishing (reliability: done at 12768 s, coverage 0.993), and its slow last pockets
    were then called a livelock."""
    return float(max(2400.0, 6.0 * area))


# --------------------------------------------------------------------------------------------
# built-in worlds and loading


def builtin_worlds() -> dict[str, str]:
    """Built-in world name -> one-line description (from the TOML files in sim/worlds/)."""
    out: dict[str, str] = {}
    for p in sorted(WORLDS_DIR.glob("*.toml")):
        try:
            data = tomllib.loads(p.read_text())
        except (OSError, tomllib.TOMLDecodeError):
            continue
        desc = str(data.get("description", "")).strip()
        out[p.stem] = desc.splitlines()[0] if desc else ""
    return out


WORLD_SUFFIXES = (".toml", ".yaml", ".yml")  # a world file (TOML, or a map_server map); else a name


def load_world(name_or_path: str) -> World:
    """Load a built-in world by name, a world ``.toml`` file or a map_server ``.yaml`` file.

    Raises :class:`WorldError` (one line) for unknown names and any problem in the files.
    """
    if not isinstance(name_or_path, (str, Path)):
        raise WorldError(f"world must be a name or a path (got {type(name_or_path).__name__})")
    text = str(name_or_path)
    builtin = WORLDS_DIR / f"{text}.toml"
    if "/" not in text and not text.endswith(WORLD_SUFFIXES) and builtin.is_file():
        world = _load_toml(builtin)
        world.source = f"builtin:{text}"
        return world
    path = Path(text)
    if path.suffix == ".toml":
        return _load_toml(path)
    if path.suffix in (".yaml", ".yml"):
        return _load_map_world(path, path.stem, extra={}, pose=None)
    names = ", ".join(builtin_worlds())
    raise WorldError(f"unknown world {text!r}: not a builtin ({names}) nor a .toml/.yaml file")


def _load_toml(path: Path) -> World:
    try:
        data = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise WorldError(f"{path}: world file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise WorldError(f"{path}: cannot read world file: {_one_line(exc)}") from None
    except tomllib.TOMLDecodeError as exc:
        raise WorldError(f"{path}: not valid TOML: {_one_line(exc)}") from None
    return parse_world(data, str(path), base_dir=path.parent)


_TOP_KEYS = {"name", "description", "size", "wall_thickness", "robot", "walls", "boxes",
             "circles", "map"}


def parse_world(data: dict, source: str, base_dir: Path | None = None) -> World:
    """Build a :class:`World` from a parsed TOML document (see module docstring)."""
    where = source or "<world>"
    if not isinstance(data, dict):
        raise WorldError(f"{where}: world must be a table")
    unknown = sorted(set(data) - _TOP_KEYS)
    if unknown:
        raise WorldError(f"{where}: unknown key(s) {', '.join(unknown)}")
    name = data.get("name", Path(source).stem if source else "world")
    if not isinstance(name, str) or not name:
        raise WorldError(f"{where}: name must be a non-empty string")
    description = data.get("description", "")
    if not isinstance(description, str):
        raise WorldError(f"{where}: description must be a string")
    wall_r = _number(data.get("wall_thickness", DEFAULT_WALL_RADIUS), where, "wall_thickness")
    if wall_r <= 0:
        raise WorldError(f"{where}: wall_thickness must be > 0 (got {wall_r})")

    pose = None
    robot = data.get("robot", {})
    if not isinstance(robot, dict):
        raise WorldError(f"{where}: [robot] must be a table")
    bad = sorted(set(robot) - {"pose"})
    if bad:
        raise WorldError(f"{where}: unknown key(s) in [robot]: {', '.join(bad)}")
    if "pose" in robot:
        pose = tuple(_numbers(robot["pose"], 3, where, "robot.pose"))

    extra = {
        "segments": _parse_walls(data.get("walls", []), where),
        "boxes": _parse_boxes(data.get("boxes", []), where),
        "circles": _parse_circles(data.get("circles", []), where),
        "wall_thickness": wall_r,
        "description": description,
    }
    if "map" in data:
        if "size" in data:
            raise WorldError(f"{where}: give either size or map, not both (map sets the size)")
        if not isinstance(data["map"], str) or not data["map"]:
            raise WorldError(f"{where}: map must be a file name")
        map_path = Path(data["map"])
        if not map_path.is_absolute():
            map_path = (base_dir or Path(".")) / map_path
        try:
            world = _load_map_world(map_path, name, extra=extra, pose=pose)
        except WorldError as exc:
            raise WorldError(f"{where}: map {exc}") from None
        world.source = source
        return world

    if "size" not in data:
        raise WorldError(f"{where}: missing size = [w, h] (or map = \"file.yaml\")")
    w, h = _numbers(data["size"], 2, where, "size")
    if w <= 0 or h <= 0:
        raise WorldError(f"{where}: size must be positive (got [{w}, {h}])")
    if pose is None:
        raise WorldError(f"{where}: missing [robot] pose = [x, y, theta]")
    world = World(name=name, size=(w, h), robot_pose=pose, source=source, **extra)
    _check_world(world, where)
    return world


def _parse_walls(items, where: str) -> list[tuple[Point, Point]]:
    segs: list[tuple[Point, Point]] = []
    for k, item in enumerate(_tables(items, where, "walls")):
        _keys(item, {"points", "closed"}, where, f"walls[{k}]")
        pts = item.get("points")
        if not isinstance(pts, list) or len(pts) < 2:
            raise WorldError(f"{where}: walls[{k}].points must be a list of >= 2 [x, y] points")
        p = [tuple(_numbers(q, 2, where, f"walls[{k}].points")) for q in pts]
        closed = item.get("closed", False)
        if not isinstance(closed, bool):
            raise WorldError(f"{where}: walls[{k}].closed must be true or false")
        if closed:
            if len(p) < 3:
                raise WorldError(f"{where}: walls[{k}] closed needs >= 3 points")
            p.append(p[0])
        for a, b in zip(p[:-1], p[1:], strict=True):
            if a == b:
                raise WorldError(f"{where}: walls[{k}] has a zero-length piece at {a}")
            segs.append((a, b))
    return segs


def _parse_boxes(items, where: str) -> list[tuple[Point, Point, float]]:
    out = []
    for k, item in enumerate(_tables(items, where, "boxes")):
        _keys(item, {"center", "size", "angle"}, where, f"boxes[{k}]")
        for req in ("center", "size"):
            if req not in item:
                raise WorldError(f"{where}: boxes[{k}] is missing {req}")
        c = tuple(_numbers(item["center"], 2, where, f"boxes[{k}].center"))
        s = tuple(_numbers(item["size"], 2, where, f"boxes[{k}].size"))
        if s[0] <= 0 or s[1] <= 0:
            raise WorldError(f"{where}: boxes[{k}].size must be positive (got {list(s)})")
        a = _number(item.get("angle", 0.0), where, f"boxes[{k}].angle")
        out.append((c, s, a))
    return out


def _parse_circles(items, where: str) -> list[tuple[Point, float]]:
    out = []
    for k, item in enumerate(_tables(items, where, "circles")):
        _keys(item, {"center", "radius"}, where, f"circles[{k}]")
        for req in ("center", "radius"):
            if req not in item:
                raise WorldError(f"{where}: circles[{k}] is missing {req}")
        c = tuple(_numbers(item["center"], 2, where, f"circles[{k}].center"))
        r = _number(item["radius"], where, f"circles[{k}].radius")
        if r <= 0:
            raise WorldError(f"{where}: circles[{k}].radius must be positive (got {r})")
        out.append((c, r))
    return out


def _tables(items, where: str, what: str) -> list[dict]:
    if not isinstance(items, list) or not all(isinstance(i, dict) for i in items):
        raise WorldError(f"{where}: {what} must be an array of tables ([[{what}]])")
    return items


def _keys(item: dict, allowed: set[str], where: str, what: str) -> None:
    bad = sorted(set(item) - allowed)
    if bad:
        raise WorldError(f"{where}: unknown key(s) in {what}: {', '.join(bad)}")


def _number(v, where: str, what: str) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise WorldError(f"{where}: {what} must be a finite number (got {v!r})")
    return float(v)


def _numbers(v, n: int, where: str, what: str) -> list[float]:
    if not isinstance(v, list) or len(v) != n:
        raise WorldError(f"{where}: {what} must be a list of {n} numbers (got {v!r})")
    return [_number(x, where, what) for x in v]


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split())


def _check_world(world: World, where: str) -> None:
    """Geometry inside the world rectangle; robot inside and not overlapping any solid."""
    xmin, xmax, ymin, ymax = world.extent
    tol = 1e-9

    def inside(p: Point) -> bool:
        return xmin - tol <= p[0] <= xmax + tol and ymin - tol <= p[1] <= ymax + tol

    for k, (a, b) in enumerate(world.segments):
        for p in (a, b):
            if not inside(p):
                raise WorldError(f"{where}: wall piece {k} point {list(p)} is outside the world")
    for k, (c, _r) in enumerate(world.circles):
        if not inside(c):
            raise WorldError(f"{where}: circle {k} centre {list(c)} is outside the world")
    for k, (c, _s, _a) in enumerate(world.boxes):
        if not inside(c):
            raise WorldError(f"{where}: box {k} centre {list(c)} is outside the world")
    x, y, _t = world.robot_pose
    if not (xmin + ROBOT_RADIUS <= x <= xmax - ROBOT_RADIUS
            and ymin + ROBOT_RADIUS <= y <= ymax - ROBOT_RADIUS):
        raise WorldError(f"{where}: robot pose ({x}, {y}) is outside the world")
    c = clearance(world, x, y)
    if c < ROBOT_RADIUS:
        raise WorldError(f"{where}: robot at ({x}, {y}) is inside or touching a wall "
                         f"(clearance {c:.2f} m < radius {ROBOT_RADIUS} m)")


# --------------------------------------------------------------------------------------------
# ROS map_server import

def _load_map_world(yaml_path: Path, name: str, extra: dict, pose) -> World:
    """A world from a ROS map_server map (read by common.mapio, nav2 semantics)."""
    where = str(yaml_path)
    try:
        grid, geom = read_map_server(yaml_path)
    except MapIOError as exc:
        raise WorldError(f"{where}: {_one_line(exc)}") from None
    solid = map_grid_to_solid(grid)
    if solid.all():
        raise WorldError(f"{where}: map has no free pixel")
    res = geom.resolution
    ox, oy = float(geom.origin_x), float(geom.origin_y)
    world = World(
        name=name,
        size=(geom.width * res, geom.height * res),
        robot_pose=(0.0, 0.0, 0.0),
        source=where,
        origin=(ox, oy),
        **extra,
    )
    world.boxes = solid_to_boxes(solid, res, (ox, oy)) + world.boxes
    if pose is None:
        world.robot_pose = pick_start_pose(world)
        if clearance(world, world.robot_pose[0], world.robot_pose[1]) < ROBOT_RADIUS:
            raise WorldError(f"{where}: no free place for the robot in the map")
    else:
        world.robot_pose = tuple(pose)
    _check_world(world, where)
    return world


def map_grid_to_solid(grid: np.ndarray) -> np.ndarray:
    """int8 map grid (row 0 = min y) -> bool solid mask: every cell that is not free (0).

    The one-cell border is made solid so the free space is always bounded.
    """
    solid = np.asarray(grid) != 0
    solid[0, :] = solid[-1, :] = True
    solid[:, 0] = solid[:, -1] = True
    return solid


def solid_to_boxes(solid: np.ndarray, res: float, origin: Point) -> list[tuple[Point, Point, float]]:
    """Solid cells (row 0 = min y) -> axis-aligned boxes: horizontal runs merged upwards.

    Every solid pixel is covered exactly once, so rasterizing the boxes at ``res`` (with the
    same origin) gives back the mask.
    """
    h, w = solid.shape
    ox, oy = origin
    boxes: list[tuple[Point, Point, float]] = []
    active: dict[tuple[int, int], int] = {}  # (c0, c1) -> first row

    def close(c0: int, c1: int, r0: int, r1: int) -> None:
        # rows r0..r1-1 -> y from oy + r0 * res to oy + r1 * res
        x0, x1 = ox + c0 * res, ox + c1 * res
        y0, y1 = oy + r0 * res, oy + r1 * res
        boxes.append((((x0 + x1) / 2, (y0 + y1) / 2), (x1 - x0, y1 - y0), 0.0))

    for r in range(h + 1):
        runs: set[tuple[int, int]] = set()
        if r < h:
            row = solid[r].astype(np.int8)
            d = np.diff(np.concatenate(([0], row, [0])))
            starts = np.flatnonzero(d == 1)
            ends = np.flatnonzero(d == -1)
            runs = set(zip(starts.tolist(), ends.tolist(), strict=True))
        for key in list(active):
            if key not in runs:
                close(key[0], key[1], active.pop(key), r)
        for key in runs:
            active.setdefault(key, r)
    return boxes


# --------------------------------------------------------------------------------------------
# geometry: clearance, rasterization, start pose


def clearance(world: World, x: float, y: float) -> float:
    """Distance [m] from (x, y) to the nearest solid surface (<= 0 inside a solid)."""
    best = math.inf
    if world.segments:
        s = np.asarray(world.segments, dtype=np.float64)  # (n, 2, 2)
        d = _point_segment_distance(x, y, s[:, 0, 0], s[:, 0, 1], s[:, 1, 0], s[:, 1, 1])
        best = min(best, float(d.min()) - world.wall_thickness)
    if world.circles:
        c = np.array([[cx, cy, r] for (cx, cy), r in world.circles])
        best = min(best, float((np.hypot(c[:, 0] - x, c[:, 1] - y) - c[:, 2]).min()))
    if world.boxes:
        b = np.array([[cx, cy, sx, sy, a] for (cx, cy), (sx, sy), a in world.boxes])
        ca, sa = np.cos(b[:, 4]), np.sin(b[:, 4])
        dx, dy = x - b[:, 0], y - b[:, 1]
        u = np.abs(ca * dx + sa * dy) - b[:, 2] / 2
        v = np.abs(-sa * dx + ca * dy) - b[:, 3] / 2
        outside = np.hypot(np.maximum(u, 0), np.maximum(v, 0))
        inside = np.minimum(np.maximum(u, v), 0)
        best = min(best, float((outside + inside).min()))
    return best


def _point_segment_distance(px, py, ax, ay, bx, by):
    """Euclidean distance from points to segments (numpy broadcasting)."""
    dx, dy = bx - ax, by - ay
    L2 = dx * dx + dy * dy
    t = np.clip(((px - ax) * dx + (py - ay) * dy) / np.where(L2 > 0, L2, 1.0), 0.0, 1.0)
    return np.hypot(px - (ax + t * dx), py - (ay + t * dy))


def _grid_shape(world: World, resolution: float) -> tuple[int, int]:
    w = int(math.ceil(world.size[0] / resolution - _EPS))
    h = int(math.ceil(world.size[1] / resolution - _EPS))
    return max(h, 1), max(w, 1)


def rasterize(world: World, resolution: float) -> tuple[np.ndarray, float, float]:
    """Truth occupancy: bool (h, w), True = solid, and the origin (x, y) [m] of cell (0, 0).

    A cell is solid when its square overlaps a solid shape with positive area (walls with
    their thickness, legs, boxes), so thin legs and diagonal walls are never lost and solid
    curves stay 4-connected (8-connected free space cannot leak through a wall).
    Row i, column j covers x in origin_x + [j, j+1] * resolution (as common/grid.py).
    """
    if not (isinstance(resolution, (int, float)) and math.isfinite(resolution)
            and resolution > 0):
        raise WorldError(f"rasterize: resolution must be a positive number (got {resolution!r})")
    res = float(resolution)
    h, w = _grid_shape(world, res)
    ox, oy = world.origin
    solid = np.zeros((h, w), dtype=bool)

    def window(x0: float, x1: float, y0: float, y1: float):
        """Index ranges of cells whose open squares can overlap [x0, x1] x [y0, y1]."""
        c0 = max(int(math.floor((x0 - ox) / res + _EPS)), 0)
        c1 = min(int(math.ceil((x1 - ox) / res - _EPS)), w)
        r0 = max(int(math.floor((y0 - oy) / res + _EPS)), 0)
        r1 = min(int(math.ceil((y1 - oy) / res - _EPS)), h)
        if c0 >= c1 or r0 >= r1:
            return None
        cx = ox + (np.arange(c0, c1) + 0.5) * res
        cy = oy + (np.arange(r0, r1) + 0.5) * res
        return r0, r1, c0, c1, cx[None, :], cy[:, None]

    half = res / 2
    r = world.wall_thickness
    for (ax, ay), (bx, by) in world.segments:
        win = window(min(ax, bx) - r, max(ax, bx) + r, min(ay, by) - r, max(ay, by) + r)
        if win is None:
            continue
        r0, r1, c0, c1, cx, cy = win
        d = _square_segment_distance(cx, cy, half, ax, ay, bx, by)
        solid[r0:r1, c0:c1] |= d < r - 1e-12
    for (px, py), rad in world.circles:
        win = window(px - rad, px + rad, py - rad, py + rad)
        if win is None:
            continue
        r0, r1, c0, c1, cx, cy = win
        dx = np.maximum(np.abs(cx - px) - half, 0.0)
        dy = np.maximum(np.abs(cy - py) - half, 0.0)
        solid[r0:r1, c0:c1] |= dx * dx + dy * dy < rad * rad - 1e-12
    for (px, py), (sx, sy), ang in world.boxes:
        ca, sa = math.cos(ang), math.sin(ang)
        ex = abs(ca) * sx / 2 + abs(sa) * sy / 2  # half extents of the bounding box
        ey = abs(sa) * sx / 2 + abs(ca) * sy / 2
        win = window(px - ex, px + ex, py - ey, py + ey)
        if win is None:
            continue
        r0, r1, c0, c1, cx, cy = win
        if abs(sa) < 1e-12 or abs(ca) < 1e-12:  # axis aligned: the window is exact
            solid[r0:r1, c0:c1] = True
            continue
        # separating axis test, strict (positive-area) overlap; axes x, y, box u, box v
        tol = 1e-9
        ok = np.ones((r1 - r0, c1 - c0), dtype=bool)
        ok &= np.abs(cx - px) < ex + half - tol
        ok &= np.abs(cy - py) < ey + half - tol
        proj_sq = half * (abs(ca) + abs(sa))  # half extent of a cell projected on u or v
        ok &= np.abs(ca * (cx - px) + sa * (cy - py)) < sx / 2 + proj_sq - tol
        ok &= np.abs(-sa * (cx - px) + ca * (cy - py)) < sy / 2 + proj_sq - tol
        solid[r0:r1, c0:c1] |= ok
    return solid, float(ox), float(oy)


def _square_segment_distance(cx, cy, half, ax, ay, bx, by):
    """Distance between axis-aligned squares (centres cx, cy, half side) and a segment."""
    # endpoints to squares
    d = np.minimum(
        np.hypot(np.maximum(np.abs(cx - ax) - half, 0), np.maximum(np.abs(cy - ay) - half, 0)),
        np.hypot(np.maximum(np.abs(cx - bx) - half, 0), np.maximum(np.abs(cy - by) - half, 0)),
    )
    # square corners to the segment
    for sx in (-half, half):
        for sy in (-half, half):
            d = np.minimum(d, _point_segment_distance(cx + sx, cy + sy, ax, ay, bx, by))
    # intersection (separating axis test): overlap on x, y and the segment normal -> 0
    nx, ny = -(by - ay), bx - ax
    n = math.hypot(nx, ny)
    inter = ((np.minimum(ax, bx) <= cx + half) & (np.maximum(ax, bx) >= cx - half)
             & (np.minimum(ay, by) <= cy + half) & (np.maximum(ay, by) >= cy - half))
    if n > 0:
        nx, ny = nx / n, ny / n
        inter &= np.abs(nx * (cx - ax) + ny * (cy - ay)) <= half * (abs(nx) + abs(ny))
    return np.where(inter, 0.0, d)


def _components8(free: np.ndarray) -> np.ndarray:
    n, labels = cv2.connectedComponents(free.astype(np.uint8), connectivity=8)
    return labels


def truth_free_reachable(world: World, resolution: float) -> tuple[np.ndarray, float, float]:
    """Free cells 8-connected to the robot's start cell: bool (h, w) and origin (x, y) [m].

    The set the old coverage figure (``coverage_free``) is measured on, and the superset of
    :func:`truth_mappable` (the set ``coverage`` is measured on, DESIGN §6 / docs/design.md
    "Measuring a run"). If the start cell itself is solid (robot close to a wall on a coarse
    grid), the nearest free cell within the robot radius is used.
    """
    solid, ox, oy = rasterize(world, resolution)
    return _free_component(world, solid, ox, oy, resolution), ox, oy


def _free_component(world: World, solid: np.ndarray, ox: float, oy: float,
                    res: float) -> np.ndarray:
    """The 8-connected free component of the start cell (see :func:`truth_free_reachable`)."""
    free = ~solid
    start = _nearest_cell(free, ox, oy, res, world.robot_pose, ROBOT_RADIUS + res)
    if start is None:
        raise WorldError(f"{world.source or world.name}: robot start is not in free space")
    return _label_of(free, start)


def _label_of(mask: np.ndarray, cell: tuple[int, int]) -> np.ndarray:
    """The 8-connected component of ``mask`` that holds ``cell``."""
    labels = _components8(mask)
    return labels == labels[cell]


def _nearest_cell(mask: np.ndarray, ox: float, oy: float, res: float, pose,
                  max_dist: float) -> tuple[int, int] | None:
    """The cell of ``mask`` that holds the point (pose x, y), or else the ``mask`` cell whose
    centre is nearest to it within ``max_dist`` [m] (ties: lowest row, then column)."""
    x, y = pose[0], pose[1]
    row = int(math.floor((y - oy) / res))
    col = int(math.floor((x - ox) / res))
    h, w = mask.shape
    if 0 <= row < h and 0 <= col < w and mask[row, col]:
        return row, col
    rr, cc = np.nonzero(mask)
    if rr.size == 0:
        return None
    d = np.hypot(ox + (cc + 0.5) * res - x, oy + (rr + 0.5) * res - y)
    k = int(np.argmin(d))
    return (int(rr[k]), int(cc[k])) if d[k] <= max_dist else None


def disc_kernel(radius: float, resolution: float) -> np.ndarray:
    """uint8 (2k+1, 2k+1) mask of the cell offsets whose *square* comes nearer than ``radius``
    [m] to the centre of the middle cell: a disc of ``radius`` centred on a cell centre
    overlaps exactly these cells with positive area."""
    k = int(math.ceil(radius / resolution + 0.5))
    a = np.maximum(np.abs(np.arange(-k, k + 1)) - 0.5, 0.0) * resolution
    return (np.hypot(a[:, None], a[None, :]) < radius - 1e-9).astype(np.uint8)


def _dilate(mask: np.ndarray, kernel: np.ndarray, outside: int) -> np.ndarray:
    """Binary dilation of ``mask`` by ``kernel`` (centred); cells outside the raster count as
    ``outside`` (1: set, as solid beyond the world's edge)."""
    k = kernel.shape[0] // 2
    src = np.pad(mask.astype(np.uint8), k, constant_values=outside)
    return cv2.dilate(src, kernel)[k:-k, k:-k].astype(bool)


def _positions(world: World, solid: np.ndarray, free_comp: np.ndarray, ox: float, oy: float,
               res: float, radius: float) -> np.ndarray:
    """Reachable robot centre cells (definition (a) of :func:`truth_mappable`)."""
    fits = free_comp & ~_dilate(solid, disc_kernel(radius, res), outside=1)
    start = _nearest_cell(fits, ox, oy, res, world.robot_pose, START_SEARCH * res)
    if start is None:  # the robot cannot move on this raster: it maps from where it stands
        only = np.zeros_like(fits)
        only[_nearest_cell(free_comp, ox, oy, res, world.robot_pose, math.inf)] = True
        return only
    return _label_of(fits, start)


def truth_robot_positions(world: World, resolution: float, radius: float = ROBOT_RADIUS
                          ) -> tuple[np.ndarray, float, float]:
    """Reachable robot centre positions: bool (h, w) and origin (x, y) [m]; definition (a) of
    :func:`truth_mappable`."""
    solid, ox, oy = rasterize(world, resolution)
    comp = _free_component(world, solid, ox, oy, resolution)
    return _positions(world, solid, comp, ox, oy, resolution, radius), ox, oy


def truth_mappable(world: World, resolution: float, radius: float = ROBOT_RADIUS,
                   laser_range: float = LASER_RANGE) -> tuple[np.ndarray, float, float]:
    """The free cells the robot can map: bool (h, w) and origin (x, y) [m]. Coverage is
    measured on this set (DESIGN §6, docs/design.md "Measuring a run"); it is a subset of
    :func:`truth_free_reachable`. On the truth raster of ``resolution``:

    (a) reachable centre positions (:func:`truth_robot_positions`): free cells whose distance
        to the nearest solid cell (from the cell centre to the solid cell's square; cells
        beyond the raster are solid) is at least ``radius`` [m], 8-connected to the start cell
        (if the start cell is not such a cell, the nearest one within :data:`START_SEARCH`
        cells; if there is none, the start cell alone: the robot maps from where it stands);
    (b) the target set: every free cell the robot's disc overlaps from a reachable position,
        plus every free cell within ``laser_range`` [m] (centre to centre) of a reachable
        position and in its line of sight: a Bresenham ray from one of the two cells passes
        through the other with only free cells before it. Rays go from a cell to every cell on
        the border of the square of half side ``laser_range`` around it (8 * range / resolution
        rays; together they pass through every cell of the square).

    Every reachable position is a viewpoint (no sampling of positions); see :func:`_visible`.
    """
    for name, v in (("radius", radius), ("laser_range", laser_range)):
        if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
            raise WorldError(f"truth_mappable: {name} must be a positive number (got {v!r})")
    solid, ox, oy = rasterize(world, resolution)
    comp = _free_component(world, solid, ox, oy, resolution)
    pos = _positions(world, solid, comp, ox, oy, resolution, radius)
    covered = _dilate(pos, disc_kernel(radius, resolution), outside=0) & comp
    return covered | _visible(solid, comp, pos, covered, laser_range / resolution), ox, oy


def _visible(solid: np.ndarray, comp: np.ndarray, pos: np.ndarray, covered: np.ndarray,
             reach: float) -> np.ndarray:
    """The cells of ``comp`` outside ``covered`` in line of sight of a ``pos`` cell within
    ``reach`` [cells] (definition (b) of :func:`truth_mappable`).

    Rays start at those cells and stop at the first position, so most stop at once; only for
    the cells that no such ray settles (behind gaps, through slits) are rays then cast from
    the positions near them, as the laser goes. Cells and positions more than ``reach``
    8-connected steps apart through free cells are never in line of sight: no ray for them.
    """
    n = int(math.floor(reach + _EPS))
    if n < 1:
        return np.zeros_like(comp)
    from topoexplore.sim import rays as rk  # numba: only where a truth mask is made

    rays = rk.ray_table(rk.square_border(n))
    r2 = reach * reach + _EPS
    cand = _within_steps(pos, comp, n) & ~covered
    seen = rk.sees_goal(solid, cand, pos, rays, r2)  # from the cells to the positions
    hard = cand & ~seen
    if hard.any():  # from the positions near the rest to them
        viewpoints = pos & _within_steps(hard, comp, n)
        start, ids = rk.rays_through(rays)
        hr, hc = np.nonzero(hard)
        seen |= rk.rays_to(solid, viewpoints, hr, hc, rays, start, ids, r2) & hard
    return seen


def _within_steps(seeds: np.ndarray, free: np.ndarray, n: int) -> np.ndarray:
    """Cells of ``free`` at most ``n`` 8-connected steps through ``free`` from ``seeds``. Two
    cells in line of sight within n cells are that close (the Bresenham line is such a path),
    so no ray is needed from or to the other cells."""
    near = (seeds & free).astype(np.uint8)
    allowed = free.astype(np.uint8)
    kernel = np.ones((3, 3), np.uint8)
    count = int(near.sum())
    for _ in range(n):
        near = cv2.dilate(near, kernel) & allowed
        grown = int(near.sum())
        if grown == count:
            break
        count = grown
    return near.astype(bool)


def pick_start_pose(world: World, resolution: float = PICK_RESOLUTION) -> tuple[float, float, float]:
    """Deterministic start pose: the free cell with the largest clearance in the largest
    8-connected free region (ties: lowest row, then column), heading 0."""
    solid, ox, oy = rasterize(world, resolution)
    free = (~solid).astype(np.uint8)
    if not free.any():
        raise WorldError(f"{world.source or world.name}: no free space for the robot")
    labels = _components8(free.astype(bool))
    counts = np.bincount(labels[free.astype(bool)])
    biggest = int(np.argmax(counts))
    # distance to the nearest solid cell centre, minus half a cell (conservative) [m]
    dist = distance_transform(free) * resolution
    dist[labels != biggest] = -1.0
    k = int(np.argmax(dist))
    row, col = divmod(k, free.shape[1])
    x = ox + (col + 0.5) * resolution
    y = oy + (row + 0.5) * resolution
    return (round(x, 6), round(y, 6), 0.0)
