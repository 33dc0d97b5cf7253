"""Where a localized run lost its pose: ``topoexplore bench posetrace``.

    topoexplore bench posetrace TRACE.npz [--stretch 5] [--worst 8]
                                [--replay [--set localizer.KEY=VALUE ...]]

Reads the per-scan trace that ``bench inproc --pose-trace DIR`` writes (stamp, odometry,
truth, the estimate every core took, and the localizer's match: trusted or not, score,
conditioning) and cuts the run into stretches of ``--stretch`` metres of true travel. For each
it gives the position error of the estimate at its start and end, and how much the heading
error of the estimate and of odometry changed over it. Heading is what turns a small error
into a large one: 0.05 rad off is 1 m after 20 m of driving, and on a new part of the map the
error stays in the map the scans make. So the stretches are ranked by how much the
estimate's heading error changed; a stretch where the estimate turned away from the truth
while odometry did not is one where the scan matcher, not odometry, made the error.

The first line is the run's figures: pose RMS / median / max [m], heading RMS / max [rad],
the share of scans whose match was trusted.

``--replay`` runs the localizer and the mapper again over the trace's scans and odometry
(``bench inproc``'s :func:`~topoexplore.tools.bench.inproc.replay_localizer`), with the run's
parameters and the ``--set`` overrides, and reports the replay as above beside the recorded
figures. The robot drives the recorded path whatever the localizer does, so two settings are
compared on the same scans, free of the run-to-run noise a changed path brings (a run's
pose error depends on where it drove: docs/benchmarks.md). What it cannot show is how a
setting changes the path.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from topoexplore.common.params import LocalizerParams

KEYS = ("t", "odom", "truth", "estimate", "matched", "score", "conditioning")
REPLAY_KEYS = ("ranges", "scan", "params")  # bench inproc writes them too
MAX_SCANS = 10_000_000  # a trace longer than this is not one of ours
END = 5  # scans averaged at each end of a stretch for its heading change


class TraceError(ValueError):
    """A trace file that cannot be read as one."""


def wrap(a: np.ndarray) -> np.ndarray:
    """Angles [rad] to [-pi, pi)."""
    return (np.asarray(a, np.float64) + math.pi) % (2 * math.pi) - math.pi


def load_trace(path: Path, replay: bool = False) -> dict[str, np.ndarray]:
    """The arrays of a trace file, checked: every key, (n,) or (n, 3) float, finite poses;
    with ``replay`` also the scans and parameters a replay needs."""
    keys = KEYS + (REPLAY_KEYS if replay else ())
    try:
        with np.load(path, allow_pickle=False) as z:
            got = {k: np.asarray(z[k]) for k in (*keys, "params") if k in z.files}
    except OSError as exc:  # missing, unreadable
        raise TraceError(f"{path}: {exc.strerror or exc}") from None
    except (ValueError, zipfile.BadZipFile, EOFError):  # numpy's words for "not an .npz"
        raise TraceError(f"{path}: not a pose trace (not an .npz archive of arrays)") from None
    missing = [k for k in keys if k not in got]
    if missing:
        raise TraceError(f"{path}: not a pose trace (no {', '.join(missing)})")
    n = len(got["t"])
    if n > MAX_SCANS:
        raise TraceError(f"{path}: {n} scans, more than {MAX_SCANS}")
    for k in KEYS:
        want = (n, 3) if k in ("odom", "truth", "estimate") else (n,)
        if got[k].shape != want or not np.issubdtype(got[k].dtype, np.number):
            raise TraceError(f"{path}: {k} has shape {got[k].shape} ({got[k].dtype}), "
                             f"expected {want} numbers")
    for k in ("t", "odom", "truth", "estimate"):
        if not np.isfinite(got[k]).all():
            raise TraceError(f"{path}: {k} holds a value that is not finite")
    if replay:
        r, g = got["ranges"], got["scan"]
        if r.ndim != 2 or r.shape[0] != n or (n and r.shape[1] < 2) \
                or not np.issubdtype(r.dtype, np.floating):
            raise TraceError(f"{path}: ranges has shape {r.shape}, expected ({n}, beams)")
        if g.shape != (4,) or not np.isfinite(g).all():
            raise TraceError(f"{path}: scan must hold 4 finite numbers (angle_min, "
                             "angle_increment, range_min, range_max)")
        if got["params"].shape != () or not np.issubdtype(got["params"].dtype, np.str_):
            raise TraceError(f"{path}: params must be the run's parameters as JSON text")
    return got


@dataclass(frozen=True)
class Stretch:
    first: int  # scan index where it starts
    last: int  # scan index where it ends (inclusive)
    start_xy: tuple[float, float]  # [m] the true position at its start
    end_xy: tuple[float, float]  # [m] and at its end
    travel: float  # [m] true travel over it
    error_start: float  # [m] position error of the estimate at its start
    error_end: float  # [m] at its end
    heading_change: float  # [rad] change of the estimate's heading error over it (the mean
    #   over END scans at each end)
    odom_heading_change: float  # [rad] the same for odometry
    matched: float  # share of its scans whose match was trusted (nan: no localizer)
    conditioning: float  # mean conditioning of its matches (nan: none)


def summary(tr: dict[str, np.ndarray]) -> dict[str, float]:
    """The run's figures: pose error RMS / median / max [m], heading error RMS / max [rad],
    the share of scans with a trusted match (nan when the localizer did not run)."""
    d = tr["estimate"][:, :2] - tr["truth"][:, :2]
    e = np.hypot(d[:, 0], d[:, 1])
    h = np.abs(wrap(tr["estimate"][:, 2] - tr["truth"][:, 2]))
    tried = tr["matched"] >= 0
    if not len(e):
        return {"scans": 0}
    return {"scans": len(e), "pose_rms_m": float(np.sqrt(np.mean(e ** 2))),
            "pose_median_m": float(np.median(e)), "pose_max_m": float(e.max()),
            "heading_rms_rad": float(np.sqrt(np.mean(h ** 2))), "heading_max_rad": float(h.max()),
            "matched": float(np.mean(tr["matched"][tried] == 1)) if tried.any() else math.nan}


def stretches(tr: dict[str, np.ndarray], length: float) -> list[Stretch]:
    """The run cut into pieces of ``length`` [m] of true travel (the last may be shorter),
    in order."""
    truth, est, odom = tr["truth"], tr["estimate"], tr["odom"]
    n = len(truth)
    if n == 0:
        return []
    step = np.hypot(*np.diff(truth[:, :2], axis=0).T)
    travel = np.concatenate(([0.0], np.cumsum(step)))
    cut = np.floor(travel / length).astype(np.int64)
    bounds = np.flatnonzero(np.diff(cut)) + 1
    starts = np.concatenate(([0], bounds))
    ends = np.concatenate((bounds, [n])) - 1
    err = np.hypot(*(est[:, :2] - truth[:, :2]).T)
    h_est = np.unwrap(wrap(est[:, 2] - truth[:, 2]))
    h_odom = np.unwrap(wrap(odom[:, 2] - truth[:, 2]))
    out = []
    for a, b in zip(starts.tolist(), ends.tolist(), strict=True):
        seg = slice(a, b + 1)
        # a heading error's change between the means of up to END scans at each end (one
        # scan's error jumps while the robot turns)
        m = max(1, min(END, (b - a + 1) // 2))
        head, tail = slice(a, a + m), slice(b + 1 - m, b + 1)
        tried = tr["matched"][seg] >= 0
        cond = tr["conditioning"][seg][tried & np.isfinite(tr["conditioning"][seg])]
        out.append(Stretch(
            a, b, (float(truth[a, 0]), float(truth[a, 1])),
            (float(truth[b, 0]), float(truth[b, 1])), float(travel[b] - travel[a]),
            float(err[a]), float(err[b]), float(h_est[tail].mean() - h_est[head].mean()),
            float(h_odom[tail].mean() - h_odom[head].mean()),
            float(np.mean(tr["matched"][seg][tried] == 1)) if tried.any() else math.nan,
            float(cond.mean()) if cond.size else math.nan))
    return out


def along_track(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(n-1,) [m] each step of poses a along a's heading before it, minus the same for
    poses b: the component of a step that a scan pinning only the cross direction (a
    corridor) leaves free. Each in its own frame, as odometry measures its increments."""
    def forward(p: np.ndarray) -> np.ndarray:
        d = np.diff(p[:, :2], axis=0)
        return d[:, 0] * np.cos(p[:-1, 2]) + d[:, 1] * np.sin(p[:-1, 2])

    return forward(a) - forward(b)


WEAK_MIN_SCANS = 20  # a run of weakly pinned scans counts from this many on (4 s at 5 Hz)


def weak_stretches(tr: dict[str, np.ndarray], ratio: float, min_scans: int = WEAK_MIN_SCANS
                   ) -> list[tuple[int, int, float, float]]:
    """The runs of at least ``min_scans`` consecutive matched scans whose conditioning is
    below ``ratio`` (localizer.degenerate_ratio: the scan pins the position along one
    direction this much less than across it), each as (first scan, last scan, along-track
    error the estimate added over it, the same for odometry) [m]. Where the two agree the
    estimate is odometry's along the corridor, as step 5 of the localizer makes it."""
    n = len(tr["t"])
    if n < 2:
        return []
    weak = (tr["matched"] >= 0) & (np.nan_to_num(tr["conditioning"], nan=1.0) < ratio)
    est = along_track(tr["estimate"], tr["truth"])
    odo = along_track(tr["odom"], tr["truth"])
    edges = np.flatnonzero(np.diff(np.concatenate(([0], weak[1:].astype(np.int8), [0]))))
    out = []
    for a, b in zip(edges[::2].tolist(), edges[1::2].tolist(), strict=True):
        if b - a >= min_scans:  # steps a .. b-1 end at scans a+1 .. b
            out.append((a + 1, b, float(est[a:b].sum()), float(odo[a:b].sum())))
    return out


def worst(parts: list[Stretch], k: int) -> list[Stretch]:
    """The ``k`` stretches whose estimate turned most against the truth, worst first."""
    return sorted(parts, key=lambda s: -abs(s.heading_change))[:k]


def report(tr: dict[str, np.ndarray], length: float, k: int) -> list[str]:
    """The lines ``main`` prints."""
    s = summary(tr)
    if not s["scans"]:
        return ["0 scans in the trace"]
    trusted = "-" if math.isnan(s["matched"]) else f"{100 * s['matched']:.1f} %"
    lines = [f"{s['scans']} scans: pose error RMS {s['pose_rms_m']:.3f} m, median "
             f"{s['pose_median_m']:.3f} m, max {s['pose_max_m']:.3f} m; heading error RMS "
             f"{s['heading_rms_rad']:.4f} rad, max {s['heading_max_rad']:.4f} rad; trusted "
             f"matches {trusted}", *_weak_lines(tr),
             f"stretches of {length:g} m whose estimate turned most against the truth "
             "(heading error change of the estimate and of odometry [rad]):",
             "  scans            from -> to [m]                    error [m]      estimate  "
             "odometry  trusted  conditioning"]
    for p in worst(stretches(tr, length), k):
        tm = "-" if math.isnan(p.matched) else f"{100 * p.matched:.0f} %"
        cd = "-" if math.isnan(p.conditioning) else f"{p.conditioning:.2f}"
        lines.append(
            f"  {p.first:6d}-{p.last:<6d}  ({p.start_xy[0]:6.1f},{p.start_xy[1]:6.1f}) -> "
            f"({p.end_xy[0]:6.1f},{p.end_xy[1]:6.1f})  {p.error_start:5.2f} -> "
            f"{p.error_end:5.2f}  {p.heading_change:+8.4f}  {p.odom_heading_change:+8.4f}  "
            f"{tm:>7s}  {cd:>5s}")
    return lines


def _weak_lines(tr: dict[str, np.ndarray]) -> list[str]:
    """The report's line on the stretches the laser could not pin along (none without a
    localizer)."""
    if not (tr["matched"] >= 0).any():
        return []
    ratio = _ratio(tr)
    w = weak_stretches(tr, ratio)
    share = float(np.mean(np.nan_to_num(tr["conditioning"], nan=1.0)[tr["matched"] >= 0]
                          < ratio))
    head = (f"scans pinned weakly along one direction (conditioning < {ratio:g}): "
            f"{100 * share:.0f} %; {len(w)} runs of {WEAK_MIN_SCANS} or more such scans")
    if len(w) < 2:
        return [head]
    e = np.array([x[2] for x in w])
    o = np.array([x[3] for x in w])
    corr = f"{np.corrcoef(e, o)[0, 1]:.2f}" if e.std() > 0 and o.std() > 0 else "-"
    return [head + f": along-track error added per run RMS {np.sqrt(np.mean(e ** 2)):.3f} m "
            f"(odometry's {np.sqrt(np.mean(o ** 2)):.3f} m; correlation {corr})"]


def _ratio(tr: dict[str, np.ndarray]) -> float:
    """The run's localizer.degenerate_ratio (its recorded parameters), else the default."""
    try:
        return float(json.loads(str(tr.get("params", "")))["localizer"]["degenerate_ratio"])
    except (KeyError, ValueError, TypeError):
        return LocalizerParams().degenerate_ratio


def replay(tr: dict[str, np.ndarray], sets: list[str]) -> dict[str, np.ndarray]:
    """The trace the localizer makes of the recorded scans with the run's parameters and
    ``sets`` (ParamError, TraceError)."""
    from topoexplore.common.params import params_from_dict
    from topoexplore.tools.bench.inproc import replay_localizer

    try:
        data = json.loads(str(tr["params"]))
    except json.JSONDecodeError as exc:
        raise TraceError(f"params is not JSON ({exc})") from None
    P = params_from_dict(data, sets)
    if not P.localizer.enabled:
        raise TraceError("the localizer is off in this run's parameters: add --set "
                         "localizer.enabled=true")
    return replay_localizer(P, tr["t"], tr["odom"], tr["truth"], tr["ranges"], tr["scan"])


def trace_files(paths: list[Path]) -> list[Path]:
    """The trace files named, a directory standing for its ``*.npz`` (TraceError: none)."""
    out: list[Path] = []
    for p in paths:
        out += sorted(p.glob("*.npz")) if p.is_dir() else [p]
    if not out:
        raise TraceError(f"no .npz trace in {', '.join(map(str, paths))}")
    return out


def figures(item: tuple[Path, bool, tuple[str, ...]]) -> tuple[str, dict, dict | None]:
    """One trace's summary, and its replay's with ``--set``s when asked (a pool's task)."""
    path, again, sets = item
    tr = load_trace(path, replay=again)
    return path.name, summary(tr), summary(replay(tr, list(sets))) if again else None


def _line(s: dict) -> str:
    if not s["scans"]:
        return "0 scans"
    return (f"RMS {s['pose_rms_m']:.3f} m, median {s['pose_median_m']:.3f}, max "
            f"{s['pose_max_m']:.3f}; heading RMS {s['heading_rms_rad']:.4f} rad")


def many(files: list[Path], again: bool, sets: list[str], jobs: int) -> list[str]:
    """The lines for several traces: each one's figures (recorded, and replayed), then the
    geometric mean of the pose RMS over them."""
    from concurrent.futures import ProcessPoolExecutor

    with ProcessPoolExecutor(max(1, min(jobs, len(files)))) as pool:
        got = list(pool.map(figures, [(f, again, tuple(sets)) for f in files]))
    lines = []
    for name, rec, new in got:
        lines.append(f"{name}: recorded {_line(rec)}"
                     + (f" | replayed {_line(new)}" if new is not None else ""))

    def gmean(col: int) -> str:
        v = [g[col]["pose_rms_m"] for g in got if g[col] and g[col]["scans"]]
        return f"{math.exp(np.mean(np.log(np.maximum(v, 1e-6)))):.4f}" if v else "-"

    lines.append(f"pose RMS, geometric mean over {len(got)} trace(s): recorded {gmean(1)}"
                 + (f", replayed {gmean(2)}" + (f" with {' '.join(sets)}" if sets else "")
                    if again else ""))
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="topoexplore bench posetrace", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("trace", type=Path, nargs="+",
                    help="a .npz written by bench inproc --pose-trace, or a directory of them "
                         "(several: one line each and the geometric mean)")
    ap.add_argument("--stretch", type=float, default=5.0, help="[m] of true travel (default 5)")
    ap.add_argument("--worst", type=int, default=8, help="stretches to list (default 8)")
    ap.add_argument("--replay", action="store_true",
                    help="run the localizer again over the recorded scans and odometry")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="with --replay: a parameter override (repeatable)")
    ap.add_argument("--jobs", type=int, default=2, help="traces replayed at once (default 2)")
    a = ap.parse_args(argv)
    if not (math.isfinite(a.stretch) and a.stretch > 0) or a.worst < 0 or a.jobs < 1:
        print("topoexplore bench posetrace: --stretch must be > 0, --worst >= 0, --jobs >= 1",
              file=sys.stderr)
        return 2
    if a.set and not a.replay:
        print("topoexplore bench posetrace: --set needs --replay", file=sys.stderr)
        return 2
    from topoexplore.common.params import ParamError

    try:
        files = trace_files(a.trace)
        if len(files) > 1:
            print("\n".join(many(files, a.replay, a.set, a.jobs)))
            return 0
        tr = load_trace(files[0], replay=a.replay)
        if a.replay:
            print("recorded: " + report(tr, a.stretch, 0)[0])
            tr = replay(tr, a.set)
            print("replayed" + (f" with {' '.join(a.set)}" if a.set else "") + ": ", end="")
    except (TraceError, ParamError) as exc:
        print(f"topoexplore bench posetrace: {exc}", file=sys.stderr)
        return 2
    print("\n".join(report(tr, a.stretch, a.worst)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
