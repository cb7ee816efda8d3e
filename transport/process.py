"""The prologue every fleet process shares: its common arguments, its readiness line, its log
lines and its exit.

A process prints one JSON line ``{"event": "ready", "role": ..., "pid": ...}`` on stdout once
its subscriptions are declared (:func:`announce`); the launcher and the tests wait on that line
(with a timeout) instead of sleeping.  Log lines go to stderr, one whole line at a time
(:func:`log`).
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import sys
import threading
from typing import Any, NoReturn, cast

from ground.scenario import MAX_SEED, ROS_DOMAIN_MAX
from transport.faults import FaultPlan, FaultPlanError
from transport.net import MODES, NetConfig, lease_seconds

EXCHANGES = ("mesh", "place", "relay")
"""How the agents' plans travel (``--exchange``): to every agent, to the agents near, or through
the tracker's digest."""


def exchange_for(clock: str, exchange: str = "auto") -> str:
    """The exchange ``auto`` stands for on ``clock``: by place on the realtime clock, where an
    agent's CPU a step must not grow with the fleet; every plan to every agent on lockstep, which
    keeps a run equal to ``fleet simulate`` (whose agents know every robot).  Every agent of a
    fleet must use the same exchange: ``fleet run`` hands its own to all."""
    if exchange != "auto":
        return exchange
    return "place" if clock == "realtime" else "mesh"


def lease_arg(text: str) -> float:
    """argparse type of ``--lease``: seconds in :data:`transport.net.LEASE_RANGE`."""
    try:
        return lease_seconds(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def seed_arg(text: str) -> int:
    """argparse type of ``--seed``: an integer in [0, :data:`ground.scenario.MAX_SEED`]."""
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if not 0 <= n <= MAX_SEED:
        raise argparse.ArgumentTypeError(f"must be in [0, {MAX_SEED}], got {n}")
    return n


def domain_arg(text: str) -> int:
    """argparse type of ``--ros-domain``: an integer in [0, :data:`ground.scenario.ROS_DOMAIN_MAX`]."""
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if not 0 <= n <= ROS_DOMAIN_MAX:
        raise argparse.ArgumentTypeError(f"must be in [0, {ROS_DOMAIN_MAX}], got {n}")
    return n


DEADLINE = 0.5
"""A step's command is due this long after its tick, as a fraction of Ts: the default ``--deadline``
of the robot sides (the simulated tracker, ``epuck_link``) and of the camera tracker, which waits
for the links' reports of a miss until then (docs/design.md, "Missed deadlines")."""


def add_common_args(ap: argparse.ArgumentParser) -> None:
    """Add the options every fleet process takes to ``ap``: ``--scenario``, ``--fleet``, the
    Zenoh network's (``--listen``, ``--connect``, ``--zenoh-config``, ``--lease``, ``--mode``),
    ``--faults``, ``--timeout`` [s], ``--clock``, ``--exchange`` (:func:`add_exchange_arg`) and
    ``--delay-compensation`` (:func:`add_delay_compensation_arg`)."""
    ap.add_argument("--scenario", required=True, help="scenario TOML file")
    ap.add_argument("--fleet", default="lab", help="fleet name in the Zenoh keys (default lab)")
    ap.add_argument("--listen", action="append", default=None, help="Zenoh endpoint to listen on")
    ap.add_argument("--connect", action="append", default=[], help="Zenoh endpoint to connect to")
    ap.add_argument(
        "--faults", default=None, metavar="JSON",
        help="fault plan (JSON text or file, transport/faults.py): drop or delay chosen received messages",
    )  # fmt: skip
    ap.add_argument(
        "--zenoh-config", default=None, metavar="FILE",
        help="Zenoh JSON5 configuration (secure deployment, deploy/README.md); replaces --listen/--connect",
    )  # fmt: skip
    ap.add_argument(
        "--lease", type=lease_arg, default=None, metavar="SECONDS",
        help=f"Zenoh transport lease [s] (default {NetConfig.lease:g}, or the --zenoh-config file's): how "
        "soon a hung or cut-off peer is dropped and its liveliness token goes; a short lease costs "
        "CPU (docs/design.md, \"Liveliness lease\")",
    )  # fmt: skip
    ap.add_argument(
        "--mode", choices=MODES, default=None,
        help="Zenoh session mode (default peer): the star topology makes the hub a router and every "
        "other process a client of it (docs/design.md, \"Topology\")",
    )  # fmt: skip
    ap.add_argument("--timeout", type=float, default=30.0, help="lockstep wait limit [s]")
    ap.add_argument(
        "--clock", choices=["lockstep", "realtime"], default="lockstep",
        help="lockstep: step when every agent answered; realtime: wall-clock steps at Ts",
    )  # fmt: skip
    add_exchange_arg(ap)
    add_delay_compensation_arg(ap)


def add_exchange_arg(ap: argparse.ArgumentParser) -> None:
    """``--exchange``: how the agents' plans travel, for ``fleet run`` and every process of it."""
    ap.add_argument(
        "--exchange", choices=["auto", *EXCHANGES], default="auto",
        help="how plans travel: mesh (every agent to every agent), place (agent to agent, each taking "
        "only the plans of the cells about its own: a few a step whatever the fleet's size; "
        "docs/design.md, \"Plans by place\") or relay (one digest a step from the tracker; "
        "docs/design.md, \"Relayed plans\"); auto (default): place on the realtime clock, mesh on "
        "lockstep, where it keeps fleet run equal to fleet simulate",
    )  # fmt: skip


def add_delay_compensation_arg(ap: argparse.ArgumentParser) -> None:
    """``--delay-compensation``: plans made a step ahead, for ``fleet run``, ``fleet simulate``
    and every process of a fleet."""
    ap.add_argument(
        "--delay-compensation", action=argparse.BooleanOptionalAction, default=True,
        help="plan a step ahead (the default): each agent makes its plan of step k + 1 during step k, "
        "from the prediction, and at tick k + 1 only applies the ancillary law to its measurement, "
        "so no solve lies between a pose and its command; --no-delay-compensation solves each "
        "step's plan after its tick (docs/design.md, \"Delay compensation\")",
    )  # fmt: skip


def fault_plan(args: argparse.Namespace) -> FaultPlan | None:
    """The ``--faults`` plan of a process, or None; a bad plan is one line on stderr and exit 2."""
    if not getattr(args, "faults", None):
        return None
    try:
        return FaultPlan.parse(args.faults)
    except FaultPlanError as e:
        print(f"error: --faults: {e}", file=sys.stderr)
        raise SystemExit(2) from None


def announce(role: str, **info: Any) -> None:
    """Freeze the start-up heap, then print the readiness line the launcher waits for.

    ``gc.freeze`` moves every object alive now (modules, the tube design, the
    solver, Zenoh's) out of the collector's reach, so a full collection during
    the run scans only what the run allocated.  A full collection of an agent's
    start-up heap takes tens of milliseconds, and agents started together would
    run theirs at about the same step: a step in which many miss the deadline."""
    gc.collect()
    gc.freeze()
    print(json.dumps({"event": "ready", "role": role, "pid": os.getpid(), **info}), flush=True)


def log(role: str, msg: str) -> None:
    """One line on stderr, written whole: processes share the launcher's stderr, and
    ``print`` writes the text and the newline separately, which interleaves lines."""
    sys.stderr.write(f"[{role}] {msg}\n")
    sys.stderr.flush()


def wait_owning(cond: threading.Condition, timeout: float | None) -> None:
    """``cond.wait(timeout)`` that holds the lock again however it ends.

    A signal's exception (Ctrl-C in a notebook or a script) can land inside CPython's
    ``Condition.wait`` after it has let go of the lock and before the ``try`` that takes it
    back. The caller's ``with`` would then release a lock it no longer holds, and a
    KeyboardInterrupt would turn into "cannot release un-acquired lock"."""
    try:
        cond.wait(timeout)
    except BaseException:
        if not cast(Any, cond)._is_owned():
            cond.acquire()
        raise


def exit_process(code: int) -> NoReturn:
    """End a fleet process with ``code`` once its ``main`` has cleaned up.

    Zenoh's Python callback threads are not daemons and have been seen to
    outlive a closed session; at interpreter shutdown they kept a finished
    agent alive for good.  ``os._exit`` after flushing cannot hang."""
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)
