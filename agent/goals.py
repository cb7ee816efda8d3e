"""The goals an agent is given at run time: published on its goal key (``fleet goal``) or sent
as a query (a script, the ROS face), each judged by the one goal rule
(:func:`ground.scenario.goal_problem`) and taken by the first plan the agent makes after it.

A query is answered with a msgpack map, ``{"ok": true}`` or ``{"ok": false, "reason": "<one
line>"}``; a payload that is not a valid Goal for this robot is counted with the rejected
payloads and answered as an error (``reply_err``) with the same map.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from agent.channels import TRACKER
from agent.controller import TubeMPC
from ground.scenario import Scenario, goal_problem
from ground.wire import Goal, Keys, Plan, Tick, WireError, decode
from transport.bus import Inbox, goal_reply


class Goals:
    """One agent's goals given at run time (see the module docstring).

    ``ahead``: the agent plans a step ahead, so a goal accepted now is due at the plan of the
    step after next; ``say`` takes its one-line notes."""

    def __init__(
        self, me: str, scn: Scenario, footprint: float, ctrl: TubeMPC, inbox: Inbox, others: list[str],
        keys: Keys, ahead: bool, say: Callable[[str], None],
    ) -> None:  # fmt: skip
        self.me, self.scn, self.footprint, self.ctrl, self.inbox = me, scn, footprint, ctrl, inbox
        self.others, self.keys, self.ahead, self.say = others, keys, ahead, say
        self.seen: Goal | None = None
        """The newest goal published on the key that was judged."""
        self.pending: list[tuple[int, Goal]] = []
        """Goals queries gave and the agent accepted, in order, each with the first step whose
        plan takes it (under inbox.cond): the step after the newest tick when it came, or with
        delay compensation the one after that, since that step's plan may be under way already
        (made ahead), as ``fleet simulate`` takes a goal given at sample k at the plan of step
        k + 1.  Only the newest goal per step is kept."""

    def take(self, k: int) -> None:
        """Take, for the plan of step k, a goal published at run time (judged here) and one a
        query gave (judged when it came, :meth:`answer`)."""
        with self.inbox.cond:
            goal = self.inbox.get(Goal, self.me)
        if goal is not None and goal is not self.seen:
            self.seen = goal
            with self.inbox.cond:
                problem = self.problem(goal)
            if problem is not None:
                self.say(f"goal {goal.goal.round(3).tolist()} rejected: {problem}")
            else:
                self._set(goal.goal, k)
        with self.inbox.cond:
            asked = [g for due, g in self.pending if due <= k]
            self.pending = [(due, g) for due, g in self.pending if due > k]
        if asked:
            self._set(asked[-1].goal, k)

    def problem(self, goal: Goal) -> str | None:
        """Why ``goal`` cannot be taken, or None (inbox.cond held), by the one goal rule
        (:func:`~ground.scenario.goal_problem`): the walls, the obstacles, a passage from this
        robot's committed point, and the other robots' goals, each the one in ``goal.batch`` if
        it names the robot, else the one its latest plan carries."""
        plans = [pl for j in self.others if (pl := self.inbox.get(Plan, j)) is not None]
        return goal_problem(self.scn, self.footprint, goal.goal, plans, goal.batch, at=self.ctrl.last_point)

    def answer(self, query: Any) -> None:
        """A goal sent as a query on this robot's goal key (a Zenoh thread): decoded strictly
        (a malformed one is counted with the rejected payloads), judged, and, if accepted, kept
        for the plan it is due at; the reply says which (:func:`transport.bus.goal_reply`)."""
        inbox = self.inbox
        try:
            try:
                payload = query.payload
                if payload is None:
                    raise WireError("payload: none")
                goal = decode(payload.to_bytes(), Goal, robot=self.me)
            except WireError as e:
                with inbox.cond:
                    inbox.rejects.reject(str(query.key_expr), e)
                query.reply_err(goal_reply(e.reason))
                return
            with inbox.cond:
                problem = self.problem(goal)
                if problem is None:
                    tick = inbox.get(Tick, TRACKER)
                    due = (-1 if tick is None else tick.step) + 1 + self.ahead
                    if self.pending and self.pending[-1][0] == due:
                        self.pending.pop()  # the newer goal for the same step replaces it
                    self.pending.append((due, goal))
            if problem is not None:
                self.say(f"goal {goal.goal.round(3).tolist()} rejected: {problem}")
            query.reply(self.keys.goal(self.me), goal_reply(problem))
        finally:
            query.drop()

    def _set(self, goal: np.ndarray, k: int) -> None:
        """Steer to ``goal`` (2,) [m] from step k on (an accepted goal)."""
        if not np.array_equal(goal, self.ctrl.goal):
            self.ctrl.set_goal(goal)
            self.say(f"new goal {goal.round(3).tolist()} at step {k}")
