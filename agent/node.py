"""The agent process: a thin Zenoh shell around :class:`agent.controller.TubeMPC`.

``python -m agent --scenario S --robot ID [--fleet F] [--connect E] [--listen E]``

Lockstep protocol (docs/runtime-notes.md): at step k the agent waits for the
tracker's tick k, its own pose and odometry of step k and the plans that the
live neighbours committed at step k−1 (liveliness says who is live; every
wait is bounded).  It then steps the controller and publishes its plan and
its command for step k.  A neighbour whose plan of step k−1 does not arrive in
time is used with its last known plan, and the event is counted.
"""

from __future__ import annotations

import argparse
import sys
from functools import partial
from typing import Any

import numpy as np

from agent.controller import TubeMPC
from agent.coordination import NeighbourInfo
from agent.models import measured_state
from fleet.runtime import Inbox, add_common_args, announce, load_validated, log, open_session, publisher
from fleet.scenario import ConfigError, check_point, controlled_point
from fleet.wire import Command, Goal, Keys, Odom, Plan, Pose, Tick


def _neighbour(plan: Plan) -> NeighbourInfo:
    return NeighbourInfo(
        id=plan.robot,
        last_point=plan.committed[-1].copy(),
        footprint=plan.footprint,
        priority=plan.priority,
        rank=plan.rank,
        target=plan.target.copy(),
        goal=plan.goal.copy(),
        phase=plan.phase,
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m agent", description=__doc__.splitlines()[0])
    add_common_args(ap)
    ap.add_argument("--robot", required=True, help="robot id from the scenario")
    args = ap.parse_args(argv)
    role = f"agent {args.robot}"
    try:
        scn, design = load_validated(args.scenario)
        ids = [r.id for r in scn.robots]
        if args.robot not in ids:
            raise ConfigError("--robot", f"{args.robot!r} is not in the scenario (robots: {', '.join(ids)})")
    except ConfigError as e:
        print(f"agent: error: {e}", file=sys.stderr)
        return 2
    rank = ids.index(args.robot)
    spec = scn.robots[rank]
    p = design.params
    ctrl = TubeMPC(
        design,
        controlled_point(spec.start, p.lookahead),
        np.array(spec.goal, dtype=float),
        scn.arena,
        obstacles=scn.obstacles,
        priority=spec.priority,
        rank=rank,
        seed=scn.simulation.seed * 1000 + rank,
    )
    keys = Keys(args.fleet)
    me = args.robot
    session = open_session(args)
    inbox = Inbox(keys, role)
    subs = [
        inbox.subscribe(session, keys.pose(me), Pose, keep=True),
        inbox.subscribe(session, keys.odom(me), Odom, keep=True),
        inbox.subscribe(session, keys.plan(), Plan, keep=True, remote=True),
        inbox.subscribe(session, keys.goal(me), Goal),
        inbox.subscribe(session, keys.clock, Tick),
        inbox.watch_liveliness(session),
    ]
    pub_plan = publisher(session, keys.plan(me))
    pub_cmd = publisher(session, keys.cmd(me))
    token = session.liveliness().declare_token(keys.alive(me))
    announce("agent", robot=me)
    stale = 0
    k = 0
    goal_seen: Goal | None = None
    try:
        while True:
            if not inbox.wait(partial(_tick_at_least, inbox, k), args.timeout):
                log(role, f"no tick {k} within {args.timeout} s; stopping")
                return 1
            tick = inbox.get(Tick, "tracker")
            assert tick is not None
            if tick.stop:
                break
            if not inbox.wait(partial(_measured, inbox, me, k), args.timeout):
                log(role, f"no pose/odometry for step {k}; stopping")
                return 1
            others = [r for r in ids if r != me]
            if k > 0:
                # Realtime: the neighbours' plans must not hold up this step's deadline.
                limit = args.timeout if args.clock == "lockstep" else 0.3 * p.Ts
                ok = inbox.wait(partial(_plans_in, inbox, others, k - 1), limit)
                if not ok:
                    stale += 1
            with inbox.cond:
                pose = inbox.get(Pose, me, k)
                odom = inbox.get(Odom, me, k)
                plans = [inbox.get(Plan, j, k - 1) or inbox.get(Plan, j) for j in others]
                goal = inbox.get(Goal, me)
            if goal is not None and goal is not goal_seen:
                goal_seen = goal
                problem = goal_problem(scn, design.footprint, goal.goal, [pl for pl in plans if pl])
                if problem is not None:
                    log(role, f"goal {goal.goal.round(3).tolist()} rejected: {problem}")
                elif not np.array_equal(goal.goal, ctrl.goal):
                    ctrl.set_goal(goal.goal)
                    log(role, f"new goal {goal.goal.round(3).tolist()} at step {k}")
            assert pose is not None and odom is not None
            cam = np.array([pose.x, pose.y, pose.theta])
            x = measured_state(cam, np.array([odom.vx, odom.vy]), p.lookahead)
            nbs = [_neighbour(pl) for pl in plans if pl is not None]
            out = ctrl.step(x, nbs)
            info = ctrl.info()
            # The command first: the robot side waits on it; the neighbours need the
            # plan only at the next step, which cannot start before the robots move.
            pub_cmd.put(Command(robot=me, step=k, ax=float(out.a[0]), ay=float(out.a[1])).encode())
            pub_plan.put(
                Plan(
                    robot=me, step=k, t0=(k + 1) * p.Ts, Ts=p.Ts, committed=out.committed, nominal=out.plan,
                    footprint=design.footprint, priority=spec.priority, rank=rank, phase=info.phase,
                    target=out.target, goal=ctrl.goal, status=out.status, solve_time=out.solve_time,
                    tube_ok=out.tube_ok,
                ).encode()
            )  # fmt: skip
            inbox.prune(k - 2)
            k += 1
    finally:
        c = ctrl.counters
        log(
            role,
            f"stopped after {k} steps: {c.solves} solves, {c.fallbacks} fallbacks, "
            f"{c.tube_exits} tube exits, {stale} late neighbour plans, "
            f"{inbox.rejects.total} rejected payloads",
        )
        token.undeclare()
        for s in subs:
            s.undeclare()
        session.close()
    return 0


def goal_problem(scn: Any, footprint: float, goal: np.ndarray, plans: list[Plan]) -> str | None:
    """Why a goal (2,) [m] given at run time cannot be accepted, or None.

    It must clear the walls and obstacles by the footprint radius [m] and park
    at least the two footprints away from every neighbour's current goal."""
    try:
        check_point(scn, goal, footprint, "goal")
    except ConfigError as e:
        return e.reason
    for pl in plans:
        d = float(np.linalg.norm(goal - pl.goal))
        if d < footprint + pl.footprint:
            need = footprint + pl.footprint
            return f"{d:.3f} m from {pl.robot}'s goal, closer than the footprints allow ({need:.3f} m)"
    return None


def _measured(inbox: Inbox, me: str, k: int) -> bool:
    return inbox.get(Pose, me, k) is not None and inbox.get(Odom, me, k) is not None


def _plans_in(inbox: Inbox, others: list[str], step: int) -> bool:
    """Every live neighbour's plan of ``step`` has arrived."""
    return all(inbox.get(Plan, j, step) is not None for j in others if j in inbox.live)


def _tick_at_least(inbox: Inbox, k: int) -> bool:
    t = inbox.get(Tick, "tracker")
    return t is not None and (t.stop or t.step >= k)
