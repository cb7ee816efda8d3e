"""The agent's side of the bus: its Zenoh session, subscriptions, publishers and tokens
(:class:`Channels`), and what its steps wait for in the inbox (the predicates below, each called
with ``inbox.cond`` held).  The agent process (:mod:`agent.node`) drives them; the controller
never sees them.  Every command and plan this robot publishes leaves by :meth:`Channels.put_command`
and :meth:`Channels.put_plan`."""

from __future__ import annotations

import argparse
import threading
from collections.abc import Collection
from typing import Any

import numpy as np

from agent.coordination import PLACE_LAG
from ground.geometry import Cell, block, cell_name, cell_of
from ground.wire import Command, Digest, Goal, Keys, LinkState, Odom, Outcome, Plan, Pose, Tick
from transport.bus import Inbox, open_session, publisher, put
from transport.process import fault_plan, log

TRACKER = "tracker"
"""The tracker's id: the sender of the ticks, outcomes and digests, and its liveliness token."""


class Channels:
    """The agent's side of Zenoh: session, subscriptions, publishers, liveliness token."""

    def __init__(
        self, args: argparse.Namespace, keys: Keys, me: str, role: str, on_input: Any = None,
        tracked: bool = True, side: float | None = None, start: np.ndarray | None = None,
    ) -> None:  # fmt: skip
        """``on_input``: called with each tick, pose and odometry of this robot stored (a Zenoh
        thread, or the draining thread; the inbox's lock held), or None.  ``tracked``: the
        odometry comes from the tracker (a simulated robot), not from the robot's
        ``epuck_link``.  ``side`` [m]: plans by place, in cells of that side, from the robot's
        ``start`` (2,) [m], its controlled point; None: every plan (mesh) or the digest."""
        self.session = open_session(args)
        self.inbox = inbox = Inbox(keys, role, fault_plan(args))
        # Realtime: the tracker sends this robot's pose and odometry just before the tick,
        # batched on one link, so they are in when the tick is.  With relayed plans, or with
        # delay compensation (whose tick's callback answers at once), they are then taken from
        # Zenoh's queues after the tick (Inbox.drain) instead of by a callback each: two
        # wake-ups and GIL hand-overs a step fewer in the race to the deadline.  The digest of
        # step k − 1 comes half a step before tick k, once the tracker has the commands of
        # k − 1, and is decoded by callback then, while the cores are idle
        # (docs/design.md, "Relayed plans").
        # The odometry of a robot on an epuck_link comes from the link, once it has the pose: it
        # is taken by callback, which answers the tick if it is the last in.
        drained = self.drained = args.clock == "realtime" and (
            args.exchange == "relay" or bool(args.delay_compensation)
        )
        self.subs = [
            inbox.subscribe(self.session, keys.pose(me), Pose, keep=True, drained=drained, then=on_input),
            inbox.subscribe(
                self.session, keys.odom(me), Odom, keep=True, drained=drained and tracked, then=on_input
            ),
            # The neighbours' plans: each on its own key (mesh), or a step's plans at once in
            # the tracker's digest (relay: one message a step); by place, see move_to.
            *(
                [inbox.subscribe(self.session, keys.digest, Digest, keep=True)]
                if args.exchange == "relay"
                else []
                if side is not None
                else [inbox.subscribe(self.session, keys.plan(), Plan, keep=True, remote=True)]
            ),
            inbox.subscribe(self.session, keys.goal(me), Goal),
            inbox.subscribe(self.session, keys.link(), LinkState),
            inbox.subscribe(self.session, keys.clock, Tick, then=on_input),
            inbox.watch_liveliness(self.session),
        ]
        if args.delay_compensation:
            self.subs.append(inbox.subscribe(self.session, keys.outcome, Outcome))
        self.pub_plan = publisher(self.session, keys.plan(me))
        self.pub_cmd = publisher(self.session, keys.cmd(me))
        self.args, self.keys, self.me, self.role = args, keys, me, role
        self.token: Any = None
        self.side = side
        self.cell: Cell = (0, 0)
        """The cell of this robot's last committed point (plans by place)."""
        self.block: dict[Cell, Any] = {}
        """The subscriptions to the plans of the groups of cells about :attr:`cell`'s (:data:`GROUP`)."""
        self.place_token: Any = None
        self.poses: dict[str, Any] = {}
        """The subscriptions to other robots' camera poses, by robot (:meth:`watch_poses`)."""
        self.plans: dict[str, Any] = {}
        """Plans by place: the subscriptions to other robots' own plan keys (:meth:`watch_plans`)."""
        if side is not None:
            self.subs.append(inbox.watch_places(self.session, PLACE_LAG))
            assert start is not None
            self.cell = cell_of(start, side)
            self._subscribe_block()

    def put_command(self, command: Command) -> None:
        """Publish this robot's command, once encoded: the one way a command leaves the agent."""
        self.pub_cmd.put(command.encode())

    def put_plan(self, plan: Plan) -> None:
        """Publish this robot's plan on its key and, by place, on its cell's, once encoded.
        By place, a plan whose last committed point is in a new cell first moves the robot's
        place token and subscriptions there (:meth:`move_to`)."""
        data = plan.encode()
        if self.side is not None:
            cell = cell_of(plan.committed[-1], self.side)
            if cell != self.cell or self.place_token is None:
                self.move_to(cell, plan.step)
            # A put, not a publisher per group: a declaration would travel to every peer.
            put(self.session, self.keys.near(self.me, cell_name(group_of(cell))), data)
        self.pub_plan.put(data)

    def move_to(self, cell: Cell, step: int) -> None:
        """The robot's last committed point is in ``cell`` from its plan of ``step`` on: declare the
        place token there (before the old one goes, so that the robot has one from its first plan
        on) and subscribe to the plans of the cells about it.  The first token waits for the
        first plan: an agent that (re)joins a running fleet then declares the step it plans,
        newer than the token it left where it was (at its start it would say step 0)."""
        moved = group_of(cell) != group_of(self.cell)
        self.cell = cell
        old, self.place_token = self.place_token, self._place_token(step)
        if old is not None:
            old.undeclare()
        if moved:
            self._subscribe_block()

    def _place_token(self, step: int) -> Any:
        return self.session.liveliness().declare_token(self.keys.at(self.me, cell_name(self.cell), step))

    def _subscribe_block(self) -> None:
        want = block(group_of(self.cell), 1)
        for c in [c for c in self.block if c not in want]:
            self.inbox.unsubscribe(self.block.pop(c))
        for c in want - set(self.block):
            self.block[c] = self.inbox.subscribe(
                self.session, self.keys.near("*", cell_name(c)), Plan, keep=True, remote=True
            )

    def watch_plans(self, robots: Collection[str]) -> None:
        """Plans by place: take the plans of exactly ``robots`` on their own keys too, wherever
        they are (those a gate waits for: :meth:`agent.neighbours.Neighbourhood._gate_news`)."""
        for j in [j for j in self.plans if j not in robots]:
            self.inbox.unsubscribe(self.plans.pop(j))
        for j in robots:
            if j not in self.plans:
                key = self.keys.plan(j)
                self.plans[j] = self.inbox.subscribe(self.session, key, Plan, keep=True, remote=True)

    def watch_poses(self, robots: Collection[str]) -> None:
        """Take the camera poses of exactly ``robots`` (the robots off their plans whose stand
        the guard waits for, :attr:`agent.hazards.Guard.watched`): declared when a robot comes,
        undeclared when it goes, so a fleet with no fault takes none."""
        for j in [j for j in self.poses if j not in robots]:
            self.inbox.unsubscribe(self.poses.pop(j))
        for j in robots:
            if j not in self.poses:
                self.poses[j] = self.inbox.subscribe(self.session, self.keys.pose(j), Pose)

    def go_live(self, on_goal: Any) -> None:
        """Answer goal queries with ``on_goal``, then declare the liveliness token."""
        args, keys, me = self.args, self.keys, self.me
        self.subs.append(self.session.declare_queryable(keys.goal(me), on_goal))
        # A peer that joins a running fleet drops what it publishes until it has heard the
        # others' subscriptions; the tracker waits for the commands of every live agent, so
        # become live only once the commands have a taker.
        if not _wait_matching(self.pub_cmd, args.timeout):
            log(self.role, f"nobody subscribes to {keys.cmd(me)} within {args.timeout} s; going live anyway")
        self.token = self.session.liveliness().declare_token(keys.alive(me))

    def close(self) -> None:
        """Undeclare the tokens and subscriptions, then close the session."""
        for token in (self.token, self.place_token):
            if token is not None:
                token.undeclare()
        for sub in [*self.subs, *self.block.values(), *self.poses.values(), *self.plans.values()]:
            sub.undeclare()
        self.session.close()


GROUP = 2
"""Plans by place travel by groups of GROUP × GROUP cells (their key names the group).  An agent
subscribes to its own group and the eight around it: whichever cell of its group it is in, they
hold the cells it coordinates with (one apart from its own) and one ring more, so that a robot
coming into reach has been heard from for a step at least.  It declares them again only when it
changes group: every declaration travels to every peer, and at one cell a group each step's
crossings cost the receiving side of every process more than the plans they saved."""


def group_of(cell: Cell) -> Cell:
    """The group (:data:`GROUP`) of ``cell``."""
    return (cell[0] // GROUP, cell[1] // GROUP)


def _wait_matching(pub: Any, timeout: float) -> bool:
    """Wait until ``pub`` has a matching subscriber, for at most ``timeout`` [s]."""
    matched = threading.Event()
    listener = pub.declare_matching_listener(lambda status: matched.set() if status.matching else None)
    try:
        return bool(pub.matching_status) or matched.wait(timeout)
    finally:
        listener.undeclare()


def own_measured(inbox: Inbox, me: str, k: int) -> bool:
    """This robot's pose and odometry of step k are in, or withheld by the fault plan."""
    return all(inbox.get(t, me, k) is not None or inbox.lost(t, me, k) for t in (Pose, Odom))


def plans_in(inbox: Inbox, others: list[str], step: int) -> bool:
    """Every live neighbour's plan of ``step`` has arrived (or was withheld by the fault plan), of
    the neighbours that planned the step before.  One silent since (hung, or alive again after
    a stop and joining) is not waited for: it is kept clear of as a disc until its plans come, as
    on the realtime clock, and a lockstep fleet does not stall a timeout a step on it."""
    return all(
        inbox.get(Plan, j, step) is not None or inbox.lost(Plan, j, step)
        for j in others
        if j in inbox.live and _planning(inbox, j, step)
    )


def _planning(inbox: Inbox, j: str, step: int) -> bool:
    """Robot j's agent made (or the fault plan withheld) a plan of ``step`` − 1 or later."""
    if step <= 0:
        return True
    newest = inbox.get(Plan, j)
    return (newest is not None and newest.step >= step - 1) or inbox.lost(Plan, j, step - 1)


def digest_in(inbox: Inbox, others: list[str], step: int) -> bool:
    """The tracker's digest of ``step`` has arrived: what it lacks is late or lost."""
    d = inbox.get(Digest, TRACKER)
    return d is not None and d.step >= step


def tick_is(inbox: Inbox, k: int) -> bool:
    """The newest tick is tick k, and not the stop."""
    t = inbox.get(Tick, TRACKER)
    return t is not None and not t.stop and t.step == k


def outcome_at_least(inbox: Inbox, k: int) -> bool:
    """The tracker's outcome of step k (or of a later step) has arrived."""
    o = inbox.get(Outcome, TRACKER)
    return o is not None and o.step >= k


def tick_at_least(inbox: Inbox, k: int) -> bool:
    """Tick k (or a later one, or the stop) has arrived."""
    t = inbox.get(Tick, TRACKER)
    return t is not None and (t.stop or t.step >= k)
