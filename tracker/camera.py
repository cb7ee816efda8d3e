"""The ArUco camera tracker process: an overhead camera's frames in, robot poses and the clock out.

``python -m tracker --scenario S --source camera [--device N | --video FILE [--rate R]]
[--steps N] [--wait-agents] [--fleet F] [--listen E] [--connect E]``

Each frame is turned into poses by :class:`tracker.vision.Tracker` (detection, floor homography,
marker offset).  Every Ts = ``controller.Ts`` (step k, time k·Ts) the process publishes one
:class:`ground.wire.Pose` per robot whose marker was found, ``seq = k`` and ``t`` = the capture
time [s] of the frame used, then ``Tick(robot="tracker", step=k, t=k·Ts, stop=False)``: the
simulated tracker's messages and keys, without Odom (on hardware ``epuck_link`` publishes the
odometry).  The tick's ``fallback`` and ``braked`` come from the links'
:class:`ground.wire.Applied` reports of step k − 1 (:mod:`tracker.reports`; ``misses`` counts
them); the same pose goes on the truth key too, as the supervisor's best ground truth on real
robots.  With ``--delay-compensation`` the :class:`ground.wire.Outcome` of step k follows tick k
as soon as every link that reported a recent step has reported step k (a link decides at once
when its command came in time), or :data:`tracker.reports.OUTCOME_WAIT`·Ts after the links'
``--deadline``; tick k + 1 says the same again (docs/design.md, "Delay compensation").  Clocks:

* ``--video FILE``: frame i was captured at t = i / fps [s]; step k uses the last frame with
  t ≤ k·Ts and is published at wall time k·Ts / ``--rate`` after the start.  The end of the file
  ends the run with ``Tick(stop=True)``.
* ``--device N``: t = ``time.monotonic()`` when ``read()`` returned the frame, minus that of the
  first frame [s] (so it includes the driver's latency); step k uses the newest frame at wall
  time k·Ts, unless it is older than ``STALE_STEPS``·Ts.  The run ends after ``--steps``
  (default: the scenario's duration) with ``Tick(stop=True)``, or with exit code 1 when the
  device stops delivering frames.

SIGINT/SIGTERM end either run at the next step with ``Tick(stop=True)`` and exit code 0.
``--serve`` keeps the fleet up past the scenario's duration (``--steps`` still caps it), for goal
after goal, until a signal or a stop request (a :class:`ground.wire.Script` with ``stop``:
``fleet stop``).
``--wait-agents`` holds step 0 until every robot's agent and the supervisor are alive (as the
simulated tracker does).  Exit codes: 0 done, 1 failed (calibration, agents not up, device
lost), 2 bad input (one line ``tracker: error: <field>: <reason>``).  ``--clock`` and
``--timeout``, common to the fleet's processes, are accepted and ignored: a camera cannot wait,
so this source always runs on the wall clock.  Without ``camera.homography`` the tracker
calibrates from the fiducials of the first frames (at most ``CALIBRATION_TRIES`` frames) or
exits 1.  A summary of the tracker's counts is logged at exit.
"""

from __future__ import annotations

import argparse
import math
import signal
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ground.geometry import wrap_angle
from ground.scenario import CameraSpec, ConfigError, Scenario, load_scenario
from ground.wire import Applied, Keys, Outcome, Pose, Script, Tick, Truth
from tracker.intrinsics import Intrinsics
from tracker.reports import OUTCOME_WAIT, REPORT_WAIT, Reports
from tracker.vision import (
    CALIBRATION_FRAMES,
    CALIBRATION_TRIES,
    OPENCV_MISSING,
    Calibration,
    Tracker,
    calibrate_from,
    camera_setup,
    cv2_module,
    quiet_opencv,
)
from transport.bus import Inbox, open_session, publisher
from transport.process import DEADLINE, add_common_args, announce, log

ROLE = "tracker"
MAX_BAD_IN_A_ROW = 50
"""Failed reads in a row taken as the end of a video, or as a lost device."""
FIRST_FRAME_TIMEOUT = 10.0
"""Wait for a device's first frame [s]."""
STALE_STEPS = 2.0
"""A device frame older than this many Ts is not used (the step gets no poses)."""
PROGRESS_EVERY = 100
"""Steps between progress lines on stderr."""


def main(argv: list[str] | None = None) -> int:
    """``python -m tracker --source camera``; returns the exit code (0 done, 1 failed, 2 bad input)."""
    ap = argparse.ArgumentParser(
        prog="python -m tracker --source camera", description="ArUco camera tracker (see tracker/camera.py)"
    )
    add_common_args(ap)
    ap.add_argument("--source", choices=["camera"], default="camera", help="pose source")
    src = ap.add_mutually_exclusive_group()
    src.add_argument("--device", type=int, default=None, help="video device N (default: camera.device or 0)")
    src.add_argument("--video", default=None, help="play a video file instead of a camera")
    ap.add_argument(
        "--rate", type=float, default=1.0, help="--video: play R× faster than real time (default 1)"
    )
    ap.add_argument(
        "--steps", type=int, default=None, help="stop after N steps (default: end of video / duration)"
    )
    ap.add_argument(
        "--serve", action="store_true",
        help="a device: keep the fleet up past the scenario's duration, until SIGINT, SIGTERM or a stop "
        "request (fleet stop)",
    )  # fmt: skip
    ap.add_argument(
        "--wait-agents", action="store_true", help="wait for every agent and the supervisor first"
    )
    ap.add_argument("--start-timeout", type=float, default=60.0, help="--wait-agents: wait limit [s]")
    ap.add_argument(
        "--deadline", type=float, default=DEADLINE,
        help="--delay-compensation: the links' command deadline after the tick, as a fraction of Ts "
        "(their --deadline): a step's outcome waits for their reports of a miss until then",
    )  # fmt: skip
    ap.add_argument("--calibration-frames", type=int, default=CALIBRATION_FRAMES,
                    help="without camera.homography: frames averaged for the calibration")  # fmt: skip
    args = ap.parse_args(argv)
    try:
        import cv2
    except ImportError:
        print(f"tracker: error: {OPENCV_MISSING}", file=sys.stderr)
        return 2
    quiet_opencv(cv2)
    try:
        scn, camera, markers, calibration, intrinsics, source = _checked(args)
    except ConfigError as e:
        print(f"tracker: error: {e}", file=sys.stderr)
        return 2
    try:
        if calibration is None:
            try:
                calibration = _calibrate_source(source, camera, args.calibration_frames, intrinsics)
            except ConfigError as e:
                print(f"tracker: error: {e}", file=sys.stderr)
                return 1
            log(
                ROLE,
                f"calibrated from {len(calibration.image_points)} fiducials over {calibration.frames} "
                f"frames: RMS {calibration.rms_error * 1000:.2f} mm, "
                f"max {calibration.max_error * 1000:.2f} mm",
            )
        _check_noise(scn, camera, calibration)
        try:
            tracker = Tracker(camera, markers, calibration, report=_log, intrinsics=intrinsics)
        except ConfigError as e:
            print(f"tracker: error: {e}", file=sys.stderr)
            return 2
        session = open_session(args)
        run = CameraRun(args, scn, source, tracker, session)
        try:
            return run.run()
        finally:
            run.close()
            session.close()
    finally:
        source.close()


def _checked(
    args: argparse.Namespace,
) -> tuple[Scenario, CameraSpec, dict[int, str], Calibration | None, Intrinsics | None, Any]:
    """The scenario, its camera, the robots' markers, the calibration file's homography if any,
    the lens intrinsics if any, and the opened frame source; ConfigError names the bad option
    (nothing is left open)."""
    if not 0 < args.deadline < 1:
        raise ConfigError("--deadline", f"must be in (0, 1), got {args.deadline}")
    if args.exchange == "relay":
        raise ConfigError(
            "--exchange", "relay needs the simulated tracker; the camera tracker relays no plans"
        )
    if not (math.isfinite(args.rate) and args.rate > 0):
        raise ConfigError("--rate", f"must be > 0, got {args.rate}")
    if args.steps is not None and args.steps < 1:
        raise ConfigError("--steps", f"must be >= 1, got {args.steps}")
    if args.calibration_frames < 1:
        raise ConfigError("--calibration-frames", f"must be >= 1, got {args.calibration_frames}")
    scn = load_scenario(args.scenario)
    camera, markers = camera_setup(scn)
    calibration = Calibration.load(camera.homography) if camera.homography is not None else None
    intrinsics = Intrinsics.load(camera.intrinsics) if camera.intrinsics is not None else None
    source: VideoSource | DeviceSource
    if args.video is not None:
        source = VideoSource(args.video)
    else:
        source = DeviceSource.open(args.device if args.device is not None else (camera.device or 0))
    size = frame_size(source.cap)
    if calibration is not None and size is not None and size != calibration.image_size:
        source.close()
        w, h = calibration.image_size
        raise ConfigError(
            "camera.homography",
            f"{camera.homography} is for {w}×{h} px images, the source gives {size[0]}×{size[1]} px "
            "(calibrate again with fleet calibrate)",
        )
    if intrinsics is not None and size is not None and size != intrinsics.image_size:
        source.close()
        w, h = intrinsics.image_size
        raise ConfigError(
            "camera.intrinsics",
            f"{camera.intrinsics} is for {w}×{h} px images, the source gives {size[0]}×{size[1]} px",
        )
    return scn, camera, markers, calibration, intrinsics, source


def _calibrate_source(
    source: VideoSource | DeviceSource, camera: CameraSpec, want: int, intrinsics: Intrinsics | None
) -> Calibration:
    if isinstance(source, VideoSource):
        # The frames stay in the file: the run starts again from frame 0.
        cal = calibrate_from((f.image for f in source.frames()), camera, want=want, tries=CALIBRATION_TRIES,
                             intrinsics=intrinsics)  # fmt: skip
        source.rewind()
        return cal

    def reads() -> Iterator[np.ndarray | None]:
        for _ in range(CALIBRATION_TRIES):
            yield source.read_now()

    return calibrate_from(reads(), camera, want=want, tries=CALIBRATION_TRIES, intrinsics=intrinsics)


def _check_noise(scn: Scenario, camera: CameraSpec, cal: Calibration) -> None:
    """Compare the calibration and the camera's claimed noise bounds with the design."""
    bound_p, bound_th = scn.controller.pose_noise
    if camera.position_noise is not None:
        if cal.rms_error > camera.position_noise:
            log(
                ROLE,
                f"calibration RMS {cal.rms_error * 1000:.2f} mm exceeds camera.position_noise "
                f"{camera.position_noise * 1000:.2f} mm",
            )
        if camera.position_noise > bound_p:
            log(
                ROLE,
                f"camera.position_noise {camera.position_noise * 1000:.2f} mm exceeds "
                f"controller.pose_noise[0] {bound_p * 1000:.2f} mm the tube is designed for",
            )
    if camera.heading_noise is not None and camera.heading_noise > bound_th:
        log(
            ROLE,
            f"camera.heading_noise {camera.heading_noise:.4f} rad exceeds controller.pose_noise[1] "
            f"{bound_th:.4f} rad the tube is designed for",
        )


class CameraRun:
    """The camera tracker on the bus: one step every Ts until the end of the video, ``--steps``
    or a signal (see the module docstring)."""

    def __init__(
        self, args: argparse.Namespace, scn: Scenario, source: VideoSource | DeviceSource, tracker: Tracker,
        session: Any,
    ):  # fmt: skip
        self.args, self.scn, self.source, self.tracker = args, scn, source, tracker
        self.Ts = scn.controller.Ts
        self.ids = ids = [r.id for r in scn.robots]
        keys = Keys(args.fleet)
        self.stopping = threading.Event()
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, lambda *_: self.stopping.set())
        self.inbox = inbox = Inbox(keys, ROLE)
        # What each robot's epuck_link applied over a step (its command, its candidate, or the
        # brake), for the next tick: the agents and their neighbours then agree on which plans
        # were executed (docs/design.md, "Missed deadlines").
        self.subs = [
            inbox.watch_liveliness(session),
            inbox.subscribe(session, keys.applied(), Applied, keep=True),
        ]
        self.pubs = {rid: publisher(session, keys.pose(rid)) for rid in ids}
        # On hardware the camera is the best ground truth there is: the supervisor's safety
        # monitor reads it on the truth key (not express: nobody waits on it).
        self.truths = {rid: publisher(session, keys.truth(rid), express=False) for rid in ids}
        self.clock = publisher(session, keys.clock)
        self.outcome = publisher(session, keys.outcome) if args.delay_compensation else None
        """Delay compensation: each step's outcome, from the links' reports, as soon as they are in."""
        self.video = isinstance(source, VideoSource)
        self.limit = args.steps
        if self.limit is None and not self.video and not args.serve:
            self.limit = round(scn.duration / self.Ts)
        self.stop_asked = False
        """A stop request came (served: ``fleet stop``)."""
        if args.serve:
            self.subs.append(inbox.subscribe(session, keys.script, Script, then=self._on_script))
        self.reports = Reports(ids)
        self.late = self.misses = 0
        self.last: Frame | None = None

    def _on_script(self, msg: Script) -> None:
        """A stop request came (served; inbox.cond held): end the run at the next step."""
        if msg.stop:
            self.stop_asked = True
            self.stopping.set()

    def run(self) -> int:
        """Announce, wait for the fleet and the first frame, then step; the exit code."""
        args, inbox, source, Ts = self.args, self.inbox, self.source, self.Ts
        announce(ROLE, robots=self.ids, source="camera", steps=self.limit)
        if args.wait_agents:
            expected = {*self.ids, "supervisor"}
            if not inbox.wait(lambda: expected <= inbox.live, args.start_timeout):
                log(ROLE, f"not up within {args.start_timeout} s: {', '.join(sorted(expected - inbox.live))}")
                return 1
        if isinstance(source, DeviceSource):
            source.start()
            if not source.wait_first(FIRST_FRAME_TIMEOUT):
                log(ROLE, f"{source.name}: no frame within {FIRST_FRAME_TIMEOUT:g} s")
                return 1
        pace = Ts / args.rate if self.video else Ts
        t_start = time.monotonic()
        k, code = 0, 0
        fallback: dict[str, int] = {}
        braked: dict[str, int] = {}
        while not self.stopping.is_set() and (self.limit is None or k < self.limit):
            wait = t_start + k * pace - time.monotonic()
            if wait > 0:
                if self.stopping.wait(wait):
                    break
            elif -wait > pace:
                self.late += 1
            frame, state = self._frame(k)
            if state == "lost":
                code = 1
                break
            if state == "end":
                break  # end of the file
            self._publish(k, frame)
            if k > 0:
                fallback, braked, missed = self.reports.for_tick(inbox, k, REPORT_WAIT * Ts, _log)
                self.misses += len(missed)
            inbox.prune(k - Reports.LOOKBACK)
            self.clock.put(
                Tick(
                    robot=ROLE,
                    step=k,
                    t=k * Ts,
                    stop=False,
                    misses=self.misses,
                    fallback=fallback,
                    braked=braked,
                ).encode()
            )
            if self.outcome is not None:
                self._outcome(k, t_start + (k + 1) * pace)
            if k % PROGRESS_EVERY == 0 and k:
                log(ROLE, f"step {k}")
            k += 1
        self.clock.put(Tick(robot=ROLE, step=k, t=k * Ts, stop=True, misses=self.misses).encode())
        why = "step limit" if self.limit is not None and k >= self.limit else "end of video"
        if self.stopping.is_set():
            why = "a stop was asked (fleet stop)" if self.stop_asked else "signal"
        log(ROLE, f"run ended at step {k} ({why}); {self.late} late steps; {self.tracker.counts.summary()}")
        return code

    def _outcome(self, k: int, next_tick: float) -> None:
        """Delay compensation: the outcome of step k (its tick just went out), once the links'
        reports of it are in, or :data:`~tracker.reports.OUTCOME_WAIT`·Ts after their deadline,
        and not after the next tick is due (``next_tick`` [s, time.monotonic]) unless that
        leaves less than the :data:`~tracker.reports.REPORT_WAIT`·Ts a tick waits for them
        (a step that went out late); tick k + 1 says the same again.  The links' deadline is
        in wall time: a video played faster than real time (``--rate`` above 1) leaves their
        misses too late for the outcome, to be logged as untold."""
        now = time.monotonic()
        due = min(
            now + (self.args.deadline + OUTCOME_WAIT) * self.Ts, max(next_tick, now + REPORT_WAIT * self.Ts)
        )
        fallback, braked, missed = self.reports.for_outcome(self.inbox, k, max(0.0, due - now), _log)
        self.misses += len(missed)
        assert self.outcome is not None
        self.outcome.put(Outcome(robot=ROLE, step=k, fallback=fallback, braked=braked).encode())

    def _frame(self, k: int) -> tuple[Frame | None, str]:
        """The frame of step k (None if there is none to use) and the source's state: "ok",
        "end" (the end of a video) or "lost" (the device stopped delivering frames)."""
        source, t_k = self.source, k * self.Ts
        if isinstance(source, VideoSource):
            index = math.floor(t_k * source.fps + 1e-6)
            last = self.last
            frame = last if last is not None and index <= last.index else source.frame_at(index)
            return frame, "end" if frame is None else "ok"
        if not source.alive():
            log(ROLE, f"{source.name}: stopped delivering frames ({source.failed_reads} failed reads)")
            return None, "lost"
        frame, age = source.newest()
        if frame is not None and age > STALE_STEPS * self.Ts:
            self.tracker.skip(f"the newest frame of {source.name} is {age:.2f} s old")
            frame = None
        return frame, "ok"

    def _publish(self, k: int, frame: Frame | None) -> None:
        """Step k's poses (and truths) of every robot found in ``frame``."""
        if frame is None:
            return
        self.last = frame
        found = self.tracker.process(frame.image, label=f"{frame.index} (step {k})")
        for rid, (x, y, th) in found.items():
            th = wrap_angle(th)
            self.pubs[rid].put(Pose(robot=rid, seq=k, t=frame.t, x=x, y=y, theta=th).encode())
            self.truths[rid].put(Truth(robot=rid, seq=k, t=frame.t, x=x, y=y, theta=th).encode())

    def close(self) -> None:
        """Undeclare the subscribers."""
        for s in self.subs:
            s.undeclare()


def _log(msg: str) -> None:
    """The tracker's log line (what :class:`tracker.reports.Reports` reports)."""
    log(ROLE, msg)


@dataclass
class Frame:
    """One captured frame: ``index`` counts frames from the start of the source,
    ``t`` [s] is its capture time on the source's clock, ``image`` is None when
    it could not be read."""

    index: int
    t: float
    image: np.ndarray | None


class VideoSource:
    """Frames of a video file; frame i was captured at t = i / fps [s]."""

    def __init__(self, path: str) -> None:
        cv2 = cv2_module()
        if not Path(path).is_file():
            raise ConfigError("--video", f"{path}: no such file")
        self.path = path
        self.cap = cv2.VideoCapture(path)
        if not self.cap.isOpened():
            raise ConfigError("--video", f"{path}: cannot open as a video")
        self.fps = float(self.cap.get(cv2.CAP_PROP_FPS))
        if not (math.isfinite(self.fps) and self.fps > 0):
            raise ConfigError("--video", f"{path}: the file gives no frame rate")
        n = int(self.cap.get(cv2.CAP_PROP_FRAME_COUNT))
        self.frame_count: int | None = n if n > 0 else None
        """Frames in the file, None if the container does not say."""
        self.next_index = 0
        self.bad_in_a_row = 0

    def frame_at(self, index: int) -> Frame | None:
        """Frame ``index`` (≥ the next unread one; the ones before it are skipped
        undecoded), or None at the end of the file.  A frame that cannot be
        read has ``image`` None."""
        if index < self.next_index:
            raise ValueError(f"frame {index} was already read (next is {self.next_index})")
        state = "end"
        while self.next_index <= index:
            state = self._grab()
            if state == "end":
                return None
        image = None
        if state == "ok":
            ok, got = self.cap.retrieve()
            image = got if ok and got is not None else None
        return Frame(index, index / self.fps, image)

    def _grab(self) -> str:
        """Advance one frame: "ok", "bad" (a failed grab before the end the file
        declares, at most MAX_BAD_IN_A_ROW in a row) or "end"."""
        if self.frame_count is not None and self.next_index >= self.frame_count:
            return "end"
        if self.cap.grab():
            self.next_index += 1
            self.bad_in_a_row = 0
            return "ok"
        if self.frame_count is None or self.bad_in_a_row >= MAX_BAD_IN_A_ROW:
            return "end"
        self.bad_in_a_row += 1
        self.next_index += 1
        return "bad"

    def rewind(self) -> None:
        """Start again from frame 0 (the file is reopened: seeking is not reliable for every codec)."""
        cv2 = cv2_module()
        self.cap.release()
        self.cap = cv2.VideoCapture(self.path)
        if not self.cap.isOpened():
            raise ConfigError("--video", f"{self.path}: cannot reopen")
        self.next_index = 0
        self.bad_in_a_row = 0

    def frames(self) -> Iterator[Frame]:
        """Every frame in order."""
        while (f := self.frame_at(self.next_index)) is not None:
            yield f

    def close(self) -> None:
        """Release the video file."""
        self.cap.release()


class DeviceSource:
    """The newest frame of a camera, read continuously on a thread.

    ``t`` of a frame is ``time.monotonic()`` when ``read()`` returned it, minus
    that of the first frame read after :meth:`start` [s].  After
    MAX_BAD_IN_A_ROW failed reads in a row the thread gives up
    (:meth:`alive` turns False)."""

    def __init__(self, capture: Any, name: str) -> None:
        self.cap = capture
        """An opened ``cv2.VideoCapture`` (or anything with ``read()`` and ``release()``)."""
        self.name = name
        self.cond = threading.Condition()
        self.latest: Frame | None = None
        self.t0: float | None = None
        """``time.monotonic()`` of the first frame [s]."""
        self.read_count = 0
        self.failed_reads = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    @staticmethod
    def open(device: int) -> DeviceSource:
        """Open ``/dev/video<device>``; ConfigError (``--device``) if it cannot be opened."""
        cv2 = cv2_module()
        cap = cv2.VideoCapture(device)
        if not cap.isOpened():
            raise ConfigError("--device", f"cannot open video device {device}")
        return DeviceSource(cap, f"device {device}")

    def read_now(self) -> np.ndarray | None:
        """One frame read synchronously (before :meth:`start`), None on failure."""
        ok, image = self.cap.read()
        return image if ok else None

    def start(self) -> None:
        """Start the capture thread; the first frame it reads sets :attr:`t0`."""
        self._thread = threading.Thread(target=self._run, name="camera-capture", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        in_a_row = 0
        while not self._stop.is_set() and in_a_row < MAX_BAD_IN_A_ROW:
            ok, image = self.cap.read()
            now = time.monotonic()
            with self.cond:
                if not ok or image is None:
                    self.failed_reads += 1
                    in_a_row += 1
                    continue
                in_a_row = 0
                if self.t0 is None:
                    self.t0 = now
                self.latest = Frame(self.read_count, now - self.t0, image)
                self.read_count += 1
                self.cond.notify_all()
        with self.cond:
            self.cond.notify_all()

    def alive(self) -> bool:
        """The capture thread is running."""
        return self._thread is not None and self._thread.is_alive()

    def wait_first(self, timeout: float) -> bool:
        """Wait up to ``timeout`` [s] for the first frame."""
        deadline = time.monotonic() + timeout
        with self.cond:
            while self.latest is None:
                left = deadline - time.monotonic()
                if left <= 0 or not self.alive():
                    return False
                self.cond.wait(left)
        return True

    def newest(self) -> tuple[Frame | None, float]:
        """The newest frame and its age [s] (now − its capture time)."""
        with self.cond:
            f, t0 = self.latest, self.t0
        if f is None or t0 is None:
            return None, math.inf
        return f, time.monotonic() - (t0 + f.t)

    def close(self) -> None:
        """Stop the capture thread (waiting up to 2 s for it) and release the camera."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self.cap.release()


# --------------------------------------------------------------------------- the process


def frame_size(cap: Any) -> tuple[int, int] | None:
    """(width, height) [px] an opened ``cv2.VideoCapture`` reports, None if it does not say."""
    cv2 = cv2_module()
    w, h = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
    return (w, h) if w > 0 and h > 0 else None
