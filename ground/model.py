"""The nominal model every robot is planned with, and which its robot side propagates.

Each axis of the controlled point is a double integrator, sampled at ``Ts`` [s] with a
zero-order hold on the acceleration::

    x = [px, vx, py, vy]   [m, m/s, m, m/s], world frame
    u = [ax, ay]           [m/s²], world frame
    x⁺ = A x + B u,        A = blkdiag(A₁, A₁),  B = blkdiag(B₁, B₁)
    A₁ = [[1, Ts], [0, 1]],  B₁ = [[Ts²/2], [Ts]]

The agent's tube MPC plans with it (:mod:`agent.tube`), and the robot side propagates the
nominal state of a command's shifted candidate with it when a command misses its deadline
(:func:`chain_input`): both take it from here, and so does an agent planning a step ahead,
which predicts what its robot side applied.  The ancillary law that keeps the robot in its tube
about the nominal state is here too (:func:`ancillary_law`), and so is the brake that every robot
side applies when it stops a robot (:func:`brake_input`), with what it bounds (:func:`stopping`).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


def double_integrator(Ts: float) -> tuple[Array, Array, Array]:
    """``(A (4, 4), B (4, 2), C (2, 4))`` of the two decoupled double integrators at period
    ``Ts`` [s]; ``C`` selects the position ``(px, py)``."""
    A = np.zeros((4, 4))
    B = np.zeros((4, 2))
    for i in (0, 1):
        A[2 * i : 2 * i + 2, 2 * i : 2 * i + 2] = [[1.0, Ts], [0.0, 1.0]]
        B[2 * i : 2 * i + 2, i] = [0.5 * Ts * Ts, Ts]
    C = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]])
    return A, B, C


def position_to_rest_state() -> Array:
    """``E`` (4, 2): maps a position ``[x, y]`` [m] to the state at rest there."""
    return np.array([[1.0, 0.0], [0.0, 0.0], [0.0, 1.0], [0.0, 0.0]])


def chain_input(x_next: Array, v_next: Array, m: int, x: Array, A: Array, B: Array, K: Array) -> Array | None:
    """The robot side's fallback ``m`` ≥ 0 steps after the step of the last command it
    applied (m = 0: the very next step), with no command in time.

    ``x_next`` (4,) and ``v_next`` (M, 2) are that command's shifted candidate
    (:attr:`StepOutput.x_next`); ``x`` (4,) [m, m/s] is the measured state now.
    Returns u = v̂ + K(x − x̂) (2,) [m/s²] with x̂ propagated m steps by the nominal
    model x̂⁺ = A x̂ + B v̂, or None once the candidate is used up (m ≥ M).  The
    agent, told so by the tick, takes the same candidate (``TubeMPC.rewind``):
    it is feasible by construction, so x − x̂ stays in Z and the references
    already committed stay valid."""
    if not 0 <= m < v_next.shape[0]:
        return None
    x_hat = np.asarray(x_next, dtype=float)
    for i in range(m):
        x_hat = A @ x_hat + B @ v_next[i]
    return ancillary_law(x, x_hat, v_next[m], K)


def ancillary_law(x: Array, x_hat: Array, v_hat: Array, K: Array) -> Array:
    """The ancillary law, the one place its sign is written: u = v̂ + K(x − x̂) (2,) [m/s²] for
    the state ``x`` (4,) [m, m/s], the nominal state ``x_hat`` (4,) and input ``v_hat`` (2,) of
    the same step, and the gain ``K`` (2, 4) [1/s², 1/s]."""
    return np.asarray(v_hat + K @ (np.asarray(x, dtype=float) - x_hat))


def brake_input(v: Array, Ts: float, a_max: float) -> Array:
    """The brake, per axis: the acceleration (2,) [m/s²] that stops the velocity ``v`` (2,) [m/s]
    of the controlled point within one step of ``Ts`` [s] if ``a_max`` [m/s²] allows, else
    ``a_max`` against it.  Every robot side brakes a robot with it (the simulated tracker,
    ``fleet simulate``), and so does an agent that holds without poses; its bound is
    :func:`stopping`."""
    return np.clip(-np.asarray(v, dtype=float) / Ts, -a_max, a_max)


MAX_BRAKE_STEPS = 10_000
"""Most steps :func:`stopping` follows a brake for before it gives up [steps]."""


def travel_floor(delta: Array, v_max: float, a_max: float, within: float = 0.0) -> float:
    """The least time [s] in which the controlled point, at rest, can come within ``within`` [m]
    of a point ``delta`` (2,) [m] away, under the model's bounds |v| ≤ ``v_max`` [m/s] and
    |a| ≤ ``a_max`` [m/s²] per axis, on any path, with no one in the way: a lower bound on any
    robot's time to goal.

    The axes are independent double integrators, so the time is the larger of the two axes'
    (the faster axis can always slow down to match).  Each axis must cover at least its
    displacement less ``within`` (a point within ``within`` of the goal is within it on each
    axis), and an axis covering d from rest at best accelerates at ``a_max`` to ``v_max``,
    cruises and arrives at full speed: d/v_max + v_max/(2·a_max) if d ≥ v_max²/(2·a_max), else
    √(2·d/a_max).  Arriving at rest would take longer, so this bounds a robot that stops at its
    goal too, and sampling only adds time.  Raises ValueError for a non-positive bound."""
    if not (v_max > 0 and a_max > 0):
        raise ValueError(f"travel_floor: v_max {v_max} and a_max {a_max} must be > 0")
    ramp = v_max * v_max / (2.0 * a_max)
    worst = 0.0
    for d in np.maximum(np.abs(np.asarray(delta, dtype=float).reshape(2)) - within, 0.0):
        t = d / v_max + v_max / (2.0 * a_max) if d >= ramp else math.sqrt(2.0 * d / a_max)
        worst = max(worst, float(t))
    return worst


def stopping(v_max: float, a_max: float, Ts: float) -> tuple[int, float]:
    """(steps [steps], distance [m]): a robot whose controlled point moves at most ``v_max``
    [m/s] per axis and is braked by :func:`brake_input` from a sample on, with ``a_max`` [m/s²]
    at period ``Ts`` [s], is at rest after ``steps`` steps and stays there, and its controlled
    point has moved at most ``distance`` from where the brake began (Euclidean: the axes brake
    independently, so √2 times one axis's distance).

    Per axis the speed falls by ``a_max·Ts`` a step, and the last step takes what is left, so
    the worst case starts at ``v_max``: followed here step by step (zero-order hold, the
    nominal model :func:`double_integrator`).  The velocity bound holds while the state is in
    X, which the tube keeps (docs/method.md §3).  Raises ValueError for a non-positive bound
    or period, or if the brake does not stop within :data:`MAX_BRAKE_STEPS`."""
    if not (v_max >= 0 and a_max > 0 and Ts > 0):
        raise ValueError(f"stopping: v_max {v_max}, a_max {a_max} and Ts {Ts} must be ≥ 0, > 0, > 0")
    v, dist, steps = float(v_max), 0.0, 0
    while v > 0.0:
        if steps >= MAX_BRAKE_STEPS:
            raise ValueError(f"stopping: no rest within {MAX_BRAKE_STEPS} steps")
        a = min(v / Ts, a_max)
        dist += v * Ts - 0.5 * a * Ts * Ts
        v = 0.0 if a < a_max else v - a_max * Ts
        steps += 1
    return steps, math.sqrt(2.0) * dist
