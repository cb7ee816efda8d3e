"""``python -m fleet.running.forkserver``: start processes by fork from one that imported their code once.

Every agent imports the same modules (numpy, scipy, ProxSuite, Zenoh, the tube design's code):
about 0.45 s of CPU each, so 7 s of the 8.5 s that 16 agents take to get ready on 2 cores
(docs/performance.md, "Start-up").  ``fleet run`` therefore starts this process next to the
tracker; it imports the ``--preload`` modules once, freezes its heap (``gc.freeze``, so that the
children's collections do not copy the shared pages), and forks one child per request.  A child
starts with the imports done and runs ``module.main(argv)``.

Fork is safe here because nothing has started a thread or opened a Zenoh session yet: the process
checks that it has one thread before it serves (OpenBLAS and libgomp start theirs on import unless
``OMP_NUM_THREADS=1``, which it sets).  A child opens its own session after the fork, as a freshly
spawned process would.

The protocol, on the Unix socket ``--socket-fd`` (``SOCK_SEQPACKET``, one JSON message a packet):

* request: ``{"module": "agent.node", "argv": [...], "title": "python -m agent ..."}`` with one
  file descriptor attached, the child's stdout (the child's stderr is this process's; its stdin
  is ``/dev/null``).  ``title`` is the command line the child shows in ``ps`` and
  ``/proc/PID/cmdline`` (one string, arguments separated by spaces): the one a spawned process
  would have, so that tools find an agent by its command line either way;
* reply: ``{"pid": N}`` once forked, in request order; a request it cannot serve gets
  ``{"error": "<one line>"}``;
* later, for every child: ``{"exit": N, "code": C}`` once it has ended and been reaped (C as
  :attr:`subprocess.Popen.returncode`: negative for a signal).

When the launcher stops writing (it is done, or gone) the children still running get SIGTERM,
then SIGKILL after :data:`GRACE`; their exits are reported as before, and the process exits.
``fleet.running.launch.ForkServer`` is the other end.
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import importlib
import json
import os
import selectors
import signal
import socket
import sys
import time
import traceback
from pathlib import Path
from typing import Any

import setproctitle

GRACE = 5.0
"""How long children get after SIGTERM when the socket closes [s], before SIGKILL."""
MAX_REQUEST = 1 << 16
"""Largest request [bytes]: a command line of a few hundred bytes, with room to spare."""


def _threads() -> int:
    return len(os.listdir("/proc/self/task"))


def _child(module: str, argv: list[str], title: str, out_fd: int, close: list[int]) -> None:
    """Become the process ``module`` would be: stdout on ``out_fd``, stdin empty, default
    signal handling, ``title`` as its command line; run ``module.main(argv)`` and exit with its
    code.  Never returns."""
    code = 1
    try:
        for fd in close:
            os.close(fd)
        if title:
            comm = Path("/proc/self/comm")
            name = comm.read_text().strip()
            setproctitle.setproctitle(title)
            with contextlib.suppress(OSError):  # the threads' name stays the interpreter's, as spawned
                comm.write_text(name)
        signal.set_wakeup_fd(-1)
        signal.signal(signal.SIGCHLD, signal.SIG_DFL)
        signal.signal(signal.SIGINT, signal.default_int_handler)  # Ctrl-C: as in any Python process
        os.dup2(out_fd, 1)
        os.close(out_fd)
        null = os.open(os.devnull, os.O_RDONLY)
        os.dup2(null, 0)
        os.close(null)
        sys.argv = [module, *argv]
        result = importlib.import_module(module).main(argv)
        code = int(result or 0)
    except SystemExit as e:  # argparse's usage errors (exit 2) and the like
        code = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
    except KeyboardInterrupt:  # Ctrl-C: end by SIGINT, as an interpreter does
        sys.stdout.flush()
        sys.stderr.flush()
        signal.signal(signal.SIGINT, signal.SIG_DFL)
        os.kill(os.getpid(), signal.SIGINT)
    except BaseException:  # the crash, reported as a spawned process would
        traceback.print_exc()
    finally:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)


def _reap(sock: socket.socket, children: set[int]) -> None:
    """Report every child that has ended: ``{"exit": pid, "code": returncode}``."""
    while children:
        try:
            pid, status = os.waitpid(-1, os.WNOHANG)
        except ChildProcessError:
            children.clear()
            return
        if pid == 0:
            return
        children.discard(pid)
        _report(sock, pid, os.waitstatus_to_exitcode(status))


def _report(sock: socket.socket, pid: int, code: int) -> None:
    try:
        sock.send(json.dumps({"exit": pid, "code": code}).encode())
    except OSError:
        pass  # the launcher is gone; the rest is cleanup


def _serve(sock: socket.socket, preload: list[str]) -> int:
    wake_r, wake_w = os.pipe()
    os.set_blocking(wake_r, False)
    os.set_blocking(wake_w, False)
    signal.set_wakeup_fd(wake_w)
    signal.signal(signal.SIGCHLD, lambda *_: None)  # a handler, so that SIGCHLD reaches the wakeup fd
    children: set[int] = set()
    sel = selectors.DefaultSelector()
    sel.register(sock, selectors.EVENT_READ)
    sel.register(wake_r, selectors.EVENT_READ)
    open_ = True
    while open_:
        for key, _ in sel.select():
            if key.fileobj == wake_r:
                _drain(wake_r)
                _reap(sock, children)
                continue
            try:
                data, fds, _flags, _addr = socket.recv_fds(sock, MAX_REQUEST, 4)
            except OSError:
                data, fds = b"", []
            if not data:
                open_ = False
                break
            reply = _fork(data, fds, preload, [sock.fileno(), wake_r, wake_w, sel.fileno()])
            if "pid" in reply:
                children.add(reply["pid"])
            try:
                sock.send(json.dumps(reply).encode())
            except OSError:
                open_ = False
        _reap(sock, children)
    sel.unregister(sock)  # at its end: from here on only SIGCHLD wakes the selector
    _end(sock, children, sel, wake_r)
    return 0


def _drain(wake_r: int) -> None:
    """Empty the signal wake-up pipe (non-blocking)."""
    with contextlib.suppress(BlockingIOError):
        while os.read(wake_r, 512):
            pass


def _fork(data: bytes, fds: list[int], preload: list[str], close: list[int]) -> dict[str, Any]:
    try:
        req = json.loads(data)
        module, argv, title = req["module"], req["argv"], req.get("title", "")
        if module not in preload:
            raise ValueError(f"module {module!r} was not preloaded ({', '.join(preload)})")
        if not (isinstance(argv, list) and all(isinstance(a, str) for a in argv) and isinstance(title, str)):
            raise ValueError("argv must be a list of strings, title a string")
        if len(fds) != 1:
            raise ValueError(f"expected 1 file descriptor (stdout), got {len(fds)}")
    except (ValueError, KeyError, TypeError) as e:
        for fd in fds:
            os.close(fd)
        return {"error": str(e).splitlines()[0] if str(e) else type(e).__name__}
    sys.stdout.flush()
    sys.stderr.flush()
    pid = os.fork()
    if pid == 0:
        _child(module, argv, title, fds[0], close)
    os.close(fds[0])
    return {"pid": pid}


def _end(sock: socket.socket, children: set[int], sel: selectors.BaseSelector, wake_r: int) -> None:
    """SIGTERM the children still running, SIGKILL them after :data:`GRACE`; reap and report
    them all (the launcher closed its writing end only, and reads on).  ``sel`` waits on the
    signal wake-up pipe ``wake_r``: each SIGCHLD wakes it."""
    for pid in children:
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGTERM)
    deadline = time.monotonic() + GRACE
    _reap(sock, children)
    while children and (left := deadline - time.monotonic()) > 0:
        sel.select(left)
        _drain(wake_r)
        _reap(sock, children)
    for pid in children:
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGKILL)
        try:
            _, status = os.waitpid(pid, 0)  # SIGKILL cannot be refused: this returns
        except ChildProcessError:
            continue
        _report(sock, pid, os.waitstatus_to_exitcode(status))
    children.clear()


def main(argv: list[str] | None = None) -> int:
    """``python -m fleet.running.forkserver``: import the ``--preload`` modules, check that this process
    has one thread, announce readiness and serve the launcher on ``--socket-fd`` until it stops
    writing (see the module docstring); returns the exit code (0, 1 with more than one thread, 2 a bad
    socket)."""
    ap = argparse.ArgumentParser(
        prog="python -m fleet.running.forkserver", description=__doc__.splitlines()[0]
    )
    ap.add_argument("--socket-fd", type=int, required=True, help="the launcher's Unix socket")
    ap.add_argument("--preload", action="append", required=True, help="module to import once (repeatable)")
    args = ap.parse_args(argv)
    os.environ.setdefault("OMP_NUM_THREADS", "1")  # OpenBLAS and libgomp: no threads at import
    try:
        sock = socket.socket(fileno=args.socket_fd)
    except OSError as e:
        print(f"forkserver: error: --socket-fd: {e}", file=sys.stderr)
        return 2
    for module in args.preload:
        importlib.import_module(module)
    if _threads() != 1:
        print(f"forkserver: error: {_threads()} threads after the imports; fork is unsafe", file=sys.stderr)
        return 1
    gc.collect()
    gc.freeze()
    # Ctrl-C reaches the whole process group: the agents take it, and the launcher then stops
    # writing, which ends this process once it has reported their exits.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    print(json.dumps({"event": "ready", "role": "forkserver", "pid": os.getpid()}), flush=True)
    return _serve(sock, args.preload)


if __name__ == "__main__":
    sys.exit(main())
