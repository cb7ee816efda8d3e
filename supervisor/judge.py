"""The one safety judge: what a run did, from ground truth and the plans, and ``summary.json``.

``fleet simulate`` (:mod:`fleet.simulate`) and the supervisor process (:mod:`supervisor.monitor`)
both judge a run with a :class:`Judge`, fed the same two streams step by step:

* :meth:`Judge.truth` — one sample of the robots' true axle-centre poses (the initial one
  included), and the camera's poses of it where there are any: centre distances and
  collisions (two centres closer than two body radii), arena and obstacle violations, each
  controlled point's distance to its goal and the camera's error;
* :meth:`Judge.plans` — one step's plans (:class:`~ground.wire.Plan`) and which of them were
  never executed (the robot side did not apply their command): the separation of the
  references committed at that step, every robot's solver figures, and whether an executed plan
  kept what its predecessor had committed.

:meth:`Judge.summary` turns them into the run's ``summary.json``, the same schema for both;
a field only the in-process simulator can measure (a robot's step time, its realised
disturbance, its shifted candidate's violation) is added by :meth:`Judge.simulated` and absent
from a process run's summary.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np

from ground.bus import remember_steps
from ground.geometry import Array, controlled_point, wrap_angle
from ground.scenario import Scenario, settled_since
from ground.wire import BLIND, Plan

SOLVED = "PROXQP_SOLVED"
"""The one solver status whose plan is a solution; every other status is a fallback."""
SLACK = 1e-9
"""Rounding slack of every distance check [m]."""

Pose3 = Sequence[float] | Array
"""A pose (x [m], y [m], θ [rad]), world frame, (3,)."""


class Judge:
    """The safety figures of one run, updated one sample and one step at a time."""

    def __init__(self, scn: Scenario):
        p = scn.controller
        self.scn = scn
        self.ids = [r.id for r in scn.robots]
        self.Ts = p.Ts
        """Sampling period [s]."""
        self.radius = p.robot_radius
        """Body radius [m]: two true centres closer than two of them collide."""
        self.lookahead = p.lookahead
        """Controlled point ahead of the axle [m] (:mod:`ground.geometry`)."""
        self.goals = {r.id: np.array(r.goal, dtype=float) for r in scn.robots}
        """Each robot's current goal (2,) [m]: a goal changed at run time counts from its plan on."""
        self.footprint: float | None = None
        """The largest footprint radius r_i a plan has carried [m]; None before the first plan."""
        self.min_distance = math.inf
        self.collisions = self.obstacle_violations = self.arena_violations = 0
        self.min_ref = math.inf
        self.ref_violations = 0
        self.steps = 0
        """Steps whose plans were judged."""
        self.skipped_steps = 0
        """Samples whose ground truth was lost on the way, not judged."""
        self.poses: dict[str, list[tuple[float, ...]]] = {r: [] for r in self.ids}
        """True poses per sample."""
        self.errors: dict[str, list[float]] = {r: [] for r in self.ids}
        """Distance of the controlled point to the current goal per sample [m]."""
        self.refs: dict[str, list[Array]] = {
            r.id: [controlled_point(r.start, self.lookahead)] for r in scn.robots
        }
        """The executed committed reference for each sample's time (2,) [m]: at sample 0 the
        start, where every agent's initial reference stays put; then one per step of plans, in
        whatever order the plans and the truths arrive."""
        self.pose_error: dict[str, list[float]] = {r: [0.0, 0.0] for r in self.ids}
        """Largest camera error per robot: [per-axis position [m], heading [rad]]."""
        self.last_plans: dict[str, Plan] = {}
        """The latest executed plan of each robot seen so far."""
        self.unexecuted: dict[str, set[int]] = {r: set() for r in self.ids}
        """Per robot, recent steps whose plan was reported not executed."""
        self.robot: dict[str, dict[str, Any]] = {
            r: {"solves": 0, "failures": 0, "tube_exits": 0, "status": {}, "solve_ms": [], "candidate": 0,
                "braked": 0, "breaks": 0, "blind": 0, "link_losses": 0, "late": 0}
            for r in self.ids
        }  # fmt: skip
        self.extras: dict[str, dict[str, Any]] = {r: {} for r in self.ids}
        """Per robot, the figures only the in-process simulator measures (:meth:`simulated`)."""
        self.repairs: dict[str, int] = {}
        """Per robot, solutions whose ȳ was pulled back onto the coordination rows (the
        in-process simulator reads the controller's counter)."""

    # ------------------------------------------------------------------ inputs
    def truth(self, poses: Mapping[str, Pose3], measured: Mapping[str, Pose3 | None] | None = None) -> None:
        """One sample of true poses, every robot's; ``measured`` (the camera's poses of that
        sample, None where none) feeds the camera-error figures."""
        for r, m in (measured or {}).items():
            if m is not None:
                t, err = poses[r], self.pose_error[r]
                err[0] = max(err[0], abs(m[0] - t[0]), abs(m[1] - t[1]))
                err[1] = max(err[1], abs(wrap_angle(m[2] - t[2])))
        xmin, xmax, ymin, ymax = self.scn.arena
        radius = self.radius
        centres = {r: np.array(poses[r][:2], dtype=float) for r in self.ids}
        for i, a in enumerate(self.ids):
            c = centres[a]
            if not (xmin + radius - SLACK <= c[0] <= xmax - radius + SLACK) or not (
                ymin + radius - SLACK <= c[1] <= ymax - radius + SLACK
            ):
                self.arena_violations += 1
            for ob in self.scn.obstacles:
                if ob.distance(c) < radius - SLACK:
                    self.obstacle_violations += 1
            for b in self.ids[i + 1 :]:
                d = float(np.linalg.norm(c - centres[b]))
                self.min_distance = min(self.min_distance, d)
                if d < 2.0 * radius:
                    self.collisions += 1
            pose = tuple(float(v) for v in poses[a])
            self.poses[a].append(pose)
            pt = controlled_point(pose, self.lookahead)
            self.errors[a].append(float(np.linalg.norm(pt - self.goals[a])))

    def skipped(self) -> None:
        """A sample whose ground truth was lost on the way: not judged."""
        self.skipped_steps += 1

    def plans(self, plans: Mapping[str, Plan], unexecuted: Iterable[str] = ()) -> None:
        """One step's plans.  A robot missing from ``plans`` (dead, or it skipped the step) is
        checked with its last executed plan and not counted as a solve.  A robot in
        ``unexecuted`` made its plan, which counts as a solve, but its robot side did not apply
        the command (:attr:`~ground.wire.Tick.fallback`, :attr:`~ground.wire.Tick.braked`): the
        robot kept to its last executed plan, and that is what is checked."""
        skipped = set(unexecuted)
        k = self.steps
        for r in skipped:
            if r in self.unexecuted:
                remember_steps(self.unexecuted[r], (k,), k)
        executed = {r: pl for r, pl in plans.items() if r not in skipped}
        for r, pl in executed.items():
            prev = self.last_plans.get(r)
            # Checked when every step between was reported unexecuted (a plan lost on its way
            # to the supervisor would look like a break).  A blind agent's robot braked off its
            # reference, which its neighbours stopped relying on: it starts again where it is.
            if (
                prev is not None
                and prev.status != BLIND
                and pl.step > prev.step
                and all(s in self.unexecuted[r] for s in range(prev.step + 1, pl.step))
                and not continues(prev, pl)
            ):
                self.robot[r]["breaks"] += 1
        last = {**self.last_plans, **executed}
        self.last_plans = last
        for pl in plans.values():
            self.footprint = pl.footprint if self.footprint is None else max(self.footprint, pl.footprint)
        for i, a in enumerate(self.ids):
            if a not in last:
                continue
            pa = last[a]
            for b in self.ids[i + 1 :]:
                if b not in last:
                    continue
                pb = last[b]
                d = float(np.linalg.norm(pa.committed[-1] - pb.committed[-1]))
                self.min_ref = min(self.min_ref, d)
                if d < pa.footprint + pb.footprint - SLACK:
                    self.ref_violations += 1
            made = plans.get(a)
            if made is None:
                continue
            st = self.robot[a]
            st["late"] = max(st["late"], made.late)  # the agent's count so far
            st["status"][made.status] = st["status"].get(made.status, 0) + 1
            if made.status == BLIND:  # no measurement, no QP: the robot braked
                st["blind"] += 1
            else:
                st["solves"] += 1
                st["failures"] += made.status != SOLVED
                st["tube_exits"] += not made.tube_ok
                st["solve_ms"].append(made.solve_time * 1e3)
            self.goals[a] = made.goal.copy()
            # The executed reference for the next sample ("stay put" past its end).
            at = min(max(k - pa.step, 0), len(pa.committed) - 1)
            self.refs[a].append(pa.committed[at].copy())
        self.steps += 1

    def link_lost(self, robot: str) -> None:
        """The radio link to ``robot`` was lost: it drove on uncontrolled (no deadman)."""
        if robot in self.robot:
            self.robot[robot]["link_losses"] += 1

    def off_plan(self, robot: str, kind: str) -> None:
        """The robot side did not apply ``robot``'s command of a step: it followed the shifted
        candidate (``kind`` "candidate") or braked ("braked")."""
        if robot in self.robot:
            self.robot[robot][kind] += 1

    def simulated(self, robot: str, step_ms: float, w_ratio: float, candidate_violation: float) -> None:
        """Figures of one step that only the in-process simulator measures: the controller's
        step time [ms], the realised one-step error of the measured state relative to W
        (max_j |w_j| / W_j) and the shifted candidate's constraint violation in the step's QP."""
        ex = self.extras[robot]
        for name, v in (
            ("step_ms", step_ms),
            ("w_ratio", w_ratio),
            ("candidate_violation", candidate_violation),
        ):
            ex.setdefault(name, []).append(float(v))

    # ------------------------------------------------------------------ output
    def reached(self, robot: str) -> bool:
        """The robot has arrived: its controlled point has stayed within the goal tolerance for
        the settle time up to the last sample (:func:`ground.scenario.settled_since`)."""
        return settled_since(self.errors[robot], self.Ts) is not None

    def summary(self, completed: bool, wall_time: float) -> dict[str, Any]:
        """``summary.json`` of the run (see the README's "summary.json")."""
        robots = {r: self._robot_summary(r) for r in self.ids}
        fin = lambda v: v if math.isfinite(v) else None  # noqa: E731
        sim = self.steps * self.Ts
        out: dict[str, Any] = {
            "scenario": self.scn.name,
            "completed": completed,
            "steps": self.steps,
            "sim_time_s": sim,
            "wall_time_s": wall_time,
            "real_time_factor": sim / wall_time if wall_time > 0 else None,
            "min_distance_m": fin(self.min_distance),
            "collision_distance_m": 2.0 * self.radius,
            "collisions": self.collisions,
            "min_reference_separation_m": fin(self.min_ref),
            "required_reference_separation_m": None if self.footprint is None else 2.0 * self.footprint,
            "reference_separation_violations": self.ref_violations,
            "obstacle_violations": self.obstacle_violations,
            "arena_violations": self.arena_violations,
            "all_goals_reached": all(v["reached_goal"] for v in robots.values()),
            "footprint_radius_m": self.footprint,
            "unjudged_steps": self.skipped_steps,
            "places_heard_late": sum(v["places_heard_late"] for v in robots.values()),
            "robots": robots,
        }
        steps_ms = [v for r in self.ids for v in self.extras[r].get("step_ms", [])]
        if steps_ms:
            out["step_time_ms"] = percentiles(steps_ms)
        return out

    def _robot_summary(self, r: str) -> dict[str, Any]:
        err = np.array(self.errors[r]) if self.errors[r] else np.array([math.inf])
        since = settled_since(self.errors[r], self.Ts)
        pts = np.array([controlled_point(q, self.lookahead) for q in self.poses[r]]).reshape(-1, 2)
        st = self.robot[r]
        out: dict[str, Any] = {
            "goal": self.goals[r].tolist(),
            "reached_goal": since is not None,
            "time_to_goal_s": None if since is None else since * self.Ts,
            "final_error_m": float(err[-1]),
            "path_length_m": float(np.linalg.norm(np.diff(pts, axis=0), axis=1).sum()),
            "straight_line_m": float(np.linalg.norm(pts[0] - self.goals[r])) if len(pts) else 0.0,
            "qp_solves": st["solves"],
            "qp_failures": st["failures"],
            "fallbacks": st["failures"],
            "tube_exits": st["tube_exits"],
            "steps_on_candidate": st["candidate"],
            "steps_braked": st["braked"],
            "steps_blind": st["blind"],
            "link_losses": st["link_losses"],
            "places_heard_late": st["late"],
            "reference_breaks": st["breaks"],
            "status_counts": dict(st["status"]),
            "max_reference_deviation_m": self.deviation(r),
            "max_pose_error": {"position_m": self.pose_error[r][0], "heading_rad": self.pose_error[r][1]},
            "solve_time_ms": percentiles(st["solve_ms"]),
        }
        ex = self.extras[r]
        if ex:
            out["step_time_ms"] = percentiles(ex["step_ms"])
            out["max_w_ratio"] = max(ex["w_ratio"], default=0.0)
            out["max_candidate_violation"] = max(ex["candidate_violation"], default=0.0)
        if r in self.repairs:
            out["repairs"] = self.repairs[r]
        return out

    def deviation(self, robot: str) -> float:
        """The largest distance [m] of the robot's true controlled point from the executed
        reference committed for the same time (‖p − ỹ‖, which the tube bounds by ρ)."""
        poses, refs = self.poses[robot], self.refs[robot]
        worst = 0.0
        for pose, ref in zip(poses, refs, strict=False):
            worst = max(worst, float(np.linalg.norm(controlled_point(pose, self.lookahead) - ref)))
        return worst

    def trace_refs(self, samples: int) -> Array:
        """The executed reference of every robot for each of ``samples`` samples, (R, T, 2) [m]
        (NaN where none is known yet)."""
        refs = np.full((len(self.ids), samples, 2), np.nan)
        for i, r in enumerate(self.ids):
            got = np.array(self.refs[r][:samples]).reshape(-1, 2)
            refs[i, : len(got)] = got
        return refs


def verdict(summary: Mapping[str, Any]) -> str | None:
    """Why a run (its ``summary.json``) failed, in one line, or None if it passed: every step
    judged, no collision, every robot at its goal."""
    why = []
    if not summary.get("completed", False):
        why.append(f"only {summary.get('steps', 0)} steps of the run were judged")
    if summary.get("collisions"):
        why.append(f"{summary['collisions']} collision samples")
    missing = [r for r, v in summary.get("robots", {}).items() if not v["reached_goal"]]
    if missing:
        why.append("goal not reached by " + ", ".join(missing))
    return "; ".join(why) or None


def percentiles(values: Iterable[float]) -> dict[str, float]:
    """``{"p50", "p99", "max"}`` of a series (0 for an empty one)."""
    a = np.fromiter(values, dtype=float)
    if a.size == 0:
        a = np.zeros(1)
    return {"p50": float(np.percentile(a, 50)), "p99": float(np.percentile(a, 99)), "max": float(a.max())}


def continues(prev: Plan, plan: Plan) -> bool:
    """``plan`` keeps what ``prev`` committed (a committed reference is never changed, only
    extended): with d = plan.step − prev.step ≥ 1, its references for the times prev had
    committed are prev's, exactly; "stay put" (prev's end point) fills the d − 1 steps between
    whose plans were not executed; only the last point is new.  A robot whose agent started
    again from where it is (restarted, or its robot braked) breaks this, and so would an agent
    and a robot side that disagree on what was executed."""
    d = plan.step - prev.step
    n = prev.committed.shape[0]
    if plan.committed.shape[0] != n or d < 1:
        return False
    kept = max(n - d, 0)
    if not np.array_equal(plan.committed[:kept], prev.committed[d : d + kept]):
        return False
    return bool(np.all(plan.committed[kept : n - 1] == prev.committed[-1]))
