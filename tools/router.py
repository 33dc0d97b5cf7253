"""A Zenoh router process (there is no zenohd on PyPI: a Python session in router mode is one).

``python -m topoexplore.tools.router --listen tcp/127.0.0.1:7447`` (the supervisor starts it).
"""

from __future__ import annotations

import argparse
import sys
import threading

from topoexplore.common.bus import Bus, BusError, init_logging
from topoexplore.common.keys import DEFAULT_ENDPOINT
from topoexplore.common.node import ignore_further_signals, stop_on_signals


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="topoexplore router", description=__doc__)
    ap.add_argument("--listen", default=DEFAULT_ENDPOINT, help="endpoint(s) to listen on")
    ap.add_argument("--zenoh-config", default=None, help="Zenoh JSON5 config file (base)")
    ap.add_argument("--shared-memory", action="store_true",
                    help="zenoh's shared-memory transport on (bus.shared_memory)")
    args = ap.parse_args(argv)
    init_logging()
    stop = threading.Event()
    stop_on_signals(stop.set)  # no lock in a signal handler: back-to-back signals deadlocked
    try:
        bus = Bus.router(args.listen, config_file=args.zenoh_config,
                         shared_memory=args.shared_memory)
    except BusError as exc:
        print(f"topoexplore router: {exc}", file=sys.stderr)
        return 2
    print(f"router listening on {args.listen}", flush=True)
    try:
        stop.wait()
    finally:
        ignore_further_signals()
        bus.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
