"""``topoexplore view``: a live Foxglove view of a running stack.

Starts a Foxglove WebSocket server (``foxglove-sdk``), subscribes to the robot's keys and serves
the channels of :mod:`tools.fox` live: the map, the scan, the frames, the trail, the
topological graph with ``id(P)`` labels, the plan and the status. In Foxglove: *Open
connection* -> *Foxglove WebSocket* -> ``ws://HOST:PORT``, then import the layout
``docs/foxglove-layout.json`` (or write it with ``--write-layout FILE``).

Bus samples are decoded (validated) on zenoh's threads and only the newest of each key is kept
for the converter thread, so a slow viewer never holds up the bus: at lockstep speed the view
shows the latest state, not every message (``record`` keeps every message).
"""

from __future__ import annotations

import argparse
import json
import math
import threading
import time
from pathlib import Path
from typing import Any

from topoexplore.common.bus import Bus, BusError
from topoexplore.common.keys import DEFAULT_ENDPOINT, TOPICS, Keys
from topoexplore.common.node import add_bus_args, add_param_args, params_from_args, stop_on_signals
from topoexplore.common.params import ParamError
from topoexplore.tools.argtypes import OneLineParser, UsageError, fail, port, positive
from topoexplore.tools.extras import ExtraMissing, require
from topoexplore.tools.fox import TOPICS as FOX_TOPICS
from topoexplore.tools.fox import FoxScene, channel_schema

VIEW_TOPICS = ("scan", "odom", "truth", "map", "topo", "reliability", "plan", "explore/status",
               "sim/status")
DEFAULT_PORT = 8765


def layout() -> Any:
    """The Foxglove layout: the 3D scene in the map frame beside the exploration status."""
    import foxglove.layouts as fl

    topics = {
        "/viz/map": fl.BaseRendererGridTopicSettings(visible=True, color_mode="rgba-fields",
                                                     frame_locked=True),
        "/viz/scan": fl.BaseRendererLaserScanTopicSettings(visible=True, point_size=3.0),
        "/viz/graph": fl.BaseRendererSceneUpdateTopicSettings(visible=True),
        "/viz/plan": fl.BaseRendererSceneUpdateTopicSettings(visible=True),
        "/viz/trail": fl.BaseRendererSceneUpdateTopicSettings(visible=True),
    }
    scene = fl.ThreeDeePanel(title="exploration", config=fl.ThreeDeeConfig(
        fixed_frame="map", follow_tf="map", follow_mode="follow-none", topics=topics,
        camera_state=fl.ThreeDeeCameraState(perspective=False, distance=30.0, phi=0.0,
                                            theta_offset=90.0)))
    status = fl.RawMessagesPanel(title="planner status",
                                 config=fl.RawMessagesConfig(topic_path="/status/explore"))
    sim = fl.RawMessagesPanel(title="simulator",
                              config=fl.RawMessagesConfig(topic_path="/status/sim"))
    side = fl.SplitContainer(direction="column", items=[
        fl.SplitItem(proportion=2, content=status), fl.SplitItem(proportion=1, content=sim)])
    return fl.Layout(content=fl.SplitContainer(direction="row", items=[
        fl.SplitItem(proportion=3, content=scene), fl.SplitItem(proportion=1, content=side)]))


def write_layout(path: str | Path) -> None:
    Path(path).write_text(json.dumps(json.loads(layout().to_json()), indent=1) + "\n")


def make_channels(context: Any = None) -> dict[str, Any]:
    """Every Foxglove channel of :data:`tools.fox.TOPICS`, made before a client can connect.

    foxglove-sdk 0.30.3 can advertise a channel made while a client is connected before it
    will accept a subscription to it: the client's subscribe is answered "Unknown channel ID"
    and that panel stays empty (4 of 51 runs of the view test when each channel was made at
    its first message; 0 of 50 with every channel made up front). Channels that exist when a
    client connects are advertised on connection, before the client's messages are read."""
    import foxglove

    out = {}
    for topic in FOX_TOPICS:
        enc, name, sch_enc, data = channel_schema(topic)
        out[topic] = foxglove.Channel(topic, message_encoding=enc, context=context,
                                      schema=foxglove.Schema(name=name, encoding=sch_enc,
                                                             data=data))
    return out


class LiveView:
    """Bus -> Foxglove channels: :meth:`offer` (zenoh threads) keeps the newest message per
    topic; the converter thread turns them into Foxglove messages and logs them."""

    def __init__(self, scene: FoxScene, context: Any = None):
        self.scene = scene
        self._latest: dict[str, Any] = {}
        self._cv = threading.Condition()
        self._stop = False
        self._channels = make_channels(context)
        self.counts: dict[str, int] = {}
        self.errors = 0
        self.last_error = ""
        self._thread = threading.Thread(target=self._loop, name="view", daemon=True)
        self._thread.start()

    def offer(self, topic: str, msg: Any) -> None:
        with self._cv:
            self._latest[topic] = msg
            self._cv.notify()

    def close(self) -> None:
        with self._cv:
            self._stop = True
            self._cv.notify()
        self._thread.join(timeout=5.0)

    def _loop(self) -> None:
        order = {t: i for i, t in enumerate(VIEW_TOPICS)}  # the graph after its reliability
        while True:
            with self._cv:
                self._cv.wait_for(lambda: self._latest or self._stop)
                if self._stop:
                    return
                batch = sorted(self._latest.items(), key=lambda kv: order.get(kv[0], 99))
                self._latest.clear()
            for topic, msg in batch:
                try:
                    for fox_topic, fmsg in self.scene.convert(topic, msg):
                        self._log(fox_topic, fmsg)
                except Exception as exc:  # noqa: BLE001 - the view goes on
                    self.errors += 1
                    self.last_error = f"{topic}: {type(exc).__name__}: {exc}"

    def _log(self, topic: str, fmsg: Any) -> None:
        data = json.dumps(fmsg).encode() if isinstance(fmsg, dict) else fmsg.encode()
        self._channels[topic].log(data, log_time=time.time_ns())
        self.counts[topic] = self.counts.get(topic, 0) + 1


def build_parser() -> argparse.ArgumentParser:
    p = OneLineParser(prog="topoexplore view", description="live Foxglove view of a running stack")
    p.add_argument("--host", default="127.0.0.1",
                   help="address to serve on (default 127.0.0.1; 0.0.0.0 for other machines)")
    p.add_argument("--port", type=port, default=DEFAULT_PORT,
                   help=f"WebSocket port (default {DEFAULT_PORT}; 0: any free port)")
    p.add_argument("--duration", type=positive, default=None, help="stop after S seconds")
    p.add_argument("--write-layout", metavar="FILE", default=None,
                   help="write the Foxglove layout to FILE and exit")
    add_bus_args(p)
    add_param_args(p)
    return p


def main(argv: list[str] | None = None) -> int:
    try:
        args = build_parser().parse_args(argv)
        require("foxglove", what="topoexplore view")
        if args.write_layout:
            write_layout(args.write_layout)
            return 0
        P = params_from_args(args)
    except (UsageError, ParamError, ExtraMissing, ValueError) as exc:
        return fail(str(exc))
    except OSError as exc:
        return fail(f"cannot write {args.write_layout}: {exc.strerror or exc}")
    return serve(args, Keys(P.bus.namespace, P.bus.robot),
                 FoxScene(P.laser.offset, P.reliability.p_reliable))


def serve(args: argparse.Namespace, keys: Keys, scene: FoxScene) -> int:
    import foxglove

    stop = threading.Event()
    restore = stop_on_signals(stop.set)
    bus = server = None
    view = LiveView(scene)  # every channel exists before a client can connect
    try:
        try:
            server = foxglove.start_server(name=f"topoexplore {keys.prefix}", host=args.host,
                                           port=args.port)
        except Exception as exc:  # noqa: BLE001 - a taken port, a bad host
            return fail(f"cannot serve on {args.host}:{args.port}: {exc}")
        try:
            connect = args.connect or (None if args.zenoh_config else DEFAULT_ENDPOINT)
            bus = Bus.client(connect, name="view", config_file=args.zenoh_config,
                             wait_for_router=True)  # a view may start before its router
        except BusError as exc:
            return fail(str(exc))
        for topic in VIEW_TOPICS:
            bus.subscribe(keys.topic(topic), TOPICS[topic],
                          lambda msg, k, t=topic: view.offer(t, msg))
        print(f"view of {keys.prefix} on ws://{args.host}:{server.port} (Foxglove: open "
              f"connection, Foxglove WebSocket; layout docs/foxglove-layout.json)", flush=True)
        t_end = time.monotonic() + args.duration if args.duration else math.inf
        while not stop.is_set() and time.monotonic() < t_end:
            stop.wait(min(0.5, max(0.0, t_end - time.monotonic())))
    finally:
        if bus is not None:
            bus.close()
        view.close()
        if server is not None:
            server.stop()
        restore()
    shown = ", ".join(f"{t} {n}" for t, n in sorted(view.counts.items())) or "nothing"
    print(f"view stopped: {shown}; {view.errors} errors"
          + (f" (last: {view.last_error})" if view.errors else ""))
    return 0
