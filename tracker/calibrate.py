"""``fleet calibrate SCENARIO.toml (--image F | --video F | --device N) [--out FILE] [--frames N]``

Fits the floor-plane homography of the camera tracker (image px → world m)
to the scenario's ``[camera]`` fiducials and writes it as JSON: the 3×3
``homography``, per fiducial id its image centre ``image_px``, its world
position ``world_m`` and its reprojection error ``error_m``, the RMS and
largest reprojection errors [m], the image size [px], the frames averaged,
the source and a UTC timestamp.  With a video or a device, each fiducial's
image centre is averaged over up to ``--frames`` frames (at most
:data:`tracker.vision.CALIBRATION_TRIES` are read).

The output goes to ``--out``, else to ``camera.homography`` (relative to the
scenario file), else next to the scenario as ``<stem>.homography.json``.
Exit codes: 0 written; 1 the RMS error exceeds ``camera.position_noise``
(nothing written); 2 bad input, with one line ``fleet: error: <field>:
<reason>``.
"""

from __future__ import annotations

import argparse
import itertools
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from ground.scenario import ConfigError, Scenario, load_scenario
from tracker.vision import CALIBRATION_FRAMES, CALIBRATION_TRIES, OPENCV_MISSING, calibrate_from, quiet_opencv

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm", ".webp")
"""File suffixes that :func:`calibrate` reads as a still image rather than a video."""


def add_arguments(ap: argparse.ArgumentParser) -> None:
    """The arguments of ``fleet calibrate`` (for a subcommand parser)."""
    ap.add_argument("scenario", help="scenario TOML with a [camera] table")
    src = ap.add_mutually_exclusive_group(required=True)
    src.add_argument("--image", help="a still image of the fiducials")
    src.add_argument("--video", help="a video file of the fiducials")
    src.add_argument("--device", type=int, help="video device N (/dev/videoN)")
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
        cal = calibrate_from(iter([image]), scn.camera, want=1, tries=1)
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
            cal = calibrate_from(frames_in, scn.camera, want=want, tries=CALIBRATION_TRIES)
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
    if args.image is not None:
        source: str | int = args.image
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
    out = Path(args.out) if args.out is not None else default_out(load_scenario(args.scenario))
    print(
        f"wrote {out}: {len(cal.image_points)} fiducials over {cal.frames} frame(s), "
        f"reprojection RMS {cal.rms_error * 1000:.3f} mm, max {cal.max_error * 1000:.3f} mm"
    )
    if len(cal.image_points) == 4:
        print(
            "fleet calibrate: note: 4 fiducials fix a homography exactly, so the RMS is 0 by construction "
            "and measures nothing; place 5 or more to check the calibration",
            file=sys.stderr,
        )
    return 0


def main(argv: list[str] | None = None) -> int:
    """``fleet calibrate``'s entry point; returns the exit code."""
    ap = argparse.ArgumentParser(prog="fleet calibrate", description=__doc__.splitlines()[0].strip("`"))
    add_arguments(ap)
    return run(ap.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
