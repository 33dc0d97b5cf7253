"""``topoexplore bench oracle``: each strategy's path over a short tour that knows the map.

    topoexplore bench oracle [--worlds a,b] [--corpus DIR] [--from-results DIR|FILE ...]
                             [--jobs 2] [--json OUT]

For each world, :func:`sim.oracle.oracle_tour` plans on the true map a short tour of viewpoints
that together see 99 % of the cells the coverage figure counts. With ``--from-results`` (the
``runs.jsonl`` of ``bench robust`` or its directory, or the ``--json`` file of ``bench
inproc`` / ``bench explore``) every finished run's path is divided by its world's tour, and the
geometric mean per strategy (and per style) is printed beside the tour lengths. Without
worlds, the worlds of the results are taken, or else the built-in suite.

A tour is planned once per world geometry and oracle code and then read from
``$TOPOEXPLORE_CACHE_DIR/oracle`` (else ``~/.cache/topoexplore/oracle``; :func:`world_key`).

World names are looked up as ``DIR/NAME.toml`` in ``--corpus``, then as the world file the
results' run was given (bench inproc / explore run with a file), then as a shared real map
(``NAME.yaml``), then as a built-in world or a file.
"""

from __future__ import annotations

import argparse
import functools
import hashlib
import json
import math
import os
import sys
import time
from collections import defaultdict
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

from topoexplore.tools.bench.explore import BenchArgError, default_worlds, resolve_world
from topoexplore.tools.paths import shared_maps_dir


def world_file(name: str, corpus: Path | None, recorded: str | None = None) -> str:
    """The world argument for a result's world name (module docstring); ``recorded``: the
    world file the run itself was given (bench inproc / explore with a file), used when the
    corpus does not hold the name."""
    if corpus is not None and (corpus / f"{name}.toml").is_file():
        return str(corpus / f"{name}.toml")
    if recorded is not None:
        return recorded
    maps = shared_maps_dir()
    if maps is not None and (maps / f"{name}.yaml").is_file():
        return str(maps / f"{name}.yaml")
    return resolve_world(name)[1]


CACHE_ENV = "TOPOEXPLORE_CACHE_DIR"  # where tours are kept; default ~/.cache/topoexplore
_SOURCES = ("oracle", "rays", "world")  # the modules of topoexplore.sim a tour depends on


def cache_dir() -> Path:
    """The directory of kept oracle tours: ``$TOPOEXPLORE_CACHE_DIR/oracle``, else
    ``$XDG_CACHE_HOME/topoexplore/oracle`` (``~/.cache`` without it)."""
    base = os.environ.get(CACHE_ENV)
    if base:
        return Path(base) / "oracle"
    xdg = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(xdg) / "topoexplore" / "oracle"  # no home at all: "~/.cache", unwritable


@functools.lru_cache(maxsize=1)
def _code_digest() -> str:
    """The oracle's code, so that a changed rule is never answered from the cache."""
    import importlib

    h = hashlib.sha256()
    for name in _SOURCES:
        h.update(Path(importlib.import_module(f"topoexplore.sim.{name}").__file__).read_bytes())
    return h.hexdigest()


def world_key(world) -> str:
    """The cache key of a loaded world: its geometry (walls, shapes, start, extent, as
    loaded, so a map_server image is in it) and the oracle's code."""
    h = hashlib.sha256(_code_digest().encode())
    h.update(repr((world.size, world.robot_pose, world.segments, world.circles, world.boxes,
                   world.wall_thickness, world.origin)).encode())
    return h.hexdigest()[:32]


@functools.lru_cache(maxsize=64)
def _tour(path: str) -> dict[str, Any]:
    """The figures of the oracle tour of the world file path: kept on disk by world and
    code (:func:`world_key`; a tour of a 60 x 60 m floor takes about 40 s, and every benchmark of
    it asks again), and per process."""
    from topoexplore.sim.oracle import oracle_tour
    from topoexplore.sim.world import load_world

    world = load_world(path)
    f = cache_dir() / f"{world_key(world)}.json"
    try:
        kept = json.loads(f.read_text())
        if isinstance(kept, dict) and isinstance(kept.get("oracle_m"), (int, float)):
            return kept
    except (OSError, ValueError):
        pass  # none kept, or a file that is not one: planned (and written) again
    t0 = time.monotonic()
    o = oracle_tour(world)
    fig = {"oracle_m": round(o.length_m, 2), "nearest_neighbour_m": round(o.greedy_length_m, 2),
           "viewpoints": int(len(o.points) - 1), "seen": round(o.seen_fraction, 4),
           "candidates": o.candidates, "spacing_m": o.spacing_m,
           "wall_s": round(time.monotonic() - t0, 1)}
    try:  # written whole, then renamed: two workers of one benchmark may both write it
        f.parent.mkdir(parents=True, exist_ok=True)
        tmp = f.with_suffix(f".{os.getpid()}.tmp")
        tmp.write_text(json.dumps(fig))
        tmp.replace(f)
    except OSError:
        pass  # an unwritable cache costs time, never the figure
    return fig


def tour_length(path: str) -> float | None:
    """[m] the oracle tour of the world file path; None if the world cannot be loaded or has
    no reachable position."""
    from topoexplore.sim.world import WorldError

    try:
        return _tour(path)["oracle_m"]
    except (WorldError, ValueError):
        return None


def one(name: str, path: str) -> dict[str, Any]:
    """The oracle figures of one world (``wall_s``: the time the tour took when it was
    planned, kept with it)."""
    return {"world": name, "path": path, **_tour(path)}


def load_runs(sources: Sequence[str]) -> list[dict]:
    """Runs from runs.jsonl files (or their directories) and JSON reports with a "runs"
    list; later sources replace earlier runs of the same (world, strategy, seed)."""
    runs: dict[tuple, dict] = {}
    for src in sources:
        p = Path(src)
        if p.is_dir():
            p = p / "runs.jsonl"
        try:
            text = p.read_text()
        except OSError as exc:
            raise BenchArgError(f"--from-results: cannot read {p}: {exc.strerror}") from None
        try:
            if p.suffix == ".jsonl":
                rows = [json.loads(line) for line in text.splitlines() if line.strip()]
            else:
                rows = json.loads(text)["runs"]
        except (ValueError, KeyError, TypeError):
            raise BenchArgError(f"--from-results: {p}: not a runs.jsonl or a report with "
                                "a 'runs' list") from None
        for r in rows:
            if not isinstance(r, dict) or "world" not in r or "strategy" not in r:
                raise BenchArgError(f"--from-results: {p}: a run without world / strategy")
            name = Path(str(r.get("world_label") or r["world"])).stem
            runs[(name, r["strategy"], r.get("seed", 0))] = {
                **r, "world": name, "world_file": _recorded_file(str(r["world"]), p.parent)}
    return list(runs.values())


def _recorded_file(world: str, base: Path) -> str | None:
    """The world file a run was given (absolute, or relative to where the results are or to
    the working directory), if it names one that exists; else None (a name)."""
    from topoexplore.sim.world import WORLD_SUFFIXES

    if not world.endswith(WORLD_SUFFIXES):
        return None
    for p in (Path(world), base / world):
        if p.is_file():
            return str(p)
    return None


def _finished(r: dict) -> bool:
    if "outcome" in r:
        return r["outcome"] == "finished"
    return bool(r.get("finished")) and float(r.get("coverage", 0.0)) >= 0.95


def ratios(runs: Sequence[dict], tour_of: Callable[[dict], float | None]) -> dict[str, Any]:
    """Per strategy: geometric mean of path / tour_of(run) [m] over the finished runs (and per
    style: the run's style, or the part of the world name before the first '-'), and the
    runs left out (not finished, no tour, no path)."""
    logs: dict[str, list[float]] = defaultdict(list)
    styles: dict[tuple[str, str], list[float]] = defaultdict(list)
    left_out: list[str] = []
    for r in runs:
        o, path = tour_of(r), float(r.get("path_length_m") or 0.0)
        if not o or o <= 0 or path <= 0 or not _finished(r):
            left_out.append(f"{r['world']}/{r['strategy']}")
            continue
        x = math.log(path / o)
        logs[r["strategy"]].append(x)
        styles[(r["strategy"], r.get("style") or str(r["world"]).split("-")[0])].append(x)
    out = {s: {"geomean": math.exp(sum(v) / len(v)), "n": len(v)} for s, v in logs.items()}
    for (s, st), v in styles.items():
        out[s].setdefault("by_style", {})[st] = math.exp(sum(v) / len(v))
    return {"strategies": out, "left_out": left_out}


def suite_ratios(runs: Sequence[dict]) -> dict[str, Any]:
    """:func:`ratios` for bench inproc / explore, whose runs' ``world`` is the world argument
    they ran with; {"tours": {world: tour [m] or None}} beside."""
    tours: dict[str, float | None] = {}

    def tour_of(r: dict) -> float | None:
        w = str(r["world"])
        if w not in tours:
            try:
                tours[w] = tour_length(resolve_world(w)[1])
            except BenchArgError:
                tours[w] = None
        return tours[w]

    return {**ratios([r for r in runs if _finished(r)], tour_of), "tours": tours}


def suite_line(o: dict[str, Any]) -> str:
    """One line for a report: path / oracle tour per strategy."""
    parts = [f"{s} {v['geomean']:.2f} ({v['n']} runs)" for s, v in o["strategies"].items()]
    return ("path / oracle tour (a short tour planned on the true map, `topoexplore bench "
            "oracle`), geometric mean over the runs finished with coverage >= 0.95: "
            + (", ".join(parts) if parts else "none"))


def main(argv: list[str] | None = None) -> int:
    from topoexplore.sim.world import WORLD_SUFFIXES

    ap = argparse.ArgumentParser(prog="topoexplore bench oracle", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--worlds", default=None, help="world names or files (comma separated)")
    ap.add_argument("--corpus", type=Path, default=None, help="bench robust corpus directory")
    ap.add_argument("--from-results", nargs="+", default=[], metavar="SRC",
                    help="runs.jsonl (or its directory) or a bench inproc / explore JSON")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--json", type=Path, default=None, help="write the figures here")
    a = ap.parse_args(argv)
    try:
        if a.jobs < 1:
            raise BenchArgError("--jobs must be >= 1")
        runs = load_runs(a.from_results)
        if a.worlds:
            names = [w.strip() for w in a.worlds.split(",") if w.strip()]
        elif runs:
            names = sorted({r["world"] for r in runs})
        else:
            names = default_worlds()[0]
        recorded = {r["world"]: r["world_file"] for r in runs if r.get("world_file")}
        todo = [(Path(n).stem if n.endswith(WORLD_SUFFIXES) else n,
                 world_file(n, a.corpus, recorded.get(n))) for n in names]
    except BenchArgError as exc:
        print(f"topoexplore bench oracle: {exc}", file=sys.stderr)
        return 2
    t0 = time.monotonic()
    with ProcessPoolExecutor(max_workers=a.jobs) as pool:
        got = list(pool.map(one, [n for n, _ in todo], [p for _, p in todo]))
    oracles = {g["world"]: g for g in got}
    by_world: dict[str, dict[str, list[float]]] = defaultdict(lambda: defaultdict(list))
    for r in runs:
        if _finished(r) and float(r.get("path_length_m", 0.0)) > 0:
            by_world[r["world"]][r["strategy"]].append(math.log(float(r["path_length_m"])))
    strategies = sorted({r["strategy"] for r in runs})
    print(f"{'world':32s} {'oracle [m]':>10s} {'views':>5s} {'seen':>6s}"
          + "".join(f" {s[:14]:>14s}" for s in strategies))
    for g in got:
        row = by_world.get(g["world"], {})
        cells = "".join(  # geometric mean over the world's seeds
            f" {math.exp(sum(row[s]) / len(row[s])) / g['oracle_m']:14.2f}"
            if row.get(s) and g["oracle_m"] > 0 else f" {'-':>14s}" for s in strategies)
        print(f"{g['world']:32s} {g['oracle_m']:10.1f} {g['viewpoints']:5d} {g['seen']:6.3f}"
              + cells)
    an = ratios(runs, lambda r: oracles[r["world"]]["oracle_m"] if r["world"] in oracles
                else None)
    for s, v in sorted(an["strategies"].items()):
        styles = ", ".join(f"{k} {x:.2f}" for k, x in sorted(v.get("by_style", {}).items()))
        print(f"{s}: path / oracle geometric mean {v['geomean']:.3f} over {v['n']} finished "
              f"run(s)" + (f" ({styles})" if styles else ""))
    print(f"{len(got)} world(s) in {time.monotonic() - t0:.0f} s")
    if a.json is not None:
        a.json.write_text(json.dumps({"oracles": got, "analysis": an,
                                      "command": "topoexplore bench oracle " + " ".join(
                                          argv if argv is not None else sys.argv[1:])},
                                     indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
