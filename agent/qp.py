"""The per-step QP of one agent (docs/method.md §5; paper eqs. 12–13, 19–32).

Decision vector ``ξ = [x̂_t (4), v̂_t … v̂_{t+N−1} (2N), ȳ (2)]`` (n = 2N + 6).
With the committed reference ``ỹ_t … ỹ_{t+N−1}`` and its reference states
``x̃_t … x̃_{t+N−1}`` (``ũ_k = −K_r(x̃_k − E ỹ_{k+1})``), the QP is::

    min  Σ_{k<N} ‖x̂_k − x̃_k‖²_Q + ‖v̂_k − ũ_k‖²_R
         + γ‖ȳ − ỹ_{t+N−1}‖² + ‖ȳ − y_goal‖²_T   (+ convexified V_coll)
    s.t. x_t − x̂_t ∈ Z                         (|Z_F(x_t − x̂_t)| ≤ Z_f)
         x̂_k ∈ X̂, v̂_k ∈ Û
         |C(x̂_k − x̃_k)|∞ ≤ δ                    (tracking tube Δ^z)
         x̂_{t+N} = x̃_{t+N}(ȳ) = (A − BK_r) x̃_{t+N−1} + B K_r E ȳ
         |ȳ − ỹ_{t+N−1}|∞ ≤ ε,  ȳ ∈ arena ⊖ r_i
         coordination half-planes  nᵀ ȳ ≥ b      (docs/method.md §6)

``ũ_{t+N−1}`` is affine in ȳ, so its cost term couples v̂_{t+N−1} and ȳ.
The Hessian and all but the coordination rows of the constraint matrix are
constant: they are built once, and each step only updates vectors (and the
few coordination rows).  The state and tube rows share one two-sided row per
position (one row instead of two per bound).

ProxSuite (dense, box constraints, PrimalDualLDLT) solves it with the
settings of :func:`configure` (docs/method.md §9); every call returns its status, and anything but
``PROXQP_SOLVED`` is a failure for the caller to handle.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import proxsuite

from agent.sets import Array
from agent.tube import TubeDesign
from ground.params import ControllerParams

_PX = proxsuite.proxqp
INACTIVE = 1e9
"""Bound magnitude of an unused coordination row (the row never binds)."""


def configure(s: Any, p: ControllerParams) -> None:
    """Set a ProxSuite ``settings`` object to the settings every solve of this project uses
    (docs/method.md §9): absolute tolerance 1e-5 with the duality-gap check, a strict
    primal-infeasibility threshold (the default flags feasible QPs of this shape), the
    iteration caps of ``p``, and a cold start from the previous result (the documented warm
    start reuses a shrunken proximal parameter and reports false infeasibility)."""
    s.eps_abs = 1e-5
    s.eps_rel = 0.0
    s.check_duality_gap = True
    s.eps_duality_gap_abs = 1e-4
    s.eps_duality_gap_rel = 0.0
    s.default_mu_in = 1e-2
    s.eps_primal_inf = 1e-9
    s.max_iter = p.max_iter
    s.max_iter_in = p.max_iter_in
    s.initial_guess = _PX.InitialGuess.COLD_START_WITH_PREVIOUS_RESULT
    s.verbose = False


@dataclass
class StepData:
    """Everything one step's QP depends on.  Shapes for horizon N."""

    x: Array
    """Measured state (4,) [m, m/s], or its prediction (:attr:`z_f`)."""
    x_ref: Array
    """Reference states x̃_t … x̃_{t+N−1}, (N, 4)."""
    y_ref: Array
    """Committed reference ỹ_t … ỹ_{t+N−1}, (N, 2) [m]."""
    goal: Array
    """Target of the goal term (2,) [m] (the goal, or a tie-breaker waypoint)."""
    y_box: Array
    """Box for ȳ: (xmin, xmax, ymin, ymax) of arena ⊖ r_i [m]."""
    pos_box: Array
    """Box X̂ for positions (xmin, xmax, ymin, ymax) [m]."""
    coord_normals: Array
    """Coordination half-planes nᵀ ȳ ≥ b: normals (M, 2), unit length."""
    coord_bounds: Array
    """Right-hand sides b (M,) [m]."""
    penalty_H: Array | None = None
    """Convexified V_coll Hessian on ȳ (2, 2), or None."""
    penalty_g: Array | None = None
    """Convexified V_coll gradient term on ȳ (2,), or None."""
    z_f: Array | None = None
    """Facet offsets (p,) of the set constraint (a) keeps ``x − x̂_t`` in: None for Z
    (``design.Z_f``); Z ⊖ W (``design.Z_f_ahead``) when ``x`` is a prediction."""


@dataclass
class SolveResult:
    """What one :meth:`TubeQP.solve` gives: ``ok`` only for a ``PROXQP_SOLVED`` status with
    a finite solution found within the time budget; ``iterations`` are the solver's."""

    status: str
    """Solver status name, e.g. ``PROXQP_SOLVED``; ``TIME_BUDGET_EXCEEDED`` if discarded for time."""
    ok: bool
    xi: Array | None
    """Solution (n,), a copy; None unless ok."""
    iterations: int
    solve_time: float
    """Wall time of update + solve [s]."""


class TubeQP:
    """Assembles the QP once and solves it each step with ProxSuite."""

    def __init__(self, design: TubeDesign, max_coord_rows: int = 16):
        p = design.params
        self.design = design
        N = self.N = p.horizon
        A, B, E, K_r = design.A, design.B, design.E, design.K_r
        n = self.n = 2 * N + 6
        self.iv = slice(4, 4 + 2 * N)
        self.iy = slice(4 + 2 * N, 6 + 2 * N)
        self.max_coord_rows = max_coord_rows

        # S[k] (4, n): x̂_{t+k} = S[k] ξ for k = 0..N.
        S = np.zeros((N + 1, 4, n))
        S[0, :, 0:4] = np.eye(4)
        for k in range(N):
            S[k + 1] = A @ S[k]
            S[k + 1, :, 4 + 2 * k : 6 + 2 * k] += B
        self.S = S
        self.S_pos = S[:, [0, 2], :].reshape(-1, n)
        """Stacked position rows: (S_pos ξ).reshape(N+1, 2) are x̂_t … x̂_{t+N} positions."""

        # Cost rows: ‖L ξ − r‖²_Wt with the target r assembled per step.
        Qd = np.diag(p.Q)
        Rd = np.diag(p.R)
        rows, weights = [], []
        for k in range(N):
            rows.append(S[k])
            weights.append(Qd)
        for k in range(N):
            Lk = np.zeros((2, n))
            Lk[:, 4 + 2 * k : 6 + 2 * k] = np.eye(2)
            if k == N - 1:
                Lk[:, self.iy] = -K_r @ E  # v̂_{N−1} − ũ_{N−1}(ȳ) = v̂ − K_r E ȳ + K_r x̃_{N−1}
            rows.append(Lk)
            weights.append(Rd)
        Ly = np.zeros((2, n))
        Ly[:, self.iy] = np.eye(2)
        rows += [Ly, Ly]
        weights += [p.gamma * np.eye(2), np.diag(p.T)]
        L = np.vstack(rows)
        Wt = np.zeros((L.shape[0], L.shape[0]))
        o = 0
        for w in weights:
            Wt[o : o + w.shape[0], o : o + w.shape[0]] = w
            o += w.shape[0]
        self.H0 = 2.0 * L.T @ Wt @ L
        self.H0 = 0.5 * (self.H0 + self.H0.T)
        self.G_map = -2.0 * L.T @ Wt  # g = G_map @ r
        self.r_len = L.shape[0]

        # Equality: S[N] ξ − B K_r E ȳ = (A − BK_r) x̃_{N−1}.
        Aeq = S[N].copy()
        Aeq[:, self.iy] -= B @ K_r @ E
        self.Aeq = Aeq
        self.AR = A - B @ K_r

        # Inequalities: Z rows, then per k=1..N−1 rows [px, vx, py, vy], then coordination rows.
        ZF = design.Z_F
        self.nz = ZF.shape[0]
        Cz = np.zeros((self.nz, n))
        Cz[:, 0:4] = ZF
        Cs = S[1:N].reshape(-1, n)  # (4(N−1), n), row 4(k−1)+j is component j of x̂_{t+k}
        self.ns = Cs.shape[0]
        Cc = np.zeros((max_coord_rows, n))
        Cc[:, self.iy] = np.array([1.0, 0.0])
        self.C = np.vstack([Cz, Cs, Cc])
        self.n_in = self.C.shape[0]
        self.ic = slice(self.nz + self.ns, self.n_in)

        self.vb = float(design.x_bound[1])
        self.ub_u = float(design.u_hat[0])

        self.qp = _PX.dense.QP(
            n, 4, self.n_in, True, _PX.dense.HessianType.Dense, _PX.dense.DenseBackend.PrimalDualLDLT
        )
        configure(self.qp.settings, p)
        self._initialised = False
        self.time_budget = p.solve_time_budget

    # ------------------------------------------------------------------ data
    def problem(self, d: StepData) -> dict[str, Array]:
        """Dense problem arrays for step data ``d``: H, g, A, b, C, l, u, l_box, u_box."""
        N, p, design = self.N, self.design.params, self.design
        K_r, E = design.K_r, design.E
        x_ref, y_ref = d.x_ref, d.y_ref
        u_ref = -(x_ref[:-1] - y_ref[1:] @ E.T) @ K_r.T  # ũ_t … ũ_{t+N−2}, (N−1, 2)
        r = np.concatenate(
            [x_ref.ravel(), u_ref.ravel(), -K_r @ x_ref[-1], y_ref[-1], np.asarray(d.goal, dtype=float)]
        )
        g = self.G_map @ r
        H = self.H0
        if d.penalty_H is not None and d.penalty_g is not None:
            H = H.copy()
            H[self.iy, self.iy] += d.penalty_H
            g = g.copy()
            g[self.iy] += d.penalty_g
        b = self.AR @ x_ref[-1]

        delta = p.delta
        pb = d.pos_box
        l = np.empty(self.n_in)
        u = np.empty(self.n_in)
        zc = design.Z_F @ d.x
        z_f = design.Z_f if d.z_f is None else d.z_f
        l[: self.nz] = zc - z_f
        u[: self.nz] = zc + z_f
        ls = l[self.nz : self.nz + self.ns].reshape(N - 1, 4)
        us = u[self.nz : self.nz + self.ns].reshape(N - 1, 4)
        ls[:, 0] = np.maximum(pb[0], x_ref[1:, 0] - delta)
        us[:, 0] = np.minimum(pb[1], x_ref[1:, 0] + delta)
        ls[:, 2] = np.maximum(pb[2], x_ref[1:, 2] - delta)
        us[:, 2] = np.minimum(pb[3], x_ref[1:, 2] + delta)
        ls[:, 1] = ls[:, 3] = -self.vb
        us[:, 1] = us[:, 3] = self.vb

        C = self.C.copy()
        m = d.coord_normals.shape[0]
        if m > self.max_coord_rows:
            raise ValueError(f"{m} coordination rows exceed the assembled capacity {self.max_coord_rows}")
        cc = C[self.ic]
        cc[:, self.iy] = np.array([1.0, 0.0])
        cc[:m, self.iy] = d.coord_normals
        lc = l[self.ic]
        uc = u[self.ic]
        lc[:] = -INACTIVE
        uc[:] = INACTIVE
        lc[:m] = d.coord_bounds

        lb = np.empty(self.n)
        ub = np.empty(self.n)
        x0r = x_ref[0]
        lb[0] = max(pb[0], x0r[0] - delta)
        ub[0] = min(pb[1], x0r[0] + delta)
        lb[2] = max(pb[2], x0r[2] - delta)
        ub[2] = min(pb[3], x0r[2] + delta)
        lb[1] = lb[3] = -self.vb
        ub[1] = ub[3] = self.vb
        lb[self.iv] = -self.ub_u
        ub[self.iv] = self.ub_u
        eps = p.epsilon
        yl = y_ref[-1]
        yb = d.y_box
        lb[self.iy] = [max(yb[0], yl[0] - eps), max(yb[2], yl[1] - eps)]
        ub[self.iy] = [min(yb[1], yl[0] + eps), min(yb[3], yl[1] + eps)]
        return {"H": H, "g": g, "A": self.Aeq, "b": b, "C": C, "l": l, "u": u, "l_box": lb, "u_box": ub}

    @staticmethod
    def violation(prob: dict[str, Array], xi: Array) -> float:
        """Largest constraint violation of ``xi`` in ``prob`` (0 if feasible)."""
        eq = np.abs(prob["A"] @ xi - prob["b"]).max(initial=0.0)
        cx = prob["C"] @ xi
        ineq = max(
            float(np.max(prob["l"] - cx, initial=0.0)),
            float(np.max(cx - prob["u"], initial=0.0)),
        )
        box = max(
            float(np.max(prob["l_box"] - xi, initial=0.0)),
            float(np.max(xi - prob["u_box"], initial=0.0)),
        )
        return float(max(eq, ineq, box, 0.0))

    @staticmethod
    def objective(prob: dict[str, Array], xi: Array) -> float:
        """The QP's cost ½ ξᵀHξ + gᵀξ of ``prob`` at ``xi`` (n,)."""
        return float(0.5 * xi @ prob["H"] @ xi + prob["g"] @ xi)

    # ----------------------------------------------------------------- solve
    def solve(self, prob: dict[str, Array], warm: Array | None) -> SolveResult:
        """Update the ProxSuite model with ``prob`` and solve, warm-started at ``warm`` (n,).

        The status is always checked; only ``PROXQP_SOLVED`` yields ``ok``."""
        t0 = time.perf_counter()
        qp = self.qp
        H_changed = prob["H"] is not self.H0
        if not self._initialised:
            qp.init(
                prob["H"], prob["g"], prob["A"], prob["b"], prob["C"], prob["l"], prob["u"],
                prob["l_box"], prob["u_box"],
            )  # fmt: skip
            self._initialised = True
            self._H_is_base = not H_changed
        else:
            kwargs = dict(
                g=prob["g"], b=prob["b"], C=prob["C"], l=prob["l"], u=prob["u"],
                l_box=prob["l_box"], u_box=prob["u_box"],
            )  # fmt: skip
            if H_changed or not self._H_is_base:
                kwargs["H"] = prob["H"]
                self._H_is_base = not H_changed
            qp.update(**kwargs)
        if warm is not None:
            # COLD_START_WITH_PREVIOUS_RESULT keeps x, y, z: seed x with the
            # shifted candidate (the views write into solver memory).
            qp.results.x[:] = warm
        qp.solve()
        dt = time.perf_counter() - t0
        info = qp.results.info
        status = info.status.name
        ok = info.status == _PX.QPSolverOutput.PROXQP_SOLVED
        xi = np.array(qp.results.x, copy=True) if ok else None
        if ok and xi is not None and not np.all(np.isfinite(xi)):
            ok, xi, status = False, None, "NON_FINITE_SOLUTION"
        if ok and self.time_budget is not None and dt > self.time_budget:
            ok, xi, status = False, None, "TIME_BUDGET_EXCEEDED"
        if not ok:
            # Never reuse a failed iterate as the next warm start.
            qp.results.x[:] = 0.0 if warm is None else warm
            qp.results.y[:] = 0.0
            qp.results.z[:] = 0.0
        return SolveResult(status=status, ok=ok, xi=xi, iterations=int(info.iter), solve_time=dt)


def daqp_solve(prob: dict[str, Array]) -> tuple[Array | None, int]:
    """Solve ``prob`` with DAQP, a dual active-set solver (the cross-check of the tests and the benchmark).

    Used as the second solver in cross-checks and as the benchmark yardstick;
    needs the optional ``daqp`` package (``pip install -e '.[test]'``).
    Returns (ξ (n,) or None, DAQP exit flag; 1 means optimal)."""
    import daqp

    n = prob["H"].shape[0]
    A = np.vstack([prob["A"], prob["C"]])
    upper = np.concatenate([prob["u_box"], prob["b"], prob["u"]])
    lower = np.concatenate([prob["l_box"], prob["b"], prob["l"]])
    sense = np.zeros(upper.size, dtype=np.int32)
    sense[n : n + prob["A"].shape[0]] = 5  # equality rows
    x, _, flag, _ = daqp.solve(
        np.ascontiguousarray(prob["H"]),
        np.ascontiguousarray(prob["g"]),
        np.ascontiguousarray(A),
        np.ascontiguousarray(upper),
        np.ascontiguousarray(lower),
        sense,
    )
    return (np.array(x) if flag == 1 else None), int(flag)
