"""Which other robots an agent coordinates with this step, and which it keeps clear of as discs.

A robot coordinates with a neighbour by the split rule (:func:`agent.coordination.split_halfplanes`)
only when it has that neighbour's plan of the previous step and the neighbour is alive and its
robot not braked.  Every other robot is a *hazard*: a disc around its last known committed
point, grown for every step its plans have been missing, or, once it is off its plans for good
(its agent gone, its robot braked, its agent blind), a static disc of bounded size: first the
bound of where its reference and its brake can still take it, then, once its robot is known to
stand still, a disc about where the camera sees it (:func:`agent.coordination.hazard_halfplanes`).
:class:`Guard` sorts them, step by step (docs/method.md §6).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Container, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from agent.coordination import PLACE_LAG, UNCONTROLLED_PRIORITY, Hazard, NeighbourInfo
from ground.geometry import Array, Cell, Whereabouts, cell_centre, cell_of, cells_apart, controlled_point
from ground.model import stopping
from ground.params import ControllerParams
from ground.scenario import RobotSpec
from ground.wire import BLIND, UNDER_WAY, LinkState, Plan


def neighbour_of(plan: Plan) -> NeighbourInfo:
    """What the controller uses of a neighbour's plan.  Its arrays are views of the received
    plan's, which nothing changes (a copy each costs three calls per neighbour and step)."""
    return NeighbourInfo(
        plan.robot, plan.committed[-1], plan.footprint, plan.priority, plan.rank, plan.target, plan.goal,
        plan.phase, plan.phase_age,
    )  # fmt: skip


def starts_of(robots: Sequence[RobotSpec], lookahead: float, footprint: float) -> dict[str, NeighbourInfo]:
    """What every agent knows of each of ``robots`` (the scenario's, in rank order) before its
    first plan: at rest at its start's controlled point (ℓ = ``lookahead`` [m]), with the
    ``footprint`` [m] of the design and its goal as target (:meth:`Guard.classify` at step 0)."""
    return {
        r.id: NeighbourInfo(
            id=r.id, last_point=controlled_point(r.start, lookahead), footprint=footprint,
            priority=r.priority, rank=i, target=np.array(r.goal, float), goal=np.array(r.goal, float),
        )
        for i, r in enumerate(robots)
    }  # fmt: skip


def loose(ls: LinkState | None, newest: Plan | None) -> bool:
    """The robot's link is down, or back with no plan yet made from where the robot stands: it
    drives on (or stood) uncontrolled, off its plans (:meth:`Guard._loose`)."""
    return ls is not None and (not ls.up or (-1 if newest is None else newest.step) < ls.back)


def in_reach(
    others: Sequence[str], mine: Cell, side: float, last: Mapping[str, Plan | None],
    places: Mapping[str, Whereabouts], starts: Mapping[str, NeighbourInfo], live: Container[str],
    discs: Container[str] = (),
    within: int = 1,
) -> list[str]:  # fmt: skip
    """The robots of ``others`` that an agent whose last committed point is in cell ``mine``
    (cells of ``side`` [m]) coordinates with, with plans by place (docs/method.md §6); with
    ``within`` = :data:`~agent.coordination.VIEW_CELLS`, those its navigator sees:

    * every robot whose agent is gone (not in ``live``), and every one in ``discs``: those its
      robot side braked, whose link is down (:func:`loose`) or whose last plan says its agent
      is blind.  They are kept clear of as discs, which can be wider than a cell, so their
      rows may be needed beyond the reach; the QP drops the rows of a far disc itself
      (:func:`agent.coordination.hazard_halfplanes`);
    * every other robot whose last committed point is at most ``within`` cells from ``mine``
      (Chebyshev: its own cell and the eight around it by default), by what was last heard of
      it: its newest plan (``last``), or its place token (``places``) if that is newer, or
      else its start (``starts``).

    A robot farther away gets no row from the split rule (:func:`agent.coordination.place_side`),
    so leaving it out changes nothing the constraints guarantee."""
    out = []
    for j in others:
        pl, w = last.get(j), places.get(j)
        if w is not None and (pl is None or pl.step < w.since):
            cell = w.cell
        else:
            cell = cell_of(starts[j].last_point if pl is None else pl.committed[-1], side)
        if (
            j not in live
            or j in discs
            or (pl is not None and pl.status == BLIND)
            or cells_apart(cell, mine) <= within
        ):
            out.append(j)
    return out


def trail_steps(point_noise: float, horizon: int, epsilon: float) -> int:
    """Steps [steps] over which the heading of a robot driving on uncontrolled is measured
    (:meth:`Guard._velocity`): the fewest W ≥ 1 whose noise moves the predicted end of its sweep
    by at most ε.  Each camera point is within √2·η of the true one (η = ``point_noise`` [m] per
    axis), so two W steps apart give the velocity within 2·√2·η/(W·Ts), and the point N + 1
    steps ahead within 2·√2·η·(N + 1)/W; ε [m] is what a reference moves a step, the most one
    step of the navigator's replies could make up.  Fewer steps follow the robot's arc more
    closely (its chord over W steps lags its heading by half the angle turned): 2 steps with
    the epuck preset, 11 with η = 1 mm."""
    return max(1, math.ceil(2.0 * math.sqrt(2.0) * point_noise * (horizon + 1) / epsilon - 1e-9))


@dataclass
class _OffPlan:
    """One robot off its plans for good, as one agent knows it (:class:`Guard`): an episode that
    ends when the robot is a neighbour again, or loose."""

    since: int
    """The step the agent first kept clear of it as off its plans [steps]."""
    kind: str
    """Why, as first found: dead, braked or blind."""
    seen: int
    """The last step the agent classified it at [steps]: a step skipped since (the agent fell
    behind the clock) ends the episode, for the robot may have moved meanwhile."""
    run_from: int | None = None
    """The first step of the robot side's current run of braking it, as the reports (Tick.braked,
    Outcome.braked) say, or None [steps]."""
    run_to: int = -1
    """The last step of that run reported [steps]."""
    rest_disc: Hazard | None = None
    """The disc about where the camera saw it once its robot stood still, or None."""
    frozen: tuple[Array, float] | None = None
    """The episode's frozen disc as last computed: (centre (2,) [m], radius [m])."""
    back: int | None = None
    """The first step its robot was reported not braked after a run of braking (its agent drives
    it again: it started again where the robot stood), with no plan of it heard since, or None
    [steps]."""


class Guard:
    """Sorts the other robots, each step, into neighbours and hazards (docs/method.md §6.4).

    * A live robot whose plan of step k − 1 is in is a *neighbour*: the split rule.
    * A live robot whose latest plan is m ≥ 1 steps older (lost or late) is *stale*: a disc
      around its last known committed point ĉ_j of radius r_j + (m + 1)·√2·ε, since its
      appended point moves at most ε per axis a step.
    * A robot off its plans for good, *dead* (liveliness gone; its robot side brakes it),
      *braked* (its robot side says so) or *blind* (its agent holds without poses,
      :data:`ground.wire.BLIND`), noticed at step k₀ with its newest plan of step s: a static
      disc about ĉ_j of radius r_j + max(N, k₀ − s)·√2·ε + d_stop.  Its reference had moved at
      most that far from ĉ_j when it left its plans (no later than k₀), its robot followed at
      most the rest of its last plan's candidate (N steps), and the brake adds d_stop
      (:func:`ground.model.stopping`).  m is frozen at k₀: the disc never grows after.
    * Once its robot side has braked it for S = (the brake's steps to rest) + 1 steps in a row,
      its robot stands still, and a camera pose of it from then on gives the *rest* disc: about
      that measured controlled point, of radius r_j + 2·√2·η (η the pose noise on the point,
      :attr:`ground.params.ControllerParams.point_noise`): the true point is within √2·η of
      it, and an agent that starts again there commits its own measurement, within 2·√2·η of
      it, so the split rule's invariant holds from its first plan.  Poses come from
      ``poses``; :attr:`watched` says whose the agent should take.
    * A robot whose agent is back (alive, its robot not braked) with no plan heard since is
      stale: the smaller of the stale disc and its rest disc grown by √2·ε a step since.
    * At step 0 every robot is a neighbour at its scenario start, as in ``fleet simulate``.

    The disc rule alone keeps the appended points R apart whatever the other robot does, so
    mixing it with a neighbour's split rule is safe.  Changes are logged the first time each,
    then only counted."""

    def __init__(self, me: str, p: ControllerParams, log: Callable[[str], None], side: float | None = None):
        """``side`` [m]: the cells of plans by place (:func:`agent.coordination.place_side`), for
        the discs of robots known only by their place token; None: plans go to every agent."""
        self.me = me
        self.side = side
        self.log = log
        self.Ts = p.Ts
        self.eps = math.sqrt(2.0) * p.epsilon
        """Euclidean reach of one step [m]: ȳ moves at most ε per axis (the QP's ε box)."""
        self.N = p.horizon
        steps, self.brake = stopping(p.v_max, p.a_max, p.Ts)
        """``brake``: how far [m] a braked robot's controlled point moves before it stands still."""
        self.stop_after = steps + 1
        """Steps [steps] of braking after which a robot stands still: the brake's steps to rest
        from v_max (:func:`ground.model.stopping`), and one for a brake decided within its step
        (``epuck_link`` decides at the deadline, holding the step's acceleration until then)."""
        self.noise = math.sqrt(2.0) * p.point_noise
        """How far a camera's controlled point may be from the true one [m]: √2·η."""
        self.rest_margin = 2.0 * self.noise + self.eps
        """What a disc about a camera pose of a robot at rest adds to r_j [m]: 2·√2·η, for the true
        point and another measurement of it, and √2·ε, for the point its agent appends in the step
        it starts again in, so that its first plan ends inside the disc."""
        self.body = p.robot_radius + p.lookahead
        """The body's reach about the controlled point [m]."""
        self.hazard_steps = 0
        self.transitions = 0
        self._state: dict[str, str] = {}
        self._logged: set[tuple[str, str, str]] = set()
        self._off: dict[str, _OffPlan] = {}
        self.trail = trail_steps(p.point_noise, p.horizon, p.epsilon)
        """Steps over which a robot driving on uncontrolled is seen heading (:func:`trail_steps`)."""
        self._trail: dict[str, list[tuple[int, float, float]]] = {}
        """Per robot driving on uncontrolled, the camera's controlled points of it the link
        states carried, (seq [steps], x [m], y [m]), over the last :attr:`trail` steps."""

    @property
    def watched(self) -> set[str]:
        """The robots whose camera poses :meth:`classify` can use: dead or braked, not yet known to
        stand still where the camera saw them (an agent subscribes to their poses)."""
        return {
            j
            for j, ep in self._off.items()
            if ep.rest_disc is None and ep.back is None and ep.kind != "blind"
        }

    def classify(
        self, k: int, others: list[str], fresh: dict[str, Plan | None], last: dict[str, Plan | None],
        live: set[str], starts: dict[str, NeighbourInfo], braked: frozenset[str] | set[str] = frozenset(),
        links: Mapping[str, LinkState | None] | None = None, places: Mapping[str, Whereabouts] | None = None,
        poses: Mapping[str, tuple[int, Array]] | None = None,
    ) -> tuple[list[NeighbourInfo], list[Hazard]]:  # fmt: skip
        """(neighbours, hazards) for step k from the plans of step k − 1 (``fresh``),
        the latest plans (``last``), the live set, the robots their robot side braked
        over step k − 1 (Tick.braked or Outcome.braked: the report of that step; a robot not in
        it was not braked then): those have left their plans as a dead robot's has,
        and the newest link state of each robot (``links``): a robot whose link is down drives
        on uncontrolled, a moving obstacle.  With plans by place, ``places``: the robots' place
        tokens; a robot without a plan of step k − 1 whose token is newer than its newest plan
        known here (it moved to another cell since, out of this agent's hearing, or its plans
        of the new cell were lost) is kept clear of as the smaller of the disc its plan gives and
        one about that cell (:meth:`_placed`).  ``poses``: the newest camera pose heard of each
        robot in :attr:`watched`, as (its seq [steps], the controlled point (2,) [m])."""
        nbs: list[NeighbourInfo] = []
        hazards: list[Hazard] = []
        for j in others:
            pl = fresh.get(j)
            if k == 0:
                nbs.append(starts[j])
                continue
            ls = None if links is None else links.get(j)
            newest = pl if pl is not None else last.get(j)
            if ls is not None and loose(ls, newest):
                # Down, or back but with no plan yet made from where the robot stands.
                self._off.pop(j, None)
                hazards.append(self._loose(k, j, ls, last.get(j), starts[j]))
                self._note(j, "loose", k)
                continue
            blind = newest is not None and newest.status == BLIND
            on_plan = j in live and j not in braked and not blind
            if pl is not None and on_plan:
                self._off.pop(j, None)
                nbs.append(neighbour_of(pl))
                if self._state.get(j, "neighbour") != "neighbour":
                    self._note(j, "neighbour", k)
                continue
            old = last.get(j)
            centre, since, r_j = (
                (starts[j].last_point, -1, starts[j].footprint) if old is None
                else (old.committed[-1], old.step, old.footprint)
            )  # fmt: skip
            ep = self._off.get(j)
            if ep is not None and ep.seen < k - 1:
                del self._off[j]  # a step not classified: what it did meanwhile is not known
            if on_plan:
                hz, state = self._stale(k, j, old, centre, since, r_j, starts[j])
            else:
                state = "dead" if j not in live else "braked" if j in braked else "blind"
                hz = self._off_plan(k, j, state, centre, since, r_j, j in braked, j in live, poses)
            where = None if places is None else places.get(j)
            if where is not None and (old is None or old.step < where.since):
                # Both discs hold; the token's is the smaller once the plan is old enough.
                placed = self._placed(j, where, starts[j])
                if placed.radius < hz.radius:
                    hz, state = placed, "placed"
            hazards.append(hz)
            self._note(j, state, k)
        self.hazard_steps += len(hazards)
        return nbs, hazards

    def _stale(
        self, k: int, j: str, old: Plan | None, centre: Array, since: int, r_j: float, start: NeighbourInfo
    ) -> tuple[Hazard, str]:
        """A live robot, its robot not braked, whose plan of step k − 1 is missing: its appended
        point is within (m + 1)·√2·ε of its last committed point known (m steps missed).  If its
        agent has just come back from an off-plan episode whose rest disc is known, its first plan
        starts where the robot stands, inside that disc: the smaller disc of the two."""
        m = max(k - 1 - since, 0)
        hz = Hazard(j, np.array(centre, dtype=float), r_j + (m + 1) * self.eps,
                    neighbour_of(old) if old is not None else start, "stale")  # fmt: skip
        ep = self._off.get(j)
        if ep is not None:
            ep.seen = k
            if ep.back is None:
                ep.back = k
            if old is not None and old.step >= ep.back - 1:
                del self._off[j]  # a plan of its own since it came back: the stale disc about it holds
            elif (moved := self._moved(k, ep, r_j)) is not None and moved.radius < hz.radius:
                hz = Hazard(j, moved.centre, moved.radius, hz.info, "stale")
        return hz, "stale"

    def _moved(self, k: int, ep: _OffPlan, r_j: float) -> Hazard | None:
        """Where a robot whose agent drives it again since step ``ep.back`` (after a run of braking)
        can have appended its points by step k − 1: its agent started again where the robot stood,
        at its measurement, and moved its appended point √2·ε a step from there, from the step
        before ``back`` at the earliest (a plan made a step ahead).  About the rest disc, which
        holds that first point, grown by (k − back + 1)·√2·ε; with no rest disc, the episode's
        frozen disc is only known to hold the robot's body, so its measurement lies up to
        ρ_j − ε + √2·η further, and its first point √2·ε further still.  None if the episode has
        neither."""
        assert ep.back is not None
        grow = (k - ep.back + 1) * self.eps
        if ep.rest_disc is not None:
            return Hazard(ep.rest_disc.id, ep.rest_disc.centre, ep.rest_disc.radius + grow, None, ep.kind)
        if ep.frozen is None:
            return None
        centre, radius = ep.frozen
        rho, epsilon = r_j - self.body, self.eps / math.sqrt(2.0)
        return Hazard("", centre, radius + rho - epsilon + self.noise + self.eps + grow, None, ep.kind)

    def _off_plan(
        self, k: int, j: str, kind: str, centre: Array, since: int, r_j: float, braked: bool, live: bool,
        poses: Mapping[str, tuple[int, Array]] | None,
    ) -> Hazard:  # fmt: skip
        """A robot off its plans for good (``kind`` dead, braked or blind), its newest plan of step
        ``since`` ending at ``centre`` (2,) [m]: the static disc of its episode (see the class
        docstring), the rest disc once its robot is known to stand still."""
        ep = self._off.get(j)
        if ep is None or (ep.back is not None and braked):  # (braked again after it moved: anew)
            ep = self._off[j] = _OffPlan(since=k, kind=kind, seen=k)
        ep.seen, ep.kind = k, kind
        if braked:
            # The report of step k − 1 says its robot side braked it.
            if ep.run_from is None:
                ep.run_from = k - 1
            ep.run_to = k - 1
        elif ep.run_from is not None and ep.back is None:
            # Braked before, not over step k − 1: its robot side applied its agent's command, so its
            # agent drives it again (whatever this agent's view of its liveliness), or a report was
            # lost.  Either way it may move now: from where it stood.
            ep.back = k
        m0 = max(ep.since - 1 - since, 0)
        ep.frozen = (np.array(centre, dtype=float), r_j + max(self.N, m0 + 1) * self.eps + self.brake)
        if ep.back is not None:
            moved = self._moved(k, ep, r_j)
            assert moved is not None
            if since >= ep.back - 1:  # a plan of its own since it moves again: the smaller disc
                radius = r_j + (max(k - 1 - since, 0) + 1) * self.eps
                if radius < moved.radius:
                    return Hazard(j, np.array(centre, dtype=float), radius, None, kind)
            return Hazard(j, moved.centre, moved.radius, None, kind)
        if ep.run_from is not None and ep.rest_disc is None and poses is not None:
            got = poses.get(j)
            if got is not None and got[0] >= ep.run_from + self.stop_after:
                point = np.array(got[1], dtype=float)
                ep.rest_disc = Hazard(j, point, r_j + self.rest_margin, None, kind, True)
                where = f" at ({point[0]:.3f}, {point[1]:.3f}), radius {ep.rest_disc.radius:.3f} m"
                self._note(j, "rest", k, where)
        if ep.rest_disc is not None:
            return Hazard(j, ep.rest_disc.centre, ep.rest_disc.radius, None, kind, True)
        return Hazard(j, ep.frozen[0], ep.frozen[1], None, kind)

    def _loose(self, k: int, j: str, ls: LinkState, old: Plan | None, start: NeighbourInfo) -> Hazard:
        """A robot whose link is down (or back, with no plan yet from where it stands): a disc
        about its newest measured controlled point, grown by ``ls.speed`` for every step from
        that pose to the step after the one ȳ is for (k + N, with a step to spare).  Not a
        static disc: it moves, at its last wheel speeds.

        With no pose, the disc is about its last committed point ĉ_j, of its plan of step s (or
        its start, s = 0): its reference was within N·√2·ε of ĉ_j then, and from then on the
        robot moved at most the faster of its plan's reach (√2·ε a step) and ``ls.speed``, on
        its plan or adrift (the loss is noticed only after a reply timeout)."""
        r_j = start.footprint if old is None else old.footprint
        if ls.seq >= 0:
            centre, since, step_reach = np.array([ls.x, ls.y]), ls.seq, ls.speed * self.Ts
        else:
            centre = np.array(start.last_point if old is None else old.committed[-1], dtype=float)
            since = 0 if old is None else old.step
            r_j += self.N * self.eps
            step_reach = max(ls.speed * self.Ts, self.eps)
        radius = r_j + step_reach * max(k + self.N + 1 - since, 0)
        heads = centre + self._velocity(j, ls) * self.Ts * max(k + self.N + 1 - since, 0)
        info = NeighbourInfo(
            j, centre, r_j, priority=UNCONTROLLED_PRIORITY, rank=0, target=heads, phase=UNDER_WAY
        )
        return Hazard(j, centre, radius, info, "loose", drift=step_reach)

    def _velocity(self, j: str, ls: LinkState) -> Array:
        """Where a robot that drives on uncontrolled heads: its controlled point's velocity (2,)
        [m/s], from the camera's points of it over the last :attr:`trail` steps (0 with
        fewer than two, or none).  For the navigator only, which makes way for its sweep to
        where it will be at the end of the horizon (shaping: the disc bounds it whatever it
        does)."""
        trail = self._trail.setdefault(j, [])
        if ls.seq >= 0 and (not trail or ls.seq > trail[-1][0]):
            trail.append((ls.seq, ls.x, ls.y))
        while trail and trail[0][0] < trail[-1][0] - self.trail:
            trail.pop(0)
        if len(trail) < 2:
            return np.zeros(2)
        (s0, x0, y0), (s1, x1, y1) = trail[0], trail[-1]
        return np.array([x1 - x0, y1 - y0]) / ((s1 - s0) * self.Ts)

    def _placed(self, j: str, where: Whereabouts, start: NeighbourInfo) -> Hazard:
        """A robot known only by its place token: its last committed point was in the token's
        cell when the token came, and since then moved at most √2·ε a step for
        :data:`agent.coordination.PLACE_LAG` steps before a newer token would have come.  Its
        agent may have fallen silent there, and then its robot followed the last candidate for
        up to N steps more before braking: a disc of radius r_j + side/√2 + (N + lag)·√2·ε +
        d_stop about the cell's centre, whatever the robot does (alive, its newer plans would
        move the token on)."""
        assert self.side is not None
        radius = start.footprint + self.side / math.sqrt(2.0) + (self.N + PLACE_LAG) * self.eps + self.brake
        return Hazard(j, cell_centre(where.cell, self.side), radius, None, "placed")

    def _note(self, j: str, state: str, k: int, detail: str = "") -> None:
        if state == "rest":  # not a class of its own: its off-plan class goes on
            if (j, "rest", "") not in self._logged:
                self._logged.add((j, "rest", ""))
                self.log(f"step {k}: {j}: stands still{detail}; kept clear of as a static disc about it")
            return
        before = self._state.get(j, "neighbour")
        self._state[j] = state
        if state == before or (state == "stale" and before in ("dead", "braked", "blind", "loose")):
            return
        self.transitions += 1
        if (j, state, before) in self._logged:
            return  # each kind of change is logged once per neighbour, then counted
        self._logged.add((j, state, before))
        what = {
            "neighbour": "coordinating again",
            "stale": "its plan is late or lost; kept clear of as a growing static disc",
            "dead": "not alive; kept clear of as a static obstacle while it stops",
            "braked": "braked by its robot side; kept clear of as a static obstacle while it stops",
            "blind": "without poses, braking; kept clear of as a static obstacle while it stops",
            "loose": "link down, driving on uncontrolled; kept clear of as a moving obstacle",
            "placed": "known by its place token only; kept clear of as a disc about its cell",
        }[state]
        self.log(f"step {k}: {j}: {what}")
