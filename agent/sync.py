"""What an agent knows of its own robot: whether it has joined the fleet, the state it plans
from, and whether its robot side applied its commands (docs/design.md, "Missed deadlines").

The agent process (:mod:`agent.node`) measures, hears the clock and the robot sides' reports, and
hands them here; :class:`Sync` decides, with no transport and no logging of its own: what it has
to say goes to the ``say`` it is given (one line each, once an episode).

* A step with a measurement plans from it; one without plans from the nominal model's
  prediction for ``blind_steps`` steps, then holds braked; the first measurement after that
  starts again where the robot is, as a restarted agent does.
* An agent that (re)joins a running fleet starts where its robot is, its references at rest.
* When the clock says the robot side did not apply the last commands, the agent takes the
  candidate the robot followed instead (:meth:`TubeMPC.rewind`), or starts again where the robot
  braked.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from agent.controller import TubeMPC
from ground.wire import LinkState

REJOIN_GAP = 5
"""Steps missed (0.5 s at Ts = 0.1 s, the link watchdog's time) after which an agent re-initialises."""


class Sync:
    """One agent's standing against its own robot (see the module docstring).

    ``ctrl`` is the robot's controller, ``design`` its tube design (for ``A`` (4, 4) and ``B``
    (4, 2), the nominal model), ``blind_steps`` the steps it may plan on that model's prediction
    while poses are missing, and ``say`` where its one-line notes go."""

    def __init__(self, ctrl: TubeMPC, design: Any, blind_steps: int, say: Callable[[str], None]) -> None:
        self.ctrl, self.design, self.blind_steps, self.say = ctrl, design, blind_steps, say
        self.joined = False
        """The agent plans from its robot's state (it has joined the fleet, and not braked since)."""
        self.x_est: np.ndarray | None = None
        """The state (4,) [m, m/s] the last step planned from, or None."""
        self.a_prev = np.zeros(2)
        """The acceleration (2,) [m/s²] the last command carried."""
        self.blind = 0
        """Steps in a row without a measurement of its own."""
        self.synced = -1
        """The robot side executed this controller's plans up to this step."""
        self.ran: list[int] = []
        """Steps after ``synced`` at which the controller stepped."""
        self.rejoined = False
        """Joined again in this braking episode (said once)."""
        self.behind = ""
        """What the robot side did instead of this agent's last commands: "" (applied them),
        "candidate" or "braked"; each episode is said once."""
        self.reported = -1
        """The newest step whose outcome (what the robot sides did) has been taken."""
        self.cut_since: int | None = None
        """The step this robot's radio link was found down at, while it is (None: up)."""

    @property
    def holding(self) -> bool:
        """Past ``blind_steps`` steps without poses: the robot brakes and holds."""
        return self.blind > self.blind_steps

    def state(self, k: int, x: np.ndarray | None) -> np.ndarray | None:
        """The state (4,) [m, m/s] to plan from at step k, given the measured one ``x`` or None:
        the measurement, or the nominal model's prediction while poses are missing; None before
        the first measurement."""
        if x is not None:
            if self.holding:
                # Its robot braked off the committed reference, and its neighbours kept clear
                # of it as of a braked robot (BLIND): start again from where it is, as a
                # restarted agent does, with the tube about the new measurement.
                self.say(f"step {k}: measurements back after {self.blind} steps; starting again where it is")
                self.joined = False
            self.blind = 0
            if not self.joined and k > 0:
                # (Re)joining a running fleet: start where the robot is, references at rest there.
                self.ctrl.reset(x[[0, 2]], x)
                if not self.rejoined:  # once a braking episode: it starts again at each of its steps
                    self.say(f"joined at step {k} at ({x[0]:.3f}, {x[2]:.3f})")
                self.rejoined = self.behind == "braked"
            self.joined = True
            return x
        if self.x_est is None:
            return None
        self.blind += 1
        if self.blind == self.blind_steps + 1:
            self.say(f"step {k}: no pose for {self.blind} steps; braking and holding")
        design = self.design
        return np.asarray(design.A @ self.x_est + design.B @ self.a_prev)  # the nominal model's prediction

    def cut(self, k: int, link: LinkState | None) -> bool:
        """This robot's radio link is down at step k, or back with the robot held until the step
        its agent starts again at (``link``, the newest :class:`~ground.wire.LinkState` of its
        robot; None on a simulated robot): the robot drives on (or stands) uncontrolled, and
        nothing planned now reaches it.  Said once an outage."""
        cut = link is not None and (not link.up or k < link.back)
        if cut and self.cut_since is None:
            self.cut_since = k
            self.say(
                f"step {k}: the robot's link is down; it drives on uncontrolled, so nothing is "
                "solved until the link is back"
            )
        elif not cut and self.cut_since is not None:
            self.say(f"step {k}: the robot's link is back after {k - self.cut_since} steps")
            self.cut_since = None
        return cut

    def catch_up(self, k: int, tick: int, executed: int | None, stop: bool) -> int:
        """The clock is at step ``tick`` while the agent is at step k: the step to go on from.
        Hung for more than :data:`REJOIN_GAP` steps while the clock does not say what the robot
        did (``executed`` None: a camera tracker without ``epuck_link``'s report), it starts
        again from where the robot is, like a restarted agent."""
        if tick <= k:
            return k
        if self.joined and tick > k + REJOIN_GAP and executed is None:
            self.joined, self.x_est = False, None
        if self.joined and not stop:
            self.say(f"fell behind the clock: step {k} → {tick}")
        return tick

    def take_report(self, k: int, executed: int | None, braked: bool) -> None:
        """Take what the robot side did up to step k − 1: ``executed``, the last step whose
        command it applied if it did not apply the newest (None: it applied them all), and
        whether it braked.  It followed the shifted candidate of its last applied command (or
        braked): do the same."""
        if self.joined and executed is not None:
            # Controller steps after the last applied command were not applied; the steps
            # between the last one known to match and now that it never took (it fell behind
            # the clock) were followed on the candidate too.
            unapplied = sum(1 for s in self.ran if s > executed)
            coasted = k - 1 - max(self.synced, executed) - unapplied
            if braked or not self.ctrl.rewind(unapplied, coasted):
                if self.behind != "braked":  # said once a braking episode
                    self.say(f"step {k}: robot braked after step {executed}; starting again where it is")
                self.behind, self.joined, self.x_est = "braked", False, None
            else:
                if not self.behind:
                    self.say(f"step {k}: commands after step {executed} not applied; on its candidate")
                self.behind = self.behind or "candidate"
        elif executed is None:
            self.behind, self.rejoined = "", False
        self.synced, self.ran, self.reported = k - 1, [], k - 1
