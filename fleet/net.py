"""Zenoh session configuration for the fleet's processes (DESIGN §6).

The embedded default is peer-to-peer on loopback: no router, multicast
scouting off (its defaults listen on every interface), explicit
``tcp/127.0.0.1`` endpoints.  One process (the first started, normally the
tracker) listens on a known port; every other process connects to it and
listens on an ephemeral loopback port of its own, and gossip scouting over
those links lets the peers find each other.
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


def loopback(port: int) -> str:
    """The Zenoh endpoint ``tcp/127.0.0.1:<port>``."""
    return f"tcp/{LOOPBACK}:{port}"


@dataclass(frozen=True)
class NetConfig:
    """Where a process listens and what it connects to."""

    listen: list[str] = field(default_factory=lambda: [loopback(0)])
    connect: list[str] = field(default_factory=list)
    mode: str = "peer"

    def zenoh(self) -> Any:
        """A ``zenoh.Config`` for this process (imports zenoh lazily)."""
        import zenoh

        conf = zenoh.Config()
        conf.insert_json5("mode", json.dumps(self.mode))
        conf.insert_json5("listen/endpoints", json.dumps(self.listen))
        conf.insert_json5("connect/endpoints", json.dumps(self.connect))
        conf.insert_json5("scouting/multicast/enabled", "false")
        return conf

    def args(self) -> list[str]:
        """Command-line arguments that reproduce this configuration in a child process."""
        out: list[str] = []
        for e in self.listen:
            out += ["--listen", e]
        for e in self.connect:
            out += ["--connect", e]
        return out
