"""The experiment API (:mod:`fleet.experiment.api`) on the in-process simulator: each method's contract, seen
from a script, and the examples run as a user runs them."""

from __future__ import annotations

import importlib.util
import itertools
import json
import math
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

from fleet import Event, Fleet, FleetError, GoalRefused
from ground.geometry import controlled_point
from ground.scenario import GOAL_TOLERANCE, ConfigError, settle_samples

ROOT = Path(__file__).resolve().parents[2]
SWAP4 = ROOT / "scenarios" / "swap_4.toml"
OBSTACLE4 = ROOT / "scenarios" / "obstacle_four.toml"


def _truth_error(fleet: Fleet, rid: str) -> float:
    """The true controlled point's distance to the robot's goal [m]."""
    b = fleet._b.sample()  # the true pose, which a script does not see (the judge does)
    pt = controlled_point(b.truth[rid], fleet.scenario.controller.lookahead)
    return float(np.linalg.norm(pt - np.array(fleet.goals()[rid])))


def test_wait_arrived_returns_at_the_first_settled_sample(tmp_path):
    """wait_arrived runs the clock until every robot has stayed within the goal tolerance for the
    settle time, no longer: one sample earlier, not every robot had."""
    with Fleet.launch(SWAP4, seed=3, processes=False, out=tmp_path) as fleet:
        assert fleet.step == 0 and fleet.time == 0.0
        assert fleet.wait_arrived(timeout=240)
        assert fleet.arrived() and all(_truth_error(fleet, r) <= GOAL_TOLERANCE for r in fleet.ids)
        k = fleet.step
        arrivals = [e for e in fleet.events() if e.kind == "arrived"]
        assert sorted(e.robot for e in arrivals) == sorted(fleet.ids)
        assert max(e.step for e in arrivals) == k  # the last arrival ended the wait
        n = settle_samples(fleet.Ts)
        for rid in fleet.ids:  # each settled exactly n samples before its arrival event
            errs = fleet._progress[rid].errors
            at = next(e.step for e in arrivals if e.robot == rid)
            assert all(v <= GOAL_TOLERANCE for v in errs[at - n + 1 : at + 1])
            assert errs[at - n] > GOAL_TOLERANCE
        assert fleet.wait_arrived(timeout=0) and fleet.step == k  # already there: no step taken
    s = fleet.summary
    assert s is not None and s["all_goals_reached"] and s["collisions"] == 0
    assert json.loads((tmp_path / "summary.json").read_text())["steps"] == s["steps"] == k
    assert (tmp_path / "trace.npz").exists()


def test_timeout_returns_false_and_the_fleet_runs_on(tmp_path):
    with Fleet.launch(SWAP4, seed=3, processes=False, out=tmp_path) as fleet:
        assert fleet.wait_arrived(timeout=1.0) is False
        assert fleet.step == 10 and fleet.time == pytest.approx(1.0)  # seconds of the fleet's clock
        assert fleet.wait_arrived(["r1"], timeout=120) is True
        assert fleet.arrived(["r1"])
        k = fleet.step
        fleet.wait(2.0)
        assert fleet.step == k + 20
    assert fleet.summary is not None and fleet.summary["steps"] >= 10


def test_goto_moves_one_robot_and_it_settles_there(tmp_path):
    with Fleet.launch(SWAP4, seed=3, processes=False, out=tmp_path) as fleet:
        assert fleet.wait_arrived(timeout=240)
        fleet.goto({"r1": (0.3, 0.2)})
        assert fleet.goals()["r1"] == (0.3, 0.2) and not fleet.arrived(["r1"])
        assert fleet.wait_arrived(["r1"], timeout=60)
        assert _truth_error(fleet, "r1") <= GOAL_TOLERANCE
        x, y = fleet.points()["r1"]
        assert math.hypot(x - 0.3, y - 0.2) < 3 * GOAL_TOLERANCE  # measured: the camera's noise on top
    s = fleet.summary
    assert s is not None and s["robots"]["r1"]["goal"] == [0.3, 0.2] and s["robots"]["r1"]["reached_goal"]


@pytest.mark.parametrize(
    ("scenario", "goals", "robot", "reason"),
    [
        (SWAP4, {"r1": (5.0, 5.0)}, "r1", "outside the arena"),
        (SWAP4, {"r1": (0.97, 0.0)}, "r1", "x = 1"),  # within the footprint of a wall
        (OBSTACLE4, {"r2": (0.05, 0.1)}, "r2", "obstacle"),
        (SWAP4, {"r1": (0.05, 0.75)}, "r1", "r4's goal"),  # next to r4's goal (0, 0.8)
        (SWAP4, {"r9": (0.0, 0.0)}, "r9", "unknown robot id"),
        # A batch whose two goals are too close to each other: neither is taken.
        (SWAP4, {"r2": (0.3, -0.3), "r3": (0.3, -0.35)}, "r2", "r3's goal"),
    ],
)
def test_a_refused_goto_names_the_robot_and_changes_nothing(tmp_path, scenario, goals, robot, reason):
    with Fleet.launch(scenario, seed=1, processes=False, out=tmp_path) as fleet:
        fleet.wait(0.5)
        before = fleet.goals()
        with pytest.raises(GoalRefused) as info:
            fleet.goto(goals)
        assert info.value.robot == robot and reason in info.value.reason and str(info.value).startswith(robot)
        assert fleet.goals() == before
        fleet.wait(0.2)
        assert fleet.goals() == before  # nothing was queued for a later step either
        assert [e.kind for e in fleet.events() if e.robot == robot] == ["refused"]


def test_a_swap_given_as_one_batch_is_accepted(tmp_path):
    """Two robots may take each other's goals in one call: each new goal is checked against the
    other's new goal, not its old one."""
    with Fleet.launch(SWAP4, seed=3, processes=False, out=tmp_path) as fleet:
        g = fleet.goals()
        with pytest.raises(GoalRefused):
            fleet.goto({"r1": g["r3"]})  # alone, it lands on r3's goal
        fleet.goto({"r1": g["r3"], "r3": g["r1"]})
        assert fleet.goals()["r1"] == g["r3"] and fleet.goals()["r3"] == g["r1"]
        assert fleet.wait_arrived(["r1", "r3"], timeout=120)


def test_formation_assigns_least_total_distance(tmp_path):
    pts = [(0.35, 0.35), (-0.35, 0.35), (-0.35, -0.35), (0.35, -0.35)]
    with Fleet.launch(SWAP4, seed=3, processes=False, out=tmp_path) as fleet:
        fleet.wait(3.0)
        here = fleet.points()
        centre, heading = (0.1, -0.05), 0.3
        got = fleet.formation(pts, centre=centre, heading=heading)
        c, s = math.cos(heading), math.sin(heading)
        world = [(centre[0] + c * x - s * y, centre[1] + s * x + c * y) for x, y in pts]
        assert np.allclose(sorted(got.values()), sorted(world), atol=1e-12)  # rotated, then moved
        cost = lambda a: sum(math.dist(here[r], a[r]) for r in a)  # noqa: E731
        best = min(cost(dict(zip(fleet.ids, p, strict=True))) for p in itertools.permutations(world))
        assert cost(got) == pytest.approx(best, abs=1e-12)
        assert fleet.goals() == got
        assert fleet.wait_arrived(timeout=120)
        with pytest.raises(FleetError, match="3 points for 4 robots"):
            fleet.formation(pts[:3])
        assert fleet.formation([(0.0, 0.8), (0.0, -0.8)], robots=["r1", "r2"]).keys() == {"r1", "r2"}


def test_mission_visits_waypoints_in_order(tmp_path):
    loop = [(0.4, 0.4), (-0.4, 0.4), (-0.4, -0.4)]
    with Fleet.launch(
        ROOT / "scenarios" / "paper_two_robots.toml", seed=1, processes=False, out=tmp_path
    ) as fleet:
        fleet.mission({"r1": loop})
        assert fleet.goals()["r1"] == loop[0]
        assert fleet.wait_arrived(["r1"], timeout=120)
        hits = [e for e in fleet.events() if e.robot == "r1" and e.kind in ("waypoint", "arrived")]
        assert [e.kind for e in hits] == ["waypoint", "waypoint", "arrived"]
        assert [e.detail for e in hits] == [f"({x:.3f}, {y:.3f})" for x, y in loop]
        assert [e.step for e in hits] == sorted(e.step for e in hits)
        assert fleet.waypoints_reached()["r1"] == 3 and fleet.waypoints_reached()["r2"] == 0
        with pytest.raises(GoalRefused, match="outside the arena"):
            fleet.mission({"r2": [(0.0, 0.0), (3.0, 0.0)]})  # every waypoint checked first
    assert fleet.summary is not None and fleet.summary["waypoints_reached"] == {"r1": 3, "r2": 0}


def test_events_carry_step_and_robot(tmp_path):
    with Fleet.launch(SWAP4, seed=3, processes=False, out=tmp_path) as fleet:
        fleet.wait_arrived(timeout=240)
        evs = list(fleet.events())
        assert evs and all(
            isinstance(e, Event) and e.robot in fleet.ids and 0 <= e.step <= fleet.step for e in evs
        )
        assert list(fleet.events()) == []  # each event once


def test_the_same_script_gives_the_same_run(tmp_path):
    def script(out: Path) -> list[tuple[float, ...]]:
        with Fleet.launch(SWAP4, seed=5, processes=False, out=out) as fleet:
            fleet.wait(2.0)
            fleet.goto({"r2": (0.2, 0.2)})
            fleet.wait_arrived(["r2"], timeout=60)
            return [fleet.poses()[r] for r in fleet.ids]

    assert script(tmp_path / "a") == script(tmp_path / "b")


def test_after_close_the_fleet_refuses_work_and_an_exception_still_closes(tmp_path):
    with pytest.raises(RuntimeError, match="the script failed"):
        with Fleet.launch(SWAP4, seed=3, processes=False, out=tmp_path) as fleet:
            fleet.wait(1.0)
            raise RuntimeError("the script failed")
    assert fleet.summary is not None and fleet.summary["steps"] == 10
    assert (tmp_path / "summary.json").exists()
    with pytest.raises(FleetError, match="closed"):
        fleet.goto({"r1": (0.0, 0.0)})
    with pytest.raises(FleetError, match="closed"):
        fleet.wait_arrived()
    assert fleet.close() is fleet.summary


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [({"clock": "wallclock"}, "clock"), ({"clock": "realtime", "processes": False}, "clock"),
     ({"processes": False, "topology": "star"}, "topology")],
)  # fmt: skip
def test_bad_launch_arguments_name_the_field(kwargs, field):
    with pytest.raises(ConfigError) as info:
        Fleet.launch(SWAP4, **kwargs)
    assert info.value.field == field


def _example(name: str) -> ModuleType:
    spec = importlib.util.spec_from_file_location(name, ROOT / "examples" / f"{name}.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.parametrize("name", ["formations", "patrol", "follow"])
def test_examples_run_in_process(tmp_path, name, capsys):
    summary = _example(name).main(processes=False, out=str(tmp_path))
    assert summary["collisions"] == 0 and summary["all_goals_reached"]
    out = capsys.readouterr().out
    if name == "formations":
        assert [ln.split()[4] for ln in out.splitlines()] == ["line", "circle", "square"]
    elif name == "patrol":
        assert summary["waypoints_reached"] == {"r1": 9, "r2": 9}
    else:
        assert out.count("done") == 3


def test_a_scenario_with_missions_runs_them_from_the_command_line(tmp_path, capsys):
    """`fleet simulate` follows the waypoints of the scenario's robots, as a script does; the
    summary counts them, the final goal once settled."""
    from fleet.cli import main

    out = tmp_path / "patrol"
    assert main(["simulate", str(ROOT / "scenarios" / "patrol_two.toml"), "--out", str(out)]) == 0
    assert "waypoints reached: {'r1': 5, 'r2': 5}" in capsys.readouterr().out
    summary = json.loads((out / "summary.json").read_text())
    assert summary["waypoints_reached"] == {"r1": 5, "r2": 5} and summary["all_goals_reached"]
    assert summary["collisions"] == 0
    # Each robot drove round the square, not straight to its goal: its path is at least the
    # square's three sides and the way to and from it.
    for rid in ("r1", "r2"):
        assert summary["robots"][rid]["path_length_m"] > 3 * 0.8 + 0.5


def test_the_readme_script_runs_as_it_stands(tmp_path, monkeypatch, capsys):
    """The README's script, on the in-process simulator (the process fleet runs the same
    script in tests/system/test_api_processes.py)."""
    text = (ROOT / "README.md").read_text()
    code = text.split("```python\n", 1)[1].split("```", 1)[0]
    assert "Fleet.launch(" in code and len(code.strip().splitlines()) <= 12
    launch = Fleet.launch.__func__  # type: ignore[attr-defined]
    monkeypatch.setattr(
        Fleet,
        "launch",
        classmethod(lambda cls, *a, **k: launch(cls, *a, **{**k, "processes": False, "out": tmp_path})),
    )
    monkeypatch.chdir(ROOT)
    exec(compile(code, "README.md", "exec"), {})
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("True {") and lines[-1] == "True"


def test_a_goal_ringed_by_obstacles_is_refused(tmp_path):
    """Four discs ring a point, the gaps between them narrower than the footprint: a goal
    inside the ring is clear of every disc, yet cannot be reached; one outside it is taken."""
    ring = "".join(
        f"\n[[obstacles]]\ncircle = {{ center = [{x}, {y}], radius = 0.12 }}\n"
        for x, y in ((0.3, 0.55), (-0.3, 0.55), (0.0, 0.85), (0.0, 0.25))
    )
    path = tmp_path / "ring.toml"
    path.write_text((ROOT / "scenarios" / "paper_two_robots.toml").read_text() + ring)
    with Fleet.launch(path, seed=1, processes=False, out=tmp_path / "run") as fleet:
        before = fleet.goals()
        with pytest.raises(GoalRefused, match=r"cannot be reached from \(-?\d\.\d\d, -?\d\.\d\d\)") as info:
            fleet.goto({"r1": (0.0, 0.55)})
        assert info.value.robot == "r1" and fleet.goals() == before
        fleet.goto({"r1": (0.6, -0.5)})
        assert fleet.wait_arrived(["r1"], timeout=60)


def test_a_goal_given_at_the_last_sample_goes_in_the_next_goals_batch():
    """A process fleet plans a step ahead, so the plan that carries a goal given at sample k may
    still be on its way when sample k + 1 is in: an agent checking a goal given then against
    that robot's newest plan would see the goal before, and could refuse a goal the script's
    own records accept (or accept one they refuse), depending on timing.  So each goal's batch
    carries the other robots' goals given at the last sample too, in place of their plans';
    older ones are in the plans already.  (A real loopback session; the queries recorded.)"""
    import zenoh

    from fleet.experiment.script import ProcessFleet
    from ground.scenario import load_scenario
    from ground.wire import Keys
    from transport.net import NetConfig, free_port, loopback

    scn = load_scenario(SWAP4)
    session = zenoh.open(NetConfig(listen=[loopback(free_port())]).zenoh())
    fleet = ProcessFleet(scn, session, Keys("batchtest"))
    asked: list[tuple[str, tuple[float, ...], dict[str, tuple[float, ...]]]] = []

    def ask(rid, goal, batch):
        asked.append((rid, tuple(goal), {r: tuple(g) for r, g in batch.items()}))
        return True, ""

    fleet._ask = ask  # type: ignore[method-assign]
    try:
        a, g, b = (0.3, 0.2), (0.0, 0.3), (-0.3, -0.2)
        fleet.k = 5
        assert fleet.send({"r1": np.array(g)}) == {}
        fleet.k = 6  # the next sample: r1's plan with g may not be in yet
        assert fleet.send({"r2": np.array(a), "r3": np.array(b)}) == {}
        assert asked[1:] == [("r2", a, {"r1": g, "r3": b}), ("r3", b, {"r1": g, "r2": a})]
        fleet.k = 8  # r1's plans carry g by now; r2's and r3's goals of sample 6 too
        assert fleet.send({"r4": np.array(a)}) == {}
        assert asked[-1] == ("r4", a, {})
    finally:
        fleet.close()
        session.close()
