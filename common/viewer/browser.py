"""A screenshot of a web page in headless Chromium, driven over the DevTools protocol: the page
is opened, left to run for ``wait_s`` seconds of real time (its scripts polling, WebGL drawing),
then captured. Used by the viewer's browser test and to make docs/viewer.png.

    python -m common.viewer.browser URL OUT.png [--wait 5] [--size 1400x900] [--webgl]
"""
from __future__ import annotations

import argparse
import base64
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


def screenshot(url: str, out: str | os.PathLike, wait_s: float = 5.0, size=(1400, 900),
               webgl: bool = False, timeout_s: float = 60.0) -> bytes:
    """Open ``url``, wait ``wait_s`` s, write a PNG of the viewport (``size`` px) to ``out`` and
    return its bytes. Raises RuntimeError when Chromium is missing or does not answer."""
    from websockets.sync.client import connect

    exe = find_chromium()
    if exe is None:
        raise RuntimeError("chromium not found (apt-get install -y chromium)")
    profile = tempfile.mkdtemp(prefix="needletrack-chromium-")
    cmd = [exe, *FLAGS, *(WEBGL_FLAGS if webgl else []), f"--user-data-dir={profile}",
           f"--window-size={size[0]},{size[1]}", "--remote-debugging-port=0", "about:blank"]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        port_file = Path(profile) / "DevToolsActivePort"
        deadline = time.monotonic() + timeout_s
        while not (port_file.exists() and port_file.read_text().strip()):
            if proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"chromium did not start (exit {proc.poll()})")
            time.sleep(0.1)
        port = int(port_file.read_text().split()[0])
        import urllib.request
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=10) as r:
            page = next(t for t in json.load(r) if t.get("type") == "page")
        with connect(page["webSocketDebuggerUrl"], max_size=None, open_timeout=timeout_s) as ws:
            ids = iter(range(1, 1 << 30))

            def call(method, **params):
                i = next(ids)
                ws.send(json.dumps({"id": i, "method": method, "params": params}))
                while True:
                    msg = json.loads(ws.recv(timeout=timeout_s))
                    if msg.get("id") == i:
                        if "error" in msg:
                            raise RuntimeError(f"{method}: {msg['error']}")
                        return msg.get("result", {})

            call("Emulation.setDeviceMetricsOverride", width=size[0], height=size[1],
                 deviceScaleFactor=1, mobile=False)
            call("Page.navigate", url=url)
            time.sleep(wait_s)
            png = base64.b64decode(call("Page.captureScreenshot", format="png")["data"])
        Path(out).write_bytes(png)
        return png
    finally:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        shutil.rmtree(profile, ignore_errors=True)


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
