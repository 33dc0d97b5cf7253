"""All parameters, in one place, with the paper's constants as defaults.

One plain struct per service, grouped in :class:`Params`. Load from a TOML file whose tables are
the section names (``[sim]``, ``[mapper]``, ...) and override single values from the command line
with ``--set section.name=value``. :func:`load_params` validates everything in one place and
raises :class:`ParamError` (one line) on any problem.
"""

from __future__ import annotations

import math
import tomllib
from pathlib import Path
from typing import Any

import msgspec

__all__ = [
    "ParamError",
    "SimParams",
    "MapperParams",
    "TopologyParams",
    "ReliabilityParams",
    "PlannerParams",
    "ControllerParams",
    "BusParams",
    "Params",
    "load_params",
    "apply_overrides",
    "params_to_dict",
]


class ParamError(ValueError):
    """A parameter file or override is invalid."""


class _P(msgspec.Struct, kw_only=True, forbid_unknown_fields=True):
    pass


class SimParams(_P):
    world: str = "paper-room"  # built-in world name or path to a world TOML / map_server YAML
    lockstep_wait_for: list[str] = msgspec.field(
        default_factory=lambda: ["mapper", "topology", "reliability", "planner", "controller"])
    lockstep_wait: float = 60.0  # [s] wall time to wait for those services before the first scan
    status_hz: float = 2.0  # [Hz] sim/status rate in real-time mode (every scan in lockstep)
    physics_hz: float = 50.0  # [Hz] physics steps
    scan_hz: float = 5.0  # [Hz] laser rate (paper: about 5 Hz)
    odom_hz: float = 20.0  # [Hz]
    beams: int = 181  # paper: SICK LMS200, 181 readings at 1 deg
    fov: float = math.pi  # [rad] 180 deg, forward
    range_max: float = 8.0  # [m]
    range_min: float = 0.02  # [m]
    range_noise: float = 0.01  # [m] Gaussian sigma
    laser_offset: float = 0.0  # [m] laser ahead of the robot centre
    robot_radius: float = 0.2  # [m] paper: Pioneer 2DX, r = 0.2 m
    v_limit: float = 1.0  # [m/s] base limits (commands are clipped)
    w_limit: float = 2.0  # [rad/s]
    watchdog: float = 0.5  # [s] sim time without cmd_vel -> stop
    speed: float = 1.0  # real-time factor in real-time mode
    lockstep: bool = False
    lockstep_timeout: float = 10.0  # [s] wall time to wait for cmd_vel before stepping anyway
    odom_drift: float = 0.0  # relative odometry noise per metre (0 = perfect odometry)
    seed: int = 0


class MapperParams(_P):
    resolution: float = 0.1  # [m] paper: 10 cm cells
    l_occ: float = 0.85  # log-odds added at a hit
    l_free: float = -0.4  # log-odds added along a beam
    l_min: float = -4.0  # clamp so cells can change back
    l_max: float = 4.0
    p_free: float = 0.35  # below: known free
    p_occ: float = 0.65  # above: occupied
    initial_size: float = 20.0  # [m] grid side at start, centred on the first pose
    grow_margin: float = 10.0  # [m] added on a side when a beam leaves the grid
    max_size: float = 400.0  # [m] refuse to grow beyond (bad pose protection)
    map_every: int = 2  # publish the map for the first scan of every block of this many scans
    # (every scan is integrated; 2 = 2.5 Hz at the paper's 5 Hz laser; 1 = every scan)


class TopologyParams(_P):
    robot_radius: float = 0.2  # [m]
    spur_length: float = 0.5  # [m] leaf edges shorter than this are pruned
    fill_holes: float = 0.05  # [m^2] occupied/unknown islands smaller than this count as free
    min_free_area: float = 0.5  # [m^2] free specks smaller than this are dropped
    open_cells: int = 1  # morphological opening radius of the free mask [cells]
    id_gate: float = 0.5  # [m] node identity gate
    corner_nodes: bool = True
    corner_min_deviation: float = 0.2  # [m] ignore corners closer than this to the chord
    skeleton_method: str = "zhang"  # zhang | skimage | lee; see docs/topology.md
    spur_clearance_factor: float = 1.6  # spur threshold = clip(f * clearance at branch, ...)
    spur_max_length: float = 1.0  # [m] ... spur_length, spur_max_length) (docs/topology.md)
    spur_rounds: int = 3  # prune / re-trace rounds per update
    frontier_spur_length: float = 0.4  # [m] a short leaf is kept if this much frontier (free
    # next to unknown) lies within its end's clearance + frontier_spur_margin; 0 disables
    frontier_spur_margin: float = 0.3  # [m]
    entry_radius: float = 0.5  # [m] robot cell not free: use the nearest free cell this close
    incremental: bool = True  # re-thin only the window that changed (checked at its seam)


class ReliabilityParams(_P):
    r_near: float = 0.5  # [m] eq. 2: D = 1 at and below
    r_far: float = 4.5  # [m] eq. 2 interpretation: D = 0.5 at and beyond
    d_c: float = 3.5  # eq. 1: D = 4 / (r + 3.5)
    alpha_full: float = math.pi / 2  # [rad] eq. 4: A = 1 at 90 deg
    p_init: float = 0.5  # paper: initial position probability
    p_reliable: float = 0.9  # paper: threshold
    p_max: float = 0.999  # numerical ceiling so a later reset is meaningful
    move_tolerance: float = 0.3  # [m] movement that resets belief
    fov: float = math.pi  # [rad]
    range_max: float = 8.0  # [m]
    laser_offset: float = 0.0  # [m]
    visit_radius: float = 0.5  # [m] counts as visited
    view_distance: float = 0.25  # [m] robot travel that makes an observation new evidence
    view_angle: float = math.radians(5.0)  # [rad] ... or change of bearing to the node
    frontier_radius: float = 0.5  # [m] observations of a node this close to a frontier don't count
    frontier_group: float = 0.0  # [m] ... nor of a node whose leaf chain is the nearest skeleton
    # to a frontier group of at least this length (core.frontier_owned); 0 disables
    recall_radius: float = 0.25  # [m] a new or moved end node within this of where a node was
    # reliable starts from that P (the place was examined; core._recall); 0 disables
    p_free: float = 0.35  # known-free threshold for the frontier test (as mapper.p_free)
    pocket_area: float = 0.5  # [m^2] enclosed unknown pockets smaller than this are no frontier
    # (the inside of an obstacle seen through a notch; common.grid.open_unknown); 0 disables
    bearing_bin: float = math.radians(0.5)  # [rad] bearings stored one per bin (eq. 3)


class PlannerParams(_P):
    strategy: str = "reliability"  # reliability | all-end-nodes | frontier
    p_reliable: float = 0.9
    robot_radius: float = 0.2  # [m]
    clearance_margin: float = 0.1  # [m] edges need clearance >= radius + margin (the controller
    # stops for returns within radius + 0.05 m of its path; docs/design.md)
    visit_radius: float = 0.5  # [m] all-end-nodes: visited when this close
    goal_tolerance: float = 0.3  # [m]
    progress_timeout: float = 20.0  # [s] sim time without progress -> blacklist target
    progress_distance: float = 0.3  # [m] progress = this much closer to target
    max_attempts: int = 2  # blacklist after this many failures of the same target
    blacklist_radius: float = 0.5  # [m] blacklisted positions also cover moved nodes
    replan_period: float = 2.0  # [s] re-evaluate target choice at most this often
    switch_ratio: float = 0.7  # switch target only if new cost < ratio * current cost
    min_frontier_size: float = 0.5  # [m] explore_lite default
    potential_scale: float = 3.0  # explore_lite default
    gain_scale: float = 1.0  # explore_lite default
    status_hz: float = 1.0  # [Hz]
    tie_tolerance: float = 0.5  # [m] path costs this close tie -> prefer the target ahead
    target_move: float = 0.3  # [m] target moved this far from where the path was built -> new path
    arrival_timeout: float = 5.0  # [s] within goal_tolerance of a still-open target -> blacklist
    waypoint_spacing: float = 0.25  # [m] path polylines thinned to about this spacing
    path_tolerance: float = 0.4  # [m] a remaining waypoint this far off the skeleton -> new path
    frontier_match_radius: float = 1.0  # [m] frontier group this close to the goal stays target
    frontier_period: float = 1.0  # [s] frontier strategy: frontiers and costs recomputed at
    # most this often while a target is being followed (explore_lite planner_frequency 1 Hz)
    done_confirm: int = 2  # consecutive updates without any candidate before reporting done
    tip_length: float = 0.3  # [m] last part of an edge into an end node that may be narrow
    frontier_completion: bool = True  # reliability / all-end-nodes: once no end node is left
    # to visit, go to the frontier groups that remain (core._completion); done = map complete
    completion_min_size: float = 1.0  # [m] ... those at least this long (and min_frontier_size):
    # a leftover speck at a wall gap is not worth a trip across the building at the end...
    completion_near: float = 4.0  # [m] ... unless its path is this short (the shorter groups
    # down to min_frontier_size: a narrow gap next to the robot may hide a whole room)
    completion_pocket_area: float = 1.5  # [m^2] ... and not bordering an enclosed unknown pocket
    # smaller than this (a box's inside, seen through gaps in its outline; common.grid.open_unknown)
    stop_when_mapped: bool = True  # reliability: done as soon as no frontier is left by the
    # completion rules, even with end nodes below p_reliable (DESIGN departure; docs/design.md)
    approach_narrow: bool = True  # an open end node behind a narrow edge: go up to the
    # narrow point and look (the map there is often only narrow because it is half seen)


class ControllerParams(_P):
    v_max: float = 0.2  # [m/s] paper: 200 mm/s
    w_max: float = 1.0  # [rad/s]
    lookahead: float = 0.4  # [m] pure pursuit
    rotate_angle: float = 0.8  # [rad] rotate in place above this heading error
    goal_tolerance: float = 0.15  # [m]
    face_tolerance: float = 0.3  # [rad] at the path end, turn to the plan's goal_heading (if
    #                             any) until within this
    start_turn: float = 2 * math.pi  # [rad] turn in place this much before following the first
    #   path: the start's surroundings are mapped before any choice (0 disables)
    slow_distance: float = 0.6  # [m] start slowing when the front is closer
    safety_distance: float = 0.3  # [m] hard stop when the front sector is closer
    front_half_angle: float = 1.2  # [rad] front sector half width (with the lateral corridor test)
    robot_radius: float = 0.2  # [m]
    stuck_time: float = 4.0  # [s] no motion while commanding -> recovery
    recovery_time: float = 1.5  # [s]
    recovery_speed: float = 0.1  # [m/s] backwards
    recovery_backup: bool = False  # back up when stuck (blind: a forward 180 deg laser sees
    #                                nothing behind; off = only turn in place, collision-free)
    heading_gain: float = 1.5  # [1/s] w = gain * heading error when turning in place
    search_window: float = 1.5  # [m] path progress is searched this far ahead of the last
    lateral_margin: float = 0.05  # [m] front sector: |lateral offset| <= robot_radius + this
    slow_min_scale: float = 0.25  # speed factor at safety_distance (1 at slow_distance)
    stuck_distance: float = 0.05  # [m] moving less than this ...
    stuck_angle: float = 0.2  # [rad] ... and turning less than this for stuck_time = stuck


class BusParams(_P):
    namespace: str = "topoexplore"
    robot: str = "robot1"
    connect: str = "tcp/127.0.0.1:7447"


class Params(_P):
    sim: SimParams = msgspec.field(default_factory=SimParams)
    mapper: MapperParams = msgspec.field(default_factory=MapperParams)
    topology: TopologyParams = msgspec.field(default_factory=TopologyParams)
    reliability: ReliabilityParams = msgspec.field(default_factory=ReliabilityParams)
    planner: PlannerParams = msgspec.field(default_factory=PlannerParams)
    controller: ControllerParams = msgspec.field(default_factory=ControllerParams)
    bus: BusParams = msgspec.field(default_factory=BusParams)


STRATEGIES = ("reliability", "all-end-nodes", "frontier")


def params_to_dict(p: Params) -> dict[str, Any]:
    return msgspec.to_builtins(p)


def _parse_value(text: str) -> Any:
    """Parse an override value as TOML (numbers, booleans, strings, arrays); bare words are strings."""
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


def apply_overrides(data: dict[str, Any], overrides: list[str]) -> dict[str, Any]:
    """Apply ``section.name=value`` overrides to a nested dict (copy)."""
    out = {k: dict(v) if isinstance(v, dict) else v for k, v in data.items()}
    for item in overrides:
        if "=" not in item or "." not in item.split("=", 1)[0]:
            raise ParamError(f"bad override {item!r}: expected section.name=value")
        path, value = item.split("=", 1)
        section, name = path.strip().split(".", 1)
        out.setdefault(section, {})
        if not isinstance(out[section], dict):
            raise ParamError(f"bad override {item!r}: {section!r} is not a section")
        out[section][name.strip()] = _parse_value(value.strip())
    return out


def _validate(p: Params) -> None:
    def pos(section: str, name: str, v: float) -> None:
        if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
            raise ParamError(f"{section}.{name} must be a positive finite number (got {v!r})")

    s = p.sim
    for name in ("physics_hz", "scan_hz", "odom_hz", "fov", "range_max", "robot_radius",
                 "v_limit", "w_limit", "watchdog", "speed", "lockstep_timeout"):
        pos("sim", name, getattr(s, name))
    if s.beams < 2 or s.beams > 10000:
        raise ParamError(f"sim.beams must be in 2..10000 (got {s.beams})")
    if s.scan_hz > s.physics_hz:
        raise ParamError("sim.scan_hz must not exceed sim.physics_hz")
    if s.range_noise < 0 or s.odom_drift < 0 or s.range_min < 0 or s.range_min >= s.range_max:
        raise ParamError("sim: noise and drift must be >= 0 and range_min < range_max")
    mp = p.mapper
    pos("mapper", "resolution", mp.resolution)
    pos("mapper", "initial_size", mp.initial_size)
    pos("mapper", "max_size", mp.max_size)
    if not (mp.l_min < 0 < mp.l_max and mp.l_free < 0 < mp.l_occ):
        raise ParamError("mapper: need l_min < 0 < l_max and l_free < 0 < l_occ")
    if mp.grow_margin < 0:
        raise ParamError("mapper.grow_margin must be >= 0")
    if mp.initial_size > mp.max_size:
        raise ParamError("mapper: initial_size must not exceed max_size")
    if isinstance(mp.map_every, bool) or not 1 <= mp.map_every <= 100:
        raise ParamError(f"mapper.map_every must be an integer in 1..100 (got {mp.map_every!r})")
    if not (0 < mp.p_free < 0.5 < mp.p_occ < 1):
        raise ParamError("mapper: need 0 < p_free < 0.5 < p_occ < 1")
    t = p.topology
    pos("topology", "robot_radius", t.robot_radius)
    pos("topology", "id_gate", t.id_gate)
    if t.spur_length < 0 or t.fill_holes < 0 or t.min_free_area < 0 or t.open_cells < 0:
        raise ParamError("topology: sizes must be >= 0")
    if (t.spur_clearance_factor < 0 or t.spur_max_length < 0 or t.spur_rounds < 0
            or t.entry_radius < 0 or t.corner_min_deviation < 0
            or t.frontier_spur_length < 0 or t.frontier_spur_margin < 0):
        raise ParamError("topology: spur/entry/corner sizes must be >= 0")
    if t.skeleton_method not in ("zhang", "skimage", "lee"):
        raise ParamError(f"topology.skeleton_method must be zhang, skimage or lee "
                         f"(got {t.skeleton_method!r})")
    r = p.reliability
    if not (0 < r.r_near < r.r_far):
        raise ParamError("reliability: need 0 < r_near < r_far")
    if not (0 < r.p_init < r.p_reliable < r.p_max < 1):
        raise ParamError("reliability: need 0 < p_init < p_reliable < p_max < 1")
    for name in ("alpha_full", "move_tolerance", "fov", "range_max", "visit_radius",
                 "bearing_bin", "d_c"):
        pos("reliability", name, getattr(r, name))
    if (r.frontier_group < 0 or r.frontier_radius < 0 or not r.pocket_area >= 0
            or not r.recall_radius >= 0):
        raise ParamError("reliability: frontier_group, frontier_radius, pocket_area and "
                         "recall_radius must be >= 0")
    pl = p.planner
    if pl.strategy not in STRATEGIES:
        raise ParamError(f"planner.strategy must be one of {', '.join(STRATEGIES)} (got {pl.strategy!r})")
    if not 0 < pl.p_reliable < 1:
        raise ParamError("planner.p_reliable must be in (0, 1)")
    for name in ("robot_radius", "visit_radius", "goal_tolerance", "progress_timeout",
                 "progress_distance", "replan_period", "status_hz", "blacklist_radius",
                 "target_move", "arrival_timeout", "waypoint_spacing", "path_tolerance",
                 "frontier_match_radius", "potential_scale"):
        pos("planner", name, getattr(pl, name))
    if pl.max_attempts < 1:
        raise ParamError("planner.max_attempts must be >= 1")
    if not 0 < pl.switch_ratio <= 1:
        raise ParamError("planner.switch_ratio must be in (0, 1]")
    if pl.done_confirm < 1:
        raise ParamError("planner.done_confirm must be >= 1")
    for name in ("clearance_margin", "tie_tolerance", "min_frontier_size", "gain_scale",
                 "tip_length", "frontier_period", "completion_min_size", "completion_near",
                 "completion_pocket_area"):
        v = getattr(pl, name)
        if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
            raise ParamError(f"planner.{name} must be a finite number >= 0 (got {v!r})")
    c = p.controller
    for name in ("v_max", "w_max", "lookahead", "rotate_angle", "goal_tolerance",
                 "face_tolerance", "safety_distance", "front_half_angle", "robot_radius",
                 "stuck_time", "recovery_time", "recovery_speed", "heading_gain", "search_window",
                 "stuck_distance", "stuck_angle"):
        pos("controller", name, getattr(c, name))
    if c.slow_distance < c.safety_distance:
        raise ParamError("controller: need slow_distance >= safety_distance")
    if not (math.isfinite(c.start_turn) and 0 <= c.start_turn <= 8 * math.pi):
        raise ParamError(f"controller.start_turn must be in [0, 8 pi] rad (got {c.start_turn!r})")
    if not 0 < c.slow_min_scale <= 1 or c.lateral_margin < 0:
        raise ParamError("controller: need 0 < slow_min_scale <= 1 and lateral_margin >= 0")
    from topoexplore.common.keys import check_segment

    for ep in p.bus.connect.split(","):
        check_endpoint(ep.strip())
    try:
        check_segment(p.bus.namespace, "namespace")
        check_segment(p.bus.robot, "robot name")
    except ValueError as exc:
        raise ParamError(str(exc)) from None


def check_endpoint(ep: str) -> str:
    """A Zenoh locator like tcp/127.0.0.1:7447 (tcp/udp/tls/quic need host:port, port 1..65535)."""
    proto, sep, addr = ep.partition("/")
    if not sep or not proto or not addr:
        raise ParamError(f"bad endpoint {ep!r}: expected PROTOCOL/HOST:PORT, e.g. tcp/127.0.0.1:7447")
    if proto in ("tcp", "udp", "tls", "quic"):
        host, colon, port = addr.rpartition(":")
        if not colon or not host or not port.isdigit() or not 1 <= int(port) <= 65535:
            raise ParamError(f"bad endpoint {ep!r}: port must be 1..65535")
    return ep


def load_params(path: str | Path | None = None, overrides: list[str] | None = None) -> Params:
    """Defaults <- TOML file <- overrides; validated. Raises ParamError with one line."""
    data: dict[str, Any] = {}
    if path is not None:
        try:
            data = tomllib.loads(Path(path).read_text())
        except FileNotFoundError:
            raise ParamError(f"parameter file not found: {path}") from None
        except (OSError, UnicodeDecodeError) as exc:
            raise ParamError(f"cannot read parameter file {path}: {exc}") from None
        except tomllib.TOMLDecodeError as exc:
            raise ParamError(f"parameter file {path} is not valid TOML: {exc}") from None
    data = apply_overrides(data, overrides or [])
    try:
        p = msgspec.convert(data, Params, strict=False)
    except msgspec.ValidationError as exc:
        raise ParamError(f"bad parameter: {exc}") from None
    _validate(p)
    return p


def with_changes(p: Params, section: str, **changes: Any) -> Params:
    """Copy of p with fields of one section replaced (re-validated)."""
    sub = msgspec.structs.replace(getattr(p, section), **changes)
    out = msgspec.structs.replace(p, **{section: sub})
    _validate(out)
    return out
