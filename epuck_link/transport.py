"""Links to a robot: link strings, serial and TCP transports, and a port that keeps them up.

A link string names how to reach one robot (``RobotSpec.link`` in the scenario,
or ``python -m epuck_link --link``):

* ``serial:DEVICE`` (``serial:/dev/rfcomm0``): advanced sercom over a serial
  device (Bluetooth RFCOMM, USB, a pseudo-terminal), 115200 Bd;
* ``tcp:HOST`` or ``tcp:HOST:PORT``: e-puck2 Wi-Fi packets over TCP, port 1000
  unless given (an IPv6 address goes in brackets, ``tcp:[::1]:1000``);
* ``emulator``: an in-process :class:`~epuck_link.emulator.EpuckEmulator`;
* ``sim``: the robot is simulated by the tracker; there is no link.

Every read and write is bounded by a timeout.  A failure raises
:class:`LinkError` with a one-line reason; :class:`RobotPort` turns it into a
log line and re-opens the link with exponential backoff, so a lost robot never
ends the process.
"""

from __future__ import annotations

import socket
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from epuck_link import protocol as P

KINDS = ("serial", "tcp", "sim", "emulator")


class LinkError(Exception):
    """The link to the robot failed; ``reason`` is one line."""

    def __init__(self, reason: str):
        self.reason = reason
        super().__init__(reason)


# ------------------------------------------------------------ link strings
@dataclass(frozen=True)
class LinkSpec:
    """A parsed link string."""

    kind: str
    """One of :data:`KINDS`."""
    device: str = ""
    """Serial device path (kind ``serial``)."""
    host: str = ""
    port: int = P.WIFI_PORT
    """TCP host and port (kind ``tcp``)."""

    def __str__(self) -> str:
        if self.kind == "serial":
            return f"serial:{self.device}"
        if self.kind == "tcp":
            host = f"[{self.host}]" if ":" in self.host else self.host
            return f"tcp:{host}:{self.port}"
        return self.kind


def parse_link(text: str) -> LinkSpec:
    """Parse a link string (see the module docstring).

    Raises ValueError with a one-line reason naming the problem."""
    if not isinstance(text, str) or not text.strip():
        raise ValueError("link: empty; expected serial:DEVICE, tcp:HOST[:PORT], sim or emulator")
    if any(c.isspace() or c == "\0" for c in text):
        raise ValueError(f"link {text!r}: contains whitespace")
    kind, sep, rest = text.partition(":")
    if kind in ("sim", "emulator"):
        if sep:
            raise ValueError(f"link {text!r}: {kind!r} takes no argument")
        return LinkSpec(kind)
    if kind == "serial":
        if not rest:
            raise ValueError(f"link {text!r}: missing the device path after 'serial:'")
        return LinkSpec("serial", device=rest)
    if kind == "tcp":
        return _parse_tcp(text, rest)
    raise ValueError(
        f"link {text!r}: unknown kind {kind!r}; expected serial:DEVICE, tcp:HOST[:PORT], sim or emulator"
    )


def _parse_tcp(text: str, rest: str) -> LinkSpec:
    port_text = ""
    if rest.startswith("["):
        end = rest.find("]")
        if end < 0:
            raise ValueError(f"link {text!r}: unclosed '[' in the host")
        host, after = rest[1:end], rest[end + 1 :]
        if after:
            if not after.startswith(":"):
                raise ValueError(f"link {text!r}: expected ':PORT' after ']'")
            port_text = after[1:]
    elif rest.count(":") > 1:
        raise ValueError(f"link {text!r}: write an IPv6 host in brackets, tcp:[ADDR]:PORT")
    else:
        host, _, port_text = rest.partition(":")
        if ":" in rest and not port_text:
            raise ValueError(f"link {text!r}: missing the port after ':'")
    if not host:
        raise ValueError(f"link {text!r}: missing the host after 'tcp:'")
    port = P.WIFI_PORT
    if port_text:
        if not port_text.isdigit() or not 1 <= int(port_text) <= 65535:
            raise ValueError(f"link {text!r}: port {port_text!r} is not an integer in 1..65535")
        port = int(port_text)
    return LinkSpec("tcp", host=host, port=port)


# -------------------------------------------------------------- transports
class Transport(ABC):
    """A byte pipe to one robot.  Methods raise :class:`LinkError` and nothing else."""

    @property
    @abstractmethod
    def name(self) -> str:
        """A short description for log lines."""

    @property
    @abstractmethod
    def is_open(self) -> bool:
        """Opened and not closed since (a failed read or write does not close it)."""

    @abstractmethod
    def open(self) -> None:
        """Open (closing first if open); LinkError with the reason if the robot is unreachable."""

    @abstractmethod
    def close(self) -> None:
        """Close; never raises, may be called when closed."""

    @abstractmethod
    def write(self, data: bytes) -> None:
        """Send all of ``data`` (bounded by the transport's timeout)."""

    @abstractmethod
    def read_exact(self, n: int, timeout: float) -> bytes:
        """Exactly ``n`` bytes, or LinkError once ``timeout`` [s] has passed."""

    @abstractmethod
    def read_some(self, n: int, timeout: float) -> bytes:
        """Up to ``n`` bytes: what has arrived, else the first that arrive within ``timeout``
        [s]; ``b""`` if none did (``timeout`` 0: only what is there now)."""

    def reopen(self) -> None:
        """Close, then open."""
        self.close()
        self.open()


class SerialTransport(Transport):
    """Advanced sercom over a serial device with pyserial (``serial.Serial(device, 115200)``)."""

    def __init__(self, device: str, baudrate: int = P.SERIAL_BAUD, timeout: float = 0.25):
        self.device = device
        self.baudrate = baudrate
        self.timeout = timeout
        """Bound of every write and of each read call [s]."""
        self._port: Any = None

    @property
    def name(self) -> str:
        """``serial:<device>``."""
        return f"serial:{self.device}"

    @property
    def is_open(self) -> bool:
        """A port is open (after :meth:`open`, until :meth:`close`)."""
        return self._port is not None

    def open(self) -> None:
        """Open the device at ``baudrate``, :attr:`timeout` bounding reads and writes, and
        drop what the input buffer holds; LinkError if it cannot be opened."""
        import serial

        self.close()
        try:
            self._port = serial.Serial(
                self.device, self.baudrate, timeout=self.timeout, write_timeout=self.timeout
            )
            self._port.reset_input_buffer()
        except (serial.SerialException, OSError, ValueError) as e:
            self.close()
            raise LinkError(f"{self.name}: cannot open: {_one_line(e)}") from None

    def close(self) -> None:
        """Close the port, if open; an error closing a dead device is ignored."""
        port, self._port = self._port, None
        if port is not None:
            try:
                port.close()
            except Exception:  # closing a dead device: nothing left to do
                pass

    def write(self, data: bytes) -> None:
        """Write ``data``; LinkError if not open, on a failure or on a short write."""
        import serial

        if self._port is None:
            raise LinkError(f"{self.name}: not open")
        try:
            n = self._port.write(data)
        except (serial.SerialException, OSError) as e:
            raise LinkError(f"{self.name}: write failed: {_one_line(e)}") from None
        if n != len(data):
            raise LinkError(f"{self.name}: wrote {n} of {len(data)} bytes")

    def read_exact(self, n: int, timeout: float) -> bytes:
        """Read ``n`` bytes; LinkError on a failure, or if they are not all in once
        ``timeout`` [s] has passed (one read call may overrun it by :attr:`timeout`)."""
        import serial

        if self._port is None:
            raise LinkError(f"{self.name}: not open")
        deadline = time.monotonic() + timeout
        buf = bytearray()
        try:
            while len(buf) < n:
                if time.monotonic() >= deadline:
                    raise LinkError(f"{self.name}: no reply: {len(buf)} of {n} bytes within {timeout:.2f} s")
                buf += self._port.read(n - len(buf))
        except (serial.SerialException, OSError) as e:
            raise LinkError(f"{self.name}: read failed: {_one_line(e)}") from None
        return bytes(buf)

    def read_some(self, n: int, timeout: float) -> bytes:
        """What is waiting, up to ``n`` bytes; if nothing is, one byte waited for up to
        ``timeout`` [s] (``b""`` if none comes, at once for ``timeout`` ≤ 0)."""
        import serial

        if self._port is None:
            raise LinkError(f"{self.name}: not open")
        try:
            waiting = int(self._port.in_waiting)
            if waiting or timeout <= 0:
                return bytes(self._port.read(min(n, waiting))) if waiting else b""
            self._port.timeout = timeout
            try:
                return bytes(self._port.read(1))
            finally:
                self._port.timeout = self.timeout
        except (serial.SerialException, OSError) as e:
            raise LinkError(f"{self.name}: read failed: {_one_line(e)}") from None


class TcpTransport(Transport):
    """A TCP client (the e-puck2's Wi-Fi server), with connect and I/O timeouts."""

    def __init__(
        self, host: str, port: int = P.WIFI_PORT, timeout: float = 0.25, connect_timeout: float = 1.0
    ):
        self.host = host
        self.port = port
        self.timeout = timeout
        self.connect_timeout = connect_timeout
        self._sock: socket.socket | None = None

    @property
    def name(self) -> str:
        """``tcp:<host>:<port>``."""
        return f"tcp:{self.host}:{self.port}"

    @property
    def is_open(self) -> bool:
        """A socket is connected (after :meth:`open`, until :meth:`close`)."""
        return self._sock is not None

    def open(self) -> None:
        """Connect within ``connect_timeout`` [s], with TCP_NODELAY and ``timeout`` [s] on the
        socket; LinkError if the robot cannot be reached."""
        self.close()
        try:
            s = socket.create_connection((self.host, self.port), timeout=self.connect_timeout)
        except OSError as e:
            raise LinkError(f"{self.name}: cannot connect: {_one_line(e)}") from None
        s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        s.settimeout(self.timeout)
        self._sock = s

    def close(self) -> None:
        """Close the socket, if open; errors are ignored."""
        s, self._sock = self._sock, None
        if s is not None:
            try:
                s.close()
            except OSError:
                pass

    def write(self, data: bytes) -> None:
        """Send all of ``data`` within ``timeout`` [s]; LinkError if not open or on a failure."""
        if self._sock is None:
            raise LinkError(f"{self.name}: not open")
        try:
            self._sock.settimeout(self.timeout)
            self._sock.sendall(data)
        except OSError as e:  # socket.timeout is an OSError
            raise LinkError(f"{self.name}: send failed: {_one_line(e)}") from None

    def read_exact(self, n: int, timeout: float) -> bytes:
        """Receive exactly ``n`` bytes within ``timeout`` [s]; LinkError past it, on a
        failure, or when the robot closes the connection."""
        if self._sock is None:
            raise LinkError(f"{self.name}: not open")
        deadline = time.monotonic() + timeout
        buf = bytearray()
        while len(buf) < n:
            left = deadline - time.monotonic()
            if left <= 0:
                raise LinkError(f"{self.name}: no reply: {len(buf)} of {n} bytes within {timeout:.2f} s")
            try:
                self._sock.settimeout(left)
                chunk = self._sock.recv(n - len(buf))
            except TimeoutError:
                continue
            except OSError as e:
                raise LinkError(f"{self.name}: receive failed: {_one_line(e)}") from None
            if not chunk:
                raise LinkError(f"{self.name}: connection closed by the robot")
            buf += chunk
        return bytes(buf)

    def read_some(self, n: int, timeout: float) -> bytes:
        """One ``recv`` of up to ``n`` bytes, waiting up to ``timeout`` [s] (0: only what
        is there); ``b""`` if nothing came, LinkError on a failure or when the robot closed the
        connection."""
        if self._sock is None:
            raise LinkError(f"{self.name}: not open")
        try:
            self._sock.settimeout(max(timeout, 0.0))  # 0: non-blocking, only what is there
            chunk = self._sock.recv(n)
        except (TimeoutError, BlockingIOError):
            return b""
        except OSError as e:
            raise LinkError(f"{self.name}: receive failed: {_one_line(e)}") from None
        if not chunk:
            raise LinkError(f"{self.name}: connection closed by the robot")
        return chunk


class LoopTransport(Transport):
    """An in-process pipe to a byte handler (the emulator's serial side): what is
    written is handled at once and its reply queued for reading."""

    def __init__(self, handler_factory: Callable[[], Callable[[bytes], bytes]], name: str = "emulator"):
        self._factory = handler_factory
        self._name = name
        self._handler: Callable[[bytes], bytes] | None = None
        self._pending = bytearray()

    @property
    def name(self) -> str:
        """The name given at construction (default ``emulator``)."""
        return self._name

    @property
    def is_open(self) -> bool:
        """A handler is in place (after :meth:`open`, until :meth:`close`)."""
        return self._handler is not None

    def open(self) -> None:
        """Make a fresh handler with the factory and drop any queued reply."""
        self._handler = self._factory()
        self._pending.clear()

    def close(self) -> None:
        """Drop the handler (queued reply bytes are dropped at the next :meth:`open`)."""
        self._handler = None

    def write(self, data: bytes) -> None:
        """Hand ``data`` to the handler at once and queue its reply."""
        if self._handler is None:
            raise LinkError(f"{self.name}: not open")
        self._pending += self._handler(data)

    def read_exact(self, n: int, timeout: float) -> bytes:
        """The first ``n`` queued reply bytes; LinkError at once if fewer are queued
        (nothing comes later: ``timeout`` is unused)."""
        if self._handler is None:
            raise LinkError(f"{self.name}: not open")
        if len(self._pending) < n:
            raise LinkError(f"{self.name}: no reply: {len(self._pending)} of {n} bytes")
        out = bytes(self._pending[:n])
        del self._pending[:n]
        return out

    def read_some(self, n: int, timeout: float) -> bytes:
        """Up to ``n`` queued reply bytes, ``b""`` if none; never waits."""
        if self._handler is None:
            raise LinkError(f"{self.name}: not open")
        out = bytes(self._pending[:n])
        del self._pending[:n]
        return out


class CutTransport(Transport):
    """Another transport whose radio link is cut while ``cut()`` holds (a fault plan's ``links``),
    as a real radio link is cut: nothing tells the link process, which learns of the loss only
    when a reply does not come within its timeout.

    * **Writes return.**  pyserial's ``Serial.write`` (3.5, ``serial/serialposix.py`` L612–664)
      returns once ``os.write`` has put the bytes in the tty, and an RFCOMM tty queues them on its
      channel and returns (Linux ``net/bluetooth/rfcomm/tty.c``, ``rfcomm_tty_write``); the
      Bluetooth controller then retransmits them until the link supervision timeout ends the
      connection (20 s by default: Core specification, HCI ``Write_Link_Supervision_Timeout``,
      default 0x7D00 slots of 0.625 ms).  A TCP ``send`` returns once the bytes are in the
      socket's send buffer, and Linux retransmits them for many minutes (``tcp_retries2``, 15 by
      default, at least 924.6 s: ``Documentation/networking/ip-sysctl.rst``).  At one short
      command an exchange, neither buffer fills before the reply timeout, so no write blocks or
      fails either.  Here the bytes are held (:attr:`writes_in_cut` counts the writes): the robot
      receives nothing and drives on at the speeds it last received, and should the link come
      back before the port gives up, they arrive late, as retransmitted bytes do.
    * **Reads time out.**  Nothing comes from the robot: pyserial's ``read`` returns what arrived
      once its timeout has passed (``serialposix.py`` L553–602), and a socket's ``recv`` raises
      ``timeout``.  A read that starts in a cut waits its whole timeout on :attr:`clock` and gets
      nothing, unless the cut ends first (the held bytes then go through and the read goes on
      with the time left).  Even the e-puck2's stream, which the robot sends whether or not a
      command came, does not get through.  So the codecs raise "no reply" one reply timeout
      after the command, and :class:`RobotPort` declares the loss then, as on a real link:
      never at the write.
    * **Opening fails** while the link is cut (the robot is out of reach), and closing drops what
      is held (the connection is gone).

    ``clock`` [s] and ``sleep`` are the time the reads wait on (tests pass a simulated clock)."""

    POLL = 0.01
    """How often a read waiting in a cut looks whether it has ended [s]."""

    def __init__(
        self,
        inner: Transport,
        cut: Callable[[], bool],
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
    ):
        self.inner = inner
        self.cut = cut
        self.clock = clock
        self.sleep = sleep
        self._held = bytearray()
        """Bytes written while cut, not yet through."""
        self.writes_in_cut = 0
        """Writes made while the link was cut (they returned, as on a dead radio link)."""
        self.silent_reads = 0
        """Reads that waited out their timeout in a cut."""

    @property
    def name(self) -> str:
        """The inner transport's name."""
        return self.inner.name

    @property
    def is_open(self) -> bool:
        """The inner transport is open."""
        return self.inner.is_open

    def open(self) -> None:
        """LinkError while the link is cut (the robot is out of reach); else drop the held
        bytes and open the inner transport."""
        if self.cut():
            raise LinkError(f"{self.name}: link cut (fault plan): robot out of reach")
        self._held.clear()
        self.inner.open()

    def close(self) -> None:
        """Drop the held bytes and close the inner transport."""
        self._held.clear()
        self.inner.close()

    def write(self, data: bytes) -> None:
        """While the link is cut, hold ``data`` and return (:attr:`writes_in_cut`); else send
        what was held, then ``data``.  LinkError if the inner transport is not open."""
        if not self.inner.is_open:
            raise LinkError(f"{self.name}: not open")
        if self.cut():
            self._held += data
            self.writes_in_cut += 1
            return
        self._release()
        self.inner.write(data)

    def read_exact(self, n: int, timeout: float) -> bytes:
        """The inner transport's read, with ``timeout`` [s] less any wait for a cut to end (the
        held bytes then go through); LinkError if the link stays cut all of ``timeout``."""
        start = self.clock()
        if self._silent(timeout):
            raise LinkError(
                f"{self.name}: no reply: 0 of {n} bytes within {timeout:.2f} s; link cut (fault plan)"
            )
        return self.inner.read_exact(n, max(0.0, start + timeout - self.clock()))

    def read_some(self, n: int, timeout: float) -> bytes:
        """As :meth:`read_exact`, but ``b""`` if the link stays cut all of ``timeout`` [s]."""
        start = self.clock()
        if self._silent(timeout):
            return b""
        return self.inner.read_some(n, max(0.0, start + timeout - self.clock()))

    def _silent(self, timeout: float) -> bool:
        """Wait while the link is cut, ``timeout`` [s] at most: True if it still is (nothing came);
        else the held bytes go through and False."""
        deadline = self.clock() + timeout
        while self.cut():
            left = deadline - self.clock()
            if left <= 0:
                if timeout > 0:
                    self.silent_reads += 1
                return True
            self.sleep(min(left, self.POLL))
        self._release()
        return False

    def _release(self) -> None:
        """The link is up again: what was written in the cut reaches the robot now, late."""
        if self._held:
            data = bytes(self._held)
            self._held.clear()
            self.inner.write(data)


def _one_line(e: BaseException) -> str:
    return " ".join(str(e).split()) or type(e).__name__


# ------------------------------------------------------------------ codecs
class Codec(ABC):
    """How wheel speeds and encoder reads travel over one kind of link."""

    def __init__(
        self,
        reply_timeout: float = 0.25,
        limit: int = P.MAX_STEPS_V1,
        clock: Callable[[], float] = time.monotonic,
    ):
        self.reply_timeout = reply_timeout
        """Longest wait for a reply [s]."""
        self.limit = limit
        """Speed clamp [steps/s]."""
        self.clock = clock
        """The time a reply is waited for on [s] (the transport's; tests pass a simulated one)."""

    @abstractmethod
    def exchange(self, t: Transport, left: int, right: int) -> tuple[int, int]:
        """Set the wheel speeds [steps/s] and return the int16 encoder counts [steps]."""

    @abstractmethod
    def stop_request(self) -> bytes:
        """Bytes that set zero speed and expect no reply."""

    def reset(self) -> None:
        """The link was (re-)opened: forget any partial reply of the last connection."""
        return None


class AsercomCodec(Codec):
    """Advanced sercom: ``0xBC l l r r 0xAF 0x00`` → 4 bytes."""

    def exchange(self, t: Transport, left: int, right: int) -> tuple[int, int]:
        """Send one chain that sets the speeds [steps/s] (clamped to ±:attr:`limit`) and reads
        the encoders; the int16 counts [steps] of the 4-byte reply.  LinkError on a late or
        malformed reply."""
        t.write(P.speed_and_encoders(left, right, self.limit))
        try:
            return P.parse_encoders(t.read_exact(P.ENCODERS_REPLY_SIZE, self.reply_timeout))
        except P.ProtocolError as e:
            raise LinkError(str(e)) from None

    def stop_request(self) -> bytes:
        """The set-speed request for zero speed, ended with ``0x00``: no encoder read, so no reply."""
        return P.terminate(P.set_speed(0, 0, self.limit))


class WifiCodec(Codec):
    """e-puck2 Wi-Fi: a 21-byte command packet asking for the sensors; the robot streams.

    Once a command has arrived, the robot's Wi-Fi processor sends a packet (``0x02`` + 104
    bytes of sensors, for the request bits used here) on every pass of its loop, new command or
    not (:class:`epuck_link.emulator.TcpServer` models it).  So an exchange takes every
    complete packet that has arrived and uses the newest sensor packet; it waits only when
    none has come since the last exchange.  Reading one reply per command instead would fall
    behind the stream without bound when it runs faster than the link polls."""

    MAX_READS = 256
    """Reads in one exchange at most: draining ends even if the stream never pauses."""

    def __init__(
        self,
        reply_timeout: float = 0.25,
        limit: int = P.MAX_STEPS_V2,
        clock: Callable[[], float] = time.monotonic,
    ):
        super().__init__(reply_timeout, limit, clock)
        self._rx = bytearray()
        self.packets = 0
        """Complete packets received."""
        self.skipped = 0
        """Sensor packets passed over for a newer one."""

    def reset(self) -> None:
        """Drop the bytes left in the receive buffer from the last connection."""
        self._rx.clear()

    def exchange(self, t: Transport, left: int, right: int) -> tuple[int, int]:
        """Send a command packet with the speeds [steps/s] that asks for the sensors, then take
        every packet that has arrived: the encoder counts [steps] of the newest sensor packet,
        waited for up to ``reply_timeout`` [s] only if none has come.  LinkError if none comes,
        or on a malformed packet."""
        t.write(P.wifi_command(left, right, request=P.REQUEST_SENSORS, limit=self.limit))
        deadline = self.clock() + self.reply_timeout
        newest: tuple[int, int] | None = None
        try:
            for _ in range(self.MAX_READS):
                chunk = t.read_some(1 << 16, 0.0)  # everything there now
                if not chunk and newest is None:
                    left_s = deadline - self.clock()
                    if left_s <= 0:
                        raise LinkError(f"{t.name}: no sensor packet within {self.reply_timeout:.2f} s")
                    chunk = t.read_some(1 << 16, left_s)
                if not chunk:
                    if newest is not None:
                        return newest
                    continue
                self._rx += chunk
                for enc in self._packets():
                    if newest is not None:
                        self.skipped += 1
                    newest = enc
        except P.ProtocolError as e:
            raise LinkError(str(e)) from None
        if newest is None:
            raise LinkError(f"{t.name}: no complete sensor packet in {self.MAX_READS} reads")
        return newest  # the stream outpaced the reads: the newest so far

    def _packets(self) -> list[tuple[int, int]]:
        """The encoder counts of each complete sensor packet in the buffer, oldest first; the
        packets are consumed, a partial one is kept."""
        rx, out = self._rx, []
        while rx:
            size = P.wifi_payload_size(rx[0])
            if len(rx) < 1 + size:
                break
            if rx[0] == P.HEADER_SENSORS:
                out.append(P.encoders_from_sensors(bytes(rx[1 : 1 + size])))
            del rx[: 1 + size]
            self.packets += 1
        return out

    def stop_request(self) -> bytes:
        """A command packet with zero speeds and request byte 0 (neither image nor
        sensors); nothing waits for its answer."""
        return P.wifi_command(0, 0, request=0, limit=self.limit)


def make_transport(spec: LinkSpec, timeout: float = 0.25) -> tuple[Transport, Codec]:
    """Transport and codec of a ``serial`` or ``tcp`` link (``emulator`` and ``sim`` are the caller's)."""
    if spec.kind == "serial":
        return SerialTransport(spec.device, timeout=timeout), AsercomCodec(timeout)
    if spec.kind == "tcp":
        return TcpTransport(spec.host, spec.port, timeout=timeout), WifiCodec(timeout)
    raise ValueError(f"link {spec}: no transport for kind {spec.kind!r}")


# -------------------------------------------------------------------- port
@dataclass(frozen=True)
class Reading:
    """One encoder read: when [s, time.monotonic], and the int16 counts [steps]."""

    t: float
    left: int
    right: int
    fresh_link: bool
    """First read after the link was (re-)opened."""


class RobotPort:
    """Keeps one robot link up in a thread of its own.

    :meth:`command` hands it the latest wheel speeds [steps/s]; the thread sends
    them at once (or again every ``period`` [s] when nothing new came), reads the
    encoders and passes each :class:`Reading` to ``on_reading``.  A failure is
    logged through ``report`` once per outage; the link is then re-opened with
    backoff from ``backoff[0]`` doubling up to ``backoff[1]`` [s], and the
    re-opening is logged too; the first command after it is zero speed, whatever was asked
    meanwhile (the robot has no deadman: it drove on at its last speeds while the link was
    down).  :meth:`brake` has zero speed sent before any speeds asked after it.  With
    ``stale_after`` [s], speeds asked longer ago than that are stale: the thread sends zero
    instead of sending them again, until new ones are asked (:attr:`stale`).  :meth:`close`
    sends zero speed and closes."""

    def __init__(
        self,
        transport: Transport,
        codec: Codec,
        report: Callable[[str], None],
        on_reading: Callable[[Reading], None],
        period: float = 0.02,
        backoff: tuple[float, float] = (0.1, 2.0),
        on_lost: Callable[[tuple[tuple[int, int], ...]], None] | None = None,
        resume_by_hand: bool = False,
        stale_after: float | None = None,
        clock: Callable[[], float] = time.monotonic,
    ):
        self.transport = transport
        self.stale_after = stale_after
        """Speeds asked longer ago than this [s] are not sent again: zero is (None: never).  The
        robot keeps the last speeds it received; whoever asks for them (the link's inner loop)
        asks again every ``period`` while it runs on time, so speeds this old were left behind by
        a loop that stalled, and the robot must not drive on at them."""
        self.clock = clock
        """The time :meth:`command` calls are dated on [s]."""
        self.stale = 0
        """Episodes of stale speeds replaced by zero (each logged once)."""
        self.brakes = 0
        """Zero-speed exchanges sent for :meth:`brake`."""
        self.resume_by_hand = resume_by_hand
        """After a re-open, send zero speed until :meth:`resume` is called (else only once): the
        caller first learns the robot stopped, then lets commands through again."""
        self.on_lost = on_lost
        """Called on the port's thread when a link that was up is lost, with the wheel speeds
        [steps/s] the robot may be driving on at: those of the last exchange that went through,
        and those of the failed one (its command may have arrived; its reply did not).  That the
        link is back shows as the first :class:`Reading` with ``fresh_link`` after a loss: its
        command was zero speed."""
        self.sent = (0, 0)
        """The wheel speeds [steps/s] of the last exchange that went through."""
        self.codec = codec
        self.report = report
        self.on_reading = on_reading
        self.period = period
        self.backoff = backoff
        self.lost = 0
        """Outages so far."""
        self.reads = 0
        self._cond = threading.Condition()
        self._speeds = (0, 0)
        self._asked: float | None = None
        """When :meth:`command` or :meth:`brake` was last called [s, :attr:`clock`] (None: never)."""
        self._new = False
        self._brake = False
        """Zero speed is sent next, before any speeds asked since (:meth:`brake`)."""
        self._held = False
        """Zero speed is sent, whatever is asked, until :meth:`resume` (``resume_by_hand``)."""
        self._stop = False
        self._thread = threading.Thread(target=self._run, name="robot-port", daemon=True)

    def start(self) -> None:
        """Start the link thread (it opens the transport)."""
        self._thread.start()

    def command(self, left: int, right: int) -> None:
        """Send these wheel speeds [steps/s] next (the latest call wins)."""
        with self._cond:
            self._speeds = (left, right)
            self._asked = self.clock()
            self._new = True
            self._cond.notify_all()

    def brake(self) -> None:
        """Send zero speed next, before whatever :meth:`command` asks after this call: a later
        command does not replace the brake, it follows it.  Speeds asked before are dropped."""
        with self._cond:
            self._speeds = (0, 0)
            self._asked = self.clock()
            self._brake = True
            self._new = False
            self._cond.notify_all()

    def resume(self) -> None:
        """Let the asked speeds through again after a re-open (``resume_by_hand``)."""
        with self._cond:
            self._held = False
            self._cond.notify_all()

    def _sleep(self, seconds: float) -> bool:
        """Wait ``seconds`` unless closing; True if closing."""
        with self._cond:
            self._cond.wait_for(lambda: self._stop, seconds)
            return self._stop

    def _run(self) -> None:
        down_since: float | None = None
        attempts = 0
        fresh = True
        zero = False
        stale = False
        while True:
            with self._cond:
                if self._stop:
                    return
            if not self.transport.is_open:
                try:
                    self.transport.open()
                except LinkError as e:
                    attempts += 1
                    if down_since is None:
                        down_since = time.monotonic()
                        self.report(f"link unavailable: {e.reason}; retrying with backoff")
                    delay = min(self.backoff[1], self.backoff[0] * 2 ** min(attempts - 1, 16))
                    if self._sleep(delay):
                        return
                    continue
                if down_since is not None:
                    self.report(
                        f"link {self.transport.name} re-opened after {attempts} attempt(s), "
                        f"{time.monotonic() - down_since:.2f} s down; zero speed first"
                    )
                else:
                    self.report(f"link {self.transport.name} open")
                # The firmware has no deadman: the robot drove on at its last speeds while the
                # link was down.  The first command stops it, whatever was asked meanwhile.
                zero = down_since is not None
                with self._cond:
                    self._held = zero and self.resume_by_hand
                down_since, attempts, fresh = None, 0, True
                self.codec.reset()
            news = None
            with self._cond:
                self._cond.wait_for(lambda: self._new or self._brake or self._stop, self.period)
                if self._stop:
                    return
                if self._brake:  # zero first; what was asked since goes next
                    self._brake = False
                    left, right = 0, 0
                    self.brakes += 1
                else:
                    was_stale, stale = stale, self._stale()
                    if stale and not was_stale:
                        self.stale += 1
                        news = (
                            f"no wheel speeds asked for {self.clock() - (self._asked or 0.0):.3f} s (the "
                            f"caller stalled): zero speed, not the stale {self._speeds}, until it asks again"
                        )
                    left, right = (0, 0) if zero or self._held or stale else self._speeds
                    self._new = False
            if news is not None:
                self.report(news)
            zero = False
            try:
                raw = self.codec.exchange(self.transport, left, right)
            except LinkError as e:
                self.lost += 1
                down_since = time.monotonic()
                self.report(f"link lost: {e.reason}; re-opening with backoff")
                self._lost((self.sent, (left, right)))
                self.transport.close()
                attempts = 1
                if self._sleep(self.backoff[0]):
                    return
                continue
            self.reads += 1
            self.sent = (left, right)
            try:
                self.on_reading(Reading(time.monotonic(), raw[0], raw[1], fresh))
            except Exception as e:  # a publishing failure must not end the link thread
                self.report(f"encoder reading not handled: {type(e).__name__}: {_one_line(e)}")
            fresh = False

    def _stale(self) -> bool:
        """The speeds to send were asked longer than ``stale_after`` ago, and are not zero (lock held)."""
        asked = self._asked
        if self.stale_after is None or asked is None or self._speeds == (0, 0):
            return False
        return self.clock() - asked > self.stale_after

    def _lost(self, possible: tuple[tuple[int, int], ...]) -> None:
        if self.on_lost is None:
            return
        try:
            self.on_lost(possible)
        except Exception as e:  # a publishing failure must not end the link thread
            self.report(f"link state not handled: {type(e).__name__}: {_one_line(e)}")

    def close(self, timeout: float = 2.0) -> bool:
        """Stop the thread, send zero speed (best effort, bounded) and close.

        Returns True if the zero-speed request was written."""
        with self._cond:
            self._stop = True
            self._cond.notify_all()
        if self._thread.is_alive():
            self._thread.join(timeout)
        sent = False
        if not self._thread.is_alive():
            try:
                if not self.transport.is_open:
                    self.transport.open()
                self.transport.write(self.codec.stop_request())
                sent = True
            except LinkError as e:
                self.report(f"could not send zero speed on close: {e.reason}")
        self.transport.close()
        return sent
