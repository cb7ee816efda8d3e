"""The agents' fork server (fleet/running/forkserver.py) seen from the launcher's end
(fleet.running.launch.ForkServer):
what a forked child is given, what its exit is reported as, and that nothing outlives the server.

The children run a probe module written to a temporary directory: it records each import of
itself in a file, so a test can tell a fork (imported once, in the server) from a spawn."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
from pathlib import Path

import pytest
from procfs import alive, argv, ppid

from fleet.running.launch import ForkServer, LaunchError, _wait_ready

PROBE = """
import json, os, sys, threading

with open(os.environ["PROBE_LOG"], "a") as f:
    f.write(f"imported in {os.getpid()}\\n")
if os.environ.get("PROBE_THREAD"):
    threading.Thread(target=threading.Event().wait, daemon=True).start()


def main(argv):
    fds = sorted(int(fd) for fd in os.listdir("/proc/self/fd"))  # one of them is listdir's own
    print(json.dumps({"event": "ready", "role": "probe", "pid": os.getpid(), "ppid": os.getppid(),
                      "stdin": sys.stdin.read(), "argv": argv, "sys_argv": sys.argv, "fds": fds}),
          flush=True)
    mode = argv[0]
    if mode == "exit":
        return int(argv[1])
    if mode == "raise":
        raise RuntimeError("the probe failed on purpose")
    if mode == "usage":
        raise SystemExit(2)
    threading.Event().wait()  # "hang": until a signal ends it
"""


@pytest.fixture
def probe_env(tmp_path):
    (tmp_path / "fork_probe.py").write_text(PROBE)
    log = tmp_path / "imports.txt"
    log.touch()
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), *sys.path]), "PROBE_LOG": str(log)}
    return env, log


@pytest.fixture
def server(probe_env, tmp_path):
    env, _ = probe_env
    with open(tmp_path / "stderr.txt", "w") as err:
        srv = ForkServer(["fork_probe"], env, err)
    try:
        assert _wait_ready([srv.proc], 60.0) == [], (tmp_path / "stderr.txt").read_text()
        yield srv
    finally:
        srv.close()


def _ready(proc) -> dict:
    assert _wait_ready([proc], 30.0) == [], proc.role
    return proc.ready


def test_children_are_forked_with_the_imports_done_and_the_stdio_of_a_spawned_process(server, probe_env):
    _, log = probe_env
    procs = [server.start(f"probe {i}", "fork_probe", ["exit", str(i)]) for i in range(3)]
    readies = [_ready(p) for p in procs]
    # Imported once, in the server: the children are its forks, not new interpreters.
    assert log.read_text().splitlines() == [f"imported in {server.popen.pid}"]
    for i, (p, r) in enumerate(zip(procs, readies, strict=True)):
        assert r["pid"] == p.pid and r["ppid"] == server.popen.pid
        assert r["argv"] == ["exit", str(i)] and r["sys_argv"] == ["fork_probe", "exit", str(i)]
        assert r["stdin"] == ""  # /dev/null, not the server's socket or pipe
        # Nothing of the server's is left open (its socket, its wake-up pipe, its epoll): stdio,
        # and the descriptor listdir used.
        assert r["fds"][:3] == [0, 1, 2] and len(r["fds"]) == 4, r["fds"]
        assert p.popen.wait(timeout=30) == i
    # Each child showed its title as its command line while it ran (checked on a live one).
    hang = server.start("probe hang", "fork_probe", ["hang"], "python -m probe --robot r9")
    _ready(hang)
    assert argv(hang.pid) == ["python", "-m", "probe", "--robot", "r9"]
    comm = [Path(f"/proc/{pid}/comm").read_text() for pid in (hang.pid, server.popen.pid)]
    assert comm[0] == comm[1]  # the thread name stays the interpreter's, as in a spawned process
    hang.popen.send_signal(signal.SIGTERM)
    assert hang.popen.wait(timeout=30) == -signal.SIGTERM


def test_exit_codes_are_reported_as_popen_reports_them(server, tmp_path):
    crash = server.start("probe crash", "fork_probe", ["raise"])
    usage = server.start("probe usage", "fork_probe", ["usage"])
    hang = server.start("probe hang", "fork_probe", ["hang"])
    for p in (crash, usage, hang):
        _ready(p)
    assert crash.popen.wait(timeout=30) == 1
    assert usage.popen.wait(timeout=30) == 2
    assert hang.popen.poll() is None
    with pytest.raises(subprocess.TimeoutExpired):
        hang.popen.wait(timeout=0.2)
    hang.popen.kill()
    assert hang.popen.wait(timeout=30) == -signal.SIGKILL
    assert "RuntimeError: the probe failed on purpose" in (tmp_path / "stderr.txt").read_text()


def test_ctrl_c_ends_the_children_as_it_ends_an_interpreter_and_the_server_serves_on(server):
    """Ctrl-C reaches the whole process group: a child ends by SIGINT (as ``python`` does on an
    unhandled KeyboardInterrupt); the server ignores it and ends only when the launcher stops."""
    hang = server.start("probe hang", "fork_probe", ["hang"])
    _ready(hang)
    os.kill(server.popen.pid, signal.SIGINT)
    os.kill(hang.pid, signal.SIGINT)
    assert hang.popen.wait(timeout=30) == -signal.SIGINT
    assert server.popen.poll() is None
    p = server.start("probe", "fork_probe", ["exit", "4"])
    assert p.popen.wait(timeout=30) == 4


def test_a_bad_request_is_refused_and_the_server_serves_on(server):
    with pytest.raises(LaunchError, match="was not preloaded"):
        server.start("other", "agent.node", ["--robot", "r1"])
    # A request that is not JSON, with no descriptor: refused with one line, nothing forked.
    socket.send_fds(server._sock, [b"\xff not json"], [])
    assert "error" in server._replies.get(timeout=30)
    p = server.start("probe", "fork_probe", ["exit", "0"])
    assert _ready(p)["ppid"] == server.popen.pid and p.popen.wait(timeout=30) == 0


def test_closing_the_server_ends_every_child_still_running_and_reports_it(server):
    procs = [server.start(f"probe {i}", "fork_probe", ["hang"]) for i in range(2)]
    pids = [_ready(p)["pid"] for p in procs]
    assert all(alive(pid) and ppid(pid) == server.popen.pid for pid in pids)
    server.close()
    assert server.popen.returncode == 0
    assert not [pid for pid in pids if alive(pid)]
    assert [p.popen.wait(timeout=5) for p in procs] == [-signal.SIGTERM] * 2


def test_a_server_with_a_thread_refuses_to_fork(probe_env, tmp_path):
    """A thread at fork time (a BLAS pool, a runtime) would be copied without its state: the
    server checks there is none before it serves, and exits 1 saying why."""
    env, _ = probe_env
    with open(tmp_path / "stderr.txt", "w") as err:
        srv = ForkServer(["fork_probe"], {**env, "PROBE_THREAD": "1"}, err)
    try:
        assert _wait_ready([srv.proc], 60.0) == ["forkserver"]
        assert srv.popen.wait(timeout=30) == 1
        assert "fork is unsafe" in (tmp_path / "stderr.txt").read_text()
        with pytest.raises(LaunchError):
            srv.start("probe", "fork_probe", ["exit", "0"])
    finally:
        srv.close()


def test_a_bad_socket_fd_is_one_line_and_exit_2():
    res = subprocess.run(
        [sys.executable, "-m", "fleet.running.forkserver", "--socket-fd", "999", "--preload", "json"],
        capture_output=True, text=True, timeout=60, stdin=subprocess.DEVNULL,
    )  # fmt: skip
    assert res.returncode == 2 and res.stderr.startswith("forkserver: error: --socket-fd:"), res.stderr
    assert len(res.stderr.strip().splitlines()) == 1  # one line, no traceback
