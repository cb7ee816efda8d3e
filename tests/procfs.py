"""Process facts read from /proc, shared by the tests that start processes."""

from __future__ import annotations

import os
from pathlib import Path


def stat(pid: int) -> list[str] | None:
    """Fields of /proc/<pid>/stat after the command name: [state, ppid, pgrp, ...], or None if gone."""
    try:
        return (Path("/proc") / str(pid) / "stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return None


def _pids() -> list[int]:
    return [int(d.name) for d in Path("/proc").iterdir() if d.name.isdigit()]


def children(pid: int) -> list[int]:
    """Direct children of ``pid``."""
    return [c for c in _pids() if (s := stat(c)) is not None and int(s[1]) == pid]


def alive(pid: int) -> bool:
    """``pid`` exists and is not a zombie."""
    s = stat(pid)
    return s is not None and s[0] != "Z"


def group_alive(pgid: int) -> list[int]:
    """Pids of process group ``pgid`` that are not zombies."""
    return [p for p in _pids() if (s := stat(p)) is not None and int(s[2]) == pgid and s[0] != "Z"]


def tcp_sockets(pid: int) -> list[tuple[str, str, str, bool]]:
    """(state, local, remote, IPv6?) of the TCP sockets ``pid`` holds, in its network namespace,
    as /proc/<pid>/net/tcp{,6} writes them (hex: state ``0A`` is LISTEN, ``01`` ESTABLISHED;
    addresses ``IP:PORT``).  Empty, or partial, if the process exits meanwhile."""
    inodes = set()
    try:
        for fd in (Path("/proc") / str(pid) / "fd").iterdir():
            try:
                target = os.readlink(fd)
            except OSError:
                continue
            if target.startswith("socket:["):
                inodes.add(target[8:-1])
    except OSError:
        return []
    out = []
    for table in ("tcp", "tcp6"):
        try:
            rows = (Path("/proc") / str(pid) / "net" / table).read_text().splitlines()[1:]
        except OSError:
            return out
        for line in rows:
            cols = line.split()
            if cols[9] in inodes:
                out.append((cols[3], cols[1], cols[2], table == "tcp6"))
    return out
