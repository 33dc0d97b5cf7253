"""``topoexplore bench explore``: the strategy comparison suite (DESIGN §6 metrics).

    topoexplore bench explore [--worlds a,b,...] [--strategies reliability,all-end-nodes,frontier]
                              [--seeds N] [--out DIR] [--max-sim-time S] [--max-wall-time S]
                              [--jobs 2] [--bus-check N | --bus [--record ...]] [--quick]
                              [--no-progress]
    topoexplore bench explore --from-results DIR [--out DIR2]

Runs every world x strategy x seed in lockstep, two at a time by default (this is a 2-core
machine), each exploration in one process: the six cores that the services run, called in
the order they run them (``bench inproc``'s pipeline, :mod:`.explore_local`), at about a
third of the CPU of the same run on the bus. Then ``--bus-check N`` (default 3) of the runs
are made again with ``topoexplore run --lockstep``, the real processes on the bus, and
compared (the same outcome, paths within 2 %). ``--bus`` makes every run that way (each run
is then 7 processes, and the suite takes about three times as long). Writes to ``--out``:

- ``results.json`` — every run's ``report.json`` plus derived fields (world label, exit code,
  run directory, distance to 90 % / 95 % coverage, the coverage-over-distance timeline), the
  per (world, strategy) aggregates, the per-pair ratios with their geometric means, the
  coverage-distance table, the machine and the command that reproduces it;
- ``results.csv`` — one row per run (scalar fields only);
- ``summary.md`` — the tables in Markdown;
- ``curves/<world>.png`` — coverage (y) over distance travelled (x), one line per strategy
  (mean over seeds on a common distance grid);
- ``runs/<world>-<strategy>-<seed>/`` — each run's own output (report, final.png, map, ...).

Coverage (docs/design.md "Measuring a run"): ``coverage``, the headline, is the share of the free
space the robot can map (reach with its footprint from the start, and see from there) that the
map knows; ``coverage_free`` beside it is the older share of every free cell connected to the
start. The curves, the distances to 90 / 95 % and the low-coverage notes use ``coverage``.

Ratios (reliability / frontier, reliability / all-end-nodes; path length and sim time) are
taken per run pair (same world, same seed). The headline figure is the geometric mean over
the pairs where both runs finished; the other pairs are listed with the reason they were
left out. ``--from-results DIR`` re-makes the summary, CSV and curves from ``DIR/results.json``
without running anything. Exit code: 0 when the suite was run (whatever the runs' outcomes),
2 on bad arguments (one line on stderr, before anything runs), 130 when interrupted (partial
results are written).
"""

from __future__ import annotations

import argparse
import csv
import datetime as _dt
import json
import math
import os
import platform
import re
import shlex
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterable, Sequence
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from topoexplore.common.params import STRATEGIES, STRATEGY_NAMES
from topoexplore.tools.extras import ExtraMissing, require
from topoexplore.tools.launch.supervisor import free_port
from topoexplore.tools.paths import checkout_root, shared_maps_dir

BUS_PATH_TOLERANCE = 0.02  # in process: a bus check agrees when the paths are this close

EXTRA_MAPS = ("lse_arena.yaml",)  # real map_server maps added to the default suite
QUICK_WORLDS = ("paper-room", "dead-end")
RATIO_PAIRS = (("reliability", "frontier"), ("reliability", "all-end-nodes"))
RATIO_METRICS = ("path_length_m", "sim_time_s")
COVERAGE_THRESHOLDS = (0.90, 0.95)
LOW_COVERAGE = 0.95  # finished runs below this coverage are pointed out in the summary
DEFAULT_SEEDS = 2
DEFAULT_MAX_SIM_TIME = 6000.0  # [s] simulated time per run (large-office needs ~3900)
DEFAULT_MAX_WALL_TIME = 1800.0  # [s] wall time per run (0: no limit)
DEFAULT_JOBS = 2  # runs at a time
DEFAULT_BUS_CHECK = 3  # in process: runs made again on the bus (one per strategy)
CURVE_POINTS = 400  # points of the common distance grid of the mean curves
PACKAGES = ("eclipse-zenoh", "numpy", "scipy", "opencv-python-headless", "pymunk", "msgspec",
            "msgpack", "scikit-image", "numba", "tqdm", "matplotlib", "topoexplore")

# aggregated per (world, strategy): field -> (column title, decimals)
AGG_FIELDS = {
    "path_length_m": ("path [m]", 1),
    "sim_time_s": ("sim time [s]", 0),
    "coverage": ("coverage", 3),
    "coverage_free": ("coverage of all free", 3),
    "map_accuracy": ("map accuracy", 3),
    "collisions": ("collisions", 1),
    "end_nodes_visited": ("end nodes visited", 1),
    "end_nodes_accepted_remote": ("accepted from a distance", 1),
    "wall_time_s": ("wall [s]", 1),
}


class BenchArgError(ValueError):
    """Bad command-line argument for ``bench explore`` (one-line message)."""


class BenchDataError(ValueError):
    """Bad data given to an analysis function (one-line message)."""


# --------------------------------------------------------------------------------------------
# pure analysis (unit-tested on hand-made reports and timelines)


def distance_to_coverage(distances: Sequence[float], coverages: Sequence[float],
                         threshold: float) -> float | None:
    """Distance travelled [m] at the first timeline sample whose coverage is >= ``threshold``.

    ``distances`` are the path lengths of the samples [m] (a stale, smaller value is treated as
    the running maximum: the path length never decreases), ``coverages`` the coverage at each
    sample (0..1). Returns ``None`` if the coverage never reaches the threshold.
    """
    d = np.asarray(distances, dtype=np.float64)
    c = np.asarray(coverages, dtype=np.float64)
    if d.ndim != 1 or c.shape != d.shape:
        raise BenchDataError(f"distances and coverages must be 1-D of equal length "
                             f"(got {d.shape} and {c.shape})")
    if not (0.0 < threshold <= 1.0):
        raise BenchDataError(f"threshold must be in (0, 1] (got {threshold})")
    if not (np.all(np.isfinite(d)) and np.all(np.isfinite(c))):
        raise BenchDataError("distances and coverages must be finite")
    hit = np.flatnonzero(c >= threshold)
    if hit.size == 0:
        return None
    return float(np.maximum.accumulate(d)[hit[0]])


def coverage_on_grid(distances: Sequence[float], coverages: Sequence[float],
                     grid: Sequence[float]) -> np.ndarray:
    """Coverage of one run at the distances ``grid`` [m]: the last sample at or before each
    distance (step function); 0 before the first sample, the final value after the last."""
    d = np.maximum.accumulate(np.asarray(distances, dtype=np.float64))
    c = np.asarray(coverages, dtype=np.float64)
    g = np.asarray(grid, dtype=np.float64)
    if d.ndim != 1 or c.shape != d.shape:
        raise BenchDataError("distances and coverages must be 1-D of equal length")
    if d.size == 0:
        return np.zeros_like(g)
    idx = np.searchsorted(d, g, side="right") - 1
    return np.where(idx >= 0, c[np.clip(idx, 0, None)], 0.0)


def mean_curve(timelines: Sequence[tuple[Sequence[float], Sequence[float]]],
               points: int = CURVE_POINTS) -> tuple[np.ndarray, np.ndarray]:
    """Mean coverage over several runs on a common distance grid 0..longest run [m].

    ``timelines`` holds ``(distances, coverages)`` per run; a run that stopped earlier keeps
    its final coverage. Returns ``(grid, mean)``; empty arrays if there is no sample at all.
    """
    tls = [(np.asarray(d, dtype=np.float64), np.asarray(c, dtype=np.float64))
           for d, c in timelines if len(d) > 0]
    if not tls:
        return np.zeros(0), np.zeros(0)
    end = max(float(np.max(d)) for d, _ in tls)
    grid = np.linspace(0.0, end, max(2, points))
    stack = np.stack([coverage_on_grid(d, c, grid) for d, c in tls])
    return grid, stack.mean(axis=0)


def geometric_mean(values: Iterable[float]) -> float | None:
    """exp(mean(log v)) of positive finite values; ``None`` for none."""
    v = np.asarray(list(values), dtype=np.float64)
    if v.size == 0:
        return None
    if not np.all(np.isfinite(v)) or np.any(v <= 0):
        raise BenchDataError("geometric mean needs positive finite values")
    return float(np.exp(np.mean(np.log(v))))


MIN_INTERVAL = 3  # values needed for an interval (with two, Student's t makes it ~ x/100..x100)


def geometric_interval(values: Iterable[float], level: float = 0.95
                       ) -> tuple[float, float] | None:
    """The level interval of the geometric mean of positive values (ratios): Student's t on
    their logs; None below MIN_INTERVAL values."""
    from scipy.stats import t as student_t

    x = np.log(np.asarray(list(values), dtype=np.float64))
    if x.size < MIN_INTERVAL:
        return None
    half = (float(student_t.ppf(0.5 + level / 2.0, x.size - 1)) * float(np.std(x, ddof=1))
            / math.sqrt(x.size))
    m = float(np.mean(x))
    return math.exp(m - half), math.exp(m + half)


def _num(v: Any) -> float | None:
    if isinstance(v, bool) or v is None:
        return None
    try:
        f = float(v)
    except (TypeError, ValueError):
        return None
    return f if math.isfinite(f) else None


def pair_ratios(runs: Sequence[dict], num: str, den: str, metric: str) -> dict[str, Any]:
    """Per (world, seed) pair: ``metric`` of strategy ``num`` / ``metric`` of strategy ``den``.

    A pair counts in the headline geometric mean only if both runs finished and both values
    are positive; every other pair is listed with ``included: false`` and the reason. A
    second figure, ``geomean_covered``, keeps only the counted pairs where both runs also
    reached coverage >= :data:`LOW_COVERAGE` (a run can "finish" with the map incomplete).
    Runs are grouped by ``world_label`` (falling back to ``world``) and ``seed``.
    """
    by_key: dict[tuple[str, int, str], dict] = {}
    for r in runs:
        by_key[(_label(r), int(r["seed"]), r["strategy"])] = r
    keys = sorted({(w, s) for (w, s, st) in by_key if st == num}
                  & {(w, s) for (w, s, st) in by_key if st == den})
    pairs = []
    for w, s in keys:
        a, b = by_key[(w, s, num)], by_key[(w, s, den)]
        va, vb = _num(a.get(metric)), _num(b.get(metric))
        ratio = va / vb if va is not None and vb is not None and vb > 0 else None
        why = []
        for name, r in ((num, a), (den, b)):
            if not r.get("finished"):
                why.append(f"{name} not finished ({r.get('stop_reason') or 'no reason'})")
        if not why and (va is None or vb is None):
            why.append(f"{metric} missing")
        elif not why and (va <= 0 or vb <= 0):
            why.append(f"{metric} is zero (ratio undefined in a geometric mean)")
        ca, cb = _num(a.get("coverage")), _num(b.get("coverage"))
        covered = ca is not None and cb is not None and min(ca, cb) >= LOW_COVERAGE
        pairs.append({"world": w, "seed": s, num: va, den: vb, "ratio": ratio,
                      "included": not why, "excluded_reason": "; ".join(why),
                      "both_covered": covered})
    included = [p["ratio"] for p in pairs if p["included"]]
    covered_r = [p["ratio"] for p in pairs if p["included"] and p["both_covered"]]
    by_world: dict[str, dict[str, Any]] = {}
    for w in sorted({p["world"] for p in pairs}):
        rs = [p["ratio"] for p in pairs if p["world"] == w and p["included"]]
        by_world[w] = {"geomean": geometric_mean(rs), "n_included": len(rs),
                       "n_pairs": sum(1 for p in pairs if p["world"] == w)}
    return {"numerator": num, "denominator": den, "metric": metric, "pairs": pairs,
            "geomean": geometric_mean(included), "n_included": len(included),
            "n_excluded": len(pairs) - len(included), "by_world": by_world,
            "geomean_covered": geometric_mean(covered_r), "n_covered": len(covered_r)}


def all_ratios(runs: Sequence[dict], strategies: Sequence[str]) -> dict[str, dict]:
    """``{"<metric>:<num>/<den>": pair_ratios(...)}`` for the pairs whose strategies ran."""
    out = {}
    for metric in RATIO_METRICS:
        for num, den in RATIO_PAIRS:
            if num in strategies and den in strategies:
                out[f"{metric}:{num}/{den}"] = pair_ratios(runs, num, den, metric)
    return out


def _stats(values: Sequence[float | None]) -> dict[str, Any]:
    v = [x for x in values if x is not None]
    if not v:
        return {"mean": None, "min": None, "max": None, "n": 0}
    return {"mean": float(np.mean(v)), "min": float(min(v)), "max": float(max(v)), "n": len(v)}


def aggregate(runs: Sequence[dict]) -> dict[str, dict[str, dict]]:
    """``{world: {strategy: {runs, finished, finished_rate, <field>: {mean, min, max, n}}}}``.

    Means are over every seed, finished or not (the finished rate says how many finished).
    """
    out: dict[str, dict[str, dict]] = {}
    for w, st in sorted({(_label(r), r["strategy"]) for r in runs}):
        rs = [r for r in runs if _label(r) == w and r["strategy"] == st]
        fin = sum(1 for r in rs if r.get("finished"))
        agg: dict[str, Any] = {"runs": len(rs), "finished": fin, "finished_rate": fin / len(rs)}
        for f in AGG_FIELDS:
            agg[f] = _stats([_num(r.get(f)) for r in rs])
        out.setdefault(w, {})[st] = agg
    return out


def coverage_distance_table(runs: Sequence[dict]) -> dict[str, dict[str, dict]]:
    """``{world: {strategy: {"d90": [per seed], "d90_mean", "d90_reached", ...}}}`` [m].

    Per seed: the distance of :func:`distance_to_coverage` (``None`` if never reached); the
    mean is over the seeds that reached it (``None`` if none did).
    """
    out: dict[str, dict[str, dict]] = {}
    for w, st in sorted({(_label(r), r["strategy"]) for r in runs}):
        rs = sorted((r for r in runs if _label(r) == w and r["strategy"] == st),
                    key=lambda r: int(r["seed"]))
        row: dict[str, Any] = {"seeds": [int(r["seed"]) for r in rs]}
        for thr in COVERAGE_THRESHOLDS:
            k = f"d{round(thr * 100)}"
            ds = [r.get(f"{k}_m") for r in rs]
            got = [d for d in ds if d is not None]
            row[k] = ds
            row[f"{k}_mean"] = float(np.mean(got)) if got else None
            row[f"{k}_reached"] = f"{len(got)}/{len(ds)}"
        out.setdefault(w, {})[st] = row
    return out


def derive(run: dict) -> dict:
    """Add the derived fields computed from the run's own data (distances to 90/95 %)."""
    tl = run.get("timeline") or []
    d = [row[1] for row in tl]
    c = [row[2] for row in tl]
    for thr in COVERAGE_THRESHOLDS:
        run[f"d{round(thr * 100)}_m"] = distance_to_coverage(d, c, thr) if tl else None
    return run


def analyse(runs: Sequence[dict], strategies: Sequence[str]) -> dict[str, Any]:
    from topoexplore.tools.bench.oracle import suite_ratios

    return {"aggregate": aggregate(runs), "ratios": all_ratios(runs, strategies),
            "coverage_distance": coverage_distance_table(runs), "oracle": suite_ratios(runs)}


def _label(r: dict) -> str:
    return str(r.get("world_label") or r.get("world"))


# --------------------------------------------------------------------------------------------
# output files


def read_timeline(path: Path) -> list[list[float]]:
    """``timeline.csv`` of a run -> ``[[sim_time_s, path_length_m, coverage], ...]``."""
    rows = []
    with path.open() as f:
        for row in csv.DictReader(f):
            rows.append([float(row["sim_time_s"]), float(row["path_length_m"]),
                         float(row["coverage"])])
    return rows


def write_csv(path: Path, runs: Sequence[dict]) -> None:
    cols: list[str] = ["world_label", "strategy", "seed", "finished"]
    for r in runs:
        for k, v in r.items():
            if k not in cols and not isinstance(v, (list, dict)):
                cols.append(k)
    with path.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=cols, extrasaction="ignore")
        w.writeheader()
        for r in runs:
            w.writerow({k: r.get(k) for k in cols})


def plot_curves(world: str, runs: Sequence[dict], strategies: Sequence[str], path: Path) -> bool:
    """Coverage over distance for one world, one line per strategy (mean over seeds).

    Returns False (and writes nothing) when no run of the world has a timeline.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    lines = []
    for st in strategies:
        rs = [r for r in runs if _label(r) == world and r["strategy"] == st]
        tls = [([row[1] for row in r["timeline"]], [row[2] for row in r["timeline"]])
               for r in rs if r.get("timeline")]
        grid, mean = mean_curve(tls)
        if grid.size:
            fin = sum(1 for r in rs if r.get("finished"))
            lines.append((st, grid, mean, len(tls), fin, len(rs)))
    if not lines:
        return False
    fig, ax = plt.subplots(figsize=(7.0, 4.5), dpi=110)
    try:
        for st, grid, mean, n_tl, fin, n in lines:
            seeds = "seed 0" if n_tl == 1 else f"mean of {n_tl} seeds"
            ax.plot(grid, mean, lw=1.8, label=f"{st} ({seeds}; {fin}/{n} finished)")
            ax.plot(grid[-1:], mean[-1:], "o", color=ax.lines[-1].get_color(), ms=4)
        for thr in COVERAGE_THRESHOLDS:
            ax.axhline(thr, color="0.6", lw=0.8, ls=":")
        ax.set_xlabel("distance travelled [m]")
        ax.set_ylabel("coverage (share of the mappable free space known)")
        ax.set_ylim(0.0, 1.02)
        ax.set_xlim(left=0.0)
        ax.set_title(f"{world}: coverage over distance")
        ax.grid(alpha=0.3)
        ax.legend(loc="lower right", fontsize=8)
        fig.tight_layout()
        path.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(path)
    finally:
        plt.close(fig)
    return True


def _n(k: int, word: str) -> str:
    if k == 1:
        return f"1 {word}"
    return f"{k} {word[:-1] + 'ies' if word.endswith('y') else word + 's'}"


def _fmt(v: Any, dec: int) -> str:
    if v is None:
        return "–"
    return f"{v:.{dec}f}"


def _fmt_stats(s: dict, dec: int) -> str:
    if s["n"] == 0:
        return "–"
    text = _fmt(s["mean"], dec)
    if s["n"] > 1 and s["max"] - s["min"] > 10.0 ** -dec / 2:
        text += f" ({_fmt(s['min'], dec)}–{_fmt(s['max'], dec)})"
    return text


def format_summary(doc: dict) -> str:
    """``summary.md`` of a results document: how it was made, the per world tables, the
    ratios, the distances to 90 / 95 % coverage, the curves and the runs."""
    worlds = [w for w in doc["config"]["world_labels"] if w in doc["aggregate"]]
    lines = (_summary_head(doc) + _summary_bus_check(doc) + _summary_worlds(doc, worlds)
             + _summary_ratios(doc) + _summary_distances(doc, worlds)
             + _summary_files(doc, worlds))
    return "\n".join(lines) + "\n"


def _summary_head(doc: dict) -> list[str]:
    """Title, what ran, how to run it again, the machine and the notes."""
    cfg = doc["config"]
    strategies = cfg["strategies"]
    mach = doc["machine"]
    L = ["# Exploration strategy comparison (`topoexplore bench explore`)", ""]
    L.append(f"Made {doc['created']}. {len(doc['runs'])} of {cfg['planned_runs']} planned runs "
             f"({_n(len(cfg['world_labels']), 'world')} x {_n(len(strategies), 'strategy')} x "
             f"{_n(cfg['seeds'], 'seed')}), lockstep, max sim time {cfg['max_sim_time']:g} s, "
             f"max wall time {cfg['max_wall_time']:g} s per run, {cfg['jobs']} at a time."
             + (f" The suite took {doc['suite_wall_s'] / 60:.1f} min of wall time and "
                f"{doc['suite_cpu_s']:.0f} s of CPU." if doc.get("suite_wall_s") else ""))
    if doc.get("interrupted"):
        L.append("")
        L.append("**Interrupted: the suite is incomplete.**")
    L += ["", "Reproduce (from the repository root):", "", "```", doc["command"], "```", ""]
    L.append(f"Machine: {mach['nproc']} CPUs ({mach['cpu_model']}), {mach['platform']}, "
             f"Python {mach['python']}, git {mach['git']}.")
    L.append("Packages: " + ", ".join(f"{k} {v}" for k, v in mach["packages"].items()) + ".")
    for note in doc.get("notes", []):
        L += ["", f"Note: {note}"]
    return L


def _summary_bus_check(doc: dict) -> list[str]:
    """How the runs were made (in process or on the bus) and, in process, the bus check."""
    if not doc["config"].get("inproc"):
        return ["", "Every run on the real processes (`topoexplore run --lockstep`, `--bus`)."]
    from topoexplore.tools.bench.explore_local import check_line

    L = ["", "Each exploration ran in one process (the cores of `bench inproc`, in the order "
         "the services run them in lockstep; no bus; `--bus` runs them all on the real "
         "processes).", ""]
    checks = doc.get("bus_check") or []
    if checks:
        agree = sum(1 for c in checks if c["agree"])
        L += [f"The same run on the real processes (`topoexplore run --lockstep`), "
              f"{agree} of {len(checks)} agree (the same outcome, paths within "
              f"{100 * BUS_PATH_TOLERANCE:g} %):", ""]
        L += [f"- {check_line(c)}" for c in checks]
    else:
        L.append("No run was checked on the bus.")
    return L


def _summary_worlds(doc: dict, worlds: list[str]) -> list[str]:
    """One table per world (a row per strategy), the runs that did not finish, and the
    finished runs with a low coverage."""
    runs = doc["runs"]
    L = ["", "## Per world and strategy", "",
         "Mean over seeds, finished or not (min–max in brackets when they differ). "
         "`coverage` = share of the free space the robot can map (reach with its footprint, "
         "see from there) that the map knows; `coverage of all free` = share of every free "
         "cell connected to the start (the older figure). "
         "`accepted from a distance` = end nodes reliable at the end without a visit."]
    cols = ["strategy", "finished"] + [t for t, _ in AGG_FIELDS.values()]
    for w in worlds:
        L += ["", f"### {w}", "", "| " + " | ".join(cols) + " |",
              "|" + "---|" * len(cols)]
        for st in doc["config"]["strategies"]:
            a = doc["aggregate"][w].get(st)
            if a is None:
                continue
            cells = [st, f"{a['finished']}/{a['runs']}"]
            cells += [_fmt_stats(a[f], dec) for f, (_, dec) in AGG_FIELDS.items()]
            L.append("| " + " | ".join(cells) + " |")
        stops = [f"{r['strategy']} seed {r['seed']}: {r.get('stop_reason') or '?'}"
                 for r in runs if _label(r) == w and not r.get("finished")]
        if stops:
            L += ["", "Not finished: " + "; ".join(stops) + "."]
    low = [f"{_label(r)}/{r['strategy']} seed {r['seed']} ({r['coverage']:.3f})" for r in runs
           if r.get("finished") and _num(r.get("coverage")) is not None
           and r["coverage"] < LOW_COVERAGE]
    if low:
        L += ["", f"Caution: finished with coverage below {LOW_COVERAGE:g} (they still count as "
              "finished in the ratios): " + "; ".join(low) + "."]
    return L


def _summary_ratios(doc: dict) -> list[str]:
    """The geometric means (overall and per world), the excluded pairs with their reasons,
    and every pair's ratio."""
    L = ["", "## Ratios (per run pair: same world, same seed)", ""]
    if not doc["ratios"]:
        L.append("No ratio: the suite does not hold both strategies of a pair.")
    for key, rr in doc["ratios"].items():
        metric, _ = key.split(":")
        name = f"{metric} {rr['numerator']} / {rr['denominator']}"
        gm = rr["geomean"]
        head = (f"**{_fmt(gm, 3)}**" if gm is not None else "**none** (no pair where both "
                "finished)")
        L.append(f"- {name}: geometric mean {head} over {rr['n_included']} pair(s) where "
                 f"both runs finished; {rr['n_excluded']} pair(s) excluded. Over the "
                 f"{rr.get('n_covered', 0)} of those where both runs also reached coverage "
                 f">= {LOW_COVERAGE:g}: {_fmt(rr.get('geomean_covered'), 3)}.")
        for w, bw in rr["by_world"].items():
            L.append(f"  - {w}: {_fmt(bw['geomean'], 3)} ({bw['n_included']}/{bw['n_pairs']} "
                     "pairs)")
    if doc.get("oracle"):
        from topoexplore.tools.bench.oracle import suite_line

        L.append(f"- {suite_line(doc['oracle'])}.")
    excluded: dict[tuple, list[str]] = {}
    for rr in doc["ratios"].values():
        for p in rr["pairs"]:
            if not p["included"]:
                excluded.setdefault((p["world"], p["seed"], rr["numerator"], rr["denominator"],
                                     p["excluded_reason"]), []).append(rr["metric"])
    if excluded:
        L += ["", "Excluded pairs:", ""]
        for (w, s, a, b, why), metrics in sorted(excluded.items()):
            L.append(f"- {w} seed {s}, {a} vs {b} ({', '.join(metrics)}): {why}")
    pair_rows = [(key, p) for key, rr in doc["ratios"].items() for p in rr["pairs"]]
    if pair_rows:
        L += ["", "| ratio | world | seed | value | counted |", "|---|---|---|---|---|"]
        for key, p in pair_rows:
            L.append(f"| {key.replace(':', ' ')} | {p['world']} | {p['seed']} | "
                     f"{_fmt(p['ratio'], 3)} | {'yes' if p['included'] else 'no'} |")
    return L


def _summary_distances(doc: dict, worlds: list[str]) -> list[str]:
    """The distance travelled to 90 % and 95 % coverage per world and strategy."""
    L = ["", "## Distance to 90 % and 95 % coverage [m]", "",
         "Distance travelled at the first timeline sample (every 0.25 m of travel) with at "
         "least that coverage; mean over the seeds that reached it (seeds reached / seeds); "
         "– = never.", "", "| world | strategy | 90 % | 95 % |", "|---|---|---|---|"]
    for w in worlds:
        for st in doc["config"]["strategies"]:
            row = doc["coverage_distance"].get(w, {}).get(st)
            if row is None:
                continue
            L.append(f"| {w} | {st} | {_fmt(row['d90_mean'], 1)} ({row['d90_reached']}) | "
                     f"{_fmt(row['d95_mean'], 1)} ({row['d95_reached']}) |")
    return L


def _summary_files(doc: dict, worlds: list[str]) -> list[str]:
    """Links to the coverage curves and to every run's directory."""
    L = ["", "## Curves and runs", ""]
    for w in worlds:
        if (doc.get("curves") or {}).get(w):
            L.append(f"- {w}: ![{w}]({doc['curves'][w]})")
    L.append("")
    L.append("Each run's directory (report.json, final.png, map.pgm/yaml, timeline.csv, "
             "logs.txt): " + ", ".join(f"[{Path(r['run_dir']).name}]({r['run_dir']}/final.png)"
                                       for r in doc["runs"] if r.get("run_dir")) + ".")
    return L


def write_all(out: Path, doc: dict) -> None:
    """results.json, results.csv, curves/*.png and summary.md from ``doc`` (analysis redone)."""
    cfg = doc["config"]
    doc.update(analyse(doc["runs"], cfg["strategies"]))
    doc["curves"] = {}
    for w in cfg["world_labels"]:
        rel = f"curves/{w}.png"
        if plot_curves(w, doc["runs"], cfg["strategies"], out / rel):
            doc["curves"][w] = rel
    out.mkdir(parents=True, exist_ok=True)
    _write_json(out / "results.json", doc)
    write_csv(out / "results.csv", doc["runs"])
    (out / "summary.md").write_text(format_summary(doc))


def _write_json(path: Path, doc: dict) -> None:
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(doc, indent=1) + "\n")
    tmp.replace(path)


# --------------------------------------------------------------------------------------------
# machine, arguments


def machine_info() -> dict[str, Any]:
    from importlib import metadata

    cpu = "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    pkgs = {}
    for p in PACKAGES:
        try:
            pkgs[p] = metadata.version(p)
        except metadata.PackageNotFoundError:
            pkgs[p] = "not installed"
    git = "unknown"
    try:
        root = checkout_root() or Path.cwd()
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root, text=True,
                              capture_output=True, timeout=10).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"],
                               cwd=root, text=True, capture_output=True, timeout=10).stdout
        if head:
            git = head + (" (with uncommitted changes)" if dirty.strip() else "")
    except (OSError, subprocess.SubprocessError):
        pass
    return {"nproc": os.cpu_count(), "cpu_model": cpu, "platform": platform.platform(),
            "python": platform.python_version(), "packages": pkgs, "git": git}


@dataclass
class Config:
    worlds: list[tuple[str, str, str]]  # (label, argument for `run`, text for the command)
    strategies: list[str]
    seeds: int
    out: Path
    max_sim_time: float
    max_wall_time: float
    jobs: int
    progress: bool = True
    notes: list[str] = field(default_factory=list)
    params: str | None = None  # --params FILE.toml for every run
    overrides: list[str] = field(default_factory=list)  # --set section.name=value, every run
    record: str = "failed"  # run --record-raw: keep the MCAP of failed runs | all | none
    #   (a kept one gets its Foxglove channels after the run)
    inproc: bool = True  # each exploration in process (explore_local); False: --bus
    bus_check: int = 0  # in process: this many of the runs again on the bus, compared

    @property
    def command(self) -> str:
        args = ["topoexplore", "bench", "explore",
                "--worlds", ",".join(t for _, _, t in self.worlds),
                "--strategies", ",".join(self.strategies), "--seeds", str(self.seeds),
                "--max-sim-time", f"{self.max_sim_time:g}",
                "--max-wall-time", f"{self.max_wall_time:g}", "--jobs", str(self.jobs)]
        if self.params:
            args += ["--params", self.params]
        for o in self.overrides:
            args += ["--set", o]
        if self.inproc:
            args += ["--bus-check", str(self.bus_check)]
        else:
            args += ["--bus"] + (["--record", self.record] if self.record != "failed" else [])
        args += ["--out", str(self.out if self.out.is_absolute() or Path.cwd().resolve() == _root()
                             else self.out.resolve())]
        return shlex.join(args)


class _Parser(argparse.ArgumentParser):
    def error(self, message: str):  # one line, no usage block
        raise BenchArgError(message)


def build_parser() -> argparse.ArgumentParser:
    ap = _Parser(prog="topoexplore bench explore", description=__doc__,
                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--worlds", help="comma-separated built-in names or world/map files "
                    "(default: every built-in world + ../shared/maps/lse_arena.yaml)")
    ap.add_argument("--strategies", help=f"comma-separated (default {','.join(STRATEGIES)})")
    ap.add_argument("--seeds", type=int, help=f"seeds 0..N-1 (default {DEFAULT_SEEDS})")
    ap.add_argument("--out", default=None, help="output directory (default runs/bench-explore)")
    ap.add_argument("--max-sim-time", type=float, default=DEFAULT_MAX_SIM_TIME,
                    help="per run, simulated seconds [s]")
    ap.add_argument("--max-wall-time", type=float, default=DEFAULT_MAX_WALL_TIME,
                    help="per run, wall seconds [s] (0: no limit)")
    ap.add_argument("--jobs", type=int, default=DEFAULT_JOBS,
                    help=f"runs at a time (default {DEFAULT_JOBS}: a run in process keeps one "
                         "core busy, a run on the bus about 1.4 of 2 cores)")
    ap.add_argument("--params", default=None, metavar="FILE.toml",
                    help="parameter file for every run (as `topoexplore run --params`)")
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.NAME=VALUE",
                    dest="overrides", help="parameter override for every run (repeatable)")
    ap.add_argument("--record", choices=("failed", "all", "none"), default=None,
                    help="with --bus: record each run's bus (run --record-raw) and keep the MCAP of the "
                    "runs that did not finish (default), of all, or record nothing; a kept "
                    "MCAP gets its Foxglove channels after the run")
    ap.add_argument("--bus", action="store_true",
                    help="every run through `topoexplore run --lockstep`: the real processes "
                         "on the bus (about 3 x the CPU of the default, each exploration in "
                         "one process)")
    ap.add_argument("--bus-check", type=int, default=None, metavar="N",
                    help=f"without --bus: make N of the runs again on the bus and compare "
                         f"(default {DEFAULT_BUS_CHECK}; 0: none)")
    ap.add_argument("--quick", action="store_true",
                    help=f"smoke suite: {','.join(QUICK_WORLDS)} x all strategies x 1 seed")
    ap.add_argument("--no-progress", action="store_true", help="no progress bar")
    ap.add_argument("--from-results", metavar="DIR",
                    help="re-make summary, CSV and curves from DIR/results.json (no runs)")
    return ap


def _root() -> Path:
    """The checkout's root (relative world paths in commands are written from there), or the
    current directory when installed from a wheel."""
    return checkout_root() or Path.cwd().resolve()


def resolve_world(text: str) -> tuple[str, str, str]:
    """World name or file -> ``(label, argument for run, text for the command)``.

    A relative file path is looked up from the current directory, then from the repository
    root. Raises :class:`BenchArgError` for unknown names and unreadable files.
    """
    from topoexplore.sim.world import WORLD_SUFFIXES, WorldError, load_world

    if "/" not in text and not text.endswith(WORLD_SUFFIXES):
        try:
            load_world(text)
        except WorldError as exc:
            raise BenchArgError(str(exc)) from None
        return text, text, text
    p = Path(text)
    cands = [p] if p.is_absolute() else [Path.cwd() / p, _root() / p]
    path = next((Path(os.path.abspath(c)) for c in cands if c.is_file()), None)  # symlinks kept
    if path is None:
        raise BenchArgError(f"world file not found: {text}")
    try:
        load_world(str(path))
    except WorldError as exc:
        raise BenchArgError(str(exc)) from None
    return path.stem, str(path), os.path.relpath(path, _root())


def default_worlds() -> tuple[list[str], list[str]]:
    """Every built-in world plus the real maps of :data:`EXTRA_MAPS` that exist; notes."""
    from topoexplore.sim.world import builtin_worlds

    worlds = list(builtin_worlds())
    notes = []
    for name in EXTRA_MAPS:
        maps = shared_maps_dir()
        p = (maps or Path("../shared/maps")) / name
        if p.is_file():
            worlds.append(str(p))
        else:
            notes.append(f"map {p} not found: skipped (needs ../shared beside the checkout)")
    return worlds, notes


RESERVED_KEYS = ("planner.strategy", "sim.world", "sim.seed", "runtime.lockstep")  # set per run


def parse_strategies(text: str) -> list[str]:
    """A comma-separated --strategies value: known strategies, each once; BenchArgError
    otherwise."""
    strategies = [s.strip() for s in text.split(",") if s.strip()]
    bad = [s for s in strategies if s not in STRATEGY_NAMES]
    if bad or not strategies:
        raise BenchArgError(f"unknown strategy {bad[0] if bad else '(none)'!r}: choose "
                            f"from {', '.join(STRATEGY_NAMES)}")
    if len(set(strategies)) != len(strategies):
        raise BenchArgError("strategy given twice")
    return strategies


def check_overrides(params_file: str | None, overrides: Sequence[str]) -> None:
    """--params / --set for every run of a suite: every run would fail the same way, so say
    it once before anything runs (BenchArgError); the keys the suite sets itself are refused."""
    if params_file is None and not overrides:
        return
    from topoexplore.common.params import ParamError, load_params

    try:
        load_params(params_file, list(overrides))
    except ParamError as exc:
        raise BenchArgError(str(exc)) from None
    for o in overrides:
        if o.split("=", 1)[0].strip() in RESERVED_KEYS:
            raise BenchArgError(f"--set {o}: the suite sets this itself (use --worlds, "
                                "--strategies, --seeds)")


def parse_config(argv: Sequence[str]) -> tuple[Config | None, argparse.Namespace]:
    """Parse and check everything (worlds load, strategies, numbers, output dir) or raise
    :class:`BenchArgError`. Returns ``(None, args)`` for ``--from-results``."""
    args = build_parser().parse_args(list(argv))
    if args.from_results is not None:
        if any(v is not None for v in (args.worlds, args.strategies, args.seeds)) or args.quick:
            raise BenchArgError("--from-results takes no --worlds/--strategies/--seeds/--quick")
        if not (Path(args.from_results) / "results.json").is_file():
            raise BenchArgError(f"no results.json in {args.from_results}")
        return None, args
    notes: list[str] = []
    if args.worlds is not None:
        texts = [w.strip() for w in args.worlds.split(",") if w.strip()]
        if not texts:
            raise BenchArgError("--worlds is empty")
    elif args.quick:
        texts = list(QUICK_WORLDS)
    else:
        texts, notes = default_worlds()
    worlds = [resolve_world(t) for t in texts]
    labels = [w[0] for w in worlds]
    dup = sorted({x for x in labels if labels.count(x) > 1})
    if dup:
        raise BenchArgError(f"world given twice: {', '.join(dup)}")
    strategies = list(STRATEGIES) if args.strategies is None else parse_strategies(
        args.strategies)
    seeds = args.seeds if args.seeds is not None else (1 if args.quick else DEFAULT_SEEDS)
    if seeds < 1:
        raise BenchArgError(f"--seeds must be >= 1 (got {seeds})")
    if not (math.isfinite(args.max_sim_time) and args.max_sim_time > 0):
        raise BenchArgError("--max-sim-time must be a positive number")
    if not (math.isfinite(args.max_wall_time) and args.max_wall_time >= 0):
        raise BenchArgError("--max-wall-time must be >= 0")
    if args.jobs < 1:
        raise BenchArgError(f"--jobs must be >= 1 (got {args.jobs})")
    out = Path(args.out or "runs/bench-explore")
    if out.exists() and not out.is_dir():
        raise BenchArgError(f"--out {out} is not a directory")
    params = None if args.params is None else str(Path(args.params).resolve())
    check_overrides(params, args.overrides)
    record, bus_check = args.record or "failed", 0
    if args.bus:
        if args.bus_check is not None:
            raise BenchArgError("--bus-check is for runs in process: with --bus every run is "
                                "on the bus")
    else:
        bus_check = DEFAULT_BUS_CHECK if args.bus_check is None else args.bus_check
        if bus_check < 0:
            raise BenchArgError(f"--bus-check must be >= 0 (got {bus_check})")
        if args.record is not None:
            raise BenchArgError("--record needs --bus: a run in process has no traffic to "
                                "record")
        record = "none"
    if record != "none":
        try:
            require("mcap", "foxglove", what="recording the runs")
        except ExtraMissing as exc:
            notes.append(f"{exc}; runs are not recorded")
            record = "none"
    return Config(worlds=worlds, strategies=strategies, seeds=seeds, out=out,
                  max_sim_time=float(args.max_sim_time), max_wall_time=float(args.max_wall_time),
                  jobs=args.jobs, progress=not args.no_progress, notes=notes, params=params,
                  overrides=list(args.overrides), record=record, inproc=not args.bus,
                  bus_check=bus_check), args


# --------------------------------------------------------------------------------------------
# running


_ACTIVE: set[subprocess.Popen] = set()
_ACTIVE_LOCK = threading.Lock()


def _stop_active() -> None:
    """Stop every run in flight, in parallel (each may take a while to stop its stack)."""
    with _ACTIVE_LOCK:
        active = list(_ACTIVE)
    threads = [threading.Thread(target=_stop, args=(p,)) for p in active]
    for t in threads:
        t.start()
    for t in threads:
        t.join()


def _stop(p: subprocess.Popen) -> None:
    """SIGTERM the run's process group (the runner stops its stack), SIGKILL if it lingers."""
    for sig, wait in ((signal.SIGTERM, 20), (signal.SIGKILL, 5)):
        if p.poll() is not None:
            return
        try:
            os.killpg(p.pid, sig)
        except ProcessLookupError:
            return
        try:
            p.wait(timeout=wait)
        except subprocess.TimeoutExpired:
            pass


def _with_foxglove(mcap: Path) -> str:
    """The Foxglove channels added to a kept recording (recorded raw: the recorder costs a
    run less that way); what happened, in a few words. On a failure the raw file stays."""
    from topoexplore.tools.record import RecordError, add_foxglove

    part = mcap.with_name(mcap.name + ".part")
    try:
        st = add_foxglove(mcap, part)
        os.replace(part, mcap)
    except (RecordError, ExtraMissing, OSError) as exc:
        part.unlink(missing_ok=True)
        return f"raw channels only (adding the Foxglove channels failed: {exc})"
    return f"Foxglove channels added after the run ({sum(st['foxglove'].values())} messages)"


def run_one(label: str, world_arg: str, strategy: str, seed: int, out: Path,
            max_sim_time: float, max_wall_time: float, params: str | None = None,
            overrides: Sequence[str] = (), record: str = "none") -> dict:
    """One ``topoexplore run --lockstep`` into ``out/runs/<label>-<strategy>-<seed>/``.

    Returns its report plus derived fields; a run that left no report gets a stub report
    (``finished: false``, metrics ``None``) whose ``stop_reason`` says what happened.
    """
    rel = f"runs/{label}-{strategy}-{seed}"
    run_dir = out / rel
    if run_dir.exists():
        shutil.rmtree(run_dir)  # never read a stale report
    run_dir.mkdir(parents=True)
    cmd = _run_command(label, world_arg, strategy, seed, run_dir, max_sim_time, max_wall_time,
                       params, overrides) + (["--record-raw"] if record != "none" else [])
    # safety net above the runner's own wall limit: startup, shutdown and the final picture
    timeout = max_wall_time + 180.0 if max_wall_time > 0 else None
    code, note = _wait_run(cmd, run_dir / "bench-stderr.txt", timeout)
    report = _read_report(run_dir, world_arg, strategy, seed, code, note)
    run = dict(report)
    run["world_label"] = label
    run["exit_code"] = code
    run["run_dir"] = rel
    mcap = run_dir / "run.mcap"
    if mcap.is_file() and record == "failed" and run.get("finished"):
        mcap.unlink()  # a finished run's recording is not kept (--record all keeps it)
    if mcap.is_file():
        run["recording_note"] = _with_foxglove(mcap)
    run["recording_file"] = f"{rel}/run.mcap" if mcap.is_file() else None
    tl_path = run_dir / "timeline.csv"
    try:
        run["timeline"] = read_timeline(tl_path) if tl_path.is_file() else []
    except (OSError, ValueError, KeyError):
        run["timeline"] = []
    return derive(run)


def _run_command(label: str, world_arg: str, strategy: str, seed: int, run_dir: Path,
                 max_sim_time: float, max_wall_time: float, params: str | None,
                 overrides: Sequence[str]) -> list[str]:
    """The ``topoexplore run`` command line of one run: quiet, lockstep, on its own router port
    and namespace (runs in parallel must not hear each other)."""
    cmd = [sys.executable, "-m", "topoexplore.tools.cli", "run", "--world", world_arg, "--strategy",
           strategy, "--seed", str(seed), "--lockstep", "--quiet", "--out", str(run_dir.resolve()),
           "--connect", f"tcp/127.0.0.1:{free_port()}",
           "--namespace", f"bench{os.getpid()}{re.sub('[^A-Za-z0-9]', '', label)[:12]}"
                          f"{STRATEGY_NAMES.index(strategy)}s{seed}",
           "--max-sim-time", f"{max_sim_time:g}", "--max-wall-time", f"{max_wall_time:g}"]
    if params:
        cmd += ["--params", params]
    for o in overrides:
        cmd += ["--set", o]
    return cmd


def _wait_run(cmd: list[str], stderr_path: Path, timeout: float | None) -> tuple[int | None, str]:
    """Run ``cmd`` in its own session (stderr to ``stderr_path``), registered in ``_ACTIVE`` so
    an interrupt can stop it. Returns (exit code, note: why the bench killed it, or "")."""
    with stderr_path.open("w") as err:
        p = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=err,
                             start_new_session=True)
        with _ACTIVE_LOCK:
            _ACTIVE.add(p)
        try:
            return p.wait(timeout=timeout), ""
        except subprocess.TimeoutExpired:
            _stop(p)
            return p.returncode, f"killed by the bench after {timeout:g} wall s"
        except BaseException:  # Ctrl-C: the run is in its own session, stop it ourselves
            _stop(p)
            raise
        finally:
            with _ACTIVE_LOCK:
                _ACTIVE.discard(p)


def _read_report(run_dir: Path, world_arg: str, strategy: str, seed: int, code: int | None,
                 note: str) -> dict:
    """The run's ``report.json``, or a stub (not finished, metrics None) saying what happened;
    the bench's ``note`` is appended to the stop reason."""
    try:
        report = json.loads((run_dir / "report.json").read_text())
    except (OSError, ValueError):
        last = [ln for ln in (run_dir / "bench-stderr.txt").read_text().splitlines() if ln]
        report = {"world": world_arg, "strategy": strategy, "seed": seed, "finished": False,
                  "stop_reason": note or f"no report.json (exit code {code}"
                                         f"{': ' + last[-1][:200] if last else ''})"}
        for f in AGG_FIELDS:
            report[f] = None
    if note and report.get("stop_reason"):
        report["stop_reason"] += f" ({note})"
    return report


def _world_area(world_arg: str) -> float:
    """Bounding area of a world [m^2] (scheduling order only; 0 if it does not load)."""
    from topoexplore.sim.world import WorldError, load_world

    try:
        w = load_world(world_arg)
    except WorldError:
        return 0.0
    return float(w.size[0] * w.size[1])


def _result_text(r: dict) -> str:
    if r.get("path_length_m") is None:
        return f"{r['strategy']}: no report"
    return (f"{_label(r)}/{r['strategy']}/{r['seed']} "
            f"{'finished' if r.get('finished') else 'NOT finished'} "
            f"{r['path_length_m']:.1f} m cov {r.get('coverage') or 0:.2f} "
            f"(free {r.get('coverage_free') or 0:.2f})")


def run_suite(cfg: Config, argv: Sequence[str]) -> int:
    """Every world x seed x strategy of ``cfg``, then the summary, CSV and curves.

    results.json is rewritten after each run, so an interrupt (Ctrl-C or SIGTERM) keeps what
    was done. Returns 0, or 130 when interrupted.
    """
    from tqdm import tqdm

    out = cfg.out
    out.mkdir(parents=True, exist_ok=True)
    plan = [(w, seed, st) for w in cfg.worlds for seed in range(cfg.seeds)
            for st in cfg.strategies]
    doc = new_results(cfg, argv, len(plan))
    for note in cfg.notes:
        print(f"topoexplore bench explore: {note}", file=sys.stderr)
    bar = tqdm(total=len(plan), unit="run", desc="bench explore", file=sys.stderr,
               dynamic_ncols=True, disable=not cfg.progress)
    suite = _SuiteRuns(cfg, doc, bar, plan)
    old_term = _sigterm_as_interrupt()
    t0, cpu0 = time.monotonic(), _cpu_s()
    try:
        _run_plan(cfg, plan, suite)
        if cfg.inproc and cfg.bus_check:
            _bus_check(cfg, doc, bar)
    except KeyboardInterrupt:
        doc["interrupted"] = True
        _stop_active()
    finally:
        if old_term is not None:
            signal.signal(signal.SIGTERM, old_term)
        bar.close()
    # [s] the suite's wall time and the CPU of this process and its finished children (the
    # workers, the bus runs' processes), issue 17's measure of it
    doc["suite_wall_s"] = round(time.monotonic() - t0, 1)
    doc["suite_cpu_s"] = round(_cpu_s() - cpu0, 1)
    write_all(out, doc)
    _print_totals(doc, len(plan), out)
    return 130 if doc["interrupted"] else 0


def _cpu_s() -> float:
    """[s] user + system CPU of this process and of its children that were waited for."""
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


def new_results(cfg: Config, argv: Sequence[str], planned: int) -> dict[str, Any]:
    """The results document before any run: how, where and on what the suite runs."""
    return {
        "version": 1,
        "created": _dt.datetime.now().astimezone().isoformat(timespec="seconds"),
        "command": cfg.command,
        "argv": list(argv),
        "machine": machine_info(),
        "config": {"worlds": [w[2] for w in cfg.worlds],
                   "world_labels": [w[0] for w in cfg.worlds], "strategies": cfg.strategies,
                   "seeds": cfg.seeds, "max_sim_time": cfg.max_sim_time,
                   "max_wall_time": cfg.max_wall_time, "jobs": cfg.jobs,
                   "params": cfg.params, "overrides": cfg.overrides,
                   "planned_runs": planned, "inproc": cfg.inproc,
                   "bus_check": cfg.bus_check},
        "notes": list(cfg.notes),
        "interrupted": False,
        "runs": [],
    }


class _SuiteRuns:
    """Runs the items of a plan and records each result (from any worker thread): the runs in
    plan order, results.json rewritten, the progress bar showing the last result."""

    def __init__(self, cfg: Config, doc: dict, bar: Any, plan: list):
        self.cfg, self.doc, self.bar = cfg, doc, bar
        self.order = {(w[0], seed, st): i for i, (w, seed, st) in enumerate(plan)}
        self.lock = threading.Lock()
        self.last = ""

    def one(self, item) -> dict:
        (label, arg, _), seed, st = item
        cfg = self.cfg
        if cfg.jobs == 1:
            self.bar.set_postfix_str(f"now {label}/{st}/{seed} | last {self.last}")
        if cfg.inproc:
            from topoexplore.tools.bench.explore_local import run_local

            return run_local(label, arg, st, seed, cfg.out, cfg.max_sim_time,
                             cfg.max_wall_time, cfg.params, cfg.overrides)
        return run_one(label, arg, st, seed, cfg.out, cfg.max_sim_time, cfg.max_wall_time,
                       cfg.params, cfg.overrides, cfg.record)

    def done(self, run: dict) -> None:
        with self.lock:
            runs = self.doc["runs"]
            runs.append(run)
            runs.sort(key=lambda r: self.order.get((_label(r), r["seed"], r["strategy"]), 0))
            _write_json(self.cfg.out / "results.json", self.doc)  # survives an interrupt
            self.last = _result_text(run)
            self.bar.set_postfix_str(f"last {self.last}", refresh=False)
            self.bar.update(1)


def _sigterm_as_interrupt() -> Any:
    """Make SIGTERM stop the suite like Ctrl-C (no run is left behind); returns the previous
    handler, or None when not on the main thread (nothing installed)."""

    def on_term(signum, frame):
        raise KeyboardInterrupt

    if threading.current_thread() is not threading.main_thread():
        return None
    return signal.signal(signal.SIGTERM, on_term)


def _run_plan(cfg: Config, plan: list, suite: _SuiteRuns) -> None:
    """One run after the other, or ``cfg.jobs`` at a time, biggest worlds first (so that no
    long run starts when the others are done). On an interrupt the runs in flight are stopped
    before the pool's exit would wait for them."""
    if cfg.jobs == 1:
        for item in plan:
            suite.done(suite.one(item))
        return
    area = {w[0]: _world_area(w[1]) for w in cfg.worlds}
    plan = sorted(plan, key=lambda it: -area[it[0][0]])
    if cfg.inproc:
        from topoexplore.tools.bench.explore_local import run_plan

        run_plan(plan, cfg, suite.done)
        return
    with ThreadPoolExecutor(max_workers=cfg.jobs) as pool:
        futs = [pool.submit(suite.one, item) for item in plan]
        try:
            for f in as_completed(futs):
                suite.done(f.result())
        except BaseException:
            for f in futs:
                f.cancel()
            _stop_active()
            raise


def _bus_check(cfg: Config, doc: dict, bar: Any) -> None:
    """``cfg.bus_check`` of the in-process runs again through ``topoexplore run --lockstep``
    (into ``out/bus/``), compared with them (``doc["bus_check"]``, results.json rewritten)."""
    from topoexplore.tools.bench.explore_local import check_line, compare, pick_bus_runs

    args = {w[0]: w[1] for w in cfg.worlds}
    picked = pick_bus_runs(doc["runs"], cfg.bus_check)
    doc["bus_check"] = []
    bar.reset(total=len(picked))
    bar.set_description("bench explore: bus check")
    for local in picked:
        label = local["world_label"]
        bus = run_one(label, args[label], local["strategy"], local["seed"], cfg.out / "bus",
                      cfg.max_sim_time, cfg.max_wall_time, cfg.params, cfg.overrides, "none")
        bus["run_dir"] = f"bus/{bus['run_dir']}"
        doc["bus_check"].append(compare(local, bus))
        _write_json(cfg.out / "results.json", doc)
        bar.set_postfix_str(check_line(doc["bus_check"][-1]), refresh=False)
        bar.update(1)


def _print_totals(doc: dict, planned: int, out: Path) -> None:
    """The suite's last words on stderr: runs, finished, files, path-length ratios."""
    n_fin = sum(1 for r in doc["runs"] if r.get("finished"))
    print(f"bench explore: {len(doc['runs'])}/{planned} runs, {n_fin} finished -> "
          f"{out}/summary.md, results.json, results.csv, curves/", file=sys.stderr)
    if doc.get("suite_wall_s") is not None:
        print(f"  suite: {doc['suite_wall_s'] / 60:.1f} min wall, {doc['suite_cpu_s']:.0f} s "
              "CPU", file=sys.stderr)
    for key, rr in doc["ratios"].items():
        if key.startswith("path_length_m"):
            print(f"  path {rr['numerator']}/{rr['denominator']}: geometric mean "
                  f"{_fmt(rr['geomean'], 3)} over {rr['n_included']} finished pair(s), "
                  f"{rr['n_excluded']} excluded", file=sys.stderr)
    if doc.get("oracle"):
        from topoexplore.tools.bench.oracle import suite_line

        print(f"  {suite_line(doc['oracle'])}", file=sys.stderr)
    if doc.get("bus_check"):
        from topoexplore.tools.bench.explore_local import check_line

        agree = sum(1 for c in doc["bus_check"] if c["agree"])
        print(f"  in process, checked on the bus: {agree} of {len(doc['bus_check'])} agree",
              file=sys.stderr)
        for c in doc["bus_check"]:
            print(f"    {check_line(c)}", file=sys.stderr)


def from_results(src: Path, out: Path | None) -> int:
    try:
        doc = json.loads((src / "results.json").read_text())
        runs = doc["runs"]
        doc["config"]["strategies"]
        doc["config"]["world_labels"]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        print(f"topoexplore bench explore: cannot read {src / 'results.json'}: {exc}",
              file=sys.stderr)
        return 2
    out = out or src
    _note_old_coverage(doc)
    for r in runs:  # older files, or runs copied without timeline: read the run directory
        if not r.get("timeline") and r.get("run_dir") and (src / r["run_dir"] / "timeline.csv"
                                                            ).is_file():
            r["timeline"] = read_timeline(src / r["run_dir"] / "timeline.csv")
        derive(r)
        if out.resolve() != src.resolve() and r.get("run_dir"):
            r["run_dir"] = os.path.relpath(src / r["run_dir"], out)
    write_all(out, doc)
    print(f"bench explore: re-made {out}/summary.md, results.json, results.csv, curves/ from "
          f"{src / 'results.json'} ({len(runs)} runs)", file=sys.stderr)
    return 0


OLD_COVERAGE_NOTE = ("runs without `coverage of all free` come from before it existed: their "
                     "`coverage` is the share of every free cell connected to the start (the "
                     "older figure), not of the free space the robot can map")


def _note_old_coverage(doc: dict) -> None:
    """Results from before ``coverage_free``: say that their ``coverage`` is the older figure."""
    old = any(r.get("coverage") is not None and "coverage_free" not in r for r in doc["runs"])
    notes = doc.setdefault("notes", [])
    if old and OLD_COVERAGE_NOTE not in notes:
        notes.append(OLD_COVERAGE_NOTE)


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        require("pymunk", "tqdm", "matplotlib", what="topoexplore bench explore")
        cfg, args = parse_config(argv)
    except (BenchArgError, ExtraMissing) as exc:
        print(f"topoexplore bench explore: {exc}", file=sys.stderr)
        return 2
    except SystemExit as exc:  # --help
        return int(exc.code or 0)
    if cfg is None:
        return from_results(Path(args.from_results), Path(args.out) if args.out else None)
    try:
        cfg.out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        print(f"topoexplore bench explore: cannot create {cfg.out}: {exc}", file=sys.stderr)
        return 2
    return run_suite(cfg, ["bench", "explore", *argv])


if __name__ == "__main__":
    raise SystemExit(main())
