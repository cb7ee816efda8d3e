"""The one safety judge: what a run did, from ground truth and the plans, and ``summary.json``.

``fleet simulate`` (:mod:`fleet.running.simulate`) and the supervisor process (:mod:`supervisor.monitor`)
both judge a run with a :class:`Judge`, fed the same two streams step by step:

* :meth:`Judge.truth` — one sample of the robots' true axle-centre poses (the initial one
  included), and the camera's poses of it where there are any: centre distances and
  collisions (two centres closer than two body radii), arena and obstacle violations, each
  controlled point's distance to its goal and the camera's error;
* :meth:`Judge.plans` — one step's plans (:class:`~ground.wire.Plan`) and which of them were
  never executed (the robot side did not apply their command): the separation of the
  references committed at that step, every robot's solver figures, and whether an executed plan
  kept what its predecessor had committed; and the discs the agents kept clear of: how long each
  robot was kept clear of as dead, braked, blind or uncontrolled, the largest disc used for it,
  and whether its true body stayed inside every disc that claimed to hold it for good (the
  discs of robots off their plans, docs/method.md §6.4), and whose goal a stopped robot covers.

:meth:`Judge.summary` turns them into the run's ``summary.json``, the same schema for both;
a field only the in-process simulator can measure (a robot's step time, its realised
disturbance, its shifted candidate's violation) is added by :meth:`Judge.simulated` and absent
from a process run's summary.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np

from ground.arrival import Arrival, arrival
from ground.geometry import Array, controlled_point, wrap_angle
from ground.model import travel_floor
from ground.scenario import GOAL_TOLERANCE, Scenario, forced_order, settled_since
from ground.wire import BLIND, LINK_DOWN, PARKED, RETURNING, WAITING, Plan, remember_steps

SOLVED = "PROXQP_SOLVED"
"""The one solver status whose plan is a solution; every other status is a fallback."""
SLACK = 1e-9
"""Rounding slack of every distance check [m]."""
HELD = (BLIND, LINK_DOWN)
"""Plan statuses of an agent that holds without solving: its robot does not follow the reference."""
KEPT_CLEAR_AS = {"dead": "dead", "braked": "braked", "blind": "blind", "loose": "uncontrolled"}
"""The disc kinds counted per robot in ``summary.json`` (``kept_clear_as``), by their name there."""
CLAIMED = frozenset({"dead", "braked"})
"""Disc kinds whose disc claims to hold the robot's true body from then on: its agent is gone or
its robot side braked it, and either stops it within the disc (docs/method.md §6.4).  A blind
agent brakes its robot by commands from a prediction, which a real robot side may not realise
exactly, so its disc is not judged."""

Pose3 = Sequence[float] | Array
"""A pose (x [m], y [m], θ [rad]), world frame, (3,)."""


MAX_EPISODES = 1000
"""Displacements, and episodes without room to make way, kept one by one in ``summary.json``
(``displaced``, ``no_room``) [episodes]: the first so many of each; each robot's counts
(``displaced``, ``no_room_steps``) and each pair's turns (``traded_places``) are exact.  It
bounds the summary's size over a run of any length."""

WALL_CHECK_STEPS = 10
"""How often the judge asks whose way home the parked robots wall in [steps] (1 s at Ts = 0.1 s):
how soon an event can say so, at one labelling of free space each time the parked robots
change."""


class Judge:
    """The safety figures of one run, updated one sample and one step at a time."""

    def __init__(self, scn: Scenario):
        p = scn.controller
        self.scn = scn
        self.ids = [r.id for r in scn.robots]
        self.Ts = p.Ts
        """Sampling period [s]."""
        self.radius = p.robot_radius
        """Body radius [m]: two true centres closer than two of them collide."""
        self.lookahead = p.lookahead
        """Controlled point ahead of the axle [m] (:mod:`ground.geometry`)."""
        self.goals = {r.id: np.array(r.goal, dtype=float) for r in scn.robots}
        """Each robot's current goal (2,) [m]: a goal changed at run time counts from its plan on."""
        self.footprint: float | None = None
        """The largest footprint radius r_i a plan has carried [m]; None before the first plan."""
        self.min_distance = math.inf
        self.collisions = self.obstacle_violations = self.arena_violations = 0
        self.min_ref = math.inf
        self.ref_violations = 0
        self.steps = 0
        """Steps whose plans were judged."""
        self.skipped_steps = 0
        """Samples whose ground truth was lost on the way, not judged."""
        self.poses: dict[str, list[tuple[float, ...]]] = {r: [] for r in self.ids}
        """True poses per sample judged."""
        self.sample_index: list[int] = []
        """Per sample, its index in :attr:`poses`, −1 for a sample not judged (:meth:`skipped`)."""
        self.errors: dict[str, list[float]] = {r: [] for r in self.ids}
        """Distance of the controlled point to the current goal per sample [m]."""
        self.refs: dict[str, list[Array]] = {
            r.id: [controlled_point(r.start, self.lookahead)] for r in scn.robots
        }
        """The executed committed reference for each sample's time (2,) [m]: at sample 0 the
        start, where every agent's initial reference stays put; then one per step of plans, in
        whatever order the plans and the truths arrive."""
        self.pose_error: dict[str, list[float]] = {r: [0.0, 0.0] for r in self.ids}
        """Largest camera error per robot: [per-axis position [m], heading [rad]]."""
        self.last_plans: dict[str, Plan] = {}
        """The latest executed plan of each robot seen so far."""
        self.unexecuted: dict[str, set[int]] = {r: set() for r in self.ids}
        """Per robot, recent steps whose plan was reported not executed."""
        self.robot: dict[str, dict[str, Any]] = {
            r: {"solves": 0, "failures": 0, "tube_exits": 0, "status": {}, "solve_ms": [], "candidate": 0,
                "braked": 0, "breaks": 0, "blind": 0, "link_losses": 0, "late": 0, "arena": 0,
                "uncontrolled": 0, "held_link_down": 0, "escapes": 0, "largest": 0.0, "displaced": 0,
                "no_room": 0, "as": dict.fromkeys(KEPT_CLEAR_AS.values(), 0)}
            for r in self.ids
        }  # fmt: skip
        self.off: set[str] = set()
        """Robots whose committed reference is not being followed: braked by their robot side
        since their last executed plan, or holding (blind, link down).  Their references are left
        out of the separation check: their robot is kept clear of by its disc instead."""
        self.blocked: dict[str, str] = dict.fromkeys(self.ids, "")
        """Per robot, the robot whose stopped disc covered its goal in its latest plan, or ""."""
        self.no_room: dict[str, str] = dict.fromkeys(self.ids, "")
        """Per robot, the robot that goes first whose corridor it found no room to leave at its
        latest plan (:attr:`~ground.wire.Plan.no_room`), or "" (assumption (A) of
        docs/method.md §7 failing as the run goes)."""
        self.no_room_episodes: list[dict[str, Any]] = []
        """Each time a robot found no room to make way: ``robot``, ``for`` (the robot that goes
        first), ``from_step`` and ``to_step`` (its first plan after that without the lack: with
        room, or no longer making way; None while it lasts).  The first :data:`MAX_EPISODES`;
        each robot's steps are all counted."""
        self._no_room_open: dict[str, dict[str, Any]] = {}
        """Per robot without room now, its episode of :attr:`no_room_episodes` (if kept)."""
        self.claims: dict[int, list[tuple[str, Array, float]]] = {}
        """Per step, the discs that claim to hold a robot's true body (robot, centre (2,) [m],
        radius [m]), judged against the sample of that step (:meth:`_judge_claims`)."""
        self.escape_excess = 0.0
        """The largest distance [m] by which a true body left a disc that claimed to hold it."""
        self.outage: dict[str, tuple[int, int]] = {}
        """Per robot whose radio link is down now: (the tick it was lost at, the newest tick seen)."""
        self.losses_seen: dict[str, int] = {}
        """Per robot, the tick its newest outage seen began at (:meth:`link_state`)."""
        self.extras: dict[str, dict[str, Any]] = {r: {} for r in self.ids}
        self._layout: tuple[float, dict[str, dict[str, list[str]]]] | None = None
        """(footprint [m], :meth:`layout` for it), once worked out."""
        self._arrival: tuple[float, Arrival] | None = None
        """(footprint [m], :meth:`arrival` for it), once worked out."""
        """Per robot, the figures only the in-process simulator measures (:meth:`simulated`)."""
        self.walled: dict[str, list[str]] = {}
        """Per robot whose way home parked robots wall in now, those robots (:meth:`_walls`)."""
        self.walled_episodes: list[dict[str, Any]] = []
        """Each time a robot's way home was walled in: ``robot``, ``by`` (the parked robots),
        ``from_step`` and ``to_step`` (the check it was found open again at; None while shut)."""
        self._carved: tuple[tuple[Any, ...], Any] | None = None
        self.phases: dict[str, int] = {}
        """Each robot's phase in its latest executed plan (:data:`~ground.wire.UNDER_WAY` …)."""
        self.displaced: list[dict[str, Any]] = []
        """Each time a parked robot left its goal (its plan's phase went from parked to
        returning: it stepped aside): ``robot``, ``for`` (the nearest robot that moves, whose way
        it cleared, or None), ``from_step`` and ``to_step`` (the step it parked again; None while
        out).  The first :data:`MAX_EPISODES`."""
        self.displacements = 0
        """Displacements of the run, all of them [episodes]."""
        self.turns: dict[tuple[str, str], tuple[str, int]] = {}
        """Per pair of robots (sorted ids), the one displaced for the other last, and how many
        times the two have displaced each other in turn (each displacement for the other of the
        pair counts after the first) (:meth:`_displacements`)."""
        self.news: list[dict[str, Any]] = []
        """The displacements of the latest step judged (``robot``, ``for``), each with
        ``traded``: its pair's turns where this one made them two or more, else 0; what the
        supervisor says as events."""
        self._out: dict[str, dict[str, Any]] = {}
        """Per robot off its goal now, its open episode of :attr:`displaced`."""
        self.repairs: dict[str, int] = {}
        """Per robot, solutions whose ȳ was pulled back onto the coordination rows (the
        in-process simulator reads the controller's counter)."""

    # ------------------------------------------------------------------ inputs
    def truth(self, poses: Mapping[str, Pose3], measured: Mapping[str, Pose3 | None] | None = None) -> None:
        """One sample of true poses, every robot's; ``measured`` (the camera's poses of that
        sample, None where none) feeds the camera-error figures."""
        for r, m in (measured or {}).items():
            if m is not None:
                t, err = poses[r], self.pose_error[r]
                err[0] = max(err[0], abs(m[0] - t[0]), abs(m[1] - t[1]))
                err[1] = max(err[1], abs(wrap_angle(m[2] - t[2])))
        xmin, xmax, ymin, ymax = self.scn.arena
        radius = self.radius
        centres = {r: np.array(poses[r][:2], dtype=float) for r in self.ids}
        d = _pair_distances(np.array([centres[r] for r in self.ids]).reshape(-1, 2))
        if d.size:
            self.min_distance = min(self.min_distance, float(d.min()))
            self.collisions += int(np.count_nonzero(d < 2.0 * radius))
        for a in self.ids:
            c = centres[a]
            if not (xmin + radius - SLACK <= c[0] <= xmax - radius + SLACK) or not (
                ymin + radius - SLACK <= c[1] <= ymax - radius + SLACK
            ):
                self.arena_violations += 1
                self.robot[a]["arena"] += 1
            for ob in self.scn.obstacles:
                if ob.distance(c) < radius - SLACK:
                    self.obstacle_violations += 1
            pose = tuple(float(v) for v in poses[a])
            self.poses[a].append(pose)
            pt = controlled_point(pose, self.lookahead)
            self.errors[a].append(float(np.linalg.norm(pt - self.goals[a])))
        self.sample_index.append(len(self.poses[self.ids[0]]) - 1)
        self._judge_claims(len(self.sample_index) - 1)

    def skipped(self) -> None:
        """A sample whose ground truth was lost on the way: not judged."""
        self.skipped_steps += 1
        self.sample_index.append(-1)

    def plans(
        self, plans: Mapping[str, Plan], unexecuted: Iterable[str] = (), braked: Iterable[str] = ()
    ) -> None:
        """One step's plans.  A robot missing from ``plans`` but in ``unexecuted`` (its agent
        dead, or it skipped the step, and its robot side kept to its last executed plan) is
        checked with that plan and not counted as a solve; one missing from both is not checked
        this step: its plan did not reach the supervisor, and its reference is unknown.  A robot in
        ``unexecuted`` made its plan, which counts as a solve, but its robot side did not apply
        the command (:attr:`~ground.wire.Tick.fallback`, :attr:`~ground.wire.Tick.braked`): the
        robot kept to its last executed plan, and that is what is checked.  A robot in
        ``braked`` (its robot side braked it over the step, :attr:`~ground.wire.Tick.braked`) no
        longer follows any plan until it has an executed plan again: its references are left
        out of the separation check (:attr:`off`)."""
        skipped = set(unexecuted)
        k = self.steps
        for r in skipped:
            if r in self.unexecuted:
                remember_steps(self.unexecuted[r], (k,), k)
        executed = {r: pl for r, pl in plans.items() if r not in skipped}
        for r, pl in executed.items():
            prev = self.last_plans.get(r)
            # Checked when every step between was reported unexecuted (a plan lost on its way
            # to the supervisor would look like a break).  A blind agent's robot braked off its
            # reference, which its neighbours stopped relying on: it starts again where it is.
            if (
                prev is not None
                and prev.status != BLIND
                and pl.step > prev.step
                and all(s in self.unexecuted[r] for s in range(prev.step + 1, pl.step))
                and not continues(prev, pl)
            ):
                self.robot[r]["breaks"] += 1
        last = {**self.last_plans, **executed}
        self.last_plans = last
        for r, pl in executed.items():
            if pl.status in HELD:
                self.off.add(r)
            else:
                self.off.discard(r)
        self.off.update(braked)
        self._displacements(k, executed, last)
        self._discs(k, plans.values())
        for pl in plans.values():
            self.footprint = pl.footprint if self.footprint is None else max(self.footprint, pl.footprint)
        # A robot that is neither in ``plans`` nor reported unexecuted by the tick is one whose
        # plan of this step did not reach the supervisor (lost, or its agent left out as gone
        # while the supervisor's own Zenoh lease lapsed): where its reference is, is unknown.
        known = set(plans) | skipped
        checked = [r for r in self.ids if r in last and r in known and r not in self.off]
        if len(checked) > 1:
            d = _pair_distances(np.array([last[r].committed[-1] for r in checked]).reshape(-1, 2))
            f = np.array([last[r].footprint for r in checked])
            iu = np.triu_indices(len(checked), 1)
            self.min_ref = min(self.min_ref, float(d.min()))
            self.ref_violations += int(np.count_nonzero(d < f[iu[0]] + f[iu[1]] - SLACK))
        for a in self.ids:
            if a not in last:
                continue
            pa = last[a]
            made = plans.get(a)
            if made is None:
                continue
            st = self.robot[a]
            st["late"] = max(st["late"], made.late)  # the agent's count so far
            st["status"][made.status] = st["status"].get(made.status, 0) + 1
            if made.status == BLIND:  # no measurement, no QP: the robot braked
                st["blind"] += 1
            elif made.status == LINK_DOWN:  # its link down: nothing solved, the robot drives on
                st["held_link_down"] += 1
            else:
                st["solves"] += 1
                st["failures"] += made.status != SOLVED
                st["tube_exits"] += not made.tube_ok
                st["solve_ms"].append(made.solve_time * 1e3)
            if not np.array_equal(made.goal, self.goals[a]):
                self._regoal(a, k, made.goal)
            self.blocked[a] = made.blocked
            self._no_room(a, k, made.no_room)
            # The executed reference for the next sample ("stay put" past its end).
            at = min(max(k - pa.step, 0), len(pa.committed) - 1)
            self.refs[a].append(pa.committed[at].copy())
        if k % WALL_CHECK_STEPS == 0 and self.footprint is not None:
            self._walls(k, last)
        self.steps += 1

    def _displacements(self, k: int, executed: Mapping[str, Plan], last: Mapping[str, Plan]) -> None:
        """The robots whose executed plan of step k left their goal (parked → returning): a
        displacement each, for the nearest robot that moves (under way or returning, on its
        plan), whose way it cleared.  Where two robots displace each other in turn, the count of
        :attr:`turns` grows: at 2 the same robot has stepped aside for the same other again, a
        cycle the progress argument does not rule out (docs/method.md §7, "What is not ruled
        out")."""
        self.news = []
        for r, pl in executed.items():
            before, self.phases[r] = self.phases.get(r), pl.phase
            if before == RETURNING and pl.phase == PARKED and r in self._out:
                self._out.pop(r)["to_step"] = k
            if before != PARKED or pl.phase != RETURNING:
                continue
            here = pl.committed[-1]
            movers = [
                j
                for j in self.ids
                if j != r and j in last and j not in self.off and last[j].phase not in (PARKED, WAITING)
            ]
            by = min(movers, key=lambda j: float(np.linalg.norm(last[j].committed[-1] - here)), default=None)
            self.robot[r]["displaced"] += 1
            self.displacements += 1
            ep = {"robot": r, "for": by, "from_step": k, "to_step": None}
            self._out[r] = ep
            if len(self.displaced) < MAX_EPISODES:
                self.displaced.append(ep)
            traded = 0
            if by is not None:
                pair = (min(r, by), max(r, by))
                last_one, n = self.turns.get(pair, (r, 0))
                self.turns[pair] = (r, n + (last_one != r))
                traded = n + 1 if last_one != r and n + 1 >= 2 else 0
            self.news.append({"robot": r, "for": by, "traded": traded})

    def traded(self) -> list[dict[str, Any]]:
        """The pairs of robots that have displaced each other in turn twice or more: ``robots``
        and ``turns`` (:attr:`turns`)."""
        return [{"robots": list(p), "turns": n} for p, (_, n) in sorted(self.turns.items()) if n >= 2]

    def _walls(self, k: int, last: Mapping[str, Plan]) -> None:
        """Whose way home the parked robots wall in at step k: each robot under way or returning
        whose committed point and goal the discs of radius r_i + r_j about the parked robots'
        committed points, past the walls and obstacles, leave in different pieces of free space
        (the loader's model, ``ground/freespace.py``: the assumption (B) of docs/method.md §7
        failing as the run goes).  Starts and ends an episode of :attr:`walled_episodes`."""
        from ground.freespace import free_space_model

        assert self.footprint is not None
        model = free_space_model(self.scn.arena, self.scn.obstacles, self.footprint)
        parked = tuple(r for r in self.ids if r in last and last[r].phase == PARKED and r not in self.off)
        # Labelled again when a parked robot comes, goes or moves by a centimetre or so.
        key = tuple((r, *np.round(last[r].committed[-1], 2).tolist()) for r in parked)
        if self._carved is None or self._carved[0] != key:
            discs = [(last[r].committed[-1], 2.0 * self.footprint) for r in parked]
            self._carved = (key, model.carve(discs))
        carved = self._carved[1]
        now: dict[str, list[str]] = {}
        for r in self.ids:
            pl = last.get(r)
            if pl is None or r in parked or r in self.off:
                continue
            here, goal = pl.committed[-1], self.goals[r]
            if model.piece_in(carved.labels, here) is None or not model.joined(here, goal):
                continue  # on a disc's rim (the grid's cells), or no way home even alone
            walls = model.walls(carved, here, goal)
            if walls:
                now[r] = [parked[i] for i in walls]
        for r, by in now.items():
            if self.walled.get(r) != by:
                self._end_wall(r, k)
                self.walled_episodes.append({"robot": r, "by": by, "from_step": k, "to_step": None})
        for r in set(self.walled) - set(now):
            self._end_wall(r, k)
        self.walled = now

    def _no_room(self, r: str, k: int, by: str) -> None:
        """Robot r's plan of step k found no room to make way for ``by`` ("" if it had room, or
        was not making way): starts and ends an episode of :attr:`no_room_episodes`."""
        before = self.no_room[r]
        self.no_room[r] = by
        self.robot[r]["no_room"] += by != ""
        if by == before:
            return
        ended = self._no_room_open.pop(r, None)
        if ended is not None:
            ended["to_step"] = k
        if by and len(self.no_room_episodes) < MAX_EPISODES:
            self._no_room_open[r] = {"robot": r, "for": by, "from_step": k, "to_step": None}
            self.no_room_episodes.append(self._no_room_open[r])

    def _end_wall(self, r: str, k: int) -> None:
        for ep in self.walled_episodes:
            if ep["robot"] == r and ep["to_step"] is None:
                ep["to_step"] = k

    def layout(self) -> dict[str, dict[str, list[str]]] | None:
        """Whose way home the scenario's other goals wall in (:func:`~ground.scenario.forced_order`),
        once a plan has given the footprint (None before); worked out once."""
        if self.footprint is None:
            return None
        if self._layout is None or self._layout[0] != self.footprint:
            self._layout = (self.footprint, forced_order(self.scn, self.footprint))
        return self._layout[1]

    def arrival(self) -> Arrival | None:
        """The order of arrival the agents keep to (:func:`~ground.arrival.arrival`: who waits for
        whom, and where), once a plan has given the footprint (None before); worked out once, as
        every agent works it out.  With the navigator off (``deadlock = false``) nobody waits."""
        if self.footprint is None:
            return None
        if self._arrival is None or self._arrival[0] != self.footprint:
            arr = arrival(self.scn, self.footprint) if self.scn.controller.deadlock else Arrival({})
            self._arrival = (self.footprint, arr)
        return self._arrival[1]

    def _regoal(self, a: str, k: int, goal: Array) -> None:
        """Robot ``a``'s plan of step k heads for a new ``goal`` (2,) [m]: the samples of steps
        k + 1 on are measured against it, as ``fleet simulate`` does, also those judged already
        (a supervisor that fell behind takes a batch of samples before the plans of their steps)."""
        self.goals[a] = np.array(goal, dtype=float)
        for s in range(k + 1, len(self.sample_index)):
            i = self.sample_index[s]
            if i >= 0:
                pt = controlled_point(self.poses[a][i], self.lookahead)
                self.errors[a][i] = float(np.linalg.norm(pt - self.goals[a]))

    def _discs(self, k: int, plans: Iterable[Plan]) -> None:
        """What the agents' plans of step k kept clear of: count, per robot, the steps it was kept
        clear of as each kind (once a step however many agents did), keep the largest disc, and
        note the claims to judge against the sample of step k."""
        kinds: dict[str, set[str]] = {}
        claims: list[tuple[str, Array, float]] = []
        for pl in plans:
            for j, (kind, _, x, y, radius) in pl.discs.items():
                st = self.robot.get(j)
                if st is None:
                    continue
                kinds.setdefault(j, set()).add(kind)
                if kind in KEPT_CLEAR_AS:  # (a stale or placed disc is about a robot on its plans)
                    st["largest"] = max(st["largest"], radius)
                if kind in CLAIMED:
                    claims.append((j, np.array([x, y]), radius))
        for j, seen in kinds.items():
            for kind in seen:
                if kind in KEPT_CLEAR_AS:
                    self.robot[j]["as"][KEPT_CLEAR_AS[kind]] += 1
        if claims:
            self.claims.setdefault(k, []).extend(claims)
            self._judge_claims(k)

    def _judge_claims(self, k: int) -> None:
        """Judge the discs of step k that claim to hold a robot's true body (:data:`CLAIMED`),
        once both the plans and the sample of step k are in: the body, within robot_radius + ℓ of
        the true controlled point, must lie inside the disc.  A disc that does not hold it is an
        *escape*: a bound of docs/method.md §6.4 that the run broke."""
        claims = self.claims.get(k)
        if claims is None or len(self.sample_index) <= k:
            return
        del self.claims[k]
        i = self.sample_index[k]
        if i < 0:
            return  # its ground truth was lost on the way
        body = self.radius + self.lookahead
        for j, centre, radius in claims:
            pt = controlled_point(self.poses[j][i], self.lookahead)
            excess = float(np.linalg.norm(pt - centre)) + body - radius
            if excess > SLACK:
                self.robot[j]["escapes"] += 1
                self.escape_excess = max(self.escape_excess, excess)

    def link_lost(self, robot: str) -> None:
        """The radio link to ``robot`` was lost: it drove on uncontrolled (no deadman)."""
        if robot in self.robot:
            self.robot[robot]["link_losses"] += 1

    def link_state(self, robot: str, up: bool, step: int, lost: int) -> None:
        """The newest radio link state of ``robot`` (:class:`~ground.wire.LinkState`): ``up``, at
        the link's newest tick ``step``, last lost at tick ``lost`` (−1: never).  An outage counts
        as uncontrolled from the tick it was lost at to the newest tick the link saw it down, and
        to the tick it is seen up again."""
        st = self.robot.get(robot)
        if st is None or lost < 0:
            return
        now = self.outage.get(robot)
        if self.losses_seen.get(robot) != lost:  # a new outage
            self.losses_seen[robot] = lost
            if now is not None:  # (the one before ended unseen)
                st["uncontrolled"] += max(now[1] - now[0], 0)
                del self.outage[robot]
            if up:  # it began and ended between two looks
                st["uncontrolled"] += max(step - lost, 0)
            else:
                self.outage[robot] = (lost, max(step, lost))
        elif now is not None:
            if up:
                st["uncontrolled"] += max(step - lost, 0)
                del self.outage[robot]
            else:
                self.outage[robot] = (lost, max(step, now[1]))

    def off_plan(self, robot: str, kind: str) -> None:
        """The robot side did not apply ``robot``'s command of a step: it followed the shifted
        candidate (``kind`` "candidate") or braked ("braked")."""
        if robot in self.robot:
            self.robot[robot][kind] += 1

    def simulated(self, robot: str, step_ms: float, w_ratio: float, candidate_violation: float) -> None:
        """Figures of one step that only the in-process simulator measures: the controller's
        step time [ms], the realised one-step error of the measured state relative to W
        (max_j |w_j| / W_j) and the shifted candidate's constraint violation in the step's QP."""
        ex = self.extras[robot]
        for name, v in (
            ("step_ms", step_ms),
            ("w_ratio", w_ratio),
            ("candidate_violation", candidate_violation),
        ):
            ex.setdefault(name, []).append(float(v))

    # ------------------------------------------------------------------ output
    def reached(self, robot: str) -> bool:
        """The robot has arrived: its controlled point has stayed within the goal tolerance for
        the settle time up to the last sample (:func:`ground.scenario.settled_since`)."""
        return settled_since(self.errors[robot], self.Ts) is not None

    def summary(self, completed: bool, wall_time: float) -> dict[str, Any]:
        """``summary.json`` of the run (see the README's "summary.json")."""
        traded = self.traded()
        robots = {r: self._robot_summary(r, traded) for r in self.ids}
        fin = lambda v: v if math.isfinite(v) else None  # noqa: E731
        sim = self.steps * self.Ts
        out: dict[str, Any] = {
            "scenario": self.scn.name,
            "completed": completed,
            "steps": self.steps,
            "sim_time_s": sim,
            "wall_time_s": wall_time,
            "real_time_factor": sim / wall_time if wall_time > 0 else None,
            "min_distance_m": fin(self.min_distance),
            "collision_distance_m": 2.0 * self.radius,
            "collisions": self.collisions,
            "min_reference_separation_m": fin(self.min_ref),
            "required_reference_separation_m": None if self.footprint is None else 2.0 * self.footprint,
            "reference_separation_violations": self.ref_violations,
            "obstacle_violations": self.obstacle_violations,
            "arena_violations": self.arena_violations,
            "disc_escapes": sum(v["disc_escapes"] for v in robots.values()),
            "max_disc_escape_m": self.escape_excess,
            "all_goals_reached": all(v["reached_goal"] for v in robots.values()),
            "footprint_radius_m": self.footprint,
            "unjudged_steps": self.skipped_steps,
            "places_heard_late": sum(v["places_heard_late"] for v in robots.values()),
            # Whose way home the others' goals wall in (the scenario's goals): null before a plan.
            "forced_order": self.layout(),
            # Who waits for whom, and where, before first going home: null before a plan.
            "order_of_arrival": _arrival_summary(self.arrival()),
            # Whose way home parked robots walled in as the run went, and when (steps).
            "walled_in": [dict(ep) for ep in self.walled_episodes],
            # Robots that found no room to step aside for a robot that goes first, and when
            # (steps): the first MAX_EPISODES of them.
            "no_room": [dict(ep) for ep in self.no_room_episodes],
            # Parked robots that stepped aside, for whom, and until when (steps); the first
            # MAX_EPISODES of them, and all of them counted.
            "displacements": self.displacements,
            "displaced": [dict(ep) for ep in self.displaced],
            # Pairs that displaced each other in turn twice or more (a cycle, docs/method.md §7).
            "traded_places": traded,
            "robots": robots,
        }
        steps_ms = [v for r in self.ids for v in self.extras[r].get("step_ms", [])]
        if steps_ms:
            out["step_time_ms"] = percentiles(steps_ms)
        return out

    def _robot_summary(self, r: str, traded: Sequence[Mapping[str, Any]] = ()) -> dict[str, Any]:
        err = np.array(self.errors[r]) if self.errors[r] else np.array([math.inf])
        since = settled_since(self.errors[r], self.Ts)
        pts = np.array([controlled_point(q, self.lookahead) for q in self.poses[r]]).reshape(-1, 2)
        steps_m = np.linalg.norm(np.diff(pts, axis=0), axis=1)  # (samples − 1,) [m]
        p = self.scn.controller
        st = self.robot[r]
        out: dict[str, Any] = {
            "goal": self.goals[r].tolist(),
            "reached_goal": since is not None,
            "time_to_goal_s": None if since is None else since * self.Ts,
            "final_error_m": float(err[-1]),
            "path_length_m": float(steps_m.sum()),
            "straight_line_m": float(np.linalg.norm(pts[0] - self.goals[r])) if len(pts) else 0.0,
            # To the sample its final stay at the goal began: the hold at the goal left out.
            "path_to_arrival_m": None if since is None else float(steps_m[:since].sum()),
            "travel_floor_s": travel_floor(pts[0] - self.goals[r], p.v_max, p.a_max, GOAL_TOLERANCE)
            if len(pts)
            else 0.0,
            "qp_solves": st["solves"],
            "qp_failures": st["failures"],
            "fallbacks": st["failures"],
            "tube_exits": st["tube_exits"],
            "steps_on_candidate": st["candidate"],
            "steps_braked": st["braked"],
            "steps_blind": st["blind"],
            "link_losses": st["link_losses"],
            "uncontrolled_s": (st["uncontrolled"] + self._open_outage(r)) * self.Ts,
            "steps_held_link_down": st["held_link_down"],
            "arena_violations": st["arena"],
            "goal_blocked_by": self.blocked[r] or None,
            "walled_in_by": self.walled.get(r),
            "no_room_steps": st["no_room"],
            "no_room_for": self.no_room[r] or None,
            "displaced": st["displaced"],
            "traded_places_with": [j for p in traded if r in p["robots"] for j in p["robots"] if j != r],
            "kept_clear_as": {**st["as"], "largest_disc_m": st["largest"] or None},
            "disc_escapes": st["escapes"],
            "places_heard_late": st["late"],
            "reference_breaks": st["breaks"],
            "status_counts": dict(st["status"]),
            "max_reference_deviation_m": self.deviation(r),
            "max_pose_error": {"position_m": self.pose_error[r][0], "heading_rad": self.pose_error[r][1]},
            "solve_time_ms": percentiles(st["solve_ms"]),
        }
        ex = self.extras[r]
        if ex:
            out["step_time_ms"] = percentiles(ex["step_ms"])
            out["max_w_ratio"] = max(ex["w_ratio"], default=0.0)
            out["max_candidate_violation"] = max(ex["candidate_violation"], default=0.0)
        if r in self.repairs:
            out["repairs"] = self.repairs[r]
        return out

    def _open_outage(self, robot: str) -> int:
        """Steps of ``robot``'s outage still open: from its loss to the last step judged."""
        now = self.outage.get(robot)
        return 0 if now is None else max(max(now[1], self.steps) - now[0], 0)

    def deviation(self, robot: str) -> float:
        """The largest distance [m] of the robot's true controlled point from the executed
        reference committed for the same time (‖p − ỹ‖, which the tube bounds by ρ)."""
        poses, refs = self.poses[robot], self.refs[robot]
        worst = 0.0
        for pose, ref in zip(poses, refs, strict=False):
            worst = max(worst, float(np.linalg.norm(controlled_point(pose, self.lookahead) - ref)))
        return worst

    def trace_refs(self, samples: int) -> Array:
        """The executed reference of every robot for each of ``samples`` samples, (R, T, 2) [m]
        (NaN where none is known yet)."""
        refs = np.full((len(self.ids), samples, 2), np.nan)
        for i, r in enumerate(self.ids):
            got = np.array(self.refs[r][:samples]).reshape(-1, 2)
            refs[i, : len(got)] = got
        return refs


def verdict(summary: Mapping[str, Any]) -> str | None:
    """Why a run (its ``summary.json``) failed, in one line, or None if it passed: every step
    judged, no collision, no robot off the arena, no robot outside a disc that claimed to hold it
    (a bound of docs/method.md §6.4 broken), every robot at its goal (one whose goal a stopped
    robot covers is named with it)."""
    why = []
    robots = summary.get("robots", {})
    if not summary.get("completed", False):
        why.append(f"only {summary.get('steps', 0)} steps of the run were judged")
    if summary.get("collisions"):
        why.append(f"{summary['collisions']} collision samples")
    if summary.get("arena_violations"):
        off = [r for r, v in robots.items() if v.get("arena_violations")]
        why.append(f"{summary['arena_violations']} arena violation samples ({', '.join(off)})")
    if summary.get("disc_escapes"):
        out = ", ".join(r for r, v in robots.items() if v.get("disc_escapes"))
        why.append(f"{summary['disc_escapes']} samples of a robot outside the disc that claimed it ({out})")
    missing = [
        r
        + (f" (goal blocked by {v['goal_blocked_by']})" if v.get("goal_blocked_by") else "")
        + (f" (way home walled in by {', '.join(v['walled_in_by'])})" if v.get("walled_in_by") else "")
        + (f" (no room to make way for {v['no_room_for']})" if v.get("no_room_for") else "")
        + (
            f" (traded places with {', '.join(v['traded_places_with'])})"
            if v.get("traded_places_with")
            else ""
        )
        for r, v in robots.items()
        if not v["reached_goal"]
    ]
    if missing:
        why.append("goal not reached by " + ", ".join(missing))
    return "; ".join(why) or None


def fault_note(summary: Mapping[str, Any]) -> str | None:
    """One line on what faults did to a run (its ``summary.json``), or None if none showed: radio
    links lost and the time their robots drove uncontrolled, robots kept clear of as off their
    plans (dead, braked, blind) with the largest disc used, goals blocked by a stopped robot, and
    discs that did not hold their robot."""
    parts = []
    robots = summary.get("robots", {})
    lost = [(r, v) for r, v in robots.items() if v.get("link_losses")]
    if lost:
        parts.append(
            "links lost: "
            + ", ".join(
                f"{r} {v['link_losses']}× ({v['uncontrolled_s']:.1f} s uncontrolled)" for r, v in lost
            )
        )
    off = []
    for r, v in robots.items():
        kept = v.get("kept_clear_as", {})
        steps = {k: n for k, n in kept.items() if k != "largest_disc_m" and n}
        if steps:
            kinds = ", ".join(f"{k} {n}" for k, n in steps.items())
            off.append(f"{r} ({kinds} steps; largest disc {kept['largest_disc_m']:.3f} m)")
    if off:
        parts.append("kept clear of: " + "; ".join(off))
    blocked = [f"{r} by {v['goal_blocked_by']}" for r, v in robots.items() if v.get("goal_blocked_by")]
    if blocked:
        parts.append("goals blocked: " + ", ".join(blocked))
    if summary.get("disc_escapes"):
        parts.append(
            f"{summary['disc_escapes']} samples of a robot outside the disc that claimed it "
            f"(by up to {summary['max_disc_escape_m']:.3f} m)"
        )
    return "; ".join(parts) or None


def percentiles(values: Iterable[float]) -> dict[str, float]:
    """``{"p50", "p99", "max"}`` of a series (0 for an empty one)."""
    a = np.fromiter(values, dtype=float)
    if a.size == 0:
        a = np.zeros(1)
    return {"p50": float(np.percentile(a, 50)), "p99": float(np.percentile(a, 99)), "max": float(a.max())}


def continues(prev: Plan, plan: Plan) -> bool:
    """``plan`` keeps what ``prev`` committed (a committed reference is never changed, only
    extended): with d = plan.step − prev.step ≥ 1, its references for the times prev had
    committed are prev's, exactly; "stay put" (prev's end point) fills the d − 1 steps between
    whose plans were not executed; only the last point is new.  A robot whose agent started
    again from where it is (restarted, or its robot braked) breaks this, and so would an agent
    and a robot side that disagree on what was executed."""
    d = plan.step - prev.step
    n = prev.committed.shape[0]
    if plan.committed.shape[0] != n or d < 1:
        return False
    kept = max(n - d, 0)
    if not np.array_equal(plan.committed[:kept], prev.committed[d : d + kept]):
        return False
    return bool(np.all(plan.committed[kept : n - 1] == prev.committed[-1]))


def _pair_distances(P: Array) -> Array:
    """Distances [m] between the points (n, 2) [m], one per pair i < j, in
    ``np.triu_indices(n, 1)`` order (n(n − 1)/2,)."""
    i, j = np.triu_indices(len(P), 1)
    return np.asarray(np.hypot(P[i, 0] - P[j, 0], P[i, 1] - P[j, 1]))


def _arrival_summary(arr: Arrival | None) -> dict[str, Any] | None:
    """The order of arrival as ``summary.json`` keeps it: per robot that waits, whom for and
    where (``wait_point`` [m]); the robots in a cycle of waits, without a wait point, and those
    the lemma does not cover (docs/method.md §7, "The order of arrival")."""
    if arr is None:
        return None
    return {
        "waits": {
            rid: {"waits_for": list(g.waits_for), "wait_point": [float(v) for v in g.wait_point]}
            for rid, g in arr.gates.items()
        },
        "unordered": list(arr.unordered),
        "no_wait_point": list(arr.no_wait_point),
        "unproven": list(arr.unproven),
    }
