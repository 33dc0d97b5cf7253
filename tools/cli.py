"""``topoexplore`` — the one console command, with subcommands.

    topoexplore run      explore a world with the whole stack, write a report and a picture
    topoexplore up       start a launch profile under the supervisor (Ctrl-C stops everything)
    topoexplore worlds   list the built-in worlds; worlds generate: write a generated world
    topoexplore keys     live keys: list | echo KEY | hz KEY | get SERVICE | pub KEY | set SERVICE
    topoexplore map      save the live map as a ROS map_server PGM + YAML pair
    topoexplore render   make a PNG from a saved run directory or a running stack
    topoexplore bench    benchmarks: stages | explore | inproc | robust | oracle | posetrace | record | faults | fuzz | hangs | codec
    topoexplore router   run a Zenoh router
    topoexplore bridge   ros2: a ROS 2 robot's scan and odom in, our cmd_vel and map out (CDR)
    topoexplore warmup   compile the numba kernels once, before the services start
    topoexplore record   record the bus into an MCAP file; play publishes one back
    topoexplore replay   run services on a recording's inputs and compare their outputs
    topoexplore view     live Foxglove view; teleop drives from the keyboard

Every error in the command line, a file or a parameter prints one line and exits non-zero.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import threading


def _err(text: str, code: int = 2) -> int:
    print(f"topoexplore: {text}", file=sys.stderr)
    return code


class _WorldsArgError(Exception):
    pass


class _WorldsParser(argparse.ArgumentParser):
    """`worlds generate` arguments: an error is one line (no usage block), exit 2."""

    def error(self, message: str):  # type: ignore[override]
        raise _WorldsArgError(message)


def _generate_parser() -> argparse.ArgumentParser:
    from topoexplore.sim.generate import DEFAULT_SIZES, MAX_NOISE, SIZE_RANGE, STYLES

    sizes = ", ".join(f"{k} {w:g} x {h:g}" for k, (w, h) in DEFAULT_SIZES.items())
    ap = _WorldsParser(prog="topoexplore worlds generate",
                       description="Write a generated world (deterministic by seed): a TOML "
                       "world, or with --slam-noise a ROS map_server map (PGM + YAML) degraded "
                       "like a SLAM map plus a TOML wrapper with the start pose. "
                       "docs/worlds.md, 'Generated worlds'.")
    ap.add_argument("--style", required=True, choices=STYLES)
    ap.add_argument("--seed", required=True, type=int, help="integer >= 0")
    ap.add_argument("--size", nargs=2, type=float, metavar=("W", "H"),
                    help=f"[m] {SIZE_RANGE[0]:g}..{SIZE_RANGE[1]:g} per side, rounded to 0.1 m "
                    f"(default: {sizes})")
    ap.add_argument("--slam-noise", type=int, metavar="LEVEL",
                    help=f"write a SLAM-like map, noise 0 (clean raster) .. {MAX_NOISE}")
    ap.add_argument("--out", required=True, metavar="DIR", help="output directory (created)")
    return ap


def cmd_worlds_generate(argv: list[str]) -> int:
    from topoexplore.sim.generate import (
        GenerateError,
        check_arguments,
        generate,
        write_generated,
    )

    try:
        args = _generate_parser().parse_args(argv)
        check_arguments(args.style, args.seed, args.size, args.slam_noise)
        gen = generate(args.style, args.seed, args.size)
        path = write_generated(gen, args.out, args.slam_noise)
    except (_WorldsArgError, GenerateError) as exc:
        return _err(f"worlds generate: {exc}")
    w = gen.world
    print(f"wrote {path}: {w.description}; start {tuple(round(v, 2) for v in w.robot_pose)}")
    return 0


def cmd_worlds(args: argparse.Namespace) -> int:
    from topoexplore.sim.world import WorldError, builtin_worlds, load_world

    if args.action is not None:
        if args.check:
            return _err("worlds: give either --check WORLD or an action, not both")
        if args.action != "generate":
            return _err(f"worlds: unknown action {args.action!r} (expected: generate)")
        return cmd_worlds_generate(args.rest)
    if args.check:
        try:
            w = load_world(args.check)
        except WorldError as exc:
            return _err(str(exc))
        print(f"{w.name}: {w.size[0]:g} m x {w.size[1]:g} m, {len(w.segments)} wall segments, "
              f"{len(w.circles)} circles, start {tuple(round(v, 2) for v in w.robot_pose)}")
        return 0
    worlds = builtin_worlds()
    width = max(len(n) for n in worlds)
    for name, text in worlds.items():
        print(f"{name:<{width}}  {text}")
    return 0


def _world_error() -> type[Exception]:
    """sim.world's WorldError when the simulator is installed (a robot install has none)."""
    try:
        from topoexplore.sim.world import WorldError
    except ImportError:
        return ValueError
    return WorldError


def cmd_up(args: argparse.Namespace) -> int:
    from topoexplore.common.bus import BusError, check_config_file
    from topoexplore.common.checkpoint import clear_state_dir
    from topoexplore.common.keys import Keys
    from topoexplore.common.node import params_from_args, stop_on_signals
    from topoexplore.common.params import ParamError
    from topoexplore.tools.extras import ExtraMissing, require
    from topoexplore.tools.launch.core import ProfileError, load_profile
    from topoexplore.tools.launch.supervisor import (
        Supervisor,
        print_line,
        profile_path,
        stamped,
    )

    WorldError = _world_error()
    if args.state_dir:
        args.set = [*args.set, f"runtime.state_dir={json.dumps(args.state_dir)}"]
    try:
        profile = load_profile(profile_path(args.profile))
        params = params_from_args(args)
        if any(s.module.startswith("topoexplore.sim.") for s in profile.processes):
            require("pymunk", what=f"the {profile.name!r} profile (it runs the simulator)")
            from topoexplore.sim.world import load_world

            load_world(args.world or params.sim.world)  # else the sim would restart forever
        for f in (args.zenoh_config, args.router_config):
            if f:
                check_config_file(f)
        clear_state_dir(params.runtime.state_dir)  # a new session: no earlier state
    except (ProfileError, ParamError, ExtraMissing, WorldError, BusError) as exc:
        return _err(str(exc))
    except OSError as exc:
        return _err(f"state dir {params.runtime.state_dir}: {exc.strerror or exc}")
    overrides = list(args.set)
    if args.lockstep:
        overrides.append("runtime.lockstep=true")
    if args.world:
        overrides.append(f'sim.world="{args.world}"')
    keys = Keys(params.bus.namespace, params.bus.robot)
    sup = Supervisor(profile, keys, params.bus.connect, params_file=args.params,
                     overrides=overrides, zenoh_config=args.zenoh_config,
                     log_level=args.log_level, router_config=args.router_config)
    stop = threading.Event()
    stop_on_signals(stop.set, sup.interrupted.set)

    def say(line: str) -> None:  # survives `up | head`: a closed stdout must not skip the stop
        print_line(stamped(line))
    say(f"[supervisor] profile {profile.name}: {', '.join(s.name for s in profile.processes)} "
        f"on {params.bus.connect} ({keys.prefix})")
    try:
        ok = sup.start()
        if ok:
            say("[supervisor] all processes up; Ctrl-C to stop")
        sup.run_until(stop)
    except BusError as exc:
        return _err(str(exc))
    finally:
        say("[supervisor] stopping")
        sup.stop()
        say(f"[supervisor] stopped ({sup.restarts} restarts)")
    return 0


def cmd_map_save(args: argparse.Namespace) -> int:
    from topoexplore.common.bus import Bus, BusError
    from topoexplore.common.mapio import MapIOError, write_map_server
    from topoexplore.common.node import params_from_args
    from topoexplore.common.params import ParamError
    from topoexplore.tools.livestate import StateError, fetch_state, map_from_state

    try:
        params = params_from_args(args)
        from topoexplore.common.keys import Keys

        keys = Keys(params.bus.namespace, params.bus.robot)
        with Bus.client(params.bus.connect, config_file=args.zenoh_config) as bus:
            grid, geom = map_from_state(fetch_state(bus, keys, "mapper", args.timeout))
        yml, pgm = write_map_server(args.output, grid, geom, params.mapper.p_free,
                                    params.mapper.p_occ)
    except (ParamError, BusError, StateError, MapIOError) as exc:
        return _err(str(exc))
    print(f"wrote {yml} and {pgm} ({geom.width}x{geom.height} cells at {geom.resolution} m)")
    return 0


def build_parser() -> argparse.ArgumentParser:
    from topoexplore.common.node import LOG_LEVELS, add_bus_args, add_param_args

    ap = argparse.ArgumentParser(prog="topoexplore", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="command", metavar="COMMAND")

    from topoexplore.tools import run as runner

    runner.add_arguments(sub.add_parser("run", help="explore a world, write report + picture"))

    up = sub.add_parser("up", help="start a launch profile under the supervisor")
    up.add_argument("--profile", default="sim",
                    help="profile name in deploy/profiles (sim, robot, sim-only, mapping) or a path")
    up.add_argument("--world", default=None, help="world for the simulator")
    up.add_argument("--lockstep", action="store_true", help="lockstep simulation")
    up.add_argument("--log-level", default=None, choices=LOG_LEVELS,
                    help="log level of every service (default INFO)")
    up.add_argument("--router-config", default=None, metavar="FILE",
                    help="Zenoh config of the profile's router (e.g. "
                         "deploy/zenoh/secure-router.json5); --zenoh-config is the services'")
    up.add_argument("--state-dir", default=None, metavar="DIR",
                    help="keep the services' checkpoints here: a restarted service resumes "
                         "(runtime.state_dir; cleared when up starts)")
    add_bus_args(up)
    add_param_args(up)

    w = sub.add_parser("worlds", help="list the built-in worlds, check or generate a world")
    w.add_argument("--check", metavar="WORLD", help="load a world (name or file) and summarize it")
    w.add_argument("action", nargs="?", metavar="generate",
                   help="generate a world: `topoexplore worlds generate --help`")
    w.add_argument("rest", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)

    for name, (_module, text) in FORWARD.items():  # each parses its own arguments
        sub.add_parser(name, help=text, add_help=False)

    mp = sub.add_parser("map", help="map tools")
    msub = mp.add_subparsers(dest="map_command", metavar="ACTION")
    ms = msub.add_parser("save", help="save the live map as map_server PGM + YAML")
    ms.add_argument("output", help="YAML path to write (the PGM goes beside it)")
    ms.add_argument("--timeout", type=float, default=3.0)
    add_bus_args(ms)
    add_param_args(ms)
    return ap


# subcommands with their own full parsers (module[:function], help): the remaining argv goes
# to them
FORWARD = {
    "keys": ("topoexplore.tools.keys",
             "keys: list | echo KEY | hz KEY | get SERVICE | pub KEY F=V | set SERVICE S.N=V"),
    "router": ("topoexplore.tools.router", "run a Zenoh router"),
    "bridge": ("topoexplore.tools.bridge",
               "ros2: a ROS 2 robot's CDR scan/odom in, our cmd_vel/map out (no ROS needed)"),
    "warmup": ("topoexplore.tools.warm",
               "compile the numba kernels once (the supervisor does it too)"),
    "render": ("topoexplore.tools.render", "PNG from a saved run directory or a running stack"),
    "bench": ("topoexplore.tools.bench",
              "benchmarks: stages | explore | inproc | robust | oracle | posetrace | record | faults | fuzz | hangs | codec"),
    "record": ("topoexplore.tools.record:main_record",
               "record the bus into an MCAP file (raw + Foxglove channels)"),
    "play": ("topoexplore.tools.record:main_play", "publish an MCAP recording back onto the bus"),
    "replay": ("topoexplore.tools.replay",
               "run services on a recording's inputs, compare the outputs"),
    "view": ("topoexplore.tools.view", "live Foxglove view of a running stack (WebSocket server)"),
    "teleop": ("topoexplore.tools.teleop",
               "drive the robot from the keyboard (stops on silence/exit)"),
}


def _closed_pipe() -> int:
    """The reader of stdout went away (``| head``): point stdout at /dev/null so the
    interpreter's last flush cannot raise again, and end as a broken pipe (128 + SIGPIPE)."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, sys.stdout.fileno())
    return 141


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    if argv and argv[0] in FORWARD:
        import importlib

        modname, _, fn = FORWARD[argv[0]][0].partition(":")
        entry = getattr(importlib.import_module(modname), fn or "main")
        try:
            return int(entry(argv[1:]) or 0)
        except KeyboardInterrupt:
            return 130
        except BrokenPipeError:  # `... | head` closed the pipe: no traceback
            return _closed_pipe()
    ap = build_parser()
    args = ap.parse_args(argv)
    try:
        if args.command == "run":
            from topoexplore.tools import run as runner

            return runner.run(args)
        if args.command == "up":
            return cmd_up(args)
        if args.command == "worlds":
            return cmd_worlds(args)
        if args.command == "map" and args.map_command == "save":
            return cmd_map_save(args)
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:
        return _closed_pipe()
    ap.print_help()
    return 2


if __name__ == "__main__":
    raise SystemExit(main())
