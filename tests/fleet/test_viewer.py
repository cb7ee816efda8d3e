"""The recording renders in the Rerun web viewer, driven in headless Chromium over DevTools.

``rerun --serve-web --bind 127.0.0.1`` serves the ``.rrd`` of a 3-robot ``fleet run``;
Debian's chromium loads the viewer with every network-reaching feature off and
host names resolving to nothing but loopback.  The screenshot must show the
recording drawn: every robot's colour (the supervisor gives each robot one)
on screen, the loading page gone.  A plain ``--screenshot`` only ever shows the
loading page; this waits for the real thing, bounded.
"""

from __future__ import annotations

import base64
import io
import json
import os
import queue
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
import urllib.parse
import urllib.request
from pathlib import Path
from typing import IO

import pytest
from procfs import group_alive

from supervisor.recorder import robot_colour
from transport.net import free_port

ROOT = Path(__file__).resolve().parents[2]
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
RERUN = Path(sys.executable).parent / "rerun"

# No Chromium feature that reaches the network: no background networking, updates,
# sync, QUIC, safe browsing, metrics or domain reliability, and DNS mapped to nothing
# except loopback.  A fresh profile per run.
FLAGS = [
    "--headless=new",
    "--no-sandbox",
    "--disable-gpu",
    "--enable-unsafe-swiftshader",
    "--use-angle=swiftshader",
    "--disable-quic",
    "--no-first-run",
    "--no-default-browser-check",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--disable-default-apps",
    "--disable-extensions",
    "--disable-domain-reliability",
    "--disable-client-side-phishing-detection",
    "--safebrowsing-disable-auto-update",
    "--metrics-recording-only",
    "--host-resolver-rules=MAP * ~NOTFOUND , EXCLUDE 127.0.0.1",
    "--remote-debugging-address=127.0.0.1",
    "--remote-debugging-port=0",
    "--window-size=1280,800",
]
RENDER_TIMEOUT = 240.0
"""Seconds allowed for the viewer's wasm to load under the software rasteriser [s]."""

pytestmark = pytest.mark.slow  # a recording rendered in a browser


def _lines(stream: IO[str]) -> queue.Queue[str]:
    q: queue.Queue[str] = queue.Queue()

    def pump() -> None:
        for line in stream:
            q.put(line)

    threading.Thread(target=pump, daemon=True).start()
    return q


def _wait_line(q: queue.Queue[str], pattern: str, timeout: float, what: str) -> re.Match[str]:
    deadline = time.monotonic() + timeout
    seen = []
    while time.monotonic() < deadline:
        try:
            line = q.get(timeout=max(0.01, deadline - time.monotonic()))
        except queue.Empty:
            break
        seen.append(line)
        m = re.search(pattern, line)
        if m:
            return m
    raise AssertionError(f"{what} not ready within {timeout} s:\n{''.join(seen[-20:])}")


class DevTools:
    """A minimal DevTools-protocol client of one page."""

    def __init__(self, ws_url: str):
        import websocket

        self.ws = websocket.create_connection(ws_url, timeout=RENDER_TIMEOUT)
        self.n = 0

    def call(self, method: str, **params: object) -> dict:
        self.n += 1
        self.ws.send(json.dumps({"id": self.n, "method": method, "params": params}))
        for _ in range(100_000):  # events interleave with the reply; bounded
            msg = json.loads(self.ws.recv())
            if msg.get("id") == self.n:
                assert "error" not in msg, msg
                return msg["result"]
        raise AssertionError(f"no reply to {method}")

    def screenshot(self) -> bytes:
        return base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])

    def evaluate(self, expr: str) -> object:
        return self.call("Runtime.evaluate", expression=expr, returnByValue=True, awaitPromise=True)[
            "result"
        ].get("value")


def colour_pixels(png: bytes, rgb: tuple[int, int, int], tol: int = 10) -> int:
    """Pixels of the screenshot within ``tol`` of ``rgb`` on every channel."""
    import numpy as np
    from PIL import Image

    img = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=int)
    return int((np.abs(img - np.array(rgb)).max(axis=2) <= tol).sum())


def rendered(png: bytes, robots: int, min_pixels: int = 40) -> bool:
    """The screenshot shows the recording: every robot's colour covers some pixels."""
    return all(colour_pixels(png, robot_colour(i)) >= min_pixels for i in range(robots))


def _stop(p: subprocess.Popen) -> None:
    """End ``p`` and everything it started: each is the leader of its own process group
    (the ``rerun`` entry point runs the viewer binary as a child; chromium has many)."""
    try:
        os.killpg(p.pid, signal.SIGTERM)
        p.wait(timeout=10)
    except (ProcessLookupError, subprocess.TimeoutExpired):
        pass
    try:  # whatever of the group is left, helpers included
        os.killpg(p.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
    p.wait(timeout=10)


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    out = tmp_path_factory.mktemp("viewer")
    env = {**os.environ, "RERUN_ANALYTICS": "0", "OMP_NUM_THREADS": "1"}
    res = subprocess.run(
        [sys.executable, "-m", "fleet.cli", "run", str(ROOT / "scenarios" / "paper_three_robots.toml"),
         "--out", str(out)],
        cwd=ROOT, env=env, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert res.returncode == 0, res.stderr[-2000:]
    return out / "recording.rrd"


def test_recording_renders_in_headless_chromium(recording, tmp_path):
    if CHROMIUM is None:
        if os.environ.get("CI"):
            pytest.fail("chromium is not installed; .ci/run installs Debian's chromium package")
        pytest.skip("chromium is not installed (apt-get install chromium)")
    # Rerun's analytics off in a private config directory, before the viewer starts.
    env = {
        **os.environ,
        "RERUN_ANALYTICS": "0",
        "XDG_CONFIG_HOME": str(tmp_path / "config"),
        "XDG_DATA_HOME": str(tmp_path / "data"),
    }
    subprocess.run([str(RERUN), "analytics", "disable"], env=env, capture_output=True, timeout=60, check=True)
    conf = json.loads((tmp_path / "config" / "rerun" / "analytics.json").read_text())
    assert conf["analytics_enabled"] is False

    web, grpc = free_port(), free_port()
    server = subprocess.Popen(
        [str(RERUN), "--serve-web", "--bind", "127.0.0.1", "--web-viewer-port", str(web), "--port", str(grpc),
         str(recording)],
        env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, stdin=subprocess.DEVNULL, text=True,
        start_new_session=True,
    )  # fmt: skip
    browser = None
    try:
        assert server.stderr is not None
        _wait_line(_lines(server.stderr), r"Hosting a web-viewer at", 60, "rerun --serve-web")
        browser = subprocess.Popen(
            [CHROMIUM, *FLAGS, f"--user-data-dir={tmp_path / 'profile'}", "about:blank"],
            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, stdin=subprocess.DEVNULL, text=True,
            start_new_session=True,
        )  # fmt: skip
        assert browser.stderr is not None
        m = _wait_line(
            _lines(browser.stderr), r"DevTools listening on ws://127\.0\.0\.1:(\d+)/", 60, "chromium"
        )
        targets = json.load(urllib.request.urlopen(f"http://127.0.0.1:{m.group(1)}/json/list", timeout=30))
        page = DevTools(next(t for t in targets if t["type"] == "page")["webSocketDebuggerUrl"])
        page.call("Page.enable")
        # The check can fail: a blank page has none of the robots' colours.
        assert not rendered(page.screenshot(), 3)

        source = urllib.parse.quote(f"rerun+http://127.0.0.1:{grpc}/proxy", safe="")
        page.call("Page.navigate", url=f"http://127.0.0.1:{web}/?url={source}")
        deadline = time.monotonic() + RENDER_TIMEOUT
        shot, state = b"", None
        while time.monotonic() < deadline:
            # Wait inside the page for a rendered frame and a second, then look.
            state = page.evaluate(
                "new Promise(r => requestAnimationFrame(() => setTimeout(() => r(JSON.stringify({"
                "text: document.body ? document.body.innerText.slice(0, 200) : '',"
                "canvas: [...document.querySelectorAll('canvas')].map(c => [c.width, c.height])"
                "})), 1000)))"
            )
            shot = page.screenshot()
            if rendered(shot, 3):
                break
        (tmp_path / "viewer.png").write_bytes(shot)
        info = json.loads(str(state))
        assert rendered(shot, 3), (
            f"viewer not rendered within {RENDER_TIMEOUT} s: {info} ({tmp_path / 'viewer.png'})"
        )
        assert "Loading" not in info["text"]
        assert any(w >= 1000 and h >= 500 for w, h in info["canvas"]), info
    finally:
        if browser is not None:
            _stop(browser)
        _stop(server)
    # Nothing of the viewer or the browser outlives the test.
    for leader in (server, browser):
        if leader is not None:
            left = group_alive(leader.pid)
            for _ in range(200):  # SIGKILL was sent; give the kernel a moment, bounded
                if not left:
                    break
                threading.Event().wait(0.05)
                left = group_alive(leader.pid)
            assert not left, f"still running after the test: {left}"
