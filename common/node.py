"""Runtime shared by every service process (the thin shells): command line, bus, inbox, signals.

A service shell builds a :class:`Node`, subscribes its inputs into the node's :class:`Inbox`,
then runs one worker loop on the main thread: wait for the next input, call the pure core,
publish. Zenoh callbacks only decode, validate and deposit messages, so no algorithm runs on a
zenoh thread and a slow stage conflates (real-time) or queues (lockstep) its input.

Lockstep: every stage stamps its outputs with the ``src_seq`` and ``stamp`` of the scan they
derive from, processes its primary input in order, and waits until its secondary inputs have
caught up with that ``src_seq``; the simulator advances only after the controller answered.
"""

from __future__ import annotations

import argparse
import bisect
import gc
import heapq
import logging
import math
import os
import random
import signal
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from typing import Any
from urllib.parse import unquote

import msgspec

from topoexplore.common import convert
from topoexplore.common import messages as m
from topoexplore.common.bus import Bus, BusError, Publisher, init_logging
from topoexplore.common.domain import Pose, compose
from topoexplore.common.keys import DEFAULT_ENDPOINT, TOPICS, Keys
from topoexplore.common.params import (
    ParamError,
    Params,
    RuntimeParams,
    load_params,
    params_to_dict,
    with_override,
)
from topoexplore.common.warm import compile_kernels

log = logging.getLogger("topoexplore")
# every service's log line: wall-clock time to the millisecond, level, logger, message
LOG_FORMAT = "%(asctime)s.%(msecs)03d %(levelname)s %(name)s: %(message)s"
LOG_DATEFMT = "%Y-%m-%dT%H:%M:%S"
LOG_LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR")
# fault injection on a service's inputs, settable while it runs (``keys set``, bench faults)
CHAOS_LIVE = ("runtime.chaos_topics", "runtime.chaos_drop", "runtime.chaos_delay",
              "runtime.chaos_seed")


# --- pure helpers (unit-tested without a bus) ------------------------------------------------


class OdomBuffer:
    """Recent odometry poses by stamp; ``pose_at(t)`` interpolates (pure, thread-safe).

    ``corrected``: the localizer runs, and every pose is odometry's composed with the
    ``map`` -> ``odom`` correction in force at its stamp (the newest one stamped at or
    before it); ``newest`` is then the newest stamp that both odometry and a correction
    cover, so a service waiting for odometry at a scan's stamp also waits for that scan's
    correction."""

    def __init__(self, horizon: float = 5.0, corrected: bool = False):
        self.horizon = horizon  # [s] history kept
        self.corrected = corrected
        self._t: list[float] = []
        self._p: list[Pose] = []
        self._ct: list[float] = []  # stamps of the corrections
        self._cp: list[Pose] = []  # map -> odom
        self._seq: int | None = None
        self._lock = threading.Lock()

    def add_correction(self, stamp: float, correction: Pose) -> None:
        with self._lock:
            if self._ct and stamp < self._ct[-1] - self.horizon:  # the clock went back
                self._ct.clear()
                self._cp.clear()
            i = bisect.bisect_right(self._ct, stamp)
            self._ct.insert(i, stamp)
            self._cp.insert(i, correction)
            cut = bisect.bisect_left(self._ct, self._ct[-1] - self.horizon)
            if cut > 0:
                del self._ct[:cut]
                del self._cp[:cut]

    def _correct(self, stamp: float, pose: Pose) -> Pose:
        """Odometry's pose at stamp on the map (under the lock)."""
        if not self._ct:
            return pose
        i = bisect.bisect_right(self._ct, stamp + 1e-6) - 1
        return compose(self._cp[max(i, 0)], pose)

    def add(self, stamp: float, pose: Pose, seq: int | None = None) -> None:
        """One pose. ``seq`` (the message's header.seq) going back means the publisher
        restarted: its clock may have gone back a little too (a simulator resumed from its
        checkpoint), so the history of the one before is dropped, not mixed in."""
        with self._lock:
            if seq is not None:
                if self._seq is not None and seq < self._seq:
                    self._t.clear()
                    self._p.clear()
                self._seq = seq
            if self._t and stamp < self._t[-1]:
                if stamp < self._t[-1] - self.horizon:  # clock went back (sim restarted)
                    self._t.clear()
                    self._p.clear()
                else:
                    i = bisect.bisect_right(self._t, stamp)
                    self._t.insert(i, stamp)
                    self._p.insert(i, pose)
                    return
            self._t.append(stamp)
            self._p.append(pose)
            cut = bisect.bisect_left(self._t, stamp - self.horizon)
            if cut > 0:
                del self._t[:cut]
                del self._p[:cut]

    @property
    def newest(self) -> float:
        with self._lock:
            t = self._t[-1] if self._t else -math.inf
            if self.corrected:
                t = min(t, self._ct[-1] if self._ct else -math.inf)
            return t

    def latest(self) -> tuple[float, Pose] | None:
        with self._lock:
            return (self._t[-1], self._correct(self._t[-1], self._p[-1])) if self._t else None

    def pose_near(self, stamp: float) -> Pose | None:
        """Pose at stamp if covered, else the newest pose (real time: a late or old input);
        None only when no odometry has arrived."""
        pose = self.pose_at(stamp)
        if pose is None:
            newest = self.latest()
            pose = newest[1] if newest is not None else None
        return pose

    def pose_at(self, stamp: float, tolerance: float = 1e-6) -> Pose | None:
        """Pose at stamp (linear interpolation, angle-aware); None if not covered yet."""
        with self._lock:
            if not self._t or stamp > self._t[-1] + tolerance or stamp < self._t[0] - tolerance:
                return None
            i = bisect.bisect_left(self._t, stamp - tolerance)
            if i < len(self._t) and abs(self._t[i] - stamp) <= tolerance:
                return self._correct(stamp, self._p[i])
            if i == 0:
                return self._correct(stamp, self._p[0])
            t0, t1 = self._t[i - 1], self._t[i]
            p0, p1 = self._p[i - 1], self._p[i]
            a = (stamp - t0) / (t1 - t0) if t1 > t0 else 1.0
            dth = math.atan2(math.sin(p1[2] - p0[2]), math.cos(p1[2] - p0[2]))
            return self._correct(stamp, Pose(p0[0] + a * (p1[0] - p0[0]),
                                             p0[1] + a * (p1[1] - p0[1]), p0[2] + a * dth))


class Inbox:
    """Latest message per topic, plus an ordered queue for the primary input.

    In real-time mode the primary queue holds one message (conflation: keep the newest); in
    lockstep it keeps every message so none is skipped, and the last few messages of every
    other topic by the scan they came from (:meth:`at`): with ``runtime.plan_lag`` the stages
    of one map work while newer maps arrive.
    """

    def __init__(self) -> None:
        self.cv = threading.Condition()
        self.latest: dict[str, Any] = {}
        self.received: dict[str, int] = {}
        self._queues: dict[str, deque] = {}
        self.dropped: dict[str, int] = {}  # conflated: a newer message replaced it unread
        self.seqs = m.SeqGaps()  # lost on the way (by header.seq), publisher restarts
        self._history: dict[str, dict[int, Any]] = {}  # topic -> src_seq -> message
        self._keep: dict[str, int] = {}

    def make_queue(self, topic: str, maxlen: int) -> None:
        with self.cv:
            self._queues[topic] = deque(maxlen=maxlen)

    def keep_history(self, topic: str, keep: int) -> None:
        """Keep the last ``keep`` messages of topic by their ``header.src_seq``."""
        with self.cv:
            self._history[topic], self._keep[topic] = {}, keep

    def at(self, topic: str, k: int) -> Any:
        """The message of topic that came from scan k, else from the newest scan before k
        that is kept; the latest message where none is (no history kept, or a restarted
        service that did not see that scan's)."""
        with self.cv:
            older = [s for s in self._history.get(topic, ()) if s <= k]
            return self._history[topic][max(older)] if older else self.latest.get(topic)

    def put(self, topic: str, msg: Any) -> None:
        with self.cv:
            self.latest[topic] = msg
            self.received[topic] = self.received.get(topic, 0) + 1
            hdr = getattr(msg, "header", None)
            if hdr is not None and hdr.seq >= 0:  # -1: a publisher that does not count
                self.seqs.check(topic, hdr.seq)
            hist = self._history.get(topic)
            if hist is not None and hdr is not None:
                hist[hdr.src_seq] = msg
                while len(hist) > self._keep[topic]:
                    del hist[min(hist)]
            q = self._queues.get(topic)
            if q is not None:
                if q.maxlen is not None and len(q) == q.maxlen:
                    self.dropped[topic] = self.dropped.get(topic, 0) + 1
                q.append(msg)
            self.cv.notify_all()

    def seq_counts(self) -> dict[str, Any]:
        with self.cv:
            return {"lost": dict(self.seqs.gaps), "lost_total": self.seqs.total,
                    "publisher_restarts": dict(self.seqs.restarts)}

    def notify(self) -> None:
        with self.cv:
            self.cv.notify_all()

    def pending(self, topic: str) -> int:
        with self.cv:
            return len(self._queues.get(topic, ()))

    def peek(self, topic: str) -> Any:
        with self.cv:
            q = self._queues.get(topic)
            return q[0] if q else None

    def pop(self, topic: str) -> Any:
        with self.cv:
            q = self._queues.get(topic)
            return q.popleft() if q else None

    def wait(self, predicate: Callable[[], bool], timeout: float) -> bool:
        with self.cv:
            return self.cv.wait_for(predicate, timeout)

    def src_seq(self, topic: str) -> int:
        msg = self.latest.get(topic)
        return msg.header.src_seq if msg is not None else -2


class Chaos:
    """Fault injection on a service's inputs (``runtime.chaos_*``, ``bench faults``): drops
    a share of the incoming messages of chosen topics (seeded) and holds the others back for
    a delay, in their order, on a thread of its own. A dropped message is never delivered,
    so the service counts it as lost by seq like any loss on the way."""

    def __init__(self, rt: RuntimeParams):
        self.dropped: dict[str, int] = {}
        self.delayed: dict[str, int] = {}
        self._cv = threading.Condition()
        self._heap: list[tuple[float, int, Callable[[], None]]] = []
        self._n = 0
        self._thread: threading.Thread | None = None
        self._closed = False
        self.configure(rt)

    def configure(self, rt: RuntimeParams) -> None:
        with self._cv:
            self.topics = frozenset(rt.chaos_topics)
            self.drop, self.delay = rt.chaos_drop, rt.chaos_delay
            self._rng = random.Random(rt.chaos_seed)
        if self.topics:
            log.warning("chaos on %s: drop %.0f %%, delay %.3f s", ",".join(sorted(self.topics)),
                        100 * self.drop, self.delay)
        elif self.dropped or self.delayed:
            log.warning("chaos off")

    def admit(self, topic: str, deliver: Callable[[], None]) -> None:
        """Deliver now, later or never."""
        if topic not in self.topics:
            deliver()
            return
        with self._cv:
            if self._rng.random() < self.drop:
                self.dropped[topic] = self.dropped.get(topic, 0) + 1
                return
            if self.delay <= 0.0:
                now = True
            else:
                now = False
                self.delayed[topic] = self.delayed.get(topic, 0) + 1
                self._n += 1
                heapq.heappush(self._heap, (time.monotonic() + self.delay, self._n, deliver))
                if self._thread is None:
                    self._thread = threading.Thread(target=self._loop, name="chaos", daemon=True)
                    self._thread.start()
                self._cv.notify()
        if now:
            deliver()

    def _loop(self) -> None:
        while True:
            with self._cv:
                while not self._closed and (
                        not self._heap or self._heap[0][0] > time.monotonic()):
                    self._cv.wait(self._heap[0][0] - time.monotonic() if self._heap else None)
                if self._closed:
                    return
                deliver = heapq.heappop(self._heap)[2]
            deliver()

    def counts(self) -> dict[str, Any]:
        with self._cv:
            return {"chaos": {"topics": sorted(self.topics), "dropped": dict(self.dropped),
                              "delayed": dict(self.delayed)}} if (
                self.topics or self.dropped or self.delayed) else {}

    def close(self) -> None:
        with self._cv:
            self._closed = True
            self._cv.notify_all()


# --- the node ----------------------------------------------------------------------------------


def add_bus_args(p: argparse.ArgumentParser) -> None:
    """Command-line options shared by every process (zenoh-python examples style)."""
    g = p.add_argument_group("bus")
    g.add_argument("--connect", "-e", default=None,
                   help=f"router endpoint(s), comma separated (default {DEFAULT_ENDPOINT})")
    g.add_argument("--zenoh-config", default=None, help="Zenoh JSON5 config file (base config)")
    g.add_argument("--namespace", default=None, help="key namespace (default topoexplore)")
    g.add_argument("--robot", default=None, help="robot name (default robot1)")


def add_param_args(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("parameters")
    g.add_argument("--params", default=None, help="TOML parameter file ([sim], [mapper], ...)")
    g.add_argument("--set", action="append", default=[], metavar="SECTION.NAME=VALUE",
                   help="override one parameter (repeatable)")


def params_from_args(args: argparse.Namespace) -> Params:
    overrides = list(getattr(args, "set", []) or [])
    if getattr(args, "namespace", None):
        overrides.append(f'bus.namespace="{args.namespace}"')
    if getattr(args, "robot", None):
        overrides.append(f'bus.robot="{args.robot}"')
    if getattr(args, "connect", None):
        overrides.append(f'bus.connect="{args.connect}"')
    return load_params(getattr(args, "params", None), overrides)


class Node:
    """One service process: bus session, keys, inbox, counters, state queryable, liveliness."""

    def __init__(self, service: str, params: Params, zenoh_config: str | None = None):
        self.service = service
        self.params = params
        self.lockstep = params.runtime.lockstep
        self.keys = Keys(params.bus.namespace, params.bus.robot)
        self.stop = threading.Event()
        self.inbox = Inbox()
        self.started = time.monotonic()
        self.published: dict[str, int] = {}
        self.processed = 0
        self.errors = 0
        self._state_fns: list[Callable[[], dict]] = []
        self._live: set[str] = set()  # section.name that may change while running
        self._apply_live: list[Callable[[Params], None]] = []
        self._pending_params: Params | None = None
        self._live_lock = threading.Lock()
        bp = params.bus
        if bp.mode == "peer":
            self.bus = Bus.peer(bp.connect, bp.listen, name=service, config_file=zenoh_config,
                                shared_memory=bp.shared_memory)
        else:
            self.bus = Bus.client(bp.connect, name=service, config_file=zenoh_config,
                                  wait_for_router=True, shared_memory=bp.shared_memory)
        self._seq: dict[str, int] = {}
        self.chaos = Chaos(params.runtime)
        self.add_live(CHAOS_LIVE, lambda p: self.chaos.configure(p.runtime))

    # -- wiring ---------------------------------------------------------------------------
    def publisher(self, topic: str, reliable: bool | None = None) -> Publisher:
        """reliable defaults to lockstep (BLOCK, no loss) vs real-time (DROP, conflate)."""
        return self.bus.publisher(self.keys.topic(topic), TOPICS[topic],
                                  self.lockstep if reliable is None else reliable)

    def subscribe(self, topic: str, queue: bool = False,
                  on_msg: Callable[[Any], None] | None = None) -> None:
        """Deposit decoded messages of a topic into the inbox (and/or call on_msg)."""
        if queue:
            self.inbox.make_queue(topic, 10_000 if self.lockstep else 1)
        elif self.lockstep:
            self.inbox.keep_history(topic, 2 * self.params.runtime.plan_lag + 4)

        def deliver(msg: Any) -> None:
            if on_msg is not None:
                on_msg(msg)
            self.inbox.put(topic, msg)

        def cb(msg: Any, key: str) -> None:
            self.chaos.admit(topic, lambda: deliver(msg))

        self.bus.subscribe(self.keys.topic(topic), TOPICS[topic], cb)

    def subscribe_odom(self, buffer: OdomBuffer,
                       then: Callable[[m.Odometry], None] | None = None) -> None:
        """Odometry into the buffer (then ``then(msg)`` on the receive thread), and, for a
        corrected buffer, the localizer's map -> odom corrections."""

        def on_odom(o: m.Odometry) -> None:
            buffer.add(o.header.time, convert.pose_from_msg(o.pose.pose), o.header.seq)
            if then is not None:
                then(o)

        self.subscribe("odom", on_msg=on_odom)
        if buffer.corrected:
            self.subscribe("map_odom", on_msg=lambda c: buffer.add_correction(
                c.header.time, convert.correction_from_msg(c)))

    def header(self, topic: str, stamp: float, src_seq: int, frame: str = "map") -> m.Header:
        """The next header of ``topic``, stamped ``stamp`` [s], in ``frame`` (its frame_id)."""
        seq = self._seq.get(topic, 0)
        self._seq[topic] = seq + 1
        return m.header(seq, stamp, frame, src_seq)

    def take(self, topic: str, ready: Callable[[Any], bool] | None = None,
             poll: float = 0.2, share: float = 1.0) -> tuple[Any, bool] | None:
        """Next message of a queued topic, once ready(msg) holds (secondary inputs caught up).

        Returns None when nothing arrived within ``poll`` seconds, else (msg, ready_ok): ready_ok
        is False when the secondaries did not catch up within the wait limit (lockstep:
        ``sim.lockstep_timeout``; real-time: 0.5 s; times ``share``, for a service whose
        output another waits for under the same limit) — the caller decides whether to skip.
        """
        inbox = self.inbox
        if not inbox.wait(lambda: self.stop.is_set() or inbox.pending(topic) > 0, poll):
            return None
        msg = inbox.pop(topic)
        if msg is None:
            return None
        if ready is None:
            return msg, True
        limit = share * (self.params.runtime.lockstep_timeout if self.lockstep else 0.5)
        ok = inbox.wait(lambda: self.stop.is_set() or ready(msg), limit)
        return msg, ok and not self.stop.is_set()

    def add_state(self, fn: Callable[[], dict]) -> None:
        self._state_fns.append(fn)

    def serve_latest(self, topic: str) -> None:
        """Answer ``<prefix>/<service>/latest/<topic>`` with the last message of a subscribed
        topic (empty before the first): a restarted publisher takes its last output back
        from a peer (the mapper its map)."""

        def answer(_params: str) -> bytes:
            msg = self.inbox.latest.get(topic)
            return m.encode(msg) if msg is not None else b""

        self.bus.queryable(self.keys.latest(self.service, topic), answer)

    def latest_from_peers(self, topic: str, timeout: float = 1.0) -> Any:
        """The newest (highest ``header.src_seq``) valid message of ``topic`` that any peer's
        :meth:`serve_latest` holds, or None."""
        best = None
        for _key, payload, _err in self.bus.get(f"{self.keys.prefix}/*/latest/{topic}",
                                                timeout=timeout):
            if not payload:
                continue
            try:
                msg = m.decode(payload, TOPICS[topic])
            except m.MessageError as exc:
                log.warning("a peer's latest %s is not valid: %s", topic, exc)
                continue
            if best is None or msg.header.src_seq > best.header.src_seq:
                best = msg
        return best

    def add_live(self, names: Sequence[str], apply: Callable[[Params], None]) -> None:
        """Parameters (``section.name``) this service can change while it runs, and the
        function that hands new parameters to its core. ``apply`` runs on the worker thread
        between two steps, never during one."""
        self._live |= set(names)
        self._apply_live.append(apply)

    def params_query(self, parameters: str = "") -> dict:
        """The ``params`` queryable: ``set=<section.name=value>`` (URL-quoted) checks the value
        as at start-up and, if the parameter can change live, queues it for the worker; the
        answer holds the old and new value or an error. Without ``set``: what can change."""
        wanted = ""
        for pair in parameters.split(";"):
            k, _, v = pair.partition("=")
            if k.strip() == "set":
                wanted = unquote(v)
        if not wanted:
            return {"service": self.service, "live": sorted(self._live)}
        try:
            with self._live_lock:
                base = self._pending_params or self.params
                new, name = with_override(base, wanted)
        except (ParamError, ValueError) as exc:
            return {"error": str(exc)}
        if name not in self._live:
            live = ", ".join(sorted(self._live)) or "none"
            return {"error": f"{name} cannot change while {self.service} runs (restart it with "
                             f"--set {name}=...; live here: {live})"}
        section, field = name.split(".")
        old = getattr(getattr(base, section), field)
        with self._live_lock:
            self._pending_params = new
        self.inbox.notify()
        log.info("%s: %s %r -> %r (live)", self.service, name, old,
                 getattr(getattr(new, section), field))
        return {"service": self.service, "name": name, "old": msgspec.to_builtins(old),
                "new": msgspec.to_builtins(getattr(getattr(new, section), field))}

    def apply_pending(self) -> None:
        """Worker thread, between steps: hand queued live parameters to the core."""
        with self._live_lock:
            new, self._pending_params = self._pending_params, None
        if new is None:
            return
        for apply in self._apply_live:
            apply(new)
        self.params = new

    def state(self, parameters: str = "") -> dict:
        bad, bad_total, last_bad = self.bus.bad.snapshot()
        out: dict[str, Any] = {
            "service": self.service,
            "pid": os.getpid(),
            "uptime_s": round(time.monotonic() - self.started, 3),
            "mode": "lockstep" if self.lockstep else "realtime",
            "processed": self.processed,
            "errors": self.errors,
            "bad_messages": bad,
            "bad_messages_total": bad_total,
            "last_bad_message": last_bad,
            "callback_errors": self.bus.callback_errors,
            "received": dict(self.inbox.received),
            "dropped": dict(self.inbox.dropped),
            # messages that never arrived, by header.seq (congestion drops, a link down, a
            # payload the transport refused), and publishers seen restarting
            **self.inbox.seq_counts(),
            **self.chaos.counts(),
            "params": params_to_dict(self.params),
        }
        for fn in self._state_fns:
            out.update(fn())
        return out

    def ready(self) -> None:
        """Declare the state queryable and the liveliness token: the service is up."""
        self.bus.queryable(self.keys.state(self.service), self.state)
        self.bus.queryable(self.keys.params(self.service), self.params_query)
        self.bus.declare_token(self.keys.alive(self.service))
        log.info("%s ready on %s (%s, %s)", self.service, self.keys.prefix,
                 "lockstep" if self.lockstep else "real-time",
                 "peer" if self.params.bus.mode == "peer" else "client")

    def close(self) -> None:
        self.stop.set()
        self.inbox.notify()
        self.chaos.close()
        self.bus.close()


def stop_on_signals(*actions: Callable[[], None],
                    signals: tuple[int, ...] = (signal.SIGINT, signal.SIGTERM)) -> Callable[[], None]:
    """On SIGINT / SIGTERM run ``actions`` (e.g. ``event.set``) on a helper thread, never in
    the signal handler. A handler that sets a threading.Event takes the Event's lock; the main
    thread may hold that very lock when the signal lands (inside ``Event.wait``), or the
    first handler may hold it when a second signal lands (systemd's SIGTERM, then the
    supervisor's): a deadlock. Here the C-level handler only writes the signal number to a
    pipe (``signal.set_wakeup_fd``), and the thread reading it runs the actions.

    Main thread only. Returns a function that restores the previous handlers."""
    r, w = os.pipe()
    os.set_blocking(w, False)
    old_fd = signal.set_wakeup_fd(w, warn_on_full_buffer=False)
    old = {sig: signal.signal(sig, _ignore_here) for sig in signals}
    wanted = set(signals)

    def watch() -> None:
        while True:
            try:
                data = os.read(r, 64)
            except OSError:
                data = b""
            if not data:  # restore() closed the write end
                os.close(r)
                return
            if wanted & set(data):
                for act in actions:
                    act()

    threading.Thread(target=watch, name="signals", daemon=True).start()

    def restore() -> None:
        for sig, handler in old.items():
            signal.signal(sig, handler)
        signal.set_wakeup_fd(old_fd)
        os.close(w)  # the watcher's read returns b"" and it ends

    return restore


def ignore_further_signals(signals: tuple[int, ...] = (signal.SIGINT, signal.SIGTERM)) -> None:
    """The process is stopping: later SIGINT / SIGTERM (systemd's and the supervisor's, sent
    back to back) have nothing left to do. Python's finalization puts a Python-level handler
    back to the default, so a signal landing while the process exits killed it (exit -2
    instead of 0, seen in CI); SIG_IGN is left alone. Main thread only."""
    for sig in signals:
        signal.signal(sig, signal.SIG_IGN)


def _ignore_here(signum: int, frame: Any) -> None:
    """The Python-level handler: nothing (the wakeup pipe carries the signal)."""


def _install_signals(node_stop: threading.Event, inbox: Inbox) -> None:
    stop_on_signals(node_stop.set, inbox.notify)


def run_service(service: str, build: Callable[[Node], Callable[[], None]],
                argv: list[str] | None = None, description: str = "",
                kernels: Sequence[str] = ()) -> int:
    """Parse the shared command line, open the node, run build(node)() until stopped.

    build(node) wires subscriptions/publishers and returns ``step``: one iteration of the
    worker loop (it should wait on the inbox with a short timeout). ``kernels``: modules whose
    numba kernels the core runs (its ``WARM_MODULES``; a core that runs none loads no LLVM,
    about 60 MB); they are compiled, or loaded from the on-disk cache, before the node
    declares itself up, so no input waits on a compiler.
    Errors in the command line, parameters or bus -> one line on stderr and exit code 2.
    """
    parser = argparse.ArgumentParser(prog=f"topoexplore-{service}", description=description)
    add_bus_args(parser)
    add_param_args(parser)
    parser.add_argument("--log-level", default="INFO", choices=LOG_LEVELS)
    args = parser.parse_args(argv)
    logging.basicConfig(level=getattr(logging, args.log_level), stream=sys.stderr,
                        format=LOG_FORMAT, datefmt=LOG_DATEFMT)
    init_logging()
    sys.setswitchinterval(0.0005)  # ZENOH_NOTES: shorter GIL hand-off for callback threads
    try:
        params = params_from_args(args)
    except ParamError as exc:
        print(f"topoexplore-{service}: {exc}", file=sys.stderr)
        return 2
    try:
        node = Node(service, params, zenoh_config=args.zenoh_config)
    except BusError as exc:
        print(f"topoexplore-{service}: {exc}", file=sys.stderr)
        return 2
    _install_signals(node.stop, node.inbox)
    try:
        step = build(node)
        if kernels:
            log.info("%s: %s", service, compile_kernels(kernels).line())
        gc.collect()
        gc.freeze()  # start-up objects out of the collector: shorter GC pauses per update
        node.ready()
        while not node.stop.is_set():
            try:
                node.apply_pending()
                step()
            except Exception as exc:  # keep running: count, log, go on
                node.errors += 1
                log.exception("%s: error in step: %s", service, exc)
                time.sleep(0.05)
    finally:
        ignore_further_signals()
        node.close()
    log.info("%s stopped", service)
    return 0
