"""A fleet of processes driven by a script (``start_fleet(..., scripted=True)``, lockstep).

This test plays the script: its own Zenoh session on the fleet's hub (loopback, scouting off),
the script's liveliness token, the permits on ``fleet/F/script`` and the goals as queries on
``fleet/F/goal/R``.  Checked from outside: the tracker publishes no tick of a step before the
step's permit; a goal sent at sample k is acknowledged and carried by the plan of step k + 1,
not before (the agents plan a step ahead, by default); a goal in an obstacle or on another
robot's goal is refused with the reason and changes nothing; two robots trade goals in one
batch; a stop ends the run with every process exiting 0 and a summary; a hold longer than the
agents' ``--timeout`` ends nothing; and a script that leaves without a stop ends the run.
Every wait is bounded and waits on a message, a log line or a process, never on a clock.
"""

from __future__ import annotations

import contextlib
import os
import re
import subprocess
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import msgpack
import numpy as np

from fleet.running.launch import Launched, start_fleet
from ground.wire import SCRIPT, Goal, Keys, Plan, Script, Tick, Truth, decode
from transport.net import NetConfig, loopback

ROOT = Path(__file__).resolve().parents[2]
KEYS = Keys("lab")
ROBOTS = ["r1", "r2"]
HOME = {"r1": (0.7, 0.0), "r2": (-0.7, 0.0)}
"""The scenario's goals."""
WAIT = 60.0
"""Bound of every wait on the fleet [s]."""


def _scene(tmp_path: Path) -> Path:
    """The paper's two robots, with a disc off their way: a goal inside it must be refused."""
    path = tmp_path / "two_robots_and_a_disc.toml"
    text = (ROOT / "scenarios" / "paper_two_robots.toml").read_text()
    path.write_text(text + "\n[[obstacles]]\ncircle = { center = [0.0, 0.7], radius = 0.1 }\n")
    return path


class Log:
    """The fleet's log lines, read from a pipe its processes write their stderr to."""

    def __init__(self, fd: int):
        self.lines: list[str] = []
        self.cond = threading.Condition()
        self.thread = threading.Thread(target=self._pump, args=(fd,), daemon=True)
        self.thread.start()

    def _pump(self, fd: int) -> None:
        with os.fdopen(fd, "r", errors="replace") as stream:
            for line in stream:
                with self.cond:
                    self.lines.append(line.rstrip("\n"))
                    self.cond.notify_all()

    def wait_for(self, pred: Callable[[str], bool], timeout: float = WAIT) -> bool:
        with self.cond:
            return self.cond.wait_for(lambda: pred("\n".join(self.lines)), timeout)

    def text(self) -> str:
        with self.cond:
            return "\n".join(self.lines)


class Player:
    """This test as the fleet's script: what it received, in order, and what it sends."""

    def __init__(self, hub: str):
        import zenoh

        self.session = zenoh.open(NetConfig(listen=[loopback(0)], connect=[hub]).zenoh())
        self.cond = threading.Condition()
        self.events: list[tuple[str, str, int]] = []
        """In order of arrival: ("truth", robot, sample), ("plan", robot, step), ("tick", "", step),
        and ("permit", "", step) when this script sent one."""
        self.plans: dict[tuple[str, int], Plan] = {}
        self.live: set[str] = set()
        self.token: Any = None

        def on(typ: type) -> Callable[[Any], None]:
            def cb(sample: Any) -> None:
                msg = decode(sample.payload.to_bytes(), typ)
                with self.cond:
                    if isinstance(msg, Plan):
                        self.plans[(msg.robot, msg.step)] = msg
                        self.events.append(("plan", msg.robot, msg.step))
                    elif isinstance(msg, Truth):
                        self.events.append(("truth", msg.robot, msg.seq))
                    elif not msg.stop:
                        self.events.append(("tick", "", msg.step))
                    self.cond.notify_all()

            return cb

        def on_token(sample: Any) -> None:
            rid = str(sample.key_expr).rsplit("/", 1)[-1]
            with self.cond:
                (self.live.discard if sample.kind == zenoh.SampleKind.DELETE else self.live.add)(rid)
                self.cond.notify_all()

        self.subs = [
            self.session.declare_subscriber(KEYS.truth(), on(Truth)),
            self.session.declare_subscriber(KEYS.plan(), on(Plan)),
            self.session.declare_subscriber(KEYS.clock, on(Tick)),
            self.session.liveliness().declare_subscriber(KEYS.alive(), on_token, history=True),
        ]
        self.pub = self.session.declare_publisher(
            KEYS.script, congestion_control=zenoh.CongestionControl.BLOCK, express=True
        )

    def join(self) -> None:
        """Declare the script's token once the fleet is live in this session's view (the
        tracker starts step 0 when it sees the token)."""
        everyone = {*ROBOTS, "supervisor", "tracker"}
        with self.cond:
            assert self.cond.wait_for(lambda: everyone <= self.live, WAIT), sorted(self.live)
        self.token = self.session.liveliness().declare_token(KEYS.alive(SCRIPT))

    def _seen(self, kind: str, robot: str, k: int) -> bool:
        return (kind, robot, k) in self.events

    def sample(self, k: int) -> None:
        """Wait for sample k, every robot's ground truth: the tracker then holds step k."""
        with self.cond:
            ok = self.cond.wait_for(lambda: all(self._seen("truth", r, k) for r in ROBOTS), WAIT)
        assert ok, f"no ground truth of sample {k}"

    def ticked(self, k: int) -> bool:
        with self.cond:
            return self._seen("tick", "", k)

    def permit(self, k: int) -> None:
        with self.cond:
            self.events.append(("permit", "", k))
        self.pub.put(Script(robot=SCRIPT, step=k, stop=False).encode())

    def stop(self) -> None:
        self.pub.put(Script(robot=SCRIPT, step=-1, stop=True).encode())

    def plan(self, robot: str, k: int) -> Plan:
        with self.cond:
            ok = self.cond.wait_for(lambda: (robot, k) in self.plans, WAIT)
            assert ok, f"no plan of {robot} at step {k}"
            return self.plans[(robot, k)]

    def step(self, k: int) -> None:
        """Sample k, permit step k, then every robot's plan of step k."""
        self.sample(k)
        assert not self.ticked(k), f"tick {k} came before its permit"
        self.permit(k)
        for r in ROBOTS:
            self.plan(r, k)

    def ask(self, robot: str, payload: bytes) -> tuple[str, dict[str, Any]]:
        """Send a goal query to ``robot``'s agent: ("ok" or "err", the answer's map)."""
        replies = list(self.session.get(KEYS.goal(robot), payload=payload, timeout=WAIT))
        assert len(replies) == 1, f"{len(replies)} replies from {robot}"
        got = replies[0]
        if got.ok is not None:
            return "ok", msgpack.unpackb(got.ok.payload.to_bytes())
        return "err", msgpack.unpackb(got.err.payload.to_bytes())

    def goal(self, robot: str, xy: tuple[float, float], batch: dict[str, tuple[float, float]] | None = None):
        together = {r: np.array(g, dtype=float) for r, g in (batch or {}).items()}
        return self.ask(robot, Goal(robot=robot, goal=np.array(xy, dtype=float), batch=together).encode())

    def permits_before_ticks(self) -> list[int]:
        """Steps whose tick came before any permit of that step (none, if the tracker holds)."""
        with self.cond:
            permitted, early = -1, []
            for kind, _, k in self.events:
                if kind == "permit":
                    permitted = max(permitted, k)
                elif kind == "tick" and k > permitted:
                    early.append(k)
            return early

    def close(self) -> None:
        """Leave the fleet (idempotent): the script's token goes."""
        if self.session.is_closed():
            return
        if self.token is not None:
            self.token.undeclare()
        for s in self.subs:
            s.undeclare()
        self.session.close()


EXITED = {"tracker": 0, "supervisor": 0, "agent r1": 0, "agent r2": 0}
"""Every process of the fleet exited 0 by itself."""


@contextlib.contextmanager
def _scripted_fleet(tmp_path: Path, **options: Any) -> Iterator[tuple[Launched, Log, Player]]:
    """A scripted fleet of the scene (its log lines on a pipe) and this test in it as the script;
    on the way out the script leaves and every process still running is stopped by pid."""
    read, write = os.pipe()
    try:
        launched = start_fleet(
            str(_scene(tmp_path)), ROBOTS, tmp_path / "out", None, scripted=True, stderr=write, **options
        )
    except BaseException:
        os.close(read)
        raise
    finally:
        os.close(write)  # the processes hold their copies: the pipe ends when the last one exits
    log = Log(read)
    player = None
    try:
        player = Player(launched.hub)
        player.join()
        yield launched, log, player
    finally:
        if player is not None:
            player.close()
        launched.stop()


def _ended(launched: Launched) -> tuple[dict[str, int | None], tuple[int, str, dict[str, Any] | None]]:
    """Wait (bounded) for every process to exit by itself: their exit codes, then the run's
    verdict (:meth:`Launched.wait`)."""
    for p in launched.procs:
        try:
            p.popen.wait(timeout=WAIT)
        except subprocess.TimeoutExpired:
            pass
    return {p.role: p.popen.poll() for p in launched.procs}, launched.wait(WAIT)


def test_a_script_steps_a_lockstep_fleet_and_gives_acknowledged_goals(tmp_path):
    with _scripted_fleet(tmp_path) as (launched, log, player):
        for k in range(3):
            player.step(k)

        # Sample 3: a goal for r1, acknowledged; its plan of step 4 carries it, that of step 3
        # not: planning ahead (the default), the plan of step 3 was made during step 2.
        player.sample(3)
        new = (0.5, 0.4)
        assert player.goal("r1", new) == ("ok", {"ok": True})
        player.permit(3)
        assert np.array_equal(player.plan("r1", 4).goal, new)
        assert np.array_equal(player.plan("r1", 3).goal, HOME["r1"])

        # Sample 4: refused with the reason, and nothing changes: a goal inside the disc, one on
        # r2's goal, a payload that is no goal, and a goal for r2 sent to r1.
        player.sample(4)
        kind, answer = player.goal("r1", (0.0, 0.7))
        assert kind == "ok" and answer["ok"] is False and "inside obstacles[0]" in answer["reason"], answer
        kind, answer = player.goal("r1", (-0.6, 0.1))
        assert kind == "ok" and answer["ok"] is False and "from r2's goal" in answer["reason"], answer
        assert set(answer) == {"ok", "reason"} and "\n" not in answer["reason"]
        kind, answer = player.ask("r1", b"\x93not a goal")
        assert kind == "err" and answer["ok"] is False and answer["reason"].startswith("payload"), answer
        kind, answer = player.ask("r1", Goal(robot="r2", goal=np.array([0.0, -0.5])).encode())
        assert kind == "err" and "claims 'r2'" in answer["reason"], answer
        player.permit(4)
        assert np.array_equal(player.plan("r1", 4).goal, new)
        assert np.array_equal(player.plan("r2", 4).goal, HOME["r2"])

        # Sample 5: r1 and r2 trade goals.  Alone, each would park on the other's goal; in one
        # batch each is checked against the other's new goal, and both are taken at step 6.
        player.sample(5)
        kind, answer = player.goal("r1", HOME["r2"])
        assert kind == "ok" and answer["ok"] is False and "r2's goal" in answer["reason"], answer
        assert player.goal("r1", HOME["r2"], batch={"r2": new}) == ("ok", {"ok": True})
        assert player.goal("r2", new, batch={"r1": HOME["r2"]}) == ("ok", {"ok": True})
        player.permit(5)
        assert np.array_equal(player.plan("r1", 6).goal, HOME["r2"])
        assert np.array_equal(player.plan("r2", 6).goal, new)

        for k in range(6, 9):
            player.step(k)
        assert player.permits_before_ticks() == []

        # Sample 9: the script stops the run.
        player.sample(9)
        player.stop()
        codes, (code, why, summary) = _ended(launched)
    text = log.text()
    assert codes == EXITED, text[-3000:]
    assert "[tracker] step 9: the script asked to stop; ending the run" in text, text[-3000:]
    assert summary is not None and (tmp_path / "out" / "summary.json").exists()
    assert summary["exit_codes"] == codes and summary["completed"] and summary["steps"] == 9, summary
    goals = {r: summary["robots"][r]["goal"] for r in ROBOTS}
    assert goals == {"r1": list(HOME["r2"]), "r2": list(new)}, goals
    assert code == 1 and "goal not reached" in why  # stopped at 0.9 s: nobody is home yet
    # The two payloads that were no goal of r1's were counted by r1, and nothing else was.
    counted = dict(re.findall(r"\[agent (r\d)\] stopped after 9 steps: .*, (\d+) rejected payloads", text))
    assert counted == {"r1": "2", "r2": "0"}, text[-3000:]


def test_a_held_fleet_outlives_the_agents_timeout_and_ends_when_the_script_leaves(tmp_path):
    timeout = 2.0
    with _scripted_fleet(tmp_path, agent_timeout=timeout) as (launched, log, player):
        for k in range(2):
            player.step(k)
        # Step 2 held past the agents' --timeout: each agent says so, and lives on.
        player.sample(2)
        held = [f"[agent {r}] no tick 2 for {timeout} s: held by the script, waiting" for r in ROBOTS]
        assert log.wait_for(lambda text: all(h in text for h in held)), log.text()[-3000:]
        assert not player.ticked(2), "the tracker did not hold step 2"
        assert all(p.popen.poll() is None for p in launched.procs), {
            p.role: p.popen.poll() for p in launched.procs
        }
        player.permit(2)
        for r in ROBOTS:
            player.plan(r, 2)
        player.step(3)
        assert player.permits_before_ticks() == []
        # The script leaves without a stop: its token goes, and the tracker ends the run.
        player.sample(4)
        player.close()
        codes, (_, _, summary) = _ended(launched)
    text = log.text()
    assert codes == EXITED, text[-3000:]
    assert "[tracker] step 4: the script left the fleet (its liveliness token went); ending the run" in text
    assert summary is not None and summary["completed"] and summary["steps"] == 4, summary
    assert not any("stopping (live" in ln for ln in text.splitlines()), "an agent gave up on the clock"
