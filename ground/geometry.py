"""Geometry every process shares: a robot's controlled point, its measured state, and angles.

A robot's pose is ``(x, y, θ)`` [m, m, rad], its axle centre and heading in the world frame
(x east, y north, θ counter-clockwise from the x axis).  The MPC steers the *controlled
point*, ℓ [m] ahead of the axle along the heading (``ControllerParams.lookahead``)::

    p = (x, y) + ℓ (cos θ, sin θ)

ℓ > 0 makes ``p`` an exact double integrator under the look-ahead inner loop
(:class:`epuck_link.unicycle.LookaheadInnerLoop`); ℓ = 0 makes it the axle centre, as in the
paper.  Everything that maps a pose to the controlled point, or back, calls this module.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


def controlled_point(pose: Sequence[float] | Array, lookahead: float) -> Array:
    """The controlled point (2,) [m, world frame] of a pose ``(x, y, θ)`` [m, m, rad]:
    ``(x, y) + ℓ (cos θ, sin θ)`` with ℓ = ``lookahead`` [m]."""
    th = pose[2]
    return np.array([pose[0] + lookahead * math.cos(th), pose[1] + lookahead * math.sin(th)])


def axle_centre(point: Sequence[float] | Array, theta: float, lookahead: float) -> Array:
    """The axle centre (2,) [m, world frame] whose controlled point at heading ``theta`` [rad]
    is ``point`` (2,) [m]: the inverse of :func:`controlled_point`."""
    return np.array([point[0] - lookahead * math.cos(theta), point[1] - lookahead * math.sin(theta)])


def measured_state(
    pose: Sequence[float] | Array, velocity: Sequence[float] | Array, lookahead: float
) -> Array:
    """The controller's state ``x = [px, vx, py, vy]`` (4,) [m, m/s, world frame] from a camera
    pose ``(x, y, θ)`` [m, m, rad] and the odometry's velocity of the controlled point (2,) [m/s]."""
    x, y, th = float(pose[0]), float(pose[1]), float(pose[2])
    px = x + lookahead * math.cos(th)
    py = y + lookahead * math.sin(th)
    return np.array([px, float(velocity[0]), py, float(velocity[1])])


def wrap_angle(a: float) -> float:
    """The angle ``a`` [rad] wrapped to [−π, π)."""
    return (a + math.pi) % (2.0 * math.pi) - math.pi
