"""The free-space floor of a robot's time to goal (``ground.model.travel_floor``): no input the
model allows beats it, the fastest one meets it within a sample, and a robot alone in
``fleet simulate`` takes no less."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from ground.model import double_integrator, travel_floor
from ground.params import ControllerParams
from ground.scenario import GOAL_TOLERANCE

P = ControllerParams()
TS = P.Ts


def _first_within(delta: np.ndarray, inputs, within: float, steps: int) -> float | None:
    """Run the nominal model from rest at the origin under ``inputs(x)`` (bounded per axis, the
    velocity clipped as X clips it); the first time [s] its point is within ``within`` of
    ``delta``, or None."""
    A, B, _ = double_integrator(TS)
    x = np.zeros(4)
    for k in range(steps + 1):
        if np.linalg.norm(x[[0, 2]] - delta) <= within:
            return k * TS
        u = np.clip(inputs(x), -P.a_max, P.a_max)
        x = A @ x + B @ u
        assert np.all(np.abs(x[[1, 3]]) <= P.v_max + 1e-9), "the input left the velocity bound"
    return None


def _fastest(delta: np.ndarray):
    """Each axis: full acceleration towards its target, up to v_max, braking only on the curve
    that stops it there; a braking curve from v_max is shorter than the tolerance, so the point
    enters it at full speed: the time-optimal way to come within reach of a point, sampled."""

    def inputs(x: np.ndarray) -> np.ndarray:
        e = delta - x[[0, 2]]
        want = np.sign(e) * np.minimum(P.v_max, np.sqrt(2.0 * P.a_max * np.abs(e)))
        return np.clip((want - x[[1, 3]]) / TS, -P.a_max, P.a_max)

    return inputs


@pytest.mark.parametrize(
    "delta", [np.array(d) for d in itertools.product([-1.3, -0.2, 0.0, 0.004, 0.6, 2.0], repeat=2)]
)
def test_the_fastest_input_meets_the_floor_within_a_sample(delta):
    floor = travel_floor(delta, P.v_max, P.a_max, GOAL_TOLERANCE)
    got = _first_within(delta, _fastest(delta), GOAL_TOLERANCE, 2000)
    assert got is not None
    # Per-axis tolerance is what the floor grants: the Euclidean one may take up to a few steps
    # more on a diagonal, where each axis must come closer than the tolerance.
    assert floor - 1e-9 <= got, (floor, got)
    assert got <= travel_floor(delta, P.v_max, P.a_max, GOAL_TOLERANCE / np.sqrt(2)) + TS + 1e-9, (floor, got)


def test_no_random_input_beats_the_floor():
    rng = np.random.default_rng(7)
    arrived = 0
    for _ in range(200):
        delta = rng.uniform(-0.6, 0.6, 2)
        floor = travel_floor(delta, P.v_max, P.a_max, GOAL_TOLERANCE)
        # Random inputs biased towards the target: arrivals, each no faster than the floor.
        bias = rng.uniform(0.0, 1.0)

        def inputs(x: np.ndarray, bias=bias, delta=delta) -> np.ndarray:
            toward = np.sign(delta - x[[0, 2]]) * P.a_max
            u = bias * toward + (1 - bias) * rng.uniform(-P.a_max, P.a_max, 2)
            v = x[[1, 3]] + u * TS  # keep the velocity in its bound, as X does
            return (np.clip(v, -P.v_max, P.v_max) - x[[1, 3]]) / TS

        got = _first_within(delta, inputs, GOAL_TOLERANCE, 600)
        if got is not None:
            arrived += 1
            assert got >= floor - 1e-9, (delta, got, floor)
    assert arrived >= 100  # the check above ran


def test_bad_bounds_are_refused():
    with pytest.raises(ValueError, match="v_max"):
        travel_floor(np.ones(2), 0.0, 0.5)


@pytest.mark.parametrize("seed", range(4))
def test_a_lone_robot_takes_no_less_than_its_floor_and_its_arrival_path_is_its_path_home(seed):
    """Seeded legs of 0.5 m and more, alone in free space: the robot gets home in no less than
    its floor and, as the liveness targets ask of every robot, in at most twice it (docs/method.md
    §7 gives ε/Ts as why it cannot come near 1); its path to arrival leaves out the hold at the
    goal and is no shorter than the straight line to the tolerance circle."""
    from fleet.running.simulate import run
    from ground.scenario import parse_scenario

    rng = np.random.default_rng(seed)
    while True:
        start, goal = rng.uniform(-0.8, 0.8, 2), rng.uniform(-0.8, 0.8, 2)
        if np.linalg.norm(goal - start) >= 0.5:
            break
    scene = {
        "name": "alone",
        "duration": 90.0,
        "arena": {"bounds": [-1.0, 1.0, -1.0, 1.0]},
        "robots": [{"id": "r1", "start": [*start, rng.uniform(-np.pi, np.pi)], "goal": list(goal)}],
    }
    s = run(parse_scenario(scene)).summary()["robots"]["r1"]
    assert s["reached_goal"]
    assert s["travel_floor_s"] <= s["time_to_goal_s"] <= 2.0 * s["travel_floor_s"], s
    assert s["straight_line_m"] - GOAL_TOLERANCE <= s["path_to_arrival_m"] <= s["path_length_m"]
