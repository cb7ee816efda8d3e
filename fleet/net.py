"""Zenoh session configuration for the fleet's processes (DESIGN §6).

The embedded default is peer-to-peer on loopback: no router, multicast
scouting off (its defaults listen on every interface), explicit
``tcp/127.0.0.1`` endpoints.  One process (the first started, normally the
tracker) listens on a known port; every other process connects to it and
listens on an ephemeral loopback port of its own, and gossip scouting over
those links lets the peers find each other: a full mesh, n(n − 1)/2 links.

The star topology (``fleet run --topology star``) makes the hub's session a
Zenoh router and every other process a client of it: one link per process,
and no process but the hub listens (docs/design.md §8, "Topology").
"""

from __future__ import annotations

import json
import socket
from dataclasses import dataclass, field
from typing import Any

LOOPBACK = "127.0.0.1"


def free_port(host: str = LOOPBACK) -> int:
    """A TCP port that is free on ``host`` right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


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
    alive costs CPU in proportion to 1/lease (docs/design.md §8)."""

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
