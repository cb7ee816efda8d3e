"""``fleet markers`` (camera_tools/markers.py): printable ArUco markers at their true size.

Three independent reads of the output:

* the PDF's page content is parsed (its filled paths, in points): every marker's black
  square is ``marker_size`` to 0.001 pt, where the layout put it, with the cells of its id;
* the pages are rendered (``pdftoppm`` when installed, else the same matplotlib figures
  on Agg at a known DPI) and detected back with the tracker's ArUco detector: ids, side
  length [px] / DPI = ``marker_size`` within 2 %, the forward arrow along the marker's x
  axis (corner 0 → 1), a 100 mm ruler;
* the PNGs are detected the same way, and carry their DPI.
"""

from __future__ import annotations

import io
import re
import shutil
import subprocess
import zlib
from pathlib import Path

import numpy as np
import pytest

from ground.scenario import load_scenario

cv2 = pytest.importorskip("cv2")

from camera_tools import markers as M  # noqa: E402
from tracker.vision import make_detector  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
SCENARIO = ROOT / "deploy" / "lab_three_robots.toml"
DPI = 150
"""Rendering resolution of the pages [px/in]: a 5 cm marker spans 295 px."""
PT = M.INCH / 72.0
"""One PDF point [m]."""
PAGE_PT = {"a4": (595.2756, 841.8898), "letter": (612.0, 792.0)}
"""Paper sizes [pt] (ISO 216 A4 = 210 × 297 mm; US letter = 8.5 × 11 in)."""


@pytest.fixture(scope="module")
def scn():
    return load_scenario(SCENARIO)


def expected_ids(scn) -> list[int]:
    return [r.marker for r in scn.robots] + [f.id for f in scn.camera.fiducials]


# --------------------------------------------------------------------------- PDF content


def pdf_pages(data: bytes) -> list[tuple[tuple[float, float], bytes]]:
    """(MediaBox width, height [pt], decompressed content stream) of each page, in order."""
    objects = {int(m.group(1)): m.group(2) for m in re.finditer(rb"(?ms)^(\d+) 0 obj\s*(.*?)^endobj", data)}
    kids = re.search(rb"/Type /Pages.*?/Kids \[([^\]]*)\]", data, re.S)
    assert kids is not None, "no page tree"
    out = []
    for ref in re.findall(rb"(\d+) 0 R", kids.group(1)):
        page = objects[int(ref)]
        box = re.search(rb"/MediaBox \[\s*0 0 ([\d.]+) ([\d.]+)\s*\]", page)
        contents = re.search(rb"/Contents (\d+) 0 R", page)
        assert box is not None and contents is not None, page[:200]
        body = objects[int(contents.group(1))]
        stream = re.search(rb"stream\r?\n(.*)\r?\nendstream", body, re.S)
        assert stream is not None
        raw = stream.group(1)
        content = zlib.decompress(raw) if b"/FlateDecode" in body.split(b"stream")[0] else raw
        out.append(((float(box.group(1)), float(box.group(2))), content))
    return out


def filled_paths(content: bytes) -> list[list[np.ndarray]]:
    """The filled paths of a content stream: each a list of subpaths (k, 2) [pt], in
    page coordinates (the current transformation matrix applied).

    Enough of PDF for matplotlib's output: q/Q/cm, the m/l/h/re path operators and
    the f/f*/B/B* fills; text blocks are dropped."""
    content = re.sub(rb"\bBT\b.*?\bET\b", b"", content, flags=re.S)
    ctm = np.eye(3)  # row-vector convention: [x y 1] @ ctm
    saved: list[np.ndarray] = []
    stack: list[float] = []
    subpaths: list[list[tuple[float, float]]] = []
    fills: list[list[np.ndarray]] = []

    def page(x: float, y: float) -> tuple[float, float]:
        u = np.array([x, y, 1.0]) @ ctm
        return float(u[0]), float(u[1])

    for tok in content.split():
        try:
            stack.append(float(tok))
            continue
        except ValueError:
            pass
        if tok == b"q":
            saved.append(ctm.copy())
        elif tok == b"Q":
            ctm = saved.pop()
        elif tok == b"cm":
            a, b, c, d, e, f = stack[-6:]
            ctm = np.array([[a, b, 0.0], [c, d, 0.0], [e, f, 1.0]]) @ ctm
        elif tok == b"m":
            subpaths.append([page(stack[-2], stack[-1])])
        elif tok == b"l":
            subpaths[-1].append(page(stack[-2], stack[-1]))
        elif tok == b"re":
            x, y, w, h = stack[-4:]
            subpaths.append([page(x, y), page(x + w, y), page(x + w, y + h), page(x, y + h)])
        elif tok in (b"f", b"f*", b"B", b"B*"):
            fills.append([np.array(sp, dtype=float) for sp in subpaths])
            subpaths = []
        elif tok in (b"S", b"n"):
            subpaths = []
        stack = []
    return fills


def marker_cells(subpaths: list[np.ndarray], n: int) -> tuple[np.ndarray, np.ndarray, float] | None:
    """If the fill is an n×n-cell marker (axis-aligned rectangles on a square grid): its
    centre (2,) [pt], its cells (n, n) bool (row 0 on top) and its side [pt]; else None."""
    pts = np.vstack(subpaths)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    side = float(hi[0] - lo[0])
    if side < 10.0 or abs(float(hi[1] - lo[1]) - side) > 1e-3:
        return None
    cell = side / n
    grid = np.zeros((n, n), dtype=bool)
    for s in subpaths:
        (x0, y0), (x1, y1) = s.min(axis=0), s.max(axis=0)
        if len(s) not in (4, 5) or not np.all(np.isin(s[:, 0], [x0, x1]) & np.isin(s[:, 1], [y0, y1])):
            return None
        c0, c1 = round((x0 - lo[0]) / cell), round((x1 - lo[0]) / cell)
        r0, r1 = round((hi[1] - y1) / cell), round((hi[1] - y0) / cell)
        grid[r0:r1, c0:c1] = True
    return (lo + hi) / 2.0, grid, side


@pytest.mark.parametrize("paper", ["a4", "letter"])
def test_pdf_pages_hold_every_marker_at_its_printed_size(tmp_path, scn, paper, capsys):
    out = tmp_path / "m.pdf"
    assert M.main([str(SCENARIO), "--out", str(out), "--paper", paper]) == 0
    line = capsys.readouterr().out.strip()
    pages = M.layout(scn, paper)
    assert line.startswith(f"wrote {out}: 7 markers on {len(pages)} {paper} page(s)")
    data = out.read_bytes()
    assert b"/Subtype /Image" not in data, "markers must be vector paths, not images"
    parsed = pdf_pages(data)
    assert len(parsed) == len(pages) == 2
    side_pt = scn.camera.marker_size / PT
    n = M.marker_bits(0, scn.camera.dictionary).shape[0]
    seen = []
    for (box, content), page in zip(parsed, pages, strict=True):
        assert box == pytest.approx(PAGE_PT[paper], abs=0.01)
        found = [m for m in (marker_cells(f, n) for f in filled_paths(content)) if m is not None]
        assert len(found) == len(page.placements)
        for centre, grid, side in found:
            assert side == pytest.approx(side_pt, abs=1e-3)  # 50 mm = 141.732 pt, unscaled
            pl = min(page.placements, key=lambda p: np.hypot(*(np.array(p.centre) / PT - centre)))
            assert np.array(pl.centre) / PT == pytest.approx(centre, abs=1e-3)
            assert np.array_equal(grid, M.marker_bits(pl.marker.marker_id, scn.camera.dictionary))
            seen.append(pl.marker.marker_id)
    assert sorted(seen) == sorted(expected_ids(scn))


# --------------------------------------------------------------------------- rendered pages


def render(pdf: Path, scn, paper: str, dpi: int) -> tuple[str, list[np.ndarray]]:
    """Grey page images (H, W) uint8 at ``dpi``: the PDF through pdftoppm when it is
    installed, else the same figures (:func:`camera_tools.markers.page_figure`) on Agg."""
    exe = shutil.which("pdftoppm")
    if exe is not None:
        subprocess.run([exe, "-r", str(dpi), "-gray", "-png", str(pdf), str(pdf.with_suffix(""))], check=True)
        files = sorted(pdf.parent.glob(pdf.stem + "-*.png"), key=lambda p: int(p.stem.rsplit("-", 1)[1]))
        return "pdftoppm", [cv2.imread(str(f), cv2.IMREAD_GRAYSCALE) for f in files]
    import matplotlib

    images = []
    with matplotlib.rc_context():
        matplotlib.rcdefaults()
        for page in M.layout(scn, paper):
            buf = io.BytesIO()
            M.page_figure(page, scn).savefig(buf, format="png", dpi=dpi)
            images.append(cv2.imdecode(np.frombuffer(buf.getvalue(), np.uint8), cv2.IMREAD_GRAYSCALE))
    return "matplotlib", images


def detect(gray: np.ndarray, dictionary: str) -> dict[int, np.ndarray]:
    """Marker id → its corners (4, 2) [px] (u right, v down; ArUco order)."""
    corners, ids, _ = make_detector(dictionary).detectMarkers(gray)
    if ids is None:
        return {}
    return {
        int(i): np.asarray(c, dtype=float).reshape(4, 2) for i, c in zip(np.ravel(ids), corners, strict=True)
    }


def to_page(uv: np.ndarray, height_m: float, dpi: int) -> np.ndarray:
    """Pixel coordinates (u, v) → page frame (x right, y up) [m]; pixel centres at integers."""
    s = M.INCH / dpi
    return np.array([(uv[0] + 0.5) * s, height_m - (uv[1] + 0.5) * s])


@pytest.mark.parametrize("paper", ["a4", "letter"])
def test_rendered_pages_detect_back_at_the_marker_size(tmp_path, scn, paper):
    pdf = tmp_path / "m.pdf"
    pages = M.write_pdf(scn, pdf, paper)
    how, images = render(pdf, scn, paper, DPI)
    assert len(images) == len(pages), how
    size = scn.camera.marker_size
    seen = []
    for page, image in zip(pages, images, strict=True):
        w, h = page.size
        assert np.abs(np.subtract(image.shape, (h / M.INCH * DPI, w / M.INCH * DPI))).max() < 1.0, how
        found = detect(image, scn.camera.dictionary)
        assert sorted(found) == sorted(p.marker.marker_id for p in page.placements), how
        for pl in page.placements:
            c = found[pl.marker.marker_id]
            side_px = float(np.mean(np.linalg.norm(c - np.roll(c, -1, axis=0), axis=1)))
            assert side_px / DPI * M.INCH == pytest.approx(size, rel=0.02), (how, pl.marker)
            assert to_page(c.mean(axis=0), h, DPI) == pytest.approx(pl.centre, abs=0.001)
            x_axis = np.array([c[1, 0] - c[0, 0], -(c[1, 1] - c[0, 1])])  # corner 0 → 1, page frame
            x_axis /= np.linalg.norm(x_axis)
            if pl.marker.robot is not None:
                assert pl.arrow is not None
                tail, head = np.array(pl.arrow[0]), np.array(pl.arrow[1])
                assert np.dot(x_axis, (head - tail) / np.linalg.norm(head - tail)) > 0.999
                assert np.linalg.norm(head - tail) == pytest.approx(size)
            else:
                assert pl.arrow is None
            seen.append(pl.marker.marker_id)
        # The ruler: 11 centimetre ticks, 3 mm above the baseline (only they reach that high).
        x0, y0 = page.ruler
        v = round((h - (y0 + 0.003)) / M.INCH * DPI - 0.5)
        u0, u1 = round(x0 / M.INCH * DPI) - 20, round((x0 + 0.11) / M.INCH * DPI)
        ink = 255.0 - image[v, u0:u1].astype(float)
        dark = ink > 40
        runs = np.flatnonzero(np.diff(np.r_[0, dark.astype(int), 0]))
        centres = [
            u0 + np.average(np.arange(a, b), weights=ink[a:b])
            for a, b in zip(runs[::2], runs[1::2], strict=True)
        ]
        assert len(centres) == 11, (how, centres)
        ruler = (centres[-1] - centres[0]) / DPI * M.INCH
        assert ruler == pytest.approx(M.RULER_LENGTH, abs=1.5 * M.INCH / DPI), how
    assert sorted(seen) == sorted(expected_ids(scn))


# --------------------------------------------------------------------------- PNG


def test_pngs_detect_back_at_their_dpi(tmp_path, scn, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    folder = tmp_path / "png"
    assert M.main([str(SCENARIO), "--png", str(folder), "--dpi", "300"]) == 0
    out = capsys.readouterr().out
    assert out == f"wrote 7 PNGs to {folder}: black squares 591 px at 300 dpi = 50.04 mm\n"
    assert not (tmp_path / M.DEFAULT_OUT).exists()  # --png without --out: no PDF
    from PIL import Image

    size = scn.camera.marker_size
    names = {
        **{f"robot_{r.id}_marker{r.marker}.png": r.marker for r in scn.robots},
        **{f"fiducial_marker{f.id}.png": f.id for f in scn.camera.fiducials},
    }
    assert sorted(p.name for p in folder.iterdir()) == sorted(names)
    for name, mid in names.items():
        with Image.open(folder / name) as im:
            assert im.mode == "L"
            assert im.info["dpi"] == pytest.approx((300, 300), abs=0.01)
            gray = np.asarray(im)
        found = detect(gray, scn.camera.dictionary)
        assert list(found) == [mid], name
        c = found[mid]
        side_px = float(np.mean(np.linalg.norm(c - np.roll(c, -1, axis=0), axis=1)))
        assert side_px / 300 * M.INCH == pytest.approx(size, rel=0.02)
        # The quiet zone: a white frame one bit wide, then the black border.
        q = round(591 / 6)
        assert gray.shape == (591 + 2 * q, 591 + 2 * q)
        assert gray[:q].min() == gray[-q:].min() == gray[:, :q].min() == gray[:, -q:].min() == 255
        assert gray[q, q] == gray[-q - 1, -q - 1] == 0
        # Corner 0 → 1 runs left to right along the top edge (the marker's x axis).
        assert c[1, 0] - c[0, 0] > 0.99 * side_px and abs(c[1, 1] - c[0, 1]) < 2.0


def test_pdf_and_pngs_together(tmp_path, scn, capsys):
    pdf, folder = tmp_path / "a" / "m.pdf", tmp_path / "png"
    assert M.main([str(SCENARIO), "--out", str(pdf), "--png", str(folder), "--dpi", "100"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert [ln.split(":")[0] for ln in lines] == [f"wrote {pdf}", f"wrote 7 PNGs to {folder}"]
    assert pdf.is_file() and len(list(folder.glob("*.png"))) == 7


# --------------------------------------------------------------------------- bad input


BASE = """
name = "t"
duration = 10.0
[arena]
bounds = [-1.0, 1.0, -1.0, 1.0]
[[robots]]
id = "r1"
start = [-0.5, 0.0, 0.0]
goal = [0.5, 0.0]
marker = 1
[[robots]]
id = "r2"
start = [0.5, 0.0, 3.14]
goal = [-0.5, 0.0]
{r2}
{camera}
"""
CAMERA = """[camera]
marker_size = {size}
fiducials = [{{ id = 40, position = [-1.1, -1.1] }}, {{ id = 41, position = [1.1, -1.1] }},
             {{ id = 42, position = [1.1, 1.1] }}, {{ id = 43, position = [-1.1, 1.1] }}]
"""


def scenario_file(
    tmp_path: Path, r2: str = "marker = 2", camera: str | None = CAMERA, size: float = 0.05
) -> str:
    path = tmp_path / "s.toml"
    path.write_text(BASE.format(r2=r2, camera="" if camera is None else camera.format(size=size)))
    return str(path)


LINES = {
    "no camera": "fleet: error: camera: missing [camera] table",
    "no marker": "fleet: error: robots[1].marker: missing: robot 'r2' needs the ArUco id of its marker",
    "too large": "fleet: error: camera.marker_size: a 300.0 mm marker with its quiet zone (400.0 mm) "
    "does not fit on a4 paper (at most 135 mm)",
    "no file": "fleet: error: file: ",
    "low dpi": "fleet: error: --dpi: 100 dpi gives 3.3 px per bit of a 5.0 mm marker, fewer than 4; "
    "use at least 122",
    "dpi range": "fleet: error: --dpi: expected an integer in 72..4800, got 10",
    "out is a dir": "fleet: error: --out: ",
}
"""Case → the start of its one-line error."""
EXTRA = {
    "low dpi": ["--png", "P", "--dpi", "100"],
    "dpi range": ["--png", "P", "--dpi", "10"],
    "out is a dir": ["--out", "."],
}
"""Case → its options; P and . stand for paths in the test's directory."""


@pytest.mark.parametrize("case", list(LINES))
def test_bad_input_gets_one_line_and_exit_2(tmp_path, capsys, monkeypatch, case):
    monkeypatch.chdir(tmp_path)
    path = {
        "no camera": lambda: scenario_file(tmp_path, camera=None),
        "no marker": lambda: scenario_file(tmp_path, r2=""),
        "too large": lambda: scenario_file(tmp_path, size=0.3),
        "no file": lambda: str(tmp_path / "missing.toml"),
        "low dpi": lambda: scenario_file(tmp_path, size=0.005),
        "dpi range": lambda: scenario_file(tmp_path),
        "out is a dir": lambda: scenario_file(tmp_path),
    }[case]()
    extra = [str(tmp_path / a) if a in ("P", ".") else a for a in EXTRA.get(case, [])]
    line = LINES[case]
    assert M.main([path, *extra]) == 2
    cap = capsys.readouterr()
    assert cap.out == ""
    assert cap.err.count("\n") == 1 and cap.err.startswith(line), cap.err
    assert not list(tmp_path.glob("*.pdf")) and not (tmp_path / "P").exists()


def test_without_opencv_one_line_and_exit_2(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(__import__("sys").modules, "cv2", None)  # import cv2 → ImportError
    assert M.main([str(SCENARIO), "--out", str(tmp_path / "m.pdf")]) == 2
    assert capsys.readouterr().err == "fleet: error: markers need OpenCV: pip install 'epuck-fleet[camera]'\n"
    assert not (tmp_path / "m.pdf").exists()
