"""The transport's floor: what a fleet's message pattern costs with no fleet code at all.

    python -m benchmarks.bench_zenoh_floor [--robots 16] [--rate 25] [--seconds 20] [--cell 0]

N processes (spawned), configured as ``fleet run`` configures its processes
(``transport.net.NetConfig``: peer mode, multicast scouting off, the first listening on a
loopback port, the others connecting to it and finding each other by gossip, a full mesh;
or ``--topology star``: the first a router, the others its clients).  Each publishes one
978-byte payload (a plan's size at N = 20) ``--rate`` times a second and subscribes to every
other's, as an agent in the mesh does.  How a process takes the samples:

* ``callback``: a Python callback that only counts (Zenoh runs it on a Python thread of its own);
* ``decode``: the same callback decoding each payload as a :class:`ground.wire.Plan`;
* ``drain``: no callback; the main thread takes the queued samples from a FIFO channel once
  per period (``transport.bus.Inbox.drain``'s way);
* ``direct``: the counting callback run by Zenoh's own receiving thread
  (``zenoh.handlers.Callback(..., indirect=False)``, unstable in zenoh-python 1.x), with no
  hand-over to a Python thread of its own.

With ``--cell G`` the processes stand on a ring in cells of G, as a subscription by place would
put them: each publishes on ``floor/plan/c<cell>/r<i>`` and subscribes to its own cell and the
two beside it (``floor/plan/c<cell>/*`` each), so it takes 3 G plans a step (its own among
them) instead of N.  Without it, one cell holds everybody.  The ``plans`` column counts what a process took
per publication of its own.

The figure is the CPU of all N processes per robot-step (one publication per process), from
``/proc`` over a window after start-up, split into the main threads, the Python callback
threads and Zenoh's runtime threads.  Compare it with ``fleet bench --cpu``: the part of a
fleet's cost that no change to the fleet's own code can remove, short of sending fewer
messages or changing the transport.

With ``--pattern step`` or ``--pattern fleet``, two more processes stand in for the tracker and
the supervisor, and the tracker's stand-in drives the steps at ``--rate`` with the messages of a
whole step, not only the plans (``--pattern plans``, the default, as above).  The robots'
processes answer from their callbacks; the payloads are real encodings (:mod:`ground.wire`):

* ``fleet``: the messages ``fleet run`` sends with its default flags (simulated tracker, agents
  planning a step ahead, the tracker's realtime batching, ``tracker/sim.py``).  Each step the
  tracker puts a tick and an outcome for all, and each robot's pose, odometry and true pose; it
  takes every command and every plan.  Each agent takes the tick, the outcome, its pose and
  odometry and the plans of its cells; it puts its command on the tick and its plan on the
  outcome.  The supervisor takes the tick and every pose, true pose and plan
  (``supervisor/monitor.py``).
* ``step``: the fewest messages a step of the method needs when the agents exchange their plans
  peer to peer, with the processes the fleet has (an agent per robot, a tracker, a supervisor).
  The tracker puts each robot's measurement (pose and odometry in one message, which also
  starts the step) and one message of every true pose.  Each agent takes its measurement and
  the plans of its cells, and puts one message: its plan and its command together, which the
  tracker takes as the command and the others as the plan.  The supervisor takes every plan
  and the true poses.  (Relaying the plans through one process, ``fleet run --exchange
  relay``, sends fewer messages to each agent; it is not peer to peer.)

Their agents take the samples by ``callback`` or ``decode`` as above, or by ``drain``: no
callback at all, the main thread blocking on Zenoh's queue of the sample that starts its step
(the tick, or its measurement) and taking whatever else is queued then, the fewest wake-ups.

With ``--math`` each run also measures ``fleet simulate`` on the shipped swap of N robots, the
math alone, as ``fleet bench --cpu`` does (``bench_cpu.marginal_rows``), and each row prints
(math + floor) / math: the least target 1 ratio that a fleet sending at most this row's messages
could reach.  With ``--pattern plans`` it is a loose lower bound: the fleet's tracker and
supervisor, and each agent's tick, command and outcome, add messages that it does not send.
``--pattern step`` sends those too, as few as peer-to-peer plans allow: with it, the ratio
bounds every such design, at the pace measured.  The pace matters: what Zenoh spends by the
second (keep-alives, timers) counts per step in proportion to 1 / ``--rate``, and a lockstep
fleet steps as fast as its CPU allows (``fleet bench --targets`` measures the floor at the pace
of a fleet that met target 1).  With a tracker's stand-in the robot-steps counted are the steps
it put in the window; its stand-in and the supervisor's print how many messages they took a
step, over their lives.
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import math
import multiprocessing
import os
import platform
import queue
import sys
import time
from functools import partial
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent

MODES = ("callback", "decode", "drain", "direct")
PATTERNS = ("plans", "step", "fleet")
STEP_MODES = ("callback", "decode", "drain")
"""The modes of ``--pattern step`` and ``fleet``: how the agents take the plans."""


def least_ratio(math_ms: float, floor_ms: float) -> float:
    """The least ``fleet run`` / ``fleet simulate`` ratio (target 1) of a fleet that does the math
    (``math_ms`` per robot-step, all of ``fleet simulate``) and sends at least the floor's
    messages (``floor_ms`` per robot-step): CPU adds, so (math + floor) / math."""
    if not (math_ms > 0 and floor_ms >= 0):
        raise ValueError(
            f"the math must cost something and the floor nothing negative ({math_ms}, {floor_ms})"
        )
    return (math_ms + floor_ms) / math_ms


def _payload(i: int) -> bytes:
    import numpy as np

    from ground.wire import Plan

    path = np.cumsum(np.full((21, 2), 0.01), axis=0)
    return Plan(
        robot=f"r{i}", step=5, t0=0.6, Ts=0.1, committed=path[1:], nominal=path, footprint=0.134,
        priority=0, rank=i, phase=0, target=path[-1].copy(), goal=np.zeros(2), status="PROXQP_SOLVED",
        solve_time=1e-3, tube_ok=True,
    ).encode()  # fmt: skip


def cells_of(i: int, robots: int, cell: int) -> tuple[int, list[int], int]:
    """Process ``i``'s cell, the cells it subscribes to (its own and the two beside it on the
    ring, distinct) and how many publishers those hold, itself included.  ``cell`` 0: one cell."""
    if cell <= 0:
        return 0, [0], robots
    count = -(-robots // cell)
    mine = i // cell
    subs = sorted({(mine + d) % count for d in (-1, 0, 1)})
    return mine, subs, sum(min(cell, robots - c * cell) for c in subs)


class _Heard:
    """Which publishers a process has heard from, across its callback threads (zenoh-python runs
    each subscriber's callbacks on a thread of its own): says "heard all" on ``ready`` exactly
    once, when the ``expected``-th distinct key comes in."""

    def __init__(self, who: Any, expected: int, ready: Any):
        import threading

        self.who, self.expected, self.ready = who, expected, ready
        self.keys: set[str] = set()
        self.lock = threading.Lock()

    def add(self, key: str) -> None:
        if len(self.keys) >= self.expected:  # (the usual case, without the lock)
            return
        with self.lock:
            if len(self.keys) < self.expected:
                self.keys.add(key)
                if len(self.keys) == self.expected:
                    self.ready.put(("heard all", self.who))


def _session(hub: str, topology: str, listen: bool) -> Any:
    """A session configured as ``fleet run`` configures its processes: the one that ``listen``s
    on ``hub`` (a router in a star), or one connecting to it (a client in a star)."""
    import zenoh

    from transport.net import NetConfig, loopback, size_runtime

    size_runtime()  # Zenoh's runtime as the fleet's processes size it (transport.bus.open_session)
    if listen:
        return zenoh.open(NetConfig(listen=[hub], mode="router" if topology == "star" else "peer").zenoh())
    mode = "client" if topology == "star" else "peer"
    return zenoh.open(NetConfig(listen=[loopback(0)], connect=[hub], mode=mode).zenoh())


def _drain(sub: Any, then: Any) -> None:
    """Take what is queued on ``sub`` (a FIFO channel), at most its capacity, each by ``then``."""
    for _ in range(4096):
        sample = sub.try_recv()
        if sample is None:
            return
        then(sample)


def _peer(
    i: int, robots: int, hub: str, topology: str, mode: str, rate: float, cell: int, ready: Any, go: Any,
    stop: Any,
) -> None:  # fmt: skip
    """One process: from ``go`` until ``stop``, publish at ``rate`` and take samples by
    ``mode``; say on ``ready`` when its session is open, again once it has heard every
    publisher of the cells it subscribes to (the mesh has linked up), and at the end how many
    samples it took and how many it published."""
    os.environ["OMP_NUM_THREADS"] = "1"
    import zenoh

    from ground.wire import Plan, WireError, decode

    session = _session(hub, topology, listen=i == 0)
    mine, cells, expected = cells_of(i, robots, cell)
    heard = _Heard(i, expected, ready)
    taken = [0]

    def took(key: str) -> None:
        taken[0] += 1
        heard.add(key)

    def count(sample: Any) -> None:
        sample.payload.to_bytes()
        took(str(sample.key_expr))

    def decoded(sample: Any) -> None:
        k = str(sample.key_expr)
        try:
            decode(sample.payload.to_bytes(), Plan, robot=k.rsplit("/", 1)[-1])
        except WireError:
            pass
        took(k)

    subs: list[Any] = []
    for c in cells:
        if mode == "drain":
            subs.append(session.declare_subscriber(f"floor/plan/c{c}/*", zenoh.handlers.FifoChannel(4096)))
        elif mode == "direct":
            direct = zenoh.handlers.Callback(count, indirect=False)
            subs.append(session.declare_subscriber(f"floor/plan/c{c}/*", direct))
        else:
            subs.append(
                session.declare_subscriber(f"floor/plan/c{c}/*", count if mode == "callback" else decoded)
            )
    pub = session.declare_publisher(f"floor/plan/c{mine}/r{i}")
    published = 0
    payload = _payload(i)
    ready.put(("open", i))
    go.wait(60)
    period, t_next = 1.0 / rate, time.monotonic()
    for _ in range(int(600 * rate)):  # bounded: at most 10 min
        if stop.is_set():
            break
        pub.put(payload)
        published += 1
        if mode == "drain":
            for sub in subs:
                _drain(sub, count)
        t_next += period
        stop.wait(max(0.0, t_next - time.monotonic()))  # the publication rate
    for sub in subs:
        sub.undeclare()
    session.close()
    ready.put(("took", i, taken[0], published))


def _step_payloads(robots: int) -> dict[str, bytes]:
    """Real encodings of a step's messages other than the plan, robot ``r0``'s (the others'
    differ only in a digit): a command carries the shifted candidate of a 20-step horizon.
    ``meas`` (a pose and an odometry) and ``truths`` (every robot's true pose) stand for
    messages the fleet does not have, by their size: nothing decodes them."""
    import numpy as np

    from ground.wire import Command, Odom, Outcome, Pose, Tick, Truth

    pose = Pose(robot="r0", seq=5, t=0.5, x=0.31, y=-0.42, theta=1.1).encode()
    odom = Odom(robot="r0", seq=5, t=0.5, vx=0.01, vy=-0.02).encode()
    truth = Truth(robot="r0", seq=5, t=0.5, x=0.31, y=-0.42, theta=1.1).encode()
    return {
        "pose": pose, "truth": truth, "odom": odom,
        "tick": Tick(robot="tracker", step=5, t=0.5, stop=False, misses=0).encode(),
        "outcome": Outcome(robot="tracker", step=5).encode(),
        "cmd": Command(
            robot="r0", step=5, ax=0.01, ay=-0.02, fallback=True, x_next=np.full(4, 0.1),
            v_next=np.full((20, 2), 0.01), K=np.full((2, 4), -2.0),
        ).encode(),
        "meas": pose + odom, "truths": truth * robots,
    }  # fmt: skip


STOP = b"stop"
"""The payload of the tracker's stand-in's last trigger (tick, or measurement): the end."""


def _step_agent(
    i: int, robots: int, hub: str, topology: str, pattern: str, mode: str, cell: int, ready: Any, go: Any,
    stop: Any,
) -> None:  # fmt: skip
    """Robot ``i``'s agent in ``pattern``: it takes what an agent takes and answers, from its
    callbacks or (``drain``) from its main thread.  In ``fleet`` it puts its command on the
    tick and its plan on the outcome; in ``step`` one message on its measurement, the plan and
    the command together, which the tracker takes as its command and the others as its plan.
    Says on ``ready`` when open, when it has heard every publisher of the cells it subscribes to
    but its own, and at the end how many plans it took and how many it put."""
    os.environ["OMP_NUM_THREADS"] = "1"
    import zenoh

    from ground.wire import Plan, WireError, decode
    from transport.bus import publisher

    session = _session(hub, topology, listen=False)
    mine, cells, publishers = cells_of(i, robots, cell)
    heard = _Heard(i, publishers - 1, ready)  # an agent does not take its own plan back
    taken, published = [0], [0]
    pub_plan = publisher(session, f"floor/plan/c{mine}/r{i}")
    pub_cmd = publisher(session, f"floor/cmd/r{i}")
    plan, cmd = _payload(i), _step_payloads(robots)["cmd"]
    # What the agent puts on each of its triggers.
    answers = (
        {"tick": ((pub_cmd, cmd),), "outcome": ((pub_plan, plan),)} if pattern == "fleet"
        else {"meas": ((pub_plan, plan + cmd),)}
    )  # fmt: skip

    def on_plan(sample: Any) -> None:
        k = str(sample.key_expr)
        data = sample.payload.to_bytes()
        if mode == "decode":
            with contextlib.suppress(WireError):
                decode(data[: len(plan)], Plan, robot=k.rsplit("/", 1)[-1])
        taken[0] += 1
        heard.add(k)

    def answer(what: tuple[tuple[Any, bytes], ...]) -> None:
        with contextlib.suppress(zenoh.ZError):  # the session may be closing at the end
            for pub, payload in what:
                pub.put(payload)
                if pub is pub_plan:
                    published[0] += 1

    def on_trigger(sample: Any, what: tuple[tuple[Any, bytes], ...]) -> None:
        if sample.payload.to_bytes() != STOP and not stop.is_set():
            answer(what)

    def take(sample: Any) -> None:
        sample.payload.to_bytes()

    triggers = {"tick": "floor/tick", "outcome": "floor/outcome", "meas": f"floor/meas/r{i}"}
    inputs = [f"floor/pose/r{i}", f"floor/odom/r{i}"] if pattern == "fleet" else []
    plan_keys = [f"floor/plan/c{c}/*" for c in cells]
    remote = zenoh.Locality.REMOTE
    if mode != "drain":
        subs = [session.declare_subscriber(k, on_plan, allowed_origin=remote) for k in plan_keys]
        subs += [
            session.declare_subscriber(triggers[t], partial(on_trigger, what=a)) for t, a in answers.items()
        ]
        subs += [session.declare_subscriber(k, take) for k in inputs]
        ready.put(("open", i))
        stop.wait(600)  # bounded: at most 10 min; the callbacks do the work
    else:  # no callback: the main thread blocks on its trigger(s) in turn and drains the rest

        def fifo(key: str, origin: Any = zenoh.Locality.ANY) -> Any:
            return session.declare_subscriber(key, zenoh.handlers.FifoChannel(4096), allowed_origin=origin)

        queued = [(fifo(k, remote), on_plan) for k in plan_keys] + [(fifo(k), take) for k in inputs]
        waits = [(fifo(triggers[t]), a) for t, a in answers.items()]
        subs = [s for s, _ in queued] + [s for s, _ in waits]
        ready.put(("open", i))
        for _ in range(600 * 1000):  # the tracker's stand-in ends it with STOP (and the parent's kill)
            for trigger, what in waits:
                if trigger.recv().payload.to_bytes() == STOP:
                    break
                for sub, then in queued:
                    _drain(sub, then)
                answer(what)
            else:
                continue
            break
    for sub in subs:
        sub.undeclare()
    session.close()
    ready.put(("took", i, taken[0], published[0]))


def _step_tracker(
    robots: int, hub: str, topology: str, pattern: str, rate: float, rounds: Any, ready: Any, go: Any,
    stop: Any,
) -> None:  # fmt: skip
    """The tracker's stand-in: listens on ``hub``; from ``go`` until ``stop`` puts a step's
    messages at ``rate`` (counting the steps in ``rounds``), batched as the realtime tracker
    batches them, and takes what the robots send (``fleet``: commands and plans; ``step``: the
    plans that carry the commands) from a queue once a step, as the realtime tracker does.  Says
    on ``ready`` when open, when it has heard every robot, and at the end how much it took."""
    os.environ["OMP_NUM_THREADS"] = "1"
    import zenoh

    from transport.bus import publisher

    session = _session(hub, topology, listen=True)
    data = _step_payloads(robots)
    heard = _Heard("tracker", robots, ready)
    taken = [0]
    channel = zenoh.handlers.FifoChannel
    takes = ["floor/cmd/*", "floor/plan/**"] if pattern == "fleet" else ["floor/plan/**"]
    drained = [session.declare_subscriber(k, channel(4096)) for k in takes]
    answered = "floor/cmd/" if pattern == "fleet" else "floor/plan/"  # what says a robot answered
    puts: list[tuple[Any, bytes]] = []
    if pattern == "fleet":
        for i in range(robots):
            puts += [
                (publisher(session, f"floor/{what}/r{i}", express=False), data[what])
                for what in ("pose", "odom", "truth")
            ]
        puts += [(publisher(session, "floor/tick", express=False), data["tick"])]
        puts += [(publisher(session, "floor/outcome", express=True), data["outcome"])]
        triggers = ["floor/tick", "floor/outcome"]
    else:
        puts += [(publisher(session, f"floor/meas/r{i}", express=False), data["meas"]) for i in range(robots)]
        triggers = [f"floor/meas/r{i}" for i in range(robots)]
        puts += [(publisher(session, "floor/truth", express=False), data["truths"])]

    def take(sample: Any) -> None:
        sample.payload.to_bytes()
        taken[0] += 1
        key = str(sample.key_expr)
        if key.startswith(answered):
            heard.add(key)

    def drain() -> None:
        for sub in drained:
            _drain(sub, take)

    ready.put(("open", "tracker"))
    go.wait(60)
    period, t_next = 1.0 / rate, time.monotonic()
    for _ in range(int(600 * rate)):  # bounded: at most 10 min
        if stop.is_set():
            break
        drain()
        for pub, payload in puts:
            pub.put(payload)
        with rounds.get_lock():
            rounds.value += 1
        t_next += period
        stop.wait(max(0.0, t_next - time.monotonic()))
    for key in triggers:  # the end, sent at once, for agents blocked on their trigger (``drain``)
        session.put(key, STOP, express=True, congestion_control=zenoh.CongestionControl.BLOCK)
    drain()
    for sub in drained:
        sub.undeclare()
    session.close()
    ready.put(("counted", "tracker", taken[0]))


def _step_supervisor(robots: int, hub: str, topology: str, pattern: str, ready: Any, stop: Any) -> None:
    """The supervisor's stand-in: takes every plan and the true poses (and in ``fleet`` the tick
    and every pose).  Says on ``ready`` when open, when it has heard every robot's plan, and at
    the end how much it took."""
    os.environ["OMP_NUM_THREADS"] = "1"
    session = _session(hub, topology, listen=False)
    heard = _Heard("supervisor", robots, ready)
    taken = [0]

    def on_plan(sample: Any) -> None:
        sample.payload.to_bytes()
        taken[0] += 1
        heard.add(str(sample.key_expr))

    def take(sample: Any) -> None:
        sample.payload.to_bytes()
        taken[0] += 1

    subs = [session.declare_subscriber("floor/plan/**", on_plan)]
    keys = ("floor/tick", "floor/pose/*", "floor/truth/*") if pattern == "fleet" else ("floor/truth",)
    subs += [session.declare_subscriber(k, take) for k in keys]
    ready.put(("open", "supervisor"))
    stop.wait(600)  # bounded: at most 10 min
    for sub in subs:
        sub.undeclare()
    session.close()
    ready.put(("counted", "supervisor", taken[0]))


def _cpu(pids: list[int]) -> dict[str, float]:
    """CPU s so far of ``pids``, by thread kind."""
    from benchmarks.bench_cpu import cpu_by_kind

    out: dict[str, float] = {}
    for pid in pids:
        for kind, cpu in cpu_by_kind(pid).items():
            out[kind] = out.get(kind, 0.0) + cpu
    return out


def measure(
    robots: int, rate: float, seconds: float, mode: str, topology: str, cell: int = 0, pattern: str = "plans"
) -> dict[str, Any]:
    """One row: the processes of ``pattern`` (module docstring), started, linked up (every
    process heard every publisher it subscribes to), measured over ``seconds``, ended.  With a
    tracker's stand-in, the robot-steps are the steps it put in the window, not the nominal rate."""
    from transport.net import free_port, loopback

    ctx = multiprocessing.get_context("spawn")
    ready, go, stop = ctx.Queue(), ctx.Event(), ctx.Event()
    rounds = ctx.Value("q", 0)
    hub = loopback(free_port())
    if pattern == "plans":
        procs = [
            ctx.Process(
                target=_peer, args=(i, robots, hub, topology, mode, rate, cell, ready, go, stop), daemon=True
            )
            for i in range(robots)
        ]
    else:  # the tracker first: it listens on the hub
        procs = [
            ctx.Process(
                target=_step_tracker, args=(robots, hub, topology, pattern, rate, rounds, ready, go, stop),
                daemon=True,
            ),
            *(
                ctx.Process(
                    target=_step_agent, args=(i, robots, hub, topology, pattern, mode, cell, ready, go, stop),
                    daemon=True,
                )
                for i in range(robots)
            ),
            ctx.Process(
                target=_step_supervisor, args=(robots, hub, topology, pattern, ready, stop), daemon=True
            ),
        ]  # fmt: skip
    took: list[float] = []
    counted: dict[str, int] = {}
    try:
        procs[0].start()
        ready.get(timeout=60)  # the hub listens
        for p in procs[1:]:
            p.start()
        for _ in procs[1:]:
            ready.get(timeout=60)  # every session open
        go.set()
        for _ in procs:
            ready.get(timeout=60)  # every process heard every publisher: linked up
        pids = [p.pid for p in procs if p.pid is not None]
        roles = {"agents": pids} if pattern == "plans" else {
            "tracker": pids[:1], "agents": pids[1:-1], "supervisor": pids[-1:]
        }  # fmt: skip
        a, t0, r0 = {r: _cpu(ps) for r, ps in roles.items()}, time.monotonic(), rounds.value
        time.sleep(seconds)  # the measured window
        b, t1, r1 = {r: _cpu(ps) for r, ps in roles.items()}, time.monotonic(), rounds.value
    finally:
        stop.set()
        for _ in procs:
            try:
                msg = ready.get(timeout=30)
            except queue.Empty:
                break
            if msg[0] == "took" and msg[3] > 0:
                took.append(msg[2] / msg[3])
            elif msg[0] == "counted":
                counted[msg[1]] = msg[2]
        deadline = time.monotonic() + 30  # one wait for all: then the stragglers are killed
        for p in procs:
            p.join(timeout=max(0.0, deadline - time.monotonic()))
            if p.is_alive():
                p.kill()
    robot_steps = robots * (rate * (t1 - t0) if pattern == "plans" else r1 - r0)
    split: dict[str, float] = {}
    by_role: dict[str, float] = {}
    for role in b:
        for kind, cpu in b[role].items():
            ms = 1e3 * (cpu - a[role].get(kind, 0.0)) / robot_steps
            split[kind] = split.get(kind, 0.0) + ms
            by_role[role] = by_role.get(role, 0.0) + ms
    steps = rounds.value
    return {
        "pattern": pattern, "mode": mode, "topology": topology, "cell": cell, "rate": rate,
        "ms_per_robot_step": sum(split.values()), "by_thread_ms": split, "by_role_ms": by_role,
        "plans_per_step": sum(took) / len(took) if len(took) == robots else math.nan,
        # Messages the tracker's and the supervisor's stand-ins took per step, over their lives.
        "took_per_step": {who: n / steps for who, n in counted.items()} if steps else {},
    }  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    from benchmarks.bench_cpu import LENGTHS, SCENES, marginal_rows

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robots", type=int, default=16)
    ap.add_argument("--rate", type=float, default=25.0, help="publications per process per second")
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--topology", choices=["mesh", "star"], default="mesh")
    ap.add_argument("--modes", default=",".join(MODES))
    ap.add_argument(
        "--pattern", default="plans",
        help="comma-separated, side by side, of: plans (the plans alone), step (the fewest messages "
        "of a whole step), fleet (those fleet run sends)",
    )  # fmt: skip
    ap.add_argument("--cell", default="0", help="comma-separated cell sizes G, side by side (0: one cell)")
    ap.add_argument("--runs", type=int, default=1, help="runs of every row, interleaved")
    ap.add_argument(
        "--math", action="store_true", help="measure fleet simulate beside, each run: the floor's ratio"
    )
    args = ap.parse_args(argv)
    modes, patterns = args.modes.split(","), args.pattern.split(",")
    try:
        cells = [int(c) for c in args.cell.split(",")]
    except ValueError:
        cells = [-1]
    checks = [
        *((f"--modes: {m!r} is not one of {', '.join(MODES)}", m not in MODES) for m in modes),
        *((f"--pattern: {p!r} is not one of {', '.join(PATTERNS)}", p not in PATTERNS) for p in patterns),
        (f"--modes: a whole step's pattern takes the plans by one of {', '.join(STEP_MODES)}",
         any(p != "plans" for p in patterns) and not set(modes) <= set(STEP_MODES)),
        ("--robots: at least 2 processes", args.robots < 2),
        ("--rate: a finite rate, at least 1/600 a second", not 1 / 600 <= args.rate < math.inf),
        ("--seconds: a finite window of at least 1 s", not 1 <= args.seconds < math.inf),
        ("--runs: at least 1", args.runs < 1),
        (f"--cell: {args.cell!r} is not a comma-separated list of cell sizes (0 or more robots)",
         not all(c >= 0 for c in cells)),
        (f"--robots: --math needs a shipped swap, of {', '.join(map(str, sorted(SCENES)))} robots",
         args.math and args.robots not in SCENES),
    ]  # fmt: skip
    problem = next((why for why, bad in checks if bad), None)
    if problem is not None:
        print(f"bench_zenoh_floor: error: {problem}", file=sys.stderr)
        return 2
    print(f"transport floor: {args.robots} processes, {args.topology}, {args.rate:g} publications/s each, "
          f"{args.seconds:g} s; nproc {os.cpu_count()}, {platform.processor() or platform.machine()}, "
          f"python {platform.python_version()}, load {os.getloadavg()[0]:.1f}", flush=True)  # fmt: skip
    ratio = "least ratio" if args.math else ""
    print(f"{'pattern':<8}{'mode':<10}{'cell':>5}{'plans':>7} {'ms/robot-step':>13}{ratio:>12}  split",
          flush=True)  # fmt: skip
    for _ in range(args.runs):
        math_ms = math.nan
        if args.math:
            (sim,) = marginal_rows(args.robots, LENGTHS, 0, {"fleet simulate": ["simulate"]})
            math_ms = sim["ms_per_robot_step"]
        for pattern, cell, mode in itertools.product(patterns, cells, modes):
            r = measure(args.robots, args.rate, args.seconds, mode, args.topology, cell, pattern)
            parts = ", ".join(
                f"{k} {v:.2f}" for k, v in sorted(r["by_thread_ms"].items(), key=lambda kv: -kv[1])
            )
            if pattern != "plans":
                parts += "; " + ", ".join(f"{k} {v:.2f}" for k, v in r["by_role_ms"].items())
                parts += "; took a step: " + ", ".join(f"{k} {v:.1f}" for k, v in r["took_per_step"].items())
            row = (f"{pattern:<8}{mode:<10}{cell:>5}{r['plans_per_step']:>7.1f}"
                   f" {r['ms_per_robot_step']:>13.2f}")  # fmt: skip
            if args.math:
                row += f"{least_ratio(math_ms, r['ms_per_robot_step']):>12.2f}"
            print(f"{row}  {parts}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
