"""A served fleet (``fleet run --serve``), seen from outside: it stays up once every robot is home
and past the scenario's duration, takes formation after formation from a script that joins it,
and ends, with its summary, on ``fleet stop`` or on SIGTERM (Ctrl-C) to the command, leaving no
process behind."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from fleet import Fleet
from ground.scenario import load_scenario
from transport.net import free_port, loopback

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[2]
TWO = ROOT / "scenarios" / "paper_two_robots.toml"
WAIT = 120.0
"""Bound of every wait on a process [s]."""
FORMATIONS = [
    {"r1": (0.4, 0.4), "r2": (-0.4, -0.4)},
    {"r1": (-0.4, 0.4), "r2": (0.4, -0.4)},
    {"r1": (0.0, -0.5), "r2": (0.0, 0.5)},
]
"""Three formations, each given once the one before is reached [m, world frame]."""


@contextlib.contextmanager
def _serve(tmp_path: Path) -> Iterator[tuple[subprocess.Popen[str], str]]:
    """``fleet run TWO --serve`` on a free loopback hub, its log in ``tmp_path/fleet.log``;
    killed on the way out if it is still running."""
    hub = loopback(free_port())
    env = {**os.environ, "RERUN_ANALYTICS": "0", "PYTHONUNBUFFERED": "1"}
    argv = [sys.executable, "-m", "fleet.cli", "run", str(TWO), "--serve", "--listen", hub, "--seed", "3",
            "--out", str(tmp_path / "run")]  # fmt: skip
    with (tmp_path / "fleet.log").open("w") as log:
        proc = subprocess.Popen(
            argv, stdout=subprocess.PIPE, stderr=log, stdin=subprocess.DEVNULL, text=True, env=env
        )
    try:
        yield proc, hub
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=30)


def _ended(proc: subprocess.Popen[str]) -> tuple[int, str]:
    try:
        out, _ = proc.communicate(timeout=WAIT)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, _ = proc.communicate(timeout=30)
        raise AssertionError(f"fleet run did not end: {out[-2000:]}") from None
    return proc.returncode, out


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


def test_a_served_fleet_takes_formation_after_formation_past_its_duration_until_fleet_stop(tmp_path):
    duration_steps = round(load_scenario(TWO).duration / load_scenario(TWO).controller.Ts)
    with _serve(tmp_path) as (proc, hub):
        with Fleet.connect(TWO, connect=hub) as fleet:
            assert fleet.wait_arrived(timeout=60), "the scenario's own goals"
            for formation in FORMATIONS:
                fleet.goto(formation)
                assert fleet.wait_arrived(timeout=60), formation
            while fleet.step <= duration_steps:  # bounded: the clock runs on, and wait is in its time
                fleet.wait(5.0)
            assert proc.poll() is None  # past its duration, every robot home: still served
            last = fleet.goals()
        stop = subprocess.run(
            [sys.executable, "-m", "fleet.cli", "stop", "--connect", hub],
            capture_output=True, text=True, timeout=WAIT,
        )  # fmt: skip
        assert stop.returncode == 0 and "stopped at step" in stop.stdout, stop.stderr
        code, out = _ended(proc)
    log = (tmp_path / "fleet.log").read_text()
    assert code == 0, out[-2000:] + log[-3000:]
    assert "a stop was asked (fleet stop); ending the run" in log
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["steps"] > duration_steps and summary["collisions"] == 0 and summary["all_goals_reached"]
    assert {r: tuple(v["goal"]) for r, v in summary["robots"].items()} == last
    assert len(summary["processes"]) == 4 and not [p for p in summary["processes"].values() if _alive(p)]


def test_sigterm_to_a_served_fleet_ends_its_run_with_its_summary(tmp_path):
    """As Ctrl-C does in a terminal (``fleet run`` takes SIGTERM for it; a pytest worker's
    children ignore SIGINT): the tracker ends the run at its next step, the supervisor writes the
    summary, every process exits 0."""
    with _serve(tmp_path) as (proc, hub):
        with Fleet.connect(TWO, connect=hub) as fleet:
            assert fleet.wait_arrived(timeout=60)
            k = fleet.step
        proc.send_signal(signal.SIGTERM)
        code, out = _ended(proc)
    log = (tmp_path / "fleet.log").read_text()
    assert code == 0, out[-2000:] + log[-3000:]
    assert "stopping the served fleet" in log and "SIGTERM; ending the run" in log
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["steps"] >= k and summary["all_goals_reached"] and summary["collisions"] == 0
    assert set(summary["exit_codes"].values()) == {0}, summary["exit_codes"]
    assert len(summary["processes"]) == 4 and not [p for p in summary["processes"].values() if _alive(p)]


@pytest.mark.realtime
def test_fleet_stop_refuses_bad_input_in_one_line_and_says_when_no_fleet_stops(tmp_path):
    """Neither or both of ``--connect`` and ``--zenoh-config``: exit 2, one line, nothing sent.
    A fleet that is not served does not listen for stop requests (it ends at its duration):
    ``fleet stop`` gets no stop tick, says so and exits 1, and the fleet runs on."""
    from fleet.running.launch import start_fleet

    env = {**os.environ, "RERUN_ANALYTICS": "0"}

    def fleet(*argv: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [sys.executable, "-m", "fleet.cli", *argv], capture_output=True, text=True, env=env, timeout=WAIT
        )

    neither = fleet("stop")
    assert neither.returncode == 2 and neither.stderr.count("\n") == 1 and "neither given" in neither.stderr
    both = fleet("stop", "--connect", loopback(free_port()), "--zenoh-config", "x.json5")
    assert both.returncode == 2 and both.stderr.count("\n") == 1 and "both given" in both.stderr
    hub = loopback(free_port())
    with (tmp_path / "fleet.log").open("w") as log:
        launched = start_fleet(
            str(TWO), ["r1", "r2"], tmp_path, seed=1, clock="realtime", hub=hub, stderr=log
        )
        try:
            refused = fleet("stop", "--connect", hub, "--timeout", "3")
            assert refused.returncode == 1 and "did not stop within 3 s" in refused.stderr, refused.stderr
            assert launched.tracker.popen.poll() is None
        finally:
            launched.stop()
