"""Supervisor with real processes: a killed child comes back with its liveliness token,
and Ctrl-C on `topoexplore up` leaves no process behind."""

from __future__ import annotations

import os
import signal
import threading
import time

from tests.conftest import pid_alive
from topoexplore.common.bus import Bus
from topoexplore.common.keys import Keys
from topoexplore.tools.launch.core import ProcSpec, Profile, RestartPolicy
from topoexplore.tools.launch.supervisor import Supervisor


def wait_for(pred, timeout: float, period: float = 0.05) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(period)
    return False


def test_killed_child_comes_back(endpoint, namespace):
    profile = Profile(name="t", description="", router=True, processes=(
        ProcSpec(name="mapper", module="topoexplore.services.mapper.service"),
        ProcSpec(name="reliability", module="topoexplore.services.reliability.service"),
    ))
    keys = Keys(namespace, "robot1")
    lines: list[str] = []
    sup = Supervisor(profile, keys, endpoint, sink=lines.append,
                     policy=RestartPolicy(base=0.2, cap=1.0))
    try:
        assert sup.start(ready_timeout=60), "\n".join(lines)
        with Bus.client(endpoint) as bus:
            assert keys.alive("mapper") in bus.alive(keys.alive_all())
            old = sup.states["mapper"].pid
            os.kill(old, signal.SIGKILL)
            assert wait_for(lambda: (sup.poll() or True) and sup.states["mapper"].restarts == 1,
                            20), "\n".join(lines)
            assert wait_for(lambda: (sup.poll() or True) and sup.states["mapper"].alive, 60)
            assert sup.states["mapper"].pid != old
            assert keys.alive("mapper") in bus.alive(keys.alive_all())
        assert any("restart #1" in line for line in lines)
        assert sup.table()["processes"]["mapper"]["restarts"] == 1
    finally:
        sup.stop()
    for st in sup.states.values():
        assert st.pid is None
    assert sup.router is not None and sup.router.poll() is not None


def test_a_process_refusing_its_arguments_is_not_restarted(endpoint, namespace):
    """Exit 2 before it was up (bad arguments, parameters or files): a restart would fail the
    same way, so the supervisor gives up at once and start() says so without waiting out the
    ready timeout; the healthy process stays up."""
    profile = Profile(name="t", description="", router=True, processes=(
        ProcSpec(name="controller", module="topoexplore.services.controller.service"),
        ProcSpec(name="mapper", module="topoexplore.services.mapper.service",
                 args=("--set", "mapper.resolution=-1")),
    ))
    lines: list[str] = []
    sup = Supervisor(profile, Keys(namespace, "robot1"), endpoint, sink=lines.append,
                     policy=RestartPolicy(base=0.2, cap=1.0))
    try:
        t0 = time.monotonic()
        assert not sup.start(ready_timeout=60)
        assert time.monotonic() - t0 < 30, "\n".join(lines)
        st = sup.states["mapper"]
        assert st.given_up and st.restarts == 0 and st.last_exit == 2, "\n".join(lines)
        assert any("before it was up" in ln and "not restarted" in ln for ln in lines)
        assert wait_for(lambda: (sup.poll() or True) and sup.states["controller"].alive, 30)
    finally:
        sup.stop()


def test_a_busy_port_is_refused_and_a_dead_router_comes_back(endpoint, namespace):
    """Never join someone else's router unasked; a router that dies is restarted (counted)."""
    import socket

    import pytest

    from topoexplore.common.bus import BusError

    host, port = endpoint.split("/", 1)[1].rsplit(":", 1)
    profile = Profile(name="t", description="", router=True, processes=(
        ProcSpec(name="controller", module="topoexplore.services.controller.service"),))
    lines: list[str] = []
    with socket.socket() as other:
        other.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        other.bind((host, int(port)))
        other.listen()
        sup = Supervisor(profile, Keys(namespace, "robot1"), endpoint, sink=lines.append)
        try:
            with pytest.raises(BusError, match="already in use"):
                sup.start(ready_timeout=30)
            assert not sup.procs  # nothing was started against it
        finally:
            sup.stop()
    sup = Supervisor(profile, Keys(namespace, "robot1"), endpoint, sink=lines.append,
                     policy=RestartPolicy(base=0.2, cap=1.0))
    try:
        assert sup.start(ready_timeout=60), "\n".join(lines)
        os.killpg(sup.router.pid, signal.SIGKILL)
        assert wait_for(lambda: (sup.poll() or True) and sup.router_restarts == 1, 20)
        assert wait_for(lambda: sup._port_open(), 20), "\n".join(lines)
        assert sup.restarts == 1 and sup.table()["router_restarts"] == 1
        assert any("router exited" in ln and "restart #1" in ln for ln in lines)
    finally:
        sup.stop()


def test_a_second_stack_under_the_same_name_is_refused(endpoint, namespace):
    import pytest

    from topoexplore.common.bus import BusError

    one = Profile(name="t", description="", router=True, processes=(
        ProcSpec(name="controller", module="topoexplore.services.controller.service"),))
    two = Profile(name="t2", description="", router=False, processes=(
        ProcSpec(name="mapper", module="topoexplore.services.mapper.service"),))
    lines: list[str] = []
    first = Supervisor(one, Keys(namespace, "robot1"), endpoint, sink=lines.append)
    second = Supervisor(two, Keys(namespace, "robot1"), endpoint, sink=lines.append)
    other = Supervisor(two, Keys(namespace, "robot2"), endpoint, sink=lines.append)
    try:
        assert first.start(ready_timeout=60), "\n".join(lines)
        with pytest.raises(BusError, match="is taken"):
            second.start(ready_timeout=30)
        assert not second.procs
        assert other.start(ready_timeout=60), "\n".join(lines)  # another robot: fine
    finally:
        other.stop()
        second.stop()
        first.stop()


def test_ctrl_c_leaves_no_process_behind(procs, endpoint, namespace, tmp_path):
    up = procs.python("-m", "topoexplore.tools.cli", "up", "--profile", "mapping", "--connect", endpoint,
                      "--namespace", namespace)
    keys = Keys(namespace, "robot1")
    time.sleep(0.5)
    with Bus.client(endpoint, wait_for_router=True) as bus:
        want = {keys.alive(s) for s in ("mapper", "topology", "sim", "supervisor")}
        assert wait_for(lambda: want <= set(bus.alive(keys.alive_all())), 60)
        from topoexplore.tools.livestate import fetch_state

        table = fetch_state(bus, keys, "supervisor")
    pids = [p["pid"] for p in table["processes"].values()]
    assert all(pid_alive(p) for p in pids)
    up.send_signal(signal.SIGINT)
    out, _ = up.communicate(timeout=30)
    assert up.returncode == 0, out
    assert "stopped" in out
    assert wait_for(lambda: not any(pid_alive(p) for p in pids), 10)


def test_a_reader_that_goes_away_does_not_hang_up(procs, endpoint, namespace):
    """`topoexplore up | head -3`: the pipe closes after three lines. up must go on, stop
    cleanly on SIGTERM and leave no process behind (it used to die printing, skip its stop,
    and hang on exit with the stack still running)."""
    up = procs.python("-m", "topoexplore.tools.cli", "up", "--profile", "mapping", "--connect",
                      endpoint, "--namespace", namespace)
    keys = Keys(namespace, "robot1")
    for _ in range(3):
        assert up.stdout.readline()
    up.stdout.close()  # the reader went away
    with Bus.client(endpoint, wait_for_router=True) as bus:
        want = {keys.alive(s) for s in ("mapper", "topology", "sim", "supervisor")}
        assert wait_for(lambda: want <= set(bus.alive(keys.alive_all())), 60)
        from topoexplore.tools.livestate import fetch_state

        pids = [p["pid"] for p in fetch_state(bus, keys, "supervisor")["processes"].values()]
    up.send_signal(signal.SIGTERM)
    up.wait(timeout=30)
    assert up.returncode == 0
    assert wait_for(lambda: not any(pid_alive(p) for p in pids), 10)


def test_back_to_back_signals_stop_the_router_and_a_service(procs, namespace):
    """systemd sends SIGTERM to the whole unit and the supervisor sends its own: two signals
    at once. A handler that set an Event could deadlock on the Event's lock (2 of 10 router
    stops hung); the handlers now only write to a pipe."""
    from tests.conftest import free_port

    keys = Keys(namespace, "robot1")
    for k in range(6):
        endpoint = f"tcp/127.0.0.1:{free_port()}"
        router = procs.router(endpoint)
        assert "listening" in router.stdout.readline()
        if k % 2:  # a service too, stopped the same way
            svc = procs.python("-m", "topoexplore.services.controller.service", "--connect",
                               endpoint, "--namespace", namespace)
            with Bus.client(endpoint) as bus:
                assert wait_for(lambda: keys.alive("controller") in bus.alive(keys.alive_all()),
                                30)  # noqa: B023 - called at once, in this iteration
            for sig in (signal.SIGTERM, signal.SIGTERM, signal.SIGINT):
                svc.send_signal(sig)
            assert svc.wait(timeout=15) == 0
        for sig in (signal.SIGTERM, signal.SIGINT, signal.SIGTERM):
            router.send_signal(sig)
        assert router.wait(timeout=15) == 0


def test_clients_do_not_answer_multicast_scouting(endpoint):
    """A client connects to named endpoints; it used to answer scouting on every interface.
    Both our default client config and deploy/zenoh/client.json5 keep quiet."""
    import zenoh

    from tests.conftest import REPO
    from topoexplore.common.bus import make_config

    with Bus.router(endpoint), Bus.client(endpoint) as ours:
        quiet = Bus(make_config("client", connect=endpoint,  # the file's settings, our port
                                config_file=str(REPO / "deploy" / "zenoh" / "client.json5")))
        try:
            zids = {str(ours.session.info.zid()), str(quiet.session.info.zid())}
            hellos: list[str] = []
            scout = zenoh.scout(lambda h: hellos.append(str(h.zid)), what="peer|router|client")
            time.sleep(1.5)
            scout.stop()
            assert not zids & set(hellos), hellos
        finally:
            quiet.close()


def test_shared_memory_is_off_unless_asked_and_both_settings_deliver(endpoint, tmp_path):
    """make_config: zenoh's shared-memory transport off by default, on with shared_memory,
    and our setting overrides a config file's (like mode and endpoints). A 200 kB payload
    (over zenoh's 3 kB threshold) arrives intact through a router either way."""
    import json

    from topoexplore.common.bus import make_config

    def shm(cfg) -> bool:
        return json.loads(cfg.get_json("transport/shared_memory/enabled"))

    assert not shm(make_config("client", connect=endpoint))
    assert shm(make_config("client", connect=endpoint, shared_memory=True))
    assert shm(make_config("router", connect=None, listen=endpoint, shared_memory=True))
    f = tmp_path / "z.json5"
    f.write_text('{transport: {shared_memory: {enabled: true}}}')
    assert not shm(make_config("client", connect=endpoint, config_file=str(f)))
    payload = bytes(range(256)) * 800
    for on in (False, True):
        with Bus.router(endpoint, shared_memory=on), \
                Bus.client(endpoint, shared_memory=on) as a, \
                Bus.client(endpoint, shared_memory=on) as b:
            got: list[bytes] = []
            done = threading.Event()

            def take(sample, got=got, done=done):
                got.append(bytes(sample.payload.to_bytes()))
                done.set()

            sub = b.session.declare_subscriber("shmtest/x", take)
            try:
                pub = a.session.declare_publisher("shmtest/x")
                deadline = time.monotonic() + 10
                while not done.is_set() and time.monotonic() < deadline:
                    pub.put(payload)
                    done.wait(0.2)
                assert got and got[0] == payload, on
            finally:
                sub.undeclare()
