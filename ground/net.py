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

import json
import socket
import string
from dataclasses import dataclass, field
from pathlib import Path
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
