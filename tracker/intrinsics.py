"""The camera's lens: intrinsics, their calibration from ChArUco views, and point undistortion.

Model (OpenCV's, documentation of the calib3d module, "Camera Calibration and 3D
Reconstruction"): a point (X, Y, Z) [m] in the camera frame (x right, y down, z forward) has
normalised coordinates x' = X/Z, y' = Y/Z, r² = x'² + y'², and lands in the image at

    x'' = x'·(1 + k₁r² + k₂r⁴ + k₃r⁶) + 2p₁x'y' + p₂(r² + 2x'²)
    y'' = y'·(1 + k₁r² + k₂r⁴ + k₃r⁶) + p₁(r² + 2y'²) + 2p₂x'y'
    u = f_x·x'' + c_x,   v = f_y·y'' + c_y   [px]

with the camera matrix K = [[f_x, 0, c_x], [0, f_y, c_y], [0, 0, 1]] [px] and the distortion
coefficients D = (k₁, k₂, p₁, p₂, k₃) (dimensionless).  Webcams are typically barrel-distorted,
k₁ ≈ −0.1 … −0.4.  :meth:`Intrinsics.undistort` inverts the model for image points
(``cv2.undistortPoints`` iterated to convergence, re-projected with K): the floor homography
then sees an ideal pinhole camera.  Only points are undistorted, never whole frames.

:func:`calibrate_intrinsics` fits K and D to views of a ChArUco board
(:class:`CharucoBoardSpec`: a chessboard with ArUco markers in its white squares, so that
partly visible boards still give identified corners) with ``cv2.calibrateCamera``.  The board's
absolute size does not change K and D; only the marker-to-square ratio must match the print.
"""

from __future__ import annotations

import datetime as _dt
import json
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ground.scenario import ConfigError

INTRINSICS_FORMAT = "epuck-fleet intrinsics"
"""The ``format`` field of an intrinsics file."""
MIN_VIEWS = 8
"""Views of the board a calibration needs at least."""
MAX_VIEWS = 40
"""Views a calibration uses at most (evenly spaced over the input, e.g. a video's frames)."""
MIN_CORNERS = 8
"""ChArUco corners a view needs to count (and not all on one line)."""
COVERAGE_GRID = (6, 6)
"""Image cells (columns, rows) over which the spread of the board corners is measured."""
MIN_COVERAGE = 0.6
"""Fraction of the :data:`COVERAGE_GRID` cells that some board corner must fall into: the
distortion is largest near the image edges and must be observed there."""
MAX_RMS = 2.0
"""Reprojection RMS [px] above which a fit is refused."""
UNDISTORT_CRITERIA = (3, 100, 1e-9)
"""``cv2.undistortPoints`` termination (COUNT + EPS, iterations, pixel error): OpenCV's default
of 5 fixed iterations leaves pixel-sized errors in the corners of a strongly distorted image."""


class IntrinsicsError(ValueError):
    """A calibration that cannot be made or trusted; ``str()`` is one line ``<field>: <reason>``."""

    def __init__(self, field: str, reason: str) -> None:
        super().__init__(f"{field}: {reason}")
        self.field = field
        self.reason = reason


def cv2_module() -> Any:
    """The ``cv2`` module, imported at the call (OpenCV is optional: ImportError without it)."""
    import cv2

    return cv2


def distort_normalised(xy: np.ndarray, dist: Sequence[float]) -> np.ndarray:
    """The model's (x'', y'') (N, 2) of ideal normalised points (x', y') (N, 2);
    ``dist`` = (k₁, k₂, p₁, p₂, k₃)."""
    k1, k2, p1, p2, k3 = (float(v) for v in dist)
    p = np.asarray(xy, dtype=float).reshape(-1, 2)
    x, y = p[:, 0], p[:, 1]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return np.column_stack([xd, yd])


def undistort_points(points: np.ndarray, K: np.ndarray, dist: Sequence[float]) -> np.ndarray:
    """Ideal image points (N, 2) [px] (pinhole through K) of observed points (N, 2) [px]."""
    cv2 = cv2_module()
    p = np.asarray(points, dtype=np.float64).reshape(-1, 1, 2)
    if len(p) == 0:
        return np.zeros((0, 2))
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, UNDISTORT_CRITERIA[1], UNDISTORT_CRITERIA[2])
    K64 = np.asarray(K, dtype=np.float64)
    out = cv2.undistortPoints(p, K64, np.asarray(dist, dtype=np.float64), R=None, P=K64, criteria=crit)
    return np.asarray(out, dtype=float).reshape(-1, 2)


def distort_points(points: np.ndarray, K: np.ndarray, dist: Sequence[float]) -> np.ndarray:
    """Observed image points (N, 2) [px] of ideal pinhole points (N, 2) [px] (the model forward)."""
    K = np.asarray(K, dtype=float)
    p = np.asarray(points, dtype=float).reshape(-1, 2)
    n = np.column_stack([(p[:, 0] - K[0, 2]) / K[0, 0], (p[:, 1] - K[1, 2]) / K[1, 1]])
    d = distort_normalised(n, dist)
    return np.column_stack([K[0, 0] * d[:, 0] + K[0, 2], K[1, 1] * d[:, 1] + K[1, 2]])


def read_json(path: Path, field_name: str, writer: str) -> Any:
    """The JSON in the calibration file ``path``; raises :class:`ConfigError` naming
    ``field_name`` if it is missing (``writer`` is the command that writes it), unreadable or
    not JSON."""
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise ConfigError(field_name, f"{path}: no such file (write it with {writer})") from None
    except (OSError, UnicodeDecodeError) as e:
        raise ConfigError(field_name, f"{path}: cannot read ({e})") from None
    except json.JSONDecodeError as e:
        raise ConfigError(field_name, f"{path}: invalid JSON ({e})") from None


@dataclass(frozen=True)
class Intrinsics:
    """A calibrated camera: its matrix, its lens distortion and how well they fit."""

    K: np.ndarray = field(compare=False)
    """Camera matrix (3, 3) [px]: [[f_x, 0, c_x], [0, f_y, c_y], [0, 0, 1]], pixel centres at integers."""
    dist: tuple[float, float, float, float, float]
    """Distortion coefficients (k₁, k₂, p₁, p₂, k₃), OpenCV's model (module docstring)."""
    image_size: tuple[int, int]
    """Image (width, height) [px] the intrinsics belong to."""
    rms: float = 0.0
    """Reprojection RMS over all board corners of the calibration [px]."""
    view_errors: tuple[float, ...] = ()
    """Reprojection RMS of each view [px]."""
    frames: tuple[int, ...] = ()
    """Input frame index of each view."""

    def undistort(self, points: np.ndarray) -> np.ndarray:
        """Ideal pinhole image points (N, 2) [px] of observed points (N, 2) [px]."""
        return undistort_points(points, self.K, self.dist)

    def distort(self, points: np.ndarray) -> np.ndarray:
        """Observed image points (N, 2) [px] of ideal pinhole points (N, 2) [px]."""
        return distort_points(points, self.K, self.dist)

    def fingerprint(self) -> str:
        """A short digest of the camera matrix, the distortion and the image size: a floor
        homography fitted through these intrinsics records it, and is refused with others."""
        import hashlib

        values = [*np.asarray(self.K, dtype=float).ravel()[[0, 2, 4, 5]], *self.dist, *self.image_size]
        text = ",".join(f"{float(v):.9e}" for v in values)
        return hashlib.sha256(text.encode()).hexdigest()[:16]

    def inverts(self, tol_px: float = 0.05) -> bool:
        """The lens model inverts over the whole image: edge points [px] undistorted and
        distorted again come back within ``tol_px``.  The model is a polynomial, and a fit
        that saw too little of the image can fold over at its edges."""
        w, h = self.image_size
        t = np.linspace(0.0, 1.0, 17)
        edge = np.concatenate([np.column_stack([t * (w - 1), np.zeros_like(t)]),
                               np.column_stack([t * (w - 1), np.full_like(t, h - 1)]),
                               np.column_stack([np.zeros_like(t), t * (h - 1)]),
                               np.column_stack([np.full_like(t, w - 1), t * (h - 1)])])  # fmt: skip
        with np.errstate(all="ignore"):
            back = self.distort(self.undistort(edge))
        return bool(np.all(np.isfinite(back)) and np.max(np.linalg.norm(back - edge, axis=1)) <= tol_px)

    def to_json(self, **meta: Any) -> dict[str, Any]:
        """The intrinsics file's content (``meta``: extra top-level fields)."""
        return {
            "format": INTRINSICS_FORMAT,
            "version": 1,
            "camera_matrix": [[float(v) for v in row] for row in self.K],
            "distortion": [float(v) for v in self.dist],
            "distortion_model": "OpenCV (k1, k2, p1, p2, k3)",
            "image_size": list(self.image_size),
            "rms_px": self.rms,
            "view_errors_px": list(self.view_errors),
            "view_frames": list(self.frames),
            "created": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
            **meta,
        }

    def save(self, path: str | Path, **meta: Any) -> None:
        """Write :meth:`to_json` to ``path`` (JSON)."""
        Path(path).write_text(json.dumps(self.to_json(**meta), indent=2) + "\n")

    @staticmethod
    def load(path: str | Path, field_name: str = "camera.intrinsics") -> Intrinsics:
        """Read an intrinsics file; raises :class:`ConfigError` naming ``field_name``."""
        p = Path(path)
        d = read_json(p, field_name, "fleet calibrate --intrinsics")
        try:
            if not isinstance(d, dict) or d.get("format") != INTRINSICS_FORMAT or d.get("version") != 1:
                raise ValueError(f"not a version 1 {INTRINSICS_FORMAT!r} file")
            K = np.array(d["camera_matrix"], dtype=float)
            if K.shape != (3, 3) or not np.all(np.isfinite(K)):
                raise ValueError("camera_matrix must be a finite 3×3 matrix")
            if (
                K[0, 0] <= 0
                or K[1, 1] <= 0
                or not np.allclose(K[2], [0, 0, 1])
                or K[1, 0] != 0
                or K[0, 1] != 0
            ):
                raise ValueError(
                    "camera_matrix must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0"
                )
            dist = [float(v) for v in d["distortion"]]
            if len(dist) != 5 or not all(math.isfinite(v) for v in dist):
                raise ValueError("distortion must be 5 finite numbers (k1, k2, p1, p2, k3)")
            w, h = (int(v) for v in d["image_size"])
            if w <= 0 or h <= 0:
                raise ValueError("image_size must be positive")
            rms = float(d.get("rms_px", 0.0))
            views = tuple(float(v) for v in d.get("view_errors_px", []))
            idx = tuple(int(v) for v in d.get("view_frames", []))
        except (KeyError, TypeError, ValueError, IndexError, AttributeError, OverflowError) as e:
            reason = str(e) if type(e) is ValueError else f"missing or malformed field ({type(e).__name__})"
            raise ConfigError(field_name, f"{p}: {reason}") from None
        k1, k2, p1, p2, k3 = dist
        cal = Intrinsics(
            K=K, dist=(k1, k2, p1, p2, k3), image_size=(w, h), rms=rms, view_errors=views, frames=idx
        )
        if not cal.inverts():
            raise ConfigError(field_name, f"{p}: the lens model does not invert at the image edges")
        return cal


# --------------------------------------------------------------------------- ChArUco


@dataclass(frozen=True)
class CharucoBoardSpec:
    """A ChArUco calibration board: ``squares`` (columns, rows) of side ``square`` [m],
    ArUco markers of side ``marker`` [m] from ``dictionary`` in the white squares.

    Board frame (OpenCV's): origin at the board's outer top-left corner as printed,
    x along the columns, y along the rows (down the print), z into the board [m]."""

    squares: tuple[int, int] = (7, 5)
    """Squares across (columns) and down (rows)."""
    square: float = 0.030
    """Side of a chessboard square [m]."""
    marker: float = 0.022
    """Side of an ArUco marker (outer edge of its black border) [m], < ``square``."""
    dictionary: str = "DICT_5X5_50"
    """OpenCV ArUco dictionary of the board's markers (other than the robots' by default,
    so a board in view is never taken for a robot)."""

    def board(self) -> Any:
        """The ``cv2.aruco.CharucoBoard``."""
        cv2 = cv2_module()
        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard(self.squares, self.square, self.marker, d)

    @property
    def size(self) -> tuple[float, float]:
        """Board (width, height) [m]."""
        return (self.squares[0] * self.square, self.squares[1] * self.square)


DEFAULT_BOARD = CharucoBoardSpec()
"""The board ``fleet markers --charuco`` prints and ``fleet calibrate --intrinsics`` expects."""


@dataclass(frozen=True)
class BoardView:
    """The board corners found in one frame."""

    index: int
    """Frame index in the input (0-based)."""
    object_points: np.ndarray
    """Board corners (N, 3) [m, board frame]."""
    image_points: np.ndarray
    """Their image positions (N, 2) [px, as observed]."""


def _grey(frame: object) -> np.ndarray | None:
    """A uint8 grey image (H, W) of a grey or BGR uint8 frame; None for anything else."""
    if not isinstance(frame, np.ndarray) or frame.dtype != np.uint8 or min(frame.shape[:2], default=0) < 8:
        return None
    if frame.ndim == 2:
        return frame
    if frame.ndim == 3 and frame.shape[2] == 3:
        return np.asarray(cv2_module().cvtColor(frame, cv2_module().COLOR_BGR2GRAY))
    return None


def find_board(frames: Iterable[np.ndarray | None], board: CharucoBoardSpec = DEFAULT_BOARD
               ) -> tuple[list[BoardView], int, tuple[int, int] | None]:  # fmt: skip
    """The views of ``board`` in ``frames`` (grey or BGR uint8 images; None for an
    unreadable frame) with at least :data:`MIN_CORNERS` corners not on one line; also
    the frames read and the image (width, height) [px].  Raises
    :class:`IntrinsicsError` for frames of different sizes."""
    cv2 = cv2_module()
    b = board.board()
    detector = cv2.aruco.CharucoDetector(b)
    views: list[BoardView] = []
    size: tuple[int, int] | None = None
    n = 0
    for i, frame in enumerate(frames):
        n += 1
        gray = _grey(frame)
        if gray is None:
            continue
        fs = (int(gray.shape[1]), int(gray.shape[0]))
        if size is None:
            size = fs
        elif fs != size:
            raise IntrinsicsError(
                "frames", f"frame {i} is {fs[0]}×{fs[1]} px, the first was {size[0]}×{size[1]} px"
            )
        corners, ids, _, _ = detector.detectBoard(gray)
        if ids is None or len(ids) < MIN_CORNERS:
            continue
        if b.checkCharucoCornersCollinear(ids):
            continue
        obj, img = b.matchImagePoints(corners, ids)
        views.append(
            BoardView(
                i, np.asarray(obj, dtype=float).reshape(-1, 3), np.asarray(img, dtype=float).reshape(-1, 2)
            )
        )
    return views, n, size


def coverage(views: Sequence[BoardView], image_size: tuple[int, int]) -> float:
    """Fraction of the :data:`COVERAGE_GRID` image cells holding at least one board corner."""
    gx, gy = COVERAGE_GRID
    w, h = image_size
    hit = np.zeros((gy, gx), dtype=bool)
    for v in views:
        cx = np.clip((v.image_points[:, 0] + 0.5) * gx / w, 0, gx - 1).astype(int)
        cy = np.clip((v.image_points[:, 1] + 0.5) * gy / h, 0, gy - 1).astype(int)
        hit[cy, cx] = True
    return float(hit.mean())


def calibrate_intrinsics(
    frames: Iterable[np.ndarray | None],
    board: CharucoBoardSpec = DEFAULT_BOARD,
    *,
    min_views: int = MIN_VIEWS,
) -> Intrinsics:
    """Fit K and D (k₁, k₂, p₁, p₂, k₃) to the ChArUco views in ``frames``.

    Refuses (:class:`IntrinsicsError`, one line) when the board is in no frame, in fewer than
    ``min_views`` frames, when its corners cover less than :data:`MIN_COVERAGE` of the image's
    cells, when ``cv2.calibrateCamera`` fails or gives a non-finite or singular camera matrix,
    an RMS above :data:`MAX_RMS` px, or a lens model that does not invert over the image."""
    cv2 = cv2_module()
    views, n, size = find_board(frames, board)
    what = f"ChArUco board {board.squares[0]}×{board.squares[1]} squares, {board.dictionary}"
    if size is None:
        raise IntrinsicsError("frames", f"no readable frame among {n}")
    if not views:
        raise IntrinsicsError("frames", f"no {what} found in {n} frames")
    if len(views) < min_views:
        raise IntrinsicsError(
            "frames", f"the board was found in {len(views)} of {n} frames; need at least {min_views} views"
        )
    if len(views) > MAX_VIEWS:
        views = [views[i] for i in np.linspace(0, len(views) - 1, MAX_VIEWS).round().astype(int)]
    cov = coverage(views, size)
    if cov < MIN_COVERAGE:
        raise IntrinsicsError(
            "frames",
            f"the board corners cover {cov:.0%} of the image, need {MIN_COVERAGE:.0%}: "
            "show the board near every edge and corner of the image",
        )
    obj = [v.object_points.astype(np.float32) for v in views]
    img = [v.image_points.astype(np.float32).reshape(-1, 1, 2) for v in views]
    try:
        rms, K, dist, _, _, _, _, per_view = cv2.calibrateCameraExtended(obj, img, size, None, None)
    except cv2.error as e:
        raise IntrinsicsError(
            "fit", f"cv2.calibrateCamera failed: {str(e).strip().splitlines()[-1]}"
        ) from None
    K = np.asarray(K, dtype=float)
    dist = np.asarray(dist, dtype=float).reshape(-1)[:5]
    if not (np.all(np.isfinite(K)) and np.all(np.isfinite(dist)) and math.isfinite(rms)):
        raise IntrinsicsError("fit", "the fit did not converge (non-finite parameters)")
    if K[0, 0] <= 0 or K[1, 1] <= 0 or abs(np.linalg.det(K)) < 1e-9:
        raise IntrinsicsError("fit", "singular camera matrix")
    if rms > MAX_RMS:
        raise IntrinsicsError("fit", f"reprojection RMS {rms:.2f} px exceeds {MAX_RMS:g} px (wrong board?)")
    k1, k2, p1, p2, k3 = (float(v) for v in dist)
    cal = Intrinsics(
        frames=tuple(v.index for v in views),
        K=K, dist=(k1, k2, p1, p2, k3), image_size=(int(size[0]), int(size[1])), rms=float(rms),
        view_errors=tuple(float(e) for e in np.asarray(per_view).reshape(-1)),
    )  # fmt: skip
    # The lens model is a polynomial: it must invert over the whole image, not only where the board was.
    if not cal.inverts():
        raise IntrinsicsError(
            "fit", "the fitted lens model does not invert at the image edges (spread the views)"
        )
    return cal
