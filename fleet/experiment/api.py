"""Experiments as Python scripts: one API for the in-process simulator, the process fleet and the lab.

::

    from fleet import Fleet

    with Fleet.launch("scenarios/swap_4.toml", clock="lockstep", seed=3) as fleet:
        fleet.wait_arrived(timeout=240)
        fleet.goto({"r1": (0.3, 0.2)})
        fleet.formation([(0.35, 0.35), (-0.35, 0.35), (-0.35, -0.35), (0.35, -0.35)])
        fleet.wait_arrived(timeout=240)
    print(fleet.summary["all_goals_reached"])

A script works at the level of goals: the tube MPC drives.  It sees the fleet one sample at a
time (sample k is the state at t = k·Ts, before step k is planned); goals it gives at sample k
are taken by the agents at step k + 1 (without ``delay_compensation``, at step k).  Every wait
runs the fleet's clock: on lockstep a wait of ``timeout`` seconds is ``timeout / Ts`` steps of
simulated time, however long they take on this machine; on realtime it is wall time.

* **Arrived** is the project's one definition of settled (:func:`ground.scenario.settled_since`):
  the robot's true controlled point has stayed within :data:`ground.scenario.GOAL_TOLERANCE` of
  its current goal for :data:`ground.scenario.SETTLE_TIME`, counted from the sample its goal was
  given.  The summary's ``reached_goal`` uses the same rule.
* **Goals** are checked as the scenario's are: inside the arena, clear of the walls and the
  obstacles by the robot's footprint, reachable from where the robot is past them, and the two
  footprints and
  :data:`ground.scenario.GOAL_MARGIN` away from every other robot's goal (the goals given in the
  same call count in place of the ones they replace).  A refused call raises
  :class:`GoalRefused` naming the robot and the reason, and changes nothing.
* **Missions** are waypoints visited in order (:meth:`Fleet.mission`): a waypoint counts as
  reached once the controlled point is within the goal tolerance of it, and the robot then takes
  the next one; the last waypoint is the robot's goal, where it settles.

docs/api.md documents every method with its units and frames.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace, TracebackType
from typing import Any

import numpy as np

from fleet.experiment.backend import Backend, Event, Sample
from ground.geometry import Array, controlled_point
from ground.scenario import GOAL_TOLERANCE, Scenario, goal_problem, load_scenario, settled_since

CLOCKS = ("lockstep", "realtime")
"""The fleet's clocks: lockstep steps when every agent has answered; realtime steps at Ts."""
MAX_EVENTS = 100_000
"""Most events kept waiting for :meth:`Fleet.events` (a script that never reads them)."""
Point = tuple[float, float]
"""A point (x, y) [m], world frame."""
Pose = tuple[float, float, float]
"""A pose (x [m], y [m], θ [rad]) of the axle centre, world frame, θ counter-clockwise from +x."""


class FleetError(Exception):
    """A script asked the fleet for something it cannot do (the message says what and why)."""


class GoalRefused(FleetError, ValueError):
    """A goal that cannot be accepted: ``robot`` names the robot, ``reason`` says why.  Nothing
    of the refused call was applied."""

    def __init__(self, robot: str, reason: str):
        super().__init__(f"{robot}: {reason}")
        self.robot = robot
        self.reason = reason


@dataclass
class _Progress:
    """One robot's progress towards its current goal, sample by sample."""

    goal: Array
    errors: list[float] = field(default_factory=list)
    """Distance of the true controlled point to ``goal`` per sample since it was given [m]."""
    arrived: bool = False
    waypoints: list[Array] = field(default_factory=list)
    """The mission's waypoints still to visit after ``goal`` (2,) [m] each."""
    reached: int = 0
    """Waypoints of missions reached so far (the final ones included once settled)."""
    due: bool = False
    """At a waypoint, waiting to take the next one."""
    mission: bool = False
    """The goal is a mission's last waypoint."""


class Fleet:
    """A running fleet, seen and steered from a script (see the module docstring).

    Make one with :meth:`launch` (this script starts the fleet and ends it) or :meth:`connect`
    (it attaches to a fleet that is running), and use it as a context manager: when the block
    ends, even by an exception, everything the fleet started is ended and :attr:`summary` holds
    the run's ``summary.json``."""

    def __init__(self, backend: Backend):
        self._b = backend
        self.scenario = backend.scenario
        self.ids = [r.id for r in self.scenario.robots]
        """The robots' ids, in the scenario's order."""
        self.Ts = self.scenario.controller.Ts
        """The sampling period [s]."""
        self._lookahead = self.scenario.controller.lookahead
        self._queue: list[Event] = []
        self.events_dropped = 0
        """Events dropped unread: beyond :data:`MAX_EVENTS` waiting, the oldest go."""
        self._progress = {rid: _Progress(np.asarray(g, dtype=float)) for rid, g in backend.goals().items()}
        self._seen = -1
        self.summary: dict[str, Any] | None = None
        """The run's ``summary.json`` as a dict, once the fleet is closed."""
        self._closed = False
        self._observe(backend.sample())

    # ------------------------------------------------------------------ making one
    @classmethod
    def launch(
        cls,
        scenario: str | Path,
        clock: str = "lockstep",
        seed: int | None = None,
        processes: bool = True,
        out: str | Path | None = None,
        delay_compensation: bool = True,
        **run_options: Any,
    ) -> Fleet:
        """Start the fleet of ``scenario`` (a TOML file) and return it, at sample 0.

        ``processes=True`` starts the same processes as ``fleet run`` (an agent per robot, the
        simulated tracker, the supervisor), with this script as one more participant;
        ``processes=False`` runs the fleet in this process (``fleet simulate``'s simulator): the
        same semantics and the same summary, much faster, a pre-flight check of a script.  On
        lockstep both give the same trajectories for the same script and ``seed``.  ``out``: the
        run's directory (summary.json; default out/<scenario name>).  ``run_options`` go to
        ``fleet run`` (``exchange``, ``topology``, ``lease``, ``viewer``, ``faults``, ``hub``,
        ``ros2``, ``ros_domain``, ``ros_listen``, ``fork``: :data:`fleet.experiment.script.RUN_OPTIONS`).
        ``delay_compensation`` (the default, as ``fleet run``'s): every plan is made a step
        ahead (docs/method.md §5), on either side; a goal given at sample k is then taken by the
        plans of step k + 1 on, the first made after it.  Bad input raises
        :class:`ground.scenario.ConfigError` naming the field."""
        from ground.scenario import ConfigError

        if clock not in CLOCKS:
            raise ConfigError("clock", f"{clock!r} is not one of {', '.join(CLOCKS)}")
        scn = load_scenario(scenario)
        if processes:
            from fleet.experiment.script import ProcessFleet

            fleet = cls(
                ProcessFleet.launch(
                    scenario, scn, clock, seed, out, delay_compensation=delay_compensation, **run_options
                )
            )
        else:
            if clock != "lockstep":
                raise ConfigError("clock", "the in-process simulator runs on lockstep only")
            if run_options:
                raise ConfigError(
                    next(iter(run_options)), "is an option of a process fleet; processes=False takes none"
                )
            fleet = cls(SimulatedFleet(scn, seed, out, ahead=delay_compensation))
        missions = {r.id: r.waypoints for r in scn.robots if r.waypoints}
        if missions:  # the scenario's: from sample 0
            try:
                fleet.mission(missions)
            except BaseException:
                fleet.close()
                raise
        return fleet

    @classmethod
    def connect(
        cls,
        scenario: str | Path,
        connect: str | Sequence[str] | None = None,
        zenoh_config: str | Path | None = None,
        fleet: str = "lab",
    ) -> Fleet:
        """Attach to a fleet that is running (``fleet run``, or the lab's processes), by its hub's
        endpoint(s) ``connect`` (e.g. ``"tcp/127.0.0.1:7447"``) or a Zenoh configuration file.
        The same methods work; leaving stops nothing, and :attr:`summary` stays None."""
        from fleet.experiment.script import ProcessFleet

        scn = load_scenario(scenario)
        eps = [connect] if isinstance(connect, str) else list(connect or [])
        return cls(ProcessFleet.attach(scn, eps, None if zenoh_config is None else str(zenoh_config), fleet))

    # ------------------------------------------------------------------ reading it
    @property
    def processes(self) -> dict[str, int]:
        """The pid of every process :meth:`launch` started, by role (``tracker``,
        ``supervisor``, ``agent r1`` …); empty in process and for a joined fleet."""
        return self._b.processes

    @property
    def verdict(self) -> str | None:
        """Once closed: why the run failed, in one line (a collision, a goal not reached, a
        process that failed: ``fleet run``'s verdict), or None if it passed."""
        return self._b.verdict if self._closed else None

    @property
    def step(self) -> int:
        """The current sample's index k (t = k·Ts)."""
        return self._seen

    @property
    def time(self) -> float:
        """The fleet's clock at the current sample [s]."""
        return self._seen * self.Ts

    def poses(self) -> dict[str, Pose]:
        """The newest measured pose of every robot: {id: (x [m], y [m], θ [rad])}, axle centre,
        world frame, as its agent measured it."""
        got = self._b.sample().measured
        return {rid: (float(p[0]), float(p[1]), float(p[2])) for rid, p in got.items()}

    def points(self) -> dict[str, Point]:
        """The newest measured controlled point of every robot: {id: (x, y)} [m], world frame
        (the point ℓ ahead of the axle that the MPC steers and goals are given for)."""
        return {
            rid: (float(q[0]), float(q[1]))
            for rid, q in ((r, controlled_point(p, self._lookahead)) for r, p in self.poses().items())
        }

    def goals(self) -> dict[str, Point]:
        """Every robot's current goal: {id: (x, y)} [m], world frame (a mission's current waypoint)."""
        return {rid: (float(g[0]), float(g[1])) for rid, g in self._b.goals().items()}

    def arrived(self, robots: Iterable[str] | None = None) -> bool:
        """Whether every robot named (default: all) has settled at its current goal, now."""
        names = self._names(robots)
        return all(self._progress[r].arrived and not self._progress[r].waypoints for r in names)

    def events(self) -> Iterator[Event]:
        """The events since the last call, oldest first (see :class:`Event`).  They are
        collected while the fleet runs, during the waits."""
        self._poll_events()
        out, self._queue = self._queue, []
        yield from out

    def waypoints_reached(self) -> dict[str, int]:
        """Per robot, the waypoints of its missions reached so far (a final one once settled)."""
        return {rid: pr.reached for rid, pr in self._progress.items()}

    # ------------------------------------------------------------------ steering it
    def goto(self, goals: Mapping[str, Sequence[float] | Array]) -> None:
        """Give new goals {id: (x, y)} [m], world frame, for the controlled points; checked as
        the scenario's goals are, together (see the module docstring).  Raises
        :class:`GoalRefused` for the first that cannot be accepted, and changes nothing.  A
        robot with a mission drops the rest of it."""
        batch = self._checked(goals)
        self._send(batch)
        for rid in batch:
            self._progress[rid].waypoints = []

    def formation(
        self,
        points: Sequence[Sequence[float]],
        centre: Sequence[float] = (0.0, 0.0),
        heading: float = 0.0,
        robots: Iterable[str] | None = None,
    ) -> dict[str, Point]:
        """Send the robots (default: all) to a formation: ``points`` (M, 2) [m] in the formation's
        frame, rotated by ``heading`` [rad] and moved to ``centre`` (x, y) [m], world frame.  One
        robot per point, as many points as robots, assigned with the least total distance from
        where their controlled points are (:func:`scipy.optimize.linear_sum_assignment`), then
        given as one :meth:`goto`.  Returns the assignment {id: (x, y)} [m], world frame."""
        from scipy.optimize import linear_sum_assignment

        names = self._names(robots)
        pts = np.asarray(points, dtype=float)
        if pts.ndim != 2 or pts.shape[1] != 2:
            raise FleetError(f"formation: points must be (M, 2) [m], got shape {pts.shape}")
        if pts.shape[0] != len(names):
            raise FleetError(f"formation: {pts.shape[0]} points for {len(names)} robots; give one point each")
        c, s = math.cos(heading), math.sin(heading)
        world = pts @ np.array([[c, s], [-s, c]]) + np.asarray(centre, dtype=float).reshape(1, 2)
        here = self.points()
        cost = np.array([[math.dist(here[r], q) for q in world] for r in names])
        rows, cols = linear_sum_assignment(cost)
        pairs = zip(rows.tolist(), cols.tolist(), strict=True)
        assignment = {names[i]: (float(world[j, 0]), float(world[j, 1])) for i, j in pairs}
        self.goto(assignment)
        return assignment

    def mission(self, waypoints: Mapping[str, Sequence[Sequence[float]]]) -> None:
        """Give robots missions {id: [(x, y), ...]} [m], world frame: waypoints visited in
        order, the last one the goal.  Every waypoint is checked as a goal against the goals of
        the other robots (their missions' final goals, for those in this call); the first
        waypoint is given at once."""
        firsts: dict[str, Array] = {}
        rest: dict[str, list[Array]] = {}
        for rid, wps in waypoints.items():
            arr = np.asarray(wps, dtype=float)
            if arr.ndim != 2 or arr.shape[1] != 2 or arr.shape[0] == 0:
                raise FleetError(f"mission: {rid}: waypoints must be (n ≥ 1, 2) [m], got shape {arr.shape}")
            firsts[rid] = arr[0]
            rest[rid] = [a.copy() for a in arr[1:]]
            finals = {r: np.asarray(w, dtype=float)[-1] for r, w in waypoints.items() if r != rid}
            for wp in arr:
                self._checked({rid: wp}, finals)
        batch = self._checked(firsts)
        self._send(batch)
        for rid, more in rest.items():
            self._progress[rid].waypoints, self._progress[rid].mission = more, True

    # ------------------------------------------------------------------ running it
    def wait_arrived(self, robots: Iterable[str] | None = None, timeout: float | None = None) -> bool:
        """Run the fleet until every robot named (default: all) has arrived at its goal (the end
        of its mission), and True; False once ``timeout`` [s] of the fleet's clock have passed
        (default: the scenario's duration), the fleet still running.  Returns at once if they
        have arrived already."""
        names = self._names(robots)
        return self._run_until(lambda: self.arrived(names), timeout)

    def wait(self, seconds: float) -> None:
        """Let the fleet run for ``seconds`` [s] of its clock (lockstep: simulated time)."""
        self._run_until(lambda: False, seconds)

    def close(self) -> dict[str, Any] | None:
        """End what this script started (a launched fleet's processes, by pid) and return the
        run's summary (None for a fleet joined with :meth:`connect`).  Idempotent."""
        if not self._closed:
            self._closed = True
            self.summary = self._b.close()
            if self.summary is not None:
                self.summary["waypoints_reached"] = self.waypoints_reached()
                if self._b.out is not None:  # in the file too
                    from fleet.running.report import strict_json

                    text = json.dumps(strict_json(self.summary), indent=2)
                    (self._b.out / "summary.json").write_text(text + "\n")
        return self.summary

    def __enter__(self) -> Fleet:
        return self

    def __exit__(
        self, et: type[BaseException] | None, ev: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    # ------------------------------------------------------------------ inside
    def _names(self, robots: Iterable[str] | None) -> list[str]:
        names = self.ids if robots is None else [robots] if isinstance(robots, str) else list(robots)
        for r in names:
            if r not in self._progress:
                raise FleetError(f"{r!r} is not a robot of this fleet (robots: {', '.join(self.ids)})")
        return names

    def _checked(
        self,
        goals: Mapping[str, Sequence[float] | Array],
        others: Mapping[str, Array] | None = None,
        quiet: bool = False,
    ) -> dict[str, Array]:
        """The goals as (2,) arrays, once every one passes the checks; else :class:`GoalRefused`
        (and a ``refused`` event, unless ``quiet``)."""
        if self._closed:
            raise FleetError("the fleet is closed")
        batch: dict[str, Array] = {}
        for rid, g in goals.items():
            if rid not in self._progress:
                self._refused(rid, f"unknown robot id (robots: {', '.join(self.ids)})")
            arr = np.asarray(g, dtype=float).reshape(-1)
            if arr.shape != (2,):
                self._refused(rid, f"a goal is (x, y) [m], got {len(arr)} numbers")
            batch[rid] = arr
        fp = self._b.footprint
        now = [SimpleNamespace(robot=r, goal=q, footprint=fp) for r, q in self._b.goals().items()]
        given = {**(others or {}), **batch}
        here = self.points()
        for rid, arr in batch.items():
            near = [pl for pl in now if pl.robot != rid]
            at = np.array(here[rid]) if rid in here else None
            problem = goal_problem(
                self.scenario, fp, arr, near, {r: q for r, q in given.items() if r != rid}, at=at
            )
            if problem is not None:
                if quiet:
                    raise GoalRefused(rid, problem)
                self._refused(rid, problem)
        return batch

    def _refused(self, robot: str, reason: str) -> None:
        self._queue.append(Event(self._seen, robot, "refused", reason))
        raise GoalRefused(robot, reason)

    def _send(self, batch: Mapping[str, Array]) -> None:
        refused = self._b.send(batch)
        if refused:
            rid, why = next(iter(refused.items()))
            self._refused(rid, f"its agent refused the goal: {why}")
        for rid, g in batch.items():
            self._progress[rid] = _Progress(g, reached=self._progress[rid].reached)

    def _run_until(self, done: Any, timeout: float | None) -> bool:
        if self._closed:
            raise FleetError("the fleet is closed")
        seconds = self.scenario.duration if timeout is None else float(timeout)
        if not math.isfinite(seconds) or seconds < 0:
            raise FleetError(f"timeout must be a finite number of seconds ≥ 0, got {timeout!r}")
        end = self._seen + round(seconds / self.Ts)
        while not done():
            if self._seen >= end:
                return False
            if not self._b.advance():
                raise FleetError(f"the fleet ended at step {self._seen}")
            self._observe(self._b.sample())
        return True

    def _observe(self, s: Sample) -> None:
        """Take a new sample: errors, arrivals, waypoints."""
        if s.step <= self._seen:
            return
        self._seen = s.step
        self._poll_events()
        for rid, pr in self._progress.items():
            if rid not in s.truth:
                continue
            pt = controlled_point(s.truth[rid], self._lookahead)
            pr.errors.append(float(np.linalg.norm(pt - pr.goal)))
            if pr.waypoints and not pr.due and pr.errors[-1] <= GOAL_TOLERANCE:
                self._queue.append(Event(s.step, rid, "waypoint", f"({pr.goal[0]:.3f}, {pr.goal[1]:.3f})"))
                pr.reached += 1
                pr.due = True
            elif not pr.waypoints and not pr.arrived and settled_since(pr.errors, self.Ts) is not None:
                pr.arrived = True
                pr.reached += pr.mission
                self._queue.append(Event(s.step, rid, "arrived", f"({pr.goal[0]:.3f}, {pr.goal[1]:.3f})"))
        self._next_waypoints()

    def _next_waypoints(self) -> None:
        """Robots at a waypoint take their next one: together if they can (two robots may swap
        places), else each one that can; one whose next waypoint is a neighbour's goal waits."""
        due = {rid: pr.waypoints[0] for rid, pr in self._progress.items() if pr.due}
        if not due:
            return
        for batch in (due, *({rid: wp} for rid, wp in due.items())):
            if not all(self._progress[r].due for r in batch):
                continue
            try:
                checked = self._checked(batch, quiet=True)
            except GoalRefused:
                continue
            rest = {r: self._progress[r].waypoints[1:] for r in checked}
            self._send(checked)
            for r, more in rest.items():
                self._progress[r].waypoints, self._progress[r].mission = more, True

    def _poll_events(self) -> None:
        self._queue.extend(self._b.events())
        if len(self._queue) > MAX_EVENTS:  # nobody reads them: keep the newest
            self.events_dropped += len(self._queue) - MAX_EVENTS
            del self._queue[:-MAX_EVENTS]


class SimulatedFleet:
    """:class:`Backend` of ``Fleet.launch(..., processes=False)``: the in-process simulator
    (:class:`fleet.running.simulate.Simulation`), stepped by the script."""

    realtime = False

    @property
    def processes(self) -> dict[str, int]:
        """None started: the simulator runs in the script's process (an empty map)."""
        return {}  # one process: the script's

    def __init__(self, scn: Scenario, seed: int | None, out: str | Path | None, ahead: bool = False):
        """``ahead``: plans made a step ahead (delay compensation;
        :class:`fleet.running.simulate.Simulation`)."""
        from agent.tube import validated_design
        from fleet.running.simulate import Simulation

        self.scenario = scn
        design = validated_design(scn)
        self.footprint = float(design.footprint)
        self.sim = Simulation(scn, seed=seed, design=design, ahead=ahead)
        self.seed = self.sim.seed
        self.out: Path | None = Path(out) if out is not None else Path("out") / scn.name
        self._events: list[Event] = []
        self.verdict: str | None = None

    def sample(self) -> Sample:
        """The current step's sample: each robot's true pose and its measured (camera) pose,
        (3,) [m, m, rad]."""
        sim = self.sim
        return Sample(
            sim.k,
            {rid: tr.pose[-1] for rid, tr in sim.traces.items()},
            {rid: np.asarray(c, dtype=float) for rid, c in sim.cams.items()},
        )

    def advance(self) -> bool:
        """Step the simulator once, noting a ``fallback`` event for every robot whose step
        took its shifted candidate; always True (the script decides when the run ends)."""
        k = self.sim.k
        self.sim.step()
        for rid, out in self.sim.outputs.items():
            if out.fallback:
                self._events.append(Event(k, rid, "fallback", out.status))
        return True

    def goals(self) -> dict[str, Array]:
        """Each robot's goal (2,) [m], a copy: the one given and not yet taken, else its
        controller's."""
        sim = self.sim
        return {rid: sim.pending.get(rid, c.goal).copy() for rid, c in sim.ctrls.items()}

    def send(self, goals: Mapping[str, Array]) -> dict[str, str]:
        """Give each robot its goal from the next step on
        (:meth:`fleet.running.simulate.Simulation.set_goal`); none is refused (an empty map)."""
        for rid, g in goals.items():
            self.sim.set_goal(rid, g)
        return {}

    def events(self) -> list[Event]:
        """The events noted since the last call (:meth:`advance`'s fallbacks)."""
        out, self._events = self._events, []
        return out

    def close(self) -> dict[str, Any]:
        """Finish the run, write its outputs in :attr:`out` (:func:`fleet.running.simulate.save_run`)
        and judge it (:attr:`verdict`); returns the summary."""
        from fleet.running.simulate import save_run
        from supervisor.judge import verdict

        assert self.out is not None
        summary = save_run(self.sim.finish(), self.scenario, self.seed, self.out)
        summary["processes"] = {}
        self.verdict = verdict(summary)
        return summary


def run_scenario(
    scenario: str | Path, processes: bool, seed: int | None = None, out: str | Path | None = None,
    clock: str = "lockstep", delay_compensation: bool = True, **run_options: Any,
) -> tuple[dict[str, Any] | None, str | None]:  # fmt: skip
    """Run a scenario as ``fleet simulate`` (``processes=False``) or ``fleet run`` do, through a
    script: its robots' missions from sample 0, the run ending once every robot has arrived or
    at the scenario's duration.  (summary, verdict): the verdict is None if the run passed."""
    with Fleet.launch(
        scenario, clock=clock, seed=seed, processes=processes, out=out, delay_compensation=delay_compensation,
        **run_options,
    ) as fleet:  # fmt: skip
        fleet.wait_arrived(timeout=fleet.scenario.duration)
    return fleet.summary, fleet.verdict
