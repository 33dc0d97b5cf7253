"""``topoexplore keys pub`` and ``keys set``: write to a running stack.

- ``keys pub KEY FIELD=VALUE... [--rate HZ] [--count N] [--duration S]``: one message of the
  key's type (or a stream at a rate), like ``ros2 topic pub``. Fields are the ROS message's
  (``linear.x=0.2``, ``header.frame_id=odom``); values are YAML (``blacklisted=[3, 4]``,
  ``poses=[{pose: {position: {x: 1, y: 2}}}]``); what is not given is zero (a quaternion:
  identity), in list items too. For ``cmd_vel`` (Twist) ``v=`` and ``w=`` are short for
  ``linear.x=`` and ``angular.z=``. The header is filled in (seq counting up from a random
  start, the stamp of the robot's latest odometry (:mod:`tools.clock`; 0 if none is seen), the
  topic's frame_id) unless given: ``header.stamp=12.5`` takes seconds as a float (made into
  ``{sec: 12, nanosec: 500000000}``), ``header.stamp.sec=12 header.stamp.nanosec=5`` the ROS
  fields (a part not given is 0). The message is validated exactly as a service would decode
  it before anything is sent.
- ``keys set SERVICE section.name=VALUE``: change a parameter of a running service through its
  ``<ns>/<robot>/<service>/params`` queryable (``common.node``); the answer gives the old and
  the new value, or the service's one-line refusal (a bad value, or a parameter that cannot
  change while it runs). ``keys set SERVICE`` alone lists what can change live.

The message building (:func:`parse_assignments`, :func:`build_message`) is pure.
"""

from __future__ import annotations

import argparse
import math
import random
import time
from typing import Any
from urllib.parse import quote

import msgspec
import msgspec.inspect as mi
import yaml

from topoexplore.common import messages as m
from topoexplore.common.bus import Bus
from topoexplore.common.keys import Keys, type_for_key
from topoexplore.tools.clock import RobotClock

# the frame a hand-made message of a topic is in (REP-105)
FRAMES = {"scan": "laser", "odom": "odom", "cmd_vel": "base_link"}


class PubError(ValueError):
    """A bad assignment or a message that would not validate (one line)."""


def parse_value(text: str) -> Any:
    """``0.2`` -> 0.2, ``[1, 2]`` -> [1, 2], ``true`` -> True, ``abc`` -> 'abc' (YAML)."""
    try:
        return yaml.safe_load(text) if text.strip() else ""
    except yaml.YAMLError as exc:
        raise PubError(f"cannot read value {text!r}: {str(exc).splitlines()[0]}") from None


def parse_assignments(items: list[str]) -> dict[str, Any]:
    """``["linear.x=0.2", "header.stamp=3"]`` -> ``{"linear": {"x": 0.2}, "header":
    {"stamp": 3}}``."""
    out: dict[str, Any] = {}
    for item in items:
        path, eq, text = item.partition("=")
        parts = path.strip().split(".")
        if not eq or not all(p.isidentifier() for p in parts):
            raise PubError(f"expected FIELD=VALUE (a.b=1), got {item!r}")
        node = out
        for p in parts[:-1]:
            nxt = node.setdefault(p, {})
            if not isinstance(nxt, dict):
                raise PubError(f"{path}: {p} is given a value and fields at once")
            node = nxt
        if isinstance(node.get(parts[-1]), dict):
            raise PubError(f"{path}: given a value and fields at once")
        node[parts[-1]] = parse_value(text)
    return out


def _merge(base: dict[str, Any], extra: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for k, v in extra.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def zero_fields(msg_type: type) -> dict[str, Any]:
    """The required fields of a message type at zero ("" for text, [] for lists, nested
    structs likewise), as ``ros2 topic pub`` fills what it is not given."""
    return _zero(mi.type_info(msg_type))


def _zero(t: Any) -> Any:
    if isinstance(t, mi.StructType):
        return {f.name: _zero(f.type) for f in t.fields if f.required}
    if isinstance(t, (mi.FloatType, mi.IntType)):
        return 0
    if isinstance(t, mi.BoolType):
        return False
    if isinstance(t, mi.StrType):
        return ""
    if isinstance(t, (mi.ListType, mi.BytesType)):
        return [] if isinstance(t, mi.ListType) else b""
    return None


def _filled(t: Any, given: Any) -> Any:
    """``given`` with the required fields it lacks at zero, in nested structs and in the
    struct items of lists (a path's poses) too."""
    if isinstance(t, mi.StructType) and isinstance(given, dict):
        return {f.name: _filled(f.type, given[f.name]) if f.name in given else _zero(f.type)
                for f in t.fields if f.required or f.name in given}
    if isinstance(t, mi.ListType) and isinstance(given, list):
        return [_filled(t.item_type, v) for v in given]
    return given


def check_names(msg_type: type, fields: dict[str, Any], path: str = "") -> None:
    """PubError for a field the type does not have (a typo must not be dropped silently)."""
    info = mi.type_info(msg_type)
    known = {f.name: f.type for f in info.fields}
    for k, v in fields.items():
        if k not in known:
            short = " or v, w" if msg_type is m.Twist and not path else ""
            raise PubError(f"{msg_type.__name__} has no field {path + k!r} (fields: "
                           f"{', '.join(known)}{short})")
        t = known[k]
        if isinstance(v, dict) and isinstance(t, mi.StructType):
            check_names(t.cls, v, f"{path}{k}.")
        elif isinstance(v, list) and isinstance(t, mi.ListType) \
                and isinstance(t.item_type, mi.StructType):
            for i, item in enumerate(v):
                if isinstance(item, dict):
                    check_names(t.item_type.cls, item, f"{path}{k}.{i}.")


# cmd_vel's shorthands: a planar base's (v, w) in geometry_msgs/Twist's fields
TWIST_SHORT = {"v": ("linear", "x"), "w": ("angular", "z")}


def expand_shorthands(msg_type: type, fields: dict[str, Any]) -> dict[str, Any]:
    """Twist: ``v`` -> ``linear.x``, ``w`` -> ``angular.z`` (PubError if both are given)."""
    if msg_type is not m.Twist or not TWIST_SHORT.keys() & fields.keys():
        return fields
    out = dict(fields)
    for short, (vec, axis) in TWIST_SHORT.items():
        if short not in out:
            continue
        part = out.get(vec, {})
        if not isinstance(part, dict) or axis in part:
            raise PubError(f"{short}= and {vec}.{axis}= (or {vec}=) are the same field: give "
                           "one")
        out[vec] = {**part, axis: out.pop(short)}
    return out


def stamp_fields(value: Any) -> dict[str, Any]:
    """A stamp as given -> ``{sec, nanosec}``: seconds as a number (``12.5``, ``1e6``) or the
    ROS fields (a part not given is 0)."""
    if isinstance(value, dict):
        return {"sec": 0, "nanosec": 0, **value}
    try:
        t = float(value) if not isinstance(value, bool) else math.nan
    except (TypeError, ValueError):
        t = math.nan
    if not (math.isfinite(t) and 0.0 <= t <= 1e12):
        raise PubError(f"header.stamp={value!r}: expected seconds >= 0 (12.5) or "
                       "header.stamp.sec=.. header.stamp.nanosec=..")
    s = m.stamp(t)
    return {"sec": s.sec, "nanosec": s.nanosec}


def build_message(msg_type: type, fields: dict[str, Any], seq: int, frame: str = "map",
                  stamp: float = 0.0) -> Any:
    """A message of ``msg_type`` from ``fields`` (nested; what is not given is zero) with the
    header filled in (stamped ``stamp`` [s], frame_id ``frame``); validated as a service
    decodes it (PubError with the reason otherwise)."""
    fields = expand_shorthands(msg_type, fields)
    check_names(msg_type, fields)
    hdr = fields.get("header")
    if isinstance(hdr, dict) and "stamp" in hdr:
        fields = {**fields, "header": {**hdr, "stamp": stamp_fields(hdr["stamp"])}}
    s = m.stamp(stamp)
    base = {"header": {"stamp": {"sec": s.sec, "nanosec": s.nanosec}, "frame_id": frame,
                       "seq": seq, "src_seq": -1}}
    given = _filled(mi.type_info(msg_type), _merge(base, fields))
    try:
        msg = msgspec.convert(given, msg_type, strict=False)  # "1e6": a YAML str
        return m.decode(m.encode(msg), msg_type)
    except (msgspec.ValidationError, m.MessageError) as exc:
        raise PubError(f"not a valid {msg_type.__name__}: {exc}") from None


def cmd_pub(args: argparse.Namespace, bus: Bus, keys: Keys, stop: Any) -> int:
    from topoexplore.tools.keys import KeyToolError, _err, _out, resolve_key

    key = resolve_key(args.key, keys)
    if "*" in key:
        raise KeyToolError(f"keys pub needs one key, not a wildcard ({key})")
    msg_type = type_for_key(key)
    if msg_type is None:
        raise KeyToolError(f"{key} carries none of our message types (topics: scan, cmd_vel, ...)")
    fields = parse_assignments(args.fields)
    seq0 = random.randrange(1 << 30)  # a fresh seq: the simulator applies a cmd_vel once per seq
    frame = FRAMES.get(key.rsplit("/", 1)[-1], "map")
    build_message(msg_type, fields, seq0, frame)  # check before anything is sent
    given = fields.get("header", {})  # a dict: build_message took it
    fixed_seq = "seq" in given
    clock = None if "stamp" in given else RobotClock(bus, keys)
    pub = bus.publisher(key, msg_type, reliable=True)
    deadline = time.monotonic() + args.wait
    while not pub.matched and time.monotonic() < deadline and not stop.event.is_set():
        stop.event.wait(0.02)  # a put before the subscriber is known may be lost
    if clock is not None and clock.wait(max(0.0, deadline - time.monotonic())) is None:
        _err(f"no odometry on {keys.topic('odom')}: stamp 0 (a simulator or driver drops a "
             "cmd_vel stamped long before its clock)")
    count = args.count if args.count is not None else (None if args.rate else 1)
    t_end = time.monotonic() + args.duration if args.duration else math.inf
    period = 1.0 / args.rate if args.rate else 0.0
    sent, t_next = 0, time.monotonic()
    while not stop.event.is_set() and (count is None or sent < count) \
            and time.monotonic() < t_end:
        stamp = (clock.now() if clock is not None else None) or 0.0
        msg = build_message(msg_type, fields, seq0 if fixed_seq else seq0 + sent, frame, stamp)
        pub.put(msg)
        sent += 1
        t_next += period
        if count is not None and sent >= count:
            break
        stop.event.wait(max(0.0, t_next - time.monotonic()))
    time.sleep(0.1)  # let the last put leave before the session closes
    _out(f"published {sent} {msg_type.__name__} on {key}"
         + ("" if pub.matched else " (no subscriber was seen)"))
    return 0


def cmd_set(args: argparse.Namespace, bus: Bus, keys: Keys, stop: Any) -> int:
    from topoexplore.tools.keys import KeyToolError, _err, _get, _out

    svc = args.service.strip()
    if not svc.isidentifier():
        raise KeyToolError(f"bad service name {svc!r}")
    selector = f"{keys.prefix}/{svc}/params"
    if args.assignment:
        name, eq, value = args.assignment.partition("=")
        if not eq or len(name.split(".")) != 2:
            raise KeyToolError(f"expected section.name=VALUE, got {args.assignment!r}")
        selector += f"?set={quote(args.assignment, safe='')}"
    replies = _get(bus, selector, args.timeout)
    for _k, payload, err in replies:
        if payload is None:
            _err(f"{svc}: {err}")
            return 1
        ans = msgspec.msgpack.decode(payload)
        if not isinstance(ans, dict):
            continue
        if ans.get("error"):
            _err(f"{svc}: {ans['error']}")
            return 1
        if "old" in ans:
            _out(f"{svc}: {ans['name']}: {ans['old']!r} -> {ans['new']!r}")
        else:
            live = ", ".join(ans.get("live") or []) or "none"
            _out(f"{svc}: parameters that change live: {live}")
        return 0
    _err(f"no reply from {selector.split('?')[0]} within {args.timeout:g} s (service not running?)")
    return 1
