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
about the nominal state is here too (:func:`ancillary_law`).
"""

from __future__ import annotations

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
