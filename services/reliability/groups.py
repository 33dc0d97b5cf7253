"""The frontier-group kernel of the reliability core (numba).

A module of its own: only the frontier-group test (``reliability.frontier_group`` > 0, off by
default) runs it, and without it the reliability process never imports numba (about 60 MB
resident).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from topoexplore.common.kernels import flood_fill

__all__ = ["mark_groups"]


@njit(cache=True)
def mark_groups(front, cells, min_cells):  # pragma: no cover - compiled
    """In place on ``front`` (uint8, 1 = frontier): cells of 8-connected groups of at least
    min_cells become 3, the others 2. Visits only the listed frontier cells: they are few,
    and labelling the whole grid costs ~100 x more at 1000 x 1000."""
    w = front.shape[1]
    members = np.empty(cells.shape[0], np.int64)  # a group holds listed cells only
    for k in range(cells.shape[0]):
        m = flood_fill(front, cells[k, 0], cells[k, 1], 1, 2, members)
        if m >= min_cells:
            for i in range(m):
                q = members[i]
                front[q // w, q - (q // w) * w] = 3


# Entry kernels and the argument types the reliability core calls them with (common.warm).
WARM = {
    "mark_groups": ("(uint8[:, ::1], int64[:, ::1], int64)",),
}
