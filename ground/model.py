"""The nominal model every robot is planned with, and which its robot side propagates.

Each axis of the controlled point is a double integrator, sampled at ``Ts`` [s] with a
zero-order hold on the acceleration::

    x = [px, vx, py, vy]   [m, m/s, m, m/s], world frame
    u = [ax, ay]           [m/s²], world frame
    x⁺ = A x + B u,        A = blkdiag(A₁, A₁),  B = blkdiag(B₁, B₁)
    A₁ = [[1, Ts], [0, 1]],  B₁ = [[Ts²/2], [Ts]]

The agent's tube MPC plans with it (:mod:`agent.tube`), and the robot side propagates the
nominal state of a command's shifted candidate with it when a command misses its deadline
(:func:`epuck_link.robot_side.chain_input`): both take it from here.
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
