"""In-process closed-loop simulator (the harness of the core issue).

Each step, synchronously:

1. every robot measures its double-integrator state ``x = [px, vx, py, vy]``
   (controlled point, world frame): the camera's pose, off the plant's by
   :class:`PoseNoise`, plus the odometry's velocity (exact in simulation);
2. every agent steps its :class:`agent.controller.TubeMPC` against the
   neighbours' references committed in the *previous* step (the synchronous
   exchange of DESIGN §5);
3. every plant integrates its acceleration for Ts and receives a disturbance
   ``w``; with the pose noise, the measured state's one-step error stays in
   ``f·W`` (``f`` = ``disturbance_fraction``; the rest of W is left for the
   inner loop's discretisation error, which is measured);
4. ground truth is checked: centre distances, collisions, reference
   separation, obstacles, arena, tube membership, ‖p − ỹ‖ ≤ ρ.

Disturbances: ``uniform`` samples the box; ``adversarial`` picks the vertex
that pushes the tube error ``x − x̂`` outward on every component; ``none``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from agent.controller import TUBE_TOL, StepOutput, TubeMPC, chain_input
from agent.models import DoubleIntegratorPlant, UnicyclePlant, make_inner_loop, measured_state
from agent.sets import Array
from agent.tube import TubeDesign, require_admissible, synthesize

GOAL_TOLERANCE = 0.02
"""A goal is reached when the controlled point ends within this distance [m]."""


@dataclass
class RobotTrace:
    """Per-robot record of a run (arrays over steps)."""

    id: str
    pose: list[Array] = field(default_factory=list)
    """Axle-centre pose (x, y, θ) per step, including the initial one."""
    point: list[Array] = field(default_factory=list)
    """Controlled point (2,) per step."""
    committed_last: list[Array] = field(default_factory=list)
    """ỹ_{t+N} appended at each step."""
    goal_error: list[float] = field(default_factory=list)
    step_ms: list[float] = field(default_factory=list)
    solve_ms: list[float] = field(default_factory=list)
    modes: list[str] = field(default_factory=list)
    ref_deviation: list[float] = field(default_factory=list)
    """‖p_{t+1} − ỹ_{t+1}‖ per step [m]."""
    w_ratio: list[float] = field(default_factory=list)
    """max_j |w_j| / W_j of the realised one-step error per step."""
    candidate_violation: list[float] = field(default_factory=list)
    tube_ok: list[bool] = field(default_factory=list)
    fallback: list[bool] = field(default_factory=list)


@dataclass
class RunResult:
    scenario: str
    design: TubeDesign
    traces: dict[str, RobotTrace]
    controllers: dict[str, TubeMPC]
    steps: int
    sim_time: float
    wall_time: float
    min_distance: float
    collisions: int
    min_reference_separation: float
    required_reference_separation: float
    reference_violations: int
    obstacle_violations: int
    arena_violations: int
    pair_distances: dict[str, list[float]]
    times: list[float]

    def robot_summary(self, rid: str) -> dict[str, Any]:
        tr = self.traces[rid]
        ctr = self.controllers[rid].counters
        err = np.array(tr.goal_error)
        reached = bool(err.size and err[-1] <= GOAL_TOLERANCE)
        ttg = None
        if reached:
            bad = np.flatnonzero(err > GOAL_TOLERANCE)
            first = 0 if bad.size == 0 else int(bad[-1]) + 1
            ttg = float(self.times[first + 1])  # goal_error[i] is the state after step i
        st = np.array(tr.step_ms) if tr.step_ms else np.zeros(1)
        sv = np.array(tr.solve_ms) if tr.solve_ms else np.zeros(1)
        return {
            "reached_goal": reached,
            "time_to_goal_s": ttg,
            "final_error_m": float(err[-1]) if err.size else None,
            "qp_solves": ctr.solves,
            "qp_failures": ctr.failures,
            "fallbacks": ctr.fallbacks,
            "tube_exits": ctr.tube_exits,
            "repairs": ctr.repairs,
            "status_counts": dict(ctr.status_counts),
            "max_reference_deviation_m": float(max(tr.ref_deviation, default=0.0)),
            "max_w_ratio": float(max(tr.w_ratio, default=0.0)),
            "max_candidate_violation": float(max(tr.candidate_violation, default=0.0)),
            "step_time_ms": _stats(st),
            "solve_time_ms": _stats(sv),
        }

    @property
    def all_reached(self) -> bool:
        return all(self.robot_summary(r)["reached_goal"] for r in self.traces)

    def summary(self) -> dict[str, Any]:
        robots = {rid: self.robot_summary(rid) for rid in self.traces}
        all_steps = np.concatenate([np.array(t.step_ms) for t in self.traces.values()] or [np.zeros(1)])
        return {
            "scenario": self.scenario,
            "completed": True,
            "steps": self.steps,
            "sim_time_s": self.sim_time,
            "wall_time_s": self.wall_time,
            "real_time_factor": self.sim_time / self.wall_time if self.wall_time > 0 else None,
            "min_distance_m": self.min_distance,
            "collision_distance_m": 2.0 * self.design.params.robot_radius,
            "collisions": self.collisions,
            "min_reference_separation_m": self.min_reference_separation,
            "required_reference_separation_m": self.required_reference_separation,
            "reference_separation_violations": self.reference_violations,
            "obstacle_violations": self.obstacle_violations,
            "arena_violations": self.arena_violations,
            "all_goals_reached": all(r["reached_goal"] for r in robots.values()),
            "footprint_radius_m": self.design.footprint,
            "rho_m": self.design.rho,
            "step_time_ms": _stats(all_steps),
            "robots": robots,
        }


def _stats(a: Array) -> dict[str, float]:
    return {
        "p50": float(np.percentile(a, 50)),
        "p99": float(np.percentile(a, 99)),
        "max": float(np.max(a)),
    }


class Disturbance:
    """Samples the process disturbance w (4,) [m, m/s]; ``kind`` is uniform, adversarial or none.

    Its box is f·W less 2·``point_noise`` on the position axes [m], so that
    w plus the change of the pose noise between two measurements stays in f·W."""

    def __init__(
        self,
        kind: str,
        W: tuple[float, float],
        fraction: float,
        rng: np.random.Generator,
        point_noise: float = 0.0,
    ):
        self.kind = kind
        budget = fraction * np.array([W[0], W[1], W[0], W[1]])
        self.half = np.maximum(budget - 2.0 * point_noise * np.array([1.0, 0.0, 1.0, 0.0]), 0.0)
        self.rng = rng

    def sample(self, tube_error: Array) -> Array:
        if self.kind == "none":
            return np.zeros(4)
        if self.kind == "uniform":
            return self.rng.uniform(-1.0, 1.0, 4) * self.half
        s = np.sign(tube_error)
        zero = s == 0
        s[zero] = self.rng.choice([-1.0, 1.0], size=int(zero.sum()))
        return s * self.half


class PoseNoise:
    """The simulated camera's pose error: a normal with σ = bound/2, clipped to ±bound.

    ``bounds`` = (position per axis [m], heading [rad]).  It draws from its own
    generator, seeded from the run's seed, so the disturbance sequence does
    not depend on it and the tracker process reproduces the harness exactly."""

    def __init__(self, bounds: tuple[float, float], seed: int):
        self.bound = np.array([bounds[0], bounds[0], bounds[1]], dtype=float)
        self.rng = np.random.default_rng([seed, 1])

    def sample(self) -> Array:
        """One pose error (3,): [m, m, rad]."""
        n = self.rng.normal(0.0, 0.5, 3) * self.bound
        return np.clip(n, -self.bound, self.bound)


def measure(plant: UnicyclePlant | DoubleIntegratorPlant, noise: PoseNoise, lookahead: float) -> Array:
    """One measurement of ``plant``: its state (4,) as the agent sees it, from a
    noisy camera pose and exact odometry (the tracker publishes the same)."""
    pose = plant.pose + noise.sample()
    return measured_state(pose, plant.state()[[1, 3]], lookahead)


def make_plant(kind: str, start: Array, design: TubeDesign) -> UnicyclePlant | DoubleIntegratorPlant:
    p = design.params
    if kind == "double_integrator":
        return DoubleIntegratorPlant(start, design.A, design.B, lookahead=p.lookahead)
    return UnicyclePlant(start, make_inner_loop(p.lookahead, p.v_min), p.wheel)


def _unapplied(
    ctrl: TubeMPC, design: TubeDesign, applied: tuple[int, StepOutput | None], k: int, x: Array,
    a_prev: Array, policy: str,
) -> tuple[Array, Array]:  # fmt: skip
    """The robot side's acceleration (2,) [m/s²] when the command of step k is not
    applied, and the nominal state x̂ (4,) the tube error is then measured from."""
    if policy == "hold":
        return a_prev, ctrl.xi[0:4].copy()
    j, out = applied
    a = (
        None
        if out is None
        else chain_input(out.x_next, out.v_next, k - j - 1, x, design.A, design.B, design.K)
    )
    if a is None or not ctrl.rewind(1):
        ctrl.reset(x[[0, 2]])  # nothing to follow: braked; the agent starts again where it is
        return np.clip(-x[[1, 3]] / design.params.Ts, -design.params.a_max, design.params.a_max), x.copy()
    return a, ctrl.xi[0:4].copy()


def run(
    scenario: Any,
    seed: int | None = None,
    design: TubeDesign | None = None,
    steps: int | None = None,
    stop_when_done: bool = True,
    solver_fault: Callable[[str, int], bool] | None = None,
    extra_disturbance: Callable[[str, int], Array | None] | None = None,
    late: Callable[[str, int], bool] | None = None,
    late_policy: str = "candidate",
) -> RunResult:
    """Run ``scenario`` (a :class:`fleet.scenario.Scenario`) closed loop.

    ``solver_fault(robot_id, step)`` returning True makes that solve count as
    failed (fault injection).  ``extra_disturbance(robot_id, step)`` may return
    an extra w (4,) that is added on top of the sampled one (to leave W).

    ``late(robot_id, step)`` returning True makes that step's command miss its
    deadline: the robot side does not apply it.  With ``late_policy="candidate"``
    it applies the ancillary law on the shifted candidate of the last command it
    applied (:func:`agent.controller.chain_input`; braking once that is used up)
    and the controller rewinds to it (:meth:`TubeMPC.rewind`), as the runtime
    does; ``"hold"`` holds the previous acceleration and tells nobody (the
    runtime before the candidate fallback, for comparison)."""
    if late_policy not in ("candidate", "hold"):
        raise ValueError(f"late_policy: {late_policy!r} is not 'candidate' or 'hold'")
    t_wall = time.perf_counter()
    sim = scenario.simulation
    seed = sim.seed if seed is None else seed
    rng = np.random.default_rng(seed)
    if design is None:
        design = require_admissible(synthesize(scenario.controller, scenario.arena))
    p = design.params
    Ts = p.Ts
    n_steps = steps if steps is not None else round(scenario.duration / Ts)
    dist = Disturbance(sim.disturbance, p.W, sim.disturbance_fraction, rng, p.point_noise)
    noise = PoseNoise(p.pose_noise, seed)
    W4 = np.array([p.W[0], p.W[1], p.W[0], p.W[1]])
    robots = list(scenario.robots)
    plants, ctrls, traces, meas = {}, {}, {}, {}
    applied: dict[str, tuple[int, StepOutput | None]] = {}
    """Per robot: the step and output of the last command its robot side applied."""
    last_a: dict[str, Array] = {}
    for rank, rb in enumerate(robots):
        plant = make_plant(sim.plant, np.array(rb.start, dtype=float), design)
        start_pt = plant.state()[[0, 2]]
        fault = None
        if solver_fault is not None:
            fault = (lambda rid: lambda k: solver_fault(rid, k))(rb.id)
        ctrls[rb.id] = TubeMPC(
            design,
            start_pt,
            np.array(rb.goal, dtype=float),
            scenario.arena,
            obstacles=scenario.obstacles,
            priority=rb.priority,
            rank=rank,
            seed=seed * 1000 + rank,
            solver_fault=fault,
        )
        plants[rb.id] = plant
        applied[rb.id] = (-1, None)
        last_a[rb.id] = np.zeros(2)
        meas[rb.id] = measure(plant, noise, p.lookahead)
        tr = RobotTrace(rb.id)
        tr.pose.append(plant.pose.copy())
        tr.point.append(start_pt)
        traces[rb.id] = tr
    ids = [rb.id for rb in robots]
    radius = p.robot_radius
    xmin, xmax, ymin, ymax = scenario.arena
    pair_names = [f"{a}-{b}" for i, a in enumerate(ids) for b in ids[i + 1 :]]
    pair_d: dict[str, list[float]] = {n: [] for n in pair_names}
    times = [0.0]
    min_dist = math.inf
    min_ref = math.inf
    collisions = ref_viol = obs_viol = arena_viol = 0
    required = 2.0 * design.footprint

    def check_truth() -> None:
        nonlocal min_dist, collisions, obs_viol, arena_viol
        centres = {rid: plants[rid].pose[:2] for rid in ids}
        for i, a in enumerate(ids):
            ca = centres[a]
            if not (xmin + radius - 1e-9 <= ca[0] <= xmax - radius + 1e-9) or not (
                ymin + radius - 1e-9 <= ca[1] <= ymax - radius + 1e-9
            ):
                arena_viol += 1
            for ob in scenario.obstacles:
                if ob.distance(ca) < radius - 1e-9:
                    obs_viol += 1
            for b in ids[i + 1 :]:
                d = float(np.linalg.norm(ca - centres[b]))
                pair_d[f"{a}-{b}"].append(d)
                min_dist = min(min_dist, d)
                if d < 2.0 * radius:
                    collisions += 1

    check_truth()
    k = 0
    for k in range(n_steps):
        infos = {}
        for rid in ids:
            inf = ctrls[rid].info()
            inf.id = rid
            infos[rid] = inf
        outs = {}
        for rid in ids:
            x = meas[rid]
            nbs = [infos[j] for j in ids if j != rid]
            out = ctrls[rid].step(x, nbs)
            outs[rid] = (x, out)
        for rid in ids:
            x, out = outs[rid]
            plant = plants[rid]
            a, x_hat = out.a, out.x_hat
            if late is not None and late(rid, k):
                a, x_hat = _unapplied(ctrls[rid], design, applied[rid], k, x, last_a[rid], late_policy)
            else:
                applied[rid] = (k, out)
            last_a[rid] = a
            plant.step(a, Ts)
            w = dist.sample(x - x_hat)
            if extra_disturbance is not None:
                extra = extra_disturbance(rid, k)
                if extra is not None:
                    w = w + extra
            plant.perturb(w)
            xn = plant.state()
            meas[rid] = measure(plant, noise, p.lookahead)
            w_real = meas[rid] - (design.A @ x + design.B @ a)
            tr = traces[rid]
            tr.w_ratio.append(float(np.max(np.abs(w_real) / W4)))
            tr.pose.append(plant.pose.copy())
            pt = xn[[0, 2]]
            tr.point.append(pt)
            tr.committed_last.append(ctrls[rid].y_ref[-1].copy())
            tr.goal_error.append(float(np.linalg.norm(pt - ctrls[rid].goal)))
            tr.step_ms.append(out.step_time * 1e3)
            tr.solve_ms.append(out.solve_time * 1e3)
            tr.modes.append(out.mode)
            tr.ref_deviation.append(float(np.linalg.norm(pt - ctrls[rid].y_ref[0])))
            tr.candidate_violation.append(out.candidate_violation)
            tr.tube_ok.append(
                out.tube_ok if x_hat is out.x_hat else design.contains_error(x - x_hat, TUBE_TOL)
            )
            tr.fallback.append(out.fallback)
        # Reference separation of the points just committed (same time index).
        for i, a in enumerate(ids):
            for b in ids[i + 1 :]:
                d = float(np.linalg.norm(ctrls[a].last_point - ctrls[b].last_point))
                req = ctrls[a].r + ctrls[b].r
                min_ref = min(min_ref, d)
                if d < req - 1e-9:
                    ref_viol += 1
        times.append((k + 1) * Ts)
        check_truth()
        if stop_when_done and all(
            traces[r].goal_error[-1] <= GOAL_TOLERANCE * 0.5 and ctrls[r].at_goal for r in ids
        ):
            break
    n_done = k + 1 if n_steps > 0 else 0
    return RunResult(
        scenario=scenario.name,
        design=design,
        traces=traces,
        controllers=ctrls,
        steps=n_done,
        sim_time=n_done * Ts,
        wall_time=time.perf_counter() - t_wall,
        min_distance=min_dist if math.isfinite(min_dist) else float("inf"),
        collisions=collisions,
        min_reference_separation=min_ref if math.isfinite(min_ref) else float("inf"),
        required_reference_separation=required,
        reference_violations=ref_viol,
        obstacle_violations=obs_viol,
        arena_violations=arena_viol,
        pair_distances=pair_d,
        times=times,
    )
