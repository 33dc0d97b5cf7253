"""``topoexplore record`` and ``topoexplore play``: the bus into an MCAP file, and back.

Like ``ros2 bag record`` / ``ros2 bag play``, for our key space.

The file (MCAP, profile ``topoexplore``, zstd chunks) holds:

- **one raw channel per key** (topic = the full key, e.g. ``topoexplore/robot1/scan``) with the
  exact bytes that crossed the bus; message encoding ``msgpack``; the schema is the message
  type's JSON Schema (``msgspec.json.schema``; schema name ``topoexplore.<Type>``). Log time is
  the wall clock [ns since the epoch] when the sample arrived; publish time is the message's
  ``header.stamp`` (the sim clock in simulation) in ns, or the log time if it has none.
- **Foxglove channels** beside them (``/viz/map``, ``/viz/scan``, ``/tf``, ``/viz/trail``,
  ``/viz/graph``, ``/viz/plan``; protobuf, Foxglove's own schemas; :mod:`tools.fox`), so that
  the file opened in Foxglove shows the run the way the paper's figures do.
- metadata ``topoexplore``: the key prefix, the command and anything the caller adds.

Counting: the recorder checks each raw key's ``header.seq`` (per publisher, from 0): a jump is
counted as lost messages (``gaps``); a restarted publisher (seq back to 0) is counted as
``restarts``; ``first_seq`` is each key's first seq (0 when the recording saw the publisher
start). A recording that loses nothing has 0 gaps.

``play`` publishes the raw channels back onto the bus in log-time order with their recorded
timing (``--rate`` scales it, ``--start`` skips the first seconds, ``--keys`` picks topics, and
``--namespace``/``--robot`` move them under another prefix so that a live stack is not fed).
"""

from __future__ import annotations

import argparse
import json
import math
import queue
import sys
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path
from typing import Any

import msgspec

from topoexplore.common import messages as m
from topoexplore.common.bus import Bus, BusError
from topoexplore.common.keys import DEFAULT_ENDPOINT, TOPICS, Keys, type_for_key
from topoexplore.common.node import add_bus_args, add_param_args, params_from_args, stop_on_signals
from topoexplore.common.params import ParamError, Params, load_params
from topoexplore.tools.argtypes import OneLineParser, UsageError, fail, non_negative, positive
from topoexplore.tools.extras import ExtraMissing, require
from topoexplore.tools.fox import channel_schema, json_schema

PROFILE = "topoexplore"
MESSAGE_ENCODING = "msgpack"
SCHEMA_ENCODING = "jsonschema"
CHUNK_SIZE = 4 * 1024 * 1024  # [bytes] of an MCAP chunk before compression


class RecordError(UsageError):
    """A bad recording or a bad argument (one line)."""


class _Stamped(msgspec.Struct):
    """Only the header of any of our messages (the other fields are skipped undecoded)."""

    header: m.Header


_stamped = msgspec.msgpack.Decoder(_Stamped)


def header_of(payload: bytes) -> m.Header | None:
    """The header of a raw message, or None if it has none (or is not ours)."""
    try:
        return _stamped.decode(payload).header
    except (msgspec.DecodeError, msgspec.ValidationError):
        return None


def to_ns(t: float) -> int:
    """[s] -> [ns], clamped to the unsigned 64-bit range of MCAP times."""
    if not math.isfinite(t) or t <= 0:
        return 0
    return min(int(round(t * 1e9)), 2**64 - 1)


def topic_of(key: str, prefix: str) -> str | None:
    """Our topic name of a full key under ``prefix`` (``scan``, ``explore/status``), else None."""
    if not key.startswith(prefix + "/"):
        return None
    rest = key[len(prefix) + 1:]
    return rest if rest in TOPICS else None


class Recorder:
    """Write bus samples into an MCAP file. :meth:`put` may be called from any thread (it only
    queues); a writer thread encodes and writes, so a slow disk never stalls zenoh's threads.
    :meth:`close` drains the queue, finishes the file and returns :meth:`stats`."""

    def __init__(self, path: str | Path, prefix: str, *, foxglove: bool = True,
                 laser_offset: float = 0.0, p_reliable: float = 0.9,
                 metadata: dict[str, str] | None = None, threaded: bool = True):
        require("mcap", *(["foxglove"] if foxglove else []), what="recording")
        from mcap.writer import CompressionType, Writer

        from topoexplore.tools.fox import FoxScene

        self.path = Path(path)
        self.prefix = prefix
        self._file = self.path.open("wb")
        self._w = Writer(self._file, chunk_size=CHUNK_SIZE, compression=CompressionType.ZSTD)
        self._w.start(profile=PROFILE, library="topoexplore")
        self._w.add_metadata("topoexplore", {"prefix": prefix, **(metadata or {})})
        self._scene = FoxScene(laser_offset, p_reliable) if foxglove else None
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self.seqs = m.SeqGaps()  # messages missing by header.seq, publisher restarts
        self._q: queue.SimpleQueue[tuple[str, bytes, int] | None] = queue.SimpleQueue()
        self.counts: Counter[str] = Counter()  # raw messages written per key
        self.fox_counts: Counter[str] = Counter()
        self.bad: Counter[str] = Counter()  # raw messages that failed validation (kept raw)
        self.errors = 0  # conversion failures (logged once each kind)
        self.last_error = ""
        self.bytes = 0
        self.queued = 0
        self.max_backlog = 0
        self._written = 0
        self._closed = False
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None  # threaded False: put() writes itself
        if threaded:
            self._thread = threading.Thread(target=self._loop, name="mcap-writer", daemon=True)
            self._thread.start()

    # -- input (any thread) -----------------------------------------------------------------
    def put(self, key: str, payload: bytes, log_time_ns: int | None = None) -> None:
        with self._lock:
            if self._closed:
                return
            self.queued += 1
            self.max_backlog = max(self.max_backlog, self.queued - self._written)
            item = (key, bytes(payload), time.time_ns() if log_time_ns is None else log_time_ns)
            if self._thread is None:
                self._one(item)
            else:
                self._q.put(item)

    def close(self) -> dict[str, Any]:
        with self._lock:
            if self._closed:
                return self.stats()
            self._closed = True
            self._q.put(None)
        if self._thread is not None:
            self._thread.join()
        self._w.finish()
        self._file.close()
        return self.stats()

    @property
    def backlog(self) -> int:
        """Messages queued and not written yet."""
        return self.queued - self._written

    def stats(self) -> dict[str, Any]:
        return {"path": str(self.path), "messages": sum(self.counts.values()),
                "per_key": dict(sorted(self.counts.items())),
                "foxglove": dict(sorted(self.fox_counts.items())),
                "gaps": self.seqs.total, "gaps_per_key": dict(self.seqs.gaps),
                "restarts": dict(self.seqs.restarts), "first_seq": dict(self.seqs.first_seq),
                "bad": dict(self.bad),
                "errors": self.errors, "last_error": self.last_error, "bytes": self.bytes,
                "max_backlog": self.max_backlog}

    # -- writer thread ----------------------------------------------------------------------
    def _loop(self) -> None:
        while True:
            item = self._q.get()
            if item is None:
                return
            self._one(item)

    def _one(self, item: tuple[str, bytes, int]) -> None:
        try:
            self._write(*item)
        except Exception as exc:  # noqa: BLE001 - one bad sample must not end the file
            self.errors += 1
            self.last_error = f"{item[0]}: {type(exc).__name__}: {exc}"
        finally:
            self._written += 1

    def _channel(self, topic: str, encoding: str, schema: tuple[str, str, bytes] | None,
                 metadata: dict[str, str]) -> int:
        cid = self._channels.get(topic)
        if cid is None:
            sid = 0
            if schema is not None:
                name, enc, data = schema
                sid = self._schemas.get(name) or self._w.register_schema(name, enc, data)
                self._schemas[name] = sid
            cid = self._w.register_channel(topic, encoding, sid, metadata)
            self._channels[topic] = cid
        return cid

    def _write(self, key: str, payload: bytes, log_ns: int) -> None:
        msg_type = type_for_key(key)
        cid = self._channels.get(key)
        if cid is None:
            schema = (f"topoexplore.{msg_type.__name__}", SCHEMA_ENCODING,
                      json_schema(msg_type)) if msg_type is not None else None
            cid = self._channel(key, MESSAGE_ENCODING, schema, {"zenoh_key": key})
        hdr = header_of(payload)
        pub_ns = (hdr.stamp.sec * 1_000_000_000 + hdr.stamp.nanosec) if hdr is not None else log_ns
        seq = hdr.seq if hdr is not None else self.counts[key]
        self._w.add_message(cid, log_time=log_ns, data=payload, publish_time=pub_ns,
                            sequence=max(0, min(seq, 2**32 - 1)))
        self.counts[key] += 1
        self.bytes += len(payload)
        if hdr is not None:
            self.seqs.check(key, hdr.seq)
        topic = topic_of(key, self.prefix)
        if self._scene is None or msg_type is None or topic is None:
            return
        try:
            msg = m.decode(payload, msg_type)
        except m.MessageError as exc:
            self.bad[key] += 1
            self.last_error = f"{key}: {exc}"
            return
        for fox_topic, fmsg in self._scene.convert(topic, msg):
            fcid = self._channels.get(fox_topic)
            if fcid is None:
                enc, name, sch_enc, sch = channel_schema(fox_topic)
                fcid = self._channel(fox_topic, enc, (name, sch_enc, sch), {})
            data = (json.dumps(fmsg, allow_nan=False).encode() if isinstance(fmsg, dict)
                    else fmsg.encode())
            self._w.add_message(fcid, log_time=log_ns, data=data, publish_time=pub_ns)
            self.fox_counts[fox_topic] += 1


# --- reading back ---------------------------------------------------------------------------


def read_summary(path: str | Path) -> dict[str, Any]:
    """Channels (topic -> encoding, schema, count) and metadata of an MCAP file."""
    require("mcap", what="reading a recording")
    from mcap.reader import make_reader

    try:
        with open(path, "rb") as f:
            reader = make_reader(f)
            summary = reader.get_summary()
            meta = {r.name: dict(r.metadata) for r in reader.iter_metadata()}
    except OSError as exc:
        raise RecordError(f"cannot read {path}: {exc.strerror or exc}") from None
    except Exception as exc:  # noqa: BLE001 - the mcap reader's errors have no common base
        raise RecordError(f"{path} is not a readable MCAP file: {exc}") from None
    if summary is None or summary.statistics is None:
        raise RecordError(f"{path} has no summary (was the recording cut off?)")
    counts = summary.statistics.channel_message_counts
    chans = {}
    for cid, ch in summary.channels.items():
        sc = summary.schemas.get(ch.schema_id)
        chans[ch.topic] = {"encoding": ch.message_encoding,
                           "schema": sc.name if sc else "", "schema_encoding":
                           sc.encoding if sc else "", "count": counts.get(cid, 0)}
    st = summary.statistics
    return {"channels": chans, "metadata": meta, "messages": st.message_count,
            "start_ns": st.message_start_time, "end_ns": st.message_end_time}


def raw_messages(path: str | Path, topics: set[str] | None = None, start_ns: int = 0):
    """(key, payload, log_time_ns) of the raw channels in log-time order."""
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        reader = make_reader(f)
        for _sc, ch, msg in reader.iter_messages(log_time_order=True, start_time=start_ns or None):
            if ch.message_encoding != MESSAGE_ENCODING:
                continue
            if topics is not None and ch.topic not in topics:
                continue
            yield ch.topic, msg.data, msg.log_time


def recorded_settings(meta: dict[str, str]) -> tuple[str, list[str]]:
    """(text of the --params file, --set overrides) a ``run --record`` recording was made
    with, from its metadata (:func:`tools.run.recording_metadata`); overrides that do not
    read as a list of strings count as none."""
    try:
        overrides = json.loads(meta.get("overrides") or "[]")
    except json.JSONDecodeError:
        overrides = []
    if not isinstance(overrides, list) or not all(isinstance(o, str) for o in overrides):
        overrides = []
    return meta.get("params_toml") or "", overrides


def recorded_params(meta: dict[str, str]) -> Params | None:
    """The parameters a ``run --record`` recording was made with (:func:`recorded_settings`);
    None for a recording that does not say (``topoexplore record``)."""
    if "overrides" not in meta and not meta.get("params_toml"):
        return None
    text, overrides = recorded_settings(meta)
    try:
        with tempfile.TemporaryDirectory() as tmp:
            path = None
            if text:
                path = Path(tmp) / "params.toml"
                path.write_text(text)
            return load_params(path, overrides)
    except ParamError as exc:
        raise RecordError(f"the recording's parameters are unreadable: {exc}") from None


def add_foxglove(src: str | Path, dst: str | Path, params: Params | None = None
                 ) -> dict[str, Any]:
    """The raw recording src (``run --record-raw``, ``record --no-foxglove``) written again
    to dst with the Foxglove channels beside the raw ones, as if it had been recorded with
    them: the same raw bytes, log times and metadata (Foxglove channels src had are made
    anew). The laser mount and P limit of the pictures are the recording's own parameters
    (:func:`recorded_params`), else params', else the defaults. Converting after the run costs
    the run nothing; the conversion takes the time the recorder would have spent during it.
    Returns the recorder's counts."""
    summary = read_summary(src)
    meta = dict(summary["metadata"].get("topoexplore", {}))
    prefix = meta.pop("prefix", "")
    if not prefix or not any(c["encoding"] == MESSAGE_ENCODING
                             for c in summary["channels"].values()):
        raise RecordError(f"{src} holds no topoexplore recording (no raw msgpack channels)")
    if Path(src).resolve() == Path(dst).resolve():
        raise RecordError(f"{dst}: write the converted recording to another file")
    P = recorded_params(meta) or params or Params()
    rec = Recorder(dst, prefix, laser_offset=P.laser.offset,
                   p_reliable=P.reliability.p_reliable, metadata=meta, threaded=False)
    done = False
    try:
        for key, data, log_ns in raw_messages(src):
            rec.put(key, data, log_ns)
        done = True
    except Exception as exc:  # noqa: BLE001 - the mcap reader's errors have no common base
        raise RecordError(f"{src} cannot be read to its end ({type(exc).__name__}: {exc}); "
                          f"nothing written") from None
    finally:
        st = rec.close()
        if not done:
            Path(dst).unlink(missing_ok=True)
    return st


LAYOUT_PROBE = 5000  # messages read at most to find each channel's first one


def unreadable_channels(path: str | Path, keys: set[str]) -> dict[str, str]:
    """{key: why} of the raw channels among keys whose first message this version cannot
    decode: a recording made before a wire message changed (the ROS-shaped messages of
    2026-12-04, say). Its messages would be rejected by every service, one by one, so play
    and replay say so up front. Reads the first message of each key, within the first
    LAYOUT_PROBE messages (a key first seen later is not judged)."""
    out: dict[str, str] = {}
    seen: set[str] = set()
    for n, (key, data, _t) in enumerate(raw_messages(path, keys)):
        if key not in seen:
            seen.add(key)
            t = type_for_key(key)
            if t is not None:
                try:
                    m.decode(data, t)
                except m.MessageError as exc:
                    out[key] = str(exc)
        if seen >= keys or n >= LAYOUT_PROBE:
            break
    return out


def layout_error(path: str | Path, keys: set[str], prefix: str) -> str | None:
    """The one-line error for :func:`unreadable_channels` (None when every channel reads)."""
    bad = unreadable_channels(path, keys)
    if not bad:
        return None
    names = sorted(topic_of(k, prefix) or k for k in bad)
    first = bad[min(bad)].splitlines()[0][:160]
    return (f"{path}: this version cannot read the messages on {', '.join(names)} (first: "
            f"{first}); it was recorded with another wire layout: play it with the version "
            "that recorded it (docs/recording.md, \"Wire layout\")")


# --- command line ---------------------------------------------------------------------------


def _bus_keys(args: argparse.Namespace) -> Keys:
    return Keys(args.namespace or "topoexplore", args.robot or "robot1")


def _open(args: argparse.Namespace, name: str) -> Bus:
    connect = args.connect or (None if args.zenoh_config else DEFAULT_ENDPOINT)
    return Bus.client(connect, name=name, config_file=args.zenoh_config)


def _topics_arg(text: str | None) -> list[str] | None:
    if not text:
        return None
    out = [t.strip() for t in text.split(",") if t.strip()]
    bad = [t for t in out if t not in TOPICS]
    if bad:
        raise RecordError(f"unknown topic(s) {', '.join(bad)}: choose from "
                          f"{', '.join(TOPICS)}")
    return out


def cmd_record(args: argparse.Namespace) -> int:
    try:
        topics = _topics_arg(args.keys)
        P = params_from_args(args)
    except (RecordError, ParamError, ValueError) as exc:
        return fail(str(exc))
    keys = Keys(P.bus.namespace, P.bus.robot)
    out = Path(args.out)
    if out.parent and not out.parent.exists():
        return fail(f"cannot write {out}: folder {out.parent} does not exist")
    if args.from_file is not None:
        return _convert(args, P, out)
    stop = threading.Event()
    restore = stop_on_signals(stop.set)  # kept until the file is finished: a second Ctrl-C
    bus = rec = None  # must not leave it without its summary
    try:
        try:
            bus = _open(args, "record")
        except BusError as exc:
            return fail(str(exc))
        rec = Recorder(out, keys.prefix, foxglove=not args.no_foxglove,
                       laser_offset=P.laser.offset, p_reliable=P.reliability.p_reliable,
                       metadata={"command": " ".join(sys.argv[1:])})
        for key in ([keys.topic(t) for t in topics] if topics else [f"{keys.prefix}/**"]):
            bus.subscribe_raw(key, lambda k, p, _e: rec.put(k, p))
        if not args.quiet:
            print(f"recording {keys.prefix}/{'{' + ','.join(topics) + '}' if topics else '**'} "
                  f"into {out} (Ctrl-C to stop)", file=sys.stderr)
        t_end = time.monotonic() + args.duration if args.duration else math.inf
        while not stop.is_set() and time.monotonic() < t_end:
            stop.wait(min(0.2, max(0.0, t_end - time.monotonic())))
        bus.close()
        if rec.backlog > 1000 and not args.quiet:
            print(f"writing the last {rec.backlog} messages ...", file=sys.stderr)
        st = rec.close()
    except ExtraMissing as exc:
        return fail(str(exc))
    except OSError as exc:
        return fail(f"cannot write {out}: {exc.strerror or exc}")
    finally:
        if bus is not None:
            bus.close()
        if rec is not None:
            rec.close()
        restore()
    print(f"recorded {st['messages']} messages on {len(st['per_key'])} keys "
          f"({st['bytes'] / 1e6:.1f} MB raw, {out.stat().st_size / 1e6:.1f} MB file), "
          f"{st['gaps']} lost by seq, {sum(st['bad'].values())} bad, {st['errors']} errors")
    if args.stats:
        Path(args.stats).write_text(json.dumps(st, indent=1))
    return 0


def _convert(args: argparse.Namespace, P: Params, out: Path) -> int:
    """record --from: a raw recording with the Foxglove channels added."""
    if args.keys or args.duration or args.no_foxglove:
        return fail("--from converts a whole recording: no --keys, --duration or --no-foxglove")
    try:
        st = add_foxglove(args.from_file, out, P)
    except (RecordError, ExtraMissing) as exc:
        return fail(str(exc))
    except OSError as exc:
        return fail(f"cannot write {out}: {exc.strerror or exc}")
    if not args.quiet:
        print(f"wrote {st['messages']} raw messages and "
              f"{sum(st['foxglove'].values())} Foxglove messages into {out}")
    if args.stats:
        Path(args.stats).write_text(json.dumps(st, indent=1))
    return 0


def cmd_play(args: argparse.Namespace) -> int:
    try:
        topics = _topics_arg(args.keys)
        summary = read_summary(args.file)
    except (RecordError, ExtraMissing) as exc:
        return fail(str(exc))
    prefix = summary["metadata"].get("topoexplore", {}).get("prefix", "")
    raw = {t for t, c in summary["channels"].items() if c["encoding"] == MESSAGE_ENCODING}
    if not raw or not prefix:
        return fail(f"{args.file} holds no topoexplore recording (no raw msgpack channels)")
    target = _bus_keys(args).prefix if (args.namespace or args.robot) else prefix
    chosen = {t for t in raw if topics is None or topic_of(t, prefix) in topics}
    if not chosen:
        return fail(f"none of {', '.join(topics or [])} is in {args.file}")
    if (why := layout_error(args.file, chosen, prefix)) is not None:
        return fail(why)
    start_ns = summary["start_ns"] + to_ns(args.start)
    stop = threading.Event()
    restore = stop_on_signals(stop.set)
    bus = None
    sent = 0
    try:
        try:
            bus = _open(args, "play")
        except BusError as exc:
            return fail(str(exc))
        pubs: dict[str, Any] = {}
        t0 = None
        for key, data, log_ns in raw_messages(args.file, chosen, start_ns):
            if stop.is_set():
                break
            out_key = target + key[len(prefix):] if key.startswith(prefix + "/") else key
            if out_key not in pubs:
                pubs[out_key] = bus.publisher(out_key, reliable=True)
            if t0 is None:
                t0 = (time.monotonic(), log_ns)
            due = t0[0] + (log_ns - t0[1]) / 1e9 / args.rate
            while not stop.is_set() and (wait := due - time.monotonic()) > 0:
                stop.wait(min(wait, 0.2))
            if stop.is_set():
                break
            pubs[out_key].put(data)
            sent += 1
    finally:
        if bus is not None:
            bus.close()
        restore()
    print(f"played {sent} messages onto {target}" + (" (interrupted)" if stop.is_set() else ""))
    return 0


def build_record_parser(prog: str = "topoexplore record") -> argparse.ArgumentParser:
    p = OneLineParser(prog=prog, description="record the bus into an MCAP file (raw channels and "
                "Foxglove channels; see docs/recording.md)")
    p.add_argument("--out", "-o", required=True, help="the MCAP file to write")
    p.add_argument("--keys", default=None,
                   help=f"comma-separated topics (default: every key of the robot): "
                   f"{', '.join(TOPICS)}")
    p.add_argument("--duration", type=positive, default=None, help="stop after S seconds")
    p.add_argument("--no-foxglove", action="store_true", help="raw channels only")
    p.add_argument("--from", dest="from_file", default=None, metavar="FILE",
                   help="instead of the bus, a raw recording (run --record-raw, record "
                   "--no-foxglove): write it to --out with the Foxglove channels added")
    p.add_argument("--stats", default=None, help="write the recorder's counts as JSON here")
    p.add_argument("--quiet", "-q", action="store_true")
    add_bus_args(p)
    add_param_args(p)
    return p


def build_play_parser(prog: str = "topoexplore play") -> argparse.ArgumentParser:
    p = OneLineParser(prog=prog, description="publish a recording back onto the bus with its timing")
    p.add_argument("file", help="an MCAP file written by topoexplore record / run --record")
    p.add_argument("--rate", type=positive, default=1.0, help="speed factor (default 1)")
    p.add_argument("--keys", default=None, help="comma-separated topics (default: all)")
    p.add_argument("--start", type=non_negative, default=0.0,
                   help="skip the first S seconds of the recording")
    add_bus_args(p)
    return p


def main_record(argv: list[str] | None = None) -> int:
    try:
        args = build_record_parser().parse_args(argv)
    except UsageError as exc:
        return fail(str(exc))
    return cmd_record(args)


def main_play(argv: list[str] | None = None) -> int:
    try:
        args = build_play_parser().parse_args(argv)
    except UsageError as exc:
        return fail(str(exc))
    return cmd_play(args)
