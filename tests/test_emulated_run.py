"""A whole `fleet run` whose robots move through epuck_link and the e-puck firmware emulator.

No in-process shortcut: every robot is an emulator process speaking advanced
sercom on a pseudo-terminal, driven by its own `epuck_link` process; the
tracker (`--source emulator`) only observes the emulators' true poses, and
the agents' odometry comes from `epuck_link`.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
SCENARIO = ROOT / "scenarios" / "emulated_two_robots.toml"
ENV = {**os.environ, "OMP_NUM_THREADS": "1", "RERUN_ANALYTICS": "0"}


def _fleet(*args: str, timeout: float = 300) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "fleet.cli", *args], cwd=ROOT, env=ENV, capture_output=True, text=True,
        timeout=timeout,
    )  # fmt: skip


@pytest.fixture(scope="module")
def emulated(tmp_path_factory):
    out = tmp_path_factory.mktemp("emu2")
    return _fleet("run", str(SCENARIO), "--out", str(out)), out


def test_emulated_two_robots_complete_safely(emulated):
    res, out = emulated
    assert res.returncode == 0, res.stderr[-3000:]
    s = json.loads((out / "summary.json").read_text())
    roles = {"tracker", "supervisor", "agent r1", "agent r2"}
    roles |= {f"{kind} {r}" for kind in ("emulator", "epuck_link") for r in ("r1", "r2")}
    assert set(s["processes"]) == roles
    assert len(set(s["processes"].values())) == len(roles)
    assert all(code == 0 for code in s["exit_codes"].values()), s["exit_codes"]
    assert s["clock"] == "realtime" and s["completed"]
    assert s["collisions"] == 0 and s["all_goals_reached"]
    assert s["min_reference_separation_m"] >= s["required_reference_separation_m"] - 1e-9
    assert s["min_distance_m"] > s["collision_distance_m"]


def test_the_motion_went_through_the_link_and_the_emulated_wheels(emulated):
    """The emulators received the set-speed chains and their wheels turned; each link
    answered every camera pose with odometry and stopped its robot at the end."""
    res, out = emulated
    steps = json.loads((out / "summary.json").read_text())["steps"]
    chains = [int(n) for n in re.findall(r"\[emulator\] stopped: (\d+) sercom chains", res.stderr)]
    counts = re.findall(r"\[emulator\] stopped: .* counts \((-?\d+), (-?\d+)\)", res.stderr)
    assert len(chains) == 2 and all(n > steps for n in chains), res.stderr[-3000:]
    # Each robot drove about 1.3 m forward: ~10,000 steps of each wheel (1000 per 0.129 m).
    assert len(counts) == 2 and all(abs(int(c)) > 5000 for pair in counts for c in pair), counts
    odom = [
        int(n)
        for n in re.findall(r"\[epuck_link r\d\] stopped: zero speed sent; .* (\d+) odometry", res.stderr)
    ]
    assert len(odom) == 2 and all(n >= steps - 1 for n in odom), res.stderr[-3000:]
    assert "--source emulator" not in res.stderr  # no usage error
    assert "no emulator pose" not in res.stderr


def test_emulated_links_refuse_the_lockstep_clock(tmp_path):
    res = _fleet("run", str(SCENARIO), "--out", str(tmp_path), "--clock", "lockstep", timeout=120)
    assert res.returncode == 2
    assert res.stderr.strip().splitlines() == [
        "fleet: error: --clock: emulated robots move in wall time; use --clock realtime"
    ]


def test_fleet_run_refuses_real_and_mixed_links(tmp_path):
    text = SCENARIO.read_text()
    real = tmp_path / "real.toml"
    real.write_text(text.replace('\nlink = "emulator"', '\nlink = "serial:/dev/rfcomm0"', 1))
    mixed = tmp_path / "mixed.toml"
    mixed.write_text(text.replace('\nlink = "emulator"', '\nlink = "sim"', 1))
    bad = tmp_path / "bad.toml"
    bad.write_text(text.replace('\nlink = "emulator"', '\nlink = "bluetooth:epuck_1234"', 1))
    for path, head in (
        (real, "fleet: error: robots[0].link: 'serial:/dev/rfcomm0' is a real robot"),
        (mixed, "fleet: error: robots: fleet run needs every link sim or every link emulator"),
        (bad, "fleet: error: robots[0].link: link 'bluetooth:epuck_1234': unknown kind"),
    ):
        res = _fleet("run", str(path), "--out", str(tmp_path / "o"), timeout=120)
        lines = res.stderr.strip().splitlines()
        assert res.returncode == 2 and len(lines) == 1 and lines[0].startswith(head), res.stderr
