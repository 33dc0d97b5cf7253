"""Shared fixtures for tests that run real processes on a real Zenoh bus (loopback).

Every stack gets its own free TCP port and its own namespace, so stacks never see each other;
every process started is stopped at the end of its test (no orphans).
"""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
import uuid
from collections.abc import Callable, Hashable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"


# The modules that run whole explorations, heaviest first (seconds of their tests, measured
# with `python -m pytest --durations=60` on the 2-core machine, one worker): the suite runs on
# two xdist workers a module at a time (pyproject's addopts), and a heavy module that starts
# last leaves one worker alone at the end (e2e ~170 s, checkpoint ~75, bench_robust ~55,
# bench_explore ~45, record ~40, packaging ~35, foreign_driver ~25).
HEAVY_FIRST = ("test_explore_e2e", "test_checkpoint", "test_bench_robust", "test_bench_explore",
               "test_record", "test_packaging", "test_foreign_driver")


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Collect the heavy modules first (:data:`HEAVY_FIRST`), the rest in their own order."""
    def rank(item: pytest.Item) -> int:
        name = Path(str(item.fspath)).stem
        return HEAVY_FIRST.index(name) if name in HEAVY_FIRST else len(HEAVY_FIRST)

    items.sort(key=rank)  # stable: a module's tests keep their order


@pytest.fixture(autouse=True, scope="session")
def _own_cache_dir(tmp_path_factory) -> None:
    """Kept results (``bench oracle``'s tours) go to this session's own directory, not the
    user's cache; the processes the tests start inherit it."""
    os.environ["TOPOEXPLORE_CACHE_DIR"] = str(tmp_path_factory.mktemp("cache"))


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def endpoint() -> str:
    return f"tcp/127.0.0.1:{free_port()}"


@pytest.fixture
def namespace() -> str:
    return f"test{uuid.uuid4().hex[:10]}"


class Procs:
    """Processes started by a test; all killed (process group) at teardown."""

    def __init__(self) -> None:
        self.procs: list[subprocess.Popen] = []

    def start(self, args: list[str], **kw) -> subprocess.Popen:
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        kw.setdefault("stdout", subprocess.PIPE)
        kw.setdefault("stderr", subprocess.STDOUT)
        p = subprocess.Popen(args, env=env, cwd=REPO, start_new_session=True, text=True, **kw)
        self.procs.append(p)
        return p

    def python(self, *args: str, **kw) -> subprocess.Popen:
        return self.start([sys.executable, "-u", *args], **kw)

    def router(self, endpoint: str) -> subprocess.Popen:
        return self.python("-m", "topoexplore.tools.router", "--listen", endpoint)

    def cleanup(self) -> None:
        for p in self.procs:
            if p.poll() is None:
                try:
                    os.killpg(p.pid, signal.SIGTERM)
                except ProcessLookupError:
                    pass
        for p in self.procs:
            try:
                p.wait(timeout=5)
            except subprocess.TimeoutExpired:
                try:
                    os.killpg(p.pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
                p.wait(timeout=5)
            for f in (p.stdout, p.stderr):
                if f is not None:
                    f.close()


@pytest.fixture
def procs():
    ps = Procs()
    yield ps
    ps.cleanup()


def pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    # a zombie still answers kill(0); check its state
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(")")[-1].split()[0] != "Z"
    except OSError:
        return False


# --- slow independent work, started ahead two at a time -----------------------------------------


def needs(keys: Callable[..., list[Hashable]]):
    """Declares the slow work a test will wait for (see :func:`started_ahead`), as a function
    of the test's parameters that returns the work's keys."""

    def mark(fn):
        fn.needs = keys
        return fn

    return mark


@contextlib.contextmanager
def started_ahead(request, work: Callable[..., Any],
                  first: Callable[[tuple], bool] = lambda _key: False,
                  workers: int = 2) -> Iterator[dict[tuple, Future]]:
    """In a module fixture: runs ``work(*key)`` for the keys that this module's selected
    tests declare with :func:`needs`, ``workers`` at a time, those with ``first(key)`` true
    first; yields {key: future}. A lockstep run keeps about one core busy (the sim waits for
    each scan's command, so the stages take turns), so two of them share a 2-core machine."""
    keys: list[tuple] = []
    for item in request.session.items:
        declared = getattr(getattr(item, "function", None), "needs", None)
        if item.module is not request.module or declared is None:
            continue
        callspec = getattr(item, "callspec", None)
        keys += [k for k in declared(**(callspec.params if callspec else {})) if k not in keys]
    keys.sort(key=lambda k: not first(k))
    pool = ThreadPoolExecutor(workers)
    try:
        yield {k: pool.submit(work, *k) for k in keys}
    finally:
        pool.shutdown(cancel_futures=True)
