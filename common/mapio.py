"""Map files: ROS map_server format (image + YAML) and PNG output. The only file I/O for maps.

Format (ROS map_server / nav2 map_server)::

    image: name.pgm          # relative to the YAML's directory, or absolute
    resolution: 0.05         # [m/pixel]
    origin: [x, y, yaw]      # [m, m, rad] world pose of the lower-left pixel's corner
    negate: 0
    occupied_thresh: 0.65
    free_thresh: 0.196
    mode: trinary            # optional: trinary (default) | scale | raw

Image row 0 is the top of the map (max y); our grids have row 0 at min y, so rows are flipped.
Reading follows nav2's ``map_io.cpp``: shade = mean of the colour channels / 255;
occ = shade if negate else 1 - shade; trinary: occ > occupied_thresh -> 100, occ < free_thresh ->
0, else -1; scale: transparent -> -1, else the same two tests, else rint(100 (occ - free) /
(occupied - free)); raw: round(255 shade) if in 0..100 else -1.

Writing produces what ROS map_saver produces in trinary mode: 254 free, 0 occupied, 205 unknown,
with ``free_thresh: 0.196`` and ``occupied_thresh: 0.65`` in the YAML (205 reads back as unknown
under those thresholds; the grid itself is classified with ``p_free`` / ``p_occ``).

The YAML is read with PyYAML's safe loader (any YAML: block or flow lists, comments, quotes;
a key given twice is refused, and ``1e-2`` is a number as in YAML 1.2 and ROS's yaml-cpp) and
written with ``yaml.safe_dump`` (keys in map_server order, ``origin`` as a flow list, floats as
Python's shortest exact repr, so the geometry reads back exactly). Every problem raises
:class:`MapIOError` with a one-line message.
"""

from __future__ import annotations

import math
import os
import re
import tempfile
from pathlib import Path

import cv2
import numpy as np
import yaml

from topoexplore.common.grid import (
    FREE,
    OCCUPIED,
    GridError,
    GridGeometry,
    check_grid,
    classify,
)

__all__ = [
    "MapIOError",
    "write_map_server",
    "read_map_server",
    "read_map_yaml",
    "parse_yaml",
    "write_png",
    "PIX_FREE",
    "PIX_OCCUPIED",
    "PIX_UNKNOWN",
]

PIX_FREE = 254
PIX_OCCUPIED = 0
PIX_UNKNOWN = 205
YAML_OCCUPIED_THRESH = 0.65
YAML_FREE_THRESH = 0.196  # 205 -> occ = 50/255 = 0.19608, just above: unknown
MODES = ("trinary", "scale", "raw")
REQUIRED_KEYS = ("image", "resolution", "origin", "negate", "occupied_thresh", "free_thresh")


class MapIOError(ValueError):
    """A map file is missing, malformed or cannot be written."""


# --- YAML ------------------------------------------------------------------------------------


class _MapYamlLoader(yaml.SafeLoader):
    """``yaml.safe_load``'s loader, but a key given twice is an error (PyYAML would keep the
    last one silently) and ``1e-2`` / ``5e3`` are floats (YAML 1.2, as ROS's yaml-cpp reads
    them; PyYAML's YAML 1.1 wants a dot and a signed exponent)."""


def _construct_checked_mapping(loader: _MapYamlLoader, node: yaml.MappingNode,
                               deep: bool = False) -> dict:
    seen = set()
    for key_node, _ in node.value:
        key = loader.construct_object(key_node, deep=deep)
        try:
            if key in seen:
                raise yaml.constructor.ConstructorError(
                    None, None, f"duplicate key {key!r}", key_node.start_mark)
            seen.add(key)
        except TypeError:  # unhashable: construct_mapping says so
            break
    return loader.construct_mapping(node, deep=deep)


_MapYamlLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG,
                               _construct_checked_mapping)
_MapYamlLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float", re.compile(r"^[-+]?[0-9][0-9_]*(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"),
    list("-+0123456789"))


def _yaml_problem(exc: yaml.YAMLError) -> str:
    """A PyYAML error in one line: what, and where (line, column)."""
    mark = getattr(exc, "problem_mark", None)
    problem = getattr(exc, "problem", None)
    if problem and mark is not None:
        context = getattr(exc, "context", None)
        text = f"{context}: {problem}" if context else problem
        return f"{text} (line {mark.line + 1}, column {mark.column + 1})"
    return " ".join(str(exc).split())


def parse_yaml(text: str, where: str = "YAML") -> dict:
    """A map_server YAML document -> its top-level mapping (empty document: ``{}``).

    Malformed YAML, a key given twice, or a document that is not a ``key: value`` mapping
    raises MapIOError (one line).
    """
    try:
        doc = yaml.load(text, Loader=_MapYamlLoader)  # safe: a SafeLoader subclass
    except yaml.YAMLError as exc:
        raise MapIOError(f"{where}: not valid YAML: {_yaml_problem(exc)}") from None
    if doc is None:
        return {}
    if not isinstance(doc, dict):
        raise MapIOError(f"{where}: expected 'key: value' lines (a YAML mapping), got "
                         f"{type(doc).__name__} {_short(doc)}")
    return doc


def _short(value, limit: int = 60) -> str:
    text = " ".join(repr(value).split())
    return text if len(text) <= limit else text[:limit - 3] + "..."


def _number(meta: dict, key: str, where: str) -> float:
    v = meta[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise MapIOError(f"{where}: {key} must be a finite number (got {v!r})")
    return float(v)


def read_map_yaml(yaml_path: str | os.PathLike) -> dict:
    """Parse and check a map_server YAML. Returns a dict with ``image`` (absolute Path),
    ``resolution``, ``origin`` (x, y, yaw), ``negate`` (bool), ``occupied_thresh``,
    ``free_thresh`` and ``mode``."""
    path = Path(yaml_path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise MapIOError(f"map YAML not found: {path}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise MapIOError(f"cannot read map YAML {path}: {exc}") from None
    meta = parse_yaml(text, str(path))
    missing = [k for k in REQUIRED_KEYS if k not in meta]
    if missing:
        raise MapIOError(f"{path}: missing key(s) {', '.join(missing)}")
    image = meta["image"]
    if not isinstance(image, str) or not image:
        raise MapIOError(f"{path}: image must be a file name (got {image!r})")
    res = _number(meta, "resolution", str(path))
    if not res > 0:
        raise MapIOError(f"{path}: resolution must be > 0 (got {res})")
    origin = meta["origin"]
    if (not isinstance(origin, list) or len(origin) != 3
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool)
                       and math.isfinite(v) for v in origin)):
        raise MapIOError(f"{path}: origin must be [x, y, yaw] with 3 finite numbers "
                         f"(got {origin!r})")
    negate = meta["negate"]
    if negate not in (0, 1, True, False):
        raise MapIOError(f"{path}: negate must be 0 or 1 (got {negate!r})")
    occ_t = _number(meta, "occupied_thresh", str(path))
    free_t = _number(meta, "free_thresh", str(path))
    if not 0.0 <= free_t < occ_t <= 1.0:
        raise MapIOError(
            f"{path}: need 0 <= free_thresh < occupied_thresh <= 1 (got {free_t}, {occ_t})"
        )
    mode = meta.get("mode", "trinary")
    if mode not in MODES:
        raise MapIOError(f"{path}: mode must be one of {', '.join(MODES)} (got {mode!r})")
    img = Path(image)
    if not img.is_absolute():
        img = path.parent / img
    return {
        "image": img,
        "resolution": res,
        "origin": tuple(float(v) for v in origin),
        "negate": bool(negate),
        "occupied_thresh": occ_t,
        "free_thresh": free_t,
        "mode": mode,
    }


# --- reading -------------------------------------------------------------------------------


def pixels_to_occupancy(img: np.ndarray, negate: bool, occupied_thresh: float,
                        free_thresh: float, mode: str = "trinary") -> np.ndarray:
    """Image as read (row 0 = top; gray, BGR or BGRA uint8) -> int8 grid (row 0 = bottom).

    nav2 map_io semantics (see module docstring), including its trinary quirk of averaging the
    alpha channel in with the colours.
    """
    a = np.asarray(img)
    if a.dtype != np.uint8:
        raise MapIOError(f"map image must be 8-bit (got {a.dtype})")
    if a.ndim == 2:
        shade = a.astype(np.float64) / 255.0
        alpha = None
    elif a.ndim == 3 and a.shape[2] in (3, 4):
        chans = a[:, :, :3].astype(np.float64)
        alpha = a[:, :, 3] if a.shape[2] == 4 else None
        if mode == "trinary" and alpha is not None:
            shade = (chans.sum(axis=2) + alpha) / (4.0 * 255.0)
        else:
            shade = chans.mean(axis=2) / 255.0
    else:
        raise MapIOError(f"map image must be gray, BGR or BGRA (got shape {a.shape})")
    occ = shade if negate else 1.0 - shade
    out = np.full(a.shape[:2], -1, np.int8)
    if mode == "raw":
        v = np.round(shade * 255.0)
        ok = (v >= 0) & (v <= 100)
        out[ok] = v[ok].astype(np.int8)
    else:
        occupied = occ > occupied_thresh
        free = occ < free_thresh
        out[occupied] = 100
        out[free] = 0
        if mode == "scale":
            mid = ~occupied & ~free
            out[mid] = np.rint(
                (occ[mid] - free_thresh) / (occupied_thresh - free_thresh) * 100.0
            ).astype(np.int8)
            if alpha is not None:
                out[alpha != 255] = -1
    return np.ascontiguousarray(out[::-1])


UNROTATE_ROWS = 256  # output rows resampled at once by :func:`unrotate`


def unrotate(grid: np.ndarray, resolution: float, x: float, y: float, yaw: float
             ) -> tuple[np.ndarray, GridGeometry]:
    """A grid whose lower-left corner lies at (x, y) [m] with its rows turned by yaw [rad]
    (counter-clockwise, map_server's origin) -> the same map on an axis-aligned grid of the
    same resolution [m] that holds it whole: each cell takes the value of the source cell its
    centre falls in (nearest, so a turn by a multiple of 90 deg is exact), -1 (unknown)
    outside the source. A grid has no rotation of its own (:class:`GridGeometry`), and ROS
    tools that ignore the yaw would misplace the map by it."""
    h, w = grid.shape
    c, s = math.cos(yaw), math.sin(yaw)
    cu = np.array([0.0, w, 0.0, w]) * resolution  # the corners in the map's own frame [m]
    cv = np.array([0.0, 0.0, h, h]) * resolution
    wx, wy = x + c * cu - s * cv, y + s * cu + c * cv  # ... in the world
    eps = 1e-6 * resolution  # a corner on a cell boundary stays on it
    ox = math.floor((wx.min() + eps) / resolution) * resolution
    oy = math.floor((wy.min() + eps) / resolution) * resolution
    W = max(1, math.ceil((wx.max() - eps - ox) / resolution))
    H = max(1, math.ceil((wy.max() - eps - oy) / resolution))
    X = ox + (np.arange(W) + 0.5) * resolution - x  # output cell centres from the origin
    out = np.full((H, W), -1, np.int8)
    for r0 in range(0, H, UNROTATE_ROWS):  # a block of rows at a time: bounded memory
        Y = (oy + (np.arange(r0, min(H, r0 + UNROTATE_ROWS)) + 0.5) * resolution - y)[:, None]
        col = np.floor((c * X + s * Y) / resolution).astype(np.int64)
        row = np.floor((-s * X + c * Y) / resolution).astype(np.int64)
        ok = (col >= 0) & (col < w) & (row >= 0) & (row < h)
        block = out[r0:r0 + len(Y)]
        block[ok] = grid[row[ok], col[ok]]
    return out, GridGeometry(resolution, ox, oy, W, H)


def read_map_server(yaml_path: str | os.PathLike) -> tuple[np.ndarray, GridGeometry]:
    """Read a map_server map -> (int8 grid, row 0 = min y: 0 free, 100 occupied, -1 unknown,
    1..99 in scale mode; GridGeometry). A map with a non-zero origin yaw is turned onto an
    axis-aligned grid (:func:`unrotate`)."""
    meta = read_map_yaml(yaml_path)
    x, y, yaw = meta["origin"]
    img_path = meta["image"]
    if not img_path.is_file():
        raise MapIOError(f"{yaml_path}: image file not found: {img_path}")
    img = cv2.imread(str(img_path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise MapIOError(f"{yaml_path}: cannot decode image {img_path}")
    grid = pixels_to_occupancy(img, meta["negate"], meta["occupied_thresh"],
                               meta["free_thresh"], meta["mode"])
    if abs(yaw) > 1e-9:
        return unrotate(grid, meta["resolution"], x, y, yaw)
    h, w = grid.shape
    return grid, GridGeometry(meta["resolution"], x, y, w, h)


# --- writing -------------------------------------------------------------------------------


def occupancy_to_pixels(grid_int8: np.ndarray, p_free: float = 0.35,
                        p_occ: float = 0.65) -> np.ndarray:
    """int8 grid (row 0 = min y) -> trinary uint8 image (row 0 = top): 254 / 0 / 205."""
    cls = classify(grid_int8, p_free, p_occ)
    img = np.full(cls.shape, PIX_UNKNOWN, np.uint8)
    img[cls == FREE] = PIX_FREE
    img[cls == OCCUPIED] = PIX_OCCUPIED
    return np.ascontiguousarray(img[::-1])


def atomic_write(path: Path, data: bytes) -> None:
    """Write via a temporary file in the same directory, fsync, rename, fsync the directory:
    readers never see half a file, and after a crash the file is the old one or the new one."""
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            os.fchmod(f.fileno(), 0o644)  # mkstemp creates 0600
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
    try:
        dfd = os.open(path.parent, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(dfd)
    except OSError:
        pass  # some file systems cannot sync a directory
    finally:
        os.close(dfd)


def _check_grid(grid_int8: np.ndarray, geom: GridGeometry) -> np.ndarray:
    """:func:`common.grid.check_grid`, as a MapIOError."""
    try:
        return check_grid(grid_int8, geom)
    except GridError as exc:
        raise MapIOError(str(exc)) from None


def write_map_server(yaml_path: str | os.PathLike, grid_int8: np.ndarray, geom: GridGeometry,
                     p_free: float = 0.35, p_occ: float = 0.65) -> tuple[Path, Path]:
    """Write ``<name>.yaml`` + ``<name>.pgm`` (P5, trinary), readable by ROS/nav2 map_server.

    Cells are classified with ``p_free`` / ``p_occ`` (common.grid.classify). Parent directories
    are created; each file is written atomically. Returns (yaml_path, pgm_path).
    """
    g = _check_grid(grid_int8, geom)
    if not 0.0 < p_free <= p_occ < 1.0:
        raise MapIOError(f"need 0 < p_free <= p_occ < 1 (got {p_free}, {p_occ})")
    ypath = Path(yaml_path)
    if ypath.suffix.lower() not in (".yaml", ".yml"):
        raise MapIOError(f"map YAML path must end in .yaml or .yml: {ypath}")
    pgm = ypath.with_suffix(".pgm")
    img = occupancy_to_pixels(g, p_free, p_occ)
    h, w = img.shape
    header = f"P5\n# topoexplore map, {geom.resolution} m/pixel\n{w} {h}\n255\n".encode("ascii")
    meta = {
        "image": pgm.name,
        "resolution": float(geom.resolution),
        "origin": [float(geom.origin_x), float(geom.origin_y), 0.0],
        "negate": 0,
        "occupied_thresh": YAML_OCCUPIED_THRESH,
        "free_thresh": YAML_FREE_THRESH,
        "mode": "trinary",
    }
    text = yaml.safe_dump(meta, sort_keys=False, default_flow_style=None)
    try:
        ypath.parent.mkdir(parents=True, exist_ok=True)
        atomic_write(pgm, header + img.tobytes())
        atomic_write(ypath, text.encode("utf-8"))
    except OSError as exc:
        raise MapIOError(f"cannot write map {ypath}: {exc}") from None
    return ypath, pgm


def write_png(path: str | os.PathLike, image: np.ndarray) -> Path:
    """Write a uint8 gray/BGR/BGRA image as PNG (parents created, atomic). Returns the path."""
    p = Path(path)
    a = np.asarray(image)
    if a.dtype != np.uint8 or not (a.ndim == 2 or (a.ndim == 3 and a.shape[2] in (3, 4))):
        raise MapIOError(f"PNG image must be uint8 gray/BGR/BGRA (got {a.dtype} {a.shape})")
    if a.size == 0:
        raise MapIOError("PNG image is empty")
    if p.suffix.lower() != ".png":
        raise MapIOError(f"PNG path must end in .png: {p}")
    ok, buf = cv2.imencode(".png", a)
    if not ok:
        raise MapIOError(f"cannot encode PNG for {p}")
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
        atomic_write(p, buf.tobytes())
    except OSError as exc:
        raise MapIOError(f"cannot write {p}: {exc}") from None
    return p
