"""The discs of robots off their plans for good (docs/method.md §6.4): bounded, static, and true.

A neighbour whose agent is gone, whose robot side braked it or whose agent holds blind is kept
clear of as a disc that never grows once it is first seen off its plans, and that shrinks to a
disc about a camera pose of it once its robot is known to stand still.  These tests feed
:class:`agent.hazards.Guard` histories of their own making and check the bound against what
they fed it; the brake's bound is checked against the plants the robots are simulated with.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from agent.hazards import Guard, starts_of
from agent.tube import synthesize
from epuck_link.unicycle import DoubleIntegratorPlant
from ground.model import brake_input, double_integrator, stopping
from ground.scenario import load_scenario
from ground.wire import BLIND, Plan
from tracker.world import make_plant

SCENARIOS = Path(__file__).resolve().parents[2] / "scenarios"


@pytest.fixture(scope="module")
def design():
    scn = load_scenario(SCENARIOS / "paper_three_robots.toml")
    return synthesize(scn.controller, scn.arena)


def _plan(
    robot: str, step: int, end: tuple[float, float], footprint: float, status: str = "PROXQP_SOLVED"
) -> Plan:
    committed = np.tile(np.array(end, dtype=float), (20, 1))
    return Plan(
        robot=robot, step=step, t0=0.1 * (step + 1), Ts=0.1, committed=committed, nominal=np.zeros((21, 2)),
        footprint=footprint, priority=0, rank=1, phase=0, target=np.zeros(2), goal=np.zeros(2),
        status=status, solve_time=0.0, tube_ok=True,
    )  # fmt: skip


def _guard(design) -> tuple[Guard, dict]:
    scn = load_scenario(SCENARIOS / "paper_three_robots.toml")
    return Guard("r1", design.params, lambda _: None), starts_of(
        scn.robots, design.params.lookahead, design.footprint
    )


# ------------------------------------------------------------------ the brake
@pytest.mark.parametrize("kind", ["double_integrator", "unicycle"])
def test_the_brake_stops_a_robot_within_its_bound_and_it_stays(design, kind):
    """From any state with |v| ≤ v_max per axis, the brake (ground.model.brake_input) brings the
    simulated robot to rest within ``stopping``'s steps, its controlled point no farther than its
    distance; the bound is tight (reached within 1 % from v_max along a diagonal)."""
    p = design.params
    steps, dist = stopping(p.v_max, p.a_max, p.Ts)
    rng = np.random.default_rng(4)
    worst = 0.0
    for trial in range(60):
        heading = rng.uniform(-math.pi, math.pi)
        v = rng.uniform(-p.v_max, p.v_max, 2) if trial else np.array([p.v_max, p.v_max])
        plant = make_plant(kind, np.array([0.0, 0.0, heading]), p)
        # Drive it up to the velocity v (at most a_max per axis, as a plan would).
        for _ in range(40):
            q = plant.state()[[1, 3]]
            if np.allclose(q, v, atol=1e-12):
                break
            plant.step(np.clip((v - q) / p.Ts, -p.a_max, p.a_max), p.Ts)
        q = plant.state()[[1, 3]]
        assert np.all(np.abs(q) <= p.v_max + 1e-9)
        start = plant.state()[[0, 2]].copy()
        for _ in range(steps):
            plant.step(brake_input(plant.state()[[1, 3]], p.Ts, p.a_max), p.Ts)
        rest = plant.state()[[0, 2]].copy()
        assert np.abs(plant.state()[[1, 3]]).max() < 1e-9, (kind, trial)
        for _ in range(50):  # it stays
            plant.step(brake_input(plant.state()[[1, 3]], p.Ts, p.a_max), p.Ts)
        assert np.linalg.norm(plant.state()[[0, 2]] - rest) < 1e-9
        moved = float(np.linalg.norm(rest - start))
        assert moved <= dist + 1e-9, (kind, trial, moved, dist)
        worst = max(worst, moved)
    assert worst >= 0.99 * dist  # the corner case above reaches the bound


def test_stopping_follows_the_brake_step_by_step():
    """``stopping`` against the nominal model braked from v_max on both axes, for a few designs:
    the same steps to rest and the same distance (Euclidean over both axes)."""
    for v_max, a_max, Ts in ((0.075, 0.5, 0.1), (0.068, 0.5, 0.1), (0.1, 0.05, 0.1), (0.075, 2.0, 0.05)):
        steps, dist = stopping(v_max, a_max, Ts)
        A, B, _ = double_integrator(Ts)
        plant = DoubleIntegratorPlant(np.zeros(3), A, B)
        plant.x = np.array([0.0, v_max, 0.0, v_max])
        n = 0
        while np.abs(plant.x[[1, 3]]).max() > 1e-12:
            plant.x = A @ plant.x + B @ brake_input(plant.x[[1, 3]], Ts, a_max)
            n += 1
        assert n == steps, (v_max, a_max, Ts)
        assert math.hypot(plant.x[0], plant.x[2]) == pytest.approx(dist, rel=1e-9)
    with pytest.raises(ValueError):
        stopping(0.1, 0.0, 0.1)


# ------------------------------------------------------------------ the discs
class _Robot:
    """A robot j as the theory of docs/method.md §6.4 allows it to move, seeded: its agent appends
    a point ≤ ε per axis from the last each step while it plans; its true controlled point stays
    within ρ − ε of its reference (the tube) while it follows a plan, then within ``d_stop`` of
    where its brake began, standing still after the brake's steps; its camera sees it within η per
    axis.  ``plan_until``: the first step it makes no plan of; ``brake_at``: the first step its
    robot side brakes it over (or None); ``follow``: steps it follows its last candidate first."""

    def __init__(self, design, rng, plan_until: int, brake_at: int | None, length: int):
        p = design.params
        self.N, self.eps, self.rng = p.horizon, p.epsilon, rng
        self.steps_to_rest, self.d_stop = stopping(p.v_max, p.a_max, p.Ts)
        start = np.array([0.2, -0.1])
        appended = [start.copy()]  # appended[s + 1]: the point appended at step s (s = −1: start)
        for _ in range(length):
            appended.append(appended[-1] + rng.uniform(-self.eps, self.eps, 2))
        self.appended = appended
        self.plan_until, self.brake_at = plan_until, brake_at
        tube = design.rho - p.epsilon
        self.points, self.cams = [], []
        braked_from = None
        for t in range(length):
            s = min(t - self.N, plan_until - 1)  # the reference of sample t: appended at step t − N
            ref = appended[max(s, -1) + 1]  # (stay put once the plans stop)
            if brake_at is None or t <= brake_at:
                r = tube * math.sqrt(rng.random())
                a = rng.uniform(0, 2 * math.pi)
                point = ref + r * np.array([math.cos(a), math.sin(a)])
                if brake_at is not None and t == brake_at:
                    braked_from = point
                    u = rng.normal(size=2)
                    direction = u / np.linalg.norm(u)
            else:
                frac = min((t - brake_at) / self.steps_to_rest, 1.0)
                point = braked_from + direction * self.d_stop * frac
            self.points.append(point)
            self.cams.append(point + rng.uniform(-1, 1, 2) * p.point_noise / math.sqrt(2.0) * 0.999)

    def plan(self, step: int, footprint: float) -> Plan:
        """Its plan of ``step``: ends at the point appended at that step."""
        return _plan("r2", step, tuple(self.appended[step + 1]), footprint)


def test_an_off_plan_neighbours_disc_holds_its_body_and_never_exceeds_its_bound(design):
    """Random histories, seeded, with robots that move as the theory allows (:class:`_Robot`):
    plans lost, the agent dead (seen so a few steps late) or hung with its robot side braking
    it, after following its candidate for a while; the brake reports sometimes lost; camera poses
    late or missing.  From the step the guard first keeps clear of the robot as dead or braked:
    the disc holds its true body (robot_radius + ℓ about its controlled point) at every sample,
    never grows, and lies within r_j + max(N, m₀ + 1)·√2·ε + d_stop of the end of the newest
    plan heard (m₀: the steps missed by then); once the robot side has braked it for the brake's
    steps to rest + 1 in a row and a camera pose from then is in, it is the rest disc, radius
    r_j + 2·√2·η + √2·ε about that pose, taken once.  Runs of up to 20 000 steps."""
    p = design.params
    eps = math.sqrt(2.0) * p.epsilon
    steps_to_rest, d_stop = stopping(p.v_max, p.a_max, p.Ts)
    rest_radius = design.footprint + 2.0 * math.sqrt(2.0) * p.point_noise + eps
    body = p.robot_radius + p.lookahead
    rng = np.random.default_rng(7)
    rests = 0
    for trial in range(60):
        g, starts = _guard(design)
        starts["r2"].last_point = np.array([0.2, -0.1])
        length = 20_000 if trial < 2 else int(rng.integers(80, 800))
        death = int(rng.integers(5, 40))
        dead = rng.random() < 0.6  # else hung: alive, silent, its robot side brakes it
        brake_at = death + int(rng.integers(0, p.horizon)) if (not dead or rng.random() < 0.85) else None
        robot = _Robot(design, rng, death, brake_at, length)
        notice_lag = int(rng.integers(0, 6))
        loss = rng.uniform(0.0, 0.5)
        report_loss = 0.15 if (dead and rng.random() < 0.5) else 0.0
        last: dict[str, Plan | None] = {"r2": None}
        seen = radius_then = rest_taken = None
        for k in range(1, length):
            fresh = None
            if k - 1 < death and rng.random() >= loss:
                fresh = robot.plan(k - 1, design.footprint)
                last["r2"] = fresh
            live = set() if dead and k >= death + notice_lag else {"r2"}
            braked = brake_at is not None and k - 1 >= brake_at
            reported = {"r2"} if braked and rng.random() >= report_loss else set()
            t_cam = k - int(rng.integers(0, 2))
            poses = {"r2": (t_cam, robot.cams[t_cam])} if rng.random() < 0.8 else {}
            _, hz = g.classify(k, ["r2"], {"r2": fresh}, last, live, starts, reported, poses=poses)
            h = hz[0] if hz else None
            if h is None or h.kind not in ("dead", "braked"):
                assert seen is None or h is None or h.kind == "stale", (trial, k, h)
                continue
            if seen is None:
                seen = k
                heard = last["r2"]
                m0 = max(seen - 1 - (-1 if heard is None else heard.step), 0)
                bound = design.footprint + max(p.horizon, m0 + 1) * eps + d_stop
            reach = float(np.linalg.norm(robot.points[k] - h.centre)) + body
            assert reach <= h.radius + 1e-12, (trial, k, reach, h.radius, h.rest)  # it holds the body
            if h.rest:
                assert h.radius == pytest.approx(rest_radius)
                rests += rest_taken is None
            if report_loss:
                # A lost report of its brake makes the disc grow as for a robot driven again (it
                # may be, for all this agent knows), until the reports start a new run: only
                # loosened, so checked for holding the body alone.
                continue
            assert h.radius <= bound + 1e-12, (trial, k, h.radius, bound)
            if radius_then is not None:
                assert h.radius <= radius_then + 1e-12, (trial, k)  # never grows
            radius_then = h.radius
            if h.rest:
                if rest_taken is None:
                    rest_taken = h.centre.copy()
                    assert brake_at is not None and k >= brake_at + steps_to_rest + 1  # (its pose: no sooner)
                assert np.array_equal(h.centre, rest_taken)  # taken once, then fixed
        assert seen is not None, trial
    assert rests >= 20  # most histories found the rest


def test_the_rest_disc_waits_for_the_brake_and_a_pose_after_it(design):
    """The rest disc needs the robot side's reports that it braked the robot for the brake's
    steps to rest + 1 in a row, and a camera pose taken from then on: an older pose, or one
    before the run is long enough, leaves the frozen disc.  A report that the robot was not braked
    over a step means its agent may drive it again (dead in this agent's view or not: a restart's
    token may be late, or the report lost): from then on the rest disc grows by √2·ε a step.  A
    step this agent did not classify ends the episode: what the robot did meanwhile is unknown."""
    p = design.params
    S = stopping(p.v_max, p.a_max, p.Ts)[0] + 1
    eps = math.sqrt(2.0) * p.epsilon
    old = _plan("r2", 9, (0.3, 0.2), design.footprint)
    last = {"r2": old}
    at = np.array([0.41, 0.25])

    def braked_until_rest(g, starts, live):
        for k in range(10, 10 + S + 1):  # braked over steps 9, 10, ...: at rest from sample 9 + S
            _, hz = g.classify(k, ["r2"], {"r2": None}, last, live, starts, {"r2"}, poses={"r2": (k - 2, at)})
            assert not hz[0].rest, k  # the poses lag: none from sample 9 + S yet
        k = 10 + S + 1
        _, hz = g.classify(k, ["r2"], {"r2": None}, last, live, starts, {"r2"}, poses={"r2": (9 + S, at)})
        assert hz[0].rest and np.array_equal(hz[0].centre, at) and "r2" not in g.watched
        return k, hz[0]

    for live in ({"r2"}, set()):
        g, starts = _guard(design)
        k, rest = braked_until_rest(g, starts, live)
        assert rest.kind == ("braked" if live else "dead")
        for n in range(1, 4):  # reported not braked from step k + 1 on: it may move
            _, hz = g.classify(k + n, ["r2"], {"r2": None}, last, live, starts, set())
            assert np.array_equal(hz[0].centre, at) and not hz[0].rest
            assert hz[0].radius == pytest.approx(rest.radius + n * eps), (live, n)
    # A step not classified (this agent fell behind): the episode starts anew, frozen.
    g, starts = _guard(design)
    k, _ = braked_until_rest(g, starts, {"r2"})
    _, hz = g.classify(k + 3, ["r2"], {"r2": None}, last, {"r2"}, starts, {"r2"}, poses={"r2": (k + 2, at)})
    assert not hz[0].rest and np.array_equal(hz[0].centre, [0.3, 0.2])


def test_an_agent_back_from_its_rest_is_kept_clear_of_by_its_rest_disc_grown(design):
    """A robot at rest whose agent comes back (alive, its robot not braked) with no plan heard yet:
    its first plan starts where it stands, inside its rest disc, and its points move √2·ε a step
    from there, so the disc kept is the rest disc grown by that, not the stale disc about a plan
    made long before it stopped.  Its own plan, of the step before it came back or later, ends
    the episode; an older plan of it does not.  Without a rest disc (its robot side never said it
    braked it), the frozen disc grown by ρ_j − ε + √2·η + √2·ε, since the frozen disc is only
    known to hold its body, not where a restart puts its reference."""
    p = design.params
    eps = math.sqrt(2.0) * p.epsilon
    g, starts = _guard(design)
    old = _plan("r2", 9, (0.3, 0.2), design.footprint)
    last = {"r2": old}
    at = np.array([0.41, 0.25])
    for k in range(10, 200):
        _, hz = g.classify(k, ["r2"], {"r2": None}, last, set(), starts, {"r2"}, poses={"r2": (k - 1, at)})
    rest = hz[0]
    assert rest.rest
    for n in range(4):
        _, hz = g.classify(200 + n, ["r2"], {"r2": None}, last, {"r2"}, starts, set())
        assert hz[0].kind == "stale" and np.array_equal(hz[0].centre, at)
        assert hz[0].radius == pytest.approx(rest.radius + (n + 1) * eps)
    new = _plan("r2", 199, (0.42, 0.25), design.footprint)  # made a step ahead, before it was back
    _, hz = g.classify(204, ["r2"], {"r2": None}, {"r2": new}, {"r2"}, starts, set())
    assert np.array_equal(hz[0].centre, [0.42, 0.25])  # its own plan's stale disc
    assert hz[0].radius == pytest.approx(design.footprint + 5 * eps)
    assert "r2" not in g._off
    # Dead, and its robot side never said it braked it: no rest disc; then its robot moves.
    g, starts = _guard(design)
    for k in range(10, 40):
        _, hz = g.classify(k, ["r2"], {"r2": None}, last, set(), starts, set())
    frozen = hz[0]
    assert not frozen.rest and frozen.kind == "dead"
    _, hz = g.classify(40, ["r2"], {"r2": None}, last, set(), starts, {"r2"})
    _, hz = g.classify(41, ["r2"], {"r2": None}, last, set(), starts, set())  # braked, then not
    rho = design.footprint - p.robot_radius - p.lookahead
    extra = rho - p.epsilon + math.sqrt(2) * p.point_noise + eps + 1 * eps
    assert np.array_equal(hz[0].centre, frozen.centre)
    assert hz[0].radius == pytest.approx(frozen.radius + extra)


def test_a_blind_neighbour_is_static_and_bounded(design):
    """A live agent that holds without poses (its plans say BLIND): a static disc about its held
    end point, r_j + N·√2·ε + d_stop, however long it holds; with no rest disc (its agent brakes
    it by commands made from a prediction, not its robot side)."""
    p = design.params
    d_stop = stopping(p.v_max, p.a_max, p.Ts)[1]
    g, starts = _guard(design)
    held = _plan("r2", 9, (0.3, 0.2), design.footprint)
    for k in range(10, 3000):
        blind = dataclasses.replace(held, step=k - 1, status=BLIND)
        _, hz = g.classify(
            k, ["r2"], {"r2": blind}, {"r2": blind}, {"r2"}, starts, poses={"r2": (k - 1, np.ones(2))}
        )
        assert hz[0].kind == "blind" and not hz[0].rest
        assert hz[0].radius == pytest.approx(design.footprint + p.horizon * math.sqrt(2) * p.epsilon + d_stop)


# ------------------------------------------------------------------ paths and covered goals
def _controller(design, start, goal):
    from agent.controller import TubeMPC

    return TubeMPC(design, np.array(start, float), np.array(goal, float), (-1.0, 1.0, -1.0, 1.0))


def test_a_goal_a_stopped_robot_covers_is_named_and_the_robot_parks_where_others_can_still_park(design):
    """A dead robot at rest 0.2 m from r1's goal covers it (0.2 < r_1 + its disc's radius): the
    step says so, r1 counts as parked (nobody waits on it), and it steers to a parking point clear
    of the disc by 1 cm, inside the walls, and as far from r3's goal as goals must be apart, so
    that r3 can still park at its own.  The constraint keeps every appended point out of the
    disc all the while; a goal clear of every disc is not blocked, and is steered to."""
    from agent.coordination import Hazard, NeighbourInfo
    from ground.scenario import GOAL_MARGIN
    from ground.wire import PARKED

    fp = design.footprint
    goal = np.array([0.3, 0.0])
    rest = Hazard("r2", np.array([0.5, 0.0]), fp + 0.001, None, "dead", True)
    natural = rest.centre + (goal - rest.centre) / 0.2 * (fp + rest.radius + 0.01)  # straight back
    r3 = NeighbourInfo("r3", np.array([-0.6, 0.6]), fp, goal=natural + np.array([0.0, 0.05]))
    ctrl = _controller(design, [-0.4, 0.0], goal)
    x = np.array([-0.4, 0.0, 0.0, 0.0])
    for _ in range(40):
        out = ctrl.step(x, [r3], [rest])
        x = np.array([ctrl.xi[0], 0.0, ctrl.xi[2], 0.0])
        assert np.linalg.norm(out.committed[-1] - rest.centre) >= fp + rest.radius - 1e-9
    assert out.blocked == "r2" and ctrl.phase == PARKED
    park = ctrl.parking
    assert park is not None
    assert np.linalg.norm(park - rest.centre) >= fp + rest.radius + 0.01 - 1e-9
    assert np.linalg.norm(park - r3.goal) >= 2 * fp + GOAL_MARGIN - 1e-9
    assert np.all(np.abs(park) <= 1.0 - fp)
    # The nearest such point, to the rings' 2 cm: against a brute-force search on a 5 mm grid.
    g = np.stack(np.meshgrid(np.arange(-0.86, 0.86, 0.005), np.arange(-0.86, 0.86, 0.005)), -1).reshape(-1, 2)
    ok = (np.linalg.norm(g - rest.centre, axis=1) >= fp + rest.radius + 0.01) & (
        np.linalg.norm(g - r3.goal, axis=1) >= 2 * fp + GOAL_MARGIN
    )
    nearest = np.linalg.norm(g[ok] - goal, axis=1).min()
    assert nearest <= np.linalg.norm(park - goal) <= nearest + 0.02 + 0.005
    assert np.array_equal(ctrl.target, park) or np.linalg.norm(ctrl.target - park) < 0.3
    # Far from the disc, the goal is clear: not blocked, the goal itself steered to (its path).
    free = _controller(design, [-0.4, 0.0], [-0.6, -0.3])
    out = free.step(np.array([-0.4, 0.0, 0.0, 0.0]), [r3], [rest])
    assert out.blocked == "" and free.parking is None and np.linalg.norm(free.target - free.goal) < 0.1


def test_paths_go_around_a_stopped_robot(design):
    """The grid path from one side of a stopped robot's disc to the other goes around it: no
    waypoint of it inside the disc's clearance (r_i + its radius)."""
    from agent.navigator import Navigator

    fp = design.footprint
    nav = Navigator(footprint=fp, arena=(-1.0, 1.0, -1.0, 1.0))
    centre, clearance = np.array([0.0, 0.0]), fp + fp + 0.001
    assert nav.set_discs([(centre, clearance)]) and not nav.set_discs([(centre, clearance)])
    c, goal = np.array([-0.6, 0.02]), np.array([0.6, 0.0])
    for _ in range(200):
        wp = nav.waypoint(c, goal)
        if np.linalg.norm(goal - c) < 0.05:
            break
        assert np.linalg.norm(wp - centre) >= clearance - nav._grid.h, wp  # (cells of h)
        c = c + 0.03 * (wp - c) / max(np.linalg.norm(wp - c), 1e-9)
    assert np.linalg.norm(goal - c) < 0.05


# ------------------------------------------------------------------ a robot driving on uncontrolled
def _crossing(design, drift: float) -> tuple[float, float]:
    """r1 drives from (0.5, 0) to (−0.6, 0) across the path of a robot whose link is down and
    which drives on down the y axis at ε/Ts·0.98, kept clear of as :meth:`Guard._loose` does: a
    disc about where it is now, grown by its step for every step to k + N + 1, its edge coming
    ``drift`` a step.  (The least margin of r1's appended points to the disc [m], the least
    distance of r1's committed point of each step to where the other robot is then [m].)"""
    from agent.coordination import Hazard

    p, fp = design.params, design.footprint
    N, step = p.horizon, 0.98 * p.epsilon
    ctrl = _controller(design, [0.5, 0.0], [-0.6, 0.0])
    x = np.array([0.5, 0.0, 0.0, 0.0])
    where = lambda k: np.array([0.0, 0.6 - step * k])  # noqa: E731  # the other robot at step k
    margin, apart = math.inf, math.inf
    ours: dict[int, np.ndarray] = {}
    for k in range(200):
        hz = Hazard("r2", where(k), fp + step * (N + 1), None, "loose", drift=drift)
        out = ctrl.step(x, [], [hz])
        x = design.A @ x + design.B @ out.a  # the nominal model: no disturbance
        margin = min(margin, float(np.linalg.norm(out.committed[-1] - hz.centre)) - fp - hz.radius)
        ours[k + N] = out.committed[-1]  # r1's reference at step k + N
        if k in ours:
            apart = min(apart, float(np.linalg.norm(ours[k] - where(k))))
    return margin, apart


def test_a_robot_driving_on_uncontrolled_is_kept_clear_of_in_full(design):
    """The row against a disc that comes on (``Hazard.drift``) keeps the margin met at the step
    before: r1 gets out of the other's way and its committed points stay ≥ r_1 + r_2 from where
    the other robot is at their steps.  With the row of a disc that stays put ("not closer"
    only), the same crossing wears the margin down a step at a time until they touch: the
    case the drift is for."""
    fp, eps = design.footprint, design.params.epsilon
    margin, apart = _crossing(design, 0.98 * eps)
    assert margin >= -0.98 * eps - 1e-9, margin
    assert apart >= 2 * fp - 1e-9, apart
    worn, touched = _crossing(design, 0.0)
    assert worn < -0.1 and touched < 2 * fp, (worn, touched)


def test_the_drift_rows_sliver_is_wider_than_the_solvers_tolerance(design):
    """A row against a disc that comes on asks at most DRIFT_SHARE of what the ε box allows: the
    sliver left is at least five times the solver's absolute tolerance, with the project's own
    settings and the shipped preset's ε."""
    from types import SimpleNamespace

    from agent.coordination import DRIFT_SHARE
    from agent.qp import configure

    s = SimpleNamespace()
    configure(s, design.params)
    assert (1.0 - DRIFT_SHARE) * design.params.epsilon >= 5 * s.eps_abs


def _head_on(design, informed: bool, share: float) -> float:
    """r1 stands parked at its goal at the origin; r2, whose link is down, drives on at it along
    the x axis at ``share``·ε/Ts, from 0.9 m away, as the link states say (a camera point a
    step).  r1 keeps clear of it as :meth:`Guard._loose` makes the disc; ``informed`` False takes
    away what the navigator is told of r2.  The least distance [m] of r1's committed point of
    each step to where r2 is then."""
    from ground.wire import LinkState

    p = design.params
    guard, starts = _guard(design)
    ctrl = _controller(design, [0.0, 0.0], [0.0, 0.0])
    x = np.zeros(4)
    step = share * p.epsilon
    where = lambda k: np.array([0.9 - step * k, 0.0])  # noqa: E731
    ours: dict[int, np.ndarray] = {}
    apart = math.inf
    for k in range(1, 260):
        at = where(k)
        ls = LinkState(
            robot="r2", up=False, step=k, lost=0, back=-1, left=500, right=500, speed=step / p.Ts,
            seq=k, x=float(at[0]), y=float(at[1]),
        )  # fmt: skip
        hz = guard._loose(k, "r2", ls, None, starts["r2"])
        if not informed:
            hz = dataclasses.replace(hz, info=None)
        out = ctrl.step(x, [], [hz])
        x = design.A @ x + design.B @ out.a
        ours[k + p.horizon] = out.committed[-1]  # r1's reference at step k + N
        if k in ours:
            apart = min(apart, float(np.linalg.norm(ours[k] - where(k))))
    return apart


@pytest.mark.parametrize("share", [0.9, 1.0, 1.2, "v_max"])
def test_a_robot_driving_on_faster_than_the_box_is_dodged_not_outrun(design, share):
    """A robot whose link is down drives on at its last wheel speeds, up to v_max, which is
    faster than any reference moves (ε/Ts per axis).  Straight at a parked robot, the disc's row
    alone only backs that robot away along the line, slower than the other comes, until the
    references are closer than r_1 + r_2 (the navigator not told of it).  Told where it heads
    (:meth:`Guard._velocity`: its sweep to the end of the horizon) and that it goes first, the
    navigator makes way sideways, out of its sweep, keeping to one side, and the two stay
    r_1 + r_2 apart at every speed up to v_max."""
    p, fp = design.params, design.footprint
    s = p.v_max * p.Ts / p.epsilon if share == "v_max" else float(share)
    assert _head_on(design, informed=True, share=s) >= 2 * fp - 1e-9
    if s > 1.1:
        assert _head_on(design, informed=False, share=s) < 2 * fp - 0.05


def test_where_a_robot_driving_on_heads_is_measured_from_its_camera_points(design):
    """The navigator is told that a robot driving on uncontrolled goes before every robot, and
    heads to where its last second of camera points carries it by the end of the horizon."""
    from agent.coordination import precedence
    from ground.wire import LinkState

    p = design.params
    guard, starts = _guard(design)
    v = np.array([0.03, -0.04])  # [m/s]
    for k in range(1, 30):
        at = np.array([0.2, 0.1]) + v * p.Ts * k
        ls = LinkState(
            robot="r2", up=False, step=k, lost=0, back=-1, left=300, right=300, speed=0.05, seq=k,
            x=float(at[0]), y=float(at[1]),
        )  # fmt: skip
        hz = guard._loose(k, "r2", ls, None, starts["r2"])
    info = hz.info
    assert info is not None and np.allclose(info.last_point, at)
    assert np.allclose(info.target, at + v * p.Ts * (p.horizon + 1), atol=1e-9)
    first = precedence(info.phase, info.phase_age, info.priority, info.rank)
    assert all(first < precedence(0, 0, s.priority, s.rank) for s in starts.values())


@pytest.mark.parametrize("eta", [0.00014, 0.001])
def test_the_heading_is_measured_over_the_fewest_steps_whose_noise_stays_within_a_step(design, eta):
    """:func:`trail_steps`: with camera points off by the worst the noise allows (η per axis,
    the oldest and the newest of the window off in opposite directions), the predicted end of
    the sweep is within ε of the true one over W steps, and not over W − 1."""
    from agent.hazards import trail_steps
    from ground.wire import LinkState

    p = dataclasses.replace(design.params, pose_noise=(eta, 0.0))
    W = trail_steps(p.point_noise, p.horizon, p.epsilon)
    v = np.array([0.04, 0.0])  # [m/s]

    def end_error(window: int) -> float:
        guard = Guard("r1", p, lambda _: None)
        guard.trail = window
        _, starts = _guard(design)
        for k in range(1, window + 2):
            true = v * p.Ts * k
            off = eta * np.array([1.0, 1.0]) * (1.0 if k == window + 1 else -1.0)
            at = true + off
            ls = LinkState(
                robot="r2", up=False, step=k, lost=0, back=-1, left=300, right=300, speed=0.04, seq=k,
                x=float(at[0]), y=float(at[1]),
            )  # fmt: skip
            hz = guard._loose(k, "r2", ls, None, starts["r2"])
        ahead = (p.horizon + 1) * p.Ts
        assert hz.info is not None
        return float(np.linalg.norm((hz.info.target - hz.info.last_point) - v * ahead))

    assert end_error(W) <= p.epsilon + 1e-12
    if W > 1:
        assert end_error(W - 1) > p.epsilon


@pytest.mark.parametrize("radius", [0.3, 0.55, 0.8])
def test_a_goal_under_a_stopped_robots_disc_of_any_width_gets_the_nearest_point_beside_it(design, radius):
    """A goal covered by a stopped robot's disc gives way to the nearest point clear of it by
    PARKING_CLEAR and a goal spacing from another goal (``Navigator.clear_goal``), however wide the
    disc: the rings the point is sought on reach round the disc and one goal's keep-out, where a
    fixed reach of 0.6 m found nothing beside a disc of radius 0.8 m and kept the goal itself."""
    from agent.navigator import PARKING_CLEAR, PARKING_STEP, Navigator

    fp = design.footprint
    nav = Navigator(footprint=fp, arena=(-2.0, 2.0, -2.0, 2.0))
    goal, centre = np.array([0.0, 0.0]), np.array([0.1, 0.0])
    nav.set_discs([(centre, radius)])
    other, apart = np.array([-(radius - 0.1) - 0.2, 0.0]), 2 * fp + 0.01  # a goal on the near side
    p = nav.clear_goal(goal, [(other, apart)])
    assert np.linalg.norm(p - centre) >= radius + PARKING_CLEAR - 1e-9
    assert np.linalg.norm(p - other) >= apart - 1e-9
    # The nearest such point, to the rings' step: none of the free points of a fine scan is
    # nearer by more than a ring and the angle between two points of a ring.
    ang = np.linspace(0, 2 * np.pi, 720, endpoint=False)
    best = np.inf
    for rho in np.arange(0.001, 2 * radius + 1.0, 0.002):
        Q = goal + rho * np.column_stack([np.cos(ang), np.sin(ang)])
        ok = (np.linalg.norm(Q - centre, axis=1) >= radius + PARKING_CLEAR) & (
            np.linalg.norm(Q - other, axis=1) >= apart
        )
        if ok.any():
            best = rho
            break
    got = float(np.linalg.norm(p - goal))
    assert got <= best + PARKING_STEP + best * np.radians(10.0), (got, best)
