"""The experiment API on a fleet of processes (``Fleet.launch(..., processes=True)``) and on a
running fleet (``Fleet.connect``), seen from outside: the same script gives the same run as in
process, refusals change nothing, timeouts are in the fleet's clock, and no process outlives the
script, whether it ends, raises, is interrupted like a notebook cell, or is killed."""

from __future__ import annotations

import json
import os
import select
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from fleet import Fleet, GoalRefused
from fleet.running.launch import start_fleet
from transport.net import free_port, loopback

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[2]
TWO = ROOT / "scenarios" / "paper_two_robots.toml"
SWAP4 = ROOT / "scenarios" / "swap_4.toml"
WAIT = 120.0
"""Bound of every wait on a process [s]."""


def _script(fleet: Fleet) -> list[tuple[float, float, float]]:
    """One script for both sides: a wait, a goal, a formation, a timeout."""
    assert fleet.wait(1.0) is None and fleet.step == 10
    fleet.goto({"r2": (0.3, -0.45)})
    assert fleet.wait_arrived(["r2"], timeout=60)
    fleet.formation([(0.0, 0.5), (0.0, -0.5)])
    assert fleet.wait_arrived(timeout=0.3) is False  # three steps, then False: the fleet runs on
    assert fleet.wait_arrived(timeout=90)
    return [fleet.poses()[r] for r in fleet.ids]


@pytest.mark.parametrize("ahead", [False, True], ids=["solve-after-tick", "delay-compensation"])
def test_the_same_script_gives_the_same_run_in_process_and_as_processes(tmp_path, ahead):
    """Bit for bit: every true pose of every sample, the final measured poses, the events and
    the summary's figures; the processes are ended when the block ends.  With delay
    compensation too: a goal given at sample k is taken by the plans of step k + 1 on, on both
    sides, whenever the agent's plan of step k is made."""
    runs = {}
    for processes in (False, True):
        out = tmp_path / ("processes" if processes else "in_process")
        with Fleet.launch(
            TWO, clock="lockstep", seed=4, processes=processes, out=out, delay_compensation=ahead
        ) as fleet:
            final = _script(fleet)
            # The events of the steps a process fleet has judged by now (a plan's fallback
            # may come a step after its sample), in one order.
            events = sorted(
                (e.step, e.robot, e.kind, e.detail) for e in fleet.events() if e.step < fleet.step - 1
            )
            pids = fleet.processes
        assert (len(pids) == 4) is processes  # tracker, supervisor, two agents
        assert _gone(list(pids.values()), timeout=1.0) == []  # ended when the block ended
        runs[processes] = (final, events, fleet.summary, np.load(out / "trace.npz")["poses"])
    (f0, e0, s0, p0), (f1, e1, s1, p1) = runs[False], runs[True]
    assert f0 == f1
    assert e0 == e1 and [k for _, _, k, _ in e0].count("arrived") >= 2
    assert p0.shape == p1.shape and np.array_equal(p0, p1)
    for key in ("steps", "collisions", "min_distance_m", "min_reference_separation_m", "all_goals_reached"):
        assert s0 is not None and s1 is not None and s0[key] == s1[key], key
    assert s1 is not None and s1["exit_codes"] == dict.fromkeys(s1["processes"], 0)
    assert s0.get("delay_compensation", False) is s1.get("delay_compensation", False) is ahead
    assert (tmp_path / "processes" / "fleet.log").read_text().count("stopped after") == 2


def test_refusals_and_the_agents_answers_on_processes(tmp_path):
    with Fleet.launch(SWAP4, seed=3, processes=True, out=tmp_path) as fleet:
        before = fleet.goals()
        with pytest.raises(GoalRefused) as info:
            fleet.goto({"r1": (0.1, 0.1), "r2": (0.1, 0.2)})  # too close to each other
        assert info.value.robot == "r1" and "r2's goal" in info.value.reason
        assert fleet.goals() == before
        fleet.goto({"r1": before["r3"], "r3": before["r1"]})  # a swap: one batch, both agents accept
        assert fleet.goals()["r1"] == before["r3"] and fleet.goals()["r3"] == before["r1"]
        assert fleet.wait_arrived(["r1", "r3"], timeout=120)
    assert fleet.summary is not None
    assert fleet.summary["robots"]["r1"]["goal"] == list(before["r3"])
    assert fleet.summary["robots"]["r1"]["reached_goal"]


def test_connect_joins_a_running_fleet_and_leaves_it_running(tmp_path):
    """A fleet started as `fleet run` starts it (not scripted, lockstep): a script joins it by
    its hub, reads it, gives a goal its agent acknowledges, and leaves; the fleet runs on."""
    hub = loopback(free_port())
    log = (tmp_path / "fleet.log").open("w")
    fl = start_fleet(str(TWO), ["r1", "r2"], tmp_path, seed=2, clock="realtime", hub=hub, stderr=log)
    try:
        with Fleet.connect(TWO, connect=hub) as fleet:
            assert set(fleet.poses()) == {"r1", "r2"} and fleet.step >= 0
            assert fleet.processes == {}
            k = fleet.step
            fleet.goto({"r1": (0.3, 0.5)})  # acknowledged by r1's agent
            fleet.wait(0.5)
            assert fleet.step >= k + 1  # the fleet's own clock, not held
            assert fleet.goals()["r1"] == (0.3, 0.5)
        assert fleet.summary is None
        assert all(p.popen.poll() is None for p in fl.procs)  # nothing stopped by leaving
    finally:
        fl.stop()
        log.close()
    assert "[agent r1] new goal [0.3, 0.5]" in (tmp_path / "fleet.log").read_text()


SCRIPT = """
import json, signal, sys
from fleet import Fleet
fleet = Fleet.launch({scenario!r}, seed=1, processes=True, out={out!r})
print(json.dumps(fleet.processes), flush=True)
mode = sys.argv[1]
if mode == "raise":
    with fleet:
        fleet.wait(0.5)
        raise RuntimeError("the script failed")
if mode == "interrupt":
    # As a notebook's kernel does (and pytest's workers ignore SIGINT, which children inherit).
    signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        print("waiting", flush=True)
        fleet.wait(10_000)
    except KeyboardInterrupt:
        print(f"interrupted at {{fleet.step}}", flush=True)
    k = fleet.step
    fleet.goto({{"r1": (0.2, 0.4)}})
    ok = fleet.wait_arrived(["r1"], timeout=60)
    summary = fleet.close()
    print(f"after {{fleet.step - k}} steps: arrived {{ok}}, steps {{summary['steps']}}", flush=True)
    sys.exit(0)
fleet.wait(1.0)
print("waiting", flush=True)
fleet.wait(10_000)
"""


def _start_script(tmp_path: Path, mode: str) -> tuple[subprocess.Popen[str], dict[str, int]]:
    path = tmp_path / "script.py"
    path.write_text(textwrap.dedent(SCRIPT.format(scenario=str(TWO), out=str(tmp_path / "run"))))
    env = {**os.environ, "RERUN_ANALYTICS": "0", "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen(
        [sys.executable, str(path), mode],
        stdout=subprocess.PIPE,
        stdin=subprocess.DEVNULL,
        text=True,
        env=env,
    )
    assert proc.stdout is not None
    pids = json.loads(_line(proc))
    assert len(pids) == 4
    return proc, pids


def _line(proc: subprocess.Popen[str]) -> str:
    """The script's next line of output, within WAIT seconds (read from the pipe a byte at a
    time: a buffered reader would hide a second line from select)."""
    assert proc.stdout is not None
    fd, got = proc.stdout.fileno(), b""
    deadline = time.monotonic() + WAIT
    while not got.endswith(b"\n"):
        ready, _, _ = select.select([fd], [], [], max(0.0, deadline - time.monotonic()))
        assert ready, f"the script printed nothing more after {got!r}"
        byte = os.read(fd, 1)
        assert byte, f"the script closed its output after {got!r} (exit {proc.poll()})"
        got += byte
    return got.decode()


def _gone(pids: list[int], timeout: float = WAIT) -> list[int]:
    """Wait (on pidfds, no polling) until every process has ended; those still running after
    ``timeout`` [s]."""
    fds = {}
    for pid in pids:
        try:
            fds[os.pidfd_open(pid)] = pid
        except ProcessLookupError:
            continue
    deadline = time.monotonic() + timeout
    try:
        while fds and (left := deadline - time.monotonic()) > 0:
            ready, _, _ = select.select(list(fds), [], [], left)
            for fd in ready:
                os.close(fd)
                del fds[fd]
        return sorted(fds.values())
    finally:
        for fd in fds:
            os.close(fd)


def _kill_all(pids: list[int]) -> None:
    for pid in pids:
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass


@pytest.mark.parametrize("how", [signal.SIGKILL, signal.SIGTERM])
def test_a_killed_script_leaves_no_process_behind(tmp_path, how):
    """The tracker sees the script's liveliness token go and ends the run; every process exits
    on its own, and the supervisor still writes the summary."""
    proc, pids = _start_script(tmp_path, "wait")
    try:
        assert _line(proc).strip() == "waiting"
        proc.send_signal(how)
        assert proc.wait(timeout=WAIT) == -how
        assert _gone(list(pids.values())) == []
        assert json.loads((tmp_path / "run" / "summary.json").read_text())["steps"] >= 10
        log = (tmp_path / "run" / "fleet.log").read_text()
        assert "the script left the fleet" in log
    finally:
        proc.kill()
        _kill_all(list(pids.values()))


def test_an_exception_in_the_block_ends_every_process(tmp_path):
    proc, pids = _start_script(tmp_path, "raise")
    try:
        assert proc.wait(timeout=WAIT) == 1
        assert _gone(list(pids.values()), timeout=1.0) == []  # gone before the script exited
    finally:
        proc.kill()
        _kill_all(list(pids.values()))


def test_an_interrupted_wait_leaves_the_fleet_usable(tmp_path):
    """As in a notebook: SIGINT during a wait raises KeyboardInterrupt in the script, and the
    fleet goes on: a goal, a wait, a clean close."""
    proc, pids = _start_script(tmp_path, "interrupt")
    try:
        assert _line(proc).strip() == "waiting"
        proc.send_signal(signal.SIGINT)
        assert _line(proc).startswith("interrupted at ")
        last = _line(proc)
        assert last.startswith("after ") and "arrived True" in last, last
        assert proc.wait(timeout=WAIT) == 0
        assert _gone(list(pids.values()), timeout=1.0) == []
    finally:
        proc.kill()
        _kill_all(list(pids.values()))


@pytest.mark.parametrize("ahead", [False, True], ids=["solve-after-tick", "delay-compensation"])
def test_fleet_run_follows_the_missions_as_fleet_simulate_does(tmp_path, ahead):
    """A scenario with missions, as processes: the same steps, figures and waypoints as the
    in-process simulator, every process exiting 0; with delay compensation too (the first
    waypoints, given at sample 0, are taken by the plans of step 1 on, on both sides)."""
    from fleet.cli import main

    patrol = str(ROOT / "scenarios" / "patrol_two.toml")
    flag = ["--delay-compensation"] if ahead else ["--no-delay-compensation"]
    assert main(["simulate", patrol, "--out", str(tmp_path / "sim"), *flag]) == 0
    assert main(["run", patrol, "--out", str(tmp_path / "run"), *flag]) == 0
    sim, run = (json.loads((tmp_path / d / "summary.json").read_text()) for d in ("sim", "run"))
    assert sim.get("delay_compensation", False) is run.get("delay_compensation", False) is ahead
    assert run["waypoints_reached"] == sim["waypoints_reached"] == {"r1": 5, "r2": 5}
    for key in ("steps", "min_distance_m", "min_reference_separation_m", "all_goals_reached"):
        assert run[key] == sim[key], key
    assert set(run["exit_codes"].values()) == {0}


def test_events_report_an_agent_that_dies(tmp_path):
    """An agent killed mid-run: the script hears that it left, and that its robot side braked
    instead of applying its commands; the run's verdict names the process."""
    with Fleet.launch(TWO, seed=1, processes=True, out=tmp_path) as fleet:
        fleet.wait(0.5)
        pid = fleet.processes["agent r2"]
        os.kill(pid, signal.SIGKILL)
        assert _gone([pid]) == []
        fleet.wait(2.0)  # lockstep goes on without it, its robot braked
        evs = list(fleet.events())
        assert [e.robot for e in evs if e.kind == "dead_neighbour"] == ["r2"]
        misses = [e for e in evs if e.kind == "deadline_miss"]
        assert misses and {e.robot for e in misses} == {"r2"} and "braked" in misses[0].detail
        assert all(e.step >= 5 for e in misses)
    assert fleet.verdict is not None and "agent r2" in fleet.verdict


def test_a_realtime_fleet_runs_on_the_wall_clock_and_ends_with_the_script(tmp_path):
    with Fleet.launch(TWO, clock="realtime", seed=1, processes=True, out=tmp_path) as fleet:
        t0, k0 = time.monotonic(), fleet.step
        fleet.wait(2.0)  # the fleet's clock: wall time, not held by the script
        assert fleet.step >= k0 + 20 and time.monotonic() - t0 >= 1.8
        assert fleet.wait_arrived(timeout=60)
        pids = list(fleet.processes.values())
    assert _gone(pids, timeout=1.0) == []
    assert fleet.summary is not None and fleet.summary["all_goals_reached"] and fleet.verdict is None


@pytest.mark.parametrize("hold", [True, False])
def test_a_plan_that_trails_the_samples_is_stale_only_where_the_clock_runs_on(hold):
    """A live agent's plan comes on that agent's own link, which a script's session may serve
    after the tracker's.  On a held lockstep clock the plan cannot be missing, only late, so
    the script waits for it (bounded) and reports no stale neighbour; on a running clock a
    plan not in a step later is reported, as before."""
    import threading

    import zenoh

    from fleet.experiment.script import ProcessFleet
    from ground.scenario import load_scenario
    from ground.wire import Keys, Plan
    from transport.net import NetConfig

    scn = load_scenario(TWO)
    keys = Keys("trail")
    session = zenoh.open(NetConfig(listen=[loopback(free_port())]).zenoh())
    pf = ProcessFleet(scn, session, keys, hold=hold)
    try:
        z = np.zeros((20, 2))
        plan = {
            rid: Plan(
                robot=rid, step=0, t0=0.1, Ts=0.1, committed=z, nominal=np.zeros((21, 2)), footprint=0.134,
                priority=0, rank=i, phase=0, target=z[0], goal=z[0], status="solved", solve_time=0.0,
                tube_ok=True,
            )
            for i, rid in enumerate(pf.ids)
        }  # fmt: skip

        def deliver(rid: str) -> None:
            pf.inbox._accept(keys.plan(rid), plan[rid].encode(), Plan, True, time.monotonic())

        with pf.inbox.cond:
            pf.inbox.live |= set(pf.ids)
        deliver("r1")
        pf._collect_events(0)  # r2's plan of step 0 is not in yet: looked for again at step 1
        late = threading.Timer(0.3, deliver, ("r2",))
        late.start()
        try:
            pf._collect_events(1)
        finally:
            late.join(5.0)
        stale = [(e.step, e.robot) for e in pf._events if e.kind == "stale_neighbour"]
        assert stale == ([] if hold else [(0, "r2")])
    finally:
        pf.close()  # and the session
