"""What an agent says after a controller step: its plan for everyone, its command for its robot.

The agent process publishes these (:mod:`agent.node`), and ``fleet simulate`` hands the same
plans to the safety judge (:mod:`fleet.simulate`), so that both judge the same messages.
"""

from __future__ import annotations

from agent.controller import StepOutput, TubeMPC
from ground.geometry import Array
from ground.wire import Command, Plan


def plan_message(robot: str, k: int, ctrl: TubeMPC, out: StepOutput, late: int = 0) -> Plan:
    """The plan ``robot`` committed at step ``k`` (``out``, the step's output of ``ctrl``);
    ``late``: the places its agent has heard over the lag bound late so far.  It says which discs
    the step kept clear of, and which robot's covers the goal (docs/method.md §6.4)."""
    Ts = ctrl.params.Ts
    discs = {
        h.id: (h.kind, h.rest, float(h.centre[0]), float(h.centre[1]), float(h.radius)) for h in out.hazards
    }
    return Plan(
        robot=robot, step=k, t0=(k + 1) * Ts, Ts=Ts, committed=out.committed, nominal=out.plan,
        footprint=ctrl.r, priority=ctrl.priority, rank=ctrl.rank, phase=ctrl.phase, target=out.target,
        phase_age=ctrl.phase_age, late=late, discs=discs, blocked=out.blocked, no_room=out.no_room,
        goal=ctrl.goal, status=out.status, solve_time=out.solve_time, tube_ok=out.tube_ok,
    )  # fmt: skip


def command_message(
    robot: str, k: int, ctrl: TubeMPC, out: StepOutput, follow: bool = True, a: Array | None = None,
    brake: bool = False,
) -> Command:  # fmt: skip
    """The command of step ``k``: the acceleration u = v̂ + K(x − x̂) (``out.a``, or ``a`` (2,)
    [m/s²] for a plan made a step ahead, applied to the measurement at its step), and the shifted
    candidate with the gain K for the robot side to follow if later commands miss their deadline
    (``follow`` False: nothing to follow, e.g. while the agent holds without poses).  ``brake``:
    the robot side brakes the robot instead (the agent holds without poses)."""
    u = out.a if a is None else a
    return Command(
        robot=robot, step=k, ax=float(u[0]), ay=float(u[1]), fallback=follow, x_next=out.x_next,
        v_next=out.v_next, K=ctrl.design.K, brake=brake,
    )  # fmt: skip
