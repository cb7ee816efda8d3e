"""Shipped and seeded random scenes, run by `fleet simulate` in one process: every robot home, safely."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from fleet.running.scenes import random_scene
from fleet.running.simulate import run
from ground.scenario import GOAL_TOLERANCE, load_scenario, parse_scenario

SCENARIOS = Path(__file__).resolve().parents[2] / "scenarios"


def _safe(result):
    assert result.collisions == 0, (
        f"{result.collisions} collision samples, min distance {result.min_distance}"
    )
    assert result.min_distance >= 2 * result.design.params.robot_radius
    assert result.reference_violations == 0
    assert result.min_reference_separation >= result.required_reference_separation - 1e-9
    assert result.obstacle_violations == 0
    assert result.arena_violations == 0


def _all_home(result, within_s=None):
    s = result.summary()
    missing = {rid: round(r["final_error_m"], 3) for rid, r in s["robots"].items() if not r["reached_goal"]}
    assert not missing, f"goal not reached (final error m): {missing}"
    for r in s["robots"].values():
        assert r["final_error_m"] <= GOAL_TOLERANCE
        if within_s is not None:
            assert r["time_to_goal_s"] <= within_s


def _max_lateral(result, rid):
    """Largest |y| of the robot's controlled point [m] (the head-on scenes run along y = 0)."""
    return float(np.max(np.abs(np.array(result.traces[rid].point)[:, 1])))


def test_two_robots_head_on_without_priority():
    result = run(load_scenario(SCENARIOS / "paper_two_robots.toml"))
    _safe(result)
    _all_home(result)
    # The symmetric case resolves: someone left the line y = 0.
    assert max(_max_lateral(result, "r1"), _max_lateral(result, "r2")) > 0.1


@pytest.mark.parametrize("first", ["r1", "r2"])
def test_two_robots_head_on_with_priority(first):
    """Paper Fig. 6–7: the robot with priority keeps its line, the other escapes."""
    scn = load_scenario(SCENARIOS / "paper_two_robots_priority.toml")
    robots = tuple(replace(rb, priority=1 if rb.id == first else 0) for rb in scn.robots)
    result = run(replace(scn, robots=robots))
    _safe(result)
    _all_home(result)
    other = "r2" if first == "r1" else "r1"
    assert _max_lateral(result, first) < 0.5 * _max_lateral(result, other)


def test_three_robots_through_the_centre():
    """Paper Fig. 8–9."""
    result = run(load_scenario(SCENARIOS / "paper_three_robots.toml"))
    _safe(result)
    _all_home(result)


@pytest.mark.parametrize("n", [4, 8])
def test_antipodal_swap(n):
    result = run(load_scenario(SCENARIOS / f"swap_{n}.toml"))
    _safe(result)
    _all_home(result)


@pytest.mark.slow
@pytest.mark.parametrize("n", [16, 32])
def test_antipodal_swap_compact(n):
    """Runs with the scenario's tighter tube (footprint 0.113 m); see fleet.running.scenes.COMPACT_CONTROLLER.
    The 32 robots' goals are 0.304 m apart on the ring, R + 7.7 cm: two neighbours used to trade
    places at their goals for the whole run (docs/method.md §7, "Close goals")."""
    result = run(load_scenario(SCENARIOS / f"swap_{n}.toml"))
    _safe(result)
    _all_home(result)


@pytest.mark.parametrize("seed", range(20))
def test_random_ten_robot_scene(seed):
    """Seeded random scenes: starts and goals ≥ 0.42 m apart, all home within 150 s."""
    scn = parse_scenario(random_scene(seed, n=10, min_separation=0.42, duration=150.0))
    result = run(scn)
    _safe(result)
    _all_home(result, within_s=150.0)


def test_four_robots_around_a_static_obstacle():
    result = run(load_scenario(SCENARIOS / "obstacle_four.toml"))
    _safe(result)
    _all_home(result)
    # The obstacle was actually in the way: someone passed close to it.
    ob = result.scenario and load_scenario(SCENARIOS / "obstacle_four.toml").obstacles[0]
    closest = min(ob.distance(p[:2]) for tr in result.traces.values() for p in tr.pose)
    assert closest < 0.3
