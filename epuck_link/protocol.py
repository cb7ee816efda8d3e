"""The e-puck's wire protocols, as pure functions (docs/lab.md for the hardware).

Checked against the e-puck2 main-processor firmware (``src/epuck1x/Asercom2.c``,
``src/motors.h``) and GCtronic's e-puck2 PC-side documentation.

**Advanced sercom** (e-puck 1.x and 2, Bluetooth RFCOMM or USB serial, 115200 Bd):

* A binary request is one byte ``−c`` (two's complement of an ASCII letter
  ``c``), followed by its arguments.  Requests can be chained; the chain ends
  with ``0x00``.  The replies come back concatenated, with no header, once the
  terminator has arrived.
* Set speed ``0xBC`` (``−'D'``) + left int16 LE + right int16 LE [steps/s]; no
  reply.  The firmware clamps to ±1000 steps/s (e-puck 1.x) or ±1100 (e-puck2).
* Get encoders ``0xAF`` (``−'Q'``): reply left int16 LE, right int16 LE [steps],
  1000 steps per wheel revolution.  The counts wrap at ±32768.
* ASCII lines also exist: ``D,500,-500\\r`` → ``d\\r\\n``, ``Q\\r`` → ``q,L,R\\r\\n``.

Example: speeds +500/−500, then the terminator, is ``bc f4 01 0c fe 00``.

**e-puck2 Wi-Fi** (TCP port 1000).  The command packet has 21 bytes:

======  ==========================================================================
offset  content
======  ==========================================================================
0       ``0x80`` (packet id: set actuators)
1       request bits: bit 0 image stream, bit 1 sensor stream
2       settings bits: bit 0 calibrate IR, bit 1 obstacle avoidance,
        bit 2 the speeds are motor positions [steps] rather than speeds
3–4     left wheel, int16 LE [steps/s]
5–6     right wheel, int16 LE [steps/s]
7       LED bits: LED1, LED3, LED5, LED7, body, front
8–19    RGB LEDs 2, 4, 6, 8: red, green, blue each, 0–100
20      sound bits
======  ==========================================================================

The robot answers with a header byte then its payload: ``0x01`` + 38400 bytes
of QQVGA RGB565 image when the image stream is requested, ``0x02`` + 104 sensor
bytes when the sensor stream is requested, or the empty ``0x03`` when the
request byte is 0.  Once a command has come it answers the last one again on
every pass of its loop, about every 20 ms, new command or not: it streams
(:class:`epuck_link.emulator.WifiSide`).  In the sensor payload the encoder
counts are int16 LE at offsets 79–80 (left) and 81–82 (right).
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass

from epuck_link.unicycle import wheel_speeds
from ground.params import WheelGeometry


class ProtocolError(ValueError):
    """Bytes that do not follow the protocol; the message names the problem."""


def binary_request(letter: str) -> int:
    """The binary request byte ``−c`` of an ASCII command letter (``'D'`` → ``0xBC``)."""
    if len(letter) != 1 or not 0 < ord(letter) < 128:
        raise ValueError(f"command letter {letter!r}: expected one ASCII character")
    return -ord(letter) & 0xFF


SET_SPEED = binary_request("D")
"""``0xBC``: set the wheel speeds; 4 argument bytes, no reply."""
GET_ENCODERS = binary_request("Q")
"""``0xAF``: read the encoders; 4 reply bytes."""
TERMINATOR = 0x00
"""Ends a chain of binary requests."""
ENCODERS_REPLY_SIZE = 4
"""Reply to :data:`GET_ENCODERS` [bytes]."""
MAX_STEPS_V1 = 1000
"""Firmware speed limit of the e-puck 1.x [steps/s]."""
MAX_STEPS_V2 = 1100
"""Firmware speed limit of the e-puck2 (``MOTOR_SPEED_LIMIT``) [steps/s]."""
MODELS = ("e-puck1", "e-puck2")
"""The robots the emulator models."""


def step_rate(speed: int, model: str) -> float:
    """The rate [steps/s] the motors actually step at for a commanded ``speed`` [steps/s]: the
    step period is a whole number of timer ticks, rounded down.

    * e-puck 1.x: ``10000 / speed`` ticks of 0.1 ms (GCtronic e-puck-library 4cb85cb,
      ``library/motor_led/advance_one_timer/e_motors.c`` L290, ``e_agenda.c`` L54): 700 steps/s
      steps every 14 ticks, at 714.3.
    * e-puck2: ``100000 / (2·speed)`` ticks of 10 µs per microstep, two microsteps a step
      (e-puck2_main-processor d2e0dbb, ``src/motors.c`` L7, L309, L324; assuming ChibiOS's
      PWM period is that many ticks): 700 steps/s at 704.2."""
    if speed == 0:
        return 0.0
    v = abs(int(speed))
    if model == "e-puck1":
        rate = 10000.0 / max(10000 // v, 1)
    elif model == "e-puck2":
        rate = 100000.0 / (2 * max(100000 // (2 * v), 1))
    else:
        raise ValueError(f"model {model!r}: expected one of {', '.join(MODELS)}")
    return math.copysign(rate, speed)


CHAIN_ARGS_V1 = {binary_request(c): n for c, n in (("D", 4), ("L", 2), ("P", 4), ("W", 3), ("w", 35))}
"""Argument bytes each binary request of the e-puck 1.x firmware reads inside a chain; any
other byte is a request without arguments (GCtronic e-puck-library 4cb85cb,
``program/DemoGCtronic-complete/Asercom.c``: 'D' L339–358, 'L' L395–418, 'P' L473–490, 'W'
L533–541 and 'w' L543 when over Bluetooth, unknown requests ignored at L568–569)."""
CHAIN_ARGS_V2 = {
    **CHAIN_ARGS_V1, binary_request("Y"): 2,
    0x100 - 0x09: 19, 0x100 - 0x0A: 12, 0x100 - 0x0F: 1, 0x100 - 0x10: 1, 0x100 - 0x11: 1,
}  # fmt: skip
"""The same for the e-puck2 (e-puck2_main-processor d2e0dbb, ``src/epuck1x/Asercom2.c``): also
'Y' 2 (L1017–1031), set all actuators −0x09 19 (L475), RGB LEDs −0x0A 12 (L575–583),
−0x0F, −0x10 and −0x11 1 each (L637, L668, L700)."""
SERIAL_BAUD = 115200

_INT16 = struct.Struct("<h")
_TWO_INT16 = struct.Struct("<hh")


# ----------------------------------------------------------- numbers
def clamp_steps(value: float, limit: int = MAX_STEPS_V1) -> int:
    """A wheel speed [steps/s] rounded to an integer and clamped to ±``limit``.

    Raises ValueError for NaN or infinity (never sent to a robot)."""
    if not math.isfinite(value):
        raise ValueError(f"wheel speed {value!r} is not finite")
    if not 0 < limit <= 32767:
        raise ValueError(f"speed limit {limit} outside 1..32767")
    return max(-limit, min(limit, round(value)))


def wrap_int16(count: int) -> int:
    """A count [steps] as the int16 the firmware reports (wraps at ±32768)."""
    return (count + 32768) % 65536 - 32768


def wheel_steps(v: float, omega: float, geom: WheelGeometry) -> tuple[int, int, bool]:
    """(v [m/s], ω [rad/s]) of the axle centre → (left, right) [steps/s], saturated.

    Uses :func:`epuck_link.unicycle.wheel_speeds`: when a wheel would exceed
    ``geom.max_steps``, both are scaled by one factor, so the curvature ω/v is
    kept.  Returns ``(left, right, saturated)`` with the speeds rounded."""
    left, right, sat = wheel_speeds(v, omega, geom)
    limit = int(geom.max_steps)
    return clamp_steps(left, limit), clamp_steps(right, limit), sat


# ------------------------------------------------- advanced sercom: requests
def set_speed(left: float, right: float, limit: int = MAX_STEPS_V1) -> bytes:
    """The set-speed request: ``0xBC`` + left, right int16 LE [steps/s], clamped to ±``limit``.

    Not terminated: chain it with others, then :func:`terminate`."""
    return bytes([SET_SPEED]) + _TWO_INT16.pack(clamp_steps(left, limit), clamp_steps(right, limit))


def get_encoders() -> bytes:
    """The get-encoders request ``0xAF`` (not terminated)."""
    return bytes([GET_ENCODERS])


def terminate(*requests: bytes) -> bytes:
    """Chain binary requests and end the chain with ``0x00``."""
    return b"".join(requests) + bytes([TERMINATOR])


def speed_and_encoders(left: float, right: float, limit: int = MAX_STEPS_V1) -> bytes:
    """One chained request: set the speeds [steps/s], then read the encoders.

    Seven bytes; the robot answers with :data:`ENCODERS_REPLY_SIZE` bytes."""
    return terminate(set_speed(left, right, limit), get_encoders())


def parse_encoders(reply: bytes) -> tuple[int, int]:
    """The (left, right) counts [steps, int16, wrapping] of a get-encoders reply."""
    if len(reply) != ENCODERS_REPLY_SIZE:
        raise ProtocolError(f"encoder reply: expected {ENCODERS_REPLY_SIZE} bytes, got {len(reply)}")
    left, right = _TWO_INT16.unpack(reply)
    return int(left), int(right)


def encoders_reply(left: int, right: int) -> bytes:
    """The robot's reply to get-encoders for counts (left, right) [steps] (wrapped to int16)."""
    return _TWO_INT16.pack(wrap_int16(left), wrap_int16(right))


# ------------------------------------- advanced sercom: the robot's parser
@dataclass(frozen=True)
class SetSpeed:
    """A parsed set-speed request (speeds as sent, before the firmware clamps) [steps/s]."""

    left: int
    right: int


@dataclass(frozen=True)
class GetEncoders:
    """A parsed get-encoders request."""


@dataclass(frozen=True)
class EndOfChain:
    """The ``0x00`` that ends a binary chain: the robot sends its replies now."""


@dataclass(frozen=True)
class AsciiLine:
    """One ASCII command line, without its ``\\r``/``\\n``."""

    text: str


@dataclass(frozen=True)
class Ignored:
    """A binary request this implementation does not act on, with the argument bytes the
    firmware reads for it (none for a request it does not know: it ignores that byte alone)."""

    byte: int
    args: bytes = b""


Request = SetSpeed | GetEncoders | EndOfChain | AsciiLine | Ignored


class AsercomParser:
    """Splits the byte stream a robot receives into requests, as the firmware does.

    Feed it any chunks (a request may be split across reads); it returns each
    complete request once.  Inside a binary chain every byte is a request:
    ``0xBC`` takes 4 argument bytes, ``0xAF`` none, ``0x00`` ends the chain; the
    other requests the firmware knows are skipped with their arguments (``args``:
    :data:`CHAIN_ARGS_V1` or :data:`CHAIN_ARGS_V2`), so an argument byte is never
    taken for a request; any other byte is ignored alone.  Outside a chain, a byte
    ≥ 0x80 starts one, a printable byte starts an ASCII line (ended by ``\\r`` or
    ``\\n``), and stray ``0x00``, ``\\r``, ``\\n`` are skipped.  ASCII lines
    longer than ``max_line`` bytes are cut there."""

    def __init__(self, max_line: int = 128, args: dict[int, int] | None = None):
        self.max_line = max_line
        self.args = CHAIN_ARGS_V1 if args is None else args
        self._buf = bytearray()
        self._in_chain = False
        self._line: bytearray | None = None

    def feed(self, data: bytes) -> list[Request]:
        """Append ``data`` and return the requests it completed, in order."""
        self._buf += data
        out: list[Request] = []
        buf = self._buf
        while buf:
            if self._in_chain:
                b = buf[0]
                if b == TERMINATOR:
                    out.append(EndOfChain())
                    self._in_chain = False
                    del buf[0]
                elif b == SET_SPEED:
                    if len(buf) < 5:
                        break
                    left, right = _TWO_INT16.unpack(bytes(buf[1:5]))
                    out.append(SetSpeed(int(left), int(right)))
                    del buf[:5]
                elif b == GET_ENCODERS:
                    out.append(GetEncoders())
                    del buf[0]
                else:
                    n = self.args.get(b, 0)
                    if len(buf) < 1 + n:
                        break
                    out.append(Ignored(b, bytes(buf[1 : 1 + n])))
                    del buf[: 1 + n]
            elif self._line is not None:
                ends = [i for i in (buf.find(b"\r"), buf.find(b"\n")) if i >= 0]
                if not ends:
                    self._line += buf
                    del buf[:]
                    if len(self._line) > self.max_line:
                        out.append(AsciiLine(self._line[: self.max_line].decode("ascii", "replace")))
                        self._line = None
                    break
                end = min(ends)
                self._line += buf[:end]
                del buf[: end + 1]
                out.append(AsciiLine(self._line[: self.max_line].decode("ascii", "replace")))
                self._line = None
            else:
                b = buf[0]
                if b >= 0x80:
                    self._in_chain = True
                elif b in (TERMINATOR, 0x0D, 0x0A):
                    del buf[0]
                else:
                    self._line = bytearray()
        return out


def ascii_reply(line: str, encoders: tuple[int, int]) -> tuple[bytes, tuple[int, int] | None]:
    """The firmware's answer to an ASCII line, and the speeds it sets (or None).

    ``D,l,r`` → ``d\\r\\n`` and speeds (l, r) [steps/s]; ``Q`` → ``q,L,R\\r\\n``
    with the int16 ``encoders`` [steps]; anything else → ``z,Command not
    found\\r\\n``.  Letters are accepted in either case."""
    parts = line.strip().split(",")
    cmd = parts[0].upper() if parts[0] else ""
    if cmd == "D":
        try:
            speeds = (int(parts[1]), int(parts[2])) if len(parts) == 3 else None
        except ValueError:
            speeds = None
        return b"d\r\n", speeds
    if cmd == "Q":
        return f"q,{encoders[0]},{encoders[1]}\r\n".encode(), None
    return b"z,Command not found\r\n", None


# ------------------------------------------------------ e-puck2 Wi-Fi
WIFI_PORT = 1000
"""TCP port of the e-puck2's Wi-Fi server."""
WIFI_COMMAND = 0x80
"""First byte of a command packet (set actuators)."""
WIFI_COMMAND_SIZE = 21
REQUEST_IMAGE = 0x01
REQUEST_SENSORS = 0x02
SETTING_CALIBRATE_IR = 0x01
SETTING_OBSTACLE_AVOIDANCE = 0x02
SETTING_MOTOR_STEPS = 0x04
"""Settings bit: the two int16 set the encoder counts [steps] instead of the speeds."""
HEADER_IMAGE = 0x01
HEADER_SENSORS = 0x02
HEADER_EMPTY = 0x03
IMAGE_SIZE = 160 * 120 * 2
"""QQVGA RGB565 image payload [bytes]."""
SENSORS_SIZE = 104
"""Sensor payload [bytes]."""
SENSORS_ENCODERS_OFFSET = 79
"""Offset of the left encoder count in the sensor payload; the right one follows at 81."""
_PAYLOAD_SIZES = {HEADER_IMAGE: IMAGE_SIZE, HEADER_SENSORS: SENSORS_SIZE, HEADER_EMPTY: 0}


@dataclass(frozen=True)
class WifiCommand:
    """The fields of a Wi-Fi command packet (see the module docstring for the layout)."""

    request: int = REQUEST_SENSORS
    settings: int = 0
    left: int = 0
    right: int = 0
    """Wheel speeds [steps/s] (or encoder counts [steps] with SETTING_MOTOR_STEPS)."""
    leds: int = 0
    rgb: tuple[int, ...] = (0,) * 12
    """Red, green, blue of the RGB LEDs 2, 4, 6, 8, each 0–100."""
    sound: int = 0


def wifi_command(
    left: float,
    right: float,
    *,
    request: int = REQUEST_SENSORS,
    settings: int = 0,
    leds: int = 0,
    rgb: tuple[int, ...] = (0,) * 12,
    sound: int = 0,
    limit: int = MAX_STEPS_V2,
) -> bytes:
    """The 21-byte Wi-Fi command packet; speeds [steps/s] are clamped to ±``limit``.

    With :data:`SETTING_MOTOR_STEPS` in ``settings`` the two values are encoder
    counts [steps] instead, clamped to the int16 range only."""
    if len(rgb) != 12:
        raise ValueError(f"rgb: expected 12 values, got {len(rgb)}")
    for name, v in (("request", request), ("settings", settings), ("leds", leds), ("sound", sound), *(
        (f"rgb[{i}]", c) for i, c in enumerate(rgb)
    )):  # fmt: skip
        if not 0 <= v <= 255:
            raise ValueError(f"{name}: {v} is not a byte")
    bound = 32767 if settings & SETTING_MOTOR_STEPS else limit
    return (
        bytes([WIFI_COMMAND, request, settings])
        + _TWO_INT16.pack(clamp_steps(left, bound), clamp_steps(right, bound))
        + bytes([leds, *rgb, sound])
    )


def parse_wifi_command(packet: bytes) -> WifiCommand:
    """Decode a 21-byte Wi-Fi command packet (what the robot does)."""
    if len(packet) != WIFI_COMMAND_SIZE:
        raise ProtocolError(f"wifi command: expected {WIFI_COMMAND_SIZE} bytes, got {len(packet)}")
    if packet[0] != WIFI_COMMAND:
        raise ProtocolError(f"wifi command: first byte 0x{packet[0]:02x}, expected 0x{WIFI_COMMAND:02x}")
    left, right = _TWO_INT16.unpack(packet[3:7])
    return WifiCommand(
        request=packet[1], settings=packet[2], left=int(left), right=int(right), leds=packet[7],
        rgb=tuple(packet[8:20]), sound=packet[20],
    )  # fmt: skip


def wifi_payload_size(header: int) -> int:
    """Payload length [bytes] that follows a reply header byte."""
    try:
        return _PAYLOAD_SIZES[header]
    except KeyError:
        raise ProtocolError(f"wifi reply: unknown header 0x{header:02x}") from None


def sensors_payload(left: int, right: int, battery: int = 3500, selector: int = 15) -> bytes:
    """A 104-byte sensor payload with these encoder counts [steps] (wrapped to int16).

    Everything the emulator does not model is zero, except the raw battery ADC
    value (offsets 83–84) and the selector position (offset 89)."""
    out = bytearray(SENSORS_SIZE)
    out[SENSORS_ENCODERS_OFFSET : SENSORS_ENCODERS_OFFSET + 4] = encoders_reply(left, right)
    out[83:85] = struct.pack("<H", battery & 0xFFFF)
    out[89] = selector & 0x0F
    return bytes(out)


def encoders_from_sensors(payload: bytes) -> tuple[int, int]:
    """The (left, right) counts [steps, int16] at offsets 79–82 of a sensor payload."""
    if len(payload) != SENSORS_SIZE:
        raise ProtocolError(f"wifi sensors: expected {SENSORS_SIZE} bytes, got {len(payload)}")
    return parse_encoders(payload[SENSORS_ENCODERS_OFFSET : SENSORS_ENCODERS_OFFSET + 4])


def wifi_reply(request: int, left: int, right: int) -> bytes:
    """The robot's complete answer to a command packet with these request bits.

    Image (zeros; the emulator has no camera) first when requested, then the
    sensors when requested; the empty packet when neither was."""
    out = b""
    if request & REQUEST_IMAGE:
        out += bytes([HEADER_IMAGE]) + bytes(IMAGE_SIZE)
    if request & REQUEST_SENSORS:
        out += bytes([HEADER_SENSORS]) + sensors_payload(left, right)
    return out or bytes([HEADER_EMPTY])


# ------------------------------------------------------ encoder unwrapping
class EncoderTracker:
    """Unwraps the int16 encoder counts into continuous counts [steps].

    The first reading is taken as is; each later one adds the int16 difference
    to the previous reading, so the counts keep growing across the wrap.  This
    assumes a wheel turns less than 32767 steps between two reads (≈ 30 s at
    the top speed).  :meth:`rebase` (after the link was re-opened, when the
    robot may have been restarted) makes the next reading continue the counts
    without a jump."""

    def __init__(self) -> None:
        self.left = 0
        self.right = 0
        """Unwrapped counts [steps]."""
        self._raw: tuple[int, int] | None = None
        self._started = False

    def update(self, raw_left: int, raw_right: int) -> tuple[int, int]:
        """Take a reading (int16 counts [steps]); return the unwrapped (left, right)."""
        for v in (raw_left, raw_right):
            if not -32768 <= v <= 32767:
                raise ValueError(f"encoder reading {v} is not an int16")
        if self._raw is None:
            if not self._started:
                self.left, self.right = raw_left, raw_right
                self._started = True
        else:
            self.left += wrap_int16(raw_left - self._raw[0])
            self.right += wrap_int16(raw_right - self._raw[1])
        self._raw = (raw_left, raw_right)
        return self.left, self.right

    def rebase(self) -> None:
        """The next reading continues the counts from where they are."""
        self._raw = None
