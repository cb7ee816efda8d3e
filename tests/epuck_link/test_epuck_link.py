"""epuck_link: the e-puck protocols byte for byte, the emulator, and the link process over loopback.

Process tests start the emulator, the link and helper "agents" with subprocess,
wait on their readiness lines, talk to them through a Zenoh session of the test
(peer mode, multicast scouting off, tcp/127.0.0.1 only) and end every process
by pid.  Each rig uses a fleet name of its own.
"""

from __future__ import annotations

import itertools
import json
import math
import os
import select
import signal
import subprocess
import sys
import threading
import time
import tty
from collections.abc import Callable
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest

from epuck_link import protocol as P
from epuck_link.drive import Drive, Watchdog, WheelOdometry
from epuck_link.emulator import EpuckEmulator
from epuck_link.transport import (
    AsercomCodec,
    LinkError,
    LinkSpec,
    Reading,
    RobotPort,
    SerialTransport,
    TcpTransport,
    Transport,
    WifiCodec,
    parse_link,
)
from ground.params import WheelGeometry
from ground.wire import Command, Keys, Odom, Pose, Truth, Wheels, WireError, decode
from transport.net import NetConfig, free_port, loopback

pytestmark = pytest.mark.timeout(180)

ROOT = Path(__file__).resolve().parents[2]
SCENARIO = str(ROOT / "scenarios" / "paper_two_robots.toml")
START = (-0.7, 0.0, 0.0)
"""r1's start in that scenario [m, m, rad]."""
ENV = {**os.environ, "OMP_NUM_THREADS": "1", "RERUN_ANALYTICS": "0"}
GEOM = WheelGeometry()
STOP_BOUND = 0.6
"""The watchdog must stop the robot within this long after the commands stop [s]."""
ZERO_EXCHANGE = bytes.fromhex("bc 00 00 00 00 af 00")
FULL_AHEAD = bytes.fromhex("bc e8 03 e8 03 af 00")
ZERO_STOP = bytes.fromhex("bc 00 00 00 00 00")


# ================================================================ pure parts
def test_set_speed_bytes_are_exact():
    assert P.terminate(P.set_speed(500, -500)) == bytes.fromhex("bc f4 01 0c fe 00")
    assert P.speed_and_encoders(500, -500) == bytes.fromhex("bc f4 01 0c fe af 00")
    assert P.SET_SPEED == 0xBC == -ord("D") & 0xFF and P.GET_ENCODERS == 0xAF == -ord("Q") & 0xFF
    # Clamped to ±1000 (e-puck 1.x) unless the limit says otherwise (e-puck2: 1100).
    assert P.set_speed(1500, -2000)[1:] == bytes.fromhex("e8 03 18 fc")
    assert P.set_speed(1500, -2000, limit=P.MAX_STEPS_V2)[1:] == bytes.fromhex("4c 04 b4 fb")
    assert P.set_speed(499.6, -0.4)[1:] == bytes.fromhex("f4 01 00 00")
    with pytest.raises(ValueError, match="not finite"):
        P.set_speed(math.nan, 0)


def test_encoder_replies_and_int16_wrap():
    assert P.parse_encoders(bytes.fromhex("ff 7f 00 80")) == (32767, -32768)
    assert P.encoders_reply(32768, -32769) == bytes.fromhex("00 80 ff 7f")
    with pytest.raises(P.ProtocolError, match="expected 4 bytes"):
        P.parse_encoders(b"\x00\x01\x02")
    tr = P.EncoderTracker()
    seen = [tr.update(*raw) for raw in [(32000, -32000), (32767, -32768), (-32700, 32700), (-31000, 31000)]]
    assert seen == [(32000, -32000), (32767, -32768), (32836, -32836), (34536, -34536)]
    tr.rebase()  # a re-opened link, a robot restarted at 0: the counts go on without a jump
    assert tr.update(0, 0) == (34536, -34536) and tr.update(5, -5) == (34541, -34541)
    with pytest.raises(ValueError, match="int16"):
        tr.update(40000, 0)


def test_parser_splits_chains_across_reads_like_the_firmware():
    stream = (
        P.speed_and_encoders(500, -500) + b"\x00\r\n" + b"D,1,2\r" + P.terminate(P.get_encoders(), b"\xb2")
        + b"q\n"
    )  # fmt: skip
    whole = P.AsercomParser().feed(stream)
    parser = P.AsercomParser()
    bytewise = [r for b in stream for r in parser.feed(bytes([b]))]
    assert whole == bytewise == [
        P.SetSpeed(500, -500), P.GetEncoders(), P.EndOfChain(), P.AsciiLine("D,1,2"), P.GetEncoders(),
        P.Ignored(0xB2), P.EndOfChain(), P.AsciiLine("q"),
    ]  # fmt: skip
    assert P.ascii_reply("D,500,-500", (1, 2)) == (b"d\r\n", (500, -500))
    assert P.ascii_reply("q", (-3, 4)) == (b"q,-3,4\r\n", None)
    assert P.ascii_reply("X", (0, 0))[0] == b"z,Command not found\r\n"


def test_wifi_packet_layout():
    rgb = tuple(range(1, 13))
    pkt = P.wifi_command(300, -1200, request=P.REQUEST_SENSORS, settings=0, leds=0x21, rgb=rgb, sound=0x08)
    assert len(pkt) == P.WIFI_COMMAND_SIZE == 21
    assert pkt[:3] == bytes([0x80, 0x02, 0x00])
    assert pkt[3:7] == bytes.fromhex("2c 01 b4 fb")  # 300, −1100 (clamped at the e-puck2 limit)
    assert pkt[7] == 0x21 and tuple(pkt[8:20]) == rgb and pkt[20] == 0x08
    back = P.parse_wifi_command(pkt)
    assert (back.request, back.settings, back.left, back.right, back.leds, back.rgb, back.sound) == (
        2, 0, 300, -1100, 0x21, rgb, 0x08,
    )  # fmt: skip
    sensors = P.sensors_payload(-2, 32767)
    assert len(sensors) == 104 and sensors[79:83] == bytes.fromhex("fe ff ff 7f")
    assert P.encoders_from_sensors(sensors) == (-2, 32767)
    assert P.wifi_reply(0, 0, 0) == b"\x03"
    sensed = P.wifi_reply(P.REQUEST_SENSORS, 1, 2)
    assert sensed[0] == 0x02 and len(sensed) == 105
    with pytest.raises(P.ProtocolError, match="first byte"):
        P.parse_wifi_command(b"\x81" + pkt[1:])
    with pytest.raises(P.ProtocolError, match="unknown header"):
        P.wifi_payload_size(0x07)


def test_wheel_steps_saturate_by_one_factor():
    left, right, sat = P.wheel_steps(0.05, 0.4, GEOM)
    assert not sat
    m = GEOM.metres_per_step
    assert left == round((0.05 - 0.2 * GEOM.axle) / m) and right == round((0.05 + 0.2 * GEOM.axle) / m)
    left, right, sat = P.wheel_steps(0.3, 2.0, GEOM)  # both wheels far beyond 1000 steps/s
    assert sat and max(abs(left), abs(right)) == 1000
    ideal = ((0.3 - GEOM.axle) / m, (0.3 + GEOM.axle) / m)
    assert left / right == pytest.approx(ideal[0] / ideal[1], abs=2e-3)  # curvature kept


def test_link_strings():
    assert parse_link("serial:/dev/rfcomm0") == LinkSpec("serial", device="/dev/rfcomm0")
    assert parse_link("tcp:192.168.1.7") == LinkSpec("tcp", host="192.168.1.7", port=1000)
    assert parse_link("tcp:epuck-4242.local:1234") == LinkSpec("tcp", host="epuck-4242.local", port=1234)
    assert parse_link("tcp:[::1]:99") == LinkSpec("tcp", host="::1", port=99)
    assert parse_link("sim").kind == "sim" and parse_link("emulator").kind == "emulator"
    assert str(parse_link("tcp:h")) == "tcp:h:1000"
    bad = {
        "": "empty",
        "udp:1.2.3.4": "unknown kind 'udp'",
        "serial:": "missing the device path",
        "tcp:": "missing the host",
        "tcp:h:": "missing the port",
        "tcp:h:70000": "port '70000'",
        "tcp:h:x1": "port 'x1'",
        "tcp:::1": "IPv6",
        "sim:x": "takes no argument",
        "serial:/dev/tty S0": "whitespace",
    }
    for text, why in bad.items():
        with pytest.raises(ValueError, match=why) as e:
            parse_link(text)
        assert "\n" not in str(e.value)


def test_emulator_integrates_the_epuck_geometry():
    clock = [10.0]
    emu = EpuckEmulator(pose=(0.1, -0.2, 0.0), encoders=(32700, -32700), clock=lambda: clock[0])
    h = emu.serial_handler()
    assert h(P.terminate(P.set_speed(1000, 1000))) == b""  # set speed: no reply
    clock[0] += 1.0
    reply = h(P.speed_and_encoders(2000, -2000))  # clamped to ±1000 by the firmware
    # One second at 1000 steps/s: one wheel revolution, 2π·20.5 mm, and the counts wrapped.
    assert P.parse_encoders(reply) == (P.wrap_int16(33700), P.wrap_int16(-31700)) == (-31836, -31700)
    s = emu.snapshot()
    assert s.x == pytest.approx(0.1 + 2 * math.pi * 0.0205, abs=1e-12) and s.y == -0.2 and s.theta == 0
    clock[0] += 0.5  # spin in place at ±1000 steps/s: ω = 2·0.1288/0.053 rad/s
    s = emu.snapshot()
    assert (s.left, s.right) == (1000, -1000)
    assert s.theta == pytest.approx(-2 * GEOM.max_wheel_speed / GEOM.axle * 0.5, abs=1e-9)
    assert s.x == pytest.approx(0.1 + 2 * math.pi * 0.0205, abs=1e-12)  # the axle centre stays put
    assert h(b"Q\r") == f"q,{P.wrap_int16(34200)},-32200\r\n".encode()
    assert h(b"D,0,0\r") == b"d\r\n" and emu.snapshot().left == 0


def test_watchdog_logic():
    wd = Watchdog(0.5)
    assert wd.check(0.0, None, live=True) == (False, None)  # nothing yet
    assert wd.check(1.0, 0.9, live=False) == (False, None)  # no live agent
    ok, ev = wd.check(1.0, 0.95, live=True)
    assert ok and "driving" in ev
    assert wd.check(1.4, 0.95, live=True) == (True, None)
    ok, ev = wd.check(1.5, 0.95, live=True)
    assert not ok and "no command for 0.55 s" in ev and wd.events == 1
    assert wd.check(1.6, 0.95, live=True) == (False, None)  # logged once
    ok, ev = wd.check(1.7, 1.65, live=True)
    assert ok and "driving" in ev
    ok, ev = wd.check(1.71, 1.65, live=False)
    assert not ok and "liveliness" in ev
    assert wd.check(1.9, 1.65, live=True) == (False, None)  # the token is back, but no fresh command
    assert wd.check(2.0, 1.95, live=True)[0]


def test_drive_holds_a_and_zeroes_q_on_halt():
    from epuck_link.unicycle import LookaheadInnerLoop

    drive = Drive(LookaheadInnerLoop(0.04), GEOM, np.array(START))
    for _ in range(10):  # 0.2 s at 1 m/s² along the heading: q = 0.2 m/s → saturated
        left, right = drive.step(np.array([1.0, 0.0]), 0.02)
    assert left == right == 1000
    assert drive.velocity() == pytest.approx((GEOM.max_wheel_speed, 0.0))
    drive.halt()
    assert drive.velocity() == (0.0, 0.0)
    assert drive.step(np.zeros(2), 0.02) == (0, 0)


def test_drive_is_the_simulated_plants_inner_loop():
    """50 Hz of Drive.step gives UnicyclePlant's wheel commands and pose (5 substeps per 0.1 s),
    up to the rounding of the wheel speeds to whole steps/s; the heading turns with ω between poses."""
    from epuck_link.unicycle import LookaheadInnerLoop, UnicyclePlant, wrap_angle

    rng = np.random.default_rng(7)
    plant = UnicyclePlant(np.array(START), LookaheadInnerLoop(0.04), GEOM, substeps=5)
    drive = Drive(LookaheadInnerLoop(0.04), GEOM, np.array(START))
    for k in range(60):
        a = rng.uniform(-0.3, 0.3, 2) + (np.array([0.6, 0.2]) if k < 10 else 0.0)  # first into saturation
        left, right = plant.step(a, 0.1)
        for _ in range(5):
            dl, dr = drive.step(a, 0.02)
        assert abs(dl - left) <= 3 and abs(dr - right) <= 3
    assert plant.saturated_substeps > 0  # the saturation path was exercised too
    assert drive.pose[:2] == pytest.approx(plant.pose[:2], abs=1e-3)
    assert wrap_angle(drive.pose[2] - plant.pose[2]) == pytest.approx(0.0, abs=1e-2)
    assert abs(drive.pose[2] - START[2]) > 0.1
    assert drive.velocity() == pytest.approx(tuple(plant.loop.velocity(plant.pose)), abs=1e-3)


def test_wheels_message_is_strict():
    msg = Wheels(robot="r1", seq=3, t=0.25, left_steps=40000, right_steps=-70000, v=0.1, omega=-0.5)
    assert decode(msg.encode(), Wheels, robot="r1") == msg
    assert Keys("lab").wheels("r1") == "fleet/lab/wheels/r1" and Keys("lab").emu("r1") == "fleet/lab/emu/r1"
    base = msgpack.unpackb(msg.encode())
    for field, value in [("left_steps", 1.5), ("v", float("nan")), ("seq", -1), ("omega", "x")]:
        with pytest.raises(WireError, match=field):
            decode(msgpack.packb({**base, field: value}), Wheels)
    with pytest.raises(WireError, match="fields"):
        decode(msgpack.packb({k: v for k, v in base.items() if k != "omega"}), Wheels)
    rng = np.random.default_rng(4)
    good = msg.encode()
    for _ in range(2000):  # byte flips: a Wheels or a WireError, nothing else
        b = bytearray(good)
        b[int(rng.integers(len(b)))] = int(rng.integers(256))
        try:
            decode(bytes(b), Wheels)
        except WireError:
            pass


def test_wheel_odometry_speeds_from_count_deltas():
    odo = WheelOdometry(GEOM, origin=100.0, window=0.1)
    w0 = odo.update("r1", Reading(100.0, 32000, 32000, fresh_link=True))
    w1 = odo.update("r1", Reading(100.5, -32768, 31500, fresh_link=False))  # left wrapped, +768 steps
    assert (w0.seq, w0.v, w1.seq, w1.t) == (0, 0.0, 1, 0.5)
    assert (w1.left_steps, w1.right_steps) == (32768, 31500)
    m = GEOM.metres_per_step
    assert w1.v == pytest.approx(0.5 * (1536 - 1000) * m)
    assert w1.omega == pytest.approx((-1000 - 1536) * m / GEOM.axle)
    # Over a 0.1 s baseline: reads 20 ms apart with a jittered one in between give the true speed.
    for k in range(12):  # 1000 steps/s on both wheels
        t = 0.02 * (k + 1) + (0.008 if k == 10 else 0.0)
        count = round(1000 * t)
        w = odo.update("r1", Reading(101 + t, P.wrap_int16(count), P.wrap_int16(count), fresh_link=k == 0))
        if k == 10:
            assert w.v == pytest.approx(1000 * m, rel=0.1)
    assert w.v == pytest.approx(1000 * m, rel=1e-6) and w.omega == 0.0


class _Pty:
    """A pseudo-terminal pair in raw mode: the test holds both ends."""

    def __init__(self) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        self.path = os.ttyname(self.slave)

    def read(self, n: int, timeout: float) -> bytes:
        buf = b""
        deadline = time.monotonic() + timeout
        while len(buf) < n and time.monotonic() < deadline:
            if select.select([self.master], [], [], max(0.0, deadline - time.monotonic()))[0]:
                buf += os.read(self.master, n - len(buf))
        return buf

    def close(self) -> None:
        for fd in (self.master, self.slave):
            os.close(fd)


def test_sender_bytes_on_a_real_pty():
    """What the link's serial sender writes for +500/−500 arrives byte for byte on the other end."""
    pty = _Pty()
    port = SerialTransport(pty.path, timeout=0.5)
    try:
        port.open()
        port.write(P.terminate(P.set_speed(500, -500)))
        assert pty.read(6, 2.0) == bytes.fromhex("bc f4 01 0c fe 00")
        os.write(pty.master, bytes.fromhex("ff 7f 00 80"))  # the robot's encoder answer, sent early
        assert AsercomCodec().exchange(port, 500, -500) == (32767, -32768)
        assert pty.read(7, 2.0) == bytes.fromhex("bc f4 01 0c fe af 00")
        t0 = time.monotonic()
        with pytest.raises(LinkError, match="no reply"):  # nobody answers: bounded by the timeout
            AsercomCodec(reply_timeout=0.2).exchange(port, 0, 0)
        assert time.monotonic() - t0 < 1.0
    finally:
        port.close()
        pty.close()


class _Flaky(Transport):
    """A transport that fails to open ``fail_opens`` times, then echoes encoder replies."""

    def __init__(self, fail_opens: int):
        self.fail_opens = fail_opens
        self.opens = 0
        self.written: list[bytes] = []
        self._open = False

    name = "flaky"  # type: ignore[assignment]

    @property
    def is_open(self) -> bool:
        return self._open

    def open(self) -> None:
        self.opens += 1
        if self.opens <= self.fail_opens:
            raise LinkError("flaky: refused")
        self._open = True

    def close(self) -> None:
        self._open = False

    def write(self, data: bytes) -> None:
        self.written.append(data)

    def read_exact(self, n: int, timeout: float) -> bytes:
        return bytes(n)

    def read_some(self, n: int, timeout: float) -> bytes:
        return bytes(min(n, 4))


class _DropsOnce(_Flaky):
    """Opens every time; the exchange after ``drop_at`` writes fails once (the radio link drops)."""

    def __init__(self, drop_at: int):
        super().__init__(fail_opens=0)
        self.drop_at = drop_at

    def write(self, data: bytes) -> None:
        if len(self.written) == self.drop_at:
            self.drop_at = -1
            raise LinkError("flaky: link dropped")
        super().write(data)


def test_the_first_command_after_a_lost_link_is_zero_speed():
    """The robot has no deadman: it drove on at its last speeds while the link was down.  The
    first command after the re-open is zero speed, although 500 steps/s is still asked; the
    ones after it are the asked speeds again."""
    t = _DropsOnce(drop_at=3)
    lines: list[str] = []
    got: list[Reading] = []
    done = threading.Event()

    def on_reading(r: Reading) -> None:
        got.append(r)
        if len(got) >= 6:
            done.set()

    port = RobotPort(t, AsercomCodec(), lines.append, on_reading, period=0.01, backoff=(0.01, 0.04))
    port.command(500, 500)
    port.start()
    try:
        assert done.wait(5.0), lines
    finally:
        port.close()
    sent = [P.parse_encoders(w[1:5]) for w in t.written[:6]]  # the set-speed arguments
    assert sent[:3] == [(500, 500)] * 3 and sent[3] == (0, 0) and sent[4] == (500, 500), sent
    assert port.lost == 1 and [r.fresh_link for r in got[:5]] == [True, False, False, True, False]
    assert any("zero speed first" in m for m in lines), lines


class _ReplyLost(_Flaky):
    """Opens every time; the reply to the first command of ``speeds`` never comes (the command
    went out, the link dropped before the answer)."""

    def __init__(self, speeds: tuple[int, int]):
        super().__init__(fail_opens=0)
        self.speeds: tuple[int, int] | None = speeds

    def read_exact(self, n: int, timeout: float) -> bytes:
        if self.speeds is not None and P.parse_encoders(self.written[-1][1:5]) == self.speeds:
            self.speeds = None
            raise LinkError("flaky: reply lost")
        return super().read_exact(n, timeout)


def test_a_lost_link_reports_every_speed_the_robot_may_drive_on_at():
    """The command of 300 steps/s was written and its reply lost: the robot may have taken it,
    or still drive at the 100 steps/s confirmed before.  The loss reports both, so the fleet
    bounds the robot's speed by the faster one, not by the last confirmed one alone."""
    t = _ReplyLost((300, -300))
    lost: list[tuple[tuple[int, int], ...]] = []
    got: list[Reading] = []
    two, done = threading.Event(), threading.Event()

    def on_reading(r: Reading) -> None:
        got.append(r)
        if len(got) == 2:
            two.set()
        if r.fresh_link and len(got) > 1:
            done.set()

    port = RobotPort(t, AsercomCodec(), lambda m: None, on_reading, period=0.01, backoff=(0.01, 0.04),
                     on_lost=lost.append)  # fmt: skip
    port.command(100, 100)
    port.start()
    try:
        assert two.wait(5.0)
        port.command(300, -300)
        assert done.wait(5.0)
    finally:
        port.close()
    assert lost == [((100, 100), (300, -300))], lost
    # Written: the speeds, the unanswered one, then zero first on the re-opened link.
    sent = [P.parse_encoders(w[1:5]) for w in t.written]
    i = sent.index((300, -300))
    assert sent[i + 1] == (0, 0), sent


def test_after_a_reopen_the_port_sends_zero_until_resumed():
    """``resume_by_hand``: the link process first learns the robot took zero speed, then lets
    commands through.  The speeds asked during the outage are not sent before that, however
    many exchanges pass; after :meth:`RobotPort.resume` the newest asked speeds go out."""
    resumed = threading.Event()

    class Watched(_DropsOnce):
        def write(self, data: bytes) -> None:
            super().write(data)
            if P.parse_encoders(data[1:5]) == (200, 200):
                resumed.set()

    t = Watched(drop_at=2)
    got: list[Reading] = []
    back, more = threading.Event(), threading.Event()

    def on_reading(r: Reading) -> None:
        got.append(r)
        if r.fresh_link and len(got) > 1:
            back.set()
        if back.is_set() and sum(1 for g in got if not g.fresh_link) >= 8:
            more.set()

    port = RobotPort(t, AsercomCodec(), lambda m: None, on_reading, period=0.005, backoff=(0.01, 0.04),
                     resume_by_hand=True)  # fmt: skip
    port.command(400, 400)
    port.start()
    try:
        assert back.wait(5.0)
        assert more.wait(5.0)  # several exchanges after the re-open, all held at zero
        held = [P.parse_encoders(w[1:5]) for w in t.written]
        port.command(200, 200)
        port.resume()
        assert resumed.wait(5.0), "the resumed speeds never went out"
    finally:
        port.close()
    after = held[held.index((0, 0)) :]
    assert len(after) >= 5 and set(after) == {(0, 0)}, held


def test_robot_port_retries_with_backoff_and_reports_once():
    flaky = _Flaky(fail_opens=3)
    lines: list[str] = []
    got: list[Reading] = []
    done = threading.Event()

    def on_reading(r: Reading) -> None:
        got.append(r)
        if len(got) >= 3:
            done.set()

    port = RobotPort(flaky, AsercomCodec(), lines.append, on_reading, period=0.01, backoff=(0.01, 0.04))
    port.start()
    port.command(300, 300)
    try:
        assert done.wait(5.0)
    finally:
        assert port.close()
    assert flaky.opens == 4 and got[0].fresh_link and not got[1].fresh_link
    assert len(lines) == 2, lines  # one line per outage, one for the re-opening
    assert lines[0].startswith("link unavailable: flaky: refused")
    assert lines[1].startswith("link flaky re-opened after 3 attempt(s)")
    assert P.speed_and_encoders(300, 300) in flaky.written and flaky.written[-1] == ZERO_STOP


# ============================================================ process helpers
class Proc:
    """A started process whose stdout and stderr lines are collected."""

    def __init__(self, *args: str):
        self.popen = subprocess.Popen(
            [sys.executable, *args], cwd=ROOT, env=ENV, stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        )  # fmt: skip
        self.out: list[str] = []
        self.err: list[str] = []
        self.cond = threading.Condition()
        for stream, sink in ((self.popen.stdout, self.out), (self.popen.stderr, self.err)):
            threading.Thread(target=self._pump, args=(stream, sink), daemon=True).start()

    def _pump(self, stream: Any, sink: list[str]) -> None:
        for line in stream:
            with self.cond:
                sink.append(line)
                self.cond.notify_all()
        with self.cond:
            self.cond.notify_all()

    @property
    def pid(self) -> int:
        return self.popen.pid

    def ready(self, timeout: float = 60.0) -> dict[str, Any]:
        """The readiness line; fails with the stderr if the process died or took too long."""
        found: list[dict[str, Any]] = []

        def have() -> bool:
            for line in self.out:
                if line.startswith("{"):
                    d = json.loads(line)
                    if d.get("event") == "ready":
                        found.append(d)
                        return True
            return self.popen.poll() is not None

        with self.cond:
            self.cond.wait_for(have, timeout)
        assert found, f"not ready (exit {self.popen.poll()}): {''.join(self.err)[-2000:]}"
        return found[0]

    def wait_err(self, text: str, timeout: float, count: int = 1) -> bool:
        with self.cond:
            return self.cond.wait_for(lambda: sum(text in ln for ln in self.err) >= count, timeout)

    def stderr(self) -> str:
        with self.cond:
            return "".join(self.err)

    def stop(self, sig: int = signal.SIGTERM) -> int:
        if self.popen.poll() is None:
            self.popen.send_signal(sig)
            try:
                self.popen.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.popen.kill()
                self.popen.wait(timeout=10)
        return self.popen.returncode


class Collector:
    """Decoded messages of one type on a key, with their arrival time [s, time.monotonic]."""

    def __init__(self, session: Any, key: str, typ: type):
        self.items: list[tuple[float, Any]] = []
        self.cond = threading.Condition()
        self.typ = typ
        self.sub = session.declare_subscriber(key, self._on)

    def _on(self, sample: Any) -> None:
        msg = decode(sample.payload.to_bytes(), self.typ)
        with self.cond:
            self.items.append((time.monotonic(), msg))
            self.cond.notify_all()

    def wait(self, pred: Callable[[list[tuple[float, Any]]], bool], timeout: float) -> bool:
        with self.cond:
            return self.cond.wait_for(lambda: pred(self.items), timeout)

    def snapshot(self) -> list[tuple[float, Any]]:
        with self.cond:
            return list(self.items)


class Commander:
    """Publishes ``Command(a)`` for one robot at ``rate`` Hz until stopped (an agent's commands)."""

    def __init__(self, session: Any, keys: Keys, robot: str, a: tuple[float, float], rate: float = 20.0):
        self.pub = session.declare_publisher(keys.cmd(robot))
        self.robot, self.a, self.period = robot, a, 1.0 / rate
        self.last_put = 0.0
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        k = 0
        while True:
            with self._lock:
                if self._stop.is_set():
                    return
                self.pub.put(Command(robot=self.robot, step=k, ax=self.a[0], ay=self.a[1]).encode())
                self.last_put = time.monotonic()
            k += 1
            if self._stop.wait(self.period):
                return

    def stop(self) -> float:
        """Stop; returns when the last command was put [s, time.monotonic]."""
        with self._lock:
            self._stop.set()
        self._thread.join(5)
        self.pub.undeclare()
        return self.last_put


@pytest.fixture(scope="module")
def hub():
    """The test's own Zenoh session, listening on a free loopback port; processes connect to it."""
    import zenoh

    endpoint = loopback(free_port())
    session = zenoh.open(NetConfig(listen=[endpoint]).zenoh())
    try:
        yield session, endpoint
    finally:
        session.close()


def _fleet(tag: str) -> str:
    return f"el{os.getpid()}{tag}"


def _link(endpoint: str, fleet: str, link: str, *extra: str) -> Proc:
    return Proc(
        "-m", "epuck_link", "--scenario", SCENARIO, "--robot", "r1", "--fleet", fleet, "--connect", endpoint,
        "--link", link, *extra,
    )  # fmt: skip


def _emulator(endpoint: str, fleet: str, *extra: str) -> Proc:
    x, y, th = START
    return Proc(
        "-m", "epuck_link.emulator", "--robot", "r1", "--fleet", fleet, "--connect", endpoint,
        "--start", str(x), str(y), str(th), *extra,
    )  # fmt: skip


def _stop_time(truths: list[tuple[float, Truth]], origin: float, after: float) -> tuple[float, float, int]:
    """When the robot stopped for good, from the emulator's truth samples [s, time.monotonic].

    Returns (upper bound, lower bound, samples in the final stationary run):
    the pose changed between the two bounds' samples and never after."""
    pts = [(origin + m.t, (m.x, m.y, m.theta)) for _, m in truths if origin + m.t >= after]
    assert len(pts) > 2, "no truth samples in the window"
    i = len(pts) - 1
    while i > 0 and pts[i - 1][1] == pts[-1][1]:
        i -= 1
    assert i > 0, "the robot was not moving when the commands stopped"
    return pts[i][0], pts[i - 1][0], len(pts) - i


def _moved(truths: list[tuple[float, Truth]], metres: float) -> bool:
    return len(truths) > 1 and truths[-1][1].x - truths[0][1].x > metres


# ================================================================ processes
def test_link_cli_refuses_bad_links_in_one_line():
    for link, why in (("udp:1.2.3.4", "unknown kind 'udp'"), ("sim", "simulated by the tracker")):
        res = subprocess.run(
            [sys.executable, "-m", "epuck_link", "--scenario", SCENARIO, "--robot", "r1", "--link", link],
            cwd=ROOT, env=ENV, capture_output=True, text=True, timeout=60,
        )  # fmt: skip
        assert res.returncode == 2 and res.stderr.count("\n") == 1, res.stderr
        assert res.stderr.startswith("epuck_link: error: ") and why in res.stderr


@pytest.mark.parametrize(
    ("args", "why"),
    [(("--stream-period", "0"), "emulator: error: --stream-period: 0.0 s outside [0.001, 1]"),
     (("--stream-period", "nan"), "emulator: error: --stream-period: nan s outside"),
     (("--speed-limit", "0"), "emulator: error: --speed-limit: 0 outside 1..32767")],
)  # fmt: skip
def test_emulator_cli_refuses_bad_options_in_one_line(args: tuple[str, ...], why: str):
    res = subprocess.run(
        [sys.executable, "-m", "epuck_link.emulator", "--tcp", "0", *args],
        cwd=ROOT, env=ENV, capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert res.returncode == 2 and res.stderr.count("\n") == 1 and res.stderr.startswith(why), res.stderr


def test_in_process_emulator_link(hub):
    """``--link emulator``: the link drives an emulator of its own, which starts at the scenario's
    pose and publishes its truth on fleet/F/emu/R."""
    session, endpoint = hub
    fleet = _fleet("d")
    keys = Keys(fleet)
    truth = Collector(session, keys.emu("r1"), Truth)
    link = _link(endpoint, fleet, "emulator")
    cmd = token = None
    try:
        assert link.ready()["link"] == "emulator"
        assert truth.wait(lambda items: len(items) >= 5, 20.0)
        first = truth.snapshot()[0][1]
        assert (first.x, first.y, first.theta) == START
        token = session.liveliness().declare_token(keys.alive("r1"))
        cmd = Commander(session, keys, "r1", (0.0, 0.3))  # sideways: the robot turns left and moves
        assert truth.wait(lambda items: items[-1][1].theta > 0.2, 20.0), link.stderr()[-1500:]
        last = truth.snapshot()[-1][1]
        assert last.y > 0.0 and last.x > START[0]
    finally:
        if cmd is not None:
            cmd.stop()
        if token is not None:
            token.undeclare()
        truth.sub.undeclare()
        code = link.stop()
    assert code == 0 and "link emulator open" in link.stderr()


def _wifi_packets(t: TcpTransport, seconds: float) -> list[tuple[int, bytes]]:
    """Every complete packet (header, payload) the robot sends within ``seconds`` [s]."""
    buf, out = bytearray(), []
    deadline = time.monotonic() + seconds
    while (left := deadline - time.monotonic()) > 0:
        buf += t.read_some(1 << 16, left)
        while buf and len(buf) >= 1 + P.wifi_payload_size(buf[0]):
            n = 1 + P.wifi_payload_size(buf[0])
            out.append((buf[0], bytes(buf[1:n])))
            del buf[:n]
    return out


def test_wifi_stream_against_the_emulator():
    """The 21-byte packet and the header + 104-byte reply, against the emulator over loopback
    TCP, streamed as the ESP32 firmware does: nothing before the first valid command, then a
    packet every stream period whether or not another command comes."""
    period = 0.02
    emu = Proc("-m", "epuck_link.emulator", "--tcp", "0", "--encoders", "32760", "-32760",
               "--stream-period", str(period))  # fmt: skip
    t = None
    try:
        ready = emu.ready()
        assert ready["robot"] is None and ready["pty"] is None and ready["model"] == "e-puck1"
        host, port = ready["tcp"].rsplit(":", 1)
        assert host == "127.0.0.1"
        t = TcpTransport(host, int(port), timeout=2.0)
        t.open()
        assert _wifi_packets(t, 0.15) == []  # no command yet: silence
        t.write(P.wifi_command(0, 0, request=P.REQUEST_SENSORS))
        got = _wifi_packets(t, 0.5)
        # One command, and the robot streams: about 0.5 / 0.02 = 25 packets (a loaded machine
        # sends fewer, never more).
        assert 8 <= len(got) <= 0.5 / period + 2, len(got)
        assert all(h == P.HEADER_SENSORS for h, _ in got)
        assert P.encoders_from_sensors(got[0][1]) == (32760, -32760) and got[0][1][89] == 15  # selector
        t.write(P.wifi_command(0, 0, request=0))  # neither stream: empty packets, streamed too
        got = _wifi_packets(t, 0.3)
        assert got[-1] == (P.HEADER_EMPTY, b"") and sum(h == P.HEADER_EMPTY for h, _ in got) >= 4, got[-3:]
        # Settings bit 2: the int16s are motor positions: the counts become exactly these.
        t.write(P.wifi_command(-12345, 54, request=P.REQUEST_SENSORS, settings=P.SETTING_MOTOR_STEPS))
        got = _wifi_packets(t, 0.2)
        assert P.encoders_from_sensors(got[-1][1]) == (-12345, 54)
        # Image + sensors: 0x01 + 38400 bytes, then 0x02 + 104 bytes, each cycle.
        t.write(P.wifi_command(0, 0, request=P.REQUEST_IMAGE | P.REQUEST_SENSORS))
        got = [h for h, _ in _wifi_packets(t, 0.3)]
        k = got.index(P.HEADER_IMAGE)
        assert got[k : k + 4] == [P.HEADER_IMAGE, P.HEADER_SENSORS] * 2, got
        # Speeds through the codec: the wheels turn in opposite senses, by what the time allows at
        # the rate an e-puck1 really steps for 800 (a 12-tick period: 833.3 steps/s).
        rate = P.step_rate(800, "e-puck1")
        codec = WifiCodec(reply_timeout=2.0)
        t0 = time.monotonic()
        c0 = codec.exchange(t, 800, -800)
        deadline = time.monotonic() + 5
        c1 = c0
        while c1[0] - c0[0] < 100 and time.monotonic() < deadline:
            c1 = codec.exchange(t, 800, -800)
        elapsed = time.monotonic() - t0
        assert 100 <= c1[0] - c0[0] <= rate * elapsed + 1 and c1[1] - c0[1] == -(c1[0] - c0[0])
        codec.exchange(t, 0, 0)
    finally:
        if t is not None:
            t.close()
        assert emu.stop() == 0


def test_link_process_bytes_on_a_pty(hub):
    """The link process itself, on a pty whose other end is the test playing the robot: idle frames,
    full ahead at exactly ``bc e8 03 e8 03 af 00``, malformed commands rejected and counted, the
    watchdog's zero speed, and zero speed again on SIGTERM."""
    session, endpoint = hub
    fleet = _fleet("c")
    keys = Keys(fleet)
    pty = _Pty()
    frames: list[tuple[float, bytes]] = []
    tail = bytearray()
    cond = threading.Condition()
    stop = threading.Event()

    def robot() -> None:  # answers every 7-byte request with the encoders (123, −456)
        while not stop.is_set():
            if not select.select([pty.master], [], [], 0.05)[0]:
                continue
            try:
                data = os.read(pty.master, 4096)
            except OSError:
                return
            with cond:
                tail.extend(data)
                while len(tail) >= 7:
                    frames.append((time.monotonic(), bytes(tail[:7])))
                    del tail[:7]
                    os.write(pty.master, P.encoders_reply(123, -456))
                cond.notify_all()

    responder = threading.Thread(target=robot, daemon=True)
    responder.start()
    wheels = Collector(session, keys.wheels("r1"), Wheels)
    link = _link(endpoint, fleet, f"serial:{pty.path}")
    cmd = token = None
    try:
        info = link.ready()
        assert info["link"] == f"serial:{pty.path}" and info["watchdog"] == 0.5 and info["rate"] == 50

        def count(n: int) -> Callable[[], bool]:
            return lambda: len(frames) >= n

        with cond:
            assert cond.wait_for(count(10), 20.0)
            idle = [f for _, f in frames]
        assert set(idle) == {ZERO_EXCHANGE}, "no agent yet: zero speed, chained with get encoders"
        assert wheels.wait(lambda items: items and items[-1][1].left_steps == 123, 10.0)
        assert wheels.snapshot()[-1][1].right_steps == -456

        token = session.liveliness().declare_token(keys.alive("r1"))
        session.put(keys.pose("r1"), Pose(robot="r1", seq=0, t=0.0, x=-0.7, y=0.0, theta=0.0).encode())
        cmd = Commander(session, keys, "r1", (0.3, 0.0))
        with cond:
            assert cond.wait_for(lambda: frames[-1][1] == FULL_AHEAD, 15.0), frames[-3:]
            n_drive = len(frames)
        # Malformed commands: rejected, counted, and the robot drives on.
        bad = [
            b"\x00garbage",
            msgpack.packb({"schema": 1, "type": "cmd", "robot": "r1", "step": 0, "ax": math.nan, "ay": 0}),
            Command(robot="r2", step=0, ax=1.0, ay=0.0).encode(),  # another robot's id on r1's key
            Pose(robot="r1", seq=0, t=0.0, x=0.0, y=0.0, theta=0.0).encode(),
            msgpack.packb({"schema": 1, "type": "cmd", "robot": "r1", "step": True, "ax": 0.0, "ay": 0.0}),
        ]
        for payload in bad:
            session.put(keys.cmd("r1"), payload)
        assert link.wait_err(f"rejected payload from {keys.cmd('r1')}", 10.0)
        with cond:
            assert cond.wait_for(count(n_drive + 20), 10.0)
            driving = [f for _, f in frames[n_drive:]]
        assert set(driving) == {FULL_AHEAD} and link.popen.poll() is None
        # Commands stop: the watchdog's zero speed.
        last = cmd.stop()
        cmd = None
        with cond:
            assert cond.wait_for(lambda: frames[-1][0] > last + 0.8, 10.0)
            after = [(t, f) for t, f in frames if t > last]
        first_zero = next(t for t, f in after if f == ZERO_EXCHANGE)
        assert all(f == ZERO_EXCHANGE for t, f in after if t >= first_zero)
        assert 0.4 < first_zero - last < STOP_BOUND, first_zero - last
        assert link.wait_err("watchdog: no command for", 5.0)
        # SIGTERM: zero speed (no reply expected), exit 0.
        assert link.stop() == 0
        with cond:
            assert cond.wait_for(lambda: bytes(tail) == ZERO_STOP, 5.0), bytes(tail).hex(" ")
    finally:
        stop.set()
        if cmd is not None:
            cmd.stop()
        if token is not None:
            token.undeclare()
        wheels.sub.undeclare()
        link.stop(signal.SIGKILL)
        responder.join(2)
        pty.close()
    err = link.stderr()
    assert "5 rejected payloads" in err and "zero speed sent" in err, err[-1500:]


@pytest.fixture(scope="module")
def serial_run(hub):
    """Emulator on a pty (encoders start at 32500) + link over serial: drive full ahead across the
    int16 wrap, send camera poses, then stop the commands and let the watchdog stop the robot."""
    session, endpoint = hub
    fleet = _fleet("a")
    keys = Keys(fleet)
    truth = Collector(session, keys.emu("r1"), Truth)
    wheels = Collector(session, keys.wheels("r1"), Wheels)
    odom = Collector(session, keys.odom("r1"), Odom)
    emu = _emulator(endpoint, fleet, "--pty", "--encoders", "32500", "32500")
    link = None
    cmd = token = None
    out: dict[str, Any] = {}
    try:
        e = emu.ready()
        link = _link(endpoint, fleet, f"serial:{e['pty']}")
        link.ready()
        token = session.liveliness().declare_token(keys.alive("r1"))
        cmd = Commander(session, keys, "r1", (0.3, 0.0))
        crossed = wheels.wait(lambda items: items and items[-1][1].left_steps > 33300, 20.0)
        assert crossed, link.stderr()[-1500:]
        # Camera poses while driving: an Odom of the same seq and t for each.
        x = truth.snapshot()[-1][1].x
        for k in (100, 101, 102):
            session.put(keys.pose("r1"), Pose(robot="r1", seq=k, t=k * 0.1, x=x, y=0.0, theta=0.0).encode())
        assert odom.wait(lambda items: any(m.seq == 102 for _, m in items), 10.0)
        last = cmd.stop()
        cmd = None
        assert truth.wait(lambda items: e["clock_origin"] + items[-1][1].t > last + 1.0, 10.0)
        session.put(keys.pose("r1"), Pose(robot="r1", seq=200, t=20.0, x=x, y=0.0, theta=0.0).encode())
        assert odom.wait(lambda items: any(m.seq == 200 for _, m in items), 10.0)
        n = len(wheels.snapshot())
        assert wheels.wait(lambda items: len(items) > n + 5, 10.0)
        out.update(
            emu=e, last=last, truth=truth.snapshot(), wheels=wheels.snapshot(), odom=odom.snapshot(),
            link_alive=link.popen.poll() is None,
        )  # fmt: skip
    finally:
        if cmd is not None:
            cmd.stop()
        if token is not None:
            token.undeclare()
        for c in (truth, wheels, odom):
            c.sub.undeclare()
        codes = [p.stop() for p in (link, emu) if p is not None]
    out.update(codes=codes, link_err=link.stderr() if link else "", emu_err=emu.stderr())
    return out


def test_encoders_unwrap_across_int16(serial_run):
    r = serial_run
    assert r["codes"] == [0, 0], r["link_err"][-1500:]
    counts = [(m.left_steps, m.right_steps) for _, m in r["wheels"]]
    assert counts[0] == (32500, 32500)
    lefts = [c[0] for c in counts]
    assert all(b >= a for a, b in itertools.pairwise(lefts)), "the unwrapped count went back"
    assert max(lefts) > 33300 and all(c[0] == c[1] for c in counts)  # straight ahead, through ±32768
    seqs = [m.seq for _, m in r["wheels"]]
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))
    # The distance the emulator drove is the unwrapped count times the rim travel per step.
    final = r["truth"][-1][1]
    assert final.x - START[0] == pytest.approx((lefts[-1] - 32500) * GEOM.metres_per_step, abs=2e-4)
    assert final.y == 0.0 and final.theta == 0.0
    # Speeds from the count deltas: ≈ 1000 steps/s at full ahead, 0 at rest, never turning.
    fast = [m.v for _, m in r["wheels"] if m.v > 0.1]
    assert len(fast) > 10 and float(np.median(fast)) == pytest.approx(GEOM.max_wheel_speed, rel=0.05)
    assert all(m.omega == 0.0 for _, m in r["wheels"])
    assert r["wheels"][-1][1].v == 0.0


def test_odometry_answers_each_camera_pose(serial_run):
    by_seq = {m.seq: m for _, m in serial_run["odom"]}
    for k in (100, 101, 102):  # driving, saturated: q is the top speed along +x
        assert by_seq[k].t == pytest.approx(k * 0.1)
        assert by_seq[k].vx == pytest.approx(GEOM.max_wheel_speed, rel=1e-6) and by_seq[k].vy == 0.0
    assert (by_seq[200].vx, by_seq[200].vy) == (0.0, 0.0)  # the watchdog reset q


def test_watchdog_stops_the_robot_when_commands_stop(serial_run):
    r = serial_run
    upper, lower, run = _stop_time(r["truth"], r["emu"]["clock_origin"], r["last"] - 0.3)
    latency = upper - r["last"]
    print(f"watchdog (0.5 s): robot stopped {lower - r['last']:.3f}–{latency:.3f} s after the last command")
    assert latency <= STOP_BOUND and lower - r["last"] > 0.3  # stopped by the watchdog, not before
    assert run >= 30 and "watchdog: no command for" in r["link_err"]


@pytest.fixture(scope="module")
def wifi_rig(hub):
    """Emulator on loopback TCP + link over the Wi-Fi protocol with a 2 s command watchdog."""
    _, endpoint = hub
    fleet = _fleet("b")
    port = free_port()
    rig: dict[str, Any] = {"fleet": fleet, "keys": Keys(fleet), "port": port, "endpoint": endpoint}
    rig["start_emu"] = lambda *enc: _emulator(endpoint, fleet, "--tcp", str(port), "--encoders", *enc)
    rig["emu"] = rig["start_emu"]("1000", "1000")
    link = None
    try:
        rig["emu_ready"] = rig["emu"].ready()
        link = rig["link"] = _link(endpoint, fleet, f"tcp:127.0.0.1:{port}", "--watchdog", "2.0")
        link.ready()
        yield rig
    finally:
        if link is not None:
            link.stop()
        rig["emu"].stop()


HELPER = r"""
import json, os, sys, threading, time
import zenoh
from transport.net import NetConfig
from ground.wire import Command, Keys

endpoint, fleet, robot = sys.argv[1:4]
keys = Keys(fleet)
session = zenoh.open(NetConfig(connect=[endpoint]).zenoh())
token = session.liveliness().declare_token(keys.alive(robot))
pub = session.declare_publisher(keys.cmd(robot))
print(json.dumps({"event": "ready", "role": "helper", "pid": os.getpid()}), flush=True)
pace = threading.Event()
end = time.monotonic() + 60
k = 0
while time.monotonic() < end:
    pub.put(Command(robot=robot, step=k, ax=0.3, ay=0.0).encode())
    k += 1
    pace.wait(0.05)
"""


def test_sigkilled_agent_stops_the_robot(wifi_rig, hub):
    """An "agent" holding r1's liveliness token and commanding it is SIGKILLed: the link sees the
    token go (its watchdog timeout is 2 s here, so only liveliness can stop the robot in time)."""
    session, endpoint = hub
    keys = wifi_rig["keys"]
    truth = Collector(session, keys.emu("r1"), Truth)
    helper = Proc("-c", HELPER, endpoint, wifi_rig["fleet"], "r1")
    try:
        helper.ready()
        assert truth.wait(lambda items: _moved(items, 0.01), 20.0), wifi_rig["link"].stderr()[-1500:]
        killed = time.monotonic()
        os.kill(helper.pid, signal.SIGKILL)
        assert helper.popen.wait(10) == -signal.SIGKILL
        origin = wifi_rig["emu_ready"]["clock_origin"]
        assert truth.wait(lambda items: origin + items[-1][1].t > killed + 1.0, 10.0)
    finally:
        helper.stop(signal.SIGKILL)
        truth.sub.undeclare()
    upper, lower, run = _stop_time(truth.snapshot(), origin, killed - 0.3)
    print(f"liveliness: robot stopped {lower - killed:.3f}–{upper - killed:.3f} s after SIGKILL of the agent")
    assert upper - killed <= STOP_BOUND and run >= 30
    assert wifi_rig["link"].wait_err("liveliness token is gone", 5.0)


def test_lost_link_is_reported_and_retried(wifi_rig, hub):
    """The emulator is killed, then restarted on the same port with its counts reset: the link logs
    the loss once, keeps running, re-opens with backoff and continues the counts without a jump."""
    session, _ = hub
    link = wifi_rig["link"]
    wheels = Collector(session, wifi_rig["keys"].wheels("r1"), Wheels)
    try:
        assert wheels.wait(lambda items: len(items) >= 5, 10.0)
        os.kill(wifi_rig["emu"].pid, signal.SIGKILL)
        wifi_rig["emu"].popen.wait(10)
        assert link.wait_err("lost: ", 5.0), link.stderr()[-1500:]
        before = wheels.snapshot()[-1][1]
        assert link.popen.poll() is None
        restarted = time.monotonic()
        wifi_rig["emu"] = wifi_rig["start_emu"]("0", "0")
        wifi_rig["emu_ready"] = wifi_rig["emu"].ready()
        assert link.wait_err("re-opened after", 15.0), link.stderr()[-1500:]
        assert wheels.wait(lambda items: sum(t > restarted for t, _ in items) >= 5, 10.0)
    finally:
        wheels.sub.undeclare()
    after = [m for t, m in wheels.snapshot() if t > restarted]
    assert (after[0].left_steps, after[0].right_steps) == (before.left_steps, before.right_steps)
    assert before.left_steps >= 1000 and after[0].seq > before.seq
    err = link.stderr()
    assert err.count("lost: ") == 1 and err.count("re-opened after") == 1 and link.popen.poll() is None
    assert "Traceback" not in err
