"""The order of arrival a layout forces, made to hold: who waits for whom, and where.

:func:`ground.scenario.forced_order` says whose way home the others' goals wall in once they are
parked there.  This module turns that into a rule every agent can keep by itself, from the
scenario alone (docs/method.md §7, "The order of arrival"):

* robot j **waits for** robot i when j's goal walls in i's way by itself, or when j is the one
  chosen of several goals that wall it in together (the fewest, nearest i's goal or start first,
  whose absence opens the way);
* until every robot it waits for has been seen parked, j steers to its **wait point** instead of
  its goal: the nearest point to its goal, joined to it, at least a goal spacing from every other
  goal and wait point, whose disc splits no piece of free space;
* the waits form no cycle (robots in one get no gate, and are named).

:func:`arrival` also checks the one thing the rule needs of the geometry: for each robot, its way
from its start (by its wait point, if it has one) to its goal stays open past every goal of the
robots that do not wait for it and every wait point, all occupied at once.  Since removing discs
never shuts a way, its way is then open whichever of them are occupied at any time
(assumption (B) of the progress argument, made to hold).  A robot for which this fails is named
in :attr:`Arrival.unproven`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from ground.freespace import FreeSpace, free_space_model
from ground.geometry import controlled_point
from ground.scenario import GOAL_MARGIN, PARKED_RADIUS, Scenario, forced_order

WAIT_RING_STEP = 0.02
"""Radial step [m] of the rings about a goal on which its wait point is sought (the loader's
free space is sampled a fine cell apart, 5 mm in a 2 m arena; a point is placed to 2 cm)."""
WAIT_RING_POINTS = 36
"""Points on each ring (10° apart)."""
WAIT_CANDIDATES = 2000
"""Candidates a robot's wait point is sought among, at most, once the cheap tests pass (bounded
work at load: a robot with none gets no gate and is named)."""


@dataclass(frozen=True)
class Gate:
    """What one robot keeps to before it first goes home."""

    waits_for: tuple[str, ...]
    """The robots that must be past its goal before this one steers to it (ids)."""
    wait_point: NDArray[np.float64] = field(compare=False)
    """Where its controlled point steers meanwhile (2,) [m], world frame."""
    beyond: tuple[NDArray[np.bool_], ...] = field(compare=False, default=())
    """Per robot of :attr:`waits_for`, the cells (nx, ny) of the loader's free space
    (:attr:`space`) that lie past every goal that walls in its way: the piece of its own goal
    once those goals, the goals of every robot that does not wait for it and every wait point
    stand there.  A robot there can get home whichever of them are occupied."""
    space: FreeSpace | None = field(compare=False, default=None)
    """The loader's model of free space the cells of :attr:`beyond` are of."""

    def past(self, k: int, point: NDArray[np.float64]) -> bool:
        """Whether ``point`` (2,) [m] lies past the goals that wall in the way of robot
        ``waits_for[k]``: in a cell of ``beyond[k]``."""
        assert self.space is not None
        ix, iy = self.space.cells(point)
        return bool(self.beyond[k][ix[0], iy[0]])


@dataclass(frozen=True)
class Arrival:
    """The order of arrival of a scenario (:func:`arrival`)."""

    gates: dict[str, Gate]
    """Per robot that waits for others, its :class:`Gate`."""
    unordered: tuple[str, ...] = ()
    """Robots in a cycle of waits (each must be home before another of them parks): no order
    does it, they get no gate, and one of them must step aside for another."""
    unproven: tuple[str, ...] = ()
    """Robots whose way home the goals of those that do not wait for them and the wait points,
    all occupied at once, still wall in: the rule does not make assumption (B) hold for them."""
    no_wait_point: tuple[str, ...] = ()
    """Robots that should wait but have no wait point in the arena: they get no gate."""

    def lines(self) -> list[str]:
        """What to tell a user before a run: one line per robot that waits, then the robots
        the rule leaves without a proof."""
        out = []
        for rid, g in self.gates.items():
            x, y = (float(v) for v in g.wait_point)
            verb = "is" if len(g.waits_for) == 1 else "are"
            out.append(
                f"{rid} waits at ({x:.2f}, {y:.2f}) until {', '.join(g.waits_for)} {verb} past its goal"
            )
        if self.unordered:
            out.append(f"{', '.join(self.unordered)}: their waits form a cycle; no order of arrival does it")
        if self.no_wait_point:
            out.append(f"{', '.join(self.no_wait_point)}: no point to wait at, clear of the ways and goals")
        if self.unproven:
            out.append(
                f"{', '.join(self.unproven)}: the goals and wait points, all occupied, still wall in "
                "their way home"
            )
        return out


def arrival(scn: Scenario, footprint: float, slack: float = PARKED_RADIUS) -> Arrival:
    """The order of arrival of ``scn`` for a footprint radius [m] (module docstring), a robot
    parked or waiting standing up to ``slack`` [m] off its goal or wait point
    (:data:`~ground.scenario.PARKED_RADIUS`).  Every agent works
    it out for itself from the scenario: the same inputs give the same gates."""
    ids = [r.id for r in scn.robots]
    at = {rid: k for k, rid in enumerate(ids)}
    ell = scn.controller.lookahead
    starts = [controlled_point(r.start, ell) for r in scn.robots]
    goals = [np.asarray(r.goal, dtype=float) for r in scn.robots]
    model = free_space_model(scn.arena, scn.obstacles, footprint)
    reach = 2.0 * float(footprint)
    waits: dict[str, set[str]] = {rid: set() for rid in ids}
    walls: dict[tuple[str, str], tuple[str, ...]] = {}
    """(j, i): the robots whose goals, standing, wall in i's way, and j one of them."""
    forced = forced_order(scn, footprint)
    for rid, by in forced.items():
        for waiter in by["alone"]:
            waits[waiter].add(rid)
            walls[waiter, rid] = (waiter,)
        if by["together"]:
            for waiter in _waiters(model, at[rid], by["together"], at, starts, goals, reach, set(forced)):
                waits[waiter].add(rid)
                walls[waiter, rid] = tuple(by["together"])
    unordered = _cycles(waits)
    gated = [rid for rid in ids if waits[rid] and rid not in unordered]
    # Per robot i, the free cells left while it has not parked (nx, ny): every goal of a robot
    # that does not wait for it (and does not cover its start) and every wait point taken.
    space = []
    for i, rid in enumerate(ids):
        discs = [
            (goals[k], reach)
            for k, other in enumerate(ids)
            if k != i
            and not (other in gated and rid in waits[other])
            and float(np.hypot(*(goals[k] - starts[i]))) >= reach
        ]
        space.append(model.carve(discs).labels > 0)
    points: dict[str, NDArray[np.float64]] = {}
    missing = []
    # A wait point's disc, the robot off it by up to the slack, and its distance from every goal
    # and other wait point: two robots, each off its point towards the other.
    held, spacing = reach + slack, reach + 2.0 * slack + GOAL_MARGIN
    for rid in gated:
        me = at[rid]
        others = [goals[k] for k in range(len(ids)) if k != me] + list(points.values())
        w = _wait_point(model, space, me, scn.arena, footprint, starts[me], goals[me], others, spacing, held)
        if w is None:
            missing.append(rid)
            continue
        points[rid] = w
        rows, cols, m = model.disc_cells(w, held)
        for k in range(len(ids)):
            if k != me:
                space[k][rows, cols] &= ~m
    for rid in missing:  # no gate after all: it may park whenever, in every way it walls in
        rows, cols, m = model.disc_cells(goals[at[rid]], reach)
        for walled in waits[rid]:
            space[at[walled]][rows, cols] &= ~m
    unproven = []
    for i, rid in enumerate(ids):
        legs = [(starts[i], goals[i])]
        if rid in points:  # by its wait point
            legs = [(starts[i], points[rid]), (points[rid], goals[i])]
        lab, _ = _label(space[i])
        if any(model.joined(a, b) and not _together(model, lab, a, b) for a, b in legs):
            unproven.append(rid)

    # Per robot waited for, the cells past every goal that walls in its way: the piece of its
    # goal in its own free cells with all those goals standing too.  Once it is there, none of
    # them, parking, can shut its way home, whichever of the rest have parked.  A robot the
    # lemma does not cover has no proof to keep: the waits then only keep the order, and each
    # ends once it is past that waiter's goals, in free space with those alone.
    def past(i: str, discs: set[str], free: NDArray[np.bool_]) -> NDArray[np.bool_]:
        free = free.copy()
        for other in discs:
            rows, cols, m = model.disc_cells(goals[at[other]], reach)
            free[rows, cols] &= ~m
        lab, _ = _label(free)
        piece = model.piece_in(lab, goals[at[i]])
        return lab == piece if piece is not None else np.zeros_like(free)

    beyond: dict[str, NDArray[np.bool_]] = {}
    for rid in sorted({w for g in points for w in waits[g]}, key=at.__getitem__):
        if rid not in unproven:
            beyond[rid] = past(
                rid, {o for g in points if rid in waits[g] for o in walls[g, rid]}, space[at[rid]]
            )
    gates = {}
    for rid, w in points.items():
        order = tuple(sorted(waits[rid], key=at.__getitem__))
        regions = [beyond[i] if i in beyond else past(i, set(walls[rid, i]), model.free) for i in order]
        gates[rid] = Gate(order, w, tuple(regions), model)
    return Arrival(gates, tuple(unordered), tuple(unproven), tuple(missing))


def _label(free: NDArray[np.bool_]) -> tuple[NDArray[np.int32], int]:
    from scipy import ndimage

    lab, n = ndimage.label(free, structure=np.ones((3, 3), dtype=bool))
    return np.asarray(lab), int(n)


def _together(
    model: FreeSpace, lab: NDArray[np.int32], a: NDArray[np.float64], b: NDArray[np.float64]
) -> bool:
    """Whether points ``a`` and ``b`` (2,) [m] lie in one piece of the labelled cells ``lab``."""
    pa, pb = model.piece_in(lab, a), model.piece_in(lab, b)
    return pa is not None and pa == pb


def _waiters(
    model: FreeSpace, i: int, together: list[str], at: dict[str, int], starts: list[NDArray[np.float64]],
    goals: list[NDArray[np.float64]], reach: float, walled: set[str],
) -> list[str]:  # fmt: skip
    """Of the goals that together wall in robot i's way, the fewest whose absence opens it (all
    of them if none does): first those of robots whose own way is not walled in (``walled``:
    the robots :func:`~ground.scenario.forced_order` names), so that the waits make no cycle
    where they need not, then nearest i's goal or start first."""
    a, b = starts[i], goals[i]
    others = [k for k in range(len(goals)) if k != i and float(np.hypot(*(goals[k] - a))) >= reach]

    def key(j: str) -> tuple[bool, float, int]:
        g = goals[at[j]]
        return j in walled, float(min(np.hypot(*(g - b)), np.hypot(*(g - a)))), at[j]

    order = sorted(together, key=key)
    chosen: list[str] = []
    for j in order:
        chosen.append(j)
        out = {at[c] for c in chosen}
        if not model.walled_in(a, b, [(goals[k], reach) for k in others if k not in out]):
            break
    return chosen


def _cycles(waits: dict[str, set[str]]) -> list[str]:
    """The robots on a cycle of waits (j waits for i, …, i waits for j), in the scenario's order."""
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import connected_components

    ids = list(waits)
    at = {rid: k for k, rid in enumerate(ids)}
    edges = [(at[j], at[i]) for j, by in waits.items() for i in by]
    if not edges:
        return []
    rows, cols = zip(*edges, strict=True)
    graph = csr_matrix(([1] * len(edges), (rows, cols)), shape=(len(ids), len(ids)))
    _, label = connected_components(graph, directed=True, connection="strong")
    size = np.bincount(label)
    return [rid for k, rid in enumerate(ids) if size[label[k]] > 1 or rid in waits[rid]]


def _wait_point(
    model: FreeSpace, space: list[NDArray[np.bool_]], j: int, arena: tuple[float, float, float, float],
    footprint: float, start: NDArray[np.float64], goal: NDArray[np.float64],
    others: list[NDArray[np.float64]], spacing: float, reach: float,
) -> NDArray[np.float64] | None:  # fmt: skip
    """Robot j's wait point: the nearest point to its ``goal`` (2,) [m], ring by ring, where the
    footprint may stand inside the arena, at least ``spacing`` [m] from each of ``others`` (the
    other goals and the wait points taken), joined to its ``start`` and its goal in its own free
    cells ``space[j]``, and whose disc of radius ``reach`` [m] splits no piece of any robot's
    free cells (``space``, :meth:`~ground.freespace.FreeSpace.ring_holds`); None if there is
    none among the first :data:`WAIT_CANDIDATES` that pass the rest."""
    xmin, xmax, ymin, ymax = arena
    ang = np.linspace(0.0, 2.0 * math.pi, WAIT_RING_POINTS, endpoint=False)
    unit = np.column_stack([np.cos(ang), np.sin(ang)])
    far = math.hypot(xmax - xmin, ymax - ymin)
    lab, _ = _label(space[j])
    home = model.piece_in(lab, goal)
    if home is None or model.piece_in(lab, start) != home:
        return None
    tried = 0
    for rho in np.arange(WAIT_RING_STEP, far, WAIT_RING_STEP):
        P = goal + rho * unit
        ok = (P[:, 0] >= xmin + footprint) & (P[:, 0] <= xmax - footprint)
        ok &= (P[:, 1] >= ymin + footprint) & (P[:, 1] <= ymax - footprint)
        for q in others:
            ok &= np.hypot(P[:, 0] - q[0], P[:, 1] - q[1]) >= spacing
        if not ok.any():
            continue
        ix, iy = model.cells(P)
        ok &= model.free[ix, iy] & (lab[ix, iy] == home)
        for k in np.flatnonzero(ok):
            if tried >= WAIT_CANDIDATES:
                return None
            tried += 1
            w = P[k]
            if _splits_none(model, space, j, w, reach):
                return np.asarray(w, dtype=float)
    return None


def _splits_none(
    model: FreeSpace, space: list[NDArray[np.bool_]], j: int, w: NDArray[np.float64], reach: float
) -> bool:
    """Whether a disc of radius ``reach`` [m] about ``w`` (2,) [m] splits no piece of the free
    cells of any robot but j (``space``): each distinct box of cells about it tested once."""
    rows, cols, _ = model.disc_cells(w, reach)
    r0, r1 = max(0, rows.start - 2), min(model.nx, rows.stop + 2)
    c0, c1 = max(0, cols.start - 2), min(model.ny, cols.stop + 2)
    seen: set[bytes] = set()
    for i, free in enumerate(space):
        if i == j:
            continue
        key = free[r0:r1, c0:c1].tobytes()
        if key in seen:
            continue
        seen.add(key)
        if not model.ring_holds(w, reach, free):
            return False
    return True
