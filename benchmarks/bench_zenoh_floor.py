"""The transport's floor: what a fleet's message pattern costs with no fleet code at all.

    python benchmarks/bench_zenoh_floor.py [--robots 16] [--rate 25] [--seconds 20] [--cell 0]

N processes (spawned), configured as ``fleet run`` configures its processes
(``ground.net.NetConfig``: peer mode, multicast scouting off, the first listening on a
loopback port, the others connecting to it and finding each other by gossip, a full mesh;
or ``--topology star``: the first a router, the others its clients).  Each publishes one
978-byte payload (a plan's size at N = 20) ``--rate`` times a second and subscribes to every
other's, as an agent in the mesh does.  How a process takes the samples:

* ``callback``: a Python callback that only counts (Zenoh runs it on a Python thread of its own);
* ``decode``: the same callback decoding each payload as a :class:`ground.wire.Plan`;
* ``drain``: no callback; the main thread takes the queued samples from a FIFO channel once
  per period (``ground.bus.Inbox.drain``'s way);
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

With ``--math`` each run also measures ``fleet simulate`` on the shipped swap of N robots, the
math alone, as ``fleet bench --cpu`` does (``bench_cpu.marginal_rows``), and each row prints
(math + floor) / math: the least target 1 ratio that a fleet sending at most this row's messages
could reach.  It is a lower bound: the fleet's tracker and supervisor, and each agent's tick,
command and outcome, add messages that the floor does not send.
"""

from __future__ import annotations

import argparse
import math
import multiprocessing
import os
import platform
import queue
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

MODES = ("callback", "decode", "drain", "direct")


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

    from ground.net import NetConfig, loopback
    from ground.wire import Plan, WireError, decode

    if i == 0:
        cfg = NetConfig(listen=[hub], mode="router" if topology == "star" else "peer")
    else:
        cfg = NetConfig(listen=[loopback(0)], connect=[hub], mode="client" if topology == "star" else "peer")
    session = zenoh.open(cfg.zenoh())
    heard: set[str] = set()
    mine, cells, expected = cells_of(i, robots, cell)
    taken = [0]

    def took(key: str) -> None:
        taken[0] += 1
        if len(heard) < expected:
            heard.add(key)
            if len(heard) == expected:
                ready.put(("heard all", i))

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
                for _ in range(4096):
                    s = sub.try_recv()
                    if s is None:
                        break
                    s.payload.to_bytes()
                    took(str(s.key_expr))
        t_next += period
        stop.wait(max(0.0, t_next - time.monotonic()))  # the publication rate
    for sub in subs:
        sub.undeclare()
    session.close()
    ready.put(("took", i, taken[0], published))


def _cpu(pids: list[int]) -> dict[str, float]:
    """CPU s so far of ``pids``, by thread kind."""
    from bench_cpu import _tasks, _thread_kind

    out: dict[str, float] = {}
    for pid in pids:
        for tid, (name, cpu) in _tasks(pid).items():
            kind = _thread_kind(pid, tid, name)
            out[kind] = out.get(kind, 0.0) + cpu
    return out


def measure(
    robots: int, rate: float, seconds: float, mode: str, topology: str, cell: int = 0
) -> dict[str, Any]:
    from ground.net import free_port, loopback

    ctx = multiprocessing.get_context("spawn")
    ready, go, stop = ctx.Queue(), ctx.Event(), ctx.Event()
    hub = loopback(free_port())
    procs = [
        ctx.Process(
            target=_peer, args=(i, robots, hub, topology, mode, rate, cell, ready, go, stop), daemon=True
        )
        for i in range(robots)
    ]
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
        a, t0 = _cpu(pids), time.monotonic()
        time.sleep(seconds)  # the measured window
        b, t1 = _cpu(pids), time.monotonic()
    finally:
        stop.set()
        took: list[float] = []
        for _ in procs:
            try:
                msg = ready.get(timeout=30)
            except queue.Empty:
                break
            if msg[0] == "took" and msg[3] > 0:
                took.append(msg[2] / msg[3])
        for p in procs:
            p.join(timeout=30)
            if p.is_alive():
                p.kill()
    robot_steps = robots * rate * (t1 - t0)
    split = {k: 1e3 * (b[k] - a.get(k, 0.0)) / robot_steps for k in b}
    total = sum(split.values())
    return {
        "mode": mode, "topology": topology, "cell": cell, "ms_per_robot_step": total, "by_thread_ms": split,
        "plans_per_step": sum(took) / len(took) if len(took) == robots else math.nan,
    }  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    from bench_cpu import LENGTHS, SCENES, marginal_rows

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robots", type=int, default=16)
    ap.add_argument("--rate", type=float, default=25.0, help="publications per process per second")
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--topology", choices=["mesh", "star"], default="mesh")
    ap.add_argument("--modes", default=",".join(MODES))
    ap.add_argument("--cell", default="0", help="comma-separated cell sizes G, side by side (0: one cell)")
    ap.add_argument("--runs", type=int, default=1, help="runs of every row, interleaved")
    ap.add_argument(
        "--math", action="store_true", help="measure fleet simulate beside, each run: the floor's ratio"
    )
    args = ap.parse_args(argv)
    modes = args.modes.split(",")
    try:
        cells = [int(c) for c in args.cell.split(",")]
    except ValueError:
        cells = [-1]
    checks = [
        *((f"--modes: {m!r} is not one of {', '.join(MODES)}", m not in MODES) for m in modes),
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
    print(f"{'mode':<10}{'cell':>5}{'plans':>7} {'ms/robot-step':>13}{ratio:>12}  split", flush=True)
    for _ in range(args.runs):
        math_ms = math.nan
        if args.math:
            (sim,) = marginal_rows(args.robots, LENGTHS, 0, {"fleet simulate": ["simulate"]})
            math_ms = sim["ms_per_robot_step"]
        for cell in cells:
            for mode in modes:
                r = measure(args.robots, args.rate, args.seconds, mode, args.topology, cell)
                parts = ", ".join(
                    f"{k} {v:.2f}" for k, v in sorted(r["by_thread_ms"].items(), key=lambda kv: -kv[1])
                )
                row = f"{mode:<10}{cell:>5}{r['plans_per_step']:>7.1f} {r['ms_per_robot_step']:>13.2f}"
                if args.math:
                    row += f"{least_ratio(math_ms, r['ms_per_robot_step']):>12.2f}"
                print(f"{row}  {parts}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
