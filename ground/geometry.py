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
import re
from collections.abc import Sequence
from dataclasses import dataclass

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


# ---------------------------------------------------------------- places
Cell = tuple[int, int]
"""A square cell of the plane by place: (column, row), the floors of x / side and y / side."""


@dataclass(frozen=True)
class Whereabouts:
    """Where a robot's last committed point is, by cell (its newest place token, ``--exchange
    place``); once its agent is gone, where it was."""

    cell: Cell
    """The cell, of the fleet's side."""
    since: int
    """The step of the first plan whose last committed point was in ``cell`` [steps]."""


def cell_of(point: Sequence[float] | Array, side: float) -> Cell:
    """The cell of side ``side`` [m] holding ``point`` (2,) [m, world frame]."""
    return (math.floor(float(point[0]) / side), math.floor(float(point[1]) / side))


def cell_name(cell: Cell) -> str:
    """A cell as one chunk of a key expression: ``"3_-1"``."""
    return f"{cell[0]}_{cell[1]}"


_CELL_INT = re.compile(r"-?[0-9]{1,9}")


def parse_cell(name: str) -> Cell:
    """The inverse of :func:`cell_name`; raises ValueError on anything else."""
    col, sep, row = name.partition("_")
    if not sep or not _CELL_INT.fullmatch(col) or not _CELL_INT.fullmatch(row):
        raise ValueError(f"not a cell: {name[:40]!r}")
    return (int(col), int(row))


def cells_apart(a: Cell, b: Cell) -> int:
    """How many cells apart ``a`` and ``b`` are (Chebyshev): two points whose cells are
    d ≥ 2 apart are more than (d − 1) sides apart."""
    return max(abs(a[0] - b[0]), abs(a[1] - b[1]))


def block(centre: Cell, radius: int) -> set[Cell]:
    """The (2 radius + 1)² cells at most ``radius`` apart from ``centre``."""
    return {
        (centre[0] + i, centre[1] + j) for i in range(-radius, radius + 1) for j in range(-radius, radius + 1)
    }


def cell_centre(cell: Cell, side: float) -> Array:
    """The centre (2,) [m, world frame] of ``cell``; every point of it is within side / √2."""
    return np.array([(cell[0] + 0.5) * side, (cell[1] + 0.5) * side])
