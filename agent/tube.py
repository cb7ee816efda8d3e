"""Offline tube synthesis (Mayne et al. 2005; paper §III.A; docs/method.md §2–§4).

Nominal model per robot (:mod:`ground.model`), sampled at Ts with zero-order hold::

    x = [px, vx, py, vy]   [m, m/s, m, m/s], world frame
    u = [ax, ay]           [m/s²]
    x⁺ = A x + B u + w,    w ∈ W (a box)

Synthesised objects:

* K, the ancillary gain: ``u = v̂ + K(x − x̂)``, ``A_K = A + BK`` Schur.  It
  comes from its own LQR weights (K_Q, K_R), separate from the MPC weights.
* Z, an RPI outer approximation of the mRPI set of ``z⁺ = A_K z + w``.
* X̂ = X ⊖ Z and Û = U ⊖ KZ (boxes: bound − support).
* K_r, the reference generator ``ũ_k = −K_r(x̃_k − E ỹ_{k+1})``, and Ψ, the
  mRPI set of the lag ``e = x̃ − Eỹ``: ``e⁺ = (A − BK_r)(e − EΔ)``, Δ ∈ B_ε.
* ρ = max ‖C(Z ⊕ Ψ) ⊕ Δ^z‖₂ + ε + √2·η (η the pose noise on the controlled
  point, per axis) and the footprint r = robot_radius + ℓ + ρ.
* The wheel speed bound √2·v_max·√(1 + (L/2ℓ)²) of the look-ahead inner loop
  inside X, checked against the wheels' limit (:func:`wheel_speed_bound`).

Every admissibility failure is reported with the bound that fails and by
how much (:class:`InadmissibleDesign`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
import scipy.linalg

from agent.sets import Array, MRPIApprox, SetComputationError, Zonotope, mrpi_outer
from ground.model import double_integrator, position_to_rest_state
from ground.params import ControllerParams
from ground.scenario import ConfigError, Scenario, check_geometry


class InadmissibleDesign(ValueError):
    """The tube design is empty or inadmissible; ``failures`` lists why."""

    def __init__(self, failures: list[str]):
        self.failures = failures
        super().__init__("; ".join(failures))


def dlqr_gain(A: Array, B: Array, Q: Array, R: Array) -> Array:
    """Infinite-horizon discrete LQR gain L with u = −L x (so A − BL is Schur)."""
    P = scipy.linalg.solve_discrete_are(A, B, Q, R)
    return np.linalg.solve(R + B.T @ P @ B, B.T @ P @ A)


def _gain(A: Array, B: Array, Q: tuple[float, ...], R: tuple[float, ...], names: str) -> Array:
    """LQR gain, or a SetComputationError naming the weights if the Riccati equation has no solution."""
    try:
        L = dlqr_gain(A, B, np.diag(Q), np.diag(R))
    except (ValueError, np.linalg.LinAlgError) as e:
        raise SetComputationError(f"{names}: no stabilising LQR gain for these weights ({e})") from None
    if not np.all(np.isfinite(L)) or max(abs(np.linalg.eigvals(A - B @ L))) >= 1.0:
        raise SetComputationError(f"{names}: the LQR gain for these weights does not stabilise the model")
    return L


def _block_halfspaces(Zn: Zonotope, blocks: list[list[int]]) -> tuple[Array, Array]:
    """Exact H-rep of a zonotope that is a product over coordinate blocks.

    Falls back to the generic facet enumeration when a generator mixes blocks."""
    n = Zn.dim
    owner = []
    for g in Zn.G.T:
        nz = np.flatnonzero(np.abs(g) > 1e-15)
        hit = [b for b, idx in enumerate(blocks) if set(nz) <= set(idx)]
        if not hit:
            return Zn.halfspaces()
        owner.append(hit[0])
    rows, offs = [], []
    for b, idx in enumerate(blocks):
        cols = [k for k, o in enumerate(owner) if o == b]
        sub = Zonotope(Zn.c[idx], Zn.G[np.ix_(idx, cols)])
        Fb, fb = sub.halfspaces()
        Fn = np.zeros((Fb.shape[0], n))
        Fn[:, idx] = Fb
        rows.append(Fn)
        offs.append(fb)
    return np.vstack(rows), np.concatenate(offs)


def max_norm_2d(h_of: object, count: int = 7200) -> float:
    """max ‖p‖₂ over a convex planar set given by its support function.

    Sampled on ``count`` directions and inflated by the sampling error bound
    1/cos(π/count), so the result is an upper bound."""
    ang = np.linspace(0.0, 2.0 * np.pi, count, endpoint=False)
    d = np.column_stack([np.cos(ang), np.sin(ang)])
    return float(np.max(h_of(d))) / float(np.cos(np.pi / count))  # type: ignore[operator]


def wheel_speed_bound(p: ControllerParams) -> float:
    """Largest wheel rim speed [m/s] the look-ahead inner loop asks while |vx|, |vy| ≤ v_max.

    The loop commands v = cos θ·q_x + sin θ·q_y and ℓω = −sin θ·q_x + cos θ·q_y
    (docs/method.md §1.2), so a wheel turns at v ± ωL/2, which over all headings is at most
    ‖q‖·√(1 + (L/2ℓ)²), reached at some heading; with ‖q‖ ≤ √2·v_max at a corner of X's
    velocity box the bound is √2·v_max·√(1 + (L/2ℓ)²), L = ``p.wheel.axle``.  Infinite for
    ℓ ≤ 0: the axle centre cannot move sideways."""
    if p.lookahead <= 0:
        return math.inf
    return math.sqrt(2.0) * p.v_max * math.hypot(1.0, p.wheel.axle / (2.0 * p.lookahead))


def _wheel_failure(p: ControllerParams, asked: float) -> str:
    """One line for a design whose wheel speed bound ``asked`` [m/s] exceeds the wheels' limit:
    the amount, the smallest ℓ for this v_max (if any) and the largest v_max for this ℓ, each
    rounded towards passing at four significant digits."""
    limit = p.wheel.max_wheel_speed
    L = p.wheel.axle
    v_top = _round_sig(limit / (math.sqrt(2.0) * math.hypot(1.0, L / (2.0 * p.lookahead))), up=False)
    ratio = limit / (math.sqrt(2.0) * p.v_max)  # √(1 + (L/2ℓ)²) may be at most this
    if ratio > 1.0:
        ell_min = _round_sig(L / (2.0 * math.sqrt(ratio**2 - 1.0)))
        fix = f"the smallest lookahead for this v_max is {ell_min:.4g} m"
    else:
        fix = f"no lookahead is enough for this v_max (√2·v_max ≥ {limit:.4g} m/s)"
    return (
        f"wheel speed bound √2·v_max·√(1 + (L/2ℓ)²) = {asked:.4g} m/s (v_max {p.v_max:.4g} m/s, "
        f"lookahead ℓ {p.lookahead:.4g} m, axle L {L:.4g} m) exceeds the wheels' limit {limit:.4g} m/s "
        f"by {asked - limit:.4g} m/s, so the wheels saturate inside X: {fix}, "
        f"the largest v_max for this lookahead {v_top:.4g} m/s"
    )


def _round_sig(x: float, up: bool = True) -> float:
    """``x`` > 0 rounded up (or down) to four significant digits."""
    step = 10.0 ** (math.floor(math.log10(x)) - 3)
    return (math.ceil(x / step) if up else math.floor(x / step)) * step


@dataclass
class TubeDesign:
    """A synthesised, admissibility-checked tube design.  See module docstring."""

    params: ControllerParams
    A: Array
    B: Array
    C: Array
    E: Array
    K: Array
    """Ancillary gain (2, 4), u = v̂ + K(x − x̂)."""
    K_r: Array
    """Reference-generator gain (2, 4), ũ = −K_r(x̃ − Eỹ⁺)."""
    Z: MRPIApprox
    Psi: MRPIApprox
    Z_F: Array
    """H-rep of Z: {z : |Z_F z| ≤ Z_f}, Z_F (p, 4)."""
    Z_f: Array
    x_bound: Array
    """X̂ half-widths per state (4,) [m/s for velocities]; positions are inf
    here because X̂'s position part is the arena shrunk by ``pos_tightening``."""
    u_hat: Array
    """Box Û half-widths (2,) [m/s²]."""
    pos_tightening: float
    """h_Z along a position axis [m]: X̂ positions = arena ⊖ (robot radius + ℓ) ⊖ this."""
    KZ: Array
    """h_{KZ} per input axis (2,) [m/s²]."""
    rho: float
    """Bound on ‖p − ỹ_k‖₂ between the true controlled point and its reference [m]:
    the measured point's bound plus √2·``point_noise`` (the camera's error)."""
    footprint: float
    """Footprint radius r_i = robot_radius + ℓ + ρ [m]."""
    noise_margin: float = 0.0
    """√2·``point_noise``: the part of ρ that covers the pose measurement error [m]."""
    wheel_speed: float = 0.0
    """:func:`wheel_speed_bound`: the largest wheel speed the inner loop asks inside X [m/s]
    (infinite for ℓ = 0); admissible only up to ``params.wheel.max_wheel_speed``."""
    failures: list[str] = field(default_factory=list)

    @property
    def admissible(self) -> bool:
        """True if the design passed every check (:attr:`failures` is empty)."""
        return not self.failures

    @property
    def body_radius(self) -> float:
        """Radius around the controlled point that covers the body [m]."""
        return self.params.robot_radius + self.params.lookahead

    def contains_error(self, z: Array, tol: float = 1e-9, ahead: bool = False) -> bool:
        """True if the error z = x − x̂ (4,) lies in Z (``ahead``: in Z ⊖ W, :attr:`Z_f_ahead`)."""
        return bool(np.all(np.abs(self.Z_F @ z) <= (self.Z_f_ahead if ahead else self.Z_f) + tol))

    @property
    def W_box(self) -> Array:
        """W's half-widths (4,) [m, m/s, m, m/s] in the state order (px, vx, py, vy), zero
        ones padded as Z was synthesised with them."""
        return w_box(self.params)

    @cached_property
    def Z_f_ahead(self) -> Array:
        """Facet offsets (p,) of Z ⊖ W for plans made a step ahead from a prediction (delay
        compensation, docs/method.md §5; constraint (a′) |Z_F(x^p − x̂)| ≤ Z_f_ahead): Z's
        facets shrunk by W's support function, Z_f − h_W(Z_Fᵀ), which is Z ⊖ W exactly.
        Raises :class:`InadmissibleDesign` if a facet closes (Z is then not invariant)."""
        f = np.asarray(self.Z_f - np.abs(self.Z_F) @ self.W_box)
        if np.any(f <= 0):
            raise InadmissibleDesign([f"Z ⊖ W is empty: facet offset {float(f.min()):.3g} ≤ 0"])
        return f

    def summary(self) -> dict[str, object]:
        """Machine-readable view (used by ``fleet design --json``)."""
        zp = self.Z.Z.interval_hull()
        pp = self.Psi.Z.interval_hull()
        return {
            "preset": self.params.preset,
            "Ts_s": self.params.Ts,
            "horizon": self.params.horizon,
            "K": self.K.round(6).tolist(),
            "K_r": self.K_r.round(6).tolist(),
            "spectral_radius_A_K": float(max(abs(np.linalg.eigvals(self.A + self.B @ self.K)))),
            "Z_half_widths": {"position_m": float(zp[0]), "velocity_m_s": float(zp[1])},
            "Z_terms": self.Z.s,
            "Z_alpha": self.Z.alpha,
            "Z_error_bound": self.Z.error_bound,
            "Z_facets": int(self.Z_F.shape[0]),
            "Psi_half_widths": {"position_m": float(pp[0]), "velocity_m_s": float(pp[1])},
            "Psi_terms": self.Psi.s,
            "Psi_error_bound": self.Psi.error_bound,
            "KZ_m_s2": self.KZ.tolist(),
            "tightened": {
                "velocity_m_s": float(self.x_bound[1]),
                "acceleration_m_s2": float(self.u_hat[0]),
                "position_margin_m": self.body_radius + self.pos_tightening,
            },
            "epsilon_m": self.params.epsilon,
            "delta_m": self.params.delta,
            "pose_noise": {"position_m": self.params.pose_noise[0], "heading_rad": self.params.pose_noise[1]},
            "noise_margin_m": self.noise_margin,
            "rho_m": self.rho,
            "footprint_radius_m": self.footprint,
            "wheel_speed_m_s": self.wheel_speed,
            "wheel_limit_m_s": self.params.wheel.max_wheel_speed,
            "admissible": self.admissible,
            "failures": list(self.failures),
        }


def synthesize(
    params: ControllerParams, arena: tuple[float, float, float, float] | None = None
) -> TubeDesign:
    """Build the tube design for ``params``; check it against ``arena``.

    ``arena`` = (xmin, xmax, ymin, ymax) [m]; without it the arena checks are
    skipped.  Raises :class:`agent.sets.SetComputationError` if an mRPI
    approximation does not converge.  Admissibility failures are collected in
    ``TubeDesign.failures`` (call :func:`require_admissible` to raise).

    X̂ and Û must be non-empty and "stay put" admissible (docs/method.md §4) on both velocity
    axes (x, y) and both input rows (ax, ay), each failure naming its axis or input: h_Ψ(e_v) ≤
    (1 − m)·X̂'s bound on that velocity axis and h_{K_r(Ψ⊕EB_ε)}(e_j) ≤ (1 − m)·Û's bound on
    that input row, m = ``admissibility_margin``.

    The wheels (docs/method.md §1.2): :func:`wheel_speed_bound` must not exceed
    ``params.wheel.max_wheel_speed``, with no margin: a wheel may run at its limit
    (``epuck_link/unicycle.py`` ``wheel_speeds`` scales only above it).  The margin m is for
    the QP, where borderline designs made solves fail; the wheel bound enters no QP and is
    exact, the worst case over X's velocity box and every heading.  The compact controller of
    scenarios/swap_16, swap_32 and swap_48.toml passes it by 0.38 %, which a 5 % margin would
    refuse."""
    p = params
    A, B, C = double_integrator(p.Ts)
    E = position_to_rest_state()
    K = -_gain(A, B, p.K_Q, p.K_R, "K_Q/K_R")
    K_r = _gain(A, B, p.ref_Q, p.ref_R, "ref_Q/ref_R")
    AK = A + B @ K
    AR = A - B @ K_r

    Zr = mrpi_outer(AK, Zonotope.box(w_box(p)), p.mrpi_tol, p.mrpi_max_terms)
    blocks = [[0, 1], [2, 3]]
    Z_F, Z_f = _block_halfspaces(Zr.Z, blocks)

    # Ψ: disturbance −(A − BK_r) E Δ with Δ ∈ B_ε (box), i.e. generators
    # (A − BK_r) E diag(ε); the sign is irrelevant for a symmetric set.
    eps = p.epsilon
    Weps = Zonotope(np.zeros(4), AR @ E @ np.diag([eps, eps]))
    Weps_full = Zonotope(np.zeros(4), np.hstack([Weps.G, 1e-9 * np.eye(4)]))
    Pr = mrpi_outer(AR, Weps_full, p.mrpi_tol * 0.1, p.mrpi_max_terms)

    eye = np.eye(4)
    hZ = Zr.Z.support(eye)  # (4,)
    KZ = Zr.Z.support(K)  # h_{KZ}(e_j) = h_Z(K_j) per input row
    x_bound = np.array([np.inf, p.v_max - hZ[1], np.inf, p.v_max - hZ[3]])
    u_hat = np.array([p.a_max - KZ[0], p.a_max - KZ[1]])

    # ρ: real controlled point minus committed reference ∈ C Z ⊕ C Ψ ⊕ Δ^z, plus ε.
    CZ = Zr.Z.linear_map(C)
    CPsi = Pr.Z.linear_map(C)
    dz = Zonotope.box(np.array([p.delta, p.delta]))
    sum_set = CZ.minkowski_sum(CPsi).minkowski_sum(dz)
    noise_margin = math.sqrt(2.0) * p.point_noise
    rho = max_norm_2d(sum_set.support) + eps + noise_margin
    footprint = p.robot_radius + p.lookahead + rho

    failures: list[str] = []
    margin = p.admissibility_margin
    # One velocity axis and one input row per coordinate; the weights may differ between them
    # (ref_Q, K_Q), so every check below runs on both.
    axes = (("x", 1), ("y", 3))  # (axis, velocity index in x = [px, vx, py, vy])
    inputs = ("ax", "ay")  # rows of u = [ax, ay]
    for axis, j in axes:
        if x_bound[j] <= 0:
            failures.append(
                f"X̂ {axis} velocity bound is empty: v_max {p.v_max:.4g} m/s − h_Z {hZ[j]:.4g} m/s "
                f"= {x_bound[j]:.4g} m/s"
            )
    for j, name in enumerate(inputs):
        if u_hat[j] <= 0:
            failures.append(
                f"Û {name} bound is empty: a_max {p.a_max:.4g} m/s² − h_KZ {KZ[j]:.4g} m/s² "
                f"= {u_hat[j]:.4g} m/s²"
            )
    # Stay-put admissibility (docs/method.md §4): Ψ's velocity part in X̂ and the
    # reference input K_r(Ψ ⊕ E B_ε) in Û, per axis and per input row, both strictly, with a margin.
    hPsi = Pr.Z.support(eye)  # (4,)
    ref_u = Pr.Z.minkowski_sum(Zonotope(np.zeros(4), E @ np.diag([eps, eps])))
    hKrPsi = np.abs(K_r @ ref_u.G).sum(axis=1)  # h_{K_r(Ψ⊕EB_ε)}(e_j) per input row (2,)
    for axis, j in axes:
        allowed = (1.0 - margin) * x_bound[j]
        if x_bound[j] > 0 and hPsi[j] > allowed:
            failures.append(
                f"epsilon {eps:.4g} m too large: {axis} reference lag velocity h_Ψ {hPsi[j]:.4g} m/s "
                f"exceeds {1 - margin:.2f}·X̂ {axis} velocity bound {x_bound[j]:.4g} m/s "
                f"by {hPsi[j] - allowed:.4g} m/s"
            )
    for j, name in enumerate(inputs):
        allowed = (1.0 - margin) * u_hat[j]
        if u_hat[j] > 0 and hKrPsi[j] > allowed:
            failures.append(
                f"epsilon {eps:.4g} m too large: reference input {name} h_{{K_r(Ψ⊕EB_ε)}} "
                f"{hKrPsi[j]:.4g} m/s² exceeds {1 - margin:.2f}·Û {name} bound {u_hat[j]:.4g} m/s² "
                f"by {hKrPsi[j] - allowed:.4g} m/s²"
            )
    # Pose noise: the measured state's one-step error includes n⁺ − n, up to
    # 2·point_noise per position axis, which W must cover with room to spare.
    if 2.0 * p.point_noise > (1.0 - margin) * p.W[0]:
        failures.append(
            f"pose_noise too large: it moves the measured point by up to 2·{p.point_noise:.4g} m per "
            f"step, more than {1 - margin:.2f}·W position bound {p.W[0]:.4g} m"
        )
    wheel = wheel_speed_bound(p)
    if p.lookahead <= 0:
        # docs/method.md §1: ℓ = 0 runs the paper's eq. 3, regularised at v_min; from rest its
        # one-step error is far outside any usable W, so the tube would promise what it cannot.
        # The wheel bound below is infinite then (a sideways velocity of p needs an infinite ω):
        # this one line says both.
        failures.append(
            f"lookahead {p.lookahead:g} m: the inner loop is then the paper's eq. 3, singular at rest, "
            "whose one-step error is not bounded by W, and the wheel speed bound "
            "√2·v_max·√(1 + (L/2ℓ)²) is infinite; use a look-ahead point (e.g. lookahead = 0.04)"
        )
    elif wheel > p.wheel.max_wheel_speed:
        failures.append(_wheel_failure(p, wheel))
    if p.delta <= 0:
        failures.append(f"delta {p.delta} m must be > 0")
    if eps <= 0:
        failures.append(f"epsilon {eps} m must be > 0")
    if arena is not None:
        xmin, xmax, ymin, ymax = arena
        for name, lo, hi in (("x", xmin, xmax), ("y", ymin, ymax)):
            free = (hi - lo) - 2.0 * footprint
            if free <= 0:
                failures.append(
                    f"footprint radius {footprint:.3f} m does not fit the arena's {name} extent "
                    f"{hi - lo:.3f} m: short by {-free:.3f} m"
                )
            # Rough capacity: a robot must be able to pass another one.
            elif free < 2.0 * footprint:
                failures.append(
                    f"footprint radius {footprint:.3f} m leaves {free:.3f} m of free {name} extent, "
                    f"less than one footprint diameter {2 * footprint:.3f} m: two robots cannot pass "
                    f"(short by {2 * footprint - free:.3f} m)"
                )
    return TubeDesign(
        params=p,
        A=A,
        B=B,
        C=C,
        E=E,
        K=K,
        K_r=K_r,
        Z=Zr,
        Psi=Pr,
        Z_F=Z_F,
        Z_f=Z_f,
        x_bound=x_bound,
        u_hat=u_hat,
        pos_tightening=float(hZ[0]),
        KZ=KZ,
        rho=rho,
        footprint=footprint,
        noise_margin=noise_margin,
        wheel_speed=wheel,
        failures=failures,
    )


def w_box(p: ControllerParams) -> Array:
    """W as a box: half-widths (4,) [m, m/s, m, m/s] per state (px, vx, py, vy).  Zero
    half-widths are padded so W is full-dimensional (an outer approximation, hence still
    sound)."""
    w = np.array([p.W[0], p.W[1], p.W[0], p.W[1]], dtype=float)
    return np.maximum(w, 1e-6 * max(float(w.max()), 1e-12))


def require_admissible(design: TubeDesign) -> TubeDesign:
    """Raise :class:`InadmissibleDesign` if the design has failures."""
    if design.failures:
        raise InadmissibleDesign(design.failures)
    return design


def validated_design(scn: Scenario) -> TubeDesign:
    """The admissible tube design of a scenario, its starts and goals checked against the
    footprint; raises :class:`~ground.scenario.ConfigError` (field ``controller`` or the robot's)
    with the reason, and nothing else."""
    try:
        design = synthesize(scn.controller, scn.arena)
    except SetComputationError as e:
        raise ConfigError("controller", str(e)) from None
    if design.failures:
        raise ConfigError("controller", "inadmissible tube design: " + "; ".join(design.failures))
    check_geometry(scn, design.footprint)
    return design
