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


def ppid(pid: int) -> int | None:
    """The parent of ``pid``, None if it is gone."""
    s = stat(pid)
    return None if s is None else int(s[1])


def _pids() -> list[int]:
    return [int(d.name) for d in Path("/proc").iterdir() if d.name.isdigit()]


def children(pid: int) -> list[int]:
    """Direct children of ``pid``."""
    return [c for c in _pids() if (s := stat(c)) is not None and int(s[1]) == pid]


def descendants(pid: int) -> list[int]:
    """Children of ``pid``, their children and so on: ``fleet run``'s agents are the children of
    its fork server (fleet/running/forkserver.py)."""
    parent = {c: int(s[1]) for c in _pids() if (s := stat(c)) is not None}
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        kids = [c for c, pp in parent.items() if pp == p]
        out += kids
        todo += kids
    return out


def argv(pid: int) -> list[str]:
    """The words of ``pid``'s command line, [] if it is gone.  A spawned process's arguments are
    separated by NULs; a forked agent shows its command line as one string (setproctitle), its
    arguments separated by spaces: both split the same here."""
    try:
        raw = (Path("/proc") / str(pid) / "cmdline").read_bytes()
    except OSError:
        return []
    return raw.replace(b"\0", b" ").decode(errors="replace").split()


def role(words: list[str]) -> str | None:
    """The fleet role a command line runs: the module after ``-m`` (``tracker``,
    ``supervisor``, ``fleet.running.forkserver`` ...), ``agent ID`` for an agent; None if not ``-m``."""
    if "-m" not in words or words.index("-m") + 1 >= len(words):
        return None
    module = words[words.index("-m") + 1]
    if module == "agent" and "--robot" in words[:-1]:
        return f"agent {words[words.index('--robot') + 1]}"
    return module


def fleet_processes(launcher: int) -> dict[str, int]:
    """Pid of every process of the fleet that ``launcher`` (``fleet run``) started, by
    :func:`role`; its fork server is not one of them."""
    out = {}
    for p in descendants(launcher):
        r = role(argv(p))
        if r is not None and r != "fleet.running.forkserver":
            out[r] = p
    return out


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
