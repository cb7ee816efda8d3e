"""Processes on the namespace hosts of ``deploy/netns.py``, for the several-hosts test.

:data:`netns` is ``deploy/netns.py`` loaded as a module (it lives with the
deployment tools, not in a package).  :class:`HostProc` is a fleet process
started inside one namespace with ``ip netns exec`` (which execs in place, so
the pid is the Python process's): its JSON stdout lines are kept as events to
wait on with a deadline, its stderr lines are kept with their arrival time
and written to a log file (each line prefixed by that time [s,
``time.monotonic``]; the stdout events go to a ``.events.jsonl`` file when
the process has been stopped), and it is ended by its pid.
"""

from __future__ import annotations

import importlib.util
import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any

ROOT = Path(__file__).resolve().parent.parent


def _load_netns() -> Any:
    spec = importlib.util.spec_from_file_location("deploy_netns", ROOT / "deploy" / "netns.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses look their module up by name
    spec.loader.exec_module(mod)
    return mod


netns = _load_netns()

Event = dict[str, Any]
ENV = {**os.environ, "OMP_NUM_THREADS": "1", "RERUN_ANALYTICS": "0", "PYTHONUNBUFFERED": "1"}


class Local:
    """The "topology" of :class:`HostProc` for processes on this host: no namespace."""

    def exec_args(self, host: str, argv: list[str]) -> list[str]:
        return list(argv)


LOCAL = Local()


class HostProc:
    """A Python module run as a process inside a namespace host of ``topo`` (:data:`LOCAL`: here).

    Its stdout JSON lines are kept as events to wait on; with a ``log_dir`` its stderr and events
    are also written there."""

    def __init__(
        self, name: str, topo: Any, host: str, args: list[str], log_dir: Path | None, stdin: bool = False
    ):
        self.name = name
        self.host = host
        self.log_path = None if log_dir is None else log_dir / f"{name.replace(' ', '-')}.log"
        self._log = None if self.log_path is None else self.log_path.open("w")
        self.popen = subprocess.Popen(
            topo.exec_args(host, [sys.executable, *args]), cwd=ROOT, env=ENV, text=True,
            stdin=subprocess.PIPE if stdin else subprocess.DEVNULL,
            stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        )  # fmt: skip
        self.events: list[Event] = []
        self.stderr: list[tuple[float, str]] = []
        """(arrival time [s, time.monotonic], line) of every stderr line."""
        self.cond = threading.Condition()
        self._pumps = [
            threading.Thread(target=self._pump_out, args=(self.popen.stdout,), daemon=True),
            threading.Thread(target=self._pump_err, args=(self.popen.stderr,), daemon=True),
        ]
        for t in self._pumps:
            t.start()

    @property
    def pid(self) -> int:
        return self.popen.pid

    def _pump_out(self, stream: IO[str]) -> None:
        for line in stream:
            try:
                ev = json.loads(line)
                if not isinstance(ev, dict):
                    raise ValueError
            except ValueError:
                ev = {"event": "text", "text": line}
            ev["_t"] = time.monotonic()
            with self.cond:
                self.events.append(ev)
                self.cond.notify_all()
        with self.cond:
            self.events.append({"event": "eof", "_t": time.monotonic()})
            self.cond.notify_all()

    def _pump_err(self, stream: IO[str]) -> None:
        for line in stream:
            with self.cond:
                self.stderr.append((time.monotonic(), line.rstrip("\n")))
                if self._log is not None and not self._log.closed:
                    self._log.write(f"{self.stderr[-1][0]:12.3f} {line}")
                    self._log.flush()
                self.cond.notify_all()

    def wait_for(self, pred: Callable[[Event], bool], timeout: float) -> Event | None:
        """The first stdout event (so far or within ``timeout`` [s]) satisfying ``pred``, else None."""
        deadline = time.monotonic() + timeout
        with self.cond:
            while True:
                for ev in self.events:
                    if pred(ev):
                        return ev
                left = deadline - time.monotonic()
                if left <= 0 or (self.events and self.events[-1]["event"] == "eof"):
                    return None
                self.cond.wait(left)

    def wait_stderr(self, pred: Callable[[str], bool], timeout: float, after: float = 0.0) -> float | None:
        """Arrival time [s] of the first stderr line since ``after`` that satisfies ``pred``, waiting
        at most ``timeout`` [s]; None if none came (or the process ended without one)."""
        deadline = time.monotonic() + timeout
        with self.cond:
            while True:
                for t, line in self.stderr:
                    if t >= after and pred(line):
                        return t
                left = deadline - time.monotonic()
                if left <= 0 or (self.popen.poll() is not None and self._drained()):
                    return None
                self.cond.wait(min(left, 0.5))

    def _drained(self) -> bool:
        return not any(t.is_alive() for t in self._pumps)

    def started(self, timeout: float = 30.0) -> Event:
        """The readiness or open-failure line (probes); fails the test if neither comes in time."""
        ev = self.wait_for(lambda e: e["event"] in ("ready", "open_failed"), timeout)
        where = f"{self.name} on host {self.host}"
        assert ev is not None, f"{where} did not start within {timeout} s: {self.tail()}"
        return ev

    def ready(self, timeout: float = 30.0) -> Event:
        """The readiness line; fails the test (with the stderr tail) if it does not come in time."""
        ev = self.started(timeout)
        assert ev["event"] == "ready", f"{self.name} on host {self.host} not ready ({ev}): {self.tail()}"
        return ev

    def samples(self, key: str | None = None) -> list[Event]:
        """The samples a probe printed so far, on ``key`` or on any key."""
        with self.cond:
            return [e for e in self.events if e["event"] == "sample" and (key is None or e["key"] == key)]

    def tokens(self) -> list[Event]:
        """The liveliness tokens a probe printed so far."""
        with self.cond:
            return [e for e in self.events if e["event"] == "token"]

    def send(self, **req: str) -> None:
        """One JSON request line on stdin (probes)."""
        assert self.popen.stdin is not None
        self.popen.stdin.write(json.dumps(req) + "\n")
        self.popen.stdin.flush()

    def lines(self) -> list[str]:
        with self.cond:
            return [line for _, line in self.stderr]

    def tail(self, n: int = 25) -> str:
        return "\n".join(self.lines()[-n:])

    def wait(self, timeout: float) -> int | None:
        """Exit code within ``timeout`` [s], or None if still running."""
        try:
            return self.popen.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            return None

    def stop(self, grace: float = 5.0) -> int:
        """End the process by its pid: EOF on stdin (probes), SIGTERM, SIGKILL after ``grace`` [s]."""
        p = self.popen
        if p.poll() is None and p.stdin is not None:
            try:
                p.stdin.close()
                p.wait(timeout=grace)
            except (subprocess.TimeoutExpired, BrokenPipeError, OSError):
                pass
        if p.poll() is None:
            p.send_signal(signal.SIGTERM)
            try:
                p.wait(timeout=grace)
            except subprocess.TimeoutExpired:
                p.kill()
        code = p.wait(timeout=grace)
        for t in self._pumps:
            t.join(timeout=grace)
        if self._log is not None and self.log_path is not None:
            with self.cond:
                self._log.close()
                with self.log_path.with_suffix(".events.jsonl").open("w") as f:
                    for ev in self.events:
                        f.write(json.dumps(ev) + "\n")
        return code
