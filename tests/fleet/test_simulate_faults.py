"""``fleet simulate`` with agents killed mid-crossing (a fault plan's ``kills``): the living robots
keep every guarantee and get home, past static discs of bounded size (docs/method.md §6.4)."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from fleet.running.scenes import antipodal_swap, scene_to_toml
from fleet.running.simulate import run
from ground.model import stopping
from ground.scenario import parse_scenario

ROOT = Path(__file__).resolve().parents[2]
ENV = {**os.environ, "OMP_NUM_THREADS": "1", "RERUN_ANALYTICS": "0"}


def _swap(n: int, duration: float):
    scn = parse_scenario(antipodal_swap(n, duration=duration))
    return replace(scn, simulation=replace(scn.simulation, disturbance="adversarial"))


@pytest.mark.slow
@pytest.mark.parametrize("ahead", [True, False], ids=["delay-compensation", "no-delay-compensation"])
@pytest.mark.parametrize(
    ("n", "kills"),
    [(6, {"r2": 120}), (6, {"r2": 120, "r5": 150}), (16, {"r2": 100, "r9": 160})],
    ids=["6-one", "6-two", "16-one-then-another"],
)
def test_agents_killed_mid_crossing_never_stop_the_fleet(n, kills, ahead):
    """Agents killed mid-crossing and never restarted, under the adversarial disturbance.  No
    collision and no reference separation lost; every living robot's tube holds; each killed
    robot is kept clear of as dead, by discs no larger than r + N·√2·ε + d_stop (no plan is lost
    here, so m₀ ≤ 1) that always held its true body; every living robot whose goal is clear gets
    home, and one whose goal a stopped robot covers is named with it (and the goal is within
    reach of that robot's rest disc); the run ends before its duration."""
    duration = 60.0 * (n // 6 + 1)
    scn = _swap(n, duration)
    result = run(scn, ahead=ahead, kills=kills)
    s = result.summary()
    design, p = result.design, result.design.params
    assert s["collisions"] == 0 and s["disc_escapes"] == 0, s
    assert s["reference_separation_violations"] == 0
    assert result.steps * p.Ts < duration - 1.0, result.steps  # it ended early: nothing waited for
    bound = design.footprint + p.horizon * math.sqrt(2) * p.epsilon + stopping(p.v_max, p.a_max, p.Ts)[1]
    rest = design.footprint + 2 * math.sqrt(2) * p.point_noise
    for rid, r in s["robots"].items():
        if rid in kills:
            assert r["kept_clear_as"]["dead"] > 0 and not r["reached_goal"]
            assert r["kept_clear_as"]["largest_disc_m"] <= bound + 1e-12
            continue
        tr = result.traces[rid]
        assert all(tr.tube_ok) and max(tr.ref_deviation) <= design.rho, rid
        if r["reached_goal"]:
            assert r["goal_blocked_by"] is None
            continue
        blocker = r["goal_blocked_by"]
        assert blocker in kills, (rid, r)
        stood = result.traces[blocker].point[-1]
        assert np.linalg.norm(np.array(r["goal"]) - stood) < design.footprint + rest + 0.01, rid


def _simulate(tmp_path: Path, *args: str) -> subprocess.CompletedProcess[str]:
    scn = tmp_path / "swap_6.toml"
    scn.write_text(scene_to_toml(antipodal_swap(6, duration=80.0)))
    return subprocess.run(
        [sys.executable, "-m", "fleet.cli", "simulate", str(scn), "--out", str(tmp_path / "out"), *args],
        cwd=ROOT, env=ENV, capture_output=True, text=True, timeout=300,
    )  # fmt: skip


@pytest.mark.parametrize(
    ("plan", "why"),
    [
        ({"kills": {"r9": 5}}, "--faults: faults.kills.r9: no robot 'r9' in the scenario"),
        ({"kills": {"r2": -1}}, "--faults: faults.kills.r2: expected a step >= 0"),
        ({"rules": [{"key": "plan/*", "drop": 0.1}]}, "fleet simulate takes only kills"),
    ],
)
def test_a_fault_plan_simulate_cannot_run_is_refused_in_one_line(tmp_path, plan, why):
    res = _simulate(tmp_path, "--faults", json.dumps(plan))
    assert res.returncode == 2, res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and why in lines[0], lines
    assert not (tmp_path / "out").exists()


def test_fleet_simulate_kills_an_agent_and_says_so(tmp_path):
    """``fleet simulate --faults '{"kills": {"r2": 100}}'``: the run fails for r2 alone (its goal
    not reached), the closing lines say r2 was kept clear of as dead and the largest disc used,
    and the summary has it per robot."""
    res = _simulate(tmp_path, "--faults", json.dumps({"kills": {"r2": 100}}))
    assert res.returncode == 1, res.stderr
    assert res.stderr.strip() == "fleet: run failed: goal not reached by r2", res.stderr
    line = next(ln for ln in res.stdout.splitlines() if ln.startswith("faults: "))
    assert "kept clear of: r2 (dead " in line and "largest disc 0." in line, line
    s = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert s["robots"]["r2"]["kept_clear_as"]["dead"] > 0 and s["robots"]["r2"]["steps_braked"] > 0
    assert all(r["reached_goal"] for rid, r in s["robots"].items() if rid != "r2")
