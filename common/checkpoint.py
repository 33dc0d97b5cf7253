"""Checkpoints of a service's state (issue 14: a restarted service keeps its state).

A checkpoint is a set of named numpy arrays in one ``.npz`` file (no pickles), written
atomically (:func:`common.mapio.atomic_write`: temporary file, fsync, rename) under
``runtime.state_dir``. It carries the wall time it was written: a checkpoint older than
``runtime.checkpoint_max_age`` belongs to an earlier session and is not loaded.
"""

from __future__ import annotations

import io
import math
import zipfile
from pathlib import Path

import numpy as np

from topoexplore.common.mapio import atomic_write

FORMAT = 1
_META = "_checkpoint"  # [format, written_at [s since the epoch]]


class CheckpointError(ValueError):
    """A checkpoint file that cannot be read (one line, for the log)."""


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
