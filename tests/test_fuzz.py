"""Property-based fuzzing of what crosses the bus (issue 14, item 5): every decoder, and the
conversion each service shell applies after it, on random bytes and on random maps shaped like
our messages (right field names, any values: NaN, Inf, huge numbers, wrong types, long lists).

A payload is either refused with :class:`MessageError` or it is a message that round-trips and
that the shell's conversion takes without an exception; nothing else may happen. The
controller's output stays finite and within its limits for any valid inputs.
"""

from __future__ import annotations

import math

import msgspec
import msgspec.inspect as mi
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from topoexplore.common import convert
from topoexplore.common import messages as m
from topoexplore.tools.bench.fuzz import EXAMPLES, KINDS, fuzz_payloads

SETTINGS = settings(max_examples=300, deadline=None,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])

# the conversion each shell applies to a decoded message of each type
SHELL_INPUT = {
    m.LaserScan: convert.scan_from_msg,
    m.Odometry: convert.odom_from_msg,
    m.PoseStamped: convert.truth_from_msg,
    m.TransformStamped: convert.correction_from_msg,
    m.Twist: convert.command_from_msg,
    m.OccupancyGrid: convert.grid_from_msg,
    m.TopoGraph: convert.graph_from_msg,
    m.Reliability: convert.beliefs_from_msg,
    m.Path: convert.route_from_msg,
    m.ExploreStatus: convert.status_from_msg,
    m.SimStatus: lambda msg: msg,
}
TYPES = list(m.MESSAGE_TYPES.values())

WILD_FLOATS = st.one_of(st.floats(allow_nan=True, allow_infinity=True),
                        st.sampled_from([0.0, -0.0, 1e-300, 1e300, -1e300, 0.5, 8.0, 2**53]))
WILD_INTS = st.one_of(st.integers(-(2**63), 2**64 - 1), st.sampled_from([-1, 0, 1, 181, 2**62]))
ANY_SCALAR = st.one_of(st.none(), st.booleans(), WILD_INTS, WILD_FLOATS, st.text(max_size=20),
                       st.binary(max_size=20))


def shaped(t: mi.Type, depth: int = 0) -> st.SearchStrategy:
    """Values shaped like type ``t``: mostly the right kind with wild contents, sometimes any
    scalar in its place."""
    if isinstance(t, mi.StructType):
        fields = {f.name: shaped(f.type, depth + 1) for f in t.fields}
        right = st.fixed_dictionaries({}, optional=fields)
    elif isinstance(t, mi.ListType) and depth < 4:
        right = st.lists(shaped(t.item_type, depth + 1), max_size=6)
    elif isinstance(t, mi.FloatType):
        right = WILD_FLOATS
    elif isinstance(t, mi.IntType):
        right = WILD_INTS
    elif isinstance(t, mi.StrType):
        right = st.text(max_size=30)
    elif isinstance(t, mi.BytesType):
        right = st.binary(max_size=64)
    elif isinstance(t, mi.BoolType):
        right = st.booleans()
    elif isinstance(t, mi.UnionType):
        right = st.one_of([shaped(u, depth + 1) for u in t.types])
    else:
        right = ANY_SCALAR
    return st.one_of(right, right, right, ANY_SCALAR)


VALID = EXAMPLES  # one valid message per type: the mutation test changes one leaf


def _leaves(value, path=()):
    if isinstance(value, dict):
        for k, v in value.items():
            yield from _leaves(v, (*path, k))
    elif isinstance(value, list) and value:
        for i, v in enumerate(value):
            yield from _leaves(v, (*path, i))
    else:
        yield path


def _set(value, path, new):
    if not path:
        return new
    value = list(value) if isinstance(value, list) else dict(value)
    value[path[0]] = _set(value[path[0]], path[1:], new)
    return value


def _check(payload: bytes, msg_type: type) -> None:
    try:
        msg = m.decode(payload, msg_type)
    except m.MessageError:
        return  # refused with a reason: what a shell counts and logs
    raw = m.encode(msg)  # round trip, compared as bytes (a NaN range is not == itself)
    assert m.encode(m.decode(raw, msg_type)) == raw
    SHELL_INPUT[msg_type](msg)


@pytest.mark.parametrize("msg_type", TYPES, ids=lambda t: t.__name__)
@SETTINGS
@given(payload=st.binary(max_size=512))
def test_random_bytes_are_refused_or_taken(msg_type, payload):
    _check(payload, msg_type)


@pytest.mark.parametrize("msg_type", TYPES, ids=lambda t: t.__name__)
@SETTINGS
@given(data=st.data())
def test_message_shaped_maps_are_refused_or_taken(msg_type, data):
    value = data.draw(shaped(mi.type_info(msg_type)))
    _check(msgspec.msgpack.encode(value), msg_type)


@pytest.mark.parametrize("msg_type", TYPES, ids=lambda t: t.__name__)
@SETTINGS
@given(data=st.data())
def test_valid_messages_with_one_wild_field_are_refused_or_taken(msg_type, data):
    base = msgspec.to_builtins(VALID[msg_type])
    path = data.draw(st.sampled_from(list(_leaves(base))))
    value = _set(base, path, data.draw(st.one_of(ANY_SCALAR, st.lists(ANY_SCALAR, max_size=3))))
    _check(msgspec.msgpack.encode(value), msg_type)


def test_the_valid_examples_are_valid():
    for t, msg in VALID.items():
        _check(m.encode(msg), t)
        assert m.decode(m.encode(msg), t) == msg


@SETTINGS
@given(v=WILD_FLOATS, w=WILD_FLOATS)
def test_no_nan_or_inf_command_gets_through(v, w):
    payload = msgspec.msgpack.encode({"header": {"stamp": {"sec": 1, "nanosec": 0},
                                                 "frame_id": "base_link"},
                                      "linear": {"x": v}, "angular": {"z": w}})
    try:
        msg = m.decode(payload, m.Twist)
    except m.MessageError:
        assert not (math.isfinite(v) and math.isfinite(w)) or max(abs(v), abs(w)) > 100.0
        return
    assert math.isfinite(msg.linear.x) and math.isfinite(msg.angular.z)


def test_the_bus_fuzzer_sends_only_refused_payloads_of_every_kind():
    import random

    for t in TYPES:
        got = fuzz_payloads(t, 120, random.Random(1))
        assert len(got) == 120 and {k for k, _ in got} >= set(KINDS) - {"missing"}
        for _kind, p in got:
            with pytest.raises(m.MessageError):
                m.decode(p, t)


def test_bench_fuzz_on_a_running_stack():
    """The bus fuzzer against the real stack (50 per key here; 10 000 in the benchmark)."""
    import subprocess
    import sys

    from tests.conftest import REPO

    r = subprocess.run([sys.executable, "-m", "topoexplore.tools.cli", "bench", "fuzz",
                        "--per-key", "50"], cwd=REPO, capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0 and "all checks hold" in r.stdout, r.stdout + r.stderr[-2000:]
