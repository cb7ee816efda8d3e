"""The simulated tracker: robot plants, camera poses and the lockstep clock.

``python -m tracker --scenario S --source sim|emulator [--seed N] [--fleet F] [--listen E]``

``--source sim`` integrates each robot's unicycle with the inner loop at 20
substeps per Ts, driven by the accelerations the agents publish, and perturbs
it with a disturbance inside W (the harness's :class:`fleet.harness.Disturbance`,
same seed, same order, so a lockstep run reproduces ``fleet simulate``).  It
publishes the tick, then the camera pose (the plant's, off by
:class:`fleet.harness.PoseNoise` within the controller's ``pose_noise`` bound)
and the inner loop's velocity (odometry) of every robot, then the ground truth
on its own key.  In lockstep it waits until every live agent has answered the
step (bounded by ``--timeout``).  With ``--clock realtime`` steps start every
Ts of wall time after the first STARTUP_STEPS steps, which are taken in
lockstep; a command later than ``--deadline``·Ts after its tick is a deadline
miss (the previous acceleration is held).  With ``--exchange relay`` it
publishes, before tick k, the digest of the plans of step k−1 that it has (the
agents then subscribe to it instead of to each other's plans).

``--source emulator`` (realtime only) is the camera of a lab whose robots are
e-puck firmware emulators (:mod:`epuck_link.emulator`) driven by
``epuck_link`` processes: it observes each emulator's true pose on
``fleet/F/emu/R`` and publishes it, with the same bounded camera noise, as the
robot's pose and truth.  The motion comes from the agents' commands through
``epuck_link``, the wire protocol and the emulated wheels; this process moves
nothing, and the odometry comes from ``epuck_link`` as on real robots.
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from functools import partial
from typing import Any

import numpy as np

from agent.models import measured_state
from fleet.harness import GOAL_TOLERANCE, Disturbance, PoseNoise, make_plant
from fleet.robot_side import BRAKED, CANDIDATE, REPORT_WAIT, Reports, RobotSide
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
from fleet.scenario import ConfigError
from fleet.wire import Applied, Command, Digest, Keys, Odom, Plan, Pose, Tick, Truth

SUPERVISOR = "supervisor"
STARTUP_STEPS = 3
"""Realtime: steps taken in lockstep before the wall clock starts.  A fresh agent's first MPC
step pays one-time costs (20–35 ms each at 16 robots on 2 cores), and on the realtime clock
the third step stalled the whole fleet's messages for 30–60 ms (cause not found).  Taken in
lockstep, neither is a deadline miss; no miss at the later steps came from them."""
LAG_LIMIT = 0.25
"""Realtime: a tick later than this fraction of Ts after its time starts the clock over."""
PROGRESS_EVERY = 50
"""Steps between progress lines on stderr."""


class SimulatedWorld:
    """The robots as simulated plants, moved here from the agents' commands."""

    odometry = True
    drives = True
    """This process applies the commands (it is the robot side)."""
    known_ahead = True
    """Where the robots are at the next tick is known once the step is integrated."""

    def __init__(self, scn: Any, design: Any, dist: Disturbance):
        self.plants = {
            r.id: make_plant(scn.simulation.plant, np.array(r.start, float), design) for r in scn.robots
        }
        self.dist = dist

    def pose(self, rid: str) -> np.ndarray:
        """True axle-centre pose (3,) [m, m, rad], world frame."""
        return self.plants[rid].pose

    def state(self, rid: str) -> np.ndarray:
        """Controlled-point state [px, vx, py, vy] (4,) [m, m/s]."""
        return self.plants[rid].state()

    def advance(self, rid: str, a: np.ndarray, Ts: float) -> None:
        """Hold acceleration ``a`` (2,) [m/s²] for ``Ts`` [s], then add the disturbance."""
        plant = self.plants[rid]
        x_before = plant.state()
        plant.step(a, Ts)
        plant.perturb(self.dist.sample(x_before * 0.0))


class EmulatedWorld:
    """The robots as e-puck emulators (their own processes), seen on ``fleet/F/emu/R``."""

    odometry = False
    drives = False
    """``epuck_link`` applies the commands, not this process."""
    known_ahead = False
    """The emulators move in wall time: their poses are read at the tick."""

    def __init__(self, inbox: Inbox, lookahead: float):
        self.inbox = inbox
        self.lookahead = lookahead

    def pose(self, rid: str) -> np.ndarray:
        t = self.inbox.get(Truth, rid)
        assert t is not None, "pose() before every emulator reported"
        return np.array([t.x, t.y, t.theta])

    def state(self, rid: str) -> np.ndarray:
        x, y, th = self.pose(rid)
        ell = self.lookahead
        return np.array([x + ell * np.cos(th), 0.0, y + ell * np.sin(th), 0.0])

    def advance(self, rid: str, a: np.ndarray, Ts: float) -> None:
        """Nothing to do: the emulated wheels move in wall time."""


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m tracker", description=__doc__.splitlines()[0])
    add_common_args(ap)
    ap.add_argument(
        "--source", choices=["sim", "emulator"], default="sim",
        help="sim: simulated plants; emulator: observe epuck_link emulators (camera: tracker.camera)",
    )  # fmt: skip
    ap.add_argument("--seed", type=int, default=None, help="override the scenario's seed")
    ap.add_argument("--steps", type=int, default=None, help="override the scenario's duration [steps]")
    ap.add_argument("--start-timeout", type=float, default=60.0, help="wait for agents to come up [s]")
    ap.add_argument(
        "--watchdog", type=float, default=0.5,
        help="brake a robot whose agent sent no command for this long [s] (as epuck_link does)",
    )  # fmt: skip
    ap.add_argument(
        "--deadline",
        type=float,
        default=0.5,
        help="realtime: command deadline after the tick, as a fraction of Ts",
    )
    args = ap.parse_args(argv)
    role = "tracker"
    try:
        scn, design = load_validated(args.scenario)
    except ConfigError as e:
        print(f"tracker: error: {e}", file=sys.stderr)
        return 2
    if args.source == "emulator" and args.clock != "realtime":
        print("tracker: error: --clock: the emulated robots move in wall time; use realtime", file=sys.stderr)
        return 2
    if not 0 < args.deadline <= 1 - LAG_LIMIT:
        # Beyond, the rest of the step is too short for this process's own work, and each
        # tick would go out later than the last until the clock starts over.
        print(
            f"tracker: error: --deadline: {args.deadline} outside (0, {1 - LAG_LIMIT:g}]: the tracker "
            "needs the rest of the step",
            file=sys.stderr,
        )
        return 2
    p = design.params
    seed = scn.simulation.seed if args.seed is None else args.seed
    rng = np.random.default_rng(seed)
    sim = scn.simulation
    dist = Disturbance(sim.disturbance, p.W, sim.disturbance_fraction, rng, p.point_noise)
    noise = PoseNoise(p.pose_noise, seed)
    ids = [r.id for r in scn.robots]
    steps = args.steps if args.steps is not None else round(scn.duration / p.Ts)
    keys = Keys(args.fleet)
    session = open_session(args)
    inbox = Inbox(keys, role, fault_plan(args))
    subs = [
        # Realtime: commands are read once, at the deadline; plans once a step.
        inbox.subscribe(session, keys.cmd(), Command, keep=True, drained=args.clock == "realtime"),
        inbox.subscribe(session, keys.plan(), Plan, keep=True, drained=args.clock == "realtime"),
        # What each epuck_link applied over a step (emulated robots: the link has the
        # deadline, not this process); a simulated robot's robot side is this process, and
        # a report for it is ignored.
        inbox.subscribe(session, keys.applied(), Applied, keep=True),
        inbox.watch_liveliness(session),
    ]
    world: SimulatedWorld | EmulatedWorld
    if args.source == "emulator":
        subs.append(inbox.subscribe(session, keys.emu(), Truth))
        world = EmulatedWorld(inbox, p.lookahead)
    else:
        world = SimulatedWorld(scn, design, dist)
    # Realtime: what the agents need goes out batched, not express.  Zenoh then
    # writes each agent's pose, odometry, digest and tick in one batch on its
    # link instead of one write each: the tracker's puts took 5 ms at 16 robots,
    # each write waking a receiver that took the core.  Lockstep keeps express
    # puts, which are faster when nothing else is waiting.
    lockstep = args.clock == "lockstep"
    pubs = {
        rid: (
            publisher(session, keys.pose(rid), express=lockstep),
            publisher(session, keys.odom(rid), express=lockstep),
            publisher(session, keys.truth(rid), express=False),
        )
        for rid in ids
    }
    clock = publisher(session, keys.clock, express=lockstep)
    relay = publisher(session, keys.digest, express=lockstep) if args.exchange == "relay" else None
    announce(role, robots=ids, steps=steps)
    code = 0
    try:
        everyone = {*ids, SUPERVISOR}
        if not inbox.wait(lambda: everyone <= inbox.live, args.start_timeout):
            missing = sorted(everyone - inbox.live)
            log(role, f"not up within {args.start_timeout} s: {', '.join(missing)}")
            return 1
        if args.source == "emulator" and not inbox.wait(
            lambda: all(inbox.get(Truth, r) is not None for r in ids), args.start_timeout
        ):
            silent = [r for r in ids if inbox.get(Truth, r) is None]
            log(role, f"no emulator pose on {keys.emu()} within {args.start_timeout} s: {', '.join(silent)}")
            return 1
        k = 0
        misses = 0
        sides = {rid: RobotSide(design, args.watchdog, world.drives) for rid in ids}
        reports = Reports(ids)
        heard: set[str] = set()
        braking = dict.fromkeys(ids, False)
        on_chain: dict[str, int] = {}
        braked_map: dict[str, int] = {}
        """What the next tick says about this step (Tick.fallback, Tick.braked)."""
        realtime = args.clock == "realtime"
        t_start = time.monotonic()
        restarts, behind_s, behind = 0, 0.0, False
        """Realtime: times the clock started over because this process fell behind it, the
        time [s] it lost so, and whether it is behind now (logged once an episode)."""
        for k in range(steps):
            t = k * p.Ts
            # Each robot's pose and odometry, the digest of the plans (relay), then the
            # tick, then the truth, which only the supervisor reads.  The tick comes
            # after what the agents need: the agents it wakes would otherwise take the
            # cores from this process before the last robots' poses are out (at 16
            # robots on 2 cores, the last ones missed their deadlines).  Simulated
            # robots are where they will be at the tick once the last step is
            # integrated, so their messages are made while waiting for the tick, and
            # at the tick only sent: 9 ms → 2 ms after the tick's time at 16 robots.
            early = world.known_ahead
            if early:
                with inbox.cond:
                    measured, truths, states = _measure(world, ids, noise, pubs, k, t, p.lookahead)
                inbox.drain()
                if relay and k > 0:
                    relayed = _relayed_plans(inbox, ids, k - 1, p.horizon, sides)
                    digest = Digest.of(role, k - 1, p.Ts, p.horizon, relayed).encode()
                    if realtime:
                        # Out now, in the second half of the step, when the commands are in
                        # and the cores idle: the agents decode it before the tick, not in
                        # the race to the next deadline (docs/runtime-notes.md).
                        relay.put(digest)
            if realtime:
                _until(t_start + t)
            inbox.drain()
            with inbox.cond:
                # Who answers this step: the live agents that have been heard since they
                # came up (at step 0, all of them).  One that (re)joins is waited for only
                # once a command of it arrived: before that it may not hear the clock yet
                # (a joining Zenoh peer can miss the first samples), and waiting on it
                # would stall the fleet.
                heard &= inbox.live
                for r in ids:
                    cmd = inbox.get(Command, r)
                    if r in inbox.live and cmd is not None and cmd.step >= k - 1:
                        heard.add(r)
                answering = [r for r in ids if r in inbox.live and (k == 0 or r in heard)]
            if not early:
                with inbox.cond:  # the emulators' poses come by callback
                    measured, truths, states = _measure(world, ids, noise, pubs, k, t, p.lookahead)
            if not world.drives and k > 0:
                # The links decided step k − 1 at their own deadlines: the tick says what they
                # did, and the digest leaves out the plans they did not execute.
                wait = REPORT_WAIT * p.Ts
                on_chain, braked_map, late = reports.for_tick(inbox, k, wait, partial(log, role))
                for r, done in (*on_chain.items(), *braked_map.items()):
                    remember_steps(sides[r].unexecuted, range(done + 1, k), k)  # only the recent part is kept
                if late:
                    misses += len(late)
                    log(role, f"step {k - 1}: deadline missed by {', '.join(late)} (seen by epuck_link)")
            for pub, payload in measured:
                pub.put(payload)
            if relay is not None and k > 0:
                now_relayed = _relayed_plans(inbox, ids, k - 1, p.horizon, sides)
                if (
                    not early
                    or len(now_relayed) != len(relayed)
                    or any(a is not b for a, b in zip(now_relayed, relayed, strict=True))
                ):  # a plan came since the digest was made (or nothing was made early)
                    relayed = now_relayed
                    digest = Digest.of(role, k - 1, p.Ts, p.horizon, relayed).encode()
                    relay.put(digest)
                elif not realtime:
                    relay.put(digest)
            clock.put(
                Tick(
                    robot=role, step=k, t=t, stop=False, misses=misses, fallback=on_chain, braked=braked_map
                ).encode()
            )
            sent = time.monotonic()
            for pub, payload in truths:
                pub.put(payload)
            if k % PROGRESS_EVERY == 0 and k:
                log(role, f"step {k}")
            if realtime and k < STARTUP_STEPS:
                # The first steps are taken in lockstep (STARTUP_STEPS): every answering
                # agent's command is waited for (bounded), then the wall clock starts
                # over from this step's deadline.
                inbox.drain_until(partial(_answered, inbox, answering, k), args.timeout)
                t_start = time.monotonic() - t - args.deadline * p.Ts
            elif realtime:
                # A command must arrive within the deadline, --deadline·Ts after its tick
                # went out (epuck_link counts from the tick's arrival); otherwise the robot
                # side follows the candidate (RobotSide) and the miss is counted.  This
                # process can fall behind the wall clock when the fleet takes its cores:
                # a tick then goes out late, and a deadline counted from the tick's time
                # would have passed before the agents heard of the step.  The 32-robot
                # runs of session 10 went so seconds behind, and every agent missed
                # every deadline from then on.  A tick more than LAG_LIMIT·Ts late starts
                # the clock over from it: the simulated world then runs slower than the
                # wall clock, which is logged (docs/runtime-notes.md, "Realtime clock").
                lag = sent - (t_start + t)
                if lag > LAG_LIMIT * p.Ts:
                    t_start += lag
                    restarts, behind_s = restarts + 1, behind_s + lag
                    if not behind:
                        log(
                            role,
                            f"step {k}: the tick went out {lag * 1e3:.0f} ms late; the clock starts over",
                        )
                behind = lag > LAG_LIMIT * p.Ts
                _until(sent + args.deadline * p.Ts)  # sent ≥ t_start + t: it waited for it
                inbox.drain()
                late = [r for r in ids if inbox.get(Command, r, k) is None and r in inbox.live]
                if late and world.drives:  # emulated robots: their links judge (Applied)
                    misses += len(late)
                    log(role, f"step {k}: deadline missed by {', '.join(late)}")
            else:
                answered = inbox.wait(partial(_answered, inbox, answering, k), args.timeout)
                if not answered:
                    late = [r for r in ids if inbox.get(Command, r, k) is None]
                    log(role, f"step {k}: no command from {', '.join(late)} within {args.timeout} s")
            with inbox.cond:
                live = set(inbox.live)
            on_chain, braked_map = {}, {}
            for rid in ids:
                side = sides[rid]
                what, a, why = side.decide(
                    k, inbox.get(Command, rid, k), inbox.get(Command, rid), rid in live, states.get(rid)
                )
                if (what == BRAKED) != braking[rid]:
                    braking[rid] = what == BRAKED
                    change = f"{why}; braking" if braking[rid] else "commands again"
                    log(role, f"step {k}: {rid}: {change}")
                if what == CANDIDATE:
                    on_chain[rid] = side.applied_step
                elif what == BRAKED:
                    if world.drives:
                        braked_map[rid] = side.applied_step
                    q = world.state(rid)[[1, 3]]
                    a = np.clip(-q / p.Ts, -p.a_max, p.a_max)
                assert a is not None
                side.last_a = a
                world.advance(rid, a, p.Ts)
            if not live & set(ids):
                log(role, f"step {k}: no agent alive; stopping the run")
                k += 1
                break
            # Agents send the command before the plan of a step; the early stop below
            # judges the plans of this very step, as `fleet simulate` does.
            inbox.wait(partial(_planned, inbox, answering, k), args.timeout if not realtime else 0.0)
            inbox.prune(k if world.drives else k - Reports.LOOKBACK)
            if _all_home(inbox, ids, world, k):
                k += 1
                break
        else:
            k = steps
        # Final poses, then stop.
        if realtime:
            _until(t_start + k * p.Ts)
        for rid in ids:
            with inbox.cond:
                x, y, th = (float(v) for v in world.pose(rid))
            pubs[rid][2].put(Truth(robot=rid, seq=k, t=k * p.Ts, x=x, y=y, theta=th).encode())
        clock.put(
            Tick(
                robot=role, step=k, t=k * p.Ts, stop=True, misses=misses, fallback=on_chain, braked=braked_map
            ).encode()
        )
        log(
            role,
            f"run ended at step {k}; {misses} deadline misses, {inbox.rejects.total} rejected payloads, "
            f"clock started over {restarts} times ({behind_s:.2f} s behind the wall clock)",
        )
    finally:
        for s in subs:
            s.undeclare()
        session.close()
    return code


def _measure(
    world: SimulatedWorld | EmulatedWorld, ids: list[str], noise: PoseNoise, pubs: dict[str, Any], k: int,
    t: float, lookahead: float,
) -> tuple[list[tuple[Any, bytes]], list[tuple[Any, bytes]], dict[str, np.ndarray]]:  # fmt: skip
    """The messages of step k at time t [s]: (publisher, payload) of each robot's camera pose
    and odometry, and of its true pose; and, with odometry, each robot's measured state
    (4,) [m, m/s], the agent's x from those messages.  Draws the camera noise, robot by robot."""
    measured: list[tuple[Any, bytes]] = []
    truths: list[tuple[Any, bytes]] = []
    states: dict[str, np.ndarray] = {}
    for rid in ids:
        pub_pose, pub_odom, pub_truth = pubs[rid]
        true = world.pose(rid).copy()
        mx, my, mth = (float(v) for v in true + noise.sample())
        measured.append((pub_pose, Pose(robot=rid, seq=k, t=t, x=mx, y=my, theta=mth).encode()))
        if world.odometry:
            state = world.state(rid)
            odom = Odom(robot=rid, seq=k, t=t, vx=float(state[1]), vy=float(state[3]))
            measured.append((pub_odom, odom.encode()))
            states[rid] = measured_state(np.array([mx, my, mth]), state[[1, 3]], lookahead)
        x, y, th = (float(v) for v in true)
        truths.append((pub_truth, Truth(robot=rid, seq=k, t=t, x=x, y=y, theta=th).encode()))
    return measured, truths, states


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


def _all_home(inbox: Inbox, ids: list[str], world: SimulatedWorld | EmulatedWorld, k: int) -> bool:
    """Every plan of step k (the latest, if it is missing) parked at its agent's
    current goal (a goal changed at run time counts) and every controlled point
    within half the goal tolerance of it."""
    for rid in ids:
        if rid not in inbox.live:
            continue  # a dead agent's robot is braked where it is: it cannot get home
        with inbox.cond:  # the plans' callbacks add to the history meanwhile
            plan = inbox.newest(Plan, rid, k)  # the plan of step k if it is in
        if plan is None or np.linalg.norm(plan.committed[-1] - plan.goal) >= 1e-3:
            return False
        with inbox.cond:
            pt = world.state(rid)[[0, 2]]
        if np.linalg.norm(pt - plan.goal) > 0.5 * GOAL_TOLERANCE:
            return False
    return True
