"""Target 3's floor: pose → command latency if a command did not wait for its step's solve.

    python -m benchmarks.bench_latency_floor [--scenario scenarios/swap_16.toml] [--seconds 20] [--runs 2]

An agent today answers the pose of step k only after that step's solve: it waits for its
neighbours' plans of step k − 1, steps its :class:`agent.controller.TubeMPC` and then publishes
the command.  With delay compensation (docs/method.md §5) the command of step k
would be the ancillary law on a plan solved during step k − 1, ``u = v̂ + K(x − x̂)``, published
as soon as the pose is in, and the solve would follow it.  This bench measures what that order
would give on this machine, with everything else the same, side by side with today's order,
and what is left when there is no controller at all:

* ``solve-first`` (today): on its pose of step k, wait (≤ 0.3 Ts) for the neighbours' plans of
  step k − 1, step the controller, publish the command, then the plan;
* ``command-first``: on its pose, publish the command at once from the shifted candidate the
  last step made, then wait for the plans, step the controller and publish the plan;
* ``command-spread``: the same, but each stand-in's solve starts at its own offset, spread over
  :data:`SPREAD` of the period from the tick, so that the cores are free at the tick;
* ``echo-inbox``: no controller; the pose and odometry taken as an agent takes them
  (:class:`transport.bus.Inbox` callbacks, a main thread woken), a command put at once;
* ``echo``: nothing else in the process; the main thread blocks on Zenoh's queue of its poses
  and answers each at once, with no checks;
* ``echo-callback``: the same answer, put from the callback Zenoh runs, with no hand-over.

Each robot of the scenario is a spawned process, running the real controller (navigator, split
rule against its neighbours' real plans, ProxSuite) and the real messages in the orders that
have one, in the peer mesh that ``fleet run`` uses (``transport.net.NetConfig``).  The driver, this
process, stands in for the tracker: every Ts on the realtime clock it publishes each robot's
pose and odometry.  An observer process stands in for the supervisor's reception (it takes and
decodes every pose, plan and command) and for target 3's probe: it times each command from its
pose's arrival to its own, as ``fleet bench --targets`` does.  The driver also times each
command from the pose's put, which adds the pose's delivery.

What is not real: a stand-in plans from its own nominal model, ``x⁺ = A x + B a`` with the
controller's command, instead of from the pose it takes (the pose only starts the step).  Every
order therefore runs the same trajectories and the same QPs.  The stand-in's command-first
command is only timed, not applied.
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import math
import multiprocessing
import os
import platform
import sys
import threading
import time
from functools import partial
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent

ORDERS = ("solve-first", "command-first", "command-spread", "echo-inbox", "echo", "echo-callback")
BARE = ("echo", "echo-callback")
"""The orders with nothing in the process but the answer to each pose."""
SPREAD = (0.15, 0.85)
"""command-spread: the solves start at offsets spread evenly over this part of the period,
counted from the tick [periods]."""
WARMUP_STEPS = 20
"""Steps after every robot has answered a pose before the window opens [steps]."""
TAIL_STEPS = 5
"""Steps the driver goes on after the window, so that a late command counts as late, not as
missing [steps]."""
PLAN_WAIT = 0.3
"""How long a step waits for its neighbours' plans, in periods (the realtime agent's limit)."""


def _agent(scenario: str, rank: int, hub: str, order: str, ready: Any, stop: Any) -> None:
    """One stand-in agent (a spawned process): answer each pose of its robot in ``order``."""
    os.environ["OMP_NUM_THREADS"] = "1"
    import numpy as np
    import zenoh

    from agent.controller import TubeMPC
    from agent.hazards import neighbour_of
    from agent.protocol import command_message, plan_message
    from agent.tube import validated_design
    from ground.geometry import controlled_point, measured_state
    from ground.scenario import load_scenario
    from ground.wire import Command, Keys, Odom, Plan, Pose
    from transport.bus import Inbox, publisher
    from transport.net import NetConfig, loopback, size_runtime

    scn = load_scenario(scenario)
    keys = Keys("floor")
    spec = scn.robots[rank]
    me, others = spec.id, [r.id for r in scn.robots if r.id != spec.id]
    size_runtime()  # Zenoh's runtime as the fleet's processes size it (transport.bus.open_session)
    session = zenoh.open(NetConfig(listen=[loopback(0)], connect=[hub]).zenoh())
    pub_cmd = publisher(session, keys.cmd(me))
    if order in BARE:  # nothing else in the process: no controller, no Inbox
        _echo(session, keys, me, pub_cmd, order == "echo-callback", ready, stop)
        return
    design = validated_design(scn)
    p = design.params
    start = controlled_point(spec.start, p.lookahead)
    ctrl = TubeMPC(
        design, start, np.array(spec.goal, dtype=float), scn.arena, obstacles=scn.obstacles,
        priority=spec.priority, rank=rank, seed=scn.simulation.seed * 1000 + rank,
    )  # fmt: skip
    inbox = Inbox(keys, f"agent {me}")
    subs = [
        inbox.subscribe(session, keys.pose(me), Pose, keep=True),
        inbox.subscribe(session, keys.odom(me), Odom, keep=True),
        inbox.subscribe(session, keys.plan(), Plan, keep=True, remote=True),
    ]
    pub_plan = publisher(session, keys.plan(me))
    _ready(ready, me)
    x = design.E @ start  # at rest at the start: the stand-in's own nominal model
    x_next, v_next = x.copy(), np.zeros((ctrl.N, 2))
    K = design.K
    k = 0
    while not stop.is_set():
        if not inbox.wait(partial(_measured_from, inbox, me, k), 1.0):
            continue
        with inbox.cond:  # the newest step measured: the first ones go before the mesh links up
            k = _measured(inbox, me)
            pose, odom = inbox.get(Pose, me, k), inbox.get(Odom, me, k)
        assert pose is not None and odom is not None
        measured_state((pose.x, pose.y, pose.theta), (odom.vx, odom.vy), p.lookahead)  # taken, not used
        if order == "echo-inbox":  # no controller: the path itself, received as an agent does
            pub_cmd.put(Command(robot=me, step=k, ax=0.0, ay=0.0).encode())
            inbox.prune(k - 2)
            k += 1
            continue
        if order != "solve-first":
            a = v_next[0] + K @ (x - x_next)
            cmd = Command(robot=me, step=k, ax=float(a[0]), ay=float(a[1]), fallback=True,
                          x_next=x_next, v_next=v_next, K=K)  # fmt: skip
            pub_cmd.put(cmd.encode())
        if order == "command-spread":  # leave the tick to the commands: each solve at its own offset
            offset = SPREAD[0] + (SPREAD[1] - SPREAD[0]) * (rank + 0.5) / (len(others) + 1)
            stop.wait(max(0.0, pose.t + offset * p.Ts - time.monotonic()))
        if k > 0:
            inbox.wait(partial(_plans_in, inbox, others, k - 1), PLAN_WAIT * p.Ts)
        with inbox.cond:
            plans = [pl for j in others if (pl := inbox.newest(Plan, j, k - 1)) is not None]
        out = ctrl.step(x, [neighbour_of(pl) for pl in plans])
        if order == "solve-first":
            pub_cmd.put(command_message(me, k, ctrl, out).encode())
        pub_plan.put(plan_message(me, k, ctrl, out).encode())
        inbox.prune(k - 2)
        x = design.A @ x + design.B @ out.a
        x_next, v_next = out.x_next, out.v_next
        k += 1
    for sub in subs:
        sub.undeclare()
    session.close()


def _ready(ready: Any, who: str) -> None:
    """Freeze the start-up heap, as a fleet process does once ready
    (:func:`transport.process.announce`), and say so on ``ready``."""
    gc.collect()
    gc.freeze()
    ready.put(who)


def _measured(inbox: Any, me: str) -> int:
    """The newest step of which both this robot's pose and odometry are in, or −1."""
    from ground.wire import Odom, Pose

    pose, odom = inbox.get(Pose, me), inbox.get(Odom, me)
    if pose is None or odom is None:
        return -1
    k = min(pose.seq, odom.seq)
    return k if inbox.get(Pose, me, k) is not None and inbox.get(Odom, me, k) is not None else -1


def _measured_from(inbox: Any, me: str, k: int) -> bool:
    return _measured(inbox, me) >= k


def _plans_in(inbox: Any, others: list[str], step: int) -> bool:
    """Every neighbour's plan of ``step`` is in."""
    from ground.wire import Plan

    return all(inbox.get(Plan, j, step) is not None for j in others)


def _echo(session: Any, keys: Any, me: str, pub_cmd: Any, in_callback: bool, ready: Any, stop: Any) -> None:
    """The floor of the path: no controller, no checks.  Each of this robot's poses is answered
    with a command at once: by the main thread, blocked on Zenoh's queue of the poses (``echo``),
    or from the callback Zenoh runs on its own thread, with no hand-over at all
    (``echo-callback``)."""
    import msgpack
    import zenoh

    from ground.wire import Command

    def answer(sample: Any) -> None:
        k = msgpack.unpackb(sample.payload.to_bytes())["seq"]  # the step, without the checks
        with contextlib.suppress(zenoh.ZError):  # the last pose may come as the session closes
            pub_cmd.put(Command(robot=me, step=k, ax=0.0, ay=0.0).encode())

    if in_callback:
        sub = session.declare_subscriber(keys.pose(me), answer)
    else:
        sub = session.declare_subscriber(keys.pose(me), zenoh.handlers.FifoChannel(64))
    _ready(ready, me)
    if in_callback:
        stop.wait(900)  # bounded: the driver sets it
    while not in_callback and not stop.is_set():  # the driver sends a last pose after setting stop
        try:
            sample = sub.recv()
        except zenoh.ZError:  # the channel is closed: the session is going
            break
        answer(sample)
    sub.undeclare()
    session.close()


def _observer(hub: str, ready: Any, stop: Any, results: Any) -> None:
    """The supervisor's reception, standing in: take and decode every pose, plan and command.
    Poses and commands are timed on arrival by target 3's own probe
    (``benchmarks/bench_scale.py`` ``Observer``); {(robot, step): ms} goes on ``results`` once
    the driver stops."""
    from benchmarks.bench_scale import Observer
    from ground.wire import Plan, WireError, decode

    probe = Observer(hub, fleet="floor")

    def take_plan(sample: Any) -> None:
        with contextlib.suppress(WireError):
            decode(sample.payload.to_bytes(), Plan, robot=str(sample.key_expr).rsplit("/", 1)[-1])

    plans = probe.session.declare_subscriber(probe.keys.plan(), take_plan)
    _ready(ready, "observer")
    stop.wait(900)  # bounded: the driver sets it
    plans.undeclare()
    probe.close()
    results.put({key: 1e3 * (t - probe.pose[key]) for key, t in probe.cmd.items() if key in probe.pose})


def measure(scenario: str, order: str, seconds: float) -> dict[str, Any]:
    """One run in ``order``: spawn the stand-ins, drive them on the realtime clock, and time
    every command of the window [ms]: from its pose's arrival at the observer to its own, as
    target 3 is timed, and from the pose's put here."""
    import numpy as np
    import zenoh

    from ground.scenario import load_scenario
    from ground.wire import Command, Keys, Odom, Pose, WireError, decode
    from transport.bus import publisher
    from transport.net import NetConfig, free_port, loopback, size_runtime

    scn = load_scenario(scenario)
    ids = [r.id for r in scn.robots]
    Ts = scn.controller.Ts
    hub = loopback(free_port())
    keys = Keys("floor")
    size_runtime()  # as the tracker sizes Zenoh's runtime (transport.bus.open_session)
    session = zenoh.open(NetConfig(listen=[hub]).zenoh())
    lock = threading.Lock()
    sent: dict[tuple[str, int], float] = {}
    got: dict[tuple[str, int], float] = {}

    def on_cmd(sample: Any) -> None:
        now = time.monotonic()
        try:
            c = decode(sample.payload.to_bytes(), Command, robot=str(sample.key_expr).rsplit("/", 1)[-1])
        except WireError:
            return
        with lock:
            got.setdefault((c.robot, c.step), now)

    sub = session.declare_subscriber(keys.cmd(), on_cmd)
    pubs = {r: (publisher(session, keys.pose(r)), publisher(session, keys.odom(r))) for r in ids}
    ctx = multiprocessing.get_context("spawn")
    ready, stop, results = ctx.Queue(), ctx.Event(), ctx.Queue()
    procs = [ctx.Process(target=_observer, args=(hub, ready, stop, results), daemon=True)]
    procs += [
        ctx.Process(target=_agent, args=(scenario, i, hub, order, ready, stop), daemon=True)
        for i in range(len(ids))
    ]
    observed: dict[tuple[str, int], float] = {}
    window: tuple[int, int] | None = None
    try:
        for pr in procs:
            pr.start()
        for _ in procs:
            ready.get(timeout=120)
        gc.collect()
        gc.freeze()
        t0 = time.monotonic()
        limit = int((120 + seconds) / Ts)  # bounded: start-up, warm-up and the window
        for k in range(limit):
            tick = t0 + k * Ts  # the poses' capture time, on the monotonic clock every process shares
            out = [  # encoded before the tick: the loop at the tick only puts, and holds the GIL briefly
                (r, Pose(robot=r, seq=k, t=tick, x=s.start[0], y=s.start[1], theta=s.start[2]).encode(),
                 Odom(robot=r, seq=k, t=tick, vx=0.0, vy=0.0).encode())
                for r, s in zip(ids, scn.robots, strict=True)
            ]  # fmt: skip
            stop.wait(max(0.0, tick - time.monotonic()))  # the realtime clock
            for r, pose, odom in out:
                sent[(r, k)] = time.monotonic()  # written by this thread only, read after the run
                pubs[r][0].put(pose)
                pubs[r][1].put(odom)
            if window is None:
                with lock:
                    answered = {key[0] for key in got}
                if len(answered) == len(ids):  # every stand-in is in: warm up, then measure
                    window = (k + WARMUP_STEPS, k + WARMUP_STEPS + round(seconds / Ts))
            if window is not None and k >= window[1] + TAIL_STEPS:
                break
        if window is None:
            raise RuntimeError(f"not every stand-in answered within {limit} steps")
    finally:
        stop.set()
        for r in ids:  # wake a stand-in blocked on its poses
            pubs[r][0].put(Pose(robot=r, seq=0, t=0.0, x=0.0, y=0.0, theta=0.0).encode())
        try:
            observed = results.get(timeout=60)
        except Exception:  # queue.Empty: the observer died; the put figures still stand
            observed = {}
        for pr in procs:
            pr.join(timeout=30)
            if pr.is_alive():
                pr.kill()
        sub.undeclare()
        session.close()
    lo, hi = window
    keys_in = [key for key in sent if lo <= key[1] < hi]
    with lock:
        from_put = np.sort([1e3 * (got[key] - sent[key]) for key in keys_in if key in got])
    lat = np.sort([observed[key] for key in keys_in if key in observed])

    def pct(a: Any, q: float) -> float:
        return float(np.percentile(a, q)) if len(a) else math.nan

    return {
        "order": order,
        "commands": len(lat),
        "missing": len(keys_in) - len(lat),
        "p50_ms": pct(lat, 50),
        "p99_ms": pct(lat, 99),
        "max_ms": float(lat[-1]) if len(lat) else math.nan,
        "from_put_p99_ms": pct(from_put, 99),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default=str(ROOT / "scenarios" / "swap_16.toml"))
    ap.add_argument("--seconds", type=float, default=20.0, help="measured window of each run [s]")
    ap.add_argument("--runs", type=int, default=2, help="runs of each order, interleaved")
    ap.add_argument("--orders", default=",".join(ORDERS), help="comma-separated, of: " + ", ".join(ORDERS))
    args = ap.parse_args(argv)
    orders = args.orders.split(",")
    problem = next(
        (f"--orders: {o!r} is not one of {', '.join(ORDERS)}" for o in orders if o not in ORDERS),
        "--seconds: must be at least 1" if not args.seconds >= 1 else None,
    )
    if problem is None and args.runs < 1:
        problem = "--runs: must be at least 1"
    if problem is None:
        from ground.scenario import ConfigError, load_scenario

        try:
            load_scenario(args.scenario)
        except ConfigError as e:
            problem = str(e)
    if problem is not None:
        print(f"bench_latency_floor: error: {problem}", file=sys.stderr)
        return 2
    print(
        f"pose -> command floor: {Path(args.scenario).name}, {args.runs} x {args.seconds:g} s per order; "
        f"nproc {os.cpu_count()}, {platform.processor() or platform.machine()}, "
        f"python {platform.python_version()}, load {os.getloadavg()[0]:.1f}",
        flush=True,
    )
    print("pose arrival -> command arrival at the observer (as target 3), and p99 from the pose's put")
    print(f"{'order':<15}{'commands':>9}{'missing':>8}{'p50 ms':>8}{'p99 ms':>8}{'max ms':>8}{'put p99':>8}")
    for _ in range(args.runs):
        for order in orders:
            r = measure(args.scenario, order, args.seconds)
            print(
                f"{order:<15}{r['commands']:>9}{r['missing']:>8}{r['p50_ms']:>8.1f}{r['p99_ms']:>8.1f}"
                f"{r['max_ms']:>8.1f}{r['from_put_p99_ms']:>8.1f}",
                flush=True,
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
