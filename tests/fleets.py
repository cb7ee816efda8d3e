"""``fleet run`` started from a test: in the background, its stderr line by line, its processes
found by their command lines and ended by pid."""

from __future__ import annotations

import json
import os
import queue
import re
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import IO, Any

from procfs import argv, descendants

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "OMP_NUM_THREADS": "1", "RERUN_ANALYTICS": "0"}


def launch(
    scenario: Path, out: Path, hub: str, clock: str, extra: list[str] | None = None,
    stdout: int | IO[Any] = subprocess.DEVNULL,
) -> tuple[subprocess.Popen[str], queue.Queue[str]]:  # fmt: skip
    """``fleet run scenario --out out --listen hub --clock clock [extra]`` in the background:
    the launcher and a queue its stderr's lines come on."""
    cmd = [sys.executable, "-m", "fleet.cli", "run", str(scenario), "--out", str(out), "--listen", hub]
    launcher = subprocess.Popen(
        [*cmd, *(extra or []), "--clock", clock],
        cwd=ROOT, env=ENV, stdout=stdout, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    lines: queue.Queue[str] = queue.Queue()
    threading.Thread(target=lambda: [lines.put(x) for x in launcher.stderr], daemon=True).start()  # type: ignore[union-attr]
    return launcher, lines


def until(lines: queue.Queue[str], text: str | re.Pattern[str], log: list[str], timeout: float = 150) -> str:
    """Read ``lines`` into ``log`` until one has ``text`` (or matches it); that line.  Fails
    after ``timeout`` [s] with the last lines read."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            line = lines.get(timeout=1.0)
        except queue.Empty:
            continue
        log.append(line)
        if text.search(line) if isinstance(text, re.Pattern) else text in line:
            return line
    raise AssertionError(f"no {text!r} within {timeout} s:\n" + "".join(log[-30:]))


def stop(launcher: subprocess.Popen[str]) -> None:
    """Kill the launcher (by its pid) if it still runs."""
    if launcher.poll() is None:
        launcher.kill()
        launcher.wait(timeout=10)


def collected(lines: queue.Queue[str], log: list[str], out: Path) -> tuple[str, dict]:
    """The launcher's whole stderr (what ``log`` holds and the rest of ``lines``) and the summary."""
    while not lines.empty():
        log.append(lines.get())
    return "".join(log), json.loads((out / "summary.json").read_text())


def child_pid(launcher_pid: int, *words: str) -> int:
    """The process of the launcher's fleet whose command line has each of ``words``."""
    return next(c for c in descendants(launcher_pid) if set(words) <= set(argv(c)))


def agent_pid(launcher_pid: int, rid: str) -> int:
    """The agent process of robot ``rid`` in the launcher's fleet."""
    return child_pid(launcher_pid, "agent", rid)
