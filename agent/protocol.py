"""The step protocol, once, for the agent process and the in-process simulator alike.

What an agent says after a controller step (its plan for everyone, its command for its robot),
and the three moves of a step that both drivers make the same way (docs/design.md, "Delay
compensation" and "Missed deadlines"):

* :func:`plan_ahead` — the plan of step k + 1, made during step k from the prediction
  x^p = A x_k + B u_k (``predicted``: constraint (a) tightened by the ancillary law's reach);
* :class:`PlannedAhead` and :meth:`PlannedAhead.command_for` — at tick k + 1 only the ancillary
  law u = v̂ + K(x − x̂) of that plan is applied to the measurement, and put;
* :func:`candidate_input` — when the robot side did not apply a command, the input it gave
  instead by following the shifted candidate of its last applied command.

``agent.node`` (the process) and ``fleet.running.simulate`` (the whole fleet in one process) both call
these, so that a lockstep ``fleet run`` and ``fleet simulate`` make the same plans bit for bit.
Nothing here touches the transport.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from agent.controller import TUBE_TOL, StepOutput, TubeMPC
from agent.coordination import Hazard, NeighbourInfo
from ground.geometry import Array
from ground.model import ancillary_law, chain_input
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


def candidate_input(ctrl: TubeMPC, applied: StepOutput | None, j: int, k: int, x: Array) -> Array | None:
    """The acceleration (2,) [m/s²] a robot side gave at step k − 1 when it followed the shifted
    candidate of its last applied command, that of step j (``applied``: its controller output),
    from the state ``x`` (4,) [m, m/s] of step k − 1; None if there is nothing to follow (the
    robot braked)."""
    if applied is None:
        return None
    d = ctrl.design
    return chain_input(applied.x_next, applied.v_next, k - j - 1, x, d.A, d.B, d.K)


def plan_ahead(
    ctrl: TubeMPC,
    x: Array,
    a: Array,
    x_hat: Array,
    neighbours: Sequence[NeighbourInfo],
    hazards: Sequence[Hazard],
    seen: Sequence[NeighbourInfo] = (),
) -> tuple[StepOutput, bool]:
    """The plan of the next step, made now from the prediction A x + B a (``x`` (4,) [m, m/s] the
    state measured at this step, ``a`` (2,) [m/s²] the command applied at it), against the
    neighbours' plans of this step (:meth:`TubeMPC.step` with ``predicted``); and whether the tube
    held at ``x`` about ``x_hat`` (4,), the nominal state the command was applied about: all a
    plan made ahead can tell of the tube (its ``tube_ok``, published before the next
    measurement)."""
    d = ctrl.design
    tube_ok = d.contains_error(x - x_hat, TUBE_TOL)
    out = ctrl.step(np.asarray(d.A @ x + d.B @ a), neighbours, hazards, predicted=True, seen=seen)
    return out, tube_ok


def plan_ahead_message(
    robot: str, k: int, ctrl: TubeMPC, out: StepOutput, tube_ok: bool, late: int = 0
) -> Plan:
    """The plan of step ``k`` made a step ahead (:func:`plan_ahead`), with the tube's word on the
    measurement it was made after."""
    return replace(plan_message(robot, k, ctrl, out, late), tube_ok=tube_ok)


@dataclass(frozen=True)
class PlannedAhead:
    """A plan made a step ahead, waiting for its tick: what its command needs."""

    step: int
    x_hat: Array
    """The plan's nominal state x̂ of ``step`` (4,) [m, m/s], world frame."""
    v_hat: Array
    """Its nominal input v̂ of ``step`` (2,) [m/s²]."""
    K: Array
    """The ancillary gain (2, 4) [1/s², 1/s]."""
    command: Command
    """The command of ``step``, its acceleration still to fill in."""
    out: StepOutput
    """The controller's output the plan came from."""

    @classmethod
    def of(cls, robot: str, k: int, ctrl: TubeMPC, out: StepOutput) -> PlannedAhead:
        """The plan of step ``k`` that ``ctrl`` has just made ahead (``out``)."""
        command = command_message(robot, k, ctrl, out, a=np.zeros(2))
        return cls(k, ctrl.xi[0:4].copy(), ctrl.xi[4:6].copy(), ctrl.design.K, command, out)

    def command_for(self, x: Array) -> tuple[Command, Array]:
        """The command for the state ``x`` (4,) [m, m/s] measured at its step, and the
        acceleration u = v̂ + K(x − x̂) (2,) [m/s²] it carries."""
        a = ancillary_law(x, self.x_hat, self.v_hat, self.K)
        return replace(self.command, ax=float(a[0]), ay=float(a[1])), a
