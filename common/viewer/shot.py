"""``needletrack screenshot``: a picture of the viewer's page on a graph that runs, made by the
graph itself (the README's docs/launch.png).

It launches the graph (default ``dataflow.yaml``, every node as ``needletrack launch`` starts
it), reads the viewer's URL from the viewer's own line (``viewer: http://...``), waits until the
page's numbers hold the final method's pose with its error against the truth, lets the plots
fill for ``--settle`` seconds, screenshots the page in headless Chromium
(``common.viewer.browser``), prints the monitor's newest line and stops the graph.

    needletrack screenshot --out docs/launch.png [GRAPH.yaml] [--size 1600x900] [--settle 20]
"""
from __future__ import annotations

import argparse
import io
import json
import re
import sys
import threading
import time
import urllib.request
from pathlib import Path

from common.runtime.graph import LAUNCHER_IDENTITY, REPO_ROOT, GraphError, load_graph
from common.runtime.launcher import Launcher
from common.runtime.node import graph_param_errors
from common.runtime.zenoh_session import tls_file_errors
from common.viewer.browser import find_chromium, screenshot

URL_LINE = re.compile(r"^\[(?P<node>[^\]]+)\] viewer: (?P<url>http://\S+/)$")
MONITOR_LINE = re.compile(r"^\[(?P<node>[^\]]+)\] (?P<line>seq +\d+ .*)$")


class LaunchOutput(io.TextIOBase):
    """The launcher's output, passed on to ``out`` and read on the way: the viewer's URL and
    each monitor's newest line."""

    def __init__(self, out, viewer: str, monitors: set):
        self.out, self.viewer, self.monitors = out, viewer, monitors
        self.url = None
        self.monitor_line = None
        self.url_seen = threading.Event()

    def write(self, text: str) -> int:
        self.out.write(text)
        for line in text.splitlines():
            m = URL_LINE.match(line)
            if m and m["node"] == self.viewer:
                self.url = m["url"]
                self.url_seen.set()
            m = MONITOR_LINE.match(line)
            if m and m["node"] in self.monitors:
                self.monitor_line = m["line"]
        return len(text)

    def flush(self) -> None:
        self.out.flush()


def page_state(url: str) -> dict:
    """The page's numbers (``state.json``); {} while it does not answer."""
    try:
        with urllib.request.urlopen(url + "state.json", timeout=5) as r:
            return json.load(r)
    except (OSError, ValueError):
        return {}


def final_posed(state: dict) -> bool:
    """Whether the page shows the final method's pose with its error against the truth."""
    row = (state.get("methods") or {}).get(state.get("final") or "", {})
    return row.get("pos_err_mm") is not None


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="needletrack screenshot", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("graph", nargs="?", default="dataflow.yaml", help="graph YAML with a viewer node (default: dataflow.yaml)")
    p.add_argument("--out", required=True, help="the PNG to write (the README's: docs/launch.png)")
    p.add_argument("--size", default="1600x900", help="the browser's viewport, WxH px")
    p.add_argument("--settle", type=float, default=20.0,
                   help="seconds to let the plots fill once the final pose is on the page")
    p.add_argument("--timeout", type=float, default=300.0,
                   help="seconds to wait for the final method's pose before giving up")
    a = p.parse_args(argv)
    try:
        w, h = (int(x) for x in a.size.lower().split("x"))
    except ValueError:
        p.error(f"--size {a.size!r}: expected WxH, e.g. 1600x900")
    if find_chromium() is None:
        print("needletrack screenshot: chromium not found (Debian: apt-get install -y chromium)", file=sys.stderr)
        return 2
    path = Path(a.graph)
    if not path.exists() and a.graph == "dataflow.yaml":
        path = REPO_ROOT / "dataflow.yaml"
    try:
        graph = load_graph(path)
        viewers = [n.id for n in graph.nodes if n.module == "viewer"]
        if not viewers:
            raise GraphError(["no viewer node (module viewer) to screenshot"], str(path))
        errors = graph_param_errors(graph) + tls_file_errors(graph, [LAUNCHER_IDENTITY] + graph.ids())
        if errors:
            raise GraphError(errors, str(path))
        out = LaunchOutput(sys.stdout, viewers[0], {n.id for n in graph.nodes if n.module == "monitor"})
        launcher = Launcher(graph, out=out)
    except GraphError as exc:
        print(str(exc), file=sys.stderr)
        return 2
    runner = threading.Thread(target=launcher.run, name="launcher", daemon=True)
    try:
        launcher.start()
        runner.start()
        deadline = time.monotonic() + a.timeout
        if not out.url_seen.wait(max(0.0, deadline - time.monotonic())):
            raise TimeoutError(f"the viewer printed no URL within {a.timeout:g} s")
        while not final_posed(page_state(out.url)):
            if time.monotonic() > deadline or not runner.is_alive():
                raise TimeoutError(f"no pose of the final method with its error on {out.url} within {a.timeout:g} s")
            time.sleep(0.5)
        launcher.say(f"the final pose is on the page: {a.settle:g} s for the plots", "screenshot")
        time.sleep(a.settle)
        screenshot(out.url, a.out, wait_s=3.0, size=(w, h))
        state = page_state(out.url)
    except (RuntimeError, TimeoutError) as exc:
        print(f"needletrack screenshot: {exc}", file=sys.stderr)
        return 1
    finally:
        launcher.stop()
        if runner.is_alive():
            runner.join(60)          # run() returns through shutdown(): every node stopped
        else:
            launcher.shutdown()
    launcher.say(f"{a.out} ({w}x{h}): {state.get('head', '')}", "screenshot")
    if out.monitor_line:
        launcher.say(f"the monitor's newest line: {out.monitor_line}", "screenshot")
    return 0


if __name__ == "__main__":
    sys.exit(main())
