"""``fleet simulate``: the whole fleet in one process, closed loop, step by step.

Each step, synchronously:

1. every robot measures its state ``x = [px, vx, py, vy]`` (controlled point, world frame):
   the camera's pose, off the plant's by :class:`~tracker.world.PoseNoise`, and the
   odometry's velocity (exact in simulation);
2. every agent steps its :class:`agent.controller.TubeMPC` against the neighbours' references
   committed in the *previous* step (the synchronous exchange of docs/method.md §5);
3. every plant integrates its acceleration for Ts and receives a disturbance ``w``
   (:class:`~tracker.world.Disturbance`); with the pose noise, the measured state's one-step
   error stays in ``f·W`` (``f`` = ``disturbance_fraction``; the rest of W is left for the inner
   loop's discretisation error, which is measured);
4. the safety judge (:class:`supervisor.judge.Judge`) takes the true poses and the plans, as
   the supervisor does in a process run.

A fault plan's ``kills`` (``fleet simulate --faults``, :mod:`transport.faults`) kill a robot's agent
at a step: from then on it makes no plan, its robot side brakes its robot (and says so, as the
tick would), and every other agent keeps clear of it as of a dead robot
(:class:`agent.hazards.Guard`), from its first step without that robot's plan.

With ``ahead`` (``fleet simulate --delay-compensation``; docs/method.md §5) step 2 changes: every
robot applies at once the plan its agent made during the step before, ``u = v̂ + K(x − x̂)``,
and the agent then makes its next plan from the prediction ``A x + B u``, with the tube
constraint tightened to Z ⊖ W (``TubeMPC.step(…, predicted=True)``).  A lockstep
``fleet run --delay-compensation`` reproduces it bit for bit.

The plants, the disturbances and the camera noise are the simulated tracker's
(:mod:`tracker.world`), drawn in the same order from the same seeds, so a lockstep
``fleet run`` of the same scenario and seed reproduces this run bit for bit.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from agent.controller import TUBE_TOL, StepOutput, TubeMPC
from agent.coordination import Hazard
from agent.hazards import Guard, starts_of
from agent.protocol import candidate_input, plan_ahead, plan_ahead_message, plan_message
from agent.tube import TubeDesign, require_admissible, synthesize
from ground.arrival import arrival
from ground.geometry import Array, controlled_point
from ground.model import brake_input
from ground.scenario import Scenario, home, settle_samples
from ground.wire import Plan
from supervisor.judge import Judge
from tracker.world import Disturbance, PoseNoise, make_plant, measure

LATE_POLICIES = ("candidate", "hold")
"""What the robot side does with a command that missed its deadline (:func:`run`'s ``late``)."""


@dataclass
class RobotTrace:
    """Per-robot record of a run (lists over steps)."""

    id: str
    pose: list[Array] = field(default_factory=list)
    """Axle-centre pose (x, y, θ) (3,) [m, m, rad] per sample, the initial one included."""
    point: list[Array] = field(default_factory=list)
    """Controlled point (2,) [m] per sample."""
    committed_last: list[Array] = field(default_factory=list)
    """ỹ_{t+N} (2,) [m] appended at each step."""
    goal_error: list[float] = field(default_factory=list)
    """Distance of the controlled point to the goal after each step [m]."""
    modes: list[str] = field(default_factory=list)
    """The navigator's mode at each step."""
    ref_deviation: list[float] = field(default_factory=list)
    """‖p_{t+1} − ỹ_{t+1}‖ per step [m]."""
    w_ratio: list[float] = field(default_factory=list)
    """max_j |w_j| / W_j of the realised one-step error of the measured state, per step."""
    candidate_violation: list[float] = field(default_factory=list)
    """The shifted candidate's constraint violation in each step's QP (0: feasible)."""
    tube_ok: list[bool] = field(default_factory=list)
    """x − x̂ ∈ Z for the x̂ the robot side applied, per step."""
    fallback: list[bool] = field(default_factory=list)
    """The step applied the shifted candidate instead of a solution."""


@dataclass
class RunResult:
    """What :func:`run` returns: the traces, the controllers and the judge's figures."""

    scenario: str
    design: TubeDesign
    judge: Judge
    traces: dict[str, RobotTrace]
    controllers: dict[str, TubeMPC]
    steps: int
    sim_time: float
    """Simulated time [s]."""
    wall_time: float
    """Wall time of the run [s]."""
    times: list[float]
    """Time of each sample [s]."""
    ahead: bool = False
    """The plans were made a step ahead (delay compensation; :class:`Simulation`)."""

    @property
    def min_distance(self) -> float:
        """Smallest distance between two true centres [m]."""
        return self.judge.min_distance

    @property
    def collisions(self) -> int:
        """Samples with two centres closer than two body radii."""
        return self.judge.collisions

    @property
    def min_reference_separation(self) -> float:
        """Smallest distance between two points committed for the same time [m]."""
        return self.judge.min_ref

    @property
    def required_reference_separation(self) -> float:
        """Two footprint radii [m]."""
        return 2.0 * self.design.footprint

    @property
    def reference_violations(self) -> int:
        """Pairs of robots, summed over the steps, whose last committed points
        were closer than the sum of their footprint radii (less the judge's slack)."""
        return self.judge.ref_violations

    @property
    def obstacle_violations(self) -> int:
        """(robot, obstacle) pairs, summed over the samples, whose true centre was
        within a body radius of the obstacle (less the judge's slack)."""
        return self.judge.obstacle_violations

    @property
    def arena_violations(self) -> int:
        """Robots, summed over the samples, whose true centre was within a body radius
        of the arena's walls or beyond them (less the judge's slack)."""
        return self.judge.arena_violations

    @property
    def all_reached(self) -> bool:
        """Every robot arrived at its goal (:meth:`supervisor.judge.Judge.reached`)."""
        return all(self.judge.reached(r) for r in self.traces)

    def summary(self) -> dict[str, Any]:
        """``summary.json`` of the run (:meth:`supervisor.judge.Judge.summary`)."""
        for rid, ctrl in self.controllers.items():
            self.judge.repairs[rid] = ctrl.counters.repairs
        summary = self.judge.summary(completed=True, wall_time=self.wall_time)
        if self.ahead:  # only then: a lockstep fleet run's summary equals the default one's
            summary["delay_compensation"] = True
        return summary


def _unapplied(
    ctrl: TubeMPC, design: TubeDesign, applied: tuple[int, StepOutput | None], k: int, x: Array,
    a_prev: Array, policy: str,
) -> tuple[Array, Array, str]:  # fmt: skip
    """The robot side's acceleration (2,) [m/s²] when the command of step k is not applied,
    the nominal state x̂ (4,) the tube error is then measured from, and what it did: "candidate",
    "braked" or "held" (the previous acceleration, telling nobody)."""
    if policy == "hold":
        return a_prev, ctrl.xi[0:4].copy(), "held"
    j, out = applied
    a = candidate_input(ctrl, out, j, k, x)
    if a is None or not ctrl.rewind(1):
        ctrl.reset(x[[0, 2]])  # nothing to follow: braked; the agent starts again where it is
        p = design.params
        return brake_input(x[[1, 3]], p.Ts, p.a_max), x.copy(), "braked"
    return a, ctrl.xi[0:4].copy(), "candidate"


class Simulation:
    """The whole fleet in one process, one step at a time (see the module docstring).

    ``step()`` runs step k: the judge takes sample k, every agent plans against the references
    its neighbours committed at step k − 1, the plants move to sample k + 1.  Between two steps
    a caller may read the state (:attr:`traces`, :attr:`cams`) and give new goals
    (:meth:`set_goal`), which the agents take at the next step, after the neighbours' view of
    step k − 1 is fixed: as an agent process takes a goal that arrived before its tick.
    :func:`run` is this loop with the early end."""

    def __init__(
        self,
        scenario: Scenario,
        seed: int | None = None,
        design: TubeDesign | None = None,
        solver_fault: Callable[[str, int], bool] | None = None,
        extra_disturbance: Callable[[str, int], Array | None] | None = None,
        late: Callable[[str, int], bool] | None = None,
        late_policy: str = "candidate",
        ahead: bool = False,
        kills: Mapping[str, int] | None = None,
    ):
        if late_policy not in LATE_POLICIES:
            raise ValueError(f"late_policy: {late_policy!r} is not one of {', '.join(LATE_POLICIES)}")
        self.t_wall = time.perf_counter()
        self.scenario = scenario
        sim = scenario.simulation
        self.seed = seed = sim.seed if seed is None else seed
        rng = np.random.default_rng(seed)
        if design is None:
            design = require_admissible(synthesize(scenario.controller, scenario.arena))
        self.design = design
        p = design.params
        self.Ts = p.Ts
        """Sampling period [s]."""
        self.extra_disturbance, self.late, self.late_policy = extra_disturbance, late, late_policy
        self.ahead = ahead
        """Plans made a step ahead (delay compensation, docs/method.md §5): each step applies the
        plan made during the step before, from the prediction, and then makes the next one."""
        if ahead and late_policy != "candidate":
            raise ValueError("late_policy: plans made a step ahead are followed on the candidate only")
        self.dist = Disturbance(sim.disturbance, p.W, sim.disturbance_fraction, rng, p.point_noise)
        self.noise = PoseNoise(p.pose_noise, seed)
        self.W4 = np.array([p.W[0], p.W[1], p.W[0], p.W[1]])
        self.judge = Judge(scenario)
        self.ids = [rb.id for rb in scenario.robots]
        self.plants: dict[str, Any] = {}
        self.ctrls: dict[str, TubeMPC] = {}
        self.traces: dict[str, RobotTrace] = {}
        self.meas: dict[str, Array] = {}
        """Each robot's measured state x (4,) [m, m/s] of the current sample."""
        self.cams: dict[str, Array] = {}
        """Each robot's camera pose (x, y, θ) (3,) [m, m, rad] of the current sample."""
        self.applied: dict[str, tuple[int, StepOutput | None]] = {}
        """Per robot: the step and output of the last command its robot side applied."""
        self.last_a: dict[str, Array] = {}
        self.pending: dict[str, Array] = {}
        """Goals (2,) [m] given since the last step, taken at the next."""
        self.outputs: dict[str, StepOutput] = {}
        """Each robot's controller output of the last step."""
        self.kills = {r: s for r, s in (kills or {}).items() if r in self.ids}
        """Per robot, the step its agent dies at (:mod:`transport.faults`): it makes no plan from then on."""
        self.guards = {rid: Guard(rid, p, lambda _: None) for rid in self.ids}
        """Each agent's view of the robots it keeps clear of as discs (here: the dead ones)."""
        self.starts = starts_of(scenario.robots, p.lookahead, design.footprint)
        self.executed: dict[str, Plan] = {}
        """Each robot's newest plan that its robot side executed."""
        self.braked: set[str] = set()
        """The robots braked by their robot side over the last step (the next tick would say so)."""
        gates = arrival(scenario, design.footprint).gates if p.deadlock else {}
        for rank, rb in enumerate(scenario.robots):
            plant = make_plant(sim.plant, np.array(rb.start, dtype=float), p)
            start_pt = plant.state()[[0, 2]]
            fault = None
            if solver_fault is not None:
                fault = (lambda rid: lambda k: solver_fault(rid, k))(rb.id)
            self.ctrls[rb.id] = TubeMPC(
                design,
                start_pt,
                np.array(rb.goal, dtype=float),
                scenario.arena,
                obstacles=scenario.obstacles,
                priority=rb.priority,
                rank=rank,
                seed=seed * 1000 + rank,
                solver_fault=fault,
                gate=gates.get(rb.id),
            )
            self.plants[rb.id] = plant
            self.applied[rb.id] = (-1, None)
            self.last_a[rb.id] = np.zeros(2)
            self.meas[rb.id], self.cams[rb.id] = measure(plant, self.noise, p.lookahead)
            tr = RobotTrace(rb.id)
            tr.pose.append(plant.pose.copy())
            tr.point.append(start_pt)
            self.traces[rb.id] = tr
        self.times = [0.0]
        self.k = 0
        """The next step; also the number of steps done."""
        self.home_run = 0
        """Consecutive steps after which every robot was home (:func:`ground.scenario.home`)."""
        self.in_force: dict[str, tuple[StepOutput, Plan]] = {}
        """Ahead: each robot's plan for step :attr:`k`, made during the step before (the plan of
        step 0 from the first measurement itself, with the untightened constraint (a), as
        without delay compensation: nothing is predicted yet)."""
        if ahead:
            infos = self._infos()
            for rid in self.ids:
                out = self.ctrls[rid].step(self.meas[rid], [infos[j] for j in self.ids if j != rid])
                self.in_force[rid] = (out, plan_message(rid, 0, self.ctrls[rid], out))

    def set_goal(self, robot: str, goal: Array) -> None:
        """Give ``robot`` the goal (2,) [m], world frame, from the next step on (unchecked: the
        caller checks it, :func:`ground.scenario.goal_problem`)."""
        self.pending[robot] = np.array(goal, dtype=float).reshape(2)

    def step(self) -> None:
        """Step k (:attr:`k`): judge sample k, plan, publish, move to sample k + 1."""
        k, ids, judge, design = self.k, self.ids, self.judge, self.design
        ctrls, traces = self.ctrls, self.traces
        # The sample the agents measure now, as the supervisor judges it: the true poses
        # with the camera's.
        judge.truth({rid: traces[rid].pose[-1] for rid in ids}, self.cams)
        if self.ahead:
            self._step_ahead()
            return
        infos = self._infos()
        self._take_goals()
        gone = self._gone(k)
        poses = self._poses(k)
        outs = {}
        for rid in ids:
            if self._dead(rid, k):
                continue
            x = self.meas[rid]
            nbs = [infos[j] for j in ids if j != rid and j not in gone]
            out = ctrls[rid].step(x, nbs, self._discs(rid, k, gone, poses))
            outs[rid] = (x, out)
            self.outputs[rid] = out
        plans: dict[str, Plan] = {}
        unexecuted: list[str] = []
        braked = set()
        for rid in ids:
            if rid not in outs:  # its agent is dead: its robot side brakes it
                self._brake(rid)
                unexecuted.append(rid)
                braked.add(rid)
                continue
            x, out = outs[rid]
            plans[rid] = plan_message(rid, k, ctrls[rid], out)
            a, x_hat = out.a, out.x_hat
            if self.late is not None and self.late(rid, k):
                a, x_hat, what = _unapplied(
                    ctrls[rid], design, self.applied[rid], k, x, self.last_a[rid], self.late_policy
                )
                if what != "held":  # the robot side says so in the next tick
                    unexecuted.append(rid)
                    judge.off_plan(rid, what)
                if what == "braked":
                    braked.add(rid)
            else:
                self.applied[rid] = (k, out)
                self.executed[rid] = plans[rid]
            self.last_a[rid] = a
            self._move(rid, x, a, x_hat, braked=rid in braked)
            tube_ok = out.tube_ok if x_hat is out.x_hat else design.contains_error(x - x_hat, TUBE_TOL)
            self._record(rid, x, a, out, ctrls[rid].y_ref[0], ctrls[rid].y_ref[-1], tube_ok)
        judge.plans(plans, unexecuted, braked)
        self.braked = braked
        self._end_step()

    def _dead(self, rid: str, k: int) -> bool:
        """The agent of ``rid`` is dead at step k: it makes no plan of step k or later."""
        return self.kills.get(rid, math.inf) <= k

    def _gone(self, k: int) -> set[str]:
        """The robots the others plan step k without: no plan of step k − 1 came from them, and
        their liveliness is gone (their agent died before step k − 1's plan)."""
        return {j for j, s in self.kills.items() if s < k}

    def _poses(self, k: int) -> dict[str, tuple[int, Array]]:
        """The camera's controlled point (2,) [m] of every robot at sample k, with k: what an agent
        watching a stopped robot's poses would have (:attr:`agent.hazards.Guard.watched`)."""
        if not self._gone(k + 1):
            return {}
        ell = self.design.params.lookahead
        return {rid: (k, controlled_point(self.cams[rid], ell)) for rid in self.ids}

    def _discs(self, rid: str, k: int, gone: set[str], poses: dict[str, tuple[int, Array]]) -> list[Hazard]:
        """The discs agent ``rid`` keeps clear of at step k: the robots whose agents are ``gone``,
        as its :class:`~agent.hazards.Guard` classes them from their last executed plans, the
        robot sides' reports of the step before (:attr:`braked`) and the camera's ``poses``."""
        if not gone:
            return []
        others = [j for j in self.ids if j in gone and j != rid]
        live = {j for j in self.ids if j not in gone}
        last: dict[str, Plan | None] = {j: self.executed.get(j) for j in others}
        _, hazards = self.guards[rid].classify(
            k, others, dict.fromkeys(others), last, live, self.starts, self.braked, poses=poses
        )
        return hazards

    def _brake(self, rid: str) -> None:
        """A robot whose agent is dead, over one step: its robot side brakes it
        (:func:`ground.model.brake_input`), and the trace goes on."""
        p, tr, plant = self.design.params, self.traces[rid], self.plants[rid]
        x = self.meas[rid]
        a = brake_input(plant.state()[[1, 3]], p.Ts, p.a_max)
        self.judge.off_plan(rid, "braked")
        self.last_a[rid] = a
        self._move(rid, x, a, x, braked=True)
        tr.w_ratio.append(0.0)
        tr.pose.append(plant.pose.copy())
        pt = plant.state()[[0, 2]]
        tr.point.append(pt)
        tr.committed_last.append(self.ctrls[rid].y_ref[-1].copy())
        tr.goal_error.append(float(np.linalg.norm(pt - self.ctrls[rid].goal)))
        tr.modes.append("dead")
        tr.ref_deviation.append(math.nan)
        tr.candidate_violation.append(0.0)
        tr.tube_ok.append(True)
        tr.fallback.append(False)

    def _step_ahead(self) -> None:
        """Step k with plans made a step ahead (:attr:`ahead`; docs/method.md §5).

        A robot whose plan of step k missed its deadline (``late``) follows the shifted
        candidate of the last plan it applied, and its agent, told so by the tick, drops that
        plan before anyone makes the plans of step k + 1.  Every other robot applies its plan
        of step k to its measurement, u = v̂ + K(x − x̂), at once.  Then each agent makes its
        plan of step k + 1 from the prediction x^p = A x + B u, against the plans of step k in
        force.  The trace and the judge take the plan of step k.  The trace's ``tube_ok`` is
        x_k − x̂_k ∈ Z for the x̂ applied; a plan's is that of the step before its own (the
        plan of step 0: its own, made from the measurement), as the agent process can tell it."""
        k, ids, design, ctrls = self.k, self.ids, self.design, self.ctrls
        applied: dict[str, tuple[Array, Array]] = {}
        unexecuted: list[str] = []
        braked: set[str] = set()
        plans: dict[str, Plan] = {}
        for rid in ids:
            x = self.meas[rid]
            if self._dead(rid, k):  # its robot side brakes it: the plan in force is not applied
                if rid in self.in_force:
                    plans[rid] = self.in_force.pop(rid)[1]
                unexecuted.append(rid)
                braked.add(rid)
            elif self.late is not None and self.late(rid, k):
                a, x_hat, what = _unapplied(
                    ctrls[rid], design, self.applied[rid], k, x, self.last_a[rid], "candidate"
                )
                unexecuted.append(rid)
                self.judge.off_plan(rid, what)
                if what == "braked":
                    braked.add(rid)
                applied[rid] = (a, x_hat)
            else:
                x_hat, a = ctrls[rid].xi[0:4].copy(), ctrls[rid].ancillary(x)
                self.applied[rid] = (k, self.in_force[rid][0])
                self.executed[rid] = self.in_force[rid][1]
                applied[rid] = (a, x_hat)
        infos = self._infos()  # the plans of step k in force, the dropped ones replaced
        self._take_goals()
        gone = {j for j, s in self.kills.items() if s <= k}  # no plan of step k + 1 from them
        poses = self._poses(k)
        for rid in ids:
            if rid not in applied:
                self._brake(rid)
                continue
            ctrl, x = ctrls[rid], self.meas[rid]
            (a, x_hat), (out, plan) = applied[rid], self.in_force[rid]
            ref_next, end = ctrl.y_ref[0].copy(), ctrl.y_ref[-1].copy()
            plans[rid] = plan
            self.outputs[rid] = out
            self.last_a[rid] = a
            nbs = [infos[j] for j in ids if j != rid and j not in gone]
            self.braked = braked  # (what the outcome of step k says, before the plans of k + 1)
            hazards = self._discs(rid, k + 1, gone, poses)
            nxt, tube_ok = plan_ahead(ctrl, x, a, x_hat, nbs, hazards)
            self.in_force[rid] = (nxt, plan_ahead_message(rid, k + 1, ctrl, nxt, tube_ok))
            self._move(rid, x, a, x_hat, braked=rid in braked)
            self._record(rid, x, a, out, ref_next, end, tube_ok)
        self.judge.plans(plans, unexecuted, braked)
        self.braked = braked
        # Home is judged on the plans applied at this step, as without delay compensation.
        self._end_step({rid: (pl.committed[-1], pl.goal, pl.blocked) for rid, pl in plans.items()})

    def _infos(self) -> dict[str, Any]:
        """Every robot's view for its neighbours (its last committed point, …), by id."""
        infos = {}
        for rid in self.ids:
            inf = self.ctrls[rid].info()
            inf.id = rid
            infos[rid] = inf
        return infos

    def _take_goals(self) -> None:
        """Goals given since the last step, taken after the neighbours' view is fixed."""
        for rid, goal in self.pending.items():
            if not np.array_equal(goal, self.ctrls[rid].goal):
                self.ctrls[rid].set_goal(goal)
        self.pending = {}

    def _move(self, rid: str, x: Array, a: Array, x_hat: Array, braked: bool = False) -> None:
        """Robot ``rid``'s plant over one step with acceleration ``a`` (2,) [m/s²], disturbed
        (the adversary pushes x − x̂ outward) unless its robot side ``braked`` it (its wheels
        stop: :meth:`tracker.world.SimulatedWorld.advance`), then measured."""
        plant = self.plants[rid]
        plant.step(a, self.Ts)
        w = self.dist.sample(x - x_hat)
        if self.extra_disturbance is not None:
            extra = self.extra_disturbance(rid, self.k)
            if extra is not None:
                w = w + extra
        if not braked:
            plant.perturb(w)
        self.meas[rid], self.cams[rid] = measure(plant, self.noise, self.design.params.lookahead)

    def _record(
        self, rid: str, x: Array, a: Array, out: StepOutput, ref_next: Array, end: Array, tube_ok: bool
    ) -> None:
        """Trace robot ``rid``'s step: from ``x`` (4,) with ``a`` (2,) applied, ``out`` the
        step's controller output, ``ref_next`` (2,) [m] the reference for the sample reached,
        ``end`` (2,) [m] the end point committed, ``tube_ok`` whether x − x̂ ∈ Z."""
        design, tr, plant = self.design, self.traces[rid], self.plants[rid]
        w_real = self.meas[rid] - (design.A @ x + design.B @ a)
        tr.w_ratio.append(float(np.max(np.abs(w_real) / self.W4)))
        tr.pose.append(plant.pose.copy())
        pt = plant.state()[[0, 2]]
        tr.point.append(pt)
        tr.committed_last.append(np.array(end, dtype=float))
        tr.goal_error.append(float(np.linalg.norm(pt - self.ctrls[rid].goal)))
        tr.modes.append(out.mode)
        tr.ref_deviation.append(float(np.linalg.norm(pt - ref_next)))
        tr.candidate_violation.append(out.candidate_violation)
        tr.tube_ok.append(tube_ok)
        tr.fallback.append(out.fallback)
        self.judge.simulated(rid, out.step_time * 1e3, tr.w_ratio[-1], out.candidate_violation)

    def _end_step(self, applied: dict[str, tuple[Array, Array, str]] | None = None) -> None:
        """Close step k: every robot home (its committed end point parked at its goal and its
        point near it) counts towards the early end, as does one whose goal a stopped robot
        covers (its plan says by whom); a robot whose agent is dead is left out, as the tracker
        leaves it out (it cannot get home).  ``applied``: each robot's end point (2,), goal (2,)
        [m] and blocker of the plan applied at step k, when the controllers hold later ones."""
        ids, ctrls, traces = self.ids, self.ctrls, self.traces
        self.times.append((self.k + 1) * self.Ts)
        out = self.outputs
        ends = applied or {
            r: (ctrls[r].y_ref[-1], ctrls[r].goal, out[r].blocked if r in out else "") for r in ids
        }
        all_home = all(
            self._dead(r, self.k) or ends[r][2] or home(ends[r][0], traces[r].point[-1], ends[r][1])
            for r in ids
            if r in ends or not self._dead(r, self.k)
        )
        self.home_run = self.home_run + 1 if all_home else 0
        self.k += 1

    @property
    def done(self) -> bool:
        """Every robot has been home for :func:`ground.scenario.settle_samples` steps in a row
        (the early end)."""
        return self.home_run >= settle_samples(self.Ts)

    def finish(self) -> RunResult:
        """Judge the final sample (no camera pose used) and return the run."""
        ids, traces = self.ids, self.traces
        self.judge.truth({rid: traces[rid].pose[-1] for rid in ids})
        return RunResult(
            scenario=self.scenario.name,
            design=self.design,
            judge=self.judge,
            traces=traces,
            controllers=self.ctrls,
            steps=self.k,
            sim_time=self.k * self.Ts,
            wall_time=time.perf_counter() - self.t_wall,
            times=self.times,
            ahead=self.ahead,
        )


def run(
    scenario: Scenario,
    seed: int | None = None,
    design: TubeDesign | None = None,
    steps: int | None = None,
    stop_when_done: bool = True,
    solver_fault: Callable[[str, int], bool] | None = None,
    extra_disturbance: Callable[[str, int], Array | None] | None = None,
    late: Callable[[str, int], bool] | None = None,
    late_policy: str = "candidate",
    ahead: bool = False,
    kills: Mapping[str, int] | None = None,
) -> RunResult:
    """Run ``scenario`` closed loop.

    ``solver_fault(robot_id, step)`` returning True makes that solve count as
    failed (fault injection).  ``extra_disturbance(robot_id, step)`` may return
    an extra w (4,) that is added on top of the sampled one (to leave W).

    ``late(robot_id, step)`` returning True makes that step's command miss its
    deadline: the robot side does not apply it.  With ``late_policy="candidate"``
    it applies the ancillary law on the shifted candidate of the last command it
    applied (:func:`epuck_link.robot_side.chain_input`; braking once that is used up)
    and the controller rewinds to it (:meth:`TubeMPC.rewind`), as the process runtime
    does; ``"hold"`` holds the previous acceleration and tells nobody (the
    runtime before the candidate fallback, for comparison).

    ``ahead`` makes every plan a step ahead (delay compensation, docs/method.md §5;
    :class:`Simulation`), as the process runtime does by default.  ``kills``: robot id → the step
    its agent dies at (:mod:`transport.faults`)."""
    sim = Simulation(scenario, seed, design, solver_fault, extra_disturbance, late, late_policy, ahead, kills)
    n_steps = steps if steps is not None else round(scenario.duration / sim.Ts)
    for _ in range(n_steps):
        sim.step()
        if stop_when_done and sim.done:
            break
    return sim.finish()


def save_run(result: RunResult, scenario: Scenario, seed: int, out: Path) -> dict[str, Any]:
    """Write the run's ``trace.npz`` (for ``fleet report``) and ``summary.json`` (with the
    ``seed``) into the directory ``out``; returns the summary."""
    from fleet.running.report import strict_json
    from supervisor.trace import from_simulation

    out.mkdir(parents=True, exist_ok=True)
    from_simulation(result, scenario).save(out / "trace.npz")
    summary = result.summary()
    summary["seed"] = seed
    (out / "summary.json").write_text(json.dumps(strict_json(summary), indent=2) + "\n")
    return summary
