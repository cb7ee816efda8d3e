"""The agent process: one robot's tube MPC (:class:`agent.controller.TubeMPC`) on the fleet's bus.

``python -m agent --scenario S --robot ID [--fleet F] [--connect E] [--listen E]``

At step k the agent waits for the tracker's tick k, its own pose and odometry of step k and the
plans that the live neighbours committed at step k − 1 (liveliness says who is live; every wait
is bounded).  The plans come on the neighbours' keys (``--exchange mesh``), on the keys of the
cells about this robot's (``place``: only the neighbours in reach, :meth:`Agent._reach`) or
together in the tracker's digest of step k − 1 (``relay``).  It then steps the controller and publishes its
command and its plan for step k (:mod:`agent.protocol`).  A neighbour whose plan of step k − 1
does not arrive in time is kept clear of as a growing disc (:class:`agent.hazards.Guard`).  When
the tick says the robot side did not apply the agent's last commands, the agent takes the plan
the robot executed (:meth:`TubeMPC.rewind`) or, if the robot braked, starts again where it is
(docs/design.md, "Missed deadlines").

With ``--delay-compensation`` the agent plans a step ahead (docs/design.md, "Delay
compensation"): at tick k it only applies the ancillary law of the plan of step k, made during
step k − 1, to its measurement and publishes the command, from the Zenoh callback that brings
the last of tick k, its pose and its odometry (the main thread is not woken for it); once the
tracker's outcome of step k says which plans are in force, it makes its plan of step k + 1 from
the prediction A x_k + B u_k against the neighbours' plans of step k, and publishes it.  A step
with no such plan (the first, or after the robot braked) plans from the measurement as above,
then ahead.

Goals at run time come on ``fleet/F/goal/ID``: published (``fleet goal``), or as a query (a
script), which the agent answers with a msgpack map, ``{"ok": true}`` or ``{"ok": false,
"reason": "<one line>"}`` (a payload that is not a valid Goal for this robot is counted with the
rejected payloads and answered as an error, ``reply_err``, with the same map).  Either way the
goal is checked by the one goal rule (:func:`ground.scenario.goal_problem`): against the walls,
the obstacles, a passage from the robot's committed point and the other robots' goals (those of
the goal's ``batch`` in place of theirs), and an accepted one is taken by the first plan the agent makes
after it (planning ahead, the plan of the step after next: :attr:`Agent.pending`).
``--scripted``: a script may hold the clock for as long as it likes; no tick for ``--timeout``
then ends the agent only once the tracker is gone too (its liveliness token).
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import threading
import time
from collections.abc import Collection
from functools import partial
from typing import Any

import numpy as np

from agent.controller import SNAPSHOTS, StepOutput, TubeMPC
from agent.coordination import PLACE_LAG, VIEW_CELLS, NeighbourInfo, navigator_view, place_side
from agent.hazards import Guard, in_reach, loose, neighbour_of, starts_of
from agent.protocol import (
    PlannedAhead,
    candidate_input,
    command_message,
    plan_ahead,
    plan_ahead_message,
    plan_message,
)
from agent.tube import validated_design
from ground.arrival import arrival
from ground.geometry import (
    Cell,
    Whereabouts,
    block,
    cell_name,
    cell_of,
    controlled_point,
    measured_state,
)
from ground.scenario import ConfigError, Scenario, goal_problem, load_scenario
from ground.wire import (
    LINK_DOWN,
    Command,
    Digest,
    Goal,
    Keys,
    LinkState,
    Odom,
    Outcome,
    Plan,
    Pose,
    Tick,
    WireError,
    decode,
    remember_steps,
)
from transport.bus import Inbox, goal_reply, open_session, publisher, put
from transport.process import add_common_args, announce, exchange_for, fault_plan, log

REJOIN_GAP = 5
"""Steps missed (0.5 s at Ts = 0.1 s, the link watchdog's time) after which an agent re-initialises."""
TRACKER = "tracker"
"""The tracker's id: the sender of the ticks, and its liveliness token in a scripted run."""
UNMEASURED_SAY = 50
"""Steps without a state to plan from after which the agent says why it cannot join (once)."""


def main(argv: list[str] | None = None) -> int:
    """``python -m agent``: run one robot's agent until the run ends (see the module docstring);
    returns the exit code (0 once the run has stopped, 1 if no tick came for ``--timeout``, 2 bad
    input)."""
    ap = argparse.ArgumentParser(prog="python -m agent", description=__doc__.splitlines()[0])
    add_common_args(ap)
    ap.add_argument("--robot", required=True, help="robot id from the scenario")
    ap.add_argument(
        "--blind-steps", type=int, default=3,
        help="steps to run on the nominal model's prediction when poses stop (then brake and hold)",
    )  # fmt: skip
    ap.add_argument(
        "--scripted", action="store_true",
        help="a script drives the run and may hold the clock: without a tick for --timeout, wait on "
        "while the tracker is alive (its liveliness token)",
    )  # fmt: skip
    args = ap.parse_args(argv)
    args.exchange = exchange_for(args.clock, args.exchange)
    try:
        scn = load_scenario(args.scenario)
        ids = [r.id for r in scn.robots]
        if args.robot not in ids:
            raise ConfigError("--robot", f"{args.robot!r} is not in the scenario (robots: {', '.join(ids)})")
        design = validated_design(scn)
    except ConfigError as e:
        print(f"agent: error: {e}", file=sys.stderr)
        return 2
    agent = Agent(args, scn, design)
    announce("agent", robot=args.robot)
    try:
        while (code := agent.step()) is None:
            pass
        return code
    finally:
        agent.close()


class Agent:
    """One robot's agent: its controller, its link to the bus, and what it knows of the others."""

    def __init__(self, args: argparse.Namespace, scn: Scenario, design: Any):
        self.args, self.scn, self.design = args, scn, design
        self.me = me = args.robot
        self.role = f"agent {me}"
        ids = [r.id for r in scn.robots]
        self.rank = rank = ids.index(me)
        spec = scn.robots[rank]
        p = self.p = design.params
        gate = arrival(scn, design.footprint).gates.get(me) if p.deadlock else None
        self.ctrl = TubeMPC(
            design, controlled_point(spec.start, p.lookahead), np.array(spec.goal, dtype=float), scn.arena,
            obstacles=scn.obstacles, priority=spec.priority, rank=rank,
            seed=scn.simulation.seed * 1000 + rank, gate=gate,
        )  # fmt: skip
        self.keys = Keys(args.fleet)
        self.plans_ahead = bool(args.delay_compensation)
        """Plan a step ahead (delay compensation; docs/design.md, "Delay compensation")."""
        self.ready: PlannedAhead | None = None
        """The plan made ahead, for Zenoh's callback to answer its tick with (under inbox.cond)."""
        self.answered: tuple[int, np.ndarray] | None = None
        """The step the callback answered and the acceleration (2,) [m/s²] it sent (under inbox.cond)."""
        self.on_arrival = 0
        """Commands made ahead and put as soon as their step's tick, pose and odometry were in
        (:meth:`_command_on_arrival`): by a Zenoh callback, or by the main thread when the tick came before
        the plan was made, or while it drained the pose and odometry itself."""
        self.by_callback = 0
        """Of those, the commands put by a Zenoh callback."""
        self.place = args.exchange == "place"
        """Plans by place (docs/design.md, "Plans by place"): an agent takes the plans of the
        cells about its own, and coordinates with the robots in reach (:meth:`_reach`)."""
        self.side = place_side(design.footprint, p.epsilon, p.priority_share) if self.place else None
        """The side of the cells [m] (:func:`agent.coordination.place_side`), or None."""
        self.link = _Link(
            args,
            self.keys,
            me,
            self.role,
            self._command_on_arrival if self.plans_ahead else None,
            tracked=spec.link == "sim",
            side=self.side,
            start=controlled_point(spec.start, p.lookahead),
        )
        self.inbox = self.link.inbox
        if self.side is not None:  # the navigator acts only on robots it is sure to see
            self.ctrl.nav.view = navigator_view(self.side, p.epsilon) - 2 * design.footprint
        self.others = [r for r in ids if r != me]
        self.starts = starts_of(scn.robots, p.lookahead, design.footprint)
        self.guard = Guard(me, p, partial(log, self.role), side=self.side)
        self.k = 0
        self.joined = False
        self.x_est: np.ndarray | None = None
        self.a_prev = np.zeros(2)
        self.blind = 0
        self.goal_seen: Goal | None = None
        self.pending: list[tuple[int, Goal]] = []
        """Goals queries gave and the agent accepted, in order, each with the first step whose
        plan takes it (under inbox.cond): the step after the newest tick when it came, or with
        delay compensation the one after that, since that step's plan may be under way already
        (made ahead), as ``fleet simulate`` takes a goal given at sample k at the plan of step
        k + 1.  Only the newest goal per step is kept."""
        self.held = False
        """The clock has been held past --timeout (scripted; logged once a hold)."""
        self.links: dict[str, LinkState | None] = {}
        """The newest link state of each other robot (real and emulated robots only)."""
        self.last: dict[str, Plan | None] = {}
        self.lockstep = args.clock == "lockstep"
        self.relay = args.exchange == "relay"
        self.silent_since = time.monotonic()
        self.synced = -1
        """The robot side executed this controller's plans up to this step."""
        self.ran: list[int] = []
        """Steps after ``synced`` at which the controller stepped."""
        self.rejoined = False
        """Joined again in this braking episode (logged once)."""
        self.withdrawn: dict[str, set[int]] = {j: set() for j in self.others}
        """Per neighbour, recent steps whose plan was never executed (its command was not applied)."""
        self.behind = ""
        """What the robot side did instead of this agent's last commands: "" (applied them),
        "candidate" or "braked"; each episode is logged once."""
        self.ahead: PlannedAhead | None = None
        """The plan made ahead for the next step (the main thread's; ``ready`` is the callback's)."""
        self.reported = -1
        """The newest step whose outcome (what the robot sides did) has been taken."""
        self.sent: dict[int, StepOutput] = {}
        """The controller outputs of the recent commands sent, by step: with delay compensation
        the agent predicts what its robot side applied when it followed one's candidate."""
        self.places: dict[str, Whereabouts] = {}
        """The place tokens as :meth:`_reach` last read them (with plans by place)."""
        self.unmeasured = 0
        """Steps in a row without a state to plan from (not joined, nothing measured)."""
        self.cut_since: int | None = None
        """The step this robot's radio link was found down at, while it is (None: up)."""
        self.link.go_live(self._answer_goal)

    def step(self) -> int | None:
        """One step: wait for the tick, measure, plan, publish.  None to go on; the exit code
        once the run has stopped (0) or no tick came for ``--timeout`` (1)."""
        args, inbox, k = self.args, self.inbox, self.k
        if not inbox.wait(partial(self._step_may_go, k), 1.0):
            with inbox.cond:
                now = time.monotonic()
                seen = {f"{t}/{r}": round(now - at, 1) for (t, r), at in inbox.arrived.items()}
                alive = sorted(inbox.live)
                put = self.answered is not None and self.answered[0] == k
            if now - self.silent_since >= args.timeout:
                awaited = f"outcome of step {k} nor tick {k + 1}" if put else f"tick {k}"
                if args.scripted and TRACKER in alive:  # the script holds the clock
                    if not self.held:
                        log(self.role, f"no {awaited} for {args.timeout} s: held by the script, waiting")
                    self.held = True
                    return None
                log(
                    self.role,
                    f"no {awaited} within {args.timeout} s; stopping (live {alive}; s since: {seen})",
                )
                return 1
            return None
        self.silent_since = time.monotonic()
        self.held = False
        with inbox.cond:
            tick = inbox.get(Tick, "tracker")
            put = self.answered is not None and self.answered[0] == k
        assert tick is not None
        if put:  # tick k came and was answered: step k goes on, whatever came since (the stop)
            inbox.release(k)
        else:
            self._follow_clock(tick)
            if tick.stop:
                return 0
        k = self.k
        self._die_if_planned(k)
        if k == 0 and self.lockstep:
            # The tracker started the clock once every agent was live in its view; wait
            # (bounded) until they are in this agent's view too.  Otherwise who counts as live
            # at step 1, a neighbour or a dead robot's static disc, would depend on how fast
            # the liveliness tokens travelled.
            inbox.wait(lambda: set(self.others) <= inbox.live, args.timeout)
        x, answered = self._measure(k)
        ahead, self.ahead = self.ahead, None
        cut = self._cut(k)
        if ahead is not None and ahead.step == k and self.joined and not cut:
            # The plan of step k, made during step k − 1: apply it to x, the ancillary law,
            # unless Zenoh's callback did so already, on the same pose and odometry.
            assert x is not None
            a = answered[1] if answered is not None and answered[0] == k else self._put_command(ahead, x)
            self.x_est, self.a_prev, self.sent[k] = x, a, ahead.out
            inbox.prune(k - 2)
            self._plan_ahead(k, x, a)
            self.k += 1
            return None
        fresh, live, goal, reach = self._neighbours(k, tick.braked)
        if x is None:
            # Not joined yet and nothing measured: keep the robot still, commit nothing.
            self.link.pub_cmd.put(Command(robot=self.me, step=k, ax=0.0, ay=0.0, brake=True).encode())
            self.unmeasured += 1
            if self.unmeasured == UNMEASURED_SAY:
                with inbox.cond:
                    pose, odom = inbox.get(Pose, self.me), inbox.get(Odom, self.me)
                newest = {
                    t.TYPE: "none" if m is None else f"step {m.seq}" for t, m in ((Pose, pose), (Odom, odom))
                }
                log(
                    self.role,
                    f"step {k}: cannot join: no pose and odometry of its own of the same step for "
                    f"{self.unmeasured} steps (newest {newest}); the robot is held braked",
                )
            self.k += 1
            return None
        self.unmeasured = 0
        self._goals(goal, k)
        ctrl, blind = self.ctrl, self.blind > args.blind_steps
        nbs, hazards = self._classify(k, reach, fresh, live, tick.braked)
        if cut:
            out = ctrl.hold(x, LINK_DOWN)
        else:
            out = ctrl.hold(x) if blind else ctrl.step(x, nbs, hazards, seen=self._seen(reach, tick.braked))
        self.ran.append(k)
        self.x_est, self.a_prev = x, out.a
        # The command first: the robot side waits on it; the neighbours need the plan only at
        # the next step, which cannot start before the robots move.
        command = command_message(self.me, k, ctrl, out, follow=not (blind or cut), brake=blind)
        self.link.pub_cmd.put(command.encode())
        self.link.put_plan(plan_message(self.me, k, ctrl, out, self.inbox.heard_late))
        inbox.prune(k - 2)
        if self.plans_ahead and not cut:
            self.sent[k] = out
            self._plan_ahead(k, x, out.a)
        elif self.link.drained and not (
            blind or cut
        ):  # realtime relay, not holding blind: off the deadline's path
            _steer_ahead(ctrl, inbox, self.others, self.withdrawn, self.last, self.starts, k, self.p.Ts)
        self.k += 1
        return None

    def _plan_ahead(self, k: int, x: np.ndarray, a: np.ndarray) -> None:
        """Delay compensation: once the outcome of step k is in, make the plan of step k + 1
        from the prediction A x + B u (``x`` (4,) [m, m/s] the state of step k, ``a`` (2,)
        [m/s²] the command sent for it) and publish it (docs/design.md, "Delay compensation").

        Nothing is made ahead if the outcome is lost, or does not come before tick k + 1 on the
        realtime clock (that tick says the same, and step k + 1 plans from the measurement), if
        the robot braked (it starts again where it is), or after ``--blind-steps`` steps without
        poses.  If the robot side followed the candidate instead, the agent takes
        it too (:meth:`_take_report`), and the robot's input was the ancillary law on it."""
        args, inbox, me, ctrl = self.args, self.inbox, self.me, self.ctrl
        limit = args.timeout if self.lockstep else self.p.Ts
        inbox.wait(partial(self._outcome_known, k), limit)
        with inbox.cond:
            outcome = inbox.get(Outcome, TRACKER)
        if outcome is None or outcome.step != k:
            return
        self._take_report(k + 1, outcome)
        for s in [s for s in self.sent if s < k - 2 * SNAPSHOTS]:
            del self.sent[s]
        if not self.joined or self.blind >= max(args.blind_steps, 1) or self._cut(k + 1):
            # Braked: it starts again where it stands.  Without poses for --blind-steps steps:
            # the next step decides, on its own pose or its absence, to plan or to hold.  Its
            # robot's link down: nothing it plans reaches the robot (the next step holds).
            return
        j = outcome.executed(me)
        if j is not None:  # the robot side followed the candidate of its command of step j
            a_j = candidate_input(ctrl, self.sent.get(j), j, k, x)
            a = self.a_prev = ctrl.ancillary(x) if a_j is None else a_j  # (the same, to rounding)
        x_hat = ctrl.xi[0:4]  # the plan the command was applied about (replaced, never changed)
        fresh, live, goal, reach = self._neighbours(k + 1, outcome.braked)
        self._goals(goal, k + 1)
        nbs, hazards = self._classify(k + 1, reach, fresh, live, outcome.braked)
        out, tube_ok = plan_ahead(ctrl, x, a, x_hat, nbs, hazards, seen=self._seen(reach, outcome.braked))
        self.ran.append(k + 1)
        self.ahead = ready = PlannedAhead.of(me, k + 1, ctrl, out)
        with inbox.cond:  # ready before the plan goes out
            self.ready = ready
            self._command_on_arrival(None)  # tick k + 1 may be in already (it does not wait for this plan)
        self.link.put_plan(plan_ahead_message(me, k + 1, ctrl, out, tube_ok, self.inbox.heard_late))

    def _classify(
        self, k: int, reach: list[str], fresh: dict[str, Plan | None], live: set[str], braked: Collection[str]
    ) -> tuple[list[NeighbourInfo], list[Any]]:
        """The neighbours and the discs of step k (:meth:`Guard.classify`), with the camera poses
        of the robots off their plans that it watches; then subscribe to the poses of those it
        watches now, and drop the rest."""
        guard, inbox, lookahead = self.guard, self.inbox, self.p.lookahead
        poses: dict[str, tuple[int, np.ndarray]] = {}
        with inbox.cond:
            for j in self.link.poses:
                pose = inbox.get(Pose, j)
                if pose is not None:
                    poses[j] = (pose.seq, controlled_point((pose.x, pose.y, pose.theta), lookahead))
        out = guard.classify(
            k, reach, fresh, self.last, live, self.starts, set(braked), self.links, self.places, poses
        )
        self.link.watch_poses(guard.watched)
        return out

    def _die_if_planned(self, k: int) -> None:
        """The fault plan kills this agent at step k or before (:attr:`transport.faults.FaultPlan.kills`):
        it sends itself SIGKILL, a hard death, before anything of step k goes out."""
        plan = self.inbox.faults
        if plan is not None and plan.kills.get(self.me, k + 1) <= k:
            log(self.role, f"step {k}: killed by the fault plan (SIGKILL)")
            sys.stderr.flush()
            os.kill(os.getpid(), signal.SIGKILL)

    def _cut(self, k: int) -> bool:
        """This robot's radio link is down, or back with the robot held until the step its agent
        starts again at (:class:`~ground.wire.LinkState`): the robot drives on (or stands)
        uncontrolled, and nothing planned now reaches it.  Logged once an outage."""
        with self.inbox.cond:
            ls = self.inbox.get(LinkState, self.me)
        cut = ls is not None and (not ls.up or k < ls.back)
        if cut and self.cut_since is None:
            self.cut_since = k
            log(
                self.role,
                f"step {k}: the robot's link is down; it drives on uncontrolled, so nothing is "
                "solved until the link is back",
            )
        elif not cut and self.cut_since is not None:
            log(self.role, f"step {k}: the robot's link is back after {k - self.cut_since} steps")
            self.cut_since = None
        return cut

    def _outcome_known(self, k: int) -> bool:
        """The outcome of step k is in, or lost (fault plan); on the realtime clock, or the next
        tick came first (it says the same).  In lockstep the tracker always sends the outcome,
        but the next tick may come first (another publisher), and which way the agent plans
        must not depend on that (inbox.cond held)."""
        lost = self.inbox.lost(Outcome, TRACKER, k)
        late = not self.lockstep and _tick_at_least(self.inbox, k + 1)
        return lost or late or _outcome_at_least(self.inbox, k)

    def _step_may_go(self, k: int) -> bool:
        """What the main loop waits for at step k (inbox.cond held): tick k, or the stop.  If
        Zenoh's callback put the command of step k (:meth:`_command_on_arrival`), there is nothing to do
        until the step's outcome (:meth:`_outcome_known`): the main threads of a fleet then stay asleep
        while its commands are on their way."""
        answered = self.answered
        if answered is None or answered[0] != k:
            return _tick_at_least(self.inbox, k)
        return self._outcome_known(k) or _tick_at_least(self.inbox, k + 1)

    def _command_on_arrival(self, _: Any) -> None:
        """Delay compensation, called by the inbox as a tick, pose or odometry is stored (a Zenoh
        thread, inbox.cond held): once those of the step planned ahead are all in, put its
        command, the ancillary law applied to that pose and odometry, here and now.  The main
        thread is not woken for it; it does the rest of the step (:meth:`step`)."""
        ready = self.ready
        if ready is None:  # (also while the link is being made: no inbox yet)
            return
        inbox, me = self.inbox, self.me
        if not _tick_is(inbox, ready.step):
            return
        self._die_if_planned(ready.step)
        if self.link.drained:  # realtime: its pose and odometry came just before the tick
            inbox.drain()  # (their own calls of this find the tick and may answer first)
            if self.ready is not ready:
                return
        pose, odom = inbox.get(Pose, me, ready.step), inbox.get(Odom, me, ready.step)
        if pose is None or odom is None:
            return
        x = measured_state((pose.x, pose.y, pose.theta), (odom.vx, odom.vy), self.p.lookahead)
        a = self._put_command(ready, x)
        self.ready, self.answered = None, (ready.step, a)  # (if the put failed, the main thread answers)
        self.on_arrival += 1
        if threading.current_thread() is not threading.main_thread():
            self.by_callback += 1

    def _put_command(self, ready: PlannedAhead, x: np.ndarray) -> np.ndarray:
        """Put the command of the plan made ahead, ``ready``, for the state ``x`` (4,) [m, m/s]
        of its step; returns the acceleration u = v̂ + K(x − x̂) (2,) [m/s²] it carries."""
        command, a = ready.command_for(x)
        self.link.pub_cmd.put(command.encode())
        return a

    def _follow_clock(self, tick: Tick) -> None:
        """Catch up with tick ``tick.step``, and take what it says the robot sides executed."""
        me, k = self.me, self.k
        if tick.step > k:
            if self.joined and tick.step > k + REJOIN_GAP and tick.executed(me) is None:
                # Hung for a while, and the clock does not say what the robot did (a camera
                # tracker without epuck_link's report): start again from where the robot is,
                # like a restarted agent.  The robot sides say (below).
                self.joined, self.x_est = False, None
            if self.joined and not tick.stop:
                log(self.role, f"fell behind the clock: step {k} → {tick.step}")
            self.k = k = tick.step
        self.inbox.release(k)
        if self.reported < k - 1:  # not told yet by the outcome of step k − 1
            self._take_report(k, tick)

    def _take_report(self, k: int, report: Tick | Outcome) -> None:
        """Take what the robot sides did up to step k − 1 (``report``: tick k, or the outcome of
        step k − 1): skip the plans never executed, and take the candidate the robot followed
        instead of this agent's commands, or start again where it braked."""
        me = self.me
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
        executed = report.executed(me)
        if self.joined and executed is not None:
            # The robot side did not apply the command of step k − 1.  It followed the shifted
            # candidate of its last applied command (or braked): do the same.  Controller steps
            # after the last applied command were not applied; the steps between the last one
            # known to match and now that it never took (it fell behind the clock) were
            # followed on the candidate too.
            unapplied = sum(1 for s in self.ran if s > executed)
            coasted = k - 1 - max(self.synced, executed) - unapplied
            if me in report.braked or not self.ctrl.rewind(unapplied, coasted):
                if self.behind != "braked":  # logged once a braking episode
                    log(
                        self.role, f"step {k}: robot braked after step {executed}; starting again where it is"
                    )
                self.behind, self.joined, self.x_est = "braked", False, None
            else:
                if not self.behind:
                    log(self.role, f"step {k}: commands after step {executed} not applied; on its candidate")
                self.behind = self.behind or "candidate"
        elif executed is None:
            self.behind, self.rejoined = "", False
        self.synced, self.ran, self.reported = k - 1, [], k - 1

    def _measure(self, k: int) -> tuple[np.ndarray | None, tuple[int, np.ndarray] | None]:
        """Own measurement of step k: the state x (4,) [m, m/s] to plan from (the prediction
        while poses are missing), None if there is none yet (:meth:`_state`); and what Zenoh's
        callback answered (:meth:`_command_on_arrival`): from here on the main thread answers, and if the
        callback did, it did on the pose and odometry taken here.

        Realtime: the wait may not hold up this step's deadline; a withheld message (fault plan)
        is never waited for.  In realtime relay, own pose and odometry come just before the
        tick on one link and are drained (:class:`_Link`).  On either clock the wait ends when
        a later tick comes: the clock went on without this agent (it is joining again, and
        what was published while its session was being made again never reaches it), so the
        pose of step k will not come, and the next step's will."""
        args, inbox, me = self.args, self.inbox, self.me
        limit = args.timeout if self.lockstep else 0.3 * self.p.Ts
        wait = inbox.drain_until if self.link.drained else inbox.wait
        wait(lambda: _measured(inbox, me, k) or _tick_at_least(inbox, k + 1), limit)
        with inbox.cond:
            answered, self.ready, self.answered = self.answered, None, None
            pose = inbox.get(Pose, me, k)
            odom = inbox.get(Odom, me, k)
        return self._state(k, pose, odom), answered

    def _neighbours(
        self, k: int, braked: Collection[str]
    ) -> tuple[dict[str, Plan | None], set[str], Goal | None, list[str]]:
        """The live neighbours' plans of step k − 1, to plan step k against: (those plans, who is
        live, the latest goal given at run time, the robots in reach: :meth:`_reach`).

        Realtime: the wait may not hold up this step's deadline.  In mesh the plans come by
        callback, so a plan a little late is still used; in relay the digest came by callback
        before the tick (half a step before; with delay compensation, with the outcome)."""
        args, inbox, me = self.args, self.inbox, self.me
        limit = args.timeout if self.lockstep else 0.3 * self.p.Ts
        # (Mesh plans come by callback, which wakes a wait; only relay drains while it waits.)
        wait = inbox.drain_until if self.link.drained and self.relay else inbox.wait
        if k > 0:
            plans_in = partial(_relayed if self.relay else _plans_in, inbox, self._reach(braked), k - 1)
            # Tick k + 1 cannot go out before this agent's command of step k unless the clock no
            # longer waits for it (it is joining again): then the fleet has moved on, and plans of
            # step k − 1 missed while it rejoined will never come.
            wait(lambda: plans_in() or _tick_at_least(inbox, k + 1), limit)
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
            goal = inbox.get(Goal, me)
            self.links = {j: inbox.get(LinkState, j) for j in self.others}
        if self.side is not None:
            self._gate_news()
        return fresh, live, goal, self._reach(braked)

    def _gate_news(self) -> None:
        """Plans by place: tell the controller's gate what was heard of the robots it waits for,
        whose plans the agent takes on their own keys while it waits, wherever they are
        (:meth:`_Link.watch_plans`); with every plan, or the digest, the step hears them all."""
        gate = self.ctrl.gate
        self.link.watch_plans(() if gate is None else gate.waits_for)
        if gate is not None:
            heard = [self.last.get(j) for j in gate.waits_for]
            self.ctrl.gate_news([neighbour_of(pl) for pl in heard if pl is not None])

    def _reach(self, braked: Collection[str], within: int = 1) -> list[str]:
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

    def _seen(self, reach: list[str], braked: Collection[str]) -> list[NeighbourInfo]:
        """With plans by place, the robots beyond ``reach`` that the navigator sees too (up to
        :data:`~agent.coordination.VIEW_CELLS` cells away), by their newest plan heard, else their
        start; none otherwise, where the step knows every robot.  Shaping only: the step's
        constraints are those of ``reach``."""
        if self.side is None:
            return []
        near = set(reach)
        return [
            self.starts[j] if (pl := self.last.get(j)) is None else neighbour_of(pl)
            for j in self._reach(braked, VIEW_CELLS)
            if j not in near
        ]

    def _goals(self, goal: Goal | None, k: int) -> None:
        """Take, for the plan of step k, a goal published at run time (checked here) and one a
        query gave (accepted when it came, :meth:`_answer_goal`)."""
        if goal is not None and goal is not self.goal_seen:
            self._take_goal(goal, k)
        with self.inbox.cond:
            asked = [g for due, g in self.pending if due <= k]
            self.pending = [(due, g) for due, g in self.pending if due > k]
        if asked:
            self._set_goal(asked[-1].goal, k)

    def _state(self, k: int, pose: Pose | None, odom: Odom | None) -> np.ndarray | None:
        """The state to plan from at step k: measured, or the nominal model's prediction while
        poses are missing; None before the first measurement."""
        p, blind_steps = self.p, self.args.blind_steps
        if pose is not None and odom is not None:
            x = measured_state((pose.x, pose.y, pose.theta), (odom.vx, odom.vy), p.lookahead)
            if self.blind > blind_steps:
                # Its robot braked off the committed reference, and its neighbours kept clear
                # of it as of a braked robot (BLIND): start again from where it is, as a
                # restarted agent does, with the tube about the new measurement.
                log(
                    self.role,
                    f"step {k}: measurements back after {self.blind} steps; starting again where it is",
                )
                self.joined = False
            self.blind = 0
            if not self.joined and k > 0:
                # (Re)joining a running fleet: start where the robot is, references at rest there.
                self.ctrl.reset(x[[0, 2]], x)
                if not self.rejoined:  # once a braking episode: it starts again at each of its steps
                    log(self.role, f"joined at step {k} at ({x[0]:.3f}, {x[2]:.3f})")
                self.rejoined = self.behind == "braked"
            self.joined = True
            return x
        if self.x_est is None:
            return None
        self.blind += 1
        if self.blind == blind_steps + 1:
            log(self.role, f"step {k}: no pose for {self.blind} steps; braking and holding")
        design = self.design
        return np.asarray(design.A @ self.x_est + design.B @ self.a_prev)  # the nominal model's prediction

    def _take_goal(self, goal: Goal, k: int) -> None:
        """A goal published at run time: checked again here (``fleet goal`` checks it too)."""
        self.goal_seen = goal
        with self.inbox.cond:
            problem = self._goal_problem(goal)
        if problem is not None:
            log(self.role, f"goal {goal.goal.round(3).tolist()} rejected: {problem}")
        else:
            self._set_goal(goal.goal, k)

    def _set_goal(self, goal: np.ndarray, k: int) -> None:
        """Steer to ``goal`` (2,) [m] from step k on (an accepted goal)."""
        if not np.array_equal(goal, self.ctrl.goal):
            self.ctrl.set_goal(goal)
            log(self.role, f"new goal {goal.round(3).tolist()} at step {k}")

    def _goal_problem(self, goal: Goal) -> str | None:
        """Why ``goal`` cannot be taken, or None (inbox.cond held), by the one goal rule
        (:func:`~ground.scenario.goal_problem`): the walls, the obstacles, a passage from this
        robot's committed point, and the other robots' goals, each the one in ``goal.batch`` if
        it names the robot, else the one its latest plan carries."""
        plans = [pl for j in self.others if (pl := self.inbox.get(Plan, j)) is not None]
        at = self.ctrl.last_point
        return goal_problem(self.scn, self.design.footprint, goal.goal, plans, goal.batch, at=at)

    def _answer_goal(self, query: Any) -> None:
        """A goal sent as a query on this robot's goal key (a Zenoh thread): decoded strictly
        (a malformed one is counted with the rejected payloads), checked, and, if accepted, kept
        for the next step; the reply says which (:func:`_goal_reply`)."""
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
                problem = self._goal_problem(goal)
                if problem is None:
                    tick = inbox.get(Tick, TRACKER)
                    due = (-1 if tick is None else tick.step) + 1 + self.plans_ahead
                    if self.pending and self.pending[-1][0] == due:
                        self.pending.pop()  # the newer goal for the same step replaces it
                    self.pending.append((due, goal))
            if problem is not None:
                log(self.role, f"goal {goal.goal.round(3).tolist()} rejected: {problem}")
            query.reply(self.keys.goal(self.me), goal_reply(problem))
        finally:
            query.drop()

    def close(self) -> None:
        """Log the agent's closing counts (steps, solves, fallbacks, held steps, plans taken,
        injected faults, rejected payloads …), then undeclare its tokens and subscribers and close its
        Zenoh session."""
        c, guard = self.ctrl.counters, self.guard
        late = f"{self.inbox.heard_late} places heard over {PLACE_LAG} steps late, " if self.place else ""
        log(
            self.role,
            f"stopped after {self.k} steps: {c.solves} solves, {c.fallbacks} fallbacks, "
            f"{c.tube_exits} tube exits, {c.holds} blind holds, {c.uncontrolled} steps held with the link "
            f"down, {c.unapplied} steps on the candidate, "
            f"{c.ahead} steered ahead, {self.on_arrival} commands put on arrival "
            f"({self.by_callback} by Zenoh's callback), "
            f"{guard.hazard_steps} neighbour-steps kept clear of as static discs ({guard.transitions} "
            f"changes), {self.inbox.taken.get(Plan.TYPE, 0)} plans taken ({self.args.exchange}), "
            f"{late}{self.inbox.injected} injected faults, {self.inbox.rejects.total} rejected payloads",
        )
        self.link.close()


class _Link:
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
        they are (those a gate waits for: :meth:`Agent._gate_news`)."""
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


def _measured(inbox: Inbox, me: str, k: int) -> bool:
    """This robot's pose and odometry of step k are in, or withheld by the fault plan."""
    return all(inbox.get(t, me, k) is not None or inbox.lost(t, me, k) for t in (Pose, Odom))


def _plans_in(inbox: Inbox, others: list[str], step: int) -> bool:
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
    ctrl.steer_ahead([starts[j] if pl is None else neighbour_of(pl) for j, pl in known.items()])
    return True


def _tick_is(inbox: Inbox, k: int) -> bool:
    """The newest tick is tick k, and not the stop."""
    t = inbox.get(Tick, "tracker")
    return t is not None and not t.stop and t.step == k


def _outcome_at_least(inbox: Inbox, k: int) -> bool:
    """The tracker's outcome of step k (or of a later step) has arrived."""
    o = inbox.get(Outcome, "tracker")
    return o is not None and o.step >= k


def _tick_at_least(inbox: Inbox, k: int) -> bool:
    t = inbox.get(Tick, "tracker")
    return t is not None and (t.stop or t.step >= k)
