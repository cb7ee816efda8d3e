"""``fleet goal``: give a running agent a new goal and wait until it takes it; ``fleet stop``:
end a served fleet's run (:func:`stop_fleet`).

The operator's session connects to the fleet's hub (``fleet run --listen``), waits for the
robot's liveliness token (the readiness signal) and for the robots' plans, checks the goal by
the one goal rule (:func:`ground.scenario.goal_problem`): against the scenario's walls and
obstacles with the footprint the robot's plan carries, for a passage from the robot's committed
point and against the neighbours' current goals (the agent checks it again), then publishes it on
``fleet/<fleet>/goal/<id>`` until a plan of that robot carries it.  A goal outside the arena or
inside an obstacle is refused before anything is opened.
"""

from __future__ import annotations

import time
from functools import partial

import numpy as np

from ground.scenario import ConfigError, goal_problem, load_scenario
from ground.wire import SCRIPT, Goal, Keys, Plan, Script, Tick
from transport.bus import Inbox, join_session

RESEND = 0.5
"""Seconds between re-publications of a goal until the agent acknowledges it, and of a stop
request until the fleet stops [s]."""
TRACKER = "tracker"
"""The sender of the clock's ticks."""


def send_goal(
    scenario: str, robot: str, goal: tuple[float, float], connect: list[str], fleet: str, timeout: float,
    zenoh_config: str | None = None,
) -> tuple[int, str]:  # fmt: skip
    """Send ``goal`` (x, y) [m, world frame] to ``robot``; (exit code, one line).

    ``connect``: the hub's endpoints (peer-to-peer on loopback), or
    ``zenoh_config``: a JSON5 file, such as deploy/operator.json5 for the
    secure deployment (the operator's certificate may give goals and publish
    nothing else).
    Exit 2: bad input (the line names the field); 1: the robot is not up, did
    not take the goal within ``timeout`` [s], a neighbour parks too close, or a live
    neighbour sent no plan (its goal travels in it) within ``timeout``: nothing is sent
    then, since the goal could not be checked against that neighbour's."""

    scn = load_scenario(scenario)
    ids = [r.id for r in scn.robots]
    if robot not in ids:
        raise ConfigError("--robot", f"{robot!r} is not in the scenario (robots: {', '.join(ids)})")
    target = np.array(goal, dtype=float)
    problem = goal_problem(scn, 0.0, target, [])  # a point: finite, in the arena, outside every obstacle
    if problem is not None:  # refused before anything is opened
        raise ConfigError("goal", problem)
    keys = Keys(fleet)
    session = join_session(connect, zenoh_config)
    where = zenoh_config or ", ".join(connect)
    inbox = Inbox(keys, "operator")
    subs = [inbox.subscribe(session, keys.plan(), Plan), inbox.watch_liveliness(session)]
    try:
        if not inbox.wait(lambda: robot in inbox.live, timeout):
            return 1, f"{robot} is not alive on {where} within {timeout:g} s"
        # The neighbours' current goals travel in their plans: wait for one from every live robot.
        inbox.wait(lambda: all(inbox.get(Plan, r) is not None for r in ids if r in inbox.live), timeout)
        with inbox.cond:
            own = inbox.get(Plan, robot)
            plans = [p for r in ids if r != robot and (p := inbox.get(Plan, r)) is not None]
            unheard = [r for r in ids if r != robot and r in inbox.live and inbox.get(Plan, r) is None]
        if own is None:
            return 1, f"{robot} sent no plan within {timeout:g} s"
        if unheard:  # checked against some goals only, a goal on theirs would go out and be refused
            return 1, (
                f"no plan from {', '.join(unheard)} within {timeout:g} s: the goal cannot be checked "
                f"against {'its goal' if len(unheard) == 1 else 'their goals'}; nothing sent"
            )
        problem = goal_problem(scn, own.footprint, target, [])
        if problem is not None:  # the walls and obstacles, with the robot's own footprint
            raise ConfigError("goal", problem)
        problem = goal_problem(scn, own.footprint, target, plans, at=own.committed[-1])
        if problem is not None:
            return 1, f"goal rejected: {problem}"
        pub = session.declare_publisher(keys.goal(robot))
        payload = Goal(robot=robot, goal=target).encode()
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            pub.put(payload)
            if inbox.wait(partial(_carries, inbox, robot, target), min(RESEND, deadline - time.monotonic())):
                plan = inbox.get(Plan, robot)
                assert plan is not None
                return 0, f"{robot} took goal ({target[0]:.3f}, {target[1]:.3f}) at step {plan.step}"
            if robot not in inbox.live:
                return 1, f"{robot} left the fleet before taking the goal"
        return 1, f"{robot} did not take the goal within {timeout:g} s (see its log for the reason)"
    finally:
        for s in subs:
            s.undeclare()
        session.close()


def _carries(inbox: Inbox, robot: str, goal: np.ndarray) -> bool:
    plan = inbox.get(Plan, robot)
    return plan is not None and bool(np.array_equal(plan.goal, goal))


def stop_fleet(
    connect: list[str], fleet: str, timeout: float, zenoh_config: str | None = None
) -> tuple[int, str]:
    """``fleet stop``: ask a served fleet (``fleet run --serve``) to end its run; (exit code, one
    line).  The operator's session joins the hub as :func:`send_goal`'s does, waits for the
    fleet's clock (the readiness signal: a fleet is running there), then publishes a stop request
    (a :class:`ground.wire.Script` with ``stop``) every :data:`RESEND` s until the tracker's stop
    tick comes.  Exit 1: no clock, or no stop, within ``timeout`` [s] (a fleet that is not served
    does not listen for stop requests: it ends at its duration, or on Ctrl-C)."""
    keys = Keys(fleet)
    session = join_session(connect, zenoh_config)
    where = zenoh_config or ", ".join(connect)
    inbox = Inbox(keys, "operator")
    subs = [inbox.subscribe(session, keys.clock, Tick)]
    try:
        if not inbox.wait(partial(_ticking, inbox, False), timeout):
            return 1, f"no fleet's clock on {where} within {timeout:g} s"
        pub = session.declare_publisher(keys.script)
        payload = Script(robot=SCRIPT, step=-1, stop=True).encode()
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            pub.put(payload)
            if inbox.wait(partial(_ticking, inbox, True), min(RESEND, deadline - time.monotonic())):
                tick = inbox.get(Tick, TRACKER)
                assert tick is not None
                return 0, f"the fleet on {where} stopped at step {tick.step}"
        return 1, f"the fleet on {where} did not stop within {timeout:g} s (is it served: fleet run --serve?)"
    finally:
        for s in subs:
            s.undeclare()
        session.close()


def _ticking(inbox: Inbox, stopped: bool) -> bool:
    """A tick has come (``stopped``: the stop tick)."""
    tick = inbox.get(Tick, TRACKER)
    return tick is not None and (tick.stop or not stopped)
