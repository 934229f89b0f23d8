"""The launcher: runs a graph as one process per node, supervises and hot-swaps them.

- Module nodes run as ``python -m common.runtime.node --graph RESOLVED.yaml --node ID``; ``command``
  nodes run as given, with ``NEEDLETRACK_GRAPH``/``NEEDLETRACK_NODE`` in their environment.
- Every output line of a node is printed prefixed with ``[node id]``.
- A node that exits is restarted per its ``restart`` policy: at once, then, if it fails again
  within 10 s of starting, with exponential backoff (0.5 s doubling to 10 s); exit status 2 (bad
  configuration: bad params, an unreadable model; a source whose input failed part way, e.g. a
  corrupt bag) is never restarted, and stops the whole graph (``launch`` then exits non-zero). A
  node's exit is reported with the last ERROR line it printed: which node stopped, and why.
  Params are checked against each node's ``Params`` before anything starts. Restarts are
  counted, printed, and reported in the node's stats.
- The launcher's own Zenoh session is the graph's hub: it listens on the graph's ``listen``
  endpoints and the nodes connect to it (then to each other, by gossip). With ``--only`` and the
  endpoint already taken (another launcher runs the rest of the graph), it connects instead.
- It answers queries on ``<graph>/@launcher/status`` (its processes) and
  ``<graph>/@launcher/swap`` (hot swap, make-before-break; see ``Launcher.swap``). With
  ``zenoh.tls`` every link is mutual TLS and access control lets only the launcher identity
  (launchers, CLI tools) send swaps, handovers and commands (``zenoh_session.access_control``); a
  listen endpoint beyond loopback without TLS is warned about.
- A graph without ``zenoh.tls`` runs on per-run credentials (``common.runtime.credentials``):
  a CA and a certificate per member made at start in a 0700 directory of this user's, removed
  at the end; ``zenoh.open: true`` runs without them (a warning). Each process it starts gets a
  control token of its own (``NEEDLETRACK_CTL_TOKEN``) that only this launcher knows: a node
  hands over or takes over only when the query carries it, i.e. in a swap this launcher runs.
  A node that reports itself ``retired`` outside a swap is said so and restarted.
- A node with ``spare: true`` gets a warm spare process (``NEEDLETRACK_SPARE=1``: set up, then
  idle and unseen) ``SPARE_AFTER_S`` after its process starts; when that process exits, the
  spare takes over at once (a takeover query with its token) instead of a new process starting.
- SIGINT/SIGTERM stop every node (SIGTERM, then SIGKILL after ``STOP_GRACE_S``); nodes also
  get SIGTERM from the kernel if the launcher itself dies (``PR_SET_PDEATHSIG``).
"""
from __future__ import annotations

import ctypes
import json
import os
import queue
import secrets
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

from common.runtime.graph import (
    LAUNCHER_IDENTITY,
    REPO_ROOT,
    Graph,
    GraphError,
    NodeSpec,
    launcher_key,
    stats_key,
)
from common.runtime.graph_checks import graph_warnings
from common.runtime.zenoh_session import close_session, tls_file_errors, zenoh_config
from common.runtime.node import graph_param_errors
from common.runtime.swap import LauncherSwap

STOP_GRACE_S = 5.0
BACKOFF_MIN_S, BACKOFF_MAX_S, BACKOFF_RESET_S = 0.5, 10.0, 10.0
SPARE_AFTER_S = 5.0             # a node's spare is started once its process has run this long


def _pdeathsig():
    """In the child: get SIGTERM when the launcher dies, so no node outlives it."""
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except OSError:
        pass


def restart_delay(failures: int) -> float:
    """Seconds before restarting a node after ``failures`` quick failures in a row: at once after
    one that ran longer than ``BACKOFF_RESET_S`` (a camera killed mid-run is back without a
    pause), then ``BACKOFF_MIN_S`` doubling up to ``BACKOFF_MAX_S``."""
    return 0.0 if failures <= 1 else min(BACKOFF_MAX_S, BACKOFF_MIN_S * 2 ** (failures - 2))


def describe_status(code: int) -> str:
    if code is None:
        return "running"
    if code < 0:
        try:
            return f"killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"killed by signal {-code}"
    return f"status {code}"


@dataclass
class Proc:
    spec: NodeSpec
    popen: subprocess.Popen
    started: float
    restarts: int = 0
    role: str = "active"            # active | standby | retired
    reader: Optional[threading.Thread] = None
    token: str = ""                 # the process's control token (handover, takeover)
    last_error: str = ""            # the last ERROR line it printed: why it stopped

    @property
    def pid(self) -> int:
        return self.popen.pid


@dataclass
class Slot:
    """One node id: its current process and supervision state."""
    spec: NodeSpec
    proc: Optional[Proc] = None
    restarts: int = 0
    failures: int = 0               # consecutive quick failures (for backoff)
    restart_at: Optional[float] = None
    last_status: Optional[int] = None
    done: bool = False              # exited and will not be restarted
    force_restart: bool = False     # stopped by the launcher to be restarted (retired outside a swap)
    spare: Optional[Proc] = None    # a warm spare process (``spare: true``): set up, idle


class Launcher(LauncherSwap):
    def __init__(self, graph: Graph, only: Optional[list] = None, out=None, run_dir: Optional[str] = None,
                 stop_on_config_error: bool = True):
        self.graph = graph
        self.stop_on_config_error = stop_on_config_error
        ids = graph.ids()
        if only:
            unknown = [i for i in only if i not in ids]
            if unknown:
                raise GraphError([f"--only: no node {u!r} (nodes: {', '.join(ids)})" for u in unknown])
        self.only = list(only) if only else ids
        self.out = out or sys.stdout
        self._out_lock = threading.Lock()
        self._lock = threading.RLock()
        self.slots = {nid: Slot(graph.node(nid)) for nid in self.only}
        self._own_run_dir = run_dir is None
        self.run_dir = Path(run_dir or tempfile.mkdtemp(prefix="needletrack-run-"))
        self._gen = 0
        self.graph_file = self._write_graph()
        self._stop = threading.Event()
        self._swaps: "queue.Queue" = queue.Queue()
        self._retired: list = []
        self.session = None
        self._decl: list = []
        self._own_credentials = False
        self._swapping: set = set()          # node ids in a swap now
        self._reported: dict = {}            # pid -> the state its newest NodeStats reports

    # ---------------------------------------------------------------- output
    def say(self, text: str, who: str = "launcher") -> None:
        with self._out_lock:
            try:
                self.out.write(f"[{who}] {text}\n")
                self.out.flush()
            except (ValueError, OSError):
                pass

    def _pump(self, proc: Proc) -> None:
        for raw in iter(proc.popen.stdout.readline, b""):
            tag = proc.spec.id if proc.role == "active" else f"{proc.spec.id}:{proc.pid}"
            line = raw.decode(errors="replace").rstrip("\n")
            if line.startswith(("ERROR ", "CRITICAL ")):
                proc.last_error = line.split(" ", 1)[1][:500]
            self.say(line, tag)
        proc.popen.stdout.close()

    # ---------------------------------------------------------------- processes
    def _write_graph(self) -> Path:
        self._gen += 1
        return self.graph.dump(self.run_dir / f"graph.{self._gen}.yaml")

    def _spawn(self, spec: NodeSpec, restarts: int = 0, standby: bool = False, spare: bool = False) -> Proc:
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join([str(REPO_ROOT)] + [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p])
        token = secrets.token_hex(16)
        env.update(PYTHONUNBUFFERED="1", NEEDLETRACK_GRAPH=str(self.graph_file), NEEDLETRACK_NODE=spec.id,
                   NEEDLETRACK_RESTARTS=str(restarts), NEEDLETRACK_STANDBY="1" if standby else "0",
                   NEEDLETRACK_SPARE="1" if spare else "0",
                   NEEDLETRACK_CTL_TOKEN=token)
        # glibc would map and unmap every image-sized buffer (page faults on each frame: ~2x the
        # CPU of a receiver); keep freed memory in the heap for reuse instead
        env.setdefault("MALLOC_MMAP_THRESHOLD_", str(1 << 30))
        env.setdefault("MALLOC_TRIM_THRESHOLD_", str(1 << 30))
        env.update(spec.env)
        if spec.module:
            argv = [sys.executable, "-m", "common.runtime.node", "--graph", str(self.graph_file), "--node", spec.id]
        else:
            argv = list(spec.command)
        popen = subprocess.Popen(argv, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                 env=env, cwd=str(REPO_ROOT), start_new_session=True, preexec_fn=_pdeathsig)
        proc = Proc(spec, popen, time.monotonic(), restarts,
                    "spare" if spare else "standby" if standby else "active", token=token)
        proc.reader = threading.Thread(target=self._pump, args=(proc,), daemon=True)
        proc.reader.start()
        return proc

    @staticmethod
    def _signal(proc: Proc, sig) -> None:
        try:
            os.killpg(proc.pid, sig)
        except (ProcessLookupError, PermissionError):
            try:
                proc.popen.send_signal(sig)
            except ProcessLookupError:
                pass

    def _terminate(self, procs: list, grace: float = STOP_GRACE_S) -> None:
        for p in procs:
            if p.popen.poll() is None:
                self._signal(p, signal.SIGTERM)
        deadline = time.monotonic() + grace
        for p in procs:
            try:
                p.popen.wait(max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                self.say(f"{p.spec.id} (pid {p.pid}) did not stop in {grace:.0f} s: SIGKILL")
                self._signal(p, signal.SIGKILL)
                p.popen.wait()
            # a node's own children (command nodes) share its process group
            try:
                os.killpg(p.pid, signal.SIGKILL)
            except (ProcessLookupError, PermissionError):
                pass
            if p.reader:
                p.reader.join(1.0)

    # ---------------------------------------------------------------- hub session
    def open_session(self) -> None:
        """Open the hub session (or join the graph's hub with ``--only``), as the launcher identity
        under TLS; raises RuntimeError saying why not."""
        import zenoh

        from common.runtime import credentials
        for w in graph_warnings(self.graph):
            self.say(f"WARNING {w}")
        if credentials.applies(self.graph):
            self.graph, self._own_credentials = credentials.make(self.graph)
            self.graph_file = self._write_graph()
        errors = tls_file_errors(self.graph, [LAUNCHER_IDENTITY] + self.only)
        if errors:
            raise RuntimeError("TLS files missing:\n  " + "\n  ".join(errors))
        try:
            self.session = zenoh.open(zenoh_config(self.graph, role="hub", identity=LAUNCHER_IDENTITY))
            where = "listening on " + ", ".join(self.graph.zenoh.listen)
        except Exception as exc:
            if len(self.only) == len(self.graph.nodes):
                raise RuntimeError(f"cannot listen on {', '.join(self.graph.zenoh.listen)} ({exc}); "
                                   f"is another graph running there?") from None
            self.session = zenoh.open(zenoh_config(self.graph, role="node", identity=LAUNCHER_IDENTITY))
            where = "joining the graph at " + ", ".join(self.graph.zenoh.listen)
        if self.graph.zenoh.run_credentials:
            where += f" (mutual TLS on per-run credentials in {self.graph.zenoh.run_credentials}, access control by identity)"
        elif self.graph.zenoh.tls is not None:
            where += " (mutual TLS, access control by certificate)"
        self.say(f"graph {self.graph.name!r}: {len(self.only)} node(s), {where}")
        self._decl.append(self.session.declare_queryable(launcher_key(self.graph.name, "status"), self._q_status))
        self._decl.append(self.session.declare_queryable(launcher_key(self.graph.name, "swap"), self._q_swap))
        self._decl.append(self.session.declare_subscriber(stats_key(self.graph.name), self._on_stats))

    def _on_stats(self, sample) -> None:
        """Keep the state each process reports (to notice one that retired outside a swap)."""
        from common.runtime.messages import MessageError, NodeStats, decode
        try:
            st = decode(sample.payload.to_bytes(), NodeStats)
        except MessageError:
            return
        self._reported[st.pid] = st.counters.get("state")

    def _q_status(self, query) -> None:
        with self._lock:
            rows = []
            for nid, s in self.slots.items():
                p = s.proc
                rows.append({"node": nid, "module": s.spec.module or " ".join(s.spec.command or []),
                             "pid": p.pid if p else None, "restarts": s.restarts,
                             "state": "running" if p and p.popen.poll() is None else
                                      ("restarting" if s.restart_at else "exited"),
                             "last_status": s.last_status, "restart": s.spec.restart,
                             "uptime_s": round(time.monotonic() - p.started, 1) if p else None})
        query.reply(query.key_expr, json.dumps({"graph": self.graph.name, "launcher_pid": os.getpid(),
                                                "nodes": rows}).encode())

    # ---------------------------------------------------------------- supervision
    def start(self) -> None:
        self.open_session()
        with self._lock:
            for nid, slot in self.slots.items():
                slot.proc = self._spawn(slot.spec)
        threading.Thread(target=self._swap_loop, name="swap", daemon=True).start()

    def _supervise_once(self) -> None:
        now = time.monotonic()
        with self._lock:
            for nid, slot in self.slots.items():
                p = slot.proc
                if p is not None and p.popen.poll() is not None:
                    code = p.popen.returncode
                    slot.last_status = code
                    slot.proc = None
                    if p.reader:
                        p.reader.join(0.5)
                    policy = slot.spec.restart
                    again = (policy == "always" or (policy == "on-failure" and code != 0)) and code != 2
                    self._reported.pop(p.pid, None)
                    forced, slot.force_restart = slot.force_restart, False
                    again = again or forced
                    why = f": {p.last_error}" if code not in (0, None) and p.last_error else ""
                    if not again:
                        slot.done = True
                        self.say(f"{nid} exited with {describe_status(code)}"
                                 + ("" if code in (0, None) else f" (restart policy {policy}"
                                    + (", status 2 = bad configuration" if code == 2 else "") + ")") + why)
                        if code == 2 and self.stop_on_config_error:
                            self.say(f"{nid} cannot run as configured: stopping the graph"
                                     + ("" if why else " (see its log above)"))
                            self._stop.set()
                        continue
                    ran = now - p.started
                    if self._promote_spare(nid, slot, code):
                        continue
                    if forced:
                        delay = 0.0
                    else:
                        slot.failures = 1 if ran > BACKOFF_RESET_S else slot.failures + 1
                        delay = restart_delay(slot.failures)
                    slot.restart_at = now + delay
                    self.say(f"{nid} exited with {describe_status(code)}{why}; "
                             f"restart #{slot.restarts + 1} in {delay:.1f} s")
                elif (p is not None and not slot.force_restart and nid not in self._swapping
                      and self._reported.get(p.pid) == "retired"):
                    # only a swap this launcher runs may retire a process (its token): one that
                    # stopped publishing otherwise would be silent for good
                    slot.force_restart = True
                    self.say(f"{nid} (pid {p.pid}) stopped publishing outside a swap (it reports "
                             f"'retired'): restarting it")
                    self._signal(p, signal.SIGTERM)
                elif p is not None and slot.spec.spare and slot.spare is None and now - p.started > SPARE_AFTER_S \
                        and nid not in self._swapping:
                    slot.spare = self._spawn(slot.spec, restarts=slot.restarts + 1, spare=True)
                    self.say(f"{nid}: spare pid {slot.spare.pid} started (it takes over if pid {p.pid} exits)")
                elif p is None and slot.restart_at is not None and now >= slot.restart_at:
                    slot.restarts += 1
                    slot.restart_at = None
                    slot.proc = self._spawn(slot.spec, restarts=slot.restarts)
                    self.say(f"{nid} restarted (pid {slot.proc.pid}, restart #{slot.restarts})")
                if slot.spare is not None and slot.spare.popen.poll() is not None:
                    self.say(f"{nid}: spare pid {slot.spare.pid} exited with "
                             f"{describe_status(slot.spare.popen.returncode)}; another in {SPARE_AFTER_S:g} s")
                    if slot.spare.reader:
                        slot.spare.reader.join(0.5)
                    slot.spare = None
            self._retired = [p for p in self._retired if p.popen.poll() is None]

    def _promote_spare(self, nid: str, slot: Slot, code: int) -> bool:
        """The node's warm spare takes over from its exited process (call with the lock held);
        False when there is none that is ready."""
        spare, slot.spare = slot.spare, None
        if spare is None:
            return False
        ans = None
        if spare.popen.poll() is None:
            try:
                ans = self._ctl(nid, spare, "takeover", {"cuts": {}, "restarts": slot.restarts + 1}, timeout=1.0)
            except Exception:
                ans = None
        if not (ans or {}).get("ok"):
            self.say(f"{nid}: spare pid {spare.pid} did not take over ({ans}); restarting instead")
            threading.Thread(target=self._terminate, args=([spare], 1.0), daemon=True).start()
            return False
        slot.restarts += 1
        spare.role, spare.started = "active", time.monotonic()
        slot.proc = spare
        self.say(f"{nid} exited with {describe_status(code)}; spare pid {spare.pid} took over "
                 f"(restart #{slot.restarts})")
        return True

    def run(self, duration: Optional[float] = None, until: Optional[list] = None) -> int:
        """Supervise until every node is done, ``until`` nodes are done, ``duration`` passed or stop()."""
        t_end = None if duration is None else time.monotonic() + duration
        until = [u for u in (until or []) if u in self.slots]
        while not self._stop.is_set():
            self._supervise_once()
            with self._lock:
                if all(s.done for s in self.slots.values()):
                    break
                if until and all(self.slots[u].done for u in until):
                    self.say(f"{', '.join(until)} finished: stopping the graph")
                    break
            if t_end is not None and time.monotonic() >= t_end:
                self.say(f"ran for {duration:g} s: stopping the graph")
                break
            self._stop.wait(0.1)
        return self.shutdown()

    def stop(self) -> None:
        self._stop.set()

    def shutdown(self) -> int:
        self._stop.set()
        with self._lock:
            procs = [s.proc for s in self.slots.values() if s.proc is not None] + self._retired + \
                [s.spare for s in self.slots.values() if s.spare is not None]
            for s in self.slots.values():
                s.restart_at = None
        self._terminate(procs)
        for p in procs:
            slot = self.slots.get(p.spec.id)
            if slot is not None and slot.proc is p:
                slot.last_status = p.popen.returncode
        close_session(self.session, self._decl)
        self.session = None
        if self._own_credentials:
            from common.runtime import credentials
            credentials.remove(self.graph)
            self._own_credentials = False
        if self._own_run_dir:
            shutil.rmtree(self.run_dir, ignore_errors=True)
        bad = {nid: s.last_status for nid, s in self.slots.items()
               if s.last_status not in (0, None, -signal.SIGTERM, -signal.SIGKILL)}
        self.say("stopped" + (f"; non-zero exits: {bad}" if bad else ""))
        return 1 if bad else 0


def launch_main(argv: list) -> int:
    """``needletrack launch [GRAPH.yaml] [--only ID,...] [--duration S] [--until ID,...] [--all-methods] [--no-viewer] [--save FILE.rrd]``."""
    import argparse

    from common.runtime.graph import load_graph
    ap = argparse.ArgumentParser(prog="needletrack launch", description="Run a dataflow graph, one process per node.")
    ap.add_argument("graph", nargs="?", default="dataflow.yaml", help="graph YAML (default: dataflow.yaml)")
    ap.add_argument("--only", help="comma-separated node ids to run (the rest run elsewhere)")
    ap.add_argument("--duration", type=float, help="stop the graph after this many seconds")
    ap.add_argument("--until", help="stop the graph when these nodes (comma-separated) have finished")
    ap.add_argument("--all-methods", action="store_true",
                    help="monitor nodes print every method's pose, not only the final one")
    ap.add_argument("--no-viewer", action="store_true",
                    help="leave out the graph's viewer nodes (module viewer)")
    ap.add_argument("--save", metavar="FILE.rrd",
                    help="the viewer records the session to FILE.rrd (a second viewer node to "
                         "FILE.<id>.rrd); open it with `needletrack view FILE.rrd`")
    args = ap.parse_args(argv)
    path = Path(args.graph)
    if not path.exists() and args.graph == "dataflow.yaml":
        path = REPO_ROOT / "dataflow.yaml"
    try:
        graph = load_graph(path)
        if args.no_viewer:
            graph.nodes = [n for n in graph.nodes if n.module != "viewer"]
        if args.save:
            viewers = [n for n in graph.nodes if n.module == "viewer"]
            if not viewers:
                print(f"needletrack launch: --save: {path} has no viewer node", file=sys.stderr)
                return 2
            for i, n in enumerate(viewers):
                save = Path(args.save).resolve()
                n.params["save"] = str(save if i == 0 else save.with_suffix(f".{n.id}.rrd"))
        if args.all_methods:
            for n in graph.nodes:
                if n.module == "monitor":
                    n.params["all_methods"] = True
        only = args.only.split(",") if args.only else None
        errors = graph_param_errors(graph) + tls_file_errors(graph, [LAUNCHER_IDENTITY] + (only or graph.ids()))
        if errors:
            raise GraphError(errors, str(path))
        launcher = Launcher(graph, only=only)
    except GraphError as exc:
        print(str(exc), file=sys.stderr)
        return 2
    stopping = []

    def on_signal(signum, _frame):
        if stopping:
            return
        stopping.append(signum)
        launcher.say(f"{signal.Signals(signum).name}: stopping every node")
        launcher.stop()
    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    try:
        launcher.start()
    except RuntimeError as exc:
        print(f"needletrack launch: {exc}", file=sys.stderr)
        launcher.shutdown()
        return 1
    return launcher.run(duration=args.duration, until=args.until.split(",") if args.until else None)
