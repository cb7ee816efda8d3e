"""The supervisor's step bookkeeping against plans that claim steps the clock has not reached.

A robot's own certificate lets it publish any step on its own plan key; the
wire format accepts steps up to 2**62.  Before the clock bound, one plan of
step 10**12 made every later step look "skipped" by that robot, and the
supervisor's loop counted empty plan steps towards 10**12 under the inbox lock
(found by tests/system/test_secure_fleet.py's attacker)."""

from __future__ import annotations

import numpy as np
import pytest

from ground.wire import Keys, Plan, Tick
from supervisor.monitor import _plan_step
from transport.bus import Inbox

IDS = ["r1", "r2"]


def _plan(robot: str, step: int) -> Plan:
    pts = np.zeros((20, 2))
    return Plan(
        robot=robot, step=step, t0=0.1 * (step + 1), Ts=0.1, committed=pts, nominal=np.zeros((21, 2)),
        footprint=0.1, priority=0, rank=IDS.index(robot), phase=0, target=np.zeros(2), goal=np.zeros(2),
        status="PROXQP_SOLVED", solve_time=1e-4, tube_ok=True,
    )  # fmt: skip


def _inbox(tick_step: int, plans: dict[str, list[int]]) -> Inbox:
    inbox = Inbox(Keys("lab"), "test")
    inbox.live = set(IDS)
    tick = Tick(robot="tracker", step=tick_step, t=0.1 * tick_step, stop=False, misses=0)
    inbox._store(Tick.TYPE, tick, False)
    for r, steps in plans.items():
        for s in steps:
            inbox._store(Plan.TYPE, _plan(r, s), True)
    return inbox


def test_a_full_step_within_the_clock_is_judged() -> None:
    inbox = _inbox(5, {"r1": [0, 1, 2, 3, 4, 5], "r2": [0, 1, 2, 3, 4, 5]})
    got = _plan_step(inbox, IDS, 3)
    assert got is not None and sorted(got) == IDS and got["r2"].step == 3
    # The plans of the clock's own step wait for the next tick: it says whose were executed.
    assert _plan_step(inbox, IDS, 5) is None


def test_a_far_future_plan_neither_skips_a_robot_nor_runs_past_the_clock() -> None:
    far = 10**12
    inbox = _inbox(5, {"r1": [0, 1, 2, 3, 4, 5], "r2": [0, 1, 2, 3, far]})
    # r2's plan of step 4 may still come: the forged one must not count as "r2 moved on".
    assert _plan_step(inbox, IDS, 4) is None
    # The supervisor's drain loop: it must stop at the clock, not walk towards 10**12.
    k, judged = 0, []
    while (step := _plan_step(inbox, IDS, k)) is not None and k < 100:
        judged.append(sorted(step))
        k += 1
    assert k == 4 and judged == [IDS] * 4
    # Steps beyond the clock are never judgeable, even when every robot claims them.
    inbox2 = _inbox(5, {"r1": [far], "r2": [far]})
    assert all(_plan_step(inbox2, IDS, s) is None for s in (6, 7, far))


def test_a_robot_that_skipped_a_step_is_left_out_once_it_is_past_it() -> None:
    # Realtime: r2 fell behind and jumped from step 2 to step 4; its plan of step 3 never comes.
    inbox = _inbox(5, {"r1": [0, 1, 2, 3, 4], "r2": [0, 1, 2, 4]})
    got = _plan_step(inbox, IDS, 3)
    assert got is not None and sorted(got) == ["r1"]


def test_a_robot_whose_token_just_went_is_waited_for_then_left_out() -> None:
    """Zenoh may deliver the removal of an exiting agent's liveliness token before its last
    plan: the step waits GONE_GRACE for that plan, then is judged without the robot."""
    import time

    from supervisor.monitor import GONE_GRACE

    inbox = _inbox(6, {"r1": [0, 1, 2, 3, 4, 5], "r2": [0, 1, 2, 3, 4]})
    inbox.live = {"r1"}
    inbox.gone["r2"] = time.monotonic()  # just now: its plan of step 5 may still be on the way
    assert _plan_step(inbox, IDS, 5) is None
    inbox._store(Plan.TYPE, _plan("r2", 5), True)  # and here it is
    got = _plan_step(inbox, IDS, 5)
    assert got is not None and sorted(got) == IDS
    inbox = _inbox(6, {"r1": [0, 1, 2, 3, 4, 5], "r2": [0, 1, 2, 3, 4]})
    inbox.live = {"r1"}
    inbox.gone["r2"] = time.monotonic() - GONE_GRACE - 0.1  # gone for longer: dead
    got = _plan_step(inbox, IDS, 5)
    assert got is not None and sorted(got) == ["r1"]


def test_a_plan_whose_command_was_not_applied_is_not_what_is_checked() -> None:
    """Tick.fallback: r2's plan of step 1 was made but its command missed the deadline, so
    its robot kept to its plan of step 0.  The reference check judges that executed plan:
    the unexecuted end point, 5 cm from r1's, is no violation; had it been executed, it
    would be one.  The unexecuted plan still counts as a solve."""
    from pathlib import Path

    from ground.scenario import load_scenario
    from supervisor.judge import Judge

    scn = load_scenario(Path(__file__).resolve().parents[2] / "scenarios" / "paper_two_robots.toml")

    def plan(robot: str, step: int, end: tuple[float, float]) -> Plan:
        pl = _plan(robot, step)
        return Plan(**{**pl.__dict__, "committed": np.tile(end, (20, 1)), "footprint": 0.1})

    for unexecuted, violations in ((set(), 1), ({"r2"}, 0)):
        mon = Judge(scn)
        mon.plans({"r1": plan("r1", 0, (0.0, 0.0)), "r2": plan("r2", 0, (0.5, 0.0))})
        mon.plans({"r1": plan("r1", 1, (0.0, 0.0)), "r2": plan("r2", 1, (0.05, 0.0))}, unexecuted)
        assert mon.ref_violations == violations
        assert mon.robot["r2"]["solves"] == 2


def test_the_summary_carries_each_agents_count_of_places_heard_late() -> None:
    """Each plan carries its agent's count so far of places heard over the lag bound late; the
    summary keeps each robot's newest (the largest: a count never falls, even if its plans
    come out of order) and their sum."""
    from pathlib import Path

    from ground.scenario import load_scenario
    from supervisor.judge import Judge

    scn = load_scenario(Path(__file__).resolve().parents[2] / "scenarios" / "paper_two_robots.toml")

    def plan(robot: str, step: int, late: int) -> Plan:
        pl = _plan(robot, step)
        ends = {"r1": (0.0, 0.0), "r2": (1.0, 0.0)}
        return Plan(**{**pl.__dict__, "committed": np.tile(ends[robot], (20, 1)), "late": late})

    mon = Judge(scn)
    for k, (l1, l2) in enumerate([(0, 0), (2, 0), (5, 0), (4, 1)]):  # r1's 4 came after its 5
        mon.truth({r: (0.0, 0.0, 0.0) for r in IDS})
        mon.plans({"r1": plan("r1", k, l1), "r2": plan("r2", k, l2)})
    s = mon.summary(False, 1.0)
    assert s["robots"]["r1"]["places_heard_late"] == 5 and s["robots"]["r2"]["places_heard_late"] == 1
    assert s["places_heard_late"] == 6


def test_a_committed_reference_is_only_ever_extended() -> None:
    """``continues``: the next executed plan keeps every reference point its predecessor
    committed, with "stay put" over steps that were not executed; the judge counts a break
    (a restart, or an agent and a robot side that disagree on what was executed), but only
    where the ticks account for every step in between (a plan lost on its way is no break)."""
    from pathlib import Path

    from ground.scenario import load_scenario
    from supervisor.judge import Judge, continues

    def plan(step: int, committed: np.ndarray) -> Plan:
        return Plan(**{**_plan("r1", step).__dict__, "committed": committed})

    path = np.cumsum(np.full((40, 2), 0.01), axis=0)
    p0 = plan(0, path[1:21])
    p1 = plan(1, path[2:22])
    assert continues(p0, p1)
    stay = np.vstack([path[3:21], path[20], [0.5, 0.5]])  # step 1 not executed: "stay put" at 20
    assert continues(p0, plan(2, stay))
    moved = path[2:22].copy()
    moved[5] += 1e-9  # an earlier commitment changed
    assert not continues(p0, plan(1, moved))
    assert not continues(p0, plan(1, np.tile(path[0], (20, 1))))  # started again where it is

    scn = load_scenario(Path(__file__).resolve().parents[2] / "scenarios" / "paper_two_robots.toml")
    mon = Judge(scn)
    other = {"r2": plan(0, np.tile([0.9, 0.9], (20, 1)))}
    mon.plans({"r1": p0, **other})
    mon.plans({"r1": plan(1, path[2:22]), **other}, {"r1"})  # made, not executed
    mon.plans({"r1": plan(2, stay), **other})
    assert mon.robot["r1"]["breaks"] == 0
    mon.plans({"r1": plan(3, np.tile(path[0], (20, 1))), **other})  # a restart
    assert mon.robot["r1"]["breaks"] == 1
    mon.plans({**other})  # r1's plan of step 4 lost on the way: step 5 is not checked against 3
    mon.plans({"r1": plan(5, path[6:26]), **other})
    assert mon.robot["r1"]["breaks"] == 1


def test_the_judge_does_not_depend_on_whether_plans_or_truths_come_first() -> None:
    """The supervisor takes truths and plans as they come, and the truth of sample 0 may arrive
    after the plans of step 0 (the tracker batches truths).  The figures and the trace's
    references are the same either way: sample 0's reference is the start."""
    from pathlib import Path

    from ground.geometry import controlled_point
    from ground.scenario import load_scenario
    from supervisor.judge import Judge

    scn = load_scenario(Path(__file__).resolve().parents[2] / "scenarios" / "paper_two_robots.toml")
    ell = scn.controller.lookahead
    starts = {r.id: np.array(r.start, float) for r in scn.robots}

    def plan(robot: str, step: int) -> Plan:
        end = controlled_point(starts[robot], ell) + 0.001 * (step + 1)
        return Plan(**{**_plan(robot, step).__dict__, "committed": np.tile(end, (20, 1))})

    def run(plans_first: bool) -> Judge:
        judge = Judge(scn)
        truth0 = {r: starts[r] for r in IDS}
        truth1 = {r: starts[r] + [0.002, 0.0, 0.0] for r in IDS}
        steps = [lambda: judge.plans({r: plan(r, 0) for r in IDS}), lambda: judge.truth(truth0)]
        for s in steps if plans_first else steps[::-1]:
            s()
        judge.truth(truth1)
        return judge

    a, b = run(True), run(False)
    for r in IDS:
        assert np.array_equal(a.trace_refs(2), b.trace_refs(2))
        assert np.array_equal(a.refs[r][0], controlled_point(starts[r], ell))
        assert a.deviation(r) == b.deviation(r) > 0


def test_arrived_means_stayed_for_the_settle_time():
    """One pass through the goal is not an arrival: the controlled point must stay within the
    tolerance for SETTLE_TIME; time to goal is the start of that final stretch, and the path
    length shows the detour."""
    from ground.scenario import GOAL_TOLERANCE, settle_samples, settled_since

    Ts = 0.1
    n = settle_samples(Ts)
    near, far = 0.5 * GOAL_TOLERANCE, 2.0 * GOAL_TOLERANCE
    assert settled_since([far] * 5 + [near] * n, Ts) == 5
    assert settled_since([far] * 5 + [near] * (n - 1), Ts) is None  # not long enough yet
    assert settled_since([near] * 20 + [far], Ts) is None  # left again at the end
    assert settled_since([near] * n + [far] + [near] * (n - 1), Ts) is None


class _NoRecording:
    """Stands in for the Rerun recorder: the bookkeeping is what is under test."""

    def __getattr__(self, name: str):
        return lambda *a, **k: None


def test_a_run_whose_plans_never_came_did_not_complete() -> None:
    """The clock ran to its stop tick and every ground-truth sample came, but no agent ever
    planned (every agent exited at once): the summary must not say ``completed: true`` with
    ``steps: 0``.  With the same truths and every plan in, it completes."""
    from pathlib import Path

    from ground.scenario import load_scenario
    from ground.wire import Pose, Truth
    from supervisor.monitor import Monitor

    scn = load_scenario(Path(__file__).resolve().parents[2] / "scenarios" / "paper_two_robots.toml")
    ids = [r.id for r in scn.robots]
    assert ids == IDS
    end = 6

    def run(with_plans: bool) -> dict:
        inbox = Inbox(Keys("lab"), "test")
        inbox.live = set(ids)
        inbox._store(Tick.TYPE, Tick(robot="tracker", step=end, t=0.1 * end, stop=True, misses=0), False)
        for k in range(end + 1):
            for i, r in enumerate(ids):
                for typ in (Truth, Pose):
                    inbox._store(typ.TYPE, typ(robot=r, seq=k, t=0.1 * k, x=0.3 * i, y=0.0, theta=0.0), True)
                if with_plans and k < end:
                    inbox._store(Plan.TYPE, _plan(r, k), True)
        watch = Monitor(scn, inbox, _NoRecording())  # type: ignore[arg-type]
        watch.ids = ids
        watch.take()
        done = watch.finished()
        if done is None:  # waiting for plans that will not come: let the grace period lapse
            watch.stop_deadline = 1.0
            done = watch.finished()
        assert done is not None
        return watch.summary(done)

    s = run(with_plans=False)
    assert (s["completed"], s["steps"]) == (False, 0), s
    s = run(with_plans=True)
    assert (s["completed"], s["steps"]) == (True, end), s


def _judge_and_plan():
    """A judge of the two-robot scene, and a plan maker with end point and discs."""
    from pathlib import Path

    from ground.scenario import load_scenario
    from supervisor.judge import Judge

    scn = load_scenario(Path(__file__).resolve().parents[2] / "scenarios" / "paper_two_robots.toml")

    def plan(
        robot: str, step: int, end=(0.0, 0.0), status="PROXQP_SOLVED", discs=None, blocked="", no_room=""
    ):
        pl = _plan(robot, step)
        return Plan(**{
            **pl.__dict__, "committed": np.tile(end, (20, 1)), "status": status, "discs": discs or {},
            "blocked": blocked, "no_room": no_room,
        })  # fmt: skip

    return Judge(scn), plan, scn.controller


def test_a_disc_that_claims_a_robot_is_judged_against_its_true_body() -> None:
    """A dead or braked robot's disc claims to hold its true body from then on (docs/method.md
    §6.4): the judge checks the body (robot_radius + ℓ about the true controlled point) against
    the disc at the sample of the plan's step, whichever of the two comes first, and counts an
    escape with its excess; a stale disc (about a reference, not a body) claims nothing."""
    from ground.geometry import axle_centre

    judge, plan, p = _judge_and_plan()
    body = p.robot_radius + p.lookahead
    inside = axle_centre((0.5, 0.0), 0.0, p.lookahead)  # the true controlled point at (0.5, 0)
    r1 = (-0.5, 0.0, 0.0)
    # Step 0: r1 keeps clear of r2 as dead, a disc of radius body + 1 cm about (0.5, 0).
    judge.plans({"r1": plan("r1", 0, discs={"r2": ("dead", False, 0.5, 0.0, body + 0.01)})})
    judge.truth({"r1": r1, "r2": (*inside, 0.0)})  # the truth after the plans: held
    # Step 1: the truth first, 3 cm off the centre: the body leaves the disc by 2 cm.
    judge.truth({"r1": r1, "r2": (inside[0] + 0.03, inside[1], 0.0)})
    judge.plans({"r1": plan("r1", 1, discs={"r2": ("braked", True, 0.5, 0.0, body + 0.01)})})
    # Step 2: a stale disc claims nothing.
    judge.truth({"r1": r1, "r2": (inside[0] + 0.3, inside[1], 0.0)})
    judge.plans({"r1": plan("r1", 2, discs={"r2": ("stale", False, 0.5, 0.0, body + 0.01)})})
    s = judge.summary(False, 1.0)
    assert s["robots"]["r2"]["disc_escapes"] == 1 and s["disc_escapes"] == 1
    assert s["max_disc_escape_m"] == pytest.approx(0.02)
    kept = s["robots"]["r2"]["kept_clear_as"]
    assert kept["dead"] == kept["braked"] == 1 and kept["largest_disc_m"] == pytest.approx(body + 0.01)
    assert s["robots"]["r1"]["kept_clear_as"]["largest_disc_m"] is None


def test_a_robot_that_does_not_follow_its_reference_is_left_out_of_the_separation_check() -> None:
    """A robot its robot side braked (Tick.braked), or whose agent holds (blind, link down), does
    not follow its committed reference: the others are kept clear of its body by its disc, so its
    stale reference is not compared with theirs until it has an executed plan of its own again."""
    judge, plan, _ = _judge_and_plan()
    judge.plans({"r1": plan("r1", 0, (0.0, 0.0)), "r2": plan("r2", 0, (0.5, 0.0))})
    judge.plans({"r1": plan("r1", 1, (0.45, 0.0))}, {"r2"}, {"r2"})  # r2 braked: r1 comes close
    assert judge.ref_violations == 0 and "r2" in judge.off
    judge.plans({"r1": plan("r1", 2, (0.45, 0.0)), "r2": plan("r2", 2, (0.5, 0.0))})  # back: judged
    assert judge.ref_violations == 1 and not judge.off
    judge.plans({"r1": plan("r1", 3, (0.45, 0.0)), "r2": plan("r2", 3, (0.5, 0.0), status="HOLD_LINK_DOWN")})
    assert judge.ref_violations == 1 and judge.robot["r2"]["held_link_down"] == 1


def test_a_robot_whose_plan_never_reached_the_supervisor_is_not_judged_on_a_stale_reference() -> None:
    """A plan of step k that the supervisor never got (lost on the way, or its agent left out as
    gone while the supervisor's own lease lapsed) says nothing of where that robot's reference
    is: its old reference is not compared with the others' new ones.  Had the tick reported the
    plan unexecuted, the robot would have kept to its last one, and that is compared."""
    judge, plan, _ = _judge_and_plan()
    judge.plans({"r1": plan("r1", 0, (0.0, 0.0)), "r2": plan("r2", 0, (0.5, 0.0))})
    judge.plans({"r1": plan("r1", 1, (0.45, 0.0))})  # r2's plan of step 1 lost: not judged
    assert judge.ref_violations == 0 and judge.min_ref == pytest.approx(0.5)
    judge.plans({"r1": plan("r1", 2, (0.45, 0.0))}, {"r2"})  # r2 kept to its plan: judged
    assert judge.ref_violations == 1


def test_a_new_goal_counts_from_the_step_after_its_plan_in_whatever_order_the_judge_gets_them() -> None:
    """r2's plan of step 0 heads for a new goal, where r2 then stands.  In process the sample
    of step 1 is judged after that plan; a supervisor that fell behind takes the samples first.
    Either way every sample from step 1 on is measured against the new goal, and r2 arrives."""
    from ground.geometry import axle_centre

    results = []
    for plans_first in (True, False):
        judge, plan, p = _judge_and_plan()
        new = np.array([0.3, 0.4])
        at = (*axle_centre(tuple(new), 0.0, p.lookahead), 0.0)
        poses = {"r1": (-0.7, 0.0, 0.0), "r2": at}
        judge.truth(poses)  # sample 0
        step0 = {"r1": plan("r1", 0), "r2": Plan(**{**plan("r2", 0).__dict__, "goal": new})}
        if plans_first:
            judge.plans(step0)
        for _ in range(40):
            judge.truth(poses)
        if not plans_first:
            judge.plans(step0)
        s = judge.summary(True, 1.0)
        results.append((s["robots"]["r2"]["reached_goal"], s["robots"]["r2"]["final_error_m"]))
    assert results[0] == results[1] and results[0][0] and results[0][1] < 1e-9


def test_link_outages_count_as_uncontrolled_time_however_they_are_seen() -> None:
    """The supervisor sees each robot's newest LinkState at each look: an outage counts from the
    tick it was lost at to the tick the link saw it up again, also when it began and ended
    between two looks, and an outage still open counts to the last step judged."""
    judge, plan, p = _judge_and_plan()
    judge.link_state("r1", False, 12, 10)
    judge.link_state("r1", False, 15, 10)
    judge.link_state("r1", True, 20, 10)  # 10 steps down
    judge.link_state("r1", True, 21, 10)  # the same outage, seen again: nothing more
    judge.link_state("r1", True, 40, 33)  # lost at 33 and back by 40 between two looks: 7 more
    judge.link_state("r2", False, 50, 45)  # still down at the end
    for k in range(60):
        judge.plans({"r1": plan("r1", k), "r2": plan("r2", k, (0.5, 0.0))})
    s = judge.summary(False, 1.0)
    assert s["robots"]["r1"]["uncontrolled_s"] == pytest.approx(17 * p.Ts)
    assert s["robots"]["r2"]["uncontrolled_s"] == pytest.approx((60 - 45) * p.Ts)


def test_the_verdict_and_the_faults_line_name_what_faults_did() -> None:
    """A goal a stopped robot covers is named with it; arena violations fail a run and name the
    robot; the faults line names lost links with their uncontrolled time, the robots kept clear of
    with the largest disc, and the blocked goals."""
    from supervisor.judge import fault_note, verdict

    judge, plan, _ = _judge_and_plan()
    judge.truth({"r1": (-0.5, 0.0, 0.0), "r2": (5.0, 0.0, 0.0)})  # r2 far off the arena
    judge.plans({
        "r1": plan("r1", 0, discs={"r2": ("loose", False, 5.0, 0.0, 0.3)}, blocked="r2"),
        "r2": plan("r2", 0, (0.5, 0.0), status="HOLD_LINK_DOWN"),
    })  # fmt: skip
    judge.link_state("r2", False, 3, 0)
    s = judge.summary(True, 1.0)
    assert s["robots"]["r1"]["goal_blocked_by"] == "r2" and s["robots"]["r2"]["arena_violations"] == 1
    why = verdict(s)
    assert why is not None and "1 arena violation samples (r2)" in why and "r1 (goal blocked by r2)" in why
    note = fault_note(s)
    assert note is not None and "links lost" not in note  # no loss counted yet
    judge.link_lost("r2")
    note = fault_note(judge.summary(True, 1.0))
    assert note is not None and "links lost: r2 1×" in note
    assert "r2 (uncontrolled 1 steps; largest disc 0.300 m)" in note and "goals blocked: r1 by r2" in note


def test_a_robot_with_no_room_to_make_way_is_named_while_it_has_none() -> None:
    """Assumption (A) failing as the run goes: each time a robot's plan says it found no room to
    make way for a robot that goes first, an episode opens, naming both, and it closes at the
    first plan with room again; the steps are counted, and a robot that ends the run without
    room and away from its goal is named so in the verdict."""
    from supervisor.judge import verdict

    judge, plan, _ = _judge_and_plan()
    says = ["", "r2", "r2", "", "r2", "r2"]
    for k, by in enumerate(says):
        judge.truth({"r1": (-0.5, 0.0, 0.0), "r2": (0.5, 0.0, 0.0)})
        judge.plans({"r1": plan("r1", k, (-0.5, 0.0), no_room=by), "r2": plan("r2", k, (0.5, 0.0))})
    s = judge.summary(True, 1.0)
    assert s["no_room"] == [
        {"robot": "r1", "for": "r2", "from_step": 1, "to_step": 3},
        {"robot": "r1", "for": "r2", "from_step": 4, "to_step": None},
    ]
    assert s["robots"]["r1"]["no_room_steps"] == 4 and s["robots"]["r1"]["no_room_for"] == "r2"
    assert s["robots"]["r2"]["no_room_steps"] == 0 and s["robots"]["r2"]["no_room_for"] is None
    why = verdict(s)
    assert why is not None and "r1 (no room to make way for r2)" in why


def test_the_supervisor_says_when_a_robot_has_no_room_to_make_way_and_when_that_ends() -> None:
    """The same, seen in Rerun: the supervisor's events (its recorder's ``event``) carry a
    warning naming both robots when a plan says it found no room, and a line when a plan no
    longer says so."""
    from ground.wire import Pose, Truth
    from supervisor.monitor import Monitor

    class Events:
        def __init__(self) -> None:
            self.said: list[tuple[str, str]] = []

        def event(self, text: str, level: str = "INFO") -> None:
            self.said.append((text, level))

        def __getattr__(self, name: str):
            return lambda *a, **k: None

    judge, plan, _ = _judge_and_plan()
    inbox = Inbox(Keys("lab"), "test")
    inbox.live = set(IDS)
    says = ["", "r2", "r2", ""]
    inbox._store(
        Tick.TYPE, Tick(robot="tracker", step=len(says), t=0.1 * len(says), stop=True, misses=0), False
    )
    for k, by in enumerate(says):
        for i, r in enumerate(IDS):
            for typ in (Truth, Pose):
                inbox._store(typ.TYPE, typ(robot=r, seq=k, t=0.1 * k, x=0.5 * i, y=0.0, theta=0.0), True)
        inbox._store(Plan.TYPE, plan("r1", k, no_room=by), True)
        inbox._store(Plan.TYPE, plan("r2", k, (0.5, 0.0)), True)
    events = Events()
    watch = Monitor(judge.scn, inbox, events)  # type: ignore[arg-type]
    watch.ids = list(IDS)
    watch.take()
    said = [e for e in events.said if "room" in e[0]]
    assert said == [
        ("no_room: r1: no room to make way for r2", "WARN"),
        ("r1: no longer without room to make way", "INFO"),
    ]


def test_parked_robots_that_wall_in_a_way_home_are_named_while_they_do() -> None:
    """The run-time half of assumption (B) (docs/method.md §7): a robot parked at the mouth of
    a dead-end pocket walls in the way of the robot whose goal is deeper.  The judge names it,
    within a check period, and ends the episode once the parked robot has stepped out; a robot
    parked off the way walls in nothing."""
    from fleet.running.scenes import EPUCK_FOOTPRINT, pocket
    from ground.scenario import parse_scenario
    from supervisor.judge import WALL_CHECK_STEPS, Judge, verdict

    scn = parse_scenario(pocket(0.30, depth=2 * 0.2782 + 0.2, robots=2))
    deep, mouth = (np.array(r.goal) for r in scn.robots)
    outside = np.array([0.6, -0.7])
    judge = Judge(scn)

    def plan(robot: str, step: int, end, phase: int) -> Plan:
        return Plan(
            robot=robot, step=step, t0=0.1 * (step + 1), Ts=0.1, committed=np.tile(end, (20, 1)),
            nominal=np.zeros((21, 2)), footprint=EPUCK_FOOTPRINT, priority=0, rank=int(robot[1:]) - 1,
            phase=phase, target=np.zeros(2), goal=deep if robot == "r1" else mouth,
            status="PROXQP_SOLVED", solve_time=1e-4, tube_ok=True,
        )  # fmt: skip

    def step(k: int, r2_at, r2_phase: int) -> None:
        judge.plans({"r1": plan("r1", k, outside, 0), "r2": plan("r2", k, r2_at, r2_phase)})

    for k in range(WALL_CHECK_STEPS + 1):  # r2 parked at the mouth, r1 outside
        step(k, mouth, 2)
    assert judge.walled == {"r1": ["r2"]}
    for k in range(WALL_CHECK_STEPS + 1, 2 * WALL_CHECK_STEPS + 1):  # r2 steps out, returning
        step(k, np.array([-0.6, -0.7]), 1)
    assert judge.walled == {}
    assert judge.walled_episodes == [
        {"robot": "r1", "by": ["r2"], "from_step": 0, "to_step": 2 * WALL_CHECK_STEPS}
    ]
    for k in range(2 * WALL_CHECK_STEPS + 1, 3 * WALL_CHECK_STEPS + 1):  # parked out of the way
        step(k, np.array([-0.6, -0.7]), 2)
    assert judge.walled == {} and len(judge.summary(True, 1.0)["walled_in"]) == 1
    for k in range(3 * WALL_CHECK_STEPS + 1, 4 * WALL_CHECK_STEPS + 1):  # back at the mouth
        step(k, mouth, 2)
    assert judge.summary(True, 1.0)["robots"]["r1"]["walled_in_by"] == ["r2"]
    assert "r1 (way home walled in by r2)" in (verdict(judge.summary(True, 1.0)) or "")


def test_parked_robots_that_step_aside_are_named_and_a_pair_that_does_so_in_turn_is_flagged() -> None:
    """The run-time side of the queue of docs/method.md §7: each time a parked robot leaves its
    goal (its plan's phase goes parked → returning) the judge records a displacement, for the
    nearest robot that moves, and ends it when the robot parks again.  Two robots that displace
    each other in turn, the same one for the same other a second time, are the cycle the
    progress argument does not rule out: the summary and the verdict name them."""
    from pathlib import Path

    from ground.scenario import load_scenario
    from ground.wire import PARKED, RETURNING, UNDER_WAY
    from supervisor.judge import Judge, verdict

    scn = load_scenario(Path(__file__).resolve().parents[2] / "scenarios" / "paper_three_robots.toml")
    judge = Judge(scn)
    at = {"r1": (0.0, 0.0), "r2": (0.3, 0.0), "r3": (0.8, 0.0)}

    def step(k: int, phases: dict[str, int]) -> None:
        plans = {}
        for i, r in enumerate(("r1", "r2", "r3")):
            pl = _plan("r1", k)
            end = np.tile(at[r], (20, 1))
            plans[r] = Plan(**{**pl.__dict__, "robot": r, "rank": i, "phase": phases[r], "committed": end})
        judge.plans(plans)

    P, R, U = PARKED, RETURNING, UNDER_WAY
    step(0, {"r1": P, "r2": U, "r3": U})
    step(1, {"r1": R, "r2": U, "r3": U})  # r1 steps aside, for r2 (nearer than r3)
    assert judge.displaced == [{"robot": "r1", "for": "r2", "from_step": 1, "to_step": None}]
    step(2, {"r1": R, "r2": P, "r3": P})
    step(3, {"r1": R, "r2": R, "r3": P})  # r2 for r1, the only robot that moves
    assert judge.news == [{"robot": "r2", "for": "r1", "traded": 0}]  # said as an event, no trade yet
    step(4, {"r1": P, "r2": R, "r3": P})  # r1 home again
    assert [ep["to_step"] for ep in judge.displaced] == [4, None]
    assert judge.traded() == []  # each has stepped aside for the other once: not yet a cycle
    step(5, {"r1": R, "r2": R, "r3": P})  # r1 for r2 again: the pair is back where it was
    assert judge.news == [{"robot": "r1", "for": "r2", "traded": 2}]
    s = judge.summary(True, 1.0)
    assert s["displacements"] == 3 and len(s["displaced"]) == 3
    assert s["traded_places"] == [{"robots": ["r1", "r2"], "turns": 2}]
    assert [s["robots"][r]["displaced"] for r in ("r1", "r2", "r3")] == [2, 1, 0]
    assert s["robots"]["r1"]["traded_places_with"] == ["r2"] and s["robots"]["r3"]["traded_places_with"] == []
    assert "r1 (traded places with r2)" in (verdict(s) or "")
