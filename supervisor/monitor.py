"""The supervisor process: the live safety judge of a running fleet, its recording and summary.

``python -m supervisor --scenario S --out DIR [--fleet F] [--connect E] [--viewer]``

It subscribes to the true poses, the camera poses, the plans and the clock.  As each step is
complete it hands it to the safety judge (:class:`supervisor.judge.Judge`, the same judge as
``fleet simulate``'s) and to the Rerun recording (:class:`supervisor.recorder.Recorder`).
When the tracker's stop tick arrives (or on SIGTERM) it writes ``DIR/summary.json``,
``DIR/trace.npz`` and ``DIR/recording.rrd``.  It needs no tube design: each robot's footprint
comes with its plans.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from ground.scenario import ConfigError, Scenario, forced_order_lines, load_scenario
from ground.wire import Keys, LinkState, Plan, Pose, Tick, Truth
from supervisor.judge import Judge
from supervisor.recorder import Recorder
from supervisor.trace import Trace, outlines
from transport.bus import Inbox, open_session
from transport.process import add_common_args, announce, log

ROLE = "supervisor"
STOP_GRACE = 5.0
"""Seconds to wait for the last plans after the stop tick [s]."""
GONE_GRACE = 1.0
"""How long after a robot's liveliness token went its plans may still arrive [s]: Zenoh can
deliver the token's removal before the last plan the agent put (seen at the end of a run)."""


def main(argv: list[str] | None = None) -> int:
    """``python -m supervisor``: judge and record the run until the tracker's stop tick or
    SIGTERM, then write ``summary.json``, ``trace.npz`` and ``recording.rrd`` in ``--out``; returns the
    exit code (0 once written, 2 bad input)."""
    ap = argparse.ArgumentParser(prog="python -m supervisor", description=__doc__.splitlines()[0])
    add_common_args(ap)
    ap.add_argument("--out", required=True, help="output directory")
    ap.add_argument("--viewer", action="store_true", help="also stream to a live Rerun viewer")
    ap.add_argument(
        "--nice", type=int, default=None,
        help="scheduling niceness increment (default: 10 on the realtime clock, where the logger "
        "yields the CPU to the control loop's deadlines; 0 in lockstep, which has no deadline)",
    )  # fmt: skip
    args = ap.parse_args(argv)
    nice = niceness(args.clock, args.nice)
    if nice:
        os.nice(nice)
    try:
        scn = load_scenario(args.scenario)
    except ConfigError as e:
        print(f"supervisor: error: {e}", file=sys.stderr)
        return 2
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    keys = Keys(args.fleet)
    session = open_session(args)
    inbox = Inbox(keys, ROLE)
    subs = [
        inbox.subscribe(session, keys.truth(), Truth, keep=True),
        inbox.subscribe(session, keys.pose(), Pose, keep=True),
        inbox.subscribe(session, keys.plan(), Plan, keep=True),
        inbox.subscribe(session, keys.clock, Tick, keep=True),
        inbox.subscribe(session, keys.link(), LinkState),
        inbox.watch_liveliness(session),
    ]
    stopping = threading.Event()

    def on_term(signum: int, frame: Any) -> None:
        stopping.set()
        with inbox.cond:
            inbox.cond.notify_all()

    signal.signal(signal.SIGTERM, on_term)
    watch = Monitor(scn, inbox, Recorder(out / "recording.rrd", scn, args.viewer))
    token = session.liveliness().declare_token(keys.alive(ROLE))
    announce(ROLE)
    completed = False
    try:
        while not stopping.is_set():
            inbox.wait(lambda: stopping.is_set() or watch.progress(), 0.2)
            watch.take()
            done = watch.finished()
            if done is not None:
                completed = done
                break
    finally:
        summary = watch.summary(completed)
        summary["clock"] = args.clock
        watch.trace().save(out / "trace.npz")
        watch.recorder.close()
        (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
        log(ROLE, f"summary written to {out / 'summary.json'} after {watch.judge.steps} steps")
        token.undeclare()
        for s in subs:
            s.undeclare()
        session.close()
    return 0


def niceness(clock: str, asked: int | None) -> int:
    """The supervisor's niceness increment: ``asked`` (``--nice``), else 10 on the realtime clock
    and 0 in lockstep.  On the realtime clock the logger must not take the CPU from a step's
    deadline.  Lockstep has no deadline, and a niced logger on a busy machine gets almost none of
    it (weight 110 against 1024 per busy process): it fell hundreds of steps behind, and the run
    ended before it had judged them all."""
    if asked is not None:
        return asked
    return 10 if clock == "realtime" else 0


class Monitor:
    """Takes the fleet's messages from the inbox one complete step at a time, in step order,
    and hands them to the judge and the recorder; logs agents leaving and returning."""

    def __init__(self, scn: Scenario, inbox: Inbox, recorder: Recorder):
        self.scn = scn
        self.inbox = inbox
        self.recorder = recorder
        self.judge = Judge(scn)
        self.ids = [r.id for r in scn.robots]
        self.Ts = scn.controller.Ts
        self.k_truth = self.k_plan = self.k_tick = 0
        """The next sample, plan step and tick to take."""
        self.t0 = time.monotonic()
        self.live_seen: set[str] = set()
        self.ever_live: set[str] = set()
        self.off_plan: set[str] = set()
        """Robots whose robot side did not apply the last command (each episode logged once)."""
        self.stop_deadline = 0.0
        self.layout_said = False
        """Whether the layout's forced order has been logged (:meth:`_say_layout`)."""
        self.layout: threading.Thread | None = None
        """The thread that logs it; joined before the summary (the recording closes after)."""
        self.link_down: set[str] = set()
        """Robots whose radio link is down (epuck_link's LinkState)."""
        self.lost_at: dict[str, int] = {}
        """The tick each robot's last outage began at, as its LinkState says."""

    def progress(self) -> bool:
        """Something to take: a complete sample of ground truth or a complete step of plans
        (call with the inbox's lock held)."""
        return _step_in(self.inbox, self.ids, self.k_truth) != "wait" or (
            _plan_step(self.inbox, self.ids, self.k_plan) is not None
        )

    def take(self) -> None:
        """Judge and record every step complete now.  Complete steps are taken under the inbox's
        lock and judged and logged outside it, so Zenoh's callbacks never wait on Rerun."""
        inbox, ids = self.inbox, self.ids
        truths: list[tuple[dict[str, Truth], dict[str, Pose | None]] | None] = []
        plan_steps: list[tuple[dict[str, Plan], set[str], set[str]]] = []
        with inbox.cond:
            while (state := _step_in(inbox, ids, self.k_truth + len(truths))) != "wait":
                kk = self.k_truth + len(truths)
                if state == "skip":
                    truths.append(None)  # lost on the way: this sample is not judged
                    continue
                truth = {r: tr for r in ids if (tr := inbox.get(Truth, r, kk)) is not None}
                truths.append((truth, {r: inbox.get(Pose, r, kk) for r in ids}))
            while (step_plans := _plan_step(inbox, ids, kk := self.k_plan + len(plan_steps))) is not None:
                # Tick k + 1 says whose plan of step k was not executed (its command missed).
                t_next = inbox.get(Tick, "tracker", kk + 1)
                plan_steps.append(
                    (
                        step_plans,
                        set() if t_next is None else {*t_next.fallback, *t_next.braked},
                        set() if t_next is None else set(t_next.braked),
                    )
                )
            newest = inbox.get(Tick, "tracker")
            ticks = [] if newest is None else [
                t for kk in range(self.k_tick, newest.step + 1) if (t := inbox.get(Tick, "tracker", kk))
            ]  # fmt: skip
            if newest is not None:
                self.k_tick = max(self.k_tick, newest.step + 1)
        for item in truths:
            if item is None:
                self.judge.skipped()
            else:
                truth, measured = item
                self.judge.truth(
                    {r: (t.x, t.y, t.theta) for r, t in truth.items()},
                    {r: None if m is None else (m.x, m.y, m.theta) for r, m in measured.items()},
                )
                self.recorder.truth(self.k_truth, self.Ts, truth, measured)
            self.k_truth += 1
        for plans, skipped, braked in plan_steps:
            blocked, walled = dict(self.judge.blocked), dict(self.judge.walled)
            no_room = dict(self.judge.no_room)
            self.judge.plans(plans, skipped, braked)
            self.recorder.plans(self.k_plan, self.Ts, plans)
            self._blocked(self.k_plan, blocked)
            self._no_room(self.k_plan, no_room)
            self._walled(self.k_plan, walled)
            self._displaced(self.k_plan)
            self.k_plan += 1
        if not self.layout_said and self.judge.footprint is not None:
            # Off the judging loop: the free-space search takes a good part of a second.
            self.layout_said = True
            self.layout = threading.Thread(target=self._say_layout, daemon=True)
            self.layout.start()
        for t in ticks:
            self._applied(t)
        self.recorder.flush_if_due()
        if truths or plan_steps:
            self.stop_deadline = 0.0  # still making progress: the grace period restarts
        self._liveliness()

    def _say_layout(self) -> None:
        """An event per robot whose way home the scenario's other goals wall in, once the first
        plans have given the footprint (docs/method.md §7, "Where the layout forces an order");
        the summary keeps the same (``forced_order``, worked out once by the judge)."""
        for line in forced_order_lines(self.judge.layout() or {}):
            self.recorder.event(f"layout: {line}", "WARN")
        arr = self.judge.arrival()
        for line in [] if arr is None else arr.lines():
            self.recorder.event(f"order of arrival: {line}")

    def _blocked(self, k: int, before: dict[str, str]) -> None:
        """An event and a log line for each robot whose goal a stopped robot came to cover at
        step k (``goal_blocked``), or no longer covers."""
        for rid, by in self.judge.blocked.items():
            if by == before.get(rid, ""):
                continue
            if by:
                self.recorder.event(
                    f"goal_blocked: {rid}: its goal is covered by {by}, which stands there", "WARN"
                )
                log(ROLE, f"step {k}: {rid}: goal blocked by {by}")
            else:
                self.recorder.event(f"{rid}: its goal is clear again")
                log(ROLE, f"step {k}: {rid}: goal clear again")

    def _no_room(self, k: int, before: dict[str, str]) -> None:
        """An event and a log line for each robot that found no room to make way for a robot
        that goes first at step k (``no_room``: assumption (A) of docs/method.md §7 failing), or
        no longer lacks it (it has room, or no longer makes way)."""
        for rid, by in self.judge.no_room.items():
            if by == before.get(rid, ""):
                continue
            if by:
                self.recorder.event(f"no_room: {rid}: no room to make way for {by}", "WARN")
                log(ROLE, f"step {k}: {rid}: no room to make way for {by}")
            elif before.get(rid):
                self.recorder.event(f"{rid}: no longer without room to make way")
                log(ROLE, f"step {k}: {rid}: no longer without room to make way")

    def _walled(self, k: int, before: dict[str, list[str]]) -> None:
        """An event and a log line for each robot whose way home the parked robots came to wall
        in at step k (``walled_in``, :meth:`Judge._walls`), or no longer wall in."""
        now = self.judge.walled
        for rid, by in now.items():
            if by != before.get(rid):
                who = ", ".join(by)
                self.recorder.event(f"walled_in: {rid}: its way home is walled in by {who}, parked", "WARN")
                log(ROLE, f"step {k}: {rid}: way home walled in by {who}, parked")
        for rid in set(before) - set(now):
            self.recorder.event(f"{rid}: its way home is open again")
            log(ROLE, f"step {k}: {rid}: way home open again")

    def _displaced(self, k: int) -> None:
        """An event for each parked robot that left its goal at step k (``displaced``,
        :attr:`Judge.news`), and an event and a log line where that makes two robots that have
        displaced each other in turn twice or more (``traded_places``)."""
        for ep in self.judge.news:
            r, by = ep["robot"], ep["for"]
            self.recorder.event(f"displaced: {r}: left its goal" + (f" for {by}" if by else ""))
            if ep["traded"]:
                said = f"{min(r, by)} and {max(r, by)} have displaced each other in turn {ep['traded']} times"
                self.recorder.event(f"traded_places: {said}", "WARN")
                log(ROLE, f"step {k}: {said}")

    def _applied(self, t: Tick) -> None:
        """What the robot sides applied over step t.step − 1 (Tick.fallback, Tick.braked)."""
        for rid, kind in [*((r, "candidate") for r in t.fallback), *((r, "braked") for r in t.braked)]:
            if rid not in self.judge.robot:
                continue
            self.judge.off_plan(rid, kind)
            if rid not in self.off_plan:
                what = "on its shifted candidate" if kind == "candidate" else "braked"
                self.recorder.event(f"{rid}: command of step {t.step - 1} not applied; robot {what}", "WARN")
        now_off = set(t.fallback) | set(t.braked)
        for rid in sorted(self.off_plan - now_off):
            self.recorder.event(f"{rid}: commands applied again from step {t.step - 1}")
        self.off_plan = now_off

    def _liveliness(self) -> None:
        """Log who left or came back since the last look, outside the inbox's lock."""
        with self.inbox.cond:
            tick = self.inbox.get(Tick, "tracker")
            live = set(self.inbox.live)
            self.inbox.prune(min(self.k_truth, self.k_plan) - 1)
            links = {r: ls for r in self.ids if (ls := self.inbox.get(LinkState, r)) is not None}
        for rid, ls in links.items():
            self.judge.link_state(rid, ls.up, ls.step, ls.lost)
            # An outage is known by the tick it began at: one that began and ended between two
            # looks shows as an "up" state with a loss not seen before.
            if ls.lost >= 0 and ls.lost != self.lost_at.get(rid):
                self.lost_at[rid] = ls.lost
                self.link_down.add(rid)
                self.judge.link_lost(rid)
                self.recorder.event(
                    f"{rid}: link lost at step {ls.lost}; driving on uncontrolled at wheel speeds "
                    f"({ls.left}, {ls.right}) steps/s, up to {ls.speed:.3f} m/s", "WARN",
                )  # fmt: skip
                log(ROLE, f"step {ls.lost}: {rid}: link lost")
            if ls.up and rid in self.link_down:
                self.link_down.discard(rid)
                self.recorder.event(
                    f"{rid}: link back at step {ls.step}; robot stopped, its agent starts again at "
                    f"step {ls.back}"
                )
                log(ROLE, f"step {ls.step}: {rid}: link back")
        changed = sorted(live ^ self.live_seen)
        for rid in changed:
            what = "joined" if rid in live else "left"
            self.recorder.event(f"{rid} {what} the fleet", "INFO" if rid in live else "WARN")
        if tick is None or not tick.stop:  # neither the start nor the end of the run
            for alive, what in ((False, "not alive"), (True, "alive again")):
                who = [r for r in changed if r in self.ever_live and (r in live) == alive]
                if who:
                    verb = "is" if len(who) == 1 else "are"
                    log(ROLE, f"step {self.k_truth}: {', '.join(who)} {verb} {what}")
        self.live_seen = live
        self.ever_live |= live

    def finished(self) -> bool | None:
        """None while the run goes on; once it has ended, whether every step was judged: its
        ground truth and its plans (a robot whose agent died is left out of a step's plans once
        it is gone, :func:`_plan_step`).  After the stop tick it waits until every step is in, or
        nothing arrived for a grace period; then the run did not complete (e.g. no agent ever
        planned: the tracker's clock ran with nobody to steer, and nothing was judged)."""
        with self.inbox.cond:
            tick = self.inbox.get(Tick, "tracker")
        if tick is None or not tick.stop:
            return None
        self.stop_deadline = self.stop_deadline or time.monotonic() + STOP_GRACE
        if self.k_truth > tick.step and self.k_plan >= tick.step:
            return True
        if time.monotonic() > self.stop_deadline:
            return False
        return None

    def summary(self, completed: bool) -> dict[str, Any]:
        """The judge's summary, with the tracker's deadline misses and the rejected payloads."""
        if self.layout is not None:
            self.layout.join(timeout=30.0)
        inbox = self.inbox
        with inbox.cond:
            start = inbox.first.get(Truth.TYPE, self.t0)
            tick = inbox.get(Tick, "tracker")
            end = inbox.arrived.get((Tick.TYPE, "tracker")) if tick is not None and tick.stop else None
        # Wall time from the first ground truth's arrival to the stop tick's, taken in the
        # subscriber callbacks: the fleet's time, not this process's logging backlog.
        wall = (end if end is not None else time.monotonic()) - start
        summary = self.judge.summary(completed, wall)
        summary["deadline_misses"] = 0 if tick is None else tick.misses
        summary["rejected_payloads"] = inbox.rejects.total
        return summary

    def trace(self) -> Trace:
        """The run's trace (``trace.npz``): true poses and executed references per sample."""
        judge, ids = self.judge, self.ids
        T = min(len(judge.poses[r]) for r in ids)
        return Trace(
            name=self.scn.name, ids=ids, Ts=self.Ts,
            poses=np.array([judge.poses[r][:T] for r in ids]).reshape(len(ids), T, 3),
            refs=judge.trace_refs(T), goals=np.array([judge.goals[r] for r in ids]),
            footprint=math.nan if judge.footprint is None else judge.footprint,
            robot_radius=judge.radius, arena=self.scn.arena, obstacles=outlines(self.scn.obstacles),
        )  # fmt: skip


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
    if tick is None or k >= tick.step:
        # The tick of step k + 1 says whose plans of step k were executed; none comes for the
        # stop step, whose plans (made ahead, with delay compensation) are never executed.
        return None
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
