"""Launch real graphs in tests: the real launcher, real node processes, real Zenoh on loopback.

Use the ``run_graph`` fixture (tests/conftest.py); it stops every graph it started::

    def test_relay_forwards(run_graph):
        g = run_graph({"nodes": [
            {"id": "count", "module": "counter", "params": {"rate_hz": 50}},
            {"id": "relay", "module": "relay", "inputs": {"in": "count/out"}},
        ]})
        msgs = g.collect("relay/out", n=10, timeout=10)        # decoded messages
        assert [m.seq for m in msgs] == list(range(msgs[0].seq, msgs[0].seq + 10))
        assert g.stats("relay").counters["handler_errors"] == 0

or, without the fixture, ``with launch_graph(graph, tmp_path) as g: ...``.

- ``graph`` is a dict, YAML text or a path. ``graph`` (the name) and ``zenoh.listen`` are filled in
  with a unique name and a free port (a listen endpoint already given is replaced; ``tls/`` when
  the graph has ``zenoh.tls``), so two graphs never cross. The graph is written to
  ``<dir>/graph.yaml`` (``g.path``) and launched as ``python -m common.cli launch <graph.yaml>``;
  its output goes to ``g.log_path`` (``g.log()``).
- Launching waits until every launched node is live (its liveliness token) and raises with the
  launcher's log if one is not within ``timeout``.
- Keys are relative to the graph (``"relay/out"``) or absolute; wildcards work.
- ``g.subscribe(key)`` returns a ``Subscription`` that collects from now on: ``.wait(n, timeout)``,
  ``.messages``, ``.keys``, ``.undecodable``; ``g.collect(key, n)`` subscribes and waits.
- ``g.put(key, msg_or_bytes)``, ``g.command(node, name, **args)``, ``g.stats(node)`` (a fresh
  ``NodeStats``), ``g.wait_stats(node, pred)``, ``g.pids()``, ``g.live()``, ``g.swap(node, ...)``
  and ``g.cli(...)`` (run a ``needletrack`` command against this graph).
- The test's session is the operator's (the launcher identity): on the default per-run
  credentials it uses the launched run's (``common.runtime.credentials``), so ``g.graph`` is the
  graph as it runs (``zenoh.tls`` set, ``tls/`` endpoints); ``g.path`` is the file as written.
- ``g.stop()`` sends SIGTERM to the launcher, waits, returns its exit status, and fails if any
  node process it ever saw is still alive (it kills them first).
"""
from __future__ import annotations

import copy
import itertools
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Callable, Optional

import yaml

REPO = Path(__file__).resolve().parent.parent
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from common.runtime import credentials  # noqa: E402
from common.runtime.graph import Graph, launcher_key, live_key, load_graph, stats_key
from common.runtime.zenoh_session import zenoh_config
from common.runtime.messages import (  # noqa: E402
    Command,
    Message,
    MessageError,
    NodeStats,
    decode,
    encode,
)

_names = itertools.count()


def free_port() -> int:
    """A TCP port on 127.0.0.1 that is free now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def prepare_graph(graph, directory: Path) -> Path:
    """Write ``graph`` (dict, YAML text or path) to ``directory/graph.yaml`` with a unique name
    and a free loopback port; returns the path. The graph is not validated here."""
    if isinstance(graph, (str, Path)) and not (isinstance(graph, str) and "\n" in graph):
        data = yaml.safe_load(Path(graph).read_text())
    elif isinstance(graph, str):
        data = yaml.safe_load(graph)
    else:
        data = copy.deepcopy(graph)
    port = free_port()
    if isinstance(data, dict):
        data.setdefault("graph", f"t{os.getpid()}x{next(_names)}p{port}")
        z = data.get("zenoh") if isinstance(data.get("zenoh"), dict) else {}
        z["listen"] = [f"{'tls' if z.get('tls') else 'tcp'}/127.0.0.1:{port}"]
        data["zenoh"] = z
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / "graph.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def cli(*args, timeout: float = 60, check: bool = False) -> subprocess.CompletedProcess:
    """Run ``needletrack ARGS`` (as ``python -m common.cli``); returns the completed process."""
    env = dict(os.environ, PYTHONPATH=str(REPO))
    return subprocess.run([sys.executable, "-m", "common.cli", *map(str, args)], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=timeout, check=check)


class Subscription:
    """Messages received on a key since the subscription was declared."""

    def __init__(self, session, key: str, expect: Optional[type] = None):
        self.key = key
        self.messages: list = []
        self.keys: list = []
        self.undecodable: list = []
        self._cv = threading.Condition()
        self._expect = expect
        self._sub = session.declare_subscriber(key, self._on)

    def _on(self, sample) -> None:
        k = str(sample.key_expr)
        try:
            msg = decode(sample.payload.to_bytes(), self._expect)
        except MessageError as exc:
            with self._cv:
                self.undecodable.append((k, str(exc)))
            return
        with self._cv:
            self.messages.append(msg)
            self.keys.append(k)
            self._cv.notify_all()

    def wait(self, n: int, timeout: float = 10.0, where: Optional[Callable] = None) -> list:
        """Wait until ``n`` messages (that satisfy ``where``, if given) arrived; returns them (a copy).
        Raises ``TimeoutError`` saying how many came."""
        deadline = time.monotonic() + timeout
        with self._cv:
            while True:
                got = [m for m in self.messages if where is None or where(m)]
                if len(got) >= n:
                    return got
                left = deadline - time.monotonic()
                if left <= 0:
                    raise TimeoutError(f"{self.key}: {len(got)} of {n} messages in {timeout:g} s")
                self._cv.wait(left)

    def close(self) -> None:
        try:
            self._sub.undeclare()
        except Exception:
            pass


class RunningGraph:
    """A graph launched by ``launch_graph``; see the module docstring."""

    def __init__(self, path: Path, proc: subprocess.Popen, log_path: Path):
        self.path, self.proc, self.log_path = path, proc, log_path
        self.graph: Graph = load_graph(path)
        self.name = self.graph.name
        import zenoh
        if credentials.applies(self.graph):      # the launcher's per-run credentials, once it made them
            self.graph = credentials.wait_for(self.graph, 60.0, alive=lambda: proc.poll() is None)
        self.session = zenoh.open(zenoh_config(self.graph, role="node"))
        self._subs: list = []
        self._seen_pids: set = set()
        self._stats_lock = threading.Lock()
        self._stats: dict = {}            # node -> newest NodeStats
        self._stats_sub = self.session.declare_subscriber(stats_key(self.name), self._on_stats)
        self.returncode: Optional[int] = None

    # ---------------------------------------------------------------- keys and data
    def key(self, key: str) -> str:
        return self.graph.resolve_key(key)

    def subscribe(self, key: str, expect: Optional[type] = None) -> Subscription:
        sub = Subscription(self.session, self.key(key), expect)
        self._subs.append(sub)
        return sub

    def collect(self, key: str, n: int, timeout: float = 10.0, expect: Optional[type] = None,
                where: Optional[Callable] = None) -> list:
        """Subscribe to ``key`` and return the first ``n`` decoded messages (AssertionError with the
        launcher log if they do not come within ``timeout``)."""
        sub = self.subscribe(key, expect)
        try:
            return sub.wait(n, timeout, where)[:n]
        except TimeoutError as exc:
            raise AssertionError(f"{exc}\n--- launcher log ---\n{self.log()[-4000:]}") from None
        finally:
            sub.close()

    def put(self, key: str, payload) -> None:
        """Publish a Message or raw bytes on ``key``."""
        data = encode(payload) if isinstance(payload, Message) else bytes(payload)
        self.session.put(self.key(key), data)

    def command(self, node: str, name: str, **args) -> None:
        self.put(f"{node}/cmd", Command(name, args or None))

    # ---------------------------------------------------------------- state
    def _on_stats(self, sample) -> None:
        try:
            st = decode(sample.payload.to_bytes(), NodeStats)
        except MessageError:
            return
        with self._stats_lock:
            self._stats[st.node] = st
            self._seen_pids.add(st.pid)

    def stats(self, node: str, timeout: float = 5.0) -> NodeStats:
        """A ``NodeStats`` of ``node`` published after this call."""
        t0 = time.time_ns()
        return self.wait_stats(node, lambda st: st.stamp_ns >= t0, timeout)

    def wait_stats(self, node: str, pred: Callable, timeout: float = 10.0) -> NodeStats:
        """Wait until the newest ``NodeStats`` of ``node`` satisfies ``pred``; returns it."""
        deadline = time.monotonic() + timeout
        last = None
        while time.monotonic() < deadline:
            with self._stats_lock:
                last = self._stats.get(node)
            if last is not None and pred(last):
                return last
            time.sleep(0.05)
        raise AssertionError(f"stats of {node!r} did not satisfy the condition in {timeout:g} s; "
                             f"last: {last}\n--- launcher log ---\n{self.log()[-4000:]}")

    def live(self) -> set:
        """Node ids with a liveliness token now."""
        ids = set()
        for reply in self.session.liveliness().get(live_key(self.name), timeout=1.0):
            if reply.ok is not None:
                ids.add(str(reply.ok.key_expr).rsplit("/", 1)[-1])
        return ids

    def wait_live(self, ids, timeout: float = 30.0) -> None:
        ids = set(ids)
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise AssertionError(f"launcher exited with {self.proc.returncode}\n{self.log()[-4000:]}")
            if ids <= self.live():
                return
            time.sleep(0.1)
        raise AssertionError(f"nodes {sorted(ids - self.live())} not live after {timeout:g} s\n"
                             f"--- launcher log ---\n{self.log()[-4000:]}")

    def status(self) -> dict:
        """The launcher's table: ``{"nodes": [{"node", "pid", "restarts", "state", ...}]}``."""
        import json
        for reply in self.session.get(launcher_key(self.name, "status"), timeout=3.0):
            if reply.ok is not None:
                st = json.loads(reply.ok.payload.to_bytes().decode())
                self._seen_pids.update(r["pid"] for r in st["nodes"] if r["pid"])
                return st
        raise AssertionError(f"the launcher did not answer\n{self.log()[-4000:]}")

    def pids(self) -> dict:
        """node id -> pid of its current process (None while restarting)."""
        return {r["node"]: r["pid"] for r in self.status()["nodes"]}

    def log(self) -> str:
        return self.log_path.read_text(errors="replace") if self.log_path.exists() else ""

    def wait_log(self, text: str, timeout: float = 30.0) -> str:
        """Wait until ``text`` is in the launcher's log (a node's line reaches it through the
        launcher's relay of its output, a moment after the event it tells); returns the log."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            log = self.log()
            if text in log:
                return log
            time.sleep(0.1)
        raise AssertionError(f"{text!r} not in the launcher's log after {timeout:g} s\n"
                             f"--- launcher log ---\n{self.log()[-4000:]}")

    # ---------------------------------------------------------------- commands
    def cli(self, *args, timeout: float = 60) -> subprocess.CompletedProcess:
        """``needletrack CMD ARGS -g <this graph>``: e.g. ``g.cli("ps")``."""
        return cli(args[0], "-g", self.path, *args[1:], timeout=timeout)

    def swap(self, node: str, module: Optional[str] = None, timeout: float = 120, unset=(),
             **params) -> subprocess.CompletedProcess:
        """``needletrack swap NODE [--module M] [--param k=v ...] [--unset k ...]`` against this graph."""
        args = ["swap", node] + (["--module", module] if module else [])
        for k in unset:
            args += ["--unset", k]
        for k, v in params.items():
            args += ["--param", f"{k}={yaml.safe_dump(v, default_flow_style=True).strip().removesuffix('...').strip()}"]
        return self.cli(*args, timeout=timeout)

    # ---------------------------------------------------------------- stopping
    def stop(self, timeout: float = 20.0) -> int:
        """SIGTERM the launcher, wait, check that no node process survived; returns its status."""
        if self.returncode is not None:
            return self.returncode
        try:
            self.status()
        except AssertionError:
            pass
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        try:
            self.returncode = self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            os.killpg(self.proc.pid, signal.SIGKILL)
            self.returncode = self.proc.wait()
        for s in self._subs:
            s.close()
        try:
            self._stats_sub.undeclare()
        except Exception:
            pass
        self.session.close()
        survivors = _alive(self._seen_pids, wait=5.0)
        for pid in survivors:
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        assert not survivors, f"node processes {survivors} outlived the launcher\n{self.log()[-4000:]}"
        return self.returncode

    def __enter__(self) -> "RunningGraph":
        return self

    def __exit__(self, *exc) -> None:
        self.stop()


def _alive(pids, wait: float) -> list:
    deadline = time.monotonic() + wait
    while True:
        alive = []
        for pid in pids:
            try:
                os.kill(pid, 0)
                with open(f"/proc/{pid}/stat") as f:      # a zombie is not alive
                    if f.read().split(")")[-1].split()[0] == "Z":
                        continue
                alive.append(pid)
            except (ProcessLookupError, FileNotFoundError):
                pass
        if not alive or time.monotonic() > deadline:
            return alive
        time.sleep(0.1)


def launch_graph(graph, directory: Path, args=(), wait: bool = True, timeout: float = 40.0) -> RunningGraph:
    """Write ``graph`` (free port, unique name) into ``directory`` and launch it with
    ``needletrack launch``; if ``wait``, return once every launched node is live."""
    directory = Path(directory)
    path = prepare_graph(graph, directory)
    log_path = directory / "launch.log"
    env = dict(os.environ, PYTHONPATH=str(REPO), PYTHONUNBUFFERED="1")
    with open(log_path, "wb") as log:
        proc = subprocess.Popen([sys.executable, "-m", "common.cli", "launch", str(path), *map(str, args)],
                                cwd=REPO, env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        g = RunningGraph(path, proc, log_path)
    except Exception:
        proc.kill()
        proc.wait()
        raise
    if wait:
        only = None
        args = list(map(str, args))
        if "--only" in args:
            only = args[args.index("--only") + 1].split(",")
        try:
            g.wait_live(only or g.graph.ids(), timeout)
        except BaseException:
            g.stop()
            raise
    return g
