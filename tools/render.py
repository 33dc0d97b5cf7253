"""``topoexplore render``: a PNG of grid + topological map, from a saved run or a live stack.

    topoexplore render runs/paper-room                 # -> runs/paper-room/render.png
    topoexplore render runs/paper-room -o fig.png
    topoexplore render --live -o now.png [--connect tcp/127.0.0.1:7447] [--namespace ...]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from topoexplore.tools.livestate import StateError, beliefs_from_state, graph_from_state


def _err(text: str) -> int:
    print(f"topoexplore render: {text}", file=sys.stderr)
    return 2


def load_run(run_dir: Path):
    """(grid, geom, topo, rel, trail, robot pose, target id) from a directory written by
    `topoexplore run` (no pose and no target: the trail shows where the robot went)."""
    from topoexplore.common.mapio import read_map_server

    grid, geom = read_map_server(run_dir / "map.yaml")
    topo = rel = None
    tj = run_dir / "topology.json"
    if tj.exists():
        try:
            doc = json.loads(tj.read_text())
        except (OSError, ValueError) as exc:
            raise StateError(f"{tj}: not valid JSON ({exc})") from None
        if not isinstance(doc, dict):
            raise StateError(f"{tj}: expected an object with 'topo' and 'reliability'")
        topo = graph_from_state(doc.get("topo"))
        rel = beliefs_from_state(doc.get("reliability"))
    trail = []
    tc = run_dir / "trail.csv"
    if tc.exists():
        for i, line in enumerate(tc.read_text().splitlines()[1:], start=2):
            try:
                x, y, s = line.split(",")
                trail.append((float(x), float(y), int(s)))
            except ValueError:
                raise StateError(f"{tc}:{i}: expected x,y,segment") from None
    return grid, geom, topo, rel, trail, None, -1


def load_live(args: argparse.Namespace):
    """(grid, geom, topo, rel, trail, robot pose, target id) of a running stack: the map,
    graph and beliefs from the state queryables, the robot from its odometry (the first
    message within --timeout), the target from the planner's status."""
    import threading

    from topoexplore.common import convert
    from topoexplore.common import messages as m
    from topoexplore.common.bus import Bus
    from topoexplore.common.keys import Keys
    from topoexplore.common.node import params_from_args
    from topoexplore.tools.livestate import as_message, fetch_state, map_from_state

    params = params_from_args(args)
    keys = Keys(params.bus.namespace, params.bus.robot)
    pose: list[tuple[float, float, float]] = []
    got_pose = threading.Event()

    def on_odom(msg: m.Odometry, _k: str) -> None:
        p = convert.odom_from_msg(msg).pose
        pose[:] = [(p.x, p.y, p.theta)]
        got_pose.set()

    with Bus.client(params.bus.connect, config_file=args.zenoh_config) as bus:
        bus.subscribe(keys.odom, m.Odometry, on_odom)
        grid, geom = map_from_state(fetch_state(bus, keys, "mapper", args.timeout))
        topo = rel = None
        target = -1
        try:
            topo = graph_from_state(fetch_state(bus, keys, "topology", args.timeout).get("topo"))
            rel = beliefs_from_state(
                fetch_state(bus, keys, "reliability", args.timeout).get("last"))
            status = as_message(fetch_state(bus, keys, "planner", args.timeout).get("status"),
                                m.ExploreStatus)
            target = status.target_id if status is not None else -1
        except StateError:
            pass
        got_pose.wait(args.timeout)
    return grid, geom, topo, rel, [], (pose[0] if pose else None), target


def main(argv: list[str] | None = None) -> int:
    from topoexplore.common.bus import BusError
    from topoexplore.common.mapio import MapIOError, write_png
    from topoexplore.common.node import add_bus_args, add_param_args, params_from_args
    from topoexplore.common.params import ParamError
    from topoexplore.tools.draw import Overlays, Style, render

    ap = argparse.ArgumentParser(prog="topoexplore render", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run_dir", nargs="?", help="directory written by `topoexplore run`")
    ap.add_argument("-o", "--output", help="PNG to write (default RUN_DIR/render.png)")
    ap.add_argument("--live", action="store_true", help="render the running stack's state")
    ap.add_argument("--timeout", type=float, default=3.0)
    ap.add_argument("--title", default=None)
    add_bus_args(ap)
    add_param_args(ap)
    args = ap.parse_args(argv)
    if bool(args.run_dir) == bool(args.live):
        return _err("give a run directory or --live (one of them)")
    out = Path(args.output) if args.output else (
        Path(args.run_dir) / "render.png" if args.run_dir else Path("render.png"))
    try:
        if args.live:
            grid, geom, topo, rel, trail, pose, target = load_live(args)
        else:
            run_dir = Path(args.run_dir)
            if not (run_dir / "map.yaml").exists():
                return _err(f"{run_dir} has no map.yaml (not a run directory?)")
            grid, geom, topo, rel, trail, pose, target = load_run(run_dir)
        title = args.title if args.title is not None else (
            "live" if args.live else Path(args.run_dir).name)
        P = params_from_args(args)  # the thresholds and robot size of --params / --set
        style = Style(p_free=P.mapper.p_free, p_occ=P.mapper.p_occ,
                      p_reliable=P.reliability.p_reliable, robot_radius=P.robot.radius,
                      title=title)
        img = render(grid, geom, Overlays(topo=topo, rel=rel, trail=trail or None,
                                          robot_pose=pose, target_id=target), style)
        write_png(out, img)
    except (StateError, MapIOError, BusError, ParamError) as exc:
        return _err(str(exc))
    what = [f"{img.shape[1]}x{img.shape[0]} px"]
    if pose is not None:
        what.append(f"robot at ({pose[0]:.2f}, {pose[1]:.2f})")
    if target >= 0:
        what.append(f"target node {target}")
    print(f"wrote {out} ({'; '.join(what)})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
