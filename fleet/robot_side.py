"""The robot side's rule for each step: the command, the shifted candidate, or the brake.

Shared by the simulated tracker (:mod:`tracker.sim`, which is the robot side of simulated
robots) and by ``epuck_link`` (the robot side of an e-puck), so that a robot behaves the same
whether it is simulated or real when its agent's command misses the deadline
(docs/runtime-notes.md, "Missed deadlines").
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from agent.controller import chain_input
from fleet.runtime import remember_steps
from fleet.wire import Applied, Command

COMMAND, CANDIDATE, HELD, BRAKED = "command", "candidate", "held", "braked"


class RobotSide:
    """What a robot side applies to one robot each step (DESIGN §4 and
    docs/runtime-notes.md, "Missed deadlines"): the agent's command when it came in time;
    else the ancillary law on the shifted candidate of the last command applied; braking
    when the agent is dead, has not been heard from for ``watchdog`` [s], or the candidate
    is used up.  The simulated tracker keeps one per robot; so does ``epuck_link``, through
    :class:`LinkDeadline`.  With ``drives`` False (the tracker of robots whose ``epuck_link``
    decides) a missing command only holds the last acceleration."""

    def __init__(self, design: Any, watchdog: float, drives: bool):
        self.design = design
        self.watchdog = watchdog
        self.drives = drives
        self.applied: Command | None = None
        """The last command applied."""
        self.following = False
        """Not braked since that command: its candidate may be followed."""
        self.quiet = 0
        """Steps without a command of this or the previous step [steps]."""
        self.last_a = np.zeros(2)
        """The acceleration applied over the last step (2,) [m/s²], world frame."""
        self.unexecuted: set[int] = set()
        """Recent steps whose command was not applied: their plans were never executed."""

    @property
    def applied_step(self) -> int:
        """The step of the last command applied, −1 if none: no later plan was executed."""
        return -1 if self.applied is None else self.applied.step

    def decide(
        self, k: int, cmd: Command | None, newest: Command | None, alive: bool, x: np.ndarray | None
    ) -> tuple[str, np.ndarray | None, str]:
        """What to apply over step k: (COMMAND | CANDIDATE | HELD | BRAKED, the acceleration
        (2,) [m/s²] or None when BRAKED (the caller brakes the plant), why it is braked).

        ``cmd`` is the agent's command of step k if it came in time, ``newest`` its latest
        command of any step, ``alive`` whether its liveliness token is up, ``x`` (4,)
        [m, m/s] the state measured for it at step k (for the candidate).  A command of
        step k − 1 that came after its deadline counts as heard for the watchdog: its agent
        is alive and one step behind (a hung agent sends nothing)."""
        heard = cmd is not None or (newest is not None and newest.step >= k - 1)
        self.quiet = 0 if heard else self.quiet + 1
        if cmd is None and self.drives:
            remember_steps(self.unexecuted, (k,), k)
        if not alive or self.quiet * self.design.params.Ts > self.watchdog:
            self.brake()
            return (
                BRAKED,
                None,
                "its agent is not alive" if not alive else f"no command for {self.watchdog} s",
            )
        if cmd is not None:
            self.applied, self.following = cmd, True
            self.last_a = np.array([cmd.ax, cmd.ay])
            return COMMAND, self.last_a, ""
        if not self.drives:
            return HELD, self.last_a, ""
        last, d = self.applied, self.design
        a = None
        if last is not None and last.fallback and self.following and x is not None:
            a = chain_input(last.x_next, last.v_next, k - last.step - 1, x, d.A, d.B, d.K)
        if a is None:
            self.brake()
            return BRAKED, None, "nothing left to follow"
        return CANDIDATE, a, ""

    def brake(self) -> None:
        """Braking leaves the plan: nothing is followed after it until a command is applied."""
        self.following = False


class LinkDeadline:
    """``epuck_link``'s deadline: per step, the command if it came in time, else the
    candidate or the brake (:class:`RobotSide`), decided by the link's own clock.

    Step k starts when the link receives tick k; its command must arrive within
    ``deadline`` [s] after that.  A command that comes later is not applied: the robot
    keeps to what was decided, and the :class:`~fleet.wire.Applied` report (one per step,
    at the decision) lets the tracker tell the agent and its neighbours in tick k + 1.
    Times are the caller's monotonic clock [s]."""

    def __init__(self, robot: str, design: Any, watchdog: float, deadline: float):
        self.robot = robot
        self.side = RobotSide(design, watchdog, drives=True)
        self.deadline = deadline
        self.step: int | None = None
        """The step of the last tick received (None before the first)."""
        self.due = math.inf
        """When the command of ``step`` is due [s]."""
        self.decided = True
        self.x: np.ndarray | None = None
        """The state measured at the tick (4,) [px, vx, py, vy] in m, m/s, world frame."""

    @property
    def wake_at(self) -> float:
        """When the link must look again [s]: the deadline of an undecided step, else never."""
        return math.inf if self.decided else self.due

    def tick(
        self, k: int, now: float, x: np.ndarray | None, newest: Command | None, alive: bool
    ) -> list[tuple[str, np.ndarray | None, Applied]]:
        """Tick k received at ``now`` with the state ``x`` measured then.  Returns the
        decisions taken: the previous step's, if its deadline had not passed yet (it is
        taken without a command), and step k's, if its command (``newest``) came first."""
        out = []
        if not self.decided and self.step is not None and k > self.step:
            out.append(self._decide(None, newest, alive))
        self.step, self.due, self.decided, self.x = k, now + self.deadline, False, x
        if newest is not None and newest.step == k:
            out.append(self._decide(newest, newest, alive))
        return out

    def command(self, cmd: Command, now: float, alive: bool) -> tuple[str, np.ndarray | None, Applied] | None:
        """A command received at ``now``: applied if it is of the current step, in time,
        and the step is not decided yet; otherwise None (too late, or not ours to take)."""
        if self.decided or cmd.step != self.step or now > self.due:
            return None
        return self._decide(cmd, cmd, alive)

    def expire(
        self, now: float, newest: Command | None, alive: bool
    ) -> tuple[str, np.ndarray | None, Applied] | None:
        """At or after the deadline with no command in time: the candidate or the brake."""
        if self.decided or now < self.due:
            return None
        return self._decide(None, newest, alive)

    def _decide(
        self, cmd: Command | None, newest: Command | None, alive: bool
    ) -> tuple[str, np.ndarray | None, Applied]:
        assert self.step is not None
        k = self.step
        what, a, _ = self.side.decide(k, cmd, newest, alive, self.x)
        self.decided = True
        report = Applied(robot=self.robot, step=k, last=self.side.applied_step, braked=what == BRAKED)
        return what, a, report


def tick_maps(reports: dict[str, Applied | None]) -> tuple[dict[str, int], dict[str, int]]:
    """:attr:`~fleet.wire.Tick.fallback` and :attr:`~fleet.wire.Tick.braked` from the robot
    sides' :class:`~fleet.wire.Applied` reports of one step, by robot id (None: no report,
    which says nothing)."""
    fallback: dict[str, int] = {}
    braked: dict[str, int] = {}
    for rid, rep in reports.items():
        if rep is not None and not rep.on_time:
            (braked if rep.braked else fallback)[rid] = rep.last
    return fallback, braked
