"""The robot side's rule for each step: the command, the shifted candidate, or the brake.

Shared by the simulated tracker (:mod:`tracker.sim`, which is the robot side of simulated
robots) and by ``epuck_link`` (the robot side of an e-puck), so that a robot behaves the same
whether it is simulated or real when its agent's command misses the deadline
(docs/design.md, "Missed deadlines").
"""

from __future__ import annotations

import math

import numpy as np

from ground.model import chain_input, double_integrator
from ground.params import ControllerParams
from ground.wire import Applied, Command, remember_steps

COMMAND, CANDIDATE, HELD, BRAKED = "command", "candidate", "held", "braked"


class RobotSide:
    """What a robot side applies to one robot each step (docs/method.md §6 and
    docs/design.md, "Missed deadlines"): the agent's command when it came in time;
    else the ancillary law on the shifted candidate of the last command applied; braking
    when the agent is dead, has not been heard from for ``watchdog`` [s], or the candidate
    is used up.  The simulated tracker keeps one per robot; so does ``epuck_link``, through
    :class:`LinkDeadline`.  With ``drives`` False (the tracker of robots whose ``epuck_link``
    decides) a missing command only holds the last acceleration."""

    def __init__(self, params: ControllerParams, watchdog: float, drives: bool):
        self.Ts = params.Ts
        """Sampling period [s]."""
        self.A, self.B, _ = double_integrator(params.Ts)
        """The nominal model the candidate is propagated with (:mod:`ground.model`)."""
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
        (2,) [m/s²] or None when the caller brakes the plant: BRAKED, or a COMMAND whose agent
        asks for the brake (:attr:`~ground.wire.Command.brake`); why it is braked).

        ``cmd`` is the agent's command of step k if it came in time, ``newest`` its latest
        command of any step, ``alive`` whether its liveliness token is up, ``x`` (4,)
        [m, m/s] the state measured for it at step k (for the candidate).  A command of
        step k − 1 that came after its deadline counts as heard for the watchdog: its agent
        is alive and one step behind (a hung agent sends nothing)."""
        heard = cmd is not None or (newest is not None and newest.step >= k - 1)
        self.quiet = 0 if heard else self.quiet + 1
        if cmd is None and self.drives:
            remember_steps(self.unexecuted, (k,), k)
        if not alive or self.quiet * self.Ts > self.watchdog:
            self.brake()
            return (
                BRAKED,
                None,
                "its agent is not alive" if not alive else f"no command for {self.watchdog} s",
            )
        if cmd is not None and cmd.brake:  # its agent holds: the robot side's own brake
            self.applied, self.following = cmd, False
            self.last_a = np.zeros(2)
            return COMMAND, None, "its agent holds without poses"
        if cmd is not None:
            self.applied, self.following = cmd, True
            self.last_a = np.array([cmd.ax, cmd.ay])
            return COMMAND, self.last_a, ""
        if not self.drives:
            return HELD, self.last_a, ""
        last = self.applied
        a = None
        if last is not None and last.fallback and self.following and x is not None:
            a = chain_input(last.x_next, last.v_next, k - last.step - 1, x, self.A, self.B, last.K)
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
    keeps to what was decided, and the :class:`~ground.wire.Applied` report (one per step,
    at the decision) lets the tracker tell the agent and its neighbours in tick k + 1.

    A step still undecided when the next tick arrives (its tick reached the link more than
    half a step late), and a step whose tick never reached it, cannot be reported in time
    for the tick after it.  The only story then safe for everyone is the brake: the link
    stops the robot, reports those steps braked (the tracker puts a late braked report in
    its next tick, and the agent starts again from where the robot is), and applies no
    command until the step after the one whose tick revealed it.  Times are the caller's
    monotonic clock [s]."""

    def __init__(self, robot: str, params: ControllerParams, watchdog: float, deadline: float):
        self.robot = robot
        self.side = RobotSide(params, watchdog, drives=True)
        self.deadline = deadline
        self.step: int | None = None
        """The step of the last tick received (None before the first)."""
        self.due = math.inf
        """When the command of ``step`` is due [s]."""
        self.decided = True
        self.hold_until = -1
        """No command of this step or an earlier one is applied (after a late brake)."""
        self.x: np.ndarray | None = None
        """The state measured at step ``step`` (4,) [px, vx, py, vy] in m, m/s, world frame: the
        agent's measurement (:meth:`measured`), or the estimate at the tick without it."""

    def relinked(self) -> int:
        """The link to the robot came back after an outage: the robot was uncontrolled, off its
        plan.  Brake, apply no command of this step or the next, and so report the next step
        braked: the agent then starts again from where the robot is, as a restarted agent does.
        Returns that step, the first whose plan is made from where the robot stands (0 before
        the first tick)."""
        self.side.brake()
        if self.step is None:
            return 0
        self.hold_until = max(self.hold_until, self.step + 1)
        return self.hold_until + 1

    def measured(self, k: int, x: np.ndarray) -> None:
        """The state ``x`` (4,) [m, m/s] measured at step k (its camera pose, and the odometry
        sent with it): if step k is undecided, its candidate is followed from it, not from the
        estimate taken at the tick (the pose came after the tick)."""
        if self.step == k and not self.decided:
            self.x = x

    @property
    def wake_at(self) -> float:
        """When the link must look again [s]: the deadline of an undecided step, else never."""
        return math.inf if self.decided else self.due

    def tick(
        self, k: int, now: float, x: np.ndarray | None, newest: Command | None, alive: bool
    ) -> list[tuple[str, np.ndarray | None, Applied]]:
        """Tick k received at ``now`` [s] with the state ``x`` measured then.  Returns the
        decisions taken: the brake for the steps before k left undecided or never started
        (see the class docstring), and step k's, if its command (``newest``) came first."""
        out: list[tuple[str, np.ndarray | None, Applied]] = []
        if self.step is not None and k <= self.step:
            return out  # an old or repeated tick: nothing new
        if self.step is not None:
            late = [self.step] if not self.decided else []
            late += range(self.step + 1, k)
            if late:
                self.side.brake()
                self.hold_until = k
                for j in late[-8:]:
                    rep = Applied(robot=self.robot, step=j, last=self.side.applied_step, braked=True)
                    out.append((BRAKED, None, rep))
        self.step, self.due, self.decided, self.x = k, now + self.deadline, False, x
        if newest is not None and newest.step == k and k > self.hold_until:
            out.append(self._decide(newest, newest, alive))
        return out

    def command(self, cmd: Command, now: float, alive: bool) -> tuple[str, np.ndarray | None, Applied] | None:
        """A command received at ``now`` [s]: applied if it is of the current step, in time,
        the step is not decided yet and no late brake holds it; otherwise None."""
        if self.decided or cmd.step != self.step or now > self.due or cmd.step <= self.hold_until:
            return None
        return self._decide(cmd, cmd, alive)

    def expire(
        self, now: float, newest: Command | None, alive: bool
    ) -> tuple[str, np.ndarray | None, Applied] | None:
        """At or after the deadline [s] with no command in time: the candidate or the brake."""
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
