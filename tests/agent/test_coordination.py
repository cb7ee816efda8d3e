"""Coordination terms: the split rule's safety and feasibility, obstacles, the navigator's grid."""

from __future__ import annotations

import math

import numpy as np
import pytest

from agent.coordination import (
    NeighbourInfo,
    obstacle_halfplanes,
    repair_point,
    shares,
    split_halfplanes,
)
from agent.navigator import CORRIDOR_MARGIN, LOOKAHEAD, GridPlanner, Navigator, point_segment_distance
from ground.scenario import PARKED_RADIUS, Circle
from ground.wire import MAX_AGE, PARKED, RETURNING, UNDER_WAY

EPS = 0.0055


def _sample_in_rows(rng, c, normals, bounds, eps, count=200):
    """Points of the ε box around c that satisfy every row nᵀy ≥ b (rejection sampling)."""
    pts = c + rng.uniform(-eps, eps, (count, 2))
    ok = np.ones(count, dtype=bool)
    for n, b in zip(normals, bounds, strict=True):
        ok &= pts @ n >= b - 1e-15
    return pts[ok]


@pytest.mark.parametrize("prio", [(0, 0), (1, 0), (0, 3)])
def test_split_rule_keeps_new_points_R_apart_and_stay_put_feasible(prio):
    """nᵀ(ȳ_i − ȳ_j) ≥ R for every pair of points the two agents may append."""
    rng = np.random.default_rng(1)
    r_i, r_j = 0.134, 0.113
    R = r_i + r_j
    checked = 0
    for _ in range(300):
        c_i = rng.uniform(-0.5, 0.5, 2)
        ang = rng.uniform(0, 2 * math.pi)
        c_j = c_i + (R + rng.uniform(0.0, 3 * EPS)) * np.array([math.cos(ang), math.sin(ang)])
        ni, bi, slack_i = split_halfplanes(
            c_i, r_i, prio[0], [NeighbourInfo("j", c_j, r_j, priority=prio[1])], 0.8, EPS
        )
        nj, bj, slack_j = split_halfplanes(
            c_j, r_j, prio[1], [NeighbourInfo("i", c_i, r_i, priority=prio[0])], 0.8, EPS
        )
        assert slack_i == pytest.approx(slack_j) and slack_i >= -1e-12
        # Stay put satisfies every row exactly (recursive feasibility).
        assert all(n @ c_i >= b for n, b in zip(ni, bi, strict=True))
        assert all(n @ c_j >= b for n, b in zip(nj, bj, strict=True))
        yi = _sample_in_rows(rng, c_i, ni, bi, EPS)
        yj = _sample_in_rows(rng, c_j, nj, bj, EPS)
        if len(yi) and len(yj):
            d = np.linalg.norm(yi[:, None, :] - yj[None, :, :], axis=2)
            assert d.min() >= R - 1e-12
            checked += 1
    assert checked > 250


def test_shares_are_complementary():
    for a in range(-2, 3):
        for b in range(-2, 3):
            assert shares(a, b, 0.8) + shares(b, a, 0.8) == pytest.approx(1.0)
    assert shares(2, 1, 0.8) == 0.8 and shares(1, 1, 0.8) == 0.5


def test_rows_are_omitted_only_when_the_eps_box_implies_them():
    c_i = np.zeros(2)
    far = NeighbourInfo("j", np.array([1.0, 0.0]), 0.134)
    normals, _, _ = split_halfplanes(c_i, 0.134, 0, [far], 0.8, EPS)
    assert normals == []
    near = NeighbourInfo("j", np.array([0.268 + 0.002, 0.0]), 0.134)
    normals, bounds, _ = split_halfplanes(c_i, 0.134, 0, [near], 0.8, EPS)
    assert len(normals) == 1 and bounds[0] == pytest.approx(-0.5 * 0.002)


def test_obstacle_rows_keep_the_footprint_off_the_obstacle():
    ob = Circle(center=(0.0, 0.0), radius=0.2)
    rng = np.random.default_rng(3)
    r = 0.134
    for _ in range(200):
        ang = rng.uniform(0, 2 * math.pi)
        c = (0.2 + r + rng.uniform(0, 2 * EPS)) * np.array([math.cos(ang), math.sin(ang)])
        normals, bounds = obstacle_halfplanes(c, r, [ob], EPS)
        for y in _sample_in_rows(rng, c, normals, bounds, EPS):
            assert ob.distance(y) >= r - 1e-12


def test_grid_discs_match_brute_force_and_paths_avoid_walls():
    g = GridPlanner((-1, 1, -1, 1), 0.134, [Circle(center=(0.0, 0.0), radius=0.3)])
    rng = np.random.default_rng(0)
    pts = [rng.uniform(-1, 1, 2) for _ in range(12)]
    radii = list(rng.uniform(0.1, 0.3, 12))
    extras = list(rng.uniform(1, 10, 12))
    cost = g.static.copy()
    g.add_discs(cost, pts, radii, extras)
    d2 = ((g.centres[:, None, :] - np.array(pts)[None]) ** 2).sum(axis=2)
    assert np.allclose(cost, g.static + (d2 < np.square(radii)).astype(float) @ np.array(extras))
    # A path across the obstacle goes around it and never through blocked cells.
    start, goal = np.array([-0.7, 0.0]), np.array([0.7, 0.0])
    pred = g.field(goal, g.static)
    c, visited = g.cell(start), 0
    while c != g.cell(goal) and visited < 2000:
        c = int(pred[c])
        assert g.static[c] < GridPlanner.BLOCKED
        visited += 1
    assert c == g.cell(goal)


def test_lower_robot_in_the_corridor_yields_and_parked_robots_yield_to_all():
    nav = Navigator(footprint=0.134, arena=(-1, 1, -1, 1), rank=5)
    me = np.array([0.0, 0.0])
    goal = np.array([0.0, 0.8])
    first = NeighbourInfo("a", np.array([-0.35, 0.0]), 0.134, rank=0, target=np.array([0.3, 0.0]))
    tgt, mode = nav.target(me, goal, [first])
    assert mode == "yield" and nav.no_room == ""  # room to make way, in open space
    # The escape point is out of the corridor of the robot that goes first.
    assert abs(tgt[1]) > 0.134 * 2
    # A robot that goes after this one is not yielded to.
    nav2 = Navigator(footprint=0.134, arena=(-1, 1, -1, 1), rank=0)
    later = NeighbourInfo("b", np.array([-0.35, 0.0]), 0.134, rank=5, target=np.array([0.3, 0.0]))
    assert nav2.target(me, goal, [later])[1] != "yield"
    # A parked robot yields even to a lower-ranked robot under way.
    nav3 = Navigator(footprint=0.134, arena=(-1, 1, -1, 1), rank=0)
    nav3.phase = PARKED
    mover = NeighbourInfo(
        "c", np.array([-0.35, 0.0]), 0.134, rank=9, phase=UNDER_WAY, target=np.array([0.3, 0.0])
    )
    assert nav3.target(me, me, [mover])[1] == "yield"


def test_the_yield_range_holds_every_corridor_of_a_robot_on_its_way():
    """The range within which a robot that goes first is yielded to is derived, not chosen: a
    robot on its way steers to a carrot at most the lookahead from it along its path (so no
    farther in a straight line, whatever the path's turns and the obstacles), and its corridor
    reaches r_i + r_j + LOOKAHEAD + CORRIDOR_MARGIN from it.  A robot anywhere in that
    corridor, up to its far rim, makes way; one just outside the corridor does not.  A range
    any shorter misses the far rim."""
    fp = 0.134
    w = 2 * fp + CORRIDOR_MARGIN
    arena = (-3.0, 3.0, -3.0, 3.0)
    obstacles = [Circle(center=(0.9, 0.4), radius=0.3), Circle(center=(-1.0, -0.8), radius=0.4)]
    rng = np.random.default_rng(7)
    furthest = 0.0
    for k in range(40):
        q = rng.uniform(-2.0, 2.0, 2)
        goal = rng.uniform(-2.5, 2.5, 2)
        if min(np.hypot(*(q - o.center)) for o in obstacles) < 0.6 or np.hypot(*(goal - q)) < 0.5:
            continue
        ahead = Navigator(footprint=fp, arena=arena, obstacles=obstacles, rank=0)
        target = ahead.waypoint(q, goal)
        reach = float(np.hypot(*(target - q)))
        assert reach <= LOOKAHEAD + 1e-9, (k, reach)
        furthest = max(furthest, reach)
        first = NeighbourInfo("a", q, fp, rank=0, target=target, phase=UNDER_WAY)
        u = (target - q) / reach
        far_rim = q + (reach + w - 1e-3) * u  # inside the corridor, as far from q as it goes
        side = q + 0.5 * reach * u + (w + 1e-3) * np.array([-u[1], u[0]])  # just outside it
        for c, inside in ((far_rim, True), (side, False)):
            assert (point_segment_distance(c, q, target) < w) == inside
            nav = Navigator(footprint=fp, arena=arena, rank=5)
            assert (nav.target(c, c - 0.5 * u, [first])[1] == "yield") == inside, (k, inside)
    assert furthest > LOOKAHEAD - 0.01  # the carrots reached the lookahead: the far rim was tested


def test_the_carrot_stays_within_the_lookahead_near_the_goal():
    """The derived yield range assumes every carrot lies within the lookahead.  Near the goal
    the path ends at the goal's cell and the goal lies up to half a cell beyond it: a goal a
    little beyond the lookahead gets the point the lookahead along the last hop, not the goal
    itself (which lay up to 0.32 m away)."""
    rng = np.random.default_rng(1)
    farthest = 0.0
    for _ in range(600):
        nav = Navigator(footprint=0.134, arena=(-2.0, 2.0, -2.0, 2.0), rank=0)
        q = rng.uniform(-1.0, 1.0, 2)
        angle = rng.uniform(0.0, 2.0 * math.pi)
        goal = q + rng.uniform(0.28, 0.36) * np.array([math.cos(angle), math.sin(angle)])
        reach = float(np.hypot(*(nav.waypoint(q, goal) - q)))
        assert reach <= LOOKAHEAD + 1e-9, (q, goal, reach)
        farthest = max(farthest, reach)
    assert farthest > LOOKAHEAD - 1e-3  # goals beyond the lookahead were met


def test_the_yield_range_follows_the_lookahead_it_is_derived_from():
    """A navigator built with a longer lookahead yields over the longer range its corridors
    reach (lookahead + margin beyond r_i + r_j), not over the default's; the view caps it."""
    fp, look = 0.134, 0.5
    w = 2 * fp + CORRIDOR_MARGIN
    q, target = np.array([0.0, 0.0]), np.array([look, 0.0])
    first = NeighbourInfo("a", q, fp, rank=0, target=target, phase=UNDER_WAY)
    c = np.array([look + w - 1e-3, 0.0])  # the corridor's far rim, beyond the default range
    assert float(np.hypot(*(c - q))) > 2 * fp + LOOKAHEAD + CORRIDOR_MARGIN
    nav = Navigator(footprint=fp, arena=(-2.0, 2.0, -2.0, 2.0), rank=5, lookahead=look)
    assert nav.conflict_range == pytest.approx(look + CORRIDOR_MARGIN)
    assert nav.target(c, c + np.array([0.5, 0.0]), [first])[1] == "yield"
    capped = Navigator(footprint=fp, arena=(-2.0, 2.0, -2.0, 2.0), rank=5, lookahead=look, view=0.4)
    assert capped.conflict_range == pytest.approx(0.4)
    assert capped.target(c, c + np.array([0.5, 0.0]), [first])[1] != "yield"


def test_a_robot_displaced_by_a_returning_one_keeps_yielding_to_it_until_it_has_parked():
    """The cycle that stalled goals packed around obstacles: a parked robot a (rank 0) steps
    aside for a returning robot b (rank 5), becomes returning itself, and used to outrank b
    by rank, so b yielded back, a parked again in b's way, and so on for ever.  Among
    returning robots the one displaced first goes first (``precedence``): a, returning for
    fewer steps than b, keeps yielding to b, and b does not yield to a."""
    arena = (-1.0, 1.0, -1.0, 1.0)
    a_goal, b_goal = np.array([0.0, 0.0]), np.array([0.0, 0.9])
    # b returns along y = 0 from the left, towards the carrot at (0.3, 0): a's goal is in its corridor.
    b = NeighbourInfo("b", np.array([-0.35, 0.0]), 0.134, rank=5, target=np.array([0.3, 0.0]),
                      goal=b_goal, phase=RETURNING, phase_age=40)  # fmt: skip
    nav_a = Navigator(footprint=0.134, arena=arena, rank=0)
    nav_a.phase = PARKED
    assert nav_a.target(a_goal, a_goal, [b])[1] == "yield"
    # Displaced 6 cm, a is returning now, for fewer steps than b: it still yields to b.
    here = np.array([0.0, -0.06])
    nav_a.phase, nav_a.phase_age = RETURNING, 3
    assert nav_a.target(here, a_goal, [b])[1] == "yield"
    # b, in a's corridor (a heads back to its goal through b's path), does not yield to a.
    nav_b = Navigator(footprint=0.134, arena=arena, rank=5)
    nav_b.phase, nav_b.phase_age = RETURNING, 40
    a = NeighbourInfo("a", here, 0.134, rank=0, target=np.array([-0.4, 0.0]), goal=a_goal,
                      phase=RETURNING, phase_age=3)  # fmt: skip
    assert nav_b.target(np.array([-0.35, 0.0]), b_goal, [a])[1] != "yield"
    # Had a been displaced first, it would go first, and b would yield to it.
    a_first = NeighbourInfo(**{**a.__dict__, "phase_age": 41})
    assert nav_b.target(np.array([-0.35, 0.0]), b_goal, [a_first])[1] == "yield"


def test_a_parked_robot_holds_its_goal_against_one_returning_to_a_goal_whose_corridor_end_reaches_it():
    """Close goals: the cycle that kept two robots of the shipped 32-robot swap from parking.
    Their goals are on a ring 0.304 m apart, R + 7.7 cm with the compact footprint.  Parked a
    few centimetres off its goal towards b's, a was inside the end of the corridor of b, which
    was returning to its own goal; a yielded, became the returning one, displaced b in turn, and
    the two traded places for the whole run.  A parked robot is anywhere within PARKED_RADIUS
    of its goal and a corridor ends R + corridor_margin about the returning robot's goal, so up
    to R + corridor_margin + PARKED_RADIUS between goals the parked robot holds its goal, and
    b plans around it; farther, nothing changes."""
    r = 0.1135
    R = 2 * r
    a_goal = np.array([0.0, 0.0])
    u = np.array([1.0, 0.0])
    for gap in (0.077, CORRIDOR_MARGIN + PARKED_RADIUS - 0.001):
        b_goal = a_goal + (R + gap) * u
        a_at = a_goal + (PARKED_RADIUS - 0.0005) * u  # still parked, nearest b's goal
        # b returns to its goal from beyond it, its corridor ending at the goal.
        b = NeighbourInfo("b", b_goal + 0.2 * u, r, rank=0, target=b_goal, goal=b_goal, phase=RETURNING,
                          phase_age=40)  # fmt: skip
        nav_a = Navigator(footprint=r, arena=(-1.0, 1.0, -1.0, 1.0), rank=5)
        nav_a.phase, nav_a.phase_age = PARKED, 100
        assert np.linalg.norm(a_at - b_goal) < R + nav_a.corridor_margin  # a is in the corridor's end
        assert nav_a.target(a_at, a_goal, [b])[1] != "yield", gap
    # A pair of goals farther apart: a parked robot in the corridor yields, as before.
    b_goal = a_goal + (R + CORRIDOR_MARGIN + PARKED_RADIUS + 0.001) * u
    b = NeighbourInfo(
        "b", a_goal - 0.3 * u, r, rank=0, target=b_goal, goal=b_goal, phase=RETURNING, phase_age=40
    )
    nav_a = Navigator(footprint=r, arena=(-1.0, 1.0, -1.0, 1.0), rank=5)
    nav_a.phase, nav_a.phase_age = PARKED, 100
    assert nav_a.target(a_goal, a_goal, [b])[1] == "yield"


def test_the_close_goals_rule_lapses_for_a_robot_that_has_waited_its_patience():
    """A goal enclosed by parked robots at close goals (the interior of a grid of goals spaced
    barely over R) is reachable only if one of them steps aside: a robot displaced from it once
    (it yielded to one that went first) waited for ever, every neighbour holding its own goal
    under the close-goals rule.  The rule therefore holds only while the returning robot has
    been returning for less than the navigator's patience; from then on the parked robot in its
    corridor yields to it, as to any robot that goes first."""
    r = 0.1135
    R = 2 * r
    a_goal, u = np.array([0.0, 0.0]), np.array([1.0, 0.0])
    b_goal = a_goal + (R + 0.0105) * u  # the grid scene's spacing: R + 1 cm
    a_at = a_goal + (PARKED_RADIUS - 0.0005) * u
    patience = Navigator(footprint=r, arena=(-1.0, 1.0, -1.0, 1.0)).close_goals_patience
    for age, yields in ((0, False), (patience - 1, False), (patience, True), (MAX_AGE, True)):
        b = NeighbourInfo("b", b_goal + 0.2 * u, r, rank=0, target=b_goal, goal=b_goal, phase=RETURNING,
                          phase_age=age)  # fmt: skip
        nav_a = Navigator(footprint=r, arena=(-1.0, 1.0, -1.0, 1.0), rank=5)
        nav_a.phase, nav_a.phase_age = PARKED, 100
        assert (nav_a.target(a_at, a_goal, [b])[1] == "yield") is yields, age
    assert 0 < patience < MAX_AGE  # an age the plans can carry


def test_the_phase_age_counts_the_steps_in_a_phase_and_starts_again_when_displaced():
    """What the plan says of the age (``TubeMPC.phase_age`` → ``Plan.phase_age``): steps in the
    current phase, counted after each step, 0 at the step the phase changes."""
    from agent.controller import TubeMPC
    from agent.protocol import plan_message
    from agent.tube import require_admissible, synthesize
    from ground.params import preset

    arena = (-1.0, 1.0, -1.0, 1.0)
    design = require_admissible(synthesize(preset("epuck"), arena))
    home = np.array([0.0, 0.0])
    ctrl = TubeMPC(design, home, home, arena)
    x = np.zeros(4)
    for k in range(5):
        out = ctrl.step(x, [])
        assert (ctrl.phase, ctrl.phase_age) == (PARKED, k)
    assert plan_message("r1", 4, ctrl, out).phase_age == 4
    # Pushed 0.2 m off its goal: returning, from 0 again.
    away = np.array([0.2, 0.0])
    ctrl.reset(away, design.E @ away)
    x = design.E @ away
    for k in range(3):
        ctrl.step(x, [])
        assert (ctrl.phase, ctrl.phase_age) == (RETURNING, k)


# ------------------------------------------------------------------ the repair of ȳ
def _scaled(y, c, normals, bounds):
    """The step scaled towards c until every violated row holds: the fallback of the repair."""
    lam = 1.0
    for n, b in zip(normals, bounds, strict=True):
        if n @ y < b and n @ c > n @ y:
            lam = min(lam, max(0.0, (n @ c - b) / (n @ c - n @ y)))
    return c + lam * (y - c)


def test_the_repair_meets_every_row_exactly_and_moves_the_step_no_more_than_scaling():
    """Rows c_i meets, a solver's ȳ up to 1e-5 outside some of them: the repaired ȳ meets every
    row exactly and stays in its box; it is never farther from the solver's ȳ than the scaled
    step, and in all but a few cases it is within twice the violation of it."""
    rng = np.random.default_rng(5)
    near = 0
    for _ in range(2000):
        c = rng.uniform(-0.5, 0.5, 2)
        m = int(rng.integers(1, 5))
        normals = rng.normal(size=(m, 2))
        normals /= np.linalg.norm(normals, axis=1)[:, None]
        y0 = c + rng.uniform(-EPS, EPS, 2)
        # Each row binding at y0 or near it, met by c, and y0 up to 1e-5 outside it.
        bounds = np.minimum(normals @ y0 + rng.uniform(-2e-5, 1e-5, m), normals @ c)
        lo, hi = c - EPS, c + EPS
        y, scaled = repair_point(y0, c, normals, bounds, lo, hi)
        assert not scaled  # the polygon holds c_i: its projection is always found
        assert np.all(normals @ y >= bounds), normals @ y - bounds
        assert np.all(lo <= y) and np.all(y <= hi)
        moved = np.linalg.norm(y - y0)
        assert moved <= np.linalg.norm(_scaled(y0, c, normals, bounds) - y0) + 1e-12
        near += moved <= 2 * max(0.0, float(np.max(bounds - normals @ y0))) + 1e-9
    assert near >= 1900, near


def test_a_robot_sliding_along_a_binding_row_keeps_its_step():
    """c_i on a row (a wall or a neighbour's split), the step along it and rounding a hair
    outside: the repair keeps the step.  Scaling it, as the repair once did, stops the robot."""
    c = np.array([0.2, 0.1])
    normals, bounds = np.array([[0.0, 1.0]]), np.array([0.1])
    y0 = c + np.array([EPS, -1e-9])
    y, scaled = repair_point(y0, c, normals, bounds, c - EPS, c + EPS)
    assert not scaled and normals[0] @ y >= bounds[0]
    assert y[0] - c[0] >= 0.999 * EPS
    assert np.allclose(_scaled(y0, c, normals, bounds), c)  # what scaling did: no step at all


def test_the_row_of_a_disc_that_comes_on_is_met_by_backing_away():
    """A row c_i fails (a loose robot's disc, its edge come on by a step): the repair takes ȳ
    onto it, away from c_i, where scaling towards c_i would have undone the backing away."""
    c = np.array([0.0, 0.0])
    normals, bounds = np.array([[1.0, 0.0]]), np.array([0.004])
    y0 = np.array([0.004 - 1e-7, 0.001])
    y, scaled = repair_point(y0, c, normals, bounds, c - EPS, c + EPS)
    assert not scaled and y[0] >= 0.004 and abs(y[1] - 0.001) < 1e-12


def test_robots_seen_beyond_the_neighbours_shape_the_target_and_add_no_constraint():
    """``TubeMPC.step(seen=...)``: a robot the agent sees but does not coordinate with (plans
    by place, two cells away) makes the navigator yield, as a neighbour would, and adds no
    row: the QP's constraints, and so the guarantee, are those of the neighbours alone."""
    from agent.controller import TubeMPC
    from agent.tube import require_admissible, synthesize
    from ground.params import preset

    arena = (-1.0, 1.0, -1.0, 1.0)
    design = require_admissible(synthesize(preset("epuck"), arena))
    me, goal = np.array([0.0, -0.5]), np.array([0.0, 0.8])
    # Under way before this robot (rank 0), 0.5 m ahead on its line, heading through it.
    first = NeighbourInfo(
        "r0", np.array([0.0, 0.0]), design.footprint, rank=0, target=np.array([0.0, -0.9]),
        goal=np.array([0.0, -0.9]), phase=UNDER_WAY,
    )  # fmt: skip
    alone, seeing = (
        TubeMPC(design, me, goal, arena, rank=5).step(np.zeros(4), [], seen=s) for s in ([], [first])
    )
    assert alone.mode in ("path", "goal") and seeing.mode == "yield", (alone.mode, seeing.mode)
    assert abs(seeing.target[0]) > 0.1  # out of the corridor, to one side
    # No split row against it: the smallest slack the rows saw is that of no neighbour at all.
    assert alone.status == seeing.status and alone.min_slack == seeing.min_slack == math.inf


def test_a_parked_robot_with_nowhere_to_stand_aside_keeps_to_its_goal():
    """In a cell walled in on every side, a hair wider than the footprint, no point around a
    robot is free.  Asked to make way, a parked robot standing 2 cm off its goal steers back to
    its goal (where, goals being two footprints and a margin apart, it blocks nobody's); a robot
    under way stays where it is."""
    from ground.scenario import parse_scenario

    g, half = np.array([0.0, 0.0]), 0.15
    box = [  # four walls about a square of side 2·half around g
        [[-0.6, half], [0.6, half], [0.6, 0.6], [-0.6, 0.6]],
        [[-0.6, -0.6], [0.6, -0.6], [0.6, -half], [-0.6, -half]],
        [[-0.6, -half], [-half, -half], [-half, half], [-0.6, half]],
        [[half, -half], [0.6, -half], [0.6, half], [half, half]],
    ]
    scn = parse_scenario(
        {
            "name": "walled_cell", "duration": 10.0, "arena": {"bounds": [-1.0, 1.0, -1.0, 1.0]},
            "obstacles": [{"polygon": p} for p in box],
            "robots": [{"id": "r1", "start": [-0.8, -0.8, 0.0], "goal": [-0.8, 0.8]}],
        }
    )  # fmt: skip
    fp = 0.13405
    c = g + np.array([0.02, 0.0])
    first = NeighbourInfo(
        "r0", np.array([0.0, 0.45]), fp, rank=0, target=np.array([0.0, -0.45]), goal=np.array([0.0, -0.45]),
        phase=UNDER_WAY,
    )  # fmt: skip
    targets = {}
    for phase in (PARKED, UNDER_WAY):
        nav = Navigator(footprint=fp, arena=scn.arena, obstacles=scn.obstacles, rank=1)
        nav.phase = phase
        assert not nav._standable(c + nav._ring * 0.4).any()  # nowhere to stand aside
        targets[phase] = nav.target(c, g, [first])
        assert nav.no_room == "r0"  # assumption (A) fails here, and the navigator says so
    assert targets[PARKED][1] == targets[UNDER_WAY][1] == "yield"
    assert np.allclose(targets[PARKED][0], g) and np.allclose(targets[UNDER_WAY][0], c)
