#!/usr/bin/env python3
"""Linux network namespaces as the lab's hosts: a router host and robot hosts on one bridge.

Usage (as root: CAP_SYS_ADMIN and CAP_NET_ADMIN; needs iproute2's ``ip``)::

    python deploy/netns.py check             # can namespaces be made here? (exit 0, or 1 and why)
    python deploy/netns.py up [--owner PID] [--hosts a b] [--sysctl net.ipv4.tcp_retries2=5]
                                             # make them; prints the topology as JSON
    python deploy/netns.py cut b             # take host b's link down (a pulled cable) ...
    python deploy/netns.py restore b         # ... and up again
    python deploy/netns.py down [--owner PID]  # end what still runs inside them, remove them
    python deploy/netns.py clean             # remove leftovers whose owner process is gone

Topology, for owner ``O`` (default: the pid of the shell that runs the
script, so ``up``, ``cut`` and ``down`` from one shell agree; under ``sudo``
pass ``--owner $$``) and hosts ``a b``::

    efleet-O-router                                   efleet-O-a
      br0 198.51.100.1/24 ── to-a ═══ veth ═══ eth0 198.51.100.2/24
                         └── to-b ═══ veth ═══ eth0 198.51.100.3/24
                                                  efleet-O-b

Every address is in TEST-NET-2, 198.51.100.0/24 (RFC 5737: documentation
only, never routed) and exists only inside these namespaces: the veth pairs
are created directly between them, so nothing is added to the calling
namespace, there is no default route and no IPv6 address (``addrgenmode
none``).  Each namespace also has ``lo`` up.  ``cut``/``restore`` set a
robot host's ``eth0`` down/up (``ip -n efleet-O-b link set eth0 down``), which
its peer on the bridge sees as carrier loss: a cable pulled.  ``--sysctl``
sets a ``net.*`` kernel setting inside every namespace (never the caller's;
a key the kernel does not keep per namespace is refused).

A pulled cable and ``net.ipv4.tcp_retries2``: Zenoh (1.10) drops a client's
session when its lease (10 s) expires, but while messages to that client are
still queued its transport only closes once the socket write fails, and
Linux keeps retransmitting unacknowledged data for about 15 minutes
(``tcp_retries2 = 15``).  The router then keeps the cut host's liveliness
tokens until the cable is back.  ``tcp_retries2 = 5`` gives up after about
13 s, so the cut host is dropped (its tokens withdrawn) about 14 s after the
cut; ``tests/system/test_multihost.py`` sets it on every host.

By hand, from one root shell in the project directory (``$$`` is that
shell's pid, the default owner)::

    python deploy/netns.py up --sysctl net.ipv4.tcp_retries2=5
    python deploy/make_certs.py /tmp/pki --scenario scenarios/paper_three_robots.toml \
        --router-host 198.51.100.1
    for r in tracker supervisor; do python -m secure_router config $r --certs /tmp/pki \
        --router tls/198.51.100.1:7447 --connect-timeout 10 > /tmp/$r.json; done
    for r in r1 r2 r3; do python -m secure_router config agent --robot $r --certs /tmp/pki \
        --router tls/198.51.100.1:7447 --connect-timeout 10 > /tmp/$r.json; done
    ip netns exec efleet-$$-router python -m secure_router router --certs /tmp/pki \
        --listen tls/198.51.100.1:7447 --robots r1 r2 r3 --sim-tracker &
    S="--scenario scenarios/paper_three_robots.toml --clock realtime"
    ip netns exec efleet-$$-router python -m tracker $S --zenoh-config /tmp/tracker.json &
    ip netns exec efleet-$$-router python -m supervisor $S --out /tmp/out \
        --zenoh-config /tmp/supervisor.json &
    ip netns exec efleet-$$-a python -m agent $S --robot r1 --zenoh-config /tmp/r1.json &
    ip netns exec efleet-$$-b python -m agent $S --robot r2 --zenoh-config /tmp/r2.json &
    ip netns exec efleet-$$-b python -m agent $S --robot r3 --zenoh-config /tmp/r3.json &
    sleep 10; python deploy/netns.py cut b         # a partition, some 50 steps into the run
    sleep 20; python deploy/netns.py restore b     # r2 and r3 rejoin
    wait %2; kill %1; wait                         # the tracker ends the run; stop the router
    python deploy/netns.py down                    # /tmp/out/summary.json has the verdict

``ip netns exec`` execs in place, so a process keeps the pid its parent
started.  ``down`` and ``clean`` end the processes still inside a namespace
(listed by ``ip netns pids``: SIGTERM, then SIGKILL) before deleting it,
since a namespace with a process in it outlives its name.  ``clean``
touches only names ``efleet-<pid>-<host>`` whose ``<pid>`` is no longer
running.

The functions (:func:`create`, :func:`destroy`, :func:`clean`,
:func:`unavailable`, :class:`Topology`) are what ``tests/system/test_multihost.py``
uses.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import select
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

BASE = "efleet"
"""Prefix of every namespace this module makes: ``efleet-<owner pid>-<host>``."""
SUBNET = "198.51.100"
"""TEST-NET-2 (RFC 5737), /24: documentation only, never routed on a real network."""
PREFIX_LEN = 24
ROUTER = "router"
"""Name of the router's host."""
ROUTER_ADDRESS = f"{SUBNET}.1"
BRIDGE = "br0"
"""The bridge in the router's namespace; it holds the router's address."""
ROBOT_IF = "eth0"
"""A robot host's interface (the veth end inside its namespace)."""
HOST = re.compile(r"^[a-z][a-z0-9]{0,7}$")
"""Robot host names: short, so that ``to-<host>`` fits the kernel's 15-character limit."""
NAME = re.compile(rf"^{BASE}-(?P<owner>\d+)-(?P<host>[a-z0-9]+)$")
IP_TIMEOUT_S = 20.0
"""Limit for one ``ip`` command [s]."""
SYSCTL_KEY = re.compile(r"^net\.[a-z0-9_]+(\.[a-z0-9_]+)+$")
"""Kernel settings a topology may set: network ones, which Linux keeps per namespace."""
STOP_GRACE_S = 5.0
"""How long a process left in a namespace gets between SIGTERM and SIGKILL [s]."""


class NetnsError(RuntimeError):
    """An ``ip`` command failed; the message holds the command and its stderr."""


def ip(*args: str, check: bool = True) -> subprocess.CompletedProcess[str]:
    """Run ``ip ARGS`` (bounded by :data:`IP_TIMEOUT_S`); raises NetnsError if it fails and ``check``."""
    cmd = ["ip", *args]
    try:
        res = subprocess.run(cmd, capture_output=True, text=True, timeout=IP_TIMEOUT_S)
    except (OSError, subprocess.TimeoutExpired) as e:
        raise NetnsError(f"{' '.join(cmd)}: {e}") from None
    if check and res.returncode != 0:
        raise NetnsError(f"{' '.join(cmd)}: exit {res.returncode}: {res.stderr.strip()}")
    return res


@dataclass(frozen=True)
class Host:
    """One namespace of the topology."""

    name: str
    """``router`` or a robot host's name (``a``, ``b``, ...)."""
    netns: str
    """Namespace name, ``efleet-<owner>-<name>``."""
    interface: str
    """The interface holding the address: ``br0`` on the router, ``eth0`` on a robot host."""
    address: str
    """IPv4 address, in :data:`SUBNET`.0/24."""
    peer: str | None = None
    """A robot host's veth peer on the router's bridge (``to-<name>``); None for the router."""


@dataclass(frozen=True)
class Topology:
    """A router namespace and robot-host namespaces on one bridge (see the module docstring)."""

    owner: int
    """Pid whose lifetime the namespaces belong to (:func:`clean` removes them once it is gone)."""
    hosts: dict[str, Host] = field(default_factory=dict)

    @property
    def router(self) -> Host:
        return self.hosts[ROUTER]

    def exec_args(self, host: str, argv: Sequence[str]) -> list[str]:
        """The command line running ``argv`` inside ``host``'s namespace (same pid: exec in place)."""
        return ["ip", "netns", "exec", self.hosts[host].netns, *argv]

    def set_link(self, host: str, up: bool) -> None:
        """Set a robot host's interface up or down (down: a partition of that host)."""
        h = self.hosts[host]
        if h.peer is None:
            raise ValueError(f"host: {host!r} is the router; cut a robot host's link instead")
        ip("-n", h.netns, "link", "set", h.interface, "up" if up else "down")

    def link_up(self, host: str) -> bool:
        """Whether ``host``'s interface is administratively up."""
        h = self.hosts[host]
        info = json.loads(ip("-j", "-n", h.netns, "link", "show", h.interface).stdout)
        return "UP" in info[0]["flags"]

    def describe(self) -> dict[str, object]:
        """The topology as a JSON-able dict."""
        return {
            "owner": self.owner,
            "subnet": f"{SUBNET}.0/{PREFIX_LEN}",
            "hosts": {
                n: {"netns": h.netns, "interface": h.interface, "address": h.address, "peer": h.peer}
                for n, h in self.hosts.items()
            },
        }


def netns_name(owner: int, host: str) -> str:
    return f"{BASE}-{owner}-{host}"


def plan(owner: int, robot_hosts: Sequence[str] = ("a", "b")) -> Topology:
    """The topology for ``owner`` and ``robot_hosts``, without creating anything."""
    robot_hosts = list(robot_hosts)
    bad = [h for h in robot_hosts if not HOST.match(h) or h == ROUTER]
    if bad or not robot_hosts or len(set(robot_hosts)) != len(robot_hosts):
        raise ValueError(f"hosts: need distinct names matching {HOST.pattern}, not {ROUTER!r}: {robot_hosts}")
    if len(robot_hosts) > 250:
        raise ValueError(f"hosts: at most 250 fit in {SUBNET}.0/{PREFIX_LEN}, got {len(robot_hosts)}")
    hosts = {ROUTER: Host(ROUTER, netns_name(owner, ROUTER), BRIDGE, ROUTER_ADDRESS)}
    for i, h in enumerate(robot_hosts):
        hosts[h] = Host(h, netns_name(owner, h), ROBOT_IF, f"{SUBNET}.{i + 2}", peer=f"to-{h}")
    return Topology(owner, hosts)


def existing() -> list[str]:
    """Names of the namespaces of this module (``efleet-<pid>-<host>``) that exist now."""
    out = ip("netns", "list").stdout
    names = [line.split()[0] for line in out.splitlines() if line.strip()]
    return [n for n in names if NAME.match(n)]


def _pid_alive(pid: int) -> bool:
    """Whether a process ``pid`` exists (a zombie counts: its pid is still taken)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        pass
    return True


def end_processes(netns: str, grace: float = STOP_GRACE_S) -> list[int]:
    """End the processes inside ``netns`` by pid (SIGTERM, SIGKILL after ``grace`` [s]); their pids.

    They need not be this process's children: each is watched through a pidfd,
    which becomes readable when it exits."""
    res = ip("netns", "pids", netns, check=False)
    pids = [int(p) for p in res.stdout.split() if p.isdigit() and int(p) != os.getpid()]
    fds: dict[int, int] = {}
    for pid in pids:
        try:
            fds[pid] = os.pidfd_open(pid)
            os.kill(pid, signal.SIGTERM)
        except ProcessLookupError:
            pass
    try:
        deadline = time.monotonic() + grace
        running = dict(fds)
        while running and (left := deadline - time.monotonic()) > 0:
            ready, _, _ = select.select(list(running.values()), [], [], left)
            running = {p: fd for p, fd in running.items() if fd not in ready}
        for fd in running.values():
            signal.pidfd_send_signal(fd, signal.SIGKILL)
    finally:
        for fd in fds.values():
            os.close(fd)
    return pids


def delete(netns: str) -> None:
    """End what runs in ``netns``, then delete it (its veth ends go with it, and their peers)."""
    end_processes(netns)
    res = ip("netns", "delete", netns, check=False)
    if res.returncode != 0 and netns in existing():
        raise NetnsError(f"ip netns delete {netns}: {res.stderr.strip()}")


def destroy(topo: Topology) -> list[str]:
    """Remove every namespace of ``topo`` that exists (robot hosts first); the names removed."""
    present = set(existing())
    removed = []
    errors = []
    for h in reversed(list(topo.hosts.values())):
        if h.netns in present:
            try:
                delete(h.netns)
                removed.append(h.netns)
            except NetnsError as e:
                errors.append(str(e))
    if errors:
        raise NetnsError("; ".join(errors))
    return removed


def clean(owner: int | None = None) -> list[str]:
    """Remove leftovers: namespaces ``efleet-<pid>-*`` whose pid is gone (and ``owner``'s, if given)."""
    removed = []
    for n in existing():
        m = NAME.match(n)
        assert m is not None
        pid = int(m["owner"])
        if pid == owner or not _pid_alive(pid):
            delete(n)
            removed.append(n)
    return removed


def _proc_sys(key: str) -> Path:
    if not SYSCTL_KEY.match(key):
        raise ValueError(f"sysctl: {key!r} is not a net.* key")
    return Path("/proc/sys") / key.replace(".", "/")


def set_sysctl(netns: str, key: str, value: str) -> None:
    """Set ``key`` to ``value`` inside ``netns`` only.

    Refuses keys outside ``net.``; undoes the change and raises if the calling
    namespace's value changed too (a key the kernel does not keep per
    namespace); raises if the namespace does not read back ``value``."""
    path = _proc_sys(key)
    before = path.read_text().strip() if path.exists() else None
    ip("netns", "exec", netns, "sysctl", "-q", "-w", f"{key}={value}")
    after = path.read_text().strip() if path.exists() else None
    if after != before:
        assert before is not None
        path.write_text(before)
        raise NetnsError(f"sysctl: {key} is not kept per namespace here; left the host's value at {before}")
    got = ip("netns", "exec", netns, "sysctl", "-n", key).stdout.split()
    if got != value.split():
        raise NetnsError(f"sysctl: {key} reads {' '.join(got)!r} in {netns} after setting {value!r}")


def create(
    owner: int | None = None, robot_hosts: Sequence[str] = ("a", "b"), sysctls: dict[str, str] | None = None
) -> Topology:
    """Make the topology for ``owner`` (default: this process); removes it again if a step fails.

    ``sysctls``: ``net.*`` kernel settings applied inside every namespace (the
    hosts' settings, never the caller's), e.g. ``{"net.ipv4.tcp_retries2": "5"}``.
    Any namespaces already named for ``owner`` are removed first."""
    topo = plan(os.getpid() if owner is None else owner, robot_hosts)
    for key in sysctls or {}:
        _proc_sys(key)  # refuse a bad key before anything is made
    clean(topo.owner)
    try:
        r = topo.router
        for h in topo.hosts.values():
            ip("netns", "add", h.netns)
            ip("-n", h.netns, "link", "set", "lo", "up")
            for key, value in (sysctls or {}).items():
                set_sysctl(h.netns, key, value)
        ip("-n", r.netns, "link", "add", BRIDGE, "type", "bridge", "stp_state", "0", "forward_delay", "0")
        ip("-n", r.netns, "link", "set", BRIDGE, "addrgenmode", "none")
        ip("-n", r.netns, "addr", "add", f"{r.address}/{PREFIX_LEN}", "dev", BRIDGE)
        for h in topo.hosts.values():
            if h.peer is None:
                continue
            # Both ends made in place: the pair never appears in the calling namespace.
            ip("-n", r.netns, "link", "add", h.peer, "type", "veth", "peer", "name", h.interface,
               "netns", h.netns)  # fmt: skip
            ip("-n", r.netns, "link", "set", h.peer, "addrgenmode", "none")
            ip("-n", h.netns, "link", "set", h.interface, "addrgenmode", "none")
            ip("-n", r.netns, "link", "set", h.peer, "master", BRIDGE)
            ip("-n", r.netns, "link", "set", h.peer, "up")
            ip("-n", h.netns, "addr", "add", f"{h.address}/{PREFIX_LEN}", "dev", h.interface)
            ip("-n", h.netns, "link", "set", h.interface, "up")
        ip("-n", r.netns, "link", "set", BRIDGE, "up")
    except BaseException:
        destroy(topo)
        raise
    return topo


def unavailable() -> str | None:
    """Why namespaces, a bridge and veth pairs cannot be made here, or None if they can.

    Tries for real: a throw-away namespace ``efleet-<pid>-probe`` with a bridge
    and a veth pair inside it, removed again."""
    if shutil.which("ip") is None:
        return "the ip command (iproute2) is missing"
    name = netns_name(os.getpid(), "probe")
    try:
        ip("netns", "add", name)
    except NetnsError as e:
        return f"cannot create a network namespace (needs root: CAP_SYS_ADMIN and CAP_NET_ADMIN): {e}"
    try:
        ip("-n", name, "link", "add", "p0", "type", "veth", "peer", "name", "p1")
        ip("-n", name, "link", "add", "pbr", "type", "bridge")
    except NetnsError as e:
        return f"no veth or bridge support: {e}"
    finally:
        delete(name)
    return None


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="deploy/netns.py", description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    sub.add_parser("check", help="say whether namespaces can be made here")
    owner_help = "pid the namespaces belong to (default: the calling shell's, %(default)s)"
    for name in ("up", "down", "cut", "restore"):
        p = sub.add_parser(name)
        p.add_argument("--owner", type=int, default=os.getppid(), help=owner_help)
        if name == "up":
            p.add_argument("--hosts", nargs="+", default=["a", "b"], help="robot hosts (default a b)")
            p.add_argument("--sysctl", action="append", default=[], metavar="KEY=VALUE",
                           help="a net.* kernel setting for every namespace (repeatable)")  # fmt: skip
        if name in ("cut", "restore"):
            p.add_argument("host", help="robot host whose link goes down/up")
    sub.add_parser("clean", help="remove namespaces whose owner process is gone")
    args = ap.parse_args(argv)
    try:
        if args.cmd == "check":
            reason = unavailable()
            print(reason or "ok: namespaces, veth pairs and bridges can be made here")
            return 0 if reason is None else 1
        if args.cmd == "up":
            pairs = [kv.partition("=") for kv in args.sysctl]
            if any(not sep or not k for k, sep, _ in pairs):
                raise ValueError(f"--sysctl: expected KEY=VALUE, got {args.sysctl}")
            topo = create(args.owner, args.hosts, {k: v for k, _, v in pairs})
            print(json.dumps(topo.describe(), indent=2))
            return 0
        if args.cmd == "down":
            names = [n for n in existing() if (m := NAME.match(n)) and int(m["owner"]) == args.owner]
            for n in names:
                delete(n)
            print(json.dumps({"removed": names}))
            return 0
        if args.cmd in ("cut", "restore"):
            hosts = [m["host"] for n in existing() if (m := NAME.match(n)) and int(m["owner"]) == args.owner]
            if args.host not in hosts or args.host == ROUTER:
                print(f"netns: error: no robot host {args.host!r} for owner {args.owner} "
                      f"(have {sorted(hosts)})", file=sys.stderr)  # fmt: skip
                return 2
            topo = plan(args.owner, [h for h in hosts if h != ROUTER])
            topo.set_link(args.host, up=args.cmd == "restore")
            return 0
        print(json.dumps({"removed": clean()}))
        return 0
    except (NetnsError, ValueError) as e:
        print(f"netns: error: {e}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
