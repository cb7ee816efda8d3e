"""The robot side of one E-puck: commands in, wheel speeds out, odometry back.

``python -m epuck_link --scenario S --robot ID [--link LINK] [--watchdog 0.5] [--rate 50]
[--fleet F] [--connect E] [--listen E]``

The agent publishes an acceleration ``a = (ax, ay)`` [m/s², world frame] of
the controlled point per step (:class:`fleet.wire.Command`, ``u = v̂ + K(x − x̂)``).
This process runs the inner loop on the latest ``a`` at ``--rate`` Hz (≥ 50):
it integrates ``q̇ = a``, turns ``q`` into ``(v, ω)`` with the heading (the
latest camera heading from ``fleet/F/pose/R``, propagated between poses with
the commanded ω), into wheel speeds [steps/s] with curvature-preserving
saturation, and sends them chained with an encoder read.  It is
:class:`agent.models.UnicyclePlant`'s loop, run against a real robot.

Out:

* with every camera :class:`~fleet.wire.Pose` of seq k, an
  :class:`~fleet.wire.Odom` of seq k, same ``t``, carrying the inner loop's ``q``
  [m/s] (what the agent needs with each pose, as from the simulated tracker);
* with every encoder read, :class:`~fleet.wire.Wheels` on ``fleet/F/wheels/R``:
  the unwrapped counts and (v, ω) from their deltas.

Deadline (docs/runtime-notes.md, "Missed deadlines"): step k starts when the
link receives tick k on ``fleet/F/clock``, and its command must come within
``--deadline``·Ts (0.5 by default, as for simulated robots).  Without it, the
link follows the shifted candidate of the last command it applied, with the
ancillary law ``u = v̂ + K(x − x̂)`` on the state it measured at the tick, or
stops the wheels when there is nothing left to follow or the agent is silent or
dead (:class:`fleet.robot_side.LinkDeadline`).  A command that comes after its
deadline is not applied.  At each decision the link publishes an
:class:`~fleet.wire.Applied` report on ``fleet/F/applied/R``; the tracker puts it
in the next tick, so the agent takes the same candidate and its neighbours skip
the plan that was never executed.  Until the first tick (no clock on the
network) commands are applied as they come.

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
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from agent.models import (
    InnerLoop,
    integrate_unicycle,
    make_inner_loop,
    measured_state,
    unicycle_from_wheels,
    wrap_angle,
)
from agent.params import WheelGeometry
from agent.sets import Array
from epuck_link import protocol as P
from epuck_link.transport import (
    AsercomCodec,
    Codec,
    LinkSpec,
    LoopTransport,
    Reading,
    RobotPort,
    Transport,
    make_transport,
    parse_link,
)
from fleet.robot_side import BRAKED, CANDIDATE, LinkDeadline
from fleet.wire import Command, Keys, Odom, Pose, Tick, Wheels

MIN_RATE = 50.0
"""Slowest inner loop allowed [Hz] (docs/runtime-notes.md: the prediction error grows below)."""
MAX_DT = 0.1
"""Longest inner-loop step [s]; a stalled loop does not integrate more than this at once."""


# ------------------------------------------------------------- pure parts
class Drive:
    """The inner loop, the heading estimate and the wheel conversion.

    ``pose`` (3,) [m, m, rad, world frame] is the axle-centre estimate: set by
    each camera pose, propagated between poses with the commanded (v, ω)."""

    def __init__(self, loop: InnerLoop, geom: WheelGeometry, pose: Array):
        self.loop = loop
        self.geom = geom
        self.pose = np.array(pose, dtype=float)
        self.saturated_steps = 0
        loop.reset(self.pose, np.zeros(2))

    def on_pose(self, x: float, y: float, theta: float) -> None:
        """A camera pose [m, m, rad]: the estimate jumps to it."""
        self.pose = np.array([x, y, theta])

    def step(self, a: Array, dt: float) -> tuple[int, int]:
        """Hold acceleration ``a`` (2,) [m/s², world frame] for ``dt`` [s]; return (left, right) [steps/s]."""
        v, omega = self.loop.command(np.asarray(a, dtype=float), self.pose, dt)
        left, right, sat = P.wheel_steps(v, omega, self.geom)
        if sat:
            v, omega = unicycle_from_wheels(left, right, self.geom)
            self.saturated_steps += 1
        self.pose = integrate_unicycle(self.pose, v, omega, dt)
        self.pose[2] = wrap_angle(self.pose[2])
        if sat:
            self.loop.realised(v, omega, self.pose)
        return left, right

    def halt(self) -> None:
        """Stopped wheels: the extension state q goes to zero."""
        self.loop.reset(self.pose, np.zeros(2))

    def velocity(self) -> tuple[float, float]:
        """The inner loop's q: velocity of the controlled point [m/s, world frame]."""
        q = self.loop.velocity(self.pose)
        return float(q[0]), float(q[1])


@dataclass
class Watchdog:
    """Whether the wheels may turn: a command fresher than ``timeout`` [s] from a live agent.

    Starts stopped.  Once stopped it resumes only on a command received after
    the stop, so a live agent whose commands merely stalled, or a token that
    comes back without new commands, never restarts the robot."""

    timeout: float
    stopped: bool = True
    stopped_at: float = -math.inf
    events: int = 0
    """Stops so far (not counting the initial one)."""

    def check(
        self, now: float, last_command: float | None, live: bool, what: str = "command"
    ) -> tuple[bool, str | None]:
        """(drive allowed, event to log or None) at time ``now`` [s].

        ``last_command``: when the latest command arrived [s, same clock], or None; with the
        fleet's clock, when the deadline's rule last decided a step (``what`` = "tick")."""
        fresh = last_command is not None and now - last_command <= self.timeout
        if not self.stopped:
            if live and fresh:
                return True, None
            self.stopped, self.stopped_at = True, now
            self.events += 1
            if not live:
                return False, "watchdog: the agent's liveliness token is gone; zero speed"
            assert last_command is not None
            return False, f"watchdog: no {what} for {now - last_command:.2f} s; zero speed"
        if live and fresh and last_command is not None and last_command > self.stopped_at:
            self.stopped = False
            return True, "commands from a live agent: driving"
        return False, None


@dataclass
class WheelOdometry:
    """Encoder readings → unwrapped counts, and (v, ω) from their deltas.

    The speeds are taken over the reads of the last ``window`` seconds (at
    least two reads): the counts are whole steps and the read times jitter by
    milliseconds, so one 20 ms interval alone is noisy."""

    geom: WheelGeometry
    origin: float
    """``t = 0`` of the published Wheels [s, time.monotonic]."""
    window: float = 0.1
    """Baseline of the speed estimate [s]."""
    tracker: P.EncoderTracker = field(default_factory=P.EncoderTracker)
    seq: int = 0
    _recent: deque[tuple[float, int, int]] = field(default_factory=deque)

    def update(self, robot: str, r: Reading) -> Wheels:
        """The Wheels message of one encoder reading."""
        if r.fresh_link:
            self.tracker.rebase()  # a re-opened link: the robot may have restarted its counts
            self._recent.clear()
        left, right = self.tracker.update(r.left, r.right)
        recent = self._recent
        recent.append((r.t, left, right))
        while len(recent) > 2 and r.t - recent[1][0] >= self.window:
            recent.popleft()
        v = omega = 0.0
        t0, l0, r0 = recent[0]
        if r.t > t0:
            dt = r.t - t0
            v, omega = unicycle_from_wheels((left - l0) / dt, (right - r0) / dt, self.geom)
        t = r.t - self.origin
        msg = Wheels(robot=robot, seq=self.seq, t=t, left_steps=left, right_steps=right, v=v, omega=omega)
        self.seq += 1
        return msg


# ------------------------------------------------------------------- shell
_OFF = {
    CANDIDATE: "following the shifted candidate of the last command applied",
    BRAKED: "nothing to follow; zero speed",
}
"""How each kind of step without a command in time is logged, at the start of its episode."""


def _emulated(robot: str, start: tuple[float, float, float], pub: Any) -> tuple[Transport, Codec, Any]:
    """The ``emulator`` link: an in-process emulator behind a loop transport, publishing its truth."""
    from epuck_link.emulator import EpuckEmulator, TruthPublisher

    emu = EpuckEmulator(start)
    truth = TruthPublisher(emu, robot, pub.put)
    return LoopTransport(emu.serial_handler), AsercomCodec(), truth


def main(argv: list[str] | None = None) -> int:
    from fleet.runtime import (
        Inbox,
        add_common_args,
        announce,
        fault_plan,
        load_validated,
        log,
        open_session,
        publisher,
    )
    from fleet.scenario import ConfigError

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
        "--deadline", type=float, default=0.5,
        help="a step's command is due this long after its tick, as a fraction of Ts (as the tracker's)",
    )  # fmt: skip
    args = ap.parse_args(argv)
    me = args.robot
    role = f"epuck_link {me}"

    def fail(what: str, reason: str) -> int:
        print(f"epuck_link: error: {what}: {reason}", file=sys.stderr)
        return 2

    try:
        scn, design = load_validated(args.scenario)
    except ConfigError as e:
        print(f"epuck_link: error: {e}", file=sys.stderr)
        return 2
    spec = next((r for r in scn.robots if r.id == me), None)
    if spec is None:
        return fail(
            "--robot", f"{me!r} is not in the scenario (robots: {', '.join(r.id for r in scn.robots)})"
        )
    if not (math.isfinite(args.watchdog) and 0 < args.watchdog <= 10):
        return fail("--watchdog", f"{args.watchdog} s outside (0, 10]")
    if not (math.isfinite(args.rate) and MIN_RATE <= args.rate <= 1000):
        return fail("--rate", f"{args.rate} Hz outside [{MIN_RATE:.0f}, 1000]")
    if not (math.isfinite(args.deadline) and 0 < args.deadline < 1):
        return fail("--deadline", f"{args.deadline} outside (0, 1)")
    try:
        link: LinkSpec = parse_link(args.link if args.link is not None else spec.link)
    except ValueError as e:
        return fail("--link" if args.link is not None else f"robots.{me}.link", str(e))
    if link.kind == "sim":
        return fail(
            "link", f"{me} is simulated by the tracker (link 'sim'); give --link serial:, tcp: or emulator"
        )

    p = design.params
    geom = p.wheel
    drive = Drive(make_inner_loop(p.lookahead, p.v_min), geom, np.array(spec.start, dtype=float))
    watchdog = Watchdog(args.watchdog)
    judge = LinkDeadline(me, design, args.watchdog, args.deadline * p.Ts)
    keys = Keys(args.fleet)
    session = open_session(args)
    inbox = Inbox(keys, role, fault_plan(args))
    subs = [
        inbox.subscribe(session, keys.cmd(me), Command),
        inbox.subscribe(session, keys.pose(me), Pose, keep=True),  # each pose is answered
        inbox.subscribe(session, keys.clock, Tick),
        inbox.watch_liveliness(session),
    ]
    pub_odom = publisher(session, keys.odom(me))
    pub_wheels = publisher(session, keys.wheels(me))
    pub_applied = publisher(session, keys.applied(me))
    truth = None
    if link.kind == "emulator":
        transport, codec, truth = _emulated(me, spec.start, publisher(session, keys.emu(me)))
    else:
        transport, codec = make_transport(link)
    origin = time.monotonic()
    odometry = WheelOdometry(geom, origin)

    def on_reading(r: Reading) -> None:
        pub_wheels.put(odometry.update(me, r).encode())

    port = RobotPort(transport, codec, lambda m: log(role, m), on_reading, period=1.0 / args.rate)
    stopping = threading.Event()

    def on_signal(signum: int, frame: Any) -> None:
        stopping.set()
        with inbox.cond:
            inbox.cond.notify_all()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    port.start()
    if truth is not None:
        truth.start()
    announce("epuck_link", robot=me, link=str(link), rate=args.rate, watchdog=args.watchdog)
    period = 1.0 / args.rate
    seen_cmd: Command | None = None
    seen_tick: Tick | None = None
    last_cmd_at: float | None = None
    decided_at: float | None = None
    """When the deadline's rule last decided a step [s]: with the clock, what the watchdog watches."""
    a = np.zeros(2)
    braked = False
    """Stopped by the deadline's rule (nothing to follow) until a command is applied."""
    episode = ""
    """What the robot did instead of the last commands: "", CANDIDATE or BRAKED (logged once)."""
    odoms = 0
    off_steps = {CANDIDATE: 0, BRAKED: 0}
    now = time.monotonic()
    due = last = now

    poses = (Pose.TYPE, me)

    def news() -> bool:
        return (
            stopping.is_set()
            or inbox.get(Command, me) is not seen_cmd
            or inbox.get(Tick, "tracker") is not seen_tick
            or bool(inbox.history.get(poses))
        )

    try:
        while not stopping.is_set():
            inbox.wait(news, max(0.0, min(due, judge.wake_at) - time.monotonic()))
            now = time.monotonic()
            with inbox.cond:
                cmd = inbox.get(Command, me)
                tick = inbox.get(Tick, "tracker")
                # When they arrived, not when this loop got to them (a loaded machine).
                cmd_at = inbox.arrived.get((Command.TYPE, me), now)
                tick_at = inbox.arrived.get((Tick.TYPE, "tracker"), now)
                fresh_poses = list(inbox.history.pop(poses, {}).values())  # in order of arrival
                live = me in inbox.live
            for pose in fresh_poses:
                drive.on_pose(pose.x, pose.y, pose.theta)
                vx, vy = drive.velocity()
                pub_odom.put(Odom(robot=me, seq=pose.seq, t=pose.t, vx=vx, vy=vy).encode())
                odoms += 1
            decisions = []
            if tick is not seen_tick and tick is not None:
                seen_tick = tick
                inbox.release(tick.step)  # messages the fault plan delays
                inbox.prune(tick.step - 2)
                if not tick.stop:  # the state at the tick: the camera pose of this step, and q
                    x_k = measured_state(drive.pose, np.array(drive.velocity()), p.lookahead)
                    decisions += judge.tick(tick.step, tick_at, x_k, cmd, live)
            if cmd is not seen_cmd and cmd is not None:
                seen_cmd, last_cmd_at = cmd, cmd_at
                if judge.step is None:  # no clock yet: applied as it comes
                    a, braked = np.array([cmd.ax, cmd.ay]), False
                elif (taken := judge.command(cmd, cmd_at, live)) is not None:
                    decisions.append(taken)
            if (expired := judge.expire(now, cmd, live)) is not None:
                decisions.append(expired)
            for what, acc, report in decisions:
                decided_at = now
                pub_applied.put(report.encode())
                braked = what == BRAKED
                if acc is not None:
                    a = np.asarray(acc, dtype=float)
                if what in off_steps:
                    off_steps[what] += 1
                    if what != episode:
                        log(
                            role, f"step {report.step}: no command in time; {_OFF[what]} (step {report.last})"
                        )
                elif episode:
                    log(role, f"step {report.step}: commands in time again")
                episode = what if what in off_steps else ""
            if now < due:
                continue
            # With the clock, a decision every step keeps the watchdog quiet (the deadline's
            # rule brakes for a silent agent, and says so); without ticks, a command does.
            if judge.step is None:
                ok, event = watchdog.check(now, last_cmd_at, live)
            else:
                ok, event = watchdog.check(now, decided_at, live, "tick")
            if event is not None:
                log(role, event)
                if not ok:
                    judge.side.brake()  # nothing is followed after a stop
            dt = min(now - last, MAX_DT)
            last = now
            if ok and not braked:
                left, right = drive.step(a, dt)
            else:
                drive.halt()
                left = right = 0
            port.command(left, right)
            due += period
            if due < now:  # behind (a loaded machine): no burst of catch-up steps
                due = now + period
    finally:
        sent = port.close()
        if truth is not None:
            truth.close()
        log(
            role,
            f"stopped: zero speed {'sent' if sent else 'NOT sent'}; {port.reads} encoder reads, "
            f"{port.lost} link losses, {watchdog.events} watchdog stops, {odoms} odometry messages, "
            f"{drive.saturated_steps} saturated steps, {off_steps[CANDIDATE]} steps on the candidate, "
            f"{off_steps[BRAKED]} braked by the deadline's rule, {inbox.rejects.total} rejected payloads",
        )
        for s in subs:
            s.undeclare()
        session.close()
    return 0
