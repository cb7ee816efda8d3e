"""Coordination terms of the QP (docs/method.md §6): safety constraints and shaping.

Safety (hard, recursively feasible).  Before appending, agents i and j both
know ``c_i = ỹ^i_{t+N−1}`` and ``c_j = ỹ^j_{t+N−1}`` with
``‖c_i − c_j‖ ≥ R = r_i + r_j``.  With ``n = (c_i − c_j)/‖c_i − c_j‖`` and the
slack ``σ = ‖c_i − c_j‖ − R``, agent i imposes ``nᵀ(ȳ_i − c_i) ≥ −s_ij σ`` and
j the mirror with ``s_ji = 1 − s_ij``; then ``nᵀ(ȳ_i − ȳ_j) ≥ R``.  Staying
put satisfies every such row, so the QP stays feasible.  A convex obstacle
contributes ``nᵀ ȳ ≥ nᵀ q + r_i`` with q its point nearest c_i.

A row is omitted when ``‖ȳ − c_i‖∞ ≤ ε`` already implies it
(``s_ij σ ≥ √2 ε``), which keeps the QP small without weakening it.

Neighbours known only from an older plan, or dead, are kept clear of as static discs
(:class:`Hazard`, :func:`hazard_halfplanes`; :mod:`agent.hazards` sorts them).

Shaping (cost only, so it can never break the guarantee): :func:`polynomial_penalty`, the
paper's eq. 34, convexified per step.  The navigator that picks the goal term's target, and
breaks deadlocks, is :mod:`agent.navigator`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from agent.sets import Array
from ground.wire import OFF_PLAN, RETURNING

SQRT2 = math.sqrt(2.0)


class ConvexObstacle(Protocol):
    """A static convex obstacle: ``distance`` and ``closest_point`` in [m]."""

    def distance(self, point: Any) -> float:
        """Distance [m] from ``point`` (x, y) to the obstacle; 0 inside."""
        ...

    def closest_point(self, point: Any) -> Array:
        """The point (2,) [m] of the obstacle's boundary nearest to ``point``."""
        ...


@dataclass
class NeighbourInfo:
    """What agent i knows about agent j from j's last plan message."""

    id: str
    last_point: Array
    """c_j = ỹ^j_{t+N−1} (2,) [m]."""
    footprint: float
    """r_j [m]."""
    priority: int = 0
    rank: int = 0
    """Tie-break order among equal priorities (lower goes first)."""
    target: Array | None = None
    """j's current navigation waypoint (2,) [m], if known."""
    goal: Array | None = None
    """j's goal (2,) [m], if known."""
    phase: int = 0
    """Precedence class: 0 under way (goal never reached), 1 returning (goal
    reached once, now displaced), 2 parked (at its goal).  Lower goes first."""
    phase_age: int = 0
    """Steps j has been in ``phase`` [steps]: among returning robots the one displaced
    first goes first (:func:`precedence`)."""


def shares(prio_i: int, prio_j: int, share_hi: float) -> float:
    """s_ij: the part of the slack σ that agent i may consume against j."""
    if prio_i > prio_j:
        return share_hi
    if prio_i < prio_j:
        return 1.0 - share_hi
    return 0.5


def order_key(priority: int, rank: int) -> tuple[int, int]:
    """Sort key: smaller goes first (higher priority, then lower rank)."""
    return (-priority, rank)


def precedence(phase: int, phase_age: int, priority: int, rank: int) -> tuple[int, int, int, int]:
    """The navigator's total order (docs/method.md §7): smaller goes first.  By phase (under
    way, returning, parked); among returning robots, the one displaced longest ago first;
    then by priority and rank.  The age is what breaks the cycle of two robots that displace
    each other in turn: a parked robot that steps aside for a returning one becomes returning
    later than it, so it keeps yielding to it until that one has parked."""
    return (phase, -phase_age if phase == RETURNING else 0, *order_key(priority, rank))


UNCONTROLLED_PRIORITY = 2**31
"""The priority the navigator gives a robot that drives on uncontrolled (its link down): above
every priority a plan can carry (the wire's are below 2³¹), so it goes before every robot and
the robots in its way make way for it, as for any robot that goes first (docs/method.md §6.4)."""


PLACE_LAG = 2
"""Steps [steps] by which what an agent knows of another robot's place (its plan by place, its
place token) may lag behind where that robot's last committed point is."""


def place_side(footprint: float, eps: float, share_hi: float) -> float:
    """Side [m] of the cells by which plans travel (``--exchange place``, docs/method.md §6).

    Two committed points in cells two or more apart are more than a side apart.  At that
    distance the split rule adds no row between them (:func:`split_halfplanes`: σ·s ≥
    √2·ε·1.01 for the smallest share s), even after both have moved √2·ε a step for
    :data:`PLACE_LAG` steps: so an agent that coordinates only with the robots in its own cell
    and the eight around it gets the same rows as one that knows every robot."""
    s = min(share_hi, 1.0 - share_hi, 0.5)
    return 2.0 * footprint + SQRT2 * eps * 1.01 / s + 2.0 * PLACE_LAG * SQRT2 * eps


VIEW_CELLS = 2
"""With plans by place, the navigator sees the robots up to this many cells from its own
(Chebyshev), where the constraints need one: every agent hears them, since it subscribes to
its own group of cells and the eight groups around it (``agent.channels.GROUP``), which hold every
cell two or fewer from its own.  A robot whose cell is three or more from its own is more than
two sides away (:func:`navigator_view`)."""


def navigator_view(side: float, eps: float) -> float:
    """How far [m] the navigator of an agent with plans by place sees every robot, whatever it
    heard last: what :data:`VIEW_CELLS` cells of ``side`` [m] guarantee, less what both robots
    may have moved towards each other (√2·``eps`` [m] a step each) in the :data:`PLACE_LAG`
    steps what it heard may be old.  The navigator's yielding rule acts on robots up to
    r_i + r_j + ``conflict_range`` away (``agent.navigator.Navigator.target``); an agent with
    plans by place caps its ``conflict_range`` so that this stays within the view."""
    return VIEW_CELLS * side - 2.0 * PLACE_LAG * SQRT2 * eps


def split_halfplanes(
    c_i: Array, r_i: float, prio_i: int, neighbours: Sequence[NeighbourInfo], share_hi: float, eps: float
) -> tuple[list[Array], list[float], float]:
    """Rows ``nᵀ ȳ ≥ b`` of the split rule against each neighbour.

    Returns (normals, bounds, min_slack) where min_slack is the smallest
    σ = ‖c_i − c_j‖ − (r_i + r_j) seen [m] (negative means the invariant is
    already broken, which the caller reports)."""
    normals: list[Array] = []
    bounds: list[float] = []
    min_slack = math.inf
    for nb in neighbours:
        d = c_i - nb.last_point
        dist = float(math.hypot(d[0], d[1]))
        sigma = dist - (r_i + nb.footprint)
        min_slack = min(min_slack, sigma)
        s = shares(prio_i, nb.priority, share_hi)
        if s * sigma >= SQRT2 * eps * 1.01:
            continue  # implied by the ε box
        if dist < 1e-9:
            n = np.array([1.0, 0.0])  # coincident: any direction is consistent only if σ ≥ 0, which it is not
        else:
            n = d / dist
        normals.append(n)
        bounds.append(float(n @ c_i - s * max(sigma, 0.0)))
    return normals, bounds, min_slack


def obstacle_halfplanes(
    c_i: Array, r_i: float, obstacles: Sequence[ConvexObstacle], eps: float
) -> tuple[list[Array], list[float]]:
    """Supporting half-planes ``nᵀ ȳ ≥ nᵀ q + r_i`` of nearby convex obstacles."""
    normals: list[Array] = []
    bounds: list[float] = []
    for ob in obstacles:
        q = np.asarray(ob.closest_point(c_i), dtype=float)
        d = c_i - q
        dist = float(math.hypot(d[0], d[1]))
        if dist - r_i >= SQRT2 * eps * 1.01:
            continue
        n = d / dist if dist > 1e-9 else np.array([1.0, 0.0])
        normals.append(n)
        bounds.append(float(n @ q + r_i))
    return normals, bounds


@dataclass
class Hazard:
    """A neighbour that agent i can no longer coordinate with, as a disc.

    A neighbour whose plan of the previous step is missing (lost, late or a
    dead agent) cannot take its share of the split rule with fresh data, so i
    keeps its own appended point clear of every place the neighbour's can be:
    j's last known committed point grown by ε per step it may have moved
    since, or, once its robot is off its plans for good, the bound of where it
    can still go (docs/method.md §6.4)."""

    id: str
    centre: Array
    """The disc's centre (2,) [m], world frame: j's last known committed point ĉ_j, or where
    the camera saw its controlled point."""
    radius: float
    """r_j plus the growth [m]: where j's appended point can be now."""
    info: NeighbourInfo | None = None
    """What j's last plan said (for the navigator's yielding; None for a dead robot)."""
    kind: str = "stale"
    """Why (:data:`ground.wire.DISC_KINDS`)."""
    rest: bool = False
    """The disc is about j's measured controlled point with its robot known to stand still
    (its robot side braked it long enough to stop): it stays put."""
    drift: float = 0.0
    """How far [m] the disc's edge may come towards any point in one step, by its centre moving
    and its radius growing: a robot that drives on uncontrolled moves up to its speed times Ts
    a step (:meth:`agent.hazards.Guard._loose`); 0 for a disc whose robot is steered by a plan
    or stops (its growth bounds where a plan or a brake can take it, not where it heads)."""

    @property
    def static(self) -> bool:
        """j's robot is off its plans for good (:data:`ground.wire.OFF_PLAN`): the disc stays put, and holds
        every place j's robot can still reach, so paths plan around it and a goal inside it
        cannot be reached while it stands."""
        return self.kind in OFF_PLAN


DRIFT_SHARE = 0.99
"""The share of ε·(|n_x| + |n_y|), the most the ε box lets ȳ move along n, that a row against a
disc that comes on may ask for.  All of it would leave the box's corner as the only feasible
point; 1 % less leaves the QP a sliver 0.01·ε wide (55 µm with ε = 5.5 mm), five times the
solver's tolerance (``agent.qp`` ``eps_abs`` = 1e-5 m), so its tolerance cannot make the row
infeasible (``tests/agent/test_hazards.py`` checks the margin against the settings)."""


def hazard_halfplanes(
    c_i: Array, r_i: float, hazards: Sequence[Hazard], eps: float
) -> tuple[list[Array], list[float]]:
    """Rows ``nᵀ ȳ ≥ b`` keeping ȳ at least ``r_i + radius`` from each hazard's centre.

    n is the unit vector from the centre to c_i and b = nᵀo + min(r_i + radius, ‖c_i − o‖ + δ):
    when c_i is already closer than the margin (the hazard appeared or grew onto
    it), the row asks only not to come closer.  For a disc whose robot is steered by a
    plan or stops, δ = 0: staying put always satisfies the row, so the QP stays feasible; if
    nothing else is safe the robot stays put ("stops in its tube").

    A robot driving on uncontrolled (``Hazard.drift`` > 0) comes on whatever this one does,
    and "not closer" to where it is now would let the margin wear down by its step every step,
    until it drives into a robot that stood still (measured: a crossing robot held at the edge
    of the disc of one whose link was cut, the gap closing at the cut robot's speed until they
    touched).  For it δ is its drift, capped at what the ε box lets ȳ move along n
    (ε·(|n_x| + |n_y|)): a margin met at the step before (‖c_i − o‖ ≥ r_i + radius − drift)
    is kept in full, and one already short is not shortened.  Near a wall the box may not
    allow it; then the QP is infeasible and the controller's fallback is taken (and counted)."""
    normals: list[Array] = []
    bounds: list[float] = []
    for hz in hazards:
        d = c_i - hz.centre
        dist = float(math.hypot(d[0], d[1]))
        need = r_i + hz.radius
        if dist - need >= SQRT2 * eps * 1.01:
            continue  # implied by the ε box
        n = d / dist if dist > 1e-9 else np.array([1.0, 0.0])
        push = min(hz.drift, DRIFT_SHARE * eps * (abs(float(n[0])) + abs(float(n[1]))))
        normals.append(n)
        bounds.append(float(n @ hz.centre + min(need, dist + push)))
    return normals, bounds


def repair_point(
    ybar: Array, c: Array, normals: Array, bounds: Array, lo: Array, hi: Array
) -> tuple[Array, bool]:
    """ȳ (2,) [m] made to meet every row nᵀȳ ≥ b (``normals`` (M, 2), ``bounds`` (M,)) exactly
    and stay in its box ``lo`` ≤ ȳ ≤ ``hi`` (2,) [m], the ε box about c_i clipped to the arena;
    and whether the step had to be scaled.

    The solver meets constraints to its tolerance (1e-5); left alone, robots pressed together
    would erode the separation by that much each step.  The nearest such point is the
    projection of ȳ onto the polygon the rows and the box cut out: it moves ȳ by about the
    violation and keeps the part of the step along a binding row (a robot sliding along a wall
    or a neighbour's row goes on sliding).  In the plane that projection is ȳ itself, its
    projection onto one edge's line, or a vertex where two lines meet: every candidate is
    computed, with each bound raised by 1e-12 m so that rounding cannot leave it a hair
    outside, and the nearest that meets every row exactly is taken.

    Safety does not rest on that search: if no candidate meets every row c_i meets, the step
    is scaled instead, ȳ = c_i + λ(ȳ − c_i) with the largest λ ∈ [0, 1] that meets them.  Every
    row is convex and c_i meets it, so that point exists, at the price of the step (the robot
    stops a step).  A row c_i itself fails (a disc that comes on, ``Hazard.drift``) asks ȳ away
    from c_i: a candidate that meets it is preferred, and the scaling, which would pull ȳ back
    towards c_i, leaves it to the solver's tolerance."""
    if bounds.size == 0 or np.all(normals @ ybar >= bounds):
        return ybar, False
    eye = np.eye(2)
    A = np.vstack([normals, eye, -eye])
    B = np.concatenate([bounds, lo, -np.asarray(hi)])
    # (c_i meets the rows exactly, up to rounding: a row it is on counts as met.)
    held = np.concatenate([normals @ c >= bounds - 1e-9, np.ones(4, dtype=bool)])
    Bt = B + 1e-12
    cands = [ybar + np.maximum(0.0, Bt - A @ ybar)[:, None] * A]  # onto each line
    m = len(B)
    i, j = np.triu_indices(m, 1)
    det = A[i, 0] * A[j, 1] - A[i, 1] * A[j, 0]
    ok = np.abs(det) > 1e-9
    i, j, det = i[ok], j[ok], det[ok]
    vx = (Bt[i] * A[j, 1] - Bt[j] * A[i, 1]) / det
    vy = (A[i, 0] * Bt[j] - A[j, 0] * Bt[i]) / det
    cands.append(np.column_stack([vx, vy]))  # the vertices
    P = np.vstack(cands)
    at = P @ A.T >= B
    for must in (np.ones(m, dtype=bool), held):
        fits = np.all(at[:, must], axis=1)
        if np.any(fits):
            dist = np.linalg.norm(P[fits] - ybar, axis=1)
            return P[fits][int(np.argmin(dist))], False
    at_y = normals @ ybar
    bad = (at_y < bounds) & held[: len(bounds)]
    at_c = normals[bad] @ c
    gap = at_c - at_y[bad]
    # Largest λ with nᵀ(c + λ(ȳ − c)) ≥ b on each violated row (c satisfies it).
    safe_gap = np.where(gap > 0, gap, 1.0)
    lam = float(
        min(1.0, np.where(gap > 0, np.maximum(0.0, (at_c - bounds[bad]) / safe_gap), 0.0).min(initial=1.0))
    )
    y = c + lam * (ybar - c)
    if not np.all(normals[bad] @ y >= bounds[bad]):
        y = np.asarray(c, dtype=float).copy()  # rounding: c_i itself
    return y, True


def penalty_coefficients(dlim: float, weight: float) -> Array:
    """a_0 … a_5 of f(ρ) = weight·(1 − ρ/d_lim)^5 (paper eq. 34's degree-5 polynomial).

    f is decreasing on [0, d_lim] and f(d_lim) = f'(d_lim) = 0, so V_coll
    switches on smoothly at ρ = d_lim (ρ is a squared distance [m²])."""
    # (1 − x)^5 = Σ C(5,k) (−x)^k
    return np.array([weight * math.comb(5, k) * (-1.0 / dlim) ** k for k in range(6)])


def polynomial_penalty(
    ybar0: Array, centres: Sequence[Array], dlim: float, weight: float
) -> tuple[Array, Array] | None:
    """Convexified second-order model of Σ_j f(‖ȳ − c_j‖²) around ``ybar0``.

    Returns (H (2,2), g (2,)) to add to ½ȳᵀHȳ + gᵀȳ, or None if no term is
    active.  The exact Hessian ``4f''ddᵀ + 2f'I`` is projected onto the PSD
    cone (real-time iteration), so the QP stays convex."""
    a = penalty_coefficients(dlim, weight)
    da = np.array([k * a[k] for k in range(1, 6)])
    dda = np.array([k * (k - 1) * a[k] for k in range(2, 6)])
    H = np.zeros((2, 2))
    grad = np.zeros(2)
    active = False
    for c in centres:
        d = ybar0 - c
        rho = float(d @ d)
        if rho > dlim:
            continue
        active = True
        f1 = float(sum(da[k] * rho**k for k in range(5)))
        f2 = float(sum(dda[k] * rho**k for k in range(4)))
        grad += 2.0 * f1 * d
        Hj = 4.0 * f2 * np.outer(d, d) + 2.0 * f1 * np.eye(2)
        w, V = np.linalg.eigh(Hj)
        H += (V * np.maximum(w, 0.0)) @ V.T
    if not active:
        return None
    # Model: f(y) ≈ f0 + gradᵀ(y − y0) + ½(y − y0)ᵀH(y − y0) → linear term grad − H y0.
    return H, grad - H @ ybar0
