"""``python -m ros2_link`` as a process: it announces its node and domain, ends cleanly on SIGINT
or SIGTERM (exit 0, no traceback), and refuses bad input in one line with exit 2."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from transport.net import free_port, loopback

ROOT = Path(__file__).resolve().parents[2]
SCENARIO = ROOT / "scenarios" / "paper_two_robots.toml"


def _start(*args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "ros2_link", *args], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        stdin=subprocess.DEVNULL, text=True, env={**os.environ, "PYTHONPATH": str(ROOT)},
    )  # fmt: skip


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_the_face_announces_itself_and_ends_cleanly_on_a_signal(sig):
    proc = _start("--scenario", str(SCENARIO), "--listen", loopback(free_port()), "--ros-domain", "7")
    try:
        assert proc.stdout is not None
        ready = json.loads(proc.stdout.readline() or "{}")
        assert ready.get("event") == "ready" and ready["role"] == "ros2", ready
        assert ready["domain"] == 7 and ready["node"] == "fleet_lab" and len(ready["session"]) >= 16
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    assert "Traceback" not in err and "ROS 2 node /fleet_lab on domain 7" in err


@pytest.mark.parametrize(
    "args, line",
    [
        (["--ros-domain", "233"], "argument --ros-domain: must be in [0, 232], got 233"),
        (["--ros-domain", "-1"], "argument --ros-domain: must be in [0, 232], got -1"),
        (["--scenario", "/nonexistent.toml"], "ros2: error: file: /nonexistent.toml: no such file"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(args, line):
    argv = ["--scenario", str(SCENARIO), "--listen", loopback(free_port()), *args]
    proc = _start(*argv)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 2, err
    assert "Traceback" not in err and line in err.strip().splitlines()[-1], err
