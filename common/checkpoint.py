"""Checkpoints of a service's state (issue 14: a restarted service keeps its state).

A checkpoint is a set of named numpy arrays in one ``.npz`` file (no pickles), written
atomically (:func:`common.mapio.atomic_write`: temporary file, fsync, rename) under
``runtime.state_dir``. It carries the wall time it was written: a checkpoint older than
``runtime.checkpoint_max_age`` belongs to an earlier session and is not loaded.
"""

from __future__ import annotations

import io
import logging
import math
import time
import zipfile
from collections.abc import Callable
from pathlib import Path

import numpy as np

from topoexplore.common.mapio import atomic_write

FORMAT = 1
_META = "_checkpoint"  # [format, written_at [s since the epoch]]


class CheckpointError(ValueError):
    """A checkpoint file that cannot be read (one line, for the log)."""


def checked(arrays: dict[str, np.ndarray], name: str, kind: str, shape: tuple) -> np.ndarray:
    """``arrays[name]`` checked: numpy dtype kind ("f" float, "i" integer, "b" bool, "U"
    text) and shape (None: any length along that axis); floats must not be NaN (inf is
    allowed where a core stores "none yet" as inf). CheckpointError otherwise."""
    a = arrays.get(name)
    if a is None:
        raise CheckpointError(f"no {name!r} in the checkpoint")
    ok_kind = a.dtype.kind == kind or (kind == "i" and a.dtype.kind == "u") \
        or (kind == "f" and a.dtype.kind in "iu")
    if not ok_kind or a.ndim != len(shape) or any(
            want is not None and got != want for got, want in zip(a.shape, shape, strict=True)):
        raise CheckpointError(f"{name!r}: {a.dtype} {a.shape}, expected {kind} {shape}")
    if kind == "f" and np.isnan(a).any():
        raise CheckpointError(f"{name!r} holds NaN")
    return a


def checkpoint_path(state_dir: str, service: str) -> Path | None:
    """``<state_dir>/<service>.npz``, or None when checkpoints are off (empty state_dir)."""
    return Path(state_dir) / f"{service}.npz" if state_dir else None


def encode_checkpoint(arrays: dict[str, np.ndarray], written_at: float) -> bytes:
    if _META in arrays:
        raise ValueError(f"{_META} is reserved")
    buf = io.BytesIO()
    np.savez(buf, **arrays, **{_META: np.array([FORMAT, written_at], np.float64)})
    return buf.getvalue()


def decode_checkpoint(data: bytes) -> tuple[dict[str, np.ndarray], float]:
    """(arrays, written_at); CheckpointError for anything that is not one of our checkpoints."""
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise CheckpointError(f"not a checkpoint ({type(exc).__name__}: {exc})") from None
    meta = arrays.pop(_META, None)
    if meta is None or meta.shape != (2,) or meta[0] != FORMAT or not math.isfinite(meta[1]):
        raise CheckpointError("not a checkpoint of this version (no or bad header)")
    return arrays, float(meta[1])


def write_checkpoint(path: Path, arrays: dict[str, np.ndarray], written_at: float) -> int:
    """Write atomically; returns the size [bytes]. OSError if the directory cannot be made
    or written."""
    data = encode_checkpoint(arrays, written_at)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, data)
    return len(data)


def read_checkpoint(path: Path, now: float, max_age: float
                    ) -> tuple[dict[str, np.ndarray], float] | None:
    """(arrays, age [s]) of the checkpoint at ``path``; None if there is none or it is older
    than ``max_age`` (another session's); CheckpointError if it cannot be read."""
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        return None
    except OSError as exc:
        raise CheckpointError(f"cannot read {path}: {exc.strerror or exc}") from None
    arrays, written_at = decode_checkpoint(data)
    age = now - written_at
    if age > max_age:
        return None
    if age < -5.0:  # written in the future: a clock step; trust it no more than a stale one
        raise CheckpointError(f"{path} was written {-age:.0f} s in the future")
    return arrays, max(0.0, age)


def clear_state_dir(state_dir: str) -> int:
    """A new session (``run``, ``up --state-dir``): remove the checkpoints in ``state_dir``
    (created if missing); returns how many. OSError if it cannot be made or cleared."""
    if not state_dir:
        return 0
    d = Path(state_dir)
    d.mkdir(parents=True, exist_ok=True)
    n = 0
    for f in d.glob("*.npz"):
        f.unlink(missing_ok=True)
        n += 1
    return n


class Checkpointer:
    """A service shell's checkpoints: load at start, write when due, count what failed.

    ``stats`` (for the state queryable and report.json): written, failed, last_error, bytes,
    ms (the last write), resumed_age_s (the checkpoint a restart resumed, else None)."""

    def __init__(self, state_dir: str, service: str, every: float, max_age: float,
                 log: logging.Logger):
        self.path = checkpoint_path(state_dir, service)
        self.every = every  # [s] between two checkpoints, on the clock given to due/save
        self.max_age = max_age  # [s]
        self.log = log
        self.due_at = -math.inf  # [s] time of the next checkpoint (the first is due at once)
        self.stats: dict = {"path": str(self.path or ""), "written": 0, "failed": 0,
                            "last_error": "", "bytes": 0, "ms": 0.0, "resumed_age_s": None}

    def load(self, now: float) -> dict[str, np.ndarray] | None:
        """This service's recent checkpoint, or None (none, too old, unreadable: logged)."""
        if self.path is None:
            return None
        try:
            got = read_checkpoint(self.path, now, self.max_age)
        except CheckpointError as exc:
            self.log.error("checkpoint not used: %s", exc)
            return None
        if got is None:
            return None
        arrays, age = got
        self.stats["resumed_age_s"] = round(age, 3)
        return arrays

    def resume(self, restore: Callable[[dict[str, np.ndarray]], None], now: float) -> bool:
        """Load this service's checkpoint and hand it to ``restore`` (a core's; it raises
        CheckpointError for arrays it cannot use). True when a checkpoint was restored; a
        checkpoint that cannot be used is logged and the service starts afresh."""
        arrays = self.load(now)
        if arrays is None:
            return False
        try:
            restore(arrays)
        except CheckpointError as exc:
            self.log.error("checkpoint not used: %s", exc)
            self.stats["resumed_age_s"] = None
            return False
        return True

    def save_if_due(self, make: Callable[[], dict[str, np.ndarray]]) -> None:
        """Write ``make()`` when a checkpoint is due on the wall clock (every ``every`` s)."""
        t0 = time.monotonic()
        if self.due(t0):
            self.save(make(), t0, time.time(), lambda: time.monotonic() - t0)

    def due(self, clock: float) -> bool:
        """A checkpoint is due at ``clock`` [s] (the service's choice of clock: wall for the
        mapper, sim time for the simulator; a clock that went back makes one due)."""
        return self.path is not None and (clock >= self.due_at
                                          or clock < self.due_at - 2 * self.every)

    def save(self, arrays: dict[str, np.ndarray], clock: float, now: float,
             elapsed: Callable[[], float]) -> None:
        """Write ``arrays`` at ``clock`` (the next is due ``every`` later), stamped with the
        wall time ``now``; ``elapsed()`` [s] is what the write took. A failed write is
        counted and logged (1st, 10th, 100th, every 1000th)."""
        self.due_at = clock + self.every
        try:
            n = write_checkpoint(self.path, arrays, now)
        except OSError as exc:
            self.stats["failed"] += 1
            self.stats["last_error"] = f"{exc.strerror or exc}"
            k = self.stats["failed"]
            if k in (1, 10, 100) or k % 1000 == 0:
                self.log.error("checkpoint %s not written (%d so far): %s", self.path, k,
                               exc.strerror or exc)
            return
        self.stats["written"] += 1
        self.stats["bytes"] = n
        self.stats["ms"] = round(1000.0 * elapsed(), 2)
