"""``topoexplore bench explore`` (without ``--bus``): the suite's explorations in process,
and a sample of them checked on the real processes.

Each run is ``bench inproc``'s pipeline (the six cores called in the order the services run
them in lockstep, no bus), followed as ``topoexplore run``'s monitor follows a run on the bus,
and written the same way into ``runs/<world>-<strategy>-<seed>/``: ``report.json`` (the fields
the suite reads: path, sim time, coverage, map accuracy, collisions, end nodes seen, visited
and accepted from a distance, the stop reason), ``timeline.csv`` (coverage over sim time and
distance, sampled on map updates every 0.25 m of travel and at least every 5 s),
``trail.csv``, ``map.yaml`` and ``final.png``. A run costs its compute alone: about a third of
the CPU of the same run on the bus (docs/benchmarks.md, "The suite in process").

``bench explore`` then runs some of the same runs (:func:`pick_bus_runs`) through
``topoexplore run --lockstep`` (the real processes and the bus) and compares outcome and path
(:func:`compare`): the in-process figures stand for the bus runs only as long as these
agree.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from topoexplore.tools.run import TRAIL_STEP_M, Truth, timeline_due

BUS_MIN_PATH_M = 5.0  # [m] a bus check needs a run that drove at least this far


class WallLimit(Exception):
    """The run's wall-time limit came (raised from a hook to stop ``inproc.run``)."""


class RunFollower:
    """What ``topoexplore run``'s monitor keeps of a run, from ``inproc.run``'s hooks: end
    node ids seen and visited, targets chosen (trail segments), the trail of true poses, the
    coverage timeline and the last update's map, graph and beliefs."""

    def __init__(self, coverage_fn: Any, wall_limit: float = 0.0) -> None:
        self.coverage_fn = coverage_fn  # GridMap -> coverage in [0, 1]
        self.t0 = time.monotonic()
        self.wall_limit = wall_limit  # [s] 0: none
        self.seen: set[int] = set()
        self.visited: set[int] = set()
        self.targets = 0
        self.segment = 0
        self._target: tuple[int, float, float] | None = None
        self.trail: list[tuple[float, float, int]] = []
        self.timeline: list[tuple[float, float, float]] = []
        self.last: tuple | None = None  # (pose, graph, beliefs, plan, grid) of the last update

    def __call__(self, t, pose, graph, beliefs, plan, grid) -> None:
        self.seen.update(b.id for b in beliefs)
        self.visited.update(b.id for b in beliefs if b.visited)
        r = plan.route
        if len(r.waypoints):
            cur = (r.target_id, float(r.target_xy[0]), float(r.target_xy[1]))
            prev = self._target
            if prev is None or cur[0] != prev[0] or (
                    cur[0] < 0 and math.hypot(cur[1] - prev[1], cur[2] - prev[2]) > 1.0):
                if prev is not None:
                    self.segment += 1
                self._target = cur
                self.targets += 1
        self.last = (pose, graph, beliefs, plan, grid)

    def on_sim(self, sim: Any) -> None:
        x, y, _ = sim.truth_pose()
        if not self.trail or math.hypot(x - self.trail[-1][0], y - self.trail[-1][1]) > \
                TRAIL_STEP_M:
            self.trail.append((x, y, self.segment))
        if timeline_due(self.timeline[-1] if self.timeline else None, sim.time,
                        sim.path_length):
            self.timeline.append((sim.time, sim.path_length, self.coverage_fn(self.last[4])))
        if self.wall_limit > 0 and time.monotonic() - self.t0 > self.wall_limit:
            raise WallLimit(f"stopped after {self.wall_limit:g} wall s")


def run_local(label: str, world_arg: str, strategy: str, seed: int, out: Path,
              max_sim_time: float, max_wall_time: float = 0.0, params: str | None = None,
              overrides: Sequence[str] = ()) -> dict:
    """One in-process exploration into ``out/runs/<label>-<strategy>-<seed>/``; returns the
    report with the fields ``bench explore`` adds to a bus run's (world label, run directory,
    timeline, the distances to 90 / 95 %)."""
    import shutil

    from topoexplore.common.params import load_params, strategy_overrides
    from topoexplore.tools.bench import inproc
    from topoexplore.tools.bench.explore import derive, read_timeline

    rel = f"runs/{label}-{strategy}-{seed}"
    run_dir = out / rel
    if run_dir.exists():
        shutil.rmtree(run_dir)  # never read a stale report
    run_dir.mkdir(parents=True)
    t0 = time.monotonic()
    report: dict[str, Any] = {"world": world_arg, "strategy": strategy, "seed": int(seed),
                              "mode": "lockstep", "pipeline": "inproc", "finished": False}
    follow = None
    try:
        P = load_params(params, [f"sim.world={json.dumps(world_arg)}", f"sim.seed={int(seed)}",
                                 *strategy_overrides(strategy), *overrides])
        truth = Truth(world_arg, P)
        follow = RunFollower(lambda g: truth.coverage(g, P), max_wall_time)
        r = inproc.run(world_arg, strategy, seed, tuple(overrides), max_sim_time, follow,
                       params=params, on_sim=follow.on_sim)
    except Exception as exc:  # noqa: BLE001 - one broken run must not end the suite
        report["stop_reason"] = f"{type(exc).__name__}: {exc}"
        for k in ("path_length_m", "sim_time_s", "coverage", "coverage_free", "map_accuracy",
                  "collisions", "end_nodes_visited", "end_nodes_accepted_remote"):
            report[k] = None
    else:
        report.update(_figures(r, follow, lambda g: truth.accuracy(g, P),
                               P.reliability.p_reliable, max_sim_time))
    report["wall_time_s"] = round(time.monotonic() - t0, 3)
    _write(run_dir, report, follow, P if follow is not None else None, label)
    tl = run_dir / "timeline.csv"  # read back as a bus run's is: the same rounding
    run = dict(report, world_label=label, exit_code=0 if report["finished"] else 1,
               run_dir=rel, recording_file=None,
               timeline=read_timeline(tl) if tl.is_file() else [])
    return derive(run)


def _figures(r: dict, follow: RunFollower, acc_fn: Any, p_reliable: float,
             max_sim_time: float) -> dict[str, Any]:
    """The report's figures from ``inproc.run``'s result and what the follower kept."""
    grid = follow.last[4] if follow.last else None
    beliefs = follow.last[2] if follow.last else ()
    timeout = r["state"] == "timeout"
    follow.timeline[:] = [p for p in follow.timeline if p[0] < r["sim_time_s"]]  # as on the bus
    follow.timeline.append((r["sim_time_s"], r["path_length_m"], r["coverage"]))
    return {
        "finished": bool(r["finished"]),
        "stop_reason": (f"max sim time {max_sim_time:g} s reached" if timeout
                        else r["stop_reason"]),
        "sim_time_s": r["sim_time_s"], "path_length_m": r["path_length_m"],
        "coverage": r["coverage"], "coverage_free": r["coverage_free"],
        "map_accuracy": round(acc_fn(grid), 4) if grid is not None else 0.0,
        "collisions": r["collisions"],
        "end_nodes_seen": len(follow.seen), "end_nodes_visited": len(follow.visited),
        "end_nodes_accepted_remote": sum(1 for b in beliefs
                                         if b.p >= p_reliable and b.id not in follow.visited),
        "end_nodes_final": len(beliefs), "targets": follow.targets,
        "stage_s": r["stage_s"],
        "planner": {"escalations": r["escalations"], "blocked_marks": r["blocked_marks"]},
    }


def _write(run_dir: Path, report: dict, follow: RunFollower | None, P: Any,
           label: str) -> None:
    """report.json, timeline.csv, trail.csv, map.yaml and final.png, as ``topoexplore run``
    writes them (only the report when the run broke off: an error or the wall-time limit)."""
    from topoexplore.common.mapio import write_map_server, write_png
    from topoexplore.tools.draw import Overlays, Style, render
    from topoexplore.tools.run import write_timeline, write_trail

    (run_dir / "report.json").write_text(json.dumps(report, indent=2) + "\n")
    if follow is None or follow.last is None or report.get("path_length_m") is None:
        return  # the run did not end on its own: no figures to draw
    write_timeline(run_dir / "timeline.csv", follow.timeline)
    write_trail(run_dir / "trail.csv", follow.trail)
    pose, graph, beliefs, plan, grid = follow.last
    write_map_server(run_dir / "map.yaml", grid.data, grid.geom, P.mapper.p_free,
                     P.mapper.p_occ)
    title = (f"{label} / {report['strategy']} / seed {report['seed']} (in process): "
             f"{'finished' if report['finished'] else 'not finished'}, "
             f"{report['path_length_m']:.1f} m, {report['sim_time_s']:.0f} s, "
             f"coverage {report['coverage']:.2f}")
    img = render(grid.data, grid.geom,
                 Overlays(topo=graph, rel=beliefs, robot_pose=tuple(pose), trail=follow.trail,
                          target_id=plan.route.target_id),
                 Style(p_free=P.mapper.p_free, p_occ=P.mapper.p_occ,
                       p_reliable=P.reliability.p_reliable, robot_radius=P.robot.radius,
                       crop=True, title=title))
    write_png(run_dir / "final.png", img)


# --------------------------------------------------------------------------------------------
# the bus check


def pick_bus_runs(runs: Sequence[dict], n: int) -> list[dict]:
    """n of the in-process runs to run again on the bus: finished runs that drove at least
    BUS_MIN_PATH_M, taking the strategies in turn and a world not yet taken where there is
    one (so a small n still sees every strategy). The shortest in sim time first, for speed;
    the last pick (of two or more) is the run nearest the median sim time of its candidates
    instead, so the check also sees a map of the size the suite's runs have."""
    pool = sorted((r for r in runs if r.get("finished")
                   and (r.get("path_length_m") or 0.0) >= BUS_MIN_PATH_M),
                  key=lambda r: (r["sim_time_s"], str(r.get("world_label")), r["strategy"],
                                 r["seed"]))
    chosen: list[dict] = []
    strategies = list(dict.fromkeys(r["strategy"] for r in pool))
    while len(chosen) < n and len(chosen) < len(pool):
        for st in strategies:
            if len(chosen) >= n:
                break
            left = [r for r in pool if r["strategy"] == st and r not in chosen]
            if not left:
                continue
            worlds = {c.get("world_label") for c in chosen}
            left = [r for r in left if r.get("world_label") not in worlds] or left
            mid = left[(len(left) - 1) // 2] if n >= 2 and len(chosen) == n - 1 else left[0]
            chosen.append(mid)
    return chosen


def compare(local: dict, bus: dict) -> dict[str, Any]:
    """One bus check: the same outcome (finished or not) and how far apart the paths are."""
    from topoexplore.tools.bench.explore import BUS_PATH_TOLERANCE

    pl, pb = local.get("path_length_m"), bus.get("path_length_m")
    diff = abs(pb - pl) / pl if pl and pb is not None else None
    same = bool(local.get("finished")) == bool(bus.get("finished"))
    agree = same and diff is not None and diff <= BUS_PATH_TOLERANCE
    return {"world_label": local.get("world_label"), "strategy": local["strategy"],
            "seed": local["seed"], "inproc_path_m": pl, "bus_path_m": pb,
            "inproc_coverage": local.get("coverage"), "bus_coverage": bus.get("coverage"),
            "inproc_finished": bool(local.get("finished")),
            "bus_finished": bool(bus.get("finished")), "bus_collisions": bus.get("collisions"),
            "bus_wall_s": bus.get("wall_time_s"), "inproc_wall_s": local.get("wall_time_s"),
            "path_difference": None if diff is None else round(diff, 5), "agree": agree,
            "bus_run_dir": bus.get("run_dir")}


def check_line(c: dict) -> str:
    d = c["path_difference"]
    return (f"{c['world_label']}/{c['strategy']}/{c['seed']}: in process "
            f"{c['inproc_path_m']} m, bus {c['bus_path_m']} m"
            + ("" if d is None else f" ({100 * d:.2f} % apart)")
            + ("" if c["inproc_finished"] == c["bus_finished"] else
               f"; finished in process {c['inproc_finished']}, on the bus {c['bus_finished']}")
            + ("" if c["agree"] else "; DISAGREE"))


# --------------------------------------------------------------------------------------------
# the plan, jobs at a time


def _item(item: tuple) -> dict:
    (label, arg, _), seed, st, out, tmax, twall, params, overrides = item
    return run_local(label, arg, st, seed, out, tmax, twall, params, overrides)


def run_plan(plan: Sequence[tuple], cfg: Any, done: Any) -> None:
    """The plan's runs ``cfg.jobs`` at a time, each in a worker process (started afresh:
    nothing of this process's state is shared), ``done(run)`` as each ends. On an interrupt
    the workers are stopped."""
    import multiprocessing

    items = [(w, seed, st, cfg.out, cfg.max_sim_time, cfg.max_wall_time, cfg.params,
              tuple(cfg.overrides)) for w, seed, st in plan]
    pool = multiprocessing.get_context("spawn").Pool(cfg.jobs)
    try:
        for run in pool.imap_unordered(_item, items):
            done(run)
        pool.close()
    except BaseException:
        pool.terminate()
        raise
    finally:
        pool.join()
