"""Which other robots an agent coordinates with this step, and which it keeps clear of as discs.

A robot coordinates with a neighbour by the split rule (:func:`agent.coordination.split_halfplanes`)
only when it has that neighbour's plan of the previous step and the neighbour is alive and its
robot not braked.  Every other robot is a *hazard*: a static disc around its last known committed
point, grown for every step its plans have been missing (:func:`agent.coordination.hazard_halfplanes`).
:class:`Guard` sorts them, step by step (docs/method.md §6).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Container, Mapping, Sequence

import numpy as np

from agent.coordination import PLACE_LAG, Hazard, NeighbourInfo
from ground.geometry import Cell, Whereabouts, cell_centre, cell_of, cells_apart
from ground.params import ControllerParams
from ground.wire import BLIND, LinkState, Plan


def neighbour_of(plan: Plan) -> NeighbourInfo:
    """What the controller uses of a neighbour's plan.  Its arrays are views of the received
    plan's, which nothing changes (a copy each costs three calls per neighbour and step)."""
    return NeighbourInfo(
        plan.robot, plan.committed[-1], plan.footprint, plan.priority, plan.rank, plan.target, plan.goal,
        plan.phase, plan.phase_age,
    )  # fmt: skip


def loose(ls: LinkState | None, newest: Plan | None) -> bool:
    """The robot's link is down, or back with no plan yet made from where the robot stands: it
    drives on (or stood) uncontrolled, off its plans (:meth:`Guard._loose`)."""
    return ls is not None and (not ls.up or (-1 if newest is None else newest.step) < ls.back)


def in_reach(
    others: Sequence[str], mine: Cell, side: float, last: Mapping[str, Plan | None],
    places: Mapping[str, Whereabouts], starts: Mapping[str, NeighbourInfo], live: Container[str],
    discs: Container[str] = (),
) -> list[str]:  # fmt: skip
    """The robots of ``others`` that an agent whose last committed point is in cell ``mine``
    (cells of ``side`` [m]) coordinates with, with plans by place (docs/method.md §6):

    * every robot whose agent is gone (not in ``live``), and every one in ``discs``: those its
      robot side braked, whose link is down (:func:`loose`) or whose last plan says its agent
      is blind.  They are kept clear of as discs, which can be wider than a cell, so their
      rows may be needed beyond the reach; the QP drops the rows of a far disc itself
      (:func:`agent.coordination.hazard_halfplanes`);
    * every other robot whose last committed point is in ``mine`` or one of the eight cells
      around it, by what was last heard of it: its newest plan (``last``), or its place token
      (``places``) if that is newer, or else its start (``starts``).

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
            or cells_apart(cell, mine) <= 1
        ):
            out.append(j)
    return out


class Guard:
    """Sorts the other robots, each step, into neighbours and hazards (docs/method.md §6).

    * A live robot whose plan of step k − 1 is in is a *neighbour*: the split rule.
    * A live robot whose latest plan is m ≥ 1 steps older (lost or late) is a
      *hazard*: a static disc around its last known committed point ĉ_j of
      radius r_j + (m + 1)·√2·ε, since its appended point moves at most ε per
      axis a step.
    * A dead robot (liveliness gone; its robot side brakes it), or one whose agent
      says it is blind (:data:`ground.wire.BLIND`: no poses, braking), is a hazard of
      radius r_j + max(N, m + 1)·√2·ε + v_max²/(2 a_max): wherever its reference was
      when it died is within that of ĉ_j, and braking adds the stopping distance.
    * At step 0 every robot is a neighbour at its scenario start, as in
      ``fleet simulate``.

    The disc rule alone keeps the appended points R apart whatever the other
    robot does, so mixing it with a neighbour's split rule is safe.  Changes
    are logged the first time each, then only counted."""

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
        self.brake = p.v_max**2 / (2.0 * p.a_max)
        self.hazard_steps = 0
        self.transitions = 0
        self._state: dict[str, str] = {}
        self._logged: set[tuple[str, str, str]] = set()

    def classify(
        self, k: int, others: list[str], fresh: dict[str, Plan | None], last: dict[str, Plan | None],
        live: set[str], starts: dict[str, NeighbourInfo], braked: frozenset[str] | set[str] = frozenset(),
        links: Mapping[str, LinkState | None] | None = None, places: Mapping[str, Whereabouts] | None = None,
    ) -> tuple[list[NeighbourInfo], list[Hazard]]:  # fmt: skip
        """(neighbours, hazards) for step k from the plans of step k − 1 (``fresh``),
        the latest plans (``last``), the live set, the robots their robot side braked
        over step k − 1 (Tick.braked): those have left their plans as a dead robot's has,
        and the newest link state of each robot (``links``): a robot whose link is down drives
        on uncontrolled, a moving obstacle.  With plans by place, ``places``: the robots' place
        tokens; a robot without a plan of step k − 1 whose token is newer than its newest plan
        known here (it moved to another cell since, out of this agent's hearing, or its plans
        of the new cell were lost) is kept clear of as the smaller of the disc its plan gives and
        one about that cell (:meth:`_placed`)."""
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
                hazards.append(self._loose(k, j, ls, last.get(j), starts[j]))
                self._note(j, "loose", k)
                continue
            blind = newest is not None and newest.status == BLIND
            if pl is not None and j in live and j not in braked and not blind:
                nbs.append(neighbour_of(pl))
                if self._state.get(j, "neighbour") != "neighbour":
                    self._note(j, "neighbour", k)
                continue
            old = last.get(j)
            centre, since, r_j = (
                (starts[j].last_point, -1, starts[j].footprint) if old is None
                else (old.committed[-1], old.step, old.footprint)
            )  # fmt: skip
            m = max(k - 1 - since, 0)
            if j in live and j not in braked and not blind:
                radius = r_j + (m + 1) * self.eps
                info = neighbour_of(old) if old is not None else starts[j]
                state = "stale"
            else:
                radius = r_j + max(self.N, m + 1) * self.eps + self.brake
                info = None
                state = "dead" if j not in live else "braked" if j in braked else "blind"
            hz = Hazard(j, np.array(centre, dtype=float), radius, info)
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
        return Hazard(j, centre, radius, None)

    def _placed(self, j: str, where: Whereabouts, start: NeighbourInfo) -> Hazard:
        """A robot known only by its place token: its last committed point was in the token's
        cell when the token came, and since then moved at most √2·ε a step for
        :data:`agent.coordination.PLACE_LAG` steps before a newer token would have come.  Its
        agent may have fallen silent there, and then its robot followed the last candidate for
        up to N steps more before braking: a disc of radius r_j + side/√2 + (N + lag)·√2·ε +
        v_max²/(2 a_max) about the cell's centre, whatever the robot does (alive, its newer plans
        would move the token on)."""
        assert self.side is not None
        radius = start.footprint + self.side / math.sqrt(2.0) + (self.N + PLACE_LAG) * self.eps + self.brake
        return Hazard(j, cell_centre(where.cell, self.side), radius, None)

    def _note(self, j: str, state: str, k: int) -> None:
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
            "dead": "not alive; kept clear of as a static obstacle while its robot stops",
            "braked": "braked by its robot side; kept clear of as a static obstacle while it stops",
            "blind": "without poses, braking; kept clear of as a static obstacle while it stops",
            "loose": "link down, driving on uncontrolled; kept clear of as a moving obstacle",
            "placed": "known by its place token only; kept clear of as a disc about its cell",
        }[state]
        self.log(f"step {k}: {j}: {what}")
