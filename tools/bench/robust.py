"""``topoexplore bench robust``: every strategy on a corpus of buildings it was never tuned on.

    topoexplore bench robust [--half tune|held|real|all] [--seeds 1,3] [--sim-seeds 0,1,2]
                             [--max-area M2] [--strategies ...] [--worlds ...] [--jobs 2] [--corpus DIR]
                             [--out DIR] [--set k=v ...] [--quick] [--bus N] [--no-progress]
                             [--doc docs/robustness.md]
    topoexplore bench robust --from-results DIR [DIR ...] [--out DIR] [--doc FILE.md]
    topoexplore bench robust --compare BASE NEW [--strategies ...]

The corpus is generated (``sim/generate.py``, deterministic) into ``--corpus``: the four styles
(office, house, warehouse, cluttered) x seeds 0..7, each as a clean world and as a SLAM-like map
(noise level 2): 64 worlds. Seeds 0..5 have the style's default size (18 x 14 m to 34 x 26 m),
seeds 6 and 7 are 1.5 x that, except the clean office and warehouse of seeds 6 and 7, which are
60 m x 60 m. Tuning uses the even seeds only (``--half tune``); the odd seeds are held back
(``--half held``) and reported apart, as are the real map_server maps in ``../shared/maps``
(``--half real``). ``--seeds`` and ``--max-area`` run a part of a half (a 60 x 60 m world
takes about 15 min of one core per run). Each run is the in-process pipeline (``bench
inproc``: the cores the services run, in the same order), for speed; ``--bus N`` also runs N
of the runs (the smallest worlds) through the real processes (``topoexplore run --lockstep``)
and compares outcome and path.

``--sim-seeds`` runs every world and strategy once per simulator seed (the laser's noise; the
world is the same). One exploration is chaotic: a single different choice early changes every
trip after it, so one run per world measures a rule's effect together with that chance. Path
ratios pair runs of the same world and simulator seed, average them per world (geometric mean
over its seeds), then over the worlds, with a 95 % interval over the worlds; the spread of one
strategy's path between the seeds of a world is reported beside it.

Every run is classified: ``finished`` (done, coverage >= 0.95), ``early-done`` (done below
that), ``failed`` (the planner gave up: the robot could not plan at all), ``livelock`` (the
time limit came while the map had stopped growing for the last ``STAGNANT_S`` of sim time),
``timeout`` (the time limit came while it still grew). The time limit scales with the world's
area (:func:`topoexplore.sim.world.time_limit`).

Writes to ``--out``: ``results.json`` (every run, the analysis, the corpus and the command),
``summary.md`` (tables per strategy and half, path ratios per world, the worst ten runs with
their pictures), ``runs.jsonl`` (each run as it ends) and ``pics/<world>-<strategy>.png`` (the
final map, graph and trail of every run; ``-sim<N>`` before ``.png`` for simulator seed N > 0). ``--doc`` writes the same report where the docs keep
it, with the ten worst runs' pictures scaled down beside it; ``--from-results`` merges the
results of several invocations (one per half, say) into one report without running anything.
``--compare`` runs nothing either: it pairs the worlds of two outputs (the same corpus before
and after a change) and says whether the change made the paths shorter beyond chance
(:mod:`.compare`).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from topoexplore.common.params import STRATEGIES, STRATEGY_NAMES
from topoexplore.sim.world import load_world, time_limit
from topoexplore.tools.bench.explore import (
    BenchArgError,
    check_overrides,
    geometric_interval,
    geometric_mean,
    parse_strategies,
)
from topoexplore.tools.bench.oracle import ratios, tour_length, world_file
from topoexplore.tools.paths import shared_maps_dir

STYLES = ("office", "house", "warehouse", "cluttered")
SEEDS = tuple(range(8))
LARGE = 60.0  # [m] side of the largest worlds
NOISE = 2  # SLAM-noise level of the noisy half of the corpus
REFERENCE = ("reliability-paper",)  # the paper's rule as written: shown, not held to targets
DEFAULT_STRATEGIES = (*STRATEGIES, *REFERENCE)  # every strategy and the paper's rule
GOOD_COVERAGE = 0.95
STAGNANT_S = 600.0  # [s] sim time without map growth before the limit: a livelock
QUICK = (("house", 0, None, (12.0, 10.0)), ("house", 1, NOISE, (12.0, 10.0)),
         ("cluttered", 1, None, (12.0, 10.0)))  # --quick: small worlds of both halves


@dataclass(frozen=True)
class Item:
    """One world of the corpus."""

    name: str
    path: str
    style: str  # a generator style, or "real" for a shared map
    seed: int  # -1 for a real map
    noise: int | None
    half: str  # "tune" | "held" | "real"
    area: float  # [m^2] of the world's rectangle


def half_of(seed: int) -> str:
    return "tune" if seed % 2 == 0 else "held"


def size_of(style: str, seed: int, noise: int | None) -> tuple[float, float] | None:
    """The corpus's size [m] for a world (None: the style's default)."""
    from topoexplore.sim.generate import DEFAULT_SIZES

    if seed < 6:
        return None
    if noise is None and style in ("office", "warehouse"):
        return (LARGE, LARGE)
    w, h = DEFAULT_SIZES[style]
    return (min(LARGE, round(1.5 * w)), min(LARGE, round(1.5 * h)))


def build_corpus(corpus_dir: Path, half: str, quick: bool = False,
                 seeds: Sequence[int] | None = None, max_area: float | None = None
                 ) -> list[Item]:
    """Generate (or reuse: the files are deterministic) the corpus's worlds of one half, only
    those of `seeds` and of at most `max_area` [m^2] if given."""
    from topoexplore.sim.generate import DEFAULT_SIZES, generate, write_generated
    specs = QUICK if quick else [(st, seed, lvl, size_of(st, seed, lvl)) for st in STYLES
                                 for seed in SEEDS for lvl in (None, NOISE)]
    out: list[Item] = []
    for style, seed, level, size in specs:
        if half != "all" and half != "real" and half_of(seed) != half:
            continue
        if half == "real" or (seeds is not None and seed not in seeds):
            continue
        w, h = size or DEFAULT_SIZES[style]
        if max_area is not None and w * h > max_area:
            continue
        gen = generate(style, seed, size)
        path = write_generated(gen, corpus_dir, level)
        w = load_world(str(path))
        out.append(Item(path.stem, str(path), style, seed, level, half_of(seed), w.area))
    if half in ("all", "real") and not quick:
        out += _real_maps()
    return out


def _real_maps() -> list[Item]:
    maps = shared_maps_dir()
    items = []
    for p in sorted(maps.glob("*.yaml")) if maps else []:
        w = load_world(str(p))
        items.append(Item(p.stem, str(p), "real", -1, None, "real", w.area))
    return items


# --------------------------------------------------------------------------------------------
# one run


def run_one(item: Item, strategy: str, sets: Sequence[str], pics: Path | None,
            sim_seed: int = 0) -> dict:
    """One in-process exploration with the figures the analysis needs (``sim_seed``: the
    simulator's seed, ``sim.seed``)."""
    from topoexplore.tools.bench import inproc

    track = _Track()
    t0 = time.monotonic()
    try:
        r = inproc.run(item.path, strategy, sim_seed, tuple(sets), time_limit(item.area),
                       track)
    except Exception as exc:  # noqa: BLE001 - one broken run must not end the benchmark
        r = {"state": "error", "finished": False, "stop_reason": f"{type(exc).__name__}: {exc}",
             "path_length_m": None, "sim_time_s": None, "coverage": None,
             "coverage_free": None, "collisions": None}
    r.update(world=item.name, style=item.style, seed=item.seed, noise=item.noise,
             half=item.half, strategy=strategy, sim_seed=int(sim_seed),
             area_m2=round(item.area, 1),
             limit_s=time_limit(item.area), wall_s=round(time.monotonic() - t0, 1),
             targets=track.targets, stagnant_s=track.stagnant_s(),
             completion_m=round(track.completion_m, 2))
    r["outcome"] = classify(r)
    r["oracle_m"] = tour_length(item.path)
    if pics is not None and track.last is not None:
        r["picture"] = _picture(item, strategy, r, track, pics)
    return r


class _Track:
    """What the benchmark follows during a run: targets chosen, map growth, the trail, the
    path driven toward completion-phase targets and the last state (for the picture)."""

    def __init__(self) -> None:
        from topoexplore.services.planner.strategies.completion import COMPLETION_NOTE

        self._note = COMPLETION_NOTE  # in a completion-phase target's status reason
        self.targets = 0
        self._plan_target: tuple[int, float, float] | None = None
        self.known: list[tuple[float, int]] = []  # (t [s], known cells)
        self.trail: list[tuple[float, float, int]] = []
        self.last: tuple | None = None
        self.completion_m = 0.0  # [m] driven while the target was a completion-phase one
        self._completing = False  # ... as the previous update's plan said
        self._at: tuple[float, float] | None = None  # [m] the previous update's pose

    def __call__(self, t, pose, graph, beliefs, plan, grid) -> None:
        if self._at is not None and self._completing:
            self.completion_m += math.hypot(pose.x - self._at[0], pose.y - self._at[1])
        self._at = (pose.x, pose.y)
        self._completing = self._note in plan.status.reason
        r = plan.route
        cur = (r.target_id, round(r.target_xy[0], 1), round(r.target_xy[1], 1))
        if len(r.waypoints) and cur != self._plan_target:
            self.targets += 1
            self._plan_target = cur
        n = int(np.count_nonzero(grid.data != -1))
        if not self.known or n > self.known[-1][1]:
            self.known.append((t, n))
        if not self.trail or math.hypot(pose.x - self.trail[-1][0],
                                        pose.y - self.trail[-1][1]) > 0.05:
            self.trail.append((pose.x, pose.y, self.targets))
        self.last = (t, pose, graph, beliefs, plan, grid)

    def stagnant_s(self) -> float:
        """[s] since the map last grew by more than 0.5 % (at the end of the run)."""
        if self.last is None or not self.known:
            return 0.0
        t_end, final = self.last[0], self.known[-1][1]
        for t, n in reversed(self.known):
            if n < 0.995 * final:
                return round(t_end - t, 1)
        return round(t_end - self.known[0][0], 1)


def classify(r: dict) -> str:
    state = r.get("state")
    if state == "done":
        return "finished" if (r.get("coverage") or 0.0) >= GOOD_COVERAGE else "early-done"
    if state == "timeout":
        return "livelock" if r.get("stagnant_s", 0.0) >= STAGNANT_S else "timeout"
    return "failed" if state == "failed" else "error"


def _picture(item: Item, strategy: str, r: dict, track: _Track, pics: Path) -> str:
    from topoexplore.common.mapio import write_png
    from topoexplore.tools.draw import Overlays, Style, render

    _t, pose, graph, beliefs, _plan, grid = track.last
    title = (f"{run_label(r)} / {strategy}: {r['outcome']}, {r['path_length_m']} m, coverage "
             f"{r['coverage']}")
    img = render(grid.data, grid.geom,
                 Overlays(topo=graph, rel=beliefs, robot_pose=tuple(pose),
                          trail=track.trail or None),
                 Style(crop=True, title=title))
    name = f"{item.name}-{strategy}" + (f"-sim{sim_seed(r)}" if sim_seed(r) else "") + ".png"
    write_png(pics / name, img)
    return f"pics/{name}"


# --------------------------------------------------------------------------------------------
# analysis (pure: the runs in, the figures out)

OUTCOMES = ("finished", "early-done", "failed", "livelock", "timeout", "error")


def sim_seed(r: dict) -> int:
    """The run's simulator seed (0 for runs made before ``--sim-seeds``)."""
    return int(r.get("sim_seed") or 0)


def run_label(r: dict) -> str:
    """The world's name, with ``/sim<N>`` for simulator seed N > 0."""
    return r["world"] + (f"/sim{sim_seed(r)}" if sim_seed(r) else "")


def run_key(r: dict) -> tuple[str, str, int]:
    """What makes a run one of a kind in a report: world, strategy, simulator seed."""
    return r["world"], r["strategy"], sim_seed(r)


def _pct(values: list[float], q: float) -> float | None:
    return float(np.percentile(values, q)) if values else None


def _escalations(r: dict) -> int:
    """Watchdog steps of a run (inproc gives them per step: {"blacklist": n, ...})."""
    e = r.get("escalations") or 0
    return int(sum(e.values())) if isinstance(e, dict) else int(e)


def strategy_table(runs: Sequence[dict], strategy: str) -> dict[str, Any]:
    """Outcome counts, coverage distribution and collisions of one strategy's runs."""
    rs = [r for r in runs if r["strategy"] == strategy]
    cov = [r["coverage"] for r in rs if r.get("coverage") is not None]
    out: dict[str, Any] = {"runs": len(rs)}
    for o in OUTCOMES:
        out[o] = sum(1 for r in rs if r["outcome"] == o)
    out["finished_rate"] = out["finished"] / len(rs) if rs else None
    out["coverage_min"] = min(cov) if cov else None
    out["coverage_p5"] = _pct(cov, 5)
    out["coverage_median"] = _pct(cov, 50)
    out["collisions"] = sum(r.get("collisions") or 0 for r in rs)
    out["escalations"] = sum(_escalations(r) for r in rs)  # watchdog steps
    out["blocked_marks"] = sum(r.get("blocked_marks") or 0 for r in rs)  # learned blockages
    return out


def world_paths(runs: Sequence[dict]) -> dict[tuple[str, int], dict[str, float]]:
    """{(world, simulator seed): {strategy: path [m]}} of the runs that finished (outcome
    "finished")."""
    out: dict[tuple[str, int], dict[str, float]] = {}
    for r in runs:
        if r["outcome"] == "finished" and r.get("path_length_m") is not None:
            out.setdefault((r["world"], sim_seed(r)), {})[r["strategy"]] = \
                float(r["path_length_m"])
    return out


def path_ratio(runs: Sequence[dict], num: str, den: str, style: str | None = None
               ) -> dict[str, Any]:
    """path(num) / path(den) over the worlds where both finished (with a positive path); style
    limits it to one style. Runs pair by world and simulator seed; a world's ratio is the
    geometric mean over its pairs, and ``geomean`` the geometric mean over the worlds, with
    ``low``..``high`` its 95 % interval (Student's t on the worlds' log ratios; None below
    MIN_INTERVAL worlds). ``n``: worlds, ``pairs``: run pairs."""
    styles = {r["world"]: r["style"] for r in runs}
    logs: dict[str, list[float]] = {}
    for (w, _sim), p in world_paths(runs).items():
        if num in p and den in p and p[den] > 0 and p[num] > 0 and (
                style is None or styles[w] == style):
            logs.setdefault(w, []).append(math.log(p[num] / p[den]))
    per_world = {w: math.exp(sum(v) / len(v)) for w, v in logs.items()}
    out: dict[str, Any] = {"geomean": geometric_mean(per_world.values()), "n": len(per_world),
                           "pairs": sum(len(v) for v in logs.values()), "low": None,
                           "high": None,
                           "worlds": {w: round(v, 3) for w, v in sorted(per_world.items())}}
    ci = geometric_interval(per_world.values())
    if ci is not None:
        out["low"], out["high"] = ci
    return out


def sim_spread(runs: Sequence[dict], strategy: str) -> dict[str, Any]:
    """How far one strategy's path moves between simulator seeds of the same world: per world
    with at least two finished seeds, the longest path over the shortest; the median and the
    largest of that over the worlds (None without such a world)."""
    by: dict[str, list[float]] = {}
    for (w, _sim), p in world_paths(runs).items():
        if p.get(strategy, 0.0) > 0:
            by.setdefault(w, []).append(p[strategy])
    spread = [max(v) / min(v) for v in by.values() if len(v) >= 2]
    return {"n": len(spread), "median": _pct(spread, 50),
            "max": max(spread) if spread else None}


def over_shortest(runs: Sequence[dict], factor: float = 2.0) -> list[dict]:
    """Finished runs whose path exceeds factor x the shortest finished path of the three
    strategies (variants are measured against it, not part of it) on their world."""
    paths = world_paths(runs)
    out = []
    for (w, sim), p in paths.items():
        own = [v for st, v in p.items() if st in STRATEGIES and v > 0]
        if len(p) < 2 or not own:
            continue
        best = min(own)
        for st, v in p.items():
            if best > 0 and v > factor * best:
                out.append({"world": w, "strategy": st, "ratio": round(v / best, 2)}
                           | ({"sim_seed": sim} if sim else {}))
    return out


_SEVERITY = {"error": 0, "failed": 1, "early-done": 2, "livelock": 3, "timeout": 4,
             "finished": 5}


def completion_share(runs: Sequence[dict], strategy: str) -> dict[str, Any]:
    """The share of a finished run's path driven toward completion-phase targets (frontier
    groups once no end node is left to visit; docs/design.md), over one strategy's finished
    runs that carry it (``completion_m``, since 2026-12-05): median and largest, ``n`` runs."""
    v = [r["completion_m"] / r["path_length_m"] for r in runs
         if r["strategy"] == strategy and r["outcome"] == "finished"
         and r.get("completion_m") is not None and (r.get("path_length_m") or 0.0) > 0.0]
    return {"n": len(v), "median": _pct(v, 50), "max": max(v) if v else None}


def worst(runs: Sequence[dict], n: int = 10) -> list[dict]:
    """The n worst runs: by outcome, then coverage (the paper's rule, a reference that stops
    without a completion phase, is left out)."""
    return sorted((r for r in runs if r["strategy"] not in REFERENCE),
                  key=lambda r: (_SEVERITY[r["outcome"]], r.get("coverage") or 0.0))[:n]


def analyse(runs: Sequence[dict], strategies: Sequence[str]) -> dict[str, Any]:
    """Per half (tune / held / real): a table per strategy, path ratios, the runs over 2 x the
    shortest path, the worst runs."""
    out: dict[str, Any] = {}
    for half in ("tune", "held", "real"):
        rs = [r for r in runs if r["half"] == half]
        if not rs:
            continue
        h: dict[str, Any] = {"strategies": {s: strategy_table(rs, s) for s in strategies}}
        h["ratios"] = {f"{a}/{b}": path_ratio(rs, a, b)
                       for a, b in (("reliability", "frontier"), ("reliability", "all-end-nodes"),
                                    ("reliability", "reliability-paper"),
                                    ("reliability", "reliability-distance"),
                                    ("reliability-paper", "frontier"))
                       if a in strategies and b in strategies}
        if "reliability" in strategies and "frontier" in strategies:
            h["ratios_by_style"] = {st: path_ratio(rs, "reliability", "frontier", st)
                                    for st in sorted({r["style"] for r in rs})}
        h["oracle"] = ratios(rs, lambda r: r.get("oracle_m"))["strategies"]
        if any(sim_seed(r) for r in rs):
            h["sim_spread"] = {s: sim_spread(rs, s) for s in strategies}
        h["completion_share"] = {s: completion_share(rs, s) for s in strategies}
        h["over_2x_shortest"] = over_shortest(rs)
        h["worst"] = [{k: r.get(k) for k in ("world", "strategy", "sim_seed", "outcome",
                                              "coverage", "path_length_m", "stop_reason",
                                              "picture")}
                      for r in worst(rs)]
        out[half] = h
    return out


# --------------------------------------------------------------------------------------------
# output


def _f(v: Any, dec: int = 3) -> str:
    return "–" if v is None else (f"{v:.{dec}f}" if isinstance(v, float) else str(v))


def _median_max(per: dict[str, dict]) -> str:
    """"strategy median, largest (n)" for each strategy of {strategy: {median, max, n}}."""
    return ", ".join(f"{st} {_f(v['median'], 2)}, {_f(v['max'], 2)} ({v['n']})"
                     for st, v in per.items())


def _half_md(name: str, h: dict, link) -> list[str]:
    L = [f"### {name}", "", "| strategy | runs | finished | early done | failed | livelock | "
         "timeout | collisions | watchdog | blockages | coverage min | p5 | median |",
         "|" + "---|" * 13]
    for st, t in h["strategies"].items():
        if not t["runs"]:
            continue
        L.append(f"| {st} | {t['runs']} | {t['finished']} | {t['early-done']} | {t['failed']} "
                 f"| {t['livelock']} | {t['timeout']} | {t['collisions']} | {t['escalations']} | "
                 f"{t['blocked_marks']} | "
                 f"{_f(t['coverage_min'])} | {_f(t['coverage_p5'])} | "
                 f"{_f(t['coverage_median'])} |")
    L.append("")
    for key, rr in h["ratios"].items():
        if not rr["n"]:
            continue
        pairs = rr.get("pairs", rr["n"])
        ci = (f" (95 % interval {_f(rr['low'])}–{_f(rr['high'])})"
              if rr.get("low") is not None else "")
        L.append(f"- path {key}: geometric mean **{_f(rr['geomean'])}**{ci} over {rr['n']} "
                 "world(s) where both finished"
                 + (f", {pairs} run pairs" if pairs != rr["n"] else ""))
        if key == "reliability/frontier":  # by style right below it
            for st, rs in h.get("ratios_by_style", {}).items():
                L.append(f"  - {st}: {_f(rs['geomean'])} ({rs['n']} worlds)")
    if h.get("oracle"):
        L.append("- path / oracle tour (a short tour planned on the true map, "
                 "`topoexplore bench oracle`): " + ", ".join(
                     f"{st} **{_f(o['geomean'], 2)}** ({o['n']})"
                     for st, o in h["oracle"].items()))
    spread = {st: v for st, v in h.get("sim_spread", {}).items() if v["n"]}
    if spread:
        L.append("- path spread between simulator seeds of one world (longest / shortest "
                 "finished path; median, largest over the worlds): " + _median_max(spread))
    share = {st: v for st, v in h.get("completion_share", {}).items() if v["n"] and v["max"]}
    if share:
        L.append("- share of the path driven in the completion phase (frontier groups after "
                 "the end nodes; median, largest over the finished runs): "
                 + _median_max(share))
    over = h["over_2x_shortest"]
    L.append(f"- runs over 2 x the shortest path of the three strategies on their world: "
             f"{len(over)}"
             + (": " + ", ".join(f"{run_label(o)}/{o['strategy']} ({o['ratio']})"
                                 for o in over)
                if over else ""))
    L += ["", "Worst runs:", "", "| world | strategy | outcome | coverage | path [m] | why |",
          "|---|---|---|---|---|---|"]
    for r in h["worst"]:
        where = link(r)
        pic = f" ([picture]({where}))" if where else ""
        why = (r.get("stop_reason") or "").replace("|", "/")[:160]
        L.append(f"| {run_label(r)}{pic} | {r['strategy']} | {r['outcome']} | "
                 f"{_f(r['coverage'])} | {_f(r['path_length_m'], 1)} | {why} |")
    return L + [""]


def summary(doc: dict, link=None) -> str:
    """The markdown report; link(run) gives a worst run's picture link (default: as stored)."""
    link = link or (lambda r: r.get("picture"))
    commands = doc.get("commands") or [doc["command"]]
    L = ["# Robustness: every strategy on buildings it was not tuned on", "",
         f"Made {doc['created']} ({len(doc['runs'])} runs, {doc['wall_s']:.0f} s wall, "
         f"{doc['jobs']} at a time) with:", ""] + [f"    {c}" for c in commands] + [""]
    L += ["Outcomes: finished (done, coverage >= 0.95), early done (done below that), failed "
          "(the planner gave up), livelock (time limit, the map had not grown by 0.5 % for "
          f"{STAGNANT_S:.0f} s), timeout (time limit, still growing). Coverage is against the "
          "free space the robot can reach and see (`sim.world.truth_mappable`). Watchdog: "
          "escalation steps; blockages: learned obstacles (docs/design.md). Path ratios: "
          "geometric mean over the worlds where both strategies finished (runs paired by "
          "world and simulator seed, a world's seeds averaged first), with a 95 % interval "
          "over the worlds when there are three or more. "
          "`reliability-paper` is the paper's rule exactly as written (no completion phase: "
          "done when every end node is reliable), the reference for our departures; it is not "
          "held to the targets and not among the worst runs. `reliability-distance` is ours "
          "without the examined-surroundings test (docs/design.md, \"Reliability\").", ""]
    names = {"tune": "Tuning half (even seeds)", "held": "Held-back half (odd seeds)",
             "real": "Real maps (../shared/maps)"}
    for half, h in doc["analysis"].items():
        L += _half_md(names[half], h, link)
    if doc.get("bus"):
        L += ["### On the bus", ""] + [f"- {run_label(b)} / {b['strategy']}: {b['note']}"
                                       for b in doc["bus"]] + [""]
    return "\n".join(L) + "\n"


def merge(docs: Sequence[tuple[Path, dict]]) -> dict:
    """One report from several results.json (e.g. one per half): a later run of the same world
    and strategy replaces an earlier one; pictures keep their absolute paths (``_picture``)."""
    by: dict[tuple[str, str], dict] = {}
    for src, d in docs:
        for r in d["runs"]:
            r = dict(r)
            if r.get("picture"):
                r["_picture"] = str((src / r["picture"]).resolve())
            by[run_key(r)] = r
    runs = sorted(by.values(), key=lambda r: ({"tune": 0, "held": 1, "real": 2}[r["half"]],
                                              *run_key(r)))
    strategies = [s for s in STRATEGY_NAMES if any(r["strategy"] == s for r in runs)]
    commands: list[str] = []
    for _, d in docs:
        commands += d.get("commands") or [d["command"]]
    return {"created": max(d["created"] for _, d in docs), "commands": commands,
            "command": commands[0], "jobs": max(d["jobs"] for _, d in docs), "runs": runs,
            "wall_s": sum(d["wall_s"] for _, d in docs), "analysis": analyse(runs, strategies),
            "bus": [b for _, d in docs for b in d.get("bus") or []]}


DOC_PICTURES = 10  # pictures in the docs: the worst ten runs of the whole report
DOC_WIDTH = 720  # [px] ... scaled down to this width, as JPEG


def write_report(doc: dict, md_path: Path, pic_dir: Path, for_docs: bool = False) -> None:
    """summary(doc) to md_path, with the worst runs' pictures copied to pic_dir (linked
    relative to md_path): the worst of each half, or with for_docs the worst DOC_PICTURES of
    the whole report, scaled down (the repository keeps them)."""
    import os
    import shutil

    import cv2

    if for_docs:
        wanted = {run_key(r) for r in worst(doc["runs"], DOC_PICTURES)}
    else:
        wanted = {run_key(w) for h in doc["analysis"].values() for w in h["worst"]}
    src = {run_key(r): r.get("_picture") for r in doc["runs"]}
    links: dict[tuple[str, str, int], str] = {}
    for key in sorted(wanted):
        if not (src.get(key) and Path(src[key]).is_file()):
            continue
        pic_dir.mkdir(parents=True, exist_ok=True)
        if for_docs:
            img = cv2.imread(src[key], cv2.IMREAD_COLOR)
            if img is None:
                continue
            scale = min(1.0, DOC_WIDTH / img.shape[1])
            img = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
            dst = pic_dir / (Path(src[key]).stem + ".jpg")
            cv2.imwrite(str(dst), img, [cv2.IMWRITE_JPEG_QUALITY, 85])
        else:
            dst = pic_dir / Path(src[key]).name
            if Path(src[key]).resolve() != dst.resolve():
                shutil.copyfile(src[key], dst)
        links[key] = os.path.relpath(dst, md_path.parent)
    for h in doc["analysis"].values():
        for w in h["worst"]:
            w["picture"] = links.get(run_key(w))
    md_path.parent.mkdir(parents=True, exist_ok=True)
    md_path.write_text(summary(doc, lambda r: r.get("picture")))


# --------------------------------------------------------------------------------------------
# command line


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:
        raise BenchArgError(message)


def build_parser() -> argparse.ArgumentParser:
    ap = _Parser(prog="topoexplore bench robust", description=__doc__.split("\n\n")[0])
    ap.add_argument("--half", choices=("tune", "held", "real", "all"), default="all")
    ap.add_argument("--strategies", default=",".join(DEFAULT_STRATEGIES),
                    help="comma-separated strategies and variants (default: "
                         f"{','.join(DEFAULT_STRATEGIES)}; reliability-paper is the paper's "
                         f"rule as written; also {', '.join(sorted(set(STRATEGY_NAMES) - set(DEFAULT_STRATEGIES)))})")
    ap.add_argument("--worlds", default=None, help="only these corpus worlds (comma separated)")
    ap.add_argument("--corpus", type=Path, default=Path("runs/robust-corpus"))
    ap.add_argument("--out", type=Path, default=Path("runs/bench-robust"))
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="parameter override for every run (repeatable)")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--seeds", default=None, help="only these seeds of the half (comma separated)")
    ap.add_argument("--sim-seeds", default="0", metavar="0,1,2",
                    help="run every world and strategy once per simulator seed (sim.seed: the "
                         "laser's noise), comma separated (default: 0)")
    ap.add_argument("--max-area", type=float, default=None, metavar="M2",
                    help="only worlds of at most this area [m^2]")
    ap.add_argument("--quick", action="store_true",
                    help="three small worlds of 12 x 10 m (a smoke run)")
    ap.add_argument("--bus", type=int, default=0, metavar="N",
                    help="also run N runs (the smallest worlds) on the real processes and "
                         "compare")
    ap.add_argument("--no-progress", action="store_true")
    ap.add_argument("--from-results", nargs="+", type=Path, default=None, metavar="DIR",
                    help="run nothing: one report from these results (e.g. one per half)")
    ap.add_argument("--compare", nargs=2, type=Path, default=None, metavar=("BASE", "NEW"),
                    help="run nothing: per world and strategy, the path of NEW's runs against "
                         "BASE's (two --out directories), with a 95 %% interval and a sign test")
    ap.add_argument("--doc", type=Path, default=None, metavar="FILE.md",
                    help="also write the report here, the worst runs' pictures in img/robust/ "
                         "beside it (e.g. docs/robustness.md)")
    return ap


def _load_results(dirs: Sequence[Path]) -> list[tuple[Path, dict]]:
    out = []
    for d in dirs:
        f = d / "results.json"
        try:
            doc = json.loads(f.read_text())
            doc["runs"], doc["created"], doc["wall_s"], doc["jobs"]  # noqa: B018 - the keys used
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise BenchArgError(f"--from-results: cannot read {f}: "
                                f"{type(exc).__name__}: {exc}") from None
        out.append((d, doc))
    return out


Run = tuple[Item, str, int]  # a planned run: world, strategy, simulator seed
MAX_SIM_SEEDS = 1000


def _int_list(text: str, flag: str) -> list[int]:
    """Comma-separated integers, sorted, without repeats (a one-line error otherwise)."""
    try:
        return sorted({int(v) for v in text.split(",") if v.strip()})
    except ValueError:
        raise BenchArgError(f"{flag}: integers please (got {text!r})") from None


def _plan(a: argparse.Namespace) -> tuple[list[Run], list[str]]:
    strategies = parse_strategies(a.strategies)
    if a.jobs < 1 or a.bus < 0:
        raise BenchArgError("--jobs must be >= 1 and --bus >= 0")
    check_overrides(None, a.set)
    sims = _int_list(a.sim_seeds, "--sim-seeds")
    if not sims or sims[0] < 0 or sims[-1] >= MAX_SIM_SEEDS:
        raise BenchArgError(f"--sim-seeds: seeds 0..{MAX_SIM_SEEDS - 1} please "
                            f"(got {a.sim_seeds!r})")
    seeds = None
    if a.seeds is not None:
        seeds = _int_list(a.seeds, "--seeds")
        bad_seeds = [v for v in seeds if v not in SEEDS]
        if bad_seeds or not seeds:
            raise BenchArgError(f"--seeds: the corpus has seeds {SEEDS[0]}..{SEEDS[-1]} "
                                f"(got {a.seeds!r})")
    if a.max_area is not None and not (math.isfinite(a.max_area) and a.max_area > 0):
        raise BenchArgError("--max-area must be a positive number of m^2")
    if a.half in ("all", "real") and not a.quick and shared_maps_dir() is None:
        if a.half == "real":
            raise BenchArgError("--half real: no ../shared/maps beside the current directory "
                                "or the checkout")
        print("topoexplore bench robust: note: no ../shared/maps beside the current directory "
              "or the checkout: the real maps are left out", file=sys.stderr)
    items = build_corpus(a.corpus, a.half, a.quick, seeds, a.max_area)
    if a.worlds:
        want = {w.strip() for w in a.worlds.split(",") if w.strip()}
        missing = want - {i.name for i in items}
        if missing:
            raise BenchArgError(f"--worlds: not in this corpus half: {', '.join(sorted(missing))}")
        items = [i for i in items if i.name in want]
    items.sort(key=lambda i: -i.area)  # the longest first, so no long run starts last
    return [(i, s, k) for i in items for k in sims for s in strategies], strategies


def _execute(plan: list[Run], a: argparse.Namespace) -> list[dict]:
    from tqdm import tqdm

    pics = a.out / "pics"
    runs: list[dict] = []
    partial = (a.out / "runs.jsonl").open("w")  # every run as it ends (a long run can be read
    #                                              before the benchmark finishes)
    bar = tqdm(total=len(plan), unit="run", desc="bench robust", file=sys.stderr,
               dynamic_ncols=True, disable=a.no_progress)
    with ProcessPoolExecutor(min(a.jobs, max(1, len(plan)))) as pool:
        futs = [pool.submit(run_one, item, st, tuple(a.set), pics, k) for item, st, k in plan]
        for f in as_completed(futs):
            r = f.result()
            runs.append(r)
            partial.write(json.dumps(r) + "\n")
            partial.flush()
            bar.set_postfix_str(f"{run_label(r)}/{r['strategy']}: {r['outcome']} "
                                f"{_f(r.get('coverage'))}", refresh=False)
            bar.update(1)
    bar.close()
    partial.close()
    order = {(i.name, s, k): n for n, (i, s, k) in enumerate(plan)}
    return sorted(runs, key=lambda r: order[run_key(r)])


def _bus_check(plan: list[Run], runs: list[dict], n: int, out: Path,
               sets: Sequence[str]) -> list[dict]:
    """n runs of the plan again through `topoexplore run --lockstep` (the real processes on
    the bus), the smallest worlds first: the same outcome, and how far apart the paths are.
    In-process and bus runs order the services' work the same way but not always the same
    message for message, so paths agree closely rather than to the bit."""
    from topoexplore.tools.bench.explore import run_one as bus_run

    by = {run_key(r): r for r in runs}
    sample = sorted(plan, key=lambda p: (p[0].area, p[0].name, p[2], p[1]))[:n]
    notes = []
    for item, st, k in sample:
        rep = bus_run(item.name, item.path, st, k, out / "bus", time_limit(item.area), 0.0,
                      None, tuple(sets))
        local = by[(item.name, st, k)]
        bus_state = "done" if rep.get("finished") else (
            "timeout" if "max sim time" in str(rep.get("stop_reason")) else "failed")
        bus_outcome = classify({"state": bus_state, "coverage": rep.get("coverage"),
                                "stagnant_s": 0.0})
        pb, pl = rep.get("path_length_m"), local.get("path_length_m")
        diff = (abs(pb - pl) / pl) if pb is not None and pl else None
        same = bus_outcome == local["outcome"]
        notes.append({"world": item.name, "strategy": st, "sim_seed": k, "same_outcome": same,
                      "bus_outcome": bus_outcome, "bus_path_m": pb, "bus_coverage":
                      rep.get("coverage"), "path_difference": diff,
                      "note": (f"bus {bus_outcome}, {pb} m, coverage {rep.get('coverage')}, "
                               f"collisions {rep.get('collisions')}; in process "
                               f"{local['outcome']}, {pl} m, coverage {local['coverage']}"
                               + ("" if diff is None else f"; paths {100 * diff:.1f} % apart")
                               + ("" if same else "; DIFFERENT OUTCOME"))})
    return notes


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        from topoexplore.tools.extras import ExtraMissing, require

        a = build_parser().parse_args(argv)
        if a.compare:  # reads two outputs: needs neither the simulator nor a progress bar
            from topoexplore.tools.bench.compare import main_compare

            named = (None if a.strategies == ",".join(DEFAULT_STRATEGIES)
                     else parse_strategies(a.strategies))
            return main_compare(a.compare, named)
        try:
            require("pymunk", "tqdm", what="topoexplore bench robust")
        except ExtraMissing as exc:
            raise BenchArgError(str(exc)) from None
        if a.from_results:
            return _report_only(a)
        plan, strategies = _plan(a)
    except BenchArgError as exc:
        print(f"topoexplore bench robust: {exc}", file=sys.stderr)
        return 2
    except SystemExit as exc:  # --help
        return int(exc.code or 0)
    a.out.mkdir(parents=True, exist_ok=True)
    t0 = time.monotonic()
    runs = _execute(plan, a)
    doc = {"created": time.strftime("%Y-%m-%d %H:%M"), "command": " ".join(
        ["topoexplore", "bench", "robust", *argv]), "jobs": a.jobs, "runs": runs,
        "wall_s": time.monotonic() - t0, "analysis": analyse(runs, strategies)}
    if a.bus:
        doc["bus"] = _bus_check(plan, runs, a.bus, a.out, a.set)
    (a.out / "results.json").write_text(json.dumps(doc, indent=1) + "\n")
    (a.out / "summary.md").write_text(summary(doc))
    if a.doc:
        write_report(merge([(a.out, doc)]), a.doc, a.doc.parent / "img" / "robust", True)
    print(f"bench robust: {len(runs)} runs -> {a.out}/summary.md, results.json, pics/"
          + (f"; {a.doc}" if a.doc else ""), file=sys.stderr)
    return 0


def _fill_oracle(runs: list[dict], corpus: Path, jobs: int) -> None:
    """Runs made before the oracle get its tour (``oracle_m``) from the world in corpus (or
    the shared maps), jobs worlds at a time; None where the world is not at hand."""
    files: dict[str, str | None] = {}
    for r in runs:
        if "oracle_m" not in r and r["world"] not in files:
            try:
                files[r["world"]] = world_file(r["world"], corpus)
            except BenchArgError:
                files[r["world"]] = None
    todo = sorted(w for w, f in files.items() if f is not None)
    tours: dict[str, float | None] = dict.fromkeys(files)
    if todo:
        with ProcessPoolExecutor(max(1, min(jobs, len(todo)))) as pool:
            tours.update(zip(todo, pool.map(tour_length, [files[w] for w in todo]),
                             strict=True))
    for r in runs:
        if "oracle_m" not in r:
            r["oracle_m"] = tours[r["world"]]


def _report_only(a: argparse.Namespace) -> int:
    """--from-results: merge, analyse and write; nothing runs."""
    loaded = _load_results(a.from_results)
    _fill_oracle([r for _, d in loaded for r in d["runs"]], a.corpus, a.jobs)
    doc = merge(loaded)
    a.out.mkdir(parents=True, exist_ok=True)
    clean = {k: v for k, v in doc.items() if k != "runs"}
    clean["runs"] = [{k: v for k, v in r.items() if k != "_picture"} for r in doc["runs"]]
    write_report(doc, a.out / "summary.md", a.out / "pics")
    (a.out / "results.json").write_text(json.dumps(clean, indent=1) + "\n")
    if a.doc:
        write_report(doc, a.doc, a.doc.parent / "img" / "robust", True)
    print(f"bench robust: {len(doc['runs'])} runs from {len(a.from_results)} result(s) -> "
          f"{a.out}/summary.md" + (f", {a.doc}" if a.doc else ""), file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
