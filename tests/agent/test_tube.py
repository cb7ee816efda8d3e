"""Tube math: invariance of Z, tightening, Ψ, admissibility (docs/method.md §3–§4)."""

from __future__ import annotations

import dataclasses
import itertools
import math
import re
from pathlib import Path

import numpy as np
import pytest

from agent.sets import SetComputationError, Zonotope, mrpi_outer, unit_directions
from agent.tube import InadmissibleDesign, require_admissible, synthesize, validated_design
from epuck_link.unicycle import LookaheadInnerLoop, wheel_speeds
from ground.params import PRESETS, preset
from ground.scenario import load_scenario

ARENA = (-1.0, 1.0, -1.0, 1.0)
SCENARIOS = sorted((Path(__file__).resolve().parents[2] / "scenarios").glob("*.toml"))


@pytest.fixture(scope="module")
def design():
    return require_admissible(synthesize(preset("epuck"), ARENA))


def _W(design):
    w = design.params.W
    return Zonotope.box(np.array([w[0], w[1], w[0], w[1]]))


def test_ancillary_gain_is_stabilising_and_separate_from_mpc_weights(design):
    AK = design.A + design.B @ design.K
    assert max(abs(np.linalg.eigvals(AK))) < 1.0
    # The paper preset derives K from the MPC weights; the epuck preset must not.
    paper = synthesize(preset("paper"), ARENA)
    assert not np.allclose(paper.K, design.K)
    assert design.params.Q != design.params.K_Q


@pytest.mark.parametrize("name", ["epuck", "paper"])
def test_Z_is_robust_positively_invariant(name):
    """A_K Z ⊕ W ⊆ Z, by support functions in 256 directions of R⁴ and 720 per axis."""
    d = synthesize(preset(name), ARENA)
    Z = d.Z.Z
    W = _W(d)
    AK = d.A + d.B @ d.K
    dirs = unit_directions(4, 256, seed=1)
    lhs = Z.linear_map(AK).support(dirs) + W.support(dirs)
    assert np.all(lhs <= Z.support(dirs) + 1e-12)
    # Per-axis planes (Z is a product over axes): a dense sweep.
    plane = unit_directions(2, 720)
    for idx in ([0, 1], [2, 3]):
        D = np.zeros((720, 4))
        D[:, idx] = plane
        assert np.all(Z.linear_map(AK).support(D) + W.support(D) <= Z.support(D) + 1e-12)


def test_Z_halfspaces_describe_Z(design):
    """The H-representation used in the QP is exact: vertices on the boundary, support matches."""
    F, f = design.Z_F, design.Z_f
    Z = design.Z.Z
    # Every facet offset equals the support function in that direction.
    assert np.allclose(f, Z.support(F), atol=1e-12)
    # Random points of Z satisfy it; scaled-out points do not.
    rng = np.random.default_rng(0)
    lam = rng.uniform(-1, 1, (500, Z.G.shape[1]))
    pts = lam @ Z.G.T
    assert np.all(np.abs(pts @ F.T) <= f + 1e-12)
    # Vertices maximise random directions: on the boundary, and outside when scaled by 1.01.
    dirs = rng.standard_normal((200, 4))
    vertices = np.sign(dirs @ Z.G) @ Z.G.T
    assert np.all(np.abs(vertices @ F.T) <= f + 1e-12)
    assert np.all(np.any(np.abs((1.01 * vertices) @ F.T) > f, axis=1))


def test_Z_error_bound_is_honest(design):
    """Z = (1−α)⁻¹F_s contains F_s and exceeds it by at most the stated bound."""
    Z = design.Z.Z
    n_terms = design.Z.s
    AK = design.A + design.B @ design.K
    W = _W(design)
    gens = [np.linalg.matrix_power(AK, i) @ W.G for i in range(n_terms)]
    Fs = Zonotope(np.zeros(4), np.hstack(gens))
    hull_Z = Z.interval_hull()
    hull_F = Fs.interval_hull()
    assert np.all(hull_Z >= hull_F - 1e-15)
    assert np.all(hull_Z - hull_F <= design.Z.error_bound + 1e-12)
    assert design.Z.error_bound <= design.params.mrpi_tol


def test_tightened_bounds_equal_bound_minus_support(design):
    p = design.params
    Z = design.Z.Z
    e = np.eye(4)
    for j in (1, 3):
        assert design.x_bound[j] == pytest.approx(p.v_max - Z.support(e[j]), abs=1e-15)
        assert design.x_bound[j] == pytest.approx(p.v_max - Z.support(-e[j]), abs=1e-15)
    for i in range(2):
        assert design.u_hat[i] == pytest.approx(p.a_max - Z.support(design.K[i]), abs=1e-15)
        assert design.KZ[i] == pytest.approx(Z.support(design.K[i]), abs=1e-15)
    assert design.pos_tightening == pytest.approx(Z.support(e[0]), abs=1e-15)


def test_reference_generator_is_exact_schur_and_unit_gain(design):
    A, B, E, K_r = design.A, design.B, design.E, design.K_r
    assert max(abs(np.linalg.eigvals(A - B @ K_r))) < 1.0
    # Unit DC gain: a constant ỹ is an equilibrium x̃ = Eỹ, ũ = 0.
    y = np.array([0.3, -0.2])
    u = -K_r @ (E @ y - E @ y)
    assert np.allclose(A @ (E @ y) + B @ u, E @ y)
    # Lag set Ψ is invariant for e⁺ = (A − BK_r)(e − EΔ), Δ ∈ B_ε.
    AR = A - B @ K_r
    eps = design.params.epsilon
    Dset = Zonotope(np.zeros(4), AR @ E @ np.diag([eps, eps]))
    dirs = unit_directions(4, 256, seed=2)
    Psi = design.Psi.Z
    assert np.all(Psi.linear_map(AR).support(dirs) + Dset.support(dirs) <= Psi.support(dirs) + 1e-9)


def test_stay_put_reference_is_admissible(design):
    """Ψ's velocity part fits strictly in X̂ and K_r(Ψ ⊕ EB_ε) in Û (docs/method.md §4, with margin)."""
    m = design.params.admissibility_margin
    Psi = design.Psi.Z
    assert Psi.support(np.eye(4)[1]) < (1 - m) * design.x_bound[1]
    eps = design.params.epsilon
    ref = Psi.minkowski_sum(Zonotope(np.zeros(4), design.E @ np.diag([eps, eps])))
    assert np.abs(design.K_r @ ref.G).sum(axis=1).max() < (1 - m) * design.u_hat[0]


def test_footprint_covers_body_tube_and_lag(design):
    p = design.params
    # ρ ≥ the ∞-norm bound on each axis, and ≤ the sum of per-axis bounds × √2.
    # The pose noise adds √2·(η_p + ℓη_θ): the true point is that far from the measured one.
    per_axis = design.Z.Z.interval_hull()[0] + design.Psi.Z.interval_hull()[0] + p.delta
    noise = np.sqrt(2) * (p.pose_noise[0] + p.lookahead * p.pose_noise[1])
    assert noise > 0 and design.noise_margin == pytest.approx(noise)
    assert design.rho >= per_axis + p.epsilon + noise - 1e-12
    assert design.rho <= (np.sqrt(2) * per_axis + p.epsilon + noise) * (1 + 1e-6)
    assert design.footprint == pytest.approx(p.robot_radius + p.lookahead + design.rho)


def test_pose_noise_must_leave_room_in_W():
    """n⁺ − n moves the measured point by up to 2η per step; W must cover it, with margin."""
    p = preset("epuck")
    ok = synthesize(p.replace(pose_noise=(0.9 * 0.45 * p.W[0], 0.0)), ARENA)
    assert ok.admissible, ok.failures
    bad = synthesize(p.replace(pose_noise=(0.5 * p.W[0], 0.0)), ARENA)
    assert any("pose_noise" in f for f in bad.failures)
    # The heading error counts through the look-ahead: ℓ·η_θ alone can exhaust W.
    tilt = synthesize(p.replace(pose_noise=(0.0, 0.6 * p.W[0] / p.lookahead)), ARENA)
    assert any("pose_noise" in f for f in tilt.failures)


def test_paper_preset_is_honestly_inadmissible():
    d = synthesize(preset("paper"), ARENA)
    # docs/method.md §3: the paper's K gives a ≈ 0.35 m position half-width.
    assert 0.30 < d.Z.Z.interval_hull()[0] < 0.40
    assert not d.admissible
    assert any("velocity" in f and "m/s" in f for f in d.failures)
    # Its Z empties X̂ on both axes, each named; ℓ = 0 is one line that also says why the wheel
    # bound cannot hold, with no number (it is infinite) and no second wheel line.
    for axis in ("x", "y"):
        assert any(f.startswith(f"X̂ {axis} velocity bound is empty") and "= -" in f for f in d.failures)
    ell = [f for f in d.failures if "lookahead" in f or "wheel" in f]
    assert len(ell) == 1 and "lookahead 0 m" in ell[0] and "is infinite" in ell[0], ell
    assert d.wheel_speed == math.inf
    assert not any("nan" in f or "inf " in f for f in d.failures), d.failures
    with pytest.raises(InadmissibleDesign) as ei:
        require_admissible(d)
    assert "short by" in str(ei.value)


def test_borderline_epsilon_is_rejected_with_the_amount():
    """ε too large for the velocity bound is a configuration error naming the bound and the excess."""
    d = synthesize(preset("epuck").replace(epsilon=0.0065), ARENA)
    assert not d.admissible
    msg = " ".join(d.failures)
    assert "epsilon" in msg and "exceeds" in msg and "by" in msg


def _failing(d, *words):
    """The failures of ``d`` that contain every word."""
    return [f for f in d.failures if all(w in f for w in words)]


def test_stay_put_is_checked_on_the_y_axis_too():
    """ref_Q heavier on py than on px (a scenario may set it): the y lag speed h_Ψ(e_3) = 5.92 cm/s
    exceeds 0.95 × 6.19 cm/s while the x axis passes; the design is refused naming y, with the
    amount."""
    p = preset("epuck").replace(ref_Q=(100.0, 10.0, 500.0, 2.0))
    d = synthesize(p, ARENA)
    assert not d.admissible
    hPsi = d.Psi.Z.support(np.eye(4))
    m = p.admissibility_margin
    assert hPsi[1] < (1 - m) * d.x_bound[1] < (1 - m) * d.x_bound[3] < hPsi[3]  # only y fails
    (f,) = d.failures
    assert "y reference lag velocity" in f and "X̂ y velocity bound" in f, f
    excess = float(re.search(r"by ([0-9.e-]+) m/s$", f).group(1))
    assert excess == pytest.approx(hPsi[3] - (1 - m) * d.x_bound[3], rel=1e-3)


def test_reference_input_is_checked_on_the_ay_row_against_its_own_bound():
    """A heavier K_Q on py shrinks Û's ay bound (KZ grows on that row only) and a heavier ref_Q
    on py raises the ay reference input: each alone passes; together only the ay row fails, and
    it would pass against the ax row's bound."""
    p = preset("epuck")
    tight_K = p.replace(K_Q=(400.0, 10.0, 1e5, 10.0))
    fast_ref = p.replace(ref_Q=(100.0, 10.0, 1000.0, 40.0))
    assert synthesize(tight_K, ARENA).admissible and synthesize(fast_ref, ARENA).admissible
    d = synthesize(p.replace(K_Q=tight_K.K_Q, ref_Q=fast_ref.ref_Q), ARENA)
    eps = p.epsilon
    ref = d.Psi.Z.minkowski_sum(Zonotope(np.zeros(4), d.E @ np.diag([eps, eps])))
    h = np.abs(d.K_r @ ref.G).sum(axis=1)
    m = p.admissibility_margin
    assert h[0] < (1 - m) * d.u_hat[0] and (1 - m) * d.u_hat[1] < h[1] < (1 - m) * d.u_hat[0]
    (f,) = d.failures
    assert "reference input ay" in f and "Û ay bound" in f, f
    assert f"{d.u_hat[1]:.4g} m/s²" in f


def test_an_empty_U_hat_on_the_ay_row_is_named():
    """K_Q so heavy on py that h_KZ(e_ay) > a_max: Û is empty on ay only, and named."""
    d = synthesize(preset("epuck").replace(K_Q=(400.0, 10.0, 1e6, 10.0)), ARENA)
    assert d.u_hat[0] > 0 > d.u_hat[1]
    assert len(_failing(d, "Û ay bound is empty", "= -")) == 1, d.failures
    assert not _failing(d, "Û ax") and not _failing(d, "input ax") and not _failing(d, "x velocity"), (
        d.failures
    )


def test_a_look_ahead_of_2_cm_is_refused_by_the_wheel_bound():
    """ℓ = 2 cm asks √2·0.075·√(1 + (0.053/0.04)²) = 0.176 m/s of wheels that give 0.129 m/s."""
    d = synthesize(preset("epuck").replace(lookahead=0.02), ARENA)
    (f,) = d.failures
    assert d.wheel_speed == pytest.approx(0.17607, abs=1e-5)
    assert "wheel speed bound" in f and "0.1761 m/s" in f and "wheels' limit 0.1288 m/s" in f, f
    assert "by 0.04727 m/s" in f and "smallest lookahead for this v_max is 0.03847 m" in f, f


def _hint(f, what):
    return float(re.search(rf"{what} ([0-9.]+) m", f).group(1))


def _smallest_lookahead(p):
    """ℓ with √2·v_max·√(1 + (L/2ℓ)²) equal to the wheels' limit, for ``p``'s v_max [m]."""
    ratio = p.wheel.max_wheel_speed / (math.sqrt(2) * p.v_max)
    return p.wheel.axle / (2 * math.sqrt(ratio**2 - 1))


def test_the_wheel_bound_holds_at_its_boundary():
    """The smallest legal ℓ for v_max = 0.075 m/s is 3.846 cm: the hint the failure gives (rounded
    up) passes and 0.01 mm less fails, and so does the closed form, to 1e-9; likewise the largest
    v_max for ℓ = 2 cm.  No margin (the shipped compact design passes by 0.38 %): a wheel speed
    equal to the limit passes."""
    p = preset("epuck")
    d0 = synthesize(p, ARENA)
    exact = _smallest_lookahead(p)
    assert exact == pytest.approx(0.03846, abs=1e-5)
    for ell, ok in ((exact * (1 + 1e-9), True), (exact * (1 - 1e-9), False)):
        assert synthesize(p.replace(lookahead=ell), ARENA).admissible is ok, ell
    f = synthesize(p.replace(lookahead=0.02), ARENA).failures[0]
    ell = _hint(f, "smallest lookahead for this v_max is")
    v = _hint(f, "the largest v_max for this lookahead")
    assert synthesize(p.replace(lookahead=ell), ARENA).admissible
    assert not synthesize(p.replace(lookahead=ell - 1e-5), ARENA).admissible
    # (A v_max this low fails the stay-put check for this ε, a separate bound.)
    assert not _failing(synthesize(p.replace(lookahead=0.02, v_max=v), ARENA), "wheel")
    assert _failing(synthesize(p.replace(lookahead=0.02, v_max=v + 1e-5), ARENA), "wheel speed bound")
    # At the limit exactly the wheels do not saturate (wheel_speeds scales only above it): passes.
    at_limit = dataclasses.replace(p.wheel, max_steps=d0.wheel_speed / p.wheel.metres_per_step)
    assert at_limit.max_wheel_speed == d0.wheel_speed  # exact in floating point for these figures
    assert synthesize(p.replace(wheel=at_limit), ARENA).admissible
    # A v_max no look-ahead can serve: the failure says so instead of a negative root.
    fast = synthesize(p.replace(lookahead=0.02, v_max=0.1), ARENA)
    assert _failing(fast, "wheel speed bound", "no lookahead is enough"), fast.failures


@pytest.mark.parametrize("boundary", [False, True], ids=["epuck", "smallest_lookahead"])
def test_the_wheel_bound_is_the_inner_loops_largest_wheel_speed(boundary):
    """Over X's velocity box and every heading, the look-ahead loop's wheels reach the bound and
    never pass it (epuck_link's own mapping q → (v, ω) → wheels); at the smallest ℓ they reach
    the limit without saturating."""
    p = preset("epuck")
    ell = _smallest_lookahead(p) * (1 + 1e-9) if boundary else p.lookahead
    p = p.replace(lookahead=ell)
    d = synthesize(p, ARENA)
    loop = LookaheadInnerLoop(ell)
    geom = p.wheel
    peak = 0.0
    for q in itertools.product((-p.v_max, 0.0, p.v_max), repeat=2):
        for theta in np.linspace(-math.pi, math.pi, 3601):
            pose = np.array([0.0, 0.0, theta])
            loop.reset(pose, np.array(q))
            v, omega = loop.command(np.zeros(2), pose, 0.01)
            left, right, saturated = wheel_speeds(v, omega, geom)
            assert not saturated
            peak = max(peak, abs(left), abs(right))
    peak *= geom.metres_per_step
    assert peak <= d.wheel_speed * (1 + 1e-12)
    assert peak >= d.wheel_speed * (1 - 1e-5)


def test_the_epuck_preset_passes_the_wheel_bound_by_1_2_percent():
    """The `epuck` preset asks 0.12723 m/s of 0.12881 m/s (the `paper` preset, ℓ = 0, is refused:
    test_paper_preset_is_honestly_inadmissible)."""
    assert PRESETS == ("epuck", "paper")
    d = synthesize(preset("epuck"), ARENA)
    assert d.admissible, d.failures
    assert 1 - d.wheel_speed / d.params.wheel.max_wheel_speed == pytest.approx(0.01222, abs=1e-5)


@pytest.mark.parametrize("path", SCENARIOS, ids=[p.stem for p in SCENARIOS])
def test_every_shipped_scenario_is_admissible(path):
    design = validated_design(load_scenario(path))
    assert design.admissible
    assert design.wheel_speed <= design.params.wheel.max_wheel_speed


def test_mrpi_raises_when_it_cannot_converge():
    A = np.array([[0.999, 0.0], [0.0, 0.999]])
    W = Zonotope.box(np.array([0.01, 0.01]))
    with pytest.raises(SetComputationError, match="did not reach"):
        mrpi_outer(A, W, tol=1e-6, max_terms=50)
    with pytest.raises(SetComputationError, match="not Schur"):
        mrpi_outer(np.array([[1.0, 0.1], [0.0, 1.0]]), W, tol=1e-3, max_terms=50)


def test_design_raises_on_unconvergeable_parameters():
    with pytest.raises(SetComputationError):
        synthesize(preset("epuck").replace(mrpi_max_terms=3), ARENA)


def test_a_design_without_a_look_ahead_point_is_refused():
    """ℓ = 0 runs the paper's eq. 3, whose one-step error at rest W does not bound: the design
    says so instead of claiming the tube."""
    d = synthesize(dataclasses.replace(preset("epuck"), lookahead=0.0), ARENA)
    assert not d.admissible
    assert any("lookahead 0" in f and "not bounded by W" in f for f in d.failures), d.failures
    assert synthesize(preset("epuck"), ARENA).admissible


@pytest.mark.parametrize("name", ["epuck", "paper"])
def test_Z_minus_W_for_plans_made_ahead_holds_A_K_Z_and_leaves_room_for_W(name):
    """Constraint (a′) of plans made a step ahead (docs/method.md §5): the shrunk facets are
    exactly Z ⊖ W's, they hold A_K Z (so the shifted candidate meets them), and every point they
    admit stays in Z whatever W adds."""
    d = synthesize(preset(name), ARENA)
    f = d.Z_f_ahead
    assert np.all(f > 0) and np.all(f < d.Z_f)
    # Exactly Z ⊖ W, not a tighter set: each facet moves in by W's support in its direction.
    assert np.allclose(d.Z_f - f, Zonotope.box(d.W_box).support(d.Z_F), rtol=0, atol=1e-15)
    AK = d.A + d.B @ d.K
    # To well within the solver's tolerance: W's zero half-widths are padded by 1e-6 of the largest.
    assert np.all(d.Z.Z.linear_map(AK).support(d.Z_F) <= f + 1e-7)
    rng = np.random.default_rng(3)
    verts = np.array(list(itertools.product((-1.0, 1.0), repeat=4))) * d.W_box
    # Points admitted by the shrunk facets: Z's points (from its generators) scaled in until they are.
    Z = d.Z.Z
    pts = Z.c + rng.uniform(-1.0, 1.0, (400, Z.G.shape[1])) @ Z.G.T
    inside = pts / np.maximum(np.max(np.abs(pts @ d.Z_F.T) / f, axis=1, keepdims=True), 1.0)
    assert all(d.contains_error(z + w, tol=1e-12) for z in inside for w in verts)
    # And the check the controller makes of a prediction uses them: a point on their boundary.
    edge = pts[0] / np.max(np.abs(d.Z_F @ pts[0]) / f)
    assert d.contains_error(edge, tol=1e-12, ahead=True) and not d.contains_error(1.01 * edge, ahead=True)
