"""Zenoh session configuration for the fleet's processes (docs/design.md).

The embedded default is peer-to-peer on loopback: no router, multicast
scouting off (its defaults listen on every interface), explicit
``tcp/127.0.0.1`` endpoints.  One process (the first started, normally the
tracker) listens on a known port; every other process connects to it and
listens on an ephemeral loopback port of its own, and gossip scouting over
those links lets the peers find each other: a full mesh, n(n − 1)/2 links.

The star topology (``fleet run --topology star``) makes the hub's session a
Zenoh router and every other process a client of it: one link per process,
and no process but the hub listens (docs/design.md, "Topology").
"""

from __future__ import annotations

import itertools
import json
import os
import socket
import string
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

LOOPBACK = "127.0.0.1"


EPHEMERAL_RANGE = Path("/proc/sys/net/ipv4/ip_local_port_range")
"""Where Linux keeps the range it draws ephemeral ports from (each connection's own end, and
every ``bind`` to port 0)."""
FIXED_PORTS = (10000, 32767)
"""Ports :func:`free_port` picks from when the ephemeral range cannot be read: below Linux's
default range (32768–60999), above the well-known and most registered services."""
MIN_SPAN = 1000
"""Fewest ports a range outside the ephemeral one must hold to be used."""
_picks = itertools.count()
"""How many ports this process has picked: each pick starts its search further on."""
RUNTIME = "(app: (worker_threads: 1), acc: (handover: app), rx: (handover: app), net: (handover: app))"
"""Zenoh's runtime for every process of the fleet (its ``ZENOH_RUNTIME`` environment variable,
RON): one worker thread, to which the receive, accept and network pools hand over their work,
and the transmit pool's one worker kept apart.  Zenoh's own sizes run two receive threads and
one each for accepting and the network besides: a sample that arrives at an idle process wakes
one of them and then the Python thread of its callback.  Sized down, a 32-robot realtime fleet
missed fewer deadlines and answered its poses sooner in every interleaved pair measured
(docs/performance.md, "Zenoh's own threads").  Handing the transmit pool over too deadlocks a
router: its only worker, forwarding a sample, waits for a link's queue, which a publishing
thread holds while it waits for room that only the transmit task, queued on that same worker,
would make."""


def size_runtime() -> None:
    """Size Zenoh's runtime as :data:`RUNTIME` says, unless ``ZENOH_RUNTIME`` is already set
    (a user's own sizes, or ``()`` for Zenoh's).  Zenoh reads the variable once, when its first
    session opens: call this before."""
    os.environ.setdefault("ZENOH_RUNTIME", RUNTIME)


def _fixed_ports() -> tuple[int, int] | None:
    """The ports outside the kernel's ephemeral range that :func:`free_port` picks from: the
    larger of the gaps below it (from 10000) and above it, or None if neither holds
    :data:`MIN_SPAN` ports."""
    try:
        lo, hi = (int(v) for v in EPHEMERAL_RANGE.read_text().split())
    except (OSError, ValueError):
        return FIXED_PORTS
    below, above = (FIXED_PORTS[0], lo - 1), (hi + 1, 65535)
    best = max(below, above, key=lambda r: r[1] - r[0])
    return best if best[1] - best[0] + 1 >= MIN_SPAN else None


def free_port(host: str = LOOPBACK) -> int:
    """A TCP port that is free on ``host`` right now, for a process started next to listen on.

    The port lies below the kernel's ephemeral range. A port the kernel itself handed out and
    took back (``bind`` to port 0) would go back to that range, where the next connection any
    process opens, or the next listener on port 0 (every peer of a fleet has one), may take it
    before the process it was meant for has bound it. Below the range only another
    :func:`free_port` can, and the search starts from a place set by the process id and how
    many ports this process has picked, so two processes, or two picks in one process, start
    apart. Above the range if there is more room there; the kernel's own pick if neither side
    holds :data:`MIN_SPAN` ports. Raises OSError if no port of the range is free."""
    fixed = _fixed_ports()
    if fixed is None:  # the ephemeral range leaves no room: the kernel's pick, with its race
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            s.bind((host, 0))
            return int(s.getsockname()[1])
    lo, hi = fixed
    span = hi - lo + 1
    start = (os.getpid() * 7919 + next(_picks) * 104729) % span
    for i in range(span):  # bounded: each port of the range once
        port = lo + (start + i) % span
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            try:
                s.bind((host, port))
            except OSError:
                continue
            return port
    raise OSError(f"no free TCP port on {host} in {lo}..{hi}")


MODES = ("peer", "client", "router")
"""Zenoh session modes a process may take (``--mode``)."""

LEASE_RANGE = (0.5, 60.0)
"""Accepted Zenoh leases [s]: below 0.5 s a loaded 2-core machine drops live peers."""


def lease_seconds(text: str) -> float:
    """``--lease`` as a float in :data:`LEASE_RANGE` [s]; ValueError names the reason."""
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f"expected seconds, got {text!r}") from None
    lo, hi = LEASE_RANGE
    if not lo <= value <= hi:  # also rejects NaN
        raise ValueError(f"{text} s is outside [{lo:g}, {hi:g}] s")
    return value


def loopback(port: int) -> str:
    """The Zenoh endpoint ``tcp/127.0.0.1:<port>``."""
    return f"tcp/{LOOPBACK}:{port}"


@dataclass(frozen=True)
class NetConfig:
    """Where a process listens and what it connects to."""

    listen: list[str] = field(default_factory=lambda: [loopback(0)])
    connect: list[str] = field(default_factory=list)
    mode: str = "peer"
    """Zenoh session mode, one of :data:`MODES`: a client has one link, to what it connects
    to, and listens on nothing (its ``listen`` is not passed to Zenoh)."""
    lease: float = 10.0
    """Zenoh transport lease [s]: a peer silent this long (a hung process, a cut link)
    is dropped, and its liveliness tokens with it.  Keeping the links of the peer mesh
    alive costs CPU in proportion to 1/lease (docs/design.md, "Liveliness lease")."""

    def zenoh(self) -> Any:
        """A ``zenoh.Config`` for this process (imports zenoh lazily)."""
        import zenoh

        if self.mode not in MODES:
            raise ValueError(f"mode {self.mode!r} is not one of {', '.join(MODES)}")
        conf = zenoh.Config()
        conf.insert_json5("mode", json.dumps(self.mode))
        conf.insert_json5("listen/endpoints", json.dumps([] if self.mode == "client" else self.listen))
        conf.insert_json5("connect/endpoints", json.dumps(self.connect))
        conf.insert_json5("scouting/multicast/enabled", "false")
        conf.insert_json5("transport/link/tx/lease", str(round(self.lease * 1000)))
        return conf


class SecureConfigError(ValueError):
    """A secure configuration cannot be built; the message names the field or file."""


def render(template: str, values: dict[str, str]) -> str:
    """Fill the ``${NAME}`` placeholders of a JSON5 template; every one must be given.

    Values are escaped for a JSON string (the placeholders sit inside quotes)."""
    try:
        return string.Template(template).substitute({k: json.dumps(v)[1:-1] for k, v in values.items()})
    except KeyError as e:
        raise SecureConfigError(f"template: no value for ${{{e.args[0]}}} (--set {e.args[0]}=...)") from None
    except ValueError as e:
        raise SecureConfigError(f"template: {e}") from None


def load_config(path: str | Path, values: dict[str, str] | None = None) -> Any:
    """A ``zenoh.Config`` from a JSON5 file, its placeholders filled with ``values``."""
    import zenoh

    try:
        text = Path(path).read_text()
    except OSError as e:
        raise SecureConfigError(f"config: {e}") from None
    try:
        return zenoh.Config.from_json5(render(text, values or {}))
    except zenoh.ZError as e:
        raise SecureConfigError(f"config: {path}: {e}") from None
