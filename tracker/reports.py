"""What a tracker tells in each tick about robots whose ``epuck_link`` keeps the deadline.

The camera tracker, and the tracker of emulated robots, do not apply the agents' commands: each
robot's ``epuck_link`` does, by its own clock (:class:`epuck_link.robot_side.LinkDeadline`), and
reports what it applied (:class:`~ground.wire.Applied`).  The tracker puts those reports into its
next tick (:attr:`~ground.wire.Tick.fallback`, :attr:`~ground.wire.Tick.braked`) so that the
agent and its neighbours take the plan the robot executed (docs/design.md, "Missed
deadlines").
"""

from __future__ import annotations

from typing import Any

from ground.wire import Applied

REPORT_WAIT = 0.1
"""How long a tracker waits for a link's report before a tick, as a fraction of Ts: only for
links that reported a recent step (:attr:`Reports.expected`)."""

OUTCOME_WAIT = 0.2
"""With delay compensation, how long after a step's deadline a tracker waits for the links'
reports of that step before it sends the step's outcome, as a fraction of Ts.  A link decides
at once when its command comes in time; only a missed command is decided at the link's
deadline, counted from when its tick reached it, so the report of a miss needs this much
slack for the tick's and the report's way.  Longer would leave the agents less of the step to
plan the next one in."""


class Reports:
    """What a tracker tells in each tick from the links' :class:`~ground.wire.Applied`
    reports (the camera tracker, and the tracker of emulated robots).

    Tick k says what each robot did over step k − 1: its candidate (``fallback``) or the
    brake (``braked``), from that step's report.  A braked report that came too late for
    its own tick goes into the next one: whatever happened in between, the agent starts
    again from where its stopped robot is, and its neighbours keep clear of it as of a
    braked robot.  A late report of a step on the candidate cannot be told afterwards
    (the agent has planned on from the step it missed): it is logged and counted.  The
    inbox must keep the reports of the last :data:`LOOKBACK` steps (prune no later).

    With delay compensation (docs/design.md, "Delay compensation") the step's outcome tells
    the reports of step k as soon as they are in (:meth:`for_outcome`), and tick k + 1 says the
    same again; a report that came after the outcome is taken with the next one, as a report
    too late for its tick is taken with the next tick."""

    LOOKBACK = 8
    """Steps back that a late report is looked for."""

    def __init__(self, ids: list[str]):
        self.ids = ids
        self.expected: set[str] = set()
        """Robots whose link reported one of the last :data:`LOOKBACK` steps: waited for
        (bounded) before a tick or an outcome.  A link that is gone does not hold up every tick;
        one whose reports come late is still waited for."""
        self.seen: set[tuple[str, int]] = set()
        """(robot, step) of the reports already taken."""
        self.untold = 0
        """Late reports of steps on the candidate, never told."""
        self.told: tuple[int, dict[str, int], dict[str, int]] | None = None
        """The last outcome told: (its step, Outcome.fallback, Outcome.braked)."""

    def for_tick(
        self, inbox: Any, k: int, timeout: float, log: Any
    ) -> tuple[dict[str, int], dict[str, int], list[str]]:
        """(Tick.fallback, Tick.braked, the deadline misses to count) for tick k, after waiting
        up to ``timeout`` [s] for the expected reports of step k − 1.  A miss is a robot on its
        candidate, or braked while its agent is live (a dead agent's robot is no miss).
        ``inbox`` is subscribed to ``fleet/F/applied/*`` with ``keep``.  If the outcome of step
        k − 1 was told (:meth:`for_outcome`), the tick says the same, and counts no miss again."""
        told = self.told
        if told is not None and told[0] == k - 1:
            return dict(told[1]), dict(told[2]), []
        return self._take(inbox, k - 1, timeout, log)

    def for_outcome(
        self, inbox: Any, k: int, timeout: float, log: Any
    ) -> tuple[dict[str, int], dict[str, int], list[str]]:
        """(Outcome.fallback, Outcome.braked, the deadline misses to count) for the outcome of
        step k, after waiting up to ``timeout`` [s] for the expected reports of step k (delay
        compensation); tick k + 1 then says the same (:meth:`for_tick`)."""
        fallback, braked, missed = self._take(inbox, k, timeout, log)
        self.told = (k, fallback, braked)
        return dict(fallback), dict(braked), missed

    def _take(
        self, inbox: Any, last: int, timeout: float, log: Any
    ) -> tuple[dict[str, int], dict[str, int], list[str]]:
        """What the reports of step ``last`` say, and the late braked reports of the steps before
        it not taken yet, once the expected reports of ``last`` are in or ``timeout`` [s] passed."""
        inbox.wait(lambda: all(inbox.get(Applied, r, last) is not None for r in self.expected), timeout)
        steps = range(max(0, last - self.LOOKBACK), last + 1)
        with inbox.cond:
            got = [
                rep for r in self.ids for j in steps
                if (r, j) not in self.seen and (rep := inbox.get(Applied, r, j)) is not None
            ]  # fmt: skip
            live = set(inbox.live)
        fallback: dict[str, int] = {}
        braked: dict[str, int] = {}
        for rep in sorted(got, key=lambda a: -a.step):  # the newest first
            self.seen.add((rep.robot, rep.step))
            if rep.on_time:
                continue
            if rep.step == last:
                (braked if rep.braked else fallback)[rep.robot] = rep.last
            elif rep.braked:
                braked.setdefault(rep.robot, rep.last)
            else:
                self.untold += 1
                log(f"step {rep.step}: {rep.robot}'s robot side followed its candidate, but its report "
                    "came too late: the agent and its neighbours were not told")  # fmt: skip
        for r in braked:
            fallback.pop(r, None)
        self.seen = {(r, j) for r, j in self.seen if j >= last - self.LOOKBACK}
        self.expected = {r for r, _ in self.seen}
        return fallback, braked, [*fallback, *(r for r in braked if r in live)]
