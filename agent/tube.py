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
    failures: list[str] = field(default_factory=list)

    @property
    def admissible(self) -> bool:
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
    ``TubeDesign.failures`` (call :func:`require_admissible` to raise)."""
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
    for j, name in ((1, "velocity"), (3, "velocity")):
        if x_bound[j] <= 0:
            failures.append(
                f"X̂ {name} bound is empty: v_max {p.v_max:.4g} m/s − h_Z {hZ[j]:.4g} m/s "
                f"= {x_bound[j]:.4g} m/s"
            )
            break
    for j in range(1):
        if u_hat[j] <= 0:
            failures.append(
                f"Û is empty: a_max {p.a_max:.4g} m/s² − h_KZ {KZ[j]:.4g} m/s² = {u_hat[j]:.4g} m/s²"
            )
    # Stay-put admissibility (docs/method.md §4): Ψ's velocity part in X̂ and the
    # reference input K_r(Ψ ⊕ E B_ε) in Û, both strictly, with a margin.
    hPsi_v = float(Pr.Z.support(eye[1]))
    ref_u = Pr.Z.minkowski_sum(Zonotope(np.zeros(4), E @ np.diag([eps, eps])))
    hKrPsi = float(np.abs(K_r @ ref_u.G).sum(axis=1).max())
    if x_bound[1] > 0 and hPsi_v > (1.0 - margin) * x_bound[1]:
        failures.append(
            f"epsilon {eps:.4g} m too large: reference lag velocity h_Ψ {hPsi_v:.4g} m/s exceeds "
            f"{1 - margin:.2f}·X̂ velocity bound {x_bound[1]:.4g} m/s "
            f"by {hPsi_v - (1 - margin) * x_bound[1]:.4g} m/s"
        )
    if u_hat[0] > 0 and hKrPsi > (1.0 - margin) * u_hat[0]:
        failures.append(
            f"epsilon {eps:.4g} m too large: reference input h_{{K_r(Ψ⊕EB_ε)}} {hKrPsi:.4g} m/s² exceeds "
            f"{1 - margin:.2f}·Û bound {u_hat[0]:.4g} m/s² by {hKrPsi - (1 - margin) * u_hat[0]:.4g} m/s²"
        )
    # Pose noise: the measured state's one-step error includes n⁺ − n, up to
    # 2·point_noise per position axis, which W must cover with room to spare.
    if 2.0 * p.point_noise > (1.0 - margin) * p.W[0]:
        failures.append(
            f"pose_noise too large: it moves the measured point by up to 2·{p.point_noise:.4g} m per "
            f"step, more than {1 - margin:.2f}·W position bound {p.W[0]:.4g} m"
        )
    if p.lookahead <= 0:
        # docs/method.md §1: ℓ = 0 runs the paper's eq. 3, regularised at v_min; from rest its
        # one-step error is far outside any usable W, so the tube would promise what it cannot.
        failures.append(
            "lookahead 0 m: the inner loop is then the paper's eq. 3, singular at rest, and its "
            "one-step error is not bounded by W; use a look-ahead point (e.g. lookahead = 0.04)"
        )
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
