"""All parameters, in one place, with the paper's constants as defaults.

Sections: ``[robot]`` (the body every service shares), ``[laser]`` (the sensor), ``[runtime]``
(lockstep or real time, for every process), ``[bus]`` (where the stack lives on Zenoh), and one
section per stage: ``[sim]``, ``[mapper]``, ``[topology]``, ``[reliability]``, ``[planner]``,
``[controller]``. Each is a frozen struct whose fields declare their own constraints
(``msgspec.Meta``: positive, in a range, one of a list); rules that tie two fields together are
in the struct's ``__post_init__``, and rules across sections in :class:`Params`. Everything is
checked when parameters are loaded (:func:`load_params`), which raises :class:`ParamError` with
one line on any problem.

Load from a TOML file whose tables are the section names and override single values on the
command line with ``--set section.name=value``.
"""

from __future__ import annotations

import math
import tomllib
from pathlib import Path
from typing import Annotated, Any, Literal, get_args

import msgspec
from msgspec import Meta

from topoexplore.common.grid import Occupancy
from topoexplore.common.keys import (
    DEFAULT_ENDPOINT,
    DEFAULT_NAMESPACE,
    DEFAULT_ROBOT,
    TOPICS,
    check_endpoint,
    check_segment,
)

__all__ = [
    "ParamError",
    "STRATEGIES",
    "VARIANTS",
    "STRATEGY_NAMES",
    "strategy_overrides",
    "MOVED",
    "RobotParams",
    "LaserParams",
    "RuntimeParams",
    "BusParams",
    "SimParams",
    "MapperParams",
    "LocalizerParams",
    "LASER_MODELS",
    "TopologyParams",
    "ReliabilityParams",
    "PlannerParams",
    "ControllerParams",
    "Params",
    "load_params",
    "apply_overrides",
    "params_to_dict",
    "validated",
    "with_changes",
]


class ParamError(ValueError):
    """A parameter file or override is invalid."""


# --- constrained types (NaN fails every comparison, so each of these also refuses NaN) ------

_BIG = 1.0e9
Pos = Annotated[float, Meta(gt=0.0, le=_BIG)]  # positive and finite
NonNeg = Annotated[float, Meta(ge=0.0, le=_BIG)]  # >= 0 and finite
Neg = Annotated[float, Meta(lt=0.0, ge=-_BIG)]  # negative and finite
Prob = Annotated[float, Meta(gt=0.0, lt=1.0)]  # an open probability
Fraction = Annotated[float, Meta(gt=0.0, le=1.0)]
PosInt = Annotated[int, Meta(ge=1, le=2**31)]
NonNegInt = Annotated[int, Meta(ge=0, le=2**31)]

Strategy = Literal["reliability", "all-end-nodes", "frontier"]
STRATEGIES: tuple[str, ...] = get_args(Strategy)  # the one list of exploration strategies
SkeletonMethod = Literal["zhang", "skimage", "lee"]

# Named variants: a strategy run with a set of parameters. "reliability-paper" is the paper's
# rule exactly as it is written, the reference for our departures (docs/design.md,
# "Reliability" and "Completion phase"): one Bayes update per scan in view, no frontier tests,
# no recall of examined places, no completion phase, done only when every end node is reliable.
# "reliability-distance" is our rule without the examined-surroundings test: D from the
# distance alone (eq. 2), every other departure kept (what chose that test's default).
VARIANTS: dict[str, tuple[str, tuple[str, ...]]] = {
    "reliability-distance": ("reliability", ("reliability.examined_radius=0",)),
    "reliability-paper": ("reliability", (
        "reliability.view_distance=0", "reliability.frontier_radius=0",
        "reliability.frontier_group=0", "reliability.examined_radius=0",
        "reliability.recall_radius=0", "planner.frontier_completion=false",
        "planner.stop_when_mapped=false", "planner.grid_paths=false",
        "planner.surface_views=0", "reliability.surface_views=0")),
}
STRATEGY_NAMES: tuple[str, ...] = STRATEGIES + tuple(VARIANTS)  # what --strategy accepts


def strategy_overrides(name: str) -> list[str]:
    """The ``--set`` overrides that run strategy or variant ``name`` (ParamError if unknown);
    the user's own overrides go after them."""
    if name in STRATEGIES:
        return [f'planner.strategy="{name}"']
    if name in VARIANTS:
        base, sets = VARIANTS[name]
        return [f'planner.strategy="{base}"', *sets]
    raise ParamError(f"unknown strategy {name!r}: choose from {', '.join(STRATEGY_NAMES)}")


class _P(msgspec.Struct, kw_only=True, forbid_unknown_fields=True, frozen=True):
    pass


def _need(ok: bool, text: str) -> None:
    """A rule across fields of a struct (msgspec reports it with the section's path)."""
    if not ok:
        raise ValueError(text)


# --- shared by every process -------------------------------------------------------------


class RobotParams(_P):
    radius: Pos = 0.2  # [m] paper: Pioneer 2DX, a circle of 0.2 m
    body_margin: NonNeg = 0.05  # [m] gap kept beside the body: the controller creeps past
    #   returns within radius + this of its path (it stops only for those in the body's
    #   own path), and the planner routes through a narrow passage only where the grid
    #   clearance is at least about radius + this
    v_limit: Pos = 1.0  # [m/s] base limits: the simulator (or a driver) clips commands
    w_limit: Pos = 2.0  # [rad/s]


# laser models: the fields a [laser] model = "..." fills in where the section does not set them
LASER_MODELS: dict[str, dict[str, float]] = {
    "sick-lms200": {"beams": 181, "fov": math.pi, "range_min": 0.02, "range_max": 8.0,
                    "scan_hz": 5.0},  # the paper's Pioneer 2DX laser: 180 deg at 1 deg
    "lidar-360": {"beams": 360, "fov": 2 * math.pi, "range_min": 0.1, "range_max": 12.0,
                  "scan_hz": 10.0},  # a common 360 deg lidar: 1 deg, 12 m, 10 Hz
}


class LaserParams(_P):
    model: Literal["sick-lms200", "lidar-360"] = "sick-lms200"  # fills the fields below that
    #   the section leaves out (LASER_MODELS); a field set explicitly wins
    beams: Annotated[int, Meta(ge=2, le=10_000)] = 181  # paper: SICK LMS200, 181 readings at 1 deg
    fov: Annotated[float, Meta(gt=0.0, le=2 * math.pi)] = math.pi  # [rad] 180 deg, forward
    range_min: NonNeg = 0.02  # [m]
    range_max: Pos = 8.0  # [m]
    offset: Annotated[float, Meta(ge=-10.0, le=10.0)] = 0.0  # [m] laser ahead of the robot centre
    scan_hz: Pos = 5.0  # [Hz] paper: about 5 Hz

    def __post_init__(self) -> None:
        _need(self.range_min < self.range_max, "need range_min < range_max")


class RuntimeParams(_P):
    lockstep: bool = False  # deterministic lockstep (the sim waits for each scan's cmd_vel)
    lockstep_timeout: Pos = 10.0  # [s] wall time to wait for an input before going on anyway
    lockstep_wait_for: list[str] = msgspec.field(
        default_factory=lambda: ["mapper", "topology", "reliability", "planner", "controller"])
    lockstep_wait: Pos = 60.0  # [s] wall time to wait for those services before the first scan
    plan_lag: Annotated[int, Meta(ge=0, le=8)] = 2  # lockstep: map periods the controller
    #   follows the plan behind the scans (scan k takes the plan of the map of scan
    #   k - k % map_every - plan_lag x map_every), so the simulator and the controller run on
    #   while topology, reliability and planner work on that map (a pipeline on the second
    #   core); bench inproc follows it, and runs stay deterministic. 0: the plan of the newest
    #   map. Office on the bus 37.1 s (0, clients) -> 27.9 s (2, peers) of wall time, 1.29 x
    #   the in-process run; held-back worlds all finished at 2, coverage >= 0.991
    #   (docs/benchmarks.md)
    state_dir: str = ""  # directory of the services' checkpoints ("": none); a restarted
    #   service resumes from its checkpoint there (``run`` uses OUT/state)
    checkpoint_every: Pos = 1.0  # [s] between two checkpoints of a service (mapper: wall
    #   time; sim: sim time, the robot motion a restart can lose)
    checkpoint_max_age: Pos = 300.0  # [s] an older checkpoint is an earlier session's: ignored
    resume_from_peers: bool = True  # a restarted mapper takes its last map back from a peer
    #   that kept it (planner, reliability): the cells after its checkpoint, or all of them
    # fault injection on this service's inputs (``bench faults``; can change while it runs):
    chaos_topics: list[str] = msgspec.field(default_factory=list)  # topics whose incoming
    #   messages are dropped / delayed ([]: none)
    chaos_drop: Annotated[float, Meta(ge=0.0, le=1.0)] = 0.0  # share of them dropped (seeded)
    chaos_delay: Annotated[float, Meta(ge=0.0, le=60.0)] = 0.0  # [s] wall time each of the
    #   others is held back (order kept)
    chaos_seed: Annotated[int, Meta(ge=0, le=2**63 - 1)] = 0

    def __post_init__(self) -> None:
        _need(len(self.chaos_topics) <= 32, "at most 32 chaos_topics")
        for t in self.chaos_topics:
            _need(t in TOPICS, f"chaos_topics: {t!r} is not a topic ({', '.join(TOPICS)})")


class BusParams(_P):
    namespace: str = DEFAULT_NAMESPACE
    robot: str = DEFAULT_ROBOT
    connect: str = DEFAULT_ENDPOINT
    shared_memory: bool = False  # zenoh's shared-memory transport between the processes of
    # one host, services and router alike (common/bus.py make_config: off saves ~130 MB)
    mode: Literal["auto", "client", "peer"] = "auto"  # how a service joins the bus. client:
    #   every message through the router. peer: the services also link to each other (each
    #   listens on ``listen``, learns the others from the router) and messages go straight
    #   from one to the next; clients (viewers, tools) still reach everything through the
    #   router. auto: client, except in ``topoexplore run`` (its own router on this host, no
    #   credentials), where it is peer: office in lockstep 33.7 s against 37.4 s of wall time
    #   (docs/benchmarks.md)
    listen: str = "tcp/127.0.0.1:0"  # a peer's own endpoint (port 0: any free port)

    def __post_init__(self) -> None:
        check_segment(self.namespace, "namespace")
        check_segment(self.robot, "robot name")
        for ep in self.connect.split(","):
            check_endpoint(ep.strip())
        for ep in self.listen.split(","):
            check_endpoint(ep.strip(), any_port=True)


# --- one section per stage -----------------------------------------------------------------


class SimParams(_P):
    world: str = "paper-room"  # built-in world name or path to a world TOML / map_server YAML
    seed: Annotated[int, Meta(ge=0, le=2**63 - 1)] = 0
    speed: Pos = 1.0  # real-time factor in real-time mode
    status_hz: Pos = 2.0  # [Hz] sim/status rate in real-time mode (every scan in lockstep)
    physics_hz: Pos = 50.0  # [Hz] physics steps
    odom_hz: Pos = 20.0  # [Hz]
    range_noise: NonNeg = 0.01  # [m] Gaussian sigma of the simulated laser
    watchdog: Pos = 0.5  # [s] sim time without cmd_vel -> stop
    cmd_max_age: Pos = 1.0  # [s] sim time: a cmd_vel stamped earlier than this, or later than
    #   now (another clock), is stale and dropped; the controller stamps each command with the
    #   scan it answers, so in real time its age is the controller's latency times sim.speed
    odom_drift: NonNeg = 0.0  # [m/sqrt(m)] odometry translation random walk: after d metres
    #   of travel the error has sigma odom_drift * sqrt(d) (0 and the two below 0: perfect)
    odom_drift_heading: NonNeg | None = None  # [rad/sqrt(m)] heading random walk, the same
    #   way (None: odom_drift's value)
    odom_slip: Annotated[float, Meta(ge=0.0, le=1.0)] = 0.0  # wheel slip: while the body is
    #   held by an obstacle, this share of the commanded motion it did not make is counted


class MapperParams(_P):
    resolution: Pos = 0.1  # [m] paper: 10 cm cells
    l_occ: Pos = 0.85  # log-odds added at a hit
    l_free: Neg = -0.4  # log-odds added along a beam
    l_min: Neg = -4.0  # clamp so cells can change back
    l_max: Pos = 4.0
    surface_reach: NonNeg = 0.0  # [m] a beam does not clear the cells within this distance
    # of its hit that the surface it hit passes through (a wall face inside a cell, crossed by
    # grazing beams); 0 = off (services/mapper/core.py, docs/design.md "Mapping")
    surface_step: Pos = 0.5  # [m] ... judged from hits at most this far apart (wider: a gap,
    # such as a door no beam went through, not a surface)
    p_free: Annotated[float, Meta(gt=0.0, lt=0.5)] = 0.35  # below: known free
    p_occ: Annotated[float, Meta(gt=0.5, lt=1.0)] = 0.65  # above: occupied
    initial_size: Pos = 20.0  # [m] grid side at start, centred on the first pose
    grow_margin: NonNeg = 10.0  # [m] added on a side when a beam leaves the grid
    max_size: Pos = 400.0  # [m] refuse to grow beyond (bad pose protection)
    map_every: Annotated[int, Meta(ge=1, le=100)] = 2  # publish the map for the first scan of
    # every block of this many scans (every scan is integrated; 2 = 2.5 Hz at 5 Hz; 1 = all)

    def __post_init__(self) -> None:
        _need(self.initial_size <= self.max_size, "initial_size must not exceed max_size")
        _need(self.max_size / self.resolution <= 50_000,
              "max_size / resolution exceeds 50000 cells per side")

    @property
    def occupancy(self) -> Occupancy:
        """The classification thresholds every consumer of the map uses."""
        return Occupancy(self.p_free, self.p_occ)


class TopologyParams(_P):
    spur_length: NonNeg = 0.5  # [m] leaf edges shorter than this are pruned
    fill_holes: NonNeg = 0.05  # [m^2] occupied/unknown islands smaller than this count as free
    min_free_area: NonNeg = 0.5  # [m^2] free specks smaller than this are dropped
    open_cells: NonNegInt = 1  # morphological opening radius of the free mask [cells]
    id_gate: Pos = 0.5  # [m] node identity gate
    corner_nodes: bool = True
    corner_min_deviation: NonNeg = 0.2  # [m] ignore corners closer than this to the chord
    skeleton_method: SkeletonMethod = "zhang"  # see docs/topology.md
    spur_clearance_factor: NonNeg = 1.6  # spur threshold = clip(f * clearance at branch, ...
    spur_max_length: NonNeg = 1.0  # [m] ... spur_length, spur_max_length) (docs/topology.md)
    spur_rounds: NonNegInt = 3  # prune / re-trace rounds per update
    frontier_spur_length: NonNeg = 0.4  # [m] a short leaf is kept if this much frontier lies
    # within its end's clearance + frontier_spur_margin (docs/design.md); 0 disables
    frontier_spur_margin: NonNeg = 0.3  # [m]
    entry_radius: NonNeg = 0.5  # [m] robot cell not free: use the nearest free cell this close
    incremental: bool = True  # re-thin only the window that changed (checked at its seam)


class ReliabilityParams(_P):
    r_near: Pos = 0.5  # [m] eq. 2: D = 1 at and below
    r_far: Pos = 4.5  # [m] eq. 2 interpretation: D = 0.5 at and beyond
    d_c: Pos = 3.5  # eq. 1: D = 4 / (r + 3.5)
    alpha_full: Pos = math.pi / 2  # [rad] eq. 4: A = 1 at 90 deg
    p_init: Prob = 0.5  # paper: initial position probability
    p_reliable: Prob = 0.9  # paper: threshold (the planner's too)
    p_max: Prob = 0.999  # numerical ceiling so a later reset is meaningful
    move_tolerance: Pos = 0.3  # [m] movement that resets belief
    visit_radius: Pos = 0.5  # [m] counts as visited
    view_distance: NonNeg = 0.25  # [m] robot travel that makes an observation new evidence
    view_angle: NonNeg = math.radians(5.0)  # [rad] ... or change of bearing to the node
    frontier_radius: NonNeg = 0.5  # [m] observations of a node this close to a frontier
    # don't count (docs/design.md, "Reliability")
    frontier_clearance: bool = False  # ... this close plus the node's distance to the
    # nearest occupied cell (at most r_far): a skeleton end lies that far from the boundary
    # that ends it; off: worse on the tuning half (docs/design.md, "Reliability", rule 2)
    frontier_ahead: Annotated[float, Meta(ge=0.0, le=math.pi)] = 0.0  # [rad] ... and frontier
    # cells within the node's free disc plus frontier_radius, this close in bearing to the
    # heading its leaf edge ends in (an aisle that ends in unknown space half its width
    # beyond the node); 0 disables (docs/design.md, "Reliability", rule 2)
    examined_radius: NonNeg = 1.0  # [m] a node seen with no frontier this close has its
    # surroundings examined: the observation counts as from close by (D = 1), whatever the
    # distance (docs/design.md, "Reliability"); 0 disables
    min_frontier: NonNeg = 0.5  # [m] both tests count frontier cells only when at least
    # this much of them (in cells: this / resolution) lies within their radius, as the
    # planner's min_frontier_size: a few cells of SLAM speckle or a gap in a ragged wall are
    # no frontier (docs/design.md, "Reliability"); 0: any single cell
    frontier_group: NonNeg = 1.0  # [m] ... nor of a node whose leaf chain is the nearest
    # skeleton to a frontier group of at least this length; 0 disables (on since
    # 2026-12-07: shorter on the tuning and the held-back half, docs/design.md rule 3)
    recall_radius: NonNeg = 0.25  # [m] a new or moved end node this close to where a node was
    # reliable starts from that P; 0 disables
    pocket_area: NonNeg = 0.5  # [m^2] enclosed unknown pockets smaller than this are no
    # frontier; 0 disables
    bearing_bin: Pos = math.radians(0.5)  # [rad] bearings stored one per bin (eq. 3)
    surface_views: NonNegInt = 0  # the frontier tests skip cells the map showed occupied on
    # this many updates (planner.surface_views for the index; common/surfaces.py); 0: off

    def __post_init__(self) -> None:
        _need(self.r_near < self.r_far, "need r_near < r_far")
        _need(self.p_init < self.p_reliable < self.p_max, "need p_init < p_reliable < p_max")


class PlannerParams(_P):
    strategy: Strategy = "frontier"  # the shorter on the held-back half of the generated
    # corpus (issue 15's rule, docs/design.md "Planner"); "reliability" is the paper's method
    clearance_margin: NonNeg = 0.1  # [m] edges need clearance >= robot.radius + margin
    visit_radius: Pos = 0.5  # [m] all-end-nodes: visited when this close
    goal_tolerance: Pos = 0.3  # [m]
    progress_timeout: Pos = 20.0  # [s] sim time without progress -> a failure of the target
    progress_distance: Pos = 0.3  # [m] progress = this much closer to the target
    max_attempts: PosInt = 2  # blacklist after this many failures of the same target
    blacklist_radius: Pos = 0.5  # [m] blacklisted positions also cover moved nodes
    replan_period: Pos = 2.0  # [s] re-evaluate target choice at most this often
    switch_ratio: Fraction = 0.7  # switch target only if new cost < ratio * current cost
    min_frontier_size: NonNeg = 0.5  # [m] explore_lite default
    potential_scale: Pos = 3.0  # explore_lite default
    gain_scale: NonNeg = 1.0  # explore_lite default
    status_hz: Pos = 1.0  # [Hz]
    heartbeat: NonNeg = 0.05  # [s] robot time: in real time the planner sends its last plan
    #   again this often (on odometry, from its receive thread, while its worker loop is
    #   alive), so the controller tells a stalled planner from one busy with a long update
    #   (controller.plan_timeout); 0: off (one plan per map)
    tie_tolerance: NonNeg = 0.5  # [m] path costs this close tie -> prefer the target ahead
    target_move: Pos = 0.3  # [m] target moved this far from where the path was made -> new path
    arrival_timeout: Pos = 5.0  # [s] within goal_tolerance of a still-open target -> blacklist
    waypoint_spacing: Pos = 0.25  # [m] path polylines thinned to about this spacing
    path_tolerance: Pos = 0.4  # [m] a remaining waypoint this far off the skeleton -> new path
    frontier_match_radius: Pos = 1.0  # [m] frontier group this close to the goal stays target
    frontier_period: NonNeg = 1.0  # [s] frontier searches at most this often while following
    keep_period: NonNeg = 0.0  # [s] reliability / all-end-nodes: while the target followed
    #   stays open where it was and its path stays valid, the last evaluation is kept this long
    #   at most, unless a rule of the decision machine is due (docs/design.md "A kept
    #   evaluation"); 0: every update evaluates (the default until it decides as a whole
    #   evaluation does in every case: 1.0 cut the planner's compute by a third, paths 1.015
    #   on the held-back half, one traced difference left)
    done_confirm: PosInt = 2  # consecutive updates without any candidate before "done"
    watchdog_time: Pos = 120.0  # [s] driving without new map information -> escalate
    watchdog_area: Pos = 0.5  # [m^2] new information: the known area grew this much ...
    #   (or an end node became reliable)
    watchdog_travel: Pos = 1.0  # [m] driven in a period without information: the robot can
    #   move, so the watchdog gives up what it tried (again) instead of calling it stuck; and
    #   the first target's remaining path this much shorter than ever: a long trip, the
    #   period starts again (watchdog.py)
    blocked_time: Pos = 8.0  # [s] following a path without moving or turning -> the way
    #   ahead is blocked: a learned obstacle there
    blocked_radius: NonNeg = 0.0  # [m] ... a disc this big, just ahead of the robot (0: the
    #   controller's corridor half width, robot.radius + robot.body_margin, so that the gap
    #   it refused is closed to every search, the escape through any free cell included) ...
    blocked_memory: Pos = 300.0  # [s] ... remembered this long
    stuck_timeout: Pos = 60.0  # [s] stuck (no way out, or the watchdog's last step) this
    #   long -> failed
    tip_length: NonNeg = 0.3  # [m] last part of an edge into an end node that may be narrow
    frontier_completion: bool = True  # reliability / all-end-nodes: once no end node is left,
    # go to the frontier groups that remain (docs/design.md, "Completion phase")
    completion_min_size: NonNeg = 1.0  # [m] ... those at least this long
    completion_near: NonNeg = 4.0  # [m] ... or shorter (down to min_frontier_size) and this near
    completion_openings: NonNeg = 0.0  # [m] ... or shorter still and farther, an opening
    #   (a door seen only from afar: the robot's body fits into the unknown there and the
    #   unknown widens behind it) not yet looked into squarely from this close; its goal is
    #   the nearest place to do so; 0: off (docs/design.md "Openings")
    completion_pocket_area: NonNeg = 1.5  # [m^2] ... and not next to a smaller enclosed pocket
    completion_pocket_share: Annotated[float, Meta(ge=0.0, le=1.0)] = 0.01  # ... unless the
    #   robot can reach completion_min_size of its edge (look into it) and it is at least this
    #   share of the known free cells: a laser shadow that matters for coverage (1 = never)
    pickup_radius: NonNeg = 0.0  # [m] while end nodes are left, the frontier groups the
    # completion rules count this near by path are candidates too (cost: path length), so
    # that a corner is not left for a long trip back later; 0: off (the default: with
    # pickup_age, 3 m gave 0.909 of the path on held-back seeds 1 and 3 at simulator seed 0,
    # but 0.990 on seed 5 and 1.016 at simulator seed 1; docs/design.md "Experimental")
    pickup_age: NonNeg = 10.0  # [s] ... only groups with a cell that has been a frontier cell
    # this long (the edge of the laser's reach of the moment is not left behind)
    grid_paths: bool = True  # reliability / all-end-nodes: drive to the chosen end node on a
    # grid path (as the frontier strategy's) instead of along the skeleton's edges (a
    # departure from DESIGN §4, docs/design.md "Drive to the chosen end node on the grid");
    # the choice is the paper's either way
    stop_when_mapped: bool = True  # reliability: done once no frontier is left by the
    # completion rules, even with end nodes below p_reliable (a departure; docs/design.md)
    open_radius: NonNeg = 1.0  # [m] ... except the end nodes with min_frontier_size of
    # frontier cells this close (unexplored space beside them, however fragmented its
    # frontier): still visited; 0: none
    approach_narrow: bool = True  # an open end node behind a narrow edge: go up to the
    # narrow point and look (docs/design.md, "Approach through a narrow passage") ...
    approach_radius: NonNeg = 1.0  # [m] ... only when min_frontier_size of frontier cells
    # lie this close to the end node (unexplored space to look at); 0: every such end node
    examine_range: NonNeg = 0.0  # [m] a frontier cell looked at squarely from this close,
    # in line of sight, examine_views times and still a frontier cell is a surface, not an
    # opening: no frontier for any strategy; 0: off (the default: docs/design.md
    # "Experimental, off by default"; 2.0 is the value tried)
    examine_bearing: Annotated[float, Meta(gt=0.0, le=math.pi)] = 1.4  # [rad] ... within this
    # of the heading (no wider than half the laser's field of view) ...
    examine_angle: Annotated[float, Meta(gt=0.0, lt=math.pi / 2)] = math.pi / 4  # [rad] ...
    # the line of sight this close to the direction of an unknown neighbour ...
    examine_views: PosInt = 3  # ... on this many updates
    surface_views: NonNegInt = 3  # a cell the map showed occupied on this many updates is a
    # surface: no frontier cell when free later (a wall face cleared by grazing beams; see
    # common/surfaces.py, docs/design.md "Surfaces"); 0: off


class ControllerParams(_P):
    v_max: Pos = 0.2  # [m/s] paper: 200 mm/s
    w_max: Pos = 1.0  # [rad/s]
    lookahead: Pos = 0.4  # [m] pure pursuit
    rotate_angle: Pos = 0.8  # [rad] rotate in place above this heading error
    goal_tolerance: Pos = 0.15  # [m]
    face_tolerance: Pos = 0.3  # [rad] at the path end, turn to the plan's goal_heading
    start_turn: Annotated[float, Meta(ge=0.0, le=8 * math.pi)] = 2 * math.pi  # [rad] turn in
    # place this much before the first path (a forward laser sees nothing behind); 0 disables
    slow_distance: Pos = 0.6  # [m] start slowing when the front is closer
    safety_distance: Pos = 0.3  # [m] hard stop when the front sector is closer
    front_half_angle: Pos = 1.2  # [rad] front sector half width (with the corridor test)
    stuck_time: Pos = 4.0  # [s] no motion while commanding -> recovery
    recovery_time: Pos = 1.5  # [s]
    recovery_speed: Pos = 0.1  # [m/s] backwards
    recovery_backup: bool = True  # back up when stuck, only into space a scan of the last
    # recovery_memory s saw free (off = only turn in place)
    recovery_memory: NonNeg = 10.0  # [s] scans kept for that rear check (0: the current
    # scan only, which a forward 180 deg laser never sees behind with)
    heading_gain: Pos = 1.5  # [1/s] w = gain * heading error when turning in place
    search_window: Pos = 1.5  # [m] path progress is searched this far ahead of the last
    slow_min_scale: Fraction = 0.25  # speed factor at safety_distance (1 at slow_distance)
    stuck_distance: Pos = 0.05  # [m] moving less than this ...
    stuck_angle: Pos = 0.2  # [rad] ... and turning less than this for stuck_time = stuck
    plan_timeout: Pos = 0.25  # [s] robot time without a new plan message (the planner sends
    #   one per map and its heartbeat every planner.heartbeat: a stalled or dead planner) ->
    #   stop, mode "stale-plan". In lockstep, where the controller waits for each map's plan,
    #   at least two map periods (mapper.map_every / laser.scan_hz each)

    def __post_init__(self) -> None:
        _need(self.slow_distance >= self.safety_distance, "need slow_distance >= safety_distance")


class LocalizerParams(_P):
    """The scan matcher (services/localizer/core.py) and whether it runs."""

    enabled: bool = False  # run the localizer process; every service then takes odometry
    #   composed with its map -> odom correction (common.node.OdomBuffer)
    search_xy: Pos = 0.3  # [m] the window round odometry's guess, each way
    search_theta: Pos = 0.15  # [rad] each way
    sigma: Pos = 0.05  # [m] the likelihood field's spread round a wall: half a cell, about
    #   where a hit lies in the cell it marks. With 0.1 the match pulled a little every scan
    #   and the map took it in: pose RMS 0.145 m on office with perfect odometry (0.076 m at
    #   0.05; in process, reliability, seed 0; docs/benchmarks.md)
    coarse: Annotated[int, Meta(ge=1, le=64)] = 4  # cells per side of a coarse block
    max_points: Annotated[int, Meta(ge=10, le=10_000)] = 180  # end points matched per scan
    min_points: Annotated[int, Meta(ge=3, le=10_000)] = 20  # fewer: no match
    min_score: Fraction = 0.3  # mean likelihood of the end points below this: no match
    prior: NonNeg = 0.05  # the motion prior's weight: this share of the best possible score
    #   lost at the window's edge, so ties (as along a corridor) go to odometry's guess. On
    #   office scans against a mapped grid, guesses off by up to 0.05 m: worst error 0.33 m
    #   without it, 0.10 m with it (median 0.050 / 0.047 m)
    directional: bool = True  # an end point scores only on wall faces seen from a side its
    #   beam can reach (core.py, step 0): a thin wall mapped from one side no longer pulls a
    #   scan from the other side a cell off. With drift, pose RMS geometric mean 0.151 -> 0.110
    #   m on the held-back generated worlds (0.161 -> 0.121 on the tuning half), office 0.093
    #   -> 0.118 (docs/benchmarks.md)
    degenerate_ratio: Annotated[float, Meta(ge=0.0, le=1.0)] = 0.15  # a scan whose surfaces
    #   pin the position this much less along one direction than across it (the eigenvalue
    #   ratio of the point-to-line information, 0: a corridor) keeps odometry's guess along
    #   that direction (core.py, step 5); 0: never. Tuned on the even-seed generated worlds
    #   with drift, 0.10 / 0.15 / 0.25 (docs/benchmarks.md)
    known_only: bool = True  # match only the end points that fall, at odometry's guess, on
    #   a cell the map has observed: a point beyond the map's edge scores nothing where it is,
    #   and a pose that turns it onto a known wall gains, so in new territory every scan
    #   pulled the heading the same way (core.py, step 0b). With drift, pose RMS geometric
    #   mean in closed loop: tuning half 0.157 -> 0.152 m (7 better, 9 worse of 16),
    #   held-back 0.214 -> 0.155 (8 better, 4 worse of 12), office 0.079 -> 0.056,
    #   large-office 0.243 -> 0.193; single runs go both ways (docs/benchmarks.md)
    heading_gain: Annotated[float, Meta(ge=0.0, le=1.0)] = 0.25  # step 6: this share of
    #   the heading offset between the scan's surface directions and the run's own histogram of
    #   them turns each match (core.py); 0: off. Tuned on the even-seed generated worlds with
    #   drift, replayed: pose RMS geometric mean 0.147 m without, 0.106 / 0.106 / 0.126 at
    #   0.1 / 0.25 / 0.5. In closed loop: tuning half 0.152 -> 0.117, held-back 0.155 ->
    #   0.123 and 0.176 -> 0.106 (simulator seeds 0, 1), large-office 0.193 -> 0.176; office
    #   0.056 -> 0.082 and small_house 0.066 -> 0.107 worse (office's paired replays better;
    #   docs/benchmarks.md)
    heading_window: Annotated[float, Meta(gt=0.0, le=0.3)] = 0.05  # [rad] the offsets step 6
    #   looks at, each way


class Params(_P):
    robot: RobotParams = msgspec.field(default_factory=RobotParams)
    laser: LaserParams = msgspec.field(default_factory=LaserParams)
    runtime: RuntimeParams = msgspec.field(default_factory=RuntimeParams)
    bus: BusParams = msgspec.field(default_factory=BusParams)
    sim: SimParams = msgspec.field(default_factory=SimParams)
    mapper: MapperParams = msgspec.field(default_factory=MapperParams)
    topology: TopologyParams = msgspec.field(default_factory=TopologyParams)
    reliability: ReliabilityParams = msgspec.field(default_factory=ReliabilityParams)
    planner: PlannerParams = msgspec.field(default_factory=PlannerParams)
    controller: ControllerParams = msgspec.field(default_factory=ControllerParams)
    localizer: LocalizerParams = msgspec.field(default_factory=LocalizerParams)

    def __post_init__(self) -> None:
        _need(self.laser.scan_hz <= self.sim.physics_hz,
              "laser.scan_hz must not exceed sim.physics_hz")
        _need(self.planner.clearance_margin >= self.robot.body_margin,
              "planner.clearance_margin must be at least robot.body_margin")


# Parameters that moved to a shared section (round 2): an old name gets a one-line hint.
MOVED = {
    "sim.robot_radius": "robot.radius", "topology.robot_radius": "robot.radius",
    "planner.robot_radius": "robot.radius", "controller.robot_radius": "robot.radius",
    "sim.v_limit": "robot.v_limit", "sim.w_limit": "robot.w_limit",
    "sim.beams": "laser.beams", "sim.fov": "laser.fov", "reliability.fov": "laser.fov",
    "sim.range_min": "laser.range_min", "sim.range_max": "laser.range_max",
    "reliability.range_max": "laser.range_max", "sim.laser_offset": "laser.offset",
    "reliability.laser_offset": "laser.offset", "sim.scan_hz": "laser.scan_hz",
    "sim.lockstep": "runtime.lockstep", "sim.lockstep_timeout": "runtime.lockstep_timeout",
    "sim.lockstep_wait_for": "runtime.lockstep_wait_for",
    "sim.lockstep_wait": "runtime.lockstep_wait", "reliability.p_free": "mapper.p_free",
    "planner.p_reliable": "reliability.p_reliable", "controller.lateral_margin": "robot.body_margin",
}


def params_to_dict(p: Params) -> dict[str, Any]:
    return msgspec.to_builtins(p)


def params_from_dict(data: dict[str, Any], overrides: list[str] | None = None) -> Params:
    """The inverse of :func:`params_to_dict`, then ``section.name=value`` overrides;
    validated (ParamError)."""
    if not isinstance(data, dict):
        raise ParamError(f"parameters must be a table, not {type(data).__name__}")
    return _convert(apply_overrides(data, overrides or []))


def _parse_value(text: str) -> Any:
    """An override value as TOML (numbers, booleans, strings, arrays); bare words are strings."""
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


def _check_moved(data: dict[str, Any]) -> None:
    for section, values in data.items():
        if isinstance(values, dict):
            for name in values:
                new = MOVED.get(f"{section}.{name}")
                if new is not None:
                    raise ParamError(f"{section}.{name} is now {new} (docs/design.md, "
                                     "\"Parameters\")")


def _with_laser_model(data: dict[str, Any]) -> dict[str, Any]:
    """[laser] model = "...": its fields where the section leaves them out."""
    laser = data.get("laser")
    if not isinstance(laser, dict):
        return data
    model = LASER_MODELS.get(laser.get("model", "sick-lms200")) if isinstance(
        laser.get("model", "sick-lms200"), str) else None
    if model is None:  # an unknown model: the validation says so
        return data
    return {**data, "laser": {**model, **laser}}


def _convert(data: dict[str, Any]) -> Params:
    _check_moved(data)
    data = _with_laser_model(data)
    try:
        return msgspec.convert(data, Params, strict=False)
    except msgspec.ValidationError as exc:
        raise ParamError(f"bad parameter: {exc}") from None


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
    return _convert(apply_overrides(data, overrides or []))


def validated(p: Params) -> Params:
    """p checked against every declared constraint (structs built in code skip the field
    constraints, which msgspec checks when converting); ParamError on a violation."""
    return _convert(params_to_dict(p))


def with_override(p: Params, assignment: str) -> tuple[Params, str]:
    """p with one ``section.name=value`` applied (a TOML value, as ``--set`` takes it),
    validated as at start-up -> (new params, the canonical ``section.name``); ParamError."""
    data = apply_overrides(params_to_dict(p), [assignment])
    new = _convert(data)
    section, name = (s.strip() for s in assignment.split("=", 1)[0].split(".", 1))
    if not hasattr(getattr(new, section, None), name):
        raise ParamError(f"unknown parameter {section}.{name}")
    return new, f"{section}.{name}"


def with_changes(p: Params, section: str, **changes: Any) -> Params:
    """Copy of p with fields of one section replaced, validated."""
    data = params_to_dict(p)
    data[section] = {**data[section], **changes}
    return _convert(data)
