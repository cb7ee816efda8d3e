"""``fleet markers SCENARIO.toml [--out FILE.pdf] [--paper a4|letter] [--png DIR] [--dpi N]``

Printable ArUco markers for a scenario's camera tracker (its ``[camera]``
table, :class:`ground.scenario.CameraSpec`): every robot's marker, labelled
with the robot id, the marker id and an arrow along the robot's forward
direction, then every fiducial, labelled with its id and the world position
[m] of its centre.

PDF (``--out``, default ``markers.pdf``).  Pages of the chosen paper (A4
210 × 297 mm, letter 8.5 × 11 in) drawn by matplotlib at scale 1: a page is
one figure of exactly the paper's size and one metre of the page frame is
1/0.0254 in, so the black square of every marker (the outer edge of its
black border) measures ``camera.marker_size`` when printed at 100 % ("actual
size", not "fit to page").  Markers are vector paths, not images.  Each has a
white quiet zone one bit wide, bounded by a dashed cut line, and ticks on its
centre lines; each page has a 100 mm ruler to check the printer's scale.

Orientation.  A marker's x axis runs from its corner 0 to its corner 1: the
top edge as printed, left to right (OpenCV's ArUco convention), which is the
direction of the arrow under a robot's marker.  Mount the marker with the
arrow pointing where the robot drives (its printed top edge then lies on the
robot's left); ``camera.marker_offset`` is the marker centre relative to the
axle centre.  Fiducials may face any way: only their centres are used.

PNG (``--png DIR``, instead of the PDF unless ``--out`` is given too): one
8-bit grey image per marker, ``robot_<id>_marker<k>.png`` and
``fiducial_marker<k>.png``, the marker and its quiet zone at ``--dpi`` (default
600) with the resolution stored in the file; the black square is
round(marker_size / 0.0254 m · dpi) px.

ChArUco board (``--charuco``, instead of the markers): the calibration board of
``fleet calibrate --intrinsics`` (:data:`tracker.intrinsics.DEFAULT_BOARD`) on one
landscape page at scale 1, as vector paths, with the same 100 mm ruler
(``--out``, default ``charuco.pdf``).  Glue it flat on a rigid board.

Exit codes: 0 written; 2 bad input, with one line ``fleet: error: <field>:
<reason>`` (no OpenCV, no ``[camera]`` table, a robot without ``marker``, a
marker too large for the paper, an unusable ``--dpi`` or output path).
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ground.scenario import CameraSpec, ConfigError, Scenario, load_scenario
from tracker.intrinsics import DEFAULT_BOARD, CharucoBoardSpec

if TYPE_CHECKING:
    from matplotlib.figure import Figure

OPENCV_MISSING = "markers need OpenCV: pip install 'epuck-fleet[camera]'"
INCH = 0.0254
"""One inch [m]."""
PAPERS: dict[str, tuple[float, float]] = {"a4": (0.210, 0.297), "letter": (8.5 * INCH, 11.0 * INCH)}
"""Paper name → (width, height) [m], portrait."""
DEFAULT_OUT = "markers.pdf"
DEFAULT_DPI = 600
DPI_RANGE = (72, 4800)
"""Accepted ``--dpi`` values, inclusive."""
MIN_BIT_PX = 4
"""Fewest pixels per marker bit in a PNG."""

MARGIN = 0.012
"""Blank border of a page [m]: printers cannot print to the paper's edge."""
HEADER = 0.016
"""Height of the title band at the top of a page [m]."""
RULER_BAND = 0.018
"""Height of the ruler band at the bottom of a page [m]."""
RULER_LENGTH = 0.1
"""Length of the calibration ruler [m]."""
TICK = 0.0025
"""Length of the centre-line ticks outside a marker's cut line [m]."""
LABEL_BAND = 0.016
"""Height of the arrow and labels under a marker [m]."""
MIN_SLOT = 0.055
"""Narrowest slot of one marker [m], so its labels fit."""
GAP = (0.008, 0.006)
"""Space between slots (x, y) [m]."""


# --------------------------------------------------------------------------- what to print


@dataclass(frozen=True)
class PrintedMarker:
    """One marker to print."""

    marker_id: int
    """ArUco id in the camera's dictionary."""
    robot: str | None = None
    """The id of the robot that carries it; None for a fiducial."""
    position: tuple[float, float] | None = None
    """A fiducial's centre, world frame: x [m], y [m]; None for a robot marker."""

    @property
    def title(self) -> str:
        """First label line, e.g. ``robot r1 · marker 1`` or ``fiducial · marker 40``."""
        who = f"robot {self.robot}" if self.robot is not None else "fiducial"
        return f"{who} · marker {self.marker_id}"

    @property
    def detail(self) -> str:
        """Second label line: how to mount it."""
        if self.position is not None:
            x, y = self.position
            return f"centre at ({_signed(x)}, {_signed(y)}) m"
        return "arrow = forward, top edge = robot's left"

    @property
    def filename(self) -> str:
        """File name of its PNG."""
        if self.robot is not None:
            return f"robot_{self.robot}_marker{self.marker_id}.png"
        return f"fiducial_marker{self.marker_id}.png"


def _signed(v: float) -> str:
    return f"{v:.3f}".replace("-", "−")


def printed_markers(scn: Scenario) -> list[PrintedMarker]:
    """The robots' markers in file order, then the fiducials.  Raises
    :class:`ConfigError` without a ``[camera]`` table or for a robot without ``marker``."""
    if scn.camera is None:
        raise ConfigError(
            "camera", "missing [camera] table: no marker size, dictionary or fiducials to print"
        )
    out: list[PrintedMarker] = []
    for i, r in enumerate(scn.robots):
        if r.marker is None:
            raise ConfigError(
                f"robots[{i}].marker", f"missing: robot {r.id!r} needs the ArUco id of its marker"
            )
        out.append(PrintedMarker(marker_id=r.marker, robot=r.id))
    out += [PrintedMarker(marker_id=f.id, position=f.position) for f in scn.camera.fiducials]
    return out


def marker_bits(marker_id: int, dictionary: str = "DICT_4X4_50") -> np.ndarray:
    """The marker's cells, black border included, (n, n) bool, True = black;
    row 0 is the top row as printed, column 0 the left (corner 0 is the top left).
    n = the dictionary's marker size + 2.  Made by ``cv2.aruco.generateImageMarker``."""
    import cv2

    d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
    n = int(d.markerSize) + 2
    image = cv2.aruco.generateImageMarker(d, int(marker_id), n, borderBits=1)
    return np.asarray(image) < 128


def _bits_per_side(dictionary: str) -> int:
    return int(marker_bits(0, dictionary).shape[0])


# --------------------------------------------------------------------------- layout


@dataclass(frozen=True)
class Placement:
    """Where one marker goes on its page.  Page frame: origin at the paper's
    bottom-left corner, x to the right, y up, metres."""

    marker: PrintedMarker
    centre: tuple[float, float]
    """Centre of the marker [m], page frame."""
    arrow: tuple[tuple[float, float], tuple[float, float]] | None
    """A robot marker's forward arrow, (tail, head) [m], page frame (along the
    marker's x axis); None for a fiducial."""


@dataclass(frozen=True)
class Page:
    """One page of the PDF."""

    paper: str
    """A key of :data:`PAPERS`."""
    size: tuple[float, float]
    """(width, height) [m]."""
    number: int
    """1-based page number."""
    count: int
    """Pages in the document."""
    placements: tuple[Placement, ...]
    ruler: tuple[float, float]
    """Left end of the ruler's baseline [m], page frame; the ruler runs
    :data:`RULER_LENGTH` to the right, its ticks point up."""


def layout(scn: Scenario, paper: str = "a4") -> list[Page]:
    """Place every marker of ``scn`` (:func:`printed_markers`) on pages of
    ``paper``, row by row from the top.  Raises :class:`ConfigError` for an
    unknown paper, or a marker too large for it."""
    if paper not in PAPERS:
        raise ConfigError("--paper", f"unknown paper {paper!r} (expected one of {', '.join(PAPERS)})")
    items = printed_markers(scn)
    camera = scn.camera
    assert camera is not None
    width, height = PAPERS[paper]
    s = camera.marker_size
    cut = s * (1.0 + 2.0 / _bits_per_side(camera.dictionary))  # marker + one-bit quiet zone
    slot_w = max(cut + 2.0 * TICK, MIN_SLOT)
    slot_h = cut + 2.0 * TICK + LABEL_BAND
    use_w = width - 2.0 * MARGIN
    use_h = height - 2.0 * MARGIN - HEADER - RULER_BAND
    cols = int((use_w + GAP[0]) // (slot_w + GAP[0]))
    rows = int((use_h + GAP[1]) // (slot_h + GAP[1]))
    if cols < 1 or rows < 1:
        largest = min(use_w - 2.0 * TICK, use_h - 2.0 * TICK - LABEL_BAND) / (cut / s)
        raise ConfigError(
            "camera.marker_size",
            f"a {s * 1000:.1f} mm marker with its quiet zone ({cut * 1000:.1f} mm) does not fit on "
            f"{paper} paper (at most {math.floor(largest * 1000)} mm); use --png and print it at its size",
        )
    per_page = cols * rows
    x_left = MARGIN + (use_w - (cols * slot_w + (cols - 1) * GAP[0])) / 2.0
    y_top = height - MARGIN - HEADER
    count = math.ceil(len(items) / per_page)
    pages: list[Page] = []
    for p in range(count):
        placed: list[Placement] = []
        for k, item in enumerate(items[p * per_page : (p + 1) * per_page]):
            row, col = divmod(k, cols)
            cx = x_left + col * (slot_w + GAP[0]) + slot_w / 2.0
            top = y_top - row * (slot_h + GAP[1])
            cy = top - TICK - cut / 2.0
            arrow = None
            if item.robot is not None:
                ya = cy - cut / 2.0 - TICK - 0.0025
                arrow = ((cx - s / 2.0, ya), (cx + s / 2.0, ya))
            placed.append(Placement(marker=item, centre=(cx, cy), arrow=arrow))
        page = Page(
            paper=paper, size=(width, height), number=p + 1, count=count,
            placements=tuple(placed), ruler=(MARGIN, MARGIN + 0.004),
        )  # fmt: skip
        pages.append(page)
    return pages


# --------------------------------------------------------------------------- drawing


def marker_path(bits: np.ndarray, centre: Sequence[float], size: float) -> Any:
    """A ``matplotlib.path.Path`` of the black cells of ``bits`` ((n, n) bool,
    row 0 on top) for a marker of side ``size`` [m] centred at ``centre`` (x, y)
    [m], page frame.  One counter-clockwise rectangle per run of black cells in
    a row: with the non-zero fill rule the runs merge without seams."""
    from matplotlib.path import Path as MplPath

    n = int(bits.shape[0])
    b = size / n
    x0 = float(centre[0]) - size / 2.0
    y1 = float(centre[1]) + size / 2.0
    verts: list[tuple[float, float]] = []
    codes: list[np.uint8] = []
    for r in range(n):
        top, bottom = y1 - r * b, y1 - (r + 1) * b
        c = 0
        while c < n:
            if not bits[r, c]:
                c += 1
                continue
            end = c
            while end < n and bits[r, end]:
                end += 1
            left, right = x0 + c * b, x0 + end * b
            verts += [(left, bottom), (right, bottom), (right, top), (left, top), (left, bottom)]
            codes += [MplPath.MOVETO, MplPath.LINETO, MplPath.LINETO, MplPath.LINETO, MplPath.CLOSEPOLY]
            c = end
    return MplPath(np.array(verts, dtype=float), np.array(codes, dtype=np.uint8))


def page_figure(page: Page, scn: Scenario) -> Figure:
    """The matplotlib figure of ``page`` (Agg canvas): figure size = paper size,
    one data unit = 1 m on paper, page frame.  Save it without ``bbox_inches``."""
    from matplotlib.patches import FancyArrowPatch, PathPatch, Rectangle

    camera = scn.camera
    assert camera is not None
    width, height = page.size
    fig, ax = _blank_page(width, height)

    s = camera.marker_size
    bits_cache: dict[int, np.ndarray] = {}
    for pl in page.placements:
        mid = pl.marker.marker_id
        if mid not in bits_cache:
            bits_cache[mid] = marker_bits(mid, camera.dictionary)
        bits = bits_cache[mid]
        cx, cy = pl.centre
        cut = s * (1.0 + 2.0 / bits.shape[0])
        ax.add_patch(PathPatch(marker_path(bits, pl.centre, s), facecolor="black", edgecolor="none", lw=0))
        cut_line = Rectangle(
            (cx - cut / 2.0, cy - cut / 2.0), cut, cut, fill=False, edgecolor="0.55",
            lw=0.4, linestyle=(0, (4, 3)),
        )  # fmt: skip
        ax.add_patch(cut_line)
        h = cut / 2.0
        for (xa, ya), (xb, yb) in (
            ((cx, cy + h), (cx, cy + h + TICK)),
            ((cx, cy - h), (cx, cy - h - TICK)),
            ((cx - h, cy), (cx - h - TICK, cy)),
            ((cx + h, cy), (cx + h + TICK, cy)),
        ):
            ax.plot([xa, xb], [ya, yb], color="black", lw=0.5, solid_capstyle="butt")
        label_y = cy - h - TICK - 0.005
        if pl.arrow is not None:
            tail, head = pl.arrow
            arrow = FancyArrowPatch(
                tail, head, arrowstyle="-|>", mutation_scale=9, lw=1.0, color="black", shrinkA=0, shrinkB=0
            )
            ax.add_patch(arrow)
            label_y = tail[1] - 0.0025
        ax.text(cx, label_y, pl.marker.title, ha="center", va="top", fontsize=8.5, fontweight="bold")
        ax.text(cx, label_y - 0.0045, pl.marker.detail, ha="center", va="top", fontsize=6.5)

    n_bits = _bits_per_side(camera.dictionary)
    _header(
        ax, height,
        f"{scn.name}: ArUco {camera.dictionary}, black square {s * 1000:.1f} mm "
        f"({n_bits} × {s / n_bits * 1000:.2f} mm cells)    page {page.number}/{page.count}",
        "Print at 100 % (actual size, not 'fit to page') and check the ruler. Cut along the dashed "
        "lines: the white border belongs to the marker.",
        "Robots: the arrow points where the robot drives. Fiducials: centre at the world position "
        "shown, at the height of the robots' markers.",
    )  # fmt: skip
    _draw_ruler(ax, page.ruler)
    return fig


def _blank_page(width: float, height: float) -> tuple[Any, Any]:
    """(figure, axes) of a white page ``width`` × ``height`` [m] (Agg canvas): one data unit
    = 1 m on paper, origin at the bottom left, no axes drawn."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width / INCH, height / INCH), facecolor="white")
    FigureCanvasAgg(fig)
    ax = fig.add_axes((0.0, 0.0, 1.0, 1.0))
    ax.set_xlim(0.0, width)
    ax.set_ylim(0.0, height)
    ax.set_axis_off()
    ax.set_autoscale_on(False)
    return fig, ax


def _header(ax: Any, height: float, title: str, *notes: str) -> None:
    """A page's bold title and its lines of notes, from the top-left margin down."""
    ax.text(MARGIN, height - MARGIN, title, ha="left", va="top", fontsize=9, fontweight="bold")
    for i, note in enumerate(notes):
        ax.text(MARGIN, height - MARGIN - 0.0055 - 0.003 * i, note, ha="left", va="top", fontsize=6.5)


def _draw_ruler(ax: Any, origin: tuple[float, float]) -> None:
    """A :data:`RULER_LENGTH` ruler, baseline from ``origin`` [m] to the right, mm ticks up."""
    x0, y0 = origin
    ax.plot([x0, x0 + RULER_LENGTH], [y0, y0], color="black", lw=0.8, solid_capstyle="butt")
    n_mm = round(RULER_LENGTH * 1000)
    for mm in range(n_mm + 1):
        x = x0 + mm / 1000.0
        length = 0.004 if mm % 10 == 0 else 0.0025 if mm % 5 == 0 else 0.0015
        ax.plot([x, x], [y0, y0 + length], color="black", lw=0.4, solid_capstyle="butt")
        if mm % 10 == 0:
            label = f"{mm // 10} cm" if mm == n_mm else f"{mm // 10}"
            ax.text(x, y0 + 0.0048, label, ha="center", va="bottom", fontsize=6)
    ax.text(
        x0 + RULER_LENGTH + 0.006, y0,
        f"← this ruler measures {RULER_LENGTH * 1000:.0f} mm on a correct print",
        ha="left", va="bottom", fontsize=6.5,
    )  # fmt: skip


def write_pdf(scn: Scenario, out: str | Path, paper: str = "a4") -> list[Page]:
    """Write the markers of ``scn`` to the PDF ``out`` (parents created); returns
    its pages.  Raises :class:`ConfigError` (``--out`` when it cannot be written)."""
    import matplotlib
    from matplotlib.backends.backend_pdf import PdfPages

    pages = layout(scn, paper)
    path = Path(out)
    if path.is_dir():
        raise ConfigError("--out", f"{path}: is a directory, expected a PDF file name")
    # A user's matplotlibrc must not crop ("savefig.bbox: tight") or recolour the pages.
    with matplotlib.rc_context():
        matplotlib.rcdefaults()
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            meta = {"Title": f"ArUco markers of {scn.name}", "Creator": "epuck-fleet: fleet markers"}
            with PdfPages(path, metadata={**meta, "CreationDate": None}) as pdf:
                for page in pages:
                    pdf.savefig(page_figure(page, scn))
        except OSError as e:
            raise ConfigError("--out", f"{path}: cannot write ({e.strerror or e})") from None
    return pages


# --------------------------------------------------------------------------- ChArUco board

DEFAULT_CHARUCO_OUT = "charuco.pdf"


def charuco_figure(board: CharucoBoardSpec = DEFAULT_BOARD, paper: str = "a4") -> Figure:
    """The matplotlib figure (Agg canvas) of ``board`` on one landscape page of ``paper``:
    figure size = paper size, one data unit = 1 m on paper (page frame, y up), the board
    centred below a header and above a 100 mm ruler.  Squares and markers are vector paths;
    which squares are black and where each marker sits come from OpenCV's board, so the
    print is the board ``cv2.aruco.CharucoDetector`` looks for.  Raises
    :class:`ConfigError` (``--paper``) when the board does not fit."""
    from matplotlib.patches import PathPatch, Rectangle

    height, width = PAPERS[paper]  # landscape
    bw, bh = board.size
    if bw + 2 * MARGIN > width or bh + HEADER + RULER_BAND + 2 * MARGIN > height:
        raise ConfigError("--paper", f"a {bw * 1000:.0f} × {bh * 1000:.0f} mm board does not fit on {paper}")
    fig, ax = _blank_page(width, height)
    x0 = (width - bw) / 2.0
    top = height - MARGIN - HEADER  # board frame y = 0 (board y runs down the page)
    cv_board = board.board()
    cols, rows = board.squares
    k = 20  # px per square of the probe image
    probe = np.asarray(cv_board.generateImage((cols * k, rows * k), marginSize=0, borderBits=1))
    for r in range(rows):
        for c in range(cols):
            if probe[r * k + 1, c * k + 1] < 128:
                xy = (x0 + c * board.square, top - (r + 1) * board.square)
                ax.add_patch(
                    Rectangle(xy, board.square, board.square, facecolor="black", edgecolor="none", lw=0)
                )
    obj = cv_board.getObjPoints()
    for mid, corners in zip(np.asarray(cv_board.getIds()).reshape(-1), obj, strict=True):
        mc = np.asarray(corners, dtype=float).reshape(4, 3)
        centre = (x0 + float(mc[:, 0].mean()), top - float(mc[:, 1].mean()))
        bits = marker_bits(int(mid), board.dictionary)
        ax.add_patch(
            PathPatch(marker_path(bits, centre, board.marker), facecolor="black", edgecolor="none", lw=0)
        )
    _header(
        ax, height,
        f"ChArUco board for fleet calibrate --intrinsics: {cols} × {rows} squares of "
        f"{board.square * 1000:.1f} mm, markers {board.marker * 1000:.1f} mm, {board.dictionary}",
        "Print at 100 % (actual size) and check the ruler; glue flat on a rigid board. Show it to the "
        "camera at 8 or more places and angles, near every edge and corner of the image.",
    )  # fmt: skip
    _draw_ruler(ax, (MARGIN, MARGIN + 0.004))
    return fig


def write_charuco_pdf(out: str | Path, paper: str = "a4", board: CharucoBoardSpec = DEFAULT_BOARD) -> Path:
    """Write :func:`charuco_figure` to the PDF ``out`` (parents created); returns its path.
    Raises :class:`ConfigError` (``--out`` when it cannot be written)."""
    import matplotlib
    from matplotlib.backends.backend_pdf import PdfPages

    path = Path(out)
    if path.is_dir():
        raise ConfigError("--out", f"{path}: is a directory, expected a PDF file name")
    with matplotlib.rc_context():
        matplotlib.rcdefaults()
        fig = charuco_figure(board, paper)
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            meta = {"Title": "ChArUco calibration board", "Creator": "epuck-fleet: fleet markers --charuco"}
            with PdfPages(path, metadata={**meta, "CreationDate": None}) as pdf:
                pdf.savefig(fig)
        except OSError as e:
            raise ConfigError("--out", f"{path}: cannot write ({e.strerror or e})") from None
    return path


# --------------------------------------------------------------------------- PNG


def marker_image(marker_id: int, camera: CameraSpec, dpi: int) -> np.ndarray:
    """Marker ``marker_id`` of ``camera.dictionary`` at ``dpi``: (S + 2q, S + 2q)
    uint8, 0 black, 255 white, with S = round(marker_size / 0.0254 m · dpi) px the
    black square and q = round(S / n) px the quiet zone (n bits per side)."""
    bits = marker_bits(marker_id, camera.dictionary)
    n = int(bits.shape[0])
    side = round(camera.marker_size / INCH * dpi)
    quiet = round(side / n)
    cell = (np.arange(side) * n) // side  # bit of each pixel row/column
    image = np.full((side + 2 * quiet, side + 2 * quiet), 255, dtype=np.uint8)
    image[quiet : quiet + side, quiet : quiet + side] = np.where(bits[np.ix_(cell, cell)], 0, 255)
    return image


def check_dpi(dpi: int, camera: CameraSpec) -> None:
    """Raise :class:`ConfigError` (``--dpi``) unless ``dpi`` is in :data:`DPI_RANGE`
    and gives at least :data:`MIN_BIT_PX` px per marker bit."""
    lo, hi = DPI_RANGE
    if isinstance(dpi, bool) or not isinstance(dpi, int) or not lo <= dpi <= hi:
        raise ConfigError("--dpi", f"expected an integer in {lo}..{hi}, got {dpi!r}")
    n = _bits_per_side(camera.dictionary)
    px = camera.marker_size / INCH * dpi / n
    if px < MIN_BIT_PX:
        need = math.ceil(MIN_BIT_PX * n * INCH / camera.marker_size)
        raise ConfigError(
            "--dpi",
            f"{dpi} dpi gives {px:.1f} px per bit of a {camera.marker_size * 1000:.1f} mm marker, "
            f"fewer than {MIN_BIT_PX}; use at least {need}",
        )


def write_pngs(scn: Scenario, directory: str | Path, dpi: int = DEFAULT_DPI) -> list[Path]:
    """Write one PNG per marker of ``scn`` into ``directory`` (created) at ``dpi``;
    returns their paths.  Raises :class:`ConfigError`."""
    from PIL import Image

    items = printed_markers(scn)
    camera = scn.camera
    assert camera is not None
    check_dpi(dpi, camera)
    folder = Path(directory)
    written: list[Path] = []
    try:
        folder.mkdir(parents=True, exist_ok=True)
        for item in items:
            path = folder / item.filename
            Image.fromarray(marker_image(item.marker_id, camera, dpi)).save(path, dpi=(dpi, dpi))
            written.append(path)
    except OSError as e:
        raise ConfigError("--png", f"{folder}: cannot write ({e.strerror or e})") from None
    return written


# --------------------------------------------------------------------------- command


def add_arguments(ap: argparse.ArgumentParser) -> None:
    """The arguments of ``fleet markers`` (for a subcommand parser)."""
    ap.add_argument("scenario", help="scenario TOML with a [camera] table and a marker per robot")
    ap.add_argument("--out", help=f"output PDF (default {DEFAULT_OUT}, unless only --png is given)")
    ap.add_argument("--paper", choices=sorted(PAPERS), default="a4", help="paper size (default a4)")
    ap.add_argument(
        "--png",
        metavar="DIR",
        help="write one PNG per marker into DIR (instead of the PDF, unless --out is given)",
    )
    ap.add_argument(
        "--dpi", type=int, default=DEFAULT_DPI, help=f"resolution of the PNGs (default {DEFAULT_DPI})"
    )
    ap.add_argument(
        "--charuco", action="store_true",
        help=f"write the board of fleet calibrate --intrinsics instead (default {DEFAULT_CHARUCO_OUT})",
    )  # fmt: skip


def run(args: argparse.Namespace) -> int:
    """``fleet markers`` on parsed arguments (see :func:`add_arguments`); returns the exit code."""
    try:
        import cv2  # noqa: F401
    except ImportError:
        print(f"fleet: error: {OPENCV_MISSING}", file=sys.stderr)
        return 2
    if args.charuco:
        try:
            load_scenario(args.scenario)
            if args.png is not None:
                raise ConfigError("--png", "the ChArUco board is printed as a PDF only")
            out = write_charuco_pdf(args.out if args.out is not None else DEFAULT_CHARUCO_OUT, args.paper)
        except ConfigError as e:
            print(f"fleet: error: {e}", file=sys.stderr)
            return 2
        b = DEFAULT_BOARD
        print(
            f"wrote {out}: ChArUco board {b.squares[0]} × {b.squares[1]} squares of {b.square * 1000:.1f} mm "
            f"on {args.paper} landscape; print at 100 % and check the 100 mm ruler"
        )
        return 0
    try:
        scn = load_scenario(args.scenario)
        items = printed_markers(scn)
        camera = scn.camera
        assert camera is not None
        if args.png is not None:
            check_dpi(args.dpi, camera)
        lines = []
        if args.out is not None or args.png is None:
            out = Path(args.out if args.out is not None else DEFAULT_OUT)
            pages = write_pdf(scn, out, args.paper)
            lines.append(
                f"wrote {out}: {len(items)} markers on {len(pages)} {args.paper} page(s), black squares "
                f"{camera.marker_size * 1000:.1f} mm; print at 100 % and check the 100 mm ruler"
            )
        if args.png is not None:
            paths = write_pngs(scn, args.png, args.dpi)
            side = round(camera.marker_size / INCH * args.dpi)
            lines.append(
                f"wrote {len(paths)} PNGs to {args.png}: black squares {side} px at {args.dpi} dpi "
                f"= {side / args.dpi * INCH * 1000:.2f} mm"
            )
    except ConfigError as e:
        print(f"fleet: error: {e}", file=sys.stderr)
        return 2
    print("\n".join(lines))
    return 0


def main(argv: list[str] | None = None) -> int:
    """``fleet markers``'s entry point; returns the exit code."""
    ap = argparse.ArgumentParser(prog="fleet markers", description="Printable ArUco markers of a scenario")
    add_arguments(ap)
    return run(ap.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
