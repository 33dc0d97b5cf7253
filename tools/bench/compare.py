"""``topoexplore bench robust --compare BASE NEW``: did a change make the runs shorter, or was
it chance?

One exploration is chaotic: a rule that moves one early choice moves every trip after it, and
on the generated corpus a single world's path moves by a third either way from a change that
does nothing on average (docs/benchmarks.md, "How much one run says"). So a change is judged
over many worlds, each world one unit:

- per world and strategy, each side's path is the geometric mean over its finished runs (its
  simulator seeds), and the world's ratio is new / base (both sides finished, paths > 0);
- over the worlds: the geometric mean of those ratios with its 95 % interval (Student's t on
  the log ratios), how many worlds got shorter and longer, and the two-sided sign test's p
  (binomial, ties left out): the chance of a split at least this uneven if the change did
  nothing;
- outcome changes (a run that finished on one side and not on the other) are listed apart,
  since a path ratio cannot show them.

Pure functions over the runs of two ``bench robust`` outputs (``results.json``, or
``runs.jsonl`` of a run still going or cut short); :func:`main_compare` prints the report.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from scipy.stats import binomtest

from topoexplore.tools.bench.explore import BenchArgError, geometric_interval


def load_runs(d: Path) -> list[dict]:
    """The runs of one ``bench robust --out`` directory: results.json, else runs.jsonl (one run
    per line, as they ended). A one-line error when neither is readable."""
    f = d / "results.json"
    try:
        if f.exists():
            runs = json.loads(f.read_text())["runs"]
        else:
            f = d / "runs.jsonl"
            runs = [json.loads(line) for line in f.read_text().splitlines() if line.strip()]
        for r in runs:
            r["world"], r["strategy"], r["outcome"]  # noqa: B018 - the keys used
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise BenchArgError(f"--compare: cannot read the runs in {d} ({f.name}: "
                            f"{type(exc).__name__}: {exc})") from None
    return runs


def side_paths(runs: Sequence[dict]) -> dict[tuple[str, str], dict[str, Any]]:
    """{(world, strategy): {"path": geometric mean path [m] of the finished runs or None,
    "runs": n, "finished": n, "coverage": least coverage or None}}."""
    acc: dict[tuple[str, str], dict[str, Any]] = {}
    for r in runs:
        a = acc.setdefault((r["world"], r["strategy"]),
                           {"logs": [], "runs": 0, "finished": 0, "cov": []})
        a["runs"] += 1
        if r.get("coverage") is not None:
            a["cov"].append(float(r["coverage"]))
        p = r.get("path_length_m")
        if r["outcome"] == "finished":
            a["finished"] += 1
            if p is not None and p > 0:
                a["logs"].append(math.log(float(p)))
    return {k: {"path": math.exp(sum(a["logs"]) / len(a["logs"])) if a["logs"] else None,
                "runs": a["runs"], "finished": a["finished"],
                "coverage": min(a["cov"]) if a["cov"] else None}
            for k, a in acc.items()}


def compare(base: Sequence[dict], new: Sequence[dict], strategy: str) -> dict[str, Any]:
    """One strategy's paired comparison (module doc): per world base / new path and ratio;
    ``geomean`` of the ratios with ``low``..``high`` (None below MIN_INTERVAL worlds),
    ``shorter`` / ``longer`` / ``same`` counts, the sign test's ``p``, the ``total`` paths
    over the paired worlds, and ``outcome_changes``."""
    b, n = side_paths(base), side_paths(new)
    worlds = sorted(w for (w, s) in b if s == strategy and (w, s) in n)
    rows, logs, changes = [], [], []
    for w in worlds:
        bs, ns = b[(w, strategy)], n[(w, strategy)]
        ratio = (ns["path"] / bs["path"] if bs["path"] and ns["path"] else None)
        rows.append({"world": w, "base": bs["path"], "new": ns["path"], "ratio": ratio,
                     "base_cov": bs["coverage"], "new_cov": ns["coverage"]})
        if ratio is not None:
            logs.append(math.log(ratio))
        if (bs["finished"] == bs["runs"]) != (ns["finished"] == ns["runs"]):
            changes.append({"world": w, "base": f"{bs['finished']}/{bs['runs']} finished",
                            "new": f"{ns['finished']}/{ns['runs']} finished"})
    shorter = sum(1 for v in logs if v < 0)
    longer = sum(1 for v in logs if v > 0)
    out: dict[str, Any] = {
        "strategy": strategy, "worlds": rows, "n": len(logs), "shorter": shorter,
        "longer": longer, "same": len(logs) - shorter - longer, "outcome_changes": changes,
        "geomean": math.exp(float(np.mean(logs))) if logs else None, "low": None,
        "high": None, "p": None,
        "total": (sum(r["base"] for r in rows if r["ratio"] is not None),
                  sum(r["new"] for r in rows if r["ratio"] is not None))}
    if shorter + longer:
        out["p"] = float(binomtest(shorter, shorter + longer, 0.5).pvalue)
    ci = geometric_interval(math.exp(v) for v in logs)
    if ci is not None:
        out["low"], out["high"] = ci
    return out


def _f(v: float | None, fmt: str = ".3f") -> str:
    return "–" if v is None else format(v, fmt)


def report(c: dict[str, Any], base_name: str, new_name: str) -> str:
    """Markdown for one strategy's comparison."""
    L = [f"### {c['strategy']}: {new_name} against {base_name}", "",
         "| world | base path [m] | new path [m] | new / base | coverage base / new (min) |",
         "|---|---|---|---|---|"]
    for r in c["worlds"]:
        L.append(f"| {r['world']} | {_f(r['base'], '.1f')} | {_f(r['new'], '.1f')} | "
                 f"{_f(r['ratio'])} | {_f(r['base_cov'])} / {_f(r['new_cov'])} |")
    L.append("")
    if not c["n"]:
        L.append("No world where both sides finished.")
    else:
        ci = (f" (95 % interval {_f(c['low'])}–{_f(c['high'])})" if c["low"] is not None
              else "")
        L.append(f"- new / base, geometric mean over {c['n']} worlds: **{_f(c['geomean'])}**"
                 f"{ci}; total {c['total'][0]:.1f} → {c['total'][1]:.1f} m")
        L.append(f"- shorter on {c['shorter']}, longer on {c['longer']}, the same on "
                 f"{c['same']}; sign test p = {_f(c['p'], '.2f')} (the chance of a split at "
                 "least this uneven from a change that does nothing)")
    for ch in c["outcome_changes"]:
        L.append(f"- outcome changed on {ch['world']}: {ch['base']} → {ch['new']}")
    return "\n".join(L) + "\n"


def main_compare(dirs: Sequence[Path], strategies: Sequence[str] | None) -> int:
    """Print the comparison of every strategy run on both sides (or of those named)."""
    base_dir, new_dir = dirs
    base, new = load_runs(base_dir), load_runs(new_dir)
    both = sorted({r["strategy"] for r in base} & {r["strategy"] for r in new})
    chosen = [s for s in both if strategies is None or s in strategies]
    if not chosen:
        raise BenchArgError(f"--compare: no strategy with runs in both {base_dir} and "
                            f"{new_dir}" + (f" among {', '.join(strategies)}"
                                            if strategies else ""))
    print("\n".join(report(compare(base, new, s), str(base_dir), str(new_dir))
                    for s in chosen))
    return 0
