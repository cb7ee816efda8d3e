"""The pure parts of the robot side of an E-puck: the inner loop with its heading estimate, the
watchdog, and the wheel odometry.  :mod:`epuck_link.link` runs them against a real robot.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from epuck_link import protocol as P
from epuck_link.transport import Reading
from epuck_link.unicycle import InnerLoop, integrate_unicycle, unicycle_from_wheels
from ground.geometry import Array, wrap_angle
from ground.params import WheelGeometry
from ground.wire import Wheels

MIN_RATE = 50.0
"""Slowest inner loop allowed [Hz] (docs/design.md, "Where the inner loop runs")."""
MAX_DT = 0.1
"""Longest inner-loop step [s]; a stalled loop does not integrate more than this at once."""


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
