"""One robot alone arrives at any goal the loader accepts: the navigator plans in the loader's
model of free space (``ground.freespace``), and the repair of ȳ keeps a step that slides along a
binding row (docs/method.md §7)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from agent.navigator import GridPlanner
from agent.tube import validated_design
from fleet.running.scenes import LAYOUT_FAMILIES, _box, _robot, _scene, hard_scene, pocket
from fleet.running.simulate import run
from ground.freespace import free_space_model
from ground.scenario import parse_scenario

# Just over the least width the loader accepts for the epuck preset's footprint (2 × 0.134 m
# and a fine cell), to a width the old 5 cm grid already managed.
WIDTHS = [0.275, 0.28, 0.29, 0.30]


def _passage(width: float, length: float = 0.4) -> dict:
    """One robot from the left of the arena to the right through a straight passage ``width``
    [m] wide and ``length`` [m] long, its centre line at y = 0: between two rows of the
    navigator's 5 cm grid, whose cell centres lie at y = ±0.025 m."""
    h = width / 2
    walls = [_box(-length / 2, length / 2, h, 1.0), _box(-length / 2, length / 2, -1.0, -h)]
    robot = _robot(0, (-0.75, 0.0), (0.75, 0.0))
    return _scene(f"passage_{round(width * 1000)}mm", [robot], 120.0, 0, obstacles=walls)


def _path(grid: GridPlanner, start: np.ndarray, goal: np.ndarray) -> list[int]:
    pred = grid.field(goal, grid.static)
    cells, c = [grid.cell(start)], grid.cell(start)
    for _ in range(grid.nx * grid.ny):
        if c == grid.cell(goal):
            break
        c = int(pred[c])
        assert c >= 0, "no path"
        cells.append(c)
    return cells


@pytest.mark.parametrize("width", WIDTHS)
def test_the_navigator_sees_every_passage_the_loader_accepts(width):
    """The grid's path into a pocket the loader accepts runs through the loader's free space
    only: every waypoint is where the disc may stand, every edge joins free fine cells, and
    none crosses the pocket's thin arms (once it cut through one, and the robot rested against
    it for ever)."""
    scn = parse_scenario(pocket(width))
    fp = validated_design(scn).footprint  # the loader accepts it
    grid = GridPlanner(scn.arena, fp, scn.obstacles)
    space = free_space_model(scn.arena, scn.obstacles, fp)
    r = scn.robots[0]
    start = np.array(r.start[:2])
    goal = np.array(r.goal)
    cells = _path(grid, start, goal)
    assert grid.cell(goal) == cells[-1]
    pts = grid.points[cells[1:]]
    assert np.all(grid.static[cells[1:]] < GridPlanner.BLOCKED)
    assert np.all(grid.free_at(pts)), pts[~grid.free_at(pts)]
    for a, b in itertools.pairwise(cells[1:]):
        seg = grid.points[a] + np.linspace(0, 1, 40)[:, None] * (grid.points[b] - grid.points[a])
        assert np.all(grid.free_at(seg)), (a, b)
        assert all(space.joined(p, goal) for p in seg[::10])
    # The straight line from the start crosses an arm; the path does not.
    line = start + np.linspace(0, 1, 200)[:, None] * (goal - start)
    assert not np.all(grid.free_at(line))


# The bench's pocket 0.283 m wide, whose robot came to 0.3 m of its goal on the far side of an
# arm: the navigator took the goal itself for its target, the wall's rows stopped it there,
# and it went to and fro for the whole run.
SCENES = [pocket(w) for w in WIDTHS[:2]] + [_passage(0.277), hard_scene(60, LAYOUT_FAMILIES)]


@pytest.mark.parametrize("scene", SCENES, ids=lambda s: s["name"])
def test_one_robot_alone_arrives_where_the_loader_said_it_could(scene):
    """One robot alone, ``fleet simulate``: into a pocket just wider than the loader's least
    width, and along a passage 0.277 m wide whose centre line lies between two rows of the
    grid, where a robot sliding along the walls' rows once stopped whenever rounding put the
    solver's ȳ a hair outside them.  It arrives, with no step outside its tube."""
    scn = parse_scenario(scene)
    res = run(scn, seed=0)
    s = res.judge.summary(True, res.wall_time)
    r = s["robots"][scn.robots[0].id]
    assert r["reached_goal"], (r["final_error_m"], r["time_to_goal_s"])
    assert r["tube_exits"] == 0 and s["obstacle_violations"] == 0
    ctrl = res.controllers[scn.robots[0].id]
    assert ctrl.counters.scaled_repairs == 0, (ctrl.counters.repairs, ctrl.counters.scaled_repairs)
