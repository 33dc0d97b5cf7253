"""``topoexplore warmup``: compile the numba kernels of a launch profile once, in one process.

    topoexplore warmup [--profile sim|robot|PATH] [--clear]

On a fresh install (or after an update of the code or of numba) every kernel has to be
compiled once; numba keeps the result on disk (``__pycache__`` beside the source, or
``NUMBA_CACHE_DIR``). Without this step the services of a profile would compile at their
first start, six processes at once on two cores, each for its own kernels. The supervisor
(``topoexplore run`` and ``up``) runs this step before it starts the services, unless the
stamp the last warm-up left says that nothing has changed since (``stamp_valid``). ``--clear`` deletes the cached kernels of topoexplore first
(needed after editing ``common/kernels.py``: numba does not see that a cached caller's callee
changed).

Which kernels: each service's core names the modules whose kernels it runs
(``WARM_MODULES``), and each of those modules lists its entry kernels with their argument
types (``WARM``; ``common/warm.py``).
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import json
import multiprocessing
import multiprocessing.context
import os
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from pathlib import Path

from topoexplore.common.warm import WarmError, WarmResult, compile_kernels, kernel_files

__all__ = ["core_of", "warm_modules", "warm_cores", "clear_cache", "write_stamp", "stamp_valid",
           "main"]

NOTICE_AFTER = 0.5  # [s] a core that takes longer than this is compiling: say so


def core_of(service_module: str) -> str | None:
    """The core module beside a service module (``pkg.service`` -> ``pkg.core``), if any."""
    if not service_module or "." not in service_module:
        return None
    core = service_module.rsplit(".", 1)[0] + ".core"
    try:
        return core if importlib.util.find_spec(core) is not None else None
    except (ImportError, ValueError):
        return None


def warm_modules(core_module: str) -> tuple[str, ...]:
    """The ``WARM_MODULES`` of a core (empty when it has none)."""
    mod = importlib.import_module(core_module)
    return tuple(getattr(mod, "WARM_MODULES", ()))


def _warm_core(core: str) -> WarmResult:
    """Worker: compile (or load) one core's kernels."""
    return compile_kernels(warm_modules(core))


def _pool_context() -> multiprocessing.context.BaseContext:
    # fork is cheap, and safe while this process has not imported numba (each worker imports
    # its own); otherwise, and off Linux, spawn
    fork = sys.platform == "linux" and "numba" not in sys.modules
    return multiprocessing.get_context("fork" if fork else "spawn")


def warm_cores(cores: Sequence[tuple[str, str]], echo: Callable[[str], None],
               jobs: int | None = None,
               notice_after: float = NOTICE_AFTER) -> dict[str, WarmResult]:
    """Compile the kernels of each (label, core module), ``jobs`` cores at a time in worker
    processes (default: one per CPU), each core in one worker. ``echo`` gets one line per core
    as it finishes, and a 'compiling ...' line when nothing finished within ``notice_after``
    (the cache lacks the kernels), so a cold start never looks like a hang."""
    cores = list(cores)
    out: dict[str, WarmResult] = {}
    if not cores:
        return out
    jobs = max(1, min(jobs or os.cpu_count() or 1, len(cores)))
    with ProcessPoolExecutor(max_workers=jobs, mp_context=_pool_context()) as ex:
        futures = {ex.submit(_warm_core, core): label for label, core in cores}
        pending = set(futures)
        noticed = False
        while pending:
            done, pending = wait(pending, timeout=None if noticed else notice_after,
                                 return_when=FIRST_COMPLETED)
            if not done and not noticed:
                noticed = True
                echo(f"compiling numba kernels, {jobs} process(es) at a time (first start with "
                     f"this code; kept on disk for later starts) ...")
            for f in done:
                res = f.result()
                out[futures[f]] = res
                if res.signatures:
                    echo(f"{futures[f]}: {res.line()}")
    return {label: out[label] for label, _ in cores if label in out}


def _kernel_modules(cores: Iterable[str]) -> list[str]:
    names: list[str] = []
    for core in cores:
        names.extend(warm_modules(core))
    return list(dict.fromkeys(names))


def _package_dirs() -> list[Path]:
    import topoexplore.common
    import topoexplore.services
    import topoexplore.sim
    import topoexplore.tools

    return [Path(p) for pkg in (topoexplore.common, topoexplore.services, topoexplore.sim,
                                topoexplore.tools) for p in pkg.__path__]


def clear_cache(module_names: Iterable[str], package: bool = True) -> int:
    """Delete numba's cached files (index ``.nbi`` and code ``.nbc``) of the kernels in these
    WARM modules (wherever numba keeps them) and, with ``package``, every one in the package's
    ``__pycache__`` folders (the bench's kernels, ``common.kernels`` compiled into its
    callers). Returns the number of files removed."""
    files = {Path(f) for m in dict.fromkeys(module_names) for f in kernel_files(m)[1:]}
    if package:
        for root in _package_dirs():
            files |= set(root.rglob("__pycache__/*.nb[ic]"))
    for f in files:
        f.unlink(missing_ok=True)
    return len(files)


def profile_cores(profile_name: str) -> list[tuple[str, str]]:
    """(process name, core module) of the module processes of a launch profile."""
    from topoexplore.tools.launch.core import load_profile
    from topoexplore.tools.launch.supervisor import profile_path

    profile = load_profile(profile_path(profile_name))
    cores = []
    for spec in profile.processes:
        core = core_of(spec.module)
        if core is not None:
            cores.append((spec.name, core))
    return cores


# --- the stamp: skip the warm-up child when nothing changed since the last one ---------------


STAMP_NAME = "warmup-stamp.json"


def stamp_paths() -> list[Path]:
    """Where the stamp may live: beside this package's bytecode, else the user's cache."""
    import topoexplore.tools

    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return [Path(topoexplore.tools.__path__[0]) / "__pycache__" / STAMP_NAME,
            Path(base) / "topoexplore" / STAMP_NAME]


def _environment() -> dict[str, str]:
    """What numba's cache depends on beyond the files: versions, interpreter, cache dir."""
    import platform
    from importlib.metadata import PackageNotFoundError, version

    def ver(pkg: str) -> str:
        try:
            return version(pkg)
        except PackageNotFoundError:
            return ""

    return {"numba": ver("numba"), "llvmlite": ver("llvmlite"), "python": sys.version,
            "executable": sys.executable, "machine": platform.machine(),
            "NUMBA_CACHE_DIR": os.environ.get("NUMBA_CACHE_DIR", "")}


def _stat(path: str) -> list[int] | None:
    try:
        st = os.stat(path)
    except OSError:
        return None
    return [st.st_mtime_ns, st.st_size]


def write_stamp(cores: Sequence[tuple[str, str]], results: dict[str, WarmResult]) -> Path | None:
    """After a warm-up: the cores, the environment, and the stat of every kernel source and
    cache file, in the first stamp location that takes it. None when none does."""
    files = sorted({f for r in results.values() for f in r.files})
    doc = {"version": 1, "environment": _environment(), "cores": [list(c) for c in cores],
           "files": {f: _stat(f) for f in files}}
    for path in stamp_paths():
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_suffix(f".{os.getpid()}.tmp")
            tmp.write_text(json.dumps(doc))
            tmp.replace(path)
            return path
        except OSError:
            continue
    return None


def stamp_valid(cores: Sequence[tuple[str, str]]) -> bool:
    """True when a stamp covers these cores, in this environment, and no kernel source or
    cache file it lists has changed or gone since: the services will load every kernel."""
    want = [list(c) for c in cores]
    env = None
    for path in stamp_paths():
        try:
            doc = json.loads(path.read_text())
        except (OSError, ValueError):
            continue
        if not isinstance(doc, dict) or doc.get("version") != 1:
            continue
        files = doc.get("files")
        if not isinstance(files, dict) or not files or not all(c in doc.get("cores", [])
                                                                   for c in want):
            continue
        env = env or _environment()
        if doc.get("environment") == env and all(_stat(f) == st for f, st in files.items()):
            return True
    return False


def remove_stamp() -> None:
    for path in stamp_paths():
        try:
            path.unlink(missing_ok=True)
        except OSError:
            pass


class _Parser(argparse.ArgumentParser):
    def error(self, message: str):  # type: ignore[override]
        raise WarmError(message)


def build_parser() -> argparse.ArgumentParser:
    ap = _Parser(prog="topoexplore warmup",
                 description="Compile the numba kernels of a launch profile once (kept on disk), "
                 "so the services start without compiling.")
    ap.add_argument("--profile", default="sim",
                    help="launch profile name (deploy/profiles) or path (default sim)")
    ap.add_argument("--cores", default=None, metavar="NAME=MODULE,...",
                    help=argparse.SUPPRESS)  # the supervisor's child: its profile's cores
    ap.add_argument("--jobs", type=int, default=None,
                    help="cores compiled at a time, each in its own process (default: CPUs)")
    ap.add_argument("--clear", action="store_true",
                    help="delete topoexplore's cached kernels first, then compile them")
    return ap


def main(argv: Sequence[str] | None = None) -> int:
    from topoexplore.tools.launch.core import ProfileError

    try:
        args = build_parser().parse_args(list(sys.argv[1:] if argv is None else argv))
        if args.cores is not None:
            cores = [tuple(c.split("=", 1)) for c in args.cores.split(",") if c]
            if any(len(c) != 2 for c in cores):
                raise WarmError(f"--cores wants NAME=MODULE pairs, got {args.cores!r}")
        else:
            cores = profile_cores(args.profile)
        if args.jobs is not None and args.jobs < 1:
            raise WarmError(f"--jobs must be >= 1, got {args.jobs}")
        if args.clear:
            remove_stamp()
            n = clear_cache(_kernel_modules(c for _, c in cores))
            print(f"[warmup] removed {n} cached kernel file(s)", flush=True)
        t0 = time.monotonic()
        results = warm_cores(cores, lambda line: print(f"[warmup] {line}", flush=True),
                             jobs=args.jobs)
        write_stamp(cores, results)
    except (WarmError, ProfileError, ImportError) as exc:
        print(f"topoexplore warmup: {exc}", file=sys.stderr)
        return 2
    compiled = sum(r.compiled for r in results.values())
    loaded = sum(r.signatures - r.compiled for r in results.values())
    dt = time.monotonic() - t0
    if compiled:
        print(f"[warmup] {compiled} kernel(s) compiled, {loaded} loaded from the cache, in "
              f"{dt:.1f} s", flush=True)
    else:
        print(f"[warmup] all {loaded} kernel(s) ready (loaded from the cache) in {dt:.1f} s",
              flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
