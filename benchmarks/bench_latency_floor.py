"""Target 3's floor: pose → command latency if a command did not wait for its step's solve.

    python benchmarks/bench_latency_floor.py [--scenario scenarios/swap_16.toml] [--seconds 20] [--runs 2]

An agent today answers the pose of step k only after that step's solve: it waits for its
neighbours' plans of step k − 1, steps its :class:`agent.controller.TubeMPC` and then publishes
the command.  With delay compensation (docs/performance.md, "Floors") the command of step k
would be the ancillary law on a plan solved during step k − 1, ``u = v̂ + K(x − x̂)``, published
as soon as the pose is in, and the solve would follow it.  This bench measures what that order
would give on this machine, with everything else the same, side by side with today's order:

* ``solve-first`` (today): on its pose of step k, wait (≤ 0.3 Ts) for the neighbours' plans of
  step k − 1, step the controller, publish the command, then the plan;
* ``command-first``: on its pose, publish the command at once from the shifted candidate the
  last step made, then wait for the plans, step the controller and publish the plan.

Each robot of the scenario is a spawned process running the real controller (navigator, split
rule against its neighbours' real plans, ProxSuite) and the real messages, in the peer mesh that
``fleet run`` uses (``ground.net.NetConfig``).  The driver, this process, stands in for the
tracker: every Ts on the realtime clock it publishes each robot's pose and odometry and times
each command from the pose's put to the command's arrival.  A second process stands in for the
supervisor's reception: it takes and decodes every pose, plan and command.

What is not real: a stand-in plans from its own nominal model, ``x⁺ = A x + B a`` with the
controller's command, instead of from the pose it takes (the pose only starts the step).  Both
orders therefore run the same trajectories and the same QPs, and the robots' motion cannot
differ between them.  The stand-in's command-first command is only timed, not applied.
"""

from __future__ import annotations

import argparse
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
sys.path.insert(0, str(ROOT))

ORDERS = ("solve-first", "command-first", "command-spread", "echo-inbox", "echo")
SPREAD = 0.7
"""command-spread: the solves start at evenly spread offsets over this part of the period."""
WARMUP_STEPS = 20
"""Steps after every robot has answered a pose before the window opens [steps]."""
PLAN_WAIT = 0.3
"""How long a step waits for its neighbours' plans, in periods (the realtime agent's limit)."""


def _agent(scenario: str, rank: int, hub: str, order: str, ready: Any, stop: Any) -> None:
    """One stand-in agent (a spawned process): answer each pose of its robot in ``order``."""
    os.environ["OMP_NUM_THREADS"] = "1"
    import numpy as np
    import zenoh

    from agent.controller import TubeMPC
    from agent.hazards import neighbour_of
    from agent.messages import command_message, plan_message
    from agent.tube import validated_design
    from ground.bus import Inbox, publisher
    from ground.geometry import controlled_point, measured_state
    from ground.net import NetConfig, loopback
    from ground.scenario import load_scenario
    from ground.wire import Command, Keys, Odom, Plan, Pose

    scn = load_scenario(scenario)
    design = validated_design(scn)
    p = design.params
    spec = scn.robots[rank]
    me, others = spec.id, [r.id for r in scn.robots if r.id != spec.id]
    start = controlled_point(spec.start, p.lookahead)
    ctrl = TubeMPC(
        design, start, np.array(spec.goal, dtype=float), scn.arena, obstacles=scn.obstacles,
        priority=spec.priority, rank=rank, seed=scn.simulation.seed * 1000 + rank,
    )  # fmt: skip
    keys = Keys("floor")
    session = zenoh.open(NetConfig(listen=[loopback(0)], connect=[hub]).zenoh())
    inbox = Inbox(keys, f"agent {me}")
    subs = [
        inbox.subscribe(session, keys.pose(me), Pose, keep=True),
        inbox.subscribe(session, keys.odom(me), Odom, keep=True),
        inbox.subscribe(session, keys.plan(), Plan, keep=True, remote=True),
    ]
    pub_cmd, pub_plan = publisher(session, keys.cmd(me)), publisher(session, keys.plan(me))
    if order == "echo":
        _echo(session, keys, me, pub_cmd, ready, stop)
        return
    ready.put(me)
    x = design.E @ start  # at rest at the start: the stand-in's own nominal model
    x_next, v_next = x.copy(), np.zeros((ctrl.N, 2))
    K = design.K
    k = 0
    while not stop.is_set():
        if not inbox.wait(partial(_measured_from, inbox, me, k), 1.0):
            continue
        at = time.monotonic()
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
            cmd = Command(
                robot=me,
                step=k,
                ax=float(a[0]),
                ay=float(a[1]),
                fallback=True,
                x_next=x_next,
                v_next=v_next,
                K=K,
            )
            pub_cmd.put(cmd.encode())
        if order == "command-spread":  # leave the tick to the commands: each solve at its own offset
            stop.wait(max(0.0, at + SPREAD * p.Ts * (rank + 0.5) / (len(others) + 1) - time.monotonic()))
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


def _echo(session: Any, keys: Any, me: str, pub_cmd: Any, ready: Any, stop: Any) -> None:
    """The floor of the path: no controller, no callback, no decoding.  The main thread blocks on
    Zenoh's queue of this robot's poses and answers each with a command at once."""
    import msgpack
    import zenoh

    from ground.wire import Command

    sub = session.declare_subscriber(keys.pose(me), zenoh.handlers.FifoChannel(64))
    ready.put(me)
    while not stop.is_set():  # the driver sends a last pose after setting stop
        try:
            sample = sub.recv()
        except zenoh.ZError:  # the channel is closed: the session is going
            break
        k = msgpack.unpackb(sample.payload.to_bytes())["seq"]  # the step, without the checks
        pub_cmd.put(Command(robot=me, step=k, ax=0.0, ay=0.0).encode())
    sub.undeclare()
    session.close()


def _observer(hub: str, ready: Any, stop: Any) -> None:
    """The supervisor's reception, standing in: take and decode every pose, plan and command."""
    import zenoh

    from ground.net import NetConfig, loopback
    from ground.wire import Command, Plan, Pose, WireError, decode

    session = zenoh.open(NetConfig(listen=[loopback(0)], connect=[hub]).zenoh())

    def taker(typ: Any) -> Any:
        def take(sample: Any) -> None:
            try:
                decode(sample.payload.to_bytes(), typ, robot=str(sample.key_expr).rsplit("/", 1)[-1])
            except WireError:
                pass

        return take

    subs = [
        session.declare_subscriber(f"fleet/floor/{kind}/*", taker(typ))
        for kind, typ in (("pose", Pose), ("plan", Plan), ("cmd", Command))
    ]
    ready.put("observer")
    stop.wait(900)  # bounded: the driver sets it
    for sub in subs:
        sub.undeclare()
    session.close()


def measure(scenario: str, order: str, seconds: float, observer: bool = True) -> dict[str, Any]:
    """One run in ``order``: spawn the stand-ins, drive them on the realtime clock, and time
    every command of the window [ms]."""
    import numpy as np
    import zenoh

    from ground.bus import publisher
    from ground.net import NetConfig, free_port, loopback
    from ground.scenario import load_scenario
    from ground.wire import Command, Keys, Odom, Pose, WireError, decode

    scn = load_scenario(scenario)
    ids = [r.id for r in scn.robots]
    Ts = scn.controller.Ts
    hub = loopback(free_port())
    keys = Keys("floor")
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
    ready, stop = ctx.Queue(), ctx.Event()
    procs = [ctx.Process(target=_observer, args=(hub, ready, stop), daemon=True)] if observer else []
    procs += [
        ctx.Process(target=_agent, args=(scenario, i, hub, order, ready, stop), daemon=True)
        for i in range(len(ids))
    ]
    try:
        for pr in procs:
            pr.start()
        for _ in procs:
            ready.get(timeout=120)
        first: int | None = None
        window: tuple[int, int] | None = None
        t0 = time.monotonic()
        limit = int((120 + seconds) / Ts)  # bounded: start-up, warm-up and the window
        for k in range(limit):
            tick = t0 + k * Ts
            out = [  # encoded before the tick: the loop at the tick only puts, and holds the GIL briefly
                (r, Pose(robot=r, seq=k, t=k * Ts, x=s.start[0], y=s.start[1], theta=s.start[2]).encode(),
                 Odom(robot=r, seq=k, t=k * Ts, vx=0.0, vy=0.0).encode())
                for r, s in zip(ids, scn.robots, strict=True)
            ]  # fmt: skip
            stop.wait(max(0.0, tick - time.monotonic()))  # the realtime clock
            for r, pose, odom in out:
                sent[(r, k)] = time.monotonic()  # written by this thread only, read after the run
                pubs[r][0].put(pose)
                pubs[r][1].put(odom)
            if first is None:
                with lock:
                    answered = {key[0] for key in got}
                if len(answered) == len(ids):
                    first = k
                    window = (k + WARMUP_STEPS, k + WARMUP_STEPS + int(seconds / Ts))
            if window is not None and k >= window[1] + 2:
                break
        if window is None:
            raise RuntimeError(f"not every stand-in answered within {limit} steps")
    finally:
        stop.set()
        for r in ids:  # wake a stand-in blocked on its poses
            pubs[r][0].put(Pose(robot=r, seq=0, t=0.0, x=0.0, y=0.0, theta=0.0).encode())
        for pr in procs:
            pr.join(timeout=30)
            if pr.is_alive():
                pr.kill()
        sub.undeclare()
        session.close()
    lo, hi = window
    with lock:
        lat = [1e3 * (got[key] - sent[key]) for key in sent if lo <= key[1] < hi and key in got]
        expected = sum(1 for key in sent if lo <= key[1] < hi)
    arr = np.sort(np.array(lat))
    return {
        "order": order,
        "commands": len(lat),
        "missing": expected - len(lat),
        "p50_ms": float(np.percentile(arr, 50)) if lat else math.nan,
        "p99_ms": float(np.percentile(arr, 99)) if lat else math.nan,
        "max_ms": float(arr[-1]) if lat else math.nan,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default=str(ROOT / "scenarios" / "swap_16.toml"))
    ap.add_argument("--seconds", type=float, default=20.0, help="measured window of each run [s]")
    ap.add_argument("--runs", type=int, default=2, help="runs of each order, interleaved")
    ap.add_argument("--orders", default=",".join(ORDERS), help="comma-separated, of: " + ", ".join(ORDERS))
    ap.add_argument("--no-observer", action="store_true", help="without the supervisor's stand-in")
    args = ap.parse_args(argv)
    orders = args.orders.split(",")
    problem = next(
        (f"--orders: {o!r} is not one of {', '.join(ORDERS)}" for o in orders if o not in ORDERS),
        "--seconds: must be positive"
        if not args.seconds > 0
        else "--runs: must be at least 1"
        if args.runs < 1
        else None,
    )
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
    print(f"{'order':<14}{'commands':>9}{'missing':>8}{'p50 ms':>8}{'p99 ms':>8}{'max ms':>8}", flush=True)
    for _ in range(args.runs):
        for order in orders:
            r = measure(args.scenario, order, args.seconds, observer=not args.no_observer)
            print(
                f"{order:<14}{r['commands']:>9}{r['missing']:>8}{r['p50_ms']:>8.1f}{r['p99_ms']:>8.1f}{r['max_ms']:>8.1f}",
                flush=True,
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
