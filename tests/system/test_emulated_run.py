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

import numpy as np
import pytest

pytestmark = pytest.mark.realtime
"""Each test runs a fleet on the wall clock (tests/conftest.py runs it alone)."""

ROOT = Path(__file__).resolve().parents[2]
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


@pytest.mark.parametrize("ahead", [False, True], ids=["solve-after-tick", "delay-compensation"])
def test_a_link_without_its_command_in_time_follows_the_candidate_and_the_tick_says_so(tmp_path, ahead):
    """Commands withheld on their way to epuck_link (r1: steps 60–63; r2: 10 % at random): at
    each step's deadline the link follows the shifted candidate of the last command it
    applied, reports it (fleet/F/applied/R), and the next tick says so, so the agent takes the
    same candidate and its neighbour skips the plan never executed.  The link, the agent, the
    supervisor and the tracker count the same steps; no tube is left, no committed reference
    is broken, and the run ends safely with every goal.

    With delay compensation the step's outcome says it first, within the step, and the agents
    plan ahead: nearly every command is put by Zenoh's callback as the last of the step's pose,
    odometry (from the link) and tick comes in."""
    plan = {"seed": 1, "rules": [
        {"key": "cmd/r1", "bursts": [[60, 64]], "to": ["epuck_link r1"]},
        {"key": "cmd/r2", "drop": 0.1, "to": ["epuck_link r2"]},
    ]}  # fmt: skip
    faults = tmp_path / "faults.json"
    faults.write_text(json.dumps(plan))
    out = tmp_path / "out"
    protocol = "--delay-compensation" if ahead else "--no-delay-compensation"
    res = _fleet("run", str(SCENARIO), "--out", str(out), "--faults", str(faults), protocol)
    assert res.returncode == 0, res.stderr[-3000:]
    s = json.loads((out / "summary.json").read_text())
    assert s["completed"] and s["collisions"] == 0 and s["all_goals_reached"]
    assert s.get("delay_compensation", False) is ahead
    err = res.stderr
    link = dict(re.findall(r"\[epuck_link (r\d)\] stopped: .*?, (\d+) steps on the candidate", err))
    agent = dict(re.findall(r"\[agent (r\d)\] stopped after .*?, (\d+) steps on the candidate", err))
    on_candidate = {r: str(v["steps_on_candidate"]) for r, v in s["robots"].items()}
    assert link == agent == on_candidate, (link, agent, on_candidate)
    assert int(link["r1"]) >= 4 and int(link["r2"]) >= 10, link  # the burst; ≈ 10 % of the steps
    # Logged once an episode (one may have begun a little earlier, on the machine's own delays).
    assert re.search(r"\[epuck_link r1\] step (5\d|6[0-3]): no command in time; following the shifted", err)
    assert re.search(r"\[agent r1\] step (5\d|6[0-4]): commands after step \d+ not applied; on its cand", err)
    # The deadline's rule stopped nothing, and the watchdog only at the end (the agents gone).
    stops = re.findall(r"\[epuck_link r\d\] stopped: .*?, (\d+) watchdog stops", err)
    assert stops == ["1", "1"], stops
    braked = sum(v["steps_braked"] for v in s["robots"].values())
    assert s["deadline_misses"] == int(link["r1"]) + int(link["r2"]) + braked
    for rid, r in s["robots"].items():
        assert r["tube_exits"] == 0 and r["reference_breaks"] == 0 and r["qp_failures"] == 0, (rid, r)
    puts = dict(re.findall(r"\[agent (r\d)\] stopped after .*? \((\d+) by Zenoh's callback\)", err))
    if ahead:  # every step but the first planned ahead, and its command put on arrival
        assert set(puts) == {"r1", "r2"} and all(int(n) >= 0.9 * s["steps"] for n in puts.values()), puts
    else:
        assert puts == {"r1": "0", "r2": "0"}, puts


def test_a_robot_whose_link_is_cut_drives_on_and_is_kept_clear_of(tmp_path):
    """r1's link to its emulator is cut for 15 steps as the two robots close in head-on.  The
    emulator, like the firmware, has no deadman: r1 drives on at its last wheel speeds.  The
    link announces the loss at once; r2 keeps clear of r1 as a moving obstacle, not a static
    disc; the supervisor records the event.  When the link is back its first command stops the
    robot, r1's agent starts again where the robot is, and both robots get home safely."""
    from supervisor.recorder import read_events
    from supervisor.trace import Trace

    cut = (60, 75)
    faults = json.dumps({"links": {"r1": [list(cut)]}})
    out = tmp_path / "run"
    res = _fleet("run", str(SCENARIO), "--out", str(out), "--faults", faults)
    err = res.stderr
    assert res.returncode == 0, err[-3000:]
    s = json.loads((out / "summary.json").read_text())
    assert s["completed"] and s["collisions"] == 0 and s["all_goals_reached"], s
    assert s["robots"]["r1"]["link_losses"] == 1 and s["robots"]["r2"]["link_losses"] == 0
    # The robot moved while nobody controlled it: its last speeds, as the firmware keeps them.
    trace = Trace.load(out / "trace.npz")
    r1 = trace.ids.index("r1")
    moved = float(np.linalg.norm(trace.poses[r1, cut[1] - 1, :2] - trace.poses[r1, cut[0] + 1, :2]))
    assert moved > 0.05, moved
    assert "[epuck_link r1] link lost: " in err and "link cut (fault plan)" in err
    assert re.search(
        r"\[agent r2\] step 6\d: r1: link down, driving on uncontrolled; kept clear of as a moving", err
    )
    assert "zero speed first" in err and "[epuck_link r1] link back after an outage" in err
    assert re.search(r"\[agent r1\] step \d+: robot braked after step \d+; starting again where it is", err)
    events = [text for _, text in read_events(out / "recording.rrd")]
    assert any(t.startswith("r1: link lost at step") and "uncontrolled" in t for t in events), events
    back = [
        int(m.group(1))
        for t in events
        if (m := re.search(r"^r1: link back at step \d+;.* at step (\d+)$", t))
    ]
    assert len(back) == 1, events
    # r2 coordinates with r1 again only on a plan made from where r1 stands (of step `back` or
    # later, which r2 uses a step after): the plans before were made for a robot adrift.
    again = [int(k) for k in re.findall(r"\[agent r2\] step (\d+): r1: coordinating again", err)]
    assert again and min(k for k in again if k > cut[0]) >= back[0] + 1, (again, back)
