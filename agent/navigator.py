"""The navigator: where the goal term of a robot's QP points this step (shaping only).

The split rule (:mod:`agent.coordination`) keeps robots apart but lets a symmetric crowd stall,
since "stay put" is always feasible.  The navigator picks the target of the goal term
``‖ȳ − target‖²_T`` so that robots get home; it changes the cost, never a constraint, so
whatever it does cannot break a guarantee (docs/method.md §7).

* :class:`GridPlanner` — shortest paths on a grid over the arena, around walls, obstacles and
  parked robots; the robot follows a carrot along its path.
* :class:`Navigator` — *precedence yielding*: robots are totally ordered by (phase, age,
  priority, rank) (:func:`agent.coordination.precedence`); a robot inside the corridor that a
  nearby robot of higher precedence still has to sweep steps out of it to the best free point
  around it, and a progress watchdog sends a stalled robot to a clearance-seeking escape point
  for a while.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

from agent.coordination import UNCONTROLLED_PRIORITY, NeighbourInfo, precedence
from agent.sets import Array
from ground.arrival import WAIT_RING_STEP
from ground.freespace import free_space_model
from ground.scenario import GOAL_MARGIN, PARKED_RADIUS
from ground.wire import PARKED, RETURNING


def point_segment_distance(p: Array, a: Array, b: Array) -> float:
    """Euclidean distance from point p to segment ab [m]."""
    dx, dy = b[0] - a[0], b[1] - a[1]
    L2 = dx * dx + dy * dy
    t = 0.0 if L2 < 1e-12 else min(1.0, max(0.0, ((p[0] - a[0]) * dx + (p[1] - a[1]) * dy) / L2))
    return math.hypot(p[0] - a[0] - t * dx, p[1] - a[1] - t * dy)


_DIRECTIONS = ((1, 0), (0, 1), (1, 1), (1, -1), (-1, 0), (0, -1), (-1, -1), (-1, 1))
"""The 8 neighbours of a grid cell, as (di, dj)."""


class GridPlanner:
    """Shortest paths on an 8-connected grid over the arena (cell size ``h`` [m]), in the
    loader's model of free space (:func:`ground.freespace.free_space_model`: the same radius,
    the same fine grid, the same walls and obstacles).

    A cell stands for one point of it, its *waypoint* (:attr:`points`): its centre if a disc of
    the footprint may stand there, else the point of the cell where the disc clears the walls
    and obstacles most, as the fine grid samples it.  A cell is free if that point is; two
    neighbouring cells are joined if the segment between their waypoints runs through free
    fine cells only.  So a passage the loader accepts is a passage the grid has, however it
    falls across the cells, and a path never cuts across a thin wall between two cells.

    Cell costs: 1 in free space, ``BLOCKED`` where the disc cannot stand and between cells that
    are not joined, parked robots ⊕ (r_i + r_j) ``BLOCKED`` too, and ``1 + soft`` near moving
    robots.  Large finite costs instead of infinities keep a path defined even when the robot
    itself sits in a costly cell."""

    BLOCKED = 1e4

    def __init__(
        self,
        arena: tuple[float, float, float, float],
        footprint: float,
        obstacles: Sequence[Any],
        h: float = 0.05,
    ):
        xmin, xmax, ymin, ymax = arena
        self.h = h
        self.nx = max(2, math.ceil((xmax - xmin) / h))
        self.ny = max(2, math.ceil((ymax - ymin) / h))
        self.x0, self.y0 = xmin, ymin
        xs = xmin + (np.arange(self.nx) + 0.5) * (xmax - xmin) / self.nx
        ys = ymin + (np.arange(self.ny) + 0.5) * (ymax - ymin) / self.ny
        self.hx = (xmax - xmin) / self.nx
        self.hy = (ymax - ymin) / self.ny
        self.xs, self.ys = xs, ys
        X, Y = np.meshgrid(xs, ys, indexing="ij")
        self.centres = np.column_stack([X.ravel(), Y.ravel()])
        self.space = free_space_model(arena, obstacles, footprint)
        self.points, free = self._waypoints(footprint, obstacles)
        """Each cell's waypoint (n, 2) [m]: where a path through the cell goes."""
        self.static = np.where(free, 1.0, self.BLOCKED)
        # Fixed 8-connected edge list (both directions).
        idx = np.arange(self.nx * self.ny).reshape(self.nx, self.ny)
        src, dst = [], []
        for dx, dy in ((1, 0), (0, 1), (1, 1), (1, -1)):
            # Pair each cell (i, j) with (i + dx, j + dy) where both exist.
            j0, j1 = max(0, -dy), self.ny - max(0, dy)
            a = idx[: self.nx - dx, j0:j1]
            b = idx[dx:, j0 + dy : j1 + dy]
            a, b = a.ravel(), b.ravel()
            src += [a, b]
            dst += [b, a]
        src_a, dst_a = np.concatenate(src), np.concatenate(dst)
        # Sorted by (src, dst) once, so each plan builds its CSR matrix without sorting.
        order = np.lexsort((dst_a, src_a))
        self.src, self.dst = src_a[order], dst_a[order]
        self.length = np.linalg.norm(self.points[self.dst] - self.points[self.src], axis=1)
        self.cut = self.BLOCKED * self.length * ~self._joined(self.src, self.dst, free, footprint)
        """Per edge, the cost [m] added where the segment leaves free space (0 where it does not)."""
        self.indptr = np.concatenate([[0], np.cumsum(np.bincount(self.src, minlength=self.nx * self.ny))])
        # Each cell's edge to its neighbour in each of the 8 directions (−1 where none): a window
        # (:meth:`local_field`) takes its edges from here without scanning the whole grid.
        n = self.nx * self.ny
        keys = self.src * n + self.dst
        self.edge_of = np.full((n, 8), -1, dtype=np.int64)
        for d, (dx, dy) in enumerate(_DIRECTIONS):
            ii, jj = np.divmod(np.arange(n), self.ny)
            ok = (ii + dx >= 0) & (ii + dx < self.nx) & (jj + dy >= 0) & (jj + dy < self.ny)
            a = np.flatnonzero(ok)
            self.edge_of[a, d] = np.searchsorted(keys, a * n + (a + dx * self.ny + dy))
        for arr in (self.static, self.points, self.length, self.cut, self.edge_of, self.src, self.dst):
            arr.setflags(write=False)  # shared by every navigator of a process (:func:`grid_planner`)

    def _waypoints(self, radius: float, obstacles: Sequence[Any]) -> tuple[Array, np.ndarray]:
        """Each cell's waypoint (n, 2) [m] and whether the disc may stand there (n,)."""
        fs = self.space
        n = self.nx * self.ny
        c = self.centres
        xmin, ymin = self.x0, self.y0
        xmax, ymax = xmin + self.nx * self.hx, ymin + self.ny * self.hy
        at_centre = np.minimum(
            np.minimum(c[:, 0] - xmin, xmax - c[:, 0]), np.minimum(c[:, 1] - ymin, ymax - c[:, 1])
        )
        for ob in obstacles:
            at_centre = np.minimum(at_centre, ob.distances(c))
        FX, FY = np.meshgrid(fs.xs, fs.ys, indexing="ij")
        fine = np.column_stack([FX.ravel(), FY.ravel()])
        clear = fs.clearance.ravel()
        cell = np.clip(((fine[:, 0] - xmin) / self.hx).astype(int), 0, self.nx - 1) * self.ny + np.clip(
            ((fine[:, 1] - ymin) / self.hy).astype(int), 0, self.ny - 1
        )
        order = np.lexsort((-clear, cell))  # by cell, the clearest fine cell first
        cells, first = np.unique(cell[order], return_index=True)
        best = np.full(n, -np.inf)
        best[cells] = clear[order[first]]
        points = c.copy()
        inside = at_centre < radius
        use = np.zeros(n, dtype=bool)
        use[cells] = True
        use &= inside & (best >= radius)
        pick = np.full(n, -1)
        pick[cells] = order[first]
        points[use] = fine[pick[use]]
        return points, (at_centre >= radius) | (best >= radius)

    def _joined(self, a: np.ndarray, b: np.ndarray, free: np.ndarray, radius: float) -> np.ndarray:
        """Per edge (cells ``a`` → ``b``), whether both cells are free and the segment between
        their waypoints runs through the loader's free fine cells only."""
        fs = self.space
        ok = free[a] & free[b]
        # Far from every wall and obstacle the segment is clear; check the others.
        pa, pb = self.points[a], self.points[b]
        near = ok & (np.minimum(self._clear_at(pa), self._clear_at(pb)) < radius + 2 * self.h)
        idx = np.flatnonzero(near)
        if idx.size:
            # Samples at most a fine cell apart over the longest edge (two cell diagonals).
            steps = math.ceil(2 * math.sqrt(2) * max(self.hx, self.hy) / min(fs.hx, fs.hy)) + 1
            t = np.linspace(0.0, 1.0, steps)
            P = pa[idx, None, :] + t[None, :, None] * (pb[idx] - pa[idx])[:, None, :]
            ok[idx] = np.all(self.free_at(P.reshape(-1, 2)).reshape(idx.size, steps), axis=1)
        return ok

    def _clear_at(self, P: Array) -> Array:
        """Clearance [m] of the fine cell each point (k, 2) [m] lies in."""
        ix, iy = self.space.cells(P)
        return np.asarray(self.space.clearance[ix, iy])

    def in_sight(self, a: Array, b: Array) -> bool:
        """Whether the segment from ``a`` to ``b`` (2,) [m] runs through the loader's free space,
        sampled a fine cell apart: a goal near but behind a wall is reached along the path."""
        fs = self.space
        steps = math.ceil(float(np.linalg.norm(np.asarray(b) - np.asarray(a))) / min(fs.hx, fs.hy)) + 1
        t = np.linspace(0.0, 1.0, steps)[:, None]
        return bool(np.all(self.free_at(np.asarray(a) + t * (np.asarray(b) - np.asarray(a)))))

    def free_at(self, P: Array) -> np.ndarray:
        """Whether a disc of the footprint may stand at each point (k, 2) [m], as the loader's
        fine grid says of the cell it lies in (k,)."""
        ix, iy = self.space.cells(P)
        return np.asarray(self.space.free[ix, iy])

    def add_discs(
        self, cost: Array, centres: list[Array], radii: list[float], extras: list[float],
        block: tuple[int, int, int, int] | None = None,
    ) -> None:  # fmt: skip
        """Add ``extras[k]`` to every cell whose centre lies within ``radii[k]`` of ``centres[k]``.

        ``cost`` is the whole grid's (n,), or with ``block`` = (i0, i1, j0, j1) the cells
        [i0, i1) × [j0, j1) of it only, row by row.  Works on the bounding block of each disc."""
        I0, I1, J0, J1 = block if block is not None else (0, self.nx, 0, self.ny)
        grid = cost.reshape(I1 - I0, J1 - J0)
        for (px, py), r, extra in zip(centres, radii, extras, strict=True):
            i0 = max(I0, int((px - r - self.x0) / self.hx))
            i1 = min(I1, int((px + r - self.x0) / self.hx) + 1)
            j0 = max(J0, int((py - r - self.y0) / self.hy))
            j1 = min(J1, int((py + r - self.y0) / self.hy) + 1)
            if i0 >= i1 or j0 >= j1:
                continue
            dx = self.xs[i0:i1, None] - px
            dy = self.ys[None, j0:j1] - py
            grid[i0 - I0 : i1 - I0, j0 - J0 : j1 - J0] += extra * (dx * dx + dy * dy < r * r)

    def cell(self, p: Array) -> int:
        """Index ``i·ny + j`` of the grid cell holding point ``p`` (2,) [m, world frame]; a
        point off the grid counts as in the nearest cell along each axis."""
        i = min(self.nx - 1, max(0, int((p[0] - self.x0) / self.hx)))
        j = min(self.ny - 1, max(0, int((p[1] - self.y0) / self.hy)))
        return i * self.ny + j

    def field(self, goal: Array, cost: Array) -> Array:
        """Predecessor array of shortest paths *to* ``goal`` under cell ``cost``."""
        return self.field_and_cost(goal, cost)[0]

    def field_and_cost(self, goal: Array, cost: Array) -> tuple[Array, Array]:
        """Predecessors (n,) and costs to go (n,) [m, weighted] of shortest paths *to* ``goal``
        under cell ``cost`` (n,), over the whole grid."""
        n = self.nx * self.ny
        w = self.length * 0.5 * (cost[self.src] + cost[self.dst]) + self.cut
        G = csr_matrix((w, self.dst, self.indptr), shape=(n, n))
        dist, pred = dijkstra(G, directed=True, indices=self.cell(goal), return_predecessors=True)
        return np.asarray(pred), np.asarray(dist)

    def shortest(self, a: Array, b: Array) -> float:
        """Length [m] of the shortest way from ``a`` to ``b`` (2,) [m] of a robot alone, past the
        walls and obstacles only: the grid's path (:attr:`static` costs), pulled taut through
        the loader's free space (each point joined to the farthest later one in sight,
        :meth:`in_sight`).  Pulled taut, the path loses the grid's 8-way zigzag (up to 8 % on a
        diagonal): in the open it is the straight line.  Its corners are the grid's waypoints,
        which may pass an obstacle up to a cell wider than the taut string: 2.4 % longer round
        the end of a wall (``tests/agent/test_navigator_window.py``).  inf if the taut path
        has to take an edge the grid does not join, out of sight (there is no way).  What no
        design can beat, to that margin: the floor of path efficiency (``fleet bench
        --liveness-floor``)."""
        a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
        if self.in_sight(a, b):
            return float(np.linalg.norm(b - a))
        pred = self.field(b, self.static)
        c, goal = self.cell(a), self.cell(b)
        pts, joined = [a], [True]  # joined[k]: the grid joins pts[k − 1] to pts[k]
        for _ in range(self.nx * self.ny):
            if c == goal or pred[c] < 0:
                break
            nxt = int(pred[c])
            joined.append(self.cut[self.edge_of[c, _DIRECTIONS.index(self._direction(c, nxt))]] == 0.0)
            c = nxt
            pts.append(self.points[c])
        pts.append(b)
        joined.append(True)
        length, i = 0.0, 0
        while i < len(pts) - 1:
            j = len(pts) - 1
            while j > i + 1 and not self.in_sight(pts[i], pts[j]):
                j -= 1
            if j == i + 1 and not joined[j] and not self.in_sight(pts[i], pts[j]):
                return math.inf  # the cheapest path leaves free space: there is no way
            length += float(np.linalg.norm(pts[j] - pts[i]))
            i = j
        return length

    def _direction(self, a: int, b: int) -> tuple[int, int]:
        """The step (di, dj) from cell ``a`` to its neighbour ``b``."""
        (ia, ja), (ib, jb) = divmod(a, self.ny), divmod(b, self.ny)
        return ib - ia, jb - ja

    def window(self, centre: Array, half: float) -> tuple[int, int, int, int] | None:
        """The cells [i0, i1) × [j0, j1) within ``half`` [m] of ``centre`` (2,) [m] along each axis,
        and one more all round (the rim, where a path leaves the window); None if that is the
        whole grid, or if the arena is no wider than the window (2·``half`` along each side):
        planning it whole costs no more than a window would."""
        if self.nx * self.hx <= 2 * half and self.ny * self.hy <= 2 * half:
            return None
        i0 = max(0, int((centre[0] - half - self.x0) / self.hx) - 1)
        i1 = min(self.nx, int((centre[0] + half - self.x0) / self.hx) + 2)
        j0 = max(0, int((centre[1] - half - self.y0) / self.hy) - 1)
        j1 = min(self.ny, int((centre[1] + half - self.y0) / self.hy) + 2)
        if (i0, i1, j0, j1) == (0, self.nx, 0, self.ny):
            return None
        return i0, i1, j0, j1

    def local_field(self, goal: Array, block: tuple[int, int, int, int], cost: Array, to_go: Array) -> Array:
        """Shortest paths to ``goal`` within a window (:meth:`window`), each ending at the goal
        or at a cell of the window's rim, from where the rest of the way costs ``to_go``
        (the whole grid's costs to go (n,), :meth:`field_and_cost`).  ``cost`` holds the cell
        costs of the block (m,), row by row.  Its work grows with the window, not the arena.

        Returns the predecessors (m,) by the block's own numbering: the next cell towards the
        goal, :data:`EXIT` where the path leaves the window here (follow ``to_go``'s field from
        there), −9999 where no path is."""
        i0, i1, j0, j1 = block
        bw = j1 - j0
        m = (i1 - i0) * bw
        ii, jj = np.divmod(np.arange(m), bw)
        cells = (ii + i0) * self.ny + (jj + j0)
        E = self.edge_of[cells]  # (m, 8)
        ok = E >= 0
        e = E[ok]
        a_l = np.repeat(np.arange(m), ok.sum(axis=1))
        b = self.dst[e]
        bi, bj = np.divmod(b, self.ny)
        inside = (bi >= i0) & (bi < i1) & (bj >= j0) & (bj < j1)
        e, a_l = e[inside], a_l[inside]
        b_l = (bi[inside] - i0) * bw + (bj[inside] - j0)
        w = self.length[e] * 0.5 * (cost[a_l] + cost[b_l]) + self.cut[e]
        # The rim: the block's outer cells, where the grid goes on beyond them.  One source
        # more, joined to the rim's cells at their cost to go and to the goal at 0 (a hair
        # above: a sparse graph's zero is no edge).
        rim = ((ii == 0) & (i0 > 0)) | ((ii == i1 - i0 - 1) & (i1 < self.nx))
        rim |= ((jj == 0) & (j0 > 0)) | ((jj == bw - 1) & (j1 < self.ny))
        src_l = np.flatnonzero(rim & np.isfinite(to_go[cells]))
        src_w = np.maximum(to_go[cells[src_l]], 1e-9)
        gi, gj = divmod(self.cell(goal), self.ny)
        if i0 <= gi < i1 and j0 <= gj < j1:
            src_l = np.append(src_l, (gi - i0) * bw + (gj - j0))
            src_w = np.append(src_w, 1e-9)
        rows = np.concatenate([a_l, np.full(src_l.size, m)])
        cols = np.concatenate([b_l, src_l])
        G = csr_matrix((np.concatenate([w, src_w]), (rows, cols)), shape=(m + 1, m + 1))
        _, pred = dijkstra(G, directed=True, indices=m, return_predecessors=True)
        pred = np.asarray(pred[:m])
        pred[pred == m] = EXIT
        return pred

    def carrot(
        self, pred: Array, start: Array, goal: Array, lookahead: float,
        block: tuple[int, int, int, int] | None = None, then: Array | None = None,
    ) -> Array:  # fmt: skip
        """Point ``lookahead`` [m] along the path from ``start`` towards ``goal`` (so no farther
        from ``start`` than that), or ``goal`` if the path is shorter: along ``pred`` (the whole
        grid's, or with ``block`` a window's, :meth:`local_field`), and from where it leaves the
        window along ``then`` (the whole grid's).  The path runs from ``start`` to its cell's
        successor's waypoint, then waypoint to waypoint, and from the goal's cell (or the last
        cell with a way on, if the goal's is cut off) straight to the goal; the point lies on the
        hop that reaches the lookahead."""
        c = self.cell(start)
        gcell = self.cell(goal)
        travelled = 0.0
        prev = start
        for _ in range(self.nx * self.ny):
            if c == gcell:
                break
            nxt = -1
            if block is not None:
                i0, i1, j0, j1 = block
                ci, cj = divmod(c, self.ny)
                bw = j1 - j0
                k = int(pred[(ci - i0) * bw + cj - j0]) if i0 <= ci < i1 and j0 <= cj < j1 else EXIT
                if k >= 0:
                    nxt = (k // bw + i0) * self.ny + k % bw + j0
                elif k == EXIT and then is not None:  # left the window: the whole grid's field on
                    block, pred = None, then
            if block is None:
                nxt = int(pred[c])
            if nxt < 0:
                break  # no way on (the goal's cell is cut off): straight towards the goal
            p = self.points[nxt]
            hop = math.hypot(p[0] - prev[0], p[1] - prev[1])
            if travelled + hop >= lookahead:  # the point exactly ``lookahead`` along the path
                return prev + (lookahead - travelled) / hop * (p - prev)
            travelled += hop
            prev = p
            c = nxt
        # The last hop, to the goal itself: the goal if it lies within the lookahead, else the
        # point that far along the hop (the carrot is never farther than that from ``start``).
        hop = math.hypot(goal[0] - prev[0], goal[1] - prev[1])
        if travelled + hop <= lookahead:
            return goal
        return prev + (lookahead - travelled) / hop * (goal - prev)


@functools.lru_cache(maxsize=8)
def _grid(arena: tuple[float, ...], footprint: float, obstacles: tuple[Any, ...]) -> GridPlanner:
    return GridPlanner((arena[0], arena[1], arena[2], arena[3]), footprint, obstacles)


def grid_planner(
    arena: tuple[float, float, float, float], footprint: float, obstacles: Sequence[Any]
) -> GridPlanner:
    """The :class:`GridPlanner` of an arena, a footprint [m] and obstacles, made once per process
    and shared, read-only, by every navigator in it (``fleet simulate`` runs them all in one)."""
    return _grid(tuple(float(v) for v in arena), float(footprint), tuple(obstacles))


EXIT = -2
"""A window's predecessor (:meth:`GridPlanner.local_field`) where the path leaves it."""
PARKING_STEP = WAIT_RING_STEP
"""Radial step [m] of the rings about a covered goal on which a point to park is sought: as a
wait point's (a point is placed to 2 cm)."""
PARKING_CLEAR = GOAL_MARGIN
"""How far [m] outside every static disc a point to park must be: the goal margin."""
_ANGLES = np.linspace(0.0, 2.0 * math.pi, 36, endpoint=False)


@functools.lru_cache(maxsize=16)
def parking_rings(reach: float) -> np.ndarray:
    """Offsets (k, 2) [m] the navigator tries about a covered goal, ring by ring outwards, every
    :data:`PARKING_STEP` out to ``reach`` [m] (:meth:`Navigator.clear_goal`), 10° apart."""
    return np.vstack(
        [
            rho * np.column_stack([np.cos(_ANGLES), np.sin(_ANGLES)])
            for rho in np.arange(PARKING_STEP, reach + PARKING_STEP, PARKING_STEP)
        ]
    )


WINDOW = 2.0
"""Half side [m] of the window in which a replan weighs the other robots
(:meth:`GridPlanner.local_field`); beyond it the path follows the walls, obstacles and stopped
robots only, planned once per goal.  So a replan costs the same in any arena.  It must hold
every robot the rules act on, and the carrot: the yield range r_i + r_j + ``conflict_range``
(0.62 m with the epuck preset) plus the lookahead (0.3 m) plus what the robot moves between
replans (``replan_steps``·v_max·Ts, 0.13 m), under 1.1 m; the plan by place hears less still.
An arena no wider than the window (4 m along each side) is planned whole, as before windows:
that costs no more than a window would (docs/method.md §7)."""

CORRIDOR_MARGIN = 0.05
"""Extra half-width of the corridor of a robot that goes first, beyond r_i + r_j [m]."""

LOOKAHEAD = 0.3
"""Carrot distance along the planned path [m].  Tuned, not derived (docs/method.md §7, the
constants' table).  The design bounds it below only: that a robot on a corridor's axis,
leaving it sideways at full speed from the moment it enters, never slows the robot that goes
first asks lookahead ≥ √2·(r_i + r_j) − (r_i + r_j + :data:`CORRIDOR_MARGIN`), 0.06 m with the
epuck preset; the 0.3 m above that was chosen on the liveness bench."""

CONFLICT_RANGE = LOOKAHEAD + CORRIDOR_MARGIN
"""Extra distance beyond r_i + r_j within which a robot that goes first is yielded to [m].
Derived: a robot on its way steers to a target at most :data:`LOOKAHEAD` from its point (its
carrot, that far along its path and so no farther in a straight line (:meth:`GridPlanner.carrot`),
or its goal within that), so its corridor, that segment widened by r_i + r_j +
:data:`CORRIDOR_MARGIN`, lies within r_i + r_j + this of it: the range drops no robot such a
corridor holds, and takes none it cannot hold (docs/method.md §7)."""


@dataclass
class Navigator:
    """Chooses the target of the goal term (shaping only; see module docstring).

    Every ``replan_steps`` it plans a grid path to the goal around walls and
    static obstacles (hard), parked robots (expensive) and the moving robots
    that go first (cheaper), ignoring those that go after it, and follows a
    carrot point ``lookahead`` ahead.  On top of
    that, the yielding rule: a robot inside the corridor of a nearby robot
    that goes first (the segment to that robot's carrot, widened by
    r_i + r_j + ``corridor_margin``) moves to the best free point out of it.
    Precedence is (phase, age, priority, rank): robots under way (goal never
    reached) go first, then robots returning to a goal they were displaced
    from, the one displaced first before the others, then parked robots,
    which step aside when they block a path and return afterwards.  Parked
    robots never need to yield to each other, and the first robot in
    precedence never waits on a robot that can move."""

    footprint: float
    arena: tuple[float, float, float, float]
    obstacles: Sequence[Any] = ()
    priority: int = 0
    rank: int = 0
    view: float = math.inf
    """The farthest beyond r_i + r_j [m] this robot is sure to see the others (an agent with plans
    by place sets it from its view, :func:`agent.coordination.navigator_view`); it caps
    :attr:`conflict_range`."""
    corridor_margin: float = CORRIDOR_MARGIN
    """Extra corridor half-width beyond r_i + r_j [m]."""
    close_goals: float = CORRIDOR_MARGIN + PARKED_RADIUS
    """A parked robot does not yield to a returning one whose goal is within r_i + r_j + this of
    its own [m] (see :meth:`target`).  The returning robot's corridor ends at its goal, r_i + r_j
    + ``corridor_margin`` wide, and a parked robot stands anywhere within
    :data:`~ground.scenario.PARKED_RADIUS` of its own: any closer pair of goals, and the end
    of the corridor can cover the parked robot (docs/method.md §7, "Close goals")."""
    close_goals_patience: int = 600
    """Steps a robot may return to its goal before the close-goals rule lapses for it [steps]:
    from then on, a parked robot at a close goal yields to it as to any robot that goes first.
    A goal enclosed by parked robots at close goals (the interior of a grid of goals spaced
    barely over R) is reachable no other way (docs/method.md §7, "Close goals")."""
    lookahead: float = LOOKAHEAD
    """Carrot distance along the planned path [m] (:data:`LOOKAHEAD`)."""
    window: float = WINDOW
    """Half side of the square about the robot in which each replan weighs the other robots [m]
    (:data:`WINDOW`)."""
    replan_steps: int = 10
    """Steps between grid replans; robot of rank r replans at the steps ≡ −r (mod this) after its first."""
    soft_cost: float = 8.0
    """Extra cost per metre inside the footprint disc of a moving robot."""
    parked_cost: float = 40.0
    """Extra cost per metre inside the footprint disc of a parked robot."""
    hold_steps: int = 15
    stall_steps: int = 60
    """Steps without 2 cm of progress before the watchdog escape."""
    seed: int = 0
    phase: int = 0
    """This robot's precedence class (set by the controller each step)."""
    phase_age: int = 0
    """Steps this robot has been in ``phase`` (set by the controller each step)."""
    _grid: GridPlanner | None = None
    _ring: Array = field(default_factory=lambda: np.zeros((0, 2)))
    _ring_norm: Array = field(default_factory=lambda: np.zeros(0))
    _pred: Array | None = None
    _since_plan: int = 10**9
    _escape: Array | None = None
    _escape_left: int = 0
    no_room: str = ""
    """The robot that goes first whose corridor this robot found no free point out of, at the
    last :meth:`target`, or "": assumption (A) of docs/method.md §7 failing for it."""
    _escape_mode: str = "aside"
    """What the point held is for: "aside" (made way to) or "escape" (the watchdog's)."""
    _rng: np.random.Generator | None = None
    _best_dist: float = math.inf
    _stall: int = 0
    _discs: list[tuple[Array, float]] = field(default_factory=list)
    _discs_key: tuple[tuple[float, float, float], ...] = ()
    _static_key: tuple[Any, ...] | None = None
    _static_cost: Array = field(default_factory=lambda: np.zeros(0))
    _to_go: tuple[Array, Array] | None = None
    _block: tuple[int, int, int, int] | None = None

    def __post_init__(self) -> None:
        self._grid = grid_planner(self.arena, self.footprint, self.obstacles)
        ang = np.linspace(0.0, 2.0 * math.pi, 24, endpoint=False)
        unit = np.column_stack([np.cos(ang), np.sin(ang)])
        self._ring = np.vstack([0.5 * unit, unit])
        self._ring_norm = np.linalg.norm(self._ring, axis=1)
        self._rng = np.random.default_rng(self.seed)

    @property
    def conflict_range(self) -> float:
        """Extra distance beyond r_i + r_j within which a robot that goes first is yielded to
        [m]: ``lookahead`` + ``corridor_margin`` (as :data:`CONFLICT_RANGE`, derived there), so it
        follows them whatever they are set to, capped by :attr:`view`."""
        return min(self.lookahead + self.corridor_margin, self.view)

    @property
    def precedence(self) -> tuple[int, int, int, int]:
        """This robot's place in the order (:func:`agent.coordination.precedence`)."""
        return precedence(self.phase, self.phase_age, self.priority, self.rank)

    def reset_goal(self) -> None:
        """Forget the plan and the watchdog state (new goal)."""
        self._pred = None
        self._escape = None
        self._best_dist = math.inf
        self._stall = 0

    def set_discs(self, discs: Sequence[tuple[Array, float]]) -> bool:
        """The static discs of robots off their plans for good (docs/method.md §6.4), each as
        (centre (2,) [m], clearance [m]: r_i plus the disc's radius, within which ȳ may not
        come).  Paths go around them as around a static obstacle, and a goal inside one gives way
        to a point to park at (:meth:`clear_goal`).  Returns whether they
        changed since the last call; a change replans at the next waypoint."""
        key = tuple((round(float(c[0]), 4), round(float(c[1]), 4), round(float(r), 4)) for c, r in discs)
        if key == self._discs_key:
            return False
        self._discs_key = key
        self._discs = [(np.array(c, dtype=float), float(r)) for c, r in discs]
        self._since_plan = self.replan_steps  # replan at the next waypoint
        return True

    def clear_goal(self, goal: Array, goals: Sequence[tuple[Array, float]] = ()) -> Array:
        """``goal`` (2,) [m] itself if no static disc (:meth:`set_discs`) covers it; else the point
        nearest it, on rings :data:`PARKING_STEP` apart, where the robot may park: clear of every
        disc by :data:`PARKING_CLEAR`, clear of the walls and obstacles (the loader's free space),
        inside the walls by the footprint, and as far from every other robot's goal as goals must
        be apart (``goals``: (goal (2,) [m], the distance [m]), so that each can still park at its
        own).  The goal itself if there is none (shaping only: the constraints keep ȳ out of
        the discs).

        The rings reach round the widest covering disc (every point just outside it, on any side,
        lies within its diameter and :data:`PARKING_CLEAR` of a goal it covers) and across one
        other goal's keep-out beyond that (its diameter), however wide the disc."""
        p = np.array(goal, dtype=float)
        covering = [r for c, r in self._discs if math.hypot(*(p - c)) < r]
        if not covering:
            return p
        g = self._grid
        assert g is not None
        reach = 2.0 * max(covering) + PARKING_CLEAR + 2.0 * max((a for _, a in goals), default=0.0)
        P = p + parking_rings(round(reach, 2))
        xmin, xmax, ymin, ymax = self.arena
        r = self.footprint
        ok = (P[:, 0] >= xmin + r) & (P[:, 0] <= xmax - r) & (P[:, 1] >= ymin + r) & (P[:, 1] <= ymax - r)
        ok &= g.free_at(P)
        for c, rad in self._discs:
            ok &= np.hypot(P[:, 0] - c[0], P[:, 1] - c[1]) >= rad + PARKING_CLEAR
        for q, apart in goals:
            ok &= np.hypot(P[:, 0] - q[0], P[:, 1] - q[1]) >= apart
        if not np.any(ok):
            return p
        return P[int(np.argmax(ok))].copy()  # the rings go outwards: the first is the nearest

    def _plan(self, c: Array, goal: Array, neighbours: Sequence[NeighbourInfo]) -> None:
        g = self._grid
        assert g is not None
        key = (float(goal[0]), float(goal[1]), self._discs_key)
        if key != self._static_key:  # walls, obstacles and stopped robots: once per goal
            self._static_cost = g.static.copy()
            if self._discs:  # robots off their plans for good: as static obstacles
                g.add_discs(
                    self._static_cost, [c for c, _ in self._discs], [r for _, r in self._discs],
                    [g.BLOCKED] * len(self._discs),
                )  # fmt: skip
            self._static_key, self._to_go = key, None
        self._block = g.window(c, self.window)
        if self._block is None:
            cost = self._static_cost.copy()
        else:
            if self._to_go is None:
                self._to_go = g.field_and_cost(goal, self._static_cost)
            i0, i1, j0, j1 = self._block
            cost = self._static_cost.reshape(g.nx, g.ny)[i0:i1, j0:j1].ravel()  # a copy
        me = self.precedence
        pts, radii, extras = [], [], []
        for nb in neighbours:
            if nb.phase == PARKED:
                extras.append(self.parked_cost)
            elif precedence(nb.phase, nb.phase_age, nb.priority, nb.rank) < me:
                extras.append(self.soft_cost)  # goes first: plan around it
            else:
                continue  # goes after this robot: it yields, so plan through it
            pts.append(nb.last_point)
            radii.append(self.footprint + nb.footprint)
        if pts:
            g.add_discs(cost, pts, radii, extras, self._block)
        if self._block is None:
            self._pred = g.field(goal, cost)
        else:
            assert self._to_go is not None
            self._pred = g.local_field(goal, self._block, cost, self._to_go[1])
        self._since_plan = 0

    def waypoint(self, c: Array, goal: Array, neighbours: Sequence[NeighbourInfo] = ()) -> Array:
        """Carrot point on the planned path from ``c`` to ``goal``."""
        if self._pred is None or self._since_plan >= self.replan_steps:
            first = self._pred is None
            self._plan(c, goal, neighbours)
            if first:
                # Robots replan in turn, not all at the same step: a replan costs a few
                # milliseconds, and 16 at once on 2 cores missed the realtime deadline.
                self._since_plan = self.rank % self.replan_steps
        self._since_plan += 1
        assert self._grid is not None and self._pred is not None
        if float(np.linalg.norm(goal - c)) <= self.lookahead and self._grid.in_sight(c, goal):
            return goal
        then = None if self._to_go is None else self._to_go[0]
        return self._grid.carrot(self._pred, c, goal, self.lookahead, self._block, then)

    def target(self, c: Array, goal: Array, neighbours: Sequence[NeighbourInfo]) -> tuple[Array, str]:
        """Target of the goal term and the mode: ``goal`` or ``path`` (its own way), ``yield``
        (making way: in the corridor of a robot that goes first), ``aside`` (holding the point it
        made way to, for :attr:`hold_steps`) or ``escape`` (the progress watchdog's point)."""
        wp = self.waypoint(c, goal, neighbours)
        mode = "goal" if wp is goal else "path"
        me = self.precedence
        self.no_room = ""
        corridors, owners = [], []
        sweeps = 0  # of those corridors, the sweeps of robots driving on uncontrolled
        for nb in neighbours:
            R = self.footprint + nb.footprint
            q = nb.last_point
            if abs(q[0] - c[0]) > R + self.conflict_range or abs(q[1] - c[1]) > R + self.conflict_range:
                continue  # out of range (the exact test is below); cheaper than the order
            # Yield to those that go first (:func:`agent.coordination.precedence`).
            if nb.phase == PARKED or precedence(nb.phase, nb.phase_age, nb.priority, nb.rank) > me:
                continue
            if (
                self.phase == PARKED
                and nb.phase == RETURNING
                and nb.phase_age < self.close_goals_patience
                and nb.goal is not None
                and math.hypot(nb.goal[0] - goal[0], nb.goal[1] - goal[1]) < R + self.close_goals
            ):
                # Close goals: yielding to a robot returning to its own would displace this one
                # from its goal, and the two would trade places for ever.  The returning robot
                # plans around this parked one instead (docs/method.md §7, "Close goals").
                continue
            if math.hypot(q[0] - c[0], q[1] - c[1]) > R + self.conflict_range:
                continue
            end = nb.target if nb.target is not None else nb.last_point
            corridors.append((nb.last_point, end, R + self.corridor_margin))
            owners.append(nb.id)
            if nb.priority == UNCONTROLLED_PRIORITY:
                sweeps += point_segment_distance(c, nb.last_point, end) < R + self.corridor_margin
        blocked = [cd for cd in corridors if point_segment_distance(c, cd[0], cd[1]) < cd[2]]
        if blocked:
            # In the sweep of a robot driving on uncontrolled, the point already made for stands
            # while it is still clear of every corridor and free: chosen afresh each step, a
            # robot on the line of the one that comes on (both sides alike) turns from side to
            # side and stays on it, and the other does not stop (docs/method.md §6.4).
            held = self._escape
            if held is None or not (sweeps and self._clear_of(held, corridors)):
                held = self._escape_point(c, wp, corridors, neighbours)
            # Assumption (A) of the progress argument, checked: is the point out of every
            # corridor?  If not, name the robot whose corridor it could not leave.
            self.no_room = next(
                (
                    j
                    for j, (a, b, w) in zip(owners, corridors, strict=True)
                    if point_segment_distance(held, a, b) < w
                ),
                "",
            )
            self._escape, self._escape_mode = held, "aside"
            self._escape_left = self.hold_steps
            self._stall = 0
            return held, "yield"

        # Progress watchdog: no progress for long → a clearance-seeking escape
        # point, held for a while (docs/method.md §7).  Time spent yielding or escaping
        # does not count as a stall.
        if self._escape is not None and self._escape_left > 0:
            self._escape_left -= 1
            if np.linalg.norm(self._escape - c) > 0.02:
                return self._escape, self._escape_mode
        if self._escape is not None:
            self._escape = None
            self._best_dist = math.inf
            self._stall = 0
        dgoal = float(np.linalg.norm(goal - c))
        if dgoal < self._best_dist - 0.02 or dgoal < 0.005:
            self._best_dist = min(dgoal, self._best_dist)
            self._stall = 0
        else:
            self._stall += 1
        if self._stall > self.stall_steps:
            self._escape = self._escape_point(c, wp, corridors, neighbours, radius=0.5)
            self._escape_left, self._escape_mode = 40, "escape"
            return self._escape, "escape"
        return wp, mode

    def _standable(self, P: Array) -> np.ndarray:
        """Whether the footprint may stand at each point (k, 2) [m], clear of the walls, the
        obstacles and every static disc (k,)."""
        assert self._grid is not None
        free = self._grid.free_at(P)
        for q, r in self._discs:
            free &= np.hypot(P[:, 0] - q[0], P[:, 1] - q[1]) >= r
        return free

    def _clear_of(self, p: Array, corridors: list[tuple[Array, Array, float]]) -> bool:
        """Whether point ``p`` (2,) [m] is outside every corridor and the footprint may stand there."""
        return bool(self._standable(p[None, :])[0]) and all(
            point_segment_distance(p, a, b) >= w for a, b, w in corridors
        )

    def _escape_point(
        self,
        c: Array,
        wp: Array,
        corridors: list[tuple[Array, Array, float]],
        neighbours: Sequence[NeighbourInfo],
        radius: float = 0.4,
    ) -> Array:
        """Best free point near ``c``: outside the corridors, clear of others, towards ``wp``.

        48 candidates on two rings around ``c``, scored (all at once) by the
        distance travelled, the distance left to ``wp``, corridor penetration
        and lack of clearance from the neighbours' committed points."""
        P = c + self._ring * radius  # (48, 2)
        free = self._standable(P)
        if not np.any(free):
            # Nowhere to stand aside.  A parked robot keeps to its goal, where it blocks nobody's
            # (goals are two footprints and a margin apart): off it, it may block a neighbour's.
            return wp.copy() if self.phase == PARKED else c.copy()
        score = 0.5 * radius * self._ring_norm + 0.2 * np.hypot(wp[0] - P[:, 0], wp[1] - P[:, 1])
        for a, b, w in corridors:
            dseg = _points_segment_distance(P, a, b)
            score += np.where(dseg < w, 10.0 + 5.0 * (w - dseg), 0.0)
        if neighbours:
            Q = np.array([nb.last_point for nb in neighbours])
            R = self.footprint + np.array([nb.footprint for nb in neighbours])
            clear = np.hypot(P[:, 0, None] - Q[None, :, 0], P[:, 1, None] - Q[None, :, 1]) - R[None, :]
            score += 2.0 * np.maximum(0.1 - clear, 0.0).sum(axis=1)
        score[~free] = np.inf
        return P[int(np.argmin(score))].copy()


def _points_segment_distance(P: Array, a: Array, b: Array) -> Array:
    """Distances (k,) from points P (k, 2) to segment ab [m]."""
    dx, dy = float(b[0] - a[0]), float(b[1] - a[1])
    L2 = dx * dx + dy * dy
    ex, ey = P[:, 0] - a[0], P[:, 1] - a[1]
    if L2 < 1e-12:
        return np.hypot(ex, ey)
    t = np.minimum(np.maximum((ex * dx + ey * dy) / L2, 0.0), 1.0)
    return np.hypot(ex - t * dx, ey - t * dy)
