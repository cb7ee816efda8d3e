"""Tests of the scenario schema (ground.scenario) and the programmatic scenes (fleet.running.scenes)."""

from __future__ import annotations

import copy
import dataclasses
import functools
import itertools
import math
import pickle
import tomllib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from agent.tube import synthesize
from fleet.running.scenes import COMPACT_CONTROLLER, antipodal_swap, random_scene, scene_to_toml
from ground.params import ControllerParams, preset
from ground.scenario import (
    GOAL_MARGIN,
    MAX_SCENARIO_BYTES,
    Circle,
    ConfigError,
    Polygon,
    Scenario,
    check_geometry,
    controlled_point,
    goal_problem,
    load_scenario,
    parse_scenario,
)

SCENARIO_DIR = Path(__file__).resolve().parents[2] / "scenarios"
SHIPPED = sorted(SCENARIO_DIR.glob("*.toml"))
ARENA = (-1.0, 1.0, -1.0, 1.0)


@functools.cache
def footprint(params: ControllerParams, arena: tuple[float, float, float, float]) -> float:
    return synthesize(params, arena).footprint


def footprint_of(scn: Scenario) -> float:
    return footprint(scn.controller, scn.arena)


def base() -> dict[str, Any]:
    """A valid scenario dict exercising every table."""
    return {
        "name": "base",
        "duration": 30.0,
        "arena": {"bounds": [-1.0, 1.0, -1.0, 1.0]},
        "controller": {"preset": "epuck", "Ts": 0.1, "Q": [1, 1, 1, 1], "wheel": {"axle": 0.053}},
        "simulation": {"seed": 1, "disturbance": "uniform", "plant": "unicycle", "disturbance_fraction": 0.9},
        "robots": [
            {"id": "r1", "start": [-0.6, 0.0, 0.0], "goal": [0.6, 0.0], "priority": 0, "link": "sim"},
            {"id": "r2", "start": [0.6, 0.0, math.pi], "goal": [-0.6, 0.0]},
        ],
        "obstacles": [
            {"circle": {"center": [0.0, 0.6], "radius": 0.1}},
            {"polygon": [[0.3, -0.7], [0.5, -0.7], [0.4, -0.5]]},
        ],
    }


# --------------------------------------------------------------------------- shipped files


def test_scenarios_are_shipped() -> None:
    names = {p.stem for p in SHIPPED}
    expected = {
        "paper_two_robots",
        "paper_two_robots_priority",
        "paper_three_robots",
        "swap_4",
        "swap_8",
        "swap_16",
        "obstacle_four",
    }
    assert expected <= names


@pytest.mark.parametrize("path", SHIPPED, ids=[p.stem for p in SHIPPED])
def test_shipped_scenario_parses_and_fits(path: Path) -> None:
    scn = load_scenario(path)
    assert scn.name == path.stem
    assert scn.source == str(path)
    design = synthesize(scn.controller, scn.arena)
    assert design.failures == []
    check_geometry(scn, design.footprint)


def test_paper_two_robots_contents() -> None:
    scn = load_scenario(SCENARIO_DIR / "paper_two_robots.toml")
    assert [r.start for r in scn.robots] == [(-0.7, 0.0, 0.0), (0.7, 0.0, math.pi)]
    assert [r.goal for r in scn.robots] == [(0.7, 0.0), (-0.7, 0.0)]
    assert [r.priority for r in scn.robots] == [0, 0]
    assert scn.duration == 60.0
    assert scn.controller == preset("epuck")
    prio = load_scenario(SCENARIO_DIR / "paper_two_robots_priority.toml")
    assert [r.priority for r in prio.robots] == [1, 0]
    assert [r.start for r in prio.robots] == [r.start for r in scn.robots]


def test_paper_three_robots_contents() -> None:
    scn = load_scenario(SCENARIO_DIR / "paper_three_robots.toml")
    assert len(scn.robots) == 3
    for r in scn.robots:
        assert math.hypot(r.start[0], r.start[1]) == pytest.approx(0.7)
        assert r.goal == pytest.approx((-r.start[0], -r.start[1]))
        # heading points at the goal
        assert math.cos(r.start[2]) == pytest.approx(-r.start[0] / 0.7)
        assert math.sin(r.start[2]) == pytest.approx(-r.start[1] / 0.7)


def test_obstacle_four_contents() -> None:
    scn = load_scenario(SCENARIO_DIR / "obstacle_four.toml")
    assert scn.obstacles == (Circle(center=(0.0, 0.0), radius=0.2),)
    assert scn.duration == 120.0
    for r in scn.robots:
        assert r.goal == pytest.approx((-r.start[0], -r.start[1]))
        assert controlled_point(r.start, 0.04) == pytest.approx(0.71 / 0.75 * np.array(r.start[:2]))


@pytest.mark.parametrize(("n", "duration"), [(4, 60.0), (8, 120.0), (16, 240.0)])
def test_swap_files_match_generator(n: int, duration: float) -> None:
    from_file = load_scenario(SCENARIO_DIR / f"swap_{n}.toml")
    data = antipodal_swap(n, duration=duration)
    if n == 16:
        data["controller"] = dict(COMPACT_CONTROLLER)
    generated = parse_scenario(data)
    assert dataclasses.replace(from_file, source="") == dataclasses.replace(generated, source="")


# --------------------------------------------------------------------------- scenes


@pytest.mark.parametrize("n", [1, 2, 3, 4, 5, 8, 12, 16])
def test_antipodal_swap(n: int) -> None:
    data = antipodal_swap(n)
    scn = parse_scenario(data)
    assert scn.name == f"swap_{n}"
    check_geometry(scn, footprint_of(scn))
    for r in scn.robots:
        assert math.hypot(r.start[0], r.start[1]) == pytest.approx(0.8, abs=1e-8)
        assert r.goal == pytest.approx((-r.start[0], -r.start[1]), abs=1e-8)
        direction = (np.array(r.goal) - np.array(r.start[:2])) / 1.6
        assert (math.cos(r.start[2]), math.sin(r.start[2])) == pytest.approx(tuple(direction), abs=1e-8)
    angles = sorted(math.atan2(r.start[1], r.start[0]) % (2 * math.pi) for r in scn.robots)
    gaps = np.diff([*angles, angles[0] + 2 * math.pi])
    assert gaps == pytest.approx(np.full(n, 2 * math.pi / n), abs=1e-8)


def test_antipodal_swap_16_too_tight_is_rejected() -> None:
    scn = parse_scenario(antipodal_swap(16, radius=0.6))
    with pytest.raises(ConfigError) as exc:
        check_geometry(scn, footprint_of(scn))
    assert exc.value.field == "robots[1].start"
    assert "closer than their footprints" in exc.value.reason


@pytest.mark.parametrize("seed", range(30))
def test_random_scene_contract(seed: int) -> None:
    sep, margin, ell = 0.42, 0.16, preset("epuck").lookahead
    data = random_scene(seed)
    assert data == random_scene(seed)  # deterministic
    scn = parse_scenario(data)
    assert scn.name == f"random_10_seed{seed}"
    assert len(scn.robots) == 10
    axles = [np.array(r.start[:2]) for r in scn.robots]
    points = [controlled_point(r.start, ell) for r in scn.robots]
    goals = [np.array(r.goal) for r in scn.robots]
    for group in (axles, points, goals):
        for p in group:
            assert np.all(p >= -1.0 + margin - 1e-12) and np.all(p <= 1.0 - margin + 1e-12)
        for p, q in itertools.combinations(group, 2):
            assert np.linalg.norm(p - q) >= sep
    check_geometry(scn, footprint_of(scn))


def test_random_scene_seeds_differ_and_bounded() -> None:
    assert random_scene(0)["robots"] != random_scene(1)["robots"]
    with pytest.raises(RuntimeError):
        random_scene(0, n=60, max_tries=5000)


@pytest.mark.parametrize("data", [base(), antipodal_swap(5), random_scene(3)], ids=["base", "swap", "random"])
def test_scene_to_toml_round_trip(data: dict[str, Any], tmp_path: Path) -> None:
    text = scene_to_toml(data, comment="a comment\nover two lines")
    assert text.startswith("# a comment\n# over two lines\n")
    loaded = tomllib.loads(text)
    assert loaded == data
    path = tmp_path / "scene.toml"
    path.write_text(text)
    assert dataclasses.replace(load_scenario(path), source="<dict>") == parse_scenario(data)


# --------------------------------------------------------------------------- parsing


def test_base_parses() -> None:
    scn = parse_scenario(base())
    assert scn.source == "<dict>"
    assert scn.robots[1].priority == 0 and scn.robots[1].link == "sim"
    assert scn.controller.Q == (1.0, 1.0, 1.0, 1.0)
    assert all(isinstance(q, float) for q in scn.controller.Q)
    assert scn.simulation.seed == 1
    assert isinstance(scn.obstacles[1], Polygon)
    check_geometry(scn, footprint_of(scn))


def test_every_controller_field_accepts_its_default() -> None:
    default = preset("epuck")
    table: dict[str, Any] = {}
    for f in dataclasses.fields(ControllerParams):
        value = getattr(default, f.name)
        if value is None:
            continue
        if f.name == "wheel":
            table["wheel"] = dataclasses.asdict(value)
        else:
            table[f.name] = list(value) if isinstance(value, tuple) else value
    data = base()
    data["controller"] = table
    assert parse_scenario(data).controller == default


def test_preset_override() -> None:
    data = base()
    data["controller"] = {"preset": "epuck", "Q": [2, 2, 2, 2], "wheel": {"axle": 0.06}}
    scn = parse_scenario(data, preset_override="paper")
    paper = preset("paper")
    assert scn.controller.preset == "paper"
    assert scn.controller.K_R == paper.K_R and scn.controller.W == paper.W
    assert scn.controller.Q == (2.0, 2.0, 2.0, 2.0)
    assert scn.controller.wheel.axle == 0.06
    assert scn.controller.wheel.wheel_radius == paper.wheel.wheel_radius
    del data["controller"]
    assert parse_scenario(data, preset_override="paper").controller == paper
    assert parse_scenario(data).controller == preset("epuck")


def test_config_error_format_and_pickle() -> None:
    err = ConfigError("controller.R[1]", "expected a number, got 'abc'")
    assert str(err) == "controller.R[1]: expected a number, got 'abc'"
    assert isinstance(err, ValueError)
    again = pickle.loads(pickle.dumps(err))
    assert (again.field, again.reason) == (err.field, err.reason)


Mutation = Callable[[dict[str, Any]], None]


def _set(path: str, value: object) -> Mutation:
    """Mutation setting a dotted path (``robots.1.id``) of the base dict."""

    def apply(d: dict[str, Any]) -> None:
        *parents, last = path.split(".")
        node: Any = d
        for p in parents:
            node = node[int(p)] if isinstance(node, list) else node.setdefault(p, {})
        if isinstance(node, list):
            node[int(last)] = value
        else:
            node[last] = value

    return apply


def _delete(path: str) -> Mutation:
    def apply(d: dict[str, Any]) -> None:
        *parents, last = path.split(".")
        node: Any = d
        for p in parents:
            node = node[int(p)] if isinstance(node, list) else node[p]
        del node[int(last) if isinstance(node, list) else last]

    return apply


BAD_INPUTS: list[tuple[str, Mutation, str]] = [
    ("unknown top key", _set("durration", 3.0), "durration"),
    ("unknown arena key", _set("arena.bound", [0, 1, 0, 1]), "arena.bound"),
    ("unknown controller key", _set("controller.Rr", [1, 1]), "controller.Rr"),
    ("unknown wheel key", _set("controller.wheel.axel", 0.05), "controller.wheel.axel"),
    ("unknown simulation key", _set("simulation.sed", 3), "simulation.sed"),
    ("unknown robot key", _set("robots.1.prio", 1), "robots[1].prio"),
    ("unknown obstacle key", _set("obstacles.0.box", [0, 1]), "obstacles[0].box"),
    ("unknown circle key", _set("obstacles.0.circle.centre", [0, 0]), "obstacles[0].circle.centre"),
    ("missing name", _delete("name"), "name"),
    ("missing robots", _delete("robots"), "robots"),
    ("missing bounds", _delete("arena.bounds"), "arena.bounds"),
    ("missing goal", _delete("robots.0.goal"), "robots[0].goal"),
    ("goal not the last waypoint", _set("robots.0.waypoints", [[0.0, -0.4], [0.5, 0.0]]), "robots[0].goal"),
    ("no waypoints", _set("robots.0.waypoints", []), "robots[0].waypoints"),
    ("waypoint not a point", _set("robots.0.waypoints", [[0.0, 0.4, 1.0]]), "robots[0].waypoints[0]"),
    (
        "waypoint not finite",
        _set("robots.1.waypoints", [[math.inf, 0.0], [-0.6, 0.0]]),
        "robots[1].waypoints[0][0]",
    ),
    ("no robots", _set("robots", []), "robots"),
    ("non-numeric weight", _set("controller.R", [20, "abc"]), "controller.R[1]"),
    ("bool as number", _set("controller.Ts", True), "controller.Ts"),
    ("NaN duration", _set("duration", math.nan), "duration"),
    ("inf weight", _set("controller.Q", [1, 1, math.inf, 1]), "controller.Q[2]"),
    ("Q length", _set("controller.Q", [1, 1, 1]), "controller.Q"),
    ("W length", _set("controller.W", [0.001]), "controller.W"),
    ("start length", _set("robots.0.start", [0.0, 0.0]), "robots[0].start"),
    ("bounds length", _set("arena.bounds", [-1, 1, -1]), "arena.bounds"),
    ("float horizon", _set("controller.horizon", 2.5), "controller.horizon"),
    ("bool horizon", _set("controller.horizon", True), "controller.horizon"),
    ("short horizon", _set("controller.horizon", 1), "controller.horizon"),
    ("negative epsilon", _set("controller.epsilon", -0.01), "controller.epsilon"),
    ("zero R", _set("controller.R", [0, 20]), "controller.R[0]"),
    ("negative Q", _set("controller.Q", [1, -1, 1, 1]), "controller.Q[1]"),
    ("zero W", _set("controller.W", [0, 0]), "controller.W"),
    ("priority_share 1", _set("controller.priority_share", 1.0), "controller.priority_share"),
    ("penalty not bool", _set("controller.penalty", "yes"), "controller.penalty"),
    ("negative lookahead", _set("controller.lookahead", -0.01), "controller.lookahead"),
    ("zero budget", _set("controller.solve_time_budget", 0.0), "controller.solve_time_budget"),
    ("unknown preset", _set("controller.preset", "fast"), "controller.preset"),
    ("zero duration", _set("duration", 0.0), "duration"),
    ("bad bounds order", _set("arena.bounds", [1, -1, -1, 1]), "arena.bounds"),
    ("unknown disturbance", _set("simulation.disturbance", "gaussian"), "simulation.disturbance"),
    ("unknown plant", _set("simulation.plant", "bicycle"), "simulation.plant"),
    ("fraction 0", _set("simulation.disturbance_fraction", 0.0), "simulation.disturbance_fraction"),
    ("fraction > 1", _set("simulation.disturbance_fraction", 1.5), "simulation.disturbance_fraction"),
    ("negative seed", _set("simulation.seed", -1), "simulation.seed"),
    ("duplicate id", _set("robots.1.id", "r1"), "robots[1].id"),
    ("bad id", _set("robots.0.id", "r 1"), "robots[0].id"),
    ("empty id", _set("robots.0.id", ""), "robots[0].id"),
    ("float priority", _set("robots.0.priority", 2.5), "robots[0].priority"),
    (
        "non-convex polygon",
        _set("obstacles.1.polygon", [[0, 0], [1, 0], [0.2, 0.2], [0, 1]]),
        "obstacles[1].polygon",
    ),
    (
        "self-intersecting polygon",
        _set("obstacles.1.polygon", [[0, 0], [1, 0], [0, 1], [1, 1]]),
        "obstacles[1].polygon",
    ),
    (
        "pentagram",
        _set(
            "obstacles.1.polygon",
            [[math.cos(a), math.sin(a)] for a in (2 * math.pi * 2 * k / 5 for k in range(5))],
        ),
        "obstacles[1].polygon",
    ),
    ("two-vertex polygon", _set("obstacles.1.polygon", [[0, 0], [1, 0]]), "obstacles[1].polygon"),
    (
        "repeated vertex",
        _set("obstacles.1.polygon", [[0, 0], [1, 0], [1, 0], [0, 1]]),
        "obstacles[1].polygon",
    ),
    ("collinear polygon", _set("obstacles.1.polygon", [[0, 0], [1, 0], [2, 0]]), "obstacles[1].polygon"),
    (
        "bad polygon vertex",
        _set("obstacles.1.polygon", [[0, 0], [1, "x"], [0, 1]]),
        "obstacles[1].polygon[1][1]",
    ),
    ("circle and polygon", _set("obstacles.0.polygon", [[0, 0], [1, 0], [0, 1]]), "obstacles[0]"),
    ("zero radius", _set("obstacles.0.circle.radius", 0.0), "obstacles[0].circle.radius"),
    ("controller not a table", _set("controller", 3), "controller"),
]


@pytest.mark.parametrize(("mutate", "field"), [c[1:] for c in BAD_INPUTS], ids=[c[0] for c in BAD_INPUTS])
def test_bad_input(mutate: Mutation, field: str, tmp_path: Path) -> None:
    data = copy.deepcopy(base())
    mutate(data)
    with pytest.raises(ConfigError) as exc:
        parse_scenario(data)
    assert exc.value.field == field
    assert str(exc.value) == f"{field}: {exc.value.reason}"
    # The same through a TOML file.
    path = tmp_path / "bad.toml"
    path.write_text(scene_to_toml(data))
    with pytest.raises(ConfigError) as exc2:
        load_scenario(path)
    assert exc2.value.field == field


def test_messages() -> None:
    data = base()
    data["controller"]["Rr"] = [1, 1]
    with pytest.raises(
        ConfigError, match=r"^controller\.Rr: unknown key \(did you mean 'R'\? expected one of "
    ):
        parse_scenario(data)
    data = base()
    data["controller"]["R"] = [20, "abc"]
    with pytest.raises(ConfigError) as exc:
        parse_scenario(data)
    assert str(exc.value) == "controller.R[1]: expected a number, got 'abc'"
    for bad, words in (
        ([[0, 0], [1, 0], [0.2, 0.2], [0, 1]], "not convex: the boundary turns the other way at vertex 2"),
        ([[0, 0], [1, 0], [0, 1], [1, 1]], "not convex"),  # bow tie: zero net area, not "collinear"
        ([[0, 0], [1, 0], [2, 0]], "collinear"),
    ):
        data = base()
        data["obstacles"][1]["polygon"] = bad
        with pytest.raises(ConfigError) as exc:
            parse_scenario(data)
        assert words in exc.value.reason


BAD_GEOMETRY: list[tuple[str, Mutation, str, str]] = [
    (
        "start inside obstacle",
        _set("robots.0.start", [0.0, 0.6, 0.0]),
        "robots[0].start",
        "inside obstacles[0]",
    ),
    ("start near obstacle", _set("robots.0.start", [-0.1, 0.4, 0.0]), "robots[0].start", "from obstacles[0]"),
    ("goal inside polygon", _set("robots.1.goal", [0.4, -0.6]), "robots[1].goal", "inside obstacles[1]"),
    (
        "starts closer than footprints",
        _set("robots.1.start", [-0.4, 0.0, 0.0]),
        "robots[1].start",
        "closer than their footprints",
    ),
    (
        "goals closer than footprints",
        _set("robots.1.goal", [0.5, 0.1]),
        "robots[1].goal",
        "m from r1's goal, closer than the footprints and the margin allow",
    ),
    ("goal outside arena", _set("robots.0.goal", [1.2, 0.0]), "robots[0].goal", "outside the arena"),
    (
        "waypoint outside arena",
        _set("robots.0.waypoints", [[0.0, -0.3], [1.5, 0.0], [0.6, 0.0]]),
        "robots[0].waypoints[1]",
        "outside the arena",
    ),
    (
        "waypoint in an obstacle",
        _set("robots.0.waypoints", [[0.0, 0.6], [0.6, 0.0]]),
        "robots[0].waypoints[0]",
        "inside obstacles[0]",
    ),
    (
        "waypoint on another robot's goal",
        _set("robots.0.waypoints", [[-0.55, 0.1], [0.6, 0.0]]),
        "robots[0].waypoints[0]",
        "from the goal of 'r2'",
    ),
    ("goal near wall", _set("robots.0.goal", [0.9, 0.0]), "robots[0].goal", "from the arena wall x = 1"),
    (
        "start near wall",
        _set("robots.0.start", [-0.95, 0.0, math.pi]),
        "robots[0].start",
        "arena wall x = -1",
    ),
]


@pytest.mark.parametrize(
    ("mutate", "field", "words"), [c[1:] for c in BAD_GEOMETRY], ids=[c[0] for c in BAD_GEOMETRY]
)
def test_bad_geometry(mutate: Mutation, field: str, words: str) -> None:
    data = copy.deepcopy(base())
    mutate(data)
    scn = parse_scenario(data)
    with pytest.raises(ConfigError) as exc:
        check_geometry(scn, footprint_of(scn))
    assert exc.value.field == field
    assert words in exc.value.reason
    assert "m" in exc.value.reason


def test_geometry_message_units() -> None:
    data = base()
    data["obstacles"] = [{"circle": {"center": [0.0, 0.0], "radius": 0.05}}]
    data["robots"][0]["start"] = [0.06, 0.0, 0.0]  # controlled point (0.10, 0.00), 0.05 m from the disc
    scn = parse_scenario(data)
    with pytest.raises(ConfigError) as exc:
        check_geometry(scn, 0.134)
    assert str(exc.value) == (
        "robots[0].start: controlled point (0.10, 0.00) is 0.050 m from obstacles[0], "
        "less than the footprint radius 0.134 m"
    )


@pytest.mark.parametrize(("gap", "refused"), [(0.30, False), (0.28, False), (0.26, True), (0.0, True)])
def test_a_goal_behind_a_wall_is_refused_unless_a_passage_fits(gap: float, refused: bool) -> None:
    """A wall across the arena leaves a gap of ``gap`` [m] at its top.  The footprint (0.134 m)
    passes a gap of 2 × 0.134 = 0.268 m and more; a narrower one, or none, walls the goals in,
    and the first robot behind it is named."""
    data = base()
    data["obstacles"] = [{"polygon": [[0.3, -1.0], [0.4, -1.0], [0.4, 1.0 - gap], [0.3, 1.0 - gap]]}]
    scn = parse_scenario(data)
    if not refused:
        check_geometry(scn, 0.134)
        return
    with pytest.raises(ConfigError) as exc:
        check_geometry(scn, 0.134)
    assert str(exc.value) == (
        "robots[0].goal: goal (0.60, 0.00) cannot be reached from (-0.56, 0.00): the walls and "
        "obstacles leave no passage for a footprint of radius 0.134 m"
    )


def test_goals_given_together_are_checked_in_place_of_the_ones_they_replace() -> None:
    """``goal_problem`` with a batch: two robots trade goals (each refused alone, as it would park
    on the other's current goal), a robot of the batch counts with its new goal even when it has
    no plan, and the walls and obstacles still come first."""
    from types import SimpleNamespace

    scn = parse_scenario(base())
    fp = 0.134
    g1, g2, g3 = np.array([0.6, 0.0]), np.array([-0.6, 0.0]), np.array([0.0, -0.3])
    plans = {"r1": SimpleNamespace(robot="r1", goal=g1, footprint=fp)}
    assert "r1's goal" in str(goal_problem(scn, fp, g1, [plans["r1"]]))  # r2 alone onto r1's goal
    assert goal_problem(scn, fp, g1, [plans["r1"]], {"r1": g2}) is None  # r1 leaves it, together
    # A robot of the batch without a plan counts with the footprint, at its new goal.
    near = g3 + np.array([2 * fp + GOAL_MARGIN - 1e-3, 0.0])
    why = goal_problem(scn, fp, near, [plans["r1"]], {"r1": g2, "r3": g3})
    assert why is not None and why.startswith("goal (0.28, -0.30) is 0.277 m from r3's goal"), why
    assert goal_problem(scn, fp, near + np.array([2e-3, 0.0]), [plans["r1"]], {"r3": g3, "r1": g2}) is None
    # The batch moves no wall: a goal in an obstacle is refused whatever the others do.
    assert "obstacles[0]" in str(goal_problem(scn, fp, np.array([0.0, 0.6]), [], {"r1": g2}))


def test_a_run_time_goal_needs_a_passage_from_where_the_robot_is() -> None:
    """The one goal rule checks a passage when it is told where the robot is: a wall across the
    arena, no gap, refuses a goal beyond it from one side and takes it from the other."""
    data = base()
    data["obstacles"] = [{"polygon": [[0.3, -1.0], [0.4, -1.0], [0.4, 1.0], [0.3, 1.0]]}]
    data["robots"][0]["goal"] = [-0.6, 0.3]  # the loader's own goals stay on the start's side
    scn = parse_scenario(data)
    fp, goal = 0.134, np.array([0.7, 0.0])
    assert goal_problem(scn, fp, goal, [], at=np.array([-0.6, 0.0])) == (
        "goal (0.70, 0.00) cannot be reached from (-0.60, 0.00): the walls and obstacles leave no "
        "passage for a footprint of radius 0.134 m"
    )
    assert goal_problem(scn, fp, goal, [], at=np.array([0.7, 0.5])) is None
    assert goal_problem(scn, fp, goal, []) is None  # where the robot is not told: not checked


def test_a_goal_in_a_pocket_of_obstacles_is_refused() -> None:
    """Four discs ring the goal of r2, each gap between them narrower than its footprint allows:
    r2's goal is refused; r1's goal, outside the ring, is not the one named."""
    data = base()
    data["robots"][0]["start"] = [-0.6, 0.6, 0.0]  # out of the ring to come
    gx, gy = data["robots"][1]["goal"]
    data["obstacles"] = [
        {"circle": {"center": [gx + dx, gy + dy], "radius": 0.12}}
        for dx, dy in ((0.3, 0.0), (-0.3, 0.0), (0.0, 0.3), (0.0, -0.3))
    ]
    scn = parse_scenario(data)
    with pytest.raises(ConfigError) as exc:
        check_geometry(scn, 0.134)
    assert exc.value.field == "robots[1].goal" and "cannot be reached from" in exc.value.reason
    # The same ring, its discs shrunk so a footprint passes between them: accepted.
    for ob in data["obstacles"]:
        ob["circle"]["radius"] = 0.02
    check_geometry(parse_scenario(data), 0.134)


def test_waypoints_are_a_mission_whose_last_point_is_the_goal() -> None:
    data = base()
    del data["robots"][0]["goal"]
    data["robots"][0]["waypoints"] = [[0.0, -0.3], [-0.2, 0.3], [0.6, 0.0]]
    scn = parse_scenario(data)
    assert scn.robots[0].goal == (0.6, 0.0) and scn.robots[0].waypoints[1] == (-0.2, 0.3)
    assert scn.robots[1].waypoints == ()
    data["robots"][0]["goal"] = [0.6, 0.0]  # the same, said twice
    assert parse_scenario(data) == dataclasses.replace(scn, source=parse_scenario(data).source)
    check_geometry(scn, footprint_of(scn))


def test_a_waypoint_in_a_pocket_of_obstacles_is_refused() -> None:
    """A waypoint ringed by discs with gaps narrower than the footprint: refused, by index."""
    data = base()
    data["robots"][0]["waypoints"] = [[0.0, -0.3], [0.6, 0.0]]
    data["obstacles"] = [
        {"circle": {"center": [dx, -0.3 + dy], "radius": 0.12}}
        for dx, dy in ((0.3, 0.0), (-0.3, 0.0), (0.0, 0.3), (0.0, -0.3))
    ]
    with pytest.raises(ConfigError) as exc:
        check_geometry(parse_scenario(data), 0.134)
    assert exc.value.field == "robots[0].waypoints[0]" and "cannot be reached" in exc.value.reason


def test_distances_of_many_points_are_the_distances_of_each() -> None:
    rng = np.random.default_rng(3)
    pts = rng.uniform(-1.5, 1.5, (400, 2))
    for ob in (Polygon(((0.0, 0.0), (1.0, -0.2), (0.7, 0.9), (-0.1, 0.5))), Circle((0.2, -0.3), 0.4)):
        assert np.allclose(ob.distances(pts), [ob.distance(p) for p in pts], atol=1e-12)


def test_toml_syntax_error(tmp_path: Path) -> None:
    path = tmp_path / "broken.toml"
    path.write_text('name = "x"\nduration = 60.0\n[arena\nbounds = [0, 1, 0, 1]\n')
    with pytest.raises(ConfigError) as exc:
        load_scenario(path)
    assert exc.value.field == "file"
    assert str(path) in exc.value.reason and "line 3" in exc.value.reason


def test_missing_file(tmp_path: Path) -> None:
    path = tmp_path / "nope.toml"
    with pytest.raises(ConfigError) as exc:
        load_scenario(path)
    assert exc.value.field == "file"
    assert str(path) in exc.value.reason


def test_directory_and_non_utf8(tmp_path: Path) -> None:
    with pytest.raises(ConfigError) as exc:
        load_scenario(tmp_path)
    assert exc.value.field == "file"
    path = tmp_path / "latin1.toml"
    path.write_bytes(b'name = "\xe9"\n')
    with pytest.raises(ConfigError) as exc:
        load_scenario(path)
    assert exc.value.field == "file"


def test_bad_preset_override() -> None:
    with pytest.raises(ConfigError) as exc:
        parse_scenario(base(), preset_override="turbo")
    assert exc.value.field == "controller.preset"


def test_toml_nan_literal(tmp_path: Path) -> None:
    path = tmp_path / "nan.toml"
    path.write_text(scene_to_toml(base()).replace("duration = 30.0", "duration = nan"))
    with pytest.raises(ConfigError) as exc:
        load_scenario(path)
    assert exc.value.field == "duration"


# --------------------------------------------------------------------------- obstacle geometry


def test_circle_distance() -> None:
    c = Circle(center=(1.0, 2.0), radius=0.5)
    assert c.distance((1.0, 3.0)) == pytest.approx(0.5)
    assert c.distance((1.0, 2.1)) == 0.0
    assert c.closest_point((4.0, 2.0)) == pytest.approx([1.5, 2.0])
    assert c.closest_point((1.0, 2.2)) == pytest.approx([1.0, 2.5])
    assert np.linalg.norm(c.closest_point((1.0, 2.0)) - np.array(c.center)) == pytest.approx(0.5)


def test_polygon_stored_ccw_and_distance() -> None:
    data = base()
    # Clockwise square with a collinear midpoint on one edge.
    data["obstacles"] = [{"polygon": [[0, 0], [0, 1], [1, 1], [1, 0.5], [1, 0]]}]
    (poly,) = parse_scenario(data).obstacles
    assert isinstance(poly, Polygon)
    v = np.array(poly.vertices)
    area2 = np.sum(v[:, 0] * np.roll(v[:, 1], -1) - np.roll(v[:, 0], -1) * v[:, 1])
    assert area2 > 0
    assert len(poly.vertices) == 4
    assert set(poly.vertices) == {(0.0, 0.0), (1.0, 0.0), (1.0, 1.0), (0.0, 1.0)}
    assert poly.distance((2.0, 0.5)) == pytest.approx(1.0)
    assert poly.distance((2.0, 2.0)) == pytest.approx(math.sqrt(2.0))
    assert poly.distance((0.5, 0.5)) == 0.0
    assert poly.distance((1.0, 0.3)) == 0.0
    assert poly.closest_point((2.0, 2.0)) == pytest.approx([1.0, 1.0])
    assert poly.closest_point((0.5, -1.0)) == pytest.approx([0.5, 0.0])
    assert poly.closest_point((0.9, 0.5)) == pytest.approx([1.0, 0.5])  # inside: nearest boundary point


def test_controlled_point() -> None:
    assert controlled_point((1.0, 2.0, math.pi / 2), 0.04) == pytest.approx([1.0, 2.04])
    assert controlled_point((1.0, 2.0, 0.3), 0.0) == pytest.approx([1.0, 2.0])


def test_robot_ids_and_counts_the_wire_cannot_carry_are_refused_at_load() -> None:
    """A scenario that loads must run: an id the wire rejects (over 32 characters) or more robots
    than a tick and a relayed digest carry is one ConfigError naming the field, not a run whose
    messages are all rejected."""
    from ground.wire import MAX_RELAYED, ROBOT_ID

    ok = base()
    ok["robots"][0]["id"] = "r" * 32
    assert parse_scenario(ok).robots[0].id == "r" * 32 and ROBOT_ID.fullmatch("r" * 32)
    long = base()
    long["robots"][0]["id"] = "r" * 33
    with pytest.raises(ConfigError) as e:
        parse_scenario(long)
    assert e.value.field == "robots[0].id" and "32" in e.value.reason
    crowd = base()
    crowd["arena"]["bounds"] = [-10.0, 10.0, -10.0, 10.0]
    crowd["robots"] = [
        {
            "id": f"r{i}",
            "start": [-9.5 + 0.5 * (i % 36), -9.0 + i // 36, 0.0],
            "goal": [-9.5 + 0.5 * (i % 36), 5.0 + i // 36],
        }
        for i in range(MAX_RELAYED + 1)
    ]
    with pytest.raises(ConfigError) as e:
        parse_scenario(crowd)
    assert e.value.field == "robots" and str(MAX_RELAYED) in e.value.reason
    crowd["robots"] = crowd["robots"][:MAX_RELAYED]
    assert len(parse_scenario(crowd).robots) == MAX_RELAYED


@pytest.mark.parametrize(
    ("patch", "field", "words"),
    [
        ({"controller": {"horizon": 10000}}, "controller.horizon", "<= 200"),
        ({"controller": {"mrpi_max_terms": 10**9}}, "controller.mrpi_max_terms", "<= 1000"),
        ({"controller": {"mrpi_tol": 1e-300}}, "controller.mrpi_tol", ">= 1e-12"),
        ({"arena": {"bounds": [-1e300, 1e300, -1.0, 1.0]}}, "arena.bounds", "at most 20 m"),
        ({"simulation": {"seed": 2**32}}, "simulation.seed", "<= 4294967295"),
        ({"robots": [{"priority": 2**31}]}, "robots[0].priority", "32 bits"),
        ({"robots": [{"priority": -(2**31) - 1}]}, "robots[0].priority", "32 bits"),
    ],
)
def test_inputs_that_cannot_run_are_refused_with_the_field(patch, field, words):
    """Caps on what would exhaust memory or time, and the ranges the wire carries."""
    data = base()
    for key, value in patch.items():
        if key == "robots":
            data["robots"][0].update(value[0])
        else:
            data.setdefault(key, {}).update(value)
    with pytest.raises(ConfigError) as e:
        parse_scenario(data)
    assert e.value.field == field and words in e.value.reason, str(e.value)


def test_a_scenario_must_be_a_small_regular_file(tmp_path):
    """A device, a pipe or an oversized file is refused before it is read (no hang, no
    MemoryError); the field is ``file``."""
    import os

    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    big = tmp_path / "big.toml"
    big.write_bytes(b"#" * (MAX_SCENARIO_BYTES + 1))
    for path, words in (("/dev/zero", "not a regular file"), (fifo, "not a regular file"), (big, "at most")):
        with pytest.raises(ConfigError) as e:
            load_scenario(path)
        assert e.value.field == "file" and words in e.value.reason, str(e.value)


@pytest.mark.parametrize(
    "goal, obstacles, reason",
    [
        ([1.2, 0.0], [], "outside the arena"),
        ([0.95, 0.0], [], "from the arena wall"),
        ([0.0, 0.3], [{"circle": {"center": [0.0, 0.35], "radius": 0.1}}], "inside obstacles[0]"),
        ([0.0, 0.3], [{"circle": {"center": [0.0, 0.5], "radius": 0.1}}], "from obstacles[0]"),
        ([0.6, 0.0], [{"polygon": [[0.3, -1.0], [0.4, -1.0], [0.4, 1.0], [0.3, 1.0]]}], "cannot be reached"),
        ([0.55, 0.05], [], "from r1's goal"),
    ],
)
def test_the_loader_and_the_run_time_rule_refuse_a_goal_with_one_text(goal, obstacles, reason) -> None:
    """One goal rule: a goal the loader refuses (robots[1].goal, or robots[0]'s for the walls) is
    refused by :func:`goal_problem` with the very same text, for the same robot told where it
    starts and the goals listed before it as the others' plans."""
    from types import SimpleNamespace

    from ground.geometry import controlled_point

    data = base()
    who = 0 if reason == "cannot be reached" else 1
    data["robots"][who]["goal"] = goal
    data["obstacles"] = obstacles
    scn = parse_scenario(data)
    fp = 0.134
    with pytest.raises(ConfigError) as exc:
        check_geometry(scn, fp)
    assert exc.value.field == f"robots[{who}].goal" and reason in exc.value.reason, exc.value
    at = controlled_point(scn.robots[who].start, scn.controller.lookahead)
    earlier = [
        SimpleNamespace(robot=r.id, goal=np.asarray(r.goal, float), footprint=fp) for r in scn.robots[:who]
    ]
    assert goal_problem(scn, fp, np.asarray(goal, float), earlier, at=at) == exc.value.reason
