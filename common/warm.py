"""Numba kernels compiled before a service says it is up, once per install and not once per
process.

Every module with numba kernels lists its entry kernels (the ones Python code calls) with the
argument types the services call them with::

    WARM = {"zhang_suen": ("(uint8[:, ::1],)",), ...}

and every core lists the modules whose kernels it runs (``WARM_MODULES``, module names).
:func:`compile_kernels` compiles each listed signature, or loads it from numba's on-disk cache
(``cache=True``: ``__pycache__`` beside the source, or ``NUMBA_CACHE_DIR``), and says which.
A service does this before it declares its liveliness token, so it never drops inputs while
compiling; the supervisor does it once for the whole profile before it starts the services
(``topoexplore warmup``), so six processes do not compile the same kernels at once on a cold
cache. ``tests/test_warm.py`` checks that an exploration compiles nothing beyond the lists.
"""

from __future__ import annotations

import importlib
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

__all__ = ["WarmError", "WarmResult", "compile_kernels", "kernel_files", "kernel_table"]


class WarmError(ValueError):
    """A WARM list names something that is not a numba kernel of its module."""


@dataclass
class WarmResult:
    """What :func:`compile_kernels` did: signatures loaded from the cache or compiled."""

    loaded: int = 0
    compiled: int = 0
    present: int = 0  # already compiled in this process before (e.g. by a constructor)
    seconds: float = 0.0  # [s] wall
    cache_dirs: list[str] = field(default_factory=list)
    per_module: dict[str, tuple[int, int, float]] = field(default_factory=dict)
    # the kernel modules' source files and numba's cache files for them, after the warm-up
    # (what tools/warm.py's stamp watches)
    files: list[str] = field(default_factory=list)

    @property
    def signatures(self) -> int:
        return self.loaded + self.compiled + self.present

    def line(self) -> str:
        if self.signatures == 0:
            return "no numba kernels"
        if self.compiled == 0:
            return (f"{self.signatures} numba kernel(s) ready in {self.seconds:.2f} s "
                    f"(loaded from the cache)")
        where = ", ".join(self.cache_dirs) or "numba's cache"
        return (f"{self.compiled} numba kernel(s) compiled in {self.seconds:.1f} s "
                f"({self.signatures - self.compiled} loaded from the cache); cached in {where}")


def _types(sig: str) -> tuple:
    from numba.core import sigutils

    args, _ret = sigutils.normalize_signature(sig)
    return tuple(args)


def kernel_files(module_name: str) -> list[str]:
    """A kernel module's source file, then numba's cache files (index and code) of its
    kernels (the warm-up stamp watches them all; ``warmup --clear`` deletes the cache ones)."""
    mod = importlib.import_module(module_name)
    src = Path(mod.__file__)
    out = [str(src)]
    dirs = {Path(d.stats.cache_path) for _, d, _ in kernel_table(module_name)
            if d.stats.cache_path}
    for d in sorted(dirs):
        out += sorted(str(f) for f in d.glob(f"{src.stem}.*.nb[ic]"))
    return out


def kernel_table(module_name: str) -> list[tuple[str, object, tuple[str, ...]]]:
    """(name, dispatcher, signatures) of every kernel a module's ``WARM`` dict lists."""
    mod = importlib.import_module(module_name)
    table = getattr(mod, "WARM", None)
    if not isinstance(table, dict):
        raise WarmError(f"{module_name} has no WARM dict of kernels")
    out = []
    for name, sigs in table.items():
        disp = getattr(mod, name, None)
        if disp is None or not hasattr(disp, "compile") or not hasattr(disp, "stats"):
            raise WarmError(f"{module_name}.{name} is listed in WARM but is not a numba kernel")
        if isinstance(sigs, str) or not sigs:
            raise WarmError(f"{module_name}.{name}: WARM wants a tuple of signatures")
        out.append((name, disp, tuple(sigs)))
    return out


def compile_kernels(module_names: Iterable[str]) -> WarmResult:
    """Compile (or load from the on-disk cache) every signature the modules' WARM dicts list.

    Idempotent and cheap once done: a signature this process has already compiled costs
    nothing, one in the cache costs a load (about 10-50 ms)."""
    res = WarmResult()
    t_all = time.monotonic()
    for mname in dict.fromkeys(module_names):
        t0 = time.monotonic()
        loaded = compiled = present = 0
        for _name, disp, sigs in kernel_table(mname):
            for sig in sigs:
                hits = sum(disp.stats.cache_hits.values())
                n_before = len(disp.signatures)
                # numba keys its cache by the signature object it is given: the tuple of types
                # a call compiles with, not the string, or the two would not share entries
                disp.compile(_types(sig))
                if len(disp.signatures) == n_before:
                    present += 1  # this process has it already
                    continue
                if sum(disp.stats.cache_hits.values()) > hits:
                    loaded += 1
                else:
                    compiled += 1  # a miss, or no cache (NUMBA_CACHE_DIR unwritable)
            path = disp.stats.cache_path
            if path and path not in res.cache_dirs and compiled:
                res.cache_dirs.append(path)
        res.files.extend(kernel_files(mname))
        dt = time.monotonic() - t0
        res.loaded += loaded
        res.compiled += compiled
        res.present += present
        res.per_module[mname] = (loaded + present, compiled, dt)
    res.seconds = time.monotonic() - t_all
    return res
