"""``topoexplore bench hangs``: does ``run`` always come down, and take its children with it?

    topoexplore bench hangs [--tries 20] [--cases disk-full,broken-pipe,signals]
                            [--world paper-room] [--seed 0] [--json F]

Each try starts ``topoexplore run`` (real time x8, every service a process, its own port and
namespace) and does one of these to it (moments and sizes drawn from ``--seed``):

- ``disk-full``: ``--out`` lies on a 1 MB tmpfs mounted for the try, already filled to a
  random level, so the disk fills at a random moment: before the output directory exists,
  while logs and checkpoints are written, or while the report and the picture are; at a
  random moment the run is stopped with SIGTERM. Needs root (mount).
- ``broken-pipe``: ``run | true``: the reader of stdout is gone before ``run`` writes to it;
  then, at a random moment, SIGTERM to the process group (if it has not finished by then).
- ``signals``: at a random moment, SIGTERM to the whole process group (as systemd stops a
  unit), then SIGINT and SIGTERM to ``run`` 0-30 ms apart.

A try **hangs** when ``run`` has not exited ``--timeout`` s (wall) after the fault, or when
a process of its stack (found by its namespace on the command line) is still alive 5 s after
``run`` exited. Also reported: the exit codes, and the last line ``run`` wrote to stderr.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from topoexplore.tools.launch.supervisor import free_port

CASES = ("disk-full", "broken-pipe", "signals")
TMPFS_BYTES = 1 << 20  # [bytes] the disk of a disk-full try


def stack_pids(tag: str) -> list[int]:
    """Processes whose command line holds ``tag`` (the try's namespace)."""
    out = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit() or int(d.name) == os.getpid():
            continue
        try:
            cmd = (d / "cmdline").read_bytes()
        except OSError:
            continue
        if tag.encode() in cmd:
            out.append(int(d.name))
    return out


def _cmd(ns: str, out: Path, quiet: bool) -> list[str]:
    return [sys.executable, "-m", "topoexplore.tools.cli", "run", "--world", _cmd.world,
            "--speed", "8", "--max-sim-time", "300", "--out", str(out), "--connect",
            f"tcp/127.0.0.1:{free_port()}", "--namespace", ns, *(["--quiet"] if quiet else [])]


_cmd.world = "paper-room"  # type: ignore[attr-defined]


def _finish(proc: subprocess.Popen, ns: str, t_fault: float, timeout: float,
            err_path: Path) -> dict[str, Any]:
    """Wait for run's exit and its stack's; the row of one try."""
    row: dict[str, Any] = {}
    try:
        proc.wait(timeout=timeout)
        row["exit"] = proc.returncode
        row["exit_s"] = round(time.monotonic() - t_fault, 2)
    except subprocess.TimeoutExpired:
        row["exit"] = None
    t_exit = time.monotonic()
    left = stack_pids(ns)
    while left and time.monotonic() - t_exit < 5.0:
        time.sleep(0.1)
        left = stack_pids(ns)
    row["left_behind"] = len(left)
    row["hang"] = row["exit"] is None or bool(left)
    for pid in left:  # leave nothing running for the next try
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=10)
    try:
        lines = [ln for ln in err_path.read_text(errors="replace").splitlines() if ln.strip()]
    except OSError:
        lines = []
    row["last_line"] = lines[-1][:200] if lines else ""
    row["tracebacks"] = sum(1 for ln in lines if ln.startswith("Traceback"))
    return row


def try_disk_full(k: int, rng: random.Random, tmp: Path, timeout: float) -> dict[str, Any]:
    mnt = tmp / f"disk{k}"
    mnt.mkdir()
    subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={TMPFS_BYTES}", "tmpfs", str(mnt)],
                   check=True, capture_output=True, timeout=30)
    try:
        fill = int(rng.uniform(0.0, 1.0) * TMPFS_BYTES)
        try:
            with (mnt / "filler").open("wb") as f:
                f.write(b"\0" * fill)
        except OSError:
            pass
        ns = f"hang{os.getpid()}d{k}"
        err = tmp / f"err{k}.txt"
        with err.open("w") as ef:
            proc = subprocess.Popen(_cmd(ns, mnt / "out", True), stdout=subprocess.DEVNULL,
                                    stderr=ef, start_new_session=True)
        time.sleep(rng.uniform(1.0, 12.0))
        t_fault = time.monotonic()
        if proc.poll() is None:  # still running: stop it, so the outputs are written now
            os.killpg(proc.pid, signal.SIGTERM)
        row = {"case": "disk-full", "fill_kb": fill // 1024,
               **_finish(proc, ns, t_fault, timeout, err)}
    finally:
        subprocess.run(["umount", "-l", str(mnt)], capture_output=True, timeout=30)
    return row


def try_broken_pipe(k: int, rng: random.Random, tmp: Path, timeout: float) -> dict[str, Any]:
    ns = f"hang{os.getpid()}p{k}"
    err = tmp / f"err{k}.txt"
    with err.open("w") as ef:
        proc = subprocess.Popen(_cmd(ns, tmp / f"out{k}", False), stdout=subprocess.PIPE,
                                stderr=ef, start_new_session=True)
    proc.stdout.close()  # the reader went away before run wrote anything (``run | true``)
    time.sleep(rng.uniform(1.0, 14.0))
    t_fault = time.monotonic()
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGTERM)
    return {"case": "broken-pipe", **_finish(proc, ns, t_fault, timeout, err)}


def try_signals(k: int, rng: random.Random, tmp: Path, timeout: float) -> dict[str, Any]:
    ns = f"hang{os.getpid()}s{k}"
    err = tmp / f"err{k}.txt"
    with err.open("w") as ef:
        proc = subprocess.Popen(_cmd(ns, tmp / f"out{k}", True), stdout=subprocess.DEVNULL,
                                stderr=ef, start_new_session=True)
    at = rng.uniform(1.0, 12.0)  # [s] from start-up (numba warm-up) into the run
    time.sleep(at)
    t_fault = time.monotonic()
    try:
        os.killpg(proc.pid, signal.SIGTERM)  # the whole unit
        time.sleep(rng.uniform(0.0, 0.03))
        proc.send_signal(signal.SIGINT)
        time.sleep(rng.uniform(0.0, 0.03))
        proc.send_signal(signal.SIGTERM)
    except ProcessLookupError:
        pass
    return {"case": "signals", "at_s": round(at, 2), **_finish(proc, ns, t_fault, timeout, err)}


TRIES = {"disk-full": try_disk_full, "broken-pipe": try_broken_pipe, "signals": try_signals}


def summary(rows: list[dict]) -> str:
    lines = ["| case | tries | hangs | left behind | exit codes | tracebacks | slowest exit "
             "after the fault [s] |", "|---|---|---|---|---|---|---|"]
    for case in CASES:
        rs = [r for r in rows if r["case"] == case]
        if not rs:
            continue
        codes: dict[str, int] = {}
        for r in rs:
            codes[str(r["exit"])] = codes.get(str(r["exit"]), 0) + 1
        slow = max((r.get("exit_s") or 0.0) for r in rs)
        lines.append(f"| {case} | {len(rs)} | {sum(r['hang'] for r in rs)} "
                     f"| {sum(r['left_behind'] for r in rs)} "
                     f"| {', '.join(f'{c}: {n}' for c, n in sorted(codes.items()))} "
                     f"| {sum(r['tracebacks'] for r in rs)} | {slow:.1f} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="topoexplore bench hangs", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tries", type=int, default=20, help="tries per case (default 20)")
    ap.add_argument("--cases", default=",".join(CASES), help="comma separated: " + ", ".join(CASES))
    ap.add_argument("--world", default="paper-room")
    ap.add_argument("--timeout", type=float, default=30.0,
                    help="[wall s] after the fault before run counts as hung (default 30)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", default=None, help="write every try's row here")
    a = ap.parse_args(argv)
    cases = [c.strip() for c in a.cases.split(",") if c.strip()]
    bad = [c for c in cases if c not in TRIES]
    if bad or not (1 <= a.tries <= 1000) or not a.timeout > 0:
        print(f"topoexplore bench hangs: expected --cases from {', '.join(CASES)}, --tries "
              f"1-1000 and --timeout > 0 (got {a.cases!r}, {a.tries}, {a.timeout})",
              file=sys.stderr)
        return 2
    if "disk-full" in cases and os.geteuid() != 0:
        print("topoexplore bench hangs: disk-full mounts a tmpfs and needs root; skipped",
              file=sys.stderr)
        cases.remove("disk-full")
    _cmd.world = a.world  # type: ignore[attr-defined]
    rng = random.Random(a.seed)
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench-hangs-") as tmp:
        k = 0
        for case in cases:
            for _ in range(a.tries):
                row = TRIES[case](k, rng, Path(tmp), a.timeout)
                k += 1
                rows.append(row)
                print(json.dumps(row), flush=True)
    text = summary(rows)
    print("\n" + text)
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1))
    return 1 if any(r["hang"] for r in rows) else 0
