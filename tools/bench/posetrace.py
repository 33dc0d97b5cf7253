"""Where a localized run lost its pose: ``topoexplore bench posetrace``.

    topoexplore bench posetrace TRACE.npz [--stretch 5] [--worst 8]

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
"""

from __future__ import annotations

import argparse
import math
import sys
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

KEYS = ("t", "odom", "truth", "estimate", "matched", "score", "conditioning")
MAX_SCANS = 10_000_000  # a trace longer than this is not one of ours
END = 5  # scans averaged at each end of a stretch for its heading change


class TraceError(ValueError):
    """A trace file that cannot be read as one."""


def wrap(a: np.ndarray) -> np.ndarray:
    """Angles [rad] to [-pi, pi)."""
    return (np.asarray(a, np.float64) + math.pi) % (2 * math.pi) - math.pi


def load_trace(path: Path) -> dict[str, np.ndarray]:
    """The arrays of a trace file, checked: every key, (n,) or (n, 3) float, finite poses."""
    try:
        with np.load(path, allow_pickle=False) as z:
            got = {k: np.asarray(z[k]) for k in KEYS if k in z.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
        raise TraceError(f"{path}: not a pose trace ({type(exc).__name__}: {exc})") from None
    missing = [k for k in KEYS if k not in got]
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
             f"matches {trusted}",
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


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="topoexplore bench posetrace", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("trace", type=Path, help="a .npz written by bench inproc --pose-trace")
    ap.add_argument("--stretch", type=float, default=5.0, help="[m] of true travel (default 5)")
    ap.add_argument("--worst", type=int, default=8, help="stretches to list (default 8)")
    a = ap.parse_args(argv)
    if not (math.isfinite(a.stretch) and a.stretch > 0) or a.worst < 0:
        print("topoexplore bench posetrace: --stretch must be > 0 and --worst >= 0",
              file=sys.stderr)
        return 2
    try:
        tr = load_trace(a.trace)
    except TraceError as exc:
        print(f"topoexplore bench posetrace: {exc}", file=sys.stderr)
        return 2
    print("\n".join(report(tr, a.stretch, a.worst)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
