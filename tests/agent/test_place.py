"""Plans by place: the cells, the reach they give, and what an agent keeps clear of by them."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import zenoh

from agent.channels import group_of
from agent.coordination import (
    PLACE_LAG,
    VIEW_CELLS,
    NeighbourInfo,
    navigator_view,
    place_side,
    split_halfplanes,
)
from agent.hazards import Guard, in_reach
from agent.tube import validated_design
from ground.geometry import Whereabouts, block, cell_centre, cell_name, cell_of, cells_apart, parse_cell
from ground.scenario import load_scenario
from ground.wire import BLIND, Keys, Plan, Tick, WireError
from transport.bus import Inbox
from transport.process import exchange_for

SCN = load_scenario(Path(__file__).resolve().parents[2] / "scenarios" / "swap_16.toml")
DESIGN = validated_design(SCN)
P = DESIGN.params
SIDE = place_side(DESIGN.footprint, P.epsilon, P.priority_share)
STEP = math.sqrt(2.0) * P.epsilon
"""How far a committed point moves in a step at most [m]."""


def test_cells_name_and_parse_and_two_apart_means_more_than_a_side():
    rng = np.random.default_rng(7)
    for _ in range(2000):
        a, b = rng.uniform(-3.0, 3.0, 2), rng.uniform(-3.0, 3.0, 2)
        ca, cb = cell_of(a, SIDE), cell_of(b, SIDE)
        assert parse_cell(cell_name(ca)) == ca
        assert np.all(np.abs(a - cell_centre(ca, SIDE)) <= SIDE / 2 + 1e-12)
        if cells_apart(ca, cb) >= 2:
            assert np.max(np.abs(a - b)) > SIDE
    assert len(block((3, -1), 2)) == 25 and cells_apart((3, -1), (5, 1)) == 2
    for bad in ("3", "3_", "_1", "a_1", "1_2_3", "1_1e3", "9999999999_0"):
        with pytest.raises(ValueError):
            parse_cell(bad)


@pytest.mark.parametrize("prio", [(0, 0), (1, 0), (0, 1)])
def test_a_robot_out_of_reach_gets_no_split_row_even_after_the_lag(prio):
    """The split rule adds no row between committed points in cells two apart, after both
    moved towards each other for PLACE_LAG steps: coordinating only within reach loses no
    constraint.  Just inside that distance it does add one (the bound is not vacuous)."""
    rng = np.random.default_rng(3)
    r = DESIGN.footprint
    for _ in range(500):
        # Two points in cells two apart along a random axis, as close as those cells allow.
        x_i = rng.uniform(0.0, SIDE)
        gap = SIDE + rng.uniform(1e-9, 1e-3)  # just over a side apart
        c_i = np.array([x_i, rng.uniform(0.0, SIDE)])
        c_j = c_i + np.array([gap, rng.uniform(-1e-3, 1e-3)])
        if cells_apart(cell_of(c_i, SIDE), cell_of(c_j, SIDE)) < 2:
            continue
        towards = (c_j - c_i) / np.linalg.norm(c_j - c_i)
        c_i2, c_j2 = c_i + towards * PLACE_LAG * STEP, c_j - towards * PLACE_LAG * STEP
        nb = NeighbourInfo("r2", c_j2, r, prio[1], 1)
        normals, _, _ = split_halfplanes(c_i2, r, prio[0], [nb], P.priority_share, P.epsilon)
        assert normals == [], (c_i, c_j)
    closer = np.array([2.0 * r + STEP * 1.01 / (1.0 - P.priority_share) - 1e-3, 0.0])
    normals, _, _ = split_halfplanes(np.zeros(2), r, 0, [NeighbourInfo("r2", closer, r, 1, 1)],
                                     P.priority_share, P.epsilon)  # fmt: skip
    assert len(normals) == 1


def test_the_groups_subscribed_hold_the_reach_and_one_ring_more():
    """Whichever cell of its group a robot is in (negative indices too), the 3 x 3 groups about
    its group hold every cell at most two apart from its own: the navigator's view
    (``VIEW_CELLS``) is what the subscription delivers, no more; ``auto`` is place on the realtime
    clock only."""
    rng = np.random.default_rng(5)
    for cell in [tuple(int(v) for v in rng.integers(-50, 50, 2)) for _ in range(400)] + [(0, 0), (-1, -1)]:
        groups = block(group_of(cell), 1)
        assert {group_of(c) for c in block(cell, VIEW_CELLS)} <= groups, cell
        assert not {group_of(c) for c in block(cell, VIEW_CELLS + 1)} <= groups, cell
    assert (exchange_for("realtime"), exchange_for("lockstep")) == ("place", "mesh")
    assert exchange_for("realtime", "relay") == "relay"


def _plan(robot: str, step: int, point) -> Plan:
    return Plan(
        robot=robot, step=step, t0=0.1 * step, Ts=P.Ts, committed=np.tile(point, (P.horizon, 1)),
        nominal=np.zeros((P.horizon + 1, 2)), footprint=DESIGN.footprint, priority=0, rank=1, phase=0,
        target=np.zeros(2), goal=np.zeros(2), status="PROXQP_SOLVED", solve_time=0.0, tube_ok=True,
    )  # fmt: skip


def _starts(points: dict[str, tuple[float, float]]) -> dict[str, NeighbourInfo]:
    return {
        j: NeighbourInfo(j, np.array(q), DESIGN.footprint, 0, n) for n, (j, q) in enumerate(points.items())
    }


def test_in_reach_takes_the_newest_of_plan_token_and_start():
    """By the newest of what was heard; nothing heard: the start.  A robot kept clear of as a
    disc, which can be wider than a cell, is always in: its agent gone, its robot braked or its
    link down (``discs``), or its agent blind by its last plan."""
    mine = (0, 0)
    near, far = (0.5 * SIDE, 0.5 * SIDE), (3.5 * SIDE, 0.5 * SIDE)
    starts = _starts({"a": near, "b": far, "c": far, "d": near, "e": far, "f": far})
    last = {"b": _plan("b", 10, near), "c": _plan("c", 10, near), "d": _plan("d", 10, far)}
    places = {
        "b": Whereabouts((0, 3), 11),  # moved away after its last plan heard
        "c": Whereabouts((3, 0), 9),  # a plan newer than the token: the plan says near
        "d": Whereabouts((1, 1), 4),  # the token is older than the plan: far
        "e": Whereabouts((-1, 1), 12),  # heard of by its token only: near
    }
    live = {"a", "b", "c", "d", "e"}  # f is gone: in, wherever it is
    got = in_reach(["a", "b", "c", "d", "e", "f"], mine, SIDE, last, places, starts, live)
    assert got == ["a", "c", "e", "f"]
    blind = dataclasses.replace(last["d"], status=BLIND)
    got = in_reach(["b", "d"], mine, SIDE, {**last, "d": blind}, places, starts, live, discs={"b"})
    assert got == ["b", "d"]  # b braked (or loose), d blind: both far, both in
    assert in_reach(["a", "b", "c", "d", "e", "f"], (3, 0), SIDE, last, places, starts, set(starts)) == [
        "d", "f",
    ]  # fmt: skip


@pytest.mark.parametrize("scenario", ["swap_16", "swap_8"])
def test_the_navigator_sees_every_robot_its_yielding_rule_acts_on(scenario):
    """With plans by place the navigator takes the robots up to VIEW_CELLS cells away, all of
    them in the groups an agent hears.  Every robot now within navigator_view of c_i is among
    them, by a plan up to PLACE_LAG steps old (both robots moving towards each other since);
    the agent caps its yield range r_i + r_j + conflict_range there (compact designs, whose
    cells are small), and the epuck design's full range fits uncapped."""
    from agent.navigator import CONFLICT_RANGE

    design = validated_design(
        load_scenario(Path(__file__).resolve().parents[2] / "scenarios" / f"{scenario}.toml")
    )
    p, r = design.params, design.footprint
    side = place_side(r, p.epsilon, p.priority_share)
    view = navigator_view(side, p.epsilon)
    lag = PLACE_LAG * math.sqrt(2.0) * p.epsilon
    rng = np.random.default_rng(11)
    for _ in range(3000):
        now_i = rng.uniform(-2.0, 2.0, 2)
        ang, dist = rng.uniform(0, 2 * math.pi), view * math.sqrt(rng.uniform(0.0, 1.0))
        now_j = now_i + dist * np.array([math.cos(ang), math.sin(ang)])
        # What i heard of j, and i's own point then: each up to the lag behind, anywhere.
        heard_j = now_j + lag * rng.uniform(-1, 1, 2) / math.sqrt(2.0)
        last = {"j": _plan("j", 5, heard_j)}
        assert in_reach(["j"], cell_of(now_i, side), side, last, {}, _starts({"j": (9.0, 9.0)}), {"j"},
                        within=VIEW_CELLS) == ["j"]  # fmt: skip
    # Three cells away a robot is not seen (the view is what the cells give, no more), though
    # it may be just over two sides from c_i: the view is two sides less the lag.
    far = {"j": _plan("j", 5, (3.0 * side + 1e-6, 0.5 * side))}
    assert in_reach(["j"], (0, 0), side, far, {}, _starts({"j": (9.0, 9.0)}), {"j"}, within=VIEW_CELLS) == []
    full = 2 * r + CONFLICT_RANGE
    assert (full <= view) == (scenario == "swap_8"), (full, view)


def test_guard_keeps_clear_of_a_robot_known_by_its_token_only():
    """The cell's disc covers every point of the cell grown by N + lag steps and the braking
    distance; it replaces the plan's disc only when smaller, and a fresh plan still makes a
    neighbour, whatever the token says."""
    g = Guard("r1", P, print, side=SIDE)
    brake = P.v_max**2 / (2 * P.a_max)
    starts = _starts({"r1": (0.0, 0.0), "r2": (1.0, 1.0)})
    where = Whereabouts((2, -1), 30)
    # Never heard, long after the start: about the token's cell, not the start.
    nbs, hz = g.classify(200, ["r2"], {"r2": None}, {}, {"r2"}, starts, places={"r2": where})
    assert not nbs and np.array_equal(hz[0].centre, cell_centre((2, -1), SIDE))
    grown = hz[0].radius - DESIGN.footprint - (P.horizon + PLACE_LAG) * STEP - brake
    corners = [cell_centre((2, -1), SIDE) + SIDE / 2 * np.array([sx, sy]) for sx in (-1, 1) for sy in (-1, 1)]
    assert all(np.linalg.norm(c - hz[0].centre) <= grown + 1e-12 for c in corners)
    # An old plan (step 5) from elsewhere: its disc has grown past the cell's, which is kept;
    # soon after the start, the start's disc is the smaller.
    old = _plan("r2", 5, (1.0, 1.0))
    nbs, hz = g.classify(200, ["r2"], {"r2": None}, {"r2": old}, {"r2"}, starts, places={"r2": where})
    assert np.array_equal(hz[0].centre, cell_centre((2, -1), SIDE))
    nbs, hz = g.classify(20, ["r2"], {"r2": None}, {}, {"r2"}, starts, places={"r2": where})
    assert np.array_equal(hz[0].centre, [1.0, 1.0]) and hz[0].radius == pytest.approx(
        DESIGN.footprint + 21 * STEP
    )
    # A plan one step older than the token: its small disc is kept.
    recent = _plan("r2", 38, (0.1, -0.2))
    nbs, hz = g.classify(40, ["r2"], {"r2": None}, {"r2": recent}, {"r2"}, starts,
                         places={"r2": dataclasses.replace(where, since=39)})  # fmt: skip
    assert np.array_equal(hz[0].centre, [0.1, -0.2]) and hz[0].radius == pytest.approx(
        DESIGN.footprint + 2 * STEP
    )
    # Gone where its token was: the same cell disc, the braking included.
    nbs, hz = g.classify(200, ["r2"], {"r2": None}, {}, set(), starts,
                         places={"r2": where})  # fmt: skip
    assert np.array_equal(hz[0].centre, cell_centre((2, -1), SIDE))
    fresh = _plan("r2", 39, (0.4, 0.4))
    nbs, hz = g.classify(40, ["r2"], {"r2": fresh}, {"r2": fresh}, {"r2"}, starts, places={"r2": where})
    assert [n.id for n in nbs] == ["r2"] and not hz


class _Session:
    """Stands in for a Zenoh session: keeps the liveliness subscriber's callback."""

    def __init__(self):
        self.callback = None

    def liveliness(self):
        return self

    def declare_subscriber(self, key, callback, history):
        assert key == "fleet/lab/at/*/**" and history
        self.callback = callback
        return None


def test_inbox_keeps_each_robots_newest_place_and_where_it_went():
    keys = Keys("lab")
    inbox, session = Inbox(keys, "test"), _Session()
    inbox.watch_places(session)

    def token(kind, robot, cell, step):
        session.callback(SimpleNamespace(kind=kind, key_expr=keys.at(robot, cell_name(cell), step)))

    put, delete = zenoh.SampleKind.PUT, zenoh.SampleKind.DELETE
    token(put, "r2", (0, 0), 0)
    token(put, "r2", (1, 0), 14)  # the new token comes before the old one goes
    token(delete, "r2", (0, 0), 0)
    assert inbox.places["r2"] == Whereabouts((1, 0), 14)
    token(put, "r2", (0, 0), 0)  # an old token late (history): ignored
    assert inbox.places["r2"] == Whereabouts((1, 0), 14)
    token(delete, "r2", (1, 0), 14)  # its agent is gone: where it was stays
    assert inbox.places["r2"] == Whereabouts((1, 0), 14)
    token(put, "r2", (2, 0), 9)  # an older step, as a late history replay: ignored
    assert inbox.places["r2"] == Whereabouts((1, 0), 14)
    session.callback(SimpleNamespace(kind=put, key_expr="fleet/lab/at/r3/x_1/2"))
    assert inbox.rejects.total == 1 and "r3" not in inbox.places
    with pytest.raises(WireError):
        keys.place_of("fleet/lab/at/r3/1_1")


def test_inbox_counts_news_of_a_place_that_came_later_than_the_lag_allows():
    """6.7's proof assumes that what an agent knows of a robot's place is at most PLACE_LAG steps
    old.  The inbox measures it: a plan or place token newer than anything known of its robot,
    taken more than PLACE_LAG steps after the step it names, is counted for that robot.  What
    comes in time, what is older than what is known, and what an agent that joined a running
    fleet hears of a robot for the first time (the tokens' history, a first plan) are not."""
    keys = Keys("lab")
    inbox, session = Inbox(keys, "agent r1"), _Session()
    inbox.watch_places(session, PLACE_LAG)
    put = zenoh.SampleKind.PUT

    def token(robot, cell, step):
        session.callback(SimpleNamespace(kind=put, key_expr=keys.at(robot, cell_name(cell), step)))

    def plan(robot, step):
        near = keys.near(robot, cell_name(group_of((0, 0))))
        inbox._accept(near, _plan(robot, step, (0.0, 0.0)).encode(), Plan, True, 0.0)

    inbox.release(40)
    token("r2", (0, 0), 3)  # first heard of, long after: the history of a running fleet
    plan("r3", 12)  # the same, by a plan
    assert inbox.late == {}
    plan("r2", 40 - PLACE_LAG)  # news, as late as the lag allows
    token("r3", (1, 0), 40 - PLACE_LAG)
    assert inbox.late == {}
    plan("r2", 37 - PLACE_LAG)  # older than what is known: no news
    token("r3", (0, 0), 37 - PLACE_LAG)
    assert inbox.late == {}
    inbox.release(41)
    plan("r2", 40 - PLACE_LAG)  # the same step again: no news either
    assert inbox.late == {}
    inbox.release(45)
    plan("r2", 44 - PLACE_LAG)  # newer, one step too late
    token("r3", (2, 0), 42 - PLACE_LAG)
    plan("r3", 45 - PLACE_LAG)  # newer than r3's token, and in time
    assert inbox.late == {"r2": 1, "r3": 1}
    assert inbox.places["r3"] == Whereabouts((2, 0), 42 - PLACE_LAG)  # counted, and still taken
    assert inbox.get(Plan, "r2").step == 44 - PLACE_LAG
    plan("r4", 30)
    inbox.release(43)  # the receiver's step never goes back
    plan("r4", 44 - PLACE_LAG)
    assert inbox.late == {"r2": 1, "r3": 1, "r4": 1}
    inbox.release(50)
    plan("r2", 49 - PLACE_LAG)  # every late one is counted
    assert inbox.late == {"r2": 2, "r3": 1, "r4": 1}
    # A receiver that started with the fleet knew every robot at its start, as of step 0: a first
    # token is news if it names a later step, and its lag counts against the newest step the
    # receiver knows of, its own or the clock's.
    start = Inbox(keys, "agent r1")
    start_session = _Session()
    start.watch_places(start_session, PLACE_LAG)

    def first(robot, cell, step):
        start_session.callback(SimpleNamespace(kind=put, key_expr=keys.at(robot, cell_name(cell), step)))

    start.release(0)
    first("r2", (0, 0), 0)  # where it started: no news
    start.release(5)
    first("r3", (1, 0), 2)  # moved at step 2, heard of at step 5
    first("r4", (0, 0), 3)  # moved at step 3: as late as the lag allows
    assert start.late == {"r3": 1}
    clock = keys.clock
    start._accept(
        clock, Tick(robot="tracker", step=9, t=0.9, stop=False, misses=0).encode(), Tick, False, 0.0
    )
    assert start.step == 9  # the clock is ahead of this receiver's own step
    start._accept(keys.near("r2", cell_name((0, 0))), _plan("r2", 6, (0.0, 0.0)).encode(), Plan, True, 0.0)
    assert start.late == {"r2": 1, "r3": 1}
    # A fleet whose plans go to every agent assumes no lag: nothing is measured.
    mesh = Inbox(keys, "agent r1")
    mesh.release(40)
    mesh._accept(keys.plan("r2"), _plan("r2", 3, (0.0, 0.0)).encode(), Plan, True, 0.0)
    mesh._accept(keys.plan("r2"), _plan("r2", 4, (0.0, 0.0)).encode(), Plan, True, 0.0)
    assert mesh.late == {} and mesh.get(Plan, "r2").step == 4


def _link_args(**net) -> SimpleNamespace:
    return SimpleNamespace(
        lease=None, mode=None, zenoh_config=None, faults=None, clock="lockstep", exchange="mesh",
        delay_compensation=False, **net,
    )  # fmt: skip


def test_a_waiting_agent_takes_the_plans_of_the_robot_it_waits_for_from_anywhere_and_only_those():
    """With plans by place an agent hears only the cells about its own; a robot it waits for
    (its gate, docs/method.md §7) it hears on that robot's own key wherever it is, from the
    moment it watches it until it stops (``Channels.watch_plans``).  Two real Zenoh sessions on
    loopback; a marker put on the waited robot's own session, after its plan and into the
    waiter's cells, says when that plan would have come."""
    from agent.channels import Channels
    from transport.bus import put
    from transport.net import free_port, loopback

    keys = Keys("gate")
    hub = loopback(free_port())
    far, home = np.array([8.0 * SIDE, 8.0 * SIDE]), np.zeros(2)
    waiter = Channels(_link_args(listen=[hub], connect=[]), keys, "r1", "agent r1", side=SIDE, start=far)
    waited = Channels(_link_args(listen=[], connect=[hub]), keys, "r2", "agent r2", side=SIDE, start=home)
    try:
        marks = iter(range(1, 10_000))

        def heard(robot: str, step: int) -> bool:
            return waiter.inbox.get(Plan, robot, step) is not None

        def sync() -> None:
            """Put a marker plan into the waiter's cells on the waited robot's session until the
            waiter has it: whatever that session put before has come by then, or never will."""
            m = next(marks)
            key = keys.near("r9", cell_name(group_of(cell_of(far, SIDE))))
            for _ in range(400):  # bounded: 20 s
                put(waited.session, key, _plan("r9", m, far).encode())
                with waiter.inbox.cond:
                    if waiter.inbox.cond.wait_for(lambda m=m: heard("r9", m), 0.05):
                        return
            raise AssertionError("the marker never came: the two sessions are not linked")

        waited.put_plan(_plan("r2", 1, home))  # eight cells away: not in the waiter's cells
        sync()
        assert not heard("r2", 1) and waiter.plans == {}
        waiter.watch_plans(["r2"])
        for step in range(2, 402):  # bounded: until the subscription has reached the other peer
            waited.put_plan(_plan("r2", step, home))
            sync()
            if heard("r2", step):
                break
        else:
            raise AssertionError("the waited robot's plan never came on its own key")
        waiter.watch_plans([])
        assert waiter.plans == {}
        waited.put_plan(_plan("r2", 1000, home))
        sync()
        assert not heard("r2", 1000)
    finally:
        waited.close()
        waiter.close()
