"""Robot models (epuck_link/unicycle.py): wheels, exact unicycle arcs and the two inner loops.

The inner loops must make the controlled point behave as the double integrator of
docs/method.md §1, including from rest, where the paper's eq. 3 is singular.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from agent.tube import double_integrator
from epuck_link.unicycle import (
    DoubleIntegratorPlant,
    LookaheadInnerLoop,
    PaperInnerLoop,
    UnicyclePlant,
    integrate_unicycle,
    make_inner_loop,
    unicycle_from_wheels,
    wheel_speeds,
    wrap_angle,
)
from ground.params import WheelGeometry, preset

GEOM = WheelGeometry()
TS = 0.1
HEADINGS = (0.0, 0.7, math.pi / 2, 2.5, math.pi, -math.pi / 2, -2.2)


def _unit(angle: float) -> np.ndarray:
    return np.array([math.cos(angle), math.sin(angle)])


def _random_commands(rng: np.random.Generator, n: int) -> list[tuple[float, float]]:
    """(v, ω) pairs: small, E-puck-sized, huge, pure rotations and pure translations."""
    out: list[tuple[float, float]] = []
    for _ in range(n):
        scale_v = 10.0 ** rng.uniform(-4, 3)  # 0.1 mm/s .. 1 km/s
        scale_w = 10.0 ** rng.uniform(-4, 4)
        out.append((float(rng.uniform(-1, 1) * scale_v), float(rng.uniform(-1, 1) * scale_w)))
    out += [(0.0, 1e4), (0.0, -1e4), (1e3, 0.0), (-1e3, 0.0), (0.2, 50.0), (-0.2, -50.0)]
    return out


# --------------------------------------------------------------------------- wheels


def test_wheel_speeds_straight_line_exact_value():
    left, right, sat = wheel_speeds(0.05, 0.0, GEOM)
    expected = 0.05 / GEOM.metres_per_step
    assert expected == pytest.approx(388.18, abs=0.01)
    assert left == pytest.approx(expected, rel=1e-12)
    assert right == pytest.approx(expected, rel=1e-12)
    assert not sat


def test_metres_per_step_and_top_speed_match_epuck_geometry():
    # 2π · 20.5 mm / 1000 steps; top speed ≈ 0.129 m/s.
    assert GEOM.metres_per_step == pytest.approx(2 * math.pi * 0.0205 / 1000, rel=1e-12)
    assert GEOM.max_wheel_speed == pytest.approx(0.129, abs=5e-4)


def test_wheel_speeds_linear_formula_when_unsaturated():
    rng = np.random.default_rng(1)
    m, L = GEOM.metres_per_step, GEOM.axle
    checked = 0
    for _ in range(2000):
        v = float(rng.uniform(-0.12, 0.12))
        omega = float(rng.uniform(-4.0, 4.0))
        left, right, sat = wheel_speeds(v, omega, GEOM)
        exp_l, exp_r = (v - omega * L / 2) / m, (v + omega * L / 2) / m
        if max(abs(exp_l), abs(exp_r)) <= GEOM.max_steps:
            assert not sat
            assert left == pytest.approx(exp_l, rel=1e-12, abs=1e-9)
            assert right == pytest.approx(exp_r, rel=1e-12, abs=1e-9)
            checked += 1
        else:
            assert sat
    assert checked > 500  # the sample really exercised the unsaturated branch


def test_wheel_saturation_bounds_both_wheels_and_preserves_curvature():
    rng = np.random.default_rng(2)
    n_sat = 0
    for v, omega in _random_commands(rng, 3000):
        left, right, sat = wheel_speeds(v, omega, GEOM)
        assert math.isfinite(left) and math.isfinite(right)
        assert abs(left) <= GEOM.max_steps * (1 + 1e-12)
        assert abs(right) <= GEOM.max_steps * (1 + 1e-12)
        v2, w2 = unicycle_from_wheels(left, right, GEOM)
        # Same curvature ω/v: the vector (v, ω·L/2) keeps its direction (scaled, never rotated).
        half = 0.5 * GEOM.axle
        if v != 0 or omega != 0:
            turn = math.atan2(omega * half, v) - math.atan2(w2 * half, v2)
            assert abs(wrap_angle(turn)) <= 1e-9
        # Same signs (a scaling by a positive factor, never a reversal).
        assert v2 * v >= 0 and w2 * omega >= 0
        if v != 0:
            assert np.sign(v2) == np.sign(v)
        if omega != 0:
            assert np.sign(w2) == np.sign(omega)
        if sat:
            n_sat += 1
            # Scaled down, never up, and the larger wheel sits exactly at the limit.
            assert max(abs(left), abs(right)) == pytest.approx(GEOM.max_steps, rel=1e-12)
            m, half = GEOM.metres_per_step, 0.5 * GEOM.axle
            scale = GEOM.max_steps / max(abs(v - omega * half), abs(v + omega * half)) * m
            assert 0 < scale < 1
            # Up to the rounding of the wheel arithmetic (1e-12 of the wheel range).
            assert v2 == pytest.approx(scale * v, rel=1e-9, abs=1e-12 * GEOM.max_wheel_speed)
            assert w2 == pytest.approx(scale * omega, rel=1e-9, abs=1e-12 * GEOM.max_wheel_speed / half)
        else:
            assert v2 == pytest.approx(v, rel=1e-9, abs=1e-15)
            assert w2 == pytest.approx(omega, rel=1e-9, abs=1e-12)
    assert n_sat > 500


def test_pure_rotation_saturates_symmetrically():
    for omega in (50.0, -50.0, 1e3, -1e6):
        left, right, sat = wheel_speeds(0.0, omega, GEOM)
        assert sat
        assert left == pytest.approx(-right, rel=1e-15)
        assert abs(left) == pytest.approx(GEOM.max_steps, rel=1e-12)
        v2, w2 = unicycle_from_wheels(left, right, GEOM)
        assert v2 == pytest.approx(0.0, abs=1e-15)
        assert np.sign(w2) == np.sign(omega)
        assert abs(w2) == pytest.approx(2 * GEOM.max_wheel_speed / GEOM.axle, rel=1e-12)
    # Counter-clockwise rotation turns the right wheel forward.
    left, right, _ = wheel_speeds(0.0, 1.0, GEOM)
    assert right > 0 > left


def test_wheel_round_trip_when_unsaturated():
    rng = np.random.default_rng(3)
    for _ in range(1000):
        v = float(rng.uniform(-0.06, 0.06))
        omega = float(rng.uniform(-2.5, 2.5))
        left, right, sat = wheel_speeds(v, omega, GEOM)
        assert not sat
        v2, w2 = unicycle_from_wheels(left, right, GEOM)
        assert v2 == pytest.approx(v, abs=1e-14)
        assert w2 == pytest.approx(omega, abs=1e-12)


# --------------------------------------------------------------------------- exact arc


def _rk4(pose: np.ndarray, v: float, omega: float, dt: float, n: int = 2000) -> np.ndarray:
    def f(s: np.ndarray) -> np.ndarray:
        return np.array([v * math.cos(s[2]), v * math.sin(s[2]), omega])

    s = np.array(pose, dtype=float)
    h = dt / n
    for _ in range(n):
        k1 = f(s)
        k2 = f(s + 0.5 * h * k1)
        k3 = f(s + 0.5 * h * k2)
        k4 = f(s + h * k3)
        s = s + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return s


def test_integrate_unicycle_matches_fine_rk4():
    rng = np.random.default_rng(4)
    cases = [
        (float(rng.uniform(-0.2, 0.2)), float(rng.uniform(-10, 10)), float(rng.uniform(1e-3, 0.5)))
        for _ in range(40)
    ]
    # ω ≈ 0 on both sides of the straight-line switch, and exactly 0.
    cases += [(0.1, w, 0.3) for w in (0.0, 1e-12, -1e-10, 5e-9, -2e-8, 1e-6, -1e-4)]
    cases += [(0.0, 3.0, 0.2), (-0.13, 0.0, 0.4), (0.05, 2 * math.pi / 0.5, 0.5)]  # last: a full circle
    for v, omega, dt in cases:
        pose = np.array([rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(-math.pi, math.pi)])
        got = integrate_unicycle(pose, v, omega, dt)
        ref = _rk4(pose, v, omega, dt)
        assert got.shape == (3,)
        assert np.all(np.isfinite(got))
        # Near the straight-line switch (|ω| ≈ 1e-9) the arc formula v/ω·(sin θ₁ − sin θ) loses
        # digits to cancellation; 0.1 µm is still far below any disturbance bound.
        tol = 1e-10 if abs(omega) >= 1e-6 or omega == 0 else 1e-7
        assert got[:2] == pytest.approx(ref[:2], abs=tol)
        # The heading advances by ω·dt (the straight-line branch for |ω| < 1e-9 may drop
        # at most 1e-9·dt rad).
        tol = 1e-12 if abs(omega) >= 1e-9 else 1e-9 * dt + 1e-12
        assert got[2] == pytest.approx(pose[2] + omega * dt, abs=tol)


def test_integrate_unicycle_is_a_semigroup():
    """Exactness: two consecutive arcs equal one arc of the summed duration."""
    rng = np.random.default_rng(5)
    for _ in range(100):
        pose = np.array([rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(-math.pi, math.pi)])
        v, omega = float(rng.uniform(-0.2, 0.2)), float(rng.uniform(-5, 5))
        t1, t2 = float(rng.uniform(0, 0.3)), float(rng.uniform(0, 0.3))
        two = integrate_unicycle(integrate_unicycle(pose, v, omega, t1), v, omega, t2)
        one = integrate_unicycle(pose, v, omega, t1 + t2)
        assert two == pytest.approx(one, abs=1e-12)


def test_wrap_angle_range_and_equivalence():
    rng = np.random.default_rng(6)
    for a in rng.uniform(-50, 50, 500):
        w = wrap_angle(float(a))
        assert -math.pi <= w < math.pi
        assert math.cos(w) == pytest.approx(math.cos(a), abs=1e-9)
        assert math.sin(w) == pytest.approx(math.sin(a), abs=1e-9)


# --------------------------------------------------------------------------- look-ahead loop from rest


def _bounded_accelerations(
    rng: np.random.Generator, heading: float, n: int, v_cap: float, a_mag: float
) -> list[np.ndarray]:
    """An acceleration sequence that starts sideways, then backwards, then random,
    steered so that each velocity component stays within ``v_cap``."""
    seq: list[np.ndarray] = []
    v = np.zeros(2)
    for k in range(n):
        if k < 5:
            a = a_mag * _unit(heading + math.pi / 2)  # lateral, to the left
        elif k < 10:
            a = a_mag * _unit(heading + math.pi)  # backwards
        elif k < 15:
            a = a_mag * _unit(heading - math.pi / 2)  # lateral, to the right
        else:
            a = rng.uniform(-a_mag, a_mag, 2)
        nxt = v + TS * a
        a = np.where(np.abs(nxt) > v_cap, -np.sign(v) * a_mag, a)
        v = v + TS * a
        seq.append(a)
    return seq


@pytest.mark.parametrize("heading", HEADINGS)
@pytest.mark.parametrize("lookahead", [0.04, 0.02])
def test_lookahead_loop_from_rest_is_the_double_integrator(heading, lookahead):
    """The v = 0 singularity handled: a robot starting at rest follows x⁺ = A x + B a."""
    A, B, _ = double_integrator(TS)
    rng = np.random.default_rng(7)
    start = np.array([0.1, -0.2, heading])
    plant = UnicyclePlant(start, LookaheadInnerLoop(lookahead), GEOM)
    x0 = plant.state()
    # At rest, the controlled point is ℓ ahead of the axle centre.
    assert x0 == pytest.approx(
        [0.1 + lookahead * math.cos(heading), 0.0, -0.2 + lookahead * math.sin(heading), 0.0]
    )
    seq = _bounded_accelerations(rng, heading, 120, v_cap=0.06, a_mag=0.3)
    x_open = x0.copy()
    for k, a in enumerate(seq):
        x = plant.state()
        plant.step(a, TS)
        got = plant.state()
        pred = A @ x + B @ a
        assert np.max(np.abs(got - pred)) <= 1e-4, f"step {k}: one-step error {got - pred}"
        # Velocity is integrated exactly by the extension state.
        assert got[[1, 3]] == pytest.approx(pred[[1, 3]], abs=1e-12)
        x_open = A @ x_open + B @ a
        if k < 15:  # the start from rest (sideways, backwards, sideways), open loop
            assert np.max(np.abs(got - x_open)) <= 3e-4, f"step {k}: open-loop error {got - x_open}"
    assert plant.saturated_substeps == 0


def test_lookahead_loop_first_step_from_rest_moves_sideways():
    """Pure lateral acceleration at rest: the controlled point moves sideways at once (no turning delay)."""
    for heading in HEADINGS:
        plant = UnicyclePlant(np.array([0.0, 0.0, heading]), LookaheadInnerLoop(0.04), GEOM)
        x0 = plant.state()
        a = 0.2 * _unit(heading + math.pi / 2)
        plant.step(a, TS)
        d = plant.state()[[0, 2]] - x0[[0, 2]]
        assert d == pytest.approx(0.5 * TS**2 * a, abs=2e-5)
        assert plant.saturated_substeps == 0


def test_lookahead_loop_rejects_nonpositive_lookahead():
    for ell in (0.0, -0.01):
        with pytest.raises(ValueError):
            LookaheadInnerLoop(ell)


def test_make_inner_loop_selects_by_lookahead():
    la = make_inner_loop(0.04, 0.01)
    assert isinstance(la, LookaheadInnerLoop)
    assert la.lookahead == 0.04
    pa = make_inner_loop(0.0, 0.02)
    assert isinstance(pa, PaperInnerLoop)
    assert pa.v_min == 0.02
    assert pa.lookahead == 0.0
    # The default epuck preset uses the exact look-ahead loop, the paper preset eq. 3.
    e, p = preset("epuck"), preset("paper")
    assert isinstance(make_inner_loop(e.lookahead, e.v_min), LookaheadInnerLoop)
    assert isinstance(make_inner_loop(p.lookahead, p.v_min), PaperInnerLoop)


# --------------------------------------------------------------------------- paper eq. 3 loop


def test_paper_loop_finite_at_rest_for_any_heading_and_acceleration():
    rng = np.random.default_rng(8)
    v_min = 0.01
    for _ in range(500):
        loop = PaperInnerLoop(v_min)
        theta = float(rng.uniform(-4, 4))
        a = rng.uniform(-1, 1, 2) * 10.0 ** rng.uniform(-3, 1)
        vdot, omega = loop.rates(a, theta)
        assert math.isfinite(vdot) and math.isfinite(omega)
        a_perp = -math.sin(theta) * a[0] + math.cos(theta) * a[1]
        assert abs(omega) <= abs(a_perp) / v_min * (1 + 1e-12)
        v, w = loop.command(a, np.array([0.0, 0.0, theta]), TS / 20)
        assert math.isfinite(v) and math.isfinite(w)
    # Purely lateral acceleration at rest: no forward acceleration, a finite turn towards a.
    for theta in HEADINGS:
        for side in (1.0, -1.0):
            loop = PaperInnerLoop(v_min)
            a = 0.3 * _unit(theta + side * math.pi / 2)
            vdot, omega = loop.rates(a, theta)
            assert vdot == pytest.approx(0.0, abs=1e-12)
            assert omega == pytest.approx(side * 0.3 / v_min, rel=1e-9)


def test_paper_loop_rates_match_eq3_above_v_min():
    rng = np.random.default_rng(9)
    v_min = 0.01
    for _ in range(500):
        v = float(rng.choice([-1.0, 1.0]) * rng.uniform(v_min, 0.2))
        loop = PaperInnerLoop(v_min, v=v)
        theta = float(rng.uniform(-math.pi, math.pi))
        a = rng.uniform(-0.5, 0.5, 2)
        vdot, omega = loop.rates(a, theta)
        c, s = math.cos(theta), math.sin(theta)
        assert vdot == pytest.approx(a[0] * c + a[1] * s, rel=1e-12, abs=1e-15)
        assert omega == pytest.approx((-a[0] * s + a[1] * c) / v, rel=1e-12, abs=1e-15)
    # Exactly at ±v_min the regularisation is inactive too.
    for v in (0.01, -0.01):
        loop = PaperInnerLoop(0.01, v=v)
        assert loop.rates(np.array([0.0, 0.1]), 0.0)[1] == pytest.approx(0.1 / v, rel=1e-12)


def test_paper_loop_eq3_makes_point_a_double_integrator_when_moving():
    """Above v_min eq. 3 realises p̈ = a: the world-frame velocity derivative equals a."""
    rng = np.random.default_rng(10)
    for _ in range(200):
        theta = float(rng.uniform(-math.pi, math.pi))
        v = float(rng.choice([-1.0, 1.0]) * rng.uniform(0.02, 0.1))
        loop = PaperInnerLoop(0.01, v=v)
        a = rng.uniform(-0.5, 0.5, 2)
        vdot, omega = loop.rates(a, theta)
        # d/dt (v cos θ, v sin θ) = v̇ (cos θ, sin θ) + v ω (−sin θ, cos θ)
        acc = vdot * _unit(theta) + v * omega * np.array([-math.sin(theta), math.cos(theta)])
        assert acc == pytest.approx(a, abs=1e-12)


@pytest.mark.parametrize("heading", HEADINGS)
@pytest.mark.parametrize("side", [1.0, -1.0])
def test_paper_loop_at_rest_commanded_sideways_turns_then_moves(heading, side):
    plant = UnicyclePlant(np.array([0.0, 0.0, heading]), PaperInnerLoop(0.01), GEOM)
    phi = heading + side * math.pi / 2
    a = 0.02 * _unit(phi)
    p0 = plant.state()[[0, 2]]
    errors = [abs(wrap_angle(heading - phi))]
    states = []
    for _ in range(40):
        plant.step(a, TS)
        errors.append(abs(wrap_angle(plant.pose[2] - phi)))
        states.append(plant.state())
        assert np.all(np.isfinite(plant.pose))
    assert errors[0] == pytest.approx(math.pi / 2)
    # Turns towards the commanded direction: the heading error decreases step by step.
    assert all(e1 < e0 for e0, e1 in itertools.pairwise(errors[:12]))
    assert errors[-1] < math.radians(15)
    # ... and then moves that way: the velocity points within 5° of a, with speed growing.
    vel = states[-1][[1, 3]]
    assert np.linalg.norm(vel) > 0.03
    assert abs(wrap_angle(math.atan2(vel[1], vel[0]) - phi)) < math.radians(5)
    disp = states[-1][[0, 2]] - p0
    assert float(disp @ _unit(phi)) > 0.05
    assert plant.saturated_substeps == 0


@pytest.mark.parametrize("heading", [0.0, 1.3, -2.8])
def test_paper_loop_at_rest_commanded_backwards_reverses(heading):
    plant = UnicyclePlant(np.array([0.0, 0.0, heading]), PaperInnerLoop(0.01), GEOM)
    phi = heading + math.pi
    a = 0.1 * _unit(phi)
    for _ in range(5):
        plant.step(a, TS)
    vel = plant.state()[[1, 3]]
    assert plant.loop.v < 0  # reverses rather than turning around
    assert abs(wrap_angle(math.atan2(vel[1], vel[0]) - phi)) < math.radians(1)
    assert np.linalg.norm(vel) == pytest.approx(0.05, rel=1e-6)
    assert abs(wrap_angle(plant.pose[2] - heading)) < 1e-9


def test_paper_loop_reverses_through_zero_speed_without_blow_up():
    v_min = 0.01
    heading = 0.4
    loop = PaperInnerLoop(v_min)
    plant = UnicyclePlant(np.array([0.0, 0.0, heading]), loop, GEOM, substeps=20)
    plant.perturb(np.array([0.0, 0.04 * math.cos(heading), 0.0, 0.04 * math.sin(heading)]))
    assert loop.v == pytest.approx(0.04)
    a_back = -0.1 * _unit(heading)
    a_lat = 0.005 * _unit(heading + math.pi / 2)
    dt = TS / plant.substeps
    speeds = [loop.v]
    omegas = []
    for _ in range(10):
        pose = plant.pose
        for _ in range(plant.substeps):
            a = a_back + a_lat
            _, omega = loop.rates(a, pose[2])
            omegas.append(omega)
            v_cmd, w_cmd = loop.command(a, pose, dt)
            assert math.isfinite(v_cmd) and math.isfinite(w_cmd)
            pose = integrate_unicycle(pose, v_cmd, w_cmd, dt)
            speeds.append(loop.v)
        plant.pose = pose
    speeds_arr = np.array(speeds)
    assert speeds_arr[0] > 0 > speeds_arr[-1]
    # Continuous: each substep changes v by at most |a|·dt.
    assert np.max(np.abs(np.diff(speeds_arr))) <= 0.101 * dt + 1e-15
    assert speeds_arr[-1] == pytest.approx(0.04 - 0.1 * 1.0, abs=2e-3)
    # No blow-up: the turn rate is bounded by |a| / v_min throughout.
    assert np.all(np.isfinite(omegas))
    assert np.max(np.abs(omegas)) <= float(np.linalg.norm(a_back + a_lat)) / v_min * (1 + 1e-12)


def test_paper_loop_reverses_through_zero_in_the_plant():
    heading = -1.0
    plant = UnicyclePlant(np.array([0.2, 0.1, heading]), PaperInnerLoop(0.01), GEOM)
    plant.perturb(np.array([0.0, 0.05 * math.cos(heading), 0.0, 0.05 * math.sin(heading)]))
    a = -0.1 * _unit(heading) + 0.003 * _unit(heading + math.pi / 2)
    vs = [plant.loop.v]
    for _ in range(12):
        plant.step(a, TS)
        vs.append(plant.loop.v)
        assert np.all(np.isfinite(plant.state()))
    vs_arr = np.array(vs)
    assert vs_arr[0] > 0 > vs_arr[-1]
    assert np.max(np.abs(np.diff(vs_arr))) <= 0.101 * TS
    assert plant.saturated_substeps == 0


# --------------------------------------------------------------------------- perturbation


@pytest.mark.parametrize("heading", HEADINGS)
def test_perturb_shifts_lookahead_state_by_exactly_w(heading):
    rng = np.random.default_rng(11)
    plant = UnicyclePlant(np.array([0.3, -0.1, heading]), LookaheadInnerLoop(0.04), GEOM)
    for _ in range(3):
        plant.step(rng.uniform(-0.2, 0.2, 2), TS)
    for _ in range(20):
        x = plant.state()
        w = rng.uniform(-0.01, 0.01, 4)
        theta = plant.pose[2]
        plant.perturb(w)
        assert plant.state() == pytest.approx(x + w, abs=1e-14)
        assert plant.pose[2] == theta  # a disturbance of the state does not turn the robot


@pytest.mark.parametrize("heading", HEADINGS)
def test_perturb_paper_loop_shifts_position_and_along_track_velocity(heading):
    """With ℓ = 0 the unicycle cannot move sideways: the position shifts by exactly w,
    the velocity by the component of w along the heading."""
    rng = np.random.default_rng(12)
    plant = UnicyclePlant(np.array([0.3, -0.1, heading]), PaperInnerLoop(0.01), GEOM)
    for _ in range(20):
        x = plant.state()
        w = rng.uniform(-0.01, 0.01, 4)
        plant.perturb(w)
        got = plant.state()
        assert got[[0, 2]] == pytest.approx(x[[0, 2]] + w[[0, 2]], abs=1e-14)
        u = _unit(plant.pose[2])
        assert float(got[[1, 3]] @ u) == pytest.approx(float((x[[1, 3]] + w[[1, 3]]) @ u), abs=1e-14)
    # A velocity disturbance along the heading is reproduced exactly.
    x = plant.state()
    w = np.array([0.001, 0.004 * math.cos(plant.pose[2]), -0.002, 0.004 * math.sin(plant.pose[2])])
    plant.perturb(w)
    assert plant.state() == pytest.approx(x + w, abs=1e-14)


def test_double_integrator_plant_is_the_nominal_model():
    A, B, _ = double_integrator(TS)
    rng = np.random.default_rng(13)
    plant = DoubleIntegratorPlant(np.array([0.1, 0.2, math.pi / 2]), A, B, lookahead=0.04)
    assert plant.state() == pytest.approx([0.1, 0.0, 0.24, 0.0], abs=1e-15)
    for _ in range(30):
        x = plant.state()
        a = rng.uniform(-0.3, 0.3, 2)
        w = rng.uniform(-0.001, 0.001, 4)
        plant.step(a, TS)
        plant.perturb(w)
        assert plant.state() == pytest.approx(A @ x + B @ a + w, abs=1e-15)


def test_scalar_lookahead_plant_step_is_bit_identical_to_the_generic_step():
    """The fast path of UnicyclePlant.step (scalar arithmetic) does the generic path's
    operations in the same order: poses, extension states, wheel commands and
    saturation counts agree exactly, saturated substeps included."""
    rng = np.random.default_rng(7)
    geom = WheelGeometry()
    fast = UnicyclePlant(np.array([0.1, -0.2, 2.9]), LookaheadInnerLoop(0.04), geom)
    slow = UnicyclePlant(np.array([0.1, -0.2, 2.9]), LookaheadInnerLoop(0.04), geom)
    for _ in range(600):
        a = rng.uniform(-0.4, 0.4, 2)
        assert fast.step(a, 0.1) == slow._step_generic(a, 0.1)
        assert np.array_equal(fast.pose, slow.pose)
        assert np.array_equal(fast.loop.velocity(fast.pose), slow.loop.velocity(slow.pose))
        w = rng.uniform(-1e-3, 1e-3, 4)
        fast.perturb(w)
        slow.perturb(w)
    assert fast.saturated_substeps == slow.saturated_substeps > 100
