"""Render a map, its topological graph, reliabilities and the robot's path to a BGR image (pure).

The look follows the paper's Figs. 4, 10 and 11: the occupancy grid (free white, occupied black,
unknown grey), the thinning skeleton drawn from each edge's polyline, end / branch / corner nodes
with distinct shapes and colours, every node with its id, end nodes labelled ``id(P)`` when
reliabilities are given (green once P >= p_reliable), the robot as a circle with a heading tick,
and the robot's trail coloured by target segment (Fig. 11's "paths 1..5"), with start and end
marked, a title bar and a legend.

Arrays in, ``uint8`` BGR image out; no file I/O (save with :func:`common.mapio.write_png`).
``render(grid, geom, Overlays(...), Style(...))``: :class:`Overlays` holds what is drawn over
the grid, :class:`Style` how it is drawn. The y axis points up: image row 0 is the map's max y.
Use :func:`make_frame` (same arguments as :func:`render`) to find where a world point lands.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from topoexplore.common.domain import Belief, Graph
from topoexplore.common.grid import GridError, GridGeometry, check_grid

__all__ = [
    "RenderError",
    "Style",
    "Overlays",
    "Frame",
    "make_frame",
    "render",
    "choose_scale",
    "crop_to_content",
    "COL_FREE",
    "COL_OCCUPIED",
    "COL_UNKNOWN",
    "COL_UNCERTAIN",
    "COL_END",
    "COL_END_RELIABLE",
    "COL_BRANCH",
    "COL_CORNER",
    "COL_EDGE",
    "COL_TARGET",
    "COL_TRUTH",
    "TRAIL_COLOURS",
]


class RenderError(ValueError):
    """Inputs to the renderer are inconsistent (grid/geometry shape, bad pose, ...)."""


# BGR colours
COL_FREE = (255, 255, 255)
COL_OCCUPIED = (0, 0, 0)
COL_UNKNOWN = (150, 150, 150)  # never observed (-1)
COL_UNCERTAIN = (205, 205, 205)  # observed, between p_free and p_occ
COL_TRUTH = (110, 170, 255)  # ground-truth wall the map does not show as occupied
COL_EDGE = (215, 140, 30)  # skeleton edges
COL_END = (30, 30, 225)  # end node, P below the threshold (or no reliability given)
COL_END_RELIABLE = (40, 165, 40)  # end node with P >= p_reliable
COL_BRANCH = (170, 40, 150)  # branch node
COL_CORNER = (0, 150, 255)  # corner node
COL_TARGET = (255, 0, 255)  # ring around the current target
COL_ROBOT = (40, 220, 255)
COL_HEADING = (0, 0, 200)
COL_TEXT = (20, 20, 20)
COL_TITLE_BG = (45, 45, 45)
COL_LEGEND_BG = (242, 242, 242)
# trail segments: matplotlib "tab10" in BGR
TRAIL_COLOURS = (
    (180, 119, 31), (14, 127, 255), (44, 160, 44), (40, 39, 214), (189, 103, 148),
    (75, 86, 140), (194, 119, 227), (127, 127, 127), (34, 189, 188), (207, 190, 23),
)

TITLE_H = 34  # [px] title bar above the map
MIN_WIDTH = 720  # [px] narrower maps are padded on the right so the legend fits
DEFAULT_PX_PER_CELL = 6
MIN_LONG_SIDE = 800  # [px]
MAX_LONG_SIDE = 2400  # [px]
FONT = cv2.FONT_HERSHEY_SIMPLEX


# --- what to draw and how -------------------------------------------------------------------------


@dataclass(frozen=True)
class Style:
    """How to draw: the drawing options of :func:`render` (plain values, shareable)."""

    p_free: float = 0.35  # cells below p_free * 100 are free (white), as common.grid.classify
    p_occ: float = 0.65  # cells above p_occ * 100 are occupied (black); between: uncertain
    p_reliable: float = 0.9  # end nodes with P >= p_reliable are drawn green
    robot_radius: float = 0.2  # [m] drawn radius of the robot
    px_per_cell: int | None = None  # image pixels per cell; None: :func:`choose_scale`
    crop: bool = False  # only the known cells and the overlays, plus a 1 m margin
    title: str = ""  # title bar text ("" -> "topoexplore map")

    def __post_init__(self) -> None:
        if not 0.0 < self.p_free <= self.p_occ < 1.0:
            raise RenderError(f"need 0 < p_free <= p_occ < 1 (got {self.p_free}, {self.p_occ})")


@dataclass(frozen=True, eq=False)  # eq=False: arrays have no plain ==
class Overlays:
    """What to draw over the grid (all optional; checked by :func:`render`).

    - ``topo``: nodes by kind (end = circle, branch = square, corner = diamond) with their ids,
      edges from their polylines.
    - ``rel``: end nodes labelled ``id(P)``; green when P >= ``Style.p_reliable``, red below.
      Entries whose id is not in ``topo`` (or all, without ``topo``) are drawn as end nodes.
    - ``robot_pose``: (x, y, theta) [m, m, rad], a circle with a heading tick.
    - ``trail``: [(x, y, segment)], one colour per segment index (labelled with the index as
      given at its first point), start marked with a square, end with a cross.
    - ``target_id``: ring around that node.
    - ``truth_occupied``: bool array like the grid; true walls not mapped as occupied are tinted.
    """

    topo: Graph | None = None
    rel: Sequence[Belief] | None = None
    robot_pose: Sequence[float] | None = None
    trail: Sequence[tuple[float, float, int]] | None = None
    target_id: int = -1
    truth_occupied: np.ndarray | None = None


# --- geometry of the image ------------------------------------------------------------------------


def choose_scale(width: int, height: int, px_per_cell: int | None = None) -> float:
    """Pixels per cell: ``px_per_cell`` if given, else 6, raised so the long side is >= 800 px
    and lowered so it is <= 2400 px (fractional below 1 px per cell for huge grids)."""
    if px_per_cell is not None:
        if isinstance(px_per_cell, bool) or not isinstance(px_per_cell, (int, np.integer)) \
                or not 1 <= px_per_cell <= 100:
            raise RenderError(f"px_per_cell must be an integer in 1..100 (got {px_per_cell!r})")
        return float(px_per_cell)
    long = max(int(width), int(height), 1)
    s = float(max(DEFAULT_PX_PER_CELL, math.ceil(MIN_LONG_SIDE / long)))
    if long * s > MAX_LONG_SIDE:
        s = MAX_LONG_SIDE / long
        s = float(math.floor(s)) if s >= 1.0 else s
    return s


@dataclass(frozen=True)
class Frame:
    """Where the (possibly cropped) grid lands in the image."""

    geom: GridGeometry  # geometry of the rendered grid part
    scale: float  # [px/cell]
    top: int  # [px] map starts below the title bar
    map_w: int  # [px]
    map_h: int  # [px]

    @property
    def px_per_m(self) -> float:
        return self.scale / self.geom.resolution

    def to_pixel(self, x, y):
        """World (x, y) [m] -> image (u, v) = (column, row) [px, float]; v grows downwards."""
        g = self.geom
        u = (np.asarray(x, dtype=np.float64) - g.origin_x) / g.resolution * self.scale
        v = self.top + (g.height - (np.asarray(y, dtype=np.float64) - g.origin_y)
                        / g.resolution) * self.scale
        return u, v

    def ipx(self, x: float, y: float) -> tuple[int, int]:
        u, v = self.to_pixel(x, y)
        return int(round(float(u))), int(round(float(v)))


def crop_to_content(grid: np.ndarray, geom: GridGeometry, points: np.ndarray | None = None,
                    margin: float = 1.0) -> tuple[tuple[slice, slice], GridGeometry]:
    """Bounding box of known cells (value >= 0) and of world ``points`` (N x 2) [m], grown by
    ``margin`` [m], clipped to the grid. Returns ((row slice, col slice), cropped geometry)."""
    rows, cols = np.nonzero(np.asarray(grid) >= 0)
    rr: list[int] = []
    cc: list[int] = []
    if rows.size:
        rr = [int(rows.min()), int(rows.max())]
        cc = [int(cols.min()), int(cols.max())]
    if points is not None and len(points):
        pr, pc = geom.world_to_cell(points[:, 0], points[:, 1])
        rr += [int(pr.min()), int(pr.max())]
        cc += [int(pc.min()), int(pc.max())]
    if not rr:
        return (slice(0, geom.height), slice(0, geom.width)), geom
    mc = int(math.ceil(margin / geom.resolution))
    r0 = max(0, min(rr) - mc)
    r1 = min(geom.height, max(rr) + mc + 1)
    c0 = max(0, min(cc) - mc)
    c1 = min(geom.width, max(cc) + mc + 1)
    if r1 <= r0 or c1 <= c0:
        return (slice(0, geom.height), slice(0, geom.width)), geom
    sub = GridGeometry(geom.resolution, geom.origin_x + c0 * geom.resolution,
                       geom.origin_y + r0 * geom.resolution, c1 - c0, r1 - r0)
    return (slice(r0, r1), slice(c0, c1)), sub


def _overlay_points(ov: Overlays) -> np.ndarray:
    """World points of every overlay (N x 2) [m]: what a cropped image must still show."""
    pts: list[tuple[float, float]] = []
    if ov.topo is not None:
        pts += [(n.x, n.y) for n in ov.topo.nodes]
    if ov.rel is not None:
        pts += [(n.x, n.y) for n in ov.rel]
    if ov.robot_pose is not None:
        pts.append((float(ov.robot_pose[0]), float(ov.robot_pose[1])))
    if ov.trail:
        pts += [(float(t[0]), float(t[1])) for t in ov.trail]
    return np.asarray(pts, dtype=np.float64).reshape(-1, 2)


def _layout(g: np.ndarray, geom: GridGeometry, ov: Overlays,
            style: Style) -> tuple[Frame, tuple[slice, slice]]:
    """The frame and the (rows, cols) of ``g`` it shows (all of it unless ``style.crop``)."""
    window = (slice(0, geom.height), slice(0, geom.width))
    if style.crop:
        window, geom = crop_to_content(g, geom, _overlay_points(ov))
    s = choose_scale(geom.width, geom.height, style.px_per_cell)
    frame = Frame(geom, s, TITLE_H, max(1, int(round(geom.width * s))),
                  max(1, int(round(geom.height * s))))
    return frame, window


def make_frame(grid_int8: np.ndarray, geom: GridGeometry, overlays: Overlays | None = None,
               style: Style | None = None) -> Frame:
    """The image frame :func:`render` uses for the same arguments (for locating points)."""
    g = _check_grid(grid_int8, geom)
    return _layout(g, geom, overlays or Overlays(), style or Style())[0]


def _check_grid(grid_int8, geom: GridGeometry) -> np.ndarray:
    """:func:`common.grid.check_grid`, as a RenderError."""
    try:
        return check_grid(grid_int8, geom)
    except GridError as exc:
        raise RenderError(str(exc)) from None


# --- drawing helpers --------------------------------------------------------------------------


def _grid_image(g: np.ndarray, p_free: float, p_occ: float,
                truth: np.ndarray | None) -> np.ndarray:
    """Colour each cell (row 0 = min y) via a lookup table over the values -1..100."""
    values = np.arange(-1, 101)
    lut = np.empty((102, 3), np.uint8)
    lut[:] = COL_UNCERTAIN
    lut[(values >= 0) & (values < p_free * 100.0)] = COL_FREE
    lut[values > p_occ * 100.0] = COL_OCCUPIED
    lut[0] = COL_UNKNOWN
    idx = np.clip(g.astype(np.int16), -1, 100) + 1
    img = lut[idx]
    if truth is not None:
        img[truth & ~(g > p_occ * 100.0)] = COL_TRUTH
    return img


def _text(img, text: str, org: tuple[int, int], scale: float = 0.45, colour=COL_TEXT,
          thickness: int = 1, halo=(255, 255, 255)) -> None:
    if halo is not None:
        cv2.putText(img, text, org, FONT, scale, halo, thickness + 3, cv2.LINE_AA)
    cv2.putText(img, text, org, FONT, scale, colour, thickness, cv2.LINE_AA)


def _node_shape(img, kind: str, u: int, v: int, r: int, colour) -> None:
    if kind == "branch":
        cv2.rectangle(img, (u - r, v - r), (u + r, v + r), colour, -1, cv2.LINE_AA)
        cv2.rectangle(img, (u - r, v - r), (u + r, v + r), (0, 0, 0), 1, cv2.LINE_AA)
    elif kind == "corner":
        d = r + 1
        pts = np.array([[u, v - d], [u + d, v], [u, v + d], [u - d, v]], np.int32)
        cv2.fillPoly(img, [pts], colour, cv2.LINE_AA)
        cv2.polylines(img, [pts], True, (0, 0, 0), 1, cv2.LINE_AA)
    else:  # end
        cv2.circle(img, (u, v), r, colour, -1, cv2.LINE_AA)
        cv2.circle(img, (u, v), r, (0, 0, 0), 1, cv2.LINE_AA)


def _marker_start(img, u: int, v: int, r: int) -> None:
    cv2.rectangle(img, (u - r, v - r), (u + r, v + r), (255, 255, 255), -1)
    cv2.rectangle(img, (u - r, v - r), (u + r, v + r), (0, 120, 0), 2)


def _marker_end(img, u: int, v: int, r: int) -> None:
    cv2.line(img, (u - r, v - r), (u + r, v + r), (255, 255, 255), 5, cv2.LINE_AA)
    cv2.line(img, (u - r, v + r), (u + r, v - r), (255, 255, 255), 5, cv2.LINE_AA)
    cv2.line(img, (u - r, v - r), (u + r, v + r), (0, 0, 160), 2, cv2.LINE_AA)
    cv2.line(img, (u - r, v + r), (u + r, v - r), (0, 0, 160), 2, cv2.LINE_AA)


def _draw_robot(img, frame: Frame, pose, radius_m: float) -> None:
    x, y, th = pose
    u, v = frame.ipx(x, y)
    r = max(5, int(round(radius_m * frame.px_per_m)))
    cv2.circle(img, (u, v), r, COL_ROBOT, -1, cv2.LINE_AA)
    cv2.circle(img, (u, v), r, (0, 0, 0), 2, cv2.LINE_AA)
    tip = (int(round(u + 1.6 * r * math.cos(th))), int(round(v - 1.6 * r * math.sin(th))))
    cv2.line(img, (u, v), tip, COL_HEADING, 3, cv2.LINE_AA)


def _legend(width: int, items: list[tuple[str, object]], scale_bar: tuple[int, str] | None):
    """Legend strip: items = (label, draw(img, cx, cy)) laid out in rows."""
    pad, sw, row_h = 10, 26, 24
    x, rows = pad, [[]]
    for label, draw in items:
        (tw, _), _ = cv2.getTextSize(label, FONT, 0.45, 1)
        need = sw + 6 + tw + 18
        if x + need > width - pad and rows[-1]:
            rows.append([])
            x = pad
        rows[-1].append((x, label, draw))
        x += need
    h = pad + row_h * len(rows) + (row_h if scale_bar else 0) + pad // 2
    img = np.empty((h, width, 3), np.uint8)
    img[:] = COL_LEGEND_BG
    cv2.line(img, (0, 0), (width, 0), (120, 120, 120), 1)
    for i, row in enumerate(rows):
        cy = pad + row_h * i + row_h // 2
        for x0, label, draw in row:
            draw(img, x0 + sw // 2, cy)
            _text(img, label, (x0 + sw + 6, cy + 5), halo=None)
    if scale_bar:
        px, label = scale_bar
        cy = pad + row_h * len(rows) + row_h // 2
        cv2.line(img, (pad, cy), (pad + px, cy), (0, 0, 0), 2)
        for xx in (pad, pad + px):
            cv2.line(img, (xx, cy - 5), (xx, cy + 5), (0, 0, 0), 2)
        _text(img, label, (pad + px + 8, cy + 5), halo=None)
    return img


def _swatch(colour, border=(90, 90, 90)):
    def draw(img, cx, cy):
        cv2.rectangle(img, (cx - 11, cy - 7), (cx + 11, cy + 7), colour, -1)
        cv2.rectangle(img, (cx - 11, cy - 7), (cx + 11, cy + 7), border, 1)
    return draw


def _line_item(colour, thickness=3):
    def draw(img, cx, cy):
        cv2.line(img, (cx - 12, cy), (cx + 12, cy), colour, thickness, cv2.LINE_AA)
    return draw


def _node_item(kind, colour):
    return lambda img, cx, cy: _node_shape(img, kind, cx, cy, 6, colour)


def _scale_bar(frame: Frame, max_px: int) -> tuple[int, str]:
    for metres in (10.0, 5.0, 2.0, 1.0, 0.5, 0.2, 0.1):
        px = int(round(metres * frame.px_per_m))
        if px <= max_px and px >= 20:
            return px, f"{metres:g} m"
    return max(2, int(round(frame.px_per_m))), "1 m"


# --- the renderer ---------------------------------------------------------------------------


@dataclass(frozen=True)
class _Checked:
    """The overlays that need checking, in the form the drawing steps use."""

    truth: np.ndarray | None  # bool, like the grid
    robot_pose: tuple[float, float, float] | None
    trail: np.ndarray | None  # (N, 3): x, y, segment


def _check_overlays(ov: Overlays, shape: tuple[int, ...]) -> _Checked:
    """Check truth, robot pose and trail against the grid ``shape``; RenderError otherwise."""
    truth = None
    if ov.truth_occupied is not None:
        truth = np.asarray(ov.truth_occupied)
        if truth.shape != shape:
            raise RenderError(f"truth_occupied shape {truth.shape} differs from grid {shape}")
        truth = truth.astype(bool)
    pose = None
    if ov.robot_pose is not None:
        try:
            pose = tuple(float(v) for v in ov.robot_pose)
        except (TypeError, ValueError):
            raise RenderError(f"robot_pose must be (x, y, theta), got {ov.robot_pose!r}") from None
        if len(pose) != 3 or not all(math.isfinite(v) for v in pose):
            raise RenderError(f"robot_pose must be 3 finite numbers, got {pose!r}")
    trail = None
    if ov.trail:
        try:
            trail = np.asarray([(float(t[0]), float(t[1]), int(t[2])) for t in ov.trail])
        except (TypeError, ValueError, IndexError):
            raise RenderError("trail must be a list of (x, y, segment index)") from None
        if not np.isfinite(trail).all():
            raise RenderError("trail has non-finite points")
    return _Checked(truth, pose, trail)


def render(grid_int8: np.ndarray, geom: GridGeometry, overlays: Overlays | None = None,
           style: Style | None = None) -> np.ndarray:
    """Draw the map (paper Figs. 4/10/11 style) -> uint8 BGR image (H, W, 3).

    ``overlays`` says what to draw over the grid (:class:`Overlays`: graph, reliabilities,
    robot, trail, target, truth), ``style`` how (:class:`Style`: thresholds, scale, crop, robot
    radius, title). The image is the title bar, the map, then the legend strip.
    """
    ov = overlays or Overlays()
    style = style or Style()
    g = _check_grid(grid_int8, geom)
    checked = _check_overlays(ov, g.shape)
    frame, window = _layout(g, geom, ov, style)
    truth = checked.truth[window] if checked.truth is not None else None
    img = _draw_grid(g[window], truth, frame, style)
    if ov.topo is not None:
        _draw_edges(img, frame, ov.topo)
    if checked.trail is not None:
        _draw_trail(img, frame, checked.trail)
    _draw_nodes(img, frame, ov, style.p_reliable)
    if checked.robot_pose is not None:
        _draw_robot(img, frame, checked.robot_pose, style.robot_radius)
    _draw_title(img, frame, style.title)
    width = img.shape[1]
    items = _legend_items(truth is not None, ov.rel is not None, style.p_reliable, checked.trail)
    legend = _legend(width, items, _scale_bar(frame, width // 3))
    return np.ascontiguousarray(np.vstack([img, legend]))


def _draw_grid(g: np.ndarray, truth: np.ndarray | None, frame: Frame, style: Style) -> np.ndarray:
    """The canvas: title bar, the grid scaled into the frame (row 0 of the image = max y), and
    the background right of a map narrower than :data:`MIN_WIDTH`."""
    cells = _grid_image(g, style.p_free, style.p_occ, truth)[::-1]
    interp = cv2.INTER_NEAREST if frame.scale >= 1.0 else cv2.INTER_AREA
    map_img = cv2.resize(np.ascontiguousarray(cells), (frame.map_w, frame.map_h),
                         interpolation=interp)
    width = max(frame.map_w, MIN_WIDTH)
    canvas = np.empty((TITLE_H + frame.map_h, width, 3), np.uint8)
    canvas[:] = COL_LEGEND_BG
    canvas[TITLE_H:, :frame.map_w] = map_img
    canvas[:TITLE_H] = COL_TITLE_BG
    return canvas


def _draw_edges(img: np.ndarray, frame: Frame, topo: Graph) -> None:
    """The skeleton: each edge's polyline."""
    thick = 2 if frame.px_per_m < 40 else 3
    for e in topo.edges:
        if len(e.points) < 2:
            continue
        pts = np.asarray(e.points, dtype=np.float64)
        u, v = frame.to_pixel(pts[:, 0], pts[:, 1])
        poly = np.round(np.stack([u, v], axis=1)).astype(np.int32)
        cv2.polylines(img, [poly], False, COL_EDGE, thick, cv2.LINE_AA)


def _draw_trail(img: np.ndarray, frame: Frame, trail: np.ndarray) -> None:
    """The robot's path, one colour per segment, each labelled with its index at its start;
    the start marked with a square, the end with a cross."""
    u, v = frame.to_pixel(trail[:, 0], trail[:, 1])
    px = np.round(np.stack([u, v], axis=1)).astype(np.int32)
    seg = trail[:, 2].astype(int)
    starts = [0] + [i for i in range(1, len(seg)) if seg[i] != seg[i - 1]]
    ends = starts[1:] + [len(seg)]
    for a, b in zip(starts, ends, strict=True):
        colour = TRAIL_COLOURS[seg[a] % len(TRAIL_COLOURS)]
        lo = max(0, a - 1)  # connect to the previous segment's last point
        if b - lo >= 2:
            cv2.polylines(img, [px[lo:b]], False, colour, 2, cv2.LINE_AA)
    for a in starts:
        colour = TRAIL_COLOURS[seg[a] % len(TRAIL_COLOURS)]
        _text(img, str(seg[a]), (int(px[a, 0]) + 6, int(px[a, 1]) + 16), 0.5, colour, 2)
    _marker_start(img, int(px[0, 0]), int(px[0, 1]), 6)
    _marker_end(img, int(px[-1, 0]), int(px[-1, 1]), 7)


NODE_R = 6  # [px] base node size


def _draw_nodes(img: np.ndarray, frame: Frame, ov: Overlays, p_reliable: float) -> None:
    """Graph nodes and reliability entries (corners, then branches, then end nodes on top),
    the target ring, then every label (so no shape covers a label)."""
    rel_by_id = {n.id: n for n in ov.rel} if ov.rel is not None else {}
    drawn: list[tuple[int, str, float, float]] = []  # (id, kind, x, y)
    if ov.topo is not None:
        drawn += [(n.id, n.kind, n.x, n.y) for n in ov.topo.nodes]
    topo_ids = {d[0] for d in drawn}
    drawn += [(n.id, "end", n.x, n.y) for n in ov.rel if n.id not in topo_ids] if ov.rel else []
    order = {"corner": 0, "branch": 1, "end": 2}
    drawn.sort(key=lambda d: order.get(d[1], 3))
    labels = []
    for nid, kind, x, y in drawn:
        uu, vv = frame.ipx(x, y)
        if kind == "end":
            r = rel_by_id.get(nid)
            colour = COL_END_RELIABLE if (r is not None and r.p >= p_reliable) else COL_END
            label = f"{nid}({r.p:.2f})" if r is not None else f"{nid}"
            _node_shape(img, "end", uu, vv, NODE_R + 1, colour)
            labels.append((label, uu, vv, colour, 0.5))
        else:
            _node_shape(img, kind, uu, vv, NODE_R - 1,
                        COL_BRANCH if kind == "branch" else COL_CORNER)
            labels.append((str(nid), uu, vv, (70, 70, 70), 0.4))
        if nid == ov.target_id:
            cv2.circle(img, (uu, vv), NODE_R + 7, COL_TARGET, 3, cv2.LINE_AA)
    for label, uu, vv, colour, sc in labels:
        _text(img, label, (uu + NODE_R + 3, vv - NODE_R - 1), sc, colour, 1)


def _draw_title(img: np.ndarray, frame: Frame, title: str) -> None:
    """The title on the left of the title bar; the grid's size and extent on the right if
    both fit."""
    fg = frame.geom
    width = img.shape[1]
    head = title or "topoexplore map"
    _text(img, head, (10, 23), 0.6, (255, 255, 255), 1, halo=None)
    info = (f"{fg.width}x{fg.height} cells @ {fg.resolution:g} m  "
            f"x [{fg.origin_x:.1f}, {fg.origin_x + fg.width * fg.resolution:.1f}] "
            f"y [{fg.origin_y:.1f}, {fg.origin_y + fg.height * fg.resolution:.1f}] m")
    (tw, _), _ = cv2.getTextSize(info, FONT, 0.4, 1)
    (hw, _), _ = cv2.getTextSize(head, FONT, 0.6, 1)
    if 10 + hw + 20 + tw < width - 10:
        _text(img, info, (width - tw - 10, 22), 0.4, (200, 200, 200), 1, halo=None)


def _draw_robot_item(im, cx: int, cy: int) -> None:
    cv2.circle(im, (cx, cy), 7, COL_ROBOT, -1)
    cv2.circle(im, (cx, cy), 7, (0, 0, 0), 1)
    cv2.line(im, (cx, cy), (cx + 11, cy), COL_HEADING, 2)


def _legend_items(with_truth: bool, with_rel: bool, p_reliable: float,
                  trail: np.ndarray | None) -> list[tuple[str, object]]:
    """(label, draw) of every legend entry that applies to the image."""
    items: list[tuple[str, object]] = [
        ("free", _swatch(COL_FREE)),
        ("occupied", _swatch(COL_OCCUPIED)),
        ("unknown", _swatch(COL_UNKNOWN)),
        ("uncertain", _swatch(COL_UNCERTAIN)),
    ]
    if with_truth:
        items.append(("true wall, not mapped", _swatch(COL_TRUTH)))
    items += [
        ("edge", _line_item(COL_EDGE)),
        (f"end node (P < {p_reliable:g})" if with_rel else "end node",
         _node_item("end", COL_END)),
    ]
    if with_rel:
        items.append((f"end node reliable (P >= {p_reliable:g})",
                      _node_item("end", COL_END_RELIABLE)))
    items += [("branch node", _node_item("branch", COL_BRANCH)),
              ("corner node", _node_item("corner", COL_CORNER)),
              ("target", lambda im, cx, cy: cv2.circle(im, (cx, cy), 8, COL_TARGET, 3,
                                                       cv2.LINE_AA)),
              ("robot", _draw_robot_item)]
    if trail is not None:
        segs = list(dict.fromkeys(int(s) for s in trail[:, 2]))
        for s in segs[:10]:
            items.append((f"path {s}", _line_item(TRAIL_COLOURS[s % len(TRAIL_COLOURS)])))
        if len(segs) > 10:
            items.append((f"... {len(segs)} paths", _line_item((127, 127, 127))))
        items += [("start", lambda im, cx, cy: _marker_start(im, cx, cy, 6)),
                  ("end", lambda im, cx, cy: _marker_end(im, cx, cy, 6))]
    return items
