"""The simulated world: robots as simulated plants, their disturbances and their camera.

The simulated tracker (:mod:`tracker.sim`) and ``fleet simulate`` (:mod:`fleet.running.simulate`) move
the same plants with the same disturbances and draw the same camera noise, in the same order
from the same seeds, so that a lockstep run of the process fleet reproduces ``fleet simulate``
bit for bit.

* :class:`Disturbance` — the process disturbance w in f·W, less the pose noise's share;
  ``uniform`` samples the box, ``adversarial`` picks the vertex that pushes the tube error
  ``x − x̂`` outward on every component, ``none``;
* :class:`PoseNoise` — the simulated camera's pose error, within ``pose_noise``;
* :func:`make_plant` — a unicycle with its inner loop, or the exact nominal model;
* :class:`SimulatedWorld`, :class:`EmulatedWorld` — what the tracker moves, or only watches.
"""

from __future__ import annotations

import numpy as np

from epuck_link.unicycle import DoubleIntegratorPlant, UnicyclePlant, make_inner_loop
from ground.geometry import Array, controlled_point, measured_state
from ground.model import double_integrator
from ground.params import ControllerParams
from ground.scenario import Scenario
from ground.wire import Truth
from transport.bus import Inbox


class Disturbance:
    """Samples the process disturbance w (4,) [m, m/s]; ``kind`` is uniform, adversarial or none.

    Its box is f·W less 2·``point_noise`` on the position axes [m], so that
    w plus the change of the pose noise between two measurements stays in f·W."""

    def __init__(
        self,
        kind: str,
        W: tuple[float, float],
        fraction: float,
        rng: np.random.Generator,
        point_noise: float = 0.0,
    ):
        self.kind = kind
        budget = fraction * np.array([W[0], W[1], W[0], W[1]])
        self.half = np.maximum(budget - 2.0 * point_noise * np.array([1.0, 0.0, 1.0, 0.0]), 0.0)
        self.rng = rng

    def sample(self, tube_error: Array) -> Array:
        """One draw of w (4,) [m, m/s, m, m/s]: zero (``none``), uniform in the box
        (``uniform``), or at a corner of the box (``adversarial``), in the signs of ``tube_error`` (4,) and
        a random sign where it is zero."""
        if self.kind == "none":
            return np.zeros(4)
        if self.kind == "uniform":
            return self.rng.uniform(-1.0, 1.0, 4) * self.half
        s = np.sign(tube_error)
        zero = s == 0
        s[zero] = self.rng.choice([-1.0, 1.0], size=int(zero.sum()))
        return s * self.half


class PoseNoise:
    """The simulated camera's pose error: a normal with σ = bound/2, clipped to ±bound.

    ``bounds`` = (position per axis [m], heading [rad]).  It draws from its own
    generator, seeded from the run's seed, so the disturbance sequence does
    not depend on it and the tracker process reproduces ``fleet simulate`` exactly."""

    def __init__(self, bounds: tuple[float, float], seed: int):
        self.bound = np.array([bounds[0], bounds[0], bounds[1]], dtype=float)
        self.rng = np.random.default_rng([seed, 1])

    def sample(self) -> Array:
        """One pose error (3,): [m, m, rad]."""
        n = self.rng.normal(0.0, 0.5, 3) * self.bound
        return np.clip(n, -self.bound, self.bound)


def measure(
    plant: UnicyclePlant | DoubleIntegratorPlant, noise: PoseNoise, lookahead: float
) -> tuple[Array, Array]:
    """One measurement of ``plant``: its state (4,) [m, m/s] as the agent sees it, from a noisy
    camera pose and exact odometry, and that camera pose (3,) [m, m, rad] (the tracker
    publishes the same)."""
    pose = plant.pose + noise.sample()
    return measured_state(pose, plant.state()[[1, 3]], lookahead), pose


def make_plant(kind: str, start: Array, p: ControllerParams) -> UnicyclePlant | DoubleIntegratorPlant:
    """A simulated robot at pose ``start`` (3,) [m, m, rad], at rest: the unicycle with its inner
    loop (``"unicycle"``) or the exact nominal model (``"double_integrator"``)."""
    if kind == "double_integrator":
        A, B, _ = double_integrator(p.Ts)
        return DoubleIntegratorPlant(start, A, B, lookahead=p.lookahead)
    return UnicyclePlant(start, make_inner_loop(p.lookahead, p.v_min), p.wheel)


class SimulatedWorld:
    """The robots as simulated plants, moved here from the agents' commands."""

    odometry = True
    drives = True
    """This process applies the commands (it is the robot side)."""
    known_ahead = True
    """Where the robots are at the next tick is known once the step is integrated."""

    def __init__(self, scn: Scenario, dist: Disturbance):
        self.plants = {
            r.id: make_plant(scn.simulation.plant, np.array(r.start, float), scn.controller)
            for r in scn.robots
        }
        self.dist = dist

    def pose(self, rid: str) -> np.ndarray:
        """True axle-centre pose (3,) [m, m, rad], world frame."""
        return self.plants[rid].pose

    def state(self, rid: str) -> np.ndarray:
        """Controlled-point state [px, vx, py, vy] (4,) [m, m/s]."""
        return self.plants[rid].state()

    def advance(self, rid: str, a: np.ndarray, Ts: float, braked: bool = False) -> None:
        """Hold acceleration ``a`` (2,) [m/s²] for ``Ts`` [s], then add the disturbance, unless
        the robot side ``braked`` the robot (:func:`ground.model.brake_input`): its wheels are
        then stopped, not tracking, and a standing e-puck's steppers hold it where it is, so
        the disturbance, which stands for the inner loop's tracking error, is drawn (the draws
        stay in step with ``fleet simulate``'s) but not applied (docs/method.md §6.4)."""
        plant = self.plants[rid]
        x_before = plant.state()
        plant.step(a, Ts)
        w = self.dist.sample(x_before * 0.0)
        if not braked:
            plant.perturb(w)


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
        """The newest true pose (x, y, θ) (3,) [m, m, rad] of ``rid``'s emulator, world frame
        (its :class:`Truth` on ``fleet/F/emu/R``); asserts that one has come."""
        t = self.inbox.get(Truth, rid)
        assert t is not None, "pose() before every emulator reported"
        return np.array([t.x, t.y, t.theta])

    def state(self, rid: str) -> np.ndarray:
        """Controlled-point state [px, 0, py, 0] (4,) [m, m/s]: the emulators report no velocity."""
        px, py = controlled_point(self.pose(rid), self.lookahead)
        return np.array([px, 0.0, py, 0.0])

    def advance(self, rid: str, a: np.ndarray, Ts: float, braked: bool = False) -> None:
        """Nothing to do: the emulated wheels move in wall time."""
