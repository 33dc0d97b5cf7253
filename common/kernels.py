"""Grid kernels shared by the services and the simulator's truth: one Bresenham line, one
8-connected flood fill.

numba, pure, no I/O. Both write into caller-owned buffers and return a count, so a caller that
runs them thousands of times (the mapper: one line per beam) allocates once.

Note on numba's cache: a cached caller embeds the code of these kernels, and numba does not
notice when a function it calls from another file changes. After editing this module, run
``topoexplore warmup --clear`` (it deletes the package's cached kernels and compiles them
again), or the callers keep running the old kernel.
"""

from __future__ import annotations

from numba import njit

__all__ = ["line_length", "bresenham", "flood_fill"]


@njit(cache=True, nogil=True)
def line_length(r0, c0, r1, c1):  # pragma: no cover - compiled
    """Number of cells :func:`bresenham` writes for (r0, c0) -> (r1, c1): max(|dr|, |dc|) + 1."""
    return max(abs(r1 - r0), abs(c1 - c0)) + 1


@njit(cache=True, nogil=True)
def bresenham(r0, c0, r1, c1, rows, cols):  # pragma: no cover - compiled
    """Cells of the integer Bresenham line from (r0, c0) to (r1, c1), both ends included.

    Writes them in order from the start into ``rows[:n]`` and ``cols[:n]`` and returns n
    (= :func:`line_length`; the buffers must hold that many). Consecutive cells are
    8-adjacent; a step is diagonal where the error term says both coordinates advance.
    Indices are not checked against any grid: cells are plain integer pairs.
    """
    dr = abs(r1 - r0)
    dc = abs(c1 - c0)
    sr = 1 if r1 > r0 else -1
    sc = 1 if c1 > c0 else -1
    err = dc - dr
    r = r0
    c = c0
    n = 0
    while True:
        rows[n] = r
        cols[n] = c
        n += 1
        if r == r1 and c == c1:
            return n
        e2 = 2 * err
        if e2 > -dr:
            err -= dr
            c += sc
        if e2 < dc:
            err += dc
            r += sr


@njit(cache=True, nogil=True)
def flood_fill(img, r0, c0, old, new, out):  # pragma: no cover - compiled
    """8-connected flood fill of the cells equal to ``old`` from seed (r0, c0), in place.

    Every reached cell is set to ``new`` (``new != old``) and its flat index ``r * w + c`` is
    written to ``out`` in breadth-first order (the seed first, then neighbours in raster
    order of the 3x3 window: callers that break ties by visiting order rely on it). Returns
    the number of filled cells; 0 if the seed is outside ``img`` or not ``old``. ``out`` must
    hold the component (at most ``img.size``). Bounds-checked: works on arrays with or without
    a zero border.
    """
    h, w = img.shape
    if r0 < 0 or r0 >= h or c0 < 0 or c0 >= w or img[r0, c0] != old:
        return 0
    img[r0, c0] = new
    out[0] = r0 * w + c0
    n = 1
    head = 0
    while head < n:  # out doubles as the queue
        p = out[head]
        head += 1
        r = p // w
        c = p - r * w
        for rr in range(max(r - 1, 0), min(r + 2, h)):
            for cc in range(max(c - 1, 0), min(c + 2, w)):
                if img[rr, cc] == old:
                    img[rr, cc] = new
                    out[n] = rr * w + cc
                    n += 1
    return n
