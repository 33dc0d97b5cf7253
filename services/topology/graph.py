"""Skeleton -> topological graph kernels (numba, pure, no I/O).

Paper §2.2 and Fig. 3: a skeleton pixel with one neighbour is an *end node*, with three or more a
*branch node* (adjacent branch pixels form one node); a *corner node* is inserted where the
straight line between two nodes is blocked, at the edge pixel farthest from that line.

Conventions: skeleton/mask arrays are uint8 0/1 with a one-pixel zero border; pixels are handled
as flat indices ``r * w + c`` into such an array. Node kinds: 0 end, 1 branch, 2 corner.

The helpers of the long kernels are ``inline='always'`` (inlined in numba's IR): compiled as
functions of their own they would add about 1.5 s to the first, uncached start.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from topoexplore.common.kernels import bresenham, flood_fill
from topoexplore.services.topology.skeleton import _redundant

__all__ = ["find_entry", "build_graph", "prune_spurs", "split_corners", "KIND_NAMES"]

END, BRANCH, CORNER = 0, 1, 2
KIND_NAMES = ("end", "branch", "corner")
MIN_SELF_LOOP = 8  # self-loop edges with fewer pixels are thinning artefacts, not loops


@njit(cache=True)
def _nb(img, r, c):  # pragma: no cover - compiled
    return (img[r - 1, c - 1] + img[r - 1, c] + img[r - 1, c + 1] + img[r, c - 1]
            + img[r, c + 1] + img[r + 1, c - 1] + img[r + 1, c] + img[r + 1, c + 1])


@njit(cache=True)
def find_entry(mask, skel, r0, c0, max_steps):  # pragma: no cover - compiled
    """Breadth-first search through ``mask`` (8-connected) from (r0, c0) to the nearest skeleton
    pixel; returns its flat index or -1 (none within ``max_steps`` visited cells).

    A search, not a fill: it stops at the first skeleton pixel (usually a few cells away), where
    :func:`topoexplore.common.kernels.flood_fill` would visit the robot's whole free component.
    """
    h, w = mask.shape
    if mask[r0, c0] == 0:
        return -1
    start = r0 * w + c0
    if skel[r0, c0]:
        return start
    seen = np.zeros(h * w, np.uint8)
    q = np.empty(min(h * w, max_steps + 9), np.int64)
    q[0] = start
    seen[start] = 1
    head = 0
    n = 1
    while head < n:
        p = q[head]
        head += 1
        r = p // w
        c = p - r * w
        for dr in range(-1, 2):
            for dc in range(-1, 2):
                rr = r + dr
                cc = c + dc
                j = rr * w + cc
                if mask[rr, cc] and not seen[j]:
                    if skel[rr, cc]:
                        return j
                    seen[j] = 1
                    if n < q.shape[0]:
                        q[n] = j
                        n += 1
        if n >= q.shape[0]:
            break
    return -1


@njit(cache=True)
def component_peak(mask, dt, r0, c0):  # pragma: no cover - compiled
    """Flat index of the cell with the largest ``dt`` in the 8-connected ``mask`` component of
    (r0, c0), the first in breadth-first order on ties; (r0, c0) must be in the mask (0/1).
    Used when thinning erased a whole component (Zhang-Suen removes 2x2 remnants).
    ``mask`` is marked by the fill and restored before returning."""
    h, w = mask.shape
    comp = np.empty(h * w, np.int64)
    n = flood_fill(mask, r0, c0, 1, 2, comp)
    best = r0 * w + c0
    bv = -1.0
    for k in range(n):
        p = comp[k]
        r = p // w
        c = p - r * w
        if dt[r, c] > bv:
            bv = dt[r, c]
            best = p
    for k in range(n):
        p = comp[k]
        mask[p // w, p - (p // w) * w] = 1
    return best


@njit(cache=True)
def build_graph(skel, entry, seen, nodeid, buf):  # pragma: no cover - compiled
    """Graph of the skeleton component containing flat pixel ``entry`` (a skeleton pixel).

    ``skel`` is uint8 0/1 and writable (the component fill marks it, then restores it).
    ``seen`` (uint8, all 0) and ``nodeid`` (int32, all -1) are flat scratch arrays of the image
    size; ``seen`` is restored on return, ``nodeid`` must be restored with :func:`reset_nodeid`
    after the result has been used; ``buf`` is an int64 scratch array of the image size (this
    keeps the cost proportional to the component, not to the image).

    Returns (node_pix, node_kind, ea, eb, off, pix, nodeid, comp):
    node_pix[k] representative pixel of node k (branch: cluster pixel nearest the centroid),
    node_kind[k] 0/1/2, edge e goes from node ea[e] to eb[e] along pix[off[e]:off[e+1]] (both
    node pixels included), nodeid[p] = node of pixel p or -1, comp = the component's pixels.
    A cycle without any end/branch pixel gets one corner node (its smallest pixel) and a
    self-loop edge.
    """
    w = skel.shape[1]
    # the component, breadth-first (node and edge numbering follow this order); the fill
    # marks it 2 in skel (0/1), restored at once
    n = flood_fill(skel, entry // w, entry - (entry // w) * w, 1, 2, buf)
    comp = buf[:n].copy()
    for k in range(n):
        p = comp[k]
        skel[p // w, p - (p // w) * w] = 1
    node_pix = np.empty(n, np.int64)
    node_kind = np.empty(n, np.int8)
    nn = 0
    for k in range(n):  # end nodes: at most one neighbour
        p = comp[k]
        if _nb(skel, p // w, p - (p // w) * w) <= 1:
            nodeid[p] = nn
            node_pix[nn] = p
            node_kind[nn] = END
            nn += 1
    nn = _branch_nodes(skel, comp, nodeid, node_pix, node_kind, nn, seen)
    if nn == 0:  # an isolated cycle: give it a corner node so it is representable
        p = comp.min()
        nodeid[p] = 0
        node_pix[0] = p
        node_kind[0] = CORNER
        nn = 1
    node_pix = node_pix[:nn].copy()
    node_kind = node_kind[:nn].copy()
    ea, eb, off, pix = _trace_edges(skel, comp, nodeid, node_pix, seen)
    for k in range(n):
        seen[comp[k]] = 0
    return node_pix, node_kind, ea, eb, off, pix, nodeid, comp


@njit(cache=True, inline='always')
def _branch_nodes(skel, comp, nodeid, node_pix, node_kind, nn, seen):  # pragma: no cover
    """One branch node per 8-connected cluster of pixels with >= 3 neighbours, numbered from
    ``nn`` in ``comp`` order of the clusters' first pixels, at the cluster pixel nearest the
    cluster's centroid (the first in fill order on ties); returns the node count. ``seen``
    (flat, 0 on ``comp``) is the fill's label image (1 = unassigned branch pixel) and is left
    0 on ``comp``."""
    h, w = skel.shape
    n = comp.shape[0]
    for k in range(n):
        p = comp[k]
        if _nb(skel, p // w, p - (p // w) * w) >= 3:
            seen[p] = 1
    lab = seen.reshape((h, w))
    q = np.empty(n, np.int64)
    for k in range(n):
        p = comp[k]
        if seen[p] != 1:
            continue
        m = flood_fill(lab, p // w, p - (p // w) * w, 1, 2, q)
        sr = 0.0
        sc = 0.0
        for t in range(m):
            nodeid[q[t]] = nn
            sr += q[t] // w
            sc += q[t] - (q[t] // w) * w
        sr /= m
        sc /= m
        best = q[0]
        bd = 1e18
        for t in range(m):
            xr = q[t] // w
            d = (xr - sr) ** 2 + (q[t] - xr * w - sc) ** 2
            if d < bd:
                bd = d
                best = q[t]
        node_pix[nn] = best
        node_kind[nn] = BRANCH
        nn += 1
    for k in range(n):
        seen[comp[k]] = 0
    return nn


@njit(cache=True, inline='always')
def _trace_edges(skel, comp, nodeid, node_pix, seen):  # pragma: no cover - compiled
    """Edges of the component, from each node pixel in ``comp`` order (:func:`_edges_from`).

    Returns (ea, eb, off, pix) as in :func:`build_graph`; traced pixels are marked 2 in
    ``seen``, which the caller clears.
    """
    n = comp.shape[0]
    nn = node_pix.shape[0]
    cap = 3 * n + 24 * nn + 16
    pix = np.empty(cap, np.int64)
    off = np.empty(8 * nn + 2, np.int64)
    ea = np.empty(8 * nn + 1, np.int32)
    eb = np.empty(8 * nn + 1, np.int32)
    ne = 0
    npix = 0
    off[0] = 0
    for k in range(n):
        p = comp[k]
        if nodeid[p] >= 0:
            npix, ne = _edges_from(skel, nodeid, node_pix, seen, p, pix, npix, ea, eb, off, ne)
    return ea[:ne].copy(), eb[:ne].copy(), off[:ne + 1].copy(), pix[:npix].copy()


@njit(cache=True, inline='always')
def _edges_from(skel, nodeid, node_pix, seen, p, pix, npix, ea, eb, off,
                ne):  # pragma: no cover - compiled
    """Append the edges that leave node pixel ``p``: a two-pixel edge to each touching pixel of
    another node (once per pair), and the chain traced from each untraced edge-pixel neighbour
    (dropped at a dead end, on meeting a traced pixel, or as a self-loop shorter than
    MIN_SELF_LOOP). Edges start and end at their nodes' own pixels. Returns (npix, ne)."""
    w = skel.shape[1]
    a = nodeid[p]
    r = p // w
    c = p - r * w
    for dr in range(-1, 2):
        for dc in range(-1, 2):
            q = (r + dr) * w + c + dc
            if (dr == 0 and dc == 0) or not skel[r + dr, c + dc]:
                continue
            b = nodeid[q]
            if (b >= 0 and (b == a or q < p)) or (b < 0 and seen[q] == 2):
                continue
            start = npix
            if node_pix[a] != p:
                pix[npix] = node_pix[a]
                npix += 1
            pix[npix] = p
            pix[npix + 1] = q
            npix += 2
            if b < 0:  # an edge pixel: trace the chain
                npix, ok = _walk(skel, nodeid, seen, pix, npix, p, q)
                b = nodeid[pix[npix - 1]]
                if not ok or (b == a and npix - start < MIN_SELF_LOOP):
                    npix = start
                    continue
            if node_pix[b] != pix[npix - 1]:
                pix[npix] = node_pix[b]
                npix += 1
            ea[ne] = a
            eb[ne] = b
            ne += 1
            off[ne] = npix
    return npix, ne


@njit(cache=True, inline='always')
def _walk(skel, nodeid, seen, pix, npix, prev, cur):  # pragma: no cover - compiled
    """Follow the one-pixel-wide chain from prev through cur (both in pix already) to the next
    node pixel, appending the pixels and marking them 2 in ``seen``. At a fork the last
    neighbour in raster order is taken. Returns (npix, ok); ok is False at a dead end or at a
    pixel traced before."""
    w = skel.shape[1]
    seen[cur] = 2
    while True:
        cr = cur // w
        cc = cur - cr * w
        nxt = -1
        for dr in range(-1, 2):
            for dc in range(-1, 2):
                j = (cr + dr) * w + cc + dc
                if (dr != 0 or dc != 0) and skel[cr + dr, cc + dc] and j != prev:
                    nxt = j
        if nxt < 0:
            return npix, False
        pix[npix] = nxt
        npix += 1
        if nodeid[nxt] >= 0:
            return npix, True
        if seen[nxt] == 2:
            return npix, False
        seen[nxt] = 2
        prev = cur
        cur = nxt


@njit(cache=True)
def reset_nodeid(nodeid, comp):  # pragma: no cover - compiled
    for k in range(comp.shape[0]):
        nodeid[comp[k]] = -1


@njit(cache=True)
def decimate(pix, s0, s1, w):  # pragma: no cover - compiled
    """Drop interior polyline pixels where the step direction does not change (lossless).

    Returns (keep, koff): kept positions into ``pix`` for sub-edge k are keep[koff[k]:koff[k+1]].
    """
    m = s0.shape[0]
    keep = np.empty(pix.shape[0] + 2 * m, np.int64)
    koff = np.empty(m + 1, np.int64)
    koff[0] = 0
    n = 0
    for k in range(m):
        a = s0[k]
        b = s1[k]
        keep[n] = a
        n += 1
        for i in range(a + 1, b):
            p0 = pix[i - 1]
            p1 = pix[i]
            p2 = pix[i + 1]
            if p1 - p0 != p2 - p1:
                keep[n] = i
                n += 1
        if b > a:
            keep[n] = b
            n += 1
        koff[k + 1] = n
    return keep[:n].copy(), koff


@njit(cache=True)
def edge_lengths(pix, off, w):  # pragma: no cover - compiled
    """Polyline length of every edge in pixels (1 per straight step, sqrt(2) per diagonal)."""
    ne = off.shape[0] - 1
    out = np.zeros(ne)
    for e in range(ne):
        s = 0.0
        for k in range(off[e] + 1, off[e + 1]):
            a = pix[k - 1]
            b = pix[k]
            ar = a // w
            br = b // w
            s += ((ar - br) ** 2 + ((a - ar * w) - (b - br * w)) ** 2) ** 0.5
        out[e] = s
    return out


@njit(cache=True)
def _unknown_at(grid, mask, r, c):  # pragma: no cover - compiled
    """Grid cell (r, c) is unknown and not filled in by the cleaning (outside = unknown)."""
    h, w = grid.shape
    if r < 0 or c < 0 or r >= h or c >= w:
        return True
    return grid[r, c] < 0 and mask[r + 1, c + 1] == 0


@njit(cache=True)
def frontier_group_near(grid, mask, r0, c0, rad):  # pragma: no cover - compiled
    """Size of the largest 8-connected group of frontier cells within rad cells of padded
    pixel (r0, c0). Frontier = free in the cleaned mask and 4-adjacent to an unknown grid cell
    that the cleaning did not fill (speckles inside free space are not frontier). ``grid`` is
    the unpadded int8 map, ``mask`` the padded cleaned free mask.
    """
    front = _frontier_window(grid, mask, r0, c0, rad)
    n = front.shape[0]
    cells = np.empty(n * n, np.int64)
    best = 0
    for i in range(n):
        for j in range(n):
            if front[i, j] == 1:
                best = max(best, flood_fill(front, i, j, 1, 2, cells))
    return best


@njit(cache=True, inline='always')
def _frontier_window(grid, mask, r0, c0, rad):  # pragma: no cover - compiled
    """The frontier cells (1, else 0) of :func:`frontier_group_near` in the disc of radius rad
    around padded pixel (r0, c0), as a square uint8 window of side 2 * (int(rad) + 1) + 1."""
    h, w = grid.shape
    ir = int(rad) + 1
    n = 2 * ir + 1
    front = np.zeros((n, n), np.uint8)
    r2 = rad * rad
    for i in range(n):
        r = r0 - 1 - ir + i  # grid row
        if r < 0 or r >= h:
            continue
        for j in range(n):
            c = c0 - 1 - ir + j
            if c < 0 or c >= w or (i - ir) ** 2 + (j - ir) ** 2 > r2:
                continue
            if mask[r + 1, c + 1] == 0:
                continue
            if (_unknown_at(grid, mask, r - 1, c) or _unknown_at(grid, mask, r + 1, c)
                    or _unknown_at(grid, mask, r, c - 1) or _unknown_at(grid, mask, r, c + 1)):
                front[i, j] = 1
    return front


@njit(cache=True)
def prune_spurs(skel, node_pix, node_kind, ea, eb, off, pix, nodeid, dt,
                spur_px, factor, spur_max_px, grid, mask, front_px,
                front_cells):  # pragma: no cover - compiled
    """One round of graph-based spur pruning, in place on ``skel``; returns the number cut.

    A leaf edge (end node of degree 1 -- branch node) is cut when its length [px] is below
    clip(factor * dt[branch pixel], spur_px, spur_max_px). A branch node never loses all its
    edges (the longest is kept). The spur's pixels are erased except the branch pixel, then the
    branch cluster's dangling pixels and staircase pixels are cleaned so the skeleton stays
    one pixel wide.

    Frontier spurs: a short leaf whose end pixel has a group of >= ``front_cells`` frontier
    cells (:func:`frontier_group_near`) within dt[end] + front_px [px] is where the known map
    opens into unknown space (a corridor bending out of sight, a door seen edge-on); it is
    kept, at most one per branch node (the longest: an open end can fork into two spurs).
    ``front_cells <= 0`` disables this.
    """
    w = skel.shape[1]
    lens = edge_lengths(pix, off, w)
    cut, ncut = _spur_cuts(node_pix, node_kind, ea, eb, lens, dt, w, spur_px, factor,
                           spur_max_px, grid, mask, front_px, front_cells)
    _keep_longest(ea, eb, lens, cut, ncut)
    total = 0
    for e in range(ea.shape[0]):
        if cut[e]:
            total += 1
            _erase_spur(skel, node_kind, ea, eb, off, pix, nodeid, e)
    return total


@njit(cache=True, inline='always')
def _spur_cuts(node_pix, node_kind, ea, eb, lens, dt, w, spur_px, factor, spur_max_px, grid,
               mask, front_px, front_cells):  # pragma: no cover - compiled
    """The leaf edges shorter than their threshold, less the longest frontier spur of each
    branch node (:func:`prune_spurs`). Returns (cut per edge, cut edges per node)."""
    nn = node_pix.shape[0]
    ne = ea.shape[0]
    cut = np.zeros(ne, np.bool_)
    ncut = np.zeros(nn, np.int64)
    keep_front = np.full(nn, -1, np.int64)
    for e in range(ne):
        a = ea[e]
        b = eb[e]
        if node_kind[a] == END and node_kind[b] == BRANCH:
            j = b
        elif node_kind[b] == END and node_kind[a] == BRANCH:
            j = a
        else:
            continue
        bp = node_pix[j]
        thr = factor * dt[bp // w, bp - (bp // w) * w]
        thr = min(max(thr, spur_px), spur_max_px)
        if lens[e] < thr:
            if front_cells > 0:
                ep = node_pix[a + b - j]
                er = ep // w
                ec = ep - er * w
                if frontier_group_near(grid, mask, er, ec,
                                       dt[er, ec] + front_px) >= front_cells:
                    if keep_front[j] < 0 or lens[e] > lens[keep_front[j]]:
                        keep_front[j] = e
            cut[e] = True
            ncut[j] += 1
    for j in range(nn):
        if keep_front[j] >= 0:
            cut[keep_front[j]] = False
            ncut[j] -= 1
    return cut, ncut


@njit(cache=True, inline='always')
def _keep_longest(ea, eb, lens, cut, ncut):  # pragma: no cover - compiled
    """Un-cut the longest edge of every node that would lose all its edges (in place)."""
    nn = ncut.shape[0]
    ne = ea.shape[0]
    deg = np.zeros(nn, np.int64)
    for e in range(ne):
        deg[ea[e]] += 1
        deg[eb[e]] += 1
    for j in range(nn):
        if ncut[j] > 0 and ncut[j] >= deg[j]:
            best = -1
            bl = -1.0
            for e in range(ne):
                if cut[e] and (ea[e] == j or eb[e] == j) and lens[e] > bl:
                    bl = lens[e]
                    best = e
            cut[best] = False


@njit(cache=True, inline='always')
def _erase_spur(skel, node_kind, ea, eb, off, pix, nodeid, e):  # pragma: no cover - compiled
    """Erase leaf edge e from ``skel`` except its branch pixel and the branch cluster, then
    clean the cluster around that pixel (dangling pixels, staircases)."""
    w = skel.shape[1]
    if node_kind[ea[e]] == BRANCH:
        j = ea[e]
        keep = pix[off[e]]
    else:
        j = eb[e]
        keep = pix[off[e + 1] - 1]
    for k in range(off[e], off[e + 1]):
        p = pix[k]
        if p != keep and nodeid[p] != j:
            skel[p // w, p - (p // w) * w] = 0
    _erode_dangling(skel, nodeid, j, keep // w, keep - (keep // w) * w)
    _local_thin(skel, keep // w, keep - (keep // w) * w, 5)


@njit(cache=True, inline='always')
def _erode_dangling(skel, nodeid, j, kr, kc):  # pragma: no cover - compiled
    """Erase the pixels of node j's cluster within 4 cells of (kr, kc) that now dangle off
    another pixel of the cluster (their one neighbour is in it), until none is left."""
    h, w = skel.shape
    changed = True
    while changed:
        changed = False
        for r in range(max(kr - 4, 1), min(kr + 5, h - 1)):
            for c in range(max(kc - 4, 1), min(kc + 5, w - 1)):
                if (skel[r, c] and nodeid[r * w + c] == j and _nb(skel, r, c) == 1
                        and _touches_node(skel, nodeid, j, r, c)):
                    skel[r, c] = 0
                    changed = True


@njit(cache=True, inline='always')
def _touches_node(skel, nodeid, j, r, c):  # pragma: no cover - compiled
    """A skeleton 8-neighbour of (r, c) belongs to node j."""
    w = skel.shape[1]
    for dr in range(-1, 2):
        for dc in range(-1, 2):
            if (dr != 0 or dc != 0) and skel[r + dr, c + dc]:
                if nodeid[(r + dr) * w + c + dc] == j:
                    return True
    return False


@njit(cache=True)
def _local_thin(img, r0, c0, rad):  # pragma: no cover - compiled
    h, w = img.shape
    changed = True
    while changed:
        changed = False
        for r in range(max(r0 - rad, 1), min(r0 + rad + 1, h - 1)):
            for c in range(max(c0 - rad, 1), min(c0 + rad + 1, w - 1)):
                if img[r, c] and _redundant(img, r, c):
                    img[r, c] = 0
                    changed = True


@njit(cache=True)
def _blocked(mask, p, q, w, rows, cols):  # pragma: no cover - compiled
    """True if the Bresenham line between flat pixels p and q touches a zero cell of mask
    (rows, cols: line buffers of at least max(mask.shape) cells)."""
    r0 = p // w
    r1 = q // w
    n = bresenham(r0, p - r0 * w, r1, q - r1 * w, rows, cols)
    for i in range(n):
        if mask[rows[i], cols[i]] == 0:
            return True
    return False


@njit(cache=True)
def split_corners(mask, ea, eb, off, pix, w, min_dev_px, enabled):  # pragma: no cover - compiled
    """Corner nodes (paper §2.2, Fig. 3(c)/(d)): indices into ``pix`` where edges are split.

    For the piece pix[i..j] of an edge, if the straight line between its end pixels crosses a
    zero cell of ``mask`` and the farthest pixel lies at least ``min_dev_px`` from that line,
    split there and recurse on both halves. Self-loops are always split at the pixel farthest
    from the node (a loop needs an intermediate node to be drawn). Returns a sorted int64 array of
    split positions (absolute indices into ``pix``).
    """
    out = np.empty(pix.shape[0], np.int64)
    no = 0
    stack = np.empty((pix.shape[0] + 2, 2), np.int64)
    rows = np.empty(max(mask.shape[0], mask.shape[1]), np.int64)
    cols = np.empty(max(mask.shape[0], mask.shape[1]), np.int64)
    for e in range(ea.shape[0]):
        i0 = off[e]
        j0 = off[e + 1] - 1
        ns = 0
        if ea[e] == eb[e]:
            best = _farthest_from_start(pix, i0, j0, w)
            if best < 0:
                continue
            out[no] = best
            no += 1
            if enabled:
                stack[0, 0] = i0
                stack[0, 1] = best
                stack[1, 0] = best
                stack[1, 1] = j0
                ns = 2
        elif enabled:
            stack[0, 0] = i0
            stack[0, 1] = j0
            ns = 1
        no = _split_pieces(mask, pix, w, min_dev_px, stack, ns, out, no, rows, cols)
    res = out[:no].copy()
    res.sort()
    return res


@njit(cache=True, inline='always')
def _farthest_from_start(pix, i0, j0, w):  # pragma: no cover - compiled
    """Index k in (i0, j0) of the pixel farthest from pix[i0] (the first on ties), -1 if none."""
    pr = pix[i0] // w
    pc = pix[i0] - pr * w
    best = -1
    bd = -1.0
    for k in range(i0 + 1, j0):
        r = pix[k] // w
        c = pix[k] - r * w
        d = (r - pr) ** 2 + (c - pc) ** 2
        if d > bd:
            bd = d
            best = k
    return best


@njit(cache=True, inline='always')
def _split_pieces(mask, pix, w, min_dev_px, stack, ns, out, no, rows,
                  cols):  # pragma: no cover - compiled
    """Split the pieces on the stack recursively (:func:`split_corners`), appending the split
    positions to ``out``; returns the new count."""
    while ns > 0:
        ns -= 1
        i = stack[ns, 0]
        j = stack[ns, 1]
        if j - i < 2:
            continue
        if not _blocked(mask, pix[i], pix[j], w, rows, cols):
            continue
        best, bd = _farthest_from_chord(pix, i, j, w)
        if best < 0 or bd < min_dev_px:
            continue
        out[no] = best
        no += 1
        stack[ns, 0] = i
        stack[ns, 1] = best
        stack[ns + 1, 0] = best
        stack[ns + 1, 1] = j
        ns += 2
    return no


@njit(cache=True, inline='always')
def _farthest_from_chord(pix, i, j, w):  # pragma: no cover - compiled
    """(k, distance [px]) of the pixel in (i, j) farthest from the line through pix[i] and
    pix[j] (from pix[i] if they coincide), the first on ties; (-1, -1.0) if none."""
    ar = pix[i] // w
    ac = pix[i] - ar * w
    br = pix[j] // w
    bc = pix[j] - br * w
    vr = br - ar
    vc = bc - ac
    norm = (vr * vr + vc * vc) ** 0.5
    best = -1
    bd = -1.0
    for k in range(i + 1, j):
        r = pix[k] // w
        c = pix[k] - r * w
        if norm > 0:
            d = abs(vr * (c - ac) - vc * (r - ar)) / norm
        else:
            d = ((r - ar) ** 2 + (c - ac) ** 2) ** 0.5
        if d > bd:
            bd = d
            best = k
    return best, bd


@njit(cache=True)
def assemble(ea, eb, off, pix, splits, n_nodes, dt, w):  # pragma: no cover - compiled
    """Split edges at ``splits`` (corner nodes numbered from ``n_nodes`` in split order).

    Returns (sa, sb, s0, s1, length_px, clear_px): sub-edge node ids, inclusive pixel-index ranges
    into ``pix``, polyline length [px] and minimum ``dt`` value [px] along each sub-edge.
    """
    ne = ea.shape[0]
    m = ne + splits.shape[0]
    sa = np.empty(m, np.int32)
    sb = np.empty(m, np.int32)
    s0 = np.empty(m, np.int64)
    s1 = np.empty(m, np.int64)
    ln = np.zeros(m)
    cl = np.zeros(m)
    k = 0
    t = 0
    for e in range(ne):
        start = off[e]
        a = ea[e]
        last = off[e + 1] - 1
        while True:
            if t < splits.shape[0] and splits[t] < last:
                stop = splits[t]
                b = n_nodes + t
                t += 1
            else:
                stop = last
                b = eb[e]
            sa[k] = a
            sb[k] = b
            s0[k] = start
            s1[k] = stop
            s = 0.0
            mn = 1e18
            for i in range(start, stop + 1):
                p = pix[i]
                r = p // w
                v = dt[r, p - r * w]
                if v < mn:
                    mn = v
                if i > start:
                    q = pix[i - 1]
                    qr = q // w
                    s += ((qr - r) ** 2 + ((q - qr * w) - (p - r * w)) ** 2) ** 0.5
            ln[k] = s
            cl[k] = mn
            k += 1
            if stop == last:
                break
            a = b
            start = stop
    return sa[:k], sb[:k], s0[:k], s1[:k], ln[:k], cl[:k]


# Entry kernels and the argument types the topology core calls them with (common.warm).
WARM = {
    "find_entry": ("(uint8[:, ::1], uint8[:, ::1], int64, int64, int64)",),
    "build_graph": ("(uint8[:, ::1], int64, uint8[::1], int32[::1], int64[::1])",),
    "reset_nodeid": ("(int32[::1], int64[::1])",),
    "decimate": ("(int64[::1], int64[::1], int64[::1], int64)",),
    "prune_spurs": (
        "(uint8[:, ::1], int64[::1], int8[::1], int32[::1], int32[::1], int64[::1], int64[::1],"
        " int32[::1], float32[:, ::1], float64, float64, float64, int8[:, ::1], uint8[:, ::1],"
        " float64, int64)",),
    "split_corners": (
        "(uint8[:, ::1], int32[::1], int32[::1], int64[::1], int64[::1], int64, float64,"
        " boolean)",),
    "assemble": (
        "(int32[::1], int32[::1], int64[::1], int64[::1], int64[::1], int64, float32[:, ::1],"
        " int64)",),
}
