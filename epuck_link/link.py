"""The robot side of one E-puck: commands in, wheel speeds out, odometry back.

``python -m epuck_link --scenario S --robot ID [--link LINK] [--watchdog 0.5] [--rate 50]
[--fleet F] [--connect E] [--listen E]``

The agent publishes an acceleration ``a = (ax, ay)`` [m/s², world frame] of
the controlled point per step (:class:`ground.wire.Command`, ``u = v̂ + K(x − x̂)``).
This process runs the inner loop on the latest ``a`` at ``--rate`` Hz (≥ 50):
it integrates ``q̇ = a``, turns ``q`` into ``(v, ω)`` with the heading (the
latest camera heading from ``fleet/F/pose/R``, propagated between poses with
the commanded ω), into wheel speeds [steps/s] with curvature-preserving
saturation, and sends them chained with an encoder read.  It is
:class:`epuck_link.unicycle.UnicyclePlant`'s loop, run against a real robot.

Out:

* with every camera :class:`~ground.wire.Pose` of seq k, an
  :class:`~ground.wire.Odom` of seq k, same ``t``, carrying the inner loop's ``q``
  [m/s] (what the agent needs with each pose, as from the simulated tracker);
* with every encoder read, :class:`~ground.wire.Wheels` on ``fleet/F/wheels/R``:
  the unwrapped counts and (v, ω) from their deltas;
* at every tick, and at once when the radio link to the robot drops,
  :class:`~ground.wire.LinkState` on ``fleet/F/link/R``: while the link is down the
  robot has no deadman and drives on at the wheel speeds it last received; the message
  says how fast, and where the camera saw it last.  Once the link is back, zero speed
  is sent until the robot took it, the next step is reported braked, so the agent
  starts again, and the message names the step it starts again at.

Deadline (docs/design.md, "Missed deadlines"): step k starts when the
link receives tick k on ``fleet/F/clock``, and its command must come within
``--deadline``·Ts (0.5 by default, as for simulated robots).  Without it, the
link follows the shifted candidate of the last command it applied, with the
ancillary law ``u = v̂ + K(x − x̂)`` on the state of the step (the camera pose of
seq k with the odometry sent for it, the agent's own measurement to the bit; the
estimate at the tick while that pose has not come), or stops the wheels when there
is nothing left to follow or the agent is silent or dead
(:class:`epuck_link.robot_side.LinkDeadline`).  A command that comes after its
deadline is not applied.  At each decision the link publishes an
:class:`~ground.wire.Applied` report on ``fleet/F/applied/R``; the tracker puts it
in the next tick (with ``--delay-compensation``, in the step's outcome first), so
the agent takes the same candidate and its neighbours skip the plan that was never
executed.  Until the first tick (no clock on the network) commands are applied as
they come.

A starved link (docs/lab.md, "Robots that drive on"): the robot keeps the last wheel speeds it
received, so an inner-loop step that starts more than :data:`LATE` after it was due first sends
zero speed, before it takes any news or computes new speeds; the robot then stands while the
link catches up, and the step goes on as usual.  Such steps are counted and logged once per
episode.  While the loop is stalled, the port's thread sends zero instead of speeds asked more
than a period and :data:`LATE` ago (:class:`~epuck_link.transport.RobotPort` ``stale_after``).
A process that gets no CPU at all sends nothing: only a deadman in the firmware stops its robot.

Watchdog: without a command fresher than ``--watchdog`` seconds, or once the
agent's liveliness token ``fleet/F/alive/R`` is gone, the wheels get zero speed
(and ``q`` is reset to zero) until a new command arrives from a live agent.
Each such stop and each resumption is logged once.  SIGTERM sends zero speed,
closes the link and exits 0.

The link is the robot's ``link`` in the scenario unless ``--link`` overrides
it: ``serial:DEVICE`` (advanced sercom), ``tcp:HOST[:PORT]`` (e-puck2 Wi-Fi) or
``emulator`` (an in-process emulator that publishes its true pose on
``fleet/F/emu/R``).  Readiness line: ``{"event": "ready", "role":
"epuck_link", "pid", "robot", "link", "rate", "watchdog"}``.
"""

from __future__ import annotations

import argparse
import math
import signal
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from epuck_link.drive import MAX_DT, MIN_RATE, Drive, Watchdog, WheelOdometry
from epuck_link.protocol import MODELS, step_rate
from epuck_link.robot_side import BRAKED, CANDIDATE, LinkDeadline
from epuck_link.transport import (
    AsercomCodec,
    Codec,
    CutTransport,
    LinkSpec,
    LoopTransport,
    Reading,
    RobotPort,
    Transport,
    make_transport,
    parse_link,
)
from epuck_link.unicycle import make_inner_loop, unicycle_from_wheels
from ground.geometry import measured_state
from ground.scenario import ConfigError, RobotSpec, Scenario, load_scenario
from ground.wire import Command, Keys, LinkState, Odom, Pose, Tick
from transport.bus import Inbox, open_session, publisher
from transport.process import DEADLINE, add_common_args, announce, fault_plan, log

LATE = 1.0 / MIN_RATE
"""An inner-loop step that starts more than this after it was due sends zero speed first [s].

The robot holds the last wheel speeds it received until the next ones come, and the design
budgets that hold at one period of the slowest inner loop allowed, 1/MIN_RATE = 20 ms: about
12 % of W, while holding them a whole step costs about half of W (docs/design.md, "Where the
inner loop runs").  A step later than one more such period has let the robot hold its speeds
longer than that budget at any ``--rate`` (twice it at 50 Hz): they no longer follow the step's
acceleration, they are stale, and the robot must not drive on at them while the link catches
up, which on an overloaded machine can take seconds (a robot whose radio link was fine has
driven 0.145 m past a wall that way).  20 ms (Ts/5 for the presets) is also well above the
wake-up jitter of a loop that keeps up, a few ms, so a link that keeps up does not brake.  A
loop woken by news before its step is due is not late."""

MEASURED_KEPT = 4
"""Camera poses whose measured state is kept for the deadline's rule (:attr:`Link.measured`)."""

_OFF = {
    CANDIDATE: "following the shifted candidate of the last command applied",
    BRAKED: "nothing to follow; zero speed",
}
"""How each kind of step without a command in time is logged, at the start of its episode."""


def main(argv: list[str] | None = None) -> int:
    """``python -m epuck_link``: run the robot side of one E-puck until SIGTERM or SIGINT (see the
    module docstring); returns the exit code (0 once stopped, 2 bad input)."""
    ap = argparse.ArgumentParser(prog="python -m epuck_link", description=__doc__.splitlines()[0])
    add_common_args(ap)
    ap.add_argument("--robot", required=True, help="robot id from the scenario")
    ap.add_argument(
        "--link", default=None, help="override the robot's link: serial:DEV, tcp:HOST[:PORT], emulator"
    )
    ap.add_argument(
        "--watchdog", type=float, default=0.5, help="stop without a fresh command for this long [s]"
    )
    ap.add_argument("--rate", type=float, default=MIN_RATE, help=f"inner-loop rate [Hz], ≥ {MIN_RATE:.0f}")
    ap.add_argument(
        "--deadline", type=float, default=DEADLINE,
        help="a step's command is due this long after its tick, as a fraction of Ts (as the tracker's)",
    )  # fmt: skip
    args = ap.parse_args(argv)
    try:
        scn, spec, link = _checked(args)
    except ConfigError as e:
        print(f"epuck_link: error: {e}", file=sys.stderr)
        return 2
    keys = Keys(args.fleet)
    session = open_session(args)
    robot = Link(args, scn, spec, link, session, keys)
    stopping = threading.Event()

    def on_signal(signum: int, frame: Any) -> None:
        stopping.set()
        with robot.inbox.cond:
            robot.inbox.cond.notify_all()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    robot.start()
    announce("epuck_link", robot=spec.id, link=str(link), rate=args.rate, watchdog=args.watchdog)
    try:
        while not stopping.is_set():
            robot.run_once(stopping)
    finally:
        robot.close()
        session.close()
    return 0


def _checked(args: argparse.Namespace) -> tuple[Scenario, RobotSpec, LinkSpec]:
    """The scenario, this robot's entry and its link; ConfigError names the bad option."""
    scn = load_scenario(args.scenario)
    me = args.robot
    spec = next((r for r in scn.robots if r.id == me), None)
    if spec is None:
        raise ConfigError(
            "--robot", f"{me!r} is not in the scenario (robots: {', '.join(r.id for r in scn.robots)})"
        )
    if not (math.isfinite(args.watchdog) and 0 < args.watchdog <= 10):
        raise ConfigError("--watchdog", f"{args.watchdog} s outside (0, 10]")
    if not (math.isfinite(args.rate) and MIN_RATE <= args.rate <= 1000):
        raise ConfigError("--rate", f"{args.rate} Hz outside [{MIN_RATE:.0f}, 1000]")
    if not (math.isfinite(args.deadline) and 0 < args.deadline < 1):
        raise ConfigError("--deadline", f"{args.deadline} outside (0, 1)")
    try:
        link = parse_link(args.link if args.link is not None else spec.link)
    except ValueError as e:
        raise ConfigError("--link" if args.link is not None else f"robots.{me}.link", str(e)) from None
    if link.kind == "sim":
        raise ConfigError(
            "link", f"{me} is simulated by the tracker (link 'sim'); give --link serial:, tcp: or emulator"
        )
    return scn, spec, link


def _emulated(robot: str, start: tuple[float, float, float], pub: Any) -> tuple[Transport, Codec, Any]:
    """The ``emulator`` link: an in-process emulator behind a loop transport, publishing its truth."""
    from epuck_link.emulator import EpuckEmulator, TruthPublisher

    emu = EpuckEmulator(start)
    truth = TruthPublisher(emu, robot, pub.put)
    return LoopTransport(emu.serial_handler), AsercomCodec(), truth


class Link:
    """One robot's side: its inner loop, watchdog, deadline rule and port to the robot."""

    def __init__(
        self, args: argparse.Namespace, scn: Scenario, spec: RobotSpec, link: LinkSpec, session: Any,
        keys: Keys, clock: Callable[[], float] = time.monotonic,
    ):  # fmt: skip
        self.clock = clock
        """The inner loop's time [s]: when its steps are due, and how late they start.  On
        time.monotonic's timescale, which the inbox dates arrivals on (tests shift it)."""
        self.me = me = spec.id
        self.role = role = f"epuck_link {me}"
        p = self.p = scn.controller
        geom = p.wheel
        self.drive = Drive(make_inner_loop(p.lookahead, p.v_min), geom, np.array(spec.start, dtype=float))
        self.watchdog = Watchdog(args.watchdog)
        self.deadline = LinkDeadline(me, p, args.watchdog, args.deadline * p.Ts)
        self.inbox = inbox = Inbox(keys, role, fault_plan(args))
        self.subs = [
            inbox.subscribe(session, keys.cmd(me), Command),
            inbox.subscribe(session, keys.pose(me), Pose, keep=True),  # each pose is answered
            inbox.subscribe(session, keys.clock, Tick),
            inbox.watch_liveliness(session),
        ]
        self.pub_odom = publisher(session, keys.odom(me))
        pub_wheels = publisher(session, keys.wheels(me))
        self.pub_applied = publisher(session, keys.applied(me))
        self.pub_link = publisher(session, keys.link(me))
        self.link_lock = threading.RLock()
        self.link_up = True
        """The radio link to the robot is up: False from the port's thread at a loss, True from
        the main loop once the robot took the zero speed after it."""
        self.link_sent: tuple[tuple[int, int], ...] = ((0, 0),)
        """The wheel speeds [steps/s] the robot may have last received (one pair or two)."""
        self.link_lost = -1
        """The newest tick when the link was last lost (−1: never)."""
        self.link_back = -1
        """The first step planned from where the robot stands after the last outage (−1: none)."""
        self.camera: Pose | None = None
        """The newest camera pose."""
        self.measured: dict[int, np.ndarray] = {}
        """The state each recent camera pose gave with the odometry sent for it, by its seq
        (4,) [px, vx, py, vy] in m, m/s, world frame: what the agent measured at that step."""
        self.tick_step = -1
        """The newest tick received (−1 before the first)."""
        self.truth = None
        if link.kind == "emulator":
            transport, codec, self.truth = _emulated(me, spec.start, publisher(session, keys.emu(me)))
        else:
            transport, codec = make_transport(link)
        plan = inbox.faults
        if plan is not None and plan.links.get(me):
            transport = CutTransport(transport, lambda: plan.link_cut(me, self.tick_step))
        odometry = WheelOdometry(geom, time.monotonic())

        self.relinked = threading.Event()
        """Set by the port's thread at the first read after a lost link came back."""
        self.relinked_after = 0
        """The outages (``port.lost``) counted when the link last came back."""

        def on_reading(r: Reading) -> None:
            if r.fresh_link and self.port.lost:
                self.relinked_after = self.port.lost
                self.relinked.set()
            pub_wheels.put(odometry.update(me, r).encode())

        def on_lost(possible: tuple[tuple[int, int], ...]) -> None:
            with self.link_lock:
                self.link_up, self.link_sent = False, possible
                self.link_lost, self.link_back = max(self.tick_step, 0), -1
                self._announce_link()

        self.period = 1.0 / args.rate
        self.port = RobotPort(
            transport,
            codec,
            lambda m: log(role, m),
            on_reading,
            period=self.period,
            on_lost=on_lost,
            resume_by_hand=True,
            stale_after=self.period + LATE,  # the loop asks every period while it is on time
            clock=clock,
        )
        self.seen_cmd: Command | None = None
        self.seen_tick: Tick | None = None
        self.last_cmd_at: float | None = None
        self.decided_at: float | None = None
        """When the deadline's rule last decided a step [s]: with the clock, what the watchdog watches."""
        self.a = np.zeros(2)
        """The acceleration the inner loop holds (2,) [m/s², world frame]."""
        self.braked = False
        """Stopped by the deadline's rule (nothing to follow) until a command is applied."""
        self.episode = ""
        """What the robot did instead of the last commands: "", CANDIDATE or BRAKED (logged once)."""
        self.odoms = 0
        self.links_down = 0
        """Link-down announcements sent."""
        self.off_steps = {CANDIDATE: 0, BRAKED: 0}
        self.due = self.last = 0.0
        """When the next inner-loop step is due, and when the last one ran [s, :attr:`clock`]."""
        self.wheels = (0, 0)
        """The wheel speeds [steps/s] the inner loop last asked the port for."""
        self.late_steps = 0
        """Inner-loop steps that started over :data:`LATE` late with the wheels turning: braked first."""
        self.late_episodes = 0
        """Runs of such steps (each logged once)."""
        self.late_worst = 0.0
        """The latest of them [s after it was due]."""
        self.late_episode = False
        """The last inner-loop step started late: the episode goes on until one is on time."""

    def start(self) -> None:
        """Open the port to the robot (and start the emulator's truth): the inner loop runs from now."""
        self.port.start()
        if self.truth is not None:
            self.truth.start()
        self.due = self.last = self.clock()

    def run_once(self, stopping: threading.Event) -> None:
        """Wait for news or the next inner-loop tick, take what came, drive one inner-loop step."""
        inbox, me, drive, deadline = self.inbox, self.me, self.drive, self.deadline
        poses = (Pose.TYPE, me)

        def news() -> bool:
            return (
                stopping.is_set()
                or inbox.get(Command, me) is not self.seen_cmd
                or inbox.get(Tick, "tracker") is not self.seen_tick
                or bool(inbox.history.get(poses))
            )

        inbox.wait(news, max(0.0, min(self.due, deadline.wake_at) - self.clock()))
        now = self.clock()
        late = now - self.due > LATE
        if late and self.wheels != (0, 0):  # first of all: the robot is driving on at stale speeds
            self._brake_late(now)
        with inbox.cond:
            cmd = inbox.get(Command, me)
            tick = inbox.get(Tick, "tracker")
            # When they arrived, not when this loop got to them (a loaded machine).
            cmd_at = inbox.arrived.get((Command.TYPE, me), now)
            tick_at = inbox.arrived.get((Tick.TYPE, "tracker"), now)
            fresh_poses = list(inbox.history.pop(poses, {}).values())  # in order of arrival
            live = me in inbox.live
        if self.relinked.is_set():
            self.relinked.clear()
            log(self.role, "link back after an outage: robot stopped; braked until its agent starts again")
            back = deadline.relinked()
            drive.halt()
            self.braked = True
            # The port sent zero since the re-open; the speeds asked during the outage are stale.
            self.port.command(0, 0)
            self.port.resume()
            with self.link_lock:  # the robot took the zero speed: up, and trusted from step `back`
                if self.port.lost == self.relinked_after:  # and not lost again since
                    self.link_up, self.link_back = True, back
                self._announce_link()
        if fresh_poses:
            self.camera = fresh_poses[-1]
        for pose in fresh_poses:
            drive.on_pose(pose.x, pose.y, pose.theta)
            vx, vy = drive.velocity()
            self.pub_odom.put(Odom(robot=me, seq=pose.seq, t=pose.t, vx=vx, vy=vy).encode())
            self.odoms += 1
            # The agent's measurement of this step, to the bit: the candidate's ancillary law
            # uses it, so that an agent planning a step ahead predicts the input applied.
            x = measured_state((pose.x, pose.y, pose.theta), (vx, vy), self.p.lookahead)
            self.measured[pose.seq] = x
            deadline.measured(pose.seq, x)
        while len(self.measured) > MEASURED_KEPT:
            del self.measured[next(iter(self.measured))]  # the oldest
        decisions = []
        if tick is not self.seen_tick and tick is not None:
            self.seen_tick, self.tick_step = tick, tick.step
            # At every tick, up or down: one lost or out-of-order message never sticks.
            self._announce_link()
            inbox.release(tick.step)  # messages the fault plan delays
            inbox.prune(tick.step - 2)
            if not tick.stop:  # the state of step k: its camera pose and the odometry sent with it,
                # or without that pose (yet), the estimate at the tick
                x_k = self.measured.get(tick.step)
                if x_k is None:
                    x_k = measured_state(drive.pose, drive.velocity(), self.p.lookahead)
                decisions += deadline.tick(tick.step, tick_at, x_k, cmd, live)
                self._hold_extended()
        if cmd is not self.seen_cmd and cmd is not None:
            self.seen_cmd, self.last_cmd_at = cmd, cmd_at
            if deadline.step is None:  # no clock yet: applied as it comes
                self.a, self.braked = np.array([cmd.ax, cmd.ay]), False
            elif (taken := deadline.command(cmd, cmd_at, live)) is not None:
                decisions.append(taken)
        if (expired := deadline.expire(now, cmd, live)) is not None:
            decisions.append(expired)
        for what, acc, report in decisions:
            self._decided(now, what, acc, report)
        if now >= self.due:
            if not late:
                self.late_episode = False
            self._drive(now, live)

    def _brake_late(self, now: float) -> None:
        """This inner-loop step started more than :data:`LATE` after it was due (the process was
        starved), and the robot drives on at the speeds it was last sent, now stale: zero speed
        goes to the robot before anything else, ahead of the speeds this step will ask for
        (:meth:`RobotPort.brake`).  The step then takes its news and decides as usual (the
        deadline's rule is unchanged), so the robot stands only while the link catches up."""
        self.port.brake()
        late = now - self.due
        self.late_steps += 1
        self.late_worst = max(self.late_worst, late)
        if not self.late_episode:
            self.late_episode = True
            self.late_episodes += 1
            log(
                self.role,
                f"inner loop {late:.3f} s late (the link process was starved): zero speed first; the "
                f"robot drove on at {self.wheels} steps/s meanwhile",
            )

    def _hold_extended(self) -> None:
        """Before the agent has started again after an outage, a missed tick can lengthen the
        deadline rule's hold: the agent then starts again later, and its plans up to then are
        still of a robot that was not following them.  Move ``back`` with it."""
        deadline = self.deadline
        with self.link_lock:
            if 0 <= self.link_back and deadline.step is not None and deadline.step < self.link_back:
                if deadline.hold_until + 1 > self.link_back:
                    self.link_back = deadline.hold_until + 1
                    self._announce_link()

    def _announce_link(self) -> None:
        """Publish the link's state (:class:`~ground.wire.LinkState`): while it is down the robot
        drives on at ``link_sent``, so say how fast its controlled point can move, and where the
        camera saw it last."""
        with self.link_lock:  # the port's thread and the main loop both announce
            self._put_link_state()

    def _put_link_state(self) -> None:
        # The motors step a little faster than asked (whole timer periods): bound it for both
        # models, and for every speed pair the robot may be driving on at.
        speed, (left, right) = max((self._speed(pair, m), pair) for pair in self.link_sent for m in MODELS)
        cam = self.camera
        point = (0.0, 0.0) if cam is None else (
            cam.x + self.p.lookahead * math.cos(cam.theta), cam.y + self.p.lookahead * math.sin(cam.theta)
        )  # fmt: skip
        msg = LinkState(
            robot=self.me, up=self.link_up, step=self.tick_step, lost=self.link_lost, back=self.link_back,
            left=left, right=right, speed=speed,
            seq=-1 if cam is None else cam.seq, x=point[0], y=point[1],
        )  # fmt: skip
        self.pub_link.put(msg.encode())
        if not self.link_up:
            self.links_down += 1

    def _speed(self, wheels: tuple[int, int], model: str) -> float:
        """Speed [m/s] of the controlled point at these wheel speeds [steps/s] on ``model``."""
        v, w = unicycle_from_wheels(step_rate(wheels[0], model), step_rate(wheels[1], model), self.p.wheel)
        return math.hypot(v, w * self.p.lookahead)

    def _decided(self, now: float, what: str, acc: np.ndarray | None, report: Any) -> None:
        """Apply and report one decision of the deadline's rule."""
        self.decided_at = now
        self.pub_applied.put(report.encode())
        self.braked = acc is None  # braked, or its agent asks for the brake (Command.brake)
        if acc is not None:
            self.a = np.asarray(acc, dtype=float)
        if what in self.off_steps:
            self.off_steps[what] += 1
            if what != self.episode:
                log(self.role, f"step {report.step}: no command in time; {_OFF[what]} (step {report.last})")
        elif self.episode:
            log(self.role, f"step {report.step}: commands in time again")
        self.episode = what if what in self.off_steps else ""

    def _drive(self, now: float, live: bool) -> None:
        """One inner-loop step: the watchdog, then the wheel speeds to the robot."""
        # With the clock, a decision every step keeps the watchdog quiet (the deadline's rule
        # brakes for a silent agent, and says so); without ticks, a command does.
        if self.deadline.step is None:
            ok, event = self.watchdog.check(now, self.last_cmd_at, live)
        else:
            ok, event = self.watchdog.check(now, self.decided_at, live, "tick")
        if event is not None:
            log(self.role, event)
            if not ok:
                self.deadline.side.brake()  # nothing is followed after a stop
        dt = min(now - self.last, MAX_DT)
        self.last = now
        if ok and not self.braked:
            left, right = self.drive.step(self.a, dt)
        else:
            self.drive.halt()
            left = right = 0
        self.port.command(left, right)
        self.wheels = (left, right)
        self.due += self.period
        if self.due < now:  # behind (a loaded machine): no burst of catch-up steps
            self.due = now + self.period

    def close(self) -> None:
        """Stop the robot port, which sends zero speed (best effort, :meth:`RobotPort.close`), and
        the in-process emulator's truth publisher, if any; log the closing counts and undeclare the
        subscribers."""
        sent = self.port.close()
        if self.truth is not None:
            self.truth.close()
        log(
            self.role,
            f"stopped: zero speed {'sent' if sent else 'NOT sent'}; {self.port.reads} encoder reads, "
            f"{self.port.lost} link losses ({self.links_down} announced), {self.watchdog.events} watchdog "
            f"stops, {self.odoms} odometry "
            f"messages, {self.drive.saturated_steps} saturated steps, "
            f"{self.off_steps[CANDIDATE]} steps on the candidate, {self.off_steps[BRAKED]} braked by the "
            f"deadline's rule, {self.late_steps} late inner-loop steps braked first ({self.late_episodes} "
            f"episodes, the latest {self.late_worst:.3f} s late), {self.port.stale} stalls braked by the "
            f"port, {self.inbox.rejects.total} rejected payloads",
        )
        for s in self.subs:
            s.undeclare()
