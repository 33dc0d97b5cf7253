"""Zenoh key inspection tools: ``topoexplore keys list|echo|hz|get``.

Like ``ros2 topic list/echo/hz/bw`` and ``ros2 service call`` for our key space
(``<ns>/<robot>/<topic>``, liveliness tokens ``<ns>/<robot>/alive/<service>``, state queryables
``<ns>/<robot>/<service>/state``; see :mod:`common.keys`). Every message is decoded with the strict
validation of :func:`common.messages.decode`, so a bad payload is reported, never silently shown.

- ``keys list [--duration S] [--all-robots] [--json]``: live services, their state queryables and
  every key seen during the window with type, rate, last size and bad-message count.
- ``keys echo KEY [--once|--count N] [--field a.b] [--full] [--json] [--timeout S]``.
- ``keys hz KEY [--window N] [--duration S]``: rate, period jitter, bandwidth and size.
- ``keys get SERVICE [--field a.b] [--full] [--json] [--timeout S]``: a service's state.
- ``keys pub KEY FIELD=VALUE... [--rate HZ] [--count N] [--duration S]``: publish a message.
- ``keys set SERVICE [section.name=VALUE]``: change a live parameter (:mod:`tools.keypub`).

Exit codes: 0 success (also Ctrl-C in echo/hz, their normal way to stop); 1 nothing received /
no reply; 2 bad argument, bad key or field, no router; 130 Ctrl-C during list/get.

The formatting helpers (:func:`resolve_key`, :func:`summarize`, :func:`select_fields`,
:func:`format_yaml`, :func:`to_jsonable`, :class:`RateStats`, ...) are pure functions with no bus
and no clock, unit-tested in tests/test_keytools.py. This module never imports zenoh: it talks to
the bus through :class:`common.bus.Bus`.
"""

from __future__ import annotations

import argparse
import base64
import json
import math
import os
import re
import signal
import sys
import threading
import time
from collections import deque
from typing import Any

import msgspec
import numpy as np
import yaml

from topoexplore.common import messages as m
from topoexplore.common.bus import Bus, BusError, init_logging
from topoexplore.common.keys import (
    DEFAULT_ENDPOINT,
    DEFAULT_NAMESPACE,
    DEFAULT_ROBOT,
    SERVICES,
    TOPICS,
    Keys,
    type_for_key,
)

PROG = "topoexplore keys"

# Grid cell classes for the bytes summary of OccupancyGrid.data (same thresholds as
# common.grid.classify defaults): free 0 <= v < 35, occupied v > 65, -1 unknown.
GRID_FREE_BELOW = 35
GRID_OCC_ABOVE = 65

# First key segments that mean "relative to <ns>/<robot>" (topics, services, liveliness).
_RELATIVE_HEADS = frozenset({t.split("/")[0] for t in TOPICS} | set(SERVICES) | {"alive"})
_KEY_CHARS = re.compile(r"^[^#?$\s]+$")


class KeyToolError(ValueError):
    """Bad input to a key tool helper (bad key expression, bad field path, bad value)."""


class FieldError(KeyToolError):
    """A --field path does not exist in the message."""


class Summary(str):
    """A summary of a large value (printed unquoted in YAML, as a string in JSON)."""


# --- keys --------------------------------------------------------------------------------------


def is_wildcard(key: str) -> bool:
    """True if a key expression contains a wildcard chunk (``*`` or ``**``)."""
    return "*" in key


def check_keyexpr(key: str) -> str:
    """Validate a Zenoh key expression (the subset we accept); raise KeyToolError."""
    if not key or key.startswith("/") or key.endswith("/") or "//" in key:
        raise KeyToolError(f"bad key expression {key!r}: empty chunk or leading/trailing '/'")
    if not _KEY_CHARS.match(key):
        raise KeyToolError(f"bad key expression {key!r}: '#', '?', '$' and spaces are not allowed")
    for chunk in key.split("/"):
        if "*" in chunk and chunk not in ("*", "**"):
            raise KeyToolError(f"bad key expression {key!r}: use '*' or '**' as a whole chunk")
    return key


def resolve_key(arg: str, keys: Keys) -> str:
    """A command-line KEY -> full key expression.

    Relative to ``<ns>/<robot>`` when it starts like one of our topics, services or ``alive``
    (``scan``, ``explore/status``, ``mapper/state``, ``alive/*``); a leading ``/`` forces a full
    key (``/other/robot2/scan``); anything else (``topoexplore/**``, ``**/scan``) is taken as a
    full key expression.
    """
    if not isinstance(arg, str) or not arg.strip():
        raise KeyToolError("empty key")
    arg = arg.strip()
    if arg.startswith("/"):
        return check_keyexpr(arg[1:])
    if arg.split("/")[0] in _RELATIVE_HEADS:
        return check_keyexpr(f"{keys.prefix}/{arg}")
    return check_keyexpr(arg)


def state_selector(service: str, keys: Keys) -> str:
    """``keys get`` argument -> selector: a plain service name means ``<prefix>/<svc>/state``."""
    if not service or not service.strip():
        raise KeyToolError("empty service name")
    service = service.strip()
    if "/" not in service and not is_wildcard(service):
        return check_keyexpr(keys.state(service))
    return resolve_key(service, keys)


def short_key(key: str, prefix: str) -> str:
    """Key relative to prefix (for display), or the key itself."""
    return key[len(prefix) + 1:] if key.startswith(prefix + "/") else key


# --- decoding ----------------------------------------------------------------------------------


def decode_payload(key: str, raw: bytes) -> tuple[Any, str]:
    """Decode a payload with the message type of its key -> (plain value, type name).

    Known keys are decoded and validated strictly (:func:`common.messages.decode`); unknown keys
    are decoded as plain msgpack (type ``"?"``). Raises MessageError on any problem.
    """
    msg_type = type_for_key(key)
    if msg_type is not None:
        return to_plain(m.decode(raw, msg_type)), msg_type.__name__
    try:
        return msgspec.msgpack.decode(raw), "?"
    except (msgspec.DecodeError, msgspec.ValidationError) as exc:
        raise m.MessageError(f"not msgpack: {exc}") from None


def to_plain(msg: Any) -> Any:
    """A message struct -> nested dicts/lists (bytes kept as bytes)."""
    return msgspec.to_builtins(msg, builtin_types=(bytes, bytearray))


# --- summaries and field selection ---------------------------------------------------------


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _fmt_num(v: float) -> str:
    return f"{v:.4g}"


def summarize_numbers(values: list) -> Summary:
    """``<181 floats: min 0.1, max 10, mean 3.2>`` (non-finite values counted apart)."""
    a = np.asarray(values, dtype=np.float64)
    kind = "ints" if all(isinstance(v, int) for v in values) else "floats"
    fin = a[np.isfinite(a)]
    parts = []
    if fin.size:
        parts.append(f"min {_fmt_num(fin.min())}, max {_fmt_num(fin.max())}, "
                     f"mean {_fmt_num(fin.mean())}")
    if fin.size < a.size:
        parts.append(f"{a.size - fin.size} non-finite")
    return Summary(f"<{a.size} {kind}: {', '.join(parts)}>")


def summarize_points(values: list) -> Summary:
    """``<N points: first [x, y], last [x, y], x a..b, y c..d>`` for polylines."""
    a = np.asarray(values, dtype=np.float64)
    first = ", ".join(_fmt_num(v) for v in a[0])
    last = ", ".join(_fmt_num(v) for v in a[-1])
    ranges = ", ".join(
        f"{'xyz'[i]} {_fmt_num(np.nanmin(a[:, i]))}..{_fmt_num(np.nanmax(a[:, i]))}"
        for i in range(a.shape[1])
    )
    return Summary(f"<{len(a)} points: first [{first}], last [{last}], {ranges}>")


def summarize_bytes(data: bytes, name: str = "") -> Summary:
    """``<N bytes>``; for a grid's ``data`` field also the unknown/free/occupied cell counts."""
    n = len(data)
    if name != "data" or n == 0:
        return Summary(f"<{n} bytes>")
    a = np.frombuffer(data, dtype=np.int8)
    unknown = int(np.count_nonzero(a == -1))
    free = int(np.count_nonzero((a >= 0) & (a < GRID_FREE_BELOW)))
    occ = int(np.count_nonzero((a > GRID_OCC_ABOVE) & (a <= 100)))
    uncertain = int(np.count_nonzero((a >= GRID_FREE_BELOW) & (a <= GRID_OCC_ABOVE)))
    invalid = n - unknown - free - occ - uncertain
    text = f"<{n} bytes: unknown {unknown}, free {free}, occupied {occ}"
    if uncertain:
        text += f", uncertain {uncertain}"
    if invalid:
        text += f", invalid {invalid}"
    return Summary(text + ">")


def _is_point_list(values: list) -> bool:
    return all(
        isinstance(p, (list, tuple)) and 2 <= len(p) <= 3 and all(_is_number(v) for v in p)
        for p in values
    ) and len({len(p) for p in values}) == 1


def summarize(value: Any, full: bool = False, max_items: int = 8, name: str = "") -> Any:
    """Shorten large values for display (pure; returns a new structure).

    Bytes -> size (+ cell counts for a grid ``data`` field); numeric lists longer than
    ``max_items`` -> count/min/max/mean; long point lists -> first/last/extent; other long lists
    -> the first items and ``... N more``. Dicts and short lists are summarized recursively.
    ``full=True`` returns the value unchanged.
    """
    if max_items < 1:
        raise KeyToolError(f"max_items must be >= 1, got {max_items}")
    if full:
        return value
    if isinstance(value, (bytes, bytearray, memoryview)):
        return summarize_bytes(bytes(value), name)
    if isinstance(value, dict):
        return {k: summarize(v, False, max_items, str(k)) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        n = len(value)
        if n <= max_items:
            return [summarize(v, False, max_items, name) for v in value]
        if all(_is_number(v) for v in value):
            return summarize_numbers(list(value))
        if _is_point_list(list(value)):
            return summarize_points(list(value))
        keep = 3 if any(isinstance(v, (dict, list, tuple)) for v in value) else max_items
        head = [summarize(v, False, max_items, name) for v in value[:keep]]
        return head + [Summary(f"... {n - keep} more ({n} items)")]
    return value


def parse_field_args(fields: list[str] | None) -> list[str]:
    """``--field a.b --field c,d`` -> ["a.b", "c", "d"] (validated)."""
    out: list[str] = []
    for item in fields or []:
        for path in item.split(","):
            path = path.strip()
            if not path:
                continue
            if any(not seg for seg in path.split(".")):
                raise FieldError(f"bad field path {path!r}")
            out.append(path)
    return out


def get_field(obj: Any, path: str) -> Any:
    """Value at a dotted path (dict keys, list indices like ``poses.0``); FieldError."""
    cur = obj
    done: list[str] = []
    for seg in path.split("."):
        if isinstance(cur, dict):
            if seg in cur:
                cur = cur[seg]
            elif seg.lstrip("-").isdigit() and int(seg) in cur:
                cur = cur[int(seg)]
            else:
                avail = ", ".join(str(k) for k in list(cur)[:20])
                where = ".".join(done) or "message"
                raise FieldError(f"no field {seg!r} in {where} (fields: {avail})")
        elif isinstance(cur, (list, tuple, bytes, bytearray)):
            try:
                cur = cur[int(seg)]
            except (ValueError, IndexError):
                where = ".".join(done) or "message"
                raise FieldError(
                    f"bad index {seg!r} for {where} ({len(cur)} items)"
                ) from None
        else:
            raise FieldError(f"{'.'.join(done) or 'message'} has no fields (looking for {path!r})")
        done.append(seg)
    return cur


def select_fields(obj: Any, paths: list[str]) -> dict[str, Any]:
    """{path: value} for each dotted path (see :func:`get_field`), in the given order."""
    if not paths:
        raise FieldError("no field paths given")
    return {p: get_field(obj, p) for p in paths}


# --- output formatting -------------------------------------------------------------------------

class _YamlDumper(yaml.SafeDumper):
    """``yaml.safe_dump``'s dumper with four changes for display: a :class:`Summary` is written
    as it is (plain, never quoted: a note for the reader, not a value to read back), a list of
    scalars is written inline (a point is ``[x, y]``), objects met twice are written twice (no
    anchors), and other types are written as their ``str``."""

    def represent_list(self, data: list) -> yaml.Node:
        flow = bool(data) and not any(isinstance(v, (dict, list)) for v in data)
        return self.represent_sequence("tag:yaml.org,2002:seq", data, flow_style=flow)

    def choose_scalar_style(self):
        if isinstance(self.event.value, Summary):
            return ""
        return super().choose_scalar_style()

    def ignore_aliases(self, data: Any) -> bool:
        return True


_YamlDumper.add_representer(
    Summary, lambda d, s: d.represent_scalar("tag:yaml.org,2002:str", s))
_YamlDumper.add_representer(list, _YamlDumper.represent_list)
_YamlDumper.add_multi_representer(object, lambda d, v: d.represent_str(str(v)))


def _for_yaml(obj: Any) -> Any:
    """What the dumper should write: tuples as lists, byte buffers as bytes (``!!binary``),
    number subclasses as plain numbers, floats without binary noise (9.350000000000001 ->
    9.35) but with the ns of wall-clock stamps; non-finite floats stay (``.nan``, ``.inf``)."""
    if isinstance(obj, dict):
        return {k: _for_yaml(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_for_yaml(v) for v in obj]
    if isinstance(obj, (bytearray, memoryview)):
        return bytes(obj)
    if isinstance(obj, float):
        v = float(obj)
        return v if v == 0.0 or abs(v) < 1e-3 or not math.isfinite(v) else round(v, 9)
    if isinstance(obj, int) and not isinstance(obj, bool):
        return int(obj)
    return obj


def format_yaml(obj: Any) -> str:
    """A decoded message, part of one or a scalar as YAML text (no final newline), written by
    the PyYAML safe dumper: block style with short lists of scalars inline (a point is
    ``[x, y]``), keys in message order, unicode as is, no line folding;
    :class:`Summary` strings plain, bytes as ``!!binary``, non-finite floats as ``.nan``/``.inf``.
    """
    text = yaml.dump(_for_yaml(obj), Dumper=_YamlDumper, default_flow_style=False,
                     sort_keys=False, allow_unicode=True, width=math.inf)
    if text.endswith("\n...\n"):  # the document end marker after a lone plain scalar
        text = text[:-4]
    return text.rstrip("\n")


def _is_scalar(v: Any) -> bool:
    return not isinstance(v, (dict, list, tuple))


def to_jsonable(obj: Any) -> Any:
    """Nested value -> strict-JSON-able (bytes -> base64, non-finite floats -> strings)."""
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, (bytes, bytearray, memoryview)):
        return base64.b64encode(bytes(obj)).decode()
    if isinstance(obj, float) and not math.isfinite(obj):
        return str(obj)
    if isinstance(obj, Summary):
        return str(obj)
    return obj


def dumps_json(obj: Any) -> str:
    return json.dumps(to_jsonable(obj), allow_nan=False)


def human_bytes(n: float) -> str:
    """1520 -> '1.52 KB' (decimal units)."""
    if n < 1000:
        return f"{n:.0f} B"
    for unit in ("KB", "MB", "GB"):
        n /= 1000.0
        if n < 1000 or unit == "GB":
            return f"{n:.2f} {unit}"
    return f"{n:.2f} GB"  # pragma: no cover


def format_table(headers: list[str], rows: list[list[Any]]) -> str:
    """Plain text table; numbers right-aligned."""
    for r in rows:
        if len(r) != len(headers):
            raise KeyToolError(f"table row has {len(r)} cells, expected {len(headers)}")
    cells = [[str(h) for h in headers]] + [["-" if c is None else str(c) for c in r] for r in rows]
    widths = [max(len(r[i]) for r in cells) for i in range(len(headers))]
    numeric = [
        bool(rows) and all(_is_number(r[i]) or r[i] is None for r in rows)
        for i in range(len(headers))
    ]
    out = []
    for r in cells:
        parts = [c.rjust(w) if num else c.ljust(w)
                 for c, w, num in zip(r, widths, numeric, strict=True)]
        out.append("  ".join(parts).rstrip())
    return "\n".join(out)


# --- rate statistics (hz / bw) -----------------------------------------------------------------


class RateStats:
    """Arrival statistics of one key from explicit timestamps (no clock reads; not thread-safe).

    ``add(t, size)`` with t [s] (monotonic, non-decreasing) and size [B]. :meth:`window` gives
    the stats over the last ``window`` messages (like ``ros2 topic hz -w``), :meth:`summary`
    over everything since the first message (running mean/std of periods, Welford).
    """

    def __init__(self, window: int = 100):
        if not isinstance(window, int) or window < 2:
            raise KeyToolError(f"window must be an integer >= 2, got {window!r}")
        self.window_size = window
        self._t: deque[float] = deque(maxlen=window)
        self._s: deque[int] = deque(maxlen=window)
        self.count = 0
        self.total_bytes = 0
        self.first_t: float | None = None
        self.last_t: float | None = None
        self.first_size = 0
        self.last_size = 0
        self.size_min = 0
        self.size_max = 0
        self._np = 0  # periods seen
        self._pmean = 0.0
        self._pm2 = 0.0
        self._pmin = math.inf
        self._pmax = -math.inf

    def add(self, t: float, size: int) -> None:
        if not math.isfinite(t):
            raise KeyToolError(f"timestamp must be finite, got {t}")
        if size < 0:
            raise KeyToolError(f"size must be >= 0, got {size}")
        if self.last_t is not None:
            if t < self.last_t:
                raise KeyToolError(f"timestamps must not decrease ({t} < {self.last_t})")
            p = t - self.last_t
            self._np += 1
            d = p - self._pmean
            self._pmean += d / self._np
            self._pm2 += d * (p - self._pmean)
            self._pmin = min(self._pmin, p)
            self._pmax = max(self._pmax, p)
        else:
            self.first_t = t
            self.first_size = size
            self.size_min = self.size_max = size
        self.last_t = t
        self.last_size = size
        self.count += 1
        self.total_bytes += size
        self.size_min = min(self.size_min, size)
        self.size_max = max(self.size_max, size)
        self._t.append(t)
        self._s.append(size)

    def window(self) -> dict[str, float] | None:
        """Stats over the last ``window`` messages; None with fewer than 2 messages.

        Keys: n, rate_hz, period_mean/std/min/max [s], bandwidth [B/s], size_mean/min/max/last
        [B]. Bandwidth = bytes of messages after the first / time span (= mean size x rate).
        """
        n = len(self._t)
        if n < 2:
            return None
        t = np.asarray(self._t, dtype=np.float64)
        s = np.asarray(self._s, dtype=np.float64)
        p = np.diff(t)
        span = t[-1] - t[0]
        mean = float(p.mean())
        return {
            "n": n,
            "rate_hz": 1.0 / mean if mean > 0 else math.inf,
            "period_mean": mean,
            "period_std": float(p.std()),
            "period_min": float(p.min()),
            "period_max": float(p.max()),
            "bandwidth": float(s[1:].sum() / span) if span > 0 else math.inf,
            "size_mean": float(s.mean()),
            "size_min": float(s.min()),
            "size_max": float(s.max()),
            "size_last": float(s[-1]),
        }

    def summary(self) -> dict[str, float]:
        """Totals since the first message (rate etc. are None with fewer than 2 messages)."""
        out: dict[str, Any] = {
            "count": self.count,
            "total_bytes": self.total_bytes,
            "duration": (self.last_t - self.first_t) if self.count else 0.0,
            "size_mean": self.total_bytes / self.count if self.count else None,
            "size_min": self.size_min if self.count else None,
            "size_max": self.size_max if self.count else None,
            "rate_hz": None,
            "period_std": None,
            "period_min": None,
            "period_max": None,
            "bandwidth": None,
        }
        if self._np >= 1:
            dur = out["duration"]
            out["rate_hz"] = self._np / dur if dur > 0 else math.inf
            out["period_std"] = math.sqrt(self._pm2 / self._np)
            out["period_min"] = self._pmin
            out["period_max"] = self._pmax
            out["bandwidth"] = (self.total_bytes - self.first_size) / dur if dur > 0 else math.inf
        return out


def format_rate_line(st: dict[str, float]) -> str:
    """One ``hz`` line from :meth:`RateStats.window`."""
    return (
        f"rate {st['rate_hz']:.3f} Hz  period min {st['period_min']:.4f} "
        f"max {st['period_max']:.4f} std {st['period_std']:.5f} s  "
        f"bw {human_bytes(st['bandwidth'])}/s  size {human_bytes(st['size_mean'])} "
        f"(min {human_bytes(st['size_min'])}, max {human_bytes(st['size_max'])})  "
        f"window {st['n']}"
    )


def format_summary_line(su: dict[str, Any]) -> str:
    """The final ``hz`` line from :meth:`RateStats.summary`."""
    text = f"{su['count']} msgs, {human_bytes(su['total_bytes'])} in {su['duration']:.2f} s"
    if su["rate_hz"] is not None:
        text += (
            f": mean rate {su['rate_hz']:.3f} Hz, period std {su['period_std']:.5f} s "
            f"(min {su['period_min']:.4f}, max {su['period_max']:.4f}), "
            f"bw {human_bytes(su['bandwidth'])}/s"
        )
    if su["size_mean"] is not None:
        text += (
            f", size mean {human_bytes(su['size_mean'])} "
            f"(min {human_bytes(su['size_min'])}, max {human_bytes(su['size_max'])})"
        )
    return text


# --- the commands ------------------------------------------------------------------------------


class _Stop:
    """SIGINT/SIGTERM -> an event (so no KeyboardInterrupt lands inside zenoh calls)."""

    def __init__(self) -> None:
        self.event = threading.Event()
        self.signal: int | None = None
        self._old: dict[int, Any] = {}

    def install(self) -> None:
        if threading.current_thread() is not threading.main_thread():
            return
        for sig in (signal.SIGINT, signal.SIGTERM):
            self._old[sig] = signal.signal(sig, self._handler)

    def _handler(self, signum: int, frame: Any) -> None:
        self.signal = signum
        self.event.set()

    def restore(self) -> None:
        for sig, old in self._old.items():
            signal.signal(sig, old)
        self._old.clear()

    @property
    def interrupted(self) -> bool:
        return self.signal == signal.SIGINT


def _keys_from_args(args: argparse.Namespace) -> Keys:
    return Keys(args.namespace or DEFAULT_NAMESPACE, args.robot or DEFAULT_ROBOT)


def _open_bus(args: argparse.Namespace) -> Bus:
    connect = args.connect or (None if args.zenoh_config else DEFAULT_ENDPOINT)
    return Bus.client(connect, name="keytools", config_file=args.zenoh_config)


def _subscribe(bus: Bus, key: str, callback: Any) -> None:
    try:
        bus.subscribe_raw(key, callback)
    except Exception as exc:  # zenoh rejects the key expression
        raise KeyToolError(f"cannot subscribe to {key!r}: {_one_line(exc)}") from None


def _get(bus: Bus, selector: str, timeout: float) -> list[tuple[str, bytes | None, str]]:
    try:
        return bus.get(selector, timeout=timeout)
    except Exception as exc:
        raise KeyToolError(f"cannot query {selector!r}: {_one_line(exc)}") from None


def _out(text: str) -> None:
    print(text, flush=True)


def _err(text: str) -> None:
    print(f"{PROG}: {text}", file=sys.stderr, flush=True)


_RUST_LOC = re.compile(r"\s+at /\S+\.rs:\d+\.?")


def _one_line(text: Any) -> str:
    """One line, without zenoh's Rust source locations."""
    return " ".join(_RUST_LOC.sub("", str(text)).split())


class _KeyCollector:
    """Per-key statistics for ``list`` (fed from zenoh callback threads)."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.stats: dict[str, RateStats] = {}
        self.types: dict[str, str] = {}
        self.bad: dict[str, int] = {}
        self.last_error: dict[str, str] = {}

    def on_sample(self, key: str, payload: bytes, encoding: str, t: float) -> None:
        try:
            _, tname = decode_payload(key, payload)
            err = ""
        except m.MessageError as exc:
            t_ = type_for_key(key)
            tname = t_.__name__ if t_ is not None else "?"
            err = _one_line(exc)
        with self.lock:
            st = self.stats.get(key)
            if st is None:
                st = self.stats[key] = RateStats(window=100_000)
            st.add(max(t, st.last_t or t), len(payload))
            self.types[key] = tname
            if err:
                self.bad[key] = self.bad.get(key, 0) + 1
                self.last_error[key] = err

    def rows(self) -> list[dict[str, Any]]:
        """One row per key seen (sorted): type, count, rate, last size, bad count, last error."""
        with self.lock:
            rows = []
            for key in sorted(self.stats):
                st = self.stats[key]
                su = st.summary()
                rows.append({
                    "key": key,
                    "type": self.types.get(key, "?"),
                    "count": su["count"],
                    "rate_hz": None if su["rate_hz"] is None else round(su["rate_hz"], 3),
                    "size": st.last_size,
                    "bad": self.bad.get(key, 0),
                    "last_error": self.last_error.get(key, ""),
                })
        return rows


def _probe_state(bus: Bus, key: str, timeout: float) -> dict[str, Any]:
    """Query one state queryable -> {key, ok, size, error}."""
    try:
        replies = _get(bus, key, timeout)
    except KeyToolError as exc:
        return {"key": key, "ok": False, "size": None, "error": str(exc)}
    for _, payload, err in replies:
        if payload is None:
            return {"key": key, "ok": False, "size": None, "error": _one_line(err)}
        try:
            msgspec.msgpack.decode(payload)
            return {"key": key, "ok": True, "size": len(payload), "error": ""}
        except (msgspec.DecodeError, msgspec.ValidationError) as exc:
            return {"key": key, "ok": False, "size": len(payload),
                    "error": _one_line(f"not msgpack: {exc}")}
    return {"key": key, "ok": False, "size": None, "error": f"no reply within {timeout:g} s"}


def cmd_list(args: argparse.Namespace, bus: Bus, keys: Keys, stop: _Stop) -> int:
    if args.all_robots:
        base, sub_key = keys.namespace, f"{keys.namespace}/**"
        alive_key = f"{keys.namespace}/**/alive/*"
    else:
        base, sub_key = keys.prefix, keys.all()
        alive_key = keys.alive_all()
    col = _KeyCollector()
    _subscribe(bus, sub_key, lambda k, p, e: col.on_sample(k, p, e, time.monotonic()))
    t0 = time.monotonic()
    stop.event.wait(args.duration)
    window = time.monotonic() - t0
    if stop.event.is_set():
        return 130 if stop.interrupted else 0
    rows = col.rows()  # snapshot at the end of the window
    services, states = _live_services(bus, alive_key, keys.namespace, args.timeout)
    if args.json:
        _out(dumps_json({"base": base, "duration": round(window, 3), "services": services,
                         "states": states, "keys": rows}))
        return 0
    _print_list(base, window, services, states, rows, args.all_robots)
    return 0


def _live_services(bus: Bus, alive_key: str, namespace: str,
                   timeout: float) -> tuple[list[dict], list[dict]]:
    """The services with a liveliness token under ``alive_key``, and the answer of each one's
    state queryable (sorted by key)."""
    services = []
    states = []
    for k in bus.alive(alive_key, timeout=timeout):
        robot_prefix, service = k.rsplit("/alive/", 1)
        services.append({"service": service, "robot": short_key(robot_prefix, namespace),
                         "token": k})
        # one query per live service: replies carry the query's key, not the queryable's
        states.append(_probe_state(bus, f"{robot_prefix}/{service}/state", timeout))
    states.sort(key=lambda s: s["key"])
    return services, states


def _print_list(base: str, window: float, services: list[dict], states: list[dict],
                rows: list[dict], all_robots: bool) -> None:
    """``keys list`` as text: the live services, their state queryables, the keys seen."""
    _out(f"services alive under {base}/ ({len(services)}):")
    if services:
        _out(format_table(["SERVICE", "ROBOT", "TOKEN"], [
            [s["service"], s["robot"], short_key(s["token"], base)] for s in services]))
    _out("")
    _out(f"state queryables of the live services ({len(states)}):")
    if states:
        _out(format_table(["KEY", "REPLY", "SIZE_B"], [
            [short_key(s["key"], base) or "?", "ok" if s["ok"] else "ERROR " + s["error"],
             s["size"]] for s in states]))
    _out("")
    _out(f"keys seen in {window:.1f} s ({len(rows)}):")
    if rows:
        _out(format_table(["KEY", "TYPE", "MSGS", "RATE_HZ", "SIZE_B", "DECODE"], [
            [short_key(r["key"], base), r["type"], r["count"], r["rate_hz"], r["size"],
             "ok" if not r["bad"] else f"BAD {r['bad']}/{r['count']}"] for r in rows]))
    for r in rows:
        if r["bad"]:
            _out(f"  {short_key(r['key'], base)}: last error: {r['last_error']}")
    if not rows and not services:
        hint = "" if all_robots else " or --all-robots"
        _out(f"nothing under {base}/: is the stack running there? (check --namespace/--robot"
             f"{hint}, --connect)")


def _render(value: Any, args: argparse.Namespace, name: str = "") -> Any:
    """A value as shown: summarized for people, whole with --full and always with --json (a
    script wants the arrays; bytes become base64, non-finite floats strings)."""
    return summarize(value, full=args.full or args.json, name=name)


def _print_value(key: str, tname: str, size: int, value: Any, fields: list[str],
                 args: argparse.Namespace, many_keys: bool) -> None:
    """Print one decoded message (or its selected fields)."""
    if fields:
        sel = select_fields(value, fields)
        if len(fields) == 1:
            value = _render(sel[fields[0]], args, fields[0].rsplit(".", 1)[-1])
        else:
            value = {p: _render(v, args, p.rsplit(".", 1)[-1]) for p, v in sel.items()}
    else:
        value = _render(value, args)
    if args.json:
        if many_keys:
            _out(dumps_json({"key": key, "type": tname, "size": size, "data": value}))
        else:
            _out(dumps_json(value))
        return
    if _is_scalar(value) and fields:
        _out(format_yaml({key: value} if many_keys else value))
        return
    if many_keys:
        _out(f"# {key} [{tname}] {size} B")
    _out(format_yaml(value))
    _out("---")


def cmd_echo(args: argparse.Namespace, bus: Bus, keys: Keys, stop: _Stop) -> int:
    key = resolve_key(args.key, keys)
    fields = parse_field_args(args.field)
    count = 1 if args.once else args.count
    many = is_wildcard(key)
    cv = threading.Condition()
    pending: deque[tuple[str, bytes]] = deque(maxlen=args.queue)
    dropped = [0]

    def on_sample(k: str, payload: bytes, encoding: str) -> None:
        with cv:
            if len(pending) == pending.maxlen:
                dropped[0] += 1
            pending.append((k, payload))
            cv.notify()

    _subscribe(bus, key, on_sample)
    got = bad = 0
    last = time.monotonic()
    while not stop.event.is_set():
        with cv:
            cv.wait_for(lambda: pending or stop.event.is_set(), timeout=0.1)
            item = pending.popleft() if pending else None
        if item is None:
            if args.timeout is not None and time.monotonic() - last > args.timeout:
                what = "no message" if got == 0 else "no further message"
                _err(f"{what} on {key} within {args.timeout:g} s "
                     f"({got} shown, {bad} bad)")
                return 1
            continue
        k, payload = item
        try:
            value, tname = decode_payload(k, payload)
        except m.MessageError as exc:
            bad += 1
            _err(f"bad message on {k} ({len(payload)} B): {_one_line(exc)}")
            continue
        _print_value(k, tname, len(payload), value, fields, args, many)
        got += 1
        last = time.monotonic()
        if count is not None and got >= count:
            break
    if dropped[0]:
        _err(f"{dropped[0]} messages dropped (output too slow; queue {args.queue})")
    return 0


def cmd_hz(args: argparse.Namespace, bus: Bus, keys: Keys, stop: _Stop) -> int:
    key = resolve_key(args.key, keys)
    many = is_wildcard(key)
    lock = threading.Lock()
    stats: dict[str, RateStats] = {}

    def on_sample(k: str, payload: bytes, encoding: str) -> None:
        t = time.monotonic()
        with lock:
            st = stats.get(k)
            if st is None:
                st = stats[k] = RateStats(window=args.window)
            st.add(max(t, st.last_t or t), len(payload))

    _subscribe(bus, key, on_sample)
    t0 = time.monotonic()
    end = t0 + args.duration if args.duration is not None else math.inf
    next_print = t0 + 1.0
    seen_at_print: dict[str, int] = {}
    while not stop.event.is_set():
        now = time.monotonic()
        if now >= end:
            break
        stop.event.wait(min(next_print, end) - now)
        if time.monotonic() < next_print:
            continue
        next_print += 1.0
        with lock:
            snap = {k: (st.window(), st.count, st.last_t) for k, st in stats.items()}
        now = time.monotonic()
        for k in sorted(snap):
            win, n, last_t = snap[k]
            label = f"{short_key(k, keys.prefix)}: " if many else ""
            if win is None:
                _out(f"{label}{n} msg so far")
            else:
                stale = "" if n != seen_at_print.get(k) else (
                    f"  (no new messages for {now - last_t:.1f} s)")
                _out(label + format_rate_line(win) + stale)
            seen_at_print[k] = n
    with lock:
        final = {k: st.summary() for k, st in stats.items()}
    if not final:
        _err(f"no messages on {key} in {time.monotonic() - t0:.1f} s")
        return 0 if stop.event.is_set() else 1
    for k in sorted(final):
        label = short_key(k, keys.prefix) if many else k
        _out(f"summary {label}: {format_summary_line(final[k])}")
    return 0


def cmd_get(args: argparse.Namespace, bus: Bus, keys: Keys, stop: _Stop) -> int:
    selector = state_selector(args.service, keys)
    fields = parse_field_args(args.field)
    replies = _get(bus, selector, args.timeout)
    if stop.event.is_set():
        return 130 if stop.interrupted else 0
    ok = 0
    many = is_wildcard(selector) or len(replies) > 1
    for key, payload, err in replies:
        if payload is None:
            _err(f"error reply from {selector}: {_one_line(err)}")
            continue
        try:
            value = msgspec.msgpack.decode(payload)
        except (msgspec.DecodeError, msgspec.ValidationError) as exc:
            _err(f"reply from {key} is not msgpack ({len(payload)} B): {_one_line(exc)}")
            continue
        label = key
        if is_wildcard(key) and isinstance(value, dict) and isinstance(value.get("service"), str):
            label = f"{key} (service {value['service']})"  # replies carry the query's key
        _print_value(label, "state", len(payload), value, fields, args, many)
        ok += 1
    if ok == 0:
        if not replies:
            _err(f"no reply from {selector} within {args.timeout:g} s (service not running?)")
        return 1
    return 0


# --- command line ------------------------------------------------------------------------------


class _Parser(argparse.ArgumentParser):
    """argparse with a one-line error (no usage dump) and no SystemExit from error()."""

    def error(self, message: str) -> None:  # type: ignore[override]
        raise _UsageError(f"{self.prog}: {message}")


class _UsageError(Exception):
    pass


def _positive(kind: type, lo: float, name: str):
    def conv(text: str):
        try:
            v = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{name} must be a number, got {text!r}") from None
        if not (v >= lo) or (isinstance(v, float) and not math.isfinite(v)):
            raise argparse.ArgumentTypeError(f"{name} must be >= {lo}, got {text!r}")
        return v

    return conv


def build_parser() -> argparse.ArgumentParser:
    from topoexplore.common.node import add_bus_args

    p = _Parser(prog=PROG, description="Inspect the Zenoh keys of a running topoexplore stack.")
    sub = p.add_subparsers(dest="cmd", metavar="{list,echo,hz,get,pub,set}", required=True)

    sp = sub.add_parser("list", help="live services, state queryables and keys with rates")
    sp.add_argument("--duration", type=_positive(float, 0.05, "--duration"), default=2.0,
                    help="listening window [s] (default 2)")
    sp.add_argument("--timeout", type=_positive(float, 0.05, "--timeout"), default=1.0,
                    help="liveliness/state query timeout [s] (default 1)")
    sp.add_argument("--all-robots", action="store_true", help="every robot under the namespace")
    sp.add_argument("--json", action="store_true", help="print one JSON object")
    add_bus_args(sp)

    sp = sub.add_parser("echo", help="print decoded messages of a key")
    sp.add_argument("key", help="topic (scan, explore/status) or full key expression")
    sp.add_argument("--once", action="store_true", help="first message, then exit")
    sp.add_argument("--count", type=_positive(int, 1, "--count"), default=None,
                    help="exit after N messages")
    sp.add_argument("--field", action="append", default=[],
                    help="dotted field path(s), repeatable or comma separated "
                         "(header.stamp.sec, ranges.0)")
    sp.add_argument("--full", action="store_true", help="do not summarize large arrays")
    sp.add_argument("--json", action="store_true",
                    help="one JSON line per message, whole (arrays as arrays, bytes base64)")
    sp.add_argument("--timeout", type=_positive(float, 0.01, "--timeout"), default=None,
                    help="exit 1 if no message arrives for S seconds")
    sp.add_argument("--queue", type=_positive(int, 1, "--queue"), default=100,
                    help="messages kept while printing (oldest dropped)")
    add_bus_args(sp)

    sp = sub.add_parser("hz", help="rate, jitter, bandwidth and size of a key")
    sp.add_argument("key", help="topic (scan, explore/status) or full key expression")
    sp.add_argument("--window", type=_positive(int, 2, "--window"), default=100,
                    help="messages in the rolling window (default 100)")
    sp.add_argument("--duration", type=_positive(float, 0.05, "--duration"), default=None,
                    help="stop after S seconds and print the summary")
    add_bus_args(sp)

    sp = sub.add_parser("get", help="query a service's state (<ns>/<robot>/<SERVICE>/state)")
    sp.add_argument("service", help="service name (mapper) or full key expression")
    sp.add_argument("--field", action="append", default=[],
                    help="dotted field path(s), repeatable or comma separated")
    sp.add_argument("--full", action="store_true", help="do not summarize large values")
    sp.add_argument("--json", action="store_true", help="print JSON")
    sp.add_argument("--timeout", type=_positive(float, 0.01, "--timeout"), default=2.0,
                    help="reply timeout [s] (default 2)")
    add_bus_args(sp)

    sp = sub.add_parser("pub", help="publish a message (or a stream) on a key: FIELD=VALUE ...")
    sp.add_argument("key", help="topic (cmd_vel) or full key")
    sp.add_argument("fields", nargs="*", metavar="FIELD=VALUE",
                    help="message fields, YAML values (linear.x=0.2 angular.z=0.5; for "
                         "cmd_vel also v=0.2 w=0.5; header.stamp=12.5 [s]); the header is "
                         "filled in")
    sp.add_argument("--rate", type=_positive(float, 0.001, "--rate"), default=None,
                    help="publish at this rate [Hz] until --count/--duration or Ctrl-C")
    sp.add_argument("--count", type=_positive(int, 1, "--count"), default=None,
                    help="messages to publish (default 1, or unlimited with --rate)")
    sp.add_argument("--duration", type=_positive(float, 0.01, "--duration"), default=None,
                    help="stop after S seconds")
    sp.add_argument("--wait", type=_positive(float, 0.0, "--wait"), default=1.0,
                    help="wait up to S seconds for a subscriber before the first message")
    add_bus_args(sp)

    sp = sub.add_parser("set", help="change a parameter of a running service (section.name=V)")
    sp.add_argument("service", help="service name (controller)")
    sp.add_argument("assignment", nargs="?", default=None, metavar="SECTION.NAME=VALUE",
                    help="the change (TOML value); without it: what can change live")
    sp.add_argument("--timeout", type=_positive(float, 0.01, "--timeout"), default=2.0,
                    help="reply timeout [s] (default 2)")
    add_bus_args(sp)
    return p


def _cmd_pub(args: argparse.Namespace, bus: Bus, keys: Keys, stop: _Stop) -> int:
    from topoexplore.tools.keypub import PubError, cmd_pub

    try:
        return cmd_pub(args, bus, keys, stop)
    except PubError as exc:
        raise KeyToolError(str(exc)) from None


def _cmd_set(args: argparse.Namespace, bus: Bus, keys: Keys, stop: _Stop) -> int:
    from topoexplore.tools.keypub import cmd_set

    return cmd_set(args, bus, keys, stop)


_COMMANDS = {"list": cmd_list, "echo": cmd_echo, "hz": cmd_hz, "get": cmd_get, "pub": _cmd_pub,
             "set": _cmd_set}


def main(argv: list[str] | None = None) -> int:
    """``topoexplore keys ...``: returns the exit code (never raises on bad input)."""
    stop = _Stop()
    bus: Bus | None = None
    try:
        try:
            args = build_parser().parse_args(argv)
        except _UsageError as exc:
            print(_one_line(exc), file=sys.stderr)
            return 2
        except SystemExit as exc:  # --help
            return exc.code if isinstance(exc.code, int) else 0
        try:
            keys = _keys_from_args(args)
            if args.cmd in ("echo", "hz"):
                resolve_key(args.key, keys)
            if args.cmd in ("echo", "get"):
                parse_field_args(args.field)
            if args.cmd == "get":
                state_selector(args.service, keys)
        except ValueError as exc:
            _err(_one_line(exc))
            return 2
        init_logging()
        stop.install()
        try:
            bus = _open_bus(args)
        except BusError as exc:
            _err(_one_line(exc))
            return 2
        try:
            return _COMMANDS[args.cmd](args, bus, keys, stop)
        except KeyToolError as exc:
            _err(_one_line(exc))
            return 2
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:  # `keys echo scan | head`
        try:
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
        except OSError:
            pass
        return 0
    finally:
        if bus is not None:
            bus.close()
        stop.restore()


if __name__ == "__main__":
    raise SystemExit(main())
