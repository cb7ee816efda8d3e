"""``fleet run``: start the fleet as separate OS processes and judge the run.

Processes are started with ``subprocess`` (fork + exec, so no parent state is
inherited; never a bare fork after Zenoh is open): the tracker listens on a
free loopback port, the supervisor and one agent per robot connect to it.  In
the mesh topology every process is a Zenoh peer and the peers link to each
other; in the star topology the tracker's session is a router and every other
process a client with one link, to it (docs/design.md, "Topology").
Readiness is each process's ``{"event": "ready"}`` line, waited on with a
timeout.  The run ends when the tracker exits; everything still running is
then stopped by pid (SIGTERM, then SIGKILL).
"""

from __future__ import annotations

import json
import os
import queue
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

from ground.net import NetConfig, free_port, loopback
from supervisor.judge import verdict

TOPOLOGIES = ("mesh", "star")
"""How ``fleet run`` links its processes: a mesh of Zenoh peers, or a star around the tracker."""
STAR_LEASE = 1.0
"""Default Zenoh lease in the star [s]: a hung agent is "not alive" within about a second.  The
mesh keeps 10 s: there a 1 s lease's keep-alives cost CPU in proportion to the n(n − 1)/2 links,
while the star's n links make it cheap (docs/design.md, "Liveliness lease")."""


@dataclass
class Proc:
    role: str
    popen: subprocess.Popen[str]
    lines: queue.Queue[str] = field(default_factory=queue.Queue)
    ready: dict[str, Any] = field(default_factory=dict)
    """The process's readiness line, once seen."""

    @property
    def pid(self) -> int:
        return self.popen.pid


def _pump(stream: IO[str], q: queue.Queue[str]) -> None:
    for line in stream:
        q.put(line)


def _start(role: str, module: str, args: list[str], env: dict[str, str]) -> Proc:
    popen = subprocess.Popen(
        [sys.executable, "-m", module, *args],
        stdout=subprocess.PIPE,
        stdin=subprocess.DEVNULL,
        text=True,
        env=env,
    )
    proc = Proc(role, popen)
    assert popen.stdout is not None
    threading.Thread(target=_pump, args=(popen.stdout, proc.lines), daemon=True).start()
    return proc


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


def run_fleet(
    scenario: str,
    robots: list[str],
    out: Path,
    seed: int | None,
    fleet: str = "lab",
    timeout: float = 600.0,
    viewer: bool = False,
    clock: str = "lockstep",
    hub: str | None = None,
    links: dict[str, str] | None = None,
    faults: str | None = None,
    exchange: str = "mesh",
    lease: float | None = None,
    topology: str = "mesh",
) -> tuple[int, str, dict[str, Any] | None]:
    """Run the fleet; returns (exit code, one-line verdict, summary or None).

    ``hub`` is the tracker's listening endpoint (default: a free loopback port).
    ``faults`` is a fault plan (:mod:`ground.faults`) handed to every process.
    ``exchange`` is how plans travel: ``mesh`` (agent to agent) or ``relay``
    (the tracker's digest, docs/design.md, "Relayed plans").
    ``lease`` is every process's Zenoh transport lease [s] (default 10 s in the mesh,
    :data:`STAR_LEASE` in the star).
    ``topology``: ``mesh`` (every process a Zenoh peer) or ``star`` (the tracker a
    router, every other process a client of it).
    ``links`` maps robot id → link; robots on ``"emulator"`` get an e-puck
    firmware emulator process (advanced sercom on a pseudo-terminal) and an
    ``epuck_link`` process driving it, and the tracker observes the emulators
    (``--source emulator``, realtime clock).  Every robot is simulated or every
    robot is emulated."""
    if topology not in TOPOLOGIES:
        raise ValueError(f"topology {topology!r} is not one of {', '.join(TOPOLOGIES)}")
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
    ]
    seed_args = [] if seed is None else ["--seed", str(seed)]
    hub_mode = ["--mode", "router"] if topology == "star" else []
    spoke = [*common, "--mode", "client"] if topology == "star" else common  # all but the tracker
    procs: list[Proc] = []
    emulators: list[Proc] = []
    try:
        source = ["--source", "emulator"] if emulated else []
        procs.append(
            _start("tracker", "tracker", [*common, *hub_mode, "--listen", hub, *seed_args, *source], env)
        )
        if _wait_ready(procs, 60.0):
            return 1, "tracker did not start", None
        # The robot side: one emulator and one epuck_link per emulated robot.
        for rid in emulated:
            emu_args = [*spoke, "--connect", hub, "--robot", rid, "--pty"]
            emulators.append(_start(f"emulator {rid}", "epuck_link.emulator", emu_args, env))
        procs += emulators
        late = _wait_ready(emulators, 60.0)
        if late:
            return 1, f"not ready: {', '.join(late)}", None
        bridges = []
        for e in emulators:
            rid, pty = e.ready["robot"], e.ready["pty"]
            link_args = [*spoke, "--connect", hub, "--robot", rid, "--link", f"serial:{pty}"]
            bridges.append(_start(f"epuck_link {rid}", "epuck_link", link_args, env))
        procs += bridges
        late = _wait_ready(bridges, 60.0)
        if late:
            return 1, f"not ready: {', '.join(late)}", None
        sup_args = [*spoke, "--connect", hub, "--out", str(out), *(["--viewer"] if viewer else [])]
        sup = _start("supervisor", "supervisor", sup_args, env)
        agents = [
            _start(f"agent {rid}", "agent", [*spoke, "--connect", hub, "--robot", rid], env) for rid in robots
        ]
        procs += [sup, *agents]
        late = _wait_ready([sup, *agents], 120.0)
        if late:
            return 1, f"not ready: {', '.join(late)}", None
        tracker = procs[0]
        try:
            tracker.popen.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            return 1, f"run did not finish within {timeout:.0f} s", None
        try:
            sup.popen.wait(timeout=60)
        except subprocess.TimeoutExpired:
            sup.popen.send_signal(signal.SIGTERM)
            sup.popen.wait(timeout=30)
        for a in agents:
            try:
                a.popen.wait(timeout=30)
            except subprocess.TimeoutExpired:
                pass
    finally:
        _stop(procs, robots=tuple(emulators))
    codes = {p.role: p.popen.returncode for p in procs}
    summary_path = out / "summary.json"
    summary = json.loads(summary_path.read_text()) if summary_path.exists() else None
    if summary is not None:
        summary["processes"] = {p.role: p.pid for p in procs}
        summary["exit_codes"] = codes
        lease_s = NetConfig.lease if lease is None else lease
        summary["network"] = {"topology": topology, "exchange": exchange, "lease_s": lease_s}
        summary_path.write_text(json.dumps(summary, indent=2) + "\n")
    crashed = [r for r, c in codes.items() if c not in (0, None)]
    if crashed:
        return 1, "process failed: " + ", ".join(f"{r} (exit {codes[r]})" for r in crashed), summary
    if summary is None:
        return 1, "supervisor wrote no summary", None
    why = verdict(summary)
    return (1, why, summary) if why else (0, "ok", summary)
