"""The bus: a process's Zenoh session, its publishers and its inbox of decoded messages.

:func:`open_session` opens the session a process's arguments describe (peer-to-peer on
loopback by default, or a deployment's configuration file).  :class:`Inbox` receives, checks
and keeps what the process subscribes to, and lets its main loop wait, bounded, for what it
needs next; nothing here sleeps.
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from collections.abc import Callable, Container, Sequence
from typing import Any, TypeVar

from ground.geometry import Whereabouts
from ground.scenario import ConfigError
from ground.wire import Digest, Goal, Keys, Message, Plan, RejectCounter, Tick, WireError, decode
from transport.faults import DELIVER, FaultPlan
from transport.net import NetConfig, SecureConfigError, load_config, loopback, size_runtime
from transport.process import log, wait_owning

M = TypeVar("M", bound=Message)
_SENDER_KEYS = ("/clock", "/digest", "/outcome")
"""Keys that name no robot: the message's ``robot`` is its sender (the tracker)."""
DRAIN_CAPACITY = 4096
"""Samples a drained subscription queues between two drains (Zenoh blocks the sender beyond)."""
DRAIN_POLL = 0.001
"""How often :meth:`Inbox.drain_until` looks for a sample not yet in [s]."""


def _step_of(msg: Any) -> int | None:
    """The step (plans, commands, ticks) or sequence number (poses, odometry) of a message."""
    step = getattr(msg, "step", None)
    return getattr(msg, "seq", None) if step is None else step


def net_config(args: argparse.Namespace) -> NetConfig:
    """The loopback configuration of ``--listen``, ``--connect``, ``--mode`` and ``--lease``."""
    mode = getattr(args, "mode", None) or NetConfig.mode
    return NetConfig(
        listen=args.listen or [loopback(0)], connect=list(args.connect), mode=mode,
        lease=NetConfig.lease if args.lease is None else args.lease,
    )  # fmt: skip


def session_config(args: argparse.Namespace) -> Any:
    """The ``zenoh.Config`` of a process: the secure deployment's config file if given, else
    peer-to-peer on loopback; ``--lease``, when given, overrides the file's lease too.  A
    contradiction (``--mode`` with a file, which sets the mode; ``--listen`` on a client, or
    a client without ``--connect``) is one line on stderr and exit 2."""
    mode = getattr(args, "mode", None)
    if getattr(args, "zenoh_config", None) and mode is not None:
        print("error: --mode: the --zenoh-config file sets the session mode", file=sys.stderr)
        raise SystemExit(2)
    if mode == "client" and args.listen:
        print(
            "error: --listen: a Zenoh client listens on nothing (it connects to --connect)", file=sys.stderr
        )
        raise SystemExit(2)
    if mode == "client" and not args.connect:
        print("error: --connect: a Zenoh client needs the router's endpoint", file=sys.stderr)
        raise SystemExit(2)
    if getattr(args, "zenoh_config", None):
        try:
            conf = load_config(args.zenoh_config)
        except ValueError as e:  # SecureConfigError: names the file and the problem
            print(f"error: --zenoh-config: {e}", file=sys.stderr)
            raise SystemExit(2) from None
        if args.lease is not None:
            conf.insert_json5("transport/link/tx/lease", str(round(args.lease * 1000)))
        return conf
    return net_config(args).zenoh()


def open_session(args: argparse.Namespace) -> Any:
    """A Zenoh session (:func:`session_config`).  A session Zenoh cannot open (a client
    whose router is not there: unlike a peer, it does not wait for it) is one line on
    stderr and exit 1.  Every process of the fleet opens its session here, with Zenoh's runtime
    sized by :func:`transport.net.size_runtime`."""
    import zenoh

    conf = session_config(args)
    size_runtime()
    try:
        return zenoh.open(conf)
    except zenoh.ZError as e:
        where = ", ".join(args.connect) or getattr(args, "zenoh_config", None) or "loopback"
        print(f"error: --connect: cannot open a Zenoh session to {where}: {e}", file=sys.stderr)
        raise SystemExit(1) from None


def join_session(
    connect: Sequence[str], zenoh_config: str | None = None, mode: str = "peer",
    names: tuple[str, str] = ("--connect", "--zenoh-config"),
) -> Any:  # fmt: skip
    """A session that joins a running fleet from outside it (``fleet goal``, a script): by its
    hub's endpoints ``connect`` (a Zenoh ``mode`` session, scouting off) or by a Zenoh
    configuration file ``zenoh_config``.  Whatever is wrong, neither given or a session Zenoh
    cannot open, is a :class:`~ground.scenario.ConfigError` naming the argument, as the caller
    calls them (``names``: the endpoints', the file's)."""
    import zenoh

    if zenoh_config is not None:
        try:
            conf = load_config(zenoh_config)
        except SecureConfigError as e:
            raise ConfigError(names[1], str(e)) from None
    elif connect:
        conf = NetConfig(connect=list(connect), mode=mode).zenoh()
    else:
        raise ConfigError(
            names[0], "give the hub's endpoint (e.g. tcp/127.0.0.1:7447) or a Zenoh configuration"
        )
    try:
        return zenoh.open(conf)
    except zenoh.ZError as e:
        raise ConfigError(names[1] if zenoh_config else names[0], f"cannot open a session: {e}") from None


def publisher(session: Any, key: str, express: bool = True) -> Any:
    """A publisher that blocks rather than drops when a receiver lags.

    Lockstep correctness needs every plan, pose and tick delivered; the default
    congestion control drops samples under load.  ``express`` sends at once
    (a write per put, paid in the caller's time); without it Zenoh batches, which
    suits messages nobody waits on (ground truth for the supervisor)."""
    import zenoh

    return session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK, express=express)


def put(session: Any, key: str, payload: bytes, express: bool = True) -> None:
    """Put ``payload`` on ``key`` as a :func:`publisher` would, with no publisher declared: for
    keys that change often (a declaration travels to every peer)."""
    import zenoh

    session.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK, express=express)


GOAL_REPLY_TIMEOUT = 10.0
"""How long an agent has to answer a goal query [s]."""


def goal_reply(problem: str | None) -> bytes:
    """An agent's answer to a goal query, a msgpack map: ``{"ok": True}`` when ``problem`` is
    None, else ``{"ok": False, "reason": problem}`` (one line)."""
    import msgpack

    body: dict[str, Any] = {"ok": True} if problem is None else {"ok": False, "reason": problem}
    return bytes(msgpack.packb(body, use_bin_type=True))


def ask_goal(session: Any, keys: Keys, goal: Goal, timeout: float = GOAL_REPLY_TIMEOUT) -> tuple[bool, str]:
    """Give ``goal`` to its robot's agent as a query on its goal key and wait (at most
    ``timeout`` [s]) for the answer (:func:`goal_reply`): (accepted, the reason if not).

    The agent checks the goal as every goal is checked (:func:`ground.scenario.goal_problem`)
    and, if it accepts it, takes it at its next step."""
    import msgpack

    asked = time.monotonic()
    replies = session.get(keys.goal(goal.robot), payload=goal.encode(), timeout=timeout)
    for reply in replies:
        if reply.ok is None:
            continue
        try:
            got = msgpack.unpackb(reply.ok.payload.to_bytes())
        except (ValueError, msgpack.ExtraData) as e:
            return False, f"unreadable answer ({e})"
        if isinstance(got, dict) and got.get("ok") is True:
            return True, ""
        return False, str(got.get("reason", "refused")) if isinstance(got, dict) else "refused"
    if time.monotonic() - asked < 0.5 * timeout:  # the query ended without an answer
        return False, "no agent answered (it is not running, or access control refused the query)"
    return False, f"no answer from its agent within {timeout:g} s"


class Inbox:
    """Latest decoded messages per (type, robot), with a condition to wait on.

    Subscriber callbacks run on Zenoh's threads; the process's main loop waits
    on :meth:`wait` with a deadline, never sleeps."""

    def __init__(self, keys: Keys, role: str, faults: FaultPlan | None = None):
        self.keys = keys
        self.role = role
        self.faults = faults
        """Injected losses and delays (tests, fleet run --faults); None: none."""
        self.missing: dict[tuple[str, str], set[int]] = {}
        """Steps per (type, robot) that the fault plan dropped or delayed: waiting for them is moot."""
        self.held: list[tuple[int, str, Any, bool]] = []
        """Delayed messages: (release step, type, message, keep)."""
        self.injected = 0
        """Messages the fault plan dropped or delayed so far."""
        self.cond = threading.Condition()
        self.latest: dict[tuple[str, str], Any] = {}
        self.history: dict[tuple[str, str], dict[int, Any]] = {}
        self.live: set[str] = set()
        self.places: dict[str, Whereabouts] = {}
        """Each robot's place token, newest first (:meth:`watch_places`; ``--exchange place``)."""
        self.gone: dict[str, float] = {}
        """When [s, time.monotonic] each robot that is not live lost its liveliness token."""
        self.arrived: dict[tuple[str, str], float] = {}
        """Arrival time [s, time.monotonic] of the latest message per (type, robot)."""
        self.taken: dict[str, int] = {}
        """Messages taken (decoded, checked and stored) so far, by type."""
        self.first: dict[str, float] = {}
        """Arrival time [s, time.monotonic] of the first message of each type."""
        self.rejects = RejectCounter(report=lambda m: log(role, m))
        self._drained: list[tuple[Any, type[Message], bool, Any]] = []
        """Subscriptions read by :meth:`drain`: (subscriber, type, keep, then)."""
        self._awaited: Callable[[], bool] | None = None
        """The predicate the main loop waits on; callbacks wake it only when it holds."""
        self.step = -1
        """The newest step the receiver knows of, its own (:meth:`release`) or the clock's (a tick
        stored): what the lag of place news is measured against."""
        self.first_step: int | None = None
        """The receiver's first step (:meth:`release`): 0 if it started with the fleet."""
        self.lag: int | None = None
        """Plans by place (:meth:`watch_places`): the steps of lag that coordinating within reach
        assumes (docs/method.md §6.7); None: nothing assumed, nothing measured."""
        self.late: dict[str, int] = {}
        """Per robot, the news of its place (a plan, or a place token, newer than any known) that
        came more than :attr:`lag` steps after the step it names (:meth:`_place_news`)."""
        self.heard_late = 0
        """The sum of :attr:`late` [messages]: one int, which any thread reads without the lock."""

    def subscribe(
        self, session: Any, key: str, typ: type[M], keep: bool = False, remote: bool = False,
        drained: bool = False, then: Callable[[M], None] | None = None,
    ) -> Any:  # fmt: skip
        """Declare a subscriber on ``key`` that decodes ``typ`` and checks the robot id against the key.

        ``then``: called with each message stored, under the lock and before the main loop is
        woken (a fact that must not be lost to a newer message, e.g. a script's stop).
        ``remote``: ignore this process's own publications on ``key`` (an agent
        does not need its own plan back).  ``drained``: no callback per sample;
        Zenoh queues the samples and :meth:`drain` takes them in the caller's
        thread.  Each callback wakes a Python thread of zenoh's and takes the GIL
        from the main loop: for the commands the realtime tracker reads at its
        deadline, draining once is cheaper (docs/design.md, "Realtime
        clock").  No callback wakes a waiter for a drained sample: use it for
        messages read at a known time, and :meth:`drain_until` (bounded polls)
        for one that may be a little late."""
        import zenoh

        def on_sample(sample: Any) -> None:
            self._accept(str(sample.key_expr), sample.payload.to_bytes(), typ, keep, time.monotonic(), then)

        handler: Any = on_sample
        if drained:
            handler = zenoh.handlers.FifoChannel(DRAIN_CAPACITY)
        if remote:
            sub = session.declare_subscriber(key, handler, allowed_origin=zenoh.Locality.REMOTE)
        else:
            sub = session.declare_subscriber(key, handler)
        if drained:
            self._drained.append((sub, typ, keep, then))
        return sub

    def unsubscribe(self, sub: Any) -> None:
        """Undeclare a subscriber of :meth:`subscribe` (drained or not)."""
        with self.cond:
            self._drained = [d for d in self._drained if d[0] is not sub]
        sub.undeclare()

    def drain(self) -> int:
        """Take every queued sample of the drained subscriptions; returns how many."""
        got = 0
        for sub, typ, keep, then in self._drained:
            for _ in range(DRAIN_CAPACITY):  # bounded: at most what the queue holds
                sample = sub.try_recv()
                if sample is None:
                    break
                self._accept(
                    str(sample.key_expr), sample.payload.to_bytes(), typ, keep, time.monotonic(), then
                )
                got += 1
        return got

    def drain_until(self, predicate: Callable[[], bool], timeout: float) -> bool:
        """Drain until ``predicate()`` holds (checked under the lock) or ``timeout`` [s]
        passes; True if it holds.  Nothing calls back for a drained sample, so what is
        not in at the first drain is looked for every DRAIN_POLL seconds (bounded)."""
        deadline = time.monotonic() + timeout
        for _ in range(int(timeout / DRAIN_POLL) + 2):  # bounded; the deadline decides
            self.drain()
            with self.cond:
                if predicate():
                    return True
            left = deadline - time.monotonic()
            if left <= 0:
                return False
            threading.Event().wait(min(left, DRAIN_POLL))
        return False

    def _accept(
        self, k: str, payload: bytes, typ: type[Message], keep: bool, now: float, then: Any = None
    ) -> None:
        """Decode, check and store one received payload on key ``k`` (any thread); ``then``, if
        given, is called with the message once stored, before the waiter is woken."""
        try:
            rid = None if k.endswith(_SENDER_KEYS) else self.keys.robot_of(k)
            msg = decode(payload, typ, robot=rid)
        except WireError as e:
            with self.cond:
                self.rejects.reject(k, e)
            return
        with self.cond:
            if isinstance(msg, Digest):
                # Each relayed plan goes the way it would have come on its own key,
                # fault plan included; the digest itself marks the step as relayed.
                for plan in msg.plans():
                    self._admit(f"plan/{plan.robot}", Plan, plan, keep, now)
                self._store(Digest.TYPE, msg, False)
                self._wake()
                return
            tail = k.split("/", 2)[-1]
            if tail.startswith("near/"):  # a plan by place: the fault plan knows it by its robot
                tail = f"plan/{msg.robot}"
            if self._admit(tail, typ, msg, keep, now) and then is not None:
                then(msg)
            self._wake()

    def _admit(self, tail: str, typ: type[Message], msg: Any, keep: bool, now: float) -> bool:
        """Store a decoded message received on key ``fleet/F/<tail>``, unless the
        fault plan drops or delays it (lock held); whether it was stored now."""
        step = _step_of(msg)
        if self.faults is not None and step is not None:
            fate, delay = self.faults.decide(self.role, tail, step)
            if fate != DELIVER or delay:
                self.injected += 1
                self.missing.setdefault((typ.TYPE, msg.robot), set()).add(step)
                if fate == DELIVER:
                    self.held.append((step + delay, typ.TYPE, msg, keep))
                return False
        self._store(typ.TYPE, msg, keep)
        self.taken[typ.TYPE] = self.taken.get(typ.TYPE, 0) + 1
        self.arrived[(typ.TYPE, msg.robot)] = now
        self.first.setdefault(typ.TYPE, now)
        return True

    def _store(self, type_name: str, msg: Any, keep: bool) -> None:
        """Record ``msg`` (lock held): ``latest`` never goes back to an older step."""
        step = _step_of(msg)
        if type_name == Tick.TYPE:
            self.step = max(self.step, msg.step)
        elif type_name == Plan.TYPE and self.lag is not None:
            self._place_news(msg.robot, msg.step)
        old = self.latest.get((type_name, msg.robot))
        if step is None or old is None or (_step_of(old) or 0) <= step:
            self.latest[(type_name, msg.robot)] = msg
        if keep and step is not None:
            self.history.setdefault((type_name, msg.robot), {})[step] = msg

    def release(self, step: int) -> None:
        """Deliver the delayed messages due by ``step`` (the receiver's current step)."""
        with self.cond:
            self.step = max(self.step, step)
            if self.first_step is None:
                self.first_step = step
            due = [h for h in self.held if h[0] <= step]
            if due:
                self.held = [h for h in self.held if h[0] > step]
                for _, type_name, msg, keep in due:
                    self._store(type_name, msg, keep)

    def lost(self, typ: type[Message], robot: str, step: int) -> bool:
        """The fault plan withheld the message of ``step`` (lock held or not: a set look-up)."""
        return step in self.missing.get((typ.TYPE, robot), ())

    def watch_liveliness(self, session: Any) -> Any:
        """Subscribe to the fleet's liveliness tokens (``fleet/F/alive/*``, those already declared
        included): the id a token names joins :attr:`live`, and when the token goes it leaves :attr:`live`
        and is stamped in :attr:`gone`; each change wakes the waiters.  Returns the subscriber."""
        import zenoh

        def on_token(sample: Any) -> None:
            rid = str(sample.key_expr).rsplit("/", 1)[-1]
            with self.cond:
                if sample.kind == zenoh.SampleKind.DELETE:
                    self.live.discard(rid)
                    self.gone[rid] = time.monotonic()
                else:
                    self.live.add(rid)
                    self.gone.pop(rid, None)
                self.cond.notify_all()

        return session.liveliness().declare_subscriber(self.keys.alive(), on_token, history=True)

    def watch_places(self, session: Any, lag: int | None = None) -> Any:
        """Keep :attr:`places` from the place tokens (``--exchange place``): a robot re-declares
        its token as its last committed point enters a new cell, the new before the old goes,
        so the newest token of a robot is where it is, and a token's going changes nothing
        (once its agent is gone, it is where the robot was).  A key that is not a place token
        is rejected and counted.

        ``lag`` [steps]: how late news of a robot's place may come, as coordinating within
        reach assumes; each later one is counted in :attr:`late` (:meth:`_place_news`)."""
        import zenoh

        self.lag = lag

        def on_token(sample: Any) -> None:
            key = str(sample.key_expr)
            try:
                rid, cell, step = self.keys.place_of(key)
            except WireError as e:
                with self.cond:
                    self.rejects.reject(key, e)
                return
            if sample.kind == zenoh.SampleKind.DELETE:
                return  # a token moved on (its newer one came first) or its agent went: it stays
            with self.cond:
                had = self.places.get(rid)
                if had is None or had.since <= step:
                    self._place_news(rid, step)
                    self.places[rid] = Whereabouts(cell, step)

        return session.liveliness().declare_subscriber(self.keys.at(), on_token, history=True)

    def _place_news(self, rid: str, step: int) -> None:
        """News of where robot ``rid`` is as of ``step``, before it is stored (lock held): if it
        is newer than what was known of it (its newest plan, its place token) and came more
        than :attr:`lag` steps after ``step`` (by :attr:`step`), the reach may have been
        computed, meanwhile, from older news than its proof allows: count it, and say so once
        per robot.  A receiver that started with the fleet knew every robot at its start, as
        of step 0; one that joined a running fleet hears of each robot for the first time from
        the tokens' history or its first plan, which is not news of a move and is not counted.

        The count errs on the side of counting: a late plan counts even if the robot's token
        said in time where it went, and the delayed messages a jump releases count each."""
        if self.lag is None or self.step - step <= self.lag:
            return
        plan, where = self.latest.get((Plan.TYPE, rid)), self.places.get(rid)
        known = max(-1 if plan is None else plan.step, -1 if where is None else where.since)
        if known < 0:
            if self.first_step != 0:
                return
            known = 0
        if step <= known:
            return
        self.late[rid] = self.late.get(rid, 0) + 1
        self.heard_late += 1
        if self.late[rid] == 1:
            log(
                self.role,
                f"news of {rid}'s place at step {step} came at step {self.step}, over the {self.lag} steps "
                "of lag that coordinating within reach assumes; further ones are counted",
            )

    def _wake(self) -> None:
        """Wake the main loop if what it waits for now holds (call with the lock held).

        Every needless wake-up costs two context switches and a GIL hand-over;
        in lockstep they were a good part of each step's latency."""
        if self._awaited is None or self._awaited():
            self.cond.notify_all()

    def wait(self, predicate: Callable[[], bool], timeout: float) -> bool:
        """Wait until ``predicate()`` holds (checked under the lock) or ``timeout`` [s] passes.

        Liveliness changes always wake the waiter; messages only when ``predicate`` holds."""
        deadline = time.monotonic() + timeout
        with self.cond:
            self._awaited = predicate
            try:
                while not predicate():
                    left = deadline - time.monotonic()
                    if left <= 0:
                        return False
                    wait_owning(self.cond, left)
                return True
            finally:
                self._awaited = None

    def prune(self, before: int) -> None:
        """Forget kept messages (and tombstones) of steps < ``before``."""
        with self.cond:
            for hist in self.history.values():
                for s in [s for s in hist if s < before]:
                    del hist[s]
            for gone in self.missing.values():
                gone.difference_update([s for s in gone if s < before])

    def newest(self, typ: type[M], robot: str, at_most: int, skip: Container[int] = ()) -> M | None:
        """The newest kept message of ``robot`` whose step is ≤ ``at_most`` and not in
        ``skip`` (lock held): unlike ``get(typ, robot)``, it does not depend on what
        arrived since."""
        hist = self.history.get((typ.TYPE, robot), {})
        if at_most not in skip and (msg := hist.get(at_most)) is not None:
            return msg  # type: ignore[no-any-return]  # the usual case: no scan
        steps = [s for s in hist if s <= at_most and s not in skip]
        if steps:
            return hist[max(steps)]  # type: ignore[no-any-return]
        msg = self.latest.get((typ.TYPE, robot))
        step = 0 if msg is None else _step_of(msg) or 0
        return msg if msg is not None and step <= at_most and step not in skip else None

    def get(self, typ: type[M], robot: str, step: int | None = None) -> M | None:
        """The newest message of type ``typ`` from ``robot`` (it never goes back to an older step), or
        with ``step`` the one kept for that step (a subscription with ``keep``); None if there is none."""
        if step is None:
            return self.latest.get((typ.TYPE, robot))
        return self.history.get((typ.TYPE, robot), {}).get(step)
