"""``topoexplore teleop``: drive the robot from the keyboard in a terminal.

    w / s   faster / slower (backwards below 0)      a / d   turn left / right
    space   stop                                      q       quit (also Ctrl-C, Ctrl-D)

Publishes ``cmd_vel`` at ``--rate``. Safe by construction:
- **silence stops**: the command holds only while keys come (keep a key pressed: the
  terminal repeats it); after ``--hold`` seconds without a key the robot is sent zero;
- **exit stops**: on q, Ctrl-C, Ctrl-D, SIGTERM or an error, zero is sent three times and the
  terminal is restored;
- speeds are clamped to the controller's ``v_max`` / ``w_max`` (``--params`` / ``--set``).

Against a full stack the controller publishes too; use the ``sim-only`` profile
(``topoexplore up --profile sim-only``) or stop the controller. The key handling
(:class:`Teleop`) is pure and unit-tested; the shell reads the terminal and publishes.
"""

from __future__ import annotations

import argparse
import math
import os
import random
import select
import sys
import threading
import time
from dataclasses import dataclass

from topoexplore.common import convert
from topoexplore.common import messages as m
from topoexplore.common.bus import Bus, BusError
from topoexplore.common.domain import Command
from topoexplore.common.keys import DEFAULT_ENDPOINT, Keys
from topoexplore.common.node import add_bus_args, add_param_args, params_from_args, stop_on_signals
from topoexplore.common.params import ParamError
from topoexplore.tools.argtypes import OneLineParser, UsageError, fail, positive
from topoexplore.tools.clock import RobotClock

PROG = "topoexplore teleop"
HELP = "w/s faster/slower, a/d left/right, space stop, q quit"


@dataclass
class Teleop:
    """Keys -> (v, w), with the silence rule (pure: time comes in as an argument)."""

    v_step: float = 0.05  # [m/s] per key
    w_step: float = 0.2  # [rad/s] per key
    v_max: float = 0.2  # [m/s]
    w_max: float = 1.0  # [rad/s]
    hold: float = 1.0  # [s] without a key -> stop
    v: float = 0.0
    w: float = 0.0
    last_key: float = -math.inf  # [s]
    quit: bool = False

    def key(self, ch: str, t: float) -> None:
        self.last_key = t
        if ch in ("w", "W"):
            self.v += self.v_step
        elif ch in ("s", "S"):
            self.v -= self.v_step
        elif ch in ("a", "A"):
            self.w += self.w_step
        elif ch in ("d", "D"):
            self.w -= self.w_step
        elif ch in (" ", "x", "X"):
            self.v = self.w = 0.0
        elif ch in ("q", "Q", "\x03", "\x04"):  # q, Ctrl-C, Ctrl-D
            self.v = self.w = 0.0
            self.quit = True
        self.v = max(-self.v_max, min(self.v_max, round(self.v, 6)))
        self.w = max(-self.w_max, min(self.w_max, round(self.w, 6)))

    def command(self, t: float) -> tuple[float, float]:
        """The command to send at time t: zero after `hold` seconds of silence (and the speeds
        reset, so that the next key starts from standstill)."""
        if t - self.last_key > self.hold:
            self.v = self.w = 0.0
        return self.v, self.w


def build_parser() -> argparse.ArgumentParser:
    p = OneLineParser(prog="topoexplore teleop", description=__doc__,
                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--rate", type=positive, default=10.0, help="cmd_vel rate [Hz] (default 10)")
    p.add_argument("--hold", type=positive, default=1.0,
                   help="seconds without a key before the robot is stopped (default 1)")
    p.add_argument("--v-step", type=positive, default=0.05, help="[m/s] per key (default 0.05)")
    p.add_argument("--w-step", type=positive, default=0.2, help="[rad/s] per key (default 0.2)")
    add_bus_args(p)
    add_param_args(p)
    return p


def main(argv: list[str] | None = None) -> int:
    try:
        args = build_parser().parse_args(argv)
        P = params_from_args(args)
    except (UsageError, ParamError, ValueError) as exc:
        return fail(str(exc), PROG)
    if not os.isatty(sys.stdin.fileno()):
        return fail("needs a terminal (stdin is not a TTY)", PROG)
    state = Teleop(v_step=args.v_step, w_step=args.w_step, v_max=P.controller.v_max,
                   w_max=P.controller.w_max, hold=args.hold)
    keys = Keys(P.bus.namespace, P.bus.robot)
    try:
        connect = args.connect or (None if args.zenoh_config else DEFAULT_ENDPOINT)
        bus = Bus.client(connect, name="teleop", config_file=args.zenoh_config)
    except BusError as exc:
        return fail(str(exc), PROG)
    try:
        return _drive(bus, keys, state, args.rate)
    finally:
        bus.close()


def _drive(bus: Bus, keys: Keys, state: Teleop, rate: float) -> int:
    import termios
    import tty

    pub = bus.publisher(keys.cmd_vel, m.Twist, reliable=True)
    clock = RobotClock(bus, keys)  # commands carry the robot's time, or the sim drops them
    seq = random.randrange(1 << 30)
    stop = threading.Event()
    restore = stop_on_signals(stop.set)
    fd = sys.stdin.fileno()
    saved = termios.tcgetattr(fd)

    def send(v: float, w: float) -> None:
        nonlocal seq
        seq += 1
        hdr = m.header(seq, clock.now() or 0.0, "base_link")
        pub.put(convert.command_to_msg(Command(v, w), hdr))  # linear.x, angular.z

    print(f"teleop on {keys.cmd_vel}: {HELP}", flush=True)
    try:
        tty.setcbreak(fd)
        t_next = time.monotonic()
        while not stop.is_set() and not state.quit:
            timeout = max(0.0, t_next - time.monotonic())
            ready, _, _ = select.select([fd], [], [], timeout)
            if ready:
                data = os.read(fd, 32)
                if not data:  # the terminal closed
                    break
                for ch in data.decode(errors="ignore"):
                    state.key(ch, time.monotonic())
            if time.monotonic() >= t_next:
                v, w = state.command(time.monotonic())
                send(v, w)
                wait = "" if clock.now() is not None else "  (no odometry yet)"
                sys.stdout.write(f"\rv {v:+.2f} m/s  w {w:+.2f} rad/s{wait}   ")
                sys.stdout.flush()
                t_next += 1.0 / rate
    finally:
        for _ in range(3):  # safe on any exit: the robot is told to stop
            send(0.0, 0.0)
            time.sleep(0.02)
        termios.tcsetattr(fd, termios.TCSADRAIN, saved)
        restore()
        print("\nteleop: stopped the robot", flush=True)
    return 0
