"""Robots that drive on: a cut radio link is noticed as late as a real one, and a late link brakes first.

The e-puck firmware has no deadman: the robot keeps the last wheel speeds it received.

* A cut link (a fault plan's ``links``, :class:`epuck_link.transport.CutTransport`) behaves as a
  dead Bluetooth or Wi-Fi link does: writes return, no reply comes, and the link learns of the
  loss only from its reply timeout, while the robot drives on.  The delay is measured on a
  simulated clock, so nothing here depends on how fast the machine is.
* An inner-loop step of ``epuck_link`` that starts late sends zero speed before anything else
  (:data:`epuck_link.link.LATE`), and the port does not send speeds its caller left stale.
"""

from __future__ import annotations

import argparse
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from epuck_link import protocol as P
from epuck_link.emulator import EpuckEmulator, TcpServer
from epuck_link.transport import (
    AsercomCodec,
    CutTransport,
    LinkError,
    LoopTransport,
    Reading,
    RobotPort,
    TcpTransport,
    Transport,
    WifiCodec,
    parse_link,
)
from ground.wire import Command, Keys
from transport.net import NetConfig, free_port, loopback

pytestmark = pytest.mark.timeout(120)

ROOT = Path(__file__).resolve().parents[2]
SCENARIO = ROOT / "scenarios" / "paper_two_robots.toml"
REPLY_TIMEOUT = 0.25
"""The links' reply timeout [s] (:func:`epuck_link.transport.make_transport`)."""
TS = 0.1
"""The presets' step [s]."""
PERIOD = 0.02
"""The inner loop's period at its default 50 Hz [s]."""
BOUND = 10.0
"""Upper bound [s] on waiting for a thread's event: a failure, never a measure."""


class SimClock:
    """A simulated monotonic clock [s]: ``sleep`` advances it at once."""

    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t

    def sleep(self, seconds: float) -> None:
        self.t += max(0.0, seconds)

    def step(self) -> int:
        """The step [Ts] the clock is in."""
        return int(self.t / TS + 1e-9)


def _speeds(chain: bytes) -> tuple[int, int]:
    """The wheel speeds [steps/s] of an advanced-sercom set-speed chain (``0xBC l l r r ...``)."""
    assert chain[0] == 0x100 - ord("D"), chain
    return P.parse_encoders(chain[1:5])


# ================================================================ a cut link
def test_a_cut_serial_link_is_noticed_only_at_its_reply_timeout():
    """The link is cut from step 5 on, and asks for zero speed there.  The write returns and
    nothing answers, so the exchange fails only once its 0.25 s reply timeout has run out on
    the link's clock: the loss is declared in step 7, two whole steps into the cut, not in
    step 5 as a failed write would have it.  Meanwhile the robot got nothing and drove on at
    the speeds it had before the cut."""
    clock = SimClock()
    emu = EpuckEmulator(clock=clock)
    cut_from = 5
    t = CutTransport(LoopTransport(emu.serial_handler), lambda: clock.step() >= cut_from, clock, clock.sleep)
    codec = AsercomCodec(REPLY_TIMEOUT, clock=clock)
    t.open()
    lost_at = x_cut = None
    for _ in range(100):
        if clock.step() >= cut_from and x_cut is None:
            x_cut, t_cut = emu.snapshot().x, clock()
        try:
            codec.exchange(t, *((400, 400) if clock.step() < cut_from else (0, 0)))
        except LinkError as e:
            lost_at, why = clock(), e.reason
            break
        clock.t += PERIOD
    assert lost_at is not None and "no reply" in why and "link cut (fault plan)" in why, lost_at
    assert lost_at - cut_from * TS >= REPLY_TIMEOUT, lost_at
    assert clock.step() == cut_from + 2
    assert t.writes_in_cut == 1  # one command went into the cut, then its reply was waited for
    robot = emu.snapshot()
    assert (robot.left, robot.right) == (400, 400)  # still the speeds of before the cut: it drove on
    v = P.step_rate(400, emu.model) / emu.geom.steps_per_rev * 2 * np.pi * emu.geom.wheel_radius
    assert x_cut is not None and robot.x - x_cut == pytest.approx(v * (lost_at - t_cut))


def test_a_cut_shorter_than_the_reply_timeout_goes_unnoticed_and_delays_the_command():
    """A cut of one step (0.1 s), shorter than the reply timeout: as on a radio link that
    retransmits, the command written in the cut reaches the robot when the cut ends, its reply
    comes back late but within the timeout, and no loss is declared.  Until then the robot
    drove on at its old speeds."""
    clock = SimClock()
    emu = EpuckEmulator(clock=clock)
    t = CutTransport(LoopTransport(emu.serial_handler), lambda: clock.step() == 5, clock, clock.sleep)
    codec = AsercomCodec(REPLY_TIMEOUT, clock=clock)
    t.open()
    codec.exchange(t, 400, 400)
    clock.t = 5 * TS
    x0 = emu.snapshot().x
    codec.exchange(t, 100, 100)  # written in the cut, answered after it
    assert t.writes_in_cut == 1 and clock.step() == 6 and clock() - 5 * TS < REPLY_TIMEOUT
    robot = emu.snapshot()
    assert (robot.left, robot.right) == (100, 100)
    v = P.step_rate(400, emu.model) / emu.geom.steps_per_rev * 2 * np.pi * emu.geom.wheel_radius
    assert robot.x - x0 == pytest.approx(v * (clock() - 5 * TS))  # at the old speeds until then


def test_a_cut_wifi_link_hides_the_robots_stream():
    """Over Wi-Fi the robot streams a sensor packet every 20 ms whether or not a command
    came (:class:`epuck_link.emulator.WifiSide`).  A cut hides that stream too: the exchange
    in the cut finds no packet within the reply timeout and fails, although the emulator kept
    sending on its socket; and the zero speed asked in the cut never reached the robot."""
    emu = EpuckEmulator(model="e-puck2")
    server = TcpServer(emu, 0)
    cut = threading.Event()
    t = CutTransport(TcpTransport(server.host, server.port), cut.is_set)
    codec = WifiCodec(REPLY_TIMEOUT)
    try:
        t.open()
        codec.exchange(t, 300, 300)  # the stream starts
        before = emu.wifi_packets
        cut.set()
        with pytest.raises(LinkError, match=r"no sensor packet within 0\.25 s"):
            codec.exchange(t, 0, 0)
        assert t.writes_in_cut == 1 and t.silent_reads >= 1
        robot = emu.snapshot()
        assert (robot.left, robot.right) == (300, 300) and emu.wifi_packets == before
    finally:
        t.close()
        server.close()


def test_the_port_declares_a_cut_lost_after_the_command_and_the_timeout_then_stops_the_robot():
    """The link's port thread over a cut link: the loss is declared once a command was
    written into the cut and its reply waited for a whole reply timeout (on the cut's clock),
    with the speeds the robot may be driving on at.  The robot drove on at its last speeds;
    when the cut ends, the re-opened link sends zero speed first."""
    clock = SimClock()
    emu = EpuckEmulator()
    cutting = threading.Event()
    """The cut starts at the next write."""
    over = threading.Event()
    first_cut_write: list[float] = []

    def cut() -> bool:
        return bool(first_cut_write) and not over.is_set()

    class Watched(CutTransport):
        def write(self, data: bytes) -> None:
            if cutting.is_set() and not first_cut_write:
                first_cut_write.append(clock())
            super().write(data)

    t = Watched(LoopTransport(emu.serial_handler), cut, clock, clock.sleep)
    lost: list[tuple[float, int, tuple[tuple[int, int], ...]]] = []
    lost_event, steady, back = threading.Event(), threading.Event(), threading.Event()

    def on_lost(possible: tuple[tuple[int, int], ...]) -> None:
        lost.append((clock(), t.writes_in_cut, possible))
        lost_event.set()

    at_back: list[tuple[int, int]] = []

    def on_reading(r: Reading) -> None:
        robot = emu.snapshot()
        if robot.left == 600:
            steady.set()
        if r.fresh_link and lost:
            at_back.append((robot.left, robot.right))
            back.set()

    port = RobotPort(t, AsercomCodec(REPLY_TIMEOUT, clock=clock), lambda m: None, on_reading, period=0.005,
                     backoff=(0.005, 0.01), on_lost=on_lost)  # fmt: skip
    port.command(600, 600)
    port.start()
    try:
        assert steady.wait(BOUND)
        cutting.set()
        port.command(-200, 100)  # asked in the cut: never reaches the robot
        assert lost_event.wait(BOUND)
        robot = emu.snapshot()
        assert (robot.left, robot.right) == (600, 600)
        over.set()
        assert back.wait(BOUND)
    finally:
        port.close()
    assert at_back == [(0, 0)]  # zero speed first on the re-opened link
    (at, written, possible) = lost[0]
    assert len(lost) == 1 and written >= 1, lost
    assert at - first_cut_write[0] >= REPLY_TIMEOUT, (at, first_cut_write)
    assert (600, 600) in possible, possible


# ================================================================ a late link
def _gated(inner: Transport) -> Any:
    """``inner``, recording every write; armed, it holds the next write until released."""

    class Gate(Transport):
        def __init__(self) -> None:
            self.written: list[bytes] = []
            self.cond = threading.Condition()
            self.armed = self.holding = False

        name = "gate"  # type: ignore[assignment]

        @property
        def is_open(self) -> bool:
            return inner.is_open

        def open(self) -> None:
            inner.open()

        def close(self) -> None:
            inner.close()

        def write(self, data: bytes) -> None:
            with self.cond:
                self.written.append(data)
                self.cond.notify_all()
                if self.armed:
                    self.holding = True
                    self.cond.notify_all()
                    self.cond.wait_for(lambda: not self.armed, BOUND)
                    self.holding = False
            inner.write(data)

        def read_exact(self, n: int, timeout: float) -> bytes:
            return inner.read_exact(n, timeout)

        def read_some(self, n: int, timeout: float) -> bytes:
            return inner.read_some(n, timeout)

    return Gate()


@pytest.fixture(scope="module")
def session():
    """A Zenoh session of the test's own, on loopback, for a link run in this process."""
    import zenoh

    s = zenoh.open(NetConfig(listen=[loopback(free_port())]).zenoh())
    try:
        yield s
    finally:
        s.close()


def test_a_late_inner_loop_step_brakes_before_anything_else(session):
    """The link drives an emulated robot on a live agent's command, on a clock the test can
    stop.  A step that starts 15 ms after it was due is within a loop's jitter and goes on as
    usual.  A step that starts 30 ms late, as in a starved process, has the port write the
    e-puck's set-speed to zero first, and only then its own speeds, which are not zero.  Late
    steps are counted, and their runs (episodes) once each."""
    from epuck_link.link import Link
    from ground.scenario import load_scenario

    frozen: list[float | None] = [None]
    scn = load_scenario(SCENARIO)
    spec = next(r for r in scn.robots if r.id == "r1")
    keys = Keys(f"late{time.monotonic_ns()}")
    args = argparse.Namespace(watchdog=10.0, rate=1.0 / PERIOD, deadline=0.5, faults=None)

    def clock() -> float:
        t = frozen[0]
        return time.monotonic() if t is None else t

    link = Link(args, scn, spec, parse_link("emulator"), session, keys, clock=clock)
    gate = _gated(link.port.transport)
    link.port.transport = gate
    token = session.liveliness().declare_token(keys.alive("r1"))
    stopping = threading.Event()

    def step_at(late: float) -> None:
        """Run one inner-loop step that starts ``late`` [s] after it was due."""
        frozen[0] = link.due + late
        link.run_once(stopping)

    try:
        session.put(keys.cmd("r1"), Command(robot="r1", step=0, ax=0.3, ay=0.0).encode())
        assert link.inbox.wait(
            lambda: link.inbox.get(Command, "r1") is not None and "r1" in link.inbox.live, BOUND
        )
        link.start()
        for _ in range(200):  # on time: the wheels speed up
            link.run_once(stopping)
            if min(link.wheels) > 0:
                break
        assert min(link.wheels) > 0 and link.late_steps == 0, link.wheels
        step_at(0.015)
        assert link.late_steps == 0
        with gate.cond:  # hold the port's thread in its next write: nothing goes out meanwhile
            gate.armed = True
            assert gate.cond.wait_for(lambda: gate.holding, BOUND)
            mark = len(gate.written)
        step_at(0.030)
        assert link.late_steps == 1 and link.late_episodes == 1 and link.late_worst == pytest.approx(0.03)
        with gate.cond:
            gate.armed = False
            gate.cond.notify_all()
            assert gate.cond.wait_for(lambda: len(gate.written) >= mark + 2, BOUND)
            after = gate.written[mark : mark + 2]
        step_at(0.030)  # the same episode
        step_at(0.0)  # on time: the episode ends
        step_at(0.030)
        assert (link.late_steps, link.late_episodes) == (3, 2)
    finally:
        token.undeclare()
        link.close()
    assert after[0] == P.speed_and_encoders(0, 0)  # 0xBC 0 0 0 0 0xAF 0x00: the brake first
    assert min(_speeds(after[1])) > 0, after  # then the step's own speeds


def test_a_brake_goes_out_before_the_speeds_asked_after_it():
    """:meth:`RobotPort.brake` then :meth:`RobotPort.command` before the port's thread ran:
    zero speed is written first, then the new speeds; the latest call does not replace the brake."""
    emu = EpuckEmulator()
    gate = _gated(LoopTransport(emu.serial_handler))
    two = threading.Event()

    def on_reading(r: Reading) -> None:
        if len(gate.written) >= 2:
            two.set()

    port = RobotPort(gate, AsercomCodec(), lambda m: None, on_reading, period=0.005)
    port.brake()
    port.command(700, 700)
    port.start()
    try:
        assert two.wait(BOUND)
    finally:
        port.close()
    assert [_speeds(w) for w in gate.written[:2]] == [(0, 0), (700, 700)]
    assert port.brakes == 1


def test_the_port_does_not_send_speeds_its_caller_left_stale():
    """The port sends the latest speeds again every period.  Once they were asked longer than
    ``stale_after`` ago (on the port's clock, here the test's), it sends zero instead, logs it
    once, and sends new speeds as soon as they are asked."""
    clock = SimClock()
    emu = EpuckEmulator()
    gate = _gated(LoopTransport(emu.serial_handler))
    lines: list[str] = []
    seen = threading.Condition()

    def on_reading(r: Reading) -> None:
        with seen:
            seen.notify_all()

    def written() -> list[tuple[int, int]]:
        return [_speeds(w) for w in gate.written]

    port = RobotPort(gate, AsercomCodec(), lines.append, on_reading, period=0.002,
                     stale_after=PERIOD + 0.02, clock=clock)  # fmt: skip
    port.command(500, 500)
    port.start()
    try:
        with seen:
            assert seen.wait_for(lambda: written().count((500, 500)) >= 3, BOUND)  # sent again
            clock.t += PERIOD + 0.021  # the caller stalled
            mark = len(gate.written)
            assert seen.wait_for(lambda: (0, 0) in written()[mark:], BOUND)
        port.command(300, 300)
        with seen:
            assert seen.wait_for(lambda: (300, 300) in written(), BOUND)
    finally:
        port.close()
    sent = written()
    stopped = sent.index((0, 0), mark)
    assert set(sent[stopped : sent.index((300, 300))]) == {(0, 0)}, sent
    assert port.stale == 1 and sum("no wheel speeds asked for" in m for m in lines) == 1, lines
