"""The ArUco camera tracker (tracker/camera.py), its synthetic images (camera_tools/synth.py),
``fleet calibrate`` (camera_tools/calibrate.py) and the ``[camera]`` scenario schema.

Ground truth comes from :mod:`camera_tools.synth`: markers drawn in world coordinates and
warped into a 30°-oblique pinhole camera (1600×1200 px, 5 cm markers ≈ 18–28 px),
then blurred (σ 0.8 px) and noised (σ 2 grey levels).  All randomness is seeded.
"""

from __future__ import annotations

import json
import math
import os
import queue
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from ground.geometry import wrap_angle
from ground.scenario import ARUCO_DICTIONARIES, ConfigError, Fiducial, load_scenario, parse_scenario

cv2 = pytest.importorskip("cv2")

from camera_layout import FIDUCIALS, OFFSET, SIZE  # noqa: E402

from camera_tools.calibrate import main as calibrate_main  # noqa: E402
from camera_tools.synth import (  # noqa: E402
    PinholeCamera,
    Renderer,
    circling,
    marker_centre,
    marker_corners,
    random_poses,
    write_video,
)  # fmt: skip
from tracker import camera as C  # noqa: E402
from tracker import vision as V  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
ENV = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONIOENCODING": "utf-8"}
MARKERS = {1: "r1", 2: "r2", 3: "r3"}
POS_TOL = 0.005
"""Required position accuracy [m]."""
HEAD_TOL = math.radians(2.0)
"""Required heading accuracy [rad]."""
IMAGE_SIZE = (1600, 1200)
"""Camera image (width, height) [px]: 5 cm markers span 18–28 px through the 30° view.
At 1280×960 (14–22 px) about 1 % of markers on the far side were not detected."""
FPS = 15.0
"""Video frame rate [1/s]: 1.5 frames per Ts, so a pose's capture time t often differs
from its step's time k·Ts (by up to 1/15 s ≈ 1.5 cm of travel at 0.25 m/s)."""
VIDEO_SECONDS = 5.0
CORRUPT_FRAME = 30
"""Frame of the test video whose JPEG header is destroyed (step 20 uses it)."""


def scenario_dict(camera: dict[str, Any] | None = None, markers: bool = True) -> dict[str, Any]:
    """Three robots of paper_three_robots with markers 1..3 and a [camera] table."""
    robots = [
        {"id": "r1", "start": [0.7, 0.0, math.pi], "goal": [-0.7, 0.0]},
        {"id": "r2", "start": [-0.35, 0.606, -math.pi / 3], "goal": [0.35, -0.606]},
        {"id": "r3", "start": [-0.35, -0.606, math.pi / 3], "goal": [0.35, 0.606]},
    ]
    if markers:
        for i, r in enumerate(robots):
            r["marker"] = i + 1
    cam = {
        "marker_size": SIZE,
        "marker_offset": list(OFFSET),
        "fiducials": [{"id": k, "position": list(v)} for k, v in FIDUCIALS.items()],
    }
    cam.update(camera or {})
    return {"name": "camera_test", "duration": 30.0, "arena": {"bounds": [-1.0, 1.0, -1.0, 1.0]},
            "robots": robots, "camera": cam}  # fmt: skip


def write_scenario(path: Path, data: dict[str, Any]) -> Path:
    from fleet.running.scenes import scene_to_toml

    path.write_text(scene_to_toml(data))
    return path


@pytest.fixture(scope="module")
def cam() -> PinholeCamera:
    corners = np.array([(-1.2, -1.2), (1.2, -1.2), (1.2, 1.2), (-1.2, 1.2)])
    return PinholeCamera.viewing(
        corners, tilt=math.radians(30.0), height=2.5, width_px=IMAGE_SIZE[0], height_px=IMAGE_SIZE[1]
    )


@pytest.fixture(scope="module")
def renderer(cam: PinholeCamera) -> Renderer:
    return Renderer(cam, FIDUCIALS, marker_size=SIZE, marker_offset=OFFSET, fiducial_size=0.08)


TRAJECTORIES = {1: circling(-0.4, 0.3, 0.25, 1.0, 0.0), 2: circling(0.4, 0.3, 0.2, -1.2, 1.0),
                3: circling(0.0, -0.4, 0.3, 0.8, 2.0)}  # fmt: skip
"""Marker id → pose function of t: 0.24–0.25 m/s, 0.8–1.2 rad/s."""


# --------------------------------------------------------------------------- schema


def test_camera_table_is_parsed_with_units_and_paths(tmp_path):
    data = scenario_dict({"homography": "cal/h.json", "device": 2, "position_noise": 0.002,
                          "heading_noise": 0.01, "dictionary": "DICT_5X5_100"})  # fmt: skip
    scn = load_scenario(write_scenario(tmp_path / "s.toml", data))
    c = scn.camera
    assert c is not None and c.dictionary == "DICT_5X5_100"
    assert c.marker_size == SIZE and c.marker_offset == OFFSET
    assert c.fiducials[0] == Fiducial(id=40, position=(-1.1, -1.1)) and len(c.fiducials) == 6
    assert c.homography == tmp_path / "cal" / "h.json"  # relative to the scenario file
    assert (c.device, c.position_noise, c.heading_noise) == (2, 0.002, 0.01)
    assert [r.marker for r in scn.robots] == [1, 2, 3]
    # Scenarios without the table keep working: no camera, no markers.
    plain = load_scenario(ROOT / "scenarios" / "paper_three_robots.toml")
    assert plain.camera is None and all(r.marker is None for r in plain.robots)


def _set(path: str, value: Any):
    def mutate(d: dict[str, Any]) -> None:
        *head, last = path.split(".")
        node: Any = d
        for key in head:
            node = node[int(key)] if key.isdigit() else node[key]
        if value is _DELETE:
            del node[last]
        elif last.isdigit():
            node[int(last)] = value
        else:
            node[last] = value

    return mutate


_DELETE = object()
SCHEMA_ERRORS = [
    (_set("camera.marker_sise", 0.05), "camera.marker_sise", "unknown key (did you mean 'marker_size'?"),
    (_set("camera.fiducials", _DELETE), "camera.fiducials", "missing required key"),
    (_set("camera.fiducials", [{"id": i, "position": [i - 40.0, 0.5 * (i % 2)]} for i in (40, 41, 42)]),
     "camera.fiducials", "expected at least 4 fiducials for the floor homography, got 3"),
    (_set("camera.fiducials", [{"id": i, "position": [0.3 * (i - 40), 0.0]} for i in (40, 41, 42, 43, 44)]),
     "camera.fiducials", "no 4 fiducials in general position"),
    (_set("camera.fiducials.0.id", 50), "camera.fiducials[0].id",
     "marker id 50 is not in DICT_4X4_50 (ids 0..49)"),
    (_set("camera.fiducials.1.id", 40), "camera.fiducials[1].id",
     "duplicate marker id 40 (also camera.fiducials[0].id)"),
    (_set("camera.fiducials.2.position", [1.1, "x"]), "camera.fiducials[2].position[1]", "expected a number"),
    (_set("camera.fiducials.1.position", [-1.08, -1.1]), "camera.fiducials[1].position",
     "closer than marker_size"),
    (_set("camera.fiducials.0", {"id": 40, "positon": [0, 0]}), "camera.fiducials[0].positon",
     "unknown key (did you mean 'position'?"),
    (_set("camera.dictionary", "DICT_4X4_51"), "camera.dictionary",
     "unknown ArUco dictionary 'DICT_4X4_51' (did you mean 'DICT_4X4_50'?"),
    (_set("camera.marker_size", 0.0), "camera.marker_size", "must be > 0, got 0"),
    (_set("camera.marker_offset", [0.01]), "camera.marker_offset", "expected 2 numbers, got 1"),
    (_set("camera.homography", 3), "camera.homography", "expected a string, got 3"),
    (_set("camera.device", -1), "camera.device", "must be an integer >= 0, got -1"),
    (_set("camera.position_noise", -0.001), "camera.position_noise", "must be >= 0"),
    (_set("camera", 3), "camera", "expected a table, got 3"),
    (_set("robots.1.marker", 1), "robots[1].marker", "duplicate marker id 1 (also robots[0].marker)"),
    (_set("robots.0.marker", 40), "robots[0].marker", "marker id 40 is also camera.fiducials[0].id"),
    (_set("robots.2.marker", 50), "robots[2].marker", "marker id 50 is not in DICT_4X4_50"),
    (_set("robots.0.marker", -1), "robots[0].marker", "must be an integer >= 0, got -1"),
    (_set("robots.0.marker", True), "robots[0].marker", "expected an integer, got true (a boolean)"),
    (_set("robots.0.markers", 1), "robots[0].markers", "unknown key (did you mean 'marker'?"),
    (lambda d: (d.pop("camera"), d["robots"][0].update(marker=60)), "robots[0].marker",
     "marker id 60 is not in DICT_4X4_50"),  # no [camera] table: the default dictionary
]  # fmt: skip


@pytest.mark.parametrize(
    ("mutate", "field", "reason"), SCHEMA_ERRORS, ids=[c[1] + ":" + c[2][:24] for c in SCHEMA_ERRORS]
)
def test_schema_errors_name_the_field_and_the_reason(mutate, field, reason):
    data = scenario_dict()
    mutate(data)
    with pytest.raises(ConfigError) as err:
        parse_scenario(data)
    assert err.value.field == field, str(err.value)
    assert reason in err.value.reason, str(err.value)


def test_every_accepted_dictionary_exists_in_opencv_with_that_many_ids():
    for name, n in ARUCO_DICTIONARIES.items():
        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))
        assert d.bytesList.shape[0] == n, name


# --------------------------------------------------------------------------- geometry and accuracy


def test_marker_geometry_is_exact_under_perspective(cam):
    """With exact corners and the exact homography the pose is exact: the mapped
    corners' mean is the marker centre, the diagonals meet at its image, and the
    heading is the marker's x axis, for markers anywhere in an oblique view."""
    H = np.linalg.inv(cam.homography())
    rng = np.random.default_rng(3)
    for _ in range(200):
        x, y, th = rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(-math.pi, math.pi)
        img = cam.project(marker_corners((x, y), th, SIZE))
        cx, cy, theta, side, area = V.marker_pose(img, H)
        assert math.hypot(cx - x, cy - y) < 1e-9 and abs(wrap_angle(theta - th)) < 1e-9
        assert side == pytest.approx(SIZE, rel=1e-9) and area == pytest.approx(SIZE**2, rel=1e-9)
        assert np.allclose(V.image_centre(img), cam.project(np.array([[x, y]]))[0], atol=1e-9)
        # the image centroid is not the projected centre under perspective
        pose = V.axle_pose((cx, cy), theta, OFFSET)
        assert np.allclose(marker_centre(pose, OFFSET), (x, y), atol=1e-12)


def accuracy(label: str, pos: np.ndarray, head_deg: np.ndarray) -> str:
    """One line: max and p99 of position errors [m → mm] and heading errors [°]."""
    return (
        f"\n{label}: position max {pos.max() * 1e3:.2f} mm, p99 {np.percentile(pos, 99) * 1e3:.2f} mm; "
        f"heading max {head_deg.max():.2f}°, p99 {np.percentile(head_deg, 99):.2f}°"
    )


def test_poses_of_60_random_robots_under_perspective_blur_and_noise(renderer):
    """12 images × 5 robots: every marker found, within 5 mm and 2° of the truth."""
    det = V.make_detector()
    fids = [Fiducial(id=k, position=v) for k, v in FIDUCIALS.items()]
    cal = V.calibrate([V.detect(renderer.render({}, seed=s), det) for s in range(3)], fids, IMAGE_SIZE)
    assert cal.rms_error < 0.5e-3 and set(cal.image_points) == set(FIDUCIALS)
    rng = np.random.default_rng(2024)
    markers = {i: f"r{i}" for i in range(1, 6)}
    pos_err, head_err = [], []
    for k in range(12):
        truth = random_poses(rng, 5)
        image = renderer.render(truth, blur=0.8, noise=2.0, seed=100 + k)
        found = V.poses(V.detect(image, det), cal.H, markers, OFFSET, SIZE)
        assert set(found) == set(markers.values()), f"image {k}: found {sorted(found)}"
        for mid, (x, y, th) in truth.items():
            fx, fy, fth = found[markers[mid]]
            pos_err.append(math.hypot(fx - x, fy - y))
            head_err.append(abs(wrap_angle(fth - th)))
    pe, he = np.array(pos_err), np.degrees(head_err)
    print(accuracy("60 poses", pe, he))
    assert len(pe) == 60
    assert pe.max() < POS_TOL, pe.max()
    assert he.max() < math.degrees(HEAD_TOL), he.max()


def test_edge_refinement_beats_subpixel_corners_alone(renderer, cam):
    """The edge-line fit on top of CORNER_REFINE_SUBPIX: smaller heading errors (measured, seeded)."""
    det = V.make_detector()
    H = np.linalg.inv(cam.homography())
    rng = np.random.default_rng(7)
    err: dict[bool, list[float]] = {True: [], False: []}
    for k in range(4):
        truth = random_poses(rng, 5)
        image = renderer.render(truth, seed=k)
        for refine in (True, False):
            found = V.detect(image, det, refine=refine)
            for mid, (_, _, th) in truth.items():
                err[refine].append(abs(wrap_angle(V.marker_pose(found[mid], H)[2] - th)))
    assert np.mean(err[True]) < 0.75 * np.mean(err[False]), (np.mean(err[True]), np.mean(err[False]))


# --------------------------------------------------------------------------- what the tracker skips


def test_missing_unknown_duplicate_and_bad_frames_are_counted_not_fatal(renderer, cam):
    fids = [Fiducial(id=k, position=v) for k, v in FIDUCIALS.items()]
    cal = V.calibrate([V.detect(renderer.render({}, seed=1), V.make_detector())], fids, IMAGE_SIZE)
    spec = parse_scenario(scenario_dict()).camera
    logged: list[str] = []
    trk = V.Tracker(spec, MARKERS, cal, report=logged.append)
    r1, r3, stranger = (-0.5, 0.2, 0.3), (0.4, -0.3, -2.0), (0.0, 0.5, 1.0)
    for k in range(2):  # r2's marker absent, id 7 belongs to nobody
        got = trk.process(renderer.render({1: r1, 3: r3, 7: stranger}, seed=k), label=str(k))
        assert set(got) == {"r1", "r3"}
        assert math.hypot(got["r1"][0] - r1[0], got["r1"][1] - r1[1]) < POS_TOL
    c = trk.counts
    assert c.gaps == {"r1": 0, "r2": 2, "r3": 0} and c.unknown == {7: 2} and c.bad_frames == 0
    assert sum("marker id 7" in m for m in logged) == 1  # logged once, counted every time
    assert sum("r2: marker 2 not seen" in m for m in logged) == 1
    # Unreadable frames: skipped and counted, every robot gets a gap.
    good = renderer.render({1: r1}, seed=5)
    _, jpg = cv2.imencode(".jpg", good)
    broken = bytearray(jpg.tobytes())
    broken[2:400] = bytes(398)  # destroy the JPEG header
    bad = [
        None,  # what a failed read gives
        cv2.imdecode(np.frombuffer(broken, np.uint8), cv2.IMREAD_COLOR),  # None too
        np.zeros((4, 4), np.uint8),
        good.astype(np.float32),
        np.zeros((*IMAGE_SIZE[::-1], 5), np.uint8),
        np.zeros((480, 640), np.uint8),  # not the calibrated size
        "not an image",
    ]
    for frame in bad:
        assert trk.process(frame) == {}
    assert c.bad_frames == len(bad) and c.gaps == {"r1": len(bad), "r2": 2 + len(bad), "r3": len(bad)}
    assert sum("unusable frame" in m for m in logged) == 1
    # A garbled (but decodable) JPEG never crashes it either.
    rng = np.random.default_rng(0)
    for _ in range(5):
        noisy = bytearray(jpg.tobytes())
        at = rng.integers(1000, len(noisy) - 10, 20)
        for i in at:
            noisy[i] = int(rng.integers(0, 256))
        trk.process(cv2.imdecode(np.frombuffer(bytes(noisy), np.uint8), cv2.IMREAD_GRAYSCALE))
    # The same id twice in one frame: ambiguous, dropped and counted.
    before = c.gaps["r1"]
    assert set(trk.process(renderer.render({1: r1, 2: (0.3, 0.3, 0.0), 3: r3}, seed=9))) == {"r1", "r2", "r3"}
    twin = Renderer(
        cam, {**FIDUCIALS, 1: (0.5, 0.5)}, marker_size=SIZE, marker_offset=OFFSET, fiducial_size=SIZE
    )
    got = trk.process(twin.render({1: r1, 3: r3}, seed=3))  # a second marker 1 lies on the floor
    assert set(got) == {"r3"} and c.duplicates == {1: 1} and c.gaps["r1"] == before + 1
    # A mirrored homography (fiducials in a left-handed frame) is caught, not published.
    mirrored = V.Calibration(H=np.diag([1.0, -1.0, 1.0]) @ cal.H, image_points={}, world_points={},
                             rms_error=0.0, max_error=0.0, image_size=IMAGE_SIZE)  # fmt: skip
    trk2 = V.Tracker(spec, MARKERS, mirrored, report=logged.append)
    assert trk2.process(renderer.render({1: r1}, seed=2)) == {}
    assert trk2.counts.implausible == {1: 1} and any("mirrored" in m for m in logged)


# --------------------------------------------------------------------------- the video and the process


@pytest.fixture(scope="module")
def video(tmp_path_factory, renderer) -> Path:
    """5 s at 20 fps of TRAJECTORIES (MJPG .avi), frame CORRUPT_FRAME's JPEG header destroyed."""
    path = tmp_path_factory.mktemp("video") / "three.avi"
    n = write_video(path, renderer, TRAJECTORIES, VIDEO_SECONDS, FPS, blur=0.8, noise=2.0, seed=11)
    assert n == int(VIDEO_SECONDS * FPS)
    data = bytearray(path.read_bytes())
    soi = [i for i in range(len(data) - 2) if data[i] == 0xFF and data[i + 1] == 0xD8 and data[i + 2] == 0xFF]
    assert len(soi) == n
    data[soi[CORRUPT_FRAME] : soi[CORRUPT_FRAME] + 400] = bytes(400)
    path.write_bytes(bytes(data))
    return path


def test_device_source_keeps_the_newest_frame_and_notices_when_frames_stop(video):
    """The capture thread of ``--device``, fed by a file: it ends after the last frame
    (MAX_BAD_IN_A_ROW failed reads), and the newest frame is the last one."""
    src = C.DeviceSource(cv2.VideoCapture(str(video)), "a file as a device")
    try:
        src.start()
        assert src.wait_first(30.0)
        deadline = time.monotonic() + 60.0
        with src.cond:
            while src.alive() and time.monotonic() < deadline:
                src.cond.wait(0.5)
        assert not src.alive()
        frame, age = src.newest()
        assert frame is not None and frame.image is not None and frame.image.shape == (*IMAGE_SIZE[::-1], 3)
        # the corrupt frame is a failed read, not a frame
        assert frame.index == src.read_count - 1 == int(VIDEO_SECONDS * FPS) - 2
        assert src.failed_reads == C.MAX_BAD_IN_A_ROW + 1 and frame.t > 0.0 and age >= 0.0
    finally:
        src.close()


def _lines(stream: Any, into: queue.Queue[str]) -> None:
    for line in stream:
        into.put(line)


@pytest.mark.slow
@pytest.mark.parametrize("ahead", [False, True], ids=["solve-after-tick", "delay-compensation"])
def test_video_through_the_tracker_process_matches_the_trajectories(tmp_path, video, ahead):
    """``python -m tracker --source camera --video`` over Zenoh on loopback: every pose's
    (t, x, y, θ) matches the trajectory at t; the corrupt frame's step is skipped.

    With ``--delay-compensation``, stand-ins for the robots' links report each step at its
    tick (r2 followed its candidate at step 5, r3 braked at step 9): each step's outcome tells
    its reports, the next tick says the same, and each miss is counted once."""
    import zenoh

    from ground.wire import Applied, Keys, Outcome, Pose, Tick, decode
    from transport.net import NetConfig, free_port, loopback

    scn = write_scenario(tmp_path / "s.toml", scenario_dict())
    hub = loopback(free_port())
    # At 5× the video's pace a step lasts 20 ms; planning ahead, the outcome waits for the
    # links' reports within the step, so that run keeps the real pace.
    cmd = [sys.executable, "-m", "tracker", "--scenario", str(scn), "--source", "camera",
           "--video", str(video), "--rate", "1" if ahead else "5", "--listen", hub, "--fleet", "camtest",
           "--wait-agents", "--start-timeout", "60",
           "--delay-compensation" if ahead else "--no-delay-compensation"]  # fmt: skip
    proc = subprocess.Popen(cmd, cwd=ROOT, env=ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    out: queue.Queue[str] = queue.Queue()
    err: queue.Queue[str] = queue.Queue()
    readers = [
        threading.Thread(target=_lines, args=(s, q), daemon=True)
        for s, q in ((proc.stdout, out), (proc.stderr, err))
    ]
    for t in readers:
        t.start()
    keys = Keys("camtest")
    poses: list[Pose] = []
    ticks: list[Tick] = []
    outcomes: list[Outcome] = []
    stopped = threading.Event()
    lock = threading.Lock()
    links: dict[str, Any] = {}

    def report(step: int) -> None:
        """What each stand-in link applied over ``step``: (last applied, braked)."""
        said = {"r1": (step, False), "r2": (4, False) if step == 5 else (step, False)}
        said["r3"] = (8, True) if step == 9 else (step, False)
        for r, (last, braked) in said.items():
            links[r].put(Applied(robot=r, step=step, last=last, braked=braked).encode())

    def on_pose(sample: Any) -> None:
        msg = decode(sample.payload.to_bytes(), Pose, robot=keys.robot_of(str(sample.key_expr)))
        with lock:
            poses.append(msg)

    def on_tick(sample: Any) -> None:
        tick = decode(sample.payload.to_bytes(), Tick)
        with lock:
            ticks.append(tick)
        if tick.stop:
            stopped.set()
        elif ahead:
            report(tick.step)

    def on_outcome(sample: Any) -> None:
        with lock:
            outcomes.append(decode(sample.payload.to_bytes(), Outcome))

    session = None
    handles: list[Any] = []
    try:
        ready = json.loads(out.get(timeout=120))  # the readiness line, not a sleep
        assert ready["event"] == "ready" and ready["role"] == "tracker" and ready["source"] == "camera"
        assert ready["robots"] == ["r1", "r2", "r3"] and ready["pid"] == proc.pid
        session = zenoh.open(NetConfig(listen=[loopback(0)], connect=[hub]).zenoh())
        links.update({r: session.declare_publisher(keys.applied(r)) for r in ("r1", "r2", "r3")})
        handles += [
            session.declare_subscriber(keys.pose(), on_pose),
            session.declare_subscriber(keys.clock, on_tick),
            session.declare_subscriber(keys.outcome, on_outcome),
        ]
        # Stand in for the agents and the supervisor the tracker waits for.
        handles += [
            session.liveliness().declare_token(keys.alive(r)) for r in ("r1", "r2", "r3", "supervisor")
        ]
        assert stopped.wait(timeout=120), "no stop tick"
        assert proc.wait(timeout=60) == 0
    finally:
        for h in (*handles, *links.values()):
            h.undeclare()
        if session is not None:
            session.close()
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=30)
    for t in readers:
        t.join(timeout=10)
    stderr = "".join(err.queue)
    frames = int(VIDEO_SECONDS * FPS)
    steps = math.ceil(frames / (0.1 * FPS))  # Ts = 0.1 s: step k shows frame ⌊1.5 k⌋
    with lock:
        assert [t.step for t in ticks] == list(range(steps + 1)) and ticks[-1].stop and not ticks[-2].stop
        told = {o.step: (o.fallback, o.braked) for o in outcomes}
        said = {t.step - 1: (t.fallback, t.braked) for t in ticks[1:]}
        if ahead:
            assert sorted(told) == list(range(steps)) and len(outcomes) == steps, sorted(told)
            assert told[5] == ({"r2": 4}, {}) and told[9] == ({}, {"r3": 8}), (told[5], told[9])
            assert all(v == ({}, {}) for j, v in told.items() if j not in (5, 9)), told
            assert said == told  # each tick says what the outcome of the step before told
            assert ticks[-1].misses == 2  # each miss counted once
        else:
            assert outcomes == [] and all(v == ({}, {}) for v in said.values())
        assert all(t.t == pytest.approx(0.1 * t.step) and t.robot == "tracker" for t in ticks)
        skipped = round(CORRUPT_FRAME / (0.1 * FPS))
        assert math.floor(skipped * 0.1 * FPS) == CORRUPT_FRAME
        by_step: dict[int, set[str]] = {}
        pos_err, head_err = [], []
        for p in poses:
            by_step.setdefault(p.seq, set()).add(p.robot)
            assert p.t == math.floor(p.seq * 0.1 * FPS + 1e-6) / FPS  # capture time of the step's frame
            mid = int(p.robot[1:])
            x, y, th = TRAJECTORIES[mid](p.t)
            pos_err.append(math.hypot(p.x - x, p.y - y))
            head_err.append(abs(wrap_angle(p.theta - th)))
            assert -math.pi < p.theta <= math.pi
        assert set(by_step) == set(range(steps)) - {skipped}, sorted(set(range(steps)) - set(by_step))
        assert all(v == {"r1", "r2", "r3"} for v in by_step.values())
    pe, he = np.array(pos_err), np.degrees(head_err)
    print(accuracy(f"video, {len(pe)} poses", pe, he))
    assert pe.max() < POS_TOL and he.max() < math.degrees(HEAD_TOL)
    assert "calibrated from 6 fiducials" in stderr, stderr
    assert "1 unusable; gaps per robot {r1: 1, r2: 1, r3: 1}" in stderr, stderr
    assert "(end of video)" in stderr and "Traceback" not in stderr


def _tracker(*args: str, timeout: float = 120, pre: str = "") -> subprocess.CompletedProcess[str]:
    run = "runpy.run_module('tracker', run_name='__main__')"
    code = f"{pre}import runpy, sys; sys.argv = ['tracker', *{list(args)!r}]; {run}"
    return subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=ENV, capture_output=True, text=True,
                          timeout=timeout)  # fmt: skip


def test_tracker_process_bad_input_gets_one_line_and_exit_2(tmp_path, video):
    good = write_scenario(tmp_path / "good.toml", scenario_dict())
    unmarked = write_scenario(tmp_path / "unmarked.toml", scenario_dict(markers=False))
    no_camera = scenario_dict()
    del no_camera["camera"]
    plain = write_scenario(tmp_path / "plain.toml", no_camera)
    small = V.Calibration(H=np.eye(3), image_points={}, world_points={}, rms_error=0.0, max_error=0.0,
                          image_size=(640, 480))  # fmt: skip
    small.save(tmp_path / "small.json")
    resized = write_scenario(tmp_path / "resized.toml", scenario_dict({"homography": "small.json"}))
    lost = write_scenario(tmp_path / "lost.toml", scenario_dict({"homography": "lost.json"}))
    cases = [
        (("--scenario", str(resized), "--source", "camera", "--video", str(video)),
         "tracker: error: camera.homography: ", "is for 640×480 px images, the source gives 1600×1200 px"),
        (("--scenario", str(lost), "--source", "camera", "--video", str(video)),
         "tracker: error: camera.homography: ", "lost.json: no such file (write it with fleet calibrate)"),
        (("--scenario", str(good), "--source", "camera", "--video", str(tmp_path / "none.avi")),
         "tracker: error: --video: ", "no such file"),
        (("--scenario", str(good), "--source", "camera", "--video", str(good)),
         "tracker: error: --video: ", "cannot open"),
        (("--scenario", str(unmarked), "--source", "camera", "--video", str(video)),
         "tracker: error: robots[0].marker: ", "missing"),
        (("--scenario", str(plain), "--source", "camera", "--video", str(video)),
         "tracker: error: camera: ", "missing"),
        (("--scenario", str(good), "--source", "camera", "--video", str(video), "--rate", "0"),
         "tracker: error: --rate: ", "must be > 0"),
        (("--scenario", str(tmp_path / "nope.toml"), "--source", "sim"),
         "tracker: error: file: ", "no such file"),  # dispatched to the simulated tracker
    ]  # fmt: skip
    for args, head, reason in cases:
        res = _tracker(*args)
        assert res.returncode == 2, (args, res.stderr)
        assert res.stderr.count("\n") == 1 and res.stderr.startswith(head) and reason in res.stderr, (
            res.stderr
        )
    # Without OpenCV: one clear line.
    res = _tracker(
        "--scenario",
        str(good),
        "--source",
        "camera",
        "--video",
        str(video),
        pre="import sys; sys.modules['cv2'] = None; ",
    )
    assert res.returncode == 2
    assert res.stderr == "tracker: error: camera source needs OpenCV: pip install 'epuck-fleet[camera]'\n"


# --------------------------------------------------------------------------- fleet calibrate


def test_fleet_calibrate_writes_a_homography_that_maps_the_fiducials(tmp_path, renderer, cam, capsys, video):
    scn = write_scenario(tmp_path / "s.toml", scenario_dict({"homography": "h.json"}))
    image = tmp_path / "floor.png"
    cv2.imwrite(str(image), renderer.render({1: (0.2, 0.1, 0.5)}, seed=4))
    assert calibrate_main([str(scn), "--image", str(image)]) == 0
    assert capsys.readouterr().out.startswith(f"wrote {tmp_path / 'h.json'}: 6 fiducials")
    d = json.loads((tmp_path / "h.json").read_text())
    H = np.array(d["homography"])
    assert H.shape == (3, 3) and d["image_size"] == list(IMAGE_SIZE) and d["created"].endswith("+00:00")
    assert set(d["fiducials"]) == {str(k) for k in FIDUCIALS}
    for fid, v in d["fiducials"].items():
        assert v["world_m"] == list(FIDUCIALS[int(fid)])
        assert np.linalg.norm(V.to_plane(H, np.array([v["image_px"]]))[0] - v["world_m"]) < 1e-3
    assert d["rms_error_m"] < 0.5e-3 and d["max_error_m"] < 1e-3
    # It is the camera's true floor homography: floor points map back to within 1 mm.
    pts = np.random.default_rng(0).uniform(-1.0, 1.0, (200, 2))
    assert np.abs(V.to_plane(H, cam.project(pts)) - pts).max() < 1e-3
    # The tracker reads it back; a video calibrates too, averaging frames.
    cal = V.Calibration.load(tmp_path / "h.json")
    assert np.allclose(cal.H, H) and cal.rms_error == d["rms_error_m"]
    assert (
        calibrate_main([str(scn), "--video", str(video), "--frames", "5", "--out", str(tmp_path / "v.json")])
        == 0
    )
    assert json.loads((tmp_path / "v.json").read_text())["frames"] == 5


def test_fleet_calibrate_with_four_fiducials_says_the_rms_measures_nothing(tmp_path, renderer, capsys):
    four = [{"id": k, "position": list(FIDUCIALS[k])} for k in (40, 42, 43, 45)]
    scn = write_scenario(tmp_path / "s.toml", scenario_dict({"homography": "h.json", "fiducials": four}))
    image = tmp_path / "floor.png"
    cv2.imwrite(str(image), renderer.render({}, seed=2))
    assert calibrate_main([str(scn), "--image", str(image)]) == 0
    out, err = capsys.readouterr()
    assert out.startswith(f"wrote {tmp_path / 'h.json'}: 4 fiducials") and "RMS 0.000 mm" in out, out
    assert err.count("\n") == 1 and "RMS is 0 by construction" in err, err
    # With all six the note is not printed, and the RMS is a real residual.
    scn6 = write_scenario(tmp_path / "s6.toml", scenario_dict({"homography": "h6.json"}))
    assert calibrate_main([str(scn6), "--image", str(image)]) == 0
    out, err = capsys.readouterr()
    assert "6 fiducials" in out and "RMS 0.000 mm" not in out and "by construction" not in err, (out, err)


def test_fleet_calibrate_bad_input_exits_2_with_one_line(tmp_path, renderer, capsys):
    scn = write_scenario(tmp_path / "s.toml", scenario_dict())
    blank = tmp_path / "blank.png"
    cv2.imwrite(str(blank), np.full(IMAGE_SIZE[::-1], 128, np.uint8))
    three = tmp_path / "three.png"
    only3 = Renderer(renderer.camera, {k: FIDUCIALS[k] for k in (40, 42, 43)}, marker_size=SIZE)
    cv2.imwrite(str(three), only3.render({}, seed=1))
    text = tmp_path / "notes.png"
    text.write_text("not an image")
    no_camera = scenario_dict()
    del no_camera["camera"]
    plain = write_scenario(tmp_path / "plain.toml", no_camera)
    cases = [
        ([str(scn), "--image", str(tmp_path / "missing.png")], "--image: ", "no such file"),
        ([str(scn), "--image", str(text)], "--image: ", "not a readable image"),
        ([str(scn), "--image", str(blank)], "camera.fiducials: ", "0 of 6 fiducials seen (ids none)"),
        ([str(scn), "--image", str(three)], "camera.fiducials: ", "3 of 6 fiducials seen (ids 40, 42, 43)"),
        ([str(plain), "--image", str(three)], "camera: ", "missing [camera] table"),
        ([str(tmp_path / "nope.toml"), "--image", str(three)], "file: ", "no such file"),
        ([str(scn), "--video", str(text)], "--video: ", "no frame could be read"),
        ([str(scn), "--video", str(blank), "--frames", "0"], "--frames: ", "must be >= 1"),
    ]
    for argv, field, reason in cases:
        assert calibrate_main(argv) == 2, argv
        cap = capsys.readouterr()
        assert (
            cap.err.count("\n") == 1 and cap.err.startswith(f"fleet: error: {field}") and reason in cap.err
        ), cap.err
    # A fit worse than the claimed bound is refused (exit 1) and not written.
    tight = write_scenario(tmp_path / "tight.toml", scenario_dict({"position_noise": 1e-7}))
    good = tmp_path / "good.png"
    cv2.imwrite(str(good), renderer.render({}, seed=2))
    assert calibrate_main([str(tight), "--image", str(good), "--out", str(tmp_path / "t.json")]) == 1
    assert "camera.position_noise: reprojection RMS" in capsys.readouterr().err
    assert not (tmp_path / "t.json").exists()
