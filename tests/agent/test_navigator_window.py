"""The navigator's window: a replan weighs the other robots only near the robot, and finishes
the way on a field of the walls and obstacles planned once per goal.  Its work is bounded by
the window, whatever the arena; with no robot about, its paths are exactly the shortest; where
the window holds the whole arena, it is not used at all."""

from __future__ import annotations

import math

import numpy as np
import pytest

from agent.navigator import EXIT, WINDOW, GridPlanner, Navigator, grid_planner
from ground.scenario import Circle

BIG = (-5.0, 5.0, -5.0, 5.0)
OBSTACLES = (Circle(center=(0.0, 0.0), radius=1.0), Circle(center=(2.5, -2.0), radius=0.6))


def _walk(g: GridPlanner, start: np.ndarray, goal: np.ndarray, pred, block, then) -> float:
    """The static cost [m, weighted] of the path the fields give from ``start`` to ``goal``."""
    n = g.nx * g.ny
    w = g.length * g.static[g.src] * 0.5 + g.length * g.static[g.dst] * 0.5 + g.cut
    edge = dict(zip((g.src * n + g.dst).tolist(), w.tolist(), strict=True))
    c, total = g.cell(start), 0.0
    for _ in range(n):
        if c == g.cell(goal):
            return total
        nxt = -1
        if block is not None:
            i0, i1, j0, j1 = block
            ci, cj = divmod(c, g.ny)
            inside = i0 <= ci < i1 and j0 <= cj < j1
            k = int(pred[(ci - i0) * (j1 - j0) + cj - j0]) if inside else EXIT
            if k >= 0:
                nxt = (k // (j1 - j0) + i0) * g.ny + k % (j1 - j0) + j0
            else:
                assert k == EXIT, "no path inside the window"
                block, pred = None, then
        if block is None:
            nxt = int(pred[c])
        assert nxt >= 0
        total += edge[c * n + nxt]
        c = nxt
    raise AssertionError("the path does not end")


def test_with_no_robot_about_the_windowed_path_is_the_shortest():
    """Exactness: a path leaving the window crosses its rim, and from there costs at least the
    rim's cost to go; so the window's best way home, rim cost included, is the grid's."""
    g = grid_planner(BIG, 0.134, OBSTACLES)
    rng = np.random.default_rng(3)
    checked = 0
    while checked < 12:
        start, goal = rng.uniform(-4.6, 4.6, 2), rng.uniform(-4.6, 4.6, 2)
        if not (g.free_at(start)[0] and g.free_at(goal)[0]) or np.linalg.norm(goal - start) < 2.5:
            continue
        then, to_go = g.field_and_cost(goal, g.static)
        block = g.window(start, WINDOW)
        assert block is not None
        i0, i1, j0, j1 = block
        local = g.local_field(goal, block, g.static.reshape(g.nx, g.ny)[i0:i1, j0:j1].ravel(), to_go)
        cost = _walk(g, start, goal, local, block, then)
        assert math.isclose(cost, to_go[g.cell(start)], rel_tol=1e-9), (start, goal)
        checked += 1


def test_a_replans_work_is_bounded_by_the_window_not_the_arena():
    """In a 20 m arena (400 × 400 cells) a window holds at most (2·WINDOW/h + 4)² cells."""
    g = grid_planner((-10.0, 10.0, -10.0, 10.0), 0.134, ())
    bound = (2 * WINDOW / g.h + 4) ** 2
    for centre in ([0.0, 0.0], [9.9, -9.9], [-3.0, 7.0]):
        block = g.window(np.array(centre), WINDOW)
        assert block is not None
        i0, i1, j0, j1 = block
        ones = np.ones((i1 - i0) * (j1 - j0))
        pred = g.local_field(np.array([5.0, 5.0]), block, ones, np.zeros(g.nx * g.ny))
        assert pred.size == (i1 - i0) * (j1 - j0) <= bound < g.nx * g.ny / 20


def test_a_robot_on_a_long_way_steers_around_a_robot_in_its_window():
    """The window weighs the robots that go first: the carrot leaves the straight line to pass
    a robot standing on it, as over the whole grid, and then heads on along the static field."""
    from agent.coordination import NeighbourInfo
    from ground.wire import UNDER_WAY

    nav = Navigator(footprint=0.134, arena=BIG, rank=3)
    start, goal = np.array([-4.0, 3.0]), np.array([4.0, 3.0])
    ahead = NeighbourInfo(id="r0", last_point=np.array([-3.7, 3.0]), footprint=0.134, rank=0, phase=UNDER_WAY)
    wp = nav.waypoint(start, goal, [ahead])
    assert nav._block is not None  # the arena is larger than the window
    assert abs(wp[1] - 3.0) > 0.05, wp  # bends round the robot in the way
    alone = Navigator(footprint=0.134, arena=BIG, rank=3).waypoint(start, goal, [])
    assert abs(alone[1] - 3.0) < 0.03 and alone[0] > start[0] + 0.25, alone  # straight on


def test_an_arena_no_wider_than_the_window_is_planned_whole():
    """From anywhere in a 2 m arena, and in the 3.6 m one of the 32-robot swap, and a 3 m × 0.6 m
    corridor: no window, the plan is the whole grid's, as before windows."""
    for arena in ((-1.0, 1.0, -1.0, 1.0), (-1.8, 1.8, -1.8, 1.8), (-1.5, 1.5, -0.3, 0.3)):
        g = grid_planner(arena, 0.134, ())
        for centre in ([-0.95 * arena[1], 0.0], [0.0, 0.0], [0.9 * arena[1], 0.9 * arena[3]]):
            assert g.window(np.array(centre), WINDOW) is None, (arena, centre)
    wide = grid_planner((-2.5, 2.5, -0.3, 0.3), 0.134, ())  # 5 m long: windowed at either end
    assert wide.window(np.array([-2.2, 0.0]), WINDOW) is not None


def test_the_shortest_way_alone_is_the_straight_line_in_the_open_and_the_taut_string_round_a_wall() -> None:
    """:meth:`GridPlanner.shortest`, the floor of path efficiency: in free space exactly the
    straight line (the grid's 8-way zigzag would be up to 8 % longer); past a thin wall, the
    taut string round the wall's end inflated by the footprint, worked out by hand (two
    tangents, two arcs about the end's corners and the end itself), never shorter and at most
    3 % longer; and no way
    (inf) to a point the walls shut off."""
    from ground.scenario import Polygon

    r, w = 0.08, 0.02
    open_grid = grid_planner((-1.0, 1.0, -1.0, 1.0), r, ())
    line = open_grid.shortest(np.array([-0.7, -0.7]), np.array([0.7, 0.6]))
    assert line == pytest.approx(math.hypot(1.4, 1.3))
    wall = Polygon(((-w / 2, -0.5), (w / 2, -0.5), (w / 2, 1.0), (-w / 2, 1.0)))
    grid = grid_planner((-1.0, 1.0, -1.0, 1.0), r, (wall,))
    a, b = np.array([-0.5, 0.0]), np.array([0.5, 0.0])
    corner = np.array([-w / 2, -0.5])  # the left corner of the wall's end; the right by symmetry
    d = float(np.linalg.norm(a - corner))
    towards_a = math.atan2(a[1] - corner[1], a[0] - corner[0])
    arc = 1.5 * math.pi - (towards_a + math.acos(r / d))  # from the tangent point down to the bottom
    by_hand = 2.0 * (math.sqrt(d * d - r * r) + r * arc) + w
    got = grid.shortest(a, b)
    # Never shorter (the 5 mm cells of the loader's free space aside), at most 3 % longer: its
    # corners are the grid's waypoints, up to a cell wider of an obstacle than the string.
    assert by_hand - 0.01 <= got <= 1.03 * by_hand, (got, by_hand)
    assert got > float(np.linalg.norm(b - a)) + 0.5
    sealed = Polygon(((-w / 2, -1.0), (w / 2, -1.0), (w / 2, 1.0), (-w / 2, 1.0)))
    assert math.isinf(grid_planner((-1.0, 1.0, -1.0, 1.0), r, (sealed,)).shortest(a, b))
