"""Whose goals wall in whose way home (ground.scenario.forced_order): the layout check that says,
at load, where an order of arrival is forced (the well-formedness of Čáp et al., for goals)."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np

from fleet.running.scenes import antipodal_swap, lane_crossing, mirrored_grid, pocket, scene_to_toml
from ground.freespace import free_space_model
from ground.geometry import controlled_point
from ground.scenario import Scenario, forced_order, forced_order_lines, load_scenario

FP = 0.13405
ROOT = Path(__file__).resolve().parents[2]


def _load(tmp_path: Path, scene: dict) -> Scenario:
    path = tmp_path / f"{scene['name']}.toml"
    path.write_text(scene_to_toml(scene))
    return load_scenario(path)


def _way(scn: Scenario, rid: str) -> tuple[np.ndarray, np.ndarray]:
    r = next(r for r in scn.robots if r.id == rid)
    return controlled_point(r.start, scn.controller.lookahead), np.asarray(r.goal, dtype=float)


def _goal(scn: Scenario, rid: str) -> tuple[np.ndarray, float]:
    return np.asarray(next(r for r in scn.robots if r.id == rid).goal, dtype=float), 2 * FP


def test_goals_down_a_pocket_force_the_deepest_first(tmp_path) -> None:
    """Three goals down a dead-end pocket: the deepest robot must be home before either other
    parks, the middle one before the one at the mouth; each goal named walls the way by itself
    (checked on its own against the free-space model), and the mouth's robot is free."""
    scn = _load(tmp_path, pocket(0.30, robots=3))
    forced = forced_order(scn, FP)
    assert forced == {"r1": {"alone": ["r2", "r3"], "together": []}, "r2": {"alone": ["r3"], "together": []}}
    model = free_space_model(scn.arena, scn.obstacles, FP)
    for rid, by in forced.items():
        a, b = _way(scn, rid)
        assert model.joined(a, b)  # the walls alone leave the way open
        for other in by["alone"]:
            assert model.walled_in(a, b, [_goal(scn, other)])
    a, b = _way(scn, "r3")
    assert not model.walled_in(a, b, [_goal(scn, "r1"), _goal(scn, "r2")])
    assert forced_order_lines(forced) == [
        "r1 must get past the goals of r2, r3 before they park: each walls in its way",
        "r2 must get past the goals of r3 before they park: each walls in its way",
    ]


def test_an_interior_goal_of_a_grid_at_the_closest_spacing_is_walled_in_by_its_neighbours(tmp_path) -> None:
    """In a 4 × 4 grid of goals 0.2782 m apart (each robot heading for its mirror image), the four
    interior goals are shut in by the four goals about each (their discs of 2r overlap), and so
    are the four interior starts: their robots are named with the goals about both; no single
    goal walls a way; the other robots are free."""
    scn = _load(tmp_path, mirrored_grid(4, 4))
    forced = forced_order(scn, FP)
    goals = {r.id: np.asarray(r.goal) for r in scn.robots}
    interior = {rid for rid, g in goals.items() if np.all(np.abs(g) < 0.2)}
    assert set(forced) == interior and len(interior) == 4
    for rid, by in forced.items():
        assert by["alone"] == []
        start, goal = _way(scn, rid)
        near = {
            o for o, g in goals.items()
            if o != rid and min(abs(np.linalg.norm(g - p) - 0.2782) for p in (goal, start)) < 1e-3
        }  # fmt: skip
        assert set(by["together"]) == near and len(near) >= 4


def test_a_swap_on_a_circle_is_well_formed(tmp_path) -> None:
    """16 robots crossing a circle to the antipodes: every way home passes every parked robot
    (a goal on the robot's own start is left out: it leaves first)."""
    assert forced_order(_load(tmp_path, antipodal_swap(16)), FP) == {}


def test_two_robots_whose_goals_wall_each_others_way_are_named_as_a_cycle(tmp_path) -> None:
    """A corridor a single robot wide, each robot's goal on the other's way: each must be home
    before the other parks, which no order does."""
    scene = lane_crossing()
    forced = forced_order(_load(tmp_path, scene), FP)
    assert forced == {"r1": {"alone": ["r2"], "together": []}, "r2": {"alone": ["r1"], "together": []}}
    assert forced_order_lines(forced)[-1].startswith("r1, r2: each must be home before another of them parks")


def test_fleet_simulate_says_the_forced_order_and_the_summary_keeps_it(tmp_path) -> None:
    scene = pocket(0.30, robots=2, duration=2.0)
    path = tmp_path / "pocket.toml"
    path.write_text(scene_to_toml(scene))
    res = subprocess.run(
        [sys.executable, "-m", "fleet.cli", "simulate", str(path), "--out", str(tmp_path / "out")],
        cwd=ROOT, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert "layout: 1 of 2 robots must be home before others park:" in res.stdout, res.stdout + res.stderr
    assert "  r1 must get past the goals of r2 before they park: each walls in its way" in res.stdout
    assert re.search(
        r"order of arrival:\n  r2 waits at \(-?[0-9.]+, -?[0-9.]+\) until r1 is past its goal", res.stdout
    )
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["forced_order"] == {"r1": {"alone": ["r2"], "together": []}}
    order = summary["order_of_arrival"]
    assert order["waits"].keys() == {"r2"} and order["waits"]["r2"]["waits_for"] == ["r1"]
    assert (order["unordered"], order["no_wait_point"], order["unproven"]) == ([], [], [])


def test_fleet_run_says_the_forced_order_and_the_recording_holds_it(tmp_path) -> None:
    """The process fleet says it too: on its first lines, and as an event in the Rerun recording,
    logged by the supervisor once the first plans give it the footprint."""
    from supervisor.recorder import read_events
    from transport.net import free_port, loopback

    path = tmp_path / "pocket.toml"
    path.write_text(scene_to_toml(pocket(0.30, robots=2, duration=1.0)))
    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "fleet.cli", "run", str(path), "--out", str(out)]
    res = subprocess.run(
        [*cmd, "--listen", loopback(free_port())],
        cwd=ROOT, capture_output=True, text=True, timeout=300, env={**os.environ, "RERUN_ANALYTICS": "0"},
    )  # fmt: skip
    assert "layout: 1 of 2 robots must be home before others park:" in res.stdout, res.stdout + res.stderr
    events = [text for _, text in read_events(out / "recording.rrd")]
    want = "layout: r1 must get past the goals of r2 before they park: each walls in its way"
    assert want in events, events
    assert any(e.startswith("order of arrival: r2 waits at (") for e in events), events
    summary = json.loads((out / "summary.json").read_text())
    assert summary["forced_order"] == {"r1": {"alone": ["r2"], "together": []}}
