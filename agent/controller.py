"""One robot's tube MPC: the state machine an agent process runs each step.

Per step t (docs/method.md §5):

1. Build the QP from the measured state ``x_t`` (4,), the committed
   reference ``ỹ_t … ỹ_{t+N−1}`` and its reference states, the neighbours'
   last committed points and the static obstacles.
2. Form the *shifted candidate* from the previous solution (stay put:
   ``ȳ = ỹ_{t+N−1}``).  It is feasible by construction whenever the real
   disturbance stayed in W; its numerical constraint violation is recorded.
3. Solve with ProxSuite, warm-started at the candidate.  If the status is not
   solved (or the time budget is exceeded), apply the candidate instead: the
   *fallback*, counted and reported.
4. Apply ``a = v̂_t + K(x_t − x̂_t)`` (the ancillary law), append ȳ, shift.

Nothing here knows about transport or logging; events are returned in
:class:`StepOutput` for the caller to publish.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from agent.coordination import (
    Hazard,
    NeighbourInfo,
    hazard_halfplanes,
    obstacle_halfplanes,
    polynomial_penalty,
    repair_point,
    split_halfplanes,
)
from agent.navigator import Navigator
from agent.qp import StepData, TubeQP
from agent.sets import Array
from agent.tube import TubeDesign
from ground.arrival import Gate
from ground.model import ancillary_law, brake_input
from ground.scenario import AT_GOAL, GOAL_MARGIN, PARKED_RADIUS
from ground.wire import BLIND, LINK_DOWN, MAX_AGE, PARKED, RETURNING, UNDER_WAY, WAITING

TUBE_TOL = 2e-5
"""Tolerance of the tube check x − x̂ ∈ Z [m, m/s]: twice ProxSuite's eps_abs,
since the solver may place x̂ on the boundary of Z up to its tolerance."""


@dataclass
class StepOutput:
    """Result of one controller step."""

    a: Array
    """Acceleration to apply (2,) [m/s²], u = v̂ + K(x − x̂)."""
    committed: Array
    """Committed reference ỹ_{t+1} … ỹ_{t+N} after the append, (N, 2) [m]."""
    plan: Array
    """Nominal positions x̂_t … x̂_{t+N} of the applied plan, (N+1, 2) [m]."""
    x_hat: Array
    """Nominal state x̂_t (4,) used in the ancillary law."""
    status: str
    """ProxSuite status name, or a fallback reason."""
    fallback: bool
    """True if the shifted candidate was applied instead of a solution."""
    solve_time: float
    """Wall time of QP update + solve [s]."""
    step_time: float
    """Wall time of the whole step: assembly + solve + bookkeeping [s]."""
    candidate_violation: float
    """Constraint violation of the shifted candidate in this step's QP (0 = feasible)."""
    tube_ok: bool
    """x_t − x̂_t ∈ Z for the applied x̂_t (x^p_t − x̂_t ∈ Z ⊖ W for a predicted x^p_t)."""
    min_slack: float
    """Smallest σ = ‖c_i − c_j‖ − (r_i + r_j) against neighbours [m]."""
    target: Array
    """Target of the goal term this step (2,) [m]."""
    mode: str
    """Navigator mode: goal, path, yield, aside or escape (:meth:`agent.navigator.Navigator.target`)."""
    iterations: int = 0
    x_next: Array = field(default_factory=lambda: np.zeros(4))
    """The shifted candidate for the next step: nominal state x̂_{t+1} (4,) [m, m/s]."""
    v_next: Array = field(default_factory=lambda: np.zeros((1, 2)))
    """... and its nominal inputs v̂_{t+1} … v̂_{t+N}, (N, 2) [m/s²]: what the robot side
    follows if the next commands miss their deadline (:func:`chain_input`)."""
    hazards: Sequence[Hazard] = ()
    """The discs the step kept clear of (:class:`Hazard`)."""
    blocked: str = ""
    """The robot whose static disc covers the goal this step, or "" (:meth:`TubeMPC.blocker`)."""
    no_room: str = ""
    """The robot that goes first whose corridor this robot found no free point out of this step,
    or "" (:attr:`agent.navigator.Navigator.no_room`)."""


@dataclass
class Counters:
    """What a :class:`TubeMPC` has counted over its steps (the agent's closing log line).

    ``solves``: QPs solved, counted by solver status in ``status_counts``; ``failures`` and ``fallbacks``:
    solves without a usable solution, whose step took the shifted candidate instead; ``tube_exits``:
    steps whose error x − x̂ was not in Z."""

    solves: int = 0
    failures: int = 0
    fallbacks: int = 0
    tube_exits: int = 0
    repairs: int = 0
    """Solutions whose ȳ was moved onto the coordination rows (solver tolerance)."""
    scaled_repairs: int = 0
    """Of those, the ones whose step had to be scaled towards c_i (the projection failed)."""
    status_counts: dict[str, int] = field(default_factory=dict)
    holds: int = 0
    """Steps without a usable measurement: braked, nothing new committed (:meth:`TubeMPC.hold`)."""
    uncontrolled: int = 0
    """Steps held while the robot's radio link was down: nothing solved (:meth:`TubeMPC.hold`)."""
    row_overflows: int = 0
    """Steps with more coordination rows than the QP holds (the rest checked after the solve)."""
    ahead: int = 0
    """Steps that took the target chosen ahead, between steps (:meth:`TubeMPC.steer_ahead`)."""
    unapplied: int = 0
    """Steps whose command the robot side did not apply; it followed the shifted
    candidate instead (:meth:`TubeMPC.rewind`)."""


SNAPSHOTS = 8
"""Controller steps kept for :meth:`TubeMPC.rewind` [steps]."""


class TubeMPC:
    """Distributed robust tube MPC of one robot.

    ``start`` (2,) is the controlled point's initial position [m]; the robot is
    assumed at rest there, so the initial committed reference is ``start``
    repeated N times."""

    def __init__(
        self,
        design: TubeDesign,
        start: Array,
        goal: Array,
        arena: tuple[float, float, float, float],
        obstacles: Sequence[Any] = (),
        priority: int = 0,
        rank: int = 0,
        max_neighbour_rows: int = 12,
        seed: int = 0,
        solver_fault: Any = None,
        gate: Gate | None = None,
    ):
        self.design = design
        p = self.params = design.params
        self.N = p.horizon
        self.goal = np.asarray(goal, dtype=float)
        self.arena = arena
        self.obstacles = list(obstacles)
        self.priority = priority
        self.rank = rank
        self.r = design.footprint
        self.qp = TubeQP(design, max_coord_rows=max_neighbour_rows + len(self.obstacles))
        self.nav = Navigator(
            footprint=self.r, arena=arena, obstacles=self.obstacles, priority=priority, rank=rank, seed=seed
        )
        self.solver_fault = solver_fault
        """Optional callable(step) -> bool; True forces this step's solve to count as failed (tests)."""
        self.gate = gate
        """The order of arrival this robot keeps to (:func:`ground.arrival.arrival`): until every
        robot it waits for has been seen past its goal or parked (:attr:`seen_past`), it steers
        to its wait point, not its goal; None once that holds, or if it waits for nobody, or once
        it is given a goal at run time or rejoins at its goal (docs/method.md §7, "The order of
        arrival")."""
        self.seen_past: set[str] = set()
        """Of the robots this one waits for, those seen past its goal or parked, or whose agent is
        gone, so far (ids)."""
        xmin, xmax, ymin, ymax = arena
        r = self.r
        self.y_box = np.array([xmin + r, xmax - r, ymin + r, ymax - r])
        m = design.body_radius + design.pos_tightening
        self.pos_box = np.array([xmin + m, xmax - m, ymin + m, ymax - m])
        self.counters = Counters()
        self._history: list[tuple[Array, Array, Array]] = []
        """States (ξ, ỹ, x̃) before each of the last SNAPSHOTS steps, oldest first."""
        self._candidate: tuple[tuple[Array, Array, Array], Array] | None = None
        """The candidate of the state (ξ, ỹ, x̃) it was made for (:meth:`candidate`)."""
        self.parking: Array | None = None
        """While a stopped robot's disc covers the goal (:meth:`_static`): the point nearest the goal
        clear of the static discs, where the robot parks instead (2,) [m]; None otherwise."""
        self._discs_changed = False
        """The static discs the navigator plans around changed at this step (:meth:`_static`)."""
        self._ahead: tuple[Array, Array, str] | None = None
        """The next step's target chosen ahead (:meth:`steer_ahead`): the committed reference
        ỹ it was chosen for, the target (2,) [m] and the mode."""
        self.reached_once = False
        self.phase_age = 0
        """Steps spent in the current :attr:`phase`, counted after each step [steps]."""
        self._aged_phase = UNDER_WAY
        self.k = 0
        self.reset(np.asarray(start, dtype=float))

    # --------------------------------------------------------------- state
    def reset(self, point: Array, x: Array | None = None) -> None:
        """(Re-)initialise at ``point`` (2,) [m]: the committed reference stays put there.  The
        nominal state starts at ``x`` (4,) [m, m/s], the measured state (so x − x̂ = 0 ∈ Z),
        or at rest at ``point``.  A robot (re)joining at its goal drops its :attr:`gate`: a
        restarted agent of a robot already home does not go back to wait."""
        if self.gate is not None and float(np.linalg.norm(point - self.goal)) < PARKED_RADIUS:
            self.gate = None  # (re)joining at its goal: the order of arrival is served
        E = self.design.E
        self.y_ref = np.tile(point, (self.N, 1))
        self.x_ref = np.tile(E @ point, (self.N, 1))
        xi = np.zeros(self.qp.n)
        xi[0:4] = E @ point if x is None else x
        xi[self.qp.iy] = point
        self.xi = xi
        self.target = self.goal
        self._ahead = None

    @property
    def last_point(self) -> Array:
        """c_i = ỹ_{t+N−1} (2,) [m]."""
        return self.y_ref[-1]

    @property
    def at_goal(self) -> bool:
        """The committed end point is at the goal now (within 1 mm)."""
        return bool(np.linalg.norm(self.y_ref[-1] - self.goal) < AT_GOAL)

    @property
    def phase(self) -> int:
        """Precedence phase (:data:`agent.coordination.UNDER_WAY` …).  While a stopped robot covers
        the goal, parked: the robot can get no closer than :attr:`parking`, where it waits as a
        robot at its goal does, yielded to by nobody (docs/method.md §7)."""
        if self.parking is not None:
            return PARKED  # nobody waits on it, and it makes way for those that move
        if self.gate is not None:
            # At its wait point it has nowhere to be yet: it makes way for those that move.
            off = float(np.linalg.norm(self.y_ref[-1] - self.gate.wait_point))
            return WAITING if off < PARKED_RADIUS else UNDER_WAY
        d = float(np.linalg.norm(self.y_ref[-1] - self.goal))
        if not self.reached_once and d < AT_GOAL:
            self.reached_once = True
        if not self.reached_once:
            return UNDER_WAY
        return PARKED if d < PARKED_RADIUS else RETURNING

    def _age_phase(self) -> None:
        """Count the steps spent in the current phase (after each step)."""
        phase = self.phase
        self.phase_age = min(self.phase_age + 1, MAX_AGE) if phase == self._aged_phase else 0
        self._aged_phase = phase

    def set_goal(self, goal: Array) -> None:
        """Accept a new goal (2,) [m] at run time (the scenario's order of arrival no longer
        applies: the gate goes)."""
        self.goal = np.asarray(goal, dtype=float)
        self.gate = None
        self.reached_once = False
        self.nav.reset_goal()
        self._ahead = None

    def info(self) -> NeighbourInfo:
        """What this agent publishes about itself for its neighbours."""
        return NeighbourInfo(
            id="",
            last_point=self.last_point.copy(),
            footprint=self.r,
            priority=self.priority,
            rank=self.rank,
            target=np.asarray(self.target, dtype=float).copy(),
            goal=self.goal.copy(),
            phase=self.phase,
            phase_age=self.phase_age,
        )

    def ancillary(self, x: Array) -> Array:
        """The ancillary law on the plan in force: u = v̂_t + K(x − x̂_t) (2,) [m/s²] for the
        state ``x`` (4,) [m, m/s], x̂_t and v̂_t being the plan's first nominal state and input."""
        return ancillary_law(x, self.xi[0:4], self.xi[4:6], self.design.K)

    def candidate(self) -> Array:
        """Shifted previous solution with ȳ = ỹ_{t+N−1} (stay put), (n,), a fresh array.

        Made once per state: a step makes it for the robot side (StepOutput.x_next) and
        the next step takes it again as its warm start and fallback.  The state arrays are
        replaced, never changed in place, so their identity tells whether it is current."""
        state = (self.xi, self.y_ref, self.x_ref)
        made = self._candidate
        if made is not None and all(a is b for a, b in zip(made[0], state, strict=True)):
            return made[1].copy()
        qp, E, K_r = self.qp, self.design.E, self.design.K_r
        prev = self.xi
        c = np.empty(qp.n)
        c[0:4] = qp.S[1] @ prev
        v = prev[qp.iv].reshape(self.N, 2)
        u_stay = -K_r @ (self.x_ref[-1] - E @ self.y_ref[-1])
        c[qp.iv] = np.vstack([v[1:], u_stay]).ravel()
        c[qp.iy] = self.y_ref[-1]
        self._candidate = (state, c)
        return c.copy()

    # ---------------------------------------------------------------- step
    def steer(self, known: Sequence[NeighbourInfo]) -> tuple[Array, str]:
        """The target (2,) [m] of the goal term from c_i, and the navigator's mode.

        ``known`` are the other robots the navigator plans around and yields to.
        Shaping only: whatever it returns, the step's constraints are the same."""
        goal = self.goal if self.parking is None else self.parking
        if self.gate is not None and self.parking is None and not self._gate_opens(known):
            goal = self.gate.wait_point
        if not self.params.deadlock:
            return goal, "goal"
        self.nav.phase, self.nav.phase_age = self.phase, self.phase_age
        return self.nav.target(self.last_point, goal, known)

    def _gate_opens(self, known: Sequence[NeighbourInfo]) -> bool:
        """Whether every robot this one waits for (:attr:`gate`) has now been seen past its goal
        (its committed point, in ``known``, past the goals that wall in its way, or parked), now
        or before (:attr:`seen_past`); if so the gate goes for good, and the navigator plans
        afresh, to the goal."""
        gate = self.gate
        assert gate is not None
        self.gate_news(known)
        if not self.seen_past.issuperset(gate.waits_for):
            return False
        self.gate = None
        self.nav.reset_goal()
        return True

    def gate_news(self, heard: Sequence[NeighbourInfo]) -> None:
        """Take what is heard of other robots (their newest plans) into :attr:`seen_past`: each
        robot this one waits for whose committed point is past its goal (:meth:`Gate.past`), or
        that is parked."""
        gate = self.gate
        if gate is None:
            return
        at = {nb.id: nb for nb in heard}
        for k, rid in enumerate(gate.waits_for):
            nb = at.get(rid)
            if nb is not None and (nb.phase == PARKED or gate.past(k, nb.last_point)):
                self.seen_past.add(rid)

    def steer_ahead(self, known: Sequence[NeighbourInfo]) -> None:
        """Choose the next step's target now, between steps.

        The realtime agent calls it once its neighbours' plans of this step are in,
        in the half step after its deadline, and so takes the navigator (with its periodic
        grid re-plan) off the path from tick to command.  The next :meth:`step` takes the
        choice only if the committed reference is still the one it was chosen for: a
        :meth:`rewind`, :meth:`reset`, :meth:`hold` or :meth:`set_goal` in between drops
        it, and the step steers itself (the navigator's counters then advance twice in that
        step).  Taking it anyway would be as safe, since the target only shapes the cost,
        but a fleet that falls behind then misses more deadlines."""
        self._ahead = (self.y_ref, *self.steer(known))

    def step(
        self,
        x: Array,
        neighbours: Sequence[NeighbourInfo],
        hazards: Sequence[Hazard] = (),
        predicted: bool = False,
        seen: Sequence[NeighbourInfo] = (),
    ) -> StepOutput:
        """One control step from measured state ``x`` (4,) [m, m/s].

        ``neighbours`` are coordinated with by the split rule (their plans of
        the previous step are in); ``hazards`` are neighbours known only from an
        older plan, or dead, kept clear of as static discs (:class:`Hazard`).
        ``predicted``: ``x`` is the prediction A x + B u of a state not measured yet, the plan
        being made a step ahead (delay compensation, docs/method.md §5): constraint (a) and
        :attr:`StepOutput.tube_ok` then use Z ⊖ W (:attr:`TubeDesign.Z_f_ahead`), and the
        returned ``a`` is the law at the prediction, not a command to apply.  ``seen``: robots
        beyond the neighbours that the navigator plans around and yields to as well (plans by
        place: those up to :data:`~agent.coordination.VIEW_CELLS` cells away); no constraint."""
        t0 = time.perf_counter()
        self._snapshot()
        p, design, qp = self.params, self.design, self.qp
        c_i = self.last_point
        normals, bounds, min_slack = split_halfplanes(
            c_i, self.r, self.priority, neighbours, p.priority_share, p.epsilon
        )
        on, ob = obstacle_halfplanes(c_i, self.r, self.obstacles, p.epsilon)
        normals += on
        bounds += ob
        hn, hb = hazard_halfplanes(c_i, self.r, hazards, p.epsilon)
        normals += hn
        bounds += hb
        blocked = self._static(hazards, neighbours)
        ahead, self._ahead = self._ahead, None
        if (
            ahead is not None and ahead[0] is self.y_ref and not self._discs_changed
        ):  # replaced, never changed in place
            self.target, mode = ahead[1], ahead[2]
            self.counters.ahead += 1
        else:
            self.target, mode = self.steer(
                [*neighbours, *(h.info for h in hazards if h.info is not None), *seen]
            )
        pen = None
        if p.penalty:
            pen = polynomial_penalty(
                c_i, [nb.last_point for nb in neighbours], p.penalty_dlim, p.penalty_weight
            )
        rows_n, rows_b = np.array(normals).reshape(-1, 2), np.array(bounds)
        over: tuple[Array, Array] | None = None
        if rows_b.size > qp.max_coord_rows:
            # More rows than the QP was assembled for (a crowd of neighbours and grown
            # hazard discs): the QP takes the most binding ones, the slack at c_i being
            # how far each may move ȳ, and its solution must meet the rest too.
            order = np.argsort(rows_n @ c_i - rows_b, kind="stable")
            keep, rest = order[: qp.max_coord_rows], order[qp.max_coord_rows :]
            over = (rows_n[rest], rows_b[rest])
            rows_n, rows_b = rows_n[keep], rows_b[keep]
            self.counters.row_overflows += 1
        data = StepData(
            x=x,
            x_ref=self.x_ref,
            y_ref=self.y_ref,
            goal=self.target,
            y_box=self.y_box,
            pos_box=self.pos_box,
            coord_normals=rows_n,
            coord_bounds=rows_b,
            penalty_H=None if pen is None else pen[0],
            penalty_g=None if pen is None else pen[1],
            z_f=design.Z_f_ahead if predicted else None,
        )
        prob = qp.problem(data)
        cand = self.candidate()
        cand_violation = TubeQP.violation(prob, cand)
        res = qp.solve(prob, cand)
        status = res.status
        if res.ok and self.solver_fault is not None and self.solver_fault(self.k):
            res.ok, res.xi, status = False, None, "INJECTED_FAULT"
        if res.ok and res.xi is not None and over is not None:
            y_sol = self._repair(res.xi[qp.iy].copy(), data, prob)
            if np.any(over[0] @ y_sol < over[1] - 1e-12):
                res.ok, res.xi, status = False, None, "ROW_OVERFLOW_VIOLATED"
        ctr = self.counters
        ctr.solves += 1
        ctr.status_counts[status] = ctr.status_counts.get(status, 0) + 1
        if res.ok and res.xi is not None:
            xi = res.xi
            fallback = False
        else:
            ctr.failures += 1
            ctr.fallbacks += 1
            xi = cand
            fallback = True
        if not fallback:
            y_sol = xi[qp.iy].copy()
            xi[qp.iy] = self._repair(y_sol, data, prob)
            # Keep the terminal equality exact: x̂_{t+N} moves by B·K_r·E·Δȳ
            # when v̂_{t+N−1} moves by K_r·E·Δȳ, which is what x̃_{t+N}(ȳ) needs.
            xi[qp.iv.stop - 2 : qp.iv.stop] += design.K_r @ design.E @ (xi[qp.iy] - y_sol)
        x_hat = xi[0:4]
        tube_ok = design.contains_error(x - x_hat, tol=TUBE_TOL, ahead=predicted)
        if not tube_ok:
            ctr.tube_exits += 1
        self.xi = xi
        a = self.ancillary(x)
        self._append(xi[qp.iy])
        plan = (qp.S_pos @ xi).reshape(self.N + 1, 2)
        self.k += 1
        self._age_phase()
        nxt = self.candidate()
        return StepOutput(
            a=a,
            committed=self.y_ref.copy(),
            plan=plan,
            x_hat=x_hat.copy(),
            status=status,
            fallback=fallback,
            solve_time=res.solve_time,
            step_time=time.perf_counter() - t0,
            candidate_violation=cand_violation,
            tube_ok=tube_ok,
            min_slack=min_slack if math.isfinite(min_slack) else math.inf,
            target=np.asarray(self.target, dtype=float).copy(),
            mode=mode,
            iterations=res.iterations,
            x_next=nxt[0:4].copy(),
            v_next=nxt[qp.iv].reshape(self.N, 2),
            hazards=tuple(hazards),
            blocked=blocked,
            no_room=self.nav.no_room,
        )

    def _static(self, hazards: Sequence[Hazard], neighbours: Sequence[NeighbourInfo]) -> str:
        """Hand the static discs (robots off their plans for good) to the navigator, which plans
        around them, and say which one covers the goal, if any: the hazard row keeps ȳ at least
        r_i + its radius from its centre, so a goal closer than that cannot be reached while that
        robot stands there.  The navigator then steers to the nearest point it may park at, clear
        of them and as far from the other robots' goals as goals must be apart (:attr:`parking`)."""
        static = [(h.centre, self.r + h.radius) for h in hazards if h.static]
        # A robot whose agent is gone goes nowhere: nobody need wait for it to park.  (A braked
        # or blind one starts again where it is: it is still waited for.)
        self.seen_past.update(h.id for h in hazards if h.kind == "dead")
        self._discs_changed = self.nav.set_discs(static)
        for h in hazards:
            if h.static and math.hypot(*(self.goal - h.centre)) < self.r + h.radius:
                others = [*neighbours, *(x.info for x in hazards if x.info is not None)]
                goals = [
                    (nb.goal, self.r + nb.footprint + GOAL_MARGIN) for nb in others if nb.goal is not None
                ]
                self.parking = self.nav.clear_goal(self.goal, goals)
                return h.id
        self.parking = None
        return ""

    def hold(self, x: Array, status: str = BLIND) -> StepOutput:
        """A step without a usable measurement, or whose commands cannot reach the robot: hold,
        commit nothing new.

        ``x`` (4,) [m, m/s] is the predicted state.  No QP is built: the shifted
        candidate is applied and "stay put" appended (the references already
        committed stay valid for the neighbours), and the command brakes the
        predicted velocity to rest at up to ``a_max`` per axis [m/s²].  ``status`` says why:
        :data:`~ground.wire.BLIND` (no poses) or :data:`~ground.wire.LINK_DOWN` (the robot's
        radio link is down; it drives on uncontrolled, and is not counted as a blind hold)."""
        t0 = time.perf_counter()
        self._snapshot()
        p, qp = self.params, self.qp
        cand = self._take_candidate()
        a = brake_input(np.asarray(x)[[1, 3]], p.Ts, p.a_max)
        if status == LINK_DOWN:
            self.counters.uncontrolled += 1
        else:
            self.counters.holds += 1
        self.k += 1
        self._age_phase()
        nxt = self.candidate()
        return StepOutput(
            a=a, committed=self.y_ref.copy(), plan=(qp.S_pos @ cand).reshape(self.N + 1, 2),
            x_hat=cand[0:4].copy(), status=status, fallback=True, solve_time=0.0,
            step_time=time.perf_counter() - t0, candidate_violation=0.0, tube_ok=True, min_slack=math.inf,
            target=np.asarray(self.target, dtype=float).copy(), mode="hold", x_next=nxt[0:4].copy(),
            v_next=nxt[qp.iv].reshape(self.N, 2),
        )  # fmt: skip

    def rewind(self, unapplied: int, coasted: int = 0) -> bool:
        """The robot side did not apply the commands of the last ``unapplied`` steps of
        this controller, nor had any for ``coasted`` steps after them: it followed the
        shifted candidate of the last command it applied (:func:`chain_input`).  Undo
        those steps and take that candidate ``unapplied + coasted`` times, as it did.

        Afterwards the committed reference is what the robot executed: "stay put"
        appended at each of those steps, so neighbours that kept clear of the last
        executed plan (as a stale one) stay clear.  Returns False, changing nothing, if
        the state before those steps is no longer kept (more than SNAPSHOTS steps)."""
        if unapplied < 0 or coasted < 0 or unapplied > len(self._history):
            return False
        if unapplied:
            xi, y_ref, x_ref = self._history[-unapplied]
            del self._history[-unapplied:]
            self.xi, self.y_ref, self.x_ref = xi, y_ref, x_ref
        for _ in range(unapplied + coasted):
            self._snapshot()
            self._take_candidate()
        self.counters.unapplied += unapplied + coasted
        return True

    def _take_candidate(self) -> Array:
        """Apply the shifted candidate as this step's plan (append "stay put")."""
        cand = self.candidate()
        self.xi = cand
        self._append(cand[self.qp.iy])
        return cand

    def _snapshot(self) -> None:
        """Keep the state before this step (for :meth:`rewind`)."""
        self._history.append((self.xi, self.y_ref, self.x_ref))
        if len(self._history) > SNAPSHOTS:
            del self._history[0]

    def _repair(self, ybar: Array, data: StepData, prob: dict[str, Array]) -> Array:
        """ȳ made to meet every coordination row exactly, inside the QP's own box for it (``prob``,
        :meth:`agent.qp.TubeQP.problem`: the ε box about c_i clipped to the arena)
        (:func:`agent.coordination.repair_point`): projected, or the step scaled if that fails."""
        if data.coord_bounds.size == 0:
            return ybar
        iy = self.qp.iy
        y, scaled = repair_point(
            ybar, self.last_point, data.coord_normals, data.coord_bounds, prob["l_box"][iy], prob["u_box"][iy]
        )
        if y is not ybar:
            self.counters.repairs += 1
            self.counters.scaled_repairs += scaled
        return y

    def _append(self, ybar: Array) -> None:
        """Append ȳ = ỹ_{t+N}, advance the reference generator, drop index t."""
        d = self.design
        x_last = self.x_ref[-1]
        u_last = -d.K_r @ (x_last - d.E @ ybar)
        x_new = d.A @ x_last + d.B @ u_last
        self.x_ref = np.vstack([self.x_ref[1:], x_new])
        self.y_ref = np.vstack([self.y_ref[1:], ybar])
