"""Supervisor: starts the router and the processes of a launch profile, watches them, restarts.

- starts a Zenoh router on the bus endpoint when the profile asks for one;
- compiles the numba kernels of its module processes once, in one child process, before it
  starts them (``topoexplore warmup``: on a cold cache six processes would otherwise compile
  at once; skipped while the last warm-up's stamp holds);
- starts every process (module processes get the shared bus and parameter options);
- waits until each one's liveliness token appears (``<ns>/<robot>/alive/<name>``);
- forwards their logs, each line prefixed with ``[name]``;
- restarts a process that dies (exponential backoff, restart count), and kills one whose token
  stayed gone while it still runs (frozen); a module process that exits 2 before it was ever
  up refused its arguments, parameters or files, and is not restarted (it would fail the same
  way forever);
- on stop (Ctrl-C / SIGTERM): SIGTERM to every child's process group, SIGKILL after a grace
  period, router last; children also get SIGTERM from the kernel if the supervisor itself dies
  (PR_SET_PDEATHSIG), so no orphans are left.
"""

from __future__ import annotations

import ctypes
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from importlib import resources
from pathlib import Path

from topoexplore.common.bus import Bus, BusError
from topoexplore.common.keys import Keys
from topoexplore.common.node import LOG_DATEFMT
from topoexplore.common.params import ParamError, Params, load_params
from topoexplore.tools.launch.core import ProcSpec, ProcState, Profile, RestartPolicy, select

log = logging.getLogger("topoexplore.supervisor")

PROFILE_PACKAGE = "topoexplore.deploy"  # launch profiles travel as package data: profiles/*.toml


def _pdeathsig() -> None:  # runs in the child between fork and exec
    try:
        libc = ctypes.CDLL("libc.so.6", use_errno=True)
        libc.prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except OSError:
        pass


def free_port() -> int:
    """A TCP port on loopback that nobody listens on now."""
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def port_open(endpoint: str) -> bool:
    """Does the (first) TCP endpoint's port accept connections now? False for other
    protocols and unparsable endpoints; 0.0.0.0 is tried on loopback."""
    import socket

    proto, _, addr = endpoint.split(",")[0].partition("/")
    host, _, port = addr.rpartition(":")
    if proto != "tcp" or not port.isdigit():
        return False
    with socket.socket() as sock:
        sock.settimeout(0.2)
        try:
            return sock.connect_ex((host if host != "0.0.0.0" else "127.0.0.1", int(port))) == 0
        except OSError:
            return False


def log_time() -> str:
    """Wall-clock time as in every service log line (common.node.LOG_FORMAT)."""
    now = time.time()
    return time.strftime(LOG_DATEFMT, time.localtime(now)) + f".{int(now % 1 * 1000):03d}"


def stamped(line: str) -> str:
    """A supervisor line gets the time after its tag: ``[supervisor] <time> text``."""
    tag = "[supervisor] "
    return f"{tag}{log_time()} {line[len(tag):]}" if line.startswith(tag) else line


def print_line(line: str) -> None:
    """print() to stdout that survives a reader that went away (``up | head -3``): the first
    broken pipe sends stdout to /dev/null, so the process goes on and stops cleanly."""
    try:
        print(line, flush=True)
    except (BrokenPipeError, ValueError):
        try:
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
            os.close(devnull)
        except (OSError, ValueError):
            pass


def proc_cpu(pid: int) -> dict[str, float] | None:
    """{"user_s", "sys_s"}: CPU time a process has used, from /proc/<pid>/stat; None when
    unreadable (gone, not Linux)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        tick = os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return None
    return {"user_s": round(int(fields[11]) / tick, 2), "sys_s": round(int(fields[12]) / tick, 2)}


def proc_memory(pid: int) -> dict[str, float] | None:
    """Memory of a process [MB]; None when unreadable (gone, not Linux).

    - ``rss_mb`` / ``peak_mb``: resident now and the kernel's high-water mark (VmRSS, VmHWM);
    - ``shmem_mb``: the part of rss_mb that is shared memory (RssShmem: zenoh's buffer pools,
      which every process on the host that reads from a pool maps too);
    - ``pss_mb``: the proportional share (smaps_rollup Pss): every page shared by n processes
      counts 1/n, so the stack's pss_mb add up to what it really holds, while rss_mb counts
      the same pages of numba's LLVM, OpenCV, zenoh and the pools once per process;
    - ``private_mb``: pages no other process maps (Private_Clean + Private_Dirty), what
      stopping this process alone frees.
    """
    try:
        text = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return None
    kb = _kb_fields(text, ("VmRSS", "VmHWM", "RssShmem"))
    if "VmRSS" not in kb or "VmHWM" not in kb:
        return None
    out = {"rss_mb": round(kb["VmRSS"] / 1024, 1), "peak_mb": round(kb["VmHWM"] / 1024, 1)}
    if "RssShmem" in kb:
        out["shmem_mb"] = round(kb["RssShmem"] / 1024, 1)
    try:
        roll = _kb_fields(Path(f"/proc/{pid}/smaps_rollup").read_text(),
                          ("Pss", "Private_Clean", "Private_Dirty"))
    except OSError:  # an older kernel, or not allowed: the status figures only
        return out
    if "Pss" in roll:
        out["pss_mb"] = round(roll["Pss"] / 1024, 1)
    if "Private_Clean" in roll and "Private_Dirty" in roll:
        out["private_mb"] = round((roll["Private_Clean"] + roll["Private_Dirty"]) / 1024, 1)
    return out


def _kb_fields(text: str, keys: tuple[str, ...]) -> dict[str, float]:
    """``Key:   123 kB`` lines of a /proc file -> {key: 123.0} for the wanted keys."""
    kb = {}
    for line in text.splitlines():
        key, _, value = line.partition(":")
        if key in keys and value.split():
            kb[key] = float(value.split()[0])
    return kb


def profile_dir() -> Path:
    """The built-in launch profiles (``deploy/profiles`` in a checkout, package data once
    installed)."""
    return Path(str(resources.files(PROFILE_PACKAGE).joinpath("profiles")))


def builtin_profiles() -> list[str]:
    return sorted(p.stem for p in profile_dir().glob("*.toml"))


def profile_path(name_or_path: str) -> Path:
    """A profile name (``sim``, ``robot``, ...) or a path to a profile TOML file."""
    p = Path(name_or_path)
    if p.suffix == ".toml" or "/" in name_or_path:
        return p
    return profile_dir() / f"{name_or_path}.toml"


class Supervisor:
    def __init__(self, profile: Profile, keys: Keys, endpoint: str,
                 params_file: str | None = None, overrides: list[str] | None = None,
                 zenoh_config: str | None = None, sink: Callable[[str], None] | None = None,
                 policy: RestartPolicy | None = None, lost_grace: float = 12.0,
                 warm: bool = True, log_level: str | None = None,
                 router_config: str | None = None):
        try:  # processes started only under a parameter (``when``) follow these parameters
            params = load_params(params_file, list(overrides or []))
        except ParamError:  # the children say what is wrong, each in one line
            params = Params()
        self.profile = select(profile, params)
        self.shared_memory = params.bus.shared_memory  # the router's, like the services'
        self.keys = keys
        self.endpoint = endpoint
        self.params_file = params_file
        self.log_level = log_level  # passed to every module process (--log-level)
        self.overrides = list(overrides or [])
        self.zenoh_config = zenoh_config
        self.router_config = router_config  # the router's own config (else zenoh_config)
        self.sink = sink or print_line
        self.sink_errors = 0  # lines a failing sink could not take (the pipes drain anyway)
        self.policy = policy or RestartPolicy()
        self.lost_grace = lost_grace
        self.warm = warm
        self.interrupted = threading.Event()  # set on SIGINT/SIGTERM: abandon the warm-up
        self.router_restarts = 0
        self._router_consecutive = 0  # backoff steps (RestartPolicy.delay)
        self._router_due: float | None = None  # when a dead router is started again
        self.warm_s: float | None = None  # [s] wall time of the warm-up step, once run
        self.states = {s.name: ProcState(spec=s) for s in self.profile.processes}
        self.procs: dict[str, subprocess.Popen] = {}
        self.router: subprocess.Popen | None = None
        self.bus: Bus | None = None
        self.stopping = False
        self._lost_since: dict[str, float] = {}
        self._lock = threading.RLock()
        self._threads: list[threading.Thread] = []

    # -- processes ------------------------------------------------------------------------
    def command(self, spec: ProcSpec) -> list[str]:
        if spec.cmd:
            return list(spec.cmd)
        cmd = [sys.executable, "-u", "-m", spec.module, "--connect", self.endpoint,
               "--namespace", self.keys.namespace, "--robot", self.keys.robot]
        if self.params_file:
            cmd += ["--params", self.params_file]
        if self.zenoh_config:
            cmd += ["--zenoh-config", self.zenoh_config]
        for o in self.overrides:
            cmd += ["--set", o]
        if self.log_level:
            cmd += ["--log-level", self.log_level]
        return cmd + list(spec.args)

    def _spawn(self, name: str, cmd: list[str]) -> subprocess.Popen:
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                stdin=subprocess.DEVNULL, env=env, start_new_session=True,
                                preexec_fn=_pdeathsig, text=True, errors="replace", bufsize=1)
        t = threading.Thread(target=self._forward, args=(name, proc), daemon=True)
        t.start()
        self._threads.append(t)
        return proc

    def _forward(self, name: str, proc: subprocess.Popen) -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            text = line.rstrip()  # a child may prefix its lines itself (topoexplore warmup)
            self._emit(text if text.startswith(f"[{name}]") else f"[{name}] {text}")

    def _emit(self, line: str) -> None:
        """A line to the sink. A sink that fails (a closed pipe, a full disk) must not stop the
        draining of a child's output: a child blocked on a full pipe freezes."""
        try:
            self.sink(stamped(line))  # the one call of the sink
        except Exception:
            self.sink_errors += 1

    def warm_up(self, timeout: float = 600.0) -> bool:
        """Compile (or load) the kernels of every module process, in one child process that
        exits afterwards, its lines forwarded as ``[warmup]``. True when it succeeded; on
        failure the services still compile their own kernels at start."""
        from topoexplore.tools.warm import core_of, stamp_valid

        cores = [(s.name, c) for s in self.profile.processes if (c := core_of(s.module))]
        if not self.warm or not cores:
            return True
        t0 = time.monotonic()
        if stamp_valid(cores):  # nothing changed since the last warm-up: the services load
            self.warm_s = time.monotonic() - t0
            self._emit("[warmup] kernels cached at the last warm-up, nothing changed since")
            return True
        proc = self._spawn("warmup", [sys.executable, "-u", "-m", "topoexplore.tools.warm",
                                      "--cores", ",".join(f"{n}={c}" for n, c in cores)])
        deadline = t0 + timeout
        while proc.poll() is None:
            if self.interrupted.is_set() or time.monotonic() > deadline:
                self._kill(proc, signal.SIGKILL)
                break
            time.sleep(0.05)
        code = proc.wait()
        self._threads[-1].join(timeout=1.0)  # its log lines, forwarded by _spawn
        self.warm_s = time.monotonic() - t0
        if code != 0:
            self._emit(f"[supervisor] warm-up failed (exit {code}); the services compile "
                      f"their kernels themselves")
        return code == 0

    def start_router(self) -> None:
        """Start the router process (idempotent)."""
        if not self.profile.router or (self.router is not None and self.router.poll() is None):
            return
        if self._port_open():  # someone else's router (or program): never join it unasked
            raise BusError(f"{self.endpoint} is already in use (another router or program "
                           f"listens there): give --connect a free port, or use a profile "
                           f"without a router to join that one")
        cmd = [sys.executable, "-u", "-m", "topoexplore.tools.router", "--listen", self.endpoint]
        if self.router_config or self.zenoh_config:
            cmd += ["--zenoh-config", self.router_config or self.zenoh_config]
        if self.shared_memory:
            cmd.append("--shared-memory")
        self.router = self._spawn("router", cmd)
        self._wait_router_port()

    def _port_open(self) -> bool:
        return port_open(self.endpoint)

    def _wait_router_port(self, timeout: float = 15.0) -> None:
        """Wait until the router accepts TCP connections; raise BusError if it exits first."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.router is not None and self.router.poll() is not None:
                raise BusError(f"the router on {self.endpoint} exited at start "
                               f"(code {self.router.returncode}; see its log line)")
            if self._port_open():
                return
            time.sleep(0.05)
        raise BusError(f"the router on {self.endpoint} did not open its port in {timeout:g} s")

    def start_process(self, name: str, now: float) -> None:
        st = self.states[name]
        proc = self._spawn(name, self.command(st.spec))
        self.procs[name] = proc
        st.on_start(now, proc.pid)
        self._lost_since.pop(name, None)

    def _on_token(self, key: str, alive: bool) -> None:
        name = key.rsplit("/", 1)[-1]
        with self._lock:
            st = self.states.get(name)
            if st is None:
                return
            st.alive = alive
            if alive:
                st.was_up = True
                self._lost_since.pop(name, None)
                self._emit(f"[supervisor] {name} is up (pid {st.pid})")
            elif not self.stopping:
                self._lost_since[name] = time.monotonic()
                self._emit(f"[supervisor] {name}: liveliness token gone")

    # -- lifecycle ------------------------------------------------------------------------
    def start(self, ready_timeout: float | None = None) -> bool:
        """Start router, warm the kernels, start every process; wait for their tokens. True
        when all are up."""
        self.start_router()
        self.warm_up()
        if self.interrupted.is_set():
            return False
        self.bus = Bus.client(self.endpoint, name="supervisor", config_file=self.zenoh_config,
                              wait_for_router=True)
        taken = [k.rsplit("/", 1)[-1] for k in self.bus.alive(self.keys.alive_all())]
        if taken:  # two stacks under one name would feed each other's map and pose
            raise BusError(f"{self.keys.prefix} is taken on {self.endpoint}: "
                           f"{', '.join(taken)} already up (another stack?); use another "
                           f"--namespace or --robot")
        self.bus.watch_liveliness(self.keys.alive_all(), self._on_token)
        self.bus.declare_token(self.keys.alive("supervisor"))
        self.bus.queryable(self.keys.state("supervisor"), lambda _p: self.table())
        now = time.monotonic()
        with self._lock:
            for name in self.states:
                self.start_process(name, now)
        return self.wait_ready(ready_timeout)

    def wait_ready(self, timeout: float | None = None) -> bool:
        specs = [s for s in self.profile.processes if s.liveliness]
        limit = timeout if timeout is not None else max((s.ready_timeout for s in specs),
                                                        default=0.0)
        deadline = time.monotonic() + limit
        while time.monotonic() < deadline:
            self.poll()
            with self._lock:
                if all(self.states[s.name].alive for s in specs):
                    return True
                dead = [s.name for s in specs if self.states[s.name].given_up]
            if dead:  # it will not come up: no point waiting out the timeout
                self._emit(f"[supervisor] not up: {', '.join(dead)} gave up")
                return False
            time.sleep(0.05)
        missing = [s.name for s in specs if not self.states[s.name].alive]
        self._emit(f"[supervisor] not up after {limit:.0f} s: {', '.join(missing)}")
        return False

    def poll(self) -> None:
        """Reap exited children, (re)start due ones, kill frozen ones. Call regularly."""
        now = time.monotonic()
        with self._lock:
            for name, st in self.states.items():
                proc = self.procs.get(name)
                if proc is not None and st.pid is not None:
                    code = proc.poll()
                    if code is not None:
                        self._emit(f"[supervisor] {st.on_exit(now, code, self.policy, self.stopping)}")
                if st.pid is None and st.next_start is not None and now >= st.next_start \
                        and not self.stopping:
                    self.start_process(name, now)
                lost = self._lost_since.get(name)
                if lost is not None and st.pid is not None and now - lost > self.lost_grace:
                    self._emit(f"[supervisor] {name}: token gone for {now - lost:.0f} s while "
                              f"running; killing it")
                    self._lost_since.pop(name, None)
                    self._kill(self.procs[name], signal.SIGKILL)
            if self.router is not None and self.router.poll() is not None and not self.stopping:
                self._restart_router(now)

    def _restart_router(self, now: float) -> None:
        """A router that died comes back after the same backoff as a process; counted, and
        given up (BusError) after the policy's restart limit."""
        if self._router_due is None:
            code = self.router.returncode if self.router is not None else None
            if self.router_restarts >= self.policy.max_restarts:
                raise BusError(f"the router exited ({code}); gave up after "
                               f"{self.router_restarts} restarts")
            delay = self.policy.delay(self._router_consecutive)
            self._router_due = now + delay
            self._emit(f"[supervisor] router exited ({code}); restart "
                      f"#{self.router_restarts + 1} in {delay:.1f} s")
        if now < self._router_due:
            return
        self._router_due = None
        self.router_restarts += 1
        self._router_consecutive += 1
        self.start_router()

    def run_until(self, stop: threading.Event, period: float = 0.1) -> None:
        while not stop.is_set():
            self.poll()
            stop.wait(period)

    @staticmethod
    def _kill(proc: subprocess.Popen, sig: int) -> None:
        try:
            os.killpg(proc.pid, sig)
        except (ProcessLookupError, PermissionError):
            pass

    def stop(self, grace: float = 5.0) -> None:
        with self._lock:
            self.stopping = True
            for st in self.states.values():
                st.next_start = None
        procs = list(self.procs.values())
        for p in reversed(procs):
            if p.poll() is None:
                self._kill(p, signal.SIGTERM)
        deadline = time.monotonic() + grace
        for p in procs:
            try:
                p.wait(timeout=max(0.01, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                self._kill(p, signal.SIGKILL)
                p.wait(timeout=5)
        self.poll()
        if self.bus is not None:
            self.bus.close()
        if self.router is not None and self.router.poll() is None:
            self._kill(self.router, signal.SIGTERM)
            try:
                self.router.wait(timeout=grace)
            except subprocess.TimeoutExpired:
                self._kill(self.router, signal.SIGKILL)
                self.router.wait(timeout=5)
        for t in self._threads:
            t.join(timeout=1.0)

    def table(self) -> dict:
        mem = self.memory()
        with self._lock:
            return {
                "service": "supervisor",
                "profile": self.profile.name,
                "endpoint": self.endpoint,
                "router_restarts": self.router_restarts,
                "router_pid": (self.router.pid if self.router is not None
                               and self.router.poll() is None else None),
                "processes": {
                    n: {"pid": s.pid, "alive": s.alive, "restarts": s.restarts,
                        "last_exit": s.last_exit, "given_up": s.given_up,
                        "memory_mb": mem.get(n)}
                    for n, s in self.states.items()
                },
            }

    def memory(self) -> dict[str, dict[str, float]]:
        """Memory of each running child (and the router), :func:`proc_memory`'s figures:
        ``rss_mb`` now, ``peak_mb`` (VmHWM), ``shmem_mb``, ``pss_mb``, ``private_mb`` [MB].
        Linux only; {} elsewhere."""
        return self._per_process(proc_memory)

    def cpu(self) -> dict[str, dict[str, float]]:
        """CPU time each running child (and the router) has used so far: ``user_s``,
        ``sys_s``. With the in-process run's wall time it says what the split into processes
        costs each stage (docs/benchmarks.md). Linux only; {} elsewhere."""
        return self._per_process(proc_cpu)

    def _per_process(self, read: Callable[[int], dict[str, float] | None]
                     ) -> dict[str, dict[str, float]]:
        with self._lock:
            procs = dict(self.procs)
        if self.router is not None:
            procs["router"] = self.router
        out: dict[str, dict[str, float]] = {}
        for name, proc in procs.items():
            if proc.poll() is None and (v := read(proc.pid)) is not None:
                out[name] = v
        return out

    @property
    def restarts(self) -> int:
        """Restarts of the processes and of the router."""
        with self._lock:
            return sum(s.restarts for s in self.states.values()) + self.router_restarts
