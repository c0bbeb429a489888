"""A real headless browser for the live view's tests: Debian's chromium driven by its
chromedriver over the W3C WebDriver protocol (plain HTTP + JSON on 127.0.0.1, five calls, so no
client library is needed). scripts/setup.sh installs both (apt packages chromium,
chromium-driver). Without them the tests skip, except under CI, where they fail
(test/conftest.py: "no headless browser" skips may not happen there).
"""

from __future__ import annotations

import base64
import io
import json
import os
import shutil
import socket
import subprocess
import tempfile
import time
import urllib.error
import urllib.request

import pytest

# the flags of every headless run: no sandbox (root in CI containers), no GPU, nothing that
# talks to the network on its own (QUIC, background networking, component updates, sync)
CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic",
                  "--no-first-run", "--disable-background-networking",
                  "--disable-component-update", "--disable-sync", "--disable-dev-shm-usage"]


def browser_paths() -> tuple[str, str] | None:
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    driver = shutil.which("chromedriver")
    return (chromium, driver) if chromium and driver else None


def require_browser() -> tuple[str, str]:
    found = browser_paths()
    if found is None:
        pytest.skip("no headless browser: chromium and chromedriver not found (scripts/setup.sh "
                    "installs the Debian packages chromium and chromium-driver)")
    return found


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


class Browser:
    """One chromedriver and one headless chromium session (a fresh profile directory)."""

    def __init__(self, width: int = 900, height: int = 700, start_timeout: float = 120.0):
        chromium, driver = require_browser()
        self.profile = tempfile.mkdtemp(prefix="mapf_view_chromium_")
        self.port = _free_port()
        # chromedriver is no ROS process, but it inherits no discovery range wider than loopback
        self.driver = subprocess.Popen([driver, f"--port={self.port}"],
                                       env={**os.environ, "ROS_AUTOMATIC_DISCOVERY_RANGE":
                                            "LOCALHOST"},
                                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        self.session = None
        try:
            deadline = time.monotonic() + start_timeout
            while True:  # chromedriver answers /status once it listens
                try:
                    self._call("GET", "/status", timeout=5)
                    break
                except (urllib.error.URLError, ConnectionError, OSError):
                    if time.monotonic() > deadline or self.driver.poll() is not None:
                        raise RuntimeError("chromedriver did not start")
                    time.sleep(0.2)
            caps = {"capabilities": {"alwaysMatch": {"browserName": "chrome", "goog:chromeOptions": {
                "binary": chromium,
                "args": CHROMIUM_FLAGS + [f"--user-data-dir={self.profile}",
                                          f"--window-size={width},{height}"]}}}}
            self.session = self._call("POST", "/session", caps, timeout=start_timeout)["sessionId"]
            # the viewport itself, exactly (a window's size includes the browser's own frame);
            # device scale 1: one CSS pixel is one pixel of the screenshot
            self._call("POST", f"/session/{self.session}/goog/cdp/execute", {
                "cmd": "Emulation.setDeviceMetricsOverride",
                "params": {"width": width, "height": height, "deviceScaleFactor": 1,
                           "mobile": False}})
        except BaseException:
            self.close()
            raise

    def _call(self, method: str, path: str, body=None, timeout: float = 60.0):
        data = None if body is None else json.dumps(body).encode()
        request = urllib.request.Request(f"http://127.0.0.1:{self.port}{path}", data=data,
                                         method=method,
                                         headers={"Content-Type": "application/json"})
        with urllib.request.urlopen(request, timeout=timeout) as response:
            return json.loads(response.read())["value"]

    def open(self, url: str) -> None:
        self._call("POST", f"/session/{self.session}/url", {"url": url}, timeout=120)

    def run(self, script: str):
        """The value of a JavaScript function body (`return ...;`) in the page."""
        return self._call("POST", f"/session/{self.session}/execute/sync",
                          {"script": script, "args": []})

    def wait_for(self, script: str, timeout: float = 60.0, alive=None):
        """Poll `script` until it returns something truthy; that value (AssertionError after
        `timeout` s). `alive()`, called at each poll, may raise to give up early."""
        deadline = time.monotonic() + timeout
        while True:
            if alive is not None:
                alive()
            value = self.run(script)
            if value:
                return value
            if time.monotonic() > deadline:
                raise AssertionError(f"the page never satisfied: {script}")
            time.sleep(0.2)

    def screenshot(self):
        """The viewport as a PIL RGB image."""
        from PIL import Image

        png = base64.b64decode(self._call("GET", f"/session/{self.session}/screenshot"))
        return Image.open(io.BytesIO(png)).convert("RGB")

    def close(self) -> None:
        if self.session is not None:
            try:
                self._call("DELETE", f"/session/{self.session}", timeout=30)
            except (urllib.error.URLError, OSError):
                pass
            self.session = None
        if self.driver.poll() is None:
            self.driver.terminate()
            try:
                self.driver.wait(10)
            except subprocess.TimeoutExpired:
                self.driver.kill()
                self.driver.wait()
        shutil.rmtree(self.profile, ignore_errors=True)

    def __enter__(self) -> "Browser":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# ---- reading the picture ----------------------------------------------------------------------
OBSTACLE_RGB = (0x26, 0x26, 0x26)  # static/index.html: obstacle cells
FREE_RGB = (0xFF, 0xFF, 0xFF)


def close_to(pixel, rgb, tolerance: int = 24) -> bool:
    return all(abs(int(a) - int(b)) <= tolerance for a, b in zip(pixel, rgb))


def cell_pixel(image, row: int, col: int, cell: int, dx: float = 0.5, dy: float = 0.5,
               height: int | None = None):
    """The pixel at (dx, dy) of cell (row, col) (fractions of the cell; 0.5, 0.5 its centre);
    the page draws row 0 at the bottom of a map of `height` rows (the map frame's way, as RViz),
    the canvas at the page's top-left corner."""
    return image.getpixel((int((col + dx) * cell), int((height - 1 - row + dy) * cell)))


def check_picture(image, grid, robots, colours, cell: int) -> None:
    """Assert that `image` shows the map `grid` (every obstacle cell dark, every free cell
    without a robot light: white, or a path's or goal's tint, never obstacle-dark) and each robot
    i as a disc of colours[i] ("#rrggbb") on its cell."""
    import numpy as np

    grid = np.asarray(grid)
    problems = []
    for (row, col), value in np.ndenumerate(grid):
        # near a corner of the cell: off its border, the disc, the goal square and the path line
        pixel = cell_pixel(image, row, col, cell, 0.1, 0.1, grid.shape[0])
        if value and not close_to(pixel, OBSTACLE_RGB):
            problems.append(f"obstacle cell {(row, col)} shows {pixel}")
        if not value and close_to(pixel, OBSTACLE_RGB, 60):
            problems.append(f"free cell {(row, col)} looks like an obstacle: {pixel}")
    for i, (row, col) in enumerate(robots):
        want = tuple(int(colours[i][k:k + 2], 16) for k in (1, 3, 5))
        # on the disc above its centre: the robot's number is drawn at the centre
        pixel = cell_pixel(image, row, col, cell, 0.5, 0.25, grid.shape[0])
        if not close_to(pixel, want):
            problems.append(f"robot {i} at {(row, col)}: pixel {pixel}, expected {want}")
    assert not problems, "\n".join(problems[:20])
