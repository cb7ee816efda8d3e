"""``transport.net.free_port``: the port a launcher hands to a process it starts next."""

from __future__ import annotations

import socket

import pytest

from transport import net


def test_free_ports_come_from_beside_the_kernels_ephemeral_range_and_can_be_listened_on():
    fixed = net._fixed_ports()
    lo, hi = fixed if fixed is not None else (1, 65535)  # no room beside it: the kernel's pick
    ports = [net.free_port() for _ in range(20)]
    assert all(lo <= p <= hi for p in ports), (fixed, ports)
    assert len(set(ports)) == len(ports)  # none bound in between, yet every pick differs
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((net.LOOPBACK, ports[0]))
        s.listen()
    try:  # on this machine: none lies in the range the kernel draws from
        e_lo, e_hi = (int(v) for v in net.EPHEMERAL_RANGE.read_text().split())
    except (OSError, ValueError):
        return  # where it cannot be read, free_port uses FIXED_PORTS: checked above
    if fixed is not None:
        assert not [p for p in ports if e_lo <= p <= e_hi]


def _listen_on_three_in_a_row() -> tuple[int, list[socket.socket]]:
    """Listeners on ports b, b + 1 and b + 2, with b + 3 free just now."""
    for _ in range(50):  # bounded: a row of four free ports is common below the ephemeral range
        base, held = net.free_port(), []
        try:
            for port in range(base, base + 3):
                s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
                held.append(s)
                s.bind((net.LOOPBACK, port))
                s.listen()
            with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
                probe.bind((net.LOOPBACK, base + 3))
            return base, held
        except OSError:
            for s in held:
                s.close()
    raise AssertionError("no four free ports in a row")


def test_ports_someone_listens_on_are_skipped_and_a_full_range_raises(monkeypatch):
    base, held = _listen_on_three_in_a_row()
    try:
        monkeypatch.setattr(net, "_fixed_ports", lambda: (base, base + 3))
        assert [net.free_port() for _ in range(4)] == [base + 3] * 4
        monkeypatch.setattr(net, "_fixed_ports", lambda: (base, base + 2))
        with pytest.raises(OSError, match="no free TCP port"):
            net.free_port()
    finally:
        for s in held:
            s.close()


@pytest.mark.parametrize(
    ("ephemeral", "expected"),
    [("32768\t60999", (10000, 32767)), ("10500 60999", (61000, 65535)), ("1024 40000", (40001, 65535)),
     ("5000 64999", None), ("garbage", net.FIXED_PORTS)],
)  # fmt: skip
def test_the_ports_picked_from_are_the_larger_gap_beside_the_ephemeral_range(
    ephemeral, expected, tmp_path, monkeypatch
):
    f = tmp_path / "ip_local_port_range"
    f.write_text(ephemeral + "\n")
    monkeypatch.setattr(net, "EPHEMERAL_RANGE", f)
    assert net._fixed_ports() == expected


_THREADS = r"""
import argparse, json, os, re, sys, threading
import zenoh
from transport.bus import open_session
from transport.net import NetConfig, free_port, loopback

hub = loopback(free_port())
args = argparse.Namespace(listen=[hub], connect=[], lease=None, mode=None, zenoh_config=None)
session = open_session(args)  # as every process of the fleet opens its session
heard = threading.Event()
sub = session.declare_subscriber("probe/**", lambda sample: heard.set())
other = zenoh.open(NetConfig(connect=[hub]).zenoh())  # a second session: a link to receive on
for _ in range(200):  # bounded: until the first sample crosses the link
    other.put("probe/x", b"1")
    if heard.wait(0.05):
        break
names = sorted({re.sub(r"[-_]?\d+$", "", open(f"/proc/self/task/{t}/comm").read().strip())
                for t in os.listdir("/proc/self/task")})
print(json.dumps({"heard": heard.is_set(), "threads": names}))
other.close()
session.close()
"""


def _zenoh_threads(env: dict[str, str]) -> dict:
    """The thread names of a process that opened its session as the fleet's processes do and
    received a sample over a link."""
    import json
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    res = subprocess.run(
        [sys.executable, "-c", _THREADS], cwd=root, env={**env, "PYTHONPATH": str(root)},
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert res.returncode == 0, res.stderr[-2000:]
    out = json.loads(res.stdout.splitlines()[-1])
    assert out["heard"], out
    return out


def test_every_process_sizes_zenohs_runtime_down_and_a_users_sizes_win():
    """``transport.bus.open_session`` sizes Zenoh's runtime (``transport.net.RUNTIME``): one worker
    takes the receive, accept and network pools' work, and the transmit pool keeps a thread
    of its own (handing it over too deadlocks a router).  A ``ZENOH_RUNTIME`` the user set
    wins: ``()``, Zenoh's own sizes, brings back its receiving threads."""
    import os

    env = {k: v for k, v in os.environ.items() if k != "ZENOH_RUNTIME"}
    sized = _zenoh_threads(env)["threads"]
    assert "app" in sized and "tx" in sized, sized
    assert not {"rx", "acc", "net"} & set(sized), sized
    own = _zenoh_threads({**env, "ZENOH_RUNTIME": "()"})["threads"]
    assert "rx" in own and "acc" in own, own


def test_a_session_joining_from_outside_names_the_argument_that_is_wrong(tmp_path):
    """``join_session`` (``fleet goal``, a script): neither endpoints nor a file, a file that is
    not a configuration, and a client whose router is not there are each a ConfigError naming
    the argument as the caller calls it; nothing hangs."""
    from ground.scenario import ConfigError
    from transport.bus import join_session

    with pytest.raises(ConfigError) as none:
        join_session([], None)
    assert none.value.field == "--connect" and "hub's endpoint" in none.value.reason
    bad = tmp_path / "bad.json5"
    bad.write_text("{ not json5")
    with pytest.raises(ConfigError) as file:
        join_session([], str(bad), names=("connect", "zenoh_config"))
    assert file.value.field == "zenoh_config"
    nobody = net.loopback(net.free_port())  # a client does not wait for its router
    with pytest.raises(ConfigError) as closed:
        join_session([nobody], mode="client")
    assert closed.value.field == "--connect" and "cannot open a session" in closed.value.reason
