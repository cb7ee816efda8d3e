"""Controller parameter set: the ``[controller]`` table of a scenario file.

Every field is SI (m, s, rad).  Per-axis quantities apply identically to the x
and y axes of the double-integrator nominal model (:mod:`ground.model`): state
``x = [px, vx, py, vy]``, input ``u = [ax, ay]``.

Two presets exist:

* ``epuck`` (default): a working design for E-puck speeds.
* ``paper``: the paper's weights (Q = I4, R = 20·I2, K from the same weights,
  W = ±1 cm).  Its tube is too large for a 2 m arena; ``fleet design --preset
  paper`` says by how much.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

PRESETS = ("epuck", "paper")


@dataclass(frozen=True)
class WheelGeometry:
    """E-puck differential-drive geometry (GCtronic's e-puck figures; docs/lab.md)."""

    wheel_radius: float = 0.0205
    """Wheel radius [m]."""
    axle: float = 0.053
    """Distance between the wheel contact points [m]."""
    steps_per_rev: int = 1000
    """Motor steps per wheel revolution."""
    max_steps: float = 1000.0
    """Largest commanded wheel speed [steps/s] (firmware range ±1000)."""

    @property
    def metres_per_step(self) -> float:
        """Wheel rim travel per motor step [m]."""
        import math

        return 2.0 * math.pi * self.wheel_radius / self.steps_per_rev

    @property
    def max_wheel_speed(self) -> float:
        """Largest wheel rim speed [m/s] (≈ 0.129 m/s)."""
        return self.max_steps * self.metres_per_step


@dataclass(frozen=True)
class ControllerParams:
    """Parameters of one robot's tube MPC.

    Sign conventions (written once): the ancillary law is ``u = v̂ + K(x − x̂)``
    with ``A + BK`` Schur; the reference generator is
    ``ũ_k = −K_r(x̃_k − E ỹ_{k+1})`` with ``A − B K_r`` Schur.
    """

    preset: str = "epuck"
    Ts: float = 0.1
    """Sampling period [s]."""
    horizon: int = 20
    """Prediction horizon N [steps]."""

    # MPC cost (docs/method.md §5): diagonals of Q (4), R (2) and T (2); gamma scalar.
    Q: tuple[float, ...] = (1.0, 1.0, 1.0, 1.0)
    """Weight on x̂_k − x̃_k, diagonal over [px, vx, py, vy]."""
    R: tuple[float, ...] = (20.0, 20.0)
    """Weight on v̂_k − ũ_k, diagonal over [ax, ay]."""
    gamma: float = 1.0
    """Weight on ‖ȳ − ỹ_{t+N−1}‖² [1/m²]."""
    T: tuple[float, ...] = (50.0, 50.0)
    """Weight on ȳ − y_goal, diagonal over [x, y]."""

    # Ancillary gain K (kept separate from the MPC weights, docs/method.md §3).
    K_Q: tuple[float, ...] = (400.0, 10.0, 400.0, 10.0)
    """LQR state weight that defines K."""
    K_R: tuple[float, ...] = (1.0, 1.0)
    """LQR input weight that defines K."""

    # Reference generator K_r (docs/method.md §4).
    ref_Q: tuple[float, ...] = (100.0, 10.0, 100.0, 10.0)
    ref_R: tuple[float, ...] = (0.3, 0.3)

    W: tuple[float, float] = (0.001, 0.001)
    """Disturbance box half-widths per axis: (position [m], velocity [m/s]).

    W bounds the one-step error of the *measured* state, so it includes the
    pose noise: a measurement error n moves it by n⁺ − n, up to
    2·``point_noise`` per position axis."""
    pose_noise: tuple[float, float] = (0.0001, 0.001)
    """Bound on the tracker's pose error: (position per axis [m], heading [rad]).

    The controlled point's measured position is then off by at most
    ``point_noise`` per axis; ρ and the footprint grow by √2 of that so the
    guarantee holds for the true body, not only for the measured one."""
    epsilon: float = 0.0055
    """Reference increment bound ‖ȳ − ỹ_{t+N−1}‖∞ ≤ ε [m] (B_ε)."""
    delta: float = 0.01
    """Tracking-tube half-width Δ^z: |C(x̂_k − x̃_k)|∞ ≤ δ [m]."""
    v_max: float = 0.075
    """Velocity bound per axis, |vx|, |vy| ≤ v_max [m/s]."""
    a_max: float = 0.5
    """Acceleration bound per axis, |ax|, |ay| ≤ a_max [m/s²]."""

    robot_radius: float = 0.035
    """Physical body radius of the E-puck [m]."""
    lookahead: float = 0.04
    """Distance ℓ of the controlled point ahead of the axle centre [m].

    ℓ > 0 selects the look-ahead inner loop, exact at v = 0.  ℓ = 0 selects
    the paper's eq. 3 with the |v| ≥ v_min regularisation."""
    v_min: float = 0.01
    """Regularisation speed of eq. 3 (used when lookahead = 0) [m/s]."""
    wheel: WheelGeometry = field(default_factory=WheelGeometry)

    mrpi_tol: float = 5e-4
    """A-priori error bound of the mRPI outer approximations [m, m/s]."""
    mrpi_max_terms: int = 500
    """Cap on the number of Minkowski terms s of an mRPI approximation."""
    admissibility_margin: float = 0.05
    """Relative margin every admissibility check must keep: a borderline design makes QPs fail."""

    # Solver caps (docs/method.md §9).
    max_iter: int = 25
    """ProxSuite outer-iteration cap.  Feasible QPs of this shape need a handful."""
    max_iter_in: int = 40
    """ProxSuite inner-iteration cap per outer iteration.  With max_iter this
    bounds an infeasible solve to 1000 inner iterations, tens of milliseconds,
    instead of the seconds that an uncapped one takes."""
    solve_time_budget: float | None = None
    """Wall-time budget of one solve [s]; a slower solve is discarded and the
    fallback applied.  None disables the check (deterministic runs)."""

    # Coordination (docs/method.md §6–§8).
    priority_share: float = 0.8
    """Share of the slack σ taken by the robot with the higher priority."""
    deadlock: bool = True
    """Enable the priority-yielding deadlock tie-breaker (shapes the cost only)."""
    penalty: bool = False
    """Enable the paper's degree-5 polynomial penalty (eq. 34), convexified."""
    penalty_dlim: float = 0.12
    """Activation threshold of the penalty on the squared distance s = ‖ȳ − c_j‖² [m²]."""
    penalty_weight: float = 50.0
    """Scale of the penalty polynomial."""

    @property
    def point_noise(self) -> float:
        """Per-axis bound on the measured controlled point's error [m]: η_p + ℓ·η_θ."""
        return self.pose_noise[0] + self.lookahead * self.pose_noise[1]

    def replace(self, **changes: object) -> ControllerParams:
        """Return a copy with ``changes`` applied."""
        return dataclasses.replace(self, **changes)  # type: ignore[arg-type]


def preset(name: str) -> ControllerParams:
    """Return the named preset (``epuck`` or ``paper``)."""
    if name == "epuck":
        return ControllerParams()
    if name == "paper":
        # Paper §IV: Q = I4, R = 20·I2, [K, P] = dlqr(A, B, Q, R), W = ±1 cm.
        return ControllerParams(
            preset="paper",
            K_Q=(1.0, 1.0, 1.0, 1.0),
            K_R=(20.0, 20.0),
            W=(0.01, 0.0),
            pose_noise=(0.002, 0.0),
            lookahead=0.0,
        )
    raise ValueError(f"unknown preset {name!r}; expected one of {', '.join(PRESETS)}")
