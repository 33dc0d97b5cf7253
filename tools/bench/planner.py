"""Planner cost per update on synthetic inputs: ``python -m services.planner.bench``.

Prints medians in ms (no assertions; the tests do not time anything):
- frontier strategy: one PlannerCore.update (classify, distance transform, Dijkstra, frontier
  groups) on office-like grids of 300 x 300 and 1000 x 1000 cells, half explored;
- reliability strategy: one PlannerCore.update on a lattice-shaped topological graph
  (edge polylines at 0.1 m spacing), with and without the grid checks.
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

from topoexplore.common import messages as m
from topoexplore.common.grid import GridGeometry
from topoexplore.common.params import PlannerParams
from topoexplore.services.planner import frontier as fr
from topoexplore.services.planner.core import PlannerCore


def office_grid(n: int, seed: int = 0) -> tuple[np.ndarray, GridGeometry]:
    """n x n cells at 0.1 m: rooms of 4 m with 1 m doors; the right half unknown."""
    rng = np.random.default_rng(seed)
    g = np.zeros((n, n), dtype=np.int8)
    g[[0, -1], :] = 100
    g[:, [0, -1]] = 100
    for k in range(40, n - 1, 40):
        g[k, :] = 100
        g[:, k] = 100
    for k in range(40, n - 1, 40):
        for j in range(20, n - 1, 40):
            g[k, j - 5:j + 5] = 0
            g[j - 5:j + 5, k] = 0
    specks = rng.integers(1, n - 1, size=(n // 4, 2))
    g[specks[:, 0], specks[:, 1]] = 100
    g[:, n // 2:] = -1
    return g, GridGeometry(0.1, 0.0, 0.0, n, n)


def lattice_topo(k: int) -> m.TopoGraph:
    """k x k branch nodes 2 m apart, each edge a 0.1 m polyline; end nodes on the border."""
    h = m.Header(seq=0, stamp=0.0, frame="map", src_seq=-1)
    nodes, edges = [], []

    def nid(i, j):
        return i * k + j

    for i in range(k):
        for j in range(k):
            nodes.append(m.TopoNode(id=nid(i, j), kind="branch", x=2.0 * j + 1, y=2.0 * i + 1))

    def add(a, ax, ay, b, bx, by):
        n = max(2, int(math.hypot(bx - ax, by - ay) / 0.1) + 1)
        pts = [[ax + (bx - ax) * s, ay + (by - ay) * s] for s in np.linspace(0, 1, n)]
        edges.append(m.TopoEdge(a=a, b=b, points=pts, length=math.hypot(bx - ax, by - ay),
                                clearance=0.5))

    for i in range(k):
        for j in range(k):
            if j + 1 < k:
                add(nid(i, j), 2.0 * j + 1, 2.0 * i + 1, nid(i, j + 1), 2.0 * j + 3, 2.0 * i + 1)
            if i + 1 < k:
                add(nid(i, j), 2.0 * j + 1, 2.0 * i + 1, nid(i + 1, j), 2.0 * j + 1, 2.0 * i + 3)
    nxt = k * k
    for j in range(k):  # dead ends below the first row
        nodes.append(m.TopoNode(id=nxt, kind="end", x=2.0 * j + 1, y=0.3))
        add(nid(0, j), 2.0 * j + 1, 1.0, nxt, 2.0 * j + 1, 0.3)
        nxt += 1
    return m.TopoGraph(header=h, nodes=nodes, edges=edges)


def median_ms(f, n: int) -> float:
    f()  # warm-up (numba compile on the first call)
    ts = []
    for _ in range(n):
        t = time.perf_counter()
        f()
        ts.append(time.perf_counter() - t)
    return 1000.0 * float(np.median(ts))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=20)
    a = ap.parse_args(argv)
    print("planner update, median ms")
    for n in (300, 1000):
        g, geom = office_grid(n)
        core = PlannerCore(PlannerParams(strategy="frontier"))
        pose = (2.0, 2.0, 0.0)
        t_upd = median_ms(lambda c=core, q=pose, g=g, s=geom: c.update(0.0, q, None, None, g, s),
                          a.repeat)
        t_search = median_ms(lambda g=g, s=geom: fr.grid_search(
            g, s, 2.0, 2.0, 0.25, soft_radius=0.5, soft_penalty=2.0), a.repeat)
        reach = int(np.isfinite(fr.grid_search(g, geom, 2.0, 2.0, 0.25).dist).sum())
        print(f"  frontier {n}x{n}: update {t_upd:.1f}  (grid search alone {t_search:.1f}; "
              f"{reach} reachable cells)")
    for k in (6, 15):
        tp = lattice_topo(k)
        pts = sum(len(e.points) for e in tp.edges)
        rel = m.Reliability(header=tp.header, nodes=[])
        size = int(math.ceil((2.0 * k + 1) / 0.1))
        grid = np.zeros((size, size), dtype=np.int8)
        geom = GridGeometry(0.1, 0.0, 0.0, size, size)
        core = PlannerCore(PlannerParams())
        pose = (1.0, 1.5, 0.0)
        t0 = median_ms(lambda c=core, q=pose, tp=tp, r=rel: c.update(0.0, q, tp, r, None, None),
                       a.repeat)
        t1 = median_ms(lambda c=core, q=pose, tp=tp, r=rel, g=grid, s=geom:
                       c.update(0.0, q, tp, r, g, s), a.repeat)
        print(f"  reliability, {len(tp.nodes)} nodes / {len(tp.edges)} edges / {pts} points: "
              f"update {t0:.1f} without grid, {t1:.1f} with a {size}x{size} grid")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
