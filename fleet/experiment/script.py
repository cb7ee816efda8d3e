"""A script on the fleet's bus: the :class:`fleet.experiment.api.Backend` of a process fleet.

``Fleet.launch(..., processes=True)`` starts the processes of ``fleet run`` with the tracker in
scripted mode (:func:`fleet.running.launch.start_fleet`); ``Fleet.connect`` joins a fleet that runs.
Either way the script opens one Zenoh session, subscribes to the ground truth, the measured
poses, the plans and the clock, and declares its liveliness token ``fleet/F/alive/script``.

On a lockstep fleet it launched, the script holds the clock: the tracker publishes sample k (the
ground truth and the measured poses), then waits for the script's permit of step k
(:class:`ground.wire.Script`).  Goals go to the agents as Zenoh queries on their goal keys; each
agent answers whether it accepted its goal, and only then does the script permit the step, so
every goal is taken at exactly the step that follows the sample the script saw.  That is how the
same script gives the same trajectories here and on the in-process simulator.

When the script leaves, it tells the tracker to end the run; if it dies instead, its liveliness
token goes and the tracker ends the run by itself (no orphans).
"""

from __future__ import annotations

import threading
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from fleet.experiment.backend import Event, Sample
from ground.geometry import Array
from ground.scenario import ConfigError, Scenario
from ground.wire import MAX_BATCH, SCRIPT, Goal, Keys, Plan, Pose, Script, Tick, Truth
from supervisor.judge import SOLVED
from transport.bus import GOAL_REPLY_TIMEOUT, Inbox, ask_goal, join_session

RUN_OPTIONS = (
    "exchange", "topology", "lease", "viewer", "faults", "hub", "ros2", "ros_domain", "ros_listen", "fork",
)  # fmt: skip
"""``Fleet.launch`` options a process fleet takes (``fleet run``'s)."""
SAMPLE_TIMEOUT = 60.0
"""How long the next sample may take before the fleet counts as gone [s, wall time]."""
PLAN_GRACE = 10.0
"""On a held clock, how long a live agent's plan may trail the samples before it counts as
stale [s, wall time] (:meth:`ProcessFleet._collect_events`)."""
LOG = "fleet.log"
"""The file in the run's directory that a launched fleet's processes write their log lines to."""


class ProcessFleet:
    """A fleet of processes, seen from a script (see the module docstring)."""

    def __init__(self, scn: Scenario, session: Any, keys: Keys, launched: Any = None, hold: bool = False):
        self.scenario = scn
        self.session = session
        self.keys = keys
        self.launched = launched
        """The processes this script started (:class:`fleet.running.launch.Launched`), or None."""
        self.out: Path | None = None if launched is None else launched.out
        self.hold = hold
        """This script permits the steps (a lockstep fleet it launched)."""
        self.realtime = not hold
        self.ids = [r.id for r in scn.robots]
        self.Ts = scn.controller.Ts
        self.inbox = inbox = Inbox(keys, SCRIPT)
        self.subs = [
            inbox.subscribe(session, keys.truth(), Truth, keep=True),
            inbox.subscribe(session, keys.pose(), Pose, keep=True),
            inbox.subscribe(session, keys.plan(), Plan, keep=True),
            inbox.subscribe(session, keys.clock, Tick, keep=True),
            inbox.watch_liveliness(session),
        ]
        self.permit = session.declare_publisher(keys.script) if hold else None
        self.token = session.liveliness().declare_token(keys.alive(SCRIPT))
        self.k = -1
        """The newest complete sample."""
        self._goals = {r.id: np.array(r.goal, dtype=float) for r in scn.robots}
        self._given: dict[str, tuple[int, Array]] = {}
        """The goals this script gave, by robot, with the sample each was given at.  Until its
        robot's plans carry it (planning ahead, from the plan of the step after next, which
        may still be on its way when the next sample is in), an agent checking a goal against
        that robot's newest plan would see the goal before: so it goes in the batch of every
        goal given at the next sample too (:meth:`send`)."""
        self.footprint = 0.0
        self._events: list[Any] = []
        self._dead: set[str] = set()
        self._was_live: set[str] = set()
        """Every robot whose agent this session has seen live."""
        self._unseen: dict[int, set[str]] = {}
        """Per step, the robots whose plan of it has not come yet."""
        self._lock = threading.Lock()
        self.log: Any = None
        """The processes' log file, while they run."""
        self.verdict: str | None = None
        """Once closed: why the run failed, in one line (``fleet run``'s), or None."""

    # ------------------------------------------------------------------ making one
    @classmethod
    def launch(
        cls, path: str | Path, scn: Scenario, clock: str, seed: int | None, out: str | Path | None,
        delay_compensation: bool = True, **options: Any,
    ) -> ProcessFleet:  # fmt: skip
        """Start the processes of ``fleet run`` for a script, and join them (``delay_compensation``:
        every agent plans a step ahead)."""
        from agent.tube import validated_design
        from fleet.running.launch import LaunchError, start_fleet

        for name in options:
            if name not in RUN_OPTIONS:
                raise ConfigError(name, f"is not an option of a process fleet ({', '.join(RUN_OPTIONS)})")
        design = validated_design(scn)  # bad designs fail here, once, not in every agent
        run_dir = (Path(out) if out is not None else Path("out") / scn.name).resolve()
        run_dir.mkdir(parents=True, exist_ok=True)
        log = (run_dir / LOG).open("w")  # the processes' log lines, not the script's output
        try:
            launched = start_fleet(
                str(Path(path).resolve()), [r.id for r in scn.robots], run_dir, seed, clock=clock,
                scripted=True, stderr=log, delay_compensation=delay_compensation, **options,
            )  # fmt: skip
        except LaunchError as e:
            log.close()
            raise ConfigError("processes", f"the fleet did not start: {e} (see {run_dir / LOG})") from None
        mode = "client" if options.get("topology") == "star" else "peer"  # the star's hub routes
        try:
            session = join_session([launched.hub], mode=mode, names=("processes", "zenoh_config"))
        except BaseException:
            launched.stop()
            log.close()
            raise
        me = cls(scn, session, Keys("lab"), launched, hold=clock == "lockstep")
        me.log = log
        me.footprint = float(design.footprint)
        try:
            me._first_sample()
            me._agents_live()
        except BaseException:
            me.close()
            raise
        return me

    @classmethod
    def attach(cls, scn: Scenario, connect: list[str], zenoh_config: str | None, fleet: str) -> ProcessFleet:
        """Join a fleet that is running, by its hub's endpoints or a Zenoh configuration file."""
        from agent.tube import validated_design

        session = join_session(connect, zenoh_config, names=("connect", "zenoh_config"))
        me = cls(scn, session, Keys(fleet))
        me.footprint = float(validated_design(scn).footprint)
        try:
            me._first_sample()
            with me.inbox.cond:  # the goals in force: the newest plans carry them
                for rid in me.ids:
                    pl = me.inbox.get(Plan, rid)
                    if pl is not None:
                        me._goals[rid] = pl.goal.copy()
        except BaseException:
            me.close()
            raise
        return me

    # ------------------------------------------------------------------ Backend
    def sample(self) -> Any:
        """Sample k (:attr:`k`): each robot's true pose of step k and its newest measured pose
        of a step ≤ k, (3,) [m, m, rad]; a robot with none yet is left out."""
        k, inbox = self.k, self.inbox
        with inbox.cond:
            truth = {r: _pose(t) for r in self.ids if (t := inbox.get(Truth, r, k)) is not None}
            measured = {r: _pose(p) for r in self.ids if (p := inbox.newest(Pose, r, k)) is not None}
        return Sample(k, truth, measured)

    def advance(self) -> bool:
        """Lockstep, holding the clock: permit step k, then wait for sample k + 1.  Otherwise
        wait for a newer sample than k; a script slower than the clock skips samples."""
        k = self.k
        if self.permit is not None:
            self.permit.put(Script(robot=SCRIPT, step=k, stop=False).encode())
        if not self._wait_sample(k + 1):
            return False
        self.k = k + 1 if self.hold else self._newest()
        for step in range(k, self.k):
            self._collect_events(step)
        return True

    def _newest(self) -> int:
        """The newest sample whose ground truth has come for every robot that has any."""
        with self.inbox.cond:
            seqs = [t.seq for r in self.ids if (t := self.inbox.get(Truth, r)) is not None]
        return min(seqs, default=self.k)

    def goals(self) -> dict[str, Array]:
        """A copy of each robot's goal (2,) [m] as this script knows it: the scenario's (or,
        for a fleet it joined, the newest plans'), then those :meth:`send` gave."""
        return {r: g.copy() for r, g in self._goals.items()}

    def send(self, goals: Mapping[str, Array]) -> dict[str, str]:
        """Each goal as a query to its agent, with the rest of the batch; robot → reason for
        each refusal.  If one is refused, the accepted ones are given back their goals."""
        refused, accepted = {}, []
        recent = {r: g for r, (at, g) in self._given.items() if at >= self.k - 1 and r not in goals}
        for rid, g in goals.items():
            batch = {**recent, **{r: np.asarray(q, dtype=float) for r, q in goals.items()}}
            del batch[rid]
            batch = dict(list(batch.items())[-MAX_BATCH:])  # this call's own goals last, all kept
            ok, why = self._ask(rid, np.asarray(g, dtype=float), batch)
            if ok:
                accepted.append(rid)
            else:
                refused[rid] = why
        if refused and accepted:
            old = {r: self._goals[r] for r in accepted}
            for rid in accepted:
                self._ask(rid, old[rid], {r: q for r, q in old.items() if r != rid})
        if not refused:
            for rid, g in goals.items():
                self._goals[rid] = np.asarray(g, dtype=float).copy()
                self._given[rid] = (self.k, self._goals[rid])
        return refused

    @property
    def processes(self) -> dict[str, int]:
        """The pid of every process this script started, by role."""
        return {} if self.launched is None else dict(self.launched.pids)

    def events(self) -> list[Any]:
        """The events collected since the last call."""
        with self._lock:
            out, self._events = self._events, []
        return out

    def close(self) -> dict[str, Any] | None:
        """End a fleet this script launched (its stop :class:`~ground.wire.Script`, then up to
        120 s for the run's end and :attr:`verdict`, then what is left stopped by pid), then close the
        log, the subscribers, the token and the session.  Returns the run's summary, None for a fleet it
        joined."""
        summary = None
        try:
            if self.launched is not None:
                stop = Script(robot=SCRIPT, step=max(self.k, -1), stop=True).encode()
                if self.permit is not None:
                    self.permit.put(stop)
                else:  # a realtime fleet it launched: its clock is not held, but it ends it
                    self.session.put(self.keys.script, stop)
                code, why, summary = self.launched.wait(timeout=120.0)
                self.verdict = None if code == 0 else why
        finally:
            if self.launched is not None:
                self.launched.stop()
            if self.log is not None:
                self.log.close()
            for s in self.subs:
                s.undeclare()
            self.token.undeclare()
            self.session.close()
        return summary

    # ------------------------------------------------------------------ inside
    def _first_sample(self) -> None:
        """Wait (bounded) for a whole sample, every robot's truth and pose, so that what the
        script reads first names every robot: all of sample 0 on a held clock, the first that
        comes whole on a running one (a script joining a fleet that runs)."""
        if not self._wait_sample(0, whole=True):
            raise ConfigError("processes", f"no sample from the fleet within {SAMPLE_TIMEOUT:g} s")
        self.k = 0 if self.hold else self._newest()

    def _agents_live(self) -> None:
        """Wait until this session sees every agent it launched live.  Sample 0 comes from the
        tracker, whose session this one joined first, and the links to the agents come up
        meanwhile.  An agent declares its goal queryable before its liveliness token, on the same
        link, so once its token is here a goal query reaches it.  Bounded: an agent that died at
        start is reported as gone, and a goal for it as unanswered."""
        inbox = self.inbox
        inbox.wait(lambda: set(self.ids) <= inbox.live or self._stopped(), SAMPLE_TIMEOUT)

    def _wait_sample(self, k: int, whole: bool = True) -> bool:
        """Wait until sample k (or a later one) has come: the ground truth and the measured pose
        of every robot (of one robot, unless ``whole``); False if the run ended first."""
        inbox, ids = self.inbox, self.ids

        def come(r: str) -> bool:
            t = inbox.get(Truth, r)
            if t is None or t.seq < k:
                return False
            # A held clock sends the sample's pose with its truth: wait for that very one (the
            # truth may come first); a running one may skip, or lose, a pose.
            return (inbox.get(Pose, r, t.seq) if self.hold else inbox.newest(Pose, r, t.seq)) is not None

        def complete() -> bool:
            if self._stopped():
                return True
            n = sum(come(r) for r in ids)
            return n == len(ids) if whole else n > 0

        return inbox.wait(complete, SAMPLE_TIMEOUT) and not self._stopped()

    def _stopped(self) -> bool:
        tick = self.inbox.get(Tick, "tracker")
        return tick is not None and tick.stop

    def _ask(self, rid: str, goal: Array, batch: dict[str, Array]) -> tuple[bool, str]:
        return ask_goal(self.session, self.keys, Goal(robot=rid, goal=goal, batch=batch), GOAL_REPLY_TIMEOUT)

    def _collect_events(self, k: int) -> None:
        """The events of step k, once sample k + 1 is in: the commands of step k − 1 not applied
        (tick k says so), agents gone, and the plans' fallbacks.  A plan not in yet is looked for
        again one step later, and only then counts as stale: in lockstep the tracker has every
        plan of step k before it publishes sample k + 1, but this session may get the sample
        before the plan.  On a held clock a live agent's plan is waited for, up to
        :data:`PLAN_GRACE`, before it counts as stale."""
        inbox, out = self.inbox, []
        if self.hold:
            # Lockstep: no agent could step past a plan its neighbours wait for, so a live
            # agent's plan of an earlier step is on its way.  It comes on that agent's own link,
            # which this session may serve after the tracker's: wait for it, bounded, rather
            # than judge the order in which two links were served.
            inbox.wait(lambda: self._plans_in(k), PLAN_GRACE)
        with inbox.cond:
            live = set(inbox.live)
            self._unseen[k] = set(self.ids)
            for step in sorted(self._unseen):
                for rid in sorted(self._unseen[step]):
                    pl = inbox.get(Plan, rid, step)
                    if pl is not None:
                        self._unseen[step].discard(rid)
                        if pl.status != SOLVED:
                            out.append(Event(step, rid, "fallback", pl.status))
                    elif step < k:
                        self._unseen[step].discard(rid)
                        if rid in live:
                            out.append(
                                Event(step, rid, "stale_neighbour", f"its plan of step {step} is late")
                            )
                if not self._unseen[step]:
                    del self._unseen[step]
            self._was_live |= live
            for rid in self.ids:  # gone after this session saw it (its token may come late)
                if rid in self._was_live and rid not in live and rid not in self._dead:
                    self._dead.add(rid)
                    out.append(Event(k, rid, "dead_neighbour", "its agent left the fleet"))
            said = inbox.get(Tick, "tracker", k)  # what the robot sides did over step k − 1
            if said is not None and k > 0:
                for rid, done in {**said.fallback, **said.braked}.items():
                    what = "braked" if rid in said.braked else "followed its candidate"
                    out.append(Event(k - 1, rid, "deadline_miss", f"{what} after step {done}"))
            inbox.prune(k - 2)
        with self._lock:
            self._events += out

    def _plans_in(self, k: int) -> bool:
        """Every live agent's plan of each step before k not yet seen has come (inbox.cond held)."""
        inbox = self.inbox
        return all(
            inbox.get(Plan, rid, step) is not None or rid not in inbox.live
            for step, rids in self._unseen.items()
            if step < k
            for rid in rids
        )


def _pose(m: Pose) -> Array:
    return np.array([m.x, m.y, m.theta])
