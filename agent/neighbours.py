"""What an agent knows of the other robots, as its inbox tells it: their plans a step may use,
who is live, whose plans were never executed, where they are by place, and which of them a
step must keep clear of as discs (:class:`agent.hazards.Guard`).

The agent process (:mod:`agent.node`) asks :class:`Neighbourhood` for the neighbours of each
step it plans; the waits here are bounded as the clock allows (docs/design.md, "Plans by place",
"Relayed plans", "Missed deadlines").
"""

from __future__ import annotations

from collections.abc import Collection
from functools import partial
from typing import Any

import numpy as np

from agent.channels import Channels, digest_in, plans_in, tick_at_least
from agent.controller import TubeMPC
from agent.coordination import VIEW_CELLS, NeighbourInfo
from agent.hazards import Guard, in_reach, loose, neighbour_of
from ground.geometry import Whereabouts, cell_of, controlled_point
from ground.wire import LinkState, Outcome, Plan, Pose, Tick, remember_steps


class Neighbourhood:
    """The other robots as one agent knows them (see the module docstring).

    ``others`` are their ids; ``starts`` what each is taken for before any plan of it is heard;
    ``side`` [m] the side of the cells of plans by place, or None (every robot is in reach);
    ``wait_s`` [s] how long a step may wait for their plans; ``relay``: the plans come in the
    tracker's digest."""

    def __init__(
        self, link: Channels, ctrl: TubeMPC, guard: Guard, others: list[str],
        starts: dict[str, NeighbourInfo], side: float | None, lookahead: float, wait_s: float, relay: bool,
    ) -> None:  # fmt: skip
        self.link, self.inbox, self.ctrl, self.guard = link, link.inbox, ctrl, guard
        self.others, self.starts, self.side, self.lookahead = others, starts, side, lookahead
        self.wait_s, self.relay = wait_s, relay
        self.last: dict[str, Plan | None] = {}
        """The newest executed plan heard of each robot."""
        self.withdrawn: dict[str, set[int]] = {j: set() for j in others}
        """Per neighbour, recent steps whose plan was never executed (its command was not applied)."""
        self.links: dict[str, LinkState | None] = {}
        """The newest link state of each other robot (real and emulated robots only)."""
        self.places: dict[str, Whereabouts] = {}
        """The place tokens as :meth:`reach` last read them (with plans by place)."""

    def of_step(self, k: int, braked: Collection[str]) -> tuple[dict[str, Plan | None], set[str], list[str]]:
        """The live neighbours' plans of step k − 1, to plan step k against: (those plans, who is
        live, the robots in reach: :meth:`reach`).

        Realtime: the wait may not hold up this step's deadline.  In mesh the plans come by
        callback, so a plan a little late is still used; in relay the digest came by callback
        before the tick (half a step before; with delay compensation, with the outcome)."""
        inbox = self.inbox
        # (Mesh plans come by callback, which wakes a wait; only relay drains while it waits.)
        wait = inbox.drain_until if self.link.drained and self.relay else inbox.wait
        if k > 0:
            heard = partial(digest_in if self.relay else plans_in, inbox, self.reach(braked), k - 1)
            # Tick k + 1 cannot go out before this agent's command of step k unless the clock no
            # longer waits for it (it is joining again): then the fleet has moved on, and plans of
            # step k − 1 missed while it rejoined will never come.
            wait(lambda: heard() or tick_at_least(inbox, k + 1), self.wait_s)
        with inbox.cond:
            # Plans of step k − 1, and of no later step than each robot side executed
            # (Tick.fallback, Tick.braked): a plan whose command missed its deadline was never
            # executed, and its robot keeps to the plan before.
            fresh: dict[str, Plan | None] = {}
            for j in self.others:
                pl = inbox.get(Plan, j, k - 1) if k - 1 not in self.withdrawn[j] else None
                fresh[j] = pl
                if pl is None:  # the newest plan of step ≤ k − 1: what arrived later must not count
                    pl = inbox.newest(Plan, j, k - 1, self.withdrawn[j])
                if pl is not None and ((had := self.last.get(j)) is None or had.step < pl.step):
                    self.last[j] = pl
            live = set(inbox.live)
            self.links = {j: inbox.get(LinkState, j) for j in self.others}
        if self.side is not None:
            self._gate_news()
        return fresh, live, self.reach(braked)

    def take_report(self, k: int, report: Tick | Outcome) -> None:
        """Skip the plans never executed up to step k − 1 (``report``: tick k, or the outcome of
        step k − 1): a robot that followed its candidate, or braked, kept to an older plan."""
        for j, done in (*report.fallback.items(), *report.braked.items()):
            if j in self.withdrawn:  # the plans of steps done + 1 … k − 1 were never executed
                remember_steps(self.withdrawn[j], range(done + 1, k), k)  # only the recent part is kept
                had = self.last.get(j)
                if had is not None and had.step > done:
                    # The newest plan known of j was never executed: its robot kept to the one
                    # before, which a disc about j must be about (docs/method.md §6.4).
                    with self.inbox.cond:
                        executed_plan = self.inbox.newest(Plan, j, done, self.withdrawn[j])
                    if executed_plan is not None:
                        self.last[j] = executed_plan

    def classify(
        self, k: int, reach: list[str], fresh: dict[str, Plan | None], live: set[str], braked: Collection[str]
    ) -> tuple[list[NeighbourInfo], list[Any]]:
        """The neighbours and the discs of step k (:meth:`Guard.classify`), with the camera poses
        of the robots off their plans that it watches; then subscribe to the poses of those it
        watches now, and drop the rest."""
        guard, inbox = self.guard, self.inbox
        poses: dict[str, tuple[int, np.ndarray]] = {}
        with inbox.cond:
            for j in self.link.poses:
                pose = inbox.get(Pose, j)
                if pose is not None:
                    poses[j] = (pose.seq, controlled_point((pose.x, pose.y, pose.theta), self.lookahead))
        out = guard.classify(
            k, reach, fresh, self.last, live, self.starts, set(braked), self.links, self.places, poses
        )
        self.link.watch_poses(guard.watched)
        return out

    def reach(self, braked: Collection[str], within: int = 1) -> list[str]:
        """The other robots that a step may need to know: every one, or with plans by place those
        :func:`agent.hazards.in_reach` keeps, from the plans and place tokens heard so far, about
        the controller's own last committed point (moved by a rejoin, before any plan from it
        goes out).  ``braked``: the robots the step's tick or outcome says were braked;
        ``within``: how many cells away (:data:`~agent.coordination.VIEW_CELLS` for the
        navigator's view)."""
        if self.side is None:
            return self.others
        inbox = self.inbox
        with inbox.cond:
            self.places = dict(inbox.places)
            live = set(inbox.live)
            discs = {*braked, *(j for j in self.others if loose(inbox.get(LinkState, j), self.last.get(j)))}
        mine = cell_of(self.ctrl.last_point, self.side)
        return in_reach(
            self.others, mine, self.side, self.last, self.places, self.starts, live, discs, within
        )

    def seen(self, reach: list[str], braked: Collection[str]) -> list[NeighbourInfo]:
        """With plans by place, the robots beyond ``reach`` that the navigator sees too (up to
        :data:`~agent.coordination.VIEW_CELLS` cells away), by their newest plan heard, else their
        start; none otherwise, where the step knows every robot.  Shaping only: the step's
        constraints are those of ``reach``."""
        if self.side is None:
            return []
        near = set(reach)
        return [
            self.starts[j] if (pl := self.last.get(j)) is None else neighbour_of(pl)
            for j in self.reach(braked, VIEW_CELLS)
            if j not in near
        ]

    def steer_ahead(self, k: int, limit: float) -> bool:
        """Choose the target of step k + 1 (:meth:`TubeMPC.steer_ahead`) once the neighbours'
        plans of step k are in: the tracker relays them once it has the commands of step k, half
        a step before tick k + 1, while the cores are idle.  The navigator plans around every
        live robot's newest executed plan (else the last one the step used, else its start), as
        the step would.  Waits at most ``limit`` [s]; skipped (False) if tick k + 1 or nothing
        comes first: the step then steers itself."""
        inbox, others = self.inbox, self.others
        inbox.wait(lambda: digest_in(inbox, others, k) or tick_at_least(inbox, k + 1), limit)
        with inbox.cond:
            if tick_at_least(inbox, k + 1) or not digest_in(inbox, others, k):
                return False
            plans = {j: inbox.newest(Plan, j, k, self.withdrawn[j]) for j in others if j in inbox.live}
        known = {j: pl or self.last.get(j) for j, pl in plans.items()}
        self.ctrl.steer_ahead([self.starts[j] if pl is None else neighbour_of(pl) for j, pl in known.items()])
        return True

    def _gate_news(self) -> None:
        """Plans by place: tell the controller's gate what was heard of the robots it waits for,
        whose plans the agent takes on their own keys while it waits, wherever they are
        (:meth:`Channels.watch_plans`); with every plan, or the digest, the step hears them all."""
        gate = self.ctrl.gate
        self.link.watch_plans(() if gate is None else gate.waits_for)
        if gate is not None:
            heard = [self.last.get(j) for j in gate.waits_for]
            self.ctrl.gate_news([neighbour_of(pl) for pl in heard if pl is not None])
