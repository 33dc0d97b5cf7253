"""Planner cost per update on synthetic inputs: ``python -m topoexplore.tools.bench.planner``.

Prints medians in ms (no assertions; the tests do not time anything):
- frontier strategy: one PlannerCore.update (classify, distance transform, Dijkstra, frontier
  groups) on office-like grids of 300 x 300 and 1000 x 1000 cells, half explored;
- reliability strategy: one PlannerCore.update on a lattice-shaped topological graph
  (edge polylines at 0.1 m spacing), without a grid and with one (clearance from the grid,
  line of sight to the entry point).
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

from topoexplore.common.domain import Graph, GridMap, Node, Pose
from topoexplore.common.grid import GridGeometry, Occupancy
from topoexplore.common.params import PlannerParams
from topoexplore.services.planner.core import PlannerCore
from topoexplore.services.planner.mapview import MapView


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


def lattice_topo(k: int) -> Graph:
    """k x k branch nodes 2 m apart, each edge a 0.1 m polyline; end nodes on the border."""
    nodes, edges = [], []

    def nid(i, j):
        return i * k + j

    for i in range(k):
        for j in range(k):
            nodes.append(Node(nid(i, j), "branch", 2.0 * j + 1, 2.0 * i + 1))

    def add(a, ax, ay, b, bx, by):
        n = max(2, int(math.hypot(bx - ax, by - ay) / 0.1) + 1)
        pts = [[ax + (bx - ax) * s, ay + (by - ay) * s] for s in np.linspace(0, 1, n)]
        edges.append((a, b, pts, math.hypot(bx - ax, by - ay), 0.5))

    for i in range(k):
        for j in range(k):
            if j + 1 < k:
                add(nid(i, j), 2.0 * j + 1, 2.0 * i + 1, nid(i, j + 1), 2.0 * j + 3, 2.0 * i + 1)
            if i + 1 < k:
                add(nid(i, j), 2.0 * j + 1, 2.0 * i + 1, nid(i + 1, j), 2.0 * j + 1, 2.0 * i + 3)
    nxt = k * k
    for j in range(k):  # dead ends below the first row
        nodes.append(Node(nxt, "end", 2.0 * j + 1, 0.3))
        add(nid(0, j), 2.0 * j + 1, 1.0, nxt, 2.0 * j + 1, 0.3)
        nxt += 1
    return Graph.from_edges(nodes, edges)


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
        gm = GridMap(g, geom)
        # frontier_period 0: search on every update (a core following a target would reuse
        # its last search for frontier_period seconds, and t stays 0 here)
        core = PlannerCore(PlannerParams(strategy="frontier", frontier_period=0.0))
        pose = Pose(2.0, 2.0, 0.0)
        t_upd = median_ms(lambda c=core, q=pose, gm=gm: c.update(0.0, q, None, None, gm),
                          a.repeat)
        t_search = median_ms(lambda gm=gm: MapView(gm, Occupancy()).search(
            2.0, 2.0, 0.25, soft_radius=0.5, soft_penalty=2.0), a.repeat)
        reach = int(np.isfinite(MapView(gm, Occupancy()).search(2.0, 2.0, 0.25).dist).sum())
        print(f"  frontier {n}x{n}: update {t_upd:.1f}  (grid search alone {t_search:.1f}; "
              f"{reach} reachable cells)")
    for k in (6, 15):
        tp = lattice_topo(k)
        pts = len(tp.points)
        size = int(math.ceil((2.0 * k + 1) / 0.1))
        gm = GridMap(np.zeros((size, size), dtype=np.int8), GridGeometry(0.1, 0.0, 0.0, size,
                                                                         size))
        core = PlannerCore(PlannerParams())
        pose = Pose(1.0, 1.5, 0.0)
        t0 = median_ms(lambda c=core, q=pose, tp=tp: c.update(0.0, q, tp, [], None), a.repeat)
        t1 = median_ms(lambda c=core, q=pose, tp=tp, gm=gm: c.update(0.0, q, tp, [], gm),
                       a.repeat)
        print(f"  reliability, {len(tp.nodes)} nodes / {len(tp.edges)} edges / {pts} points: "
              f"update {t0:.1f} without grid, {t1:.1f} with a {size}x{size} grid")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
