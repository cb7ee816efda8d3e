"""The agent process: a thin Zenoh shell around :class:`agent.controller.TubeMPC`.

``python -m agent --scenario S --robot ID [--fleet F] [--connect E] [--listen E]``

Lockstep protocol (docs/runtime-notes.md): at step k the agent waits for the
tracker's tick k, its own pose and odometry of step k and the plans that the
live neighbours committed at step k−1 (liveliness says who is live; every
wait is bounded).  The plans come on the neighbours' keys (``--exchange
mesh``) or together in the tracker's digest of step k−1 (``relay``).  It then
steps the controller and publishes its plan and its command for step k.  A
neighbour whose plan of step k−1 does not arrive in time is used with its last
known plan, and the event is counted.
"""

from __future__ import annotations

import argparse
import math
import sys
import threading
import time
from functools import partial
from typing import Any

import numpy as np

from agent.controller import TubeMPC
from agent.coordination import Hazard, NeighbourInfo
from agent.models import measured_state
from fleet.runtime import (
    Inbox,
    add_common_args,
    announce,
    fault_plan,
    load_validated,
    log,
    open_session,
    publisher,
    remember_steps,
)
from fleet.scenario import ConfigError, check_point, controlled_point
from fleet.wire import Command, Digest, Goal, Keys, Odom, Plan, Pose, Tick

REJOIN_GAP = 5
"""Steps missed (0.5 s at Ts = 0.1 s, the link watchdog's time) after which an agent re-initialises."""


def _neighbour(plan: Plan) -> NeighbourInfo:
    """What the controller uses of a neighbour's plan.  Its arrays are views of the
    received plan's, which nothing changes (a copy each was 3 × 31 calls a step at 32 robots)."""
    return NeighbourInfo(
        plan.robot, plan.committed[-1], plan.footprint, plan.priority, plan.rank, plan.target, plan.goal,
        plan.phase,
    )  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m agent", description=__doc__.splitlines()[0])
    add_common_args(ap)
    ap.add_argument("--robot", required=True, help="robot id from the scenario")
    ap.add_argument(
        "--blind-steps", type=int, default=3,
        help="steps to run on the nominal model's prediction when poses stop (then brake and hold)",
    )  # fmt: skip
    args = ap.parse_args(argv)
    role = f"agent {args.robot}"
    try:
        scn, design = load_validated(args.scenario)
        ids = [r.id for r in scn.robots]
        if args.robot not in ids:
            raise ConfigError("--robot", f"{args.robot!r} is not in the scenario (robots: {', '.join(ids)})")
    except ConfigError as e:
        print(f"agent: error: {e}", file=sys.stderr)
        return 2
    rank = ids.index(args.robot)
    spec = scn.robots[rank]
    p = design.params
    ctrl = TubeMPC(
        design,
        controlled_point(spec.start, p.lookahead),
        np.array(spec.goal, dtype=float),
        scn.arena,
        obstacles=scn.obstacles,
        priority=spec.priority,
        rank=rank,
        seed=scn.simulation.seed * 1000 + rank,
    )
    keys = Keys(args.fleet)
    me = args.robot
    link = _Link(args, keys, me, role)
    inbox, pub_cmd, pub_plan = link.inbox, link.pub_cmd, link.pub_plan
    announce("agent", robot=me)
    others = [r for r in ids if r != me]
    starts = {
        r.id: NeighbourInfo(
            id=r.id, last_point=controlled_point(r.start, p.lookahead), footprint=design.footprint,
            priority=r.priority, rank=i, target=np.array(r.goal, float), goal=np.array(r.goal, float),
        )
        for i, r in enumerate(scn.robots)
    }  # fmt: skip
    guard = Guard(me, design)
    k = 0
    joined = False
    x_est: np.ndarray | None = None
    a_prev = np.zeros(2)
    blind = 0
    goal_seen: Goal | None = None
    last: dict[str, Plan | None] = {}
    lockstep = args.clock == "lockstep"
    relay = args.exchange == "relay"
    silent_since = time.monotonic()
    synced = -1
    """The robot side executed this controller's plans up to this step."""
    ran: list[int] = []
    """Steps after ``synced`` at which the controller stepped."""
    rejoined = False
    """Joined again in this braking episode (logged once)."""
    withdrawn: dict[str, set[int]] = {j: set() for j in others}
    """Per neighbour, recent steps whose plan was never executed (its command was not applied)."""
    behind = ""
    """What the robot side did instead of this agent's last commands: "" (applied them),
    "candidate" or "braked"; each episode is logged once."""
    try:
        while True:
            if not inbox.wait(partial(_tick_at_least, inbox, k), 1.0):
                with inbox.cond:
                    now = time.monotonic()
                    seen = {f"{t}/{r}": round(now - at, 1) for (t, r), at in inbox.arrived.items()}
                    alive = sorted(inbox.live)
                if now - silent_since >= args.timeout:
                    log(
                        role, f"no tick {k} within {args.timeout} s; stopping (live {alive}; s since: {seen})"
                    )
                    return 1
                continue
            silent_since = time.monotonic()
            tick = inbox.get(Tick, "tracker")
            assert tick is not None
            if tick.step > k:
                if joined and tick.step > k + REJOIN_GAP and tick.executed(me) is None:
                    # Hung for a while, and the clock does not say what the robot did
                    # (a camera tracker without epuck_link's report): start again from
                    # where the robot is, like a restarted agent.  The robot sides say (below).
                    joined = False
                    x_est = None
                if joined and not tick.stop:
                    log(role, f"fell behind the clock: step {k} → {tick.step}")
                k = tick.step
            inbox.release(k)
            for j, done in (*tick.fallback.items(), *tick.braked.items()):
                if j in withdrawn:  # the plans of steps done + 1 … k − 1 were never executed
                    remember_steps(withdrawn[j], range(done + 1, k), k)  # only the recent part is kept
            executed = tick.executed(me)
            if joined and executed is not None:
                # The robot side did not apply the command of step k − 1.  It followed
                # the shifted candidate of its last applied command (or braked): do
                # the same (docs/runtime-notes.md, "Missed deadlines").
                # Controller steps after the last applied command were not applied; the
                # steps between the last one known to match and now that it never took
                # (it fell behind the clock) were followed on the candidate too.
                unapplied = sum(1 for s in ran if s > executed)
                coasted = k - 1 - max(synced, executed) - unapplied
                if me in tick.braked or not ctrl.rewind(unapplied, coasted):
                    if behind != "braked":  # logged once a braking episode
                        log(role, f"step {k}: robot braked after step {executed}; starting again where it is")
                    behind, joined, x_est = "braked", False, None
                else:
                    if not behind:
                        log(role, f"step {k}: commands after step {executed} not applied; on its candidate")
                    behind = behind or "candidate"
            elif executed is None:
                behind, rejoined = "", False
            synced, ran = k - 1, []
            if tick.stop:
                break
            if k == 0 and lockstep:
                # The tracker started the clock once every agent was live in its view;
                # wait (bounded) until they are in this agent's view too.  Otherwise who
                # counts as live at step 1, a neighbour or a dead robot's static disc,
                # would depend on how fast the liveliness tokens travelled.
                inbox.wait(lambda: set(others) <= inbox.live, args.timeout)
            # Own measurement of step k, then the live neighbours' plans of step k − 1.
            # Realtime: neither may hold up this step's deadline; a withheld message
            # (fault plan) is never waited for.  In mesh the plans come by callback,
            # not by a drain at the start of the step: a plan a little late is then
            # still used, where that drain would count it stale, and under load the
            # growing discs kept robots from their goals (a 3-robot realtime run
            # across hosts, 60 s).  In realtime relay, own pose and odometry come just
            # before the tick on one link and are drained, and the digest came by
            # callback in the second half of the last step (_Link).
            limit = args.timeout if lockstep else 0.3 * p.Ts
            wait = inbox.drain_until if link.drained else inbox.wait
            wait(partial(_measured, inbox, me, k), limit)
            if k > 0:
                plans_in = _relayed if relay else _plans_in
                wait(partial(plans_in, inbox, others, k - 1), limit)
            with inbox.cond:
                pose = inbox.get(Pose, me, k)
                odom = inbox.get(Odom, me, k)
                # Plans of step k − 1, and of no later step than each robot side executed
                # (Tick.fallback, Tick.braked): a plan whose command missed its deadline
                # was never executed, and its robot keeps to the plan before.
                fresh: dict[str, Plan | None] = {}
                for j in others:
                    pl = inbox.get(Plan, j, k - 1) if k - 1 not in withdrawn[j] else None
                    fresh[j] = pl
                    if pl is None:  # the newest plan of step ≤ k − 1: what arrived later must not count
                        pl = inbox.newest(Plan, j, k - 1, withdrawn[j])
                    if pl is not None and ((had := last.get(j)) is None or had.step < pl.step):
                        last[j] = pl
                live = set(inbox.live)
                goal = inbox.get(Goal, me)
            if pose is not None and odom is not None:
                x = measured_state(
                    np.array([pose.x, pose.y, pose.theta]), np.array([odom.vx, odom.vy]), p.lookahead
                )
                if blind > args.blind_steps:
                    log(role, f"step {k}: measurements back after {blind} steps; planning again")
                blind = 0
                if not joined and k > 0:
                    # (Re)joining a running fleet: start at rest where the robot is.
                    ctrl.reset(x[[0, 2]])
                    if not rejoined:  # once a braking episode: it starts again at each of its steps
                        log(role, f"joined at step {k} at ({x[0]:.3f}, {x[2]:.3f})")
                    rejoined = behind == "braked"
                joined = True
            elif x_est is not None:
                blind += 1
                x = design.A @ x_est + design.B @ a_prev  # the nominal model's prediction
                if blind == args.blind_steps + 1:
                    log(role, f"step {k}: no pose for {blind} steps; braking and holding")
            else:
                # Not joined yet and nothing measured: keep the robot still, commit nothing.
                pub_cmd.put(Command(robot=me, step=k, ax=0.0, ay=0.0).encode())
                k += 1
                continue
            if goal is not None and goal is not goal_seen:
                goal_seen = goal
                problem = goal_problem(scn, design.footprint, goal.goal, [pl for pl in last.values() if pl])
                if problem is not None:
                    log(role, f"goal {goal.goal.round(3).tolist()} rejected: {problem}")
                elif not np.array_equal(goal.goal, ctrl.goal):
                    ctrl.set_goal(goal.goal)
                    log(role, f"new goal {goal.goal.round(3).tolist()} at step {k}")
            nbs, hazards = guard.classify(k, others, fresh, last, live, starts, set(tick.braked))
            out = ctrl.hold(x) if blind > args.blind_steps else ctrl.step(x, nbs, hazards)
            ran.append(k)
            x_est, a_prev = x, out.a
            # The command first: the robot side waits on it; the neighbours need the
            # plan only at the next step, which cannot start before the robots move.
            pub_cmd.put(
                Command(
                    robot=me, step=k, ax=float(out.a[0]), ay=float(out.a[1]),
                    fallback=blind <= args.blind_steps, x_next=out.x_next, v_next=out.v_next,
                ).encode()
            )  # fmt: skip
            info = ctrl.info()
            pub_plan.put(
                Plan(
                    robot=me, step=k, t0=(k + 1) * p.Ts, Ts=p.Ts, committed=out.committed, nominal=out.plan,
                    footprint=design.footprint, priority=spec.priority, rank=rank, phase=info.phase,
                    target=out.target, goal=ctrl.goal, status=out.status, solve_time=out.solve_time,
                    tube_ok=out.tube_ok,
                ).encode()
            )  # fmt: skip
            inbox.prune(k - 2)
            if link.drained and blind <= args.blind_steps:  # realtime relay, not holding blind:
                _steer_ahead(ctrl, inbox, others, withdrawn, last, starts, k, p.Ts)  # off the deadline's path
            k += 1
    finally:
        c = ctrl.counters
        log(
            role,
            f"stopped after {k} steps: {c.solves} solves, {c.fallbacks} fallbacks, "
            f"{c.tube_exits} tube exits, {c.holds} blind holds, {c.unapplied} steps on the candidate, "
            f"{c.ahead} steered ahead, "
            f"{guard.hazard_steps} neighbour-steps "
            f"kept clear of as static discs ({guard.transitions} changes), {inbox.injected} injected faults, "
            f"{inbox.rejects.total} rejected payloads",
        )
        link.close()
    return 0


class _Link:
    """The agent's side of Zenoh: session, subscriptions, publishers, liveliness token."""

    def __init__(self, args: argparse.Namespace, keys: Keys, me: str, role: str):
        self.args, self.keys, self.me, self.role = args, keys, me, role
        self.open()

    def open(self) -> None:
        args, keys, me = self.args, self.keys, self.me
        self.session = open_session(args)
        self.inbox = inbox = Inbox(keys, self.role, fault_plan(args))
        # Realtime with relayed plans: the tracker sends this robot's pose and
        # odometry just before the tick, batched on one link, so they are in when
        # the tick is.  They are then taken from Zenoh's queues after the tick
        # (Inbox.drain) instead of by a callback each: two wake-ups and GIL
        # hand-overs a step fewer in the race to the deadline.  The digest of
        # step k − 1 comes half a step before tick k, once the tracker has the
        # commands of k − 1, and is decoded by callback then, while the cores
        # are idle (docs/runtime-notes.md, "Relayed plans").
        drained = self.drained = args.clock == "realtime" and args.exchange == "relay"
        self.subs = [
            inbox.subscribe(self.session, keys.pose(me), Pose, keep=True, drained=drained),
            inbox.subscribe(self.session, keys.odom(me), Odom, keep=True, drained=drained),
            # The neighbours' plans: each on its own key (mesh), or a step's plans
            # at once in the tracker's digest (relay: one message a step).
            inbox.subscribe(self.session, keys.digest, Digest, keep=True)
            if args.exchange == "relay"
            else inbox.subscribe(self.session, keys.plan(), Plan, keep=True, remote=True),
            inbox.subscribe(self.session, keys.goal(me), Goal),
            inbox.subscribe(self.session, keys.clock, Tick),
            inbox.watch_liveliness(self.session),
        ]
        self.pub_plan = publisher(self.session, keys.plan(me))
        self.pub_cmd = publisher(self.session, keys.cmd(me))
        # A peer that joins a running fleet drops what it publishes until it has
        # heard the others' subscriptions; the tracker waits for the commands of
        # every live agent, so become live only once the commands have a taker.
        if not _wait_matching(self.pub_cmd, args.timeout):
            log(self.role, f"nobody subscribes to {keys.cmd(me)} within {args.timeout} s; going live anyway")
        self.token = self.session.liveliness().declare_token(keys.alive(me))

    def close(self) -> None:
        self.token.undeclare()
        for sub in self.subs:
            sub.undeclare()
        self.session.close()


class Guard:
    """Sorts the other robots, each step, into neighbours and hazards (DESIGN §5, "Timing").

    * A live robot whose plan of step k − 1 is in is a *neighbour*: the split rule.
    * A live robot whose latest plan is m ≥ 1 steps older (lost or late) is a
      *hazard*: a static disc around its last known committed point ĉ_j of
      radius r_j + (m + 1)·√2·ε, since its appended point moves at most ε per
      axis a step.
    * A dead robot (liveliness gone; its robot side brakes it) is a hazard of
      radius r_j + max(N, m + 1)·√2·ε + v_max²/(2 a_max): wherever its reference was
      when it died is within that of ĉ_j, and braking adds the stopping distance.
    * At step 0 every robot is a neighbour at its scenario start, as in
      ``fleet simulate``.

    The disc rule alone keeps the appended points R apart whatever the other
    robot does, so mixing it with a neighbour's split rule is safe.  Changes
    are logged the first time each, then only counted."""

    def __init__(self, me: str, design: Any):
        p = design.params
        self.me = me
        self.eps = math.sqrt(2.0) * p.epsilon
        """Euclidean reach of one step [m]: ȳ moves at most ε per axis (the QP's ε box)."""
        self.N = p.horizon
        self.brake = p.v_max**2 / (2.0 * p.a_max)
        self.hazard_steps = 0
        self.transitions = 0
        self._state: dict[str, str] = {}
        self._logged: set[tuple[str, str, str]] = set()

    def classify(
        self, k: int, others: list[str], fresh: dict[str, Plan | None], last: dict[str, Plan | None],
        live: set[str], starts: dict[str, NeighbourInfo], braked: frozenset[str] | set[str] = frozenset(),
    ) -> tuple[list[NeighbourInfo], list[Hazard]]:  # fmt: skip
        """(neighbours, hazards) for step k from the plans of step k − 1 (``fresh``),
        the latest plans (``last``), the live set and the robots their robot side braked
        over step k − 1 (Tick.braked): those have left their plans as a dead robot's has."""
        nbs: list[NeighbourInfo] = []
        hazards: list[Hazard] = []
        for j in others:
            pl = fresh.get(j)
            if k == 0:
                nbs.append(starts[j])
                continue
            if pl is not None and j in live and j not in braked:
                nbs.append(_neighbour(pl))
                if self._state.get(j, "neighbour") != "neighbour":
                    self._note(j, "neighbour", k)
                continue
            old = last.get(j)
            centre, since, r_j = (
                (starts[j].last_point, -1, starts[j].footprint) if old is None
                else (old.committed[-1], old.step, old.footprint)
            )  # fmt: skip
            m = max(k - 1 - since, 0)
            if j in live and j not in braked:
                radius = r_j + (m + 1) * self.eps
                info = _neighbour(old) if old is not None else starts[j]
                self._note(j, "stale", k)
            else:
                radius = r_j + max(self.N, m + 1) * self.eps + self.brake
                info = None
                self._note(j, "dead" if j not in live else "braked", k)
            hazards.append(Hazard(j, np.array(centre, dtype=float), radius, info))
        self.hazard_steps += len(hazards)
        return nbs, hazards

    def _note(self, j: str, state: str, k: int) -> None:
        before = self._state.get(j, "neighbour")
        self._state[j] = state
        if state == before or (state == "stale" and before in ("dead", "braked")):
            return
        self.transitions += 1
        if (j, state, before) in self._logged:
            return  # each kind of change is logged once per neighbour, then counted
        self._logged.add((j, state, before))
        what = {
            "neighbour": "coordinating again",
            "stale": "its plan is late or lost; kept clear of as a growing static disc",
            "dead": "not alive; kept clear of as a static obstacle while its robot stops",
            "braked": "braked by its robot side; kept clear of as a static obstacle while it stops",
        }[state]
        log(f"agent {self.me}", f"step {k}: {j}: {what}")


def goal_problem(scn: Any, footprint: float, goal: np.ndarray, plans: list[Plan]) -> str | None:
    """Why a goal (2,) [m] given at run time cannot be accepted, or None.

    It must clear the walls and obstacles by the footprint radius [m] and park
    at least the two footprints away from every neighbour's current goal."""
    try:
        check_point(scn, goal, footprint, "goal")
    except ConfigError as e:
        return e.reason
    for pl in plans:
        d = float(np.linalg.norm(goal - pl.goal))
        if d < footprint + pl.footprint:
            need = footprint + pl.footprint
            return f"{d:.3f} m from {pl.robot}'s goal, closer than the footprints allow ({need:.3f} m)"
    return None


def _wait_matching(pub: Any, timeout: float) -> bool:
    """Wait until ``pub`` has a matching subscriber, for at most ``timeout`` [s]."""
    matched = threading.Event()
    listener = pub.declare_matching_listener(lambda status: matched.set() if status.matching else None)
    try:
        return bool(pub.matching_status) or matched.wait(timeout)
    finally:
        listener.undeclare()


def _measured(inbox: Inbox, me: str, k: int) -> bool:
    """This robot's pose and odometry of step k are in, or withheld by the fault plan."""
    return all(inbox.get(t, me, k) is not None or inbox.lost(t, me, k) for t in (Pose, Odom))


def _plans_in(inbox: Inbox, others: list[str], step: int) -> bool:
    """Every live neighbour's plan of ``step`` has arrived (or was withheld by the fault plan)."""
    return all(
        inbox.get(Plan, j, step) is not None or inbox.lost(Plan, j, step) for j in others if j in inbox.live
    )


def _relayed(inbox: Inbox, others: list[str], step: int) -> bool:
    """The tracker's digest of ``step`` has arrived: what it lacks is late or lost."""
    d = inbox.get(Digest, "tracker")
    return d is not None and d.step >= step


def _steer_ahead(
    ctrl: TubeMPC, inbox: Inbox, others: list[str], withdrawn: dict[str, set[int]],
    last: dict[str, Plan | None], starts: dict[str, NeighbourInfo], k: int, limit: float,
) -> bool:  # fmt: skip
    """Choose the target of step k + 1 (:meth:`TubeMPC.steer_ahead`) once the
    neighbours' plans of step k are in: the tracker relays them once it has the
    commands of step k, half a step before tick k + 1, while the cores are idle.
    The navigator plans around every live robot's newest executed plan (else the last
    one the step used, else its start), as the step would.  Waits at most ``limit``
    [s]; skipped (False) if tick k + 1 or nothing comes first: the step then steers
    itself."""
    inbox.wait(lambda: _relayed(inbox, others, k) or _tick_at_least(inbox, k + 1), limit)
    with inbox.cond:
        if _tick_at_least(inbox, k + 1) or not _relayed(inbox, others, k):
            return False
        plans = {j: inbox.newest(Plan, j, k, withdrawn[j]) for j in others if j in inbox.live}
    known = {j: pl or last.get(j) for j, pl in plans.items()}
    ctrl.steer_ahead([starts[j] if pl is None else _neighbour(pl) for j, pl in known.items()])
    return True


def _tick_at_least(inbox: Inbox, k: int) -> bool:
    t = inbox.get(Tick, "tracker")
    return t is not None and (t.stop or t.step >= k)
