"""Compute-stage benchmark: every service core on synthetic office-like maps.

Run: ``.venv/bin/python -m common.benchstages [--sizes 100 300 1000] [--repeats 3]``

Maps are generated here (rooms along 2 m corridors, doors, tables, a few 1-cell chair legs; 0.1 m
cells, n x n cells). A robot drives a route along the corridors; every pose gives a simulated
181-beam scan (180 deg, 8 m, 1 cm noise) that the mapper core (``services.mapper.core``, imported
lazily) fuses into a log-odds grid -- the "noisy" map.

- mapper: time of ``MapperCore.integrate`` per scan.
- topology: the robot first maps the first 60 % of its route (not timed), then one **cold**
  full update of a fresh ``TopologyCore`` is timed (``cold_*``, repeated ``repeats`` times), and
  then the robot keeps driving at 0.04 m per scan (0.2 m/s at 5 Hz, the paper's speed) into
  unexplored corridor; ``median_ms``/``p99_ms`` are the per-scan ``update`` times of that core,
  which may reuse its previous state (incremental work measured as it really happens).
  ``clean_cold_ms``: a full update on the noise-free truth map (everything known).
- reliability, planner (reliability strategy), planner-frontier (explore_lite-style frontier
  strategy, grid search), controller: per-scan ``update`` time of each core on that same drive,
  fed like the services feed them (the topology's result, the reliability's output, the plan and
  the scan). Message decoding and the bus are not included (``topoexplore bench stages --bus``
  measures those with real processes).

All times are wall-clock ``time.perf_counter`` medians / 99th percentiles in milliseconds.
"""

from __future__ import annotations

import argparse
import math
import time
from types import SimpleNamespace

import msgspec
import numpy as np
from numba import njit

from topoexplore.common.domain import GridMap, Pose, Scan
from topoexplore.common.grid import GridGeometry
from topoexplore.common.params import MapperParams, Params, TopologyParams

__all__ = ["office_truth", "office_route", "simulate_scan", "truth_to_grid", "bench_stages",
           "format_table"]

RES = 0.1  # [m/cell]
CORRIDOR = 20  # [cells] 2 m corridors
WALL = 2  # [cells]
BLOCK = 120  # [cells] distance between corridor centre lines


def office_truth(n: int, seed: int = 0) -> tuple[np.ndarray, list[int], list[int]]:
    """Occupied-cell mask (n, n) of an office; returns (occ, corridor centre rows, vertical
    corridor centre columns). Row = y, column = x, 0.1 m cells."""
    if n < 60:
        raise ValueError(f"office maps need n >= 60 cells (got {n})")
    rng = np.random.default_rng(seed)
    occ = np.zeros((n, n), bool)
    block = BLOCK if n >= 2 * BLOCK else n
    centres = list(range(block // 2, n - CORRIDOR, block))
    half = CORRIDOR // 2
    # horizontal band boundaries (room rows) between corridors and the outer walls
    bounds = [WALL]
    for c in centres:
        bounds += [c - half - WALL, c + half + WALL]
    bounds.append(n - WALL)
    mids = [(centres[k] + centres[k + 1]) // 2 for k in range(len(centres) - 1)]
    for mrow in mids:
        occ[mrow - 1:mrow + 1, :] = True
    for c in centres:
        occ[c - half - WALL:c - half, :] = True
        occ[c + half:c + half + WALL, :] = True
    # room strips: (row0, row1, door wall row range, corridor side)
    strips = []
    for k, c in enumerate(centres):
        lo = mids[k - 1] + 1 if k > 0 else WALL
        hi = mids[k] - 1 if k < len(mids) else n - WALL
        strips.append((lo, c - half - WALL, c - half - WALL, c - half))  # rooms below corridor
        strips.append((c + half + WALL, hi, c + half, c + half + WALL))  # rooms above corridor
    verts = [40 + half]
    if n >= 200:
        verts += list(range(340, n - 100, 300)) + [n - 60 + half]
    verts = sorted(set(v for v in verts if v + half + WALL < n))
    for r0, r1, d0, d1 in strips:
        if r1 - r0 < 15:
            continue
        x = WALL
        while x < n - WALL:
            wdt = int(rng.integers(40, 71))
            x1 = min(x + wdt, n - WALL)
            if n - WALL - x1 < 25:
                x1 = n - WALL
            occ[r0:r1, x1 - 1:x1 + 1] = True  # wall on the room's right side
            if x1 - x > 20:
                door = int(rng.integers(x + 3, x1 - 12))
                occ[d0:d1, door:door + 9] = False  # 0.9 m door
                if rng.random() < 0.6 and x1 - x > 35 and r1 - r0 > 30:
                    tw, th = int(rng.integers(8, 16)), int(rng.integers(6, 11))
                    cx, cy = (x + x1) // 2, (r0 + r1) // 2
                    occ[cy - th // 2:cy + th // 2, cx - tw // 2:cx + tw // 2] = True
                for _ in range(int(rng.integers(0, 4))):  # chair legs, 1 cell
                    occ[int(rng.integers(r0 + 3, r1 - 3)), int(rng.integers(x + 3, x1 - 3))] = True
            x = x1 + 1
    for v in verts:  # vertical corridors through every band
        occ[WALL:n - WALL, v - half - WALL:v + half + WALL] = True
        occ[WALL:n - WALL, v - half:v + half] = False
    for c in centres:
        occ[c - half:c + half, WALL:n - WALL] = False
    occ[:WALL, :] = occ[-WALL:, :] = True
    occ[:, :WALL] = occ[:, -WALL:] = True
    return occ, centres, verts


def office_route(n: int, centres: list[int], verts: list[int], step: float) -> np.ndarray:
    """Poses (x, y, theta) every ``step`` [m] along a snake through the corridors."""
    xl = (verts[0] if verts else 30) * RES + 0.05
    xr = (verts[-1] if len(verts) > 1 else n - 30) * RES + 0.05
    pts = []
    for k, c in enumerate(centres):
        y = c * RES
        a, b = (xl, xr) if k % 2 == 0 else (xr, xl)
        pts += [(a, y), (b, y)]
    poses = []
    for (x0, y0), (x1, y1) in zip(pts[:-1], pts[1:], strict=True):
        d = math.hypot(x1 - x0, y1 - y0)
        th = math.atan2(y1 - y0, x1 - x0)
        for s in np.arange(0.0, d, step):
            poses.append((x0 + (x1 - x0) * s / d, y0 + (y1 - y0) * s / d, th))
    return np.asarray(poses)


@njit(cache=True)
def _raycast(occ, res, x, y, angles, rmax):  # pragma: no cover - compiled
    h, w = occ.shape
    out = np.full(angles.shape[0], rmax)
    step = res * 0.25
    for k in range(angles.shape[0]):
        ca = math.cos(angles[k])
        sa = math.sin(angles[k])
        s = 0.0
        while s < rmax:
            c = int(math.floor((x + s * ca) / res))
            r = int(math.floor((y + s * sa) / res))
            if r < 0 or c < 0 or r >= h or c >= w or occ[r, c]:
                out[k] = s
                break
            s += step
    return out


def simulate_scan(occ: np.ndarray, pose, rng: np.random.Generator, beams: int = 181,
                  range_max: float = 8.0, noise: float = 0.01) -> np.ndarray:
    """Ranges [m] of a forward 180-degree scan at ``pose`` in the truth map (origin 0, RES)."""
    ang = pose[2] + np.linspace(-math.pi / 2, math.pi / 2, beams)
    r = _raycast(occ, RES, float(pose[0]), float(pose[1]), ang, range_max)
    hit = r < range_max
    r[hit] = np.clip(r[hit] + rng.normal(0.0, noise, int(hit.sum())), 0.03, range_max - 1e-3)
    return r


def truth_to_grid(occ: np.ndarray) -> np.ndarray:
    """Noise-free, fully known int8 grid (0 free, 100 occupied)."""
    return np.where(occ, 100, 0).astype(np.int8)


def _stats(samples: list[float]) -> dict[str, float]:
    a = np.asarray(samples) * 1000.0
    return {"median_ms": float(np.median(a)), "p99_ms": float(np.percentile(a, 99))}


STAGES = ("mapper", "topology", "reliability", "planner", "planner-frontier", "controller",
          "localizer", "localizer-360")


def _scan(occ: np.ndarray, pose, rng) -> Scan:
    return Scan(simulate_scan(occ, pose, rng), -math.pi / 2, math.pi / 180.0, 0.02, 8.0)


def _cores(strategy: str = "reliability") -> SimpleNamespace:
    """The stage cores with default parameters."""
    from topoexplore.services.controller.core import ControllerCore
    from topoexplore.services.localizer.core import LocalizerCore
    from topoexplore.services.planner.core import PlannerCore
    from topoexplore.services.reliability.core import ReliabilityCore

    P = Params()
    occ = P.mapper.occupancy
    return SimpleNamespace(
        reliability=ReliabilityCore(P.reliability, P.laser, occ),
        planner=PlannerCore(P.planner, P.robot, P.reliability.p_reliable, occ),
        frontier=PlannerCore(msgspec.structs.replace(P.planner, strategy="frontier"), P.robot,
                             P.reliability.p_reliable, occ),
        controller=ControllerCore(P.controller, P.robot),
        localizer=LocalizerCore(P.localizer, P.laser.offset, P.mapper.occupancy))


def _topology_cold(grid: GridMap, clean: GridMap, start, repeats: int) -> dict[str, float]:
    """A fresh core's full update on the noisy map and on the noise-free truth map."""
    from topoexplore.services.topology.core import TopologyCore

    cold, cc, r2 = [], [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        TopologyCore(TopologyParams()).update(grid, tuple(start[:2]))
        cold.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        r2 = TopologyCore(TopologyParams()).update(clean, tuple(start[:2]))
        cc.append(time.perf_counter() - t0)
    return {"cold_median_ms": float(np.median(cold) * 1000),
            "cold_p99_ms": float(np.percentile(cold, 99) * 1000),
            "clean_cold_ms": float(np.median(cc) * 1000),
            "clean_nodes": len(r2.graph.nodes), "clean_edges": len(r2.graph.edges)}


def _timed(times: dict[str, list[float]], stage: str, fn, *args):
    t0 = time.perf_counter()
    out = fn(*args)
    times.setdefault(stage, []).append(time.perf_counter() - t0)
    return out


def _drive(mapper, topo, cores, occ, seq, rng, stages, times) -> SimpleNamespace:
    """Drive on at 0.04 m per scan; time every stage on every scan, fed as the services feed
    them. Returns the last graph and beliefs."""
    graph = beliefs = None
    for k, pose in enumerate(seq):
        t, pose = 0.2 * k, Pose(float(pose[0]), float(pose[1]), float(pose[2]))  # [s] 5 Hz
        scan = _scan(occ, pose, rng)
        _localize(cores.localizer, mapper, occ, pose, scan, rng, stages, times)
        _timed(times, "mapper", mapper.integrate, pose, scan)
        if "topology" not in stages:
            continue
        grid = mapper.grid()
        graph = _timed(times, "topology", topo.update, grid, (pose.x, pose.y)).graph
        beliefs = _timed(times, "reliability", cores.reliability.update, graph, pose, grid)
        plan = _timed(times, "planner", cores.planner.update, t, pose, graph, beliefs, grid)
        if "planner-frontier" in stages:
            _timed(times, "planner-frontier", cores.frontier.update, t, pose, graph, None, grid)
        _timed(times, "controller", cores.controller.update, t, pose, plan.route, False, scan)
    return SimpleNamespace(graph=graph, beliefs=beliefs)


def _localize(loc, mapper, occ, pose, scan, rng, stages, times) -> None:
    """The localizer on this scan (and on a 360-beam scan from the same pose) against the map
    so far, from a guess off by up to 0.1 m and 0.05 rad: time per match, and the error."""
    if "localizer" not in stages and "localizer-360" not in stages:
        return
    _timed(times, "localizer-map", loc.set_map, mapper.grid())
    guess = Pose(pose.x + rng.uniform(-0.1, 0.1), pose.y + rng.uniform(-0.1, 0.1),
                 pose.theta + rng.uniform(-0.05, 0.05))
    for stage, s in (("localizer", scan), ("localizer-360", None)):
        if stage not in stages:
            continue
        if s is None:
            inc = 2 * math.pi / 360
            r = _raycast(occ, RES, pose.x, pose.y, pose.theta - math.pi + inc * np.arange(360),
                         8.0)
            hit = r < 8.0
            r[hit] += rng.normal(0.0, 0.01, int(hit.sum()))
            s = Scan(r, -math.pi, inc, 0.02, 8.0)
        m = _timed(times, stage, loc.match, s, guess)
        times.setdefault(f"{stage}-error", []).append(math.hypot(m.pose.x - pose.x,
                                                                 m.pose.y - pose.y))
    loc.observe(scan, pose)  # the sides of the faces the mapped scan met (core step 0), for
    #   either stage run alone


def _bench_size(n: int, repeats: int, stages: tuple[str, ...], seed: int) -> dict[str, dict]:
    """Map 60 % of the route untimed except the mapper, time a cold topology update, then drive
    on and time every stage per scan (module docstring)."""
    from topoexplore.services.mapper.core import MapperCore
    from topoexplore.services.topology.core import TopologyCore

    occ, centres, verts = office_truth(n, seed)
    geom = GridGeometry(RES, 0.0, 0.0, n, n)
    rng = np.random.default_rng(seed)
    mapper = MapperCore.from_grid(GridMap(np.full((n, n), -1, np.int8), geom), MapperParams())
    coarse = office_route(n, centres, verts, 0.3)
    split = int(0.6 * len(coarse))
    times: dict[str, list[float]] = {}
    for pose in coarse[:split]:
        _timed(times, "mapper", mapper.integrate, Pose(*map(float, pose)), _scan(occ, pose, rng))
    res_topo = {}
    if "topology" in stages:
        res_topo = _topology_cold(mapper.grid(copy=True), GridMap(truth_to_grid(occ), geom),
                                  coarse[split - 1], repeats)
    fine = office_route(n, centres, verts, 0.04)
    start = coarse[split - 1]
    k0 = int(np.argmin(np.hypot(fine[:, 0] - start[0], fine[:, 1] - start[1])))
    topo = TopologyCore(TopologyParams())
    last = _drive(mapper, topo, _cores(), occ, fine[k0:k0 + max(40, 30 * repeats)], rng,
                  stages, times)
    out: dict[str, dict] = {}
    for s in STAGES:
        if s in stages and times.get(s):
            out[s] = _stats(times[s]) | {"scans": len(times[s])}
        if s.startswith("localizer") and s in out:
            err = np.asarray(times[f"{s}-error"])
            out[s] |= {"set_map_median_ms": float(np.median(times["localizer-map"]) * 1000),
                       "error_median_m": float(np.median(err)),
                       "error_p90_m": float(np.percentile(err, 90))}
    if "topology" in out:
        g = last.graph
        out["topology"] |= res_topo | {"nodes": len(g.nodes) if g else 0,
                                       "edges": len(g.edges) if g else 0,
                                       "core": topo.snapshot()}
    if "reliability" in out:
        out["reliability"]["end_nodes"] = len(last.beliefs)
    if "planner" in out:
        out["planner"]["edges"] = len(last.graph.edges)
    return out


def _warm_up() -> None:
    """Load the numba kernels (compiled or cached) and first-call caches before timing."""
    _bench_size(100, 1, STAGES, 0)


def bench_stages(sizes=(100, 300, 1000), repeats: int = 3, stages=STAGES,
                 seed: int = 0) -> dict:
    """{stage: {"NxN": {"median_ms", "p99_ms", ...}}} (see module docstring)."""
    stages = tuple(stages)
    for s in stages:
        if s not in STAGES:
            raise ValueError(f"unknown stage {s!r} (use {', '.join(STAGES)})")
    if any(s in stages for s in STAGES[2:]) and "topology" not in stages:
        stages = stages + ("topology",)  # the later stages run on its output
    if repeats < 1:
        raise ValueError("repeats must be >= 1")
    out: dict[str, dict] = {s: {} for s in stages}
    _warm_up()
    for n in sizes:
        res = _bench_size(int(n), repeats, stages, seed)
        for k, v in res.items():
            out.setdefault(k, {})[f"{n}x{n}"] = v
    return out


def format_table(results: dict) -> str:
    """Plain-text table of :func:`bench_stages` results."""
    lines = []
    for stage, per in results.items():
        if stage == "note":
            for size, v in per.items():
                lines.append(f"note {size}: {v}")
            continue
        lines.append(f"{stage}:")
        lines.append(f"  {'size':>10} {'median ms':>10} {'p99 ms':>10}  extra")
        for size, v in per.items():
            extra = ", ".join(f"{k}={v[k]:.1f}" if isinstance(v[k], float) else f"{k}={v[k]}"
                              for k in v if k not in ("median_ms", "p99_ms", "core"))
            lines.append(f"  {size:>10} {v['median_ms']:>10.2f} {v['p99_ms']:>10.2f}  {extra}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[100, 300, 1000])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--stages", nargs="+", default=list(STAGES))
    a = ap.parse_args(argv)
    res = bench_stages(tuple(a.sizes), a.repeats, tuple(a.stages))
    print(format_table(res))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
