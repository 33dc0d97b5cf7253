"""Read service state from a running stack (state queryables) and turn it into typed values."""

from __future__ import annotations

from typing import Any

import msgspec
import numpy as np

from topoexplore.common import convert
from topoexplore.common import messages as m
from topoexplore.common.bus import Bus
from topoexplore.common.domain import Belief, Graph
from topoexplore.common.grid import GridGeometry
from topoexplore.common.keys import Keys


class StateError(RuntimeError):
    """No (valid) state reply from a service."""


def fetch_state(bus: Bus, keys: Keys, service: str, timeout: float = 3.0) -> dict[str, Any]:
    replies = bus.get(keys.state(service), timeout=timeout)
    for _key, payload, err in replies:
        if payload is not None:
            try:
                value = msgspec.msgpack.decode(payload)
            except Exception as exc:
                raise StateError(f"{service} state reply is not msgpack: {exc}") from None
            if not isinstance(value, dict):
                raise StateError(f"{service} state reply is not a map")
            return value
        if err:
            raise StateError(f"{service} state query failed: {err}")
    raise StateError(f"no reply from {keys.state(service)} within {timeout:g} s "
                     f"(is the stack running on this endpoint and namespace?)")


def upgrade_header(value: Any) -> Any:
    """A message written before the headers took the ROS shape (``{seq, stamp: float, frame,
    src_seq}``, e.g. in an older run's topology.json) with its header in today's shape; any
    other value as it is."""
    h = value.get("header") if isinstance(value, dict) else None
    if not isinstance(h, dict) or "frame" not in h or isinstance(h.get("stamp"), dict):
        return value
    try:
        stamp = m.stamp(float(h.get("stamp", 0.0)))
    except (TypeError, ValueError):
        return value  # not a number: left for validation to refuse
    new = {"stamp": {"sec": stamp.sec, "nanosec": stamp.nanosec}, "frame_id": h["frame"],
           **{k: h[k] for k in ("seq", "src_seq") if k in h}}
    return {**value, "header": new}


def as_message(value: Any, msg_type: type) -> Any:
    """A message that came nested in a state reply or a saved run (as a dict) -> validated
    struct (a header of the shape before 2026-12-04 is read too: :func:`upgrade_header`)."""
    if value is None:
        return None
    value = upgrade_header(value)
    try:
        return m.decode(msgspec.msgpack.encode(value), msg_type)
    except m.MessageError as exc:
        raise StateError(str(exc)) from None


def map_from_state(state: dict[str, Any]) -> tuple[np.ndarray, GridGeometry]:
    grid = as_message(state.get("map"), m.OccupancyGrid)
    if grid is None:
        raise StateError("the mapper has no map yet")
    g = convert.grid_from_msg(grid)
    return g.data.copy(), g.geom


def graph_from_state(value: Any) -> Graph | None:
    """The topological graph nested in a state reply (or a saved topology.json), as a domain
    Graph; None when absent."""
    msg = as_message(value, m.TopoGraph)
    return None if msg is None else convert.graph_from_msg(msg)


def beliefs_from_state(value: Any) -> list[Belief] | None:
    """The reliability message nested in a state reply, as a list of Belief; None when absent."""
    msg = as_message(value, m.Reliability)
    return None if msg is None else convert.beliefs_from_msg(msg)
