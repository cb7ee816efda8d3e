"""``fleet run``: start the fleet as separate OS processes and judge the run.

Processes are started with ``subprocess`` (fork + exec, so no parent state is
inherited; never a bare fork after Zenoh is open), except the agents: on Linux they are forked
by a fork server (:mod:`fleet.running.forkserver`) that imported their code once, before any thread or
session existed, which saves each agent its 0.45 s of imports.  The tracker listens on a
free loopback port, the supervisor and one agent per robot connect to it.  In
the mesh topology every process is a Zenoh peer and the peers link to each
other; in the star topology the tracker's session is a router and every other
process a client with one link, to it (docs/design.md, "Topology").
Readiness is each process's ``{"event": "ready"}`` line, waited on with a
timeout.  The run ends when the tracker exits; everything still running is
then stopped by pid (SIGTERM, then SIGKILL).

:func:`run_fleet` is ``fleet run``: :func:`start_fleet`, then :meth:`Launched.wait` and
:meth:`Launched.stop`.  A script that drives a fleet (``fleet.Fleet``) starts it with
``start_fleet(..., scripted=True)`` and is one more participant of it until it stops it.
"""

from __future__ import annotations

import contextlib
import json
import os
import queue
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import IO, Any, Protocol

from ground.scenario import load_scenario
from supervisor.judge import verdict
from transport.net import NetConfig, free_port, loopback
from transport.process import exchange_for, wait_owning

TOPOLOGIES = ("mesh", "star")
"""How ``fleet run`` links its processes: a mesh of Zenoh peers, or a star around the tracker."""
STARTS = ("fork", "spawn") if sys.platform == "linux" else ("spawn",)
"""How ``fleet run`` may start the agents, the default first: forked by :class:`ForkServer`
(Linux only: ``SOCK_SEQPACKET`` Unix sockets, ``/proc``), or each spawned as an interpreter."""
STOP_WAIT = 60.0
"""How long a served fleet's tracker may take to end its run once told to [s]."""
STAR_LEASE = 1.0
"""Default Zenoh lease in the star [s]: a hung agent is "not alive" within about a second.  The
mesh keeps 10 s: there a 1 s lease's keep-alives cost CPU in proportion to the n(n − 1)/2 links,
while the star's n links make it cheap (docs/design.md, "Liveliness lease")."""


class Child(Protocol):
    """What the launcher needs of a process it started: :class:`subprocess.Popen`'s, or a
    :class:`Forked` agent's."""

    @property
    def pid(self) -> int:
        """The process id."""
        ...

    @property
    def returncode(self) -> int | None:
        """The exit code once known (negative: the signal that ended it), else None."""
        ...

    def poll(self) -> int | None:
        """The exit code if the process has ended, else None; never waits."""
        ...

    def wait(self, timeout: float | None = None) -> int:
        """Wait up to ``timeout`` [s] (None: for good) for the process to end and return its exit
        code; :class:`subprocess.TimeoutExpired` if it has not ended by then."""
        ...

    def send_signal(self, sig: int) -> None:
        """Send signal ``sig`` to the process."""
        ...

    def kill(self) -> None:
        """End the process with SIGKILL."""
        ...


@dataclass
class Proc:
    """A process the launcher started: its ``role`` (``tracker``, ``supervisor``, ``agent r1`` …),
    the process (:class:`Child`), and the lines of its stdout, queued by a reader thread."""

    role: str
    popen: Child
    lines: queue.Queue[str] = field(default_factory=queue.Queue)
    ready: dict[str, Any] = field(default_factory=dict)
    """The process's readiness line, once seen."""

    @property
    def pid(self) -> int:
        """The process id."""
        return self.popen.pid


def _pump(stream: IO[str], q: queue.Queue[str]) -> None:
    for line in stream:
        q.put(line)


def _start(
    role: str, module: str, args: list[str], env: dict[str, str], stderr: int | IO[str] | None = None,
    pass_fds: tuple[int, ...] = (), own_session: bool = False,
) -> Proc:  # fmt: skip
    """Start ``python -m module args`` as ``role``, its stdout read line by line; ``own_session``:
    in a session of its own, so that the terminal's Ctrl-C reaches the launcher only."""
    popen = subprocess.Popen(
        [sys.executable, "-m", module, *args],
        stdout=subprocess.PIPE,
        stdin=subprocess.DEVNULL,
        stderr=stderr,
        text=True,
        env=env,
        pass_fds=pass_fds,
        start_new_session=own_session,
    )
    proc = Proc(role, popen)
    assert popen.stdout is not None
    threading.Thread(target=_pump, args=(popen.stdout, proc.lines), daemon=True).start()
    return proc


class Forked:
    """A process the fork server started: :class:`subprocess.Popen`'s interface, with the exit
    status reported by the fork server (its parent) instead of waited for here."""

    def __init__(self, server: ForkServer, pid: int):
        self._server, self.pid = server, pid

    @property
    def returncode(self) -> int | None:
        """The exit code the fork server reported (:attr:`ForkServer.UNKNOWN` once the server
        is gone and the process too), None until then."""
        return self._server.exit_code(self.pid)

    def poll(self) -> int | None:
        """As :attr:`returncode`: never waits."""
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        """The exit code, waiting up to ``timeout`` [s] (None: for good);
        :class:`subprocess.TimeoutExpired` if the process has not ended by then."""
        code = self._server.wait_exit(self.pid, timeout)
        if code is None:
            raise subprocess.TimeoutExpired(f"pid {self.pid}", timeout or 0.0)
        return code

    def send_signal(self, sig: int) -> None:
        """Send signal ``sig``, unless the process is known to have ended (one already gone
        is ignored)."""
        if self.returncode is None:
            try:
                os.kill(self.pid, sig)
            except ProcessLookupError:
                pass

    def kill(self) -> None:
        """Send SIGKILL (as :meth:`send_signal`)."""
        self.send_signal(signal.SIGKILL)


class ForkServer:
    """The launcher's end of :mod:`fleet.running.forkserver`: start it, ask it for children, learn their
    exit codes, and close it (which ends it, and any child still running)."""

    UNKNOWN = 255
    """Exit code of a child whose fork server died before reporting it."""

    def __init__(
        self, preload: list[str], env: dict[str, str], stderr: int | IO[str] | None, own_session: bool = False
    ):
        """``own_session``: the server, and so every child it forks, in a session of its own."""
        self._sock, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        with theirs:
            args = ["--socket-fd", str(theirs.fileno()), *[a for m in preload for a in ("--preload", m)]]
            self.proc = _start(
                "forkserver", "fleet.running.forkserver", args, env, stderr, (theirs.fileno(),), own_session
            )
        self.popen = self.proc.popen
        self._replies: queue.Queue[dict[str, Any]] = queue.Queue()
        self._codes: dict[int, int] = {}
        self._gone = False
        self._cond = threading.Condition()
        self._lock = threading.Lock()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        while True:
            try:
                data = self._sock.recv(1 << 16)
            except OSError:
                data = b""
            if not data:
                break
            msg = json.loads(data)
            if "exit" in msg:
                with self._cond:
                    self._codes[int(msg["exit"])] = int(msg["code"])
                    self._cond.notify_all()
            else:
                self._replies.put(msg)
        with self._cond:
            self._gone = True
            self._cond.notify_all()
        self._replies.put({"error": f"fork server ended (exit {self.popen.wait()})"})

    def start(self, role: str, module: str, args: list[str], title: str = "", timeout: float = 30.0) -> Proc:
        """Fork ``module.main(args)`` (a module the server preloaded) as ``role``, its command
        line shown as ``title``."""
        r, w = os.pipe()
        request = json.dumps({"module": module, "argv": args, "title": title}).encode()
        try:
            with self._lock:
                socket.send_fds(self._sock, [request], [w])
                reply = self._replies.get(timeout=timeout)
        except (OSError, queue.Empty) as e:
            os.close(r)
            raise LaunchError(f"{role}: the fork server did not answer ({e or 'timeout'})") from None
        finally:
            os.close(w)
        if "pid" not in reply:
            os.close(r)
            raise LaunchError(f"{role}: {reply.get('error', reply)}")
        proc = Proc(role, Forked(self, int(reply["pid"])))
        stream = open(r, encoding="utf-8", errors="replace")  # the pump thread reads it to its end
        threading.Thread(target=_pump, args=(stream, proc.lines), daemon=True).start()
        return proc

    def exit_code(self, pid: int) -> int | None:
        """``pid``'s exit code if known, without waiting: the one the server reported, or
        :attr:`UNKNOWN` once the server is gone and the process too; else None."""
        with self._cond:
            return self._known(pid)

    def wait_exit(self, pid: int, timeout: float | None) -> int | None:
        """``pid``'s exit code, waiting up to ``timeout`` [s] (None: for good); None on timeout.
        Once the server is gone its orphans are polled, every 0.1 s, until they are gone too."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._cond:
            while (code := self._known(pid)) is None:
                left = None if deadline is None else deadline - time.monotonic()
                if left is not None and left <= 0:
                    return None
                wait_owning(self._cond, min(0.1, left or 0.1) if self._gone else left)
            return code

    def _known(self, pid: int) -> int | None:
        if pid in self._codes:
            return self._codes[pid]
        if self._gone and not _alive(pid):
            return self.UNKNOWN
        return None

    def close(self, grace: float = 10.0) -> None:
        """Stop asking: the server ends its children still running, reports their exits and
        exits; then close the socket.  ``grace`` [s]: how long the server gets (its children get
        SIGTERM, and SIGKILL after :data:`fleet.running.forkserver.GRACE`) before it is killed."""
        with contextlib.suppress(OSError):
            self._sock.shutdown(socket.SHUT_WR)
        try:
            self.popen.wait(timeout=grace)
        except subprocess.TimeoutExpired:
            self.popen.kill()
            self.popen.wait(timeout=5)
        self._reader.join(timeout=5)  # the server's end is closed: the reader is at its EOF
        self._sock.close()


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _wait_ready(procs: list[Proc], timeout: float) -> list[str]:
    """Roles that did not announce readiness within ``timeout`` [s] (or died)."""
    deadline = time.monotonic() + timeout
    pending = {p.role: p for p in procs}
    while pending and time.monotonic() < deadline:
        for role, p in list(pending.items()):
            try:
                line = p.lines.get(timeout=0.05)
            except queue.Empty:
                if p.popen.poll() is not None:
                    return [role]
                continue
            try:
                msg = json.loads(line)
                if msg.get("event") == "ready":
                    p.ready = msg
                    del pending[role]
            except (json.JSONDecodeError, AttributeError):
                continue
    return sorted(pending)


def _stop(procs: list[Proc], grace: float = 5.0, robots: tuple[Proc, ...] = ()) -> None:
    """SIGTERM every running process, the last started first, then SIGKILL after
    ``grace`` [s]; the ``robots`` (e-puck emulators) only once the others are gone,
    so that each link process has zeroed its wheels before its robot goes (sent
    together, an emulator could close its port first: "zero speed NOT sent")."""
    for group in ([p for p in procs if p not in robots], [p for p in procs if p in robots]):
        for p in reversed(group):
            if p.popen.poll() is None:
                p.popen.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + grace
        for p in group:
            try:
                p.popen.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                p.popen.kill()
                p.popen.wait(timeout=5)


class LaunchError(RuntimeError):
    """A fleet did not start (the message says which process); what had started is stopped."""


@dataclass
class Launched:
    """A fleet of processes started by :func:`start_fleet`, running.

    :meth:`wait` waits for the run's end and judges it, :meth:`stop` ends every process by pid.
    Both are safe to call more than once; :meth:`wait` stops what is left when it returns."""

    procs: list[Proc]
    """Every process started, the tracker first."""
    emulators: list[Proc]
    """The e-puck emulators among them, stopped last."""
    hub: str
    """The tracker's listening endpoint, e.g. ``tcp/127.0.0.1:7447``: a script connects to it."""
    out: Path
    """The run's directory: ``summary.json``, ``trace.npz``, ``recording.rrd``."""
    network: dict[str, Any]
    """``topology``, ``exchange`` and ``lease_s`` [s], for the summary."""
    forkserver: ForkServer | None = None
    """The agents' fork server, closed once they are stopped (None: the agents were spawned)."""
    serve: bool = False
    """A served fleet (``fleet run --serve``): Ctrl-C or SIGTERM asks the tracker to end the run."""

    @property
    def tracker(self) -> Proc:
        """The tracker's process (the first started)."""
        return self.procs[0]

    @property
    def pids(self) -> dict[str, int]:
        """Process id of every process, by role (``tracker``, ``supervisor``, ``agent r1`` …)."""
        return {p.role: p.pid for p in self.procs}

    def wait(self, timeout: float | None = 600.0) -> tuple[int, str, dict[str, Any] | None]:
        """Wait for the tracker's end (``timeout`` [s], None: for good), then for the supervisor's summary and
        the agents' exits, stop what is left, and judge the run: (exit code, one-line verdict,
        summary or None), as ``fleet run`` reports it."""
        try:
            try:
                self._wait_tracker(timeout)
            except subprocess.TimeoutExpired:
                return 1, f"run did not finish within {timeout:.0f} s", None
            sup = next(p for p in self.procs if p.role == "supervisor")
            try:
                sup.popen.wait(timeout=60)
            except subprocess.TimeoutExpired:
                sup.popen.send_signal(signal.SIGTERM)
                sup.popen.wait(timeout=30)
            for a in self.procs:
                if a.role.startswith("agent "):
                    try:
                        a.popen.wait(timeout=30)
                    except subprocess.TimeoutExpired:
                        pass
        finally:
            self.stop()
        return self._judged()

    def _wait_tracker(self, timeout: float | None) -> None:
        """Wait for the tracker's end (``timeout`` [s], None: for good).  A served fleet ends on
        Ctrl-C (or SIGTERM, which ``fleet run`` turns into it) as on a stop request: the tracker,
        told by SIGTERM, ends the run at its next step, and the summary is written as at the
        end of a duration."""
        try:
            self.tracker.popen.wait(timeout=timeout)
        except KeyboardInterrupt:
            if not self.serve:
                raise
            print("fleet: stopping the served fleet (its summary follows)", file=sys.stderr, flush=True)
            self.tracker.popen.send_signal(signal.SIGTERM)
            self.tracker.popen.wait(timeout=STOP_WAIT)

    def stop(self) -> None:
        """End every process still running, by pid: SIGTERM, then SIGKILL (:func:`_stop`)."""
        _stop(self.procs, robots=tuple(self.emulators))
        if self.forkserver is not None:
            self.forkserver.close()

    def _judged(self) -> tuple[int, str, dict[str, Any] | None]:
        """The run's verdict once every process has ended; the summary gets the processes,
        their exit codes and the network."""
        codes = {p.role: p.popen.returncode for p in self.procs}
        summary_path = self.out / "summary.json"
        summary = json.loads(summary_path.read_text()) if summary_path.exists() else None
        if summary is not None:
            summary["processes"] = self.pids
            summary["exit_codes"] = codes
            summary["network"] = self.network
            if self.network.get("delay_compensation"):  # as fleet simulate's summary says it
                summary["delay_compensation"] = True
            summary_path.write_text(json.dumps(summary, indent=2) + "\n")
        crashed = [r for r, c in codes.items() if c not in (0, None)]
        if crashed:
            return 1, "process failed: " + ", ".join(f"{r} (exit {codes[r]})" for r in crashed), summary
        if summary is None:
            return 1, "supervisor wrote no summary", None
        why = verdict(summary)
        return (1, why, summary) if why else (0, "ok", summary)


def start_fleet(
    scenario: str,
    robots: list[str],
    out: Path,
    seed: int | None,
    fleet: str = "lab",
    viewer: bool = False,
    clock: str = "lockstep",
    hub: str | None = None,
    links: dict[str, str] | None = None,
    faults: str | None = None,
    exchange: str = "auto",
    lease: float | None = None,
    topology: str = "mesh",
    scripted: bool = False,
    serve: bool = False,
    agent_timeout: float | None = None,
    stderr: int | IO[str] | None = None,
    ros2: bool | None = None,
    ros_domain: int | None = None,
    ros_listen: str | None = None,
    fork: bool | None = None,
    delay_compensation: bool = True,
) -> Launched:
    """Start the fleet of ``scenario`` (its robots ``robots``), writing to ``out``, and return
    once every process is ready.  Raises :class:`LaunchError` if one does not start, once the
    others are stopped.

    ``seed`` overrides the scenario's.  ``fleet`` is the fleet's name in the keys.
    ``hub`` is the tracker's listening endpoint (default: a free loopback port).
    ``faults`` is a fault plan (:mod:`transport.faults`) handed to every process.
    ``exchange`` is how plans travel: ``mesh`` (every agent to every agent), ``place`` (agent
    to agent by place, docs/design.md, "Plans by place") or ``relay`` (the tracker's digest,
    "Relayed plans"); ``auto``: :func:`exchange_for` the clock.
    ``lease`` is every process's Zenoh transport lease [s] (default 10 s in the mesh,
    :data:`STAR_LEASE` in the star).
    ``topology``: ``mesh`` (every process a Zenoh peer) or ``star`` (the tracker a
    router, every other process a client of it).
    ``links`` maps robot id → link; robots on ``"emulator"`` get an e-puck
    firmware emulator process (advanced sercom on a pseudo-terminal) and an
    ``epuck_link`` process driving it, and the tracker observes the emulators
    (``--source emulator``, realtime clock).  Every robot is simulated or every
    robot is emulated.

    ``scripted``: a script drives the run (docs/design.md, "Scripted runs"): it connects to
    :attr:`Launched.hub`, declares the liveliness token ``fleet/F/alive/script`` within the
    tracker's start-up time (60 s), and on lockstep permits every step (:class:`ground.wire.Script`);
    the run ends when it says so or leaves.  ``serve``: the fleet stays up once its robots are
    home, past the scenario's duration, until a stop request (``fleet stop``), or Ctrl-C or
    SIGTERM to the launcher (:meth:`Launched.wait`); its processes run in sessions of their own,
    so that the terminal's Ctrl-C reaches the launcher only.  ``agent_timeout``: each agent's
    ``--timeout`` [s] (default 30): how long it waits for a tick, a measurement or the
    neighbours' plans.
    ``stderr``: where the processes' log lines go (a file descriptor or file; default this
    process's stderr).  ``ros2``: also start the fleet's ROS 2 face (``python -m ros2_link``,
    docs/ros2.md) on domain ``ros_domain`` (default the scenario's ``[ros2]`` domain); None: as the
    scenario's ``[ros2] enabled`` says.  ``ros_listen``: the endpoint the ROS face listens on for
    ROS 2 tools in the mesh (default a free loopback port); a ROS 2 session must link to the face
    itself, since peers do not forward each other's data.  In the star, ROS 2 tools connect to the
    hub, the router.  ``fork``: fork the agents from a fork server that imported their code once
    (:mod:`fleet.running.forkserver`) rather than start each as a new interpreter; None: as
    :data:`STARTS` says (on Linux).  ``delay_compensation``: every agent plans a step ahead
    (docs/design.md, "Delay compensation")."""
    if ros_listen is not None and topology == "star":
        raise ValueError("ros_listen: in the star topology ROS 2 tools connect to the hub (the router)")
    if topology not in TOPOLOGIES:
        raise ValueError(f"topology {topology!r} is not one of {', '.join(TOPOLOGIES)}")
    exchange = exchange_for(clock, exchange)
    emulated = [r for r in robots if (links or {}).get(r, "sim") == "emulator"]
    hub = hub or loopback(free_port())
    print(f"fleet: hub {hub} (fleet goal --connect {hub} ...)", file=sys.stderr, flush=True)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "RERUN_ANALYTICS": "0"}
    if lease is None and topology == "star":
        lease = STAR_LEASE
    common = [
        "--scenario",
        scenario,
        "--fleet",
        fleet,
        "--clock",
        clock,
        "--exchange",
        exchange,
        *(["--faults", faults] if faults else []),
        *(["--lease", repr(lease)] if lease is not None else []),
        "--delay-compensation" if delay_compensation else "--no-delay-compensation",
    ]
    seed_args = [] if seed is None else ["--seed", str(seed)]
    hub_mode = ["--mode", "router"] if topology == "star" else []
    spoke = [*common, "--mode", "client"] if topology == "star" else common  # all but the tracker
    script = ["--scripted"] if scripted else []
    agent_args = [*script, *([] if agent_timeout is None else ["--timeout", repr(agent_timeout)])]
    start = partial(_start, env=env, stderr=stderr, own_session=serve)
    procs: list[Proc] = []
    emulators: list[Proc] = []
    server: ForkServer | None = None
    started = False
    try:
        source = ["--source", "emulator"] if emulated else []
        served = ["--serve"] if serve else []
        tracker_args = [*common, *hub_mode, "--listen", hub, *seed_args, *source, *script, *served]
        procs.append(start("tracker", "tracker", tracker_args))
        if STARTS[0] == "fork" if fork is None else fork:
            server = ForkServer(
                ["agent.node"], env, stderr, own_session=serve
            )  # imports while the tracker starts
        if _wait_ready(procs, 60.0):
            raise LaunchError("tracker did not start")
        _start_robot_side(emulated, [*spoke, "--connect", hub], start, procs, emulators)
        sup_args = [*spoke, "--connect", hub, "--out", str(out), *(["--viewer"] if viewer else [])]
        sup = start("supervisor", "supervisor", sup_args)
        observers = [sup]
        if ros2 is None:
            ros2 = load_scenario(scenario).ros2.enabled
        if ros2:
            domain = [] if ros_domain is None else ["--ros-domain", str(ros_domain)]
            if topology == "star":
                ros_endpoint, listen = hub, []
            else:
                ros_endpoint = ros_listen or loopback(free_port())
                listen = ["--listen", ros_endpoint]
            print(f"fleet: ROS 2 tools connect to {ros_endpoint} (docs/ros2.md)", file=sys.stderr, flush=True)
            observers.append(start("ros2", "ros2_link", [*spoke, "--connect", hub, *listen, *domain]))
        procs += observers
        if server is not None and _wait_ready([server.proc], 60.0):
            raise LaunchError("the agents' fork server did not start")
        agents = _start_agents(robots, [*spoke, "--connect", hub], agent_args, start, server, procs)
        late = _wait_ready([*observers, *agents], 120.0)
        if late:
            raise LaunchError(f"not ready: {', '.join(late)}")
        started = True
    finally:
        if not started:
            _stop(procs, robots=tuple(emulators))
            if server is not None:
                server.close()
    lease_s = NetConfig.lease if lease is None else lease
    network: dict[str, Any] = {"topology": topology, "exchange": exchange, "lease_s": lease_s}
    if delay_compensation:  # as fleet simulate's summary says it (absent in the paper's order)
        network["delay_compensation"] = True
    if ros2:
        network["ros_endpoint"] = ros_endpoint
    return Launched(procs, emulators, hub, out, network, server, serve)


def _start_agents(
    robots: list[str], args: list[str], agent_args: list[str], start: Callable[..., Proc],
    server: ForkServer | None, procs: list[Proc],
) -> list[Proc]:  # fmt: skip
    """One agent per robot, with ``args``, its ``--robot`` and ``agent_args``: forked by
    ``server`` (its title the command line it stands for), or started as an interpreter; each
    goes on ``procs`` as it starts (to be stopped whatever comes next), and all are returned."""
    agents: list[Proc] = []
    for rid in robots:
        argv = [*args, "--robot", rid, *agent_args]
        role = f"agent {rid}"
        if server is not None:
            title = " ".join([sys.executable, "-m", "agent", *argv])
            agents.append(server.start(role, "agent.node", argv, title))
        else:
            agents.append(start(role, "agent", argv))
        procs.append(agents[-1])
    return agents


def _start_robot_side(
    robots: list[str], args: list[str], start: Callable[..., Proc], procs: list[Proc], emulators: list[Proc]
) -> None:
    """The robot side of emulated ``robots``: one e-puck firmware emulator each, on a
    pseudo-terminal, then one ``epuck_link`` driving it, each started with ``args`` once the one
    before is ready; both kinds go on ``procs``, the emulators on ``emulators`` too.  LaunchError
    names those not ready within a minute."""
    for rid in robots:
        emulators.append(start(f"emulator {rid}", "epuck_link.emulator", [*args, "--robot", rid, "--pty"]))
    procs += emulators
    late = _wait_ready(emulators, 60.0)
    if late:
        raise LaunchError(f"not ready: {', '.join(late)}")
    bridges = []
    for e in emulators:
        rid, pty = e.ready["robot"], e.ready["pty"]
        bridges.append(
            start(f"epuck_link {rid}", "epuck_link", [*args, "--robot", rid, "--link", f"serial:{pty}"])
        )
    procs += bridges
    late = _wait_ready(bridges, 60.0)
    if late:
        raise LaunchError(f"not ready: {', '.join(late)}")


def run_fleet(
    scenario: str, robots: list[str], out: Path, seed: int | None, timeout: float | None = 600.0,
    **options: Any,
) -> tuple[int, str, dict[str, Any] | None]:  # fmt: skip
    """Run the fleet (``fleet run``); returns (exit code, one-line verdict, summary or None).

    ``options`` are those of :func:`start_fleet`; ``timeout`` [s] bounds the run, from the moment
    every process is ready (None: no bound, for a served fleet)."""
    try:
        launched = start_fleet(scenario, robots, out, seed, **options)
    except LaunchError as e:
        return 1, str(e), None
    try:
        return launched.wait(timeout)
    finally:
        launched.stop()
