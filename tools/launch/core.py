"""Supervisor core: launch profiles and the restart policy (pure: no processes, no clocks).

A launch profile (TOML, ``deploy/profiles/*.toml``)::

    name = "sim"
    description = "..."
    router = true                 # start a Zenoh router on the bus endpoint (false: use one)

    [[process]]
    name = "sim"
    module = "topoexplore.sim.service"  # run as `python -m topoexplore.sim.service <bus and
    #                                     parameter options>`
    # or: cmd = ["/opt/driver/bin/laser", "--port", "/dev/ttyUSB0"]  (a foreign driver)
    restart = true                # default true
    ready_timeout = 30.0          # [s] to wait for its liveliness token (module processes)
    liveliness = true             # default: true for module processes, false for cmd
    when = "localizer.enabled"    # only when this boolean parameter is true (default: always)
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any


class ProfileError(ValueError):
    """A launch profile is invalid."""


@dataclass(frozen=True)
class ProcSpec:
    name: str
    module: str = ""
    cmd: tuple[str, ...] = ()
    restart: bool = True
    ready_timeout: float = 30.0  # [s]
    liveliness: bool = True
    args: tuple[str, ...] = ()  # extra arguments for a module process
    when: str = ""  # section.name of a boolean parameter: started only when it is true


@dataclass(frozen=True)
class Profile:
    name: str
    description: str
    router: bool
    processes: tuple[ProcSpec, ...]


_PROC_KEYS = {"name", "module", "cmd", "restart", "ready_timeout", "liveliness", "args", "when"}


def parse_profile(data: dict[str, Any], source: str = "profile") -> Profile:
    def bad(text: str) -> ProfileError:
        return ProfileError(f"{source}: {text}")

    unknown = set(data) - {"name", "description", "router", "process"}
    if unknown:
        raise bad(f"unknown key(s) {sorted(unknown)}")
    procs = data.get("process", [])
    if not isinstance(procs, list) or not procs:
        raise bad("needs at least one [[process]]")
    specs = []
    names = set()
    for i, p in enumerate(procs):
        if not isinstance(p, dict):
            raise bad(f"process #{i + 1} is not a table")
        extra = set(p) - _PROC_KEYS
        if extra:
            raise bad(f"process #{i + 1}: unknown key(s) {sorted(extra)}")
        name = p.get("name")
        if not isinstance(name, str) or not name.replace("-", "_").isidentifier():
            raise bad(f"process #{i + 1}: name must be a plain word")
        if name in names:
            raise bad(f"duplicate process name {name!r}")
        names.add(name)
        module, cmd = p.get("module", ""), p.get("cmd", [])
        if bool(module) == bool(cmd):
            raise bad(f"process {name!r}: give exactly one of module or cmd")
        if module and not isinstance(module, str):
            raise bad(f"process {name!r}: module must be a string")
        if cmd and not (isinstance(cmd, list) and all(isinstance(c, str) for c in cmd)):
            raise bad(f"process {name!r}: cmd must be a list of strings")
        args = p.get("args", [])
        if not (isinstance(args, list) and all(isinstance(a, str) for a in args)):
            raise bad(f"process {name!r}: args must be a list of strings")
        timeout = p.get("ready_timeout", 30.0)
        if not isinstance(timeout, (int, float)) or timeout <= 0:
            raise bad(f"process {name!r}: ready_timeout must be a positive number")
        restart = p.get("restart", True)
        live = p.get("liveliness", bool(module))
        if not isinstance(restart, bool) or not isinstance(live, bool):
            raise bad(f"process {name!r}: restart and liveliness must be true/false")
        when = p.get("when", "")
        if not isinstance(when, str) or (when and len(when.split(".")) != 2):
            raise bad(f"process {name!r}: when must name a parameter as section.name")
        specs.append(ProcSpec(name=name, module=module, cmd=tuple(cmd), restart=restart,
                              ready_timeout=float(timeout), liveliness=live, args=tuple(args),
                              when=when))
    router = data.get("router", True)
    if not isinstance(router, bool):
        raise bad("router must be true or false")
    return Profile(name=str(data.get("name", source)), description=str(data.get("description", "")),
                   router=router, processes=tuple(specs))


def select(profile: Profile, params: Any) -> Profile:
    """The profile's processes that run with these parameters (``when``: a boolean one).
    ProfileError for a ``when`` that names no boolean parameter."""
    keep = []
    for spec in profile.processes:
        if spec.when:
            section, name = spec.when.split(".")
            value = getattr(getattr(params, section, None), name, None)
            if not isinstance(value, bool):
                raise ProfileError(f"process {spec.name!r}: when = {spec.when!r} is not a "
                                   f"true/false parameter")
            if not value:
                continue
        keep.append(spec)
    return Profile(profile.name, profile.description, profile.router, tuple(keep))


def load_profile(path: str | Path) -> Profile:
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise ProfileError(f"launch profile not found: {path}") from None
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise ProfileError(f"cannot read launch profile {path}: {exc}") from None
    return parse_profile(data, str(path))


BAD_INPUT_EXIT = 2  # exit code of a topoexplore process refusing its arguments or parameters


@dataclass
class RestartPolicy:
    """Exponential backoff: base * 2^n, capped; a process that ran long enough resets n."""

    base: float = 0.5  # [s]
    cap: float = 10.0  # [s]
    stable_after: float = 30.0  # [s] uptime after which the backoff count resets
    max_restarts: int = 100  # give up after this many restarts (reported)

    def delay(self, consecutive: int) -> float:
        return min(self.cap, self.base * (2 ** max(0, consecutive)))


@dataclass
class ProcState:
    spec: ProcSpec
    pid: int | None = None
    started_at: float = 0.0
    restarts: int = 0
    consecutive: int = 0
    alive: bool = False  # liveliness token present
    last_exit: int | None = None
    next_start: float | None = 0.0  # time to (re)start; None = do not start
    given_up: bool = False
    was_up: bool = False  # its liveliness token appeared since its last start
    history: list[str] = field(default_factory=list)

    def on_exit(self, now: float, code: int, policy: RestartPolicy, stopping: bool) -> str:
        """Record an exit; decide what happens next. Returns a one-line description."""
        uptime = now - self.started_at
        self.pid = None
        self.alive = False
        self.last_exit = code
        if uptime >= policy.stable_after:
            self.consecutive = 0
        if stopping:
            self.next_start = None
            return f"{self.spec.name} exited ({code})"
        if not self.spec.restart:
            self.next_start = None
            return f"{self.spec.name} exited ({code}); restart disabled"
        if code == BAD_INPUT_EXIT and self.spec.module and self.spec.liveliness \
                and not self.was_up:
            self.next_start = None  # our processes exit 2 on bad arguments, parameters or
            self.given_up = True  # files: a restart would fail the same way, forever
            return (f"{self.spec.name} exited ({code}) before it was up: bad arguments, "
                    f"parameters or files (see its log line); not restarted")
        if self.restarts >= policy.max_restarts:
            self.next_start = None
            self.given_up = True
            return f"{self.spec.name} exited ({code}); gave up after {self.restarts} restarts"
        delay = policy.delay(self.consecutive)
        self.consecutive += 1
        self.restarts += 1
        self.next_start = now + delay
        text = (f"{self.spec.name} exited ({code}) after {uptime:.1f} s; restart #{self.restarts} "
                f"in {delay:.1f} s")
        self.history.append(text)
        return text

    def on_start(self, now: float, pid: int) -> None:
        self.pid = pid
        self.started_at = now
        self.next_start = None
        self.alive = False
        self.was_up = False
