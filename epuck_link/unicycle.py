"""Robot models: the unicycle, its feedback-linearising inner loops, wheels.

Unicycle plant (paper eq. 1), pose ``(x, y, θ)`` [m, m, rad] of the axle
centre in the world frame, inputs ``v`` [m/s] (forward speed) and ``ω``
[rad/s] (counter-clockwise)::

    ẋ = v cos θ,   ẏ = v sin θ,   θ̇ = ω

Two inner loops turn the MPC's acceleration ``a = (ax, ay)`` [m/s²] into
``(v, ω)`` so that a point of the robot behaves as the double integrator
``p̈ = a`` of :mod:`ground.model`:

* :class:`PaperInnerLoop` — paper eq. 3, dynamic extension of ``v``::

      v̇ = ax cos θ + ay sin θ,   ω = (−ax sin θ + ay cos θ) / v

  The controlled point is the axle centre.  At ``v = 0`` the map is
  singular; we divide by ``v_eff = sgn(v)·max(|v|, v_min)`` with
  ``sgn(0) = +1``.  Below ``v_min`` the lateral acceleration realised is
  ``(|v|/v_min)·a_⊥`` instead of ``a_⊥``: a robot at rest first turns on the
  spot and only then moves sideways.  That mismatch is a one-step prediction
  error that W must cover, which is why the ``epuck`` preset does not use it.

* :class:`LookaheadInnerLoop` (default, ``ℓ > 0``) — the controlled point
  ``p = (x, y) + ℓ (cos θ, sin θ)`` obeys ``ṗ = R(θ) [v, ℓω]ᵀ``, which is
  invertible for every pose.  Integrating ``q̇ = a`` and commanding
  ``[v, ω] = diag(1, 1/ℓ) R(θ)ᵀ q`` makes ``p̈ = a`` exactly, including from
  rest: the singularity is removed rather than regularised.  The body disc
  around ``p`` grows by ℓ (see ``TubeDesign.body_radius``).

Wheel speeds (E-puck, :class:`ground.params.WheelGeometry`): ``left = (v − ω L/2)/m``,
``right = (v + ω L/2)/m`` [steps/s] with ``m`` the rim travel per step.
Saturation scales both wheels by the same factor, which preserves the
curvature ``ω/v``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ground.geometry import Array, axle_centre, controlled_point, wrap_angle
from ground.params import WheelGeometry


def wheel_speeds(v: float, omega: float, geom: WheelGeometry) -> tuple[float, float, bool]:
    """(v [m/s], ω [rad/s]) → (left, right) [steps/s], saturated.

    Returns ``(left, right, saturated)``.  When a wheel would exceed
    ``geom.max_steps``, both are scaled by one factor so ``ω/v`` is kept."""
    m = geom.metres_per_step
    left = (v - 0.5 * omega * geom.axle) / m
    right = (v + 0.5 * omega * geom.axle) / m
    peak = max(abs(left), abs(right))
    if peak > geom.max_steps:
        s = geom.max_steps / peak
        return left * s, right * s, True
    return left, right, False


def unicycle_from_wheels(left: float, right: float, geom: WheelGeometry) -> tuple[float, float]:
    """(left, right) [steps/s] → (v [m/s], ω [rad/s])."""
    m = geom.metres_per_step
    return 0.5 * (left + right) * m, (right - left) * m / geom.axle


def integrate_unicycle(pose: Array, v: float, omega: float, dt: float) -> Array:
    """Exact pose after ``dt`` [s] at constant (v, ω).

    The chord of the arc is ``v·dt·sinc(ω dt/2)`` along ``θ + ω dt/2``; this form
    has no switch between arc and line and no cancellation for small ω."""
    x, y, th = pose
    h = 0.5 * omega * dt
    sinc = 1.0 - h * h / 6.0 if abs(h) < 1e-4 else math.sin(h) / h
    chord = v * dt * sinc
    mid = th + h
    return np.array([x + chord * math.cos(mid), y + chord * math.sin(mid), th + omega * dt])


class InnerLoop:
    """Common interface: keeps its own extension state, maps a → (v, ω)."""

    lookahead: float = 0.0

    def reset(self, pose: Array, velocity: Array) -> None:
        """Initialise the extension state from a pose and the velocity (2,) of the controlled point."""
        raise NotImplementedError

    def command(self, a: Array, pose: Array, dt: float) -> tuple[float, float]:
        """Advance the extension state by ``dt`` under acceleration ``a`` (2,) and return (v, ω)."""
        raise NotImplementedError

    def realised(self, v: float, omega: float, pose: Array) -> None:
        """Tell the loop what (v, ω) the robot actually executed (anti-windup)."""
        raise NotImplementedError

    def velocity(self, pose: Array) -> Array:
        """Velocity (2,) [m/s, world frame] of the controlled point implied by the extension state."""
        raise NotImplementedError

    def point(self, pose: Array) -> Array:
        """Controlled point (2,) [m, world frame] for an axle-centre pose."""
        return controlled_point(pose, self.lookahead)


@dataclass
class LookaheadInnerLoop(InnerLoop):
    """Exact feedback linearisation of the look-ahead point (see module docstring)."""

    lookahead: float
    q: Array | None = None
    """Extension state: commanded velocity of the controlled point (2,) [m/s]."""

    def __post_init__(self) -> None:
        if self.lookahead <= 0:
            raise ValueError("lookahead must be > 0 for LookaheadInnerLoop")
        if self.q is None:
            self.q = np.zeros(2)

    def reset(self, pose: Array, velocity: Array) -> None:
        """Set q to ``velocity`` (2,) [m/s, world frame] of the controlled point
        (``pose`` is unused)."""
        self.q = np.array(velocity, dtype=float)

    def _to_unicycle(self, q: Array, theta: float) -> tuple[float, float]:
        c, s = math.cos(theta), math.sin(theta)
        return c * q[0] + s * q[1], (-s * q[0] + c * q[1]) / self.lookahead

    def command(self, a: Array, pose: Array, dt: float) -> tuple[float, float]:
        """Advance q by ``dt`` [s] under ``a`` (2,) [m/s², world frame]; return
        (v [m/s], ω [rad/s]) for q at the interval's midpoint, at the heading of ``pose``."""
        assert self.q is not None
        q_mid = self.q + 0.5 * dt * np.asarray(a)  # midpoint: O(dt³) position error
        self.q = self.q + dt * np.asarray(a)
        return self._to_unicycle(q_mid, pose[2])

    def realised(self, v: float, omega: float, pose: Array) -> None:
        """Set q to the controlled point's velocity under the executed (v, ω) at
        ``pose`` (anti-windup after a saturated substep)."""
        # Only called after a saturated substep: the executed velocity of p.
        c, s = math.cos(pose[2]), math.sin(pose[2])
        self.q = np.array([c * v - s * self.lookahead * omega, s * v + c * self.lookahead * omega])

    def velocity(self, pose: Array) -> Array:
        """A copy of q (2,) [m/s, world frame] (``pose`` is unused)."""
        assert self.q is not None
        return self.q.copy()


@dataclass
class PaperInnerLoop(InnerLoop):
    """Paper eq. 3 with the ``|v| ≥ v_min`` regularisation of the divisor."""

    v_min: float
    v: float = 0.0
    """Extension state: forward speed [m/s] (negative when reversing)."""
    lookahead: float = 0.0

    def reset(self, pose: Array, velocity: Array) -> None:
        """Set v to the component of ``velocity`` (2,) [m/s, world frame] along the
        heading of ``pose``."""
        self.v = math.cos(pose[2]) * velocity[0] + math.sin(pose[2]) * velocity[1]

    def rates(self, a: Array, theta: float) -> tuple[float, float]:
        """Eq. 3: (v̇ [m/s²], ω [rad/s]) for acceleration ``a`` at heading θ."""
        c, s = math.cos(theta), math.sin(theta)
        v_eff = math.copysign(max(abs(self.v), self.v_min), self.v if self.v != 0.0 else 1.0)
        return c * a[0] + s * a[1], (-s * a[0] + c * a[1]) / v_eff

    def command(self, a: Array, pose: Array, dt: float) -> tuple[float, float]:
        """Advance v by ``dt`` [s] under ``a`` (2,) [m/s²] (:meth:`rates`); return
        (v at the interval's midpoint [m/s], ω [rad/s])."""
        vdot, omega = self.rates(a, pose[2])
        v_mid = self.v + 0.5 * dt * vdot
        self.v += dt * vdot
        return v_mid, omega

    def realised(self, v: float, omega: float, pose: Array) -> None:
        """Set v to the executed forward speed ``v`` [m/s] (``omega`` and ``pose`` unused)."""
        self.v = v

    def velocity(self, pose: Array) -> Array:
        """The axle centre's velocity v·(cos θ, sin θ) (2,) [m/s, world frame] at the
        heading θ of ``pose``."""
        return np.array([self.v * math.cos(pose[2]), self.v * math.sin(pose[2])])


def make_inner_loop(lookahead: float, v_min: float) -> InnerLoop:
    """Look-ahead loop for ℓ > 0, the paper's eq. 3 for ℓ = 0."""
    return LookaheadInnerLoop(lookahead) if lookahead > 0 else PaperInnerLoop(v_min)


class UnicyclePlant:
    """A simulated E-puck: unicycle + wheel saturation, driven by an inner loop.

    ``step(a, Ts)`` holds ``a`` for ``Ts`` and runs the inner loop every
    ``Ts / substeps``, as the link side would.  ``state()`` returns the
    double-integrator state ``[px, vx, py, vy]`` of the controlled point, with
    the velocity taken from the inner loop's extension state (what an agent
    knows without differentiating camera poses)."""

    def __init__(self, pose: Array, loop: InnerLoop, geom: WheelGeometry, substeps: int = 20):
        self.pose = np.array(pose, dtype=float)
        self.loop = loop
        self.geom = geom
        self.substeps = substeps
        self.saturated_substeps = 0
        loop.reset(self.pose, np.zeros(2))

    def state(self) -> Array:
        """Double-integrator state [px, vx, py, vy] (4,) [m, m/s] of the controlled point,
        world frame; the velocity is the inner loop's extension state."""
        p = self.loop.point(self.pose)
        q = self.loop.velocity(self.pose)
        return np.array([p[0], q[0], p[1], q[1]])

    def step(self, a: Array, Ts: float) -> tuple[float, float]:
        """Apply ``a`` (2,) [m/s²] for ``Ts`` [s]; return the last wheel command [steps/s]."""
        if type(self.loop) is LookaheadInnerLoop:
            return self._step_lookahead(float(a[0]), float(a[1]), Ts)
        return self._step_generic(a, Ts)

    def _step_lookahead(self, ax: float, ay: float, Ts: float) -> tuple[float, float]:
        """:meth:`_step_generic` for the look-ahead loop in scalar arithmetic, the same
        operations in the same order; about 4× faster (the simulated tracker steps every
        robot on the lockstep's critical path)."""
        loop = self.loop
        assert isinstance(loop, LookaheadInnerLoop) and loop.q is not None
        geom = self.geom
        ell, m, axle, top = loop.lookahead, geom.metres_per_step, geom.axle, geom.max_steps
        dt = Ts / self.substeps
        hdt = 0.5 * dt
        qx, qy = float(loop.q[0]), float(loop.q[1])
        x, y, th = float(self.pose[0]), float(self.pose[1]), float(self.pose[2])
        left = right = 0.0
        for _ in range(self.substeps):
            mx, my = qx + hdt * ax, qy + hdt * ay
            qx, qy = qx + dt * ax, qy + dt * ay
            c, s = math.cos(th), math.sin(th)
            v, omega = c * mx + s * my, (-s * mx + c * my) / ell
            left = (v - 0.5 * omega * axle) / m
            right = (v + 0.5 * omega * axle) / m
            peak = max(abs(left), abs(right))
            sat = peak > top
            if sat:
                k = top / peak
                left, right = left * k, right * k
                v, omega = 0.5 * (left + right) * m, (right - left) * m / axle
                self.saturated_substeps += 1
            h = 0.5 * omega * dt
            sinc = 1.0 - h * h / 6.0 if abs(h) < 1e-4 else math.sin(h) / h
            chord = v * dt * sinc
            mid = th + h
            x, y, th = x + chord * math.cos(mid), y + chord * math.sin(mid), th + omega * dt
            if sat:
                c, s = math.cos(th), math.sin(th)
                qx, qy = c * v - s * ell * omega, s * v + c * ell * omega
        self.pose = np.array([x, y, wrap_angle(th)])
        loop.q = np.array([qx, qy])
        return left, right

    def _step_generic(self, a: Array, Ts: float) -> tuple[float, float]:
        dt = Ts / self.substeps
        left = right = 0.0
        for _ in range(self.substeps):
            v, omega = self.loop.command(a, self.pose, dt)
            left, right, sat = wheel_speeds(v, omega, self.geom)
            if sat:
                v, omega = unicycle_from_wheels(left, right, self.geom)
                self.saturated_substeps += 1
            self.pose = integrate_unicycle(self.pose, v, omega, dt)
            if sat:
                self.loop.realised(v, omega, self.pose)
        self.pose[2] = wrap_angle(self.pose[2])
        return left, right

    def perturb(self, w: Array) -> None:
        """Add a disturbance ``w = [dpx, dvx, dpy, dvy]`` to the double-integrator state."""
        self.pose[0] += w[0]
        self.pose[1] += w[2]
        q = self.loop.velocity(self.pose) + np.array([w[1], w[3]])
        self.loop.reset(self.pose, q)


class DoubleIntegratorPlant:
    """The exact nominal model ``x⁺ = A x + B a`` (for theory tests)."""

    def __init__(self, pose: Array, A: Array, B: Array, lookahead: float = 0.0):
        px, py = controlled_point(pose, lookahead)
        self.x = np.array([px, 0.0, py, 0.0])
        self.A, self.B = A, B
        self.theta = float(pose[2])
        self.lookahead = lookahead

    @property
    def pose(self) -> Array:
        """A pose whose controlled point is the state's position; heading follows the velocity."""
        if math.hypot(self.x[1], self.x[3]) > 1e-6:
            self.theta = math.atan2(self.x[3], self.x[1])
        x, y = axle_centre(self.x[[0, 2]], self.theta, self.lookahead)
        return np.array([x, y, self.theta])

    def state(self) -> Array:
        """A copy of the state [px, vx, py, vy] (4,) [m, m/s]."""
        return self.x.copy()

    def step(self, a: Array, Ts: float) -> tuple[float, float]:
        """x ← A x + B ``a``, ``a`` (2,) [m/s²] (``Ts`` is unused: A and B are
        given); returns (0, 0): there are no wheels."""
        self.x = self.A @ self.x + self.B @ np.asarray(a)
        return 0.0, 0.0

    def perturb(self, w: Array) -> None:
        """Add ``w`` (4,) [m, m/s, m, m/s] to the state."""
        self.x = self.x + np.asarray(w)
