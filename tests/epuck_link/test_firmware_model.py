"""The emulator's firmware behaviours, byte by byte, against GCtronic's sources.

* Advanced sercom chains: a request the firmware knows reads its argument bytes even when the
  emulator does not act on it (e-puck2_main-processor ``src/epuck1x/Asercom2.c``; e-puck-library
  ``Asercom.c``), so an argument byte is never taken for a request.
* The ESP32 Wi-Fi firmware reads commands in whole 21-byte blocks, never byte by byte, drops a
  backlog of five blocks or more, and answers the last command on every pass
  (``socket_e-puck2.c`` L146–195).
* The motors step at whole timer periods (``e_motors.c`` L290, ``motors.c`` L324)."""

from __future__ import annotations

import pytest

from epuck_link import protocol as P
from epuck_link.emulator import EpuckEmulator, WifiSide


def _emulator(model: str = "e-puck1") -> tuple[EpuckEmulator, list[float]]:
    clock = [0.0]
    return EpuckEmulator(clock=lambda: clock[0], model=model), clock


def test_chained_arguments_are_read_as_the_firmware_reads_them():
    """−'L' takes 2 argument bytes and −'P' 4.  Here their arguments hold 0xBC and 0xAF, the
    set-speed and get-encoders bytes: read one byte at a time (the firmware does not), they
    would set speeds and add replies."""
    emu, _ = _emulator()
    h = emu.serial_handler()
    led = bytes([P.binary_request("L"), P.SET_SPEED, 0x01])
    steps = bytes([P.binary_request("P"), P.GET_ENCODERS, P.SET_SPEED, 0x00, 0x00])
    reply = h(led + steps + P.speed_and_encoders(300, -300))
    assert len(reply) == P.ENCODERS_REPLY_SIZE  # one get-encoders: the one asked for
    assert emu.snapshot().left == 300 and emu.snapshot().right == -300
    assert emu.ignored == 3 + 5
    # An unknown request is ignored alone: the next byte is a request again.
    emu2, _ = _emulator()
    assert len(emu2.serial_handler()(bytes([0xC1]) + P.speed_and_encoders(10, 10))) == 4
    assert emu2.ignored == 1


def test_e_puck2_chains_also_skip_the_set_all_actuators_arguments():
    """−0x09 (set all actuators) reads 19 bytes on the e-puck2 (Asercom2.c L475); the e-puck1
    firmware has no such request, so there the same bytes are requests."""
    actuators = bytes([0x100 - 0x09]) + bytes([P.GET_ENCODERS] * 19)
    emu, _ = _emulator("e-puck2")
    assert emu.serial_handler()(actuators + bytes([P.GET_ENCODERS, 0x00])) == P.encoders_reply(0, 0)
    emu1, _ = _emulator("e-puck1")
    assert len(emu1.serial_handler()(actuators + bytes([P.GET_ENCODERS, 0x00]))) == 20 * 4


def test_a_split_chain_waits_for_its_arguments():
    emu, _ = _emulator()
    h = emu.serial_handler()
    assert h(bytes([P.binary_request("P"), 1, 2])) == b""
    assert h(bytes([3, 4, P.GET_ENCODERS])) == b""  # the chain is not over yet
    assert h(b"\x00") == P.encoders_reply(0, 0)


def _cmd(left: int, request: int = P.REQUEST_SENSORS) -> bytes:
    return P.wifi_command(left, -left, request=request)


def test_wifi_reads_whole_blocks_and_stays_misaligned_once_valid():
    emu, _ = _emulator("e-puck2")
    side = WifiSide(emu)
    # Nothing is sent before a valid command; a block not starting with 0x80 is not one.
    side.take(b"\x00" + _cmd(100)[:-1])
    assert side.cycle() == b"" and not side.valid and emu.ignored == 21
    # Once a valid command has come, one stray byte shifts every later block.
    side = WifiSide(emu)
    side.take(_cmd(100))
    first = side.cycle()
    assert first[0] == P.HEADER_SENSORS and side.valid and emu.snapshot().left == 100
    side.take(b"\x7f" + _cmd(200))  # one stray byte, then a command
    side.cycle()  # the block read is the stray byte + 20 bytes of the command: taken as is
    assert emu.snapshot().left != 200
    assert side.waiting  # the command's last byte waits for 20 more: the firmware blocks there


def test_wifi_answers_the_last_command_on_every_pass():
    emu, _ = _emulator("e-puck2")
    side = WifiSide(emu)
    side.take(_cmd(50))
    packets = [side.cycle() for _ in range(4)]  # one command, four passes: four packets
    assert all(p[0] == P.HEADER_SENSORS and len(p) == 1 + P.SENSORS_SIZE for p in packets)
    side.take(_cmd(0, request=0))
    assert side.cycle() == b"\x03" and side.cycle() == b"\x03"  # empty packets, streamed too
    side.take(_cmd(0, request=0x04))  # request bits without image or sensors: nothing sent
    assert side.cycle() == b""


def test_wifi_drops_a_backlog_but_the_last_block():
    emu, _ = _emulator("e-puck2")
    side = WifiSide(emu)
    side.take(b"".join(_cmd(v) for v in (10, 20, 30, 40, 50, 60)))
    side.cycle()
    assert side.dropped == 5 and emu.snapshot().left == 60 and not side.rx


@pytest.mark.parametrize(
    ("model", "speed", "rate"),
    [("e-puck1", 700, 10000 / 14), ("e-puck1", 500, 500.0), ("e-puck1", -950, -1000.0),
     ("e-puck2", 700, 100000 / (2 * 71)), ("e-puck2", 0, 0.0)],
)  # fmt: skip
def test_the_motors_step_at_whole_timer_periods(model: str, speed: int, rate: float):
    assert P.step_rate(speed, model) == pytest.approx(rate, rel=1e-12)
    emu, clock = _emulator(model)
    emu.set_speeds(speed, speed)
    clock[0] = 10.0
    assert emu.snapshot().left_count == round(10.0 * rate)


def test_an_unknown_model_is_refused():
    with pytest.raises(ValueError, match="model"):
        EpuckEmulator(model="e-puck3")
