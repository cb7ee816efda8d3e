"""The supervisor process: live safety monitor from ground truth, and ``summary.json``.

``python -m supervisor --scenario S --out DIR [--fleet F] [--connect E]``

It subscribes to the true poses, the plans and the clock, and for every
step computes, from ground truth: centre distances and collisions (two
centres closer than two body radii), arena and obstacle violations, the
separation of the references committed at that step, and per-robot solver
statistics.  When the tracker's stop tick arrives (or on SIGTERM) it writes
``DIR/summary.json`` with the schema of ``fleet simulate``.  Rerun logging is
a later step of issue 3.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import sys
import time
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from fleet.harness import GOAL_TOLERANCE
from fleet.runtime import Inbox, add_common_args, announce, load_validated, log, open_session, remember_steps
from fleet.scenario import ConfigError
from fleet.trace import Trace, outlines
from fleet.wire import Keys, Plan, Pose, Tick, Truth
from supervisor.recorder import Recorder

STOP_GRACE = 5.0
"""Seconds to wait for the last plans after the stop tick [s]."""
GONE_GRACE = 1.0
"""How long after a robot's liveliness token went its plans may still arrive [s]: Zenoh can
deliver the token's removal before the last plan the agent put (seen at the end of a run)."""


class Monitor:
    """Ground-truth safety figures, updated one step at a time."""

    def __init__(self, scn: Any, footprint: float, lookahead: float, radius: float):
        self.scn = scn
        self.ids = [r.id for r in scn.robots]
        self.goals = {r.id: np.array(r.goal, dtype=float) for r in scn.robots}
        self.lookahead = lookahead
        self.radius = radius
        self.required = 2.0 * footprint
        self.min_distance = math.inf
        self.collisions = self.obstacle_violations = self.arena_violations = 0
        self.min_ref = math.inf
        self.ref_violations = 0
        self.errors: dict[str, list[float]] = {r: [] for r in self.ids}
        self.poses: dict[str, list[tuple[float, float, float]]] = {r: [] for r in self.ids}
        self.refs: dict[str, list[Any]] = {r: [] for r in self.ids}
        self.robot: dict[str, dict[str, Any]] = {
            r: {
                "solves": 0,
                "failures": 0,
                "tube_exits": 0,
                "status": {},
                "solve_ms": [],
                "candidate": 0,
                "braked": 0,
                "breaks": 0,
            }
            for r in self.ids
        }
        self.skipped_steps = 0
        """Steps whose ground truth was lost on the way, not judged."""
        self.last_plans: dict[str, Plan] = {}
        """The latest executed plan of each robot seen so far."""
        self.unexecuted: dict[str, set[int]] = {r: set() for r in self.ids}
        """Per robot, recent steps whose plan the ticks reported not executed."""
        self.pose_error: dict[str, list[float]] = {r: [0.0, 0.0] for r in self.ids}
        """Largest camera error per robot: [per-axis position [m], heading [rad]]."""
        self.steps = 0

    def truth(self, poses: dict[str, Pose], measured: dict[str, Pose | None] | None = None) -> None:
        """Check one step of ground truth; ``measured`` (the camera poses) feeds the pose-error figures."""
        for r, m in (measured or {}).items():
            if m is not None:
                t = poses[r]
                err = self.pose_error[r]
                err[0] = max(err[0], abs(m.x - t.x), abs(m.y - t.y))
                err[1] = max(err[1], abs(math.remainder(m.theta - t.theta, math.tau)))
        xmin, xmax, ymin, ymax = self.scn.arena
        centres = {r: np.array([poses[r].x, poses[r].y]) for r in self.ids}
        for i, a in enumerate(self.ids):
            c = centres[a]
            if not (xmin + self.radius - 1e-9 <= c[0] <= xmax - self.radius + 1e-9) or not (
                ymin + self.radius - 1e-9 <= c[1] <= ymax - self.radius + 1e-9
            ):
                self.arena_violations += 1
            for ob in self.scn.obstacles:
                if ob.distance(c) < self.radius - 1e-9:
                    self.obstacle_violations += 1
            for b in self.ids[i + 1 :]:
                d = float(np.linalg.norm(c - centres[b]))
                self.min_distance = min(self.min_distance, d)
                if d < 2.0 * self.radius:
                    self.collisions += 1
            th = poses[a].theta
            self.poses[a].append((poses[a].x, poses[a].y, th))
            pt = c + self.lookahead * np.array([math.cos(th), math.sin(th)])
            if not self.refs[a]:
                self.refs[a].append(pt)  # the initial reference stays put at the start
            self.errors[a].append(float(np.linalg.norm(pt - self.goals[a])))

    def plans(self, plans: dict[str, Plan], unexecuted: frozenset[str] | set[str] = frozenset()) -> None:
        """One step of plans.  A robot missing from ``plans`` (dead, or it skipped the
        step) is checked with its last known plan and not counted as a solve.  A robot
        in ``unexecuted`` made its plan, which counts as a solve, but its robot side did
        not apply the command (Tick.fallback, Tick.braked): the robot kept to its last
        executed plan, and that is what is checked."""
        fresh = set(plans)
        made = plans
        executed = {r: pl for r, pl in plans.items() if r not in unexecuted}
        k = self.steps
        for r in unexecuted:
            if r in self.unexecuted:
                remember_steps(self.unexecuted[r], (k,), k)
        for r, pl in executed.items():
            prev = self.last_plans.get(r)
            # Checked when every step between was reported unexecuted by the ticks (a plan
            # lost on its way here would look like a break).
            if (
                prev is not None
                and pl.step > prev.step
                and all(s in self.unexecuted[r] for s in range(prev.step + 1, pl.step))
                and not continues(prev, pl)
            ):
                self.robot[r]["breaks"] += 1
        plans = {**self.last_plans, **executed}
        self.last_plans = plans
        for i, a in enumerate(self.ids):
            if a not in plans:
                continue
            pa = plans[a]
            for b in self.ids[i + 1 :]:
                if b not in plans:
                    continue
                pb = plans[b]
                d = float(np.linalg.norm(pa.committed[-1] - pb.committed[-1]))
                self.min_ref = min(self.min_ref, d)
                if d < pa.footprint + pb.footprint - 1e-9:
                    self.ref_violations += 1
            if a not in fresh:
                continue
            pa = made[a]
            st = self.robot[a]
            st["solves"] += 1
            st["status"][pa.status] = st["status"].get(pa.status, 0) + 1
            st["failures"] += pa.status != "PROXQP_SOLVED"
            st["tube_exits"] += not pa.tube_ok
            st["solve_ms"].append(pa.solve_time * 1e3)
            self.goals[a] = pa.goal.copy()  # a goal changed at run time counts from here on
            ex = plans.get(a)
            if ex is not None:  # the executed reference for the next step ("stay put" past its end)
                self.refs[a].append(
                    ex.committed[min(max(self.steps - ex.step, 0), len(ex.committed) - 1)].copy()
                )
        self.steps += 1

    def trace(self, Ts: float, footprint: float) -> Trace:
        T = min(len(v) for v in self.poses.values())
        refs = np.full((len(self.ids), T, 2), np.nan)
        for i, r in enumerate(self.ids):
            got = np.array(self.refs[r][:T]).reshape(-1, 2)
            refs[i, : len(got)] = got
        return Trace(
            name=self.scn.name, ids=self.ids, Ts=Ts,
            poses=np.array([self.poses[r][:T] for r in self.ids]).reshape(len(self.ids), T, 3),
            refs=refs, goals=np.array([self.goals[r] for r in self.ids]), footprint=footprint,
            robot_radius=self.radius, arena=tuple(self.scn.arena), obstacles=outlines(self.scn.obstacles),
        )  # fmt: skip

    def summary(self, Ts: float, wall: float, completed: bool) -> dict[str, Any]:
        robots = {}
        for r in self.ids:
            err = np.array(self.errors[r]) if self.errors[r] else np.array([math.inf])
            reached = bool(err[-1] <= GOAL_TOLERANCE)
            ttg = None
            if reached:
                bad = np.flatnonzero(err > GOAL_TOLERANCE)
                ttg = float((0 if bad.size == 0 else int(bad[-1]) + 1) * Ts)
            st = self.robot[r]
            sv = np.array(st["solve_ms"]) if st["solve_ms"] else np.zeros(1)
            robots[r] = {
                "goal": self.goals[r].tolist(),
                "reached_goal": reached,
                "time_to_goal_s": ttg,
                "final_error_m": float(err[-1]),
                "qp_solves": st["solves"],
                "qp_failures": st["failures"],
                "fallbacks": st["failures"],
                "tube_exits": st["tube_exits"],
                "steps_on_candidate": st["candidate"],
                "steps_braked": st["braked"],
                "reference_breaks": st["breaks"],
                "status_counts": st["status"],
                "max_pose_error": {"position_m": self.pose_error[r][0], "heading_rad": self.pose_error[r][1]},
                "solve_time_ms": {
                    "p50": float(np.percentile(sv, 50)),
                    "p99": float(np.percentile(sv, 99)),
                    "max": float(sv.max()),
                },
            }
        fin = lambda v: v if math.isfinite(v) else None  # noqa: E731
        return {
            "scenario": self.scn.name,
            "completed": completed,
            "steps": self.steps,
            "sim_time_s": self.steps * Ts,
            "wall_time_s": wall,
            "min_distance_m": fin(self.min_distance),
            "collision_distance_m": 2.0 * self.radius,
            "collisions": self.collisions,
            "min_reference_separation_m": fin(self.min_ref),
            "required_reference_separation_m": self.required,
            "reference_separation_violations": self.ref_violations,
            "obstacle_violations": self.obstacle_violations,
            "arena_violations": self.arena_violations,
            "all_goals_reached": all(v["reached_goal"] for v in robots.values()),
            "deadline_misses": 0,
            "unjudged_steps": self.skipped_steps,
            "robots": robots,
        }


def continues(prev: Plan, plan: Plan) -> bool:
    """``plan`` keeps what ``prev`` committed (DESIGN §4: a committed reference is never
    changed, only extended): with d = plan.step − prev.step ≥ 1, its references for
    the times prev had committed are prev's, exactly; "stay put" (prev's end point) fills
    the d − 1 steps between whose plans were not executed; only the last point is new.
    A robot whose agent started again from where it is (restarted, or its robot braked)
    breaks this, and so would an agent and a robot side that disagree on what was
    executed."""
    d = plan.step - prev.step
    n = prev.committed.shape[0]
    if plan.committed.shape[0] != n or d < 1:
        return False
    kept = max(n - d, 0)
    if not np.array_equal(plan.committed[:kept], prev.committed[d : d + kept]):
        return False
    return bool(np.all(plan.committed[kept : n - 1] == prev.committed[-1]))


def _run_wall_time(inbox: Inbox, fallback: float) -> float:
    """Wall time of the run [s]: from the arrival of the first ground truth to the
    arrival of the stop tick.  Arrival times are taken in the subscriber
    callbacks, so the figure is the fleet's, not this process's logging backlog."""
    with inbox.cond:
        start = inbox.first.get(Truth.TYPE, fallback)
        tick = inbox.get(Tick, "tracker")
        end = inbox.arrived.get((Tick.TYPE, "tracker")) if tick is not None and tick.stop else None
    return (end if end is not None else time.monotonic()) - start


def _plan_step(inbox: Inbox, ids: list[str], k: int) -> dict[str, Plan] | None:
    """The plans of step k once every robot's is in or will never come: a robot
    whose agent has already sent a later plan (it skipped step k, realtime) or has
    been dead for GONE_GRACE is left out.  None while some plan of step k may
    still arrive, and once no robot has reached step k (every agent gone: nothing
    left to judge).

    Only steps the clock has reached count: a plan is committed after its
    step's tick, so one that claims a later step (a forged or corrupt far-future
    step) neither makes step k judgeable nor marks another step as skipped."""
    tick = inbox.get(Tick, "tracker")
    if tick is None or k > tick.step or (k == tick.step and not tick.stop):
        return None  # the tick of step k + 1 says whose plans of step k were executed
    plans: dict[str, Plan] = {}
    reached = False
    for r in ids:
        pl = inbox.get(Plan, r, k)
        if pl is not None:
            plans[r] = pl
            reached = True
            continue
        latest = inbox.newest(Plan, r, tick.step)
        if latest is not None and latest.step > k:
            reached = True
            continue  # skipped, or its plan of step k was lost
        if (
            r not in inbox.live
            and latest is not None
            and time.monotonic() - inbox.gone.get(r, 0.0) >= GONE_GRACE
        ):
            continue  # dead for a while: no more plans
        return None
    return plans if reached else None


def _step_in(inbox: Inbox, ids: list[str], k: int) -> str:
    """``"in"`` when step k's ground truth is all in and each camera pose is in or
    will not come (a later one arrived; the final step has none); ``"skip"`` when a
    robot's truth of step k will not come (a later one arrived: lost); else ``"wait"``."""

    def later(typ: type[Pose], r: str) -> bool:
        msg = inbox.get(typ, r)
        return msg is not None and msg.seq > k

    missing = [r for r in ids if inbox.get(Truth, r, k) is None]
    if missing:
        return "skip" if all(later(Truth, r) for r in missing) else "wait"
    tick = inbox.get(Tick, "tracker")
    final = tick is not None and tick.stop and k >= tick.step
    if final or all(inbox.get(Pose, r, k) is not None or later(Pose, r) for r in ids):
        return "in"
    return "wait"


def _progress(inbox: Inbox, ids: list[str], k_truth: int, k_plan: int, stopping: dict[str, bool]) -> bool:
    """Something to process: a full step of truth or plans, or SIGTERM."""
    return (
        stopping["signal"]
        or _step_in(inbox, ids, k_truth) != "wait"
        or _plan_step(inbox, ids, k_plan) is not None
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m supervisor", description=__doc__.splitlines()[0])
    add_common_args(ap)
    ap.add_argument("--out", required=True, help="output directory")
    ap.add_argument("--viewer", action="store_true", help="also stream to a live Rerun viewer")
    ap.add_argument(
        "--nice", type=int, default=10,
        help="scheduling niceness increment (default 10): the logger yields the CPU to the control loop",
    )  # fmt: skip
    args = ap.parse_args(argv)
    if args.nice:
        os.nice(args.nice)
    role = "supervisor"
    try:
        scn, design = load_validated(args.scenario)
    except ConfigError as e:
        print(f"supervisor: error: {e}", file=sys.stderr)
        return 2
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    p = design.params
    mon = Monitor(scn, design.footprint, p.lookahead, p.robot_radius)
    keys = Keys(args.fleet)
    session = open_session(args)
    inbox = Inbox(keys, role)
    subs = [
        inbox.subscribe(session, keys.truth(), Truth, keep=True),
        inbox.subscribe(session, keys.pose(), Pose, keep=True),
        inbox.subscribe(session, keys.plan(), Plan, keep=True),
        inbox.subscribe(session, keys.clock, Tick, keep=True),
        inbox.watch_liveliness(session),
    ]
    stopping = {"signal": False}

    def on_term(signum: int, frame: Any) -> None:
        stopping["signal"] = True
        with inbox.cond:
            inbox.cond.notify_all()

    signal.signal(signal.SIGTERM, on_term)
    recorder = Recorder(out / "recording.rrd", scn, design.footprint, design.rho, p.robot_radius, args.viewer)
    token = session.liveliness().declare_token(keys.alive(role))
    announce(role)
    t0 = time.monotonic()
    ids = mon.ids
    k_truth = k_plan = k_tick = 0
    live_seen: set[str] = set()
    ever_live: set[str] = set()
    off_plan: set[str] = set()
    """Robots whose robot side did not apply the last command (to log each episode once)."""
    stop_deadline = 0.0
    completed = False
    try:
        while True:
            inbox.wait(partial(_progress, inbox, ids, k_truth, k_plan, stopping), 0.2)
            # Take the complete steps under the lock; log them outside it, so the
            # Zenoh callbacks are never held up by Rerun.
            truths: list[tuple[dict[str, Any], dict[str, Any]] | None] = []
            plan_steps: list[tuple[dict[str, Plan], set[str]]] = []
            with inbox.cond:
                while (state := _step_in(inbox, ids, k_truth + len(truths))) != "wait":
                    kk = k_truth + len(truths)
                    if state == "skip":
                        truths.append(None)  # lost on the way: this step is not judged
                        continue
                    measured = {r: inbox.get(Pose, r, kk) for r in ids}
                    truths.append(({r: inbox.get(Truth, r, kk) for r in ids}, measured))
                while (step_plans := _plan_step(inbox, ids, kk := k_plan + len(plan_steps))) is not None:
                    # Tick k + 1 says whose plan of step k was not executed (its command missed).
                    t_next = inbox.get(Tick, "tracker", kk + 1)
                    skipped = set() if t_next is None else {*t_next.fallback, *t_next.braked}
                    plan_steps.append((step_plans, skipped))
                newest_tick = inbox.get(Tick, "tracker")
                ticks = [] if newest_tick is None else [
                    t for kk in range(k_tick, newest_tick.step + 1) if (t := inbox.get(Tick, "tracker", kk))
                ]  # fmt: skip
                k_tick = max(k_tick, newest_tick.step + 1) if newest_tick is not None else k_tick
            for item in truths:
                if item is not None:
                    truth, measured = item
                    mon.truth(truth, measured)  # type: ignore[arg-type]
                    recorder.truth(k_truth, p.Ts, truth, measured)  # type: ignore[arg-type]
                else:
                    mon.skipped_steps += 1
                k_truth += 1
            for plans, skipped in plan_steps:
                mon.plans(plans, skipped)
                recorder.plans(k_plan, p.Ts, plans)
                k_plan += 1
            for t in ticks:
                # What the robot side applied over step t.step − 1 (Tick.fallback, .braked).
                for rid, kind in [
                    *((r, "candidate") for r in t.fallback),
                    *((r, "braked") for r in t.braked),
                ]:
                    if rid in mon.robot:
                        mon.robot[rid][kind] += 1
                        if rid not in off_plan:
                            what = "on its shifted candidate" if kind == "candidate" else "braked"
                            recorder.event(
                                f"{rid}: command of step {t.step - 1} not applied; robot {what}", "WARN"
                            )
                now_off = set(t.fallback) | set(t.braked)
                for rid in sorted(off_plan - now_off):
                    recorder.event(f"{rid}: commands applied again from step {t.step - 1}")
                off_plan = now_off
            recorder.flush_if_due()
            if truths or plan_steps:
                stop_deadline = 0.0  # still making progress: the grace period restarts
            with inbox.cond:
                tick = inbox.get(Tick, "tracker")
                live = set(inbox.live)
                inbox.prune(min(k_truth, k_plan) - 1)
            # Who left or came back since the last look: logged outside the lock (above).
            changed = sorted(live ^ live_seen)
            for rid in changed:
                what = "joined" if rid in live else "left"
                recorder.event(f"{rid} {what} the fleet", "INFO" if rid in live else "WARN")
            if tick is None or not tick.stop:  # neither the start nor the end of the run
                for alive, what in ((False, "not alive"), (True, "alive again")):
                    who = [r for r in changed if r in ever_live and (r in live) == alive]
                    if who:
                        verb = "is" if len(who) == 1 else "are"
                        log(role, f"step {k_truth}: {', '.join(who)} {verb} {what}")
            live_seen = live
            ever_live |= live
            if stopping["signal"]:
                break
            if tick is not None and tick.stop:
                # Every step's truth and plans are in, or nothing arrived for a grace
                # period (an agent that died never sends its last plans).
                stop_deadline = stop_deadline or time.monotonic() + STOP_GRACE
                if k_truth > tick.step and k_plan >= tick.step:
                    completed = True
                    break
                if time.monotonic() > stop_deadline:
                    completed = k_truth > tick.step
                    break
    finally:
        summary = mon.summary(p.Ts, _run_wall_time(inbox, t0), completed)
        last_tick = inbox.get(Tick, "tracker")
        summary["deadline_misses"] = 0 if last_tick is None else last_tick.misses
        summary["clock"] = args.clock
        summary["rejected_payloads"] = inbox.rejects.total
        mon.trace(p.Ts, design.footprint).save(out / "trace.npz")
        recorder.close()
        (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
        log(role, f"summary written to {out / 'summary.json'} after {mon.steps} steps")
        token.undeclare()
        for s in subs:
            s.undeclare()
        session.close()
    return 0
