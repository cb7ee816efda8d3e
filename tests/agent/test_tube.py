"""Tube math: invariance of Z, tightening, Ψ, admissibility (docs/method.md §3–§4)."""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np
import pytest

from agent.sets import SetComputationError, Zonotope, mrpi_outer, unit_directions
from agent.tube import InadmissibleDesign, require_admissible, synthesize
from ground.params import preset

ARENA = (-1.0, 1.0, -1.0, 1.0)


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
    with pytest.raises(InadmissibleDesign) as ei:
        require_admissible(d)
    assert "short by" in str(ei.value)


def test_borderline_epsilon_is_rejected_with_the_amount():
    """ε too large for the velocity bound is a configuration error naming the bound and the excess."""
    d = synthesize(preset("epuck").replace(epsilon=0.0065), ARENA)
    assert not d.admissible
    msg = " ".join(d.failures)
    assert "epsilon" in msg and "exceeds" in msg and "by" in msg


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
