"""`--screenshot PNG`: load the viewer page in headless Chromium, wait until the splats are drawn, save a PNG.

Chromium (Debian `chromium`) is driven over its DevTools protocol with the `websockets` client viser already
depends on, so nothing else is needed (no chromedriver, no selenium). "The splats are drawn" is tested, not
guessed: the page is captured with the map hidden until two captures agree (the page has settled), then with the
map shown until the picture differs from the map-less one over at least `min_changed` of its pixels and two
captures agree again (the splat sort and draw have finished).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import tempfile
import time
import urllib.request
from pathlib import Path

import numpy as np

from swarmsplat.kernels.errors import SwarmsplatError

BROWSERS = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")
# As root Chromium needs --no-sandbox; the rest keep a headless run off the network and quick to start.
FLAGS = ["--headless", "--disable-gpu", "--disable-quic", "--no-first-run", "--disable-background-networking",
         "--disable-component-update", "--disable-sync", "--hide-scrollbars", "--mute-audio",
         "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--remote-debugging-port=0",
         "--remote-allow-origins=*"]


# Closes viser's "Software WebGL rendering detected" notice (headless Chromium renders WebGL on the CPU): clicks
# the close button of the notification holding that text. Returns how many it closed.
DISMISS_JS = """(() => { let n = 0;
  for (const b of document.querySelectorAll('button')) {
    let p = b.parentElement;
    for (let i = 0; i < 3 && p; i++, p = p.parentElement) {
      if ((p.textContent || '').includes('Software WebGL rendering')) { b.click(); n++; break; }
    }
  }
  return n; })()"""


class ScreenshotError(SwarmsplatError):
    """No browser, or the page did not draw in time."""


def find_browser() -> str | None:
    """Path of a Chromium executable: $SWARMSPLAT_CHROMIUM, else the first of BROWSERS on PATH."""
    env = os.environ.get("SWARMSPLAT_CHROMIUM")
    if env:
        return env if Path(env).is_file() else None
    for name in BROWSERS:
        p = shutil.which(name)
        if p:
            return p
    return None


def require_browser() -> str:
    """find_browser(), or ScreenshotError saying how to get one."""
    browser = find_browser()
    if browser is None:
        raise ScreenshotError("--screenshot needs Chromium, which is not installed (Debian: apt-get install "
                              "chromium; or set SWARMSPLAT_CHROMIUM to its path)")
    return browser


class _Page:
    """One DevTools websocket session to a page: call(method, **params) -> result."""

    def __init__(self, ws_url: str):
        from websockets.sync.client import connect

        self.ws = connect(ws_url, max_size=None, open_timeout=20)
        self._id = 0

    def call(self, method: str, timeout: float = 60.0, **params) -> dict:
        self._id += 1
        self.ws.send(json.dumps({"id": self._id, "method": method, "params": params}))
        t_end = time.monotonic() + timeout
        while True:
            msg = json.loads(self.ws.recv(timeout=max(0.1, t_end - time.monotonic())))
            if msg.get("id") == self._id:
                if "error" in msg:
                    raise ScreenshotError(f"Chromium refused {method}: {msg['error'].get('message')}")
                return msg.get("result", {})

    def png(self) -> bytes:
        import base64

        return base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])

    def close(self) -> None:
        self.ws.close()


def _decode(png: bytes) -> np.ndarray:
    import cv2

    return cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)


def changed_fraction(a: np.ndarray, b: np.ndarray, tol: int = 12) -> float:
    """Fraction of pixels whose colour differs by more than `tol` (0-255) in any channel."""
    if a.shape != b.shape:
        return 1.0
    return float(np.mean(np.abs(a.astype(np.int16) - b.astype(np.int16)).max(axis=2) > tol))


def _settle(page: _Page, deadline: float, *, differ_from: np.ndarray | None = None, min_changed: float = 0.0,
            stable: float = 0.002, every: float = 0.5) -> tuple[bytes, np.ndarray] | None:
    """Capture until two captures in a row agree (and, with differ_from, differ from it); None at the deadline."""
    prev = None
    while time.monotonic() < deadline:
        png = page.png()
        img = _decode(png)
        if prev is not None and changed_fraction(prev, img) <= stable:
            if differ_from is None or changed_fraction(differ_from, img) >= min_changed:
                return png, img
        prev = img
        time.sleep(every)
    return None


def _dismiss_notice(page: _Page, until: float) -> None:
    """Close the software-rendering notice once it is there (it appears shortly after the page loads)."""
    while time.monotonic() < until:
        r = page.call("Runtime.evaluate", expression=DISMISS_JS, returnByValue=True)
        if r.get("result", {}).get("value"):
            return
        time.sleep(0.25)


def _start_browser(browser: str, profile: str, width: int, height: int) -> tuple[subprocess.Popen, str]:
    cmd = [browser, *FLAGS, f"--user-data-dir={profile}", f"--window-size={width},{height}", "about:blank"]
    if hasattr(os, "geteuid") and os.geteuid() == 0:
        cmd.insert(1, "--no-sandbox")
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    port_file = Path(profile) / "DevToolsActivePort"
    t_end = time.monotonic() + 30
    while time.monotonic() < t_end:
        if proc.poll() is not None:
            raise ScreenshotError(f"{browser} exited with code {proc.returncode} before it was ready")
        if port_file.is_file() and port_file.read_text().strip():
            port = int(port_file.read_text().split()[0])
            return proc, f"http://127.0.0.1:{port}"
        time.sleep(0.1)
    proc.kill()
    raise ScreenshotError(f"{browser} did not open its DevTools port within 30 s")


def _page_ws(devtools: str) -> str:
    with urllib.request.urlopen(f"{devtools}/json/list", timeout=10) as r:
        targets = json.loads(r.read())
    for t in targets:
        if t.get("type") == "page" and t.get("webSocketDebuggerUrl"):
            return t["webSocketDebuggerUrl"]
    raise ScreenshotError("Chromium has no page to drive")


def take_screenshot(viewer, out: str | Path, *, width: int = 1280, height: int = 800, timeout: float = 120.0,
                    min_changed: float = 0.002) -> Path:
    """Open `viewer.url` in headless Chromium, wait until its splats are drawn, write the page as PNG to `out`
    (atomically). ScreenshotError when there is no Chromium or nothing was drawn within `timeout` seconds."""
    from swarmsplat.kernels.fileio import atomic_write_bytes

    browser = require_browser()
    if "map" not in viewer.layers():
        raise ScreenshotError("the scene has no Gaussian map to wait for")
    deadline = time.monotonic() + timeout
    profile = tempfile.mkdtemp(prefix="swarmsplat-chromium-")
    proc = None
    try:
        proc, devtools = _start_browser(browser, profile, width, height)
        page = _Page(_page_ws(devtools))
        try:
            page.call("Page.enable")
            page.call("Emulation.setDeviceMetricsOverride", width=width, height=height, deviceScaleFactor=1,
                      mobile=False)
            viewer.set_layer_visible("map", False)
            page.call("Page.navigate", url=viewer.url)
            if not viewer.wait_for_client(max(1.0, deadline - time.monotonic())):
                raise ScreenshotError(f"the page {viewer.url} did not connect to the viewer within {timeout:.0f} s")
            _dismiss_notice(page, min(deadline, time.monotonic() + 5.0))
            base = _settle(page, deadline)
            if base is None:
                raise ScreenshotError(f"the page did not settle within {timeout:.0f} s")
            viewer.set_layer_visible("map", True)
            got = _settle(page, deadline, differ_from=base[1], min_changed=min_changed)
            if got is None:
                raise ScreenshotError(f"the splats were not drawn within {timeout:.0f} s (the page changed on less "
                                      f"than {100 * min_changed:.1f} % of its pixels)")
        finally:
            page.close()
        return atomic_write_bytes(out, got[0])
    finally:
        if proc is not None:
            proc.terminate()
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        shutil.rmtree(profile, ignore_errors=True)
