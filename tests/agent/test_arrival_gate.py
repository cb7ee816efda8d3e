"""A robot keeps to the order of arrival (``TubeMPC.gate``, ground.arrival): it steers to its
wait point until the robots it waits for are past its goal, waits there yielding to those that
move, and then goes home; a goal given at run time ends the gate (docs/method.md §7)."""

from __future__ import annotations

import numpy as np

from agent.controller import TubeMPC
from agent.coordination import NeighbourInfo, precedence
from agent.tube import require_admissible, synthesize
from fleet.running.scenes import pocket
from ground.arrival import arrival
from ground.geometry import controlled_point
from ground.scenario import PARKED_RADIUS, parse_scenario
from ground.wire import PARKED, UNDER_WAY, WAITING


def _pocket() -> tuple:
    scn = parse_scenario(pocket(0.30, robots=3))
    design = require_admissible(synthesize(scn.controller, scn.arena))
    gates = arrival(scn, design.footprint).gates
    ell = scn.controller.lookahead
    specs = {r.id: r for r in scn.robots}
    starts = {rid: controlled_point(r.start, ell) for rid, r in specs.items()}
    goals = {rid: np.asarray(r.goal, dtype=float) for rid, r in specs.items()}
    return scn, design, gates, starts, goals


def _ctrl(scn, design, gates, starts, goals, rid: str, at: np.ndarray | None = None) -> TubeMPC:
    rank = [r.id for r in scn.robots].index(rid)
    point = starts[rid] if at is None else at
    return TubeMPC(
        design, point, goals[rid], scn.arena, obstacles=scn.obstacles, rank=rank, gate=gates.get(rid)
    )  # fmt: skip


def _info(design, rid: str, point: np.ndarray, goal: np.ndarray, phase: int = UNDER_WAY) -> NeighbourInfo:
    return NeighbourInfo(
        rid, np.asarray(point, float), design.footprint, rank=0, goal=goal, target=goal, phase=phase
    )


def test_the_middle_robot_steers_to_its_wait_point_until_the_deepest_is_past() -> None:
    """In a pocket of three, the middle robot's target is its wait point while the deepest robot
    is outside the pocket or at its mouth, and its goal (by the grid path) once the deepest is
    past the middle goal's disc; the gate then stays open."""
    scn, design, gates, starts, goals = _pocket()
    ctrl = _ctrl(scn, design, gates, starts, goals, "r2")
    wait = gates["r2"].wait_point
    for where in (starts["r1"], goals["r3"]):  # outside the pocket, then at its mouth
        target, _ = ctrl.steer([_info(design, "r1", where, goals["r1"])])
        assert ctrl.gate is not None
        assert np.linalg.norm(target - wait) < np.linalg.norm(target - goals["r2"])
    below = goals["r1"] + np.array([0.0, -0.01])  # under way still, below the middle goal's disc
    ctrl.steer([_info(design, "r1", below, goals["r1"])])
    assert ctrl.gate is None
    target, _ = ctrl.steer([_info(design, "r1", starts["r1"], goals["r1"])])  # seen past once: enough
    assert ctrl.gate is None and np.linalg.norm(target - wait) > 0.1


def test_a_robot_seen_parked_opens_the_gate_and_one_unheard_of_does_not() -> None:
    """The mouth's robot waits for both others: hearing only one of them keeps it waiting; the
    other seen parked opens the gate, wherever its point (here outside the pocket, not past)."""
    scn, design, gates, starts, goals = _pocket()
    ctrl = _ctrl(scn, design, gates, starts, goals, "r3")
    gate = gates["r3"]
    assert not gate.past(0, starts["r1"]) and not gate.past(1, starts["r2"])
    ctrl.steer([_info(design, "r1", starts["r1"], goals["r1"], PARKED)])
    assert ctrl.gate is not None
    ctrl.steer([_info(design, "r2", starts["r2"], goals["r2"], UNDER_WAY)])
    assert ctrl.gate is not None  # heard, but neither past nor parked
    ctrl.steer([_info(design, "r2", starts["r2"], goals["r2"], PARKED)])
    assert ctrl.gate is None


def test_a_robot_whose_agent_is_gone_is_not_waited_for_and_a_braked_one_is() -> None:
    """A dead robot's disc (its agent gone) counts as past; a braked robot's does not: it
    starts again where it is."""
    from agent.coordination import Hazard

    scn, design, gates, starts, goals = _pocket()
    for kind, opens in (("braked", False), ("dead", True)):
        ctrl = _ctrl(scn, design, gates, starts, goals, "r2")
        disc = Hazard("r1", starts["r1"], design.footprint, kind=kind)
        ctrl.step(np.r_[starts["r2"][0], 0.0, starts["r2"][1], 0.0], [], [disc])
        assert (ctrl.gate is None) == opens, kind


def test_an_agent_joining_with_its_robot_at_its_goal_drops_the_gate() -> None:
    """A restarted agent whose robot is already home does not go back to its wait point; one
    whose robot is anywhere else keeps the gate."""
    scn, design, gates, starts, goals = _pocket()
    ctrl = _ctrl(scn, design, gates, starts, goals, "r2")
    ctrl.reset(gates["r2"].wait_point)
    assert ctrl.gate is not None
    ctrl.reset(goals["r2"] + np.array([0.01, 0.0]))
    assert ctrl.gate is None


def test_at_its_wait_point_a_robot_is_waiting_and_goes_after_every_robot_that_moves() -> None:
    """Standing at its wait point, the robot's phase is waiting, which every phase that moves
    goes before and which goes before none of them; away from it, under way."""
    scn, design, gates, starts, goals = _pocket()
    wait = gates["r2"].wait_point
    there = _ctrl(scn, design, gates, starts, goals, "r2", at=wait)
    assert there.phase == WAITING
    away = _ctrl(scn, design, gates, starts, goals, "r2", at=wait + np.array([PARKED_RADIUS + 0.01, 0.0]))
    assert away.phase == UNDER_WAY
    me = precedence(there.phase, 0, 0, 0)
    for phase in (0, 1):
        assert precedence(phase, 10**6, -(10**6), 10**6) < me


def test_a_goal_given_at_run_time_ends_the_gate() -> None:
    """The scenario's order concerns the scenario's goals: a new goal drops the gate."""
    scn, design, gates, starts, goals = _pocket()
    ctrl = _ctrl(scn, design, gates, starts, goals, "r3")
    ctrl.set_goal(np.array([0.6, 0.6]))
    target, _ = ctrl.steer([])
    assert ctrl.gate is None and ctrl.phase == UNDER_WAY
    assert np.linalg.norm(target - gates["r3"].wait_point) > 0.1
