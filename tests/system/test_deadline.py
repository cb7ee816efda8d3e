"""Missed deadlines: the robot side follows the shifted candidate.

A command that misses its deadline is not applied.  The robot side then applies
the ancillary law on the shifted candidate of the last command it applied,
``u = v̂ + K(x − x̂)`` (:func:`ground.model.chain_input`), and the agent,
told so by the next tick, takes the same candidate
(:meth:`agent.controller.TubeMPC.rewind`).  The candidate is feasible by
construction, so the theory's guarantees survive the miss: the tube error stays
in Z, the realised one-step disturbance stays in W, and the references stay
apart.  Holding the previous acceleration instead, as the runtime did before,
breaks all three; the last test shows it, so the others can fail.
"""

from __future__ import annotations

import math
import zlib
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from agent.controller import SNAPSHOTS, TubeMPC
from agent.coordination import NeighbourInfo
from agent.tube import require_admissible, synthesize
from fleet.running import simulate as harness
from ground.geometry import controlled_point
from ground.model import chain_input
from ground.scenario import load_scenario

SCENARIOS = Path(__file__).resolve().parents[2] / "scenarios"


class Late:
    """Seeded bursts of missed deadlines: each robot misses every step of a ``burst``-step
    block with probability ``frac`` (none in the first 3 steps); counts the misses."""

    def __init__(self, frac: float, burst: int, seed: int = 0):
        self.frac, self.burst, self.seed = frac, burst, seed
        self.missed: list[tuple[str, int]] = []

    @property
    def count(self) -> int:
        return len(self.missed)

    def __call__(self, rid: str, k: int) -> bool:
        late = k > 2 and zlib.crc32(f"{self.seed}/{rid}/{k // self.burst}".encode()) % 1000 < self.frac * 1000
        if late:
            self.missed.append((rid, k))
        return late


def _controller(scenario: str = "paper_three_robots") -> tuple[TubeMPC, object]:
    scn = load_scenario(SCENARIOS / f"{scenario}.toml")
    design = require_admissible(synthesize(scn.controller, scn.arena))
    r = scn.robots[0]
    ctrl = TubeMPC(
        design, controlled_point(r.start, design.params.lookahead), np.array(r.goal, float), scn.arena,
        obstacles=scn.obstacles,
    )  # fmt: skip
    return ctrl, design


def _x(ctrl: TubeMPC, rng: np.random.Generator) -> np.ndarray:
    """A measured state near the current nominal state (inside the tube)."""
    return ctrl.xi[0:4] + rng.uniform(-1e-3, 1e-3, 4)


def test_chain_input_is_the_candidate_the_controller_rewinds_to():
    """What the robot side applies m steps after the last applied command equals the ancillary
    law on the controller's own state after rewinding those m steps, for m = 0, 1, 2; and
    rewinding two steps at once equals rewinding one at a time."""
    ctrl, design = _controller()
    rng = np.random.default_rng(1)
    for _ in range(15):  # get under way
        ctrl.step(_x(ctrl, rng), [])
    applied = ctrl.step(_x(ctrl, rng), [])
    A, B, K = design.A, design.B, design.K
    for m in range(3):
        x = _x(ctrl, rng)
        ctrl.step(x, [])  # this command misses its deadline
        assert ctrl.rewind(1)
        x_hat, v_hat = ctrl.xi[0:4], ctrl.xi[4:6]
        expected = v_hat + K @ (x - x_hat)
        got = chain_input(applied.x_next, applied.v_next, m, x, A, B, K)
        assert got is not None and np.allclose(got, expected, atol=1e-12), m
    committed = ctrl.y_ref.copy()
    # The same three misses, undone at once (2 stepped, 1 never stepped: the agent fell behind).
    ctrl2, _ = _controller()
    rng = np.random.default_rng(1)
    for _ in range(16):
        ctrl2.step(_x(ctrl2, rng), [])
    for _ in range(2):
        ctrl2.step(_x(ctrl2, rng), [])
    assert ctrl2.rewind(2, coasted=1)
    assert np.allclose(ctrl2.y_ref, committed, atol=1e-12)
    assert ctrl2.counters.unapplied == 3
    # "Stay put" was appended at each: the end point did not move.
    assert np.allclose(committed[-3:], committed[-1], atol=1e-12)


def test_chain_input_ends_with_the_candidate():
    ctrl, design = _controller()
    out = ctrl.step(ctrl.xi[0:4], [])
    n = out.v_next.shape[0]
    assert n == design.params.horizon
    assert chain_input(out.x_next, out.v_next, n - 1, out.x_next, design.A, design.B, design.K) is not None
    assert chain_input(out.x_next, out.v_next, n, out.x_next, design.A, design.B, design.K) is None


def test_rewind_refuses_steps_it_no_longer_keeps():
    ctrl, _ = _controller()
    rng = np.random.default_rng(2)
    for _ in range(SNAPSHOTS + 3):
        ctrl.step(_x(ctrl, rng), [])
    before = (ctrl.xi.copy(), ctrl.y_ref.copy())
    assert not ctrl.rewind(SNAPSHOTS + 1)
    assert np.array_equal(ctrl.xi, before[0]) and np.array_equal(ctrl.y_ref, before[1])
    assert ctrl.rewind(SNAPSHOTS)


@pytest.mark.parametrize(
    ("scenario", "seed"), [("paper_three_robots", 0), ("paper_three_robots", 2), ("swap_8", 0)]
)
def test_missed_commands_on_the_candidate_keep_every_guarantee(scenario, seed):
    """15 % of 4-step blocks missed per robot, closed loop: the tube error stays in Z at every
    step, the realised disturbance stays in W, no QP falls back, the appended references stay
    apart, nothing collides, every goal is reached; every miss was taken on the candidate."""
    scn = load_scenario(SCENARIOS / f"{scenario}.toml")
    late = Late(0.15, 4, seed)
    res = harness.run(scn, late=late)
    assert late.count > 30
    assert sum(c.counters.unapplied for c in res.controllers.values()) == late.count
    for tr in res.traces.values():
        assert all(tr.tube_ok), tr.id
        assert max(tr.w_ratio) <= 1.0 + 1e-9, tr.id
        assert not any(tr.fallback), tr.id
        assert max(tr.ref_deviation) <= res.design.rho, tr.id
    assert res.collisions == 0 and res.reference_violations == 0
    assert res.all_reached
    # What the neighbours see is what was executed: a missed step appended "stay put".
    for rid, k in late.missed:
        last = res.traces[rid].committed_last
        assert np.array_equal(last[k], last[k - 1]), (rid, k)


def test_holding_the_last_acceleration_instead_breaks_the_tube():
    """The control: the same misses (seeds 0 and 2 above) with the previous acceleration
    held and nobody told: the robots leave their tubes and QPs fall back."""
    scn = load_scenario(SCENARIOS / "paper_three_robots.toml")
    for seed in (0, 2):
        res = harness.run(scn, late=Late(0.15, 4, seed), late_policy="hold")
        assert sum(not ok for tr in res.traces.values() for ok in tr.tube_ok) > 0, seed
        assert sum(sum(tr.fallback) for tr in res.traces.values()) > 0, seed


def test_more_rows_than_the_qp_holds_are_all_met_or_the_candidate_is_taken():
    """16 neighbours close around (more rows than the 12 the QP is assembled for; a crowd of
    grown hazard discs does that at 32 robots): no exception, the step counts the overflow,
    and the new end point meets every neighbour's row, the ones left out of the QP too."""
    from agent.coordination import NeighbourInfo, split_halfplanes

    ctrl, design = _controller()
    c = ctrl.last_point.copy()
    r = design.footprint
    angles = np.linspace(0, 2 * np.pi, 16, endpoint=False)
    gaps = 2 * r + 1e-3 * (1 + np.arange(16) % 3)
    around = c + gaps[:, None] * np.column_stack([np.cos(angles), np.sin(angles)])
    nbs = [NeighbourInfo(id=f"n{i}", last_point=p, footprint=r, rank=i + 1) for i, p in enumerate(around)]
    normals, bounds, _ = split_halfplanes(c, r, 0, nbs, design.params.priority_share, design.params.epsilon)
    assert len(bounds) > ctrl.qp.max_coord_rows
    out = ctrl.step(ctrl.xi[0:4], nbs)
    assert ctrl.counters.row_overflows == 1
    y = ctrl.last_point
    assert np.all(np.array(normals) @ y >= np.array(bounds) - 1e-12), out.status


def test_the_robot_side_follows_the_candidate_then_brakes():
    """epuck_link.robot_side.RobotSide, step by step: a command in time is applied; a missing one is
    replaced by the candidate of the last applied command until it is used up; a late command
    keeps the watchdog quiet, silence does not; a dead agent's robot, a braked one and one whose
    agent has no plan yet are braked; without ``drives`` (epuck_link applies the commands) the
    last acceleration is held; a command that asks for the brake is applied as the brake."""
    from epuck_link.robot_side import BRAKED, CANDIDATE, COMMAND, HELD, RobotSide
    from ground.wire import Command

    _, design = _controller()
    Ts = design.params.Ts
    x = np.array([0.01, 0.0, 0.0, 0.0])
    v_next = np.array([[0.1, 0.0], [0.2, 0.0], [0.2, 0.1]])
    cmd = Command(
        robot="r1", step=4, ax=0.3, ay=0.0, fallback=True, x_next=np.zeros(4), v_next=v_next, K=design.K
    )
    side = RobotSide(design.params, watchdog=2.5 * Ts, drives=True)
    what, a, _ = side.decide(4, cmd, cmd, True, x)
    assert what == COMMAND and side.applied_step == 4 and np.array_equal(a, [0.3, 0.0])
    for k, m in ((5, 0), (6, 1)):
        what, a, _ = side.decide(k, None, cmd, True, x)
        assert what == CANDIDATE
        assert np.array_equal(a, chain_input(cmd.x_next, v_next, m, x, design.A, design.B, design.K))
    # Silence trips the watchdog (quiet from step 6: 3 steps > 2.5 Ts at step 8).
    assert side.decide(7, None, cmd, True, x)[0] == CANDIDATE
    assert side.decide(8, None, cmd, True, x) == (BRAKED, None, f"no command for {2.5 * Ts} s")
    # A late command of the step before keeps the watchdog quiet: the candidate is used up first.
    late = RobotSide(design.params, watchdog=2.5 * Ts, drives=True)
    late.decide(4, cmd, cmd, True, x)
    steps = [late.decide(k, None, Command(robot="r1", step=k - 1, ax=0, ay=0), True, x) for k in range(5, 9)]
    assert [s[0] for s in steps] == [CANDIDATE] * 3 + [BRAKED] and steps[-1][2] == "nothing left to follow"
    # After braking there is nothing to follow until a command is applied again.
    assert late.decide(9, None, Command(robot="r1", step=8, ax=0, ay=0), True, x)[0] == BRAKED
    fresh = Command(robot="r1", step=10, ax=0.0, ay=0.0, fallback=True, v_next=v_next, K=design.K)
    assert late.decide(10, fresh, fresh, True, x)[0] == COMMAND
    assert late.decide(11, None, fresh, True, x)[0] == CANDIDATE
    # A dead agent's robot is braked at once; an agent with no plan yet gives nothing to follow.
    assert late.decide(12, fresh, fresh, False, x) == (BRAKED, None, "its agent is not alive")
    rest = Command(robot="r1", step=13, ax=0.0, ay=0.0)  # fallback=False: no plan yet
    late.decide(13, rest, rest, True, x)
    assert late.decide(14, None, rest, True, x) == (BRAKED, None, "nothing left to follow")
    link = RobotSide(design.params, watchdog=2.5 * Ts, drives=False)
    link.decide(4, cmd, cmd, True, None)
    what, a, _ = link.decide(5, None, cmd, True, None)
    assert what == HELD and np.array_equal(a, [0.3, 0.0])
    # An agent that holds without poses asks for the brake: applied as its command (so the report
    # says applied), by the robot side's own brake (no acceleration), and nothing to follow after.
    hold = Command(robot="r1", step=15, ax=0.2, ay=0.1, fallback=False, brake=True)
    what, a, _ = late.decide(15, hold, hold, True, x)
    assert what == COMMAND and a is None and late.applied_step == 15
    assert late.decide(16, None, hold, True, x) == (BRAKED, None, "nothing left to follow")


def test_remembered_steps_stay_bounded_and_keep_the_recent_ones():
    """The processes' sets of unapplied steps: every step of the last STEPS_KEPT is kept, the
    set never holds more than twice that, and a step too old on arrival is not added."""
    from ground.wire import STEPS_KEPT, remember_steps

    steps: set[int] = set()
    for k in range(1000):
        remember_steps(steps, (k,), k)
        assert set(range(max(0, k - STEPS_KEPT), k + 1)) <= steps
        assert len(steps) <= 2 * STEPS_KEPT + 1
    remember_steps(steps, range(0, 1000), 1000)  # only the recent part of a long range
    assert min(steps) >= 1000 - 2 * STEPS_KEPT - 1 and len(steps) <= 2 * STEPS_KEPT + 1
    # A range (a tick's never-executed steps, resent each tick) is added as its steps one by one.
    cases = ((range(0, 1000), 1000), (range(995, 1000), 1000), (range(10, 40), 100), (range(5, 5), 9))
    for new, now in cases:
        by_range: set[int] = {3, 7}
        by_step: set[int] = {3, 7}
        remember_steps(by_range, new, now)
        remember_steps(by_step, tuple(new), now)
        assert by_range == by_step
        assert set(range(max(new.start, now - STEPS_KEPT), new.stop)) <= by_range


def test_the_newest_plan_skips_withdrawn_and_later_steps():
    """``Inbox.newest``: the plan of the newest kept step ≤ at_most that is not skipped
    (a withdrawn plan was never executed), whatever arrived since."""
    from ground.wire import Keys, Plan
    from transport.bus import Inbox

    def plan(k: int) -> Plan:
        z = np.zeros((3, 2))
        return Plan(
            robot="r2", step=k, t0=0.1 * (k + 1), Ts=0.1, committed=z + k, nominal=z, footprint=0.1,
            priority=0, rank=1, phase=0, target=np.zeros(2), goal=np.zeros(2), status="solved",
            solve_time=0.0, tube_ok=True,
        )  # fmt: skip

    inbox = Inbox(Keys("lab"), "agent r1")
    assert inbox.newest(Plan, "r2", 5) is None
    for k in (3, 4, 6):
        inbox._store(Plan.TYPE, plan(k), keep=True)
    newest = inbox.newest
    assert [getattr(newest(Plan, "r2", k, skip), "step", None) for k, skip in (
        (6, set()), (5, set()), (4, set()), (4, {4}), (6, {6, 4}), (6, {6, 4, 3}), (2, set()),
    )] == [6, 4, 4, 3, 3, None, None]  # fmt: skip


def test_epuck_link_takes_the_command_only_by_its_deadline():
    """epuck_link.robot_side.LinkDeadline, the rule epuck_link applies at its own clock: step k
    starts when tick k is received, its command is taken until ``deadline`` after that and
    ignored later; without it the candidate of the last command applied is followed, with
    the state measured at the tick, then the robot is braked; every decision is reported
    (ground.wire.Applied) once, as the tracker will put it in the next tick."""
    from epuck_link.robot_side import BRAKED, CANDIDATE, COMMAND, LinkDeadline
    from ground.wire import Command

    _, design = _controller()
    A, B, K = design.A, design.B, design.K
    v_next = np.array([[0.1, 0.0], [0.2, 0.0]])
    x4, x5 = np.array([0.01, 0.0, 0.0, 0.0]), np.array([0.02, 0.01, 0.0, 0.0])

    def cmd(k: int) -> Command:
        return Command(
            robot="r1", step=k, ax=k / 10, ay=0.0, fallback=True, x_next=np.zeros(4), v_next=v_next, K=K
        )

    judge = LinkDeadline("r1", design.params, watchdog=0.5, deadline=0.05)
    assert judge.tick(4, 10.0, x4, None, True) == [] and judge.wake_at == 10.05
    assert judge.expire(10.049, None, True) is None  # not due yet
    what, a, rep = judge.command(cmd(4), 10.02, True)
    assert what == COMMAND and np.array_equal(a, [0.4, 0.0])
    assert (rep.robot, rep.step, rep.last, rep.braked, rep.on_time) == ("r1", 4, 4, False, True)
    assert judge.wake_at == math.inf and judge.command(cmd(4), 10.03, True) is None  # decided once
    # Step 5: no command by 10.15, so the candidate of step 4's command, from the state at tick 5.
    assert judge.tick(5, 10.1, x5, cmd(4), True) == []
    assert judge.expire(10.149, cmd(4), True) is None
    what, a, rep = judge.expire(10.151, cmd(4), True)
    assert what == CANDIDATE and np.array_equal(a, chain_input(np.zeros(4), v_next, 0, x5, A, B, K))
    assert (rep.step, rep.last, rep.braked) == (5, 4, False)
    assert judge.command(cmd(5), 10.16, True) is None  # late: not applied
    # A command that comes before its tick is taken when the tick comes.
    assert judge.command(cmd(6), 10.19, True) is None
    [(what, a, rep)] = judge.tick(6, 10.2, x5, cmd(6), True)
    assert what == COMMAND and rep.on_time and np.array_equal(a, [0.6, 0.0])
    # A command that came after its deadline is not applied, even if nothing has expired yet.
    judge.tick(7, 10.3, x5, cmd(6), True)
    assert judge.command(cmd(7), 10.351, True) is None
    assert judge.expire(10.36, cmd(7), True)[0] == CANDIDATE
    # Tick 9 before step 8's deadline (tick 8 came 0.5 Ts late): step 8 cannot be reported in
    # time, so it is braked, and so is step 9, whatever comes, until tick 10.
    judge.tick(8, 10.45, x5, cmd(7), True)
    [(w8, _, r8)] = judge.tick(9, 10.48, x5, cmd(7), True)
    assert (w8, r8.step, r8.last, r8.braked) == (BRAKED, 8, 6, True)
    assert judge.command(cmd(9), 10.49, True) is None  # in time, but held
    w9, _, r9 = judge.expire(10.54, cmd(9), True)
    assert (w9, r9.step, r9.last, r9.braked) == (BRAKED, 9, 6, True)
    assert judge.tick(10, 10.6, x5, None, True) == []
    assert judge.command(cmd(10), 10.61, True)[0] == COMMAND
    # A tick that never reached the link (11): step 11 is reported braked when 12 comes.
    [(w11, _, r11)] = judge.tick(12, 10.8, x5, cmd(10), True)
    assert (w11, r11.step, r11.last, r11.braked) == (BRAKED, 11, 10, True)
    assert judge.expire(10.86, cmd(10), True)[0] == BRAKED  # step 12 too: held
    # The candidate is followed for as long as it lasts (2 steps), then the robot is braked.
    judge.tick(13, 10.9, x5, None, True)
    judge.command(cmd(13), 10.91, True)
    whats = []
    for k in (14, 15, 16):
        judge.tick(k, 10.9 + 0.1 * (k - 13), x5, cmd(13), True)
        whats.append(judge.expire(10.96 + 0.1 * (k - 13), cmd(13), True)[0])
    assert whats == [CANDIDATE, CANDIDATE, BRAKED]
    # A dead agent's robot is braked at once.
    judge.tick(17, 11.3, x5, None, True)
    assert judge.command(cmd(17), 11.31, True)[0] == COMMAND
    judge.tick(18, 11.4, x5, cmd(17), False)
    assert judge.expire(11.5, cmd(17), False)[0] == BRAKED
    # The camera pose of step 5 came after its tick: the candidate follows from that
    # measurement (the agent's own, from which an agent planning ahead predicts the input
    # applied), not from the estimate at the tick; a measurement of another step, or one after
    # the decision, changes nothing.
    judge = LinkDeadline("r1", design.params, watchdog=0.5, deadline=0.05)
    judge.tick(4, 10.0, x4, cmd(4), True)
    judge.tick(5, 10.1, x4, cmd(4), True)
    judge.measured(4, x4 + 1.0)
    judge.measured(5, x5)
    what, a, _ = judge.expire(10.16, cmd(4), True)
    assert what == CANDIDATE and np.array_equal(a, chain_input(np.zeros(4), v_next, 0, x5, A, B, K))
    assert not np.array_equal(a, chain_input(np.zeros(4), v_next, 0, x4, A, B, K))
    judge.measured(5, x4)
    assert judge.x is x5


def _reports_inbox() -> tuple[Any, Any]:
    """A tracker's inbox, and ``put(robot, step, last, braked=False)``, which stores a link's
    Applied report in it as its subscription would."""
    from ground.wire import Applied, Keys
    from transport.bus import Inbox

    keys = Keys("lab")
    inbox = Inbox(keys, "tracker")

    def put(robot: str, step: int, last: int, braked: bool = False) -> None:
        msg = Applied(robot=robot, step=step, last=last, braked=braked)
        inbox._accept(keys.applied(robot), msg.encode(), Applied, True, 0.0)

    return inbox, put


def test_a_tracker_tells_the_links_reports_in_the_next_tick():
    """tracker.reports.Reports: tick k tells each robot's report of step k − 1 (its candidate,
    or the brake); a braked report too late for its tick goes into the next one; a late report
    of a step on the candidate is logged and counted, never told; a link that reported a
    recent step is waited for (bounded)."""
    from tracker.reports import Reports

    inbox, put = _reports_inbox()
    lines: list[str] = []
    inbox.live.update({"r1", "r2", "r3"})  # a braked robot counts as a miss while its agent lives
    reports = Reports(["r1", "r2", "r3"])
    put("r1", 4, 4)
    put("r2", 4, 3)
    assert reports.for_tick(inbox, 5, 0.0, lines.append) == ({"r2": 3}, {}, ["r2"])
    assert reports.expected == {"r1", "r2"}
    put("r2", 5, 5)
    assert reports.for_tick(inbox, 6, 0.01, lines.append) == ({}, {}, [])  # r1's is late
    put("r1", 5, 4, braked=True)  # after tick 6
    put("r3", 5, 2)  # on the candidate, after tick 6
    put("r1", 6, 4, braked=True)
    put("r2", 6, 6)
    assert reports.for_tick(inbox, 7, 0.0, lines.append) == ({}, {"r1": 4}, ["r1"])
    assert reports.untold == 1 and len(lines) == 1 and "r3's robot side followed its candidate" in lines[0]
    put("r2", 3, 2)  # too old and already told: never told again
    assert reports.for_tick(inbox, 8, 0.0, lines.append) == ({}, {}, [])
    inbox.live.discard("r3")  # a dead agent's braked robot: told, not a miss
    put("r3", 8, 5, braked=True)
    assert reports.for_tick(inbox, 9, 0.0, lines.append) == ({}, {"r3": 5}, [])


def test_with_delay_compensation_the_outcome_tells_the_links_reports_and_the_tick_repeats_it():
    """tracker.reports.Reports.for_outcome: the outcome of step k tells the reports of step k
    as soon as they are in; tick k + 1 says the same and counts no miss again; a report that
    came after the outcome is taken with the next one: a brake is told then, a candidate is
    logged and counted, never told."""
    from tracker.reports import Reports

    inbox, put = _reports_inbox()
    lines: list[str] = []
    inbox.live.update({"r1", "r2", "r3"})
    reports = Reports(["r1", "r2", "r3"])
    for r in ("r1", "r2", "r3"):
        put(r, 4, 4)
    assert reports.for_outcome(inbox, 4, 0.0, lines.append) == ({}, {}, [])
    assert reports.for_tick(inbox, 5, 0.0, lines.append) == ({}, {}, [])
    put("r1", 5, 5)
    put("r2", 5, 4)  # on its candidate, in time for the outcome
    assert reports.for_outcome(inbox, 5, 0.01, lines.append) == ({"r2": 4}, {}, ["r2"])  # r3's is late
    assert reports.for_tick(inbox, 6, 0.0, lines.append) == ({"r2": 4}, {}, [])  # the same, no miss again
    put("r3", 5, 4)  # on its candidate, after the outcome: never told
    put("r1", 6, 5, braked=True)
    put("r2", 6, 6)
    assert reports.for_outcome(inbox, 6, 0.0, lines.append) == ({}, {"r1": 5}, ["r1"])
    assert reports.untold == 1 and len(lines) == 1 and "r3's robot side followed its candidate" in lines[0]
    put("r2", 7, 7)
    put("r3", 6, 4, braked=True)  # braked, after the outcome of its step: told with the next
    put("r1", 7, 5, braked=True)
    assert reports.for_outcome(inbox, 7, 0.0, lines.append) == ({}, {"r1": 5, "r3": 4}, ["r1", "r3"])
    assert reports.for_tick(inbox, 8, 0.0, lines.append) == ({}, {"r1": 5, "r3": 4}, [])


def _in_the_way(design: object) -> list[NeighbourInfo]:
    """A robot parked-in-motion at the centre, on the path of ``_controller()``'s robot
    ((0.7, 0) to (−0.7, 0)), that goes first: the navigator plans around it."""
    r = design.footprint  # type: ignore[attr-defined]
    return [
        NeighbourInfo(
            "r9", np.array([0.0, 0.02]), r, priority=1, rank=1, target=np.array([0.0, -0.6]),
            goal=np.array([0.0, -0.6]),
        )
    ]  # fmt: skip


def test_a_target_chosen_ahead_is_the_one_the_step_would_choose():
    """The realtime agent steers between steps (TubeMPC.steer_ahead) to keep the navigator
    off the path from tick to command; with the same neighbours, every step's command,
    committed reference, target and mode are those of a controller that steers in the step."""
    a, design = _controller()
    b, _ = _controller()
    nbs = _in_the_way(design)
    rng = np.random.default_rng(3)
    modes = set()
    for _ in range(60):
        x = _x(a, rng)
        b.steer_ahead(nbs)
        oa, ob = a.step(x, nbs), b.step(x, nbs)
        # Not bit for bit: two ProxSuite instances may round differently (memory alignment).
        assert np.allclose(oa.a, ob.a, atol=1e-9) and np.allclose(oa.committed, ob.committed, atol=1e-9)
        assert np.allclose(oa.target, ob.target, atol=1e-9) and oa.mode == ob.mode
        modes.add(oa.mode)
    assert b.counters.ahead == 60 and a.counters.ahead == 0
    assert modes & {"path", "yield", "aside", "escape"}, modes  # the navigator had work to do


def test_a_target_chosen_ahead_is_dropped_once_the_reference_changed():
    """A new goal, a re-initialisation, a rewind or a blind hold between the choice and
    the step: the step steers again, as a controller that never chose ahead does."""
    ctrl, _ = _controller()
    twin, _ = _controller()  # steers in the step
    rng = np.random.default_rng(4)
    changes = {
        "set_goal": lambda c: c.set_goal(np.array([-0.2, 0.3])),
        "reset": lambda c: c.reset(c.last_point + 0.01),
        "rewind": lambda c: c.rewind(1),
        "hold": lambda c: c.hold(c.xi[0:4]),
    }
    for name, change in changes.items():
        x = _x(ctrl, rng)
        ctrl.step(x, [])
        twin.step(x, [])
        ctrl.steer_ahead(_in_the_way(ctrl.design))
        for c in (ctrl, twin):
            change(c)
        x = _x(ctrl, rng)
        out, out_twin = ctrl.step(x, []), twin.step(x, [])
        assert ctrl.counters.ahead == 0, name
        assert np.allclose(out.target, out_twin.target, atol=1e-9) and out.mode == out_twin.mode, name
    ctrl.steer_ahead([])
    ctrl.step(_x(ctrl, rng), [])
    assert ctrl.counters.ahead == 1  # and taken when nothing changed


def test_a_target_chosen_without_the_neighbours_still_keeps_them_apart():
    """The target is shaping only.  Chosen ahead from no neighbours at all, it points
    straight through the robot in the way; the split rule still keeps every appended
    point R from that robot's committed point, and the robot presses up to it."""
    ctrl, design = _controller()
    nbs = _in_the_way(design)
    R = 2 * design.footprint  # type: ignore[attr-defined]
    rng = np.random.default_rng(5)
    closest = math.inf
    for _ in range(120):
        ctrl.steer_ahead([])
        out = ctrl.step(_x(ctrl, rng), nbs)
        closest = min(closest, float(np.linalg.norm(out.committed[-1] - nbs[0].last_point)))
    assert ctrl.counters.ahead == 120
    assert R - 1e-9 <= closest < R + 0.01


def test_a_link_back_from_an_outage_brakes_until_the_agent_starts_again():
    """The robot drove on uncontrolled while its link was down (the firmware has no deadman).
    When the link comes back, the link applies no command of this step or the next and reports
    the next step braked: tick k + 2 then tells the agent, which starts again where the robot
    is (the restarted agent's path).  After that, commands are applied again."""
    from epuck_link.robot_side import BRAKED, COMMAND, LinkDeadline
    from ground.wire import Command

    _, design = _controller()

    def cmd(k: int) -> Command:
        return Command(
            robot="r1", step=k, ax=0.1, ay=0.0, fallback=True, x_next=np.zeros(4),
            v_next=np.array([[0.1, 0.0], [0.2, 0.0]]), K=design.K,
        )  # fmt: skip

    x = np.zeros(4)
    judge = LinkDeadline("r1", design.params, watchdog=0.5, deadline=0.05)
    judge.tick(4, 10.0, x, None, True)
    assert judge.command(cmd(4), 10.01, True)[0] == COMMAND
    # During step 4 the link came back: step 5 is held, tick 6 says so, and the plan of step 6
    # is the first made from where the robot stands (what the neighbours wait for).
    assert judge.relinked() == 6
    judge.tick(5, 10.1, x, None, True)
    assert judge.command(cmd(5), 10.11, True) is None  # in time, but held
    what, _, rep = judge.expire(10.16, cmd(5), True)
    assert (what, rep.step, rep.last, rep.braked) == (BRAKED, 5, 4, True)
    judge.tick(6, 10.2, x, None, True)
    assert judge.command(cmd(6), 10.21, True)[0] == COMMAND
