"""Robot poses from an overhead camera's image: ArUco detection and the floor homography.

The fiducials' centres, at known world positions p_j [m], and their image centres q_j [px] give
the plane homography H (3×3, image px → world m, :func:`fit_homography`, least squares over ≥ 4
fiducials).  A robot marker's four image corners c_0..c_3 (ArUco order: corner 0 at the
marker's top left, corner 0 → 1 along its x axis) map to w_i = H(c_i) on the plane.  Then

* marker centre  m = mean(w_0..w_3)  (exact for a square under any homography, unlike H
  applied to the image centroid, which is biased under perspective);
* heading  θ = atan2 of d = (w_1 − w_0) + (w_2 − w_3) + R(−90°)[(w_0 − w_3) + (w_1 − w_2)],
  the mean of the two x edges and the two y edges turned onto x, world frame,
  counter-clockwise from +x;
* axle centre  (x, y) = m − R(θ)·o, o = ``camera.marker_offset`` (robot frame).

Corners come from OpenCV's detector with CORNER_REFINE_SUBPIX, then :func:`refine_edges` fits
straight lines to the four outer edges.  The homography maps the plane of the fiducials; robot
markers must lie in that plane (see :class:`ground.scenario.CameraSpec`).  With the camera's
intrinsics (``camera.intrinsics``, :mod:`tracker.intrinsics`) the corners are undistorted
(points, not frames) before the homography and the heading, and the homography is fitted to
undistorted fiducial centres; without them a lens's distortion goes straight into the poses
(at k₁ = −0.3, tens of mm towards the image edges) and the tracker says so once.
Markers should span ≥ 18 px in the image (3 px per bit for 4×4): at 14–22 px about 1 % of them were missed.

Accuracy on synthetic frames (``tests/tracker/test_camera.py``: 1600×1200 px, 30° oblique view, 5 cm
markers of 18–28 px, Gaussian blur σ 0.8 px, noise σ 2 grey levels, fitted homography):
position error ≤ 0.4 mm, heading ≤ 0.7°.

:class:`Tracker` turns one frame into poses, and counts what it could not use: a missing marker
(a *gap*), an unknown id, an unreadable frame, an id seen twice, a detection whose size or
handedness on the plane is implausible.  The camera process (:mod:`tracker.camera`) and
``fleet calibrate`` (:mod:`camera_tools.calibrate`) use it.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import json
import math
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ground.scenario import CameraSpec, ConfigError, Fiducial, Scenario
from tracker.intrinsics import Intrinsics, read_json

OPENCV_MISSING = "camera source needs OpenCV: pip install 'epuck-fleet[camera]'"
"""What a camera command says when OpenCV (the ``[camera]`` extra) is not installed."""
CALIBRATION_FRAMES = 10
"""Frames whose fiducial centres are averaged for a calibration."""
CALIBRATION_TRIES = 100
"""Frames read at most while looking for the fiducials."""
SIZE_TOLERANCE = 0.25
"""A marker whose mean side on the plane is off ``marker_size`` by more than
this fraction is rejected as implausible."""
HOMOGRAPHY_FORMAT = "epuck-fleet homography"
"""The ``format`` field of a calibration file."""


class BadFrame(ValueError):
    """A frame that cannot be used (missing, empty, wrong type or shape, undecodable)."""


def cv2_module() -> Any:
    """OpenCV, imported when first needed (the ``[camera]`` extra)."""
    import cv2

    return cv2


# --------------------------------------------------------------------------- detection


def make_detector(dictionary: str = "DICT_4X4_50") -> Any:
    """An ``cv2.aruco.ArucoDetector`` for ``dictionary`` with sub-pixel corner refinement.

    Bits are read from the central 40 % of each cell, sampled at 8 px per cell.
    On 240 synthetic 5 cm markers of 14–22 px (30° oblique view, blur, noise,
    JPEG) OpenCV's defaults (13 % margin, 4 px per cell) missed 8 and these
    settings 2; at 18–28 px neither missed any."""
    cv2 = cv2_module()
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    params.perspectiveRemovePixelPerCell = 8
    params.perspectiveRemoveIgnoredMarginPerCell = 0.3
    return cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary)), params)


def _gray(image: object) -> np.ndarray:
    """A uint8 grey image (H, W) from a grey (H, W), (H, W, 1), BGR or BGRA frame; BadFrame otherwise."""
    if image is None:
        raise BadFrame("no image")
    if not isinstance(image, np.ndarray):
        raise BadFrame(f"expected an image array, got {type(image).__name__}")
    if image.dtype != np.uint8:
        raise BadFrame(f"expected 8-bit pixels, got dtype {image.dtype}")
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim == 2:
        if min(image.shape) < 8:
            raise BadFrame(f"image of {image.shape[1]}×{image.shape[0]} px is too small")
        return image
    if image.ndim == 3 and image.shape[2] in (3, 4):
        if min(image.shape[:2]) < 8:
            raise BadFrame(f"image of {image.shape[1]}×{image.shape[0]} px is too small")
        cv2 = cv2_module()
        code = cv2.COLOR_BGR2GRAY if image.shape[2] == 3 else cv2.COLOR_BGRA2GRAY
        return np.asarray(cv2.cvtColor(image, code))
    raise BadFrame(f"expected a grey or BGR image, got shape {image.shape}")


def refine_edges(gray: np.ndarray, corners: np.ndarray, bits: int = 6, iterations: int = 2) -> np.ndarray:
    """Corners (4, 2) [px] re-estimated as the intersections of straight lines fitted to
    the marker's four outer edges.

    Along the middle 70 % of each edge, the grey profile across the edge
    (half a bit in and out, at 0.25 px, bilinear) gives the point where it
    crosses halfway between the black border and the white quiet zone; a
    total-least-squares line through those points is the edge.  ``bits`` is the
    marker's side in cells, black border included (6 for 4×4).  Measured on
    60 synthetic markers (30° oblique view, blur σ 0.8 px, noise σ 2, exact
    homography), largest errors with CORNER_REFINE_SUBPIX alone → with this:
    1280×960 px (markers 14–22 px) corner 1.42 → 0.65 px, heading 2.5° → 0.84°,
    position 1.1 → 0.3 mm; 1600×1200 px corner 2.1 → 0.40 px, heading 3.3° →
    0.46°, position 1.4 → 0.22 mm.  Returns the input corners when an edge
    lacks contrast (no quiet zone) or a corner would move by more than
    max(1 bit, 2 px)."""
    cv2 = cv2_module()
    start = np.asarray(corners, dtype=float).reshape(4, 2)
    c = start.copy()
    img = np.asarray(gray, dtype=np.float32)
    side = float(np.mean(np.linalg.norm(c - np.roll(c, -1, axis=0), axis=1)))
    bit = side / bits
    reach = float(np.clip(0.5 * bit, 1.0, 4.0))
    offs = np.arange(-reach, reach + 1e-9, 0.25)
    for _ in range(iterations):
        lines = []
        for i in range(4):
            a, b = c[i], c[(i + 1) % 4]
            e = b - a
            length = float(np.linalg.norm(e))
            if length < 4.0:
                return start
            n = np.array([e[1], -e[0]]) / length  # outward: corners run clockwise in the image
            s = np.linspace(0.15, 0.85, max(6, int(length)))
            base = a + s[:, None] * e
            pts = (base[:, None, :] + offs[None, :, None] * n).astype(np.float32)
            prof = cv2.remap(img, pts[..., 0], pts[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            lo, hi = prof[:, :2].mean(axis=1), prof[:, -2:].mean(axis=1)
            mid = (lo + hi) / 2.0
            above = prof >= mid[:, None]
            k = np.argmax(above, axis=1)
            ok = (hi - lo > 20.0) & (k > 0) & above.any(axis=1)
            if ok.sum() < 3:
                return start
            rows = np.flatnonzero(ok)
            k = k[rows]
            p0, p1 = prof[rows, k - 1], prof[rows, k]
            frac = (mid[rows] - p0) / np.maximum(p1 - p0, 1e-6)
            d = offs[k - 1] + frac * (offs[k] - offs[k - 1])
            g = base[rows] + d[:, None] * n
            mu = g.mean(axis=0)
            _, _, vt = np.linalg.svd(g - mu)
            lines.append((mu, vt[0]))
        new = np.empty_like(c)
        for i in range(4):
            (p1_, d1), (p2_, d2) = lines[(i - 1) % 4], lines[i]
            A = np.column_stack([d1, -d2])
            if abs(np.linalg.det(A)) < 1e-6:
                return start
            st = np.linalg.solve(A, p2_ - p1_)
            new[i] = p1_ + st[0] * d1
        c = new
    if np.max(np.linalg.norm(c - start, axis=1)) > max(bit, 2.0):
        return start
    return c


def detect_markers(image: object, detector: Any, refine: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """All markers in ``image``: ids (N,) int and corners (N, 4, 2) [px, image frame,
    ArUco order], duplicates kept; ``refine``: :func:`refine_edges` on each.
    Raises :class:`BadFrame` for an unusable image."""
    cv2 = cv2_module()
    gray = _gray(image)
    try:
        corners, ids, _ = detector.detectMarkers(gray)
    except cv2.error as e:  # OpenCV rejects the frame: report it, do not guess
        raise BadFrame(f"detector failed: {str(e).strip().splitlines()[-1]}") from None
    if ids is None or len(corners) == 0:
        return np.zeros(0, dtype=int), np.zeros((0, 4, 2))
    flat = np.asarray(ids).reshape(-1).astype(int)  # (N,) in OpenCV 5, (N, 1) in 4.x
    pts = np.asarray([np.asarray(c, dtype=float).reshape(4, 2) for c in corners])
    if refine:
        bits = int(detector.getDictionary().markerSize) + 2
        pts = np.asarray([refine_edges(gray, p, bits) for p in pts])
    return flat, pts


def detect(
    image: object, detector: Any = None, dictionary: str = "DICT_4X4_50", refine: bool = True
) -> dict[int, np.ndarray]:
    """Markers in ``image`` (grey or BGR uint8): id → corners (4, 2) [px, image frame,
    ArUco order].  An id seen more than once is left out (ambiguous).  Raises
    :class:`BadFrame` for an unusable image."""
    det = detector if detector is not None else make_detector(dictionary)
    ids, pts = detect_markers(image, det, refine)
    uniq, counts = np.unique(ids, return_counts=True)
    once = {int(u) for u, c in zip(uniq, counts, strict=True) if c == 1}
    return {int(i): p for i, p in zip(ids, pts, strict=True) if int(i) in once}


def image_centre(corners: np.ndarray) -> np.ndarray:
    """Image (2,) [px] of a marker's centre: the intersection of the diagonals of its
    corners (4, 2) [px], exact under perspective (the centroid is not)."""
    c = np.asarray(corners, dtype=float).reshape(4, 2)
    d1, d2 = c[2] - c[0], c[3] - c[1]
    den = d1[0] * d2[1] - d1[1] * d2[0]
    if abs(den) < 1e-12:
        return np.asarray(c.mean(axis=0))
    r = c[1] - c[0]
    s = (r[0] * d2[1] - r[1] * d2[0]) / den
    return np.asarray(c[0] + s * d1)


# --------------------------------------------------------------------------- homography


def to_plane(H: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply the homography H (3, 3) to points (N, 2) [px]: their plane points (N, 2)
    [m, world frame].  Raises ValueError for a point on the horizon line."""
    p = np.asarray(points, dtype=float).reshape(-1, 2)
    q = np.column_stack([p, np.ones(len(p))]) @ np.asarray(H, dtype=float).T
    if np.any(np.abs(q[:, 2]) < 1e-12):
        raise ValueError("point on the homography's horizon line")
    return np.asarray(q[:, :2] / q[:, 2:3])


@dataclass(frozen=True)
class Calibration:
    """A fitted floor-plane homography with the points it was fitted to."""

    H: np.ndarray = field(compare=False)
    """Homography (3, 3), image px (u right, v down, pixel centres at integers) →
    world plane m, normalised so ``H[2, 2] = 1``."""
    image_points: dict[int, tuple[float, float]]
    """Fiducial id → image centre (u, v) [px] used in the fit."""
    world_points: dict[int, tuple[float, float]]
    """Fiducial id → world position (x, y) [m] used in the fit."""
    rms_error: float
    """Root mean square of |H(q_j) − p_j| over the fiducials [m]."""
    max_error: float
    """Largest |H(q_j) − p_j| [m]."""
    image_size: tuple[int, int]
    """Image (width, height) [px] the homography belongs to."""
    frames: int = 1
    """Frames whose fiducial centres were averaged."""
    undistorted: bool = False
    """The image points are undistorted through the camera's intrinsics (ideal pinhole px),
    so H must be applied to undistorted points."""
    lens: str = ""
    """:meth:`Intrinsics.fingerprint` of those intrinsics ("" when not undistorted)."""

    def errors(self) -> dict[int, float]:
        """Fiducial id → reprojection error |H(q_j) − p_j| [m]."""
        ids = sorted(self.image_points)
        q = np.array([self.image_points[i] for i in ids], dtype=float).reshape(-1, 2)
        p = np.array([self.world_points[i] for i in ids], dtype=float).reshape(-1, 2)
        e = np.linalg.norm(to_plane(self.H, q) - p, axis=1)
        return {i: float(x) for i, x in zip(ids, e, strict=True)}

    def holdout_errors(self) -> dict[int, float]:
        """Fiducial id → |H₋ⱼ(q_j) − p_j| [m], H₋ⱼ fitted without fiducial j: the floor error
        at a place the fit did not see (empty with fewer than 5 fiducials).  Unlike the
        reprojection error, it grows with what the homography cannot model (lens distortion,
        a fiducial off the plane)."""
        ids = sorted(self.image_points)
        if len(ids) < 5:
            return {}
        out: dict[int, float] = {}
        for j in ids:
            rest = [i for i in ids if i != j]
            try:
                cal = fit_homography(
                    {i: self.image_points[i] for i in rest},
                    {i: self.world_points[i] for i in rest},
                    self.image_size,
                )
                e = to_plane(cal.H, np.array([self.image_points[j]], dtype=float))[0] - self.world_points[j]
            except (ConfigError, ValueError):
                continue  # the others are degenerate on their own
            out[j] = float(np.linalg.norm(e))
        return out

    def to_json(self, **meta: Any) -> dict[str, Any]:
        """The calibration file's content (``meta``: extra top-level fields)."""
        errs = self.errors()
        return {
            "format": HOMOGRAPHY_FORMAT,
            "version": 1,
            "homography": [[float(v) for v in row] for row in self.H],
            "homography_maps": "image px (u right, v down, pixel centres at integers) -> world m",
            "image_size": list(self.image_size),
            "fiducials": {
                str(i): {
                    "image_px": list(self.image_points[i]),
                    "world_m": list(self.world_points[i]),
                    "error_m": errs[i],
                }
                for i in sorted(self.image_points)
            },
            "rms_error_m": self.rms_error,
            "max_error_m": self.max_error,
            "frames": self.frames,
            "undistorted": self.undistorted,
            "intrinsics_fingerprint": self.lens,
            "created": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
            **meta,
        }

    def save(self, path: str | Path, **meta: Any) -> None:
        """Write :meth:`to_json` to ``path`` (JSON)."""
        Path(path).write_text(json.dumps(self.to_json(**meta), indent=2) + "\n")

    @staticmethod
    def load(path: str | Path, field_name: str = "camera.homography") -> Calibration:
        """Read a calibration file; raises :class:`ConfigError` naming ``field_name``."""
        p = Path(path)
        d = read_json(p, field_name, "fleet calibrate")
        try:
            if not isinstance(d, dict) or d.get("format") != HOMOGRAPHY_FORMAT or d.get("version") != 1:
                raise ValueError(f"not a version 1 {HOMOGRAPHY_FORMAT!r} file")
            H = np.array(d["homography"], dtype=float)
            if H.shape != (3, 3) or not np.all(np.isfinite(H)) or abs(np.linalg.det(H)) < 1e-300:
                raise ValueError("homography must be a finite, invertible 3×3 matrix")
            w, h = (int(v) for v in d["image_size"])
            if w <= 0 or h <= 0:
                raise ValueError("image_size must be positive")
            fids = d["fiducials"]
            img = {int(k): (float(v["image_px"][0]), float(v["image_px"][1])) for k, v in fids.items()}
            wld = {int(k): (float(v["world_m"][0]), float(v["world_m"][1])) for k, v in fids.items()}
            rms, mx = float(d["rms_error_m"]), float(d["max_error_m"])
            frames = int(d.get("frames", 1))
            undistorted = d.get("undistorted", False)
            if not isinstance(undistorted, bool):
                raise ValueError("undistorted must be true or false")
            lens = d.get("intrinsics_fingerprint", "")
            if not isinstance(lens, str) or bool(lens) != undistorted:
                raise ValueError("intrinsics_fingerprint must name the intrinsics of an undistorted fit")
        except (KeyError, TypeError, ValueError, IndexError, AttributeError, OverflowError) as e:
            reason = str(e) if type(e) is ValueError else f"missing or malformed field ({type(e).__name__})"
            raise ConfigError(field_name, f"{p}: {reason}") from None
        return Calibration(
            H=H / H[2, 2], image_points=img, world_points=wld, rms_error=rms, max_error=mx,
            image_size=(w, h), frames=frames, undistorted=undistorted, lens=lens,
        )  # fmt: skip


def undistort_corners(corners: np.ndarray, intrinsics: Intrinsics | None) -> np.ndarray:
    """Marker corners (N, 4, 2) [px] undistorted through ``intrinsics`` (unchanged for None)."""
    c = np.asarray(corners, dtype=float)
    if intrinsics is None or c.size == 0:
        return c
    return intrinsics.undistort(c.reshape(-1, 2)).reshape(c.shape)


def fit_homography(
    image_points: Mapping[int, Sequence[float]],
    world_points: Mapping[int, Sequence[float]],
    image_size: tuple[int, int],
    frames: int = 1,
) -> Calibration:
    """Least-squares homography (image px → world m) through the fiducials seen.

    ``image_points``: fiducial id → image centre (u, v) [px]; ``world_points``:
    id → position (x, y) [m].  Uses the ids in both; needs ≥ 4 of them, no
    three of some four on a line.  Raises :class:`ConfigError`
    (``camera.fiducials``)."""
    cv2 = cv2_module()
    ids = sorted(set(image_points) & set(world_points))
    if len(ids) < 4:
        seen = ", ".join(map(str, ids)) or "none"
        raise ConfigError(
            "camera.fiducials",
            f"{len(ids)} of {len(world_points)} fiducials seen (ids {seen}); need at least 4",
        )
    q = np.array([image_points[i] for i in ids], dtype=float)
    p = np.array([world_points[i] for i in ids], dtype=float)
    H, _ = cv2.findHomography(q, p, 0)
    if H is None or not np.all(np.isfinite(H)) or abs(H[2, 2]) < 1e-12:
        raise ConfigError("camera.fiducials", f"no homography through fiducials {ids} (degenerate layout)")
    H = H / H[2, 2]
    try:
        err = np.linalg.norm(to_plane(H, q) - p, axis=1)
    except ValueError:
        raise ConfigError("camera.fiducials", f"degenerate homography through fiducials {ids}") from None
    return Calibration(
        H=H, image_points={i: (float(a), float(b)) for i, (a, b) in zip(ids, q, strict=True)},
        world_points={i: (float(a), float(b)) for i, (a, b) in zip(ids, p, strict=True)},
        rms_error=float(np.sqrt(np.mean(err**2))), max_error=float(err.max()),
        image_size=(int(image_size[0]), int(image_size[1])), frames=frames,
    )  # fmt: skip


def calibrate(
    detections: Sequence[Mapping[int, np.ndarray]],
    fiducials: Sequence[Fiducial],
    image_size: tuple[int, int],
    intrinsics: Intrinsics | None = None,
) -> Calibration:
    """Fit the homography to the fiducials of several frames' detections (id → corners
    (4, 2) [px, as observed]), averaging each fiducial's image centre over the frames
    that saw it; with ``intrinsics`` the corners are undistorted first.  Raises
    :class:`ConfigError` (``camera.fiducials``)."""
    world = {f.id: f.position for f in fiducials}
    sums: dict[int, list[np.ndarray]] = {}
    for det in detections:
        for fid, corners in det.items():
            if fid in world:
                sums.setdefault(fid, []).append(image_centre(undistort_corners(corners, intrinsics)))
    centres = {fid: tuple(np.mean(v, axis=0)) for fid, v in sums.items()}
    cal = fit_homography(centres, world, image_size, frames=len(detections))
    lens = "" if intrinsics is None else intrinsics.fingerprint()
    return dataclasses.replace(cal, undistorted=intrinsics is not None, lens=lens)


# --------------------------------------------------------------------------- poses


def marker_pose(corners: np.ndarray, H: np.ndarray) -> tuple[float, float, float, float, float]:
    """Plane pose of one marker from its image corners (4, 2) [px]: centre x, y [m],
    heading θ [rad] of its x axis (world frame, CCW from +x, in (−π, π]), mean
    side [m] and signed area [m²] (> 0 for a marker seen from above through a
    non-mirroring H)."""
    w = to_plane(H, corners)
    cx, cy = w.mean(axis=0)
    ex = (w[1] - w[0]) + (w[2] - w[3])
    ey = (w[0] - w[3]) + (w[1] - w[2])
    d = ex + np.array([ey[1], -ey[0]])
    theta = math.atan2(float(d[1]), float(d[0]))
    side = float(np.mean(np.linalg.norm(w - np.roll(w, -1, axis=0), axis=1)))
    # corners go clockwise seen from above: the shoelace sum is negative
    area = -0.5 * float(np.sum(w[:, 0] * np.roll(w[:, 1], -1) - np.roll(w[:, 0], -1) * w[:, 1]))
    return float(cx), float(cy), theta, side, area


def axle_pose(
    centre: Sequence[float], theta: float, offset: Sequence[float] = (0.0, 0.0)
) -> tuple[float, float, float]:
    """Axle-centre pose (x [m], y [m], θ [rad]) of a robot whose marker centre (x, y) [m]
    sits at ``offset`` (robot frame: x forward, y left) [m]: ``centre − R(θ)·offset``."""
    c, s = math.cos(theta), math.sin(theta)
    ox, oy = float(offset[0]), float(offset[1])
    return (float(centre[0]) - (c * ox - s * oy), float(centre[1]) - (s * ox + c * oy), float(theta))


def poses(
    corners: Mapping[int, np.ndarray],
    H: np.ndarray,
    markers: Mapping[int, str],
    offset: Sequence[float] = (0.0, 0.0),
    marker_size: float | None = None,
) -> dict[str, tuple[float, float, float]]:
    """Robot poses from detected corners: robot id → axle-centre (x [m], y [m], θ [rad]),
    world frame.  ``corners``: marker id → (4, 2) [px]; ``H``: image px → world m;
    ``markers``: marker id → robot id; ``offset``: marker centre in the robot frame
    [m].  With ``marker_size`` [m], detections of implausible size (off by more
    than ``SIZE_TOLERANCE``) or handedness are left out.  Other ids are ignored."""
    out: dict[str, tuple[float, float, float]] = {}
    for mid, c in corners.items():
        robot = markers.get(int(mid))
        if robot is None:
            continue
        try:
            cx, cy, th, side, area = marker_pose(c, H)
        except ValueError:
            continue
        if marker_size is not None and _implausible(side, area, marker_size) is not None:
            continue
        out[robot] = axle_pose((cx, cy), th, offset)
    return out


def _implausible(side: float, area: float, size: float) -> str | None:
    if area <= 0:
        return "mirrored on the plane (are the fiducial positions in a right-handed frame?)"
    if abs(side / size - 1.0) > SIZE_TOLERANCE:
        return f"side {side * 1000:.1f} mm on the plane, marker_size is {size * 1000:.1f} mm"
    return None


@dataclass
class Counts:
    """What the tracker skipped, for the summary at exit."""

    frames: int = 0
    """Frames processed, the unusable ones included (one per step)."""
    bad_frames: int = 0
    """Steps without a usable frame: unreadable or undecodable, of the wrong size, or
    (device) older than STALE_STEPS·Ts."""
    gaps: dict[str, int] = field(default_factory=dict)
    """Robot id → processed frames without a pose for it (any reason)."""
    unknown: dict[int, int] = field(default_factory=dict)
    """Marker id (neither robot nor fiducial) → frames it was seen in."""
    duplicates: dict[int, int] = field(default_factory=dict)
    """Marker id → frames it was seen more than once in (dropped)."""
    implausible: dict[int, int] = field(default_factory=dict)
    """Robot marker id → detections dropped for size or handedness."""

    def summary(self) -> str:
        """The counts in one line, for the log at exit."""

        def fmt(d: Mapping[Any, int]) -> str:
            return ", ".join(f"{k}: {v}" for k, v in sorted(d.items(), key=lambda kv: str(kv[0]))) or "none"

        return (
            f"{self.frames} frames, {self.bad_frames} unusable; gaps per robot {{{fmt(self.gaps)}}}; "
            f"unknown ids {{{fmt(self.unknown)}}}; duplicate ids {{{fmt(self.duplicates)}}}; "
            f"implausible {{{fmt(self.implausible)}}}"
        )


class Tracker:
    """Frames → robot poses, with the counting and the once-only logging.

    No Zenoh: the process of :func:`main` and the tests both drive it."""

    def __init__(
        self, camera: CameraSpec, markers: Mapping[int, str], calibration: Calibration, report: Any = None,
        intrinsics: Intrinsics | None = None,
    ) -> None:  # fmt: skip
        self.camera = camera
        self.markers = dict(markers)
        """Marker id → robot id."""
        self.fiducials = {f.id for f in camera.fiducials}
        self.calibration = calibration
        self.detector = make_detector(camera.dictionary)
        self.counts = Counts(gaps={r: 0 for r in self.markers.values()})
        self._report = report
        self._told: set[str] = set()
        self.intrinsics = intrinsics
        """The lens (corners are undistorted through it), None: not corrected."""
        if (intrinsics is None) == calibration.undistorted:
            need = "with" if calibration.undistorted else "without"
            raise ConfigError(
                "camera.intrinsics", f"the homography was fitted {need} intrinsics; so must the tracker run"
            )
        if intrinsics is not None and intrinsics.image_size != calibration.image_size:
            raise ConfigError(
                "camera.intrinsics",
                f"intrinsics for {intrinsics.image_size[0]}×{intrinsics.image_size[1]} px, the homography "
                f"for {calibration.image_size[0]}×{calibration.image_size[1]} px",
            )
        if intrinsics is not None and intrinsics.fingerprint() != calibration.lens:
            raise ConfigError(
                "camera.intrinsics",
                "the homography was fitted through other intrinsics (another lens calibration): "
                "calibrate the floor again (fleet calibrate)",
            )
        if intrinsics is None:
            self._once(
                "lens",
                "lens distortion is not corrected (no camera.intrinsics): floor errors grow towards the "
                "image edges; calibrate with fleet calibrate --intrinsics",
            )

    def _once(self, key: str, msg: str) -> None:
        if key not in self._told:
            self._told.add(key)
            if self._report is not None:
                self._report(msg)

    def skip(self, reason: str) -> None:
        """Count a step without a usable frame (a bad frame: every robot gets a gap)."""
        self.counts.frames += 1
        self.counts.bad_frames += 1
        for r in self.counts.gaps:
            self.counts.gaps[r] += 1
        self._once("bad", f"unusable frame: {reason} (skipped; further ones are counted)")

    def process(self, frame: object, label: str = "") -> dict[str, tuple[float, float, float]]:
        """Poses in one frame: robot id → axle-centre (x [m], y [m], θ [rad]), world frame.

        Never raises for a bad frame or an odd detection: it counts them (see
        :class:`Counts`).  ``label`` names the frame in log lines."""
        c = self.counts
        try:
            gray = _gray(frame)
            size = (gray.shape[1], gray.shape[0])
            if size != self.calibration.image_size:
                raise BadFrame(
                    f"frame of {size[0]}×{size[1]} px, the homography is for "
                    f"{self.calibration.image_size[0]}×{self.calibration.image_size[1]} px"
                )
            ids, pts = detect_markers(gray, self.detector)
            pts = undistort_corners(pts, self.intrinsics)
        except BadFrame as e:
            self.skip(f"frame {label}: {e}")
            return {}
        c.frames += 1
        uniq, n = np.unique(ids, return_counts=True)
        seen = {int(u): int(k) for u, k in zip(uniq, n, strict=True)}
        out: dict[str, tuple[float, float, float]] = {}
        for mid, corners in zip(ids, pts, strict=True):
            mid = int(mid)
            if mid in self.fiducials:
                continue
            robot = self.markers.get(mid)
            if robot is None or seen[mid] > 1:
                continue
            try:
                cx, cy, th, side, area = marker_pose(corners, self.calibration.H)
            except ValueError:
                why: str | None = "on the homography's horizon"
            else:
                why = _implausible(side, area, self.camera.marker_size)
            if why is not None:
                c.implausible[mid] = c.implausible.get(mid, 0) + 1
                self._once(f"implausible {mid}", f"marker {mid} ({robot}) dropped in frame {label}: {why}")
                continue
            out[robot] = axle_pose((cx, cy), th, self.camera.marker_offset)
        for mid, k in seen.items():
            if mid not in self.markers and mid not in self.fiducials:
                c.unknown[mid] = c.unknown.get(mid, 0) + 1
                self._once(f"unknown {mid}", f"marker id {mid} in frame {label} is no robot's; ignored")
            elif k > 1 and mid not in self.fiducials:
                c.duplicates[mid] = c.duplicates.get(mid, 0) + 1
                self._once(f"dup {mid}", f"marker id {mid} seen {k} times in frame {label}; dropped")
        for mid, robot in self.markers.items():
            if robot not in out:
                c.gaps[robot] += 1
                if mid not in seen:
                    self._once(
                        f"gap {robot}", f"{robot}: marker {mid} not seen in frame {label} (gaps counted)"
                    )
        return out


# --------------------------------------------------------------------------- frame sources


def camera_setup(scn: Scenario) -> tuple[CameraSpec, dict[int, str]]:
    """The scenario's camera table and marker id → robot id; ConfigError if the
    camera source cannot run on it."""
    if scn.camera is None:
        raise ConfigError("camera", "missing [camera] table: the camera source needs the fiducials")
    markers: dict[int, str] = {}
    for i, r in enumerate(scn.robots):
        if r.marker is None:
            raise ConfigError(f"robots[{i}].marker", "missing: the camera source needs each robot's ArUco id")
        markers[r.marker] = r.id
    return scn.camera, markers


def calibrate_from(
    frames: Iterator[np.ndarray | None], camera: CameraSpec, *, want: int, tries: int,
    intrinsics: Intrinsics | None = None,
) -> Calibration:  # fmt: skip
    """Calibrate from the fiducials of up to ``want`` frames that show them all,
    reading at most ``tries`` frames; with fewer, from what was seen (≥ 4 in
    general position); with ``intrinsics`` on undistorted fiducial corners.
    Raises :class:`ConfigError` (``camera.fiducials``, or ``camera.intrinsics``
    for frames of another size than the intrinsics')."""
    detector = make_detector(camera.dictionary)
    fids = {f.id for f in camera.fiducials}
    dets: list[dict[int, np.ndarray]] = []
    size: tuple[int, int] | None = None
    read = 0
    complete = 0
    for image in frames:
        read += 1
        try:
            det = detect(image, detector)
        except BadFrame:
            det = None
        if det is not None and image is not None:
            frame_size = (int(image.shape[1]), int(image.shape[0]))
            if size is None or frame_size == size:
                size = frame_size
                seen = {k: v for k, v in det.items() if k in fids}
                if seen:
                    dets.append(seen)
                    complete += seen.keys() == fids
        if complete >= want or read >= tries:
            break
    if size is None:
        raise ConfigError("camera.fiducials", f"no readable frame in the first {read} frames")
    if intrinsics is not None and intrinsics.image_size != size:
        w, h = intrinsics.image_size
        raise ConfigError(
            "camera.intrinsics", f"intrinsics for {w}×{h} px, the frames are {size[0]}×{size[1]} px"
        )
    try:
        return calibrate(dets, camera.fiducials, size, intrinsics)
    except ConfigError as e:
        raise ConfigError(e.field, f"{e.reason}, in {read} frames") from None


def quiet_opencv(cv2: Any) -> None:
    """Keep OpenCV's own warnings (e.g. a V4L2 device that cannot be opened) off stderr,
    where a process's errors are one line each; this process's counts and log
    lines report what went wrong instead."""
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)
