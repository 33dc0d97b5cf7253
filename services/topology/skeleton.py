"""Free-mask cleaning and thinning kernels for the topology core (pure, no I/O).

Paper §2.1 (Figs. 1-2): the skeleton of the known free space is obtained by thinning. Here:

- :func:`clean_free_mask` - fill small non-free islands, 3x3-style opening, break diagonal-only
  free contacts (THINNING_NOTES "Spurs and mask cleaning").
- :func:`zhang_suen` - Zhang & Suen (1984) parallel thinning in numba that only re-examines pixels
  next to a pixel deleted in the previous iteration (THINNING_NOTES: "numba Zhang-Suen re-checking
  only border pixels").
- :func:`one_pixel_wide` - removes the "staircase" pixels Zhang-Suen leaves (a pixel whose two
  4-neighbours are 8-adjacent to each other), so neighbour counting finds end and branch pixels
  correctly (paper Fig. 3(a)/(b)).

All arrays handled by the numba kernels carry a one-pixel zero border (callers pad), which keeps
the kernels free of bounds checks.
"""

from __future__ import annotations

import cv2
import numpy as np
from numba import njit

__all__ = [
    "clean_free_mask",
    "zhang_suen",
    "one_pixel_wide",
    "skeletonize",
    "SKELETON_METHODS",
]

SKELETON_METHODS = ("zhang", "skimage", "lee")

# 8-neighbourhood in counter-clockwise order starting east (row axis points "down" in the array,
# which only mirrors the picture; the kernels are symmetric in that respect).
_DR = np.array([0, -1, -1, -1, 0, 1, 1, 1], dtype=np.int64)
_DC = np.array([1, 1, 0, -1, -1, -1, 0, 1], dtype=np.int64)


def clean_free_mask(free: np.ndarray, hole_cells: int, open_cells: int) -> np.ndarray:
    """Clean a boolean free mask; return uint8 0/1 of the same shape.

    1. Non-free islands (8-connected) of at most ``hole_cells`` cells that do not touch the array
       border become free (sensor noise, unseen specks).
    2. Morphological opening with a (2*open_cells+1)^2 square (removes free slivers that leak
       through walls between beams).
    3. Diagonal-only contacts of free cells are broken (a 1-cell diagonal wall must not be crossed
       by an 8-connected skeleton).
    The result at a cell depends only on the input within ``hole_cells + 2*open_cells + 1`` cells,
    which the incremental update relies on.
    """
    m = np.ascontiguousarray(free, dtype=np.uint8)
    h, w = m.shape
    if hole_cells > 0 and m.size:
        inv = (m == 0).astype(np.uint8)
        n, lab, stats, _ = cv2.connectedComponentsWithStats(inv, connectivity=8)
        if n > 1:
            left = stats[:, cv2.CC_STAT_LEFT]
            top = stats[:, cv2.CC_STAT_TOP]
            ww = stats[:, cv2.CC_STAT_WIDTH]
            hh = stats[:, cv2.CC_STAT_HEIGHT]
            small = stats[:, cv2.CC_STAT_AREA] <= hole_cells
            small &= (left > 0) & (top > 0) & (left + ww < w) & (top + hh < h)
            small[0] = False  # label 0 = the free cells themselves
            if small.any():
                m = m | small[lab].astype(np.uint8)
    if open_cells > 0:
        k = 2 * int(open_cells) + 1
        m = cv2.morphologyEx(m, cv2.MORPH_OPEN, np.ones((k, k), np.uint8))
    _break_diagonals(m)
    return m


@njit(cache=True)
def _break_diagonals(m):  # pragma: no cover - compiled
    """Clear one cell of every 2x2 block whose free cells touch only diagonally (in place)."""
    h, w = m.shape
    for r in range(h - 1):
        for c in range(w - 1):
            a = m[r, c]
            b = m[r, c + 1]
            d = m[r + 1, c]
            e = m[r + 1, c + 1]
            if a and e and not b and not d:
                m[r, c] = 0
            elif b and d and not a and not e:
                m[r, c + 1] = 0


@njit(cache=True)
def _zs_deletable(img, r, c, sub):  # pragma: no cover - compiled
    p2 = img[r - 1, c]
    p3 = img[r - 1, c + 1]
    p4 = img[r, c + 1]
    p5 = img[r + 1, c + 1]
    p6 = img[r + 1, c]
    p7 = img[r + 1, c - 1]
    p8 = img[r, c - 1]
    p9 = img[r - 1, c - 1]
    b = p2 + p3 + p4 + p5 + p6 + p7 + p8 + p9
    if b < 2 or b > 6:
        return False
    a = ((p2 == 0 and p3 == 1) + (p3 == 0 and p4 == 1) + (p4 == 0 and p5 == 1)
         + (p5 == 0 and p6 == 1) + (p6 == 0 and p7 == 1) + (p7 == 0 and p8 == 1)
         + (p8 == 0 and p9 == 1) + (p9 == 0 and p2 == 1))
    if a != 1:
        return False
    if sub == 0:
        return p2 * p4 * p6 == 0 and p4 * p6 * p8 == 0
    return p2 * p4 * p8 == 0 and p2 * p6 * p8 == 0


@njit(cache=True)
def zhang_suen(img):  # pragma: no cover - compiled
    """Zhang-Suen thinning of a uint8 0/1 image with a zero border, in place; returns iterations.

    Only pixels 8-adjacent to a pixel deleted in the previous iteration are re-examined, which
    gives the same result as the classic full sweep (a pixel's test depends on its 3x3 window).
    """
    h, w = img.shape
    cand = np.empty(h * w, np.int64)
    n = 0
    for r in range(1, h - 1):
        for c in range(1, w - 1):
            if img[r, c] and (img[r - 1, c] == 0 or img[r + 1, c] == 0 or img[r, c - 1] == 0
                              or img[r, c + 1] == 0 or img[r - 1, c - 1] == 0
                              or img[r - 1, c + 1] == 0 or img[r + 1, c - 1] == 0
                              or img[r + 1, c + 1] == 0):
                cand[n] = r * w + c
                n += 1
    stamp = np.zeros(h * w, np.int32)
    dele = np.empty(h * w, np.int64)
    nxt = np.empty(h * w, np.int64)
    it = 0
    while n > 0:
        it += 1
        nd = 0
        for sub in range(2):
            start = nd
            for k in range(n):
                idx = cand[k]
                r = idx // w
                c = idx - r * w
                if img[r, c] and _zs_deletable(img, r, c, sub):
                    dele[nd] = idx
                    nd += 1
            for k in range(start, nd):
                idx = dele[k]
                r = idx // w
                img[r, idx - r * w] = 0
        m = 0
        for k in range(nd):
            idx = dele[k]
            r = idx // w
            c = idx - r * w
            for dr in range(-1, 2):
                for dc in range(-1, 2):
                    rr = r + dr
                    cc = c + dc
                    j = rr * w + cc
                    if img[rr, cc] and stamp[j] != it:
                        stamp[j] = it
                        nxt[m] = j
                        m += 1
        tmp = cand
        cand = nxt
        nxt = tmp
        n = m
    return it


@njit(cache=True)
def _nbcount(img, r, c):  # pragma: no cover - compiled
    return (img[r - 1, c - 1] + img[r - 1, c] + img[r - 1, c + 1] + img[r, c - 1]
            + img[r, c + 1] + img[r + 1, c - 1] + img[r + 1, c] + img[r + 1, c + 1])


@njit(cache=True)
def _redundant(img, r, c):  # pragma: no cover - compiled
    """True if (r, c) is a simple, non-end pixel with two orthogonal 4-neighbours set."""
    n = img[r - 1, c]
    e = img[r, c + 1]
    s = img[r + 1, c]
    wv = img[r, c - 1]
    if not ((n and e) or (e and s) or (s and wv) or (wv and n)):
        return False
    if _nbcount(img, r, c) < 2:
        return False
    # Yokoi 8-connectivity number (x_k counter-clockwise from east); simple iff == 1
    x0 = 1 - img[r, c + 1]
    x1 = 1 - img[r - 1, c + 1]
    x2 = 1 - img[r - 1, c]
    x3 = 1 - img[r - 1, c - 1]
    x4 = 1 - img[r, c - 1]
    x5 = 1 - img[r + 1, c - 1]
    x6 = 1 - img[r + 1, c]
    x7 = 1 - img[r + 1, c + 1]
    nc = (x0 - x0 * x1 * x2) + (x2 - x2 * x3 * x4) + (x4 - x4 * x5 * x6) + (x6 - x6 * x7 * x0)
    return nc == 1


@njit(cache=True)
def one_pixel_wide(img, r0, r1, c0, c1):  # pragma: no cover - compiled
    """Delete staircase pixels inside rows r0..r1-1, cols c0..c1-1 (in place, zero border).

    Sequential (raster order, repeated until stable), so each deletion sees the previous ones and
    8-connectivity is preserved. Returns the number of deleted pixels.
    """
    h, w = img.shape
    r0 = max(r0, 1)
    c0 = max(c0, 1)
    r1 = min(r1, h - 1)
    c1 = min(c1, w - 1)
    total = 0
    changed = True
    while changed:
        changed = False
        for r in range(r0, r1):
            for c in range(c0, c1):
                if img[r, c] and _redundant(img, r, c):
                    img[r, c] = 0
                    total += 1
                    changed = True
    return total


def skeletonize(mask01: np.ndarray, method: str = "zhang") -> np.ndarray:
    """One-pixel-wide 8-connected skeleton of a uint8 0/1 mask that has a zero border.

    ``method``: "zhang" (numba Zhang-Suen, default), "skimage" (scikit-image ``skeletonize``),
    "lee" (scikit-image Lee 1994). Every result goes through :func:`one_pixel_wide`.
    Returns a new uint8 0/1 array.
    """
    if method == "zhang":
        out = np.array(mask01, dtype=np.uint8, copy=True)
        zhang_suen(out)
    elif method in ("skimage", "lee"):
        from skimage.morphology import skeletonize as sk

        kw = {"method": "lee"} if method == "lee" else {}
        out = sk(mask01.astype(bool), **kw).astype(np.uint8)
    else:
        raise ValueError(f"unknown skeleton method {method!r} (use one of {SKELETON_METHODS})")
    h, w = out.shape
    one_pixel_wide(out, 1, h - 1, 1, w - 1)
    return out


# Entry kernels and the argument types the topology core calls them with (common.warm).
WARM = {
    "_break_diagonals": ("(uint8[:, ::1],)",),
    "zhang_suen": ("(uint8[:, ::1],)",),
    "one_pixel_wide": ("(uint8[:, ::1], int64, int64, int64, int64)",),
}
