"""Headless Chromium driven over the DevTools protocol (``Chromium``: navigate, evaluate, mouse
and keys, screenshots), and a screenshot of a web page: the page is opened, left to run for
``wait_s`` seconds of real time (its scripts polling, WebGL drawing), then captured. Used by the
viewer's and the labelling page's browser tests and to make docs/viewer.png and docs/label.png.

    python -m common.viewer.browser URL OUT.png [--wait 5] [--size 1400x900] [--webgl]
"""
from __future__ import annotations

import argparse
import base64
import contextlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--disable-dev-shm-usage", "--hide-scrollbars"]
WEBGL_FLAGS = ["--use-angle=swiftshader", "--enable-unsafe-swiftshader"]


def find_chromium() -> str | None:
    """The Chromium executable (Debian's ``chromium`` first), or None."""
    for name in ("chromium", "chromium-browser", "google-chrome"):
        path = shutil.which(name)
        if path:
            return path
    return None


class Chromium:
    """Headless Chromium with one page, driven over the DevTools protocol (a context manager):
    ``navigate(url)``, ``evaluate(js)`` (the value of a JavaScript expression, promises awaited),
    ``click(x, y)`` and ``drag`` (real mouse events at CSS pixels of the viewport), ``key(name)``
    (a key press: ``"Enter"``, ``"ArrowRight"``, ``"n"``...), ``wheel``, ``screenshot()`` (PNG
    bytes). Raises RuntimeError when Chromium is missing, does not start or answers an error."""

    KEYS = {"Enter": 13, "Backspace": 8, "Delete": 46, "Escape": 27, "ArrowLeft": 37, "ArrowUp": 38,
            "ArrowRight": 39, "ArrowDown": 40, " ": 32}

    def __init__(self, size=(1400, 900), webgl: bool = False, timeout_s: float = 60.0):
        self.size, self.webgl, self.timeout_s = tuple(size), webgl, timeout_s
        self._ids = iter(range(1, 1 << 30))

    def __enter__(self) -> "Chromium":
        from websockets.sync.client import connect

        exe = find_chromium()
        if exe is None:
            raise RuntimeError("chromium not found (apt-get install -y chromium)")
        self._profile = tempfile.mkdtemp(prefix="needletrack-chromium-")
        self._stack = contextlib.ExitStack()
        cmd = [exe, *FLAGS, *(WEBGL_FLAGS if self.webgl else []), f"--user-data-dir={self._profile}",
               f"--window-size={self.size[0]},{self.size[1]}", "--remote-debugging-port=0", "about:blank"]
        self._proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            port_file = Path(self._profile) / "DevToolsActivePort"
            deadline = time.monotonic() + self.timeout_s
            while not (port_file.exists() and port_file.read_text().strip()):
                if self._proc.poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError(f"chromium did not start (exit {self._proc.poll()})")
                time.sleep(0.1)
            port = int(port_file.read_text().split()[0])
            import urllib.request
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=10) as r:
                page = next(t for t in json.load(r) if t.get("type") == "page")
            self._ws = self._stack.enter_context(connect(page["webSocketDebuggerUrl"], max_size=None,
                                                         open_timeout=self.timeout_s))
            self.call("Emulation.setDeviceMetricsOverride", width=self.size[0], height=self.size[1],
                      deviceScaleFactor=1, mobile=False)
        except BaseException:
            self._stop()
            raise
        return self

    def __exit__(self, *exc):
        self._stop()

    def _stop(self):
        self._stack.close()
        self._proc.terminate()
        try:
            self._proc.wait(10)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.wait()
        shutil.rmtree(self._profile, ignore_errors=True)

    def call(self, method: str, **params) -> dict:
        i = next(self._ids)
        self._ws.send(json.dumps({"id": i, "method": method, "params": params}))
        while True:
            msg = json.loads(self._ws.recv(timeout=self.timeout_s))
            if msg.get("id") == i:
                if "error" in msg:
                    raise RuntimeError(f"{method}: {msg['error']}")
                return msg.get("result", {})

    def navigate(self, url: str) -> None:
        self.call("Page.navigate", url=url)

    def evaluate(self, expression: str):
        r = self.call("Runtime.evaluate", expression=expression, returnByValue=True, awaitPromise=True)
        if "exceptionDetails" in r:
            raise RuntimeError(f"evaluate {expression[:80]!r}: {r['exceptionDetails'].get('text')} "
                               f"{r['exceptionDetails'].get('exception', {}).get('description', '')}")
        return r.get("result", {}).get("value")

    def wait_for(self, expression: str, timeout_s: float = 30.0):
        """The value of ``expression`` once it is truthy (polled every 50 ms); RuntimeError after
        ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        while True:
            v = self.evaluate(expression)
            if v:
                return v
            if time.monotonic() > deadline:
                raise RuntimeError(f"{expression[:120]!r} still false after {timeout_s:g} s")
            time.sleep(0.05)

    def _mouse(self, kind: str, x: float, y: float, button: str = "left", buttons: int = 0, **kw):
        self.call("Input.dispatchMouseEvent", type=kind, x=float(x), y=float(y), button=button,
                  buttons=buttons, **kw)

    def click(self, x: float, y: float, button: str = "left") -> None:
        self._mouse("mouseMoved", x, y, "none")
        self._mouse("mousePressed", x, y, button, 1, clickCount=1)
        self._mouse("mouseReleased", x, y, button, 0, clickCount=1)

    def drag(self, x0: float, y0: float, x1: float, y1: float, steps: int = 5, button: str = "left") -> None:
        self._mouse("mouseMoved", x0, y0, "none")
        self._mouse("mousePressed", x0, y0, button, 1, clickCount=1)
        for k in range(1, steps + 1):
            self._mouse("mouseMoved", x0 + (x1 - x0) * k / steps, y0 + (y1 - y0) * k / steps, button, 1)
        self._mouse("mouseReleased", x1, y1, button, 0, clickCount=1)

    def wheel(self, x: float, y: float, delta_y: float) -> None:
        self._mouse("mouseWheel", x, y, "none", deltaX=0.0, deltaY=float(delta_y))

    def key(self, key: str) -> None:
        code = self.KEYS.get(key, ord(key.upper()) if len(key) == 1 else 0)
        text = key if len(key) == 1 else ("\r" if key == "Enter" else "")
        self.call("Input.dispatchKeyEvent", type="keyDown", key=key, windowsVirtualKeyCode=code,
                  **({"text": text} if text else {}))
        self.call("Input.dispatchKeyEvent", type="keyUp", key=key, windowsVirtualKeyCode=code)

    def screenshot(self) -> bytes:
        return base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])


def screenshot(url: str, out: str | os.PathLike, wait_s: float = 5.0, size=(1400, 900),
               webgl: bool = False, timeout_s: float = 60.0) -> bytes:
    """Open ``url``, wait ``wait_s`` s, write a PNG of the viewport (``size`` px) to ``out`` and
    return its bytes. Raises RuntimeError when Chromium is missing or does not answer."""
    with Chromium(size, webgl, timeout_s) as b:
        b.navigate(url)
        time.sleep(wait_s)
        png = b.screenshot()
    Path(out).write_bytes(png)
    return png


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m common.viewer.browser", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("url")
    p.add_argument("out")
    p.add_argument("--wait", type=float, default=5.0, help="seconds to let the page run")
    p.add_argument("--size", default="1400x900", help="viewport WxH")
    p.add_argument("--webgl", action="store_true", help="SwiftShader WebGL (for Rerun's viewer)")
    a = p.parse_args(argv)
    w, h = (int(x) for x in a.size.split("x"))
    screenshot(a.url, a.out, a.wait, (w, h), a.webgl)
    print(a.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
