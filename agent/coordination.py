"""Coordination terms of the QP (DESIGN §5): safety constraints and shaping.

Safety (hard, recursively feasible).  Before appending, agents i and j both
know ``c_i = ỹ^i_{t+N−1}`` and ``c_j = ỹ^j_{t+N−1}`` with
``‖c_i − c_j‖ ≥ R = r_i + r_j``.  With ``n = (c_i − c_j)/‖c_i − c_j‖`` and the
slack ``σ = ‖c_i − c_j‖ − R``, agent i imposes ``nᵀ(ȳ_i − c_i) ≥ −s_ij σ`` and
j the mirror with ``s_ji = 1 − s_ij``; then ``nᵀ(ȳ_i − ȳ_j) ≥ R``.  Staying
put satisfies every such row, so the QP stays feasible.  A convex obstacle
contributes ``nᵀ ȳ ≥ nᵀ q + r_i`` with q its point nearest c_i.

A row is omitted when ``‖ȳ − c_i‖∞ ≤ ε`` already implies it
(``s_ij σ ≥ √2 ε``), which keeps the QP small without weakening it.

Shaping (cost only, so it can never break the guarantee):

* :class:`Navigator` picks the target of the goal term: a waypoint around
  static obstacles (shortest path on a visibility graph of the inflated
  obstacles), and the deadlock tie-breaker: *priority yielding*.  Robots are
  totally ordered by (priority, rank).  A robot whose committed point lies in
  the corridor that a nearby higher-ordered robot still has to sweep (the
  segment from that robot's last committed point to its next waypoint,
  widened by their footprints) steps out of it to the best free point
  around it.  The highest-ordered unfinished robot therefore never waits on
  a lower one that can move, which is what breaks gridlock.
* :func:`polynomial_penalty`, the paper's eq. 34, convexified per step.
"""

from __future__ import annotations

import heapq
import math
from dataclasses import dataclass, field
from typing import Any, Protocol, Sequence

import numpy as np

from agent.sets import Array

SQRT2 = math.sqrt(2.0)


class ConvexObstacle(Protocol):
    """A static convex obstacle: ``distance`` and ``closest_point`` in [m]."""

    def distance(self, point: Any) -> float: ...

    def closest_point(self, point: Any) -> Array: ...


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
    done: bool = False
    """j has reached its goal."""


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


def obstacle_outline(ob: Any, inflate: float, sides: int = 16) -> Array:
    """Polygon (k, 2) containing ``ob`` grown by ``inflate`` [m] (CCW).

    Circles (``center``, ``radius``) become circumscribed regular polygons;
    polygons (``vertices``) are grown along their vertex bisectors."""
    if hasattr(ob, "radius"):
        r = (ob.radius + inflate) / math.cos(math.pi / sides)
        ang = np.linspace(0.0, 2.0 * math.pi, sides, endpoint=False) + math.pi / sides
        return np.column_stack([ob.center[0] + r * np.cos(ang), ob.center[1] + r * np.sin(ang)])
    V = np.asarray(ob.vertices, dtype=float)
    out = []
    k = len(V)
    for i in range(k):
        e1 = V[i] - V[i - 1]
        e2 = V[(i + 1) % k] - V[i]
        n1 = np.array([e1[1], -e1[0]]) / np.linalg.norm(e1)
        n2 = np.array([e2[1], -e2[0]]) / np.linalg.norm(e2)
        bis = n1 + n2
        cosh = float(n1 @ bis / np.linalg.norm(bis))
        out.append(V[i] + inflate * bis / np.linalg.norm(bis) / max(cosh, 0.2))
    return np.array(out)


def _segment_hits_polygon(a: Array, b: Array, P: Array) -> bool:
    """True if segment ab passes through the interior of convex CCW polygon P."""
    # Cyrus–Beck clipping against each edge's inner half-plane.
    t0, t1 = 0.0, 1.0
    d = b - a
    k = len(P)
    for i in range(k):
        e = P[(i + 1) % k] - P[i]
        n = np.array([-e[1], e[0]])  # inward for CCW
        num = float(n @ (a - P[i]))
        den = float(n @ d)
        if abs(den) < 1e-12:
            if num < 1e-9:
                return False
            continue
        t = -num / den
        if den > 0:
            t0 = max(t0, t)
        else:
            t1 = min(t1, t)
        if t0 >= t1 - 1e-9:
            return False
    return t1 - t0 > 1e-9


def point_segment_distance(p: Array, a: Array, b: Array) -> float:
    d = b - a
    L2 = float(d @ d)
    t = 0.0 if L2 < 1e-12 else min(1.0, max(0.0, float((p - a) @ d) / L2))
    return float(np.linalg.norm(p - (a + t * d)))


@dataclass
class Navigator:
    """Chooses the goal-term target of one agent (shaping only; see module docstring)."""

    footprint: float
    arena: tuple[float, float, float, float]
    obstacles: Sequence[Any] = ()
    priority: int = 0
    rank: int = 0
    conflict_range: float = 0.35
    """Extra distance beyond r_i + r_j within which a higher robot is yielded to [m]."""
    corridor_margin: float = 0.05
    """Extra corridor half-width beyond r_i + r_j [m]."""
    hold_steps: int = 15
    seed: int = 0
    _outlines: list[Array] = field(default_factory=list)
    _nodes: Array | None = None
    _escape: Array | None = None
    _escape_left: int = 0
    _rng: np.random.Generator | None = None
    _best_dist: float = math.inf
    _stall: int = 0

    def __post_init__(self) -> None:
        infl = self.footprint + 0.02
        self._outlines = [obstacle_outline(o, infl) for o in self.obstacles]
        nodes = [v for P in self._outlines for v in P]
        # Nodes are pushed slightly outward so paths graze, not enter, the outlines.
        self._nodes = np.array(nodes) if nodes else np.zeros((0, 2))
        self._rng = np.random.default_rng(self.seed)

    # ---------------------------------------------------------- static paths
    def _visible(self, a: Array, b: Array) -> bool:
        return not any(_segment_hits_polygon(a, b, P) for P in self._outlines)

    def waypoint(self, c: Array, goal: Array) -> Array:
        """Next waypoint from ``c`` towards ``goal`` around static obstacles."""
        if not self._outlines or self._visible(c, goal):
            return goal
        assert self._nodes is not None
        pts = np.vstack([c, goal, self._nodes])
        n = len(pts)
        dist = [math.inf] * n
        prev = [-1] * n
        dist[0] = 0.0
        heap = [(0.0, 0)]
        while heap:
            d, i = heapq.heappop(heap)
            if d > dist[i]:
                continue
            if i == 1:
                break
            for j in range(1, n):
                if j == i:
                    continue
                nd = d + float(np.linalg.norm(pts[j] - pts[i]))
                if nd < dist[j] and self._visible(pts[i], pts[j]):
                    dist[j] = nd
                    prev[j] = i
                    heapq.heappush(heap, (nd, j))
        if prev[1] < 0:
            return goal
        j = 1
        while prev[j] != 0:
            j = prev[j]
        return pts[j]

    # ------------------------------------------------------------- yielding
    def target(self, c: Array, goal: Array, neighbours: Sequence[NeighbourInfo]) -> tuple[Array, str]:
        """Target of the goal term and the mode (``goal``, ``waypoint``, ``yield``, ``escape``)."""
        wp = self.waypoint(c, goal)
        mode = "goal" if wp is goal else "waypoint"
        me = order_key(self.priority, self.rank)
        corridors = []
        for nb in neighbours:
            if nb.done or order_key(nb.priority, nb.rank) > me:
                continue
            R = self.footprint + nb.footprint
            if np.linalg.norm(nb.last_point - c) > R + self.conflict_range:
                continue
            end = nb.target if nb.target is not None else nb.last_point
            corridors.append((nb.last_point, end, R + self.corridor_margin))
        blocked = [cd for cd in corridors if point_segment_distance(c, cd[0], cd[1]) < cd[2]]
        if blocked:
            self._escape = self._escape_point(c, wp, corridors, neighbours)
            self._escape_left = self.hold_steps
            return self._escape, "yield"

        # Progress watchdog: a robot that has made no progress for long picks a
        # clearance-seeking escape point and holds it (DESIGN §5).
        dgoal = float(np.linalg.norm(goal - c))
        if dgoal < self._best_dist - 0.02:
            self._best_dist = dgoal
            self._stall = 0
        elif dgoal > 0.02:
            self._stall += 1
        if self._escape is not None and self._escape_left > 0:
            self._escape_left -= 1
            if np.linalg.norm(self._escape - c) > 0.02:
                return self._escape, "escape"
        self._escape = None
        if self._stall > 60:
            self._stall = 0
            self._best_dist = dgoal
            self._escape = self._escape_point(c, wp, corridors, neighbours, radius=0.5)
            self._escape_left = 40
            return self._escape, "escape"
        return wp, mode

    def _escape_point(
        self,
        c: Array,
        wp: Array,
        corridors: list[tuple[Array, Array, float]],
        neighbours: Sequence[NeighbourInfo],
        radius: float = 0.4,
    ) -> Array:
        """Best free point near ``c``: outside the corridors, clear of others, towards ``wp``."""
        assert self._rng is not None
        xmin, xmax, ymin, ymax = self.arena
        r = self.footprint
        ang = np.linspace(0.0, 2.0 * math.pi, 24, endpoint=False)
        cands = [c + rad * np.array([math.cos(a), math.sin(a)]) for rad in (0.5 * radius, radius) for a in ang]
        best, best_score = c, math.inf
        for p in cands:
            if not (xmin + r <= p[0] <= xmax - r and ymin + r <= p[1] <= ymax - r):
                continue
            if any(ob.distance(p) < r + 0.01 for ob in self.obstacles):
                continue
            score = 0.5 * float(np.linalg.norm(p - c)) + 0.2 * float(np.linalg.norm(wp - p))
            for a, b, w in corridors:
                dseg = point_segment_distance(p, a, b)
                if dseg < w:
                    score += 10.0 + 5.0 * (w - dseg)
            for nb in neighbours:
                clear = float(np.linalg.norm(p - nb.last_point)) - (r + nb.footprint)
                if clear < 0.1:
                    score += 2.0 * (0.1 - clear)
            if not self._visible(c, p):
                score += 5.0
            if score < best_score:
                best, best_score = p, score
        return np.asarray(best, dtype=float)
