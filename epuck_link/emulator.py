"""An e-puck firmware emulator speaking the real protocols byte for byte.

``python -m epuck_link.emulator [--pty] [--tcp PORT] [--start X Y THETA] [--encoders L R]
[--model e-puck1|e-puck2] [--speed-limit N] [--stream-period S]
[--robot ID [--fleet F] [--connect E] [--listen E] [--rate HZ]]``

* ``--pty``: advanced sercom on a pseudo-terminal pair (``os.openpty``, raw
  mode); the slave's path is announced, ``epuck_link --link serial:PATH`` opens
  it.  Binary chains (``0xBC`` set speed, ``0xAF`` get encoders, ``0x00``) and
  the ASCII lines ``D,l,r`` and ``Q`` are answered as the firmware does.
  Inside a chain, the other requests the firmware knows are skipped with their
  arguments (:data:`epuck_link.protocol.CHAIN_ARGS_V2`).
* ``--tcp PORT``: the e-puck2 Wi-Fi protocol on ``127.0.0.1:PORT`` (0: a free
  port), one client at a time, as the ESP32 firmware runs it (:class:`WifiSide`):
  21-byte blocks, and once a valid command has come a packet every
  ``--stream-period`` seconds (default 0.02), new command or not.  The image
  stream is answered with a black image.

The robot is a differential drive with the E-puck geometry
(:class:`ground.params.WheelGeometry`: wheel radius 20.5 mm, axle 53 mm, 1000
steps per revolution).  Speeds are clamped to ±``--speed-limit`` steps/s, and
the motors step at whole timer periods (:func:`epuck_link.protocol.step_rate`:
700 steps/s runs at 714 on an e-puck1); between two requests the wheels turn
at constant speed and the pose is
integrated exactly (:func:`epuck_link.unicycle.integrate_unicycle`) in wall time, or
on an injected clock in tests.  The encoder counts are kept exactly and
reported as int16s that wrap, as the firmware does.

With ``--robot`` the ground-truth pose of the axle centre (world frame, m and
rad) is published as :class:`ground.wire.Truth` on ``fleet/F/emu/R`` at
``--rate`` Hz (default 100).  Its ``t`` is seconds since the emulator started,
on ``time.monotonic``; the readiness line gives that origin as
``clock_origin`` [s, time.monotonic].  Without ``--robot`` no Zenoh session is
opened.

Readiness line: ``{"event": "ready", "role": "emulator", "pid", "robot",
"pty", "tcp", "clock_origin", "truth_key", "speed_limit"}``.
"""

from __future__ import annotations

import argparse
import os
import select
import signal
import socket
import sys
import threading
import time
import tty
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from epuck_link import protocol as P
from epuck_link.unicycle import integrate_unicycle, unicycle_from_wheels, wrap_angle
from ground.params import WheelGeometry
from ground.wire import Truth

LOOPBACK = "127.0.0.1"


@dataclass(frozen=True)
class Snapshot:
    """The emulated robot at time ``t`` [s, on the emulator's clock]."""

    t: float
    x: float
    y: float
    theta: float
    """Pose of the axle centre: position [m], heading [rad] in [−π, π), world frame."""
    left: int
    right: int
    """Wheel speeds [steps/s] (after the firmware clamp)."""
    left_count: int
    right_count: int
    """Encoder counts [steps], not wrapped."""


class EpuckEmulator:
    """The robot: wheel speeds, pose and encoders, advanced on ``clock`` [s].

    Thread-safe: the serial and TCP servers and the truth publisher share it."""

    def __init__(
        self,
        pose: tuple[float, float, float] = (0.0, 0.0, 0.0),
        encoders: tuple[int, int] = (0, 0),
        geom: WheelGeometry | None = None,
        speed_limit: int | None = None,
        clock: Callable[[], float] = time.monotonic,
        model: str = "e-puck1",
    ):
        if model not in P.MODELS:
            raise ValueError(f"model {model!r}: expected one of {', '.join(P.MODELS)}")
        self.model = model
        """``e-puck1`` or ``e-puck2``: the firmware's speed limit, chained requests and step timing."""
        self.geom = geom or WheelGeometry()
        self.speed_limit = speed_limit or (P.MAX_STEPS_V1 if model == "e-puck1" else P.MAX_STEPS_V2)
        self.clock = clock
        self._lock = threading.Lock()
        self._pose = np.array(pose, dtype=float)
        self._counts = [float(encoders[0]), float(encoders[1])]
        self._speeds = (0, 0)
        self.origin = clock()
        """Clock reading at creation: ``t = 0`` of the published truth [s]."""
        self._t = self.origin
        self.chains = 0
        """Binary request chains answered."""
        self.wifi_packets = 0
        self.ignored = 0
        """Bytes ignored: unknown binary requests, Wi-Fi bytes before a 0x80."""

    def _advance(self) -> float:
        now = self.clock()
        dt = now - self._t
        if dt > 0:
            # The motors step at whole timer periods, a little faster than commanded.
            left, right = (P.step_rate(s, self.model) for s in self._speeds)
            if left or right:
                v, omega = unicycle_from_wheels(left, right, self.geom)
                self._pose = integrate_unicycle(self._pose, v, omega, dt)
                self._counts[0] += left * dt
                self._counts[1] += right * dt
            self._t = now
        return self._t

    def set_speeds(self, left: int, right: int) -> None:
        """Command the wheels [steps/s]; the firmware clamps them to ±speed_limit."""
        lim = self.speed_limit
        with self._lock:
            self._advance()
            self._speeds = (max(-lim, min(lim, left)), max(-lim, min(lim, right)))

    def set_counts(self, left: int, right: int) -> None:
        """Overwrite the encoder counts [steps] (the Wi-Fi "motor steps" setting)."""
        with self._lock:
            self._advance()
            self._counts = [float(left), float(right)]

    def encoders(self) -> tuple[int, int]:
        """The counts [steps] as the firmware reports them: int16, wrapping."""
        with self._lock:
            self._advance()
            return P.wrap_int16(round(self._counts[0])), P.wrap_int16(round(self._counts[1]))

    def snapshot(self) -> Snapshot:
        """The robot now (pose, wheel speeds, unwrapped counts)."""
        with self._lock:
            t = self._advance()
            x, y, th = (float(v) for v in self._pose)
            return Snapshot(
                t, x, y, wrap_angle(th), self._speeds[0], self._speeds[1],
                round(self._counts[0]), round(self._counts[1]),
            )  # fmt: skip

    # ---------------------------------------------------------- protocols
    def serial_handler(self) -> Callable[[bytes], bytes]:
        """A handler for one serial connection: bytes received → bytes to send back."""
        parser = P.AsercomParser(args=P.CHAIN_ARGS_V1 if self.model == "e-puck1" else P.CHAIN_ARGS_V2)
        pending = bytearray()

        def handle(data: bytes) -> bytes:
            out = bytearray()
            for req in parser.feed(data):
                if isinstance(req, P.SetSpeed):
                    self.set_speeds(req.left, req.right)
                elif isinstance(req, P.GetEncoders):
                    pending.extend(P.encoders_reply(*self.encoders()))
                elif isinstance(req, P.EndOfChain):
                    out += pending
                    pending.clear()
                    self.chains += 1
                elif isinstance(req, P.AsciiLine):
                    reply, speeds = P.ascii_reply(req.text, self.encoders())
                    if speeds is not None:
                        self.set_speeds(*speeds)
                    out += reply
                else:
                    self.ignored += 1 + len(req.args)
            return bytes(out)

        return handle

    def wifi(self) -> WifiSide:
        """The Wi-Fi processor's side of one TCP connection (:class:`WifiSide`)."""
        return WifiSide(self)


class WifiSide:
    """The e-puck2's ESP32 Wi-Fi firmware for one connection, pass by pass, as GCtronic's
    ``e-puck2/esp-idf`` (branch ``wifi``, e2f4883) ``Projects/ESP32_E-Puck_2/main/
    socket_e-puck2.c`` does it:

    * Commands are read in whole 21-byte blocks, one a reading pass, never resynchronised
      byte by byte (L164–177).  Only a block starting with ``0x80`` makes the connection valid
      (L171–172); after that every block is taken as a command whatever its first byte
      (L174–177): a stream that lost its alignment stays misaligned.
    * With five blocks or more waiting, all but the last are dropped (L146–161).
    * Once a valid command has come, every reading pass re-applies the last command and
      answers it by its request byte, new command or not (L182–195): ``0x00`` the empty
      packet, bit 0 the image (then the sensors if bit 1), bit 1 the sensors; a request byte
      with neither bit answers nothing.  So the robot *streams*.
    * The loop is a state machine, one state a pass, each pass ended by ``vTaskDelay(10)``
      (L279): state 3 reads at most one block and applies it (L145–197), the next pass sends
      the answer (states 5 and 6, L240–277; the image, state 4 at L199, takes one more) and
      goes back to state 3.  So one block is read per packet sent, two passes apart; a
      :meth:`cycle` is those two passes.

    :meth:`take` queues received bytes; :meth:`cycle` is one packet's worth of passes and
    returns the bytes to send (the server paces it, :class:`TcpServer`)."""

    BACKLOG_BLOCKS = 5

    def __init__(self, emulator: EpuckEmulator):
        self.emu = emulator
        self.rx = bytearray()
        self.valid = False
        self.last: bytes | None = None
        self.dropped = 0
        """Blocks dropped from a backlog."""

    def take(self, data: bytes) -> None:
        """Queue ``data`` received from the client; :meth:`cycle` reads it a block at a time."""
        self.rx += data

    @property
    def waiting(self) -> bool:
        """A partial block is in: the firmware blocks on the rest of it (MSG_WAITALL, L174)."""
        return 0 < len(self.rx) < P.WIFI_COMMAND_SIZE

    def cycle(self) -> bytes:
        """Read at most one block, then answer the last valid command (empty until there is one)."""
        size = P.WIFI_COMMAND_SIZE
        if len(self.rx) >= self.BACKLOG_BLOCKS * size:
            keep = size + len(self.rx) % size  # the last whole block, and a partial one after it
            self.dropped += (len(self.rx) - keep) // size
            del self.rx[: len(self.rx) - keep]
        if len(self.rx) >= size:
            block = bytes(self.rx[:size])
            del self.rx[:size]
            if block[0] == P.WIFI_COMMAND or self.valid:
                self.valid, self.last = True, block
                self.emu.wifi_packets += 1
            else:
                self.emu.ignored += size
        if self.last is None:
            return b""
        # The header of a later block is not checked: read its fields as they stand.
        cmd = P.parse_wifi_command(bytes([P.WIFI_COMMAND]) + self.last[1:])
        if cmd.settings & P.SETTING_MOTOR_STEPS:
            self.emu.set_counts(cmd.left, cmd.right)
        else:
            self.emu.set_speeds(cmd.left, cmd.right)
        if cmd.request == 0 or cmd.request & (P.REQUEST_IMAGE | P.REQUEST_SENSORS):
            return P.wifi_reply(cmd.request, *self.emu.encoders())
        return b""


# ------------------------------------------------------------------ servers
class PtyServer:
    """Serves the serial protocol on a pseudo-terminal; clients open :attr:`path`.

    The emulator keeps the slave side open too, so a client may close and
    re-open the device."""

    def __init__(self, emulator: EpuckEmulator, report: Callable[[str], None] = lambda m: None):
        self.emulator = emulator
        self.report = report
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)  # no echo, no CR/LF translation: bytes pass unchanged
        self.path = os.ttyname(self._slave)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="pty-server", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        handle = self.emulator.serial_handler()
        while not self._stop.is_set():
            ready, _, _ = select.select([self._master], [], [], 0.1)
            if not ready:
                continue
            try:
                data = os.read(self._master, 4096)
            except OSError as e:
                self.report(f"pty read failed: {e}")
                return
            reply = handle(data)
            if reply:
                os.write(self._master, reply)

    def close(self) -> None:
        """Stop serving and close both ends of the pty."""
        self._stop.set()
        self._thread.join(1.0)
        for fd in (self._master, self._slave):
            try:
                os.close(fd)
            except OSError:
                pass


STREAM_PERIOD = 0.02
"""Seconds between two packets of the e-puck2's sensor stream: two passes of the ESP32 loop,
each ended by ``vTaskDelay(10)`` at a 1 kHz tick (``socket_e-puck2.c`` L279, ``sdkconfig``
L593); the UART exchange with the main processor runs alongside and may stretch it to 30 ms."""


class TcpServer:
    """Serves the Wi-Fi protocol on ``host:port`` (0: a free port), one client at a time, and
    streams as the robot does: one packet every ``stream_period`` [s] once a valid command
    has come (:class:`WifiSide`)."""

    def __init__(
        self,
        emulator: EpuckEmulator,
        port: int = 0,
        host: str = LOOPBACK,
        report: Callable[[str], None] = lambda m: None,
        stream_period: float = STREAM_PERIOD,
    ):
        self.emulator = emulator
        self.report = report
        self.stream_period = stream_period
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # restart on the same port
        self._sock.bind((host, port))
        self._sock.listen(1)
        self._sock.settimeout(0.1)
        self.host = host
        self.port = int(self._sock.getsockname()[1])
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="tcp-server", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                conn, addr = self._sock.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            self.report(f"wifi client {addr[0]}:{addr[1]} connected")
            with conn:
                self._serve(conn)
            self.report(f"wifi client {addr[0]}:{addr[1]} left")

    def _serve(self, conn: socket.socket) -> None:
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        side = self.emulator.wifi()
        due = time.monotonic()
        while not self._stop.is_set():
            # Until the next packet is due, take what arrives (bounded, so a close is seen).
            wait = min(0.1, max(0.0, due - time.monotonic())) if side.valid else 0.1
            ready, _, _ = select.select([conn], [], [], wait)
            if ready:
                try:
                    data = conn.recv(65536)
                except OSError:
                    return
                if not data:
                    return
                side.take(data)
            now = time.monotonic()
            if (
                side.waiting
                or (side.valid and now < due)
                or (not side.valid and len(side.rx) < P.WIFI_COMMAND_SIZE)
            ):
                continue
            was_valid = side.valid
            reply = side.cycle()
            # The next packet a stream period on (from this one, for the first of the stream),
            # or now if the server fell behind: never a burst to catch up.
            due = max(due + self.stream_period, now) if was_valid else now + self.stream_period
            try:
                if reply:
                    conn.sendall(reply)
            except OSError:
                return

    def close(self) -> None:
        """Stop serving and close the listening socket."""
        self._stop.set()
        self._thread.join(1.0)
        self._sock.close()


class TruthPublisher:
    """Publishes the emulator's pose as :class:`ground.wire.Truth` at ``rate`` [Hz].

    ``put`` sends one encoded message (a Zenoh publisher's ``put``).  ``t`` is
    seconds since the emulator's origin; ``seq`` counts from 0."""

    def __init__(self, emulator: EpuckEmulator, robot: str, put: Callable[[bytes], Any], rate: float = 100.0):
        if not 0 < rate <= 1000:
            raise ValueError(f"truth rate {rate} Hz outside (0, 1000]")
        self.emulator = emulator
        self.robot = robot
        self.put = put
        self.period = 1.0 / rate
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="truth", daemon=True)

    def start(self) -> None:
        """Start publishing (a thread of its own)."""
        self._thread.start()

    def _run(self) -> None:
        seq = 0
        due = time.monotonic()
        while not self._stop.wait(max(0.0, due - time.monotonic())):
            s = self.emulator.snapshot()
            t = s.t - self.emulator.origin
            self.put(Truth(robot=self.robot, seq=seq, t=t, x=s.x, y=s.y, theta=s.theta).encode())
            seq += 1
            due += self.period
            now = time.monotonic()
            if due < now:  # late (a loaded machine): skip the missed samples rather than burst
                due = now

    def close(self) -> None:
        """Stop publishing."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(1.0)


# --------------------------------------------------------------------- CLI
def main(argv: list[str] | None = None) -> int:
    """``python -m epuck_link.emulator``: serve the emulated robot on a pseudo-terminal and/or a TCP
    port, with ``--robot`` publishing its true pose, until SIGTERM or SIGINT (see the module
    docstring); returns the exit code (0 once stopped, 2 bad input or a server that cannot start)."""
    from ground.scenario import ConfigError
    from ground.wire import Keys
    from transport.bus import open_session, publisher
    from transport.process import add_common_args, announce, log

    ap = argparse.ArgumentParser(prog="python -m epuck_link.emulator", description=__doc__.splitlines()[0])
    add_common_args(ap)
    for action in ap._actions:  # the emulator needs no scenario; with one, --robot's start is the default
        if action.dest == "scenario":
            action.required = False
            action.help = "scenario TOML file (optional: the start pose of --robot)"
    ap.add_argument("--pty", action="store_true", help="serve advanced sercom on a pseudo-terminal")
    ap.add_argument(
        "--tcp", type=int, default=None, metavar="PORT", help="serve Wi-Fi on 127.0.0.1:PORT (0: free)"
    )
    ap.add_argument("--start", type=float, nargs=3, default=None, metavar=("X", "Y", "THETA"),
                    help="start pose [m, m, rad] (default: the scenario's, else 0 0 0)")  # fmt: skip
    ap.add_argument("--encoders", type=int, nargs=2, default=(0, 0), metavar=("L", "R"),
                    help="initial encoder counts [steps]")  # fmt: skip
    ap.add_argument("--model", choices=P.MODELS, default="e-puck1",
                    help="the robot: speed limit, chained requests, step timing")  # fmt: skip
    limits = f"e-puck1 {P.MAX_STEPS_V1}, e-puck2 {P.MAX_STEPS_V2}"
    ap.add_argument(
        "--speed-limit",
        type=int,
        default=None,
        help=f"firmware clamp [steps/s] (default the model's: {limits})",
    )
    ap.add_argument("--stream-period", type=float, default=STREAM_PERIOD, metavar="S",
                    help=f"seconds between Wi-Fi packets (default {STREAM_PERIOD})")  # fmt: skip
    ap.add_argument("--robot", default=None, help="publish the true pose on fleet/F/emu/ROBOT")
    ap.add_argument("--rate", type=float, default=100.0, help="truth publishing rate [Hz] (default 100)")
    args = ap.parse_args(argv)
    role = "emulator"
    try:
        start = _start_pose(args)
    except ConfigError as e:
        print(f"emulator: error: {e}", file=sys.stderr)
        return 2

    emu = EpuckEmulator(
        (start[0], start[1], start[2]), tuple(args.encoders), speed_limit=args.speed_limit, model=args.model
    )

    def report(msg: str) -> None:
        log(role, msg)

    stopping = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stopping.set())
    signal.signal(signal.SIGINT, lambda *_: stopping.set())
    servers: list[PtyServer | TcpServer] = []
    session: Any = None
    truth: TruthPublisher | None = None
    try:
        try:
            pty_srv = PtyServer(emu, report) if args.pty else None
            tcp_srv = (
                TcpServer(emu, args.tcp, report=report, stream_period=args.stream_period)
                if args.tcp is not None else None
            )  # fmt: skip
        except OSError as e:
            print(f"emulator: error: {'--tcp' if args.tcp is not None else '--pty'}: {e}", file=sys.stderr)
            return 2
        servers = [s for s in (pty_srv, tcp_srv) if s is not None]
        truth_key = None
        if args.robot is not None:
            keys = Keys(args.fleet)
            truth_key = keys.emu(args.robot)
            session = open_session(args)
            pub = publisher(session, truth_key)
            truth = TruthPublisher(emu, args.robot, pub.put, args.rate)
            truth.start()
        announce(
            role, robot=args.robot, pty=pty_srv.path if pty_srv else None,
            tcp=f"{LOOPBACK}:{tcp_srv.port}" if tcp_srv else None, clock_origin=emu.origin,
            truth_key=truth_key, speed_limit=emu.speed_limit, model=emu.model,
        )  # fmt: skip
        while not stopping.wait(0.5):
            pass
        s = emu.snapshot()
        report(
            f"stopped: {emu.chains} sercom chains, {emu.wifi_packets} wifi packets, "
            f"{emu.ignored} ignored bytes; "
            f"pose ({s.x:.4f}, {s.y:.4f}, {s.theta:.4f}), counts ({s.left_count}, {s.right_count})"
        )
    finally:
        if truth is not None:
            truth.close()
        for srv in servers:
            srv.close()
        if session is not None:
            session.close()
    return 0


def _start_pose(args: argparse.Namespace) -> tuple[float, float, float]:
    """The emulated robot's start pose [m, m, rad], after checking the options; ConfigError
    names the bad one."""
    from ground.scenario import ConfigError, load_scenario
    from ground.wire import ROBOT_ID

    if not args.pty and args.tcp is None:
        args.pty = True
    if args.tcp is not None and not 0 <= args.tcp <= 65535:
        raise ConfigError("--tcp", f"port {args.tcp} outside 0..65535")
    if args.speed_limit is not None and not 0 < args.speed_limit <= 32767:
        raise ConfigError("--speed-limit", f"{args.speed_limit} outside 1..32767")
    if not 0.001 <= args.stream_period <= 1.0:  # NaN fails too
        raise ConfigError("--stream-period", f"{args.stream_period} s outside [0.001, 1]")
    if not 0 < args.rate <= 1000:
        raise ConfigError("--rate", f"{args.rate} Hz outside (0, 1000]")
    if args.robot is not None and not ROBOT_ID.fullmatch(args.robot):
        raise ConfigError("--robot", f"{args.robot!r} must match {ROBOT_ID.pattern}")
    start = tuple(args.start) if args.start is not None else (0.0, 0.0, 0.0)
    if args.start is None and args.scenario is not None and args.robot is not None:
        scn = load_scenario(args.scenario)
        spec = next((r for r in scn.robots if r.id == args.robot), None)
        if spec is None:
            raise ConfigError("--robot", f"{args.robot!r} is not in the scenario")
        start = spec.start
    if not all(np.isfinite(start)):
        raise ConfigError("--start", "expected finite numbers")
    return (float(start[0]), float(start[1]), float(start[2]))


if __name__ == "__main__":
    from transport.process import exit_process

    exit_process(main())
