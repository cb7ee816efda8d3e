"""The simulated tracker: robot plants, camera poses and the fleet's clock.

``python -m tracker --scenario S --source sim|emulator [--seed N] [--fleet F] [--listen E]``

``--source sim`` integrates each robot's unicycle with the inner loop at 20 substeps per Ts,
driven by the accelerations the agents publish, and perturbs it with a disturbance inside W
(:class:`tracker.world.Disturbance`, the same seed and order as ``fleet simulate``, so that a
lockstep run reproduces it).  Each step it publishes every robot's camera pose (the plant's, off
by :class:`tracker.world.PoseNoise` within the controller's ``pose_noise`` bound) and odometry
(the inner loop's velocity), then the tick, then the ground truth on its own key.  It is the
robot side of the simulated robots: each step it applies a robot's command if it came in time,
else the ancillary law on the shifted candidate, else the brake
(:class:`epuck_link.robot_side.RobotSide`, as ``epuck_link`` does on a real robot).

In lockstep it waits until every live agent has answered the step (bounded by ``--timeout``).
With ``--clock realtime`` steps start every Ts of wall time after the first
:data:`STARTUP_STEPS` steps, which are taken in lockstep; a command later than
``--deadline``·Ts after its tick is a deadline miss.  With ``--exchange relay`` it publishes,
before tick k, the digest of the plans of step k − 1 that it has (the agents then subscribe to
it instead of to each other's plans).

``--scripted``: a script drives the run (``fleet.Fleet``): it ends when the script sends a
:class:`ground.wire.Script` with ``stop``, when its liveliness token goes (the script died), on
SIGTERM, or when no agent is alive; not early when every robot is home, nor at the scenario's
duration (``--steps`` still caps it).  On lockstep the tracker publishes the ground truth of sample
k and the measured poses and odometry first, then holds step k, for as long as it takes, until
the script permits it (a Script of ``step`` ≥ k), and only then publishes the digest and the tick
of step k: the script sees sample k and gives its goals before step k is planned (an agent reads
its pose only once the tick has come).  Meanwhile the tracker's liveliness
token tells the agents (``--scripted``) that the clock is held, not dead.

``--serve``: the fleet stays up, its robots held at their goals once home, for goal after goal
(``fleet goal``, a script's ``Fleet.connect``, ROS 2): the run ends on SIGTERM or SIGINT, on a
stop request (a :class:`ground.wire.Script` with ``stop``: ``fleet stop``), or when no agent is
alive; not early when every robot is home, nor at the scenario's duration (``--steps`` still
caps it).  Its clock runs free: nothing holds it.

``--source emulator`` (realtime only) is the camera of a lab whose robots are e-puck firmware
emulators (:mod:`epuck_link.emulator`) driven by ``epuck_link`` processes: it observes each
emulator's true pose on ``fleet/F/emu/R`` and publishes it, with the same bounded camera noise,
as the robot's pose and truth.  This process then moves nothing: the links apply the commands
and report what they did (:mod:`tracker.reports`), and the odometry comes from them.  With
``--delay-compensation`` the outcome of a step says what the links reported of it, as soon as
the reports are in (or :data:`tracker.reports.OUTCOME_WAIT`·Ts after the deadline).
"""

from __future__ import annotations

import argparse
import itertools
import signal
import sys
import threading
import time
from functools import partial
from typing import Any

import numpy as np

from epuck_link.robot_side import BRAKED, CANDIDATE, RobotSide
from ground.geometry import measured_state
from ground.model import brake_input
from ground.scenario import ConfigError, Scenario, home, load_scenario, settle_samples
from ground.wire import (
    LINK_DOWN,
    SCRIPT,
    Applied,
    Command,
    Digest,
    Keys,
    Odom,
    Outcome,
    Plan,
    Pose,
    Script,
    Tick,
    Truth,
    remember_steps,
)
from tracker.reports import OUTCOME_WAIT, REPORT_WAIT, Reports
from tracker.world import Disturbance, EmulatedWorld, PoseNoise, SimulatedWorld
from transport.bus import Inbox, open_session, publisher
from transport.process import DEADLINE, add_common_args, announce, fault_plan, log, seed_arg

ROLE = "tracker"
SUPERVISOR = "supervisor"
STARTUP_STEPS = 3
"""Realtime: steps taken in lockstep before the wall clock starts.  A fresh agent's first MPC
step pays one-time costs, and the first realtime steps of a fresh fleet were seen to stall its
messages for tens of milliseconds; taken in lockstep, neither is a deadline miss."""
LAG_LIMIT = 0.25
"""Realtime: a tick later than this fraction of Ts after its time starts the clock over."""
PROGRESS_EVERY = 50
"""Steps between progress lines on stderr."""
HOLD_POLL = 1.0
"""Scripted lockstep: how often [s] a held step looks again at what may end the hold, besides
being woken by it."""
SCRIPT_GRACE = 1.0
"""Scripted: how long [s] a tracker whose agents are all gone waits for the script's token to go
too, to name the cause. A killed script's fork server ends its agents at once, and their
tokens may go a few milliseconds before the script's."""


def main(argv: list[str] | None = None) -> int:
    """``python -m tracker --source sim|emulator``; returns the exit code (0 once the run has
    ended, 1 if the agents and the supervisor did not come up within ``--start-timeout``, 2 bad
    input)."""
    ap = argparse.ArgumentParser(prog="python -m tracker", description=__doc__.splitlines()[0])
    add_common_args(ap)
    ap.add_argument(
        "--source", choices=["sim", "emulator"], default="sim",
        help="sim: simulated plants; emulator: observe epuck_link emulators (camera: tracker.camera)",
    )  # fmt: skip
    ap.add_argument("--seed", type=seed_arg, default=None, help="override the scenario's seed")
    ap.add_argument("--steps", type=int, default=None, help="override the scenario's duration [steps]")
    ap.add_argument("--start-timeout", type=float, default=60.0, help="wait for agents to come up [s]")
    ap.add_argument(
        "--watchdog", type=float, default=0.5,
        help="brake a robot whose agent sent no command for this long [s] (as epuck_link does)",
    )  # fmt: skip
    ap.add_argument(
        "--deadline",
        type=float,
        default=DEADLINE,
        help="realtime: command deadline after the tick, as a fraction of Ts",
    )
    ap.add_argument(
        "--scripted", action="store_true",
        help="a script drives the run: on lockstep each step waits for its permit; the run ends on "
        "the script's stop or when it leaves, not early nor at the scenario's duration",
    )  # fmt: skip
    ap.add_argument(
        "--serve", action="store_true",
        help="keep the fleet up, its robots held at their goals, until SIGTERM, SIGINT or a stop "
        "request (fleet stop); not early when every robot is home, nor at the scenario's duration",
    )  # fmt: skip
    args = ap.parse_args(argv)
    try:
        scn = load_scenario(args.scenario)
        if args.source == "emulator" and args.clock != "realtime":
            raise ConfigError("--clock", "the emulated robots move in wall time; use realtime")
        if not 0 < args.deadline <= 1 - LAG_LIMIT:
            # Beyond, the rest of the step is too short for this process's own work, and each
            # tick would go out later than the last until the clock starts over.
            raise ConfigError(
                "--deadline",
                f"{args.deadline} outside (0, {1 - LAG_LIMIT:g}]: the tracker needs the rest of the step",
            )
    except ConfigError as e:
        print(f"tracker: error: {e}", file=sys.stderr)
        return 2
    steps = args.steps if args.steps is not None else round(scn.duration / scn.controller.Ts)
    if (args.scripted or args.serve) and args.steps is None:
        steps = None  # until the script or a stop request ends the run
    session = open_session(args)
    tracker = SimTracker(args, scn, session)
    if args.scripted or args.serve:
        signal.signal(signal.SIGTERM, tracker.on_term)
    if args.serve:
        signal.signal(signal.SIGINT, tracker.on_term)
    announce(ROLE, robots=tracker.ids, steps=steps)
    try:
        if not tracker.wait_start(args.start_timeout):
            return 1
        k = 0
        for k in itertools.count() if steps is None else range(steps):
            end = tracker.step(k)
            if end is not None:
                k = end
                break
        else:
            k = steps or 0
        tracker.finish(k)
    finally:
        tracker.close()
        session.close()
    return 0


class SimTracker:
    """The simulated tracker's state and its work each step (see the module docstring)."""

    def __init__(self, args: argparse.Namespace, scn: Scenario, session: Any):
        self.args = args
        self.p = p = scn.controller
        self.ids = ids = [r.id for r in scn.robots]
        self.keys = keys = Keys(args.fleet)
        seed = scn.simulation.seed if args.seed is None else args.seed
        sim = scn.simulation
        dist = Disturbance(
            sim.disturbance, p.W, sim.disturbance_fraction, np.random.default_rng(seed), p.point_noise
        )
        self.noise = PoseNoise(p.pose_noise, seed)
        self.realtime = args.clock == "realtime"
        self.home_run = 0
        """Consecutive steps every live robot has been home (the early end)."""
        self.inbox = inbox = Inbox(keys, ROLE, fault_plan(args))
        self.subs = [
            # Realtime: commands are read once, at the deadline; plans once a step.
            inbox.subscribe(session, keys.cmd(), Command, keep=True, drained=self.realtime),
            inbox.subscribe(session, keys.plan(), Plan, keep=True, drained=self.realtime),
            # What each epuck_link applied over a step (emulated robots: the link has the
            # deadline, not this process); a simulated robot's robot side is this process, and
            # a report for it is ignored.
            inbox.subscribe(session, keys.applied(), Applied, keep=True),
            inbox.watch_liveliness(session),
        ]
        self.world: SimulatedWorld | EmulatedWorld
        if args.source == "emulator":
            self.subs.append(inbox.subscribe(session, keys.emu(), Truth))
            self.world = EmulatedWorld(inbox, p.lookahead)
        else:
            self.world = SimulatedWorld(scn, dist)
        # Realtime: what the agents need goes out batched, not express.  Zenoh then writes each
        # agent's pose, odometry, digest and tick in one batch on its link instead of one write
        # each, each write waking a receiver that takes the core.  Lockstep keeps express puts,
        # which are faster when nothing else is waiting.
        express = not self.realtime
        self.pubs = {
            rid: (
                publisher(session, keys.pose(rid), express=express),
                publisher(session, keys.odom(rid), express=express),
                publisher(session, keys.truth(rid), express=False),
            )
            for rid in ids
        }
        self.clock = publisher(session, keys.clock, express=express)
        self.relay = publisher(session, keys.digest, express=express) if args.exchange == "relay" else None
        self.ahead = bool(args.delay_compensation)
        """Delay compensation: the agents plan a step ahead (docs/design.md, "Delay compensation").
        Step k's outcome goes out as soon as it is decided, with the digest of the plans of step k
        in force."""
        self.outcome = publisher(session, keys.outcome, express=True) if self.ahead else None
        self.sides = {rid: RobotSide(p, args.watchdog, self.world.drives) for rid in ids}
        self.reports = Reports(ids)
        self.heard: set[str] = set()
        self.braking = dict.fromkeys(ids, False)
        self.on_chain: dict[str, int] = {}
        self.braked_map: dict[str, int] = {}
        """What the next tick says about this step (Tick.fallback, Tick.braked)."""
        self.misses = 0
        self.t_start = time.monotonic()
        self.restarts, self.behind_s, self.behind = 0, 0.0, False
        """Realtime: times the clock started over because this process fell behind it, the time
        [s] it lost so, and whether it is behind now (logged once an episode)."""
        self.digest: bytes | None = None
        self.relayed: list[Plan] = []
        self.scripted = args.scripted
        self.serve = args.serve
        self.asked_only = self.scripted or self.serve
        """The run ends only when asked (by the script, a signal or a stop request), not when every
        robot is home nor at the scenario's duration."""
        self.stopping = threading.Event()
        """SIGTERM (or, serving, SIGINT) came: end the run at the next step."""
        self.signal = "SIGTERM"
        """The signal that came."""
        self.stop_asked = False
        """A Script with ``stop`` came: from the script, or ``fleet stop`` (under inbox.cond)."""
        self.truths_out = -1
        """The newest sample whose ground truth is out (scripted lockstep publishes it first)."""
        self.token: Any = None
        if self.asked_only:
            self.subs.append(inbox.subscribe(session, keys.script, Script, then=self._on_script))
        if self.scripted:
            # The agents (--scripted) wait on a held clock for as long as this token is there.
            self.token = session.liveliness().declare_token(keys.alive(ROLE))

    def on_term(self, signum: int, frame: Any) -> None:
        """SIGTERM in a scripted or served run (or SIGINT, served): end it at the next step, or
        now if a step is held."""
        self.signal = signal.Signals(signum).name
        self.stopping.set()
        with self.inbox.cond:
            self.inbox.cond.notify_all()

    def _on_script(self, msg: Script) -> None:
        """A Script came (inbox.cond held): a stop is kept whatever its step."""
        self.stop_asked = self.stop_asked or msg.stop

    def _asked_to_end(self) -> str | None:
        """Scripted or served: why the run ends now (a stop asked, the script gone, a signal), or
        None (inbox.cond held or not: reads only)."""
        if self.stopping.is_set():
            return self.signal
        if self.stop_asked:
            return "the script asked to stop" if self.scripted else "a stop was asked (fleet stop)"
        if self.scripted and SCRIPT not in self.inbox.live:
            return "the script left the fleet (its liveliness token went)"
        return None

    def _hold(self, k: int) -> bool:
        """Scripted lockstep: wait, as long as it takes, until the script permits step k; False
        when the run ends instead (logged)."""
        inbox = self.inbox

        def free() -> bool:
            permit = inbox.get(Script, SCRIPT)
            return self._asked_to_end() is not None or (permit is not None and permit.step >= k)

        while not inbox.wait(free, HOLD_POLL):
            pass
        why = self._asked_to_end()
        if why is not None:
            log(ROLE, f"step {k}: {why}; ending the run")
        return why is None

    def wait_start(self, timeout: float) -> bool:
        """Wait until every agent and the supervisor are alive, and the script in a scripted run
        (and, with emulated robots, every emulator has reported its pose); False, logged, if they
        are not within ``timeout`` [s]."""
        inbox, ids = self.inbox, self.ids
        everyone = {*ids, SUPERVISOR, *([SCRIPT] if self.scripted else [])}
        if not inbox.wait(lambda: everyone <= inbox.live, timeout):
            log(ROLE, f"not up within {timeout} s: {', '.join(sorted(everyone - inbox.live))}")
            return False
        if self.args.source == "emulator" and not inbox.wait(
            lambda: all(inbox.get(Truth, r) is not None for r in ids), timeout
        ):
            silent = [r for r in ids if inbox.get(Truth, r) is None]
            log(ROLE, f"no emulator pose on {self.keys.emu()} within {timeout} s: {', '.join(silent)}")
            return False
        return True

    def step(self, k: int) -> int | None:
        """Step k: measure and publish, tick, collect the commands, move the robots.  None to go
        on; else the sample the run ends at: k + 1 after this step (every robot home, or no agent
        alive), or k, the step not taken (scripted: the script's stop, the script gone, SIGTERM)."""
        p, inbox, ids = self.p, self.inbox, self.ids
        t = k * p.Ts
        if self.asked_only and (why := self._asked_to_end()) is not None:
            log(ROLE, f"step {k}: {why}; ending the run")
            return k
        # Each robot's pose and odometry, the digest of the plans (relay), then the tick, then
        # the truth, which only the supervisor reads.  The tick comes after what the agents
        # need: the agents it wakes would otherwise take the cores from this process before the
        # last robots' poses are out.  Simulated robots are where they will be at the tick once
        # the last step is integrated, so their messages are made while waiting for the tick,
        # and at the tick only sent.
        early = self.world.known_ahead
        if early:
            with inbox.cond:
                measured, truths, states = self._measure(k, t)
            inbox.drain()
            if self.relay is not None and k > 0 and not self.ahead:
                self.relayed = _relayed_plans(inbox, ids, k - 1, p.horizon, self.sides)
                self.digest = Digest.of(ROLE, k - 1, p.Ts, p.horizon, self.relayed).encode()
                if self.realtime:
                    # Out now, in the second half of the step, when the commands are in and the
                    # cores idle: the agents decode it before the tick, not in the race to the
                    # next deadline (docs/design.md, "Relayed plans").
                    self.relay.put(self.digest)
        if self.scripted and not self.realtime:
            # The script sees sample k first (the truth, and the poses its agents will measure:
            # an agent reads them only after the tick), gives its goals, then permits step k.
            assert early, "lockstep moves simulated robots only"
            for pub, payload in (*truths, *measured):
                pub.put(payload)
            self.truths_out = k
            if not self._hold(k):
                return k
        if self.realtime:
            _until(self.t_start + t)
        inbox.drain()
        answering = self._answering(k)
        if not early:
            with inbox.cond:  # the emulators' poses come by callback
                measured, truths, states = self._measure(k, t)
        if not self.world.drives and k > 0:
            self._links_reported(k)
        for pub, payload in measured if self.truths_out < k else ():
            pub.put(payload)
        if self.relay is not None and k > 0 and not self.ahead:
            self._relay(k, early)
        self.clock.put(
            Tick(
                robot=ROLE, step=k, t=t, stop=False, misses=self.misses, fallback=self.on_chain,
                braked=self.braked_map,
            ).encode()
        )  # fmt: skip
        sent = time.monotonic()
        if self.truths_out < k:
            for pub, payload in truths:
                pub.put(payload)
        if k % PROGRESS_EVERY == 0 and k:
            log(ROLE, f"step {k}")
        self._collect(k, t, sent, answering)
        with inbox.cond:
            live = set(inbox.live)
        self._apply(k, live, states)
        if self.ahead:
            self._outcome(k, answering, sent)
        if not live & set(ids):
            why = None
            if self.scripted:  # woken by the liveliness change, at the latest after SCRIPT_GRACE
                inbox.wait(lambda: self._asked_to_end() is not None, SCRIPT_GRACE)
                why = self._asked_to_end()
            log(ROLE, f"step {k}: {why or 'no agent alive'}; stopping the run")
            return k + 1
        # Agents send the command before the plan of a step (with delay compensation, the plan
        # made ahead came during the step before); the early stop below judges the plans of this
        # very step, as `fleet simulate` does.
        inbox.wait(partial(_planned, inbox, answering, k), 0.0 if self.realtime else self.args.timeout)
        inbox.prune(k if self.world.drives else k - Reports.LOOKBACK)
        if self.asked_only:  # the script, a signal or a stop request ends the run
            return None
        excused = _all_home(inbox, ids, self.world, k)
        self.home_run = self.home_run + 1 if excused is not None else 0
        if self.home_run < settle_samples(p.Ts):
            return None
        left = f" ({'; '.join(excused)})" if excused else ""
        log(ROLE, f"step {k}: every robot home for {self.home_run} steps{left}; ending the run")
        return k + 1

    def _answering(self, k: int) -> list[str]:
        """Who answers step k: the live agents that have been heard since they came up (at step
        0, all of them).  One that (re)joins is waited for only once a command of it arrived:
        before that it may not hear the clock yet (a joining Zenoh peer can miss the first
        samples), and waiting on it would stall the fleet."""
        inbox = self.inbox
        with inbox.cond:
            self.heard &= inbox.live
            for r in self.ids:
                cmd = inbox.get(Command, r)
                if r in inbox.live and cmd is not None and cmd.step >= k - 1:
                    self.heard.add(r)
            return [r for r in self.ids if r in inbox.live and (k == 0 or r in self.heard)]

    def _links_reported(self, k: int, sent: float | None = None) -> None:
        """The links decided step k − 1 at their own deadlines: the tick says what they did, and
        the digest leaves out the plans they did not execute.  With ``sent`` (delay compensation:
        when tick k − 1 went out [s]) the step's outcome says it first, as soon as the links'
        reports are in, and tick k says the same again (:class:`tracker.reports.Reports`)."""
        p, reports = self.p, self.reports
        if sent is None:
            take = partial(reports.for_tick, self.inbox, k, REPORT_WAIT * p.Ts)
        else:
            due = sent + (self.args.deadline + OUTCOME_WAIT) * p.Ts
            take = partial(reports.for_outcome, self.inbox, k - 1, max(0.0, due - time.monotonic()))
        self.on_chain, self.braked_map, late = take(partial(log, ROLE))
        for r, done in (*self.on_chain.items(), *self.braked_map.items()):
            remember_steps(self.sides[r].unexecuted, range(done + 1, k), k)  # only the recent part is kept
        if late:
            self.misses += len(late)
            log(ROLE, f"step {k - 1}: deadline missed by {', '.join(late)} (seen by epuck_link)")

    def _relay(self, k: int, early: bool) -> None:
        """The digest of step k − 1, again if a plan came since it was made early."""
        p = self.p
        assert self.relay is not None
        now_relayed = _relayed_plans(self.inbox, self.ids, k - 1, p.horizon, self.sides)
        if (
            not early
            or len(now_relayed) != len(self.relayed)
            or any(a is not b for a, b in zip(now_relayed, self.relayed, strict=True))
        ):  # a plan came since the digest was made (or nothing was made early)
            self.relayed = now_relayed
            self.digest = Digest.of(ROLE, k - 1, p.Ts, p.horizon, self.relayed).encode()
            self.relay.put(self.digest)
        elif not self.realtime:
            assert self.digest is not None
            self.relay.put(self.digest)

    def _outcome(self, k: int, answering: list[str], sent: float) -> None:
        """Delay compensation: step k is decided (the tick went out at ``sent`` [s]); the digest
        of the plans of step k in force (relay), then the outcome, which sets the agents planning
        step k + 1."""
        p, inbox = self.p, self.inbox
        assert self.outcome is not None
        if not self.world.drives:  # emulated robots: their links decided, and report it
            self._links_reported(k + 1, sent)
        if self.relay is not None:
            # A plan made ahead came during the step before; one made from the measurement (at
            # step 0, after a brake) follows its command at once: wait for those of the commands
            # applied, as the agents would on their own keys (bounded by the deadline in realtime).
            applied = [r for r in answering if r not in self.on_chain and r not in self.braked_map]
            if self.realtime:
                due = sent + self.args.deadline * p.Ts
                inbox.drain_until(partial(_planned, inbox, applied, k), max(0.0, due - time.monotonic()))
            else:
                inbox.wait(partial(_planned, inbox, applied, k), self.args.timeout)
            self.relayed = _relayed_plans(inbox, self.ids, k, p.horizon, self.sides)
            self.relay.put(Digest.of(ROLE, k, p.Ts, p.horizon, self.relayed).encode())
        self.outcome.put(Outcome(robot=ROLE, step=k, fallback=self.on_chain, braked=self.braked_map).encode())

    def _collect(self, k: int, t: float, sent: float, answering: list[str]) -> None:
        """Wait for step k's commands: every answering agent's (bounded) in lockstep and in the
        realtime start-up steps, until the deadline on the realtime clock."""
        args, p, inbox = self.args, self.p, self.inbox
        if self.realtime and k < STARTUP_STEPS:
            # Every answering agent's command is waited for (bounded), then the wall clock
            # starts over from this step's deadline.
            inbox.drain_until(partial(_answered, inbox, answering, k), args.timeout)
            self.t_start = time.monotonic() - t - args.deadline * p.Ts
        elif self.realtime:
            # A command must arrive within the deadline, --deadline·Ts after its tick went out
            # (epuck_link counts from the tick's arrival); otherwise the robot side follows the
            # candidate and the miss is counted.  This process can fall behind the wall clock
            # when the fleet takes its cores: a tick then goes out late, and a deadline counted
            # from the tick's time would have passed before the agents heard of the step.  A tick
            # more than LAG_LIMIT·Ts late starts the clock over from it: the simulated world then
            # runs slower than the wall clock, which is logged (docs/design.md, "Realtime
            # clock").
            lag = sent - (self.t_start + t)
            if lag > LAG_LIMIT * p.Ts:
                self.t_start += lag
                self.restarts, self.behind_s = self.restarts + 1, self.behind_s + lag
                if not self.behind:
                    log(ROLE, f"step {k}: the tick went out {lag * 1e3:.0f} ms late; the clock starts over")
            self.behind = lag > LAG_LIMIT * p.Ts
            due = sent + args.deadline * p.Ts
            # With delay compensation the commands come at once (each agent only applies the
            # ancillary law): decide as soon as they are in, so that the agents have the rest
            # of the step to plan the next one.
            early = self.ahead and inbox.drain_until(
                partial(_answered, inbox, self.ids, k), due - time.monotonic()
            )  # every live agent's, a rejoining one's too (answering or not)
            if not early:
                _until(due)  # sent ≥ t_start + t: it waited for it
            if time.monotonic() - due > LAG_LIMIT * p.Ts:
                # This process itself woke late (stopped, or starved of the CPU): commands
                # that came in time may still sit in Zenoh's queues, unread while it slept.
                # They are given one deadline's length to be read before any is judged missed.
                inbox.drain_until(partial(_answered, inbox, answering, k), args.deadline * p.Ts)
            else:
                inbox.drain()
            late = [r for r in self.ids if inbox.get(Command, r, k) is None and r in inbox.live]
            if late and self.world.drives:  # emulated robots: their links judge (Applied)
                self.misses += len(late)
                log(ROLE, f"step {k}: deadline missed by {', '.join(late)}")
        elif not inbox.wait(partial(_answered, inbox, answering, k), args.timeout):
            late = [r for r in self.ids if inbox.get(Command, r, k) is None]
            log(ROLE, f"step {k}: no command from {', '.join(late)} within {args.timeout} s")

    def _apply(self, k: int, live: set[str], states: dict[str, np.ndarray]) -> None:
        """Move every robot over step k: its command, its candidate or the brake."""
        p, inbox, world = self.p, self.inbox, self.world
        self.on_chain, self.braked_map = {}, {}
        for rid in self.ids:
            side = self.sides[rid]
            what, a, why = side.decide(
                k, inbox.get(Command, rid, k), inbox.get(Command, rid), rid in live, states.get(rid)
            )
            if (what == BRAKED) != self.braking[rid]:
                self.braking[rid] = what == BRAKED
                change = f"{why}; braking" if self.braking[rid] else "commands again"
                log(ROLE, f"step {k}: {rid}: {change}")
            if what == CANDIDATE:
                self.on_chain[rid] = side.applied_step
            elif what == BRAKED and world.drives:
                self.braked_map[rid] = side.applied_step
            stopping = a is None  # braked, or its agent asks for the brake (Command.brake)
            if a is None:
                a = brake_input(world.state(rid)[[1, 3]], p.Ts, p.a_max)
            side.last_a = a
            world.advance(rid, a, p.Ts, braked=stopping)

    def _measure(
        self, k: int, t: float
    ) -> tuple[list[tuple[Any, bytes]], list[tuple[Any, bytes]], dict[str, np.ndarray]]:
        """The messages of step k at time t [s]: (publisher, payload) of each robot's camera pose
        and odometry, and of its true pose; and, with odometry, each robot's measured state (4,)
        [m, m/s], the agent's x from those messages.  Draws the camera noise, robot by robot."""
        world, lookahead = self.world, self.p.lookahead
        measured: list[tuple[Any, bytes]] = []
        truths: list[tuple[Any, bytes]] = []
        states: dict[str, np.ndarray] = {}
        for rid in self.ids:
            pub_pose, pub_odom, pub_truth = self.pubs[rid]
            true = world.pose(rid).copy()
            mx, my, mth = (float(v) for v in true + self.noise.sample())
            measured.append((pub_pose, Pose(robot=rid, seq=k, t=t, x=mx, y=my, theta=mth).encode()))
            if world.odometry:
                state = world.state(rid)
                odom = Odom(robot=rid, seq=k, t=t, vx=float(state[1]), vy=float(state[3]))
                measured.append((pub_odom, odom.encode()))
                states[rid] = measured_state(np.array([mx, my, mth]), state[[1, 3]], lookahead)
            x, y, th = (float(v) for v in true)
            truths.append((pub_truth, Truth(robot=rid, seq=k, t=t, x=x, y=y, theta=th).encode()))
        return measured, truths, states

    def finish(self, k: int) -> None:
        """The final poses (sample k; out already if a scripted step k was held), then the stop tick."""
        p = self.p
        if self.realtime:
            _until(self.t_start + k * p.Ts)
        for rid in self.ids if self.truths_out < k else ():
            with self.inbox.cond:
                x, y, th = (float(v) for v in self.world.pose(rid))
            self.pubs[rid][2].put(Truth(robot=rid, seq=k, t=k * p.Ts, x=x, y=y, theta=th).encode())
        if not self.world.drives and k > 0 and not self.ahead:
            # As tick k would: what the links did over the last step (with delay compensation
            # the step's outcome said it already).
            self._links_reported(k)
        self.clock.put(
            Tick(
                robot=ROLE, step=k, t=k * p.Ts, stop=True, misses=self.misses, fallback=self.on_chain,
                braked=self.braked_map,
            ).encode()
        )  # fmt: skip
        log(
            ROLE,
            f"run ended at step {k}; {self.misses} deadline misses, {self.inbox.rejects.total} rejected "
            f"payloads, clock started over {self.restarts} times "
            f"({self.behind_s:.2f} s behind the wall clock)",
        )

    def close(self) -> None:
        """Undeclare the liveliness token (a scripted run's) and the subscribers."""
        if self.token is not None:
            self.token.undeclare()
        for s in self.subs:
            s.undeclare()


def _relayed_plans(
    inbox: Inbox, ids: list[str], step: int, horizon: int, sides: dict[str, RobotSide]
) -> list[Plan]:
    """What the digest of ``step`` relays (``--exchange relay``): each robot's newest
    plan of a step ≤ ``step`` whose command was not left unapplied (a plan whose command
    missed its deadline was never executed: the robot followed the plan before), as it came
    on its robot's own key (the subscription checks the id against the key), with the
    design's horizon.  One that missed the digest of its step is in the next: late,
    as on its own key."""
    with inbox.cond:
        plans = [inbox.newest(Plan, r, step, sides[r].unexecuted) for r in ids]
    return [pl for pl in plans if pl is not None and pl.committed.shape[0] == horizon]


def _until(when: float) -> None:
    """Wait for the monotonic clock to reach ``when`` [s] (the realtime clock's pacing)."""
    left = when - time.monotonic()
    if left > 0:
        threading.Event().wait(left)


def _answered(inbox: Inbox, ids: list[str], k: int) -> bool:
    """Every live agent's command of step k has arrived (or was withheld by the fault plan)."""
    return all(
        inbox.get(Command, r, k) is not None or inbox.lost(Command, r, k) for r in ids if r in inbox.live
    )


def _planned(inbox: Inbox, ids: list[str], k: int) -> bool:
    """Every live agent's plan of step k has arrived (or was withheld by the fault plan)."""
    return all(inbox.get(Plan, r, k) is not None or inbox.lost(Plan, r, k) for r in ids if r in inbox.live)


def _all_home(
    inbox: Inbox, ids: list[str], world: SimulatedWorld | EmulatedWorld, k: int
) -> list[str] | None:
    """Every plan of step k (the latest, if it is missing) parked at its agent's
    current goal (a goal changed at run time counts) and every controlled point
    within half the goal tolerance of it, or its goal blocked by a stopped robot (the plan says
    by whom: it cannot get there while that robot stands; ``summary.json`` names both).  A robot
    whose agent is gone, or whose radio link is down (its agent holds: nothing it plans reaches
    the robot), cannot get home now, and is left out.  The robots counted without being home,
    each with why, or None if one is not home."""
    excused = []
    for rid in ids:
        if rid not in inbox.live:
            excused.append(f"{rid}: its agent is not alive")  # its robot is braked where it is
            continue
        with inbox.cond:  # the plans' callbacks add to the history meanwhile
            plan = inbox.newest(Plan, rid, k)  # the plan of step k if it is in
        if plan is None:
            return None
        if plan.status == LINK_DOWN:
            excused.append(f"{rid}: its link is down")
            continue
        with inbox.cond:
            pt = world.state(rid)[[0, 2]]
        if plan.blocked:
            excused.append(f"{rid}: its goal covered by {plan.blocked}")
        elif not home(plan.committed[-1], pt, plan.goal):
            return None
    return excused
