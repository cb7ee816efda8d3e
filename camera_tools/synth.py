"""Synthetic overhead-camera images and videos of ArUco-marked robots.

For users without a camera and for the tests: a tilted pinhole camera looks
at the floor plane z = 0 (world frame, m); fiducials and robot markers are
ArUco markers with a white quiet zone, drawn in world coordinates and warped
into the image through the camera's floor homography, so their corners sit
exactly where the perspective model puts them.  The image is rendered at
``SUPERSAMPLE``× resolution and area-averaged down (anti-aliasing), then
blurred (Gaussian, σ in px) and given additive Gaussian noise, seeded.

Lens distortion (``PinholeCamera.distortion`` = (k₁, k₂, p₁, p₂, k₃), OpenCV's
model, see :mod:`tracker.intrinsics`; default none): the ideal pinhole image is
rendered first, on a canvas large enough for what the lens pulls into view,
then each output pixel (u_d, v_d) takes the ideal image at its undistorted
position (``cv2.undistortPoints`` iterated to convergence, once per renderer)
through ``cv2.remap`` (bilinear), before the blur and the noise.
:func:`board_view` renders a ChArUco board at any pose in front of the camera
the same way, for intrinsic calibration.

``python -m camera_tools.synth --scenario S (--video OUT.avi | --image OUT.png)
[--duration T] [--fps F] [--seed N]`` renders a scenario with a ``[camera]``
table and robot ``marker`` ids: each robot drives in a straight line from its
start to its goal; the video plays through ``python -m tracker --source
camera --video OUT.avi``.

Pixel convention (OpenCV's): pixel (u, v) has its centre at integer
coordinates, u to the right, v down; the image is (height, width) uint8.
"""

from __future__ import annotations

import argparse
import functools
import math
import sys
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from tracker.intrinsics import CharucoBoardSpec, distort_normalised, distort_points, undistort_points
from tracker.vision import OPENCV_MISSING, cv2_module
from transport.process import seed_arg

SUPERSAMPLE = 2
"""Rendering resolution factor before the area-averaging downscale."""
BODY_RADIUS = 0.037
"""Radius of the drawn E-puck body [m] (the e-puck's body is 70–75 mm across)."""

PoseFn = Callable[[float], tuple[float, float, float]]
"""A trajectory: time t [s] → axle-centre pose (x [m], y [m], θ [rad]), world frame."""


@dataclass(frozen=True)
class PinholeCamera:
    """A pinhole camera, with optional lens distortion, looking at the floor plane z = 0.

    The camera sits at ``position`` and its optical axis passes through
    ``target`` on the floor; image "right" is the world direction
    forward × z (so a camera behind the arena on −y sees +x to the right and
    +y up the image, a non-mirrored view from above)."""

    width: int = 1600
    """Image width [px]."""
    height: int = 1200
    """Image height [px]."""
    focal: float = 1000.0
    """Focal length [px] (square pixels); the principal point is the image centre."""
    position: tuple[float, float, float] = (0.0, -1.4, 2.6)
    """Camera centre, world frame (x, y, z) [m], z > 0."""
    target: tuple[float, float] = (0.0, 0.0)
    """Floor point (x, y) [m] on the optical axis."""
    distortion: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)
    """Lens distortion (k₁, k₂, p₁, p₂, k₃), OpenCV's model (:mod:`tracker.intrinsics`);
    all zero: an ideal pinhole."""

    @property
    def distorted(self) -> bool:
        """The lens distorts (some coefficient is non-zero)."""
        return any(v != 0.0 for v in self.distortion)

    def distort(self, points: np.ndarray) -> np.ndarray:
        """Observed image points (N, 2) [px] of ideal pinhole image points (N, 2) [px]."""
        if not self.distorted:
            return np.asarray(points, dtype=float).reshape(-1, 2)
        return distort_points(points, self.intrinsics(), self.distortion)

    def rotation(self) -> np.ndarray:
        """World → camera rotation (3, 3); rows are the camera's x (right), y (down), z (forward) axes."""
        c = np.asarray(self.position, dtype=float)
        f = np.array([self.target[0], self.target[1], 0.0]) - c
        f /= np.linalg.norm(f)
        r = np.cross(f, [0.0, 0.0, 1.0])
        if np.linalg.norm(r) < 1e-9:  # looking straight down: world +x to the right
            r = np.array([1.0, 0.0, 0.0])
        r /= np.linalg.norm(r)
        d = np.cross(f, r)
        return np.stack([r, d, f])

    def intrinsics(self) -> np.ndarray:
        """Camera matrix K (3, 3) [px]."""
        return np.array(
            [
                [self.focal, 0.0, (self.width - 1) / 2.0],
                [0.0, self.focal, (self.height - 1) / 2.0],
                [0, 0, 1.0],
            ]
        )

    def homography(self) -> np.ndarray:
        """Floor → image homography K [r₁ r₂ t] (3, 3): (x, y, 1) [m, world] ↦ z_c·(u, v, 1)
        [px], where z_c [m] is the point's depth in front of the camera."""
        R = self.rotation()
        t = -R @ np.asarray(self.position, dtype=float)
        return np.asarray(self.intrinsics() @ np.column_stack([R[:, 0], R[:, 1], t]))

    def project(self, points: np.ndarray) -> np.ndarray:
        """Image points (N, 2) [px] of floor points (N, 2) [m, world frame], through the lens."""
        return self.distort(_apply(self.homography(), points))

    @staticmethod
    def viewing(
        points: np.ndarray,
        *,
        tilt: float = math.radians(30.0),
        height: float = 2.5,
        width_px: int = 1600,
        height_px: int = 1200,
        margin: float = 0.04,
        distortion: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0),
    ) -> PinholeCamera:
        """A camera ``height`` [m] above the floor, behind (−y of) the centre of
        ``points`` (N, 2) [m, world frame] and looking at them ``tilt`` [rad] off
        vertical, aimed so their image is centred and with the focal length
        [px] that fits them in the image (through the lens ``distortion``)
        with ``margin`` (fraction of the image size) to spare."""
        pts = np.asarray(points, dtype=float).reshape(-1, 2)
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        cx, cy = (lo + hi) / 2.0
        position = (float(cx), float(cy - height * math.tan(tilt)), float(height))

        def normalised(target_y: float) -> np.ndarray:
            cam = PinholeCamera(width=width_px, height=height_px, focal=1.0, position=position,
                                target=(float(cx), target_y))  # fmt: skip
            R = cam.rotation()
            pc = (R @ (np.column_stack([pts, np.zeros(len(pts))]) - np.asarray(position)).T).T
            return np.asarray(pc[:, :2] / pc[:, 2:3])

        # Aim so the points' image is vertically centred (secant iterations on the target's y).
        ty0, ty1 = float(cy), float(cy) + 0.1
        v0 = float(np.mean([normalised(ty0)[:, 1].min(), normalised(ty0)[:, 1].max()]))
        for _ in range(20):
            n1 = normalised(ty1)[:, 1]
            v1 = float((n1.min() + n1.max()) / 2.0)
            if abs(v1) < 1e-9 or abs(v1 - v0) < 1e-15:
                break
            ty0, ty1, v0 = ty1, ty1 - v1 * (ty1 - ty0) / (v1 - v0), v1
        n = distort_normalised(normalised(ty1), distortion)
        xn, yn = np.abs(n[:, 0]).max(), np.abs(n[:, 1]).max()
        f = min((0.5 - margin) * width_px / max(xn, 1e-9), (0.5 - margin) * height_px / max(yn, 1e-9))
        return PinholeCamera(
            width=width_px,
            height=height_px,
            focal=float(f),
            position=position,
            target=(float(cx), ty1),
            distortion=tuple(float(v) for v in distortion),  # type: ignore[arg-type]
        )


def _apply(H: np.ndarray, points: np.ndarray) -> np.ndarray:
    p = np.asarray(points, dtype=float).reshape(-1, 2)
    q = np.column_stack([p, np.ones(len(p))]) @ np.asarray(H, dtype=float).T
    return np.asarray(q[:, :2] / q[:, 2:3])


LENS_CANVAS_GROWTH = 1.8
"""The ideal canvas of a distorting camera is at most this many times the image's size per axis."""


@dataclass(frozen=True)
class LensMap:
    """How a distorting lens forms the image: output px (u_d, v_d) shows the ideal pinhole
    image at ``(map_u, map_v)[v_d, u_d]`` [px on the ideal canvas]; ideal px (u, v) sits
    at canvas px (u + offset[0], v + offset[1])."""

    map_u: np.ndarray = field(compare=False)
    """(height, width) float32 [canvas px]."""
    map_v: np.ndarray = field(compare=False)
    """(height, width) float32 [canvas px]."""
    offset: tuple[int, int]
    """Canvas px of ideal px (0, 0)."""
    canvas: tuple[int, int]
    """Canvas (width, height) [px]: it holds every ideal point some output pixel shows
    (up to :data:`LENS_CANVAS_GROWTH`)."""

    def apply(self, ideal: np.ndarray) -> np.ndarray:
        """The observed image (height, width) float32 of an ideal canvas image (float32)."""
        cv2 = cv2_module()
        return np.asarray(
            cv2.remap(ideal, self.map_u, self.map_v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        )


@functools.lru_cache(maxsize=4)
def lens_map(camera: PinholeCamera) -> LensMap | None:
    """The :class:`LensMap` of ``camera`` (None for an ideal pinhole), computed once per camera:
    every output pixel undistorted (``cv2.undistortPoints``, iterated to convergence)."""
    if not camera.distorted:
        return None
    w, h = camera.width, camera.height
    vv, uu = np.mgrid[0:h, 0:w].astype(np.float64)
    ideal = undistort_points(
        np.column_stack([uu.ravel(), vv.ravel()]), camera.intrinsics(), camera.distortion
    )
    g = (LENS_CANVAS_GROWTH - 1.0) / 2.0
    lo = np.maximum(np.floor(ideal.min(axis=0)) - 2, [-g * w, -g * h]).astype(int)
    hi = np.minimum(np.ceil(ideal.max(axis=0)) + 3, [w + g * w, h + g * h]).astype(int)
    ox, oy = int(max(0, -lo[0])), int(max(0, -lo[1]))
    canvas = (int(max(hi[0], w) + ox), int(max(hi[1], h) + oy))
    mu = (ideal[:, 0] + ox).reshape(h, w).astype(np.float32)
    mv = (ideal[:, 1] + oy).reshape(h, w).astype(np.float32)
    return LensMap(map_u=mu, map_v=mv, offset=(ox, oy), canvas=canvas)


def marker_image(marker_id: int, dictionary: str = "DICT_4X4_50", bit_px: int = 16) -> np.ndarray:
    """An ArUco marker with a one-bit white quiet zone, (S, S) uint8, S = (bits + 4)·``bit_px``.

    ``bits`` is the dictionary's marker size (4 for 4×4) plus its black
    border; the black square spans pixels [bit_px, S − bit_px)."""
    cv2 = cv2_module()
    d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
    inner = (d.markerSize + 2) * bit_px
    m = cv2.aruco.generateImageMarker(d, int(marker_id), inner, borderBits=1)
    return np.asarray(cv2.copyMakeBorder(m, bit_px, bit_px, bit_px, bit_px, cv2.BORDER_CONSTANT, value=255))


def marker_corners(centre: Sequence[float], angle: float, size: float) -> np.ndarray:
    """World corners (4, 2) [m] of a marker of side ``size`` [m] centred at ``centre``
    (x, y) [m] with its x axis at ``angle`` [rad]: ArUco's order, corner 0 at the
    marker's (−s/2, +s/2), then clockwise seen from above (0 → 1 is the +x edge)."""
    h = size / 2.0
    local = np.array([[-h, h], [h, h], [h, -h], [-h, -h]])
    c, s = math.cos(angle), math.sin(angle)
    return np.asarray(local @ np.array([[c, s], [-s, c]]) + np.asarray(centre, dtype=float)[:2])


def marker_centre(pose: Sequence[float], offset: Sequence[float] = (0.0, 0.0)) -> np.ndarray:
    """World centre (2,) [m] of the marker of a robot at ``pose`` (x, y, θ) whose marker
    sits at ``offset`` (robot frame: x forward, y left) [m] from the axle centre."""
    x, y, th = (float(v) for v in pose[:3])
    c, s = math.cos(th), math.sin(th)
    return np.array([x + c * offset[0] - s * offset[1], y + s * offset[0] + c * offset[1]])


class Renderer:
    """Renders frames of one camera: floor texture, fiducials and robots.

    ``fiducials`` maps ArUco id → world centre (x, y) [m] (axis-aligned, side
    ``fiducial_size`` [m]); robot markers have side ``marker_size`` [m] and
    sit at ``marker_offset`` (robot frame) [m] from the axle centre."""

    def __init__(
        self,
        camera: PinholeCamera,
        fiducials: Mapping[int, Sequence[float]],
        *,
        marker_size: float = 0.05,
        marker_offset: Sequence[float] = (0.0, 0.0),
        fiducial_size: float = 0.08,
        dictionary: str = "DICT_4X4_50",
        floor_seed: int = 0,
    ) -> None:
        self.camera = camera
        self.fiducials = {int(k): (float(v[0]), float(v[1])) for k, v in fiducials.items()}
        self.marker_size = float(marker_size)
        self.marker_offset = (float(marker_offset[0]), float(marker_offset[1]))
        self.fiducial_size = float(fiducial_size)
        self.dictionary = dictionary
        ss = SUPERSAMPLE
        self.lens = lens_map(camera)
        """Where the ideal image is drawn and how the lens bends it (None: no distortion)."""
        ox, oy = self.lens.offset if self.lens is not None else (0, 0)
        canvas = self.lens.canvas if self.lens is not None else (camera.width, camera.height)
        # final px p ↔ supersampled px ss·p + (ss − 1)/2 (pixel centres at integers)
        S = np.array([[ss, 0.0, (ss - 1) / 2.0], [0.0, ss, (ss - 1) / 2.0], [0.0, 0.0, 1.0]])
        self.H = S @ np.array([[1.0, 0.0, ox], [0.0, 1.0, oy], [0.0, 0.0, 1.0]]) @ camera.homography()
        """Floor → supersampled ideal canvas homography (3, 3)."""
        self.size = (canvas[0] * ss, canvas[1] * ss)
        self._markers: dict[int, np.ndarray] = {}
        self._static = self._render_floor(floor_seed)
        for fid, pos in self.fiducials.items():
            self._paste_marker(self._static, fid, pos, 0.0, self.fiducial_size)
        self._work = self._static.copy()
        """Supersampled scratch image: robots are pasted into it, their regions are
        downsampled into the frame, then restored from ``_static``."""
        self._small = cv2_module().resize(self._static, canvas, interpolation=cv2_module().INTER_AREA)
        """The static scene on the ideal canvas at the camera's resolution, float32."""

    def _render_floor(self, seed: int) -> np.ndarray:
        """Grey floor with low-frequency shading and tile seams every 0.5 m, float32 (H·ss, W·ss)."""
        cv2 = cv2_module()
        rng = np.random.default_rng(seed)
        w, h = self.size
        coarse = rng.normal(0.0, 1.0, (h // 96 + 2, w // 96 + 2)).astype(np.float32)
        shade = cv2.resize(coarse, (w, h), interpolation=cv2.INTER_CUBIC)
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
        r2 = ((xx - w / 2) / w) ** 2 + ((yy - h / 2) / h) ** 2
        floor = (150.0 + 10.0 * shade) * (1.0 - 0.35 * r2)
        img = np.clip(floor, 0, 255).astype(np.float32)
        # tile seams: projected world lines, anti-aliased
        for k in np.arange(-5.0, 5.01, 0.5):
            for a, b in (((k, -5.0), (k, 5.0)), ((-5.0, k), (5.0, k))):
                pts = np.linspace(a, b, 200)
                depth = np.column_stack([pts, np.ones(len(pts))]) @ self.H[2]
                front = depth > 0.05  # in front of the camera
                if front.sum() < 2:
                    continue
                uv = _apply(self.H, pts[front])
                poly = np.round(uv * 16).astype(np.int32).reshape(-1, 1, 2)
                cv2.polylines(img, [poly], False, 120.0, 2, cv2.LINE_AA, shift=4)
        return img

    def _marker_src(self, marker_id: int) -> np.ndarray:
        if marker_id not in self._markers:
            self._markers[marker_id] = marker_image(marker_id, self.dictionary, 24).astype(np.float32)
        return self._markers[marker_id]

    def _paste_marker(
        self, img: np.ndarray, marker_id: int, centre: Sequence[float] | np.ndarray, angle: float, size: float
    ) -> None:
        """Warp marker ``marker_id`` (side ``size`` [m], x axis at ``angle`` [rad], centre
        (x, y) [m]) into ``img`` (float32, supersampled) with an anti-aliased alpha."""
        cv2 = cv2_module()
        src = self._marker_src(marker_id)
        n = src.shape[0]
        bits = n / 24 - 2  # marker bits including the black border
        s = size / (bits * 24)  # [m] per source pixel
        c, sn = math.cos(angle), math.sin(angle)
        mid = (n - 1) / 2.0
        # source px (u, v) → marker-local (s(u − mid), −s(v − mid)) → world
        A = np.array([[s, 0.0, -s * mid], [0.0, -s, s * mid], [0.0, 0.0, 1.0]])
        Rw = np.array([[c, -sn, centre[0]], [sn, c, centre[1]], [0.0, 0.0, 1.0]])
        M = self.H @ Rw @ A
        quad = _apply(M, np.array([[-0.5, -0.5], [n - 0.5, -0.5], [n - 0.5, n - 0.5], [-0.5, n - 0.5]]))
        x0, y0 = np.floor(quad.min(axis=0)).astype(int) - 2
        x1, y1 = np.ceil(quad.max(axis=0)).astype(int) + 2
        x0, y0 = max(x0, 0), max(y0, 0)
        x1, y1 = min(x1, self.size[0]), min(y1, self.size[1])
        if x1 <= x0 or y1 <= y0:
            return
        T = np.array([[1.0, 0.0, -x0], [0.0, 1.0, -y0], [0.0, 0.0, 1.0]]) @ M
        dsize = (int(x1 - x0), int(y1 - y0))
        warped = cv2.warpPerspective(src, T, dsize, flags=cv2.INTER_LINEAR, borderValue=0.0)
        alpha = cv2.warpPerspective(
            np.ones_like(src),
            T,
            dsize,
            flags=cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=0.0,
        )
        roi = img[y0:y1, x0:x1]
        roi[:] = roi * (1.0 - alpha) + warped * alpha

    def _paste_body(self, img: np.ndarray, pose: Sequence[float]) -> None:
        """The robot's dark body disc (radius BODY_RADIUS [m]) under its marker."""
        cv2 = cv2_module()
        a = np.linspace(0.0, 2.0 * math.pi, 96, endpoint=False)
        ring = np.column_stack([pose[0] + BODY_RADIUS * np.cos(a), pose[1] + BODY_RADIUS * np.sin(a)])
        poly = np.round(_apply(self.H, ring) * 16).astype(np.int32).reshape(-1, 1, 2)
        cv2.fillPoly(img, [poly], 60.0, cv2.LINE_AA, shift=4)

    def _roi(self, pose: Sequence[float]) -> tuple[int, int, int, int]:
        """Supersampled pixel box (x0, y0, x1, y1), aligned to SUPERSAMPLE, that holds a
        robot's body and marker (quiet zone included)."""
        ss = SUPERSAMPLE
        reach = max(
            BODY_RADIUS, math.hypot(*self.marker_offset) + self.marker_size * 0.5 * math.sqrt(2) * 8 / 6
        )
        reach += 0.01
        box = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * reach + np.asarray(pose[:2], dtype=float)
        uv = _apply(self.H, box)
        x0, y0 = (math.floor(v / ss) * ss - ss for v in uv.min(axis=0))
        x1, y1 = (math.ceil(v / ss) * ss + ss for v in uv.max(axis=0))
        return max(x0, 0), max(y0, 0), min(x1, self.size[0]), min(y1, self.size[1])

    def render(
        self,
        robots: Mapping[int, Sequence[float]],
        *,
        blur: float = 0.8,
        noise: float = 2.0,
        seed: int = 0,
    ) -> np.ndarray:
        """One frame (height, width) uint8 with the robots at ``robots``: marker id →
        axle-centre pose (x [m], y [m], θ [rad], world frame).  ``blur`` is the
        Gaussian σ [px] (0: none), ``noise`` the additive noise σ [grey levels]."""
        cv2 = cv2_module()
        ss = SUPERSAMPLE
        out = self._small.copy()
        rois = []
        for mid, pose in robots.items():
            rois.append(self._roi(pose))
            self._paste_body(self._work, pose)
            c = marker_centre(pose, self.marker_offset)
            self._paste_marker(self._work, int(mid), c, float(pose[2]), self.marker_size)
        for x0, y0, x1, y1 in rois:
            if x1 > x0 and y1 > y0:
                size = ((x1 - x0) // ss, (y1 - y0) // ss)
                patch = cv2.resize(self._work[y0:y1, x0:x1], size, interpolation=cv2.INTER_AREA)
                out[y0 // ss : y1 // ss, x0 // ss : x1 // ss] = patch
        for x0, y0, x1, y1 in rois:
            self._work[y0:y1, x0:x1] = self._static[y0:y1, x0:x1]
        return _sensor(out, self.lens, blur, noise, seed)


def _sensor(out: np.ndarray, lens: LensMap | None, blur: float, noise: float, seed: int) -> np.ndarray:
    """The ideal image ``out`` (height, width) float32 through the lens (None: none), the
    optics' blur (Gaussian σ [px]) and the sensor's noise (σ [grey levels], seeded), quantised
    to uint8."""
    cv2 = cv2_module()
    if lens is not None:
        out = lens.apply(out)
    if blur > 0:
        out = cv2.GaussianBlur(out, (0, 0), blur)
    if noise > 0:
        out += noise * np.random.default_rng(seed).standard_normal(out.shape, dtype=np.float32)
    return np.asarray(np.clip(np.rint(out), 0, 255).astype(np.uint8))


def random_poses(
    rng: np.random.Generator, n: int, half: float = 0.9, spacing: float = 0.12
) -> dict[int, tuple[float, float, float]]:
    """n robot poses (x, y, θ) [m, m, rad], world frame, drawn from ``rng`` in
    [−half, half]² [m], markers at least ``spacing`` [m] apart, keyed by marker ids 1..n."""
    out: dict[int, tuple[float, float, float]] = {}
    while len(out) < n:
        p = (
            float(rng.uniform(-half, half)),
            float(rng.uniform(-half, half)),
            float(rng.uniform(-math.pi, math.pi)),
        )
        if all(math.hypot(p[0] - q[0], p[1] - q[1]) > spacing for q in out.values()):
            out[len(out) + 1] = p
    return out


def board_view(
    camera: PinholeCamera,
    board: CharucoBoardSpec,
    R: np.ndarray,
    t: np.ndarray,
    *,
    px_per_square: int = 40,
    background: float = 110.0,
    blur: float = 0.8,
    noise: float = 2.0,
    seed: int = 0,
) -> np.ndarray:
    """One frame (height, width) uint8 of the ChArUco ``board`` (printed with a white margin
    of one square) at pose ``R`` (3, 3), ``t`` (3,) [m]: board frame → camera frame
    (x right, y down, z forward), in front of ``background`` [grey level], through the lens."""
    cv2 = cv2_module()
    ss = SUPERSAMPLE
    cols, rows = board.squares
    q = int(px_per_square)
    tex = board.board().generateImage(((cols + 2) * q, (rows + 2) * q), marginSize=q, borderBits=1)
    tex = np.asarray(tex, dtype=np.float32)
    s = board.square / q  # [m] per texture px
    A = np.array([[s, 0.0, 0.5 * s - board.square], [0.0, s, 0.5 * s - board.square], [0.0, 0.0, 1.0]])
    R = np.asarray(R, dtype=float).reshape(3, 3)
    t = np.asarray(t, dtype=float).reshape(3)
    w_m, h_m = board.size
    corners = np.array([[-board.square, -board.square, 0], [w_m + board.square, h_m + board.square, 0]])
    if np.any((corners @ R.T + t)[:, 2] <= 0.01):
        raise ValueError("the board is not in front of the camera")
    lens = lens_map(camera)
    ox, oy = lens.offset if lens is not None else (0, 0)
    canvas = lens.canvas if lens is not None else (camera.width, camera.height)
    S = np.array([[ss, 0.0, (ss - 1) / 2.0 + ss * ox], [0.0, ss, (ss - 1) / 2.0 + ss * oy], [0.0, 0.0, 1.0]])
    G = S @ camera.intrinsics() @ np.column_stack([R[:, 0], R[:, 1], t]) @ A
    big = cv2.warpPerspective(tex, G, (canvas[0] * ss, canvas[1] * ss), flags=cv2.INTER_LINEAR,
                              borderMode=cv2.BORDER_CONSTANT, borderValue=float(background))  # fmt: skip
    out = np.asarray(cv2.resize(big, canvas, interpolation=cv2.INTER_AREA), dtype=np.float32)
    return _sensor(out, lens, blur, noise, seed)


def board_poses(
    camera: PinholeCamera, board: CharucoBoardSpec, n: int, *, fill: float = 0.35, tilt: float = 0.5,
    seed: int = 0,
) -> list[tuple[np.ndarray, np.ndarray]]:  # fmt: skip
    """``n`` board poses (R (3, 3), t (3,) [m], board → camera frame) for an intrinsic
    calibration: the board's centre on a jittered grid over the whole image (corners and
    edges included), its width about ``fill`` of the image width, turned up to ``tilt``
    [rad] about its x and y axes, random in sign (seeded)."""
    rng = np.random.default_rng(seed)
    K = camera.intrinsics()
    w_m, h_m = board.size
    depth = K[0, 0] * w_m / (fill * camera.width)
    gx = max(2, math.ceil(math.sqrt(n * camera.width / camera.height)))
    gy = max(2, math.ceil(n / gx))
    cells = [(i, j) for j in range(gy) for i in range(gx)]
    order = rng.permutation(len(cells))
    out = []
    for k in range(n):
        i, j = cells[order[k % len(cells)]]
        u = (i + 0.5 + rng.uniform(-0.3, 0.3)) / gx * camera.width
        v = (j + 0.5 + rng.uniform(-0.3, 0.3)) / gy * camera.height
        ideal = undistort_points(np.array([[u, v]]), K, camera.distortion)[0] if camera.distorted else (u, v)
        z = depth * rng.uniform(0.85, 1.15)
        centre = np.array([(ideal[0] - K[0, 2]) / K[0, 0] * z, (ideal[1] - K[1, 2]) / K[1, 1] * z, z])
        a, b, c = rng.uniform(-tilt, tilt), rng.uniform(-tilt, tilt), rng.uniform(-0.3, 0.3)
        Rx = np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
        Ry = np.array([[math.cos(b), 0, math.sin(b)], [0, 1, 0], [-math.sin(b), 0, math.cos(b)]])
        Rz = np.array([[math.cos(c), -math.sin(c), 0], [math.sin(c), math.cos(c), 0], [0, 0, 1]])
        R = Rx @ Ry @ Rz
        out.append((R, centre - R @ np.array([w_m / 2.0, h_m / 2.0, 0.0])))
    return out


def write_video(
    path: str | Path,
    renderer: Renderer,
    trajectories: Mapping[int, PoseFn],
    duration: float,
    fps: float = 20.0,
    *,
    blur: float = 0.8,
    noise: float = 2.0,
    seed: int = 0,
    quality: int = 95,
) -> int:
    """Write an MJPG ``.avi`` of the robots moving along ``trajectories`` (marker id →
    pose function of t [s]); frame i shows time t = i / ``fps`` [s], for
    t < ``duration`` [s].  Returns the number of frames, after checking that
    the file reads back with that many frames of the camera's size.
    Raises OSError if the file cannot be written or read back."""
    cv2 = cv2_module()
    n = max(1, math.ceil(duration * fps - 1e-9))
    size = (renderer.camera.width, renderer.camera.height)
    out = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), float(fps), size, True)
    if not out.isOpened():
        raise OSError(f"{path}: cannot open an MJPG video writer")
    out.set(cv2.VIDEOWRITER_PROP_QUALITY, float(quality))
    try:
        for i in range(n):
            t = i / fps
            poses = {mid: fn(t) for mid, fn in trajectories.items()}
            gray = renderer.render(poses, blur=blur, noise=noise, seed=seed * 1_000_003 + i)
            out.write(cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR))
    finally:
        out.release()
    cap = cv2.VideoCapture(str(path))
    try:
        count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        ok, frame = cap.read()
    finally:
        cap.release()
    if not ok or frame is None or frame.shape[:2] != (size[1], size[0]) or count != n:
        raise OSError(f"{path}: the written video does not read back ({count} of {n} frames)")
    return n


def circling(cx: float, cy: float, r: float, w: float, phase: float) -> PoseFn:
    """A robot driving a circle about (cx, cy) [m] of radius ``r`` [m] at ``w`` [rad/s]
    (negative: clockwise) from angle ``phase`` [rad], heading along the circle."""

    def pose(t: float) -> tuple[float, float, float]:
        a = phase + w * t
        return (cx + r * math.cos(a), cy + r * math.sin(a), a + math.copysign(math.pi / 2, w))

    return pose


def straight_lines(scn: Any, speed: float = 0.05) -> dict[int, PoseFn]:
    """Each marked robot of scenario ``scn`` drives from its start to its goal at ``speed``
    [m/s], facing the goal, then stops: marker id → pose function of t [s]."""
    out: dict[int, PoseFn] = {}
    for r in scn.robots:
        if r.marker is None:
            continue
        sx, sy, sth = r.start
        gx, gy = r.goal
        dist = math.hypot(gx - sx, gy - sy)
        th = math.atan2(gy - sy, gx - sx) if dist > 1e-9 else sth

        def pose(t: float, sx: float = sx, sy: float = sy, gx: float = gx, gy: float = gy, th: float = th,
                 dist: float = dist) -> tuple[float, float, float]:  # fmt: skip
            f = min(1.0, speed * t / dist) if dist > 1e-9 else 1.0
            return (sx + f * (gx - sx), sy + f * (gy - sy), th)

        out[r.marker] = pose
    return out


def scene_renderer(scn: Any, **camera: Any) -> Renderer:
    """A renderer for scenario ``scn`` (needs a ``[camera]`` table) with a camera from
    :meth:`PinholeCamera.viewing` over the arena and fiducials (``camera``: its keywords)."""
    cam = scn.camera
    xmin, xmax, ymin, ymax = scn.arena
    pts = [(xmin, ymin), (xmax, ymin), (xmax, ymax), (xmin, ymax)] + [f.position for f in cam.fiducials]
    return Renderer(
        PinholeCamera.viewing(np.array(pts), **camera),
        {f.id: f.position for f in cam.fiducials},
        marker_size=cam.marker_size,
        marker_offset=cam.marker_offset,
        dictionary=cam.dictionary,
    )


def main(argv: list[str] | None = None) -> int:
    """``python -m camera_tools.synth``; returns the exit code (0 done, 2 bad input)."""
    ap = argparse.ArgumentParser(prog="python -m camera_tools.synth", description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", required=True, help="scenario TOML with a [camera] table and robot markers")
    out = ap.add_mutually_exclusive_group(required=True)
    out.add_argument("--video", help="write an MJPG .avi of the robots driving start → goal")
    out.add_argument("--image", help="write one frame (PNG) of the robots at their starts")
    ap.add_argument("--duration", type=float, default=10.0, help="video length [s] (default 10)")
    ap.add_argument("--fps", type=float, default=20.0, help="video frame rate [1/s] (default 20)")
    ap.add_argument("--seed", type=seed_arg, default=0, help="noise seed")
    args = ap.parse_args(argv)
    try:
        import cv2  # noqa: F401
    except ImportError:
        print(f"tracker: error: {OPENCV_MISSING}", file=sys.stderr)
        return 2
    from ground.scenario import ConfigError, load_scenario

    try:
        scn = load_scenario(args.scenario)
        if scn.camera is None:
            raise ConfigError("camera", "missing [camera] table (fiducials and marker size)")
        for i, r in enumerate(scn.robots):
            if r.marker is None:
                raise ConfigError(f"robots[{i}].marker", "missing: every robot needs an ArUco id")
        if not (args.duration > 0 and args.fps > 0):
            raise ConfigError("--duration/--fps", "must be > 0")
    except ConfigError as e:
        print(f"tracker: error: {e}", file=sys.stderr)
        return 2
    renderer = scene_renderer(scn)
    traj = straight_lines(scn)
    if args.image:
        frame = renderer.render({m: fn(0.0) for m, fn in traj.items()}, seed=args.seed)
        if not cv2_module().imwrite(args.image, frame):
            print(f"tracker: error: --image: {args.image}: cannot write", file=sys.stderr)
            return 2
        print(f"wrote {args.image}")
        return 0
    try:
        n = write_video(args.video, renderer, traj, args.duration, args.fps, seed=args.seed)
    except OSError as e:
        print(f"tracker: error: --video: {e}", file=sys.stderr)
        return 2
    print(f"wrote {args.video}: {n} frames at {args.fps:g} fps")
    return 0


if __name__ == "__main__":
    sys.exit(main())
