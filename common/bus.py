"""The bus: the one module in topoexplore that imports zenoh.

Everything else talks to Zenoh through :class:`Bus`:

- sessions from config: a router (``open_router``) or a client of a router (default), or any
  Zenoh JSON5 config file (``--zenoh-config``);
- publishers of typed messages with a chosen congestion control (BLOCK where loss is not
  acceptable, e.g. lockstep; DROP for conflated real-time data);
- subscribers that decode and validate every message (:func:`common.messages.decode`), count and
  log bad ones per key, and never let an exception vanish in a zenoh callback thread;
- liveliness tokens and liveliness watching; a state queryable per service; ``get``;
- clean close (always close: an open session with callbacks keeps the process alive).

See ../shared/ZENOH_NOTES.md for the measured facts behind these choices.
"""

from __future__ import annotations

import logging
import re
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import msgspec
import zenoh

from topoexplore.common import messages as m
from topoexplore.common.keys import DEFAULT_ENDPOINT

log = logging.getLogger("topoexplore.bus")

MSGPACK = "application/msgpack"


class BusError(RuntimeError):
    """The bus could not be opened or configured (bad endpoint, no router, bad config file)."""


def _endpoints(value: str | list[str] | None) -> list[str]:
    if value is None:
        return []
    if isinstance(value, str):
        return [v.strip() for v in value.split(",") if v.strip()]
    return list(value)


def check_config_file(path: str) -> None:
    """A Zenoh config file that exists and parses, else BusError naming it (checked before a
    stack starts, so that a typo is not reported later as a router that would not start)."""
    import os

    if not os.path.isfile(path):
        raise BusError(f"zenoh config file {path}: not found")
    try:
        zenoh.Config.from_file(path)
    except Exception as exc:  # ZError for a bad file; drop the Rust source location
        text = re.sub(r"\s+at \S+\.rs:\d+\.?$", "", str(exc).strip())
        raise BusError(f"zenoh config file {path}: {text}") from None


def make_config(
    mode: str = "client",
    connect: str | list[str] | None = DEFAULT_ENDPOINT,
    listen: str | list[str] | None = None,
    config_file: str | None = None,
    wait_for_router: bool = False,
    shared_memory: bool = False,
) -> zenoh.Config:
    """Build a Zenoh config. A config file, when given, is the base; mode, endpoints and
    ``shared_memory`` override it.

    zenoh's shared-memory transport (on by default in zenoh: payloads over 3 KB go through a
    16 MB pool per process, mapped by every process that reads from it) is off unless
    ``shared_memory``: here it saved about 3 % of the CPU of an office or large-office run
    and cost the stack 339 MB resident and 133 MB proportional memory on office
    (docs/benchmarks.md, "Memory"). Both ends of a link need it on (``bus.shared_memory``, for the services and
    the router alike); a link where one end has it off carries copies.
    """
    import json

    try:
        cfg = zenoh.Config.from_file(config_file) if config_file else zenoh.Config()
        if mode not in ("client", "router", "peer"):
            raise BusError(f"unknown zenoh mode {mode!r} (client, router or peer)")
        if not config_file or mode:
            cfg.insert_json5("mode", json.dumps(mode))
        if connect and mode != "router":
            cfg.insert_json5("connect/endpoints", json.dumps(_endpoints(connect)))
        if listen or mode == "router":
            cfg.insert_json5("listen/endpoints", json.dumps(_endpoints(listen or connect)))
        if mode == "router":
            cfg.insert_json5("scouting/delay", "0")
            cfg.insert_json5("scouting/multicast/enabled", "false")
        if wait_for_router and mode == "client":
            cfg.insert_json5("connect/timeout_ms", "-1")
        if mode == "client" and not config_file:
            # a client connects to named endpoints: it has no reason to answer multicast
            # scouting on every interface (it did: a Hello to anyone who asks)
            cfg.insert_json5("scouting/multicast/enabled", "false")
        cfg.insert_json5("transport/shared_memory/enabled", json.dumps(bool(shared_memory)))
        _apply_credentials(cfg, mode)
    except BusError:
        raise
    except Exception as exc:  # zenoh raises ZError for bad keys/values/files
        raise BusError(f"bad zenoh configuration: {exc}") from None
    return cfg


CREDENTIALS_ENV = "TOPOEXPLORE_ZENOH_CREDENTIALS"  # file: one line "user:password"
USERS_ENV = "TOPOEXPLORE_ZENOH_USERS"  # a router's user dictionary (lines "user:password")


def read_credentials(path: str) -> tuple[str, str]:
    """(user, password) from a file holding one line ``user:password``; BusError otherwise.
    Credentials come from files named by the environment, never from the command line."""
    try:
        text = open(path, encoding="utf-8").read().strip()
    except OSError as exc:
        raise BusError(f"{CREDENTIALS_ENV}: cannot read {path}: {exc.strerror or exc}") from None
    user, sep, password = text.partition(":")
    if not sep or not user or not password or "\n" in text:
        raise BusError(f"{CREDENTIALS_ENV}: {path} must hold one line user:password")
    return user, password


def _apply_credentials(cfg: zenoh.Config, mode: str) -> None:
    """usrpwd authentication from the environment: ``TOPOEXPLORE_ZENOH_CREDENTIALS`` (this
    process's user and password, for a client or a router that connects to another) and, for
    a router, ``TOPOEXPLORE_ZENOH_USERS`` (the users it accepts; else its config file's
    ``transport.auth.usrpwd.dictionary_file``)."""
    import json
    import os

    path = os.environ.get(CREDENTIALS_ENV)
    if path:
        user, password = read_credentials(path)
        cfg.insert_json5("transport/auth/usrpwd/user", json.dumps(user))
        cfg.insert_json5("transport/auth/usrpwd/password", json.dumps(password))
    users = os.environ.get(USERS_ENV)
    if users and mode == "router":
        if not os.path.isfile(users):
            raise BusError(f"{USERS_ENV}: no such file {users}")
        cfg.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(users))


_NUMBER = re.compile(r"-?\d+(\.\d+)?(e[-+]?\d+)?|\b(nan|inf)\b", re.IGNORECASE)
MAX_KINDS = 32  # kinds of error logged apart per key; beyond, the 5 s summary only


def error_kind(error: str) -> str:
    """An error message with its numbers masked: "3 ranges are not finite" and "5 ranges are
    not finite" are one kind."""
    return _NUMBER.sub("#", error)[:160]


@dataclass
class BadMessageCounter:
    """Counts bad messages per key and logs the first of each kind of error per key (then at
    most one line per key every 5 s): a flood of garbage is counted, not echoed."""

    counts: dict[str, int] = field(default_factory=dict)
    last_error: str = ""
    _last_log: dict[str, float] = field(default_factory=dict)
    _kinds: dict[str, set[str]] = field(default_factory=dict)
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def add(self, key: str, error: str) -> None:
        with self._lock:
            self.counts[key] = self.counts.get(key, 0) + 1
            self.last_error = f"{key}: {error}"
            now = time.monotonic()
            kinds = self._kinds.setdefault(key, set())
            kind = error_kind(error)
            if kind not in kinds and len(kinds) < MAX_KINDS:
                kinds.add(kind)
                self._last_log[key] = now
                log.warning("bad message #%d on %s: %s", self.counts[key], key, error)
            elif now - self._last_log.get(key, 0.0) > 5.0:
                self._last_log[key] = now
                log.warning("bad message #%d on %s (%d kinds so far): %s", self.counts[key],
                            key, len(kinds), error)

    @property
    def total(self) -> int:
        with self._lock:
            return sum(self.counts.values())

    def snapshot(self) -> tuple[dict[str, int], int, str]:
        """(counts per key, their total, the last error), read together: a state reply whose
        total counted messages its per-key counts did not yet show misled its reader."""
        with self._lock:
            return dict(self.counts), sum(self.counts.values()), self.last_error


class Publisher:
    """Publisher of one message type on one key."""

    def __init__(self, zpub: Any, key: str, msg_type: type | None):
        self._pub = zpub
        self.key = key
        self.msg_type = msg_type
        self.count = 0
        self._lock = threading.Lock()

    def put(self, msg: Any, attachment: bytes | None = None) -> None:
        """Publish a message struct (encoded to msgpack) or raw bytes (with an attachment,
        as rmw_zenoh's publications carry one)."""
        payload = msg if isinstance(msg, (bytes, bytearray)) else m.encode(msg)
        with self._lock:
            if attachment is None:
                self._pub.put(bytes(payload))
            else:
                self._pub.put(bytes(payload), attachment=bytes(attachment))
            self.count += 1

    @property
    def matched(self) -> bool:
        try:
            return bool(self._pub.matching_status.matching)
        except Exception:
            return False


class Bus:
    """A Zenoh session with typed publish/subscribe, liveliness and queryables."""

    def __init__(self, config: zenoh.Config, name: str = ""):
        self.name = name
        init_logging()
        try:
            self.session = zenoh.open(config)
        except Exception as exc:
            raise BusError(f"cannot open zenoh session: {exc}") from None
        self.bad = BadMessageCounter()
        self.callback_errors = 0
        self._decls: list[Any] = []
        self._closed = False
        self._lock = threading.Lock()

    # -- construction helpers -------------------------------------------------------------
    @classmethod
    def client(cls, connect: str = DEFAULT_ENDPOINT, name: str = "", config_file: str | None = None,
               wait_for_router: bool = False, shared_memory: bool = False) -> Bus:
        return cls(make_config("client", connect=connect, config_file=config_file,
                               wait_for_router=wait_for_router, shared_memory=shared_memory),
                   name)

    @classmethod
    def peer(cls, connect: str = DEFAULT_ENDPOINT, listen: str = "tcp/127.0.0.1:0",
             name: str = "", config_file: str | None = None,
             shared_memory: bool = False) -> Bus:
        """A peer session: it listens on ``listen`` (port 0: any free one), connects to the
        router at ``connect``, and links straight to the other peers the router names, so a
        message between two services takes one link instead of two (``bus.mode``)."""
        return cls(make_config("peer", connect=connect, listen=listen, config_file=config_file,
                               shared_memory=shared_memory), name)

    @classmethod
    def router(cls, listen: str = DEFAULT_ENDPOINT, name: str = "router",
               config_file: str | None = None, shared_memory: bool = False) -> Bus:
        return cls(make_config("router", connect=None, listen=listen, config_file=config_file,
                               shared_memory=shared_memory), name)

    def __enter__(self) -> Bus:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    # -- publish --------------------------------------------------------------------------
    def publisher(self, key: str, msg_type: type | None = None, reliable: bool = False,
                  encoding: str = MSGPACK) -> Publisher:
        """Declare a publisher. reliable=True -> congestion control BLOCK (no loss), else DROP."""
        cc = zenoh.CongestionControl.BLOCK if reliable else zenoh.CongestionControl.DROP
        zpub = self.session.declare_publisher(key, encoding=encoding, congestion_control=cc)
        self._decls.append(zpub)
        return Publisher(zpub, key, msg_type)

    # -- subscribe ------------------------------------------------------------------------
    def subscribe(self, key: str, msg_type: type, callback: Callable[[Any, str], None]) -> None:
        """Subscribe with decoding + validation. callback(msg, key) runs on a zenoh thread.

        Bad messages are counted per key and logged; exceptions in the callback are counted and
        logged too (zenoh would swallow them silently).
        """

        def on_sample(sample: Any) -> None:
            k = str(sample.key_expr)
            try:
                msg = m.decode(sample.payload.to_bytes(), msg_type)
            except m.MessageError as exc:
                self.bad.add(k, str(exc))
                return
            try:
                callback(msg, k)
            except Exception as exc:  # a service bug must not vanish
                self.callback_errors += 1
                log.exception("error handling message on %s: %s", k, exc)

        sub = self.session.declare_subscriber(key, on_sample)
        self._decls.append(sub)

    def subscribe_raw(self, key: str, callback: Callable[[str, bytes, str], None]) -> None:
        """Subscribe without decoding: callback(key, payload, encoding)."""

        def on_sample(sample: Any) -> None:
            try:
                callback(str(sample.key_expr), sample.payload.to_bytes(), str(sample.encoding))
            except Exception as exc:
                self.callback_errors += 1
                log.exception("error in raw subscriber on %s: %s", key, exc)

        self._decls.append(self.session.declare_subscriber(key, on_sample))

    # -- liveliness -----------------------------------------------------------------------
    def declare_token(self, key: str) -> None:
        self._decls.append(self.session.liveliness().declare_token(key))

    def watch_liveliness(self, key: str, callback: Callable[[str, bool], None],
                         history: bool = True) -> None:
        """callback(key, alive) for every token appearing (True) or disappearing (False)."""

        def on_sample(sample: Any) -> None:
            try:
                callback(str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT)
            except Exception as exc:
                log.exception("error in liveliness callback: %s", exc)

        self._decls.append(
            self.session.liveliness().declare_subscriber(key, on_sample, history=history)
        )

    def alive(self, key: str, timeout: float = 1.0) -> list[str]:
        """Keys of live tokens matching key (a liveliness query)."""
        out = []
        for reply in self.session.liveliness().get(key, timeout=timeout):
            if reply.ok is not None:
                out.append(str(reply.ok.key_expr))
        return sorted(out)

    # -- queryables -----------------------------------------------------------------------
    def queryable(self, key: str, handler: Callable[[str], Any]) -> None:
        """Answer queries on key with msgpack of handler(parameters) (a dict or a struct)."""

        def on_query(query: Any) -> None:
            try:
                params = str(query.parameters) if query.parameters is not None else ""
                value = handler(params)
                payload = value if isinstance(value, bytes) else msgspec.msgpack.encode(value)
                query.reply(key, payload, encoding=MSGPACK)  # our own key, not a wildcard
            except Exception as exc:
                log.exception("state query failed: %s", exc)
                try:
                    query.reply_err(f"{type(exc).__name__}: {exc}".encode())
                except Exception:
                    pass

        self._decls.append(self.session.declare_queryable(key, on_query))

    def get(self, selector: str, timeout: float = 2.0) -> list[tuple[str, bytes | None, str]]:
        """Query; returns [(key, payload or None, error text)]."""
        out = []
        for reply in self.session.get(selector, timeout=timeout):
            if reply.ok is not None:
                out.append((str(reply.ok.key_expr), reply.ok.payload.to_bytes(), ""))
            else:
                out.append(("", None, reply.err.payload.to_bytes().decode(errors="replace")))
        return out

    # -- info / close ---------------------------------------------------------------------
    def routers(self) -> list[str]:
        try:
            return [str(z) for z in self.session.info.routers_zid()]
        except Exception:
            return []

    def close(self) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
        try:
            self.session.close()
        except Exception as exc:  # closing twice or after a router loss
            log.debug("close: %s", exc)

    @property
    def closed(self) -> bool:
        return self._closed


_LOG_INIT = False


def init_logging() -> None:
    """Zenoh's own (Rust) logging: off unless asked with RUST_LOG (e.g. RUST_LOG=zenoh=warn).

    It writes to stdout, and at session close it reports benign races ("Received Data for
    unknown expr_id") as errors, which would corrupt the output of our tools.
    """
    global _LOG_INIT
    if _LOG_INIT:
        return
    _LOG_INIT = True
    try:
        zenoh.init_log_from_env_or("off")
    except Exception:
        pass
