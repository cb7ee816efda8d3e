"""The per-step QP: structure, solver settings and agreement with a second solver."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from agent.qp import TubeQP, daqp_solve
from fleet.running.simulate import run
from ground.scenario import load_scenario


@pytest.fixture(scope="module")
def recorded():
    """QPs recorded from the 8-robot swap, where robots meet in the centre.

    Every 5th QP, plus every one with a coordination row (about 1 % of them: the
    robots' appended points are rarely close enough to bind)."""
    probs: list[dict] = []
    orig = TubeQP.problem
    count = {"k": 0}

    def recording(self, d):
        prob = orig(self, d)
        count["k"] += 1
        coordinated = bool(np.any(prob["l"][self.ic] > -1e8))
        if count["k"] % 5 == 0 or coordinated:
            probs.append({k: np.array(v, copy=True) for k, v in prob.items()})
        return prob

    scn = load_scenario(Path(__file__).resolve().parents[2] / "scenarios" / "swap_8.toml")
    TubeQP.problem = recording
    try:
        result = run(scn, steps=800)  # the whole run: all home after about 550 steps
    finally:
        TubeQP.problem = orig
    return result, probs


def test_proxsuite_and_daqp_agree(recorded):
    result, probs = recorded
    assert len(probs) >= 400
    qp = TubeQP(result.design, max_coord_rows=probs[0]["C"].shape[0] - TubeQP(result.design, 0).n_in)
    n_active = 0
    for prob in probs:
        res = qp.solve(prob, None)
        assert res.ok, res.status
        ref, flag = daqp_solve(prob)
        assert flag == 1 and ref is not None
        f_px, f_ref = TubeQP.objective(prob, res.xi), TubeQP.objective(prob, ref)
        assert abs(f_px - f_ref) <= 1e-6 * max(1.0, abs(f_ref))
        # The applied input v̂_t, and ȳ, agree (within 1e-3 of the limit).
        assert np.max(np.abs(res.xi[4:6] - ref[4:6])) <= 1e-3 * result.design.params.a_max
        assert np.max(np.abs(res.xi[qp.iy] - ref[qp.iy])) <= 1e-5
        assert TubeQP.violation(prob, res.xi) <= 2e-5
        n_active += int(np.any(prob["l"][qp.ic] > -1e8))
    # The instances exercised the coordination rows, not only free motion.
    assert n_active >= 20


def test_matrices_are_assembled_once(recorded):
    result, probs = recorded
    qp = TubeQP(result.design, max_coord_rows=probs[0]["C"].shape[0] - TubeQP(result.design, 0).n_in)
    H0 = probs[0]["H"]
    fixed = slice(0, qp.nz + qp.ns)
    for prob in probs[1:]:
        assert np.array_equal(prob["H"], H0)
        assert np.array_equal(prob["A"], probs[0]["A"])
        assert np.array_equal(prob["C"][fixed], probs[0]["C"][fixed])
        # Only the ȳ columns of the coordination rows may change.
        other = np.ones(qp.n, dtype=bool)
        other[qp.iy] = False
        assert not np.any(prob["C"][qp.ic][:, other])


def test_failed_solve_is_reported_not_applied(recorded):
    """An infeasible QP returns a failure status within the iteration caps, and no solution."""
    result, probs = recorded
    qp = TubeQP(result.design, max_coord_rows=probs[0]["C"].shape[0] - TubeQP(result.design, 0).n_in)
    prob = {k: v.copy() for k, v in probs[10].items()}
    # ȳ must be both ≥ and ≤ incompatible values: ε box against a coordination row.
    row = qp.ic.start
    prob["C"][row, :] = 0.0
    prob["C"][row, qp.iy] = [1.0, 0.0]
    prob["l"][row] = prob["u_box"][qp.iy][0] + 0.05
    prob["u"][row] = 1e9
    res = qp.solve(prob, None)
    assert not res.ok
    assert res.xi is None
    assert res.status in ("PROXQP_PRIMAL_INFEASIBLE", "PROXQP_MAX_ITER_REACHED")
    p = result.design.params
    assert res.iterations <= p.max_iter * p.max_iter_in
    # The next feasible QP solves again (no poisoned warm start).
    assert qp.solve(probs[11], None).ok


def test_time_budget_discards_slow_solves(recorded):
    result, probs = recorded
    design = result.design
    slow = design.params.replace(solve_time_budget=1e-12)
    from agent.tube import TubeDesign

    d2 = TubeDesign(**{**design.__dict__, "params": slow})
    qp = TubeQP(d2, max_coord_rows=probs[0]["C"].shape[0] - TubeQP(design, 0).n_in)
    res = qp.solve(probs[0], None)
    assert not res.ok and res.status == "TIME_BUDGET_EXCEEDED" and res.xi is None
