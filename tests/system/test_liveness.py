"""Every robot gets home and stays: the scenes that used to stall.

Each scene runs in `fleet simulate` and must end with every robot arrived (within the goal
tolerance for the settle time, ``ground.scenario.settled_since``) and no collision.  The
order that makes this so is ``agent.coordination.precedence`` (docs/method.md §7, "Why
robots get home").  The breadth — 100+ generated scenes — is ``fleet bench --liveness``.
"""

from __future__ import annotations

import math

import pytest

from fleet.running.scenes import (
    COMPACT_CONTROLLER,
    MIN_GOAL_SPACING,
    antipodal_swap,
    corridor_swap,
    hard_scene,
    mirrored_grid,
    random_scene,
    ring,
)
from fleet.running.simulate import run
from ground.scenario import GOAL_MARGIN, parse_scenario


def _two_close() -> dict:
    """Two robots whose goals are the closest the loader accepts (2 footprints + 1 cm)."""
    g = 0.5 * MIN_GOAL_SPACING
    return {
        "name": "two_close", "duration": 120.0, "arena": {"bounds": [-1.0, 1.0, -1.0, 1.0]},
        "robots": [
            {"id": "r1", "start": [-0.6, 0.0, 0.0], "goal": [g, 0.0]},
            {"id": "r2", "start": [0.6, 0.0, math.pi], "goal": [-g, 0.0]},
        ],
    }  # fmt: skip


def _swap20() -> dict:
    """20 robots, compact controller (footprint ≈ 0.1135 m), goals 0.238 m apart."""
    d = antipodal_swap(20, radius=0.238 / (2 * math.sin(math.pi / 20)) + 0.031, duration=300.0)
    d["controller"] = dict(COMPACT_CONTROLLER)
    return d


SCENES = {
    "two_close": _two_close,
    "odd_ring_5": lambda: ring(5, spacing=0.317, duration=150.0),
    "grid_3x3": lambda: mirrored_grid(3, 3, duration=200.0),
    "swap_20_compact": _swap20,
    # Six robots passing head-on in a corridor barely two wide: the columns cross, then the
    # three robots of a column park 0.331 m apart (docs/method.md §7, "Close goals").
    "corridor_6": lambda: corridor_swap(6, duration=300.0),
    # Dense random scenes at the closest spacing: two robots under way trade places through a
    # gap between two parked ones that opens and closes.
    "dense_14": lambda: random_scene(0, n=14, min_separation=MIN_GOAL_SPACING, duration=300.0, margin=0.15),
    "dense_16": lambda: hard_scene(7),
    # Goals packed around obstacles: parked robots displaced by a returning one, which then
    # went first by rank and displaced it in turn (docs/method.md §7, the progress argument).
    "obstacle_goals_9": lambda: hard_scene(41),
}


@pytest.mark.parametrize("name", list(SCENES))
def test_every_robot_arrives_and_stays(name):
    scn = parse_scenario(SCENES[name]())
    res = run(scn)
    s = res.summary()
    assert s["collisions"] == 0 and s["reference_separation_violations"] == 0
    late = {r: round(v["final_error_m"], 3) for r, v in s["robots"].items() if not v["reached_goal"]}
    assert not late, f"{name}: not arrived (final error m): {late}"
    assert s["steps"] * scn.controller.Ts < scn.duration, "ended by the duration, not by arriving"
    for v in s["robots"].values():
        assert v["path_length_m"] >= v["straight_line_m"] - 0.05


@pytest.mark.parametrize("width", [0.30, 0.341])
def test_a_pocket_fills_from_the_bottom_and_nobody_is_walled_in(width):
    """Three goals down a dead-end pocket (ground.arrival): each robot but the deepest waits at
    its wait point until the robots whose way its goal walls in are past it, so the judge never
    finds a way home walled in and nobody has to leave its goal.  Without the gates, the 0.341 m
    pocket left its middle robot out for good."""
    from fleet.running.scenes import pocket

    scn = parse_scenario(pocket(width, depth=3 * MIN_GOAL_SPACING + 0.2, robots=3, duration=300.0))
    s = run(scn).summary()
    assert s["collisions"] == 0
    assert s["order_of_arrival"]["waits"].keys() == {"r2", "r3"}  # the gates were there
    robots = s["robots"]
    assert all(v["reached_goal"] for v in robots.values()), {r: v["final_error_m"] for r, v in robots.items()}
    assert s["walled_in"] == [] and s["displacements"] == 0


def test_closest_goals_are_the_footprints_plus_the_margin():
    """Goals 1 mm closer than 2 footprints + GOAL_MARGIN are refused, naming both robots (the
    field the second, the text the first) and the sum that was needed."""
    from agent.tube import validated_design
    from ground.scenario import ConfigError

    d = _two_close()
    g = 0.5 * (MIN_GOAL_SPACING - 0.001)
    d["robots"][0]["goal"], d["robots"][1]["goal"] = [g, 0.0], [-g, 0.0]
    with pytest.raises(ConfigError) as e:
        validated_design(parse_scenario(d))
    assert e.value.field == "robots[1].goal" and "from r1's goal" in e.value.reason
    assert f"+ {GOAL_MARGIN:g}" in e.value.reason


def test_a_train_that_must_back_into_a_lane_is_named_as_having_no_room():
    """Assumption (A) failing, seen from outside: two trains meet in a single-file lane, and the
    robot that meets the one going first has no point out of its corridor.  The summary names
    it, and the robot it could not make way for, and counts its steps without room, each a step
    its navigator had it make way (mode ``yield``); the robot that goes first never lacks room."""
    from fleet.running.scenes import LAYOUT_FAMILIES

    data = hard_scene(36, LAYOUT_FAMILIES)
    assert data["name"] == "hard_36_file_trains_3"
    data["duration"] = 40.0
    res = run(parse_scenario(data))
    s = res.summary()
    ids = {r["id"] for r in data["robots"]}
    assert s["no_room"], "no episode of no room"
    for ep in s["no_room"]:
        assert ep["robot"] in ids and ep["for"] in ids - {ep["robot"]}, ep
    for rid, v in s["robots"].items():
        assert v["no_room_steps"] <= res.traces[rid].modes.count("yield"), rid
    assert max(v["no_room_steps"] for v in s["robots"].values()) > 0
    assert s["robots"]["r1"]["no_room_steps"] == 0  # the first in precedence makes way for nobody
