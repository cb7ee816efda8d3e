"""``fleet calibrate SCENARIO.toml (--image F | --video F | --device N) [--out FILE] [--frames N]``
``fleet calibrate SCENARIO.toml --intrinsics (--image F [F ...] | --video F) [--out FILE]``

Floor homography (first form).  Fits the floor-plane homography of the camera tracker (image px → world m)
to the scenario's ``[camera]`` fiducials and writes it as JSON: the 3×3
``homography``, per fiducial id its image centre ``image_px``, its world
position ``world_m`` and its reprojection error ``error_m``, the RMS and
largest reprojection errors [m], the image size [px], the frames averaged,
the source and a UTC timestamp.  With a video or a device, each fiducial's
image centre is averaged over up to ``--frames`` frames (at most
:data:`tracker.vision.CALIBRATION_TRIES` are read).

The output goes to ``--out``, else to ``camera.homography`` (relative to the
scenario file), else next to the scenario as ``<stem>.homography.json``.
With 5 or more fiducials it also prints the largest floor error over the
fiducials, each predicted by a homography fitted without it, and a recommended
``controller.pose_noise[0]``: that error plus :data:`DETECTION_ERROR`.

With ``camera.intrinsics`` in the scenario, the fiducial corners are undistorted
first and the file says so (``"undistorted": true``); the tracker then needs the
same intrinsics.

Lens intrinsics (``--intrinsics``).  Fits the camera matrix and the lens
distortion (:mod:`tracker.intrinsics`) to views of the ChArUco board that
``fleet markers --charuco`` prints (:data:`tracker.intrinsics.DEFAULT_BOARD`),
from image files or the frames of a video: hold the board at 8 or more places
and angles, near every edge and corner of the image.  It prints the
reprojection RMS [px] and the worst view, and writes the JSON to ``--out``,
else to ``camera.intrinsics``, else next to the scenario as
``<stem>.intrinsics.json``.  Too few views, no board, a poor spread or a
failed fit: one line and exit 2.

Exit codes: 0 written; 1 the RMS error exceeds ``camera.position_noise``
(nothing written); 2 bad input, with one line ``fleet: error: <field>:
<reason>``.
"""

from __future__ import annotations

import argparse
import itertools
import math
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from ground.scenario import ConfigError, Scenario, load_scenario
from tracker.intrinsics import DEFAULT_BOARD, Intrinsics, IntrinsicsError, calibrate_intrinsics
from tracker.vision import CALIBRATION_FRAMES, CALIBRATION_TRIES, OPENCV_MISSING, calibrate_from, quiet_opencv

DETECTION_ERROR = 0.5e-3
"""Position error of a single marker detection [m] added to the floor error in the recommended
``pose_noise``: the tracker erred by up to 0.4 mm on synthetic frames (``tracker/vision.py``)."""
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm", ".webp")
"""File suffixes that :func:`calibrate` reads as a still image rather than a video."""


def add_arguments(ap: argparse.ArgumentParser) -> None:
    """The arguments of ``fleet calibrate`` (for a subcommand parser)."""
    ap.add_argument("scenario", help="scenario TOML with a [camera] table")
    src = ap.add_mutually_exclusive_group(required=True)
    src.add_argument(
        "--image", nargs="+", help="a still image of the fiducials (--intrinsics: images of the board)"
    )
    src.add_argument("--video", help="a video file of the fiducials")
    src.add_argument("--device", type=int, help="video device N (/dev/videoN)")
    ap.add_argument(
        "--intrinsics", action="store_true",
        help="calibrate the lens (camera matrix, distortion) from views of the ChArUco board instead",
    )  # fmt: skip
    ap.add_argument("--out", help="output JSON (default: camera.homography, else <scenario>.homography.json)")
    ap.add_argument(
        "--frames", type=int, default=CALIBRATION_FRAMES,
        help=f"video/device: frames to average (default {CALIBRATION_FRAMES})",
    )  # fmt: skip


def default_out(scn: Scenario) -> Path:
    """Where the calibration goes without ``--out``."""
    if scn.camera is not None and scn.camera.homography is not None:
        return scn.camera.homography
    src = Path(scn.source)
    return src.with_name(src.stem + ".homography.json")


def default_intrinsics_out(scn: Scenario) -> Path:
    """Where the intrinsics go without ``--out``."""
    if scn.camera is not None and scn.camera.intrinsics is not None:
        return scn.camera.intrinsics
    src = Path(scn.source)
    return src.with_name(src.stem + ".intrinsics.json")


def _read_images(paths: list[str]) -> Iterator[Any]:
    cv2 = __import__("cv2")
    for name in paths:
        path = Path(name)
        if not path.is_file():
            raise ConfigError("--image", f"{path}: no such file")
        image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if image is None:
            raise ConfigError("--image", f"{path}: not a readable image")
        yield image


def _read_video(path: Path) -> Iterator[Any]:
    cv2 = __import__("cv2")
    if not path.is_file():
        raise ConfigError("--video", f"{path}: no such file")
    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise ConfigError("--video", f"{path}: cannot open")
    try:
        while True:
            ok, image = cap.read()
            if not ok:
                return
            yield image
    finally:
        cap.release()


def calibrate_lens(
    scenario_path: str | Path, images: list[str] | None = None, video: str | Path | None = None,
    out_path: str | Path | None = None,
) -> tuple[Intrinsics, Path]:  # fmt: skip
    """Fit the lens intrinsics to the ChArUco views in ``images`` (paths) or ``video`` (a
    path) and write them (``out_path``, see :func:`default_intrinsics_out`); returns them
    and where they went.  Raises :class:`ConfigError` for bad input and
    :class:`tracker.intrinsics.IntrinsicsError` when no trustworthy fit can be made."""
    scn = load_scenario(scenario_path)
    frames = _read_images(images) if images is not None else _read_video(Path(str(video)))
    cal = calibrate_intrinsics(frames, DEFAULT_BOARD)
    out = Path(out_path) if out_path is not None else default_intrinsics_out(scn)
    b = DEFAULT_BOARD
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        cal.save(out, source=str(video) if video is not None else list(images or []),
                 board={"squares": list(b.squares), "square_m": b.square, "marker_m": b.marker,
                        "dictionary": b.dictionary})  # fmt: skip
    except OSError as e:
        raise ConfigError("--out", f"{out}: cannot write ({e.strerror or e})") from None
    return cal, out


def _frames(cap: Any, video: bool, limit: int) -> Iterator[Any]:
    """Up to ``limit`` frames of an opened capture (None for a failed device read;
    a failed read ends a video)."""
    for _ in range(limit):
        ok, image = cap.read()
        if not ok and video:
            return
        yield image if ok else None


def calibrate(
    scenario_path: str | Path,
    source: str | Path | int,
    out_path: str | Path | None = None,
    *,
    frames: int | None = None,
    kind: str | None = None,
) -> Any:
    """Fit and write the homography of ``scenario_path``'s camera; returns the
    :class:`tracker.vision.Calibration`.

    ``source``: a device index (int), or the path of an image (suffix in
    :data:`IMAGE_SUFFIXES`) or a video; ``kind`` ("image" | "video" |
    "device") overrides the guess.  ``frames``: video/device frames to
    average (default :data:`tracker.vision.CALIBRATION_FRAMES`).
    ``out_path``: see :func:`default_out`.  Raises :class:`ConfigError` for
    bad input (no OpenCV, no ``[camera]`` table, an unreadable source, too few
    fiducials seen)."""
    try:
        import cv2
    except ImportError:
        raise ConfigError("camera", OPENCV_MISSING) from None
    scn = load_scenario(scenario_path)
    if scn.camera is None:
        raise ConfigError("camera", "missing [camera] table (fiducials and their positions)")
    want = CALIBRATION_FRAMES if frames is None else frames
    if want < 1:
        raise ConfigError("--frames", f"must be >= 1, got {want}")
    if kind is None:
        if isinstance(source, int):
            kind = "device"
        else:
            kind = "image" if Path(source).suffix.lower() in IMAGE_SUFFIXES else "video"
    if kind not in ("image", "video", "device"):
        raise ConfigError("kind", f"unknown source kind {kind!r} (expected image, video or device)")
    field = f"--{kind}"
    intrinsics = Intrinsics.load(scn.camera.intrinsics) if scn.camera.intrinsics is not None else None
    if kind == "device":
        if isinstance(source, bool) or not isinstance(source, int) or source < 0:
            raise ConfigError(field, f"expected a device index >= 0, got {source!r}")
        cap = cv2.VideoCapture(source)
        described = f"device {source}"
    else:
        path = Path(str(source))
        if not path.is_file():
            raise ConfigError(field, f"{path}: no such file")
        described = str(path)
    if kind == "image":
        image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if image is None:
            raise ConfigError(field, f"{path}: not a readable image")
        cal = calibrate_from(iter([image]), scn.camera, want=1, tries=1, intrinsics=intrinsics)
    else:
        if kind == "video":
            cap = cv2.VideoCapture(str(path))
        if not cap.isOpened():
            raise ConfigError(field, f"{described}: cannot open")
        try:
            ok, first = cap.read()
            if not ok or first is None:
                raise ConfigError(field, f"{described}: no frame could be read")
            frames_in = itertools.chain([first], _frames(cap, kind == "video", CALIBRATION_TRIES - 1))
            cal = calibrate_from(
                frames_in, scn.camera, want=want, tries=CALIBRATION_TRIES, intrinsics=intrinsics
            )
        finally:
            cap.release()
    out = Path(out_path) if out_path is not None else default_out(scn)
    bound = scn.camera.position_noise
    if bound is not None and cal.rms_error > bound:
        raise CalibrationTooCoarse(
            "camera.position_noise",
            f"reprojection RMS {cal.rms_error * 1000:.2f} mm exceeds the bound {bound * 1000:.2f} mm; "
            f"{out} not written",
        )
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        cal.save(out, source=described, scenario=str(scenario_path), dictionary=scn.camera.dictionary)
    except OSError as e:
        raise ConfigError("--out", f"{out}: cannot write ({e.strerror or e})") from None
    return cal


class CalibrationTooCoarse(ConfigError):
    """The fit worked but is worse than ``camera.position_noise`` (exit 1, not 2)."""


def run(args: argparse.Namespace) -> int:
    """``fleet calibrate`` on parsed arguments (see :func:`add_arguments`); returns the exit code."""
    try:
        import cv2
    except ImportError:
        print(f"fleet: error: {OPENCV_MISSING}", file=sys.stderr)
        return 2
    quiet_opencv(cv2)
    if args.intrinsics:
        return _run_intrinsics(args)
    if args.image is not None:
        if len(args.image) != 1:
            msg = "the floor homography takes one image (several only with --intrinsics)"
            print(f"fleet: error: --image: {msg}", file=sys.stderr)
            return 2
        source: str | int = args.image[0]
        kind = "image"
    elif args.video is not None:
        source, kind = args.video, "video"
    else:
        source, kind = args.device, "device"
    try:
        cal = calibrate(args.scenario, source, args.out, frames=args.frames, kind=kind)
    except CalibrationTooCoarse as e:
        print(f"fleet: error: {e}", file=sys.stderr)
        return 1
    except ConfigError as e:
        print(f"fleet: error: {e}", file=sys.stderr)
        return 2
    scn = load_scenario(args.scenario)
    out = Path(args.out) if args.out is not None else default_out(scn)
    lens = (
        "on undistorted fiducials"
        if cal.undistorted
        else "lens distortion not corrected (no camera.intrinsics)"
    )
    print(
        f"wrote {out}: {len(cal.image_points)} fiducials over {cal.frames} frame(s), "
        f"reprojection RMS {cal.rms_error * 1000:.3f} mm, max {cal.max_error * 1000:.3f} mm; {lens}"
    )
    held = cal.holdout_errors()
    if held:
        worst = max(held, key=lambda i: held[i])
        rec = math.ceil((held[worst] + DETECTION_ERROR) * 1e4) / 1e4
        print(
            f"largest floor error over fiducials {held[worst] * 1000:.2f} mm (fiducial {worst}, fitted "
            f"without it); recommended controller.pose_noise[0] >= {rec:.4f} m "
            f"(that + {DETECTION_ERROR * 1000:.1f} mm marker detection), "
            f"now {scn.controller.pose_noise[0]:g} m"
        )
    if len(cal.image_points) == 4:
        print(
            "fleet calibrate: note: 4 fiducials fix a homography exactly, so the RMS is 0 by construction "
            "and measures nothing; place 5 or more to check the calibration",
            file=sys.stderr,
        )
    return 0


def _run_intrinsics(args: argparse.Namespace) -> int:
    """``fleet calibrate --intrinsics``; returns the exit code."""
    if args.device is not None:
        print("fleet: error: --device: --intrinsics reads a video file or image files", file=sys.stderr)
        return 2
    try:
        cal, out = calibrate_lens(args.scenario, args.image, args.video, args.out)
    except (ConfigError, IntrinsicsError) as e:
        print(f"fleet: error: {e}", file=sys.stderr)
        return 2
    worst = int(np.argmax(cal.view_errors)) if cal.view_errors else 0
    k1, k2, p1, p2, k3 = cal.dist
    print(
        f"wrote {out}: {len(cal.view_errors)} views, reprojection RMS {cal.rms:.3f} px "
        f"(worst view: frame {cal.frames[worst] if cal.frames else '?'}, "
        f"{max(cal.view_errors, default=0.0):.3f} px); f = ({cal.K[0, 0]:.1f}, {cal.K[1, 1]:.1f}) px, "
        f"c = ({cal.K[0, 2]:.1f}, {cal.K[1, 2]:.1f}) px, k1 {k1:+.4f}, k2 {k2:+.4f}, p1 {p1:+.5f}, "
        f"p2 {p2:+.5f}, k3 {k3:+.4f}"
    )
    return 0


def main(argv: list[str] | None = None) -> int:
    """``fleet calibrate``'s entry point; returns the exit code."""
    ap = argparse.ArgumentParser(prog="fleet calibrate", description=__doc__.splitlines()[0].strip("`"))
    add_arguments(ap)
    return run(ap.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
