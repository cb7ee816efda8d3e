"""The agent process: one robot's tube MPC (:class:`agent.controller.TubeMPC`) on the fleet's bus.

``python -m agent --scenario S --robot ID [--fleet F] [--connect E] [--listen E]``

At step k the agent waits for the tracker's tick k, its own pose and odometry of step k and the
plans that the live neighbours committed at step k − 1 (liveliness says who is live; every wait
is bounded).  The plans come on the neighbours' keys (``--exchange mesh``), on the keys of the
cells about this robot's (``place``: only the neighbours in reach,
:meth:`agent.neighbours.Neighbourhood.reach`) or together in the tracker's digest of step k − 1
(``relay``).  It then steps the controller and publishes its
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
after it (planning ahead, the plan of the step after next: :class:`agent.goals.Goals`).
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
from functools import partial
from typing import Any

import numpy as np

from agent.channels import (
    TRACKER,
    Channels,
    outcome_at_least,
    own_measured,
    tick_at_least,
    tick_is,
)
from agent.controller import SNAPSHOTS, StepOutput, TubeMPC
from agent.coordination import PLACE_LAG, navigator_view, place_side
from agent.goals import Goals
from agent.hazards import Guard, starts_of
from agent.neighbours import Neighbourhood
from agent.protocol import (
    PlannedAhead,
    candidate_input,
    command_message,
    plan_ahead,
    plan_ahead_message,
    plan_message,
)
from agent.sync import Sync
from agent.tube import validated_design
from ground.arrival import arrival
from ground.geometry import (
    controlled_point,
    measured_state,
)
from ground.scenario import ConfigError, Scenario, load_scenario
from ground.wire import (
    LINK_DOWN,
    Command,
    Keys,
    LinkState,
    Odom,
    Outcome,
    Plan,
    Pose,
    Tick,
)
from transport.process import add_common_args, announce, exchange_for, log

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
        cells about its own, and coordinates with the robots in reach
        (:meth:`agent.neighbours.Neighbourhood.reach`)."""
        self.side = place_side(design.footprint, p.epsilon, p.priority_share) if self.place else None
        """The side of the cells [m] (:func:`agent.coordination.place_side`), or None."""
        self.link = Channels(
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
        self.lockstep = args.clock == "lockstep"
        self.relay = args.exchange == "relay"
        say = partial(log, self.role)
        self.guard = Guard(me, p, say, side=self.side)
        self.sync = Sync(self.ctrl, design, args.blind_steps, say)
        """Whether the agent has joined, the state it plans from, what its robot side did."""
        starts = starts_of(scn.robots, p.lookahead, design.footprint)
        wait_s = args.timeout if self.lockstep else 0.3 * p.Ts  # realtime: within the step's deadline
        self.nbhd = Neighbourhood(
            self.link, self.ctrl, self.guard, self.others, starts, self.side, p.lookahead, wait_s, self.relay
        )
        """What the agent knows of the other robots."""
        self.k = 0
        self.goals = Goals(
            me, scn, design.footprint, self.ctrl, self.inbox, self.others, self.keys, self.plans_ahead, say
        )
        """The goals given at run time."""
        self.held = False
        """The clock has been held past --timeout (scripted; logged once a hold)."""
        self.silent_since = time.monotonic()
        self.ahead: PlannedAhead | None = None
        """The plan made ahead for the next step (the main thread's; ``ready`` is the callback's)."""
        self.sent: dict[int, StepOutput] = {}
        """The controller outputs of the recent commands sent, by step: with delay compensation
        the agent predicts what its robot side applied when it followed one's candidate."""
        self.unmeasured = 0
        """Steps in a row without a state to plan from (not joined, nothing measured)."""
        self.link.go_live(self.goals.answer)

    def step(self) -> int | None:
        """One step: wait for the tick, measure, plan, publish.  None to go on; the exit code
        once the run has stopped (0) or no tick came for ``--timeout`` (1)."""
        inbox, k = self.inbox, self.k
        if not inbox.wait(partial(self._step_may_go, k), 1.0):
            return self._no_tick(k)
        self.silent_since = time.monotonic()
        self.held = False
        with inbox.cond:
            tick = inbox.get(Tick, TRACKER)
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
            inbox.wait(lambda: set(self.others) <= inbox.live, self.args.timeout)
        x, answered = self._measure(k)
        ahead, self.ahead = self.ahead, None
        cut = self._cut(k)
        if ahead is not None and ahead.step == k and self.sync.joined and not cut:
            # The plan of step k, made during step k − 1: apply it to x, the ancillary law,
            # unless Zenoh's callback did so already, on the same pose and odometry.
            assert x is not None
            a = answered[1] if answered is not None and answered[0] == k else self._put_command(ahead, x)
            self.sync.x_est, self.sync.a_prev, self.sent[k] = x, a, ahead.out
            inbox.prune(k - 2)
            self._plan_ahead(k, x, a)
        else:
            self._plan_now(k, x, tick, cut)
        self.k += 1
        return None

    def _plan_now(self, k: int, x: np.ndarray | None, tick: Tick, cut: bool) -> None:
        """Step k with no plan made ahead for it: plan from ``x`` (4,) [m, m/s] against the
        neighbours' plans of step k − 1 and publish the command and the plan; hold (blind, or
        the robot's link ``cut``); or, with nothing measured yet, keep the robot braked."""
        fresh, live, reach = self.nbhd.of_step(k, tick.braked)
        if x is None:
            self._unmeasured(k)
            return
        self.unmeasured = 0
        self.goals.take(k)
        ctrl, blind = self.ctrl, self.sync.holding
        nbs, hazards = self.nbhd.classify(k, reach, fresh, live, tick.braked)
        if cut:
            out = ctrl.hold(x, LINK_DOWN)
        elif blind:
            out = ctrl.hold(x)
        else:
            out = ctrl.step(x, nbs, hazards, seen=self.nbhd.seen(reach, tick.braked))
        self.sync.ran.append(k)
        self.sync.x_est, self.sync.a_prev = x, out.a
        # The command first: the robot side waits on it; the neighbours need the plan only at
        # the next step, which cannot start before the robots move.
        self.link.put_command(command_message(self.me, k, ctrl, out, follow=not (blind or cut), brake=blind))
        self.link.put_plan(plan_message(self.me, k, ctrl, out, self.inbox.heard_late))
        self.inbox.prune(k - 2)
        if self.plans_ahead and not cut:
            self.sent[k] = out
            self._plan_ahead(k, x, out.a)
        elif self.link.drained and not (blind or cut):  # realtime relay: off the deadline's path
            self.nbhd.steer_ahead(k, self.p.Ts)

    def _unmeasured(self, k: int) -> None:
        """Not joined yet and nothing measured at step k: keep the robot still, commit nothing;
        after :data:`UNMEASURED_SAY` such steps, say why (once)."""
        self.link.put_command(Command(robot=self.me, step=k, ax=0.0, ay=0.0, brake=True))
        self.unmeasured += 1
        if self.unmeasured == UNMEASURED_SAY:
            with self.inbox.cond:
                pose, odom = self.inbox.get(Pose, self.me), self.inbox.get(Odom, self.me)
            newest = {
                t.TYPE: "none" if m is None else f"step {m.seq}" for t, m in ((Pose, pose), (Odom, odom))
            }
            log(
                self.role,
                f"step {k}: cannot join: no pose and odometry of its own of the same step for "
                f"{self.unmeasured} steps (newest {newest}); the robot is held braked",
            )

    def _no_tick(self, k: int) -> int | None:
        """No tick (or outcome) for a second at step k: go on waiting (None) until ``--timeout``,
        then stop (1), unless a script holds the clock while the tracker is alive."""
        args, inbox = self.args, self.inbox
        with inbox.cond:
            now = time.monotonic()
            seen = {f"{t}/{r}": round(now - at, 1) for (t, r), at in inbox.arrived.items()}
            alive = sorted(inbox.live)
            put = self.answered is not None and self.answered[0] == k
        if now - self.silent_since < args.timeout:
            return None
        awaited = f"outcome of step {k} nor tick {k + 1}" if put else f"tick {k}"
        if args.scripted and TRACKER in alive:  # the script holds the clock
            if not self.held:
                log(self.role, f"no {awaited} for {args.timeout} s: held by the script, waiting")
            self.held = True
            return None
        log(self.role, f"no {awaited} within {args.timeout} s; stopping (live {alive}; s since: {seen})")
        return 1

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
        if not self.sync.joined or self.sync.blind >= max(args.blind_steps, 1) or self._cut(k + 1):
            # Braked: it starts again where it stands.  Without poses for --blind-steps steps:
            # the next step decides, on its own pose or its absence, to plan or to hold.  Its
            # robot's link down: nothing it plans reaches the robot (the next step holds).
            return
        j = outcome.executed(me)
        if j is not None:  # the robot side followed the candidate of its command of step j
            a_j = candidate_input(ctrl, self.sent.get(j), j, k, x)
            a = self.sync.a_prev = ctrl.ancillary(x) if a_j is None else a_j  # (the same, to rounding)
        x_hat = ctrl.xi[0:4]  # the plan the command was applied about (replaced, never changed)
        fresh, live, reach = self.nbhd.of_step(k + 1, outcome.braked)
        self.goals.take(k + 1)
        nbs, hazards = self.nbhd.classify(k + 1, reach, fresh, live, outcome.braked)
        out, tube_ok = plan_ahead(ctrl, x, a, x_hat, nbs, hazards, seen=self.nbhd.seen(reach, outcome.braked))
        self.sync.ran.append(k + 1)
        self.ahead = ready = PlannedAhead.of(me, k + 1, ctrl, out)
        with inbox.cond:  # ready before the plan goes out
            self.ready = ready
            self._command_on_arrival(None)  # tick k + 1 may be in already (it does not wait for this plan)
        self.link.put_plan(plan_ahead_message(me, k + 1, ctrl, out, tube_ok, self.inbox.heard_late))

    def _die_if_planned(self, k: int) -> None:
        """The fault plan kills this agent at step k or before (:attr:`transport.faults.FaultPlan.kills`):
        it sends itself SIGKILL, a hard death, before anything of step k goes out."""
        plan = self.inbox.faults
        if plan is not None and plan.kills.get(self.me, k + 1) <= k:
            log(self.role, f"step {k}: killed by the fault plan (SIGKILL)")
            sys.stderr.flush()
            os.kill(os.getpid(), signal.SIGKILL)

    def _cut(self, k: int) -> bool:
        """This robot's radio link is down at step k, or back with the robot held
        (:meth:`agent.sync.Sync.cut`)."""
        with self.inbox.cond:
            ls = self.inbox.get(LinkState, self.me)
        return self.sync.cut(k, ls)

    def _outcome_known(self, k: int) -> bool:
        """The outcome of step k is in, or lost (fault plan); on the realtime clock, or the next
        tick came first (it says the same).  In lockstep the tracker always sends the outcome,
        but the next tick may come first (another publisher), and which way the agent plans
        must not depend on that (inbox.cond held)."""
        lost = self.inbox.lost(Outcome, TRACKER, k)
        late = not self.lockstep and tick_at_least(self.inbox, k + 1)
        return lost or late or outcome_at_least(self.inbox, k)

    def _step_may_go(self, k: int) -> bool:
        """What the main loop waits for at step k (inbox.cond held): tick k, or the stop.  If
        Zenoh's callback put the command of step k (:meth:`_command_on_arrival`), there is nothing to do
        until the step's outcome (:meth:`_outcome_known`): the main threads of a fleet then stay asleep
        while its commands are on their way."""
        answered = self.answered
        if answered is None or answered[0] != k:
            return tick_at_least(self.inbox, k)
        return self._outcome_known(k) or tick_at_least(self.inbox, k + 1)

    def _command_on_arrival(self, _: Any) -> None:
        """Delay compensation, called by the inbox as a tick, pose or odometry is stored (a Zenoh
        thread, inbox.cond held): once those of the step planned ahead are all in, put its
        command, the ancillary law applied to that pose and odometry, here and now.  The main
        thread is not woken for it; it does the rest of the step (:meth:`step`)."""
        ready = self.ready
        if ready is None:  # (also while the link is being made: no inbox yet)
            return
        inbox, me = self.inbox, self.me
        if not tick_is(inbox, ready.step):
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
        self.link.put_command(command)
        return a

    def _follow_clock(self, tick: Tick) -> None:
        """Catch up with tick ``tick.step``, and take what it says the robot sides executed."""
        self.k = k = self.sync.catch_up(self.k, tick.step, tick.executed(self.me), tick.stop)
        self.inbox.release(k)
        if self.sync.reported < k - 1:  # not told yet by the outcome of step k − 1
            self._take_report(k, tick)

    def _take_report(self, k: int, report: Tick | Outcome) -> None:
        """Take what the robot sides did up to step k − 1 (``report``: tick k, or the outcome of
        step k − 1): the others' plans never executed, and this robot's own side."""
        self.nbhd.take_report(k, report)
        self.sync.take_report(k, report.executed(self.me), self.me in report.braked)

    def _measure(self, k: int) -> tuple[np.ndarray | None, tuple[int, np.ndarray] | None]:
        """Own measurement of step k: the state x (4,) [m, m/s] to plan from (the prediction
        while poses are missing), None if there is none yet (:meth:`agent.sync.Sync.state`); and what Zenoh's
        callback answered (:meth:`_command_on_arrival`): from here on the main thread answers, and if the
        callback did, it did on the pose and odometry taken here.

        Realtime: the wait may not hold up this step's deadline; a withheld message (fault plan)
        is never waited for.  In realtime relay, own pose and odometry come just before the
        tick on one link and are drained (:class:`Channels`).  On either clock the wait ends when
        a later tick comes: the clock went on without this agent (it is joining again, and
        what was published while its session was being made again never reaches it), so the
        pose of step k will not come, and the next step's will."""
        args, inbox, me = self.args, self.inbox, self.me
        limit = args.timeout if self.lockstep else 0.3 * self.p.Ts
        wait = inbox.drain_until if self.link.drained else inbox.wait
        wait(lambda: own_measured(inbox, me, k) or tick_at_least(inbox, k + 1), limit)
        with inbox.cond:
            answered, self.ready, self.answered = self.answered, None, None
            pose = inbox.get(Pose, me, k)
            odom = inbox.get(Odom, me, k)
        x = (
            None
            if pose is None or odom is None
            else measured_state((pose.x, pose.y, pose.theta), (odom.vx, odom.vy), self.p.lookahead)
        )
        return self.sync.state(k, x), answered

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
