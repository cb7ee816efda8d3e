"""Lens distortion: the synthetic lens (camera_tools/synth.py), the intrinsics and their ChArUco
calibration (tracker/intrinsics.py), undistorted tracking (tracker/vision.py), ``fleet
calibrate --intrinsics`` and ``fleet markers --charuco``.

The lens is OpenCV's model (calib3d, "Camera Calibration and 3D Reconstruction") with
k₁ = −0.3, k₂ = 0.1, a strong webcam's barrel distortion, on the 1600×1200 px, 30°-oblique
camera of test_camera.py refitted so the distorted arena fills the image.  All randomness
is seeded.
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from ground.geometry import wrap_angle
from ground.scenario import CameraSpec, ConfigError, Fiducial, load_scenario

cv2 = pytest.importorskip("cv2")

from camera_layout import FIDUCIALS, OFFSET, SIZE  # noqa: E402

from camera_tools.calibrate import main as calibrate_main  # noqa: E402
from camera_tools.markers import charuco_figure  # noqa: E402
from camera_tools.markers import main as markers_main  # noqa: E402
from camera_tools.synth import (  # noqa: E402
    PinholeCamera,
    Renderer,
    board_poses,
    board_view,
    circling,
    lens_map,
    marker_centre,
    marker_corners,
    random_poses,
    write_video,
)
from tracker import intrinsics as I  # noqa: E402
from tracker import vision as V  # noqa: E402

LENS = (-0.3, 0.1, 0.0, 0.0, 0.0)
"""(k₁, k₂, p₁, p₂, k₃) of the test lens."""
IMAGE_SIZE = (1920, 1440)
VIEWS = 16
"""ChArUco views of the calibration."""
POS_TOL = 2e-3
"""Required position accuracy with intrinsics [m]."""
HEAD_TOL = 1.0
"""Required heading accuracy with intrinsics [°]."""


@pytest.fixture(scope="module")
def lens_cam() -> PinholeCamera:
    corners = np.array([(-1.2, -1.2), (1.2, -1.2), (1.2, 1.2), (-1.2, 1.2)])
    return PinholeCamera.viewing(
        corners,
        tilt=math.radians(30.0),
        height=2.5,
        width_px=IMAGE_SIZE[0],
        height_px=IMAGE_SIZE[1],
        distortion=LENS,
    )


@pytest.fixture(scope="module")
def lens_renderer(lens_cam: PinholeCamera) -> Renderer:
    return Renderer(lens_cam, FIDUCIALS, marker_size=SIZE, marker_offset=OFFSET, fiducial_size=0.08)


@pytest.fixture(scope="module")
def board_frames(lens_cam: PinholeCamera) -> list[np.ndarray]:
    poses = board_poses(lens_cam, I.DEFAULT_BOARD, VIEWS, seed=1)
    return [board_view(lens_cam, I.DEFAULT_BOARD, R, t, seed=10 + i) for i, (R, t) in enumerate(poses)]


@pytest.fixture(scope="module")
def fitted(board_frames: list[np.ndarray]) -> I.Intrinsics:
    return I.calibrate_intrinsics(board_frames)


def camera_spec() -> CameraSpec:
    return CameraSpec(
        marker_size=SIZE, marker_offset=OFFSET,
        fiducials=tuple(Fiducial(id=k, position=v) for k, v in FIDUCIALS.items()),
    )  # fmt: skip


def write_scenario(path: Path, camera: dict[str, Any] | None = None) -> Path:
    from fleet.running.scenes import scene_to_toml

    cam = {
        "marker_size": SIZE,
        "marker_offset": list(OFFSET),
        "fiducials": [{"id": k, "position": list(v)} for k, v in FIDUCIALS.items()],
        **(camera or {}),
    }
    data = {"name": "lens_test", "duration": 10.0, "arena": {"bounds": [-1.0, 1.0, -1.0, 1.0]},
            "robots": [{"id": "r1", "start": [0.0, 0.0, 0.0], "goal": [0.5, 0.0], "marker": 1}],
            "camera": cam}  # fmt: skip
    path.write_text(scene_to_toml(data))
    return path


# --------------------------------------------------------------------------- the lens model


def test_lens_model_is_opencvs_and_undistortion_inverts_it():
    """distort_normalised agrees with cv2.projectPoints (all five coefficients), and
    undistort_points inverts the model to 1e-6 px over the whole test image."""
    rng = np.random.default_rng(3)
    xy = rng.uniform(-0.7, 0.7, (500, 2))
    dist = (-0.28, 0.09, 0.0015, -0.0012, -0.02)
    cv_px, _ = cv2.projectPoints(np.column_stack([xy, np.ones(len(xy))]), np.zeros(3), np.zeros(3), np.eye(3),
                                 np.array(dist))  # fmt: skip
    assert np.abs(I.distort_normalised(xy, dist) - cv_px.reshape(-1, 2)).max() < 1e-12
    K = PinholeCamera.viewing(np.array([(-1.2, -1.2), (1.2, 1.2)]), distortion=LENS).intrinsics()
    grid = np.stack(np.meshgrid(np.linspace(0, 1599, 41), np.linspace(0, 1199, 31)), -1).reshape(-1, 2)
    back = I.distort_points(I.undistort_points(grid, K, LENS), K, LENS)
    assert np.abs(back - grid).max() < 1e-6


def test_default_camera_has_no_lens():
    assert not PinholeCamera().distorted and lens_map(PinholeCamera()) is None


def test_rendered_corners_sit_where_the_lens_puts_them(lens_renderer, lens_cam):
    """Detected marker corners match the lens model's projection (< 0.5 px), while the ideal
    pinhole's projection is off by several px towards the image edges."""
    rng = np.random.default_rng(11)
    truth = random_poses(rng, 12, half=1.0)
    image = lens_renderer.render(truth, blur=0.8, noise=0.0, seed=0)
    found = V.detect(image, V.make_detector())
    assert set(truth) <= set(found)
    err, ideal_err = [], []
    for mid, pose in truth.items():
        world = marker_corners(marker_centre(pose, OFFSET), pose[2], SIZE)
        err.append(np.abs(found[mid] - lens_cam.project(world)).max())
        ideal_err.append(np.abs(found[mid] - V.to_plane(lens_cam.homography(), world)).max())
    print(f"\ncorner error through the lens model {max(err):.3f} px, ideal pinhole {max(ideal_err):.1f} px")
    assert max(err) < 0.5
    assert max(ideal_err) > 10.0


# --------------------------------------------------------------------------- calibration


def test_charuco_calibration_recovers_the_lens(fitted, lens_cam):
    """RMS below 0.5 px, and the fitted lens undistorts the true lens's image into an ideal
    pinhole image: over the whole image, fitted undistortion ∘ true distortion is a
    homography (straight lines stay straight) to within 0.3 px at 95 % of the image's points
    and 1 px in its far corners, which the boards barely reach.  K itself is only
    determined to about 1 % (it trades off against the board poses); the floor homography
    absorbs that projective remainder."""
    print(
        f"\nintrinsics: RMS {fitted.rms:.3f} px, worst view {max(fitted.view_errors):.3f} px; "
        f"f {fitted.K[0, 0]:.1f} (true {lens_cam.focal:.1f}) px, "
        f"k1 {fitted.dist[0]:+.4f}, k2 {fitted.dist[1]:+.4f}"
    )
    assert fitted.rms < 0.5 and len(fitted.view_errors) == VIEWS
    assert fitted.image_size == IMAGE_SIZE
    K = lens_cam.intrinsics()
    observed = np.stack(
        np.meshgrid(np.linspace(0, IMAGE_SIZE[0] - 1, 33), np.linspace(0, IMAGE_SIZE[1] - 1, 25)), -1
    ).reshape(-1, 2)
    ideal = I.undistort_points(observed, K, LENS)  # the true pinhole image
    mine = fitted.undistort(observed)
    H, _ = cv2.findHomography(mine, ideal, 0)
    residual = np.linalg.norm(V.to_plane(H, mine) - ideal, axis=1)
    p95 = np.percentile(residual, 95)
    print(f"fitted undistortion vs truth, up to a homography: p95 {p95:.3f} px, max {residual.max():.3f} px")
    assert p95 < 0.3 and residual.max() < 1.0
    # Without undistortion the observed image is far from any pinhole image.
    H0, _ = cv2.findHomography(observed, ideal, 0)
    assert np.linalg.norm(V.to_plane(H0, observed) - ideal, axis=1).max() > 20.0


def test_floor_errors_without_intrinsics_are_large_and_with_them_within_2_mm_and_1_degree(
    lens_renderer, fitted
):
    """60 robot poses over the whole arena (6 frames × 10 robots) through the k₁ = −0.3 lens:
    the homography alone is off by tens of mm; with the fitted intrinsics every pose is
    within 2 mm and 1°."""
    det = V.make_detector()
    fid_dets = [V.detect(lens_renderer.render({}, seed=s), det) for s in range(2)]
    fids = camera_spec().fiducials
    plain = V.calibrate(fid_dets, fids, IMAGE_SIZE)
    undist = V.calibrate(fid_dets, fids, IMAGE_SIZE, fitted)
    assert undist.undistorted and not plain.undistorted
    markers = {i: f"r{i}" for i in range(1, 11)}
    told: list[str] = []
    without = V.Tracker(camera_spec(), markers, plain, report=told.append)
    with_ = V.Tracker(camera_spec(), markers, undist, intrinsics=fitted)
    rng = np.random.default_rng(2026)
    errs: dict[str, list[tuple[float, float]]] = {"without": [], "with": []}
    for k in range(6):
        truth = random_poses(rng, 10, half=1.0)
        image = lens_renderer.render(truth, blur=0.8, noise=2.0, seed=200 + k)
        for name, tracker in (("without", without), ("with", with_)):
            found = tracker.process(image, label=str(k))
            assert set(found) == set(markers.values()), f"{name}, frame {k}: {sorted(found)}"
            for mid, (x, y, th) in truth.items():
                fx, fy, fth = found[markers[mid]]
                errs[name].append((math.hypot(fx - x, fy - y), math.degrees(abs(wrap_angle(fth - th)))))
    e0, e1 = np.array(errs["without"]), np.array(errs["with"])
    print(
        f"\nwithout intrinsics: position max {e0[:, 0].max() * 1e3:.1f} mm, "
        f"heading max {e0[:, 1].max():.2f}°; "
        f"fiducial RMS {plain.rms_error * 1e3:.1f} mm"
        f"\nwith intrinsics: position max {e1[:, 0].max() * 1e3:.2f} mm, heading max {e1[:, 1].max():.2f}°; "
        f"fiducial RMS {undist.rms_error * 1e3:.2f} mm"
    )
    assert len(e1) == 60
    assert e0[:, 0].max() > 10e-3  # the problem
    assert e1[:, 0].max() < POS_TOL and e1[:, 1].max() < HEAD_TOL  # solved
    # The lens barely turns a small marker (0.7° at most here, within the bound anyway), but
    # the heading from undistorted corners is still several times closer to the truth.
    assert e1[:, 1].max() < 0.5 * e0[:, 1].max(), (e1[:, 1].max(), e0[:, 1].max())
    assert sum("lens distortion is not corrected" in m for m in told) == 1


VIDEO_TRAJECTORIES = {1: circling(-0.5, 0.45, 0.4, 1.0, 0.0), 2: circling(0.5, 0.4, 0.4, -1.2, 1.0),
                      3: circling(0.0, -0.5, 0.4, 0.8, 2.0)}  # fmt: skip
"""Marker id → pose function of t [s]: three robots over most of the arena, out to 0.9 m
from its centre, where the lens bends most."""
VIDEO_FPS = 10.0
VIDEO_SECONDS = 3.0


@pytest.fixture(scope="module")
def lens_video(tmp_path_factory, lens_renderer) -> Path:
    """3 s at 10 fps of VIDEO_TRAJECTORIES through the k₁ = −0.3 lens (MJPG .avi)."""
    path = tmp_path_factory.mktemp("lens_video") / "three.avi"
    n = write_video(path, lens_renderer, VIDEO_TRAJECTORIES, VIDEO_SECONDS, VIDEO_FPS, seed=7)
    assert n == int(VIDEO_SECONDS * VIDEO_FPS)
    return path


def _video_frames(path: Path) -> list[np.ndarray]:
    cap = cv2.VideoCapture(str(path))
    frames = []
    try:
        while True:
            ok, frame = cap.read()
            if not ok:
                break
            frames.append(frame)
    finally:
        cap.release()
    return frames


def _track_video(frames: list[np.ndarray], intrinsics: I.Intrinsics | None) -> np.ndarray:
    """The tracker's frame processing (tracker/camera.py: calibrate from the video's first
    frames, then every frame through :class:`tracker.vision.Tracker`) over ``frames``:
    (position error [m], heading error [°]) of every robot in every frame (N, 2)."""
    cal = V.calibrate_from(iter(frames), camera_spec(), want=V.CALIBRATION_FRAMES,
                           tries=V.CALIBRATION_TRIES, intrinsics=intrinsics)  # fmt: skip
    assert len(cal.image_points) == len(FIDUCIALS) and cal.undistorted == (intrinsics is not None)
    markers = {mid: f"r{mid}" for mid in VIDEO_TRAJECTORIES}
    tracker = V.Tracker(camera_spec(), markers, cal, intrinsics=intrinsics)
    errs = []
    for i, frame in enumerate(frames):
        found = tracker.process(frame, label=str(i))
        assert set(found) == set(markers.values()), f"frame {i}: {sorted(found)}"
        for mid, fn in VIDEO_TRAJECTORIES.items():
            x, y, th = fn(i / VIDEO_FPS)
            fx, fy, fth = found[markers[mid]]
            errs.append((math.hypot(fx - x, fy - y), math.degrees(abs(wrap_angle(fth - th)))))
    return np.array(errs)


def test_video_of_three_robots_through_the_lens_matches_their_trajectories_with_intrinsics(
    lens_video, fitted
):
    """A video of three robots driving circles through the k₁ = −0.3 lens, decoded from MJPG and
    tracked as ``python -m tracker --source camera --video`` does (homography from the video's
    first frames, then frame by frame): with the intrinsics fitted to the ChArUco views every
    position is within 2 mm and every heading within 1° of the trajectory at the frame's
    time; without them the same video's positions are off by far more than 2 mm.  (Their
    headings stay within about 0.75°: a radial distortion shears a small marker but barely
    turns it, at most 0.62° anywhere in this arena by the lens model alone.)"""
    frames = _video_frames(lens_video)
    assert len(frames) == int(VIDEO_SECONDS * VIDEO_FPS)
    e1 = _track_video(frames, fitted)
    e0 = _track_video(frames, None)
    print(
        f"\nvideo, {len(e1)} poses: with intrinsics position max {e1[:, 0].max() * 1e3:.2f} mm, "
        f"heading max {e1[:, 1].max():.2f}°; without position max {e0[:, 0].max() * 1e3:.1f} mm, "
        f"heading max {e0[:, 1].max():.2f}°"
    )
    assert len(e1) == len(e0) == 3 * len(frames)
    assert e1[:, 0].max() < POS_TOL and e1[:, 1].max() < HEAD_TOL  # solved
    assert e0[:, 0].max() > 10 * POS_TOL  # the problem, on the same video


def test_calibration_refuses_too_few_views_no_board_poor_spread_and_mixed_sizes(board_frames, lens_cam):
    def refused(frames: list[np.ndarray]) -> str:
        with pytest.raises(I.IntrinsicsError) as e:
            I.calibrate_intrinsics(frames)
        msg = str(e.value)
        assert "\n" not in msg and msg.startswith(e.value.field + ": ")
        return msg

    assert "found in 5 of 5 frames; need at least 8 views" in refused(board_frames[:5])
    blank = np.full(IMAGE_SIZE[::-1], 128, np.uint8)
    assert "no ChArUco board 7×5 squares, DICT_5X5_50 found in 3 frames" in refused([blank] * 3)
    # Ten views, all near the image centre: the edges, where the distortion is, are never seen.
    b = I.DEFAULT_BOARD
    rng = np.random.default_rng(5)
    centre = []
    for i in range(10):
        a, c = rng.uniform(-0.4, 0.4, 2)
        R = cv2.Rodrigues(np.array([a, c, 0.0]))[0]
        t = np.array([0.0, 0.0, 1.1 + 0.02 * i]) - R @ np.array([b.size[0] / 2, b.size[1] / 2, 0.0])
        centre.append(board_view(lens_cam, b, R, t, seed=i))
    assert "cover" in refused(centre) and "every edge and corner" in refused(centre)
    small = cv2.resize(board_frames[1], (800, 600))
    assert "frames: frame 1 is 800×600 px" in refused([board_frames[0], small])


@pytest.mark.parametrize(
    "fit, reason",
    [
        ("raise", "fit: cv2.calibrateCamera failed: "),
        ("nan", "fit: the fit did not converge (non-finite parameters)"),
        ("singular", "fit: singular camera matrix"),
        ("rms", "fit: reprojection RMS 3.50 px exceeds 2 px (wrong board?)"),
        ("folds", "fit: the fitted lens model does not invert at the image edges (spread the views)"),
    ],
)
def test_calibration_refuses_a_failed_or_singular_fit_in_one_line(
    board_frames, monkeypatch, tmp_path, capsys, fit, reason
):
    """Good views, but ``cv2.calibrateCamera`` fails, diverges, returns a singular camera matrix
    or a poor RMS: one line naming the fit, and no intrinsics; ``fleet calibrate --intrinsics``
    prints that line and exits 2, writing nothing."""
    real = cv2.calibrateCameraExtended

    def fake(obj: Any, img: Any, size: Any, K: Any, D: Any) -> Any:
        if fit == "raise":
            raise cv2.error("OpenCV(5.0) calibration.cpp:1: error: (-215:Assertion failed) degenerate views")
        rms, K, D, *rest = real(obj, img, size, K, D)
        if fit == "nan":
            D = np.full_like(D, np.nan)
        elif fit == "singular":
            K = np.zeros_like(K)
        elif fit == "folds":  # a strong k₁ that the views near the centre alone could not rule out
            D = np.array([[-1.5, 0.0, 0.0, 0.0, 0.0]])
        else:
            rms = 3.5
        return (rms, K, D, *rest)

    monkeypatch.setattr(cv2, "calibrateCameraExtended", fake)
    with pytest.raises(I.IntrinsicsError) as e:
        I.calibrate_intrinsics(board_frames[:8])
    msg = str(e.value)
    assert "\n" not in msg and e.value.field == "fit" and msg.startswith(reason), msg
    if fit == "singular":
        paths = []
        for i, f in enumerate(board_frames[:8]):
            paths.append(str(tmp_path / f"view{i}.png"))
            cv2.imwrite(paths[-1], f)
        scn = write_scenario(tmp_path / "s.toml")
        assert calibrate_main([str(scn), "--intrinsics", "--image", *paths]) == 2
        cap = capsys.readouterr()
        assert cap.err == f"fleet: error: {reason}\n" and cap.out == "", cap
        assert not (tmp_path / "s.intrinsics.json").exists()


# --------------------------------------------------------------------------- files, schema, commands


def test_intrinsics_file_round_trips_and_bad_files_name_the_field(tmp_path, fitted):
    path = tmp_path / "lens.json"
    fitted.save(path)
    back = I.Intrinsics.load(path)
    assert np.allclose(back.K, fitted.K) and back.dist == fitted.dist and back.image_size == fitted.image_size
    d = json.loads(path.read_text())
    for mutate, reason in [
        (lambda d: d.update(distortion=[0.1, 0.2]), "distortion must be 5 finite numbers"),
        (lambda d: d.update(camera_matrix=[[0, 0, 1], [0, 1, 1], [0, 0, 1]]), "fx, fy > 0"),
        (lambda d: d.update(format="other"), "not a version 1"),
        (lambda d: d.pop("image_size"), "missing or malformed field"),
        (lambda d: d.update(image_size=[1e400, 1440]), "missing or malformed field (OverflowError)"),
        (lambda d: d.update(distortion=[-1.5, 0.0, 0.0, 0.0, 0.0]), "does not invert at the image edges"),
    ]:
        bad = json.loads(json.dumps(d))
        mutate(bad)
        path.write_text(json.dumps(bad))
        with pytest.raises(ConfigError) as e:
            I.Intrinsics.load(path)
        assert str(e.value).startswith("camera.intrinsics: ") and reason in str(e.value), str(e.value)
    with pytest.raises(ConfigError, match=r"camera\.intrinsics: .*no such file"):
        I.Intrinsics.load(tmp_path / "missing.json")


def test_camera_intrinsics_key_is_resolved_and_checked(tmp_path):
    scn = load_scenario(write_scenario(tmp_path / "s.toml", {"intrinsics": "cal/lens.json"}))
    assert scn.camera is not None and scn.camera.intrinsics == tmp_path / "cal" / "lens.json"
    assert load_scenario(write_scenario(tmp_path / "p.toml")).camera.intrinsics is None  # type: ignore[union-attr]
    for value, reason in [(3, "expected a string"), ("  ", "expected a non-empty file path")]:
        with pytest.raises(ConfigError) as e:
            load_scenario(write_scenario(tmp_path / "b.toml", {"intrinsics": value}))
        assert str(e.value).startswith("camera.intrinsics: ") and reason in str(e.value), str(e.value)


def test_tracker_refuses_a_homography_and_intrinsics_that_do_not_belong_together(lens_renderer, fitted):
    det = V.make_detector()
    fid_dets = [V.detect(lens_renderer.render({}, seed=0), det)]
    plain = V.calibrate(fid_dets, camera_spec().fiducials, IMAGE_SIZE)
    undist = V.calibrate(fid_dets, camera_spec().fiducials, IMAGE_SIZE, fitted)
    with pytest.raises(ConfigError, match=r"camera\.intrinsics: the homography was fitted without"):
        V.Tracker(camera_spec(), {1: "r1"}, plain, intrinsics=fitted)
    with pytest.raises(ConfigError, match=r"camera\.intrinsics: the homography was fitted with "):
        V.Tracker(camera_spec(), {1: "r1"}, undist)
    # Intrinsics of the same size but another lens calibration: the floor fit does not hold.
    other = dataclasses.replace(fitted, dist=(-0.15, *fitted.dist[1:]))
    with pytest.raises(ConfigError, match=r"camera\.intrinsics: the homography was fitted through other"):
        V.Tracker(camera_spec(), {1: "r1"}, undist, intrinsics=other)
    V.Tracker(camera_spec(), {1: "r1"}, undist, intrinsics=fitted)  # its own: accepted


def test_fleet_calibrate_intrinsics_from_images_and_video_then_the_floor(
    tmp_path, board_frames, lens_renderer, capsys
):
    paths = []
    for i, f in enumerate(board_frames):
        paths.append(str(tmp_path / f"view{i:02d}.png"))
        cv2.imwrite(paths[-1], f)
    scn = write_scenario(tmp_path / "s.toml", {"intrinsics": "lens.json", "homography": "h.json"})
    assert calibrate_main([str(scn), "--intrinsics", "--image", *paths]) == 0
    out = capsys.readouterr().out
    assert out.startswith(f"wrote {tmp_path / 'lens.json'}: {VIEWS} views, reprojection RMS"), out
    lens = I.Intrinsics.load(tmp_path / "lens.json")
    assert lens.rms < 0.5 and abs(lens.dist[0] - LENS[0]) < 0.05
    # The floor homography: without intrinsics, a fiducial predicted by the others is off by
    # tens of mm; with them it is fitted on undistorted fiducials and the error is sub-mm.
    floor = tmp_path / "floor.png"
    cv2.imwrite(str(floor), lens_renderer.render({}, seed=3))
    bare = write_scenario(tmp_path / "bare.toml", {"homography": "bare.json"})
    assert calibrate_main([str(bare), "--image", str(floor)]) == 0
    out = capsys.readouterr().out
    assert "lens distortion not corrected" in out, out
    bare_mm = float(re.search(r"largest floor error over fiducials ([0-9.]+) mm", out)[1])  # type: ignore[index]
    assert calibrate_main([str(scn), "--image", str(floor)]) == 0
    out = capsys.readouterr().out
    assert "on undistorted fiducials" in out, out
    lens_mm = float(re.search(r"largest floor error over fiducials ([0-9.]+) mm", out)[1])  # type: ignore[index]
    rec = float(re.search(r"recommended controller.pose_noise\[0\] >= ([0-9.]+) m", out)[1])  # type: ignore[index]
    print(
        f"\nheld-out fiducial error: without intrinsics {bare_mm:.2f} mm, with {lens_mm:.2f} mm; "
        f"pose_noise {rec}"
    )
    assert bare_mm > 10.0 and lens_mm < 1.0 and lens_mm / 1000 + 0.5e-3 <= rec < lens_mm / 1000 + 0.6e-3
    cal = V.Calibration.load(tmp_path / "h.json")
    assert cal.undistorted and cal.rms_error < 0.5e-3
    # From a video file too.
    video = tmp_path / "board.avi"
    w = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 5.0, IMAGE_SIZE, True)
    for f in board_frames:
        w.write(cv2.cvtColor(f, cv2.COLOR_GRAY2BGR))
    w.release()
    assert (
        calibrate_main([str(scn), "--intrinsics", "--video", str(video), "--out", str(tmp_path / "v.json")])
        == 0
    )
    assert I.Intrinsics.load(tmp_path / "v.json").rms < 0.5
    capsys.readouterr()


def test_fleet_calibrate_intrinsics_bad_input_exits_2_with_one_line(tmp_path, board_frames, capsys):
    scn = write_scenario(tmp_path / "s.toml")
    few = []
    for i, f in enumerate(board_frames[:3]):
        few.append(str(tmp_path / f"few{i}.png"))
        cv2.imwrite(few[-1], f)
    blank = tmp_path / "blank.png"
    cv2.imwrite(str(blank), np.full(IMAGE_SIZE[::-1], 128, np.uint8))
    text = tmp_path / "notes.avi"
    text.write_text("not a video")
    cases = [
        ([str(scn), "--intrinsics", "--image", *few], "frames: ", "found in 3 of 3 frames; need at least 8"),
        ([str(scn), "--intrinsics", "--image", str(blank)], "frames: ", "no ChArUco board"),
        ([str(scn), "--intrinsics", "--image", str(tmp_path / "nope.png")], "--image: ", "no such file"),
        ([str(scn), "--intrinsics", "--video", str(text)], "--video: ", "cannot open"),
        ([str(scn), "--intrinsics", "--device", "0"], "--device: ", "video file or image files"),
        ([str(scn), "--image", *few], "--image: ", "takes one image"),
    ]
    for argv, field, reason in cases:
        assert calibrate_main(argv) == 2, argv
        cap = capsys.readouterr()
        assert cap.err.count("\n") == 1 and cap.err.startswith(f"fleet: error: {field}"), cap.err
        assert reason in cap.err, cap.err
    assert not (tmp_path / "s.intrinsics.json").exists()


def test_printed_charuco_board_is_the_board_at_exact_size(tmp_path, capsys):
    """The print, rasterised at 200 dpi, is found by OpenCV's ChArUco detector with all its
    inner corners, 30 mm apart to 0.5 %; ``fleet markers --charuco`` writes it as a PDF."""
    dpi = 200
    fig = charuco_figure(I.DEFAULT_BOARD, "a4")
    fig.set_dpi(dpi)
    fig.canvas.draw()
    image = np.asarray(fig.canvas.buffer_rgba())[:, :, 0].copy()  # type: ignore[attr-defined]
    corners, ids, _, _ = cv2.aruco.CharucoDetector(I.DEFAULT_BOARD.board()).detectBoard(image)
    cols, rows = I.DEFAULT_BOARD.squares
    assert ids is not None and len(ids) == (cols - 1) * (rows - 1)
    c = corners.reshape(rows - 1, cols - 1, 2)
    step = np.linalg.norm(np.diff(c, axis=1), axis=2)
    expected = I.DEFAULT_BOARD.square / 0.0254 * dpi
    assert np.abs(step / expected - 1).max() < 0.005
    scn = write_scenario(tmp_path / "s.toml")
    out = tmp_path / "board.pdf"
    assert markers_main([str(scn), "--charuco", "--out", str(out)]) == 0
    assert out.read_bytes().startswith(b"%PDF") and "ChArUco board 7 × 5" in capsys.readouterr().out
